"""The compiled order statistics (vfm_core._robust_kernels) give numpy's numbers exactly."""

from __future__ import annotations

import numpy as np
import pytest

from vfm_core import _robust_kernels as rk


def _windows() -> list[np.ndarray]:
    rng = np.random.default_rng(20261126)
    out = []
    for n in [1, 2, 3, 4, 5, 30, 31, 199, 200, 364, 365]:
        out.append(rng.normal(size=n))
        out.append(np.round(rng.normal(size=n), 1))  # many ties
        out.append(rng.standard_t(2, size=n) * 1e-3)  # heavy tails, small values
        out.append(np.full(n, 0.25))  # all equal
    return out


@pytest.mark.parametrize("r", _windows(), ids=lambda r: f"n{len(r)}")
def test_median_mad_equals_numpy(r: np.ndarray) -> None:
    before = r.copy()
    centre, mad = rk.median_mad(r)
    assert centre == np.median(r)
    assert mad == np.median(np.abs(r - np.median(r)))
    assert np.array_equal(r, before)  # the window is not changed


@pytest.mark.parametrize("r", [w for w in _windows() if len(w) >= 3], ids=lambda r: f"n{len(r)}")
def test_tail_excesses_equal_numpy(r: np.ndarray) -> None:
    centre = float(np.median(r))
    scale = 1.4826 * float(np.median(np.abs(r - centre))) or 1.0
    k = int(0.9 * (len(r) - 1))
    u, over = rk.tail_excesses(r, centre, scale, k)
    z = np.abs(r - centre) / scale
    u_np = float(np.partition(z, k)[k])
    assert u == u_np
    assert np.array_equal(over, z[z > u_np] - u_np)  # same values, same order
    assert over.sum() == (z[z > u_np] - u_np).sum()


def test_not_finite_values_answer_nan() -> None:
    r = np.array([1.0, np.nan, 3.0])
    assert np.isnan(rk.median_mad(r)[0])
    u, over = rk.tail_excesses(np.array([1.0, np.inf, 3.0]), 2.0, 1.0, 1)
    assert np.isnan(u) and len(over) == 0
    assert rk.load() is not None
