"""Compiled steps of the plain Sachdeva model (``mm`` without effects), with numba.

An ``ol`` update of ``mm`` is E optimiser steps, each the closed-form gradient of the MAP
objective (:class:`vfm_core.learning.training.MapObjective` with
:meth:`vfm_core.models.Mechanistic.rate_vjp`), the per-well gradient clip, one Adam (or
SGD) step and the projection into the priors' bounds. In torch that is some 245 tensor
operations per step on tensors of a few numbers, each a microsecond or two of dispatch:
4 ms for one well's update, while the arithmetic is a few hundred floating-point
operations. The same holds for a ``bayes`` update (an extended Kalman step on six
parameters) and for a prediction. The compiled functions
(:mod:`vfm_core.learning._mm_numba`, numba, compiled once and cached on disk) run the same
arithmetic, in the same order, as one loop over wells and samples:

- :func:`mm_online_steps`: ``ol``'s E steps (``OnlineLearning`` and the service's
  ``learn_many``);
- :func:`predict_rates`: the rate every learning method predicts with;
- ``bayes`` and ``bayes_spread``: ``BayesianFilter``'s update and prediction (see
  :attr:`vfm_core.learning.bayes.BayesianFilter.compiled`);
- :class:`FitSteps`: the training steps of :func:`vfm_core.learning.training.fit_batch`'s
  second pass (the initial fit and every ``pbl`` retrain) for the plain ``mm``, the
  plain hybrids and ``nn`` with two hidden layers (its products in BLAS through
  ``np.dot``, the rest fused), each well for its own count, with the convergence stop of a retrain on
  the whole batch; :class:`MtlFitSteps`: the same for ``mtl`` with two residual blocks, whose
  shared network steps the whole field together (one count, one early-stopping and one
  convergence decision for the field). ``mm``, ``hem`` and ``ham`` with compiled effects
  (below) train there too (``effect_fit_steps``, ``hybrid_effect_fit_steps``: the fit's
  step with the effects' gradient of the online kernels, each mini-batch's times, well
  tests and feature columns beside its rows). ``VFM_FIT_KERNEL=0`` turns these off alone
  (a comparison side by side: ``benchmarks/bench_study.py --fit-kernel 0,1``).

Effects that multiply the rate (their ``area_factor`` or ``output_factor``: erosion,
erosion_time, valve, the valve families, mpfm_bias; :meth:`vfm_core.effects.Effect.compiled_factor`)
run on the same kernels: a compiled per-effect function
(:func:`vfm_core.learning._mm_numba.effect_factor`) gives each sample's rate factor F and
dF / d(effect parameters), the rate is the plain one times F, and the effects' parameters
step, filter and clip beside the mechanistic ones (:func:`effect_online_steps`,
:func:`effect_rates` for ``mm``; :func:`hybrid_online_steps`, :func:`hybrid_rates` and
the filter for ``hem`` and ``ham``; :class:`FitSteps` for the batch fit of all three).
The library's two effects that change the flux itself (real_gas: Papay's Z in the gas
density; slip: the flux times a power of Simpson's slip multiplier) run there too, one
of each per model: the kernels compute that flux and
its derivatives in closed form (:func:`vfm_core.learning._mm_numba.flux_rate_grad`,
through Z to M_gas and through both fluxes of the slip factor), and their factor in F is 1.
``suggest`` (the generic correction ``vfm diagnose`` proposes: linear, log-linear or
seasonal in one driver, learned or fixed) runs there as a rate factor too: the effect
computes its per-sample columns with its hook's arithmetic in numpy (the step
(x - x0) / scale, or the season's sin and cos, or the whole fixed factor:
``Suggest.compiled_columns``, appended to the batch's features by :func:`_fx`) and the
kernel's factor and dF / dk follow the form. ``critical_ratio`` runs there as well: the
kernels solve Sachdeva's ratio y_c per sample by the torch hook's bisection and compute the
flux at p_cr + weight (y_c - p_cr); like the hook, no gradient flows through y_c
(:func:`vfm_core.learning._mm_numba._rate_at`). Not beside real gas (torch then).
``tests/test_effect_kernels.py`` compares them with the torch path and with autograd.

It is the same algorithm, not a new one: ``tests/test_kernels.py`` checks each against
the torch path (parameters, optimiser and filter states to 1e-10 or better after many
updates, predictions to 1e-13, the gradient against autograd). Anything else (a user's
effect without a compiled form, two effects of one flux kind, the critical ratio beside
real gas; another optimiser or a schedule, ``bayes:iterations=2``) runs the torch path.

``VFM_KERNELS=0`` in the environment turns the kernels off (the torch path then runs), for
a comparison side by side or where numba cannot compile.
"""

from __future__ import annotations

import logging
import os
import threading
from collections.abc import Sequence
from types import SimpleNamespace
from typing import Any

import numpy as np
import torch

logger = logging.getLogger(__name__)

__all__ = [
    "kernels_enabled",
    "compiled",
    "compiled_effects",
    "effect_arguments",
    "effect_bounds",
    "effect_online_steps",
    "effect_parameters",
    "effect_rates",
    "effects_applies",
    "FitSteps",
    "MtlFitSteps",
    "fit_parameters",
    "sgd_online_steps",
    "mtl_online_steps",
    "mtl_parameters",
    "plain_mtl",
    "plain_lr",
    "plain_nn",
    "hybrid_applies",
    "hybrid_effects_applies",
    "hybrid_online_steps",
    "hybrid_parameters",
    "hybrid_rates",
    "mm_online_applies",
    "mm_online_steps",
    "mm_rates",
    "physics_layout",
    "plain_hybrid",
    "plain_mm",
    "predict_rates",
    "warm",
    "writable",
]

#: the order of the parameters in ``PhysicalParameters.z`` of ``mm`` (PHYSICAL_NAMES)
_NAMES = ("rho_oil", "rho_wat", "kappa", "m_gas", "p_cr", "c_d")
_SIX = np.arange(6)
_FIVE = np.array([0, 1, 2, 3, 4, -1])
#: CompiledFactor.SUGGEST: an effect whose columns the model computes (``compiled_columns``)
_SUGGEST = 7

#: the compiled functions (``online``, ``rates``, ``bayes``, ``bayes_spread``), once built
_KERNEL: SimpleNamespace | None = None
_FAILED: str | None = None
_LOCK = threading.Lock()  # one compilation, whichever thread asks first


def kernels_enabled() -> bool:
    """False when ``VFM_KERNELS=0`` or numba is missing or could not compile the kernel."""
    return os.environ.get("VFM_KERNELS", "1") != "0" and _kernel() is not None


def _kernel() -> SimpleNamespace | None:
    global _KERNEL, _FAILED
    if _KERNEL is None and _FAILED is None:
        with _LOCK:
            if _KERNEL is None and _FAILED is None:
                try:
                    _KERNEL = _build()
                except Exception as exc:  # pragma: no cover - numba missing or broken here
                    _FAILED = f"{type(exc).__name__}: {exc}"
                    logger.warning(
                        "The compiled mm kernels are off (%s); the torch path runs instead.",
                        _FAILED,
                    )
    return _KERNEL


