"""The allocation's intervals: calibrated from what the allocator sees (issue 40).

The booked rates' variance is checked by Monte Carlo in the allocation's own linear-Gaussian
model (where 90 % must fall inside), the wells' variance factor against a filter whose well
tests scatter more (or less) than it states, and the prior's misfit against its formula."""

from __future__ import annotations

import numpy as np
import pandas as pd
import torch

from vfm_core.data import DTYPE, Batch
from vfm_core.learning import DEFAULT_TRAIN, TrainSettings, parse_method
from vfm_core.learning.bayes import Z90
from vfm_core.models import make_model
from vfm_core.separator import (
    WellFilters,
    booked_allocation,
    calibrated_prior,
    well_test_factor,
)


def _coverage(m: int, well_sd: float, meter_sd: float, draws: int, seed: int) -> tuple:
    """Coverage of the booked rates' 90 % intervals over ``draws`` readings whose wells'
    true log rates are drawn from the very prior the allocation is given; also the
    coverage with the posterior variance alone (without the booking's share of the
    meter's error)."""
    rng = np.random.default_rng(seed)
    mu = torch.tensor(np.log(rng.uniform(50.0, 400.0, m)), dtype=DTYPE)
    a = rng.normal(0.0, well_sd, (m, m)) / np.sqrt(m)
    sigma = torch.tensor(a @ a.T + np.eye(m) * well_sd**2, dtype=DTYPE)
    chol = torch.linalg.cholesky(sigma)
    flowing = torch.ones(m, dtype=torch.bool)
    s2 = meter_sd**2
    share = mu.exp() / mu.exp().sum()
    s_alloc = float(share @ sigma @ share) + s2
    inside = inside_post = 0
    for _ in range(draws):
        truth = mu + chol @ torch.tensor(rng.normal(size=m), dtype=DTYPE)
        measured = float(truth.exp().sum()) * float(np.exp(rng.normal(0.0, meter_sd)))
        booked, sd = booked_allocation(mu, flowing, sigma, s2, measured)
        err = (truth - booked.log()).abs()
        inside += int((err <= Z90 * sd).sum())
        post_sd = (sd**2 - s2**2 / s_alloc).clamp(min=0).sqrt()
        inside_post += int((err <= Z90 * post_sd).sum())
    return inside / (draws * m), inside_post / (draws * m)


def test_booked_rates_cover_90_percent_when_the_prior_is_right():
    # wells known to 0.5 %, a total measured to 1.5 %: the booking puts most of the meter's
    # error into every well, which the posterior variance alone leaves out
    cov, cov_post = _coverage(m=8, well_sd=0.005, meter_sd=0.015, draws=1500, seed=4401)
    assert 0.87 <= cov <= 0.93, cov
    assert cov_post < 0.80, cov_post
    # wells known to 3 %, the meter's share small: both near 90 %
    cov, cov_post = _coverage(m=6, well_sd=0.03, meter_sd=0.015, draws=1500, seed=4402)
    assert 0.87 <= cov <= 0.93, cov
    assert cov_post >= 0.84, cov_post


INPUTS = {
    "A": [0.45, 100.0, 25.0, 60.0, 0.1, 0.7],
    "B": [0.5, 110.0, 25.0, 60.0, 0.1, 0.7],
    "C": [0.4, 105.0, 25.0, 60.0, 0.1, 0.7],
    "D": [0.55, 95.0, 25.0, 60.0, 0.1, 0.7],
}


def _filter_after_tests(
    error_sd: float, wells: tuple = ("A", "B"), n_tests: int = 12, method: str = "bayes"
):
    """A ``bayes`` filter over ``mm`` wells, started with a tight covariance, that then
    learns ``n_tests`` monthly well tests whose log errors about its forecast have the sd
    ``error_sd`` (its stated well-test sd is about 1 %); each well's errors are drawn from
    its own generator, so one-well filters see the same errors."""
    wells = list(wells)
    n = len(wells)
    x = torch.tensor([INPUTS[w] for w in wells], dtype=DTYPE).unsqueeze(1)
    mask = torch.ones(n, 1, dtype=torch.bool)
    rows = torch.zeros(n, 1, dtype=torch.int64)
    t0 = int(pd.Timestamp("2020-01-01", tz="UTC").value)
    model = make_model("mm", wells, seed=0)
    meth = parse_method(method)
    meth.bind(model, train=DEFAULT_TRAIN.get("mm", TrainSettings()))
    times = torch.full((n, 1), t0, dtype=torch.int64)
    model.setup(Batch(wells, x, torch.full((n, 1), 50.0, dtype=DTYPE), mask, times, rows))
    theta, P, _, _ = meth.filter_state()
    tight = torch.eye(P.shape[-1], dtype=DTYPE).expand_as(P) * 1e-4
    meth.set_filter_state(theta, tight, times[:, 0], torch.ones(n, dtype=torch.bool))
    rngs = [np.random.default_rng(4403 + ord(w[0])) for w in wells]
    test = torch.ones(n, 1, dtype=torch.bool)
    for k in range(n_tests):
        when = torch.full((n, 1), t0 + (k + 1) * 30 * 86_400 * 10**9, dtype=torch.int64)
        probe = Batch(wells, x, torch.zeros(n, 1, dtype=DTYPE), mask, when, rows, test)
        draws = [[r.normal(0.0, error_sd)] for r in rngs]
        noise = torch.tensor(draws, dtype=DTYPE)
        y = meth.predict(probe).mean * noise.exp()
        meth.on_measurement(Batch(wells, x, y, mask, when, rows, test))
    return meth


