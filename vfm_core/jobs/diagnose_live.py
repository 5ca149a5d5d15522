"""Paired, block-wise tests of "does adding this effect lower the error", and their FDR control.

The diagnosis (:mod:`vfm_core.jobs.diagnose`) replays the baseline and each candidate over
the same held-out measurements under a protocol (fit-once, live, outage). Two runs on the same
rows give the paired per-measurement difference of absolute percentage errors

    d_i = 100 (|r_cand,i| - |r_base,i|),   r = (measured - predicted) / measured,

in percentage points, whose mean over the rows is exactly the change of the MAPE. These
differences are autocorrelated (a meter drifts for weeks, a learner's state carries over), so
they are grouped into **blocks**: consecutive spans of :data:`BLOCK_DAYS` days of one well.
The dependence is that of the differences around a straight line in time per well (a
systematic change, such as the growing gain of adding wear, is the signal tested, not
noise). The block length is at least twice their integrated autocorrelation time, and
is doubled (up to :data:`MAX_BLOCK_DAYS`) while the block means of the same well are still
correlated from one block to the next (their pooled lag-1 autocorrelation above
``2/sqrt(pairs)``, the approximate 5 % bound of a white series): the tests below need nearly
independent blocks, and allow for what correlation is left (:func:`sign_flip_p`).

* **The change and its interval**: the row-weighted mean of d (the MAPE change), and a 95 %
  percentile interval from a block bootstrap (blocks resampled with replacement within each
  well, :data:`BOOTSTRAP` replicates, a fixed seed).
* **The p-value** (one-sided, H1: the candidate lowers the error): a sign-flip randomisation
  test of the block sums. Under H0 (no change in expected loss, independent blocks whose
  sums are symmetric about 0), every sign pattern is as likely; with up to
  :data:`EXACT_BLOCKS` blocks all 2^B patterns are enumerated (exact). With more blocks, or
  block means still positively correlated, the self-normalised sum against Student's t
  with the AR(1) variance inflation (1 + rho)/(1 - rho). A well's own test uses its blocks; the field's (pooled) test
  the blocks of every well.
* **False discoveries** (:func:`filtered_bh`): every test of a diagnosis (each candidate x
  protocol, pooled and per well; candidates not replayed enter with p = 1, as they were
  chosen on the same held-out period) is one family, controlled at :data:`FDR_Q` by the
  Benjamini-Hochberg step-up procedure (:func:`benjamini_hochberg`) over the tests that
  can reach significance. A sign-flip test of B blocks cannot give a p-value below 2^-B
  whatever the change (:func:`attainable_p`): a well with two blocks, or a protocol with
  three, can never be rejected, and counting it in the family only raised the bar of the
  others (a wear candidate lowering one well's live error in each of its 7 blocks, p =
  1/128, was "noise" in a family of 54 tests). The filter looks at the blocks' sizes, not
  their signs (independent filtering). Under the complete null that bounds the
  chance of any discovery at q; the tests of one candidate over wells and protocols are
  positively dependent, under which BH still controls the FDR (Benjamini & Yekutieli
  2001, PRDS).
"""

from __future__ import annotations

import functools
import itertools
import math
from typing import Any

import numpy as np
import pandas as pd

__all__ = [
    "BLOCK_DAYS",
    "MAX_BLOCK_DAYS",
    "BOOTSTRAP",
    "EXACT_BLOCKS",
    "FDR_Q",
    "PROCEDURE",
    "paired_differences",
    "block_ids",
    "choose_block_days",
    "sign_flip_p",
    "paired_test",
    "benjamini_hochberg",
    "attainable_p",
    "filtered_bh",
    "TRIAL_DAYS",
    "trial_forecast",
]

