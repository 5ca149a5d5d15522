"""The MPFM checked against the well tests: the rule of the service's MPFM alarm, offline too.

A well test is the reference a multiphase meter is checked against. The rule (the
service's :class:`service.engine.alarms.MpfmCheck` applies it live, :func:`mpfm_checks`
over a whole observation frame): the median of the well's MPFM readings within
``window_s`` (24 h) either side of the well test, and at its choke (no choke move between
them, :func:`steady_span`, s54), is compared with the well test; when
they differ by more than ``rel`` (10 %) of the well test, the meter disagrees with it
(:func:`compare`). A well test with no MPFM reading in its window is not compared.

Against its usual difference (:func:`against_usual`): a meter that has read 2 % high for
months and reads 9 % high today moved by 7 %, though the band still takes it. Each compared
well test's log ratio is set against the median of the well's last ``USUAL_PAIRS`` (20)
earlier ones, in robust standard deviations (1.4826 MAD, at least ``MIN_SPREAD``, 1 %):
``z``; from ``MIN_PAIRS`` (8) earlier pairs on. ``|z| > SHIFT_Z`` (3) says the MPFM moved
against the well tests (the meter, not the well: a well that changed moves both meters).
This is what tells a residual alarm on the MPFM's stream apart (:func:`which_moved`): the
alarm says the MPFM left the model; a well test after it began says whether the
well went with it (``|z| < SAME_Z``, 1: the MPFM reads against it as usual), or the meter
moved (``|z| > SHIFT_Z``), or it cannot tell (in between). On clean simulated fields 4 to
5 % of the pairs have ``|z| > 3`` (the pairs' tails are heavier than a Gaussian's), so the
z is read only beside an alarm, never as an alarm of its own (alarms guide, "A meter that
starts to read off").

Why a fixed band and not a sequential test on the same pairs: a pair's spread is 2.5 to
5 % on simulated fields (the meter's noise over one to three readings, the well test's,
and the rate moving within the 24 h), and well tests come 3 to 8 weeks apart, so a CUSUM
on them needs three or more well tests (months) even for a 10 % step, which the band
flags at the first well test after it (see the alarms guide, "A meter that starts to read
off").
"""

from __future__ import annotations

import math
import statistics
from collections.abc import Sequence
from typing import Any

import numpy as np
import pandas as pd

from vfm_core import schema

__all__ = [
    "CHOKE_MOVE",
    "MIN_PAIRS",
    "SAME_Z",
    "SHIFT_Z",
    "USUAL_PAIRS",
    "against_usual",
    "compare",
    "awaiting_well_test",
    "mpfm_checks",
    "steady_span",
    "which_moved",
]

#: earlier pairs a well test is set against, at most and at least; the z beyond which the
#: MPFM moved; the least robust sd of a pair's log ratio (1 %: a well test's own noise)
USUAL_PAIRS = 20
MIN_PAIRS = 8
SHIFT_Z = 3.0
#: the |z| within which a well test says the MPFM reads as it usually does against it
SAME_Z = 1.0
MIN_SPREAD = 0.01
#: a relative change of the choke's reading between two samples above which the choke moved
#: (its position is a set point: it stays put between moves; a 1 % move changes the rate by
#: about 1 % or more, a move smaller than that is lost in the pair's spread of 2.5-5 %)
CHOKE_MOVE = 0.01


def compare(readings: Sequence[float], q_total: float, rel: float) -> dict[str, Any] | None:
    """The MPFM readings (Sm3/h) near a well test of ``q_total`` Sm3/h against it:
    ``{"mpfm_median", "mpfm_readings", "relative_difference", "agrees"}``, or None when
    there is nothing to compare (no reading, or a well test that is not positive).

    >>> compare([105.0, 112.0, 111.0], 100.0, 0.10)["agrees"]
    False
    >>> compare([105.0, 108.0, 103.0], 100.0, 0.10)["relative_difference"]
    0.05
    """
    if not (math.isfinite(q_total) and q_total > 0) or not readings:
        return None
    median = float(statistics.median(readings))
    difference = (median - q_total) / q_total
    return {
        "mpfm_median": median,
        "mpfm_readings": len(readings),
        "relative_difference": difference,
        "agrees": abs(difference) <= rel,
    }