#: the training loops' kernels, compiled on first use: name -> function, or None (failed)
_LAZY: dict[str, Any] = {}


def _lazy(name: str) -> Any:
    """The kernel ``name`` of :mod:`vfm_core.learning._mm_numba`, compiled (or loaded from
    numba's cache) the first time a model asks for it, on a made-up sample; None when the
    kernels are off or it cannot compile (the torch path runs). The training loops' kernels
    take 1-7 s each to compile the first time, so a process compiles only those of the
    models it trains, and a service start-up (:func:`warm`) none of them."""
    if not kernels_enabled():
        return None
    if name not in _LAZY:
        with _LOCK:
            if name not in _LAZY:
                from vfm_core.learning import _mm_numba as k

                try:
                    getattr(k, f"warm_{name}")()
                    _LAZY[name] = getattr(k, name)
                except Exception as exc:  # pragma: no cover - numba broken here
                    logger.warning(
                        "The compiled %s is off (%s: %s); the torch path runs instead.",
                        name,
                        type(exc).__name__,
                        exc,
                    )
                    _LAZY[name] = None
    return _LAZY[name]


def compiled() -> SimpleNamespace | None:
    """The compiled functions (``online``, ``rates``, ``bayes``, ``bayes_spread`` of
    :mod:`vfm_core.learning._mm_numba`), or None when the kernels are off."""
    return _kernel() if kernels_enabled() else None


def warm() -> bool:
    """Compile (or load from numba's cache) the kernels now, so that a service's first
    measurement does not wait for them (about 4.5 s the first time on this machine, 0.4 s
    from the cache). The training loops' kernels are not among them: they compile on a
    model's first fit (:func:`_lazy`). Returns whether the kernels are enabled."""
    return kernels_enabled()


def mm_online_applies(model: Any) -> bool:
    """True when :func:`mm_online_steps` computes ``model``'s online steps: exactly the
    plain ``mm`` (no effects, no subclass), in float64, and the kernel is enabled (``mm``
    with compiled effects: :func:`effects_applies`)."""
    return plain_mm(model) and kernels_enabled()


def plain_mm(model: Any) -> bool:
    """True for exactly the plain ``mm`` (:meth:`~vfm_core.models.base.ChokeModel.compiled_as`
    says so): what the kernels compute (whether they are enabled or not)."""
    from vfm_core.models.physical import PHYSICAL_NAMES

    return model.compiled_as() == "mm" and PHYSICAL_NAMES == _NAMES


def mm_online_steps(
    model: Any,
    batch: Any,
    moments: tuple[torch.Tensor, torch.Tensor] | tuple[np.ndarray, np.ndarray] | None,
    counts: np.ndarray,
    hold: np.ndarray,
    *,
    steps: int,
    noise: float,
    lr: float,
    betas: tuple[float, float],
    eps: float,
    max_norm: float,
) -> None:
    """E steps of ``ol`` on ``model`` (``mm``, see :func:`mm_online_applies`) and ``batch``,
    in place: ``model.phys.z`` [W, 6]; with Adam (``moments`` its exp_avg and exp_avg_sq
    [W, 6]) the moments, and ``counts`` [W] (each well's step count before, as floats) is
    advanced by ``steps``; ``moments`` None is SGD. A well in ``hold`` [W] keeps its
    parameters (its moments still move, as torch's optimiser moves them), as
    ``OnlineLearning`` holds wells without a new measurement."""
    kernel = _kernel()
    assert kernel is not None
    z_t = model.phys.z
    with torch.no_grad():
        z = _in_place(z_t)
        if moments is None:
            m = np.zeros_like(z)
            v = np.zeros_like(z)
        else:
            m = _in_place(moments[0])
            v = _in_place(moments[1])
        kernel.online(
            z,
            m,
            v,
            counts,
            hold,
            np.ascontiguousarray(batch.x.numpy()),
            np.ascontiguousarray(batch.y.numpy()),
            np.ascontiguousarray(batch.mask.numpy()),
            *buffer_views(model, _SCALES[:2]),
            *buffer_views(model.phys, ("mu", "sigma", *_BOUNDS)),
            float(noise),
            float(lr),
            float(betas[0]),
            float(betas[1]),
            float(eps),
            float(max_norm),
            int(steps),
            moments is not None,
        )
        _written_back([z_t] + ([] if moments is None else list(moments)), [z, m, v])


def predict_rates(model: Any, batch: Any) -> torch.Tensor:
    """``model.predict_batch(batch)``: compiled for the plain ``mm``
    (:func:`mm_online_applies`) and the plain hybrids (:func:`hybrid_applies`), the model's
    own otherwise."""
    if mm_online_applies(model):
        q = mm_rates(model, batch)
    elif hybrid_applies(model) or hybrid_effects_applies(model):
        q = hybrid_rates(model, batch)
    elif effects_applies(model):
        q = effect_rates(model, batch)
    else:
        return model.predict_batch(batch)  # type: ignore[no-any-return]
    return torch.where(model.ready.unsqueeze(1), q, torch.full_like(q, float("nan")))


def hybrid_applies(model: Any) -> bool:
    """True when :func:`hybrid_rates` computes ``model``'s rate: :func:`plain_hybrid` and
    the kernels enabled."""
    return plain_hybrid(model) and kernels_enabled()


def plain_hybrid(model: Any) -> bool:
    """True for exactly ``hem`` or ``ham`` in the kernels' shape (the model's
    :meth:`~vfm_core.models.base.ChokeModel.compiled_as` says so): what the kernels compute."""
    return model.compiled_as() in ("hem", "ham")


def hybrid_parameters(model: Any) -> list[torch.nn.Parameter]:
    """The parameters :func:`hybrid_online_steps` steps, in its order: z, W1, b1, W2, b2,
    then each effect's z (a hybrid with compiled effects, :func:`hybrid_effects_applies`)."""
    net = model.net
    own = [model.phys.z, net.weights[0], net.biases[0], net.weights[1], net.biases[1]]
    return own + effect_parameters(model)[1:]


def hybrid_effects_applies(model: Any) -> bool:
    """True when :func:`hybrid_online_steps` and :func:`hybrid_rates` compute ``hem`` or
    ``ham`` with its effects (every one with a compiled form), the kernels enabled."""
    return compiled_effects(model) in ("hem", "ham") and kernels_enabled()