def test_variance_factor_follows_the_wells_well_test_errors():
    wide = _filter_after_tests(0.05)  # errors about 5 times the stated sd
    exact = _filter_after_tests(0.0)  # errors far below it
    f_wide, meter = well_test_factor(wide)
    f_exact, _ = well_test_factor(exact)
    assert bool((f_wide > 2.0).all()), f_wide
    assert bool((f_exact < 0.5).all()), f_exact
    assert torch.allclose(meter, torch.full_like(meter, 0.01))  # the default test meter
    # one-well filters (as the service holds them) give the same factors
    one = [_filter_after_tests(0.05, (w,)) for w in ("A", "B")]
    f_one, _ = well_test_factor(WellFilters(["A", "B"], one))
    assert torch.allclose(f_one, f_wide)
    # and the allocation's intervals widen with the factor, narrow without the errors
    params = torch.diag(torch.tensor([0.01**2, 0.01**2], dtype=DTYPE))
    tau2 = torch.tensor([0.015**2, 0.015**2], dtype=DTYPE)
    mu = torch.log(torch.tensor([100.0, 200.0], dtype=DTYPE))
    flowing = torch.ones(2, dtype=torch.bool)
    sds = [
        booked_allocation(mu, flowing, calibrated_prior(params, tau2, f, meter), 0.015**2, 303.0)[1]
        for f in (f_exact, torch.ones(2, dtype=DTYPE), f_wide)
    ]
    assert bool((sds[0] < sds[1]).all()) and bool((sds[1] < sds[2]).all()), sds


def test_calibrated_prior_scales_the_parameters_and_keeps_the_misfit_beyond_the_test_meter():
    params = torch.tensor([[4e-4, -1e-4, 0.0], [-1e-4, 9e-4, 0.0], [0.0, 0.0, 0.0]], dtype=DTYPE)
    tau2 = torch.tensor([0.03**2, 0.005**2, 0.0], dtype=DTYPE)  # the third is shut in
    factor = torch.tensor([4.0, 1.0, 2.0], dtype=DTYPE)
    meter = torch.full((3,), 0.01, dtype=DTYPE)
    prior = calibrated_prior(params, tau2, factor, meter)
    c = factor.sqrt()
    expected = params * torch.outer(c, c)
    expected[0, 0] += 4.0 * 0.03**2 - 0.01**2  # misfit beyond the test meter's noise
    # the second well's tests scatter less than its meter: no misfit left
    assert torch.allclose(prior, expected)
    assert float(prior[2].abs().sum()) == 0.0


def test_a_separators_members_pool_their_variance_factors():
    # four wells whose tests fall far closer to the forecasts than the filter states (as
    # when its tau is the residual of a fit that could not follow a drift): each well's own
    # factor, from its 6 errors, stays pulled towards the stated prior (c^2 = 1); pooled
    # over the separator's members (their prior the one under which the others' errors
    # are most likely) they come nearer to what the errors say
    wells = ("A", "B", "C", "D")
    meth = _filter_after_tests(0.001, wells, n_tests=6)
    errors = meth.well_test_errors()
    said = errors[:, 1] / errors[:, 0]  # each well's mean squared standardised error
    own, _ = well_test_factor(meth)
    ix = torch.arange(4)
    pooled, meter = well_test_factor(meth, ix)
    assert bool((said < 0.2).all()), said
    nearer = (pooled / said).log().abs() < (own / said).log().abs()
    assert bool((pooled < own).all()) and bool(nearer.all()), (said, own, pooled)
    assert float(pooled.max()) < 0.1 * float(own.min()), (own, pooled)
    assert torch.allclose(meter, torch.full_like(meter, 0.01))
    # a subset is pooled over its own members; a lone well keeps its own factor
    assert torch.allclose(well_test_factor(meth, torch.tensor([2]))[0], own[2:3])
    pair, _ = well_test_factor(meth, torch.tensor([0, 3]))
    assert bool((pair < own[[0, 3]]).all()) and not torch.allclose(pair, pooled[[0, 3]])
    # one-well filters (the service's) pool to the same numbers
    one = [_filter_after_tests(0.001, (w,), n_tests=6) for w in wells]
    assert torch.allclose(well_test_factor(WellFilters(list(wells), one), ix)[0], pooled)
    # the factors cal_pool=on gives a filter over these wells (the same errors: the factor
    # widens the intervals only); such a filter, pooling already, keeps its own
    field = _filter_after_tests(0.001, wells, n_tests=6, method="bayes:cal_pool=on")
    assert torch.allclose(well_test_factor(field)[0], pooled)
    assert torch.allclose(well_test_factor(field, ix)[0], well_test_factor(field)[0])
