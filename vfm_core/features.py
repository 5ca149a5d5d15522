"""Per-row features that effects and the diagnosis use beyond the six inputs.

:func:`standard_features` computes them for a whole observation frame (offline);
:class:`FeatureTracker` keeps them up to date one row at a time (the streaming service),
so the two agree once a well's first 90 days are over. Units are named with each feature
in :data:`STANDARD_FEATURES`.
"""

from __future__ import annotations

import bisect
import math
from collections.abc import Mapping
from typing import Any, ClassVar

import numpy as np
import pandas as pd

from vfm_core.schema import TARGET, TIME, WELL

__all__ = [
    "HOURS_PER_YEAR",
    "STANDARD_FEATURES",
    "standard_features",
    "standard_scale",
    "FeatureTracker",
]

HOURS_PER_YEAR = 365.25 * 24.0
#: Longest time step (hours) integrated into the cumulative throughput: longer gaps
#: between rows are shut-ins or historian gaps, not production.
_MAX_STEP_HOURS = 48.0


# --- features ---------------------------------------------------------------------------
#: Names of the features :func:`standard_features` computes, with their units.
STANDARD_FEATURES: dict[str, str] = {
    "years_on": "years since the well's first row (yr)",
    "throughput_years": "cumulative produced standard volume over one year of the well's "
    "early median rate (year-equivalents, -)",
    "water_cut": "water share of the liquid mass, eta_wat / (eta_oil + eta_wat) (-)",
}


def standard_features(frame: pd.DataFrame) -> pd.DataFrame:
    """Per-row features effects and diagnosis use, indexed like ``frame``.

    ``throughput_years`` integrates the last measured rate (forward-filled, so a row never
    sees its own measurement) over time per well, gaps longer than 48 h counted as 48 h,
    divided by the well's median measured rate in its first 90 days times one year.
    """
    out = pd.DataFrame(index=frame.index)
    t = pd.to_datetime(frame[TIME], utc=True)
    hours = (t - t.min()).dt.total_seconds().to_numpy() / 3600.0
    wells = frame[WELL].astype(str).to_numpy()
    q = pd.to_numeric(frame[TARGET], errors="coerce").to_numpy(dtype=float)
    years_on = np.zeros(len(frame))
    throughput = np.zeros(len(frame))
    for well in pd.unique(wells):
        idx = np.flatnonzero(wells == well)
        idx = idx[np.argsort(hours[idx], kind="stable")]
        h = hours[idx]
        years_on[idx] = (h - h[0]) / HOURS_PER_YEAR
        rate = pd.Series(q[idx]).ffill().fillna(0.0).to_numpy()
        dt = np.clip(np.diff(h, prepend=h[0]), 0.0, _MAX_STEP_HOURS)
        prev_rate = np.concatenate([[0.0], rate[:-1]])
        cumulative = np.cumsum(prev_rate * dt)
        early = q[idx][(h - h[0]) <= 90 * 24.0]
        early = early[np.isfinite(early) & (early > 0)]
        finite = q[idx][np.isfinite(q[idx]) & (q[idx] > 0)]
        scale = np.median(early) if len(early) else (np.median(finite) if len(finite) else 1.0)
        throughput[idx] = cumulative / (scale * HOURS_PER_YEAR)
    out["years_on"] = years_on
    out["throughput_years"] = throughput
    oil = frame["eta_oil"].to_numpy(dtype=float)
    wat = 1.0 - frame["eta_gas"].to_numpy(dtype=float) - oil
    out["water_cut"] = np.clip(wat / np.clip(oil + wat, 1e-9, None), 0.0, 1.0)
    return out


def standard_scale(q: np.ndarray, time_ns: np.ndarray, first_ns: int) -> float:
    """The throughput scale of :func:`standard_features`: the median measured rate (Sm3/h)
    of the well's first 90 days (else of all its rows; 1 without any)."""
    ok = np.isfinite(q) & (q > 0)
    early = ok & (time_ns - first_ns <= int(90 * 24 * 3600 * 1e9))
    if early.any():
        return float(np.median(q[early]))
    return float(np.median(q[ok])) if ok.any() else 1.0