def hybrid_online_steps(
    model: Any,
    batch: Any,
    moments: list[tuple[torch.Tensor, torch.Tensor]] | list[tuple[np.ndarray, np.ndarray]] | None,
    counts: np.ndarray,
    hold: np.ndarray,
    *,
    steps: int,
    noise: float,
    lr: float,
    betas: tuple[float, float],
    eps: float,
    max_norm: float,
    params: list[torch.nn.Parameter] | None = None,
) -> None:
    """E steps of ``ol`` on ``hem`` or ``ham`` (see :func:`hybrid_applies`) and ``batch``,
    in place, as :func:`mm_online_steps`: the parameters of :func:`hybrid_parameters`;
    with Adam their moments (``moments``, one (exp_avg, exp_avg_sq) pair per parameter in
    that order) and ``counts`` [5, W] (each parameter's step count per well, as floats),
    advanced by ``steps``; ``moments`` None is SGD. Wells in ``hold`` keep their
    parameters. ``params``: :func:`hybrid_parameters` of the model, when the caller has
    them (the lookup costs more than the step). The moments are updated in place."""
    kernel = _kernel()
    assert kernel is not None
    params = hybrid_parameters(model) if params is None else params
    pos, mu, sigma = physics_layout(model)
    a_max, y_scale, x_mean, x_std = buffer_views(model, _SCALES)
    kind = compiled_effects(model) or model.compiled_as()
    with torch.no_grad():
        values = [_in_place(p) for p in params]
        if moments is None:
            state = [np.zeros_like(v) for v in values for _ in range(2)]
        else:  # (optimiser state, in no graph: written in place)
            state = [_in_place(t) for pair in moments for t in pair]
        eff = values[5:]
        own = list(zip(state[10::2], state[11::2], strict=True)) if moments is not None else None
        effects = _effect_state(model, eff, own, 5)
        kernel.hybrid_online(
            2 if kind == "ham" else 1,
            *values[:5],
            *state[:10],
            counts,
            hold,
            np.ascontiguousarray(batch.x.numpy()),
            np.ascontiguousarray(batch.y.numpy()),
            np.ascontiguousarray(batch.mask.numpy()),
            a_max,
            y_scale,
            pos,
            mu,
            sigma,
            x_mean,
            x_std,
            *buffer_views(model.phys, _BOUNDS),
            float(noise),
            float(lr),
            float(betas[0]),
            float(betas[1]),
            float(eps),
            float(max_norm),
            int(steps),
            moments is not None,
            effects,
            _fx(model, batch),
        )
        _effect_state_back(eff, own, effects)
        _written_back(
            [*params, *(t for pair in moments or [] for t in pair)],
            values + (state if moments is not None else []),
        )


def fit_parameters(model: Any) -> list[torch.nn.Parameter] | None:
    """The parameters :func:`fit_steps` trains, in its order (z; then W1, b1, W2, b2 of a
    hybrid; then each effect's z of a model with compiled effects), when it computes
    ``model``'s training steps (the plain ``mm`` or a plain hybrid, either with compiled
    effects (:func:`effects_applies`, :func:`hybrid_effects_applies`), the plain ``nn`` or
    ``lr``, the kernels enabled); else None."""
    if mm_online_applies(model) and _lazy("fit_steps") is not None:
        return [model.phys.z]
    if effects_applies(model) and _lazy("effect_fit_steps") is not None:
        return effect_parameters(model)
    if hybrid_effects_applies(model) and _lazy("hybrid_effect_fit_steps") is not None:
        return hybrid_parameters(model)
    if hybrid_applies(model) and _lazy("fit_steps") is not None:
        return hybrid_parameters(model)
    if plain_nn(model) and _lazy("nn_fit_steps") is not None:
        net = model.net
        return [t for pair in zip(net.weights, net.biases, strict=True) for t in pair]
    if plain_lr(model) and _lazy("lr_fit_steps") is not None:
        return [model.w, model.b]
    return None


def plain_lr(model: Any) -> bool:
    """True for exactly ``lr`` in float64 (the model's ``compiled_as``): what
    :func:`vfm_core.learning._mm_numba.lr_fit_steps` computes."""
    return model.compiled_as() == "lr"  # type: ignore[no-any-return]


def plain_nn(model: Any) -> bool:
    """True for exactly ``nn`` with two hidden layers, in float64 (the model's
    ``compiled_as``): what :func:`vfm_core.learning._mm_numba.nn_fit_steps` computes."""
    return model.compiled_as() == "nn"  # type: ignore[no-any-return]


def sgd_online_steps(
    model: Any, batch: Any, hold: np.ndarray, *, steps: int, lr: float, max_norm: float
) -> None:
    """E steps of ``ol`` with SGD on the plain ``nn`` (:func:`plain_nn`) or ``lr``
    (:func:`plain_lr`) and ``batch``, in place (``nn_fit_steps`` or ``lr_fit_steps`` of
    :mod:`vfm_core.learning._mm_numba` on the same batch each step): the gradient of the
    mean squared scaled error (``ol`` keeps the prior on physical parameters only: these
    models have none), the per-well clip, the SGD step. Wells in ``hold`` (no new
    measurement) keep their parameters: with SGD a well without data does not move."""
    params = fit_parameters(model)
    assert params is not None and len(params) in (2, 6)
    step = _lazy("nn_fit_steps" if len(params) == 6 else "lr_fit_steps")
    with torch.no_grad():
        values = [_in_place(p) for p in params]
        mask = batch.mask.numpy() & ~np.asarray(hold, dtype=bool)[:, None]
        n = mask.sum(1).astype(np.float64)
        todo = np.where(n > 0, int(steps), 0).astype(np.int64)
        moments = tuple(np.zeros_like(v) for v in values for _ in range(2))  # SGD: unused
        (y_scale,) = buffer_views(model, ("y_scale",))
        step(
            tuple(values), moments, np.zeros((len(values), len(n))), todo,
            np.ascontiguousarray(model.normalise(batch.x).numpy()),
            np.ascontiguousarray(batch.y.numpy()), np.ascontiguousarray(mask),
            int(mask.shape[1]), True, n, y_scale, 0.0, float(lr), 0.9, 0.999, 1e-8,
            float(max_norm), False, np.zeros(len(n)), False, np.zeros((1, 0, 6)),
            np.zeros((1, 0)), np.zeros((1, 0), dtype=bool), np.zeros((1, 1)),
            *(buffer_views(model, ("w_prec",)) if len(params) == 2 else ()),
        )  # fmt: skip
        _written_back(params, values)


def plain_mtl(model: Any) -> bool:
    """True for exactly ``mtl`` with two residual blocks, in float64 (the model's
    ``compiled_as``), the kernels enabled: what
    :func:`vfm_core.learning._mm_numba.mtl_online` computes."""
    return model.compiled_as() == "mtl" and _lazy("mtl_online") is not None


def mtl_parameters(model: Any) -> list[torch.nn.Parameter]:
    """The parameters of :func:`mtl_online_steps`, in its order (the model's own)."""
    return [
        model.beta, model.w_in, model.b_in, *model.w1, *model.b1, *model.w2, *model.b2,
        model.w_out, model.b_out,
    ]  # fmt: skip


def mtl_online_steps(
    model: Any,
    batch: Any,
    moments: list[tuple[np.ndarray, np.ndarray]],
    count: float,
    idle: np.ndarray,
    *,
    steps: int,
    lr: float,
    betas: tuple[float, float],
    eps: float,
    max_norm: float,
) -> None:
    """E steps of ``ol`` with Adam on ``mtl`` (:func:`plain_mtl`) and ``batch``, in place:
    the parameters of :func:`mtl_parameters`, ``moments`` their Adam moments (numpy views,
    updated in place), ``count`` their common step count before. Wells in ``idle`` keep
    their task vectors (see :func:`vfm_core.learning._mm_numba.mtl_online`)."""
    params = mtl_parameters(model)
    with torch.no_grad():
        values = [_in_place(p) for p in params]
        (y_scale,) = buffer_views(model, ("y_scale",))
        _lazy("mtl_online")(
            tuple(values),
            tuple(a for pair in moments for a in pair),
            np.array([float(count)]),
            np.ascontiguousarray(np.asarray(idle, dtype=bool)),
            np.ascontiguousarray(model.normalise(batch.x).numpy()),
            np.ascontiguousarray(batch.y.numpy()),
            np.ascontiguousarray(batch.mask.numpy()),
            y_scale,
            int(steps),
            float(betas[0]),
            float(betas[1]),
            float(eps),
            float(lr),
            float(max_norm),
        )
        _written_back(params, values)


