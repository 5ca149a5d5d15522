"""Online learning (``ol``): a few gradient steps from the current parameters on each new
measurement (paper eq. MAP-OL).

For each new measurement, E steps of rate gamma on that observation alone; the prior pull
stays on for physical parameters only. The optimiser's state (Adam's moments) carries over
from one measurement to the next and is part of the method's state.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Hashable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
import torch.optim.optimizer as _torch_optimizer

from vfm_core.data import DTYPE, Batch
from vfm_core.learning.kernels import (
    compiled_effects,
    effect_online_steps,
    effect_parameters,
    effects_applies,
    fit_parameters,
    hybrid_applies,
    hybrid_effects_applies,
    hybrid_online_steps,
    hybrid_parameters,
    kernels_enabled,
    mm_online_applies,
    mm_online_steps,
    mtl_online_steps,
    mtl_parameters,
    plain_hybrid,
    plain_lr,
    plain_mm,
    plain_mtl,
    plain_nn,
    sgd_online_steps,
)
from vfm_core.learning.memory import Memory
from vfm_core.learning.method import LearningMethod, ready_for_group, register
from vfm_core.learning.stacking import StackedModel, stack_for_learning
from vfm_core.learning.training import (
    MapObjective,
    clip_per_well_,
    make_optimizer,
    optimizer_step_,
    plain_optimizer,
    split_parameters,
)
from vfm_core.models import MODELS, ChokeModel

__all__ = ["OnlineSettings", "DEFAULT_ONLINE", "OnlineLearning", "online_defaults"]


@dataclass(frozen=True)
class OnlineSettings:
    """Online learning: E steps of rate gamma per new measurement."""

    optimizer: str = "adam"
    lr: float = 1e-2
    steps: int = 10
    schedule_power: float = 0.0
    noise: float = 0.05
    #: per-well cap on the gradient norm of one step, so a single odd measurement
    #: (or an input far outside the training range) cannot throw the model away
    max_grad_norm: float = 1.0


def online_defaults(model: ChokeModel | type[ChokeModel]) -> OnlineSettings:
    """The online settings a model starts from: its class's ``online_defaults``."""
    return OnlineSettings(**model.online_defaults)


#: Online defaults per registered model, by name: each model's own ``online_defaults``
#: (see :attr:`vfm_core.models.base.ChokeModel.online_defaults`)
DEFAULT_ONLINE: dict[str, OnlineSettings] = {
    name: online_defaults(cls) for name, cls in MODELS.items()
}


