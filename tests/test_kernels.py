"""The compiled online step of the plain ``mm`` (vfm_core/learning/kernels.py) computes what
the torch path computes (issue 16).

- many ``ol`` updates (Adam and SGD, wells without a measurement held still) leave the
  same parameters, Adam moments and step counts as the torch path, to rounding;
- one step's gradient equals autograd's through the model's plain forward;
- the learner learns through it: a well whose rates rose moves its C_D up and its error
  falls;
- the kernel is used only where it applies, and ``VFM_KERNELS=0`` turns it off.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from vfm_core.data import DTYPE, Batch, make_batch, target_mask
from vfm_core.jobs.study import wells_of
from vfm_core.learning import DEFAULT_ONLINE, DEFAULT_TRAIN, parse_method
from vfm_core.learning.kernels import (
    hybrid_applies,
    kernels_enabled,
    mm_online_applies,
    mm_online_steps,
    predict_rates,
)
from vfm_core.learning.online import OnlineSettings
from vfm_core.learning.training import per_well_loss
from vfm_core.models import make_model
from vfm_core.observations import validate_frame
from vfm_core.simulate import simulate_field

pytestmark = pytest.mark.skipif(not kernels_enabled(), reason="numba is not installed here")


@pytest.fixture(scope="module")
def stream() -> tuple[Batch, list[Batch]]:
    """Three simulated wells: a history of 150 measurements each, then 60 one-sample columns."""
    frame = validate_frame(simulate_field(wells=3, years=1.0, seed=4).observations).frame
    wells = wells_of(frame)
    batch = make_batch(frame, wells, np.flatnonzero(target_mask(frame, "all")))
    rank = torch.cumsum(batch.mask.long(), 1)
    return batch.select(rank <= 150), [batch.select(rank == 151 + k) for k in range(60)]


def _learner(history: Batch, online: OnlineSettings, name: str = "mm") -> tuple[object, object]:
    model = make_model(name, history.wells)
    method = parse_method("ol")
    train = replace(DEFAULT_TRAIN[name], max_iter=60, early_stopping=False)
    method.bind(model, train=train, online=online)
    method.fit(history)
    method.start(int(history.time_ns[history.mask].max()))
    return model, method


def _run(
    monkeypatch: pytest.MonkeyPatch, kernels: str, stream: tuple[Batch, list[Batch]], **kw: object
) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    monkeypatch.setenv("VFM_KERNELS", kernels)
    history, cols = stream
    model, method = _learner(history, OnlineSettings(**kw))  # type: ignore[arg-type]
    assert mm_online_applies(model) is (kernels == "1")
    for k, col in enumerate(cols):
        if k % 3 == 1:  # the middle well has no measurement this time: it is held still
            col = col.select(col.mask & torch.tensor([True, False, True]).unsqueeze(1))
        method.on_measurement(col)  # type: ignore[attr-defined]
    z = model.phys.z.detach().clone()  # type: ignore[attr-defined]
    state = method._opt.state.get(model.phys.z, {})  # type: ignore[attr-defined]
    return z, {k: v.clone() for k, v in state.items()}


@pytest.mark.parametrize(
    "settings",
    [
        dict(optimizer="adam", lr=1e-3, steps=10),
        dict(optimizer="adam", lr=1e-1, steps=3, max_grad_norm=0.05),  # the clip bites
        dict(optimizer="sgd", lr=1e-4, steps=10),
    ],
)
def test_kernel_matches_the_torch_steps(
    monkeypatch: pytest.MonkeyPatch, stream: tuple[Batch, list[Batch]], settings: dict
) -> None:
    z_fast, state_fast = _run(monkeypatch, "1", stream, **settings)
    z_torch, state_torch = _run(monkeypatch, "0", stream, **settings)
    assert not torch.equal(z_torch, torch.zeros_like(z_torch))  # it learned something
    assert torch.allclose(z_fast, z_torch, rtol=0, atol=1e-12 * float(z_torch.abs().max()))
    assert state_fast.keys() == state_torch.keys()
    for key, value in state_torch.items():
        scale = float(value.abs().max())
        assert torch.allclose(state_fast[key], value, rtol=0, atol=1e-12 * scale), key


def _hybrid_run(
    monkeypatch: pytest.MonkeyPatch,
    kernels: str,
    stream: tuple[Batch, list[Batch]],
    name: str,
    **kw: object,
) -> dict[str, torch.Tensor]:
    monkeypatch.setenv("VFM_KERNELS", kernels)
    history, cols = stream
    model, method = _learner(history, OnlineSettings(**kw), name)  # type: ignore[arg-type]
    assert hybrid_applies(model) is (kernels == "1")
    for k, col in enumerate(cols):
        if k % 3 == 1:  # the middle well has no measurement this time: it is held still
            col = col.select(col.mask & torch.tensor([True, False, True]).unsqueeze(1))
        method.on_measurement(col)  # type: ignore[attr-defined]
    out = {}
    for i, p in enumerate(model.parameters()):  # type: ignore[attr-defined]
        out[f"param{i}"] = p.detach().clone()
        for key, value in method._opt.state.get(p, {}).items():  # type: ignore[attr-defined]
            out[f"param{i}.{key}"] = value.clone()
    return out


@pytest.mark.parametrize(
    ("name", "settings"),
    [
        ("hem", dict(optimizer="adam", lr=1e-2, steps=2)),
        ("ham", dict(optimizer="adam", lr=1e-2, steps=2)),
        ("ham", dict(optimizer="adam", lr=1e-1, steps=3, max_grad_norm=0.05)),  # the clip bites
        ("hem", dict(optimizer="sgd", lr=1e-3, steps=2)),
    ],
)
def test_hybrid_kernel_matches_the_torch_steps(
    monkeypatch: pytest.MonkeyPatch, stream: tuple[Batch, list[Batch]], name: str, settings: dict
) -> None:
    """hem and ham: every parameter (physics and network) and its Adam state after 60
    updates, compiled and torch."""
    fast = _hybrid_run(monkeypatch, "1", stream, name, **settings)
    slow = _hybrid_run(monkeypatch, "0", stream, name, **settings)
    assert fast.keys() == slow.keys()
    assert len(slow) == (5 * 4 if settings["optimizer"] == "adam" else 5)  # (step, moments)
    for key, value in slow.items():
        scale = float(value.abs().max())
        assert scale > 0, key  # every parameter learned, every state moved
        assert torch.allclose(fast[key], value, rtol=0, atol=1e-10 * scale), key


def test_kernel_gradient_is_autograds(stream: tuple[Batch, list[Batch]]) -> None:
    """One SGD step of rate lr moves z by -lr times the objective's gradient; autograd
    through the plain formula (an input that requires grad keeps the closed form out)."""
    history, _ = stream
    model, _ = _learner(history, OnlineSettings())
    batch = history.select(torch.cumsum(history.mask.long(), 1) > 140)  # 10 samples per well
    z0 = model.phys.z.detach().clone()  # type: ignore[attr-defined]
    noise = 0.05
    x = batch.x.clone().requires_grad_(True)
    plain = replace(batch, x=x)
    n = batch.count().to(DTYPE)
    loss = per_well_loss(model, plain, noise, True, n).sum()  # type: ignore[arg-type]
    (grad,) = torch.autograd.grad(loss, model.phys.z)  # type: ignore[attr-defined]
    lr = 1e-9  # far inside the bounds: no projection
    mm_online_steps(
        model,
        batch,
        None,
        np.zeros(batch.n_wells),
        np.zeros(batch.n_wells, dtype=bool),
        steps=1,
        noise=noise,
        lr=lr,
        betas=(0.9, 0.999),
        eps=1e-8,
        max_norm=1e12,  # no clip
    )
    step = (model.phys.z.detach() - z0) / -lr  # type: ignore[attr-defined]
    assert float(grad.abs().max()) > 0
    assert torch.allclose(step, grad, rtol=1e-5, atol=1e-6 * float(grad.abs().max()))


def test_learning_through_the_kernel_follows_a_well_whose_rates_rose(
    stream: tuple[Batch, list[Batch]],
) -> None:
    history, cols = stream
    model, method = _learner(history, OnlineSettings(optimizer="adam", lr=1e-2, steps=10))
    assert mm_online_applies(model)
    risen = [replace(c, y=c.y * 1.10) for c in cols]  # the truth: 10 % more through the choke
    c_d = model.physical_parameters()["c_d"].clone()  # type: ignore[attr-defined]

    def error(col: Batch) -> float:
        q = method.predict(col).mean  # type: ignore[attr-defined]
        return float((((q - col.y) / col.y).abs())[col.mask].mean())

    before = np.mean([error(c) for c in risen[:10]])
    for col in risen:
        method.on_measurement(col)  # type: ignore[attr-defined]
    after = np.mean([error(c) for c in risen[-10:]])
    assert np.isfinite(before) and np.isfinite(after)
    assert after < 0.5 * before
    assert bool((model.physical_parameters()["c_d"] > c_d).all())  # type: ignore[attr-defined]


def test_kernel_only_where_it_applies(monkeypatch: pytest.MonkeyPatch) -> None:
    wells = ["A", "B"]
    assert mm_online_applies(make_model("mm", wells))
    assert not mm_online_applies(make_model("mm", wells, effects=["erosion"]))
    for name in ("hem", "ham", "lr"):
        assert not mm_online_applies(make_model(name, wells))
    monkeypatch.setenv("VFM_KERNELS", "0")
    assert not kernels_enabled()
    assert not mm_online_applies(make_model("mm", wells))


def test_a_kernel_that_cannot_compile_leaves_the_torch_path(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    from vfm_core.learning import kernels

    def broken() -> None:
        raise RuntimeError("no LLVM here")

    monkeypatch.setattr(kernels, "_KERNEL", None)
    monkeypatch.setattr(kernels, "_FAILED", None)
    monkeypatch.setattr(kernels, "_build", broken)
    assert not kernels.kernels_enabled()
    assert not mm_online_applies(make_model("mm", ["A"]))
    assert "no LLVM here" in caplog.text


# -- bayes on the plain mm ------------------------------------------------------------------------
_BAYES_STATE = ("_P", "_last", "_noise", "_h", "_scale", "_started", "_run")


@pytest.fixture(scope="module")
def field() -> Batch:
    """Three simulated wells, every measured row (MPFM and well tests)."""
    frame = validate_frame(simulate_field(wells=3, years=1.0, seed=4).observations).frame
    return make_batch(frame, wells_of(frame), np.flatnonzero(target_mask(frame, "all")))


def _bayes_run(
    monkeypatch: pytest.MonkeyPatch, kernels: str, field: Batch, text: str, name: str = "mm"
) -> tuple[dict[str, torch.Tensor], list[torch.Tensor]]:
    """Fit ``text`` on the first 150 rows of wells 0 and 1 (well 2 has no history: its
    filter starts at its first measurement), then 60 updates that take every path of the
    filter: one or two measurements per well, a well without one, outliers refused, three
    in a row (a reset), a rate of zero. Returns the state and every update's answer."""
    monkeypatch.setenv("VFM_KERNELS", kernels)
    # the same initial fit for both (its compiled steps match to rounding, which the
    # filter's many updates would amplify past this test's tolerance)
    monkeypatch.setenv("VFM_FIT_KERNEL", "0")
    rank = torch.cumsum(field.mask.long(), 1)
    no_history = torch.tensor([True, True, False]).unsqueeze(1)
    history = field.select((rank <= 150) & no_history)
    model = make_model(name, history.wells)
    method = parse_method(text)
    train = replace(DEFAULT_TRAIN[name], max_iter=60, early_stopping=False)
    method.bind(model, train=train, online=DEFAULT_ONLINE[name])
    method.fit(history)
    method.start(int(history.time_ns[history.mask].max()))
    assert method.compiled is (kernels == "1")
    answers = []
    k = 151
    for step in range(60):
        take = (rank == k) | (rank == k + 1) if step % 5 == 2 else rank == k
        k += 2 if step % 5 == 2 else 1
        col = field.select(take)
        y = col.y.clone()
        if step % 3 == 1:  # the middle well has no measurement this time
            col = col.select(col.mask & torch.tensor([True, False, True]).unsqueeze(1))
        if step % 7 == 3:
            y[0] *= 4.0  # an outlier on well 0: refused
        if 20 <= step < 23:
            y[2] *= 3.0  # well 2 changed: refused twice, then a reset
        if step == 30:
            y[0] = 0.0  # no rate: not taken
        answers.append(method.on_measurement(replace(col, y=y)).clone())
        forecast = method.predict(col)
        answers += [t.clone() for t in forecast]
    state = {name: getattr(method, name).clone() for name in _BAYES_STATE}
    state.update({f"count_{k}": v.clone() for k, v in method.stats().items()})
    for i, p in enumerate(model.parameters()):  # the physics and (hybrids) the network
        state[f"param{i}"] = p.detach().clone()
    return state, answers


