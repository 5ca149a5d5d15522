"""Compiled order statistics for the streaming detectors (numba; imported only when first
used, see :func:`load`): the median and MAD of a reference window, and the excesses over a
quantile of its scaled deviations.

The instrument-fault detectors (:mod:`vfm_core.sensor_faults`) and the residual CUSUM
(:mod:`vfm_core.residual_alarm`) recompute such statistics of windows of up to a year of
daily values thousands of times a well-year; numpy's partial sorts cost a few
microseconds a call in overhead alone, these a fraction of it.

They give exactly the numbers of the numpy expressions they stand for, for finite values
(an order statistic is one of the values, whatever the algorithm that selects it; the
deviations are the same float operations): ``median_mad(r)`` is ``(np.median(r),
np.median(np.abs(r - np.median(r))))`` and ``tail_excesses(r, c, s, k)`` is ``(u, z[z >
u] - u)`` with ``z = np.abs(r - c) / s`` and ``u = np.partition(z, k)[k]``, in the order of
``r`` (a sum of the excesses in numpy then adds them as numpy did; ``tail_sum`` adds them
itself, in numpy's order: its pairwise summation of up to 128 values).
``scaled_spread_root(e, base, steps)`` is the bisection of the choke-rate witness's fit
(:meth:`vfm_core.rate_witness.ChokeRateWitness.fit`), its robust sds of ``e / np.sqrt(base +
omega * omega)`` in one call instead of a numpy round trip each, and ``huber_slope`` its
reweighted slope (elementwise operations in numpy's order, sums in numpy's pairwise order). For values that are
not all finite they answer NaN (numpy's NaN rules are not theirs) and the callers take
their numpy path, as they do for ``VFM_KERNELS=0``.
"""

from __future__ import annotations

import os
from types import SimpleNamespace

import numba
import numpy as np

__all__ = [
    "clipped_deviations",
    "huber_slope",
    "load",
    "median_mad",
    "scaled_spread_root",
    "tail_excesses",
    "tail_sum",
]

jit = numba.njit(cache=True, nogil=True, error_model="numpy")


@jit
def _select(w: np.ndarray, k: int) -> float:
    """The ``k``-th smallest value of ``w`` (0-based), moving ``w``'s values so that those
    before position ``k`` are no larger than it (Hoare's quickselect, median-of-three
    pivot)."""
    lo, hi = 0, len(w) - 1
    while hi > lo:
        mid = (lo + hi) // 2
        a, b, c = w[lo], w[mid], w[hi]
        if a < b:
            pivot = b if b < c else (c if a < c else a)
        else:
            pivot = a if a < c else (c if b < c else b)
        i, j = lo, hi
        while i <= j:
            while w[i] < pivot:
                i += 1
            while w[j] > pivot:
                j -= 1
            if i <= j:
                w[i], w[j] = w[j], w[i]
                i += 1
                j -= 1
        if k <= j:
            hi = j
        elif k >= i:
            lo = i
        else:
            break
    return w[k]


@jit
def _median_of(w: np.ndarray) -> float:
    """The median of ``w`` (non-empty), as ``np.median`` computes it; reorders ``w``."""
    n = len(w)
    k = n // 2
    upper = _select(w, k)
    if n % 2:
        return upper
    lower = w[0]  # the largest of the values before position k
    for i in range(1, k):
        if w[i] > lower:
            lower = w[i]
    return (lower + upper) / 2.0


@jit
def median_mad(r: np.ndarray) -> tuple[float, float]:
    """The median of ``r`` (non-empty) and the median of its absolute deviations from it
    (the raw MAD: times 1.4826 a robust sd); NaN, NaN when a value is not finite. ``r`` is
    not changed."""
    for x in r:
        if not np.isfinite(x):
            return np.nan, np.nan
    w = r.copy()
    centre = _median_of(w)
    for i in range(len(r)):
        w[i] = abs(r[i] - centre)
    return centre, _median_of(w)


@jit
def tail_excesses(r: np.ndarray, centre: float, scale: float, k: int) -> tuple[float, np.ndarray]:
    """With ``z = |r - centre| / scale``: its ``k``-th smallest value ``u`` and the excesses
    ``z - u`` of the values beyond it, in the order of ``r``; NaN and no excesses when a
    value, the centre or the scale is not finite."""
    n = len(r)
    z = np.empty(n)
    if not (np.isfinite(centre) and np.isfinite(scale)):
        return np.nan, z[:0]
    for i in range(n):
        if not np.isfinite(r[i]):
            return np.nan, z[:0]
        z[i] = abs(r[i] - centre) / scale
    u = _select(z.copy(), k)
    count = 0
    for i in range(n):
        if z[i] > u:
            count += 1
    over = np.empty(count)
    j = 0
    for i in range(n):
        if z[i] > u:
            over[j] = z[i] - u
            j += 1
    return u, over