@register
class OnlineLearning(LearningMethod):
    """``ol``: E optimiser steps on every new measurement (see the module docstring)."""

    key = "ol"
    kind = "ol"
    summary = "a few gradient steps on each new measurement"
    example = "ol"

    def __init__(self, text: str = "ol") -> None:
        super().__init__(text)
        self.online = OnlineSettings()
        self._opt: torch.optim.Optimizer | None = None
        self._sched: Any = None
        #: the optimiser's parameters, and the model's per-well and shared ones (cached
        #: with the optimiser: an update takes E steps and must not walk the model each time)
        self._params: list[torch.nn.Parameter] = []
        self._groups: tuple[list[torch.nn.Parameter], list[torch.nn.Parameter]] = ([], [])
        #: the plain hybrid's parameters in the compiled steps' order (None: not compiled)
        self._hybrid: list[torch.nn.Parameter] | None = None
        #: the compiled steps apply (the kernels on): the plain mm, or the plain hybrids
        self._compiled = False
        #: the compiled steps are the plain nn's or lr's with SGD (kernels.sgd_online_steps)
        self._nn = False
        #: ... or the plain mtl's with Adam (kernels.mtl_online_steps)
        self._mtl = False
        #: ... or mm's with effects that have a compiled form (kernels.effect_online_steps)
        self._effects = False
        self.updates = 0

    def bind(  # type: ignore[override]
        self, model: ChokeModel, *, online: OnlineSettings | None = None, **kw: Any
    ) -> OnlineLearning:
        super().bind(model, **kw)
        self.online = online or online_defaults(model)
        self._opt, self._sched = None, None
        return self

    def _rebind(self, model: ChokeModel) -> None:
        self._opt, self._sched = None, None
        self._compiled = False

    def _optimiser(self) -> torch.optim.Optimizer:
        if self._opt is None:
            params = [p for p in self.model.parameters() if p.requires_grad]
            s = self.online
            self._opt, self._sched = make_optimizer(params, s.optimizer, s.lr, s.schedule_power)
            self._params = params
            self._groups = split_parameters(self.model)
            # the plain hem and ham, every parameter stepped: their compiled steps
            shape = plain_hybrid(self.model) or compiled_effects(self.model) in ("hem", "ham")
            hybrid = hybrid_parameters(self.model) if shape else None
            self._hybrid = hybrid if hybrid is not None and self._all_of(hybrid) else None
            # with torch's plain Adam or SGD: the plain mm (its one tensor, z) or the
            # plain hybrids (every parameter) step compiled
            mm = plain_mm(self.model) and self._all_of([self.model.phys.z])  # type: ignore[union-attr, list-item]
            # mm with compiled effects (rate factors, real gas, slip), every parameter stepped
            self._effects = compiled_effects(self.model) == "mm" and self._all_of(
                effect_parameters(self.model)
            )
            # the plain nn or lr with SGD (their default), every parameter stepped
            plain = plain_nn(self.model) or plain_lr(self.model)
            net = fit_parameters(self.model) if plain else None
            self._nn = (
                net is not None and self._all_of(net) and isinstance(self._opt, torch.optim.SGD)
            )
            # the plain mtl with Adam (its default), every parameter stepped
            self._mtl = (
                plain_mtl(self.model)
                and isinstance(self._opt, torch.optim.Adam)
                and self._all_of(mtl_parameters(self.model))
            )
            self._compiled = (
                plain_optimizer(self._opt)
                and self._sched is None
                and (mm or self._hybrid is not None or self._nn or self._mtl or self._effects)
            )
        return self._opt

    def _learn_compiled(self, batch: Batch) -> torch.Tensor:
        """:meth:`_learn` with the compiled steps: the same set-up and masks, taken in numpy
        (a microsecond each, where a torch operation on a few booleans costs two or three),
        then the E steps. The wells that learned [W]."""
        model = self.model
        mask = batch.mask.numpy()
        has = mask.any(1)
        if (has & ~model.ready.numpy()).any():
            model.setup(batch)  # wells seen for the first time: their scales
        ready = model.ready.numpy() & has
        if not ready.any():
            return torch.from_numpy(ready)
        if (mask & ~ready[:, None]).any():
            batch = batch.select(torch.from_numpy(mask & ready[:, None]))
        assert self._opt is not None
        # Adam's momentum would move wells that have no new measurement: hold them still.
        self._compiled_steps(batch, self._opt, ~ready, self._hybrid)
        self.updates += 1
        return torch.from_numpy(ready)

    def _learn(self, batch: Batch, memory: Memory | None = None) -> torch.Tensor:
        model = self.model
        opt = self._optimiser()
        if self._compiled and kernels_enabled() and self._one_step_count(opt):
            return self._learn_compiled(batch)
        model.setup(batch)
        ready = model.ready & (batch.count() > 0)
        if not bool(ready.any()):
            return ready
        if bool((batch.mask & ~ready.unsqueeze(1)).any()):
            batch = batch.select(batch.mask & ready.unsqueeze(1))
        # Adam's momentum would move wells that have no new measurement: hold them still.
        idle = ~ready
        any_idle = bool(idle.any())
        held = [(p, p.detach()[idle].clone()) for p in self._groups[0]] if any_idle else []
        # the same batch for every step: its counts once
        n = batch.count().to(DTYPE)
        s = self.online
        objective = MapObjective(model, batch, s.noise, True, n)
        for _ in range(s.steps):
            objective.gradients_(self._params)
            clip_per_well_(model, s.max_grad_norm, self._groups)
            optimizer_step_(opt)
            model.project_()
            for p, before in held:
                p.data[idle] = before
        if self._sched is not None:
            self._sched.step()
        self.updates += 1
        return ready

    def _one_step_count(self, opt: torch.optim.Optimizer) -> bool:
        """False for ``mtl`` when its tensors' Adam step counts differ (a state loaded from
        elsewhere): its compiled steps keep one count, so torch's path runs then."""
        if not self._mtl:
            return True
        step_counts, _ = self._adam_views(opt, mtl_parameters(self.model))
        return len({float(c) for c in step_counts}) == 1

    def _all_of(self, params: list[torch.nn.Parameter]) -> bool:
        """True when the optimiser steps exactly ``params`` (in any order)."""
        return len(self._params) == len(params) and {id(p) for p in self._params} == {
            id(p) for p in params
        }

    def _adam_state(self, opt: torch.optim.Optimizer, p: torch.nn.Parameter) -> dict[str, Any]:
        """``p``'s Adam state, started as torch's Adam starts it."""
        state = opt.state[p]
        if len(state) == 0:
            state["step"] = torch.tensor(0.0, dtype=_torch_optimizer._get_scalar_dtype())
            state["exp_avg"] = torch.zeros_like(p, memory_format=torch.preserve_format)
            state["exp_avg_sq"] = torch.zeros_like(p, memory_format=torch.preserve_format)
        return state  # type: ignore[no-any-return]

    def _adam_views(
        self, opt: torch.optim.Optimizer, params: list[torch.nn.Parameter]
    ) -> tuple[list[torch.Tensor], list[tuple[np.ndarray, np.ndarray]]]:
        """Adam's step counts of ``params`` and numpy views of their moments (the compiled
        steps write them in place), kept while the optimiser and its state stay the same
        (the torch path updates the same tensors in place too)."""
        cached = self.__dict__.get("_adam_cache")
        if (
            cached is not None
            and cached[0] is opt
            and len(cached[1]) == len(params)
            and all(a is b for a, b in zip(cached[1], params, strict=True))
            and opt.state.get(params[0], {}).get("exp_avg") is cached[2]
        ):
            return cached[3], cached[4]  # type: ignore[no-any-return]
        states = [self._adam_state(opt, p) for p in params]
        step_counts = [st["step"] for st in states]
        views = [(st["exp_avg"].numpy(), st["exp_avg_sq"].numpy()) for st in states]
        self.__dict__["_adam_cache"] = (opt, list(params), states[0]["exp_avg"], step_counts, views)
        return step_counts, views

    def _compiled_steps(
        self,
        batch: Batch,
        opt: torch.optim.Optimizer,
        idle: np.ndarray,
        params: list[torch.nn.Parameter] | None = None,
    ) -> None:
        """The E steps of :meth:`_learn`, compiled, on the optimiser's own state: the plain
        ``mm`` (``params`` None: :func:`vfm_core.learning.kernels.mm_online_steps`), ``mm``
        with compiled effects (:func:`~vfm_core.learning.kernels.effect_online_steps`) or
        ``hem`` / ``ham``, plain or with compiled effects (``params`` in the order of
        :func:`~vfm_core.learning.kernels.hybrid_online_steps`)."""
        if self._mtl:
            step_counts, views = self._adam_views(opt, mtl_parameters(self.model))
            group = opt.param_groups[0]
            s = self.online
            mtl_online_steps(
                self.model, batch, views, float(step_counts[0]), idle, steps=s.steps,
                lr=float(group["lr"]), betas=tuple(group["betas"]), eps=float(group["eps"]),
                max_norm=s.max_grad_norm,
            )  # fmt: skip
            torch._foreach_add_(step_counts, float(s.steps))
            for p in self._params:
                p.grad = None
            return
        if self._nn:
            s = self.online
            lr = float(opt.param_groups[0]["lr"])
            sgd_online_steps(
                self.model, batch, idle, steps=s.steps, lr=lr, max_norm=s.max_grad_norm
            )
            for p in self._params:
                p.grad = None
            return
        z: torch.nn.Parameter = self.model.phys.z  # type: ignore[assignment, union-attr]
        if self._effects:
            params = effect_parameters(self.model)
        steps = [z] if params is None else params
        group = opt.param_groups[0]
        counts = np.zeros((len(steps), z.shape[0]))  # each parameter's step count per well
        step_counts = []
        moments = None
        adam = isinstance(opt, torch.optim.Adam)
        if adam:
            step_counts, moments = self._adam_views(opt, steps)
            counts[:] = torch.stack(step_counts).numpy().reshape(-1, 1)
        s = self.online
        kw: dict[str, Any] = dict(
            steps=s.steps,
            noise=s.noise,
            lr=group["lr"],
            betas=tuple(group.get("betas", (0.9, 0.999))),
            eps=group.get("eps", 1e-8),
            max_norm=s.max_grad_norm,
        )
        if params is None:
            first = None if moments is None else moments[0]
            mm_online_steps(self.model, batch, first, counts[0], idle, **kw)
        elif self._effects:
            effect_online_steps(self.model, batch, moments, counts, idle, **kw)
        else:
            hybrid_online_steps(self.model, batch, moments, counts, idle, params=params, **kw)
        if adam:
            torch._foreach_add_(step_counts, float(s.steps))
        for p in steps:
            p.grad = None

    # -- many wells at once ----------------------------------------------------------------------
    def learn_key(self) -> Hashable | None:
        """Methods of exactly this class with the same online settings and optimiser
        hyperparameters, on gradient models of one specification, learn together: the E
        steps on the stacked models, each well with its own optimiser state. None (one at a
        time): a learning-rate schedule, an optimiser other than torch's plain Adam or SGD,
        more than one parameter group."""
        if type(self) is not OnlineLearning or self.model.gradient_free:
            return None
        s = self.online
        opt = self._optimiser()
        if s.schedule_power != 0 or self._sched is not None or len(opt.param_groups) != 1:
            return None
        if not isinstance(opt, torch.optim.Adam | torch.optim.SGD) or not plain_optimizer(opt):
            return None
        group = opt.param_groups[0]
        hyper: tuple[Any, ...]
        if isinstance(opt, torch.optim.Adam):
            hyper = ("adam", group["lr"], tuple(group["betas"]), group["eps"])
        else:
            hyper = ("sgd", group["lr"], None, None)
        return ("ol", self.model.stack_key(), s.steps, s.noise, s.max_grad_norm, *hyper)

    @classmethod
    def learn_group(
        cls,
        methods: Sequence[LearningMethod],
        batches: Sequence[Batch],
        memories: Sequence[Memory | None],
    ) -> list[bool | None]:
        """The E steps of the wells that are ready, on their models stacked into one (each
        well with its own Adam moments and step count, so its own bias correction, its own
        gradient clipping and projection); then each well's parameters and optimiser state
        are written back, as learning one by one leaves them."""
        learners = [m for m in methods if isinstance(m, OnlineLearning)]
        assert len(learners) == len(methods)
        for m in learners:
            m._optimiser()  # (what _learn does first, with the model's set-up)
        ready = ready_for_group(methods, batches)
        out: list[bool | None] = [None] * len(methods)
        if len(ready) < 2:
            return out
        group = [learners[k] for k in ready]
        models = [m.model for m in group]
        stacked, batch = stack_for_learning(models, [batches[k] for k in ready])
        finish = _stacked_steps(stacked, group, batch)
        stacked.store(models)
        finish()
        for k in ready:
            learners[k].updates += 1
            out[k] = True
        return out

    def tuning(self, grid: str) -> list[dict[str, Any]]:
        """Step size gamma, steps E and optimiser (the paper's grid, or a small one)."""
        if grid == "paper":
            rates = [5e-1, 1e-1, 1e-2, 1e-3, 1e-4, 1e-5, 1e-6, 1e-7, 1e-10]
            steps = [1, 10, 20]
        else:
            rates, steps = [1e-1, 1e-2, 1e-3, 1e-4], [1, 10]
        return [
            {"online": {"optimizer": opt, "lr": lr, "steps": e}}
            for lr in rates
            for e in steps
            for opt in ("sgd", "adam")
        ]

    def state_dict(self) -> dict[str, Any]:
        state = super().state_dict()
        state["optimizer"] = self._opt.state_dict() if self._opt is not None else {}
        state["updates"] = self.updates
        return state

    def load_state_dict(self, state: dict[str, Any]) -> None:
        super().load_state_dict(state)
        self.updates = int(state.get("updates", 0))
        self._opt, self._sched = None, None
        if state.get("optimizer"):
            self._optimiser().load_state_dict(state["optimizer"])