@pytest.mark.parametrize(
    ("name", "text"),
    [
        ("mm", "bayes"),
        ("mm", "bayes:huber=0:gate=0:adapt=0:calibrate=0"),
        ("mm", "bayes:noise_well_test=0.01:params=c_d+kappa:drift=4"),
        ("hem", "bayes"),
        ("ham", "bayes"),
        ("ham", "bayes:params=kappa+head.bias:drift=2"),
    ],
)
def test_bayes_kernel_matches_the_torch_filter(
    monkeypatch: pytest.MonkeyPatch, field: Batch, name: str, text: str
) -> None:
    fast, fast_answers = _bayes_run(monkeypatch, "1", field, text, name)
    slow, slow_answers = _bayes_run(monkeypatch, "0", field, text, name)
    if text == "bayes" and name == "mm":  # every path was taken
        for key in ("count_refused", "count_resets", "count_downweighted"):
            assert int(slow[key].sum()) > 0, key
    assert int(slow["count_updates"].min()) > 20
    for key, value in slow.items():
        if value.dtype in (torch.bool, torch.int64):
            assert torch.equal(fast[key], value), key
        else:
            scale = float(value.abs().max())  # (0 for the calibration when it is off)
            assert torch.allclose(fast[key], value, rtol=0, atol=1e-10 * scale), key
    for a, b in zip(fast_answers, slow_answers, strict=True):
        if a.dtype == torch.bool:
            assert torch.equal(a, b)
        else:
            assert torch.allclose(a, b, rtol=1e-10, atol=0, equal_nan=True)


