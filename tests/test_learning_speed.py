"""The faster learning paths compute what the plain ones do (issue 16).

- the choke mass flux's closed-form gradient equals autograd's through the same formula;
- the learners' optimiser step equals torch.optim's to the bit, state included;
- one online (and one Bayesian) update of several wells in one call equals each well's
  own update, so batching wells changes nothing but the cost;
- every model's closed-form gradient (no autograd) equals autograd's through its forward;
- the study's rounds and retrain batches, cut from rows packed once, hold what packing
  them anew holds.
"""

from __future__ import annotations

import copy
from dataclasses import replace

import numpy as np
import pandas as pd
import pytest
import torch

from vfm_core import physics as ph
from vfm_core.data import DTYPE, Batch, make_batch, target_mask
from vfm_core.jobs.study import _day_rounds, _StudyMemory, wells_of
from vfm_core.learning import DEFAULT_ONLINE, DEFAULT_TRAIN, fit_batch, parse_method
from vfm_core.learning.training import (
    _minibatch,
    _Sampler,
    map_gradients_,
    optimizer_step_,
    scaled_errors,
    well_generators,
    zero_grad_,
)
from vfm_core.models import make_model
from vfm_core.observations import validate_frame
from vfm_core.simulate import simulate_field


def _flux_case(seed: int = 0) -> tuple[tuple[torch.Tensor, ...], list[torch.Tensor]]:
    gen = torch.Generator().manual_seed(seed)
    w, n = 4, 7

    def rand(*lo_hi: float) -> torch.Tensor:
        lo, hi = lo_hi
        return lo + (hi - lo) * torch.rand(w, n, generator=gen, dtype=DTYPE)

    p_up = rand(20e5, 70e5)  # Pa
    p_down = p_up * rand(0.05, 0.95)  # both sides of the critical ratio
    t_up = rand(300.0, 350.0)  # K
    eta_gas = rand(0.0, 0.3)
    eta_gas[0, 0] = 0.0  # no gas at all
    eta_oil = (1.0 - eta_gas) * rand(0.0, 1.0)
    means = (840.0, 1017.5, 1.28, 0.0205, 0.55)
    params = [
        torch.full((w, 1), v, dtype=DTYPE)
        + 0.01 * v * torch.randn(w, 1, generator=gen, dtype=DTYPE)
        for v in means
    ]
    params.append(rand(0.9, 1.1))  # gas Z per sample
    return (p_up, p_down, t_up, eta_gas, eta_oil), [p.requires_grad_() for p in params]


def test_flux_gradient_in_closed_form_equals_autograd_through_the_formula():
    inputs, params = _flux_case()
    weights = torch.rand(inputs[0].shape, generator=torch.Generator().manual_seed(1), dtype=DTYPE)
    names = ("rho_oil", "rho_wat", "kappa", "m_gas", "p_cr", "z")
    flux = ph.choke_mass_flux(*inputs, **dict(zip(names, params, strict=True)))
    assert type(flux.grad_fn).__name__.startswith("_FluxFunction")
    closed = torch.autograd.grad((flux * weights).sum(), params)
    plain_params = [p.detach().clone().requires_grad_() for p in params]
    plain, _ = ph._flux(*inputs, *plain_params, False)
    assert torch.equal(flux.detach(), plain.detach())  # the same forward, to the bit
    auto = torch.autograd.grad((plain * weights).sum(), plain_params)
    for name, c, a in zip(names, closed, auto, strict=True):
        assert c.shape == a.shape, name
        assert torch.allclose(c, a, rtol=1e-12, atol=0.0), name
        assert bool((a != 0).any()), name  # every parameter matters somewhere here


def test_flux_gradient_passes_gradcheck():
    inputs, params = _flux_case(seed=2)
    names = ("rho_oil", "rho_wat", "kappa", "m_gas", "p_cr", "z")

    def flux(*values: torch.Tensor) -> torch.Tensor:
        return ph.choke_mass_flux(*inputs, **dict(zip(names, values, strict=True)))

    assert torch.autograd.gradcheck(flux, tuple(params))


