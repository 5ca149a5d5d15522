"""The spread of a ``bayes`` forecast takes the sensitivity h of the log rate to the
filtered parameters at the predicted sample, not at the well's last measured one (issue
38; docs/guide/bayes.md, "Why `hem` and `ham` under-cover in case 2"). For a hybrid, h's
output-layer part is the network's hidden activations at the sample, so h P h differs
from sample to sample; the last measured sample is the direction the last update shrank P
along. Checked by hand on both paths (compiled and ``VFM_KERNELS=0``).
"""

from __future__ import annotations

import math

import pandas as pd
import pytest
import torch

from vfm_core.learning.bayes import BayesianFilter
from vfm_core.learning.streaming import WellLearner

T0 = 1_500_000_000_000_000_000  # epoch ns
HOUR = 3_600_000_000_000
Z90 = 1.6448536269514722
#: the last measured sample and another one, far from it (-, bar, bar, degC, -, -)
MEASURED = [0.35, 60.0, 20.0, 70.0, 0.1, 0.6]
OTHER = [0.75, 55.0, 20.0, 70.0, 0.1, 0.6]


def _learner(model: str) -> WellLearner:
    """``model`` fitted on 60 hourly rows of a valve opened from 0.3 to 0.8 (1 % noise),
    then one MPFM reading at :data:`MEASURED`; no intervals' factor (their own spread)."""
    learner = WellLearner("W1", model, "bayes:calibrate=0:cal_prior=0")
    x = torch.tensor([MEASURED] * 60, dtype=torch.float64)
    x[:, 0] = torch.linspace(0.3, 0.8, 60, dtype=torch.float64)
    noise = torch.randn(60, generator=torch.Generator().manual_seed(5), dtype=torch.float64)
    y = 2000.0 * x[:, 0] ** 1.3 * (1.0 + 0.01 * noise)
    learner.fit_history(x, y, T0 + torch.arange(60, dtype=torch.int64) * HOUR)
    when = pd.Timestamp(int(T0 + 61 * HOUR), tz="UTC")
    q = learner.predict(MEASURED, when)["q_total"]
    assert q is not None
    assert learner.learn(MEASURED, 1.02 * q, when, "mpfm")
    return learner


def _by_hand(learner: WellLearner, sample: list[float], when: pd.Timestamp) -> float:
    """sqrt(h (P + Q dt) h + s^2) with h at ``sample`` (the well-test meter's noise s)."""
    method = learner.method
    assert isinstance(method, BayesianFilter)
    _, row = learner.prepare_sample(sample, when)
    assert row is not None
    one = learner.sample_batch(row)
    _, h = method.log_rate_and_gradient(one, torch.ones(1, dtype=torch.bool))
    P = method.grown_covariance(torch.tensor([int(when.value)]))
    noise = method.filter_state()[3][0, 1]
    return math.sqrt(float(h[0] @ P[0] @ h[0] + noise**2))


@pytest.mark.parametrize("kernels", ["1", "0"])
@pytest.mark.parametrize("model", ["hem", "ham"])
def test_the_spread_takes_h_at_the_predicted_sample(
    monkeypatch: pytest.MonkeyPatch, model: str, kernels: str
) -> None:
    """A hybrid's forecast sd at the last measured sample and at another one are each
    sqrt(h_s (P + Q dt) h_s + s^2) with h_s at that sample, and they differ (with h at
    the last measured sample both would be the first)."""
    monkeypatch.setenv("VFM_KERNELS", kernels)
    monkeypatch.setenv("VFM_FIT_KERNEL", "0")  # the same fit on both paths
    learner = _learner(model)
    when = pd.Timestamp(int(T0 + 85 * HOUR), tz="UTC")  # a day after the reading
    sd = {}
    for name, sample in (("measured", MEASURED), ("other", OTHER)):
        prediction = learner.predict(sample, when)
        q, p95 = prediction["q_total"], prediction["q_total_p95"]
        assert q is not None and p95 is not None
        sd[name] = math.log(p95 / q) / Z90
        assert sd[name] == pytest.approx(_by_hand(learner, sample, when), rel=1e-6)
    # the samples' spreads differ: the test tells h at the sample from h at the last one
    assert abs(sd["other"] / sd["measured"] - 1.0) > 0.05