def _optimiser_settings(opt: torch.optim.Optimizer) -> tuple[bool, tuple[float, ...]]:
    """Whether ``opt`` is Adam (else SGD), and its (lr, beta1, beta2, eps)."""
    group = opt.param_groups[0]
    return isinstance(opt, torch.optim.Adam), (
        float(group["lr"]),
        *(float(b) for b in group.get("betas", (0.9, 0.999))),
        float(group.get("eps", 1e-8)),
    )


def _early_stopping(  # noqa: PLR0913 - the pass's state
    sampler: Any,
    steps: int,
    chunk_size: int,
    has: np.ndarray,
    best_iter: np.ndarray,
    patience: int,
    run: Any,
) -> np.ndarray:
    """Early stopping's pass over compiled chunks: ``run(chunk)`` steps the kernel on the
    sampler's chunk and gives the held-out error after each step [W, taken]; a well with
    ``has`` keeps the step of its best error, and the pass ends once every such well has
    gone ``patience`` steps without a better one (the torch loop's rule, its 1e-12 margin).
    Returns ``best_iter`` updated; the sampler has taken exactly the steps the torch loop
    would have (the kernel's steps past the end are undone by the caller, which restores
    the parameters)."""
    best_loss = np.full(len(has), np.inf)
    since = np.zeros(len(has), dtype=np.int64)
    k = 0
    while k < steps:
        chunk = sampler.take(min(chunk_size, steps - k))
        taken = chunk[3]
        out = run(chunk)
        for i in range(taken):
            v = out[:, i]
            improved = has & (v < best_loss - 1e-12)
            best_loss = np.where(improved, v, best_loss)
            best_iter = np.where(improved, k + i + 1, best_iter)
            since = np.where(improved, 0, since + 1)
            if bool((since[has] >= patience).all()):
                sampler.taken -= taken - (i + 1)  # the steps past the stop
                return best_iter
        k += taken
    return best_iter


