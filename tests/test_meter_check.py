"""The MPFM-against-well-test rule offline (vfm_core.meter_check), on numbers checked by hand."""

from __future__ import annotations

import math

import pandas as pd
import pytest

from vfm_core.meter_check import (
    MIN_PAIRS,
    against_usual,
    awaiting_well_test,
    compare,
    mpfm_checks,
    which_moved,
)

T0 = pd.Timestamp("2020-03-01 12:00", tz="UTC")
H = pd.Timedelta(hours=1)


def _row(well: str, source: str, when: pd.Timestamp, q: float) -> dict:
    return {"time": when, "well": well, "source": source, "q_total": q}


def test_each_well_test_is_compared_with_the_median_within_24_h() -> None:
    frame = pd.DataFrame(
        [
            _row("W01", "mpfm", T0 - 23 * H, 105.0),
            _row("W01", "mpfm", T0 + 2 * H, 112.0),
            _row("W01", "mpfm", T0 + 24 * H, 111.0),  # on the window's edge: in
            _row("W01", "mpfm", T0 + 25 * H, 500.0),  # outside the window: not used
            _row("W01", "well_test", T0, 100.0),
            _row("W02", "mpfm", T0 - H, 190.0),
            _row("W02", "mpfm", T0 + H, 210.0),
            _row("W02", "well_test", T0, 200.0),
            _row("W03", "well_test", T0, 50.0),  # no MPFM reading near it: not compared
            _row("W03", "mpfm", T0 + 48 * H, 50.0),
        ]
    )
    checks = mpfm_checks(frame).set_index("well")
    assert list(checks.index) == ["W01", "W02"]
    # W01: median(105, 112, 111) = 111 against 100: 11 % above, outside the 10 % band
    assert checks.loc["W01", "mpfm_median"] == 111.0
    assert checks.loc["W01", "mpfm_readings"] == 3
    assert checks.loc["W01", "relative_difference"] == pytest.approx(0.11)
    assert not checks.loc["W01", "agrees"]
    # W02: median(190, 210) = 200 against 200
    assert checks.loc["W02", "relative_difference"] == 0.0 and checks.loc["W02", "agrees"]
    assert checks.loc["W01", "time"] == T0
    # a wider band accepts W01; a narrower window leaves it one reading (112: 12 % above)
    assert mpfm_checks(frame, rel=0.12).set_index("well").loc["W01", "agrees"]
    narrow = mpfm_checks(frame, window_s=3 * 3600.0).set_index("well")
    assert narrow.loc["W01", "mpfm_readings"] == 1
    assert narrow.loc["W01", "relative_difference"] == pytest.approx(0.12)


def test_nothing_to_compare() -> None:
    assert compare([], 100.0, 0.1) is None
    assert compare([100.0], 0.0, 0.1) is None
    assert compare([100.0], float("nan"), 0.1) is None
    empty = mpfm_checks(pd.DataFrame([_row("W01", "mpfm", T0, 10.0)]))
    assert empty.empty and "relative_difference" in empty.columns


def test_a_pair_against_the_usual_difference() -> None:
    earlier = [0.02, 0.01, 0.03, 0.02, 0.025, 0.015, 0.02, 0.01]
    # log ratios: median log(1.02); MAD of the logs about 0.0049 -> sd 0.0073, floored at 0.01
    usual = against_usual(earlier, 0.09)
    assert usual is not None
    assert usual["usual_difference"] == pytest.approx(0.02)
    assert usual["usual_spread"] == 0.01
    assert usual["z"] == pytest.approx(math.log(1.09 / 1.02) / 0.01)
    assert usual["shifted"]
    assert not against_usual(earlier, 0.04)["shifted"]  # z = 1.9
    assert against_usual(earlier[:7], 0.09) is None  # fewer than MIN_PAIRS
    assert against_usual(earlier, -1.0) is None


