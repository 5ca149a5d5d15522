"""The MPFM checked against the well tests: the rule of the service's MPFM alarm, offline too.

A well test is the reference a multiphase meter is checked against. The rule (the
service's :class:`service.engine.alarms.MpfmCheck` applies it live, :func:`mpfm_checks`
over a whole observation frame): the median of the well's MPFM readings within
``window_s`` (24 h) either side of the well test is compared with the well test; when
they differ by more than ``rel`` (10 %) of the well test, the meter disagrees with it
(:func:`compare`). A well test with no MPFM reading in its window is not compared.

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

__all__ = ["compare", "mpfm_checks"]


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


def mpfm_checks(frame: pd.DataFrame, rel: float = 0.10, window_s: float = 86_400.0) -> pd.DataFrame:
    """Every well test of ``frame`` (validated observations) compared with the MPFM
    readings within ``window_s`` of it, by :func:`compare`: one row per compared well test,
    columns ``well``, ``time``, ``well_test_q_total`` and :func:`compare`'s fields."""
    rows: list[dict[str, Any]] = []
    window = int(round(window_s * 1e9))
    ns = pd.to_datetime(frame[schema.TIME], utc=True).dt.as_unit("ns").astype("int64")
    for well, g in frame.assign(_ns=ns).groupby(schema.WELL, sort=True):
        g = g.sort_values("_ns", kind="stable")
        mpfm = g[g[schema.SOURCE] == schema.MPFM]
        times = mpfm["_ns"].to_numpy()
        rates = mpfm[schema.TARGET].to_numpy(dtype=float)
        tests = g[g[schema.SOURCE] == schema.WELL_TEST]
        for t, q in zip(tests["_ns"], tests[schema.TARGET].to_numpy(dtype=float), strict=True):
            lo = np.searchsorted(times, t - window, "left")
            hi = np.searchsorted(times, t + window, "right")
            found = compare([float(r) for r in rates[lo:hi] if math.isfinite(r)], q, rel)
            if found is not None:
                when = pd.Timestamp(int(t), tz="UTC")
                rows.append({"well": str(well), "time": when, "well_test_q_total": q, **found})
    columns = ["well", "time", "well_test_q_total", "mpfm_median", "mpfm_readings"]
    return pd.DataFrame(rows, columns=[*columns, "relative_difference", "agrees"])
