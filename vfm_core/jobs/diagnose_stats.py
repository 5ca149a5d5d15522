"""Statistics of a diagnosis' residuals: drivers beyond per-well trends, a test of whether any
driver explains more than chance would, and the noise floor of the meters.

All three work on a *residual frame* (see :func:`vfm_core.jobs.diagnose.residual_frame`): one
row per scored measurement with ``time``, ``well``, ``source``, the inputs, derived variables
and the relative residual ``r`` = (measured - predicted)/measured.

**Drivers.** A residual that drifts per well (a meter's slow drift, a model fitted on older
data) correlates with every variable that also moves with time in each well: cumulative
throughput, depleting pressures, rising water cut. Ranking variables on the raw residual
then names whichever of them follows the drift best (the reason ``vfm diagnose`` once
advised an effect of ``throughput_years`` on Volve, where wear is the worst candidate).
So the residual is first *detrended*: a straight line in time is removed per well and
meter (source), and a variable is scored on what it explains of the rest, as a function of
its own deviation from its per-well straight line (the Frisch-Waugh-Lovell way of
controlling for a confounder: both sides lose what the trends explain; the time of year is
taken as it is). Its score is the out-of-sample R^2 of a binned-mean smoother of the variable: the scored period is cut into
consecutive time blocks, the smoother is fitted on all blocks but one and scored on the
held-out block, in turn. ``raw_score`` is the same on the residual before detrending.

**Chance.** Residuals and variables are both autocorrelated, so a plain permutation test
would find "significant" drivers in pure meter drift. The test here keeps each series'
autocorrelation: the detrended residual of every well and source is shifted circularly in
time by a random lag (10-90 % of its span, never within 45 days of a whole number of
years, which would keep a yearly wave aligned with the season), which breaks its alignment
with the variables and nothing else; each shift gives the best score any eligible variable reaches
by chance. A variable's p-value is the share of shifts whose best chance score is at least
its own (the max-statistic correction for trying many variables).

**Noise floor.** What no model of the inputs can remove is the meters' own white noise.
It is estimated from differences of the log residual log(measured/predicted) between
consecutive readings of one meter on one well close in time (at most 48 h apart for an MPFM, 14 days for well tests):
the model's error barely changes between them, the noise is independent, so the median
absolute difference gives the noise scale (robust to the odd jump when a choke moves), and
the floor is the mean absolute relative error of Gaussian noise of that scale (Rice 1984's
difference estimator, in its robust form). A slow meter drift is not in it: the true floor
can be a little higher.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
import pandas as pd

__all__ = [
    "DRIVER_VARIABLES",
    "ELIGIBLE_DRIVERS",
    "UNITS",
    "ALPHA",
    "SHIFTS",
    "driver_values",
    "detrend",
    "rank_drivers",
    "noise_floor",
    "acts_through",
]

#: Variables the residual is examined against (numeric, then categorical).
DRIVER_VARIABLES: tuple[str, ...] = (
    "time",
    "day_of_year",
    "choke",
    "p_up",
    "p_down",
    "p_ratio",
    "t_up",
    "eta_gas",
    "eta_oil",
    "water_cut",
    "throughput_years",
    "well",
    "source",
    "flow_regime",
)
CATEGORICAL = frozenset({"well", "source", "flow_regime"})
#: Variables a verdict may name as the driver of an effect outside the library: physical
#: variables and the season. Time and well are what the detrending removes (confounders);
#: source and flow regime are covered by the mpfm_bias and critical_ratio candidates.
ELIGIBLE_DRIVERS: tuple[str, ...] = (
    "day_of_year",
    "choke",
    "p_up",
    "p_down",
    "p_ratio",
    "t_up",
    "eta_gas",
    "eta_oil",
    "water_cut",
    "throughput_years",
)
UNITS: dict[str, str] = {
    "time": "date",
    "day_of_year": "day",
    "choke": "fraction",
    "p_up": "bar",
    "p_down": "bar",
    "p_ratio": "p_down/p_up",
    "t_up": "degC",
    "eta_gas": "-",
    "eta_oil": "-",
    "water_cut": "water/liquid mass",
    "throughput_years": "year-equivalents",
}
#: Significance level of the chance test (family-wise over the eligible drivers).
ALPHA = 0.01
#: Circular shifts of the chance test (p-values come in steps of 1/(SHIFTS + 1)).
SHIFTS = 199
#: Relative residuals are clipped to +-100 % (a diverged prediction must not decide alone).
CLIP = 1.0
#: Longest gap between two readings of one meter whose difference measures its noise.
FLOOR_GAP = {"mpfm": pd.Timedelta(hours=48), "well_test": pd.Timedelta(days=14)}
_MIN_PAIRS = 10
#: Circular shifts avoid lags within this many days of a whole number of years.
_YEAR_GUARD = 45.0
_NS_PER_YEAR = 86400e9 * 365.25


def driver_values(res: pd.DataFrame, name: str) -> np.ndarray:
    """A driver's values per row: decimal years for ``time``, day of the year (0 on
    1 January) for ``day_of_year``, else the column."""
    if name == "time":
        return 1970.0 + res["time"].astype("int64").to_numpy() / _NS_PER_YEAR
    if name == "day_of_year" and name not in res.columns:
        t = pd.DatetimeIndex(res["time"])
        return (t.day_of_year - 1 + t.hour / 24.0).to_numpy(dtype=float)
    return res[name].to_numpy()


def _groups(res: pd.DataFrame) -> np.ndarray:
    keys = res["well"].astype(str) + "\x00" + res["source"].astype(str)
    return pd.factorize(keys.to_numpy())[0]


def detrend(res: pd.DataFrame, values: np.ndarray | None = None) -> np.ndarray:
    """The clipped residual (or ``values``) minus a straight line in time fitted per well and
    source (a mean where fewer than 3 rows or no time span)."""
    r = (
        np.clip(res["r"].to_numpy(dtype=float), -CLIP, CLIP)
        if values is None
        else np.asarray(values, dtype=float)
    )
    t = driver_values(res, "time")
    g = _groups(res)
    n = np.bincount(g).astype(float)
    mt = np.bincount(g, weights=t) / n
    mr = np.bincount(g, weights=r) / n
    dt = t - mt[g]
    stt = np.bincount(g, weights=dt * dt)
    str_ = np.bincount(g, weights=dt * (r - mr[g]))
    slope = np.where((n >= 3) & (stt > 1e-12), str_ / np.where(stt > 0, stt, 1.0), 0.0)
    return r - mr[g] - slope[g] * dt


class _Folds:
    """Held-out time blocks and each variable's bins per block, fixed once so that scoring
    another residual vector (a shifted one) costs a few ``bincount`` calls."""

    def __init__(
        self, res: pd.DataFrame, names: Sequence[str], blocks: int, bins: int, partial: bool
    ) -> None:
        order = np.argsort(res["time"].to_numpy(), kind="stable")
        block = np.empty(len(res), dtype=int)
        block[order] = np.arange(len(res)) * blocks // len(res)
        self.tests = [block == b for b in range(blocks)]
        self.codes: dict[str, list[tuple[np.ndarray, np.ndarray, int]]] = {}
        for name in names:
            x = driver_values(res, name)
            if partial and name not in CATEGORICAL and name not in ("time", "day_of_year"):
                # Frisch-Waugh-Lovell: the variable's own per-well trend goes too, so that what
                # is binned is the part of x that the detrended residual can depend on
                x = detrend(res, x.astype(float))
            per_fold = []
            for test in self.tests:
                train = ~test
                if name in CATEGORICAL:
                    cats, codes = np.unique(x.astype(str), return_inverse=True)
                    per_fold.append((codes[train], codes[test], len(cats)))
                    continue
                xf = x.astype(float)
                edges = np.unique(np.quantile(xf[train], np.linspace(0, 1, bins + 1)))
                if len(edges) < 2:
                    per_fold.append((np.zeros(train.sum(), int), np.zeros(test.sum(), int), 1))
                    continue
                k = len(edges) - 1
                code_train = np.clip(np.searchsorted(edges, xf[train], side="right") - 1, 0, k - 1)
                code_test = np.clip(np.searchsorted(edges, xf[test], side="right") - 1, 0, k - 1)
                per_fold.append((code_train, code_test, k))
            self.codes[name] = per_fold

    def score(self, name: str, r: np.ndarray) -> float:
        """Held-out R^2 of the binned means of ``r`` by the variable, over all blocks."""
        sse = sst = 0.0
        for test, (c_train, c_test, k) in zip(self.tests, self.codes[name], strict=True):
            r_train, r_test = r[~test], r[test]
            if len(r_train) == 0 or len(r_test) == 0:
                continue
            mean = float(r_train.mean())
            sums = np.bincount(c_train, weights=r_train, minlength=k)
            counts = np.bincount(c_train, minlength=k)
            means = np.where(counts > 0, sums / np.maximum(counts, 1), mean)
            sse += float(((r_test - means[c_test]) ** 2).sum())
            sst += float(((r_test - mean) ** 2).sum())
        return 1.0 - sse / sst if sst > 0 else 0.0


class _Shifter:
    """Circular shifts of a residual within every well and source (rows in time order).

    Each group is shifted by a random time lag of 10-90 % of its span, converted to a row
    offset. Lags within :data:`_YEAR_GUARD` of a whole number of years are redrawn: such a
    shift keeps a yearly wave aligned with the day of the year, and would make the season
    look like chance."""

    def __init__(self, res: pd.DataFrame) -> None:
        g = _groups(res)
        t = res["time"].astype("int64").to_numpy() / 86400e9  # days
        self.order = np.lexsort((t, g))
        g_sorted = g[self.order]
        self.sizes = np.bincount(g)
        self.starts = np.concatenate([[0], np.cumsum(self.sizes)[:-1]])
        self.g_sorted = g_sorted
        self.rank = np.arange(len(self.order)) - self.starts[g_sorted]
        self.times = [
            t[self.order][a : a + n] for a, n in zip(self.starts, self.sizes, strict=True)
        ]

    def _offset(self, rng: np.random.Generator, days: np.ndarray) -> int:
        n = len(days)
        span = float(days[-1] - days[0]) if n > 1 else 0.0
        if n < 3 or span <= 0:
            return 0
        for _ in range(20):
            lag = span * (0.1 + 0.8 * rng.random())
            phase = lag % 365.25
            if min(phase, 365.25 - phase) >= _YEAR_GUARD or lag < 365.25 - _YEAR_GUARD:
                break
        offset = int(np.searchsorted(days, days[0] + lag))
        return min(max(offset, 1), n - 1)

    def shift(self, r: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        offsets = np.array([self._offset(rng, d) for d in self.times], dtype=int)
        sizes = np.maximum(self.sizes, 1)
        source = (
            self.starts[self.g_sorted] + (self.rank + offsets[self.g_sorted]) % sizes[self.g_sorted]
        )
        out = np.empty_like(r)
        out[self.order] = r[self.order][source]
        return out


def rank_drivers(
    residuals: pd.DataFrame,
    variables: Sequence[str] = DRIVER_VARIABLES,
    *,
    blocks: int = 6,
    bins: int = 10,
    shifts: int = 0,
    seed: int = 0,
) -> list[dict[str, Any]]:
    """What each variable explains of the residual beyond per-well trends, best first.

    Each entry: ``name``, ``score`` (held-out R^2 on the detrended residual, see the module
    docstring), ``raw_score`` (the same on the residual as it is), ``unit``, ``role``
    (``driver`` for :data:`ELIGIBLE_DRIVERS`, else ``confounder``) and, with ``shifts`` > 0,
    ``p_value`` of the chance test (eligible drivers only; None for the others).
    """
    variables = [
        v
        for v in variables
        if v in CATEGORICAL or v in ("time", "day_of_year") or v in residuals.columns
    ]
    ok = np.isfinite(residuals["r"].to_numpy(dtype=float))
    res = residuals[ok].reset_index(drop=True)
    if len(res) < 2 * blocks:
        return [
            {
                "name": v,
                "score": 0.0,
                "raw_score": 0.0,
                "unit": UNITS.get(v, "category"),
                "role": "driver" if v in ELIGIBLE_DRIVERS else "confounder",
                "p_value": None,
            }
            for v in variables
        ]
    folds = _Folds(res, variables, blocks, bins, partial=True)
    raw = _Folds(res, variables, blocks, bins, partial=False)
    r_raw = np.clip(res["r"].to_numpy(dtype=float), -CLIP, CLIP)
    r_d = detrend(res)
    out: list[dict[str, Any]] = []
    for name in variables:
        out.append(
            {
                "name": name,
                "score": folds.score(name, r_d),
                "raw_score": raw.score(name, r_raw),
                "unit": UNITS.get(name, "category"),
                "role": "driver" if name in ELIGIBLE_DRIVERS else "confounder",
                "p_value": None,
            }
        )
    eligible = [v for v in variables if v in ELIGIBLE_DRIVERS]
    if shifts > 0 and eligible:
        rng = np.random.default_rng(seed)
        shifter = _Shifter(res)
        best = np.empty(shifts)
        for s in range(shifts):
            shifted = shifter.shift(r_d, rng)
            best[s] = max(folds.score(v, shifted) for v in eligible)
        for d in out:
            if d["name"] in eligible:
                d["p_value"] = float((1 + np.sum(best >= d["score"])) / (shifts + 1))
    return sorted(out, key=lambda d: -d["score"])


def noise_floor(residuals: pd.DataFrame) -> dict[str, Any]:
    """The meters' white-noise floor as a MAPE (%), overall and per source; see the module
    docstring. ``mape`` is None when no meter has enough close pairs of readings."""
    res = residuals.copy()
    if {"measured", "predicted"} <= set(res.columns):
        # in logs, the meter's relative noise adds to the model's error whatever its size
        # (in (m - p)/m it is scaled by p/q: a model that under-predicts shrinks it)
        with np.errstate(divide="ignore", invalid="ignore"):
            res["r"] = np.log(
                res["measured"].to_numpy(dtype=float) / res["predicted"].to_numpy(dtype=float)
            )
    res = res[np.isfinite(res["r"].to_numpy(dtype=float))]
    by_source: dict[str, dict[str, Any]] = {}
    weighted = 0.0
    rows = 0
    for source, g_src in res.groupby("source", sort=True):
        gap = FLOOR_GAP.get(str(source), FLOOR_GAP["mpfm"])
        total_rows = est_rows = pairs = 0
        acc = 0.0
        for _, g in g_src.groupby("well", sort=False):
            g = g.sort_values("time", kind="stable")
            total_rows += len(g)
            r = np.clip(g["r"].to_numpy(dtype=float), -CLIP, CLIP)
            close = np.diff(g["time"].to_numpy()) <= gap.to_timedelta64()
            d = np.diff(r)[close]
            if len(d) < _MIN_PAIRS:
                continue
            sd = float(np.median(np.abs(d))) / (0.6745 * math.sqrt(2.0))
            acc += len(g) * 100.0 * sd * math.sqrt(2.0 / math.pi)
            est_rows += len(g)
            pairs += len(d)
        value = acc / est_rows if est_rows else None
        by_source[str(source)] = {
            "mape": value,
            "pairs": pairs,
            "rows": total_rows,
            "max_gap_h": gap.total_seconds() / 3600.0,
        }
        if value is not None:
            weighted += value * total_rows
            rows += total_rows
    return {
        "mape": weighted / rows if rows else None,
        "by_source": by_source,
        "method": "median absolute difference of the log residual log(measured/predicted) between consecutive readings of one "
        "meter on one well (MPFM at most 48 h apart, well tests 14 days), as the mean absolute "
        "error of Gaussian noise of that scale; a slow meter drift is not included",
    }


#: The variable a candidate's effect acts through (for its before/after panel, and the
#: physics behind a driver).
_EFFECT_DRIVER = {
    "erosion": "throughput_years",
    "erosion_time": "time",
    "valve": "choke",
    "real_gas": "p_up",
    "slip": "eta_gas",
    "critical_ratio": "p_ratio",
    "mpfm_bias": "time",
}


def acts_through(effect: str) -> str | None:
    """The variable a library effect acts through (a valve family: the choke opening, its
    area a function of it; real gas: p_up; ...), or None (a correction, a user's effect)."""
    return _EFFECT_DRIVER.get(effect) or ("choke" if effect.startswith("valve") else None)