def test_bayes_kernel_only_where_it_applies(field: Batch) -> None:
    for text, model in [
        # (effects that multiply the rate, real gas, slip and the critical ratio are
        # compiled: tests/test_effect_kernels.py; the critical ratio beside real gas is not)
        ("bayes", make_model("mm", field.wells, effects=["critical_ratio", "real_gas"])),
        ("bayes:iterations=2", make_model("mm", field.wells)),
        ("bayes", make_model("hem", field.wells, effects=["real_gas", "critical_ratio"])),
        ("bayes", make_model("nn", field.wells)),
        ("bayes", make_model("ham", field.wells, hidden=(8, 8))),
    ]:
        method = parse_method(text)
        method.bind(model, train=DEFAULT_TRAIN["mm"], online=DEFAULT_ONLINE["mm"])
        assert not method.compiled, text
    plain = parse_method("bayes")
    plain.bind(
        make_model("mm", field.wells), train=DEFAULT_TRAIN["mm"], online=DEFAULT_ONLINE["mm"]
    )
    assert plain.compiled


@pytest.mark.parametrize("name", ["mm", "hem", "ham"])
def test_compiled_prediction_is_the_models_rate(
    monkeypatch: pytest.MonkeyPatch, field: Batch, name: str
) -> None:
    """The compiled rate (what every learning method predicts with) against the model's
    predict_batch and forward (torch), on every row, with a well not set up (NaN), the
    parameters away from the prior and, for the hybrids, a network that is not zero."""
    model = make_model(name, field.wells)
    model.setup(field.select(field.mask & torch.tensor([True, True, False]).unsqueeze(1)))
    gen = torch.Generator().manual_seed(3)
    with torch.no_grad():
        z = model.phys.z  # type: ignore[attr-defined]
        z.copy_(torch.linspace(-0.8, 0.8, z.numel(), dtype=DTYPE).reshape(z.shape))
        if model.net is not None:  # type: ignore[attr-defined]
            for p in model.net.parameters():  # type: ignore[attr-defined]
                p.copy_(0.05 * torch.randn(p.shape, generator=gen, dtype=DTYPE))
    assert mm_online_applies(model) or hybrid_applies(model)  # the compiled rate runs
    fast = predict_rates(model, field)
    monkeypatch.setenv("VFM_KERNELS", "0")
    slow = predict_rates(model, field)
    with torch.no_grad():
        plain = model.forward_batch(field)
    assert bool(torch.isnan(fast[2]).all()) and bool(torch.isfinite(fast[:2]).all())
    # (hem adds the network's output to the physics: a sum, rounded as such)
    tol = 1e-13 * float(fast[:2].abs().max())
    assert torch.allclose(fast, slow, rtol=1e-13, atol=tol, equal_nan=True)
    assert torch.allclose(fast[:2], plain[:2], rtol=1e-13, atol=tol)
    if model.net is not None:  # type: ignore[attr-defined]
        # the network is in the compiled rate: without it the rates differ
        monkeypatch.setenv("VFM_KERNELS", "1")
        with torch.no_grad():
            for p in model.net.parameters():  # type: ignore[attr-defined]
                p.zero_()
        assert not torch.allclose(fast[:2], predict_rates(model, field)[:2], rtol=1e-3)


