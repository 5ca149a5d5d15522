"""The pressure-rate witness (vfm_core.pressure_witness): a p_up reading that drifts while
the measured rate does not follow is found; a clean well and a real p_up change the rate
follows raise nothing; its state resumes; bad settings are refused."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from vfm_core.errors import ConfigError
from vfm_core.pressure_witness import PressureWitness

_SHARE = 2 * 0.1 / 24  # the witness's two shares of the detectors' budget
_NS_PER_DAY = 86_400 * 10**9


def _well(seed: int, days: int, *, drift_from: int | None = None, real_from: int | None = None):
    """Daily means of a synthetic well: a choke moved every 5-15 days, a slowly declining
    and wandering p_up (bar a) that drops as the choke opens, an independent p_down, and
    a rate that answers the choke with elasticity 0.9 and p_up with 1 (critical flow),
    with 1.5 % noise on each day's mean. ``drift_from``: the p_up reading (not the well)
    drifts up 30 % a month from that day; ``real_from``: the well's p_up itself rises
    20 % a month from that day for 30 days, and the rate follows."""
    rng = np.random.default_rng(seed)
    u, p_static, p_down = 0.5, 120.0, 30.0
    next_move = 10
    out = []
    for d in range(days):
        if d == next_move:
            u = float(np.clip(u * math.exp(rng.normal(0.0, 0.15)), 0.1, 0.95))
            next_move = d + int(rng.integers(5, 16))
        p_static *= math.exp(-0.0002 + 0.001 * rng.standard_normal())
        if real_from is not None and real_from <= d < real_from + 30:
            p_static *= math.exp(0.2 / 30)
        p_down = 30.0 + 0.9 * (p_down - 30.0) + 0.4 * rng.standard_normal()
        p_up = p_static * (1.0 - 0.08 * u)
        lq = math.log(400.0) + 0.9 * math.log(u / 0.5) + math.log(p_up / 100.0)
        lq += 0.015 * rng.standard_normal()
        reading = p_up * math.exp(0.002 * rng.standard_normal())
        if drift_from is not None and d >= drift_from:
            reading *= 1.0 + 0.3 * (d - drift_from) / 30.0
        logs = (math.log(u), math.log(reading), math.log(reading - p_down))
        out.append((20_000 + d, lq, logs))
    return out


def _run(w: PressureWitness, rows, start: int = 0, stop: int | None = None):
    found = []
    for d, lq, logs in rows[start:stop]:
        f = w.day(d, lq, logs)
        if f is not None:
            found.append(f)
    return found


def test_a_drifting_reading_the_rate_does_not_follow_is_found() -> None:
    start = 400
    rows = _well(11, 470, drift_from=start)
    w = PressureWitness(_SHARE)
    found = _run(w, rows)
    raised = [f for f in found if f.action == "raise"]
    assert raised, "a 30 %/month p_up drift at 1.5 % noise was not found in 70 days"
    first = raised[0]
    assert first.sensor == "p_up"
    assert first.day - (20_000 + start) <= 14  # found within two weeks
    # its onset: the ramp that explains most (within the longest ramp tested)
    assert 20_000 + start - w.window_days <= first.start_day <= first.day
    assert first.z > w.z_lim
    assert "p_up" in first.evidence and "threshold" in first.evidence
    # the witness learned the well: its choke elasticity near the true 0.9
    assert w.fit is not None and abs(w.fit["rate"].coef[1] - 0.9) < 0.15


def test_a_clean_well_raises_nothing_over_years() -> None:
    for seed in (21, 22):
        w = PressureWitness(_SHARE)
        assert _run(w, _well(seed, 2 * 365)) == []
        assert w.fit is not None  # it did test (the fit exists)


def test_a_real_p_up_change_the_rate_follows_is_not_a_fault() -> None:
    rows = _well(31, 500, real_from=400)
    # the p_up reading did rise about 20 % (the test would have its trend to look at)
    assert rows[430][2][1] - rows[399][2][1] > 0.15
    assert _run(PressureWitness(_SHARE), rows) == []


def test_state_round_trip_resumes_the_same() -> None:
    rows = _well(11, 470, drift_from=400)
    a = PressureWitness(_SHARE)
    _run(a, rows, 0, 300)
    b = PressureWitness(_SHARE)
    b.restore(json.loads(json.dumps(a.state())))  # plain JSON
    assert b.state() == a.state()
    assert a.fit is not None and b.fit is not None
    for name, fit in a.fit.items():
        np.testing.assert_allclose(b.fit[name].coef, fit.coef)
        got = (b.fit[name].var_e, b.fit[name].var_w, b.fit[name].kappa)
        assert got == pytest.approx((fit.var_e, fit.var_w, fit.kappa))
    fa, fb = _run(a, rows, 300), _run(b, rows, 300)
    assert [(f.action, f.sensor, f.day) for f in fa] == [(f.action, f.sensor, f.day) for f in fb]
    assert fa  # the drift was found by both


def test_rate_readings_are_averaged_per_day() -> None:
    w = PressureWitness(_SHARE)
    day0 = 20_000 * _NS_PER_DAY
    for k, q in enumerate((100.0, 400.0)):  # one day, two readings
        assert w.rate(day0 + k * 3_600 * 10**9, q, 0.5, 100.0, 30.0) is None
    assert not w.days  # the day is still open
    w.rate(day0 + _NS_PER_DAY, 300.0, 0.5, 100.0, 30.0)  # the next day closes it
    ((d, lq, lu, lp, ldp, flagged),) = w.days
    assert d == 20_000 and lq == pytest.approx(math.log(200.0))  # the mean of the logs
    assert (lu, lp, ldp) == pytest.approx((math.log(0.5), math.log(100.0), math.log(70.0)))
    assert not flagged
    # refused: a closed choke, a rate of zero, a reading out of time order
    assert w.rate(day0 + _NS_PER_DAY, 300.0, 0.0, 100.0, 30.0) is None
    assert w.rate(day0 + _NS_PER_DAY, 0.0, 0.5, 100.0, 30.0) is None
    w.rate(day0, 300.0, 0.5, 100.0, 30.0)
    assert w.today is not None and w.today[1] == 1


@pytest.mark.parametrize(
    "kwargs",
    [
        {"share": 0.0},
        {"share": math.nan},
        {"share": 0.01, "window_days": 3},
        {"share": 0.01, "reference_days": 2},
        {"share": 0.01, "history_days": 10},
        {"share": 0.01, "min_days": 5},
        {"share": 0.01, "refit_days": 0},
    ],
)
def test_bad_settings_are_refused(kwargs) -> None:
    with pytest.raises(ConfigError, match="must"):
        PressureWitness(**kwargs)
