"""Hotelling's T^2 drift test: exact references, a hand-worked case, false alarms, detection delay."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from vfm_core.errors import ConfigError, DataError
from vfm_core.hotelling import StreamingHotelling, estimate_update_period, hotelling_two_sample


def test_one_dimension_equals_students_pooled_t_test() -> None:
    rng = np.random.default_rng(1)
    a, b = rng.normal(0, 1, (30, 1)), rng.normal(0.6, 1, (17, 1))
    r = hotelling_two_sample(a, b)
    t = stats.ttest_ind(a[:, 0], b[:, 0], equal_var=True)
    assert r.t2 == pytest.approx(t.statistic**2, rel=1e-12)
    assert r.p_value == pytest.approx(t.pvalue, rel=1e-10)
    assert (r.df1, r.df2) == (1, 45)


def test_hand_worked_two_dimensional_case() -> None:
    # x1 = (0,0),(2,0),(0,2),(2,2): mean (1,1), S1 = [[4/3, 0], [0, 4/3]]
    # x2 = (3,1),(5,1),(3,3),(5,3): mean (4,2), S2 = S1, pooled S = S1
    # T^2 = (4*4/8) d' S^-1 d = 2 * (9 + 1) * 3/4 = 15; F = 15 * (8-2-1)/(2*6) = 6.25 ~ F(2, 5)
    x1 = np.array([[0, 0], [2, 0], [0, 2], [2, 2]], dtype=float)
    x2 = x1 + np.array([3.0, 1.0])
    r = hotelling_two_sample(x1, x2)
    assert r.t2 == pytest.approx(15.0)
    assert r.f == pytest.approx(6.25)
    assert r.p_value == pytest.approx(stats.f.sf(6.25, 2, 5))


def test_matches_a_direct_scipy_reference_in_many_dimensions() -> None:
    rng = np.random.default_rng(2)
    a, b = rng.normal(size=(40, 6)), rng.normal(0.3, 1.0, (25, 6))
    diff = a.mean(0) - b.mean(0)
    s = ((39) * np.cov(a.T) + 24 * np.cov(b.T)) / 63
    t2 = 40 * 25 / 65 * diff @ np.linalg.solve(s, diff)
    f = t2 * (65 - 6 - 1) / (6 * 63)
    r = hotelling_two_sample(a, b)
    assert r.t2 == pytest.approx(t2, rel=1e-10)
    assert r.p_value == pytest.approx(stats.f.sf(f, 6, 58), rel=1e-9)


def test_single_observation_against_reference() -> None:
    ref = np.random.default_rng(3).normal(size=(50, 3))
    r = hotelling_two_sample(ref, np.array([[6.0, 0.0, 0.0]]))
    assert r.df2 == 50 + 1 - 3 - 1 and r.p_value < 1e-3


def test_degenerate_covariance_names_the_input() -> None:
    rng = np.random.default_rng(4)
    a = np.column_stack([rng.normal(size=20), np.ones(20)])
    b = np.column_stack([rng.normal(size=10), np.ones(10)])
    with pytest.raises(DataError, match="choke"):
        hotelling_two_sample(a, b, names=["p_up", "choke"])
    with pytest.raises(DataError, match="n1 \\+ n2 - d - 1"):
        hotelling_two_sample(a[:2], b[:1])


def test_false_alarm_rate_near_nominal_on_a_stationary_stream() -> None:
    """Averaged over reference windows, a sample is flagged with probability alpha; a
    confirmed alarm (3 in a row) is much rarer: about alpha^3 per sample."""
    rng = np.random.default_rng(5)
    flagged = n = confirmed_runs = 0
    for _ in range(60):
        det = StreamingHotelling(reference_size=100, alpha=0.05, confirm=3)
        for row in rng.normal(size=(100 + 300, 6)):
            det.update(row)
            if det.n_seen > 100:
                n += 1
                flagged += det.last_detected
                confirmed_runs += det.run == 3
    rate = flagged / n
    assert rate == pytest.approx(0.05, abs=0.01)
    assert confirmed_runs / n < 0.002  # nominal 0.05^3 = 1.25e-4 (plus reference noise)


def test_detects_a_mean_shift_quickly() -> None:
    """A shift of 2 standard deviations in every one of 6 inputs is confirmed within 10 samples."""
    rng = np.random.default_rng(6)
    delays = []
    for _ in range(20):
        det = StreamingHotelling(reference_size=200, alpha=0.05, confirm=3)
        for row in rng.normal(size=(200, 6)):
            det.update(row)
        for k, row in enumerate(rng.normal(2.0, 1.0, size=(50, 6)), start=1):
            if det.update(row):
                delays.append(k)
                break
    assert len(delays) == 20 and max(delays) <= 10


def test_streaming_detector_survives_a_constant_input_and_resets() -> None:
    rng = np.random.default_rng(7)
    x = np.column_stack([rng.normal(size=300), np.ones(300)])  # choke held fully open
    det = StreamingHotelling(reference_size=100, alpha=0.01, confirm=3)
    for row in x:
        det.update(row)
    assert det.degenerate == 1 and not det.drift_detected
    for _ in range(5):
        det.update([5.0, 1.0])
    assert det.drift_detected
    det.reset(x[-100:])
    assert not det.drift_detected and det.update([0.0, 1.0]) is False
    clone = StreamingHotelling()
    clone.load_state_dict(det.state_dict())
    clone.update([0.1, 1.0])
    det.update([0.1, 1.0])
    assert clone.p_value == pytest.approx(det.p_value)


def test_algorithm_a1_finds_the_shift() -> None:
    rng = np.random.default_rng(8)
    x = np.vstack([rng.normal(size=(300, 4)), rng.normal(2.0, 1.0, size=(100, 4))])
    times = np.datetime64("2019-01-01") + np.arange(400) * np.timedelta64(1, "D")
    res = estimate_update_period(x, times, reference=200, alpha=0.05, confirm=3)
    assert 300 <= res.index <= 305
    assert (
        res.period == np.timedelta64(res.index - 199, "D")
        and res.period / np.timedelta64(1, "D") >= 100
    )
    with pytest.raises(ConfigError):
        estimate_update_period(x, reference=1)
