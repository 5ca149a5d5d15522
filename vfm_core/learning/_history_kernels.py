"""The filter's start compiled (numba; imported only when first used, see :func:`load`):
:func:`history_pass` is :func:`vfm_core.learning.bayes._history_pass`, the linear Kalman
filter over a fit's history rows, the same arithmetic without a tensor operation a row.

The torch reference steps every well together, one history row after another: some 25
small tensor operations a row, each a few microseconds of dispatch on a few numbers. A
filter start (the first fit, and every refit of ``bayes:refresh=...``) makes two such
passes over every row of the history, so a refit cost about 1 s on a field of 4 wells with
two years of MPFM readings (measured: docs/guide/bayes.md, "Per-well networks on request",
session 50), 90 % of a case-1 study with ``refresh=14d``. Here each well is one loop over
its own rows (wells left out of the start are skipped), and the Joseph form's
(I - K H') P (I - K H')' + K K' R is expanded as P - K (P H)' - (P H) K' + (H' P H + R) K K'
(P symmetric): O(D^2) a row instead of O(D^3). The numbers are the reference's to
rounding (``tests/test_bayes_refresh.py`` checks 1e-9 after a pass of two thousand rows).
"""

from __future__ import annotations

import math
import os
from types import SimpleNamespace

import numba
import numpy as np

__all__ = ["history_pass", "load"]

jit = numba.njit(cache=True, nogil=True, error_model="numpy")

_LOADED: list[SimpleNamespace | None] = []


@jit
def _row_update(
    p: np.ndarray,
    m: np.ndarray,
    h: np.ndarray,
    r: float,
    rv: float,
    ph: np.ndarray,
    k_gain: np.ndarray,
) -> float:
    """One row's Kalman update of a well's state ``m`` [D] and covariance ``p`` [D, D] in
    place (sensitivity ``h`` [D], innovation ``r``, meter variance ``rv``; ``ph`` and
    ``k_gain`` [D] are scratch): Huber beyond 3 sd, refused beyond 6 (the reference's
    constants). Returns H' P H, the innovation's parameter variance."""
    d = h.shape[0]
    hph = 0.0
    for i in range(d):
        s = 0.0
        for j in range(d):
            s += p[i, j] * h[j]
        ph[i] = s
        hph += s * h[i]
    z = abs(r / math.sqrt(hph + rv))
    weight = 3.0 / z if z > 3.0 else 1.0
    if z <= 6.0:
        rk = rv / weight
        denom = hph + rk
        for i in range(d):
            k_gain[i] = ph[i] / denom
            m[i] = m[i] + k_gain[i] * r
        for i in range(d):
            for j in range(i, d):
                v = p[i, j] - k_gain[i] * ph[j] - ph[i] * k_gain[j] + denom * k_gain[i] * k_gain[j]
                p[i, j] = v
                p[j, i] = v
    return hph


@jit
def history_pass(  # noqa: PLR0913 - the reference's arguments, as arrays
    y: np.ndarray,
    log_h: np.ndarray,
    jac: np.ndarray,
    ok: np.ndarray,
    r_var: np.ndarray,
    time_ns: np.ndarray,
    p0: np.ndarray,
    q: np.ndarray,
    never: int,
    ns_per_year: float,
) -> tuple:  # type: ignore[type-arg]
    """The pass of :func:`~vfm_core.learning.bayes._history_pass` (log space): ``y``,
    ``log_h`` [W, N], ``jac`` [W, N, D], ``ok`` [W, N] (rows to take), ``r_var`` [W, N]
    (each row's meter variance), ``time_ns`` [W, N] (epoch ns), ``p0`` [W, D] (the start's
    diagonal), ``q`` [D] (drift variance a year). Returns m [W, D], P [W, D, D], the
    innovations and their parameter variance [W, N], the last sensitivity [W, D] and the
    last time [W] (``never``: no row)."""
    n_w, n, d = jac.shape
    m_all = np.zeros((n_w, d))
    p_all = np.zeros((n_w, d, d))
    innov = np.zeros((n_w, n))
    hph_all = np.zeros((n_w, n))
    h_last = np.zeros((n_w, d))
    last_all = np.full(n_w, never, dtype=np.int64)
    ph = np.empty(d)
    k_gain = np.empty(d)
    for w in range(n_w):
        m = m_all[w]
        p = p_all[w]
        for i in range(d):
            p[i, i] = p0[w, i]
        last = never
        for k in range(n):
            if not ok[w, k]:
                continue
            t = time_ns[w, k]
            if last != never:
                dt = float(max(t - last, 0)) / ns_per_year
                for i in range(d):
                    p[i, i] = p[i, i] + q[i] * dt
            h = jac[w, k]
            hm = 0.0
            for i in range(d):
                hm += h[i] * m[i]
            r = y[w, k] - log_h[w, k] - hm
            hph = _row_update(p, m, h, r, r_var[w, k], ph, k_gain)
            innov[w, k] = r
            hph_all[w, k] = hph
            for i in range(d):
                h_last[w, i] = h[i]
            last = t
        last_all[w] = last
    return m_all, p_all, innov, hph_all, h_last, last_all


def load() -> SimpleNamespace | None:
    """The compiled :func:`history_pass`, compiled or loaded from numba's cache on the first
    call (run once on made-up rows); None when ``VFM_KERNELS=0`` or it cannot compile (the
    caller's torch path runs)."""
    if not _LOADED:
        kernels = None
        if os.environ.get("VFM_KERNELS", "1") != "0":
            try:
                ones = np.ones((1, 2))
                history_pass(
                    ones,
                    ones,
                    np.ones((1, 2, 2)),
                    np.ones((1, 2), dtype=np.bool_),
                    ones,
                    np.array([[0, 1]], dtype=np.int64),
                    ones,
                    np.ones(2),
                    -1,
                    1.0,
                )
                kernels = SimpleNamespace(history_pass=history_pass)
            except Exception:  # pragma: no cover - numba broken here: torch instead
                kernels = None
        _LOADED.append(kernels)
    return _LOADED[0]