def test_compiled_rates_only_where_they_apply() -> None:
    wells = ["A", "B"]
    assert hybrid_applies(make_model("hem", wells)) and hybrid_applies(make_model("ham", wells))
    assert not hybrid_applies(make_model("ham", wells, effects=["erosion"]))
    assert not hybrid_applies(make_model("mm", wells))
    assert not hybrid_applies(make_model("nn", wells))


def test_bayes_intervals_compiled_for_a_hybrid(
    monkeypatch: pytest.MonkeyPatch, field: Batch
) -> None:
    """``ham`` with ``bayes`` (its update stays in torch): the compiled spread gives the
    torch path's sd and 90 % bounds, NaN where a well has no filter state yet."""
    rank = torch.cumsum(field.mask.long(), 1)
    history = field.select((rank <= 150) & torch.tensor([True, True, False]).unsqueeze(1))
    model = make_model("nn", history.wells)
    method = parse_method("bayes")
    train = replace(DEFAULT_TRAIN["nn"], max_iter=60, early_stopping=False)
    method.bind(model, train=train, online=DEFAULT_ONLINE["nn"])
    method.fit(history)
    method.start(int(history.time_ns[history.mask].max()))
    assert not method.compiled  # its update is torch's
    for k in range(151, 161):
        method.on_measurement(
            field.select((rank == k) & torch.tensor([True, True, False]).unsqueeze(1))
        )
    later = field.select((rank > 170) & (rank <= 180))
    fast = method.predict(later)
    monkeypatch.setenv("VFM_KERNELS", "0")
    slow = method.predict(later)
    assert fast.std is not None and slow.std is not None
    assert bool(torch.isnan(fast.std[2]).all()) and bool(torch.isfinite(fast.std[:2]).all())
    assert bool((fast.std[:2] > 0).all())
    for a, b in zip(fast, slow, strict=True):
        assert torch.allclose(a, b, rtol=1e-12, atol=0, equal_nan=True)