class FitSteps:
    """:func:`vfm_core.learning.training.fit_batch`'s training loops, compiled
    (:func:`vfm_core.learning._mm_numba.fit_steps`, ``effect_fit_steps``, ``nn_fit_steps``,
    ``hybrid_effect_fit_steps``, ``lr_fit_steps``) for the plain ``mm``, a plain hybrid,
    either with compiled effects, the plain ``nn`` or ``lr``: :meth:`run` (the second
    pass: each well its own number of steps) and :meth:`search` (the first: early stopping
    on the held-out slice), each with a fresh Adam (or SGD) of ``opt``'s settings, in
    place, on the sampler's mini-batches. The same arithmetic as the torch loops
    (``tests/test_kernels.py`` and ``tests/test_effect_kernels.py`` compare them), without
    a torch call per step."""

    #: steps per call while early stopping watches (the steps past its stop are wasted)
    SEARCH_CHUNK = 16

    def __init__(
        self, model: Any, params: list[torch.nn.Parameter], opt: torch.optim.Optimizer
    ) -> None:
        self.model, self.params = model, params
        self.adam, self.hyper = _optimiser_settings(opt)
        # mm or a hybrid with compiled effects: its own tensors, then each effect's z
        self.effects = effects_applies(model) or hybrid_effects_applies(model)
        self.own = 1 if effects_applies(model) else 5  # the model's own tensors
        self.network = len(params) == 6 and not self.effects  # nn: W1, b1, W2, b2, W3, b3
        self.linear = len(params) == 2 and not self.effects  # lr: w, b
        self.sampler: Any = None
        self.val_fx: tuple[np.ndarray, ...] | None = None
        self.full_fx: tuple[Any, tuple[np.ndarray, ...]] | None = None
        shape = compiled_effects(model) or model.compiled_as()
        self.kind = 0 if len(params) <= 2 or shape == "mm" else (2 if shape == "ham" else 1)
        self.n_w = int(params[0].shape[0])

    def _begin(self) -> None:
        """The arrays the kernel steps (the parameters' own memory) and a fresh optimiser."""
        n_w = self.n_w
        self.values = [_in_place(p) for p in self.params]
        if self.effects:  # the model's own; the effects' parameters side by side
            own = self.own
            self.values, self.eff = self.values[:own], self.values[own:]
            self.state = _effect_state(self.model, self.eff, None, own)
            self.moments = tuple(np.zeros_like(v) for v in self.values for _ in range(2))
            self.counts = np.zeros((len(self.params), n_w))
            return
        if len(self.params) == 1:  # mm, no network: empty arrays of its shapes
            self.values += [np.zeros((n_w, 6, 0)), np.zeros((n_w, 0)), np.zeros((n_w, 0, 1))]
            self.values += [np.zeros((n_w, 1))]
        self.moments = tuple(np.zeros_like(v) for v in self.values for _ in range(2))
        self.counts = np.zeros((len(self.values) if self.network or self.linear else 5, n_w))

    def _end(self) -> None:
        if self.effects:
            _effect_state_back(self.eff, None, self.state)
            _written_back(list(self.params), self.values + self.eff)
            return
        _written_back(list(self.params), self.values[: len(self.params)])

    def _chunk_fx(self, same: bool) -> tuple[np.ndarray, ...]:
        """The effects of the sampler's last chunk as the kernel reads them (:func:`_fx`;
        the whole batch's, once, when every step is on the whole batch)."""
        sampler = self.sampler
        if not same:
            return _fx(self.model, sampler.taken_batch())
        if self.full_fx is None or self.full_fx[0] is not sampler:
            self.full_fx = (sampler, _fx(self.model, sampler.batch))
        return self.full_fx[1]

    def _effect_steps(  # noqa: PLR0913 - one chunk's arrays
        self,
        data: tuple[Any, ...],
        todo: np.ndarray,
        n_full: np.ndarray,
        noise: float,
        max_norm: float,
        losses: np.ndarray,
        val: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None,
    ) -> None:
        """:meth:`_steps` on ``mm`` or a hybrid with compiled effects (``effect_fit_steps``,
        ``hybrid_effect_fit_steps``): ``data`` x, y, has, width, same."""
        model = self.model
        fx = self._chunk_fx(bool(data[4]))
        a_max, y_scale, x_mean, x_std = buffer_views(model, _SCALES)
        valid: tuple[Any, ...]
        if val is None:
            empty = (np.zeros((1, 0, 6)), np.zeros((1, 0)), np.zeros((1, 0), dtype=bool))
            valid = (False, *empty, fx, np.zeros((1, 1)))
        else:
            valid = (True, *val[:3], self.val_fx, val[3])
        rest = (float(noise), self.hyper, float(max_norm), self.adam, losses, self.state, fx, valid)
        bounds = buffer_views(model.phys, _BOUNDS)
        if self.own == 1:
            scales = (a_max, y_scale, *buffer_views(model.phys, ("mu", "sigma")), *bounds)
            _lazy("effect_fit_steps")(
                self.values[0], self.moments, self.counts, todo, data[:5], n_full, scales, *rest
            )
            return
        layout = (a_max, y_scale, *physics_layout(model), x_mean, x_std, *bounds)
        _lazy("hybrid_effect_fit_steps")(
            self.kind, tuple(self.values), self.moments, self.counts, todo, data[:5], n_full,
            layout, *rest,
        )  # fmt: skip

    def _inputs(self, x: torch.Tensor) -> np.ndarray:
        """The rows as the kernel reads them: normalised for ``nn``, in file units else."""
        normalised = self.network or self.linear
        return np.ascontiguousarray((self.model.normalise(x) if normalised else x).numpy())

    def _steps(  # noqa: PLR0913 - one chunk's arrays
        self,
        chunk: tuple[torch.Tensor, torch.Tensor, torch.Tensor, int, bool],
        todo: np.ndarray,
        n_full: np.ndarray,
        noise: float,
        max_norm: float,
        losses: np.ndarray,
        val: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None,
        size: int,
    ) -> None:
        model = self.model
        x, y, has, taken, same = chunk
        width = int(x.shape[1]) if same else int(size)
        lr, beta1, beta2, eps = self.hyper
        data = (
            self._inputs(x),
            np.ascontiguousarray(y.numpy()),
            np.ascontiguousarray(has.numpy()),
            width,
            bool(same),
            n_full,
        )
        empty = (np.zeros((1, 0, 6)), np.zeros((1, 0)), np.zeros((1, 0), dtype=bool))
        validation = (True, *val) if val is not None else (False, *empty, np.zeros((1, 1)))
        if self.effects:
            self._effect_steps(data, todo, n_full, noise, max_norm, losses, val)
            return
        steps = (noise, lr, beta1, beta2, eps, max_norm, self.adam, losses, *validation)
        if self.network or self.linear:
            (y_scale,) = buffer_views(model, ("y_scale",))
            step = _lazy("nn_fit_steps" if self.network else "lr_fit_steps")
            prior = () if self.network else buffer_views(model, ("w_prec",))  # lr's slopes
            step(
                tuple(self.values), self.moments, self.counts, todo, *data, y_scale, *steps, *prior
            )
            return
        a_max, y_scale, x_mean, x_std = buffer_views(model, _SCALES)
        pos, mu, sigma = physics_layout(model)
        z_low, z_high = buffer_views(model.phys, _BOUNDS)
        _lazy("fit_steps")(
            self.kind,
            *self.values,
            self.moments,
            self.counts,
            todo,
            *data,
            a_max,
            y_scale,
            pos,
            mu,
            sigma,
            x_mean,
            x_std,
            z_low,
            z_high,
            *steps,
        )

    def run(
        self,
        sampler: Any,
        iterations: torch.Tensor,
        noise: float,
        max_norm: float,
        converge: tuple[int, float, int] | None = None,
    ) -> torch.Tensor:
        """Step well w ``iterations[w]`` times (the sampler's draws, chunk by chunk); with
        ``converge`` (check, tol, patience: a retrain on the whole batch), a well also stops
        once the mean objective of ``check`` steps has not fallen below the best block's by
        the fraction ``tol``, ``patience`` blocks in a row, as the torch loop stops it.
        Returns the steps each well took."""
        want = iterations.clone()
        n_w = self.n_w
        self.sampler = sampler
        with torch.no_grad():
            self._begin()
            n_full = sampler.counts.to(torch.float64).numpy()
            losses = np.zeros(n_w)
            best_block = np.full(n_w, np.inf)
            stale = np.zeros(n_w, dtype=np.int64)
            total, done = int(want.max()) if n_w else 0, 0
            while done < total:
                limit = total - done if converge is None else min(converge[0], total - done)
                chunk = sampler.take(limit)
                taken = chunk[3]
                todo = (want.numpy() - done).clip(0, taken).astype(np.int64)
                losses[:] = 0.0
                self._steps(chunk, todo, n_full, noise, max_norm, losses, None, sampler.size)
                done += taken
                if converge is not None and done % converge[0] == 0 and done < total:
                    check, tol, patience = converge
                    mean = losses / check
                    improved = mean < best_block * (1.0 - tol)
                    best_block = np.minimum(best_block, mean)
                    stale = np.where(improved, 0, stale + 1)
                    stop = torch.from_numpy((stale >= patience) & (want.numpy() > done))
                    if bool(stop.any()):
                        want = torch.where(stop, torch.full_like(want, done), want)
                        total = int(want.max())
            self._end()
        return want

    def search(
        self,
        sampler: Any,
        val: Any,
        has_val: torch.Tensor,
        best_iter: torch.Tensor,
        steps: int,
        patience: int,
        noise: float,
        max_norm: float,
    ) -> torch.Tensor:
        """Early stopping's pass: every well steps on, up to ``steps``, and after each step
        its error on ``val`` (the held-out batch) is measured; a well with ``has_val`` keeps
        the step of its best error, and the pass ends once every such well has gone
        ``patience`` steps without a better one. Returns ``best_iter`` updated; the sampler
        has taken exactly the steps the torch loop would have (the kernel's steps past the
        end are undone by the caller, which restores the parameters)."""
        n_w = self.n_w
        val_arrays = (
            self._inputs(val.x),
            np.ascontiguousarray(val.y.numpy()),
            np.ascontiguousarray(val.mask.numpy()),
        )
        self.sampler = sampler
        self.val_fx = _fx(self.model, val) if self.effects else None
        with torch.no_grad():
            self._begin()
            n_full = sampler.counts.to(torch.float64).numpy()
            losses = np.zeros(n_w)

            def run(chunk: Any) -> np.ndarray:
                taken = chunk[3]
                out = np.zeros((n_w, taken))
                todo = np.full(n_w, taken, dtype=np.int64)
                val = (*val_arrays, out)
                self._steps(chunk, todo, n_full, noise, max_norm, losses, val, sampler.size)
                return out

            chosen = _early_stopping(
                sampler, steps, self.SEARCH_CHUNK, has_val.numpy(), best_iter.clone().numpy(),
                patience, run,
            )  # fmt: skip
            self._end()
        return torch.from_numpy(chosen)