#: Shortest block, days: a month spans the slow drift of an MPFM and a learner's memory.
BLOCK_DAYS = 30
#: Longest block, days (the doubling stops here, so that a year still gives a few blocks).
MAX_BLOCK_DAYS = 120
#: Bootstrap replicates of the interval.
BOOTSTRAP = 2000
#: Most blocks for which the sign-flip distribution is enumerated exactly (2^16 patterns).
EXACT_BLOCKS = 16
#: The window of the trial forecast, days of data: the service's trial of a change
#: (``trial.duration_s``, 30 days of data by default), backtested at the end of the history.
TRIAL_DAYS = 30
#: The false discovery rate controlled over a diagnosis's family of tests.
FDR_Q = 0.05
#: The procedure, in words (diagnosis.json and the report say it).
PROCEDURE = (
    "Benjamini-Hochberg at q = 0.05 over every test of the diagnosis (candidates x protocols "
    "x wells and the field; candidates not replayed count with p = 1) that can reach "
    "significance (a test of B blocks cannot give p below 2^-B: one whose smallest attainable "
    "p is above q can never be rejected, and is left out of the family); each test "
    "one-sided, a sign-flip randomisation test of the paired per-measurement differences of "
    "absolute percentage error summed over held-out blocks of one well (30 days, doubled up "
    "to 120 while consecutive block means stay correlated)"
)


def paired_differences(base: pd.DataFrame, cand: pd.DataFrame) -> pd.DataFrame:
    """The paired rows of two runs on the same scored measurements: ``time``, ``well``,
    ``d`` (percentage points: |r_cand| - |r_base|), ``base_ape`` and ``cand_ape`` (%);
    rows where either prediction is not finite are dropped. ``base`` and ``cand`` are
    prediction frames of :func:`vfm_core.jobs.study.run_prequential` (same rows)."""
    if len(base) != len(cand):
        raise ValueError("The two runs do not score the same rows.")
    m = base["measured"].to_numpy(dtype=float)
    pb = base["predicted"].to_numpy(dtype=float)
    pc = cand["predicted"].to_numpy(dtype=float)
    ok = np.isfinite(m) & (m != 0) & np.isfinite(pb) & np.isfinite(pc)
    eb = 100.0 * np.abs((m - pb) / np.where(ok, m, 1.0))
    ec = 100.0 * np.abs((m - pc) / np.where(ok, m, 1.0))
    return pd.DataFrame(
        {
            "time": pd.to_datetime(base["time"], utc=True).to_numpy()[ok],
            "well": base["well"].astype(str).to_numpy()[ok],
            "d": (ec - eb)[ok],
            "base_ape": eb[ok],
            "cand_ape": ec[ok],
        }
    )