def test_flux_without_parameter_gradients_keeps_autograd_for_the_inputs():
    inputs, params = _flux_case()
    p_up = inputs[0].clone().requires_grad_()
    names = ("rho_oil", "rho_wat", "kappa", "m_gas", "p_cr", "z")
    flux = ph.choke_mass_flux(p_up, *inputs[1:], **dict(zip(names, params, strict=True)))
    (g,) = torch.autograd.grad(flux.sum(), [p_up])
    assert bool((g != 0).any())


@pytest.mark.parametrize("kind", ["adam", "sgd"])
def test_optimizer_step_equals_torch_optim_to_the_bit(kind: str):
    gen = torch.Generator().manual_seed(0)
    a = [torch.nn.Parameter(torch.randn(3, 4, generator=gen, dtype=DTYPE)) for _ in range(2)]
    b = [torch.nn.Parameter(p.detach().clone()) for p in a]
    make = torch.optim.Adam if kind == "adam" else torch.optim.SGD
    opt_a, opt_b = make(a, lr=1e-2), make(b, lr=1e-2)
    for _ in range(25):
        grads = [torch.randn(3, 4, generator=gen, dtype=DTYPE) for _ in a]
        opt_a.zero_grad()
        zero_grad_(b)
        for p, q, g in zip(a, b, grads, strict=True):
            p.grad, q.grad = g.clone(), g.clone()
        opt_a.step()
        optimizer_step_(opt_b)
    for p, q in zip(a, b, strict=True):
        assert torch.equal(p, q)
        assert not torch.equal(p, torch.zeros_like(p))
    sa, sb = opt_a.state_dict(), opt_b.state_dict()
    assert sa["param_groups"] == sb["param_groups"]
    for k in sa["state"]:
        for name, value in sa["state"][k].items():
            assert torch.equal(value, sb["state"][k][name]), name


def _field_batches() -> tuple[Batch, list[Batch]]:
    frame = validate_frame(simulate_field(wells=3, years=1.0, seed=4).observations).frame
    wells = wells_of(frame)
    batch = make_batch(frame, wells, np.flatnonzero(target_mask(frame, "all")))
    rank = torch.cumsum(batch.mask.long(), 1)
    history = batch.select(rank <= 60)
    return history, [batch.select(rank == 61 + k) for k in range(5)]


def _one_well(batch: Batch, j: int) -> Batch:
    assert batch.well_test is not None and batch.extra is not None
    s = slice(j, j + 1)
    return Batch(
        batch.wells[s],
        batch.x[s],
        batch.y[s],
        batch.mask[s],
        batch.time_ns[s],
        batch.row[s],
        batch.well_test[s],
        batch.extra[s],
        batch.extra_names,
    )


@pytest.mark.parametrize(
    ("model_name", "method_text"), [("mm", "ol"), ("ham", "ol"), ("mm", "bayes")]
)
def test_an_update_of_every_well_in_one_call_equals_each_wells_own(model_name, method_text):
    history, columns = _field_batches()
    train = DEFAULT_TRAIN[model_name]
    field = make_model(model_name, history.wells)
    method = parse_method(method_text).bind(field, train=train, online=DEFAULT_ONLINE[model_name])
    # the batch fit once, then every method (the field's and each well's) starts from it
    iterations = fit_batch(field, history, train)["iterations"]
    fitted = copy.deepcopy(field.state_dict())
    method.adopt(history, iterations)
    singles = []
    for j, well in enumerate(history.wells):
        model = make_model(model_name, [well])
        shapes = {k: v.shape for k, v in model.state_dict().items()}
        state = {
            k: v[j : j + 1].clone() if v.shape != shapes[k] else v.clone()
            for k, v in fitted.items()
        }
        model.load_state_dict(state)
        one = parse_method(method_text).bind(model, train=train, online=DEFAULT_ONLINE[model_name])
        one.adopt(_one_well(history, j), iterations[j : j + 1])
        singles.append(one)
    before = {k: v.clone() for k, v in field.state_dict().items()}
    for column in columns:
        method.on_measurement(column)
        for j, one in enumerate(singles):
            one.on_measurement(_one_well(column, j))
    moved = False
    for name, value in field.state_dict().items():
        if value.shape == singles[0].model.state_dict()[name].shape:
            continue  # not per well (prior constants)
        for j, one in enumerate(singles):
            own = one.model.state_dict()[name][0]
            assert torch.allclose(value[j], own, rtol=1e-10, atol=1e-12), (name, j)
        moved |= not torch.equal(value, before[name])
    assert moved  # the updates did something


