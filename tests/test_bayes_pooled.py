"""The well-test variance factor's prior taken from the other wells' errors (``cal_pool``,
empirical Bayes; the rule: docs/guide/bayes.md, "Pooled over the wells"): wells that agree
learn their common factor from all of them, wells that disagree keep their own, a filter of
one well keeps the stated prior.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from vfm_core.errors import ConfigError
from vfm_core.jobs.study import run_prequential
from vfm_core.learning.method import parse_method
from vfm_core.models import make_model
from vfm_core.simulate import simulate_field

DISCOUNT = 0.99  # each new error discounts the older ones (the filter's variance discount)


def _factors(spec: str, z2: np.ndarray) -> np.ndarray:
    """The learned factor c^2 [W] of a ``bayes`` filter over W wells whose well tests gave
    the squared standardised forecast errors ``z2`` [W, n] (in time order; NaN: none),
    put into the filter as the discounted count and sum it keeps."""
    wells = [f"W{i}" for i in range(z2.shape[0])]
    method = parse_method(spec).bind(make_model("mm", wells))
    state = method.state_dict()
    cal = state["cal"].clone()
    for w, row in enumerate(z2):
        for value in row[np.isfinite(row)]:
            cal[w, 1, 0] = DISCOUNT * cal[w, 1, 0] + 1.0
            cal[w, 1, 1] = DISCOUNT * cal[w, 1, 1] + float(value)
    state["cal"] = cal
    method.load_state_dict(state)
    return method.well_test_factor().numpy()


def test_one_well_keeps_the_stated_prior() -> None:
    """A filter of one well has no other wells: its factor is the stated rule's,
    (nu0 + sum z^2) / (nu0 + n), pooled or not."""
    z2 = np.array([[0.3, 2.0, 0.1, 0.7]])
    count = sum(DISCOUNT**i for i in range(4))
    total = sum(DISCOUNT ** (3 - i) * v for i, v in enumerate(z2[0]))
    expected = (2.0 + total) / (2.0 + count)
    assert _factors("bayes:cal_pool=on", z2)[0] == pytest.approx(expected, rel=1e-12)
    assert _factors("bayes", z2)[0] == pytest.approx(expected, rel=1e-12)


def test_wells_that_agree_learn_their_common_factor_from_all_of_them() -> None:
    """Six wells whose filters' variance is twice their errors' (c^2 = 0.5, as mm's on its
    own physics, whose drift allowance exceeds the wells' drift), nine well tests each: the
    factor learned with the other wells' errors as the prior is nearer the truth than each
    well's own (mean squared log error over 200 fields at most half; the stated prior,
    c^2 = 1 worth two errors, pulls each well's own towards 1), and a well with no well test
    yet starts from the others' (near 0.5, not 1)."""
    rng = np.random.default_rng(20)
    pooled, own = [], []
    for _ in range(200):
        z2 = 0.5 * rng.chisquare(1, size=(6, 9))
        pooled.append(_factors("bayes:cal_pool=on", z2))
        own.append(_factors("bayes", z2))
    err_pooled = np.mean(np.log(np.array(pooled) / 0.5) ** 2)
    err_own = np.mean(np.log(np.array(own) / 0.5) ** 2)
    assert err_pooled < 0.5 * err_own, (err_pooled, err_own)
    fresh = 0.5 * rng.chisquare(1, size=(6, 9))
    fresh[5] = np.nan  # the sixth well has had no well test
    factors = _factors("bayes:cal_pool=on", fresh)
    assert 0.3 < factors[5] < 0.75
    assert _factors("bayes", fresh)[5] == pytest.approx(1.0)


def test_wells_that_disagree_keep_their_own_factors() -> None:
    """Three wells with c^2 = 0.2 and three with 5 (a model right on some wells and far off
    on others), nine well tests each: the prior's weight stays small, so each well keeps
    its side (the pooled mean, about 2.6, is no well's) and the factors are no further from
    the truth than each well's own (mean squared log error over 100 fields)."""
    rng = np.random.default_rng(21)
    true = np.array([0.2, 0.2, 0.2, 5.0, 5.0, 5.0])
    pooled, own = [], []
    for _ in range(100):
        z2 = true[:, None] * rng.chisquare(1, size=(6, 9))
        pooled.append(_factors("bayes:cal_pool=on", z2))
        own.append(_factors("bayes", z2))
    log_pooled = np.log(np.array(pooled))
    assert np.median(log_pooled[:, :3]) < np.log(0.5) and np.median(log_pooled[:, 3:]) > np.log(2.5)
    err_pooled = np.mean((log_pooled - np.log(true)) ** 2)
    err_own = np.mean((np.log(np.array(own)) - np.log(true)) ** 2)
    assert err_pooled <= err_own, (err_pooled, err_own)


def test_one_well_filters_given_the_others_errors_pool_as_one_filter() -> None:
    """The service holds one filter a well: each given the other wells' statistics
    (``well_test_errors``, ``pool_with``) learns the factor one filter over all the wells
    learns; without them, its own (the stated prior)."""
    rng = np.random.default_rng(22)
    z2 = 0.5 * rng.chisquare(1, size=(4, 7))
    together = _factors("bayes:cal_pool=on", z2)
    wells = [f"W{i}" for i in range(4)]
    alone = []
    for i, well in enumerate(wells):
        method = parse_method("bayes:cal_pool=on").bind(make_model("mm", [well]))
        state = method.state_dict()
        cal = state["cal"].clone()
        for value in z2[i]:
            cal[0, 1, 0] = DISCOUNT * cal[0, 1, 0] + 1.0
            cal[0, 1, 1] = DISCOUNT * cal[0, 1, 1] + float(value)
        state["cal"] = cal
        method.load_state_dict(state)
        alone.append(method)
    own = np.array([m.well_test_factor().item() for m in alone])
    assert own == pytest.approx(_factors("bayes", z2), rel=1e-12)
    stats = [m.well_test_errors() for m in alone]
    for i, method in enumerate(alone):
        method.pool_with(torch.cat([t for j, t in enumerate(stats) if j != i]))
    pooled = np.array([m.well_test_factor().item() for m in alone])
    assert pooled == pytest.approx(together, rel=1e-9)
    assert not np.allclose(pooled, own)
    with pytest.raises(ValueError, match="finite"):
        alone[0].pool_with(torch.tensor([[1.0, float("nan")]]))


def test_the_option_is_checked() -> None:
    with pytest.raises(ConfigError, match="cal_pool"):
        parse_method("bayes:cal_pool=maybe")


def test_mm_case_2_intervals_narrower_and_still_covering() -> None:
    """mm learning from well tests only on a field of its own physics (four wells, three
    years): the filter's variance is larger than its errors on every well. With the pooled
    prior the 90 % intervals are narrower (median width measured 5.06 -> 4.26 %) and still
    cover 85-97 % (measured 94 -> 92 %); the predictions themselves do not change."""
    field = simulate_field(wells=4, years=3, seed=5).observations
    runs = {}
    for spec in ("bayes", "bayes:cal_pool=on"):
        pr = run_prequential(field, "mm", spec, targets="well_test").predictions
        ok = pr["predicted_p05"].notna() & pr["predicted_p95"].notna()
        runs[spec] = pr[ok]
    own, pooled = runs["bayes"], runs["bayes:cal_pool=on"]
    assert len(pooled) >= 30
    np.testing.assert_allclose(pooled["predicted"], own["predicted"], rtol=1e-12)

    def width(pr) -> float:
        return float(((pr["predicted_p95"] - pr["predicted_p05"]) / pr["predicted"]).median())

    inside = (pooled["measured"] >= pooled["predicted_p05"]) & (
        pooled["measured"] <= pooled["predicted_p95"]
    )
    assert width(pooled) < 0.9 * width(own)
    assert 0.85 <= float(inside.mean()) <= 0.97, float(inside.mean())