def test_the_arrays_kept_for_the_steps_follow_their_tensors() -> None:
    """The numpy views and the prior layout the compiled steps keep between calls are
    given anew when a buffer is replaced or the priors change in place (a stale view
    would step with old scales or priors)."""
    from vfm_core.learning.kernels import buffer_views, physics_layout

    model = make_model("ham", ["a", "b"])
    first = buffer_views(model, ("a_max", "y_scale"))
    assert buffer_views(model, ("a_max", "y_scale")) is first  # kept
    with torch.no_grad():
        model.y_scale.mul_(3.0)  # in place: the view shows it
    assert np.allclose(first[1], 3.0)
    model.y_scale = torch.full((2,), 7.0, dtype=DTYPE)  # a new tensor: a new view
    again = buffer_views(model, ("a_max", "y_scale"))
    assert again is not first and np.allclose(again[1], 7.0)
    layout = physics_layout(model)
    assert physics_layout(model) is layout
    with torch.no_grad():
        model.phys.mu.add_(1.0)
    moved = physics_layout(model)
    assert np.allclose(moved[1][:5], layout[1][:5] + 1.0)


# -- fit_batch's training steps, compiled (kernels.FitSteps) --------------------------------
def _fit_twice(
    monkeypatch: pytest.MonkeyPatch, name: str, flag: str, history: Batch, later: Batch
) -> tuple[dict[str, torch.Tensor], list[list[int]], int]:
    """An initial fit (early stopping, then pass 2), a retrain on mini-batches with given
    counts, and a retrain on a batch that fits in one (the convergence stop): the
    parameters, the counts run, and how many times the compiled steps ran."""
    from vfm_core.learning import kernels
    from vfm_core.learning.training import fit_batch

    monkeypatch.setenv("VFM_FIT_KERNEL", flag)
    calls = []
    for cls in (kernels.FitSteps, kernels.MtlFitSteps):
        monkeypatch.setattr(
            cls, "run", lambda self, *a, _run=cls.run: calls.append(1) or _run(self, *a)
        )
    model = make_model(name, history.wells)
    settings = replace(DEFAULT_TRAIN[name], batch_size=64)
    counts = [fit_batch(model, history, settings)["iterations"].tolist()]
    given = torch.tensor([120, 30, 90])
    counts.append(fit_batch(model, later, settings, iterations=given)["iterations"].tolist())
    # the whole batch at every step; a tolerance that stops some wells' retrains early
    small = replace(settings, batch_size=1000, retrain_tol=0.2)
    counts.append(fit_batch(model, later, small, iterations=given)["iterations"].tolist())
    state = {k: v.detach().clone() for k, v in model.state_dict().items()}
    return state, counts, len(calls)