def steady_span(
    times: Sequence[int], chokes: Sequence[float], time_ns: int
) -> tuple[int, int] | None:
    """The span (epoch ns, both ends in) around ``time_ns`` in which the choke did not move,
    from samples (``times`` ascending, with the choke's reading, fraction open): from the
    first to the last sample whose reading is within :data:`CHOKE_MOVE` (relative) of the
    reading of the sample nearest ``time_ns``, with no move between. On a side with no
    sample that moved, the span is open (a reading after the last sample, or before the
    first, is at the same choke as far as anything shows). A well test is compared only
    with the MPFM readings in that span: across a choke move the rate itself changes (a
    choke closed from 0.38 to 0.25 two hours before a well test put the median of the day's
    readings 48 % above it, with both meters right). A reading between the last sample
    before a move and the first after it is left out (the move fell somewhere between).
    None without samples.

    >>> h = 3600 * 10**9
    >>> steady_span([0, h, 2 * h, 3 * h, 4 * h], [0.5, 0.5, 0.3, 0.3, 0.3], 3 * h + 10)[0] // h
    2
    >>> steady_span([0, h, 2 * h], [0.5, 0.5, 0.3], 10)[1] // h
    1
    """
    if not len(times):
        return None
    k = int(np.searchsorted(times, time_ns))
    if k == len(times) or (k > 0 and time_ns - times[k - 1] <= times[k] - time_ns):
        k -= 1

    def same(i: int, j: int) -> bool:
        a, b = chokes[i], chokes[j]
        return bool(abs(a - b) <= CHOKE_MOVE * max(abs(a), abs(b), 1e-9))

    a = k
    while a > 0 and same(a - 1, a):
        a -= 1
    b = k
    while b + 1 < len(times) and same(b + 1, b):
        b += 1
    lo = int(times[a]) if a > 0 else -_OPEN
    hi = int(times[b]) if b + 1 < len(times) else _OPEN
    return lo, hi


#: an open end of :func:`steady_span` (epoch ns far beyond any data)
_OPEN = 2**62


def against_usual(earlier: Sequence[float], difference: float) -> dict[str, Any] | None:
    """A pair's ``difference`` (relative, as :func:`compare` gives it) against the well's
    ``earlier`` ones (relative, oldest first; the last :data:`USUAL_PAIRS` are used):
    ``{"usual_difference", "usual_spread", "z", "shifted"}`` (the median, the robust sd of
    the log ratios, the pair's z, whether ``|z| > SHIFT_Z``), or None with fewer than
    :data:`MIN_PAIRS` earlier pairs.

    >>> r = against_usual([0.02, 0.01, 0.03, 0.02, 0.025, 0.015, 0.02, 0.01], 0.09)
    >>> round(r["usual_difference"], 3), r["shifted"]
    (0.02, True)
    """
    logs = np.log1p(np.asarray(earlier[-USUAL_PAIRS:], dtype=float))
    logs = logs[np.isfinite(logs)]
    if len(logs) < MIN_PAIRS or not difference > -1.0:
        return None
    centre = float(np.median(logs))
    spread = max(1.4826 * float(np.median(np.abs(logs - centre))), MIN_SPREAD)
    z = (math.log1p(difference) - centre) / spread
    return {
        "usual_difference": math.expm1(centre),
        "usual_spread": spread,
        "z": z,
        "shifted": abs(z) > SHIFT_Z,
    }