def block_ids(pairs: pd.DataFrame, days: float) -> np.ndarray:
    """Block number of each row: the well's code x 100000 + whole ``days`` since the well's
    first scored row."""
    t = pd.DatetimeIndex(pairs["time"]).as_unit("ns").asi8.astype(np.int64)
    codes, _ = pd.factorize(pairs["well"].to_numpy())
    first = np.full(codes.max() + 1 if len(codes) else 0, np.iinfo(np.int64).max)
    np.minimum.at(first, codes, t)
    k = ((t - first[codes]) // int(days * 86400e9)).astype(np.int64)
    return codes.astype(np.int64) * 100000 + k


def _block_sums(pairs: pd.DataFrame, days: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per block, in time order within each well: its well code, sum of d, and row count."""
    ids = block_ids(pairs, days)
    uniq, inv = np.unique(ids, return_inverse=True)
    s = np.bincount(inv, weights=pairs["d"].to_numpy(dtype=float), minlength=len(uniq))
    n = np.bincount(inv, minlength=len(uniq)).astype(float)
    return uniq // 100000, s, n


def _detrend(x: np.ndarray) -> np.ndarray:
    """``x`` less its straight line in the index (its mean with fewer than four values):
    a systematic change of the difference (wear grows, so does what adding it removes) is
    the signal tested, not dependence of the noise around it."""
    finite = np.isfinite(x)
    if finite.sum() < 4:
        return np.where(finite, x - np.nanmean(x), np.nan)
    t = np.arange(len(x), dtype=float)
    slope, icept = np.polyfit(t[finite], x[finite], 1)
    return x - (icept + slope * t)


def _lag1(well: np.ndarray, s: np.ndarray, n: np.ndarray) -> tuple[float, int]:
    """Pooled lag-1 autocorrelation of consecutive block means within each well (wells with
    at least three blocks), and the number of pairs it rests on."""
    mean = s / np.maximum(n, 1.0)
    num = den = 0.0
    pairs = 0
    for code in np.unique(well):
        x = mean[well == code]
        if len(x) < 3:
            continue
        x = _detrend(x)
        num += float(np.sum(x[1:] * x[:-1]))
        den += float(np.sum(x * x))
        pairs += len(x) - 1
    return (num / den if den > 0 else 0.0), pairs


def _autocorrelation_days(pairs: pd.DataFrame) -> float:
    """The integrated autocorrelation time (days) of each well's daily mean difference
    around its straight line in time, pooled over wells: 1 + 2 sum of the autocorrelations
    up to the first that is not positive (Geyer's initial positive sequence), lags up to a
    third of the span."""
    day = pd.DatetimeIndex(pairs["time"]).as_unit("ns").asi8 // int(86400e9)
    frame = pd.DataFrame({"well": pairs["well"].to_numpy(), "day": day, "d": pairs["d"].to_numpy()})
    daily = frame.groupby(["well", "day"], sort=True)["d"].mean()
    acf_num: np.ndarray | None = None
    acf_den = 0.0
    max_lag = 0
    series = []
    for _, g in daily.groupby(level=0, sort=False):
        days = g.index.get_level_values(1).to_numpy()
        full = np.full(int(days.max() - days.min() + 1), np.nan)
        full[days - days.min()] = g.to_numpy()
        series.append(full)
        max_lag = max(max_lag, len(full) // 3)
    if max_lag < 2:
        return 1.0
    acf_num = np.zeros(max_lag)
    for x in series:
        x = _detrend(x)
        ok = np.isfinite(x)
        x0 = np.where(ok, x, 0.0)
        acf_den += float(np.sum(x0 * x0))
        for lag in range(1, min(max_lag, len(x) // 3) + 1):
            acf_num[lag - 1] += float(np.sum(x0[lag:] * x0[:-lag]))
    if acf_den <= 0:
        return 1.0
    rho = acf_num / acf_den
    stop = np.flatnonzero(rho <= 0)
    k = int(stop[0]) if len(stop) else len(rho)
    return float(1.0 + 2.0 * np.sum(rho[:k]))


def choose_block_days(pairs: pd.DataFrame) -> tuple[float, float]:
    """The block length (days) and the lag-1 autocorrelation of its block means.

    At least :data:`BLOCK_DAYS`, and at least twice the integrated autocorrelation time of
    the daily differences (blocks that long have nearly independent means); then doubled
    while the block means are still correlated (lag-1 above ``2/sqrt(pairs)``, the 5 %
    bound of a white series); at most :data:`MAX_BLOCK_DAYS`. Whatever correlation is left
    is allowed for in the p-value (:func:`sign_flip_p`).
    """
    tau = _autocorrelation_days(pairs)
    days = float(BLOCK_DAYS)
    while days < 2.0 * tau and days * 2 <= MAX_BLOCK_DAYS:
        days *= 2
    rho, n = _lag1(*_block_sums(pairs, days))
    while n > 0 and rho > 2.0 / math.sqrt(n) and days * 2 <= MAX_BLOCK_DAYS:
        days *= 2
        rho, n = _lag1(*_block_sums(pairs, days))
    return days, rho


@functools.lru_cache(maxsize=EXACT_BLOCKS + 1)
def _signs(n: int) -> np.ndarray:
    return np.array(list(itertools.product((1.0, -1.0), repeat=n)))


def sign_flip_p(sums: np.ndarray, rho: float = 0.0) -> float:
    """One-sided p-value of H1 "the mean is below 0" from block sums.

    Independent blocks (``rho`` <= 0): the sign-flip randomisation test, exact over all
    sign patterns up to :data:`EXACT_BLOCKS` blocks. Otherwise (more blocks, or block
    means still correlated with lag-1 autocorrelation ``rho`` > 0) the self-normalised sum
    sum(s) / sqrt(sum(s^2) (1 + rho)/(1 - rho)) against Student's t with B - 1 degrees of
    freedom: the AR(1) variance inflation of a mean, and t's heavier tails for few blocks.
    1.0 with fewer than two blocks.
    """
    s = np.asarray(sums, dtype=float)
    s = s[np.isfinite(s)]
    if len(s) < 2 or not np.any(s != 0):
        return 1.0
    obs = float(s.sum())
    rho = min(max(float(rho), 0.0), 0.9) if math.isfinite(rho) else 0.0
    if len(s) <= EXACT_BLOCKS and rho == 0.0:
        totals = _signs(len(s)) @ s
        return float(np.mean(totals <= obs + 1e-12 * max(1.0, abs(obs))))
    from scipy.stats import t as student

    z = obs / math.sqrt(float(np.sum(s * s)) * (1.0 + rho) / (1.0 - rho))
    return float(student.cdf(z, df=len(s) - 1))


def attainable_p(sums: np.ndarray) -> float:
    """The smallest p-value :func:`sign_flip_p` can give for block sums of these sizes,
    whatever their signs: every block lower (1.0 with fewer than two blocks).

    A function of the sums' absolute values alone, which under the null (signs
    independent of sizes) carry no information about the signs: the exact test's
    2^z / 2^B (z: blocks whose sum is 0, every sign of which gives the same total), or the
    t approximation's bound (the self-normalised sum is at most sqrt(B) in size), with no
    autocorrelation allowed for (any ``rho`` > 0 only raises the p-value), the smaller of the
    two for up to :data:`EXACT_BLOCKS` blocks. :func:`filtered_bh` leaves out of the family a
    test that cannot reach significance."""
    s = np.abs(np.asarray(sums, dtype=float))
    s = s[np.isfinite(s)]
    if len(s) < 2 or not np.any(s != 0):
        return 1.0
    from scipy.stats import t as student

    bound = float(student.cdf(-math.sqrt(float(s.sum() ** 2 / np.sum(s * s))), df=len(s) - 1))
    if len(s) > EXACT_BLOCKS:
        return bound
    lowest = -float(s.sum())
    totals = _signs(len(s)) @ s
    exact = float(np.mean(totals <= lowest + 1e-12 * max(1.0, abs(lowest))))
    return min(exact, bound)


def _interval(well: np.ndarray, s: np.ndarray, n: np.ndarray, seed: int) -> tuple[float, float]:
    """95 % block-bootstrap interval of the row-weighted mean difference (within wells)."""
    rng = np.random.default_rng(seed)
    tot_s = np.zeros(BOOTSTRAP)
    tot_n = np.zeros(BOOTSTRAP)
    for code in np.unique(well):
        sw, nw = s[well == code], n[well == code]
        pick = rng.integers(0, len(sw), size=(BOOTSTRAP, len(sw)))
        tot_s += sw[pick].sum(axis=1)
        tot_n += nw[pick].sum(axis=1)
    means = tot_s / np.maximum(tot_n, 1.0)
    lo, hi = np.percentile(means, [2.5, 97.5])
    return float(lo), float(hi)


def paired_test(
    pairs: pd.DataFrame, days: float | None = None, *, seed: int = 0, interval: bool = True
) -> dict[str, Any]:
    """The change of the MAPE (points) with its interval and one-sided p-value, pooled over
    the wells of ``pairs`` (see the module docstring). ``days``: the block length (default
    chosen by :func:`choose_block_days`)."""
    if pairs.empty:
        return {
            "change": None,
            "low": None,
            "high": None,
            "p_value": 1.0,
            "attainable_p": 1.0,
            "n": 0,
            "n_blocks": 0,
            "block_days": days,
            "base_mape": None,
            "mape": None,
        }
    if days is None:
        days, _ = choose_block_days(pairs)
    well, s, n = _block_sums(pairs, days)
    rho, _ = _lag1(well, s, n)
    change = float(s.sum() / n.sum())
    lo, hi = (
        _interval(well, s, n, seed) if interval and len(s) >= 2 else (float("nan"), float("nan"))
    )
    return {
        "change": change,
        "low": lo,
        "high": hi,
        "p_value": sign_flip_p(s, rho),
        "attainable_p": attainable_p(s),
        "n": int(len(pairs)),
        "n_blocks": int(len(s)),
        "block_days": float(days),
        "lag1": rho,
        "base_mape": float(pairs["base_ape"].mean()),
        "mape": float(pairs["cand_ape"].mean()),
    }


def benjamini_hochberg(p_values: list[float], q: float = FDR_Q) -> tuple[np.ndarray, np.ndarray]:
    """Which hypotheses the Benjamini-Hochberg step-up procedure rejects at FDR ``q``, and the
    adjusted p-values (q-values) of each."""
    p = np.asarray(p_values, dtype=float)
    p = np.where(np.isfinite(p), p, 1.0)
    m = len(p)
    if m == 0:
        return np.zeros(0, dtype=bool), np.zeros(0)
    order = np.argsort(p, kind="mergesort")
    ranked = p[order] * m / np.arange(1, m + 1)
    adjusted = np.minimum.accumulate(ranked[::-1])[::-1]
    out = np.empty(m)
    out[order] = np.minimum(adjusted, 1.0)
    return out <= q, out


def filtered_bh(
    p_values: list[float], attainable: list[float], q: float = FDR_Q
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Benjamini-Hochberg over the tests that can reach significance: those whose smallest
    attainable p-value (``attainable``, :func:`attainable_p`) is at most ``q``. BH rejects
    no test whose p-value is above q, so a test that cannot go below it can never be
    rejected; in the family it only raises every other test's bar (BH's k q / m). Which
    tests are in depends on the block sums' sizes only, not on their signs: under the null
    the filter is independent of the p-value (independent filtering, Bourgon, Gentleman and
    Huber 2010; Tarone 1990 for discrete tests), so BH over what is left keeps the FDR at
    ``q``; and it rejects at least what BH over every test rejects. Returns which are
    rejected, the q-values (BH's adjusted p-values within the family, 1.0 outside it) and
    which are in the family."""
    p = np.asarray(p_values, dtype=float)
    p = np.where(np.isfinite(p), p, 1.0)
    a = np.asarray(attainable, dtype=float)
    a = np.where(np.isfinite(a), np.minimum(a, p), 0.0)  # unknown: counted
    family = a <= q
    rejected = np.zeros(len(p), dtype=bool)
    adjusted = np.ones(len(p))
    if family.any():
        rejected[family], adjusted[family] = benjamini_hochberg(list(p[family]), q)
    return rejected, adjusted, family


def trial_forecast(pairs: pd.DataFrame) -> dict[str, Any]:
    """What a trial of the change would measure, forecast from a backtest of it (points).

    ``pairs`` (:func:`paired_differences`) are the candidate *as the service installs it*
    (fitted on everything before the last :data:`TRIAL_DAYS` days of data, then learning
    with the well's method) against the baseline's live replay (the shadow) over those days.
    ``change`` is their MAPE difference (row-weighted, as the trial's ``mape - shadow_mape``).
    The interval is a 95 % *prediction* interval for the next window of as many days, under
    the trial's own rule (:mod:`service.engine.trial`: daily block means of the paired
    differences, nearly independent): with k daily means of sd s, the next window's mean
    differs from this one's by a variable of sd s sqrt(1/k + 1/k) (two independent means),
    so ``change +/- t(0.975, k - 1) s sqrt(2/k)``. It does not cover a gain that grows with
    time (wear): the next window's gain is then larger than this one's. ``n_blocks`` are
    the days with pairs; no interval below three."""
    out: dict[str, Any] = {
        "change": None,
        "low": None,
        "high": None,
        "n": int(len(pairs)),
        "n_blocks": 0,
        "block_days": 1.0,
        "window_days": float(TRIAL_DAYS),
        "base_mape": None,
        "mape": None,
    }
    if pairs.empty:
        return out
    day = pd.DatetimeIndex(pairs["time"]).as_unit("ns").asi8 // int(86400e9)
    means = (
        pd.DataFrame({"w": pairs["well"].to_numpy(), "day": day, "d": pairs["d"].to_numpy()})
        .groupby(["w", "day"], sort=False)["d"]
        .mean()
        .to_numpy(dtype=float)
    )
    k = len(means)
    change = float(pairs["d"].mean())
    out.update(
        change=change,
        n_blocks=int(k),
        base_mape=float(pairs["base_ape"].mean()),
        mape=float(pairs["cand_ape"].mean()),
    )
    if k >= 3:
        from scipy.stats import t as student

        half = float(student.ppf(0.975, k - 1)) * float(np.std(means, ddof=1)) * math.sqrt(2.0 / k)
        out.update(low=change - half, high=change + half)
    return out