@jit
def _pairwise_sum(a: np.ndarray, n: int) -> float:
    """``a[:n].sum()`` as numpy adds a contiguous float64 array of at most 128 values (its
    pairwise summation's leaf: eight running sums from eight values on, then the rest)."""
    if n < 8:
        res = 0.0
        for i in range(n):
            res += a[i]
        return res
    r0, r1, r2, r3, r4, r5, r6, r7 = a[0], a[1], a[2], a[3], a[4], a[5], a[6], a[7]
    i = 8
    while i < n - (n % 8):
        r0 += a[i]
        r1 += a[i + 1]
        r2 += a[i + 2]
        r3 += a[i + 3]
        r4 += a[i + 4]
        r5 += a[i + 5]
        r6 += a[i + 6]
        r7 += a[i + 7]
        i += 8
    res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    while i < n:
        res += a[i]
        i += 1
    return res


@jit
def _half(n: int) -> int:
    """Where numpy's pairwise sum splits ``n`` values above 128: half, rounded down to a
    multiple of eight."""
    n2 = n // 2
    return n2 - n2 % 8


# numpy's pairwise sum above 128 values, one function per level of halving (no recursion:
# numba's cache does not keep recursive functions safely); six levels cover 4096 values
@jit
def _sum1(a: np.ndarray, lo: int, n: int) -> float:
    if n <= 128:
        return _pairwise_sum(a[lo:], n)
    h = _half(n)
    return _pairwise_sum(a[lo:], h) + _pairwise_sum(a[lo + h :], n - h)


@jit
def _sum2(a: np.ndarray, lo: int, n: int) -> float:
    if n <= 128:
        return _pairwise_sum(a[lo:], n)
    h = _half(n)
    return _sum1(a, lo, h) + _sum1(a, lo + h, n - h)


@jit
def _sum3(a: np.ndarray, lo: int, n: int) -> float:
    if n <= 128:
        return _pairwise_sum(a[lo:], n)
    h = _half(n)
    return _sum2(a, lo, h) + _sum2(a, lo + h, n - h)


@jit
def _sum4(a: np.ndarray, lo: int, n: int) -> float:
    if n <= 128:
        return _pairwise_sum(a[lo:], n)
    h = _half(n)
    return _sum3(a, lo, h) + _sum3(a, lo + h, n - h)


@jit
def _sum5(a: np.ndarray, lo: int, n: int) -> float:
    if n <= 128:
        return _pairwise_sum(a[lo:], n)
    h = _half(n)
    return _sum4(a, lo, h) + _sum4(a, lo + h, n - h)


@jit
def _numpy_sum(a: np.ndarray, n: int) -> float:
    """``a[:n].sum()`` of a contiguous float64 array as numpy adds it (pairwise: halves
    above 128 values, :func:`_pairwise_sum` at or below), for ``n`` up to 4096."""
    if n <= 128:
        return _pairwise_sum(a, n)
    h = _half(n)
    return _sum5(a, 0, h) + _sum5(a, h, n - h)


@jit
def clipped_deviations(r: np.ndarray, centre: float, scale: float) -> np.ndarray:
    """``z = (r - centre) / scale`` clipped to [-4, 4], less its mean (``z.sum() / len(z)``,
    numpy's sum), as ``vfm_core.residual_alarm._long_run_factor`` makes it with numpy's
    ufuncs; empty when a value, the centre or the scale is not finite, or ``r`` holds more
    than 4096 values."""
    n = len(r)
    z = np.empty(n)
    if not (np.isfinite(centre) and np.isfinite(scale)) or n > 4096:
        return z[:0]
    for i in range(n):
        v = r[i]
        if not np.isfinite(v):
            return z[:0]
        v = (v - centre) / scale
        z[i] = -4.0 if v < -4.0 else (4.0 if v > 4.0 else v)
    mean = _numpy_sum(z, n) / n
    for i in range(n):
        z[i] -= mean
    return z


@jit
def tail_sum(r: np.ndarray, centre: float, scale: float, k: int) -> tuple[float, int, float]:
    """:func:`tail_excesses` summed: ``(u, count, total)`` with ``count`` the excesses and
    ``total`` their sum as numpy's ``.sum()`` gives it; NaN, 0, NaN when a value, the centre
    or the scale is not finite, or there are more than 128 excesses (numpy's pairwise sum
    splits those: the caller's numpy path then)."""
    u, over = tail_excesses(r, centre, scale, k)
    if not np.isfinite(u) or len(over) > 128:
        return np.nan, 0, np.nan
    return u, len(over), _pairwise_sum(over, len(over))


@jit
def _robust_sd_of(w: np.ndarray) -> float:
    """1.4826 MAD of ``w`` (finite values), reordering ``w``."""
    centre = _median_of(w)
    for i in range(len(w)):
        w[i] = abs(w[i] - centre)
    return 1.4826 * _median_of(w)