def _sorted_median(values: list[float]) -> float:
    """The median of a sorted, non-empty list: what ``np.median`` gives (the middle value,
    or the mean of the two middle ones), without sorting or converting the list."""
    n = len(values)
    mid = n // 2
    return values[mid] if n % 2 else (values[mid - 1] + values[mid]) / 2


class FeatureTracker:
    """The standard features of one well, kept up to date one row at a time (the service).

    Follows :func:`standard_features` row by row: ``advance(t)`` integrates the last measured
    rate up to ``t`` (steps capped at 48 h, never backwards) and returns the features at
    ``t``; ``measured(t, q)`` then records the row's own rate, which only later rows see.
    The throughput scale is the median measured rate of the well's first 90 days; until 90
    days have passed it is the median so far (offline, the whole 90 days are known at once).
    State is plain numbers (:meth:`state` / :meth:`from_state`), for checkpoints.
    """

    names: ClassVar[tuple[str, ...]] = tuple(STANDARD_FEATURES)
    # :meth:`advance` writes its list in this order
    assert names == ("years_on", "throughput_years", "water_cut")
    _EARLY_NS: ClassVar[int] = int(90 * 24 * 3600 * 1e9)

    def __init__(self) -> None:
        self.first_ns: int | None = None
        self.last_ns: int | None = None
        self.last_rate = 0.0
        self.cumulative = 0.0  # Sm3 (rate x hours)
        #: the measured rates of the first 90 days, kept sorted: their median is read in
        #: O(1) after each new rate (a young well's MPFM adds thousands of them)
        self.early: list[float] = []
        self.scale: float | None = None  # fixed once the first 90 days are over

    def _scale(self) -> float:
        if self.scale is not None:
            return self.scale
        return _sorted_median(self.early) if self.early else 1.0

    def advance(self, time_ns: int, eta_gas: float, eta_oil: float) -> list[float]:
        """Features at ``time_ns`` for a row with these mass fractions, in :attr:`names` order."""
        if self.first_ns is None:
            self.first_ns = self.last_ns = time_ns
        assert self.last_ns is not None
        if time_ns > self.last_ns:
            hours = min((time_ns - self.last_ns) / 3.6e12, _MAX_STEP_HOURS)
            self.cumulative += self.last_rate * hours
            self.last_ns = time_ns
        if self.scale is None and time_ns - self.first_ns > self._EARLY_NS and self.early:
            self.scale = _sorted_median(self.early)
        wat = 1.0 - eta_gas - eta_oil
        scale = self.scale if self.scale is not None else self._scale()
        # in :attr:`names` order (asked once per sample: no dict of names)
        return [
            max(time_ns - self.first_ns, 0) / 3.6e12 / HOURS_PER_YEAR,
            self.cumulative / (scale * HOURS_PER_YEAR),
            min(max(wat / max(eta_oil + wat, 1e-9), 0.0), 1.0),
        ]

    def advance_many(
        self, times_ns: np.ndarray, eta_gas: np.ndarray, eta_oil: np.ndarray
    ) -> np.ndarray:
        """:meth:`advance` for rows with no measurement among them (a block of samples),
        in one pass: the features [N, k] in :attr:`names` order, and the same state after.

        Without a measurement the last rate and the scale's median stay fixed, so the
        throughput integrates one rate over the rows' capped steps; ``times_ns`` need not
        rise (a step backwards integrates nothing, as in :meth:`advance`)."""
        t = np.asarray(times_ns, dtype=np.int64)
        n = len(t)
        if n == 0:
            return np.zeros((0, len(self.names)))
        if self.first_ns is None:
            self.first_ns = self.last_ns = int(t[0])
        assert self.last_ns is not None
        # the clock only moves forward: each row's step is from the latest time before it
        clock = np.maximum.accumulate(np.concatenate([[self.last_ns], t]))
        hours = np.minimum(np.diff(clock) / 3.6e12, _MAX_STEP_HOURS)
        # summed in the order :meth:`advance` adds (the same rounding)
        cumulative = np.cumsum(np.concatenate([[self.cumulative], self.last_rate * hours]))[1:]
        scale = self._scale()  # the median of the early rates: no row here changes it
        wat = 1.0 - np.asarray(eta_gas, dtype=float) - np.asarray(eta_oil, dtype=float)
        values = {
            "years_on": np.maximum(t - self.first_ns, 0) / 3.6e12 / HOURS_PER_YEAR,
            "throughput_years": cumulative / (scale * HOURS_PER_YEAR),
            "water_cut": np.clip(wat / np.maximum(np.asarray(eta_oil) + wat, 1e-9), 0.0, 1.0),
        }
        self.cumulative = float(cumulative[-1])
        self.last_ns = int(clock[-1])
        if self.scale is None and self.last_ns - self.first_ns > self._EARLY_NS and self.early:
            self.scale = _sorted_median(self.early)
        return np.stack([values[name] for name in self.names], axis=1)

    def measured(self, time_ns: int, q_total: float) -> None:
        """Record a measured rate (Sm3/h) at ``time_ns`` (after :meth:`advance` for that row)."""
        if not (math.isfinite(q_total) and q_total > 0):
            return
        if self.first_ns is None:
            self.first_ns = self.last_ns = time_ns
        if self.scale is None and time_ns - self.first_ns <= self._EARLY_NS:
            bisect.insort(self.early, float(q_total))
        self.last_rate = float(q_total)

    @classmethod
    def from_frame(cls, frame: pd.DataFrame) -> tuple[FeatureTracker, np.ndarray]:
        """A tracker that has seen one well's rows (time order) and those rows' features [N, k]."""
        feats = standard_features(frame)
        tr = cls()
        if frame.empty:
            return tr, np.zeros((0, len(cls.names)))
        ns = pd.DatetimeIndex(pd.to_datetime(frame[TIME], utc=True)).as_unit("ns").asi8
        q = pd.to_numeric(frame[TARGET], errors="coerce").to_numpy(dtype=float)
        order = np.argsort(ns, kind="stable")
        tr.first_ns, tr.last_ns = int(ns[order[0]]), int(ns[order[-1]])
        ok = np.isfinite(q) & (q > 0)
        early = ok & (ns - tr.first_ns <= cls._EARLY_NS)
        if tr.last_ns - tr.first_ns <= cls._EARLY_NS:  # the first 90 days are not over yet
            tr.scale = None
            tr.early = sorted(float(v) for v in q[early])  # sorted: time order is not needed
        else:
            tr.scale = standard_scale(q, ns, tr.first_ns)
        if ok.any():
            tr.last_rate = float(q[order][ok[order]][-1])
        last = order[-1]
        tr.cumulative = (
            float(feats["throughput_years"].to_numpy()[last])
            * standard_scale(q, ns, tr.first_ns)
            * HOURS_PER_YEAR
        )
        return tr, feats[list(cls.names)].to_numpy(dtype=float)

    def state(self) -> dict[str, Any]:
        return {
            "first_ns": self.first_ns,
            "last_ns": self.last_ns,
            "last_rate": self.last_rate,
            "cumulative": self.cumulative,
            "early": list(self.early),
            "scale": self.scale,
        }

    @classmethod
    def from_state(cls, state: Mapping[str, Any]) -> FeatureTracker:
        tr = cls()
        tr.first_ns = state.get("first_ns")
        tr.last_ns = state.get("last_ns")
        tr.last_rate = float(state.get("last_rate", 0.0))
        tr.cumulative = float(state.get("cumulative", 0.0))
        tr.early = sorted(float(v) for v in state.get("early", []))
        scale = state.get("scale")
        tr.scale = None if scale is None else float(scale)
        return tr