def which_moved(
    alarm: dict[str, Any],
    check: dict[str, Any] | None,
    pairs: Sequence[tuple[int, float]] = (),
) -> dict[str, Any] | None:
    """Beside an active residual alarm on the MPFM's stream (``alarm``: the residual
    alarm's view, ``source`` ``mpfm``, ``since`` ISO, and ``shift``, the alarm's relative
    size when known, with ``shift_se``, its standard error in log terms,
    :class:`vfm_core.residual_alarm.AlarmSize`), what the well tests compared since the
    alarm began say (``check``: the well's latest MPFM check, with :func:`against_usual`'s
    fields, set against the pairs from before the alarm; ``pairs``: the well's compared
    well tests as (epoch ns, relative difference), those from the alarm's start to the
    check's well test read together with it): ``{"well_test_time", "z", "moved", "text",
    "alarm_shift", "meter_z", "n_well_tests", "z_latest"}`` with ``moved`` ``meter``,
    ``well`` or ``unclear``. None when the alarm is on another stream, or no such well
    test has been set against its usual difference yet.

    Several well tests since the alarm read together (s54): their pairs' mean move from
    the usual difference, whose spread is the pairs' over the square root of their number
    (``z`` is that mean's; ``z_latest`` the latest pair's alone, as before). A shift that
    one well test cannot tell from the pairs' spread is told by two or three: a well test
    comes every 3 to 8 weeks, and an alarm on a meter or a well that moved stays active.
    With one well test (or no ``pairs``) this is the latest pair's reading, as before.

    Two readings of the pair's move ``d`` (its z times the pairs' spread): if the meter
    moved, ``d`` is the alarm's shift (the well tests stayed); if the well moved, ``d`` is
    0 (both meters went with it). ``meter`` when ``|z| > SHIFT_Z`` (and, with a known
    shift, in its direction); ``well`` when ``|z| < SAME_Z`` and, with a known shift, the
    pair lies at least ``SHIFT_Z - SAME_Z`` spreads from it (``meter_z``: how many spreads
    ``d`` is from the shift; the spread there is the pairs' and the shift's standard error
    together). A shift within two spreads can be neither told apart nor
    ruled out by one well test: ``unclear``, and the text says so (a meter that drifts
    slowly raises its alarm at a small shift). Without a shift (an alarm from before s51)
    the z alone decides, as before.

    >>> alarm = {"active": True, "source": "mpfm", "since": "2020-05-01T00:00:00+00:00"}
    >>> check = {"well_test_time": "2020-05-20T06:00:00+00:00", "z": 4.2,
    ...          "relative_difference": 0.09, "usual_difference": 0.01, "usual_spread": 0.02}
    >>> which_moved(alarm, check)["moved"]
    'meter'
    >>> which_moved({**alarm, "shift": 0.02}, {**check, "z": 0.3})["moved"]
    'unclear'
    >>> which_moved({**alarm, "shift": 0.08}, {**check, "z": 0.3})["moved"]
    'well'
    """
    if alarm.get("source") != "mpfm" or not alarm.get("since") or check is None:
        return None
    z, when = check.get("z"), check.get("well_test_time")
    if z is None or not math.isfinite(z) or not when:
        return None
    if pd.Timestamp(when) < pd.Timestamp(alarm["since"]):
        return None
    z_latest = float(z)
    day = str(when)[:10]
    now, usual = 100 * check["relative_difference"], 100 * check["usual_difference"]
    spread = _number(check.get("usual_spread"))
    moves = _moves_since(alarm, check, pairs) if spread > 0 else []
    n = len(moves) if moves else 1
    if n > 1:  # the pairs since the alarm together: their mean move, in its own spreads
        z, reads = _together(moves, check["usual_difference"], spread, day)
    else:
        reads = (
            f"the MPFM reads {now:+.1f} % against the well test of {day}, usually {usual:+.1f} %"
        )
    shift = _number(alarm.get("shift"))
    s, wide = _shift_and_spread(alarm, spread / math.sqrt(n))
    known = math.isfinite(wide)
    meter_z = (z * spread / math.sqrt(n) - s) / wide if known else None
    moved, text = _decide(z, s, wide, meter_z, n, reads, shift)
    return {
        "well_test_time": when,
        "z": z,
        "moved": moved,
        "text": text,
        "alarm_shift": shift if known else None,
        "meter_z": meter_z,
        "n_well_tests": n,
        "z_latest": z_latest,
    }


def _decide(
    z: float, s: float, wide: float, meter_z: float | None, n: int, reads: str, shift: float
) -> tuple[str, str]:
    """:func:`which_moved`'s rule on a move of ``z`` spreads (``s``: the alarm's shift in
    log terms, ``wide``: the spread about it, NaN when not known; ``n`` well tests read):
    ``(moved, text)``."""
    known = math.isfinite(wide)
    apart = SHIFT_Z - SAME_Z
    if abs(z) > SHIFT_Z and (not known or z * s > 0):
        moved, text = "meter", f"{reads} (z {z:+.1f}): the meter moved, not the well"
    elif abs(z) < SAME_Z and (meter_z is None or abs(meter_z) >= apart):
        moved, text = "well", f"{reads} (z {z:+.1f}): the well test moved with it: the well changed"
    elif known and abs(s) < apart * wide:
        whose = "the pairs'" if n == 1 else "their mean's"
        size = f"the alarm's shift ({100 * shift:+.1f} %) is within {apart:.0f} of {whose} "
        size += f"spreads ({100 * wide:.1f} %)"
        cannot = "no one well test can tell" if n == 1 else f"{n} well tests cannot tell yet"
        moved, text = "unclear", f"{reads} (z {z:+.1f}); {size}: {cannot}"
    else:
        these = "this well test" if n == 1 else f"these {n} well tests"
        moved, text = "unclear", f"{reads} (z {z:+.1f}): {these} cannot tell meter from well"
    return moved, text


