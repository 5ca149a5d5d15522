"""The paired block tests and the false-discovery control of the diagnosis
(:mod:`vfm_core.jobs.diagnose_live`), by hand and on made-up series with a known answer:
exact sign-flip p-values, Benjamini-Hochberg against its definition, the block length
growing with the autocorrelation, the test's size on autocorrelated differences without a
change (at most its nominal 5 %) and its power with one.
"""

from __future__ import annotations

import itertools

import numpy as np
import pandas as pd
import pytest

from vfm_core.jobs import diagnose_live as live


def _pairs(d: np.ndarray, wells: int = 1, start: str = "2020-01-01") -> pd.DataFrame:
    """Daily paired differences ``d`` (one column per well) as the frame the tests take."""
    d = np.asarray(d, dtype=float).reshape(len(d), -1) if d.ndim == 1 else d
    times = pd.date_range(start, periods=d.shape[0], freq="D", tz="UTC")
    parts = [
        pd.DataFrame(
            {
                "time": times,
                "well": f"W{k}",
                "d": d[:, k],
                "base_ape": 3.0,
                "cand_ape": 3.0 + d[:, k],
            }
        )
        for k in range(d.shape[1])
    ]
    return pd.concat(parts, ignore_index=True)


def _ar1(rng: np.random.Generator, n: int, rho: float, sd: float = 1.0) -> np.ndarray:
    x = np.empty(n)
    x[0] = rng.normal(0, sd)
    for i in range(1, n):
        x[i] = rho * x[i - 1] + rng.normal(0, sd * np.sqrt(1 - rho**2))
    return x


def test_sign_flip_p_is_exact_by_enumeration() -> None:
    sums = np.array([-3.0, -1.0, 2.0, -0.5])
    obs = sums.sum()
    totals = [np.dot(s, sums) for s in itertools.product((1, -1), repeat=4)]
    assert live.sign_flip_p(sums) == pytest.approx(np.mean(np.array(totals) <= obs + 1e-12))
    # every block lower: the smallest p a 4-block test can give, 1/16
    assert live.sign_flip_p(np.array([-1.0, -2.0, -0.1, -3.0])) == pytest.approx(1 / 16)
    assert live.sign_flip_p(np.array([1.0])) == 1.0  # one block: no test
    # many blocks: the normal approximation, one-sided
    big = np.full(40, -1.0)
    assert live.sign_flip_p(big) < 1e-6  # (t with 39 degrees of freedom)
    assert live.sign_flip_p(-big) > 0.999


def test_benjamini_hochberg_by_its_definition() -> None:
    p = [0.001, 0.008, 0.039, 0.041, 0.042, 0.06, 0.074, 0.205, 0.212, 0.216]
    rejected, q = live.benjamini_hochberg(p, 0.05)
    # largest k with p_(k) <= k q / m: k = 2 (0.008 <= 0.01; 0.039 > 0.015; ... 0.042 > 0.025)
    assert rejected.tolist() == [True, True] + [False] * 8
    assert q[0] == pytest.approx(0.01) and q[1] == pytest.approx(0.04)
    assert np.all(np.diff(q[np.argsort(p)]) >= -1e-12)  # q-values keep the p order
    assert live.benjamini_hochberg([], 0.05)[0].size == 0


def test_the_change_is_the_mape_change_and_the_interval_covers_it() -> None:
    rng = np.random.default_rng(1)
    d = rng.normal(-0.3, 1.0, (360, 3))
    pairs = _pairs(d)
    t = live.paired_test(pairs, seed=0)
    assert t["change"] == pytest.approx(float(d.mean()))
    assert t["change"] == pytest.approx(t["mape"] - t["base_mape"])
    assert t["low"] < t["change"] < t["high"]
    assert t["p_value"] < 0.01 and t["n"] == d.size
    assert t["n_blocks"] == 3 * 12 and t["block_days"] == 30


def test_blocks_grow_with_the_autocorrelation() -> None:
    rng = np.random.default_rng(2)
    white = _pairs(rng.normal(0, 1, (720, 4)))
    assert live.choose_block_days(white)[0] == live.BLOCK_DAYS
    # a meter error that drifts over months: 30-day block means are still correlated
    slow = np.column_stack([_ar1(rng, 720, 0.995) for _ in range(4)])
    days, _ = live.choose_block_days(_pairs(slow))
    assert days > live.BLOCK_DAYS


@pytest.mark.parametrize("rho", [0.0, 0.97])
def test_size_without_a_change_is_at_most_nominal(rho: float) -> None:
    """No change in expected loss, white or autocorrelated (an MPFM drifting over weeks):
    the one-sided test at 5 % rejects in at most about 5 % of 300 fields (binomial sd 1.3 %)."""
    rng = np.random.default_rng(3)
    hits = 0
    for _ in range(300):
        d = np.column_stack([_ar1(rng, 540, rho) for _ in range(3)])
        hits += live.paired_test(_pairs(d), seed=0)["p_value"] < 0.05
    assert hits / 300 <= 0.08


def test_power_with_a_real_change() -> None:
    rng = np.random.default_rng(4)
    hits = 0
    for _ in range(50):
        d = np.column_stack([_ar1(rng, 540, 0.9) - 0.4 for _ in range(3)])
        hits += live.paired_test(_pairs(d), seed=0)["p_value"] < 0.05
    assert hits / 50 >= 0.9


def test_paired_differences_drop_rows_without_a_prediction() -> None:
    base = pd.DataFrame(
        {
            "time": pd.date_range("2020-01-01", periods=3, freq="D", tz="UTC"),
            "well": "A",
            "predicted": [100.0, np.nan, 90.0],
            "measured": [100.0, 100.0, 100.0],
        }
    )
    cand = base.assign(predicted=[95.0, 100.0, 100.0])
    out = live.paired_differences(base, cand)
    assert out["d"].tolist() == pytest.approx([5.0, -10.0])
    with pytest.raises(ValueError, match="same rows"):
        live.paired_differences(base, cand.iloc[:2])
