"""Beside a residual alarm on the MPFM's stream, the well tests say whether the meter or the
well moved (vfm_core.meter_check: the pair's z against the well's usual difference).

The well runs ``mm`` with a retrain period longer than the data (``pbl:3650d``, see
``alarm_support``): two MPFM readings a day with 3 % noise around 1000 Sm3/h, and a well
test a week (1 % noise) at the true rate. On day 70 the MPFM reads 12 % higher: either the
meter moved (the well tests stay at 1000) or the well did (they go to 1120 with it). The
residual alarm is the same in both; the well tests after it tell them apart.
"""

from __future__ import annotations

from datetime import timedelta
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from alarm_support import INPUTS, T0, fixed_model_service
from test_service_alarm import http_get

from replay.client import FieldClient, sample_of
from service.app import Service
from service.testing import wait_until
from vfm_core.messages import Measurement

pytestmark = pytest.mark.timeout(180)

STEP_DAY, DAYS = 70, 90


def send_field(
    client: FieldClient,
    meter_moved: bool,
    seed: int,
    days: int = DAYS,
    tests_until: int | None = None,
) -> int:
    """In time order, over ``days`` days: two samples with an MPFM reading a day (3 and
    15 h; +12 % from STEP_DAY) and each week a sample with a well test at 09:00 (days 3,
    10, ...; none from day ``tests_until`` on); returns the measurements."""
    rng = np.random.default_rng(seed)
    n = 0
    for day in range(days):
        meter = 1.12 if day >= STEP_DAY else 1.0
        well = 1.0 if meter_moved or day < STEP_DAY else 1.12
        for hour, source, level, noise in (
            (3, "mpfm", meter, 0.03),
            (9, "well_test", well, 0.01),
            (15, "mpfm", meter, 0.03),
        ):
            if source == "well_test" and (
                day % 7 != 3 or (tests_until is not None and day >= tests_until)
            ):
                continue
            t = T0 + timedelta(days=day, hours=hour)
            client.send_sample("W01", sample_of(t, INPUTS))
            q = 1000.0 * level * float(np.exp(noise * rng.standard_normal()))
            client.send_measurement("W01", source, Measurement(time=t, q_total=q))
            n += 1
    return n


@pytest.mark.parametrize("meter_moved", [True, False])
def test_the_well_tests_say_which_moved(tmp_path: Path, meter_moved: bool) -> None:
    with fixed_model_service(tmp_path) as (service, client):
        wait_learned_all(service, send_field(client, meter_moved, seed=3))
        view = http_get(service, "/wells/W01").json()
    alarm, check = view["residual_alarm"], view["mpfm_check"]
    assert alarm["active"] and alarm["source"] == "mpfm" and alarm["direction"] == "high"
    # the alarm's size at its raise: the MPFM's 12 % step against the model fitted once,
    # from the few readings between the alarm's start and its raise (3 % noise each)
    assert abs(np.log1p(alarm["shift"]) - np.log1p(0.12)) < 3 * alarm["shift_se"]
    assert 0.01 < alarm["shift_se"] < 0.04
    # the change's onset (the CUSUM's change-point estimate) lies near the step of day 70
    # (2021-07-10), before the alarm was raised
    assert "2021-07-08" <= alarm["onset"][:10] <= "2021-07-11" and alarm["onset"] <= alarm["since"]
    # the latest well test (day 87) against the ten before the alarm (not the two after it)
    assert check["well_test_time"].startswith("2021-07-27")
    assert abs(check["usual_difference"]) < 0.03 and 0.01 <= check["usual_spread"] < 0.04
    moved = alarm["which_moved"]
    assert moved["well_test_time"] == check["well_test_time"]
    if meter_moved:  # the MPFM reads 12 % above the well test, usually about 0
        assert check["relative_difference"] == pytest.approx(0.12, abs=0.04)
        assert check["shifted"] and check["z"] > 3
        assert moved["moved"] == "meter" and "the meter moved" in moved["text"]
        assert abs(moved["meter_z"]) < 3  # the pair moved by about the alarm's size
    else:  # the well tests went up with the MPFM
        assert abs(check["relative_difference"]) < 0.04 and not check["shifted"]
        assert moved["moved"] == "well" and "the well changed" in moved["text"]
        assert moved["meter_z"] < -2  # far below where a meter move would put the pair
    assert moved["alarm_shift"] == alarm["shift"]
    # every well test since the alarm began is read, together (s54): days 73, 80 and 87
    since = pd.Timestamp(alarm["since"])
    tested = [d for d in range(3, DAYS, 7) if T0 + timedelta(days=d, hours=9) >= since]
    assert len(tested) >= 2 and moved["n_well_tests"] == len(tested), (tested, moved)
    assert moved["z_latest"] == pytest.approx(check["z"], rel=1e-12)
    assert f"against the {len(tested)} well tests since the alarm began" in moved["text"]
    # a restart sets the latest well test against the same earlier ones (from the store)
    with fixed_model_service(tmp_path) as (service, _):
        again = http_get(service, "/wells/W01").json()
    assert again["mpfm_check"]["z"] == pytest.approx(check["z"], rel=1e-12)
    assert again["residual_alarm"]["which_moved"] == moved
    assert again["residual_alarm"]["shift"] == alarm["shift"]
    assert alarm["awaiting_well_test"] is None  # which_moved has the answer