def _together(moves: Sequence[float], usual: float, spread: float, day: str) -> tuple[float, str]:
    """The z of the mean of ``moves`` (log moves from the ``usual`` relative difference,
    pairs of robust sd ``spread``) and the sentence that reads them (``day``: the latest's)."""
    mean, n = statistics.fmean(moves), len(moves)
    now = 100 * math.expm1(math.log1p(usual) + mean)
    reads = (
        f"the MPFM reads {now:+.1f} % on average against the {n} well tests since the "
        f"alarm began (the latest of {day}), usually {100 * usual:+.1f} %"
    )
    return mean / (spread / math.sqrt(n)), reads


def _moves_since(
    alarm: dict[str, Any], check: dict[str, Any], pairs: Sequence[tuple[int, float]]
) -> list[float]:
    """The log moves from the usual difference (``check``'s, from before the alarm) of the
    pairs compared from the alarm's start to ``check``'s well test, that one included (an
    empty list when ``pairs`` does not hold it: then the check is read alone)."""
    since = pd.Timestamp(alarm["since"]).value
    until = pd.Timestamp(check["well_test_time"]).value
    centre = math.log1p(check["usual_difference"])
    chosen = [(t, r) for t, r in pairs if since <= t <= until and r > -1.0]
    if not chosen or max(t for t, _ in chosen) != until:
        return []
    return [math.log1p(r) - centre for _, r in chosen]


def _shift_and_spread(alarm: dict[str, Any], spread: Any) -> tuple[float, float]:
    """The alarm's shift in log terms and the spread a pair would have about it if the
    meter moved (the pairs' robust sd and the shift's standard error together); NaN both
    where either is not known."""
    shift, spread = _number(alarm.get("shift")), _number(spread)
    if not (spread > 0 and shift > -1.0):
        return math.nan, math.nan
    se = _number(alarm.get("shift_se"))
    return math.log1p(shift), math.hypot(spread, se if se >= 0 else 0.0)


def _number(v: Any) -> float:
    """``v`` as a finite float, or NaN (None, text, inf)."""
    return float(v) if isinstance(v, int | float) and math.isfinite(v) else math.nan


def awaiting_well_test(
    alarm: dict[str, Any],
    check: dict[str, Any] | None,
    test_ns: Sequence[int],
    now_ns: int | None = None,
) -> dict[str, Any] | None:
    """Beside an active residual alarm on the MPFM's stream that :func:`which_moved` cannot
    read yet, what will tell: ``{"last_well_test", "typical_gap_days", "due", "pairs",
    "text"}``. ``test_ns`` are the times (epoch ns) of the well's well tests compared with
    its MPFM (the service keeps the last ``2 * USUAL_PAIRS``); ``typical_gap_days`` is the
    median gap between them (days; None below three), ``due`` the last one plus that gap,
    ``pairs`` how many came before the alarm (from :data:`MIN_PAIRS` on, the next well test
    can say which moved, unless the alarm's shift is within two of the pairs' spreads in
    ``check``, :func:`which_moved`: the text then says so), ``overdue`` whether ``now_ns`` (the well's latest data time,
    epoch ns; None: not known) is past ``due``: the text then says since when, instead of
    "due about" a date gone by. None when :func:`which_moved` has its answer, or the alarm
    is not on the MPFM's stream.

    >>> alarm = {"active": True, "source": "mpfm", "since": "2020-05-01T00:00:00+00:00"}
    >>> day = 86_400 * 10**9
    >>> tests = [pd.Timestamp("2020-01-01", tz="UTC").value + k * 30 * day for k in range(9)]
    >>> awaiting_well_test(alarm, None, tests)["due"][:10]
    '2020-09-27'
    >>> late = pd.Timestamp("2020-10-20", tz="UTC").value
    >>> later = {**alarm, "since": "2020-08-01T00:00:00+00:00"}
    >>> awaiting_well_test(later, None, tests, late)["text"][-42:]
    'overdue since 2020-09-27, usually 30 days)'
    """
    if alarm.get("source") != "mpfm" or not alarm.get("since"):
        return None
    if which_moved(alarm, check) is not None:
        return None
    ns = np.sort(np.asarray(list(test_ns), dtype=np.int64))
    pairs = int(np.sum(ns < pd.Timestamp(alarm["since"]).value))
    gap = float(np.median(np.diff(ns))) / 86_400e9 if len(ns) >= 3 else None
    last = pd.Timestamp(int(ns[-1]), tz="UTC") if len(ns) else None
    due = last + pd.Timedelta(days=gap) if last is not None and gap is not None else None
    overdue = due is not None and now_ns is not None and int(now_ns) > due.value
    if pairs < MIN_PAIRS:
        text = (
            f"which moved, the meter or the well, needs {MIN_PAIRS} well tests compared with "
            f"the MPFM before the alarm; this well has {pairs}"
        )
    else:
        text = (
            "no well test since the alarm: the next one tells whether the meter or the well moved"
        )
        s, wide = _shift_and_spread(alarm, (check or {}).get("usual_spread"))
        if abs(s) < (SHIFT_Z - SAME_Z) * wide:  # (False with NaN)
            text = (
                f"no well test since the alarm; its shift ({100 * math.expm1(s):+.1f} %) is "
                f"within {SHIFT_Z - SAME_Z:.0f} of the pairs' spreads ({100 * wide:.1f} %): "
                "one well test will not tell whether the meter or the well moved"
            )
        if last is not None:
            text += f" (last {last.date().isoformat()}"
            if due is not None and overdue:
                text += f", overdue since {due.date().isoformat()}, usually {gap:.0f} days)"
            else:
                text += f", due about {due.date().isoformat()})" if due is not None else ")"
    return {
        "last_well_test": None if last is None else last.isoformat(),
        "typical_gap_days": gap,
        "due": None if due is None else due.isoformat(),
        "pairs": pairs,
        "overdue": overdue,
        "text": text,
    }