def test_which_moved_beside_an_mpfm_alarm() -> None:
    alarm = {"active": True, "source": "mpfm", "since": "2020-05-01T00:00:00+00:00"}
    check = {
        "well_test_time": "2020-05-20T06:00:00+00:00",
        "relative_difference": 0.01,
        "usual_difference": 0.008,
    }
    said = {z: which_moved(alarm, {**check, "z": z}) for z in (4.0, -3.5, 2.0, 0.5)}
    assert [said[z]["moved"] for z in (4.0, -3.5, 2.0, 0.5)] == [
        "meter",
        "meter",
        "unclear",
        "well",
    ]
    assert "usually +0.8 %" in said[0.5]["text"] and "2020-05-20" in said[0.5]["text"]
    # nothing to say: the alarm is on the well tests, the well test came before the
    # alarm, or it was not set against earlier pairs
    assert which_moved({**alarm, "source": "well_test"}, {**check, "z": 4.0}) is None
    early = {**check, "z": 4.0, "well_test_time": "2020-04-20T06:00:00+00:00"}
    assert which_moved(alarm, early) is None
    assert which_moved(alarm, {**check, "z": None}) is None
    assert which_moved(alarm, None) is None


def test_which_moved_sets_the_pair_against_the_alarms_size() -> None:
    """With the alarm's size known: ``well`` only where the pair is also far from where a
    meter move would put it; a shift within two spreads cannot be told by one well test
    (a slow meter drift raises its alarm at a small shift); ``meter`` only in the
    alarm's direction."""
    alarm = {"active": True, "source": "mpfm", "since": "2020-05-01T00:00:00+00:00"}
    check = {
        "well_test_time": "2020-05-20T06:00:00+00:00",
        "relative_difference": 0.01,
        "usual_difference": 0.008,
        "usual_spread": 0.03,
    }
    small = which_moved({**alarm, "shift": 0.04}, {**check, "z": 0.2})
    assert small["moved"] == "unclear" and "no one well test can tell" in small["text"]
    assert "+4.0 %" in small["text"] and small["alarm_shift"] == 0.04
    assert small["meter_z"] == pytest.approx((0.2 * 0.03 - math.log1p(0.04)) / 0.03)
    large = which_moved({**alarm, "shift": 0.12}, {**check, "z": 0.2})
    assert large["moved"] == "well" and large["meter_z"] < -2
    assert which_moved({**alarm, "shift": 0.12}, {**check, "z": 3.8})["moved"] == "meter"
    against = which_moved({**alarm, "shift": 0.12}, {**check, "z": -3.8})
    assert against["moved"] == "unclear"  # the pair moved the other way from the alarm
    # without a size (an alarm from before s51): the z alone, as before
    assert which_moved(alarm, {**check, "z": 0.2})["moved"] == "well"
    assert which_moved({**alarm, "shift": None}, {**check, "z": 0.2})["meter_z"] is None


def test_which_moved_reads_the_well_tests_since_the_alarm_together() -> None:
    """A 6 % shift against pairs that spread 3 %: one well test cannot tell the meter
    from the well (2 spreads apart), three can (their mean's spread is 3 % / sqrt 3).
    Pairs from before the alarm, or after the check's well test, are not read."""
    alarm = {"active": True, "source": "mpfm", "since": "2020-05-01T00:00:00+00:00", "shift": 0.06}
    usual, spread = 0.008, 0.03
    times = [pd.Timestamp(d, tz="UTC") for d in ("2020-05-10", "2020-06-20", "2020-08-01")]
    before = (pd.Timestamp("2020-04-01", tz="UTC").value, 0.5)  # before the alarm: not read
    later = (pd.Timestamp("2020-09-01", tz="UTC").value, -0.5)  # after the check: not read

    def check(rel: float) -> dict:
        z = (math.log1p(rel) - math.log1p(usual)) / spread
        return {
            "well_test_time": times[-1].isoformat(),
            "relative_difference": rel,
            "usual_difference": usual,
            "usual_spread": spread,
            "z": z,
        }

    moved = math.expm1(math.log1p(usual) + math.log1p(0.06))  # the meter moved by 6 %
    for rel, alone, together in ((moved, "unclear", "meter"), (usual, "unclear", "well")):
        pairs = [before, *[(t.value, rel) for t in times], later]
        one = which_moved(alarm, check(rel))
        three = which_moved(alarm, check(rel), pairs)
        assert one["moved"] == alone and one["n_well_tests"] == 1, one
        assert three["moved"] == together and three["n_well_tests"] == 3, three
        assert three["z"] == pytest.approx(one["z"] * math.sqrt(3))
        assert three["z_latest"] == pytest.approx(one["z"])
        assert "on average against the 3 well tests since the alarm began" in three["text"]
        assert "(the latest of 2020-08-01)" in three["text"]
    # the check's own pair missing from ``pairs``: the check alone, as before
    alone = which_moved(alarm, check(moved), [(times[0].value, moved)])
    assert alone["n_well_tests"] == 1 and alone["moved"] == "unclear"