@pytest.mark.parametrize("model_name", ["lr", "nn", "mtl", "mm", "hem", "ham"])
@pytest.mark.parametrize("physical_only", [True, False])
def test_closed_form_gradients_equal_autograd(model_name, physical_only):
    """Every model's closed-form gradient (``rate_vjp`` + ``prior_gradients``) is autograd's
    through its own forward, wells with and without data, mini-batch weighting included."""
    history, _ = _field_batches()
    model = make_model(model_name, history.wells)
    fit_batch(model, history, replace(DEFAULT_TRAIN[model_name], max_iter=20, patience=3))
    with torch.no_grad():  # away from the prior means, so that every term counts
        for p in model.parameters():
            p.add_(0.05 * torch.randn(p.shape, generator=torch.Generator().manual_seed(3)))
    assert model.rate_vjp(history) is not None
    params = [p for p in model.parameters() if p.requires_grad]
    keep = torch.rand(history.mask.shape, generator=torch.Generator().manual_seed(2)) < 0.5
    batch = history.select(keep)
    n = batch.count().to(DTYPE) + 3.0
    n[1] = 0.0  # a well that does not count
    closed_loss = map_gradients_(
        model, params, batch, 0.05, physical_only, n, batch.count().to(DTYPE)
    )
    closed = [p.grad.clone() for p in params]
    zero_grad_(params)
    e = scaled_errors(model, batch)
    mse = (e**2).sum(1) / batch.count().clamp(min=1).to(DTYPE)
    prior = model.prior_penalty(physical_only) * 0.05**2 / n.clamp(min=1.0)
    loss = torch.where(n > 0, mse + prior, torch.zeros_like(mse))
    loss.sum().backward()
    assert torch.allclose(closed_loss, loss.detach(), rtol=1e-12, atol=1e-15)
    nonzero = 0
    for p, g in zip(params, closed, strict=True):
        assert torch.allclose(g, p.grad, rtol=1e-9, atol=1e-12 * float(p.grad.abs().max()) + 1e-300)
        nonzero += int(g.abs().gt(0).any())
    assert nonzero >= 1


def test_models_with_effects_or_subclasses_fall_back_to_autograd():
    """A closed form belongs to its exact class: effects or a subclass change the rate."""
    history, _ = _field_batches()

    class Shifted(type(make_model("mm", ["W"]))):  # a user's variant of the rate
        def forward_batch(self, batch: Batch) -> torch.Tensor:
            return super().forward_batch(batch) + 1.0

    assert Shifted(history.wells).rate_vjp(history) is None
    frame_model = make_model("mm", history.wells, effects=["slip"])
    assert frame_model.rate_vjp(history) is None


def _same_samples(a: Batch, b: Batch) -> None:
    """The same samples in the same places (padding, masked, may differ)."""
    assert torch.equal(a.mask, b.mask) and torch.equal(a.row, b.row)
    m = a.mask
    assert torch.equal(a.x[m], b.x[m]) and torch.equal(a.y[m], b.y[m])
    assert torch.equal(a.time_ns[m], b.time_ns[m]) and torch.equal(a.extra[m], b.extra[m])
    assert torch.equal(a.well_test, b.well_test)