@jit
def huber_slope(x: np.ndarray, y: np.ndarray, var: np.ndarray, steps: int) -> tuple[float, float]:
    """The choke-rate witness's slope of ``y = beta x`` by Huber-weighted least squares and
    its standard error (``vfm_core.rate_witness._huber_slope``, up to ``steps`` reweightings):
    the same elementwise operations in the same order, order statistics, and sums in
    numpy's order (at most 128 values). NaN, NaN when a value is not finite or there are
    more than 128 (the caller's numpy path then)."""
    n = len(x)
    if n > 128:
        return np.nan, np.nan
    for i in range(n):
        if not (np.isfinite(x[i]) and np.isfinite(y[i]) and np.isfinite(var[i])):
            return np.nan, np.nan
    w0 = np.empty(n)
    root = np.empty(n)
    for i in range(n):
        w0[i] = 1.0 / var[i]
        root[i] = np.sqrt(w0[i])
    w = w0.copy()
    tmp = np.empty(n)
    beta = 0.0
    for _ in range(steps):
        last = beta
        for i in range(n):
            tmp[i] = w[i] * x[i] * y[i]
        num = _pairwise_sum(tmp, n)
        for i in range(n):
            tmp[i] = w[i] * x[i] * x[i]
        beta = num / _pairwise_sum(tmp, n)
        if abs(beta - last) < 1e-6:
            break
        for i in range(n):
            tmp[i] = (y[i] - beta * x[i]) * root[i]
        r = tmp.copy()
        scale = max(_robust_sd_of(tmp), 1e-9)
        for i in range(n):
            u = abs(r[i]) / scale
            w[i] = w0[i] * min(1.0, 1.345 / max(u, 1e-12))
    for i in range(n):
        tmp[i] = (y[i] - beta * x[i]) * root[i]
    scale = max(_robust_sd_of(tmp), 1.0)
    for i in range(n):
        tmp[i] = w0[i] * x[i] * x[i]
    return beta, scale / np.sqrt(_pairwise_sum(tmp, n))


@jit
def _scaled_spread(e: np.ndarray, base: np.ndarray, omega: float, w: np.ndarray) -> float:
    """1.4826 MAD of ``e / sqrt(base + omega^2)`` (``w``: scratch of ``e``'s length)."""
    o2 = omega * omega
    for i in range(len(e)):
        w[i] = e[i] / np.sqrt(base[i] + o2)
    centre = _median_of(w)
    for i in range(len(e)):
        w[i] = abs(e[i] / np.sqrt(base[i] + o2) - centre)
    return 1.4826 * _median_of(w)


@jit
def scaled_spread_root(e: np.ndarray, base: np.ndarray, steps: int) -> tuple[float, float]:
    """``(omega, kappa)`` of the choke-rate witness's spread (``ChokeRateWitness.fit``):
    with ``spread(o)`` the 1.4826 MAD of ``e / sqrt(base + o^2)``, ``omega = 0`` and
    ``kappa = max(1, spread(0))`` when ``spread(0) <= 1``, else ``omega`` the upper end of
    ``steps`` bisections of [0, 1] for ``spread(omega) = 1`` and ``kappa = max(1,
    spread(omega))``. NaN, NaN when a value of ``e`` or ``base`` is not finite."""
    n = len(e)
    for i in range(n):
        if not (np.isfinite(e[i]) and np.isfinite(base[i])):
            return np.nan, np.nan
    w = np.empty(n)
    first = _scaled_spread(e, base, 0.0, w)
    if not np.isfinite(first):
        return np.nan, np.nan
    if not first > 1.0:
        return 0.0, max(1.0, first)
    lo, hi = 0.0, 1.0
    for _ in range(steps):
        mid = 0.5 * (lo + hi)
        if _scaled_spread(e, base, mid, w) > 1.0:
            lo = mid
        else:
            hi = mid
    return hi, max(1.0, _scaled_spread(e, base, hi, w))


_LOADED: list[SimpleNamespace | None] = []


def load() -> SimpleNamespace | None:
    """The compiled functions (``median_mad``, ``tail_excesses``, ``tail_sum``,
    ``scaled_spread_root``, ``huber_slope``, ``clipped_deviations``),
    compiled or loaded from numba's cache on the first call (run once on a made-up window); None when
    ``VFM_KERNELS=0`` or they cannot compile (the callers' numpy path runs)."""
    if not _LOADED:
        kernels = None
        if os.environ.get("VFM_KERNELS", "1") != "0":
            try:
                probe = np.array([3.0, 1.0, 2.0, 5.0])
                median_mad(probe)
                tail_excesses(probe, 2.0, 1.0, 2)
                scaled_spread_root(probe, probe, 2)
                tail_sum(probe, 2.0, 1.0, 2)
                huber_slope(probe, probe, probe, 2)
                clipped_deviations(probe, 2.0, 1.0)
                kernels = SimpleNamespace(
                    clipped_deviations=clipped_deviations,
                    huber_slope=huber_slope,
                    median_mad=median_mad,
                    tail_excesses=tail_excesses,
                    tail_sum=tail_sum,
                    scaled_spread_root=scaled_spread_root,
                )
            except Exception:  # pragma: no cover - numba broken here: numpy instead
                kernels = None
        _LOADED.append(kernels)
    return _LOADED[0]
