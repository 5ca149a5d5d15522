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
``r`` (a sum of the excesses in numpy then adds them as numpy did). For values that are
not all finite they answer NaN (numpy's NaN rules are not theirs) and the callers take
their numpy path, as they do for ``VFM_KERNELS=0``.
"""

from __future__ import annotations

import os
from types import SimpleNamespace

import numba
import numpy as np

__all__ = ["load", "median_mad", "tail_excesses"]

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


_LOADED: list[SimpleNamespace | None] = []


def load() -> SimpleNamespace | None:
    """The compiled functions (``median_mad``, ``tail_excesses``), compiled or loaded from
    numba's cache on the first call (run once on a made-up window); None when
    ``VFM_KERNELS=0`` or they cannot compile (the callers' numpy path runs)."""
    if not _LOADED:
        kernels = None
        if os.environ.get("VFM_KERNELS", "1") != "0":
            try:
                probe = np.array([3.0, 1.0, 2.0, 5.0])
                median_mad(probe)
                tail_excesses(probe, 2.0, 1.0, 2)
                kernels = SimpleNamespace(median_mad=median_mad, tail_excesses=tail_excesses)
            except Exception:  # pragma: no cover - numba broken here: numpy instead
                kernels = None
        _LOADED.append(kernels)
    return _LOADED[0]