def test_study_rounds_and_memory_cut_from_packed_rows_equal_packing_anew():
    """The study's day rounds (shared models), its rounds per distinct time (methods that
    couple the wells) and its retrain memory select from rows packed once; they hold exactly
    what a per-day (per-time) select and a fresh make_batch hold."""
    frame = validate_frame(simulate_field(wells=3, years=1.0, seed=4).observations).frame
    t0 = pd.Timestamp(frame["time"].iloc[len(frame) // 2])
    gap = (frame["well"] == frame["well"].iloc[0]) & frame["time"].between(
        t0, t0 + pd.Timedelta("40D")
    )
    frame = frame[~gap].reset_index(drop=True)  # a well without measurements for 40 days
    wells = wells_of(frame)
    is_target = target_mask(frame, "all")
    test = make_batch(frame, wells, np.flatnonzero(is_target))
    day = torch.div(test.time_ns, 86_400 * 10**9, rounding_mode="floor")
    days = torch.unique(day[test.mask])
    rounds = _day_rounds(test)
    assert len(rounds) == len(days) > 100
    for d, got in zip(days, rounds, strict=True):
        _same_samples(test.select(day == d), got)
    # ... and one round per distinct time (a method that couples the wells)
    times = torch.unique(test.time_ns[test.mask])
    by_time = _day_rounds(test, 1)
    assert len(by_time) == len(times) > len(days)
    for t, got in list(zip(times, by_time, strict=True))[:150]:
        _same_samples(test.select((test.time_ns == t) & test.mask), got)
    memory = _StudyMemory(frame, is_target, wells)
    t = pd.DatetimeIndex(frame["time"]).as_unit("ns").asi8
    for until, window in [(t[len(t) // 3], None), (t[-1], 30 * 86_400 * 10**9), (t[-1] + 1, None)]:
        keep = is_target & (t < until) & (t >= (until - window if window else t.min()))
        _same_samples(make_batch(frame, wells, np.flatnonzero(keep)), memory.batch(until, window))


def test_chunked_sampler_draws_the_mini_batches_of_one_draw_per_iteration():
    """The retrains' sampler draws ahead a chunk of iterations at a time; its mini-batches
    are _minibatch's, and after ``finish`` every well's random stream is where taking the
    same iterations one at a time leaves it."""
    history, _ = _field_batches()
    size = 16
    assert int(history.count().min()) > size
    gens_a = well_generators(history.wells, 0)
    gens_b = well_generators(history.wells, 0)
    sampler = _Sampler(history, size, gens_a)
    taken = sampler.chunk + 3  # a chunk and part of the next
    for _ in range(taken):
        got, counts = sampler.next()
        want, want_counts = _minibatch(history, size, gens_b)
        assert torch.equal(counts, want_counts)
        for f in ("x", "y", "mask", "time_ns", "row", "well_test", "extra"):
            assert torch.equal(getattr(got, f), getattr(want, f)), f
    sampler.finish()
    for a, b in zip(gens_a, gens_b, strict=True):
        assert torch.equal(torch.rand(5, generator=a), torch.rand(5, generator=b))


def test_a_retrain_stops_once_converged_where_running_on_gains_little():
    """A warm-started retrain on data that fit in one batch stops each well once its
    objective has converged: fewer iterations than the full count, the objective still
    lowered from the warm start (the new data learned) and within 2 % of what the full
    count reaches. On mini-batches (a noisy objective) it runs the full count."""
    history, _ = _field_batches()
    train = DEFAULT_TRAIN["mm"]
    rank = torch.cumsum(history.mask.long(), 1)
    model = make_model("mm", history.wells)
    fit_batch(model, history.select(rank <= 40), train)
    start = copy.deepcopy(model.state_dict())
    # a bias the retrain has to learn away: the newer data read 10 % high
    newer = history.select(rank > 0)
    newer.y = torch.where(rank[:, : newer.y.shape[1]] > 40, newer.y * 1.1, newer.y)
    cap = torch.full((newer.n_wells,), 150, dtype=torch.int64)
    params = [p for p in model.parameters() if p.requires_grad]

    def objective() -> float:
        n = newer.count().to(DTYPE)
        return float(map_gradients_(model, params, newer, train.noise, False, n).sum())

    before = objective()
    full = fit_batch(model, newer, replace(train, retrain_tol=0.0), cap)["iterations"]
    reached_full = objective()
    model.load_state_dict(start)
    stopped = fit_batch(model, newer, train, cap)["iterations"]
    reached = objective()
    assert torch.equal(full, cap)
    assert bool((stopped < cap).all()) and int(stopped.min()) >= 3 * train.retrain_check
    assert reached < 0.8 * before
    assert reached < 1.02 * reached_full
    # on mini-batches the objective is noisy: no convergence stop, the full count
    model.load_state_dict(start)
    noisy = fit_batch(model, newer, replace(train, batch_size=16), cap)["iterations"]
    assert torch.equal(noisy, cap)
    # an initial fit without early stopping ("to convergence", as the diagnosis fits mm)
    # is no retrain: it runs max_iter in full
    model.load_state_dict(start)
    whole = fit_batch(model, newer, replace(train, early_stopping=False, max_iter=120))
    assert bool((whole["iterations"] == 120).all())