@pytest.mark.parametrize("name", ["mm", "hem", "ham", "nn", "lr", "mtl"])
def test_compiled_training_steps_match_the_torch_loop(
    monkeypatch: pytest.MonkeyPatch, stream: tuple[Batch, list[Batch]], name: str
) -> None:
    history, _ = stream
    rank = torch.cumsum(history.mask.long(), 1)
    first = history.select(rank <= 80)
    torch_state, torch_counts, torch_calls = _fit_twice(monkeypatch, name, "0", first, history)
    state, counts, calls = _fit_twice(monkeypatch, name, "1", first, history)
    assert torch_calls == 0 and calls == 3  # the kernel ran every pass 2 here, torch none
    assert counts == torch_counts
    # the convergence stop ended some well's retrain before its given count
    assert any(c < g for c, g in zip(counts[2], [120, 30, 90], strict=True))
    for key, value in torch_state.items():
        torch.testing.assert_close(state[key], value, rtol=1e-9, atol=1e-12, msg=key)
    # and the parameters moved: the retrains learned something
    fresh = dict(make_model(name, history.wells).named_parameters())
    assert fresh and all(not torch.equal(p.detach(), state[k]) for k, p in fresh.items())


def test_compiled_training_steps_only_where_they_apply(
    monkeypatch: pytest.MonkeyPatch, stream: tuple[Batch, list[Batch]]
) -> None:
    from vfm_core.learning import kernels
    from vfm_core.learning.training import fit_batch

    history, _ = stream
    calls = []
    for cls in (kernels.FitSteps, kernels.MtlFitSteps):
        monkeypatch.setattr(
            cls, "run", lambda self, *a, _run=cls.run: calls.append(1) or _run(self, *a)
        )
    short = replace(DEFAULT_TRAIN["nn"], max_iter=5, early_stopping=False)
    fit_batch(make_model("nn", history.wells, hidden=(8,)), history, short)  # one layer: torch
    fit_batch(make_model("mtl", history.wells, blocks=1), history, short)  # one block: torch
    # the critical ratio beside real gas has no compiled form (test_effect_kernels.py: the
    # effects that have one)
    both = make_model("mm", history.wells, effects=["critical_ratio", "real_gas"])
    assert kernels.fit_parameters(both) is None
    assert calls == []
    monkeypatch.setenv("VFM_KERNELS", "0")
    fit_batch(make_model("mm", history.wells), history, replace(short, lr=1e-2))
    assert calls == []