class MtlFitSteps:
    """:func:`vfm_core.learning.training.fit_batch`'s training loops for the plain ``mtl``
    (:func:`plain_mtl`), compiled (:func:`vfm_core.learning._mm_numba.mtl_fit_steps`): the
    shared network steps every well together, so :meth:`run` runs one count for the field
    (with one convergence decision on the sum of the wells' objectives) and :meth:`search`
    one early-stopping decision on the sum of their held-out errors, as the torch loops do
    for a shared model. The same arithmetic (``tests/test_kernels.py``), its products in
    BLAS through ``np.dot``, without a torch call per step."""

    SEARCH_CHUNK = FitSteps.SEARCH_CHUNK

    def __init__(
        self, model: Any, params: list[torch.nn.Parameter], opt: torch.optim.Optimizer
    ) -> None:
        self.model, self.params = model, params
        self.adam, self.hyper = _optimiser_settings(opt)
        self.n_w = int(model.beta.shape[0])

    def _begin(self) -> None:
        self.values = [_in_place(p) for p in self.params]
        self.moments = tuple(np.zeros_like(v) for v in self.values for _ in range(2))
        self.count = np.zeros(1)

    def _end(self) -> None:
        _written_back(list(self.params), self.values)

    def _steps(  # noqa: PLR0913 - one chunk's arrays
        self,
        chunk: tuple[torch.Tensor, torch.Tensor, torch.Tensor, int, bool],
        n_full: np.ndarray,
        noise: float,
        max_norm: float,
        losses: np.ndarray,
        val: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None,
        size: int,
    ) -> None:
        model = self.model
        x, y, has, taken, same = chunk
        (y_scale,) = buffer_views(model, ("y_scale",))
        empty = (np.zeros((1, 0, 6)), np.zeros((1, 0)), np.zeros((1, 0), dtype=bool))
        validation = (
            (True, *val)
            if val is not None
            else (False, *empty, np.zeros(1, dtype=bool), np.zeros(1))
        )
        _lazy("mtl_fit_steps")(
            tuple(self.values),
            self.moments,
            self.count,
            int(taken),
            np.ascontiguousarray(model.normalise(x).numpy()),
            np.ascontiguousarray(y.numpy()),
            np.ascontiguousarray(has.numpy()),
            int(x.shape[1]) if same else int(size),
            bool(same),
            n_full,
            y_scale,
            len(model.wells),
            float(noise),
            self.hyper,
            float(max_norm),
            self.adam,
            losses,
            *validation,
        )

    def run(
        self,
        sampler: Any,
        iterations: torch.Tensor,
        noise: float,
        max_norm: float,
        converge: tuple[int, float, int] | None = None,
    ) -> torch.Tensor:
        """Step the field ``max(iterations)`` times (the sampler's draws, chunk by chunk);
        with ``converge`` (check, tol, patience: a retrain on the whole batch), stop once the
        summed mean objective of ``check`` steps has not fallen below the best block's by the
        fraction ``tol``, ``patience`` blocks in a row. Returns the steps taken, per well."""
        n_w = self.n_w
        total = int(iterations.max()) if n_w else 0
        with torch.no_grad():
            self._begin()
            n_full = sampler.counts.to(torch.float64).numpy()
            best_block, stale, done = np.inf, 0, 0
            while done < total:
                limit = total - done if converge is None else min(converge[0], total - done)
                chunk = sampler.take(limit)
                taken = chunk[3]
                losses = np.zeros((taken, n_w))
                self._steps(chunk, n_full, noise, max_norm, losses, None, sampler.size)
                done += taken
                if converge is not None and done % converge[0] == 0 and done < total:
                    check, tol, patience = converge
                    block = np.zeros(n_w)
                    for i in range(taken):  # as the torch loop adds them, step by step
                        block += losses[i]
                    mean = float((block / check).sum())
                    improved = mean < best_block * (1.0 - tol)
                    best_block = min(best_block, mean)
                    stale = 0 if improved else stale + 1
                    if stale >= patience:
                        total = done
            self._end()
        return torch.full_like(iterations, total)

    def search(
        self,
        sampler: Any,
        val: Any,
        has_val: torch.Tensor,
        best_iter: torch.Tensor,
        steps: int,
        patience: int,
        noise: float,
        max_norm: float,
    ) -> torch.Tensor:
        """Early stopping's pass, one decision for the field: after each step the held-out
        error summed over the wells of ``has_val``; those wells keep the step of its best
        value, and the pass ends once it has gone ``patience`` steps without a better one
        (see :meth:`FitSteps.search`)."""
        n_w = self.n_w
        has = has_val.numpy()
        val_arrays = (
            np.ascontiguousarray(self.model.normalise(val.x).numpy()),
            np.ascontiguousarray(val.y.numpy()),
            np.ascontiguousarray(val.mask.numpy()),
            np.ascontiguousarray(has),
        )
        with torch.no_grad():
            self._begin()
            n_full = sampler.counts.to(torch.float64).numpy()

            def run(chunk: Any) -> np.ndarray:
                taken = chunk[3]
                out = np.zeros(taken)
                losses = np.zeros((taken, n_w))
                val = (*val_arrays, out)
                self._steps(chunk, n_full, noise, max_norm, losses, val, sampler.size)
                return np.tile(out, (n_w, 1))  # the field's one error, for every well

            chosen = _early_stopping(
                sampler, steps, self.SEARCH_CHUNK, has, best_iter.clone().numpy(), patience, run
            )
            self._end()
        return torch.from_numpy(chosen)