def test_awaiting_the_well_test_that_says_which_moved() -> None:
    alarm = {"active": True, "source": "mpfm", "since": "2020-05-01T00:00:00+00:00"}
    day = 86_400 * 10**9
    start = pd.Timestamp("2020-01-01", tz="UTC").value
    tests = [start + k * 12 * day for k in range(10)]  # 2020-01-01 .. 2020-04-18, every 12 d
    waiting = awaiting_well_test(alarm, None, tests)
    assert waiting is not None and waiting["pairs"] == 10
    assert waiting["typical_gap_days"] == pytest.approx(12.0)
    assert waiting["last_well_test"].startswith("2020-04-18")
    assert waiting["due"].startswith("2020-04-30")
    assert "due about 2020-04-30" in waiting["text"] and not waiting["overdue"]
    # the well's data past the due date: overdue, and since when
    late = awaiting_well_test(alarm, None, tests, pd.Timestamp("2020-05-09", tz="UTC").value)
    assert late["overdue"] and "overdue since 2020-04-30, usually 12 days" in late["text"]
    early = awaiting_well_test(alarm, None, tests, pd.Timestamp("2020-04-29", tz="UTC").value)
    assert not early["overdue"] and "due about 2020-04-30" in early["text"]
    # an alarm whose shift is within two of the pairs' spreads (the latest check, before
    # it): one well test will not tell either, and the text says so
    before = {"well_test_time": "2020-04-18T06:00:00+00:00", "z": 0.4, "usual_spread": 0.03}
    before |= {"relative_difference": 0.01, "usual_difference": 0.0}
    small = awaiting_well_test({**alarm, "shift": 0.04, "shift_se": 0.01}, before, tests)
    assert "its shift (+4.0 %) is within 2 of the pairs' spreads (3.2 %)" in small["text"]
    assert "one well test will not tell" in small["text"] and "due about" in small["text"]
    large = awaiting_well_test({**alarm, "shift": 0.12, "shift_se": 0.01}, before, tests)
    assert large["text"].startswith("no well test since the alarm: the next one tells")
    # too few pairs before the alarm: the next well test cannot tell either, and it says so
    few = awaiting_well_test(alarm, None, tests[: MIN_PAIRS - 1])
    assert few is not None and few["pairs"] == MIN_PAIRS - 1
    assert f"needs {MIN_PAIRS} well tests" in few["text"]
    # one well test: no gap, no due date
    one = awaiting_well_test(alarm, None, tests[:1])
    assert one is not None and one["typical_gap_days"] is None and one["due"] is None
    # which_moved has its answer, or the alarm is on the well tests: nothing awaited
    check = {
        "well_test_time": "2020-05-20T06:00:00+00:00",
        "relative_difference": 0.1,
        "usual_difference": 0.0,
        "z": 4.0,
    }
    assert awaiting_well_test(alarm, check, tests) is None
    assert awaiting_well_test({**alarm, "source": "well_test"}, None, tests) is None


def test_only_readings_at_the_well_tests_choke_are_compared() -> None:
    """A choke move 2 h before the well test: the readings before it (at another rate)
    are left out, offline as in the service; readings with no sample's choke known are
    compared as before."""
    rows = []
    for h in range(-20, 24, 2):
        choke, q = (0.4, 1000.0) if h < -1 else (0.25, 600.0)
        rows.append({**_row("W01", "mpfm", T0 + h * H, q), "choke": choke})
    rows.append({**_row("W01", "well_test", T0, 610.0), "choke": 0.25})
    checks = mpfm_checks(pd.DataFrame(rows)).set_index("well")
    assert checks.loc["W01", "agrees"] and checks.loc["W01", "mpfm_readings"] == 12
    assert checks.loc["W01", "mpfm_median"] == 600.0
    # no choke column (rates only): every reading within 24 h, the median of 22
    bare = pd.DataFrame([{k: v for k, v in r.items() if k != "choke"} for r in rows])
    assert mpfm_checks(bare).set_index("well").loc["W01", "mpfm_readings"] == 22