@pytest.mark.parametrize("name", ["nn", "lr"])
def test_compiled_sgd_online_steps_match_the_torch_steps(
    monkeypatch: pytest.MonkeyPatch, stream: tuple[Batch, list[Batch]], name: str
) -> None:
    """``nn`` and ``lr`` with ``ol``'s SGD (their default): 60 updates, a well without a
    measurement every third time, compiled and in torch, end at the same parameters."""
    history, columns = stream
    states = {}
    for kernels in ("0", "1"):
        monkeypatch.setenv("VFM_KERNELS", kernels)
        model = make_model(name, history.wells)
        method = parse_method("ol")
        train = replace(DEFAULT_TRAIN[name], max_iter=60, early_stopping=False)
        method.bind(model, train=train, online=DEFAULT_ONLINE[name])
        method.fit(history)
        method.start(int(history.time_ns[history.mask].max()))
        before = {k: v.clone() for k, v in model.state_dict().items()}
        for i, col in enumerate(columns):
            if i % 3 == 1:  # the middle well has no measurement this time: it stays
                col = col.select(col.mask & torch.tensor([True, False, True]).unsqueeze(1))
            method.on_measurement(col)
        assert method._nn is (kernels == "1")
        states[kernels] = (before, {k: v.clone() for k, v in model.state_dict().items()})
    (before, slow), (_, fast) = states["0"], states["1"]
    for key, value in slow.items():
        torch.testing.assert_close(fast[key], value, rtol=1e-9, atol=1e-12, msg=key)
    last = "net.biases.2" if name == "nn" else "b"
    assert not torch.equal(slow[last], before[last])  # it learned


