"""The residual alarm (self-starting two-sided CUSUM): its design, false alarms, delays, state."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest

from vfm_core.errors import ConfigError
from vfm_core.residual_alarm import (
    AlarmSize,
    ResidualCusum,
    alarm_size,
    alarms_from_predictions,
    cusum_arl0,
    cusum_threshold,
    standardised_residual,
)

DAY_NS = 86_400 * 10**9


def feed(det: ResidualCusum, values: np.ndarray, start: int = 0) -> None:
    for i, v in enumerate(values):
        det.update(float(v), (start + i) * DAY_NS)


def test_threshold_from_the_target_run_length_by_hand() -> None:
    # Siegmund, two-sided, k = 0.5: ARL = (e^(h + 1.166) - (h + 1.166) - 1) / (2 * 0.25) / 2
    h = 5.0
    assert cusum_arl0(h, 0.5) == pytest.approx((math.exp(6.166) - 6.166 - 1.0), rel=1e-12)
    assert cusum_threshold(cusum_arl0(h, 0.5), 0.5) == pytest.approx(h, abs=1e-6)
    assert cusum_threshold(1000.0) == pytest.approx(5.75, abs=0.005)
    # a longer target run length asks for more evidence
    assert cusum_threshold(10_000.0) > cusum_threshold(1000.0) > cusum_threshold(100.0)
    with pytest.raises(ConfigError, match="arl0"):
        cusum_threshold(1.0)


@pytest.mark.parametrize("scale", ["mad", "winsorised"])
def test_in_control_run_length_matches_the_design_on_iid_gaussian_residuals(scale: str) -> None:
    # 60 000 periods of N(0, 1): at a design ARL of 200 periods, ~300 alarms are expected.
    # The self-starting scale (estimated, not known) and the active spans move the rate a
    # little; the measured run length must lie within 35 % of the design.
    arl0 = 200.0
    det = ResidualCusum(arl0=arl0, period_s=0.0, window=365, scale=scale)
    rng = np.random.default_rng(20261125)
    n = 60_000
    feed(det, rng.standard_normal(n))
    tested = n - det.min_periods
    run_length = tested / len(det.events)
    assert 0.65 * arl0 < run_length < 1.35 * arl0, (run_length, len(det.events))


def test_period_means_of_varying_counts_keep_the_winsorised_scale_near_the_design() -> None:
    # Days of 1 to 6 readings: period means N(0, 1/n), a scale mixture whose tails are heavier
    # than a Gaussian's. 1.4826 MAD then falls short of their standard deviation and the
    # CUSUM alarms far more often than designed (the residual alarm's false alarms on the
    # fields of a second physics); the winsorised mean and sd of the reference hold the
    # run length much nearer the design.
    arl0, n = 200.0, 60_000
    rng = np.random.default_rng(20261127)
    means = rng.standard_normal(n) / np.sqrt(rng.integers(1, 7, n))
    run_length = {}
    for scale in ("mad", "winsorised"):
        det = ResidualCusum(arl0=arl0, period_s=0.0, window=365, scale=scale)
        feed(det, means)
        run_length[scale] = (n - det.min_periods) / len(det.events)
    assert run_length["winsorised"] > 0.6 * arl0, run_length
    assert run_length["winsorised"] > 1.25 * run_length["mad"], run_length
    with pytest.raises(ConfigError, match="scale"):
        ResidualCusum(scale="iqr")


def test_one_spike_alone_does_not_raise_an_alarm() -> None:
    det = ResidualCusum(period_s=0.0)
    rng = np.random.default_rng(3)
    feed(det, rng.standard_normal(100))
    det.update(50.0, 100 * DAY_NS)  # a meter spike: clipped at 4 standard deviations
    assert not det.alarm and det.statistic < det.threshold


def test_a_step_of_two_sd_is_found_within_the_expected_delay() -> None:
    # A shift of delta = 2 sd with k = 0.5, h = 5.75: the mean delay is about
    # (h + 1.166) / (delta - k) = 4.6 periods (Siegmund's approximation of the out-of-control
    # run length for large h); allow up to 12 over 50 repetitions' 95th percentile.
    delays = []
    for seed in range(50):
        rng = np.random.default_rng(1000 + seed)
        det = ResidualCusum(period_s=0.0)
        feed(det, rng.standard_normal(200))
        if det.alarm:  # a false alarm still active at the step: it says nothing of the delay
            continue
        for i in range(100):
            det.update(float(rng.standard_normal()) + 2.0, (200 + i) * DAY_NS)
            if det.alarm:
                delays.append(i + 1)
                assert det.direction == "high"
                break
        else:
            pytest.fail(f"seed {seed}: a step of 2 sd was not found in 100 periods")
    assert len(delays) >= 45
    assert 3.0 <= float(np.mean(delays)) <= 7.0
    assert float(np.percentile(delays, 95)) <= 12


def test_daily_periods_average_the_readings_and_the_alarm_clears() -> None:
    det = ResidualCusum(period_s=86_400.0, min_periods=20)
    rng = np.random.default_rng(7)
    four_a_day = DAY_NS // 4
    t = 0
    for _ in range(60 * 4):  # 60 days, 4 readings a day
        det.update(0.03 * float(rng.standard_normal()), t)
        t += four_a_day
    assert det.n_periods == 59 and not det.alarm  # the 60th day is still open
    for _ in range(10 * 4):  # readings 6 % below the model for 10 days
        det.update(-0.06 + 0.03 * float(rng.standard_normal()), t)
        t += four_a_day
    assert det.alarm and det.direction == "low"
    since = det.since_ns
    assert since is not None and 60 * DAY_NS <= since <= 64 * DAY_NS
    for _ in range(40 * 4):  # back in control: the sums decay to 0 and the alarm ends
        det.update(0.03 * float(rng.standard_normal()), t)
        t += four_a_day
    assert not det.alarm
    (event,) = det.events
    assert event.end_ns is not None and event.end_ns > since
    assert event.closed == "cleared"  # back to the reference, not accepted as a new level


def test_state_round_trip_continues_identically() -> None:
    rng = np.random.default_rng(11)
    values = np.concatenate([rng.standard_normal(80), rng.standard_normal(40) + 1.5])
    a = ResidualCusum(period_s=0.0, scale="winsorised", accept_periods=20)
    feed(a, values[:90])
    b = ResidualCusum()
    b.load_state_dict(a.state_dict())
    feed(a, values[90:100], start=90)
    feed(b, values[90:100], start=90)
    assert a.alarm  # the shift was found; saved again inside the alarm
    c = ResidualCusum()
    c.load_state_dict(b.state_dict())
    feed(a, values[100:], start=100)
    feed(c, values[100:], start=100)
    assert (c.scale, c.accept_periods) == ("winsorised", 20)
    assert [e.as_dict() for e in a.events] == [e.as_dict() for e in c.events]
    assert (a.alarm, a.statistic) == (c.alarm, c.statistic)
    assert a.events[0].closed == "accepted"  # 20 periods of the new level, across the load


def test_residuals_and_settings() -> None:
    assert standardised_residual(110.0, 100.0, 5.0) == pytest.approx(2.0)
    assert standardised_residual(110.0, 100.0) == pytest.approx(math.log(1.1))
    assert math.isnan(standardised_residual(110.0, float("nan")))
    assert math.isnan(standardised_residual(0.0, 100.0))
    with pytest.raises(ConfigError, match="min_periods"):
        ResidualCusum(window=10, min_periods=20)
    with pytest.raises(ConfigError, match="clip"):
        ResidualCusum(k=0.5, clip=0.5)


def test_alarms_from_predictions_per_well_and_meter() -> None:
    rng = np.random.default_rng(5)
    times = pd.date_range("2020-01-01", periods=300, freq="12h", tz="UTC")
    rows = []
    for well, shift in (("A", 0.0), ("B", 0.08)):
        measured = 100.0 * np.exp(0.02 * rng.standard_normal(len(times)))
        measured[200:] *= 1.0 + shift  # B: 8 % above the model from day 100
        rows.append(
            pd.DataFrame(
                {
                    "time": times,
                    "well": well,
                    "source": "mpfm",
                    "predicted": 100.0,
                    "measured": measured,
                }
            )
        )
    alarms = alarms_from_predictions(pd.concat(rows, ignore_index=True))
    # A may have a false alarm (a design rate of one per 1000 days); it ends again, while
    # B's shift holds on: its alarm closes as an accepted new level 30 days after its
    # signal, and the new level, steady, raises nothing more
    assert all(a["end"] is not None for a in alarms if a["well"] == "A")
    (a,) = [a for a in alarms if a["well"] == "B"]
    assert a["direction"] == "high" and a["source"] == "mpfm" and a["closed"] == "accepted"
    assert (
        pd.Timestamp("2020-04-10", tz="UTC") <= a["start"] <= pd.Timestamp("2020-04-14", tz="UTC")
    )
    assert a["end"] - a["start"] == pd.Timedelta(days=30)  # 30 periods after the signal
    # its size at the raise: the 8 % step (2 % scatter: the median of the readings between
    # the start and the raise against the 30 before)
    assert a["shift"] == pytest.approx(0.08, abs=0.02)
    # with accept_periods = 0 (the rule before s46) it holds to the end of the data
    (old,) = alarms_from_predictions(rows[1], accept_periods=0)
    assert old["start"] == a["start"] and old["end"] is None and old["closed"] is None


def level_shifts(det: ResidualCusum, levels: list[tuple[int, float]], seed: int) -> None:
    """One reading a day, 2 % log-normal scatter around a level that steps: ``levels`` are
    (first day, level) pairs."""
    rng = np.random.default_rng(seed)
    end = levels[-1][0] + 60
    for day in range(end):
        level = [v for first, v in levels if first <= day][-1]
        det.update(level + 0.02 * float(rng.standard_normal()), day * DAY_NS + DAY_NS // 2)


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_an_alarm_whose_level_stays_is_accepted_and_a_second_change_is_found(seed: int) -> None:
    # The residuals move 6 % low on day 60 and stay there (the learner settled on a new
    # bias); on day 260 a second change takes them 6 % lower still. With a reference frozen
    # for the whole alarm (accept_periods = 0) the first alarm lasts to the end and the
    # second change raises nothing; with the default of the residual alarm (30) the first
    # closes as accepted 30 periods after its signal, the reference restarts from those
    # periods, and the second change is an alarm of its own within days.
    levels = [(0, 0.0), (60, -0.06), (260, -0.12)]
    frozen = ResidualCusum(accept_periods=0, scale="winsorised")
    level_shifts(frozen, levels, seed)
    (only,) = frozen.events
    assert only.end_ns is None and only.direction == "low"
    det = ResidualCusum(accept_periods=30, scale="winsorised")
    level_shifts(det, levels, seed)
    first, second = det.events
    assert first.direction == second.direction == "low"
    assert 60 * DAY_NS <= first.start_ns <= 64 * DAY_NS
    assert first.closed == "accepted" and first.end_ns == first.start_ns + 30 * DAY_NS
    assert 260 * DAY_NS <= second.start_ns <= 265 * DAY_NS
    assert second.end_ns is not None  # accepted too: the -12 % level held for 30 periods
    with pytest.raises(ConfigError, match="accept_periods"):
        ResidualCusum(accept_periods=3)


def test_a_state_saved_before_acceptance_existed_still_loads() -> None:
    # A detector saved before s46 (no accept_periods, no post, events without closed) with
    # an alarm active: it resumes, keeps its reference and alarm, and the detector it is
    # loaded into accepts the alarm's level after accept_periods periods from the load.
    old = ResidualCusum(scale="winsorised")
    level_shifts(old, [(0, 0.0), (60, -0.06)], seed=4)  # to day 120: the alarm is active
    assert old.alarm
    saved = old.state_dict()
    for key in ("accept_periods", "post"):
        del saved[key]
    for e in saved["events"]:
        del e["closed"]
    det = ResidualCusum(accept_periods=30)
    det.load_state_dict(saved)
    assert det.alarm and det.accept_periods == 30 and det.scale == "winsorised"
    assert det.state_dict()["reference"] == saved["reference"]
    rng = np.random.default_rng(5)
    for day in range(120, 160):
        det.update(-0.06 + 0.02 * float(rng.standard_normal()), day * DAY_NS + DAY_NS // 2)
    (event,) = det.events
    assert event.closed == "accepted" and not det.alarm


def _catching_up(seed: int, jump_at: int | None = None) -> np.ndarray:
    """Period means: N(0, 1), 3 sd low from period 100 and back to 0 linearly over 90
    periods (a learner following a change slowly); from ``jump_at`` 3 sd high."""
    rng = np.random.default_rng(seed)
    t = np.arange(400)
    level = np.where(t >= 100, -3.0 * np.clip(1.0 - (t - 100) / 90.0, 0.0, None), 0.0)
    if jump_at is not None:
        level[jump_at:] = 3.0
    return rng.standard_normal(len(t)) + level


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_the_way_back_after_an_accepted_alarm_is_quiet_and_beyond_it_is_not(seed: int) -> None:
    # s46's rule (alarm_on_return): the low alarm is accepted 30 periods after its signal,
    # at a level the learner then leaves, and the way back to 0 is an alarm the other way
    # (the echo of bench_alarms' sand fields). s47's default: the way back is quiet; a
    # change beyond the level before the alarm (3 sd high at period 140, while the
    # residuals are still on their way back) is an alarm within a few periods.
    values = _catching_up(seed)
    echo = ResidualCusum(period_s=0.0, scale="winsorised", accept_periods=30, alarm_on_return=True)
    feed(echo, values)
    assert [(e.direction, e.closed) for e in echo.events][:2] == [
        ("low", "accepted"),
        ("high", "accepted"),
    ]
    det = ResidualCusum(period_s=0.0, scale="winsorised", accept_periods=30)
    feed(det, values)
    low = [e for e in det.events if e.start_ns >= 90 * DAY_NS]
    assert [(e.direction, e.closed) for e in low] == [("low", "accepted")]
    assert 100 * DAY_NS <= low[0].start_ns <= 105 * DAY_NS
    # beyond the old level, during the way back: found
    beyond = ResidualCusum(period_s=0.0, scale="winsorised", accept_periods=30)
    jumped = _catching_up(seed, jump_at=140)
    feed(beyond, jumped[:135])
    assert beyond.state_dict()["back"] is not None  # inside the quiet way back
    resumed = ResidualCusum()
    resumed.load_state_dict(beyond.state_dict())
    feed(beyond, jumped[135:], start=135)
    feed(resumed, jumped[135:], start=135)
    high = [e for e in beyond.events if e.direction == "high" and e.start_ns >= 140 * DAY_NS]
    assert high and high[0].start_ns <= 145 * DAY_NS
    assert [e.as_dict() for e in resumed.events] == [e.as_dict() for e in beyond.events]


def test_an_alarms_size_is_the_step_against_the_readings_before_it() -> None:
    """AlarmSize by hand: readings at 100 Sm3/h, the model 100 Sm3/h, then 7 % above it;
    ratios not positive are skipped; too few readings before the start give None; the
    state round-trips; the keep bounds the memory."""
    size = AlarmSize(keep=50)
    for day in range(60):
        measured = 100.0 * (1.07 if day >= 40 else 1.0) * (1.0 + 0.001 * (-1) ** day)
        size.add(day * DAY_NS, measured, 100.0)
    size.add(60 * DAY_NS, 0.0, 100.0)  # not positive: skipped
    size.add(60 * DAY_NS, 100.0, None)  # no prediction: skipped
    found = size.at_raise(40 * DAY_NS, 45 * DAY_NS)
    assert found is not None and found["readings"] == 6 and found["reference"] == 30
    assert found["shift"] == pytest.approx(0.07, abs=0.003)
    assert found["onset_ns"] == 40 * DAY_NS
    # the usual error before the change: +-0.1 % about the model, by hand
    assert found["typical"] == pytest.approx(0.001, rel=0.01)
    # a CUSUM onset some days early: the scan finds the step's day, the size is the same
    early = size.at_raise(36 * DAY_NS, 45 * DAY_NS)
    assert early is not None and early["onset_ns"] == 40 * DAY_NS and early["readings"] == 6
    assert early["shift"] == pytest.approx(0.07, abs=0.003)
    assert size.at_raise(15 * DAY_NS, 20 * DAY_NS) is None  # 5 kept before day 15 (keep 50)
    again = AlarmSize(keep=50)
    again.restore(size.state())
    assert again.at_raise(40 * DAY_NS, 45 * DAY_NS) == found
    assert len(size.state()["t"]) == 50


def test_an_alarm_is_small_when_its_shift_is_under_the_meters_usual_error() -> None:
    """The rule by hand (:func:`alarm_size`), then end to end: readings twice a day at 3 %
    noise about a fixed model, a +12 % step on day 60 gives a full alarm and a +2 % step a
    small one (its size at the raise under the readings' usual error before it, about
    2.4 %: the mean of |N(0, 3 %)| is 3 % x sqrt(2 / pi)); the fields come with every alarm."""
    assert alarm_size(0.012, 0.024) == {"small": True, "typical_error_percent": 2.4}
    assert alarm_size(-0.03, 0.024)["small"] is False
    assert alarm_size(0.012, None) == {"small": None, "typical_error_percent": None}
    assert alarm_size(math.nan, 0.024)["small"] is None
    n = 2 * 200
    time = pd.date_range("2020-01-01", periods=n, freq="12h", tz="UTC")
    noise = np.exp(np.random.default_rng(1).normal(0.0, 0.03, n))
    found = {}
    for step in (1.12, 1.02):
        measured = 1000.0 * np.where(np.arange(n) / 2 >= 60, step, 1.0) * noise
        frame = pd.DataFrame(
            {
                "time": time,
                "well": "W01",
                "source": "mpfm",
                "predicted": 1000.0,
                "measured": measured,
            }
        )
        (first, *_) = alarms_from_predictions(frame, flush=False)
        assert first["start"] >= pd.Timestamp("2020-03-01", tz="UTC"), first
        assert 1.5 < first["typical_error_percent"] < 3.3, first
        found[step] = first
    assert found[1.12]["small"] is False and found[1.12]["shift"] > 0.08
    assert found[1.02]["small"] is True and 0.0 < found[1.02]["shift"] < 0.024