def _same_parameters(a: list[torch.nn.Parameter], b: list[torch.nn.Parameter]) -> bool:
    """True when ``a`` and ``b`` hold the same parameters (in any order)."""
    return len(a) == len(b) and {id(p) for p in a} == {id(p) for p in b}


def _mm_steps(
    model: ChokeModel,
    batch: Batch,
    moments: list[Any] | None,
    counts: np.ndarray,
    hold: np.ndarray,
    **kw: Any,
) -> None:
    """:func:`~vfm_core.learning.kernels.mm_online_steps` with the moments and step counts
    of its one parameter given as lists (of :func:`_compiled_order`'s functions)."""
    mm_online_steps(model, batch, None if moments is None else moments[0], counts[0], hold, **kw)


def _compiled_order(
    model: ChokeModel, params: list[torch.nn.Parameter]
) -> tuple[list[torch.nn.Parameter], Callable[..., None]] | None:
    """The compiled ``ol`` steps of ``model`` (the plain ``mm``, ``mm`` with compiled
    effects, or ``hem`` / ``ham`` plain or with compiled effects): the parameters in their
    order and the function, when they step exactly ``params``; else None."""
    order: list[torch.nn.Parameter]
    run: Callable[..., None]
    if mm_online_applies(model):
        order, run = [model.phys.z], _mm_steps  # type: ignore[list-item,union-attr]
    elif effects_applies(model):
        order, run = effect_parameters(model), effect_online_steps
    elif hybrid_applies(model) or hybrid_effects_applies(model):
        order = hybrid_parameters(model)
        run = functools.partial(hybrid_online_steps, params=order)
    else:
        return None
    return (order, run) if _same_parameters(params, order) else None