def test_compiled_mtl_online_steps_match_the_torch_steps(
    monkeypatch: pytest.MonkeyPatch, stream: tuple[Batch, list[Batch]]
) -> None:
    """``mtl`` with ``ol``'s Adam (its default): 60 updates, a well without a measurement
    every third time (its task vector held, its moments moving), compiled and in torch,
    end at the same parameters, Adam moments and step counts."""
    history, columns = stream
    states = {}
    for kernels in ("0", "1"):
        monkeypatch.setenv("VFM_KERNELS", kernels)
        model = make_model("mtl", history.wells)
        method = parse_method("ol")
        train = replace(DEFAULT_TRAIN["mtl"], max_iter=60, early_stopping=False)
        method.bind(model, train=train, online=DEFAULT_ONLINE["mtl"])
        method.fit(history)
        method.start(int(history.time_ns[history.mask].max()))
        before = {k: v.clone() for k, v in model.state_dict().items()}
        held = []
        for i, col in enumerate(columns):
            if i % 3 == 1:  # the middle well has no measurement this time: it stays
                col = col.select(col.mask & torch.tensor([True, False, True]).unsqueeze(1))
                beta = model.beta.detach()[1].clone()
                method.on_measurement(col)
                held.append(torch.equal(model.beta.detach()[1], beta))
            else:
                method.on_measurement(col)
        assert method._mtl is (kernels == "1") and all(held)
        optimizer = method.state_dict()["optimizer"]["state"]
        states[kernels] = (before, {k: v.clone() for k, v in model.state_dict().items()}, optimizer)
    (before, slow, slow_opt), (_, fast, fast_opt) = states["0"], states["1"]
    for key, value in slow.items():
        torch.testing.assert_close(fast[key], value, rtol=1e-9, atol=1e-12, msg=key)
    for i, st in slow_opt.items():
        assert float(fast_opt[i]["step"]) == float(st["step"]) == 60 * DEFAULT_ONLINE["mtl"].steps
        for name in ("exp_avg", "exp_avg_sq"):
            torch.testing.assert_close(fast_opt[i][name], st[name], rtol=1e-9, atol=1e-15)
    assert not torch.equal(slow["w_out"], before["w_out"])  # it learned


def test_a_training_kernel_that_cannot_compile_leaves_the_torch_loop(
    monkeypatch: pytest.MonkeyPatch,
    stream: tuple[Batch, list[Batch]],
    caplog: pytest.LogCaptureFixture,
) -> None:
    """The training loops' kernels compile on first use; one that fails is logged once and
    its models train in torch (here ``nn``), the others keep theirs."""
    from vfm_core.learning import _mm_numba, kernels
    from vfm_core.learning.training import fit_batch

    def broken() -> None:
        raise RuntimeError("no compiler here")

    monkeypatch.setattr(kernels, "_LAZY", {})
    monkeypatch.setattr(_mm_numba, "warm_nn_fit_steps", broken)
    history, _ = stream
    model = make_model("nn", history.wells)
    with caplog.at_level("WARNING", logger=kernels.__name__):
        assert kernels.fit_parameters(model) is None
        assert kernels.fit_parameters(model) is None  # asked again: not compiled again
    assert sum("nn_fit_steps is off" in r.getMessage() for r in caplog.records) == 1
    short = replace(DEFAULT_TRAIN["nn"], max_iter=5, early_stopping=False)
    before = model.net.biases[2].detach().clone()
    fit_batch(model, history, short)  # the torch loop
    assert not torch.equal(model.net.biases[2].detach(), before)
    assert kernels.fit_parameters(make_model("mm", history.wells)) is not None


@pytest.mark.parametrize("name", ["mm", "mtl"])
def test_a_whole_batch_fit_with_early_stopping(
    monkeypatch: pytest.MonkeyPatch, stream: tuple[Batch, list[Batch]], name: str
) -> None:
    """``batch_size = 0`` (every step on the whole batch) with early stopping: the sampler
    draws nothing, so nothing is rewound after the search (a KeyError before), and the
    compiled loops choose what torch's choose."""
    from vfm_core.learning.training import fit_batch

    history, _ = stream
    settings = replace(DEFAULT_TRAIN[name], batch_size=0, max_iter=40)
    results = {}
    for flag in ("0", "1"):
        monkeypatch.setenv("VFM_FIT_KERNEL", flag)
        model = make_model(name, history.wells)
        counts = fit_batch(model, history, settings)["iterations"].tolist()
        results[flag] = (counts, {k: v.clone() for k, v in model.state_dict().items()})
    assert results["0"][0] == results["1"][0] and max(results["1"][0]) > 0
    for key, value in results["0"][1].items():
        torch.testing.assert_close(results["1"][1][key], value, rtol=1e-9, atol=1e-12, msg=key)
