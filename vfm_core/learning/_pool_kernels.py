"""The pooled prior of ``bayes:cal_pool=on`` compiled (numba; imported only when first used,
see :func:`load`): :func:`pooled_prior` is
:func:`vfm_core.learning.bayes._pooled_prior`'s type-II maximum likelihood, the same
arithmetic without its arrays of wells x weights x wells.

The numpy reference builds, for every well w, every prior weight k of the grid and every
other well j, an array of that size and makes some 30 passes over it (about 0.5 ms for ten
wells, 45 ms for a hundred). Here each well's prior is one loop over the other wells per
weight and fixed-point step, and what does not depend on the well is computed once per
call and left out by subtraction (leave one out):

- the pooled mean of the errors the scale's iteration starts from, sum s / sum n over the
  other wells and the stated prior: the sums over every well less the well's own;
- the log-gamma part of the likelihood, sum over the other wells of
  log Gamma(k / 2 + n_j / 2): one sum per weight (k's grid is the same for every well),
  less the well's own term.

What stays per well and weight is the scale's fixed point and the log terms that depend on
it, b_w: a sum over every live well less the well's own term (J divisions a step, J
logarithms), run for the 33 weights at once (the innermost loops over the weights, which
the compiler vectorises). So a call costs O(G J) log-gamma values and O(W G J) divisions
and logarithms (G = 33 weights, J the wells with errors): each well's prior is linear in
the number of wells, a few nanoseconds a well pair and weight (measured: 9 us for one
well with ten others, 39 us for ten wells in the filter, 235 us for thirty). The numbers
are the reference's to rounding (the sums' order differs; ``tests/test_bayes_pooled.py``
checks 1e-12).
"""

from __future__ import annotations

import math
import os
from types import SimpleNamespace

import numba
import numpy as np

__all__ = ["load", "pooled_prior"]

jit = numba.njit(cache=True, nogil=True, error_model="numpy")

_LOADED: list[SimpleNamespace | None] = []


@jit
def any_other(count: np.ndarray, n_w: int, count_sum: float) -> bool:
    """Whether any of the first ``n_w`` wells has another well's error (count > 0)."""
    for w in range(n_w):
        if count_sum - count[w] > 0:
            return True
    return False


@jit
def _live_halves(count: np.ndarray, total: np.ndarray, nu0: float) -> tuple:  # type: ignore[type-arg]
    """The stated prior (nu0 errors of z^2 = 1) and the wells with errors (count > 0),
    halved: ``(n / 2, s / 2)`` [J], and the sum of every count."""
    n_all = count.shape[0]
    nh = np.empty(n_all + 1)
    sh = np.empty(n_all + 1)
    nh[0] = nu0 / 2.0
    sh[0] = nu0 / 2.0
    n_live = 1
    count_sum = 0.0
    for j in range(n_all):
        count_sum += count[j]
        if count[j] > 0:
            nh[n_live] = count[j] / 2.0
            sh[n_live] = total[j] / 2.0
            n_live += 1
    return nh[:n_live], sh[:n_live], count_sum


@jit
def _log_gammas(grid: np.ndarray, top: float, nh: np.ndarray, count: np.ndarray, n_w: int) -> tuple:  # type: ignore[type-arg]
    """The log-gamma parts of the likelihood per weight k of ``grid`` up to ``top`` (the
    grid increases): log Gamma(k / 2) [G], the sum over the live wells and the prior of
    log Gamma(k / 2 + n / 2) [G], and each of the first ``n_w`` wells' own term [G, n_w]
    (0 for a well with no error), to be left out of its sum."""
    n_g = grid.shape[0]
    lg_all = np.zeros(n_g)
    lg_a = np.zeros(n_g)
    lg_own = np.zeros((n_g, n_w))
    for g in range(n_g):
        if grid[g] > top:
            break
        a = grid[g] / 2.0
        lg_a[g] = math.lgamma(a)
        acc = 0.0
        for j in range(nh.shape[0]):
            acc += math.lgamma(a + nh[j])
        lg_all[g] = acc
        for w in range(n_w):
            if count[w] > 0:
                lg_own[g, w] = math.lgamma(a + count[w] / 2.0)
    return lg_a, lg_all, lg_own


@jit
def _scales(  # noqa: PLR0913 - one well's search
    a: np.ndarray,
    n_gw: int,
    nh: np.ndarray,
    sh: np.ndarray,
    own: float,
    nw: float,
    sw: float,
    pooled: float,
    steps: int,
    b: np.ndarray,
) -> None:
    """One well's prior scale b = k c0sq / 2 for each of the first ``n_gw`` weights (a =
    k / 2), written into ``b``: ``steps`` fixed-point steps of m a / b = sum over the other
    wells of (a + n / 2) / (b + s / 2) from the pooled mean; the sum over every live well
    (``nh``, ``sh``) less the well's own term (``own`` 1: ``nw``, ``sw``). Every weight
    at once: the innermost loops run over the weights (vectorised)."""
    m = nh.shape[0] - own
    acc = np.empty(n_gw)
    for g in range(n_gw):
        b[g] = a[g] * pooled
    for _ in range(steps):
        acc[:] = 0.0
        for j in range(nh.shape[0]):
            nj, sj = nh[j], sh[j]
            for g in range(n_gw):
                acc[g] += (a[g] + nj) / (b[g] + sj)
        for g in range(n_gw):
            b[g] = m * a[g] / (acc[g] - own * (a[g] + nw) / (b[g] + sw))