@dataclass
class _StackedOptimiser:
    """The learners' optimiser states over the stacked model's parameters: per stacked
    parameter (``params``), each learner's own tensor (``own``), the wells' Adam moments
    stacked along the well dimension (None with SGD) and their step counts; ``stepped``
    counts the steps each stacked parameter took here (torch's Adam skips one without a
    gradient), ``factors`` caches the wells' bias corrections by step counts."""

    opts: list[torch.optim.Optimizer]
    adam: bool
    lr: float
    betas: tuple[float, float]
    eps: float
    params: list[torch.nn.Parameter]
    own: list[list[torch.nn.Parameter]]
    moments: list[tuple[torch.Tensor, torch.Tensor] | None]
    steps: list[list[float]]

    def __post_init__(self) -> None:
        self.stepped = [0] * len(self.params)
        self.factors: dict[tuple[float, ...], tuple[torch.Tensor, torch.Tensor]] = {}

    def adam_step_(self, j: int, p: torch.nn.Parameter, g: torch.Tensor) -> None:
        """torch's Adam step on stacked parameter ``j`` (``p``, gradient ``g``), each well
        with its own step count and so its own bias correction."""
        beta1, beta2 = self.betas
        lr, k = self.lr, len(self.opts)
        exp_avg, exp_avg_sq = self.moments[j]  # type: ignore[misc]
        counts = self.steps[j] = [c + 1.0 for c in self.steps[j]]
        exp_avg.lerp_(g, 1 - beta1)
        exp_avg_sq.mul_(beta2).addcmul_(g, g, value=1 - beta2)
        fk = (p.dim(), *counts)
        if fk not in self.factors:  # each well's bias correction, as torch's Adam's
            shape = (k, *([1] * (p.dim() - 1)))
            size = [-(lr / (1 - beta1**c)) for c in counts]
            root = [(1 - beta2**c) ** 0.5 for c in counts]
            self.factors[fk] = (
                torch.tensor(size, dtype=p.dtype).reshape(shape),
                torch.tensor(root, dtype=p.dtype).reshape(shape),
            )
        neg_step_size, bias_correction2_sqrt = self.factors[fk]
        # torch: param.addcdiv_(exp_avg, denom, value=-step_size), per well here
        denom = exp_avg_sq.sqrt().div_(bias_correction2_sqrt).add_(self.eps)
        p.addcdiv_(exp_avg * neg_step_size, denom)

    def write_back(self) -> None:
        """Each well's optimiser state, in place (the learners' tensors stay their own)."""
        if not self.adam:
            return
        scalar = _torch_optimizer._get_scalar_dtype()
        with torch.no_grad():
            for j in range(len(self.params)):
                if not self.stepped[j]:
                    continue
                exp_avg, exp_avg_sq = self.moments[j]  # type: ignore[misc]
                states = [opt.state[q] for opt, q in zip(self.opts, self.own[j], strict=True)]
                for st, q in zip(states, self.own[j], strict=True):
                    if not st:  # its first step: the state torch's Adam would create
                        st["step"] = torch.tensor(0.0, dtype=scalar)
                        st["exp_avg"] = torch.zeros_like(q, memory_format=torch.preserve_format)
                        st["exp_avg_sq"] = torch.zeros_like(q, memory_format=torch.preserve_format)
                # (integer step counts: adding them at once is adding one per step)
                torch._foreach_add_([st["step"] for st in states], float(self.stepped[j]))
                torch._foreach_copy_([st["exp_avg"] for st in states], list(exp_avg.split(1, 0)))
                torch._foreach_copy_(
                    [st["exp_avg_sq"] for st in states], list(exp_avg_sq.split(1, 0))
                )