def mpfm_checks(frame: pd.DataFrame, rel: float = 0.10, window_s: float = 86_400.0) -> pd.DataFrame:
    """Every well test of ``frame`` (validated observations) compared with the MPFM
    readings within ``window_s`` of it, by :func:`compare`, and with the well's earlier
    pairs by :func:`against_usual` (NaN / None before :data:`MIN_PAIRS`): one row per
    compared well test, columns ``well``, ``time``, ``well_test_q_total`` and the two
    functions' fields."""
    rows: list[dict[str, Any]] = []
    window = int(round(window_s * 1e9))
    ns = pd.to_datetime(frame[schema.TIME], utc=True).dt.as_unit("ns").astype("int64")
    for well, g in frame.assign(_ns=ns).groupby(schema.WELL, sort=True):
        g = g.sort_values("_ns", kind="stable")
        mpfm = g[g[schema.SOURCE] == schema.MPFM]
        times = mpfm["_ns"].to_numpy()
        rates = mpfm[schema.TARGET].to_numpy(dtype=float)
        tests = g[g[schema.SOURCE] == schema.WELL_TEST]
        choke = g["choke"] if "choke" in g else pd.Series(np.nan, index=g.index)
        known = choke.notna().to_numpy()
        sample_ns, chokes = g["_ns"].to_numpy()[known], choke.to_numpy(dtype=float)[known]
        earlier: list[float] = []
        for t, q in zip(tests["_ns"], tests[schema.TARGET].to_numpy(dtype=float), strict=True):
            lo_ns, hi_ns = t - window, t + window
            steady = steady_span(sample_ns, chokes, t)
            if steady is not None:  # only the readings at the well test's choke
                lo_ns, hi_ns = max(lo_ns, steady[0]), min(hi_ns, steady[1])
            lo = np.searchsorted(times, lo_ns, "left")
            hi = np.searchsorted(times, hi_ns, "right")
            found = compare([float(r) for r in rates[lo:hi] if math.isfinite(r)], q, rel)
            if found is None:
                continue
            usual = against_usual(earlier, found["relative_difference"]) or _NO_USUAL
            earlier.append(found["relative_difference"])
            when = pd.Timestamp(int(t), tz="UTC")
            rows.append({"well": str(well), "time": when, "well_test_q_total": q, **found, **usual})
    columns = ["well", "time", "well_test_q_total", "mpfm_median", "mpfm_readings"]
    return pd.DataFrame(rows, columns=[*columns, "relative_difference", "agrees", *_NO_USUAL])


_NO_USUAL: dict[str, Any] = {
    "usual_difference": math.nan,
    "usual_spread": math.nan,
    "z": math.nan,
    "shifted": None,
}
