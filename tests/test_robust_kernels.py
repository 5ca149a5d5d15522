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


@pytest.mark.parametrize("r", [w for w in _windows() if len(w) >= 3], ids=lambda r: f"n{len(r)}")
def test_tail_sum_equals_numpy(r: np.ndarray) -> None:
    centre = float(np.median(r))
    scale = 1.4826 * float(np.median(np.abs(r - centre))) or 1.0
    k = int(0.9 * (len(r) - 1))
    u, count, total = rk.tail_sum(r, centre, scale, k)
    z = np.abs(r - centre) / scale
    u_np = float(np.partition(z, k)[k])
    over = z[z > u_np] - u_np
    assert (u, count) == (u_np, len(over))
    assert total == over.sum()  # numpy's own order of additions, to the last bit


def test_pairwise_sum_equals_numpy_up_to_128_values() -> None:
    rng = np.random.default_rng(39)
    for n in range(0, 129):
        a = rng.normal(size=n) * 10.0 ** rng.uniform(-6, 6, size=n)  # rounding matters
        assert rk._pairwise_sum(a, n) == a.sum()
    many = np.abs(rng.normal(size=2000))
    assert np.isnan(rk.tail_sum(many, 0.0, 1.0, 100)[0])  # over 128 excesses: numpy's path


def _spread_root_numpy(e: np.ndarray, base: np.ndarray, steps: int) -> tuple[float, float]:
    """The witness's bisection in numpy (what ChokeRateWitness.fit did before the kernel)."""

    def spread(omega: float) -> float:
        x = e / np.sqrt(base + omega * omega)
        return 1.4826 * float(np.median(np.abs(x - np.median(x))))

    omega, kappa = 0.0, max(1.0, spread(0.0))
    if spread(0.0) > 1.0:
        lo, hi = 0.0, 1.0
        for _ in range(steps):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if spread(mid) > 1.0 else (lo, mid)
        omega, kappa = hi, max(1.0, spread(hi))
    return omega, kappa


@pytest.mark.parametrize("n", [8, 9, 40, 100])
@pytest.mark.parametrize("wide", [0.5, 3.0])
def test_scaled_spread_root_equals_numpy(n: int, wide: float) -> None:
    rng = np.random.default_rng(n)
    base = rng.uniform(1e-4, 4e-3, size=n)
    e = rng.standard_t(3, size=n) * wide * np.sqrt(base)  # narrower and wider than one
    assert rk.scaled_spread_root(e, base, 24) == _spread_root_numpy(e, base, 24)
    e[1] = np.nan
    assert np.isnan(rk.scaled_spread_root(e, base, 24)[0])


def _huber_numpy(x: np.ndarray, y: np.ndarray, var: np.ndarray) -> tuple[float, float]:
    """The witness's Huber slope in numpy (rate_witness._huber_slope's numpy path)."""

    def robust_sd(r: np.ndarray) -> float:
        return 1.4826 * float(np.median(np.abs(r - np.median(r))))

    w0 = 1.0 / var
    w = w0.copy()
    beta = 0.0
    for _ in range(20):
        last, beta = beta, float((w * x * y).sum() / (w * x * x).sum())
        if abs(beta - last) < 1e-6:
            break
        r = (y - beta * x) * np.sqrt(w0)
        u = np.abs(r) / max(robust_sd(r), 1e-9)
        w = w0 * np.minimum(1.0, 1.345 / np.maximum(u, 1e-12))
    scale = max(robust_sd((y - beta * x) * np.sqrt(w0)), 1.0)
    return beta, scale / float(np.sqrt((w0 * x * x).sum()))


@pytest.mark.parametrize("n", [8, 9, 17, 64, 100])
def test_huber_slope_equals_numpy(n: int) -> None:
    rng = np.random.default_rng(100 + n)
    moves = np.empty((n, 3))  # the witness passes strided columns of its moves
    moves[:, 0] = rng.normal(scale=0.05, size=n)
    moves[:, 2] = rng.uniform(1e-4, 2e-3, size=n)
    moves[:, 1] = 0.8 * moves[:, 0] + rng.standard_t(2, size=n) * np.sqrt(moves[:, 2])
    x, y, var = moves.T
    assert rk.huber_slope(x, y, var, 20) == _huber_numpy(x, y, var)
    y = y.copy()
    y[0] = np.inf
    assert np.isnan(rk.huber_slope(x, y, var, 20)[0])


def test_numpy_sum_and_clipped_deviations_equal_numpy() -> None:
    rng = np.random.default_rng(365)
    for n in [*range(1, 300, 7), 364, 365, 366, 729, 1000, 4096]:
        a = rng.normal(size=n) * 10.0 ** rng.uniform(-4, 4, size=n)
        assert rk._numpy_sum(a, n) == a.sum()  # numpy's pairwise halves above 128 values
        centre, scale = float(np.median(a)), float(np.std(a)) or 1.0
        z = a - centre
        z /= scale
        np.maximum(z, -4.0, out=z)
        np.minimum(z, 4.0, out=z)
        z -= z.sum() / len(z)
        assert np.array_equal(rk.clipped_deviations(a, centre, scale), z)
    assert len(rk.clipped_deviations(np.array([1.0, np.nan, 2.0]), 1.0, 1.0)) == 0
    assert len(rk.clipped_deviations(np.zeros(5000), 0.0, 1.0)) == 0  # numpy's path then