def _stacked_optimiser(stacked: StackedModel, learners: list[OnlineLearning]) -> _StackedOptimiser:
    """The learners' optimisers gathered over the stacked model's trainable parameters."""
    model = stacked.model
    trainable = [w for w in stacked.parameters() if stacked.tensor(model, w).requires_grad]
    if not trainable:
        raise ValueError("The model has no parameters to learn.")
    opts = [lrn._optimiser() for lrn in learners]
    group = opts[0].param_groups[0]
    adam = isinstance(opts[0], torch.optim.Adam)
    betas = tuple(group["betas"]) if adam else (0.9, 0.999)
    eps = group["eps"] if adam else 1e-8
    # the stacked parameters and, per parameter, the wells' Adam states and step counts
    params: list[torch.nn.Parameter] = []
    own: list[list[torch.nn.Parameter]] = []  # per stacked parameter: each learner's own
    moments: list[tuple[torch.Tensor, torch.Tensor] | None] = []
    steps: list[list[float]] = []
    for where in trainable:
        mine = [stacked.tensor(lrn.model, where) for lrn in learners]
        params.append(stacked.tensor(model, where))  # type: ignore[arg-type]
        own.append(mine)  # type: ignore[arg-type]
        if not adam:
            moments.append(None)
            steps.append([])
            continue
        states = [opt.state.get(q) or {} for opt, q in zip(opts, mine, strict=True)]
        pairs = list(zip(states, mine, strict=True))
        moments.append(
            (
                torch.cat([st["exp_avg"] if st else torch.zeros_like(q) for st, q in pairs], 0),
                torch.cat([st["exp_avg_sq"] if st else torch.zeros_like(q) for st, q in pairs], 0),
            )
        )
        steps.append([float(st["step"]) if st else 0.0 for st in states])
    return _StackedOptimiser(
        opts=opts,
        adam=adam,
        lr=group["lr"],
        betas=betas,  # type: ignore[arg-type]
        eps=eps,
        params=params,
        own=own,
        moments=moments,
        steps=steps,
    )