@jit
def _best_weight(  # noqa: PLR0913 - one well's search
    a: np.ndarray,
    n_gw: int,
    nh: np.ndarray,
    sh: np.ndarray,
    own: float,
    nw: float,
    sw: float,
    b: np.ndarray,
    lg_a: np.ndarray,
    lg_all: np.ndarray,
    lg_own: np.ndarray,
) -> int:
    """The first of the first ``n_gw`` weights under which the other wells' errors are
    most likely (as numpy's argmax of the reference), given each weight's scale ``b``:
    the sum over the other wells of log Gamma(a + n / 2) - log Gamma(a) + a log b
    - (a + n / 2) log(b + s / 2), over every live well less the well's own term."""
    m = nh.shape[0] - own
    acc = np.zeros(n_gw)
    for j in range(nh.shape[0]):
        nj, sj = nh[j], sh[j]
        for g in range(n_gw):
            acc[g] += (a[g] + nj) * math.log(b[g] + sj)
    best_ll = -np.inf
    best_g = 0
    for g in range(n_gw):
        logs = acc[g] - own * (a[g] + nw) * math.log(b[g] + sw)
        lg = lg_all[g] - own * lg_own[g]
        ll = lg - m * lg_a[g] + m * a[g] * math.log(b[g]) - logs
        if ll > best_ll:
            best_ll = ll
            best_g = g
    return best_g


@jit
def pooled_prior(  # noqa: PLR0913 - the arrays of one call
    count: np.ndarray,
    total: np.ndarray,
    n_w: int,
    nu0: float,
    fractions: np.ndarray,
    steps: int,
    k_out: np.ndarray,
    c0sq_out: np.ndarray,
) -> None:
    """Each of the first ``n_w`` wells' prior (k, c0sq) for its well-test variance factor
    from the other wells' (discounted) error counts ``count`` [J0] and sums of squares
    ``total`` [J0] (the filter's wells first, then the wells outside it), with the stated
    prior (nu0 errors of z^2 = 1) as one more well: the weight k of the grid
    nu0 ((nu0 + sum count) / nu0)^``fractions`` [G] (increasing, the same for every well)
    that makes the other wells' errors most likely among those not above nu0 + their
    count, the scale by ``steps`` fixed-point steps from the pooled mean. Written into
    ``k_out`` and ``c0sq_out`` [n_w]; the stated prior (nu0, 1) for every well when no
    well has another's error. Every sum runs over all the live wells and the prior, the
    well's own term then subtracted (leave one out)."""
    nh, sh, count_sum = _live_halves(count, total, nu0)
    if not any_other(count, n_w, count_sum):
        k_out[:] = nu0
        c0sq_out[:] = 1.0
        return
    n_sum, s_sum = 2.0 * nh.sum(), 2.0 * sh.sum()
    grid = nu0 * ((nu0 + count_sum) / nu0) ** fractions
    lg_a, lg_all, lg_own = _log_gammas(grid, nu0 + count_sum + 1e-9, nh, count, n_w)
    a = grid / 2.0
    b = np.empty(grid.shape[0])
    for w in range(n_w):
        own = 1.0 if count[w] > 0 else 0.0
        nw, sw = count[w] / 2.0, total[w] / 2.0
        pooled = (s_sum - own * total[w]) / (n_sum - own * count[w])
        cap = nu0 + (count_sum - count[w]) + 1e-9
        n_gw = 0  # the weights this well may take (the reference's -inf beyond them)
        while n_gw < grid.shape[0] and grid[n_gw] <= cap:
            n_gw += 1
        _scales(a, n_gw, nh, sh, own, nw, sw, pooled, steps, b)
        best = _best_weight(a, n_gw, nh, sh, own, nw, sw, b, lg_a, lg_all, lg_own[:, w])
        k_out[w] = grid[best]
        c0sq_out[w] = 2.0 * b[best] / grid[best]


def load() -> SimpleNamespace | None:
    """The compiled :func:`pooled_prior`, compiled or loaded from numba's cache on the first
    call (run once on made-up errors); None when ``VFM_KERNELS=0`` or it cannot compile
    (the caller's numpy path runs)."""
    if not _LOADED:
        kernels = None
        if os.environ.get("VFM_KERNELS", "1") != "0":
            try:
                k, c = np.zeros(2), np.zeros(2)
                grid = np.array([0.0, 1.0])
                pooled_prior(np.array([1.0, 2.0]), np.array([0.5, 3.0]), 2, 2.0, grid, 2, k, c)
                kernels = SimpleNamespace(pooled_prior=pooled_prior)
            except Exception:  # pragma: no cover - numba broken here: numpy instead
                kernels = None
        _LOADED.append(kernels)
    return _LOADED[0]
