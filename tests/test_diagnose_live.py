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


def test_the_trial_forecast_is_the_window_mean_with_a_prediction_interval_of_daily_means() -> None:
    rng = np.random.default_rng(5)
    d = rng.normal(-0.5, 1.0, 30)
    pairs = _pairs(d)
    out = live.trial_forecast(pairs)
    assert out["change"] == pytest.approx(d.mean())
    assert out["n_blocks"] == 30 and out["n"] == 30 and out["window_days"] == live.TRIAL_DAYS
    from scipy.stats import t as student

    # two independent means of 30 daily values: sd of their difference s sqrt(2/30)
    half = student.ppf(0.975, 29) * d.std(ddof=1) * np.sqrt(2 / 30)
    assert out["low"] == pytest.approx(d.mean() - half)
    assert out["high"] == pytest.approx(d.mean() + half)
    assert live.trial_forecast(_pairs(d[:2]))["low"] is None  # too few days for an interval
    assert live.trial_forecast(pairs.iloc[:0])["change"] is None


def test_on_a_wearing_well_the_trial_forecast_sees_the_gain_the_whole_history_hides() -> None:
    """Wear grows: adding it to a wearing well's model, fitted on the whole history as the
    service installs a change, gains more than the live replay over the whole history says
    (there the candidate was fitted on the short, little-worn start); the forecast, a
    backtest of that change over the history's last 30 days, says so, and what a trial
    then measures over the next 30 days lies within its prediction interval."""
    from vfm_core.effects import resolve_effect
    from vfm_core.jobs.diagnose import _with_features
    from vfm_core.jobs.diagnose_verdicts import trial_test
    from vfm_core.jobs.study import run_prequential
    from vfm_core.observations import validate_frame
    from vfm_core.simulate import simulate_field

    split, end = pd.Timestamp("2016-06-01", tz="UTC"), pd.Timestamp("2016-12-01", tz="UTC")
    month = pd.Timedelta(days=live.TRIAL_DAYS)
    ero = resolve_effect("erosion")
    sim = simulate_field(wells=1, years=1.5, seed=48, hidden=["erosion:rate=0.3"])
    frame = validate_frame(sim.observations).frame
    frame = _with_features(frame[frame.time < end + month].reset_index(drop=True), [ero])
    history = frame[frame.time < end].reset_index(drop=True)
    base = run_prequential(frame, "mm", "ol", split=split).predictions  # the shadow, on and on
    cand = run_prequential(history, "mm", "ol", split=split, effects=[ero]).predictions
    before = base[pd.to_datetime(base["time"], utc=True) < end].reset_index(drop=True)
    whole = live.paired_test(live.paired_differences(before, cand))
    since = pd.to_datetime(history["time"], utc=True).max() - month
    backtest = run_prequential(history, "mm", "ol", split=since, effects=[ero]).predictions
    forecast = trial_test(before, backtest, ["W01"], since)
    # the trial: the change made at the end of the history, 30 days of data on
    applied = run_prequential(frame, "mm", "ol", split=end, effects=[ero]).predictions
    measured = trial_test(base, applied, ["W01"], end)
    assert whole["change"] < 0 and forecast["change"] < 0 and measured["change"] < 0
    assert abs(forecast["change"]) > abs(whole["change"]) + 0.3, (forecast, whole)
    assert forecast["low"] <= measured["change"] <= forecast["high"], (forecast, measured)
    assert forecast["n"] > 20 and forecast["base_mape"] > forecast["mape"]


def test_the_smallest_attainable_p_is_that_of_every_block_lower() -> None:
    """Whatever the signs, a sign-flip test of B blocks gives no p below 2^-B (2^z / 2^B
    with z blocks of sum 0); with more blocks than are enumerated, the t approximation's
    bound; fewer than two blocks, 1."""
    rng = np.random.default_rng(11)
    for b in (4, 7, 9):
        sums = rng.normal(0.0, 1.0, b)
        low = live.attainable_p(sums)
        assert low == pytest.approx(2.0**-b)
        assert live.sign_flip_p(-np.abs(sums)) == pytest.approx(low)  # every block lower
        for _ in range(20):  # no sign pattern goes below it
            assert live.sign_flip_p(sums * rng.choice([-1.0, 1.0], b)) >= low - 1e-12
    assert live.attainable_p(np.array([-1.0, 0.0, -2.0, -1.0, -3.0])) == pytest.approx(2 / 32)
    big = rng.normal(0.0, 1.0, 30)
    assert live.attainable_p(big) == pytest.approx(live.sign_flip_p(-np.abs(big)))
    assert live.attainable_p(np.array([-3.0])) == 1.0


def test_filtered_bh_leaves_out_what_cannot_be_rejected_and_is_bh_otherwise() -> None:
    """Tests that can all reach significance: exactly Benjamini-Hochberg. Tests that cannot
    (a well with two blocks: p >= 1/4) leave the family, so the others' bar is that of a
    family without them; it never rejects less than BH over every test."""
    p = [0.001, 0.008, 0.039, 0.041, 0.042, 0.06, 0.074, 0.205, 0.212, 0.216]
    rej, q, fam = live.filtered_bh(p, [1e-9] * len(p), 0.05)
    bh_rej, bh_q = live.benjamini_hochberg(p, 0.05)
    assert rej.tolist() == bh_rej.tolist() and q == pytest.approx(bh_q) and fam.all()
    # seven blocks all lower: p = 1/128, among 40 tests of two blocks that cannot reach 0.05
    p2 = [1 / 128, 1 / 128] + [0.25] * 40
    reach = [1 / 128, 1 / 128] + [0.25] * 40
    assert not live.benjamini_hochberg(p2, 0.05)[0].any()  # BH over all: 1/128 > 2 x 0.05/42
    rej, q, fam = live.filtered_bh(p2, reach, 0.05)
    assert rej.tolist() == [True, True] + [False] * 40
    assert fam.tolist() == [True, True] + [False] * 40 and np.all(q[2:] == 1.0)
    rng = np.random.default_rng(13)
    for _ in range(200):  # never fewer rejections than BH over every test
        b = rng.integers(2, 12, size=30)
        p3, a3 = rng.uniform(0, 1, 30) ** 3, 0.5 ** b.astype(float)
        p3 = np.maximum(p3, a3)
        assert (
            live.filtered_bh(list(p3), list(a3))[0].sum()
            >= live.benjamini_hochberg(list(p3))[0].sum()
        )


def test_filtered_bh_keeps_the_false_discovery_rate_of_discrete_null_tests() -> None:
    """Under the complete null, with tests of 2 to 9 blocks as a diagnosis of short wells
    has them (exact sign-flip p-values of symmetric block sums), any discovery in a family
    of 40 happens in at most about q = 5 % of 300 families (binomial sd 1.3 %)."""
    rng = np.random.default_rng(12)
    any_hit = 0
    for _ in range(300):
        blocks = rng.integers(2, 10, size=40)
        sums = [rng.normal(0.0, 1.0, b) for b in blocks]
        p = [live.sign_flip_p(s) for s in sums]
        reach = [live.attainable_p(s) for s in sums]
        any_hit += bool(live.filtered_bh(p, reach, 0.05)[0].any())
    assert any_hit / 300 <= 0.08