def _compiled_stacked_steps(
    opt: _StackedOptimiser, model: ChokeModel, learners: list[OnlineLearning], batch: Batch
) -> None:
    """The E steps compiled, where the kernels take them for this model and optimiser
    (``opt.stepped`` set then; left at 0 otherwise)."""
    s = learners[0].online
    params, adam, k = opt.params, opt.adam, len(learners)
    lr, betas, eps, steps, moments = opt.lr, opt.betas, opt.eps, opt.steps, opt.moments
    if (compiled := _compiled_order(model, params)) is not None:
        order, run = compiled
        index = [[id(p) for p in params].index(id(q)) for q in order]
        before_all = np.array([steps[j] if adam else [0.0] * k for j in index], dtype=np.float64)
        run(  # the same steps, compiled
            model, batch, [moments[j] for j in index] if adam else None, before_all,
            np.zeros(k, dtype=bool), steps=s.steps, noise=s.noise, lr=lr, betas=betas, eps=eps,
            max_norm=s.max_grad_norm,
        )  # fmt: skip
        for j in index:
            opt.stepped[j] = s.steps
    elif (
        not adam
        and all(lrn._nn and lrn._compiled for lrn in learners)
        and _same_parameters(params, fit_parameters(model) or [])
    ):
        # the plain nn or lr with SGD: the same steps, compiled, as each learner's own
        # OnlineLearning takes them one by one
        sgd_online_steps(
            model, batch, np.zeros(k, dtype=bool), steps=s.steps, lr=lr, max_norm=s.max_grad_norm
        )
        opt.stepped = [s.steps] * len(params)