def test_before_the_next_well_test_the_alarm_says_when_it_is_due(tmp_path: Path) -> None:
    """The MPFM steps on day 70 and the data stop before the well test of day 73: the alarm
    is up, no well test can say which moved yet, and the view says when the next is due
    (a week after the last, from the gaps between the ten compared before the alarm)."""
    with fixed_model_service(tmp_path) as (service, client):
        wait_learned_all(service, send_field(client, True, seed=3, days=STEP_DAY + 3))
        view = http_get(service, "/wells/W01").json()
    alarm = view["residual_alarm"]
    assert alarm["active"] and alarm["source"] == "mpfm"
    assert alarm["which_moved"] is None
    waiting = alarm["awaiting_well_test"]
    assert waiting["pairs"] == 10  # days 3, 10, ..., 66
    assert waiting["last_well_test"].startswith("2021-07-06")  # day 66
    assert waiting["typical_gap_days"] == pytest.approx(7.0)
    assert waiting["due"].startswith("2021-07-13")  # day 73
    assert "the next one tells whether the meter or the well moved" in waiting["text"]
    assert not waiting["overdue"] and "due about 2021-07-13" in waiting["text"]


def test_an_overdue_well_test_is_said_to_be_overdue(tmp_path: Path) -> None:
    """The same step, the data going on to day 79 without a well test after day 66: the
    well test due on day 73 is overdue, and the text says since when, not "due about"."""
    with fixed_model_service(tmp_path) as (service, client):
        sent = send_field(client, True, seed=3, days=STEP_DAY + 10, tests_until=STEP_DAY)
        wait_learned_all(service, sent)
        view = http_get(service, "/wells/W01").json()
    waiting = view["residual_alarm"]["awaiting_well_test"]
    assert waiting["due"].startswith("2021-07-13") and waiting["overdue"]
    assert "overdue since 2021-07-13, usually 7 days" in waiting["text"]
    assert "due about" not in waiting["text"]


def wait_learned_all(service: Service, count: int) -> None:
    """Every measurement stored and decided (a well test off the model may be held)."""
    store = service.store
    assert store is not None

    def stored() -> bool:
        rows = store.history("W01", 0, 2**62, 10_000)[1]
        return len(rows) == count and all(m.status != "pending" for m in rows)

    wait_until(stored, 60, "every measurement to be stored and decided")


def test_a_choke_move_before_a_well_test_is_no_meter_disagreement(tmp_path: Path) -> None:
    """The choke closes from 0.4 to 0.25 an hour and a half before a well test, and the
    rate falls with it (to 60 %): both meters read the rate right. The MPFM readings of the
    day before the move (every 2 h; every 6 h after it) would put the median of the 24 h
    either side 1.6 times above the well test; only those at the well test's choke are
    compared (vfm_core.meter_check.steady_span), and they agree."""
    rng = np.random.default_rng(7)
    move = T0 + timedelta(days=3, hours=1)
    with fixed_model_service(tmp_path) as (service, client):
        n = 0
        for hour in range(0, 5 * 24, 2):  # a sample and an MPFM reading every 2 h, 5 days
            t = T0 + timedelta(hours=hour)
            level = 1.0 if t < move else 0.6
            inputs = (0.4 if t < move else 0.25, *INPUTS[1:])
            client.send_sample("W01", sample_of(t, inputs))
            q = 1000.0 * level * float(np.exp(0.02 * rng.standard_normal()))
            if t < move or hour % 6 == 0:  # after the move, a reading every 6 h
                client.send_measurement("W01", "mpfm", Measurement(time=t, q_total=q))
                n += 1
            if t == move + timedelta(hours=1):  # the well test, between two samples
                test = t + timedelta(minutes=30)
                client.send_measurement("W01", "well_test", Measurement(time=test, q_total=600.0))
                n += 1
        wait_learned_all(service, n)
        check = http_get(service, "/wells/W01").json()["mpfm_check"]
    assert check["well_test_time"].startswith((T0 + timedelta(days=3)).date().isoformat())
    assert check["agrees"] and check["alarm"] is None, check
    assert abs(check["relative_difference"]) < 0.05, check
    # compared again once its window passed: the readings after the move within 24 h of
    # the well test only, 06:00 of day 3 to 00:00 of day 4 (4; 12 before the move were in
    # the window)
    assert check["mpfm_readings"] == 4, check
