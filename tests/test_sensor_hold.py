"""Holding learning only where a frozen input matters (vfm_core.sensor_faults,
``WellSensorFaults.suspect`` with the sample's values): a frozen ``p_down`` in critical
flow under every choke law holds nothing, in subcritical flow it holds as before; the
offline plan (``plan_sensor_faults``) follows the same rule.

Synthetic wells: p_up 100 bar a, a gas mass fraction of 0.1 (the lowest critical ratio of
the choke laws is then 0.45: ``critical_floor``), p_down frozen at its last reading."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import pandas as pd
import pytest

from vfm_core.jobs.study_faults import plan_sensor_faults
from vfm_core.sensor_faults import SENSORS, WellSensorFaults, critical_floor

DAY_NS = 86_400 * 10**9
ORIGIN = 1_500_000_000 * 10**9


def frozen_p_down_well(
    p_down: float, seed: int, days: int = 400, frozen_from: int = 300
) -> Iterator[tuple[int, list[float]]]:
    """Two samples a day: the inputs with noise, p_down stuck at its last reading from day
    ``frozen_from``. Yields (time ns, inputs)."""
    rng = np.random.default_rng(seed)
    last = p_down
    for d in range(days):
        for hour in (rng.uniform(0, 11), rng.uniform(12, 23)):
            t = ORIGIN + d * DAY_NS + int(hour * 3_600e9)
            if d < frozen_from:
                last = p_down + rng.normal(0.0, 0.1)
            x = [0.5, 100.0 + rng.normal(0.0, 0.2), last, 60.0 + rng.normal(0.0, 0.1)]
            x += [0.1 + rng.normal(0.0, 1e-4), 0.6 + rng.normal(0.0, 1e-4)]
            yield t, x


def held_inside(p_down: float, seed: int) -> tuple[int, int, int]:
    """(samples inside the frozen fault, of them held without the values, held with them)."""
    det = WellSensorFaults()
    inside = plain = with_values = 0
    for t, x in frozen_p_down_well(p_down, seed):
        det.update(t, x)
        fault = det.suspect(t)
        if fault is not None and (fault.sensor, fault.kind) == ("p_down", "frozen"):
            inside += 1
            plain += 1
            with_values += det.suspect(t, values=x) is not None
    return inside, plain, with_values


def test_the_floor_of_the_synthetic_wells_is_what_their_docstring_says() -> None:
    assert critical_floor(100.0, 60.0, 0.1, 0.6) == pytest.approx(0.45, abs=0.01)


@pytest.mark.parametrize("seed", [4101, 4102])
def test_a_frozen_p_down_in_critical_flow_holds_nothing(seed: int) -> None:
    """p_down / p_up = 0.2: the fault is found (and shown), but no sample inside it holds
    a measurement: the rate does not depend on p_down there."""
    inside, plain, with_values = held_inside(20.0, seed)
    assert inside > 100  # found within days of day 300, open to day 400
    assert plain == inside and with_values == 0


@pytest.mark.parametrize("seed", [4101, 4102])
def test_a_frozen_p_down_in_subcritical_flow_still_holds(seed: int) -> None:
    """p_down / p_up = 0.7: the rate depends on p_down; every sample inside the fault
    holds its measurement, as without the rule."""
    inside, plain, with_values = held_inside(70.0, seed)
    assert inside > 100 and with_values == plain == inside


def test_near_the_floor_the_stand_in_s_span_decides() -> None:
    """p_down / p_up = 0.43, just under the floor (0.45): early in the fault the reading
    and its stand-in's 90 % span stay under the floor (nothing held); as the fault ages the
    span grows (the true p_down may have moved) and reaches above it: held."""
    det = WellSensorFaults()
    verdicts = []
    for t, x in frozen_p_down_well(43.0, 4103, days=500):
        det.update(t, x)
        if det.suspect(t) is not None:
            verdicts.append(det.suspect(t, values=x) is not None)
    assert len(verdicts) > 300
    assert not any(verdicts[:20]) and all(verdicts[-50:])


def test_the_offline_plan_holds_by_the_same_rule() -> None:
    """``plan_sensor_faults`` (``vfm evaluate``'s plan of what the service holds): a
    critical and a subcritical well with the same frozen p_down; only the latter's
    measurements inside the fault are held."""
    rows = []
    for well, level in (("CRIT", 20.0), ("SUB", 70.0)):
        for t, x in frozen_p_down_well(level, 4104):
            rows.append(
                {
                    "time": pd.Timestamp(t, tz="UTC"),
                    "well": well,
                    **dict(zip(SENSORS, x, strict=True)),
                }
            )
    frame = pd.DataFrame(rows)
    frame["source"] = "sensor"
    frame["q_total"] = np.nan
    plan = plan_sensor_faults(frame)
    held = pd.Series(plan.held).groupby(frame["well"].to_numpy()).sum()
    assert held["CRIT"] == 0
    assert held["SUB"] > 100