def _torch_stacked_steps(
    opt: _StackedOptimiser, model: ChokeModel, s: OnlineSettings, batch: Batch
) -> None:
    """The E steps in torch: the MAP objective's gradients, each well's clipping, the
    optimiser's step per well (SGD, or :meth:`_StackedOptimiser.adam_step_`), projection."""
    groups = split_parameters(model)
    objective = MapObjective(model, batch, s.noise, True, batch.count().to(DTYPE))
    for _ in range(s.steps):
        objective.gradients_(opt.params)
        clip_per_well_(model, s.max_grad_norm, groups)
        with torch.no_grad():
            for j, p in enumerate(opt.params):
                g = p.grad
                if g is None:  # no gradient this step: torch's Adam skips the parameter
                    continue
                opt.stepped[j] += 1
                if not opt.adam:
                    p.add_(g, alpha=-opt.lr)
                    continue
                opt.adam_step_(j, p, g)
        model.project_()


def _stacked_steps(
    stacked: StackedModel, learners: list[OnlineLearning], batch: Batch
) -> Callable[[], None]:
    """``ol``'s E optimiser steps (:meth:`OnlineLearning._learn`) on the stacked model, each
    well with its own Adam moments and step count (its own bias correction), its own
    gradient clipping and projection. Returns what writes the optimiser states back."""
    opt = _stacked_optimiser(stacked, learners)
    _compiled_stacked_steps(opt, stacked.model, learners, batch)
    if not opt.stepped[0]:
        _torch_stacked_steps(opt, stacked.model, learners[0].online, batch)
    return opt.write_back