def physics_layout(model: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """How the kernels read the six Sachdeva parameters (``_NAMES``) of ``mm``, ``hem`` or
    ``ham``: theta[i] = mu[i] + sigma[i] z[pos[i]], or mu[i] where pos[i] < 0 (``ham``'s
    C_D, which the network replaces: C_D0, its prior mean, the network's reference)."""
    from vfm_core import physics as ph

    phys = model.phys
    if len(phys.names) == 6:
        return _SIX, phys.mu.numpy(), phys.sigma.numpy()
    assert len(phys.names) == 5  # ham: no C_D
    # asked at every step: kept while the priors' tensors and their contents stay the same
    mu_t, sigma_t = phys.mu, phys.sigma
    versions = (mu_t._version, sigma_t._version)
    cached = phys.__dict__.get("_vfm_layout")
    if cached is not None and cached[0] is mu_t and cached[1] is sigma_t and cached[2] == versions:
        return cached[3]  # type: ignore[no-any-return]
    c_d0 = ph.PRIORS["c_d"].mean
    layout = _FIVE, np.append(mu_t.numpy(), c_d0), np.append(sigma_t.numpy(), 0.0)
    phys.__dict__["_vfm_layout"] = (mu_t, sigma_t, versions, layout)
    return layout


def hybrid_rates(model: Any, batch: Any) -> torch.Tensor:
    """The rate [W, N] (Sm3/h) of ``hem`` or ``ham`` (see :func:`hybrid_applies`), what
    ``model.forward_batch`` gives, without a graph."""
    kernel = _kernel()
    assert kernel is not None
    phys, net = model.phys, model.net
    pos, mu, sigma = physics_layout(model)
    out = np.empty(tuple(batch.y.shape))
    kind = compiled_effects(model) or model.compiled_as()
    with torch.no_grad():
        eff = [p.detach().numpy() for p in effect_parameters(model)[1:]]
        kernel.hybrid_rates(
            phys.z.detach().numpy(),
            pos,
            mu,
            sigma,
            np.ascontiguousarray(batch.x.numpy()),
            model.a_max.numpy(),
            model.x_mean.numpy(),
            model.x_std.numpy(),
            net.weights[0].detach().numpy(),
            net.biases[0].detach().numpy(),
            net.weights[1].detach().numpy(),
            net.biases[1].detach().numpy(),
            model.y_scale.numpy(),
            kind == "ham",
            out,
            _joined(eff) if eff else _no_effects("eff")[0],
            _fx(model, batch),
        )
    return torch.from_numpy(out)


def mm_rates(model: Any, batch: Any) -> torch.Tensor:
    """The plain ``mm``'s rate [W, N] (Sm3/h) of every sample of ``batch``, what
    ``model.forward_batch`` gives (see :func:`mm_online_applies`), without a graph."""
    kernel = _kernel()
    assert kernel is not None
    phys = model.phys
    out = np.empty(tuple(batch.y.shape))
    with torch.no_grad():
        kernel.rates(
            phys.z.detach().numpy(),
            np.ascontiguousarray(batch.x.numpy()),
            model.a_max.numpy(),
            phys.mu.numpy(),
            phys.sigma.numpy(),
            out,
        )
    return torch.from_numpy(out)


# -- models with compiled effects (Effect.compiled_factor: rate factors, real gas, slip) ----
def compiled_effects(model: Any) -> str | None:
    """``mm``, ``hem`` or ``ham`` when the kernels compute ``model`` with its effects (the
    model's ``compiled_with_effects``: every effect has a compiled form), else None."""
    probe = getattr(model, "compiled_with_effects", None)
    return None if probe is None else probe()  # type: ignore[no-any-return]


def effects_applies(model: Any) -> bool:
    """True when :func:`effect_online_steps` and :func:`effect_rates` compute ``model``:
    ``mm`` with effects that all have a compiled form, the kernels enabled."""
    return compiled_effects(model) == "mm" and kernels_enabled()


def effect_parameters(model: Any) -> list[torch.nn.Parameter]:
    """The parameters of :func:`effect_online_steps`, in its order: the mechanistic z,
    then each effect's z (in the order of ``model.effects``)."""
    return [model.phys.z, *(model.effect_block(e.name).z for e in model.effects)]


def _effect_priors(model: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The effects' parameters' prior means and sds (SI) and bounds in z, concatenated in
    the order of :func:`effect_parameters` (kept while the blocks hold the same tensors)."""
    parts = [
        buffer_views(model.effect_block(e.name), ("mu", "sigma", *_BOUNDS)) for e in model.effects
    ]
    if len(parts) == 1:
        return parts[0]  # type: ignore[return-value]
    return tuple(np.concatenate(col) for col in zip(*parts, strict=True))  # type: ignore[return-value]


def _effect_terms(model: Any, names: tuple[str, ...]) -> np.ndarray:
    """The kernels' table of the model's effects [T, 6] (code, first parameter, number of
    parameters, feature column in ``names``, two settings), for batches whose feature
    columns are ``names`` (kept per model and names)."""
    cache: dict[tuple[str, ...], np.ndarray] = model.__dict__.setdefault("_vfm_terms", {})
    terms = cache.get(names)
    if terms is None:
        rows, start, made = [], 0, len(names)
        for e in model.effects:
            form = e.compiled_factor()
            size = len(e.parameters)
            column = names.index(form.column) if form.column is not None else 0
            if form.code == _SUGGEST:  # its two columns after the batch's features
                column, made = made, made + 2
            rows.append([form.code, start, size, column, *form.settings])
            start += size
        terms = np.array(rows, dtype=np.int64).reshape(len(rows), 6)
        cache[names] = terms
    return terms


#: the kernels' arguments for a model without effects (never written), once built
_EMPTY: dict[str, tuple[np.ndarray, ...]] = {}


def _no_effects(what: str) -> tuple[np.ndarray, ...]:
    """``fx`` (the effects, ``what`` = "fx") or ``eff`` (their state, "eff") of a model
    without effects, as :mod:`vfm_core.learning._mm_numba` takes them."""
    if what not in _EMPTY:
        from vfm_core.learning import _mm_numba as k

        _EMPTY["fx"], _EMPTY["eff"] = k.no_effects(), k.no_effect_state()
    return _EMPTY[what]


def _fx(model: Any, batch: Any) -> tuple[np.ndarray, ...]:
    """The effects as the kernels read them (``fx`` of ``_mm_numba._factor_at``): terms,
    the parameters' prior means and sds (SI), the batch's feature columns [W, N, E], well
    tests [W, N], times [W, N] (ns), the wells' reference openings [W]."""
    if not getattr(model, "effects", None):
        return _no_effects("fx")
    n_w, n = int(batch.y.shape[0]), int(batch.y.shape[1])
    extra = (
        np.zeros((n_w, n, 0)) if batch.extra is None else np.ascontiguousarray(batch.extra.numpy())
    )
    made = model.compiled_columns(batch)  # the effects' own columns (suggest's driver)
    if made is not None:
        extra = np.ascontiguousarray(np.concatenate([extra, made], -1))
    test = (
        np.zeros((n_w, n), dtype=bool)
        if batch.well_test is None
        else np.ascontiguousarray(batch.well_test.numpy())
    )
    mu_e, sigma_e, _, _ = _effect_priors(model)
    return (
        _effect_terms(model, tuple(batch.extra_names)),
        mu_e,
        sigma_e,
        extra,
        test,
        np.ascontiguousarray(batch.time_ns.numpy()),
        model.u_ref.numpy(),
    )


def effect_arguments(model: Any, batch: Any) -> tuple[tuple[np.ndarray, ...]]:
    """The effect argument of the compiled filter (``bayes`` of
    :mod:`vfm_core.learning._mm_numba`), the empty one for a model without effects."""
    return (_fx(model, batch),)


def effect_bounds(model: Any) -> tuple[np.ndarray, np.ndarray]:
    """The bounds in z of the effects' parameters, concatenated (empty without effects)."""
    if not getattr(model, "effects", None):
        return np.zeros(0), np.zeros(0)
    _, _, low, high = _effect_priors(model)
    return low, high


def effect_rates(model: Any, batch: Any) -> torch.Tensor:
    """The rate [W, N] (Sm3/h) of ``mm`` with compiled effects (see :func:`effects_applies`),
    what ``model.forward_batch`` gives, without a graph."""
    kernel = _kernel()
    assert kernel is not None
    phys = model.phys
    out = np.empty(tuple(batch.y.shape))
    with torch.no_grad():
        kernel.effect_rates(
            phys.z.detach().numpy(),
            np.ascontiguousarray(batch.x.numpy()),
            model.a_max.numpy(),
            phys.mu.numpy(),
            phys.sigma.numpy(),
            _joined([p.detach().numpy() for p in effect_parameters(model)[1:]]),
            _fx(model, batch),
            out,
        )
    return torch.from_numpy(out)


def _effect_state(
    model: Any,
    eff: list[np.ndarray],
    moments: list[tuple[np.ndarray, np.ndarray]] | None,
    first: int,
) -> tuple[np.ndarray, ...]:
    """``eff`` of the online kernels: the effects' parameters side by side (``eff`` their
    arrays), their Adam moments (zeros for SGD), each parameter's row of the step counts
    (the effects' tensors after the model's ``first`` ones), their bounds in z."""
    if not eff:
        return _no_effects("eff")
    ze = _joined(eff)
    if moments is None:
        me, ve = np.zeros_like(ze), np.zeros_like(ze)
    else:
        me, ve = _joined([a for a, _ in moments]), _joined([b for _, b in moments])
    sizes = [a.shape[1] for a in eff]
    rows = np.repeat(np.arange(first, first + len(eff), dtype=np.int64), sizes)
    _, _, low, high = _effect_priors(model)
    return ze, me, ve, rows, low, high


def _effect_state_back(
    eff: list[np.ndarray],
    moments: list[tuple[np.ndarray, np.ndarray]] | None,
    state: tuple[np.ndarray, ...],
) -> None:
    """Write the kernels' ``eff`` (:func:`_effect_state`) back into the arrays it joined."""
    if not eff:
        return
    _split_back(eff, state[0])
    if moments is not None:
        _split_back([a for a, _ in moments], state[1])
        _split_back([b for _, b in moments], state[2])


def _joined(arrays: list[np.ndarray]) -> np.ndarray:
    """Arrays [W, k_i] side by side [W, sum k_i]: the one array itself (its memory, written
    in place) when there is one."""
    if len(arrays) == 1:
        return _in_place(arrays[0])
    return np.ascontiguousarray(np.concatenate(arrays, axis=1))


def _split_back(arrays: list[np.ndarray], joined: np.ndarray) -> None:
    """Write ``joined`` (from :func:`_joined`) back into ``arrays`` (unless it is the one)."""
    if len(arrays) == 1 and joined is arrays[0]:
        return
    start = 0
    for a in arrays:
        k = a.shape[1]
        np.copyto(a, joined[:, start : start + k])
        start += k


def effect_online_steps(
    model: Any,
    batch: Any,
    moments: list[tuple[torch.Tensor, torch.Tensor]] | list[tuple[np.ndarray, np.ndarray]] | None,
    counts: np.ndarray,
    hold: np.ndarray,
    *,
    steps: int,
    noise: float,
    lr: float,
    betas: tuple[float, float],
    eps: float,
    max_norm: float,
) -> None:
    """E steps of ``ol`` on ``mm`` with compiled effects (see :func:`effects_applies`) and
    ``batch``, in place, as :func:`mm_online_steps`: the parameters of
    :func:`effect_parameters`; with Adam their moments (``moments``, one (exp_avg,
    exp_avg_sq) pair per parameter in that order) and ``counts`` [len(parameters), W]
    (each parameter's step count per well, as floats), advanced by ``steps``; ``moments``
    None is SGD. Wells in ``hold`` keep their parameters."""
    kernel = _kernel()
    assert kernel is not None
    params = effect_parameters(model)
    with torch.no_grad():
        z = _in_place(params[0])
        eff = [p.detach().numpy() for p in params[1:]]
        if moments is None:
            m, v = np.zeros_like(z), np.zeros_like(z)
            own = None
        else:
            m, v = _in_place(moments[0][0]), _in_place(moments[0][1])
            own = [(_in_place(a), _in_place(b)) for a, b in moments[1:]]
        state = _effect_state(model, eff, own, 1)
        kernel.effect_online(
            z,
            m,
            v,
            counts,
            hold,
            np.ascontiguousarray(batch.x.numpy()),
            np.ascontiguousarray(batch.y.numpy()),
            np.ascontiguousarray(batch.mask.numpy()),
            *buffer_views(model, _SCALES[:2]),
            *buffer_views(model.phys, ("mu", "sigma")),
            buffer_views(model.phys, _BOUNDS),
            float(noise),
            (float(lr), float(betas[0]), float(betas[1]), float(eps)),
            float(max_norm),
            int(steps),
            moments is not None,
            state,
            _fx(model, batch),
        )
        _effect_state_back(eff, own, state)
        _written_back([params[0]], [z])
        if moments is not None:
            assert own is not None
            _written_back(
                [t for pair in moments for t in pair],
                [m, v, *(a for pair in own for a in pair)],
            )


#: the buffers the kernels read: the model's scales, the physics' bounds
_SCALES = ("a_max", "y_scale", "x_mean", "x_std")
_BOUNDS = ("z_low", "z_high")


def buffer_views(module: torch.nn.Module, names: tuple[str, ...]) -> tuple[np.ndarray, ...]:
    """numpy views of ``module``'s buffers ``names``, kept while it holds the same tensors
    (they change in place; a step asks for them every time, and a module attribute and
    its view cost a microsecond each)."""
    buffers = module._buffers
    tensors = tuple(buffers[name] for name in names)
    cache: dict[tuple[str, ...], tuple[tuple[Any, ...], tuple[np.ndarray, ...]]] = (
        module.__dict__.setdefault("_vfm_views", {})
    )
    hit = cache.get(names)
    if hit is not None and all(a is b for a, b in zip(hit[0], tensors, strict=True)):
        return hit[1]
    views = tuple(t.detach().numpy() for t in tensors)  # type: ignore[union-attr]
    cache[names] = (tensors, views)
    return views


def _in_place(t: torch.Tensor | np.ndarray) -> np.ndarray:
    """The array a kernel updates ``t`` in: ``t``'s own memory when it is contiguous (a
    learning step holds no graph of it, so nothing saved for a backward pass can see the
    change), else a contiguous copy that :func:`_written_back` copies back. An array
    (a view of a tensor the caller keeps) is taken as it is."""
    a: np.ndarray = t if isinstance(t, np.ndarray) else t.detach().numpy()
    return a if a.flags.c_contiguous else np.ascontiguousarray(a)


def _written_back(tensors: Sequence[torch.Tensor | np.ndarray], arrays: list[np.ndarray]) -> None:
    """Copy each array of :func:`_in_place` that is not its tensor's own memory back."""
    for t, a in zip(tensors, arrays, strict=False):
        if a is t or not a.flags.owndata:  # the memory itself (a view owns none)
            continue
        if isinstance(t, np.ndarray):
            np.copyto(t, a)
        else:
            t.copy_(torch.from_numpy(a))


def writable(owner: Any, name: str) -> np.ndarray:
    """``owner.name`` as a numpy view the kernel writes into (made contiguous first)."""
    t = getattr(owner, name)
    if not t.is_contiguous():
        t = t.contiguous()
        setattr(owner, name, t)
    return t.numpy()  # type: ignore[no-any-return]


def _build() -> SimpleNamespace:
    """Import (compile, or load from numba's cache) the kernels and run each once on a
    made-up sample: a machine where numba cannot compile them falls back to the torch path
    (kernels_enabled() is then False), not fails at a measurement."""
    from vfm_core.learning import _mm_numba as k

    k.warm_up()
    return SimpleNamespace(
        online=k.online,
        hybrid_online=k.hybrid_online,
        rates=k.rates,
        hybrid_rates=k.hybrid_rates,
        bayes=k.bayes,
        bayes_spread=k.bayes_spread,
        bayes_gradients=k.bayes_gradients,
        effect_rates=k.effect_rates,
        effect_online=k.effect_online,
    )
