"""MAP training of a model on a batch: the initial fit and every retrain.

:func:`fit_batch` minimises the squared scaled error plus the prior penalty weighted by
sigma_eps^2 / N (paper eq. objective-function), with Adam or SGD on mini-batches, and
early stopping on the latest slice of each well's data: a first pass on all but that
slice finds the best number of iterations per well, a second pass from the same start on
all the data runs exactly that many (so the newest data are learned from, not only used
to stop). A periodic retrain, warm-started from the current parameters, runs the initial
fit's count at most and, on data that fit in one batch, stops a well earlier once its
objective has converged. Wells stay independent: losses, gradient clipping and iteration counts are per
well; only a shared model (``mtl``) couples them.
"""

from __future__ import annotations

import os
import time
import zlib
from dataclasses import asdict, dataclass, replace
from typing import Any

import torch
import torch.optim.optimizer as _torch_optimizer

from vfm_core.data import DTYPE, Batch
from vfm_core.errors import ConfigError
from vfm_core.models import MODELS, ChokeModel

__all__ = [
    "TrainSettings",
    "DEFAULT_TRAIN",
    "train_defaults",
    "fit_batch",
    "make_optimizer",
    "optimizer_step_",
    "plain_optimizer",
    "zero_grad_",
    "scaled_errors",
    "per_well_loss",
    "map_gradients_",
    "MapObjective",
    "clip_per_well_",
    "split_parameters",
    "well_generators",
    "settings_from_dict",
]


@dataclass(frozen=True)
class TrainSettings:
    """Batch (MAP) training: optimiser, learning rate, early stopping."""

    optimizer: str = "adam"
    lr: float = 1e-2
    max_iter: int = 400
    patience: int = 40
    val_fraction: float = 0.2
    #: iterations used for a well whose data are too few to hold out a slice
    default_iter: int = 100
    #: learning-rate schedule gamma_k = gamma_0 / k^power (0 = constant)
    schedule_power: float = 0.0
    #: relative measurement noise sigma_eps (weights the prior against the data)
    noise: float = 0.05
    #: a periodic retrain (warm start) runs the initial fit's early-stopped iteration
    #: count per well, at most this many
    retrain_max_iter: int = 150
    #: a retrain also stops a well once its objective has converged: the mean objective
    #: of a block of ``retrain_check`` iterations has not fallen below the best block's by
    #: this relative amount for two blocks in a row (0: no convergence stop, every retrain
    #: runs its full count). 1 % of the objective is half a percent of the root-mean-square
    #: error. Only a retrain whose data fit in one batch (``batch_size`` per well) stops so:
    #: there the objective is exact, while on mini-batches their noise would stop it before
    #: it has converged (a warm-started retrain of ``lr`` then lost 0.1 pp of MAPE)
    retrain_tol: float = 1e-2
    #: iterations per block of the retrain's convergence test
    retrain_check: int = 10
    #: per-well cap on the gradient norm: inputs that drifted far from the training
    #: statistics must not blow a step up
    max_grad_norm: float = 10.0
    #: samples per well in each step's mini-batch, drawn at random from the well's data
    #: (0 = full batch); the cost of a step then stays flat as history grows
    batch_size: int = 256
    seed: int = 0
    #: False: no held-out slice; every initial fit runs ``max_iter`` iterations (for models
    #: whose priors are their regulariser, on data whose latest slice is not like the rest)
    early_stopping: bool = True
    #: wall-clock budget of one fit, seconds (0: none): past it the fit stops where it is,
    #: keeping every parameter it has reached (a service must never wait on a retrain)
    time_budget_s: float = 0.0


def train_defaults(model: ChokeModel | type[ChokeModel]) -> TrainSettings:
    """The batch settings a model starts from: its class's ``train_defaults``."""
    return TrainSettings(**model.train_defaults)


#: Batch defaults per registered model, by name: each model's own ``train_defaults``
#: (see :attr:`vfm_core.models.base.ChokeModel.train_defaults`)
DEFAULT_TRAIN: dict[str, TrainSettings] = {
    name: train_defaults(cls) for name, cls in MODELS.items()
}


def make_optimizer(
    params: list[torch.nn.Parameter], kind: str, lr: float, power: float
) -> tuple[torch.optim.Optimizer, torch.optim.lr_scheduler.LRScheduler | None]:
    if kind == "adam":
        opt: torch.optim.Optimizer = torch.optim.Adam(params, lr=lr)
    elif kind == "sgd":
        opt = torch.optim.SGD(params, lr=lr)
    else:
        raise ConfigError(f"Unknown optimizer '{kind}'; choose 'adam' or 'sgd'.")
    sched = None
    if power > 0:
        sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda k: 1.0 / (k + 1) ** power)
    return opt, sched


def _plain(opt: torch.optim.Optimizer) -> bool:
    """True for an optimiser :func:`optimizer_step_` can step itself: make_optimizer's
    Adam or SGD with torch's defaults otherwise, on CPU, and no step hooks."""
    if opt._optimizer_step_pre_hooks or opt._optimizer_step_post_hooks:  # type: ignore[attr-defined]
        return False
    if _torch_optimizer._global_optimizer_pre_hooks or (
        _torch_optimizer._global_optimizer_post_hooks
    ):
        return False
    for group in opt.param_groups:
        if group.get("weight_decay", 0) != 0 or group.get("maximize") or group.get("foreach"):
            return False
        if group.get("differentiable") or group.get("fused") or group.get("capturable"):
            return False
        if not isinstance(group["lr"], float) or any(p.is_cuda for p in group["params"]):
            return False
        if isinstance(opt, torch.optim.Adam):
            if group["amsgrad"] or group.get("decoupled_weight_decay"):
                return False
            if not all(isinstance(b, float) for b in group["betas"]):
                return False
        elif isinstance(opt, torch.optim.SGD):
            if group["momentum"] != 0 or group.get("nesterov"):
                return False
        else:
            return False
    return True


def plain_optimizer(opt: torch.optim.Optimizer) -> bool:
    """True for an optimiser :func:`optimizer_step_` steps itself (:func:`_plain`), asked
    once per optimiser."""
    plain = getattr(opt, "_vfm_plain", None)
    if plain is None:
        plain = _plain(opt)
        opt._vfm_plain = plain  # type: ignore[attr-defined]
    return bool(plain)


def zero_grad_(params: list[torch.nn.Parameter]) -> None:
    """``optimizer.zero_grad()`` (gradients set to None) without its per-call machinery."""
    for p in params:
        p.grad = None


def optimizer_step_(opt: torch.optim.Optimizer) -> None:
    """``opt.step()`` for the plain Adam and SGD of :func:`make_optimizer`, cheaper.

    The learners take thousands of steps on tensors of a few numbers, where torch.optim's
    per-call machinery (hooks, profiler records, grad-mode switches) costs more than the
    arithmetic. This is the same arithmetic as torch's single-tensor Adam and SGD (results
    identical to the bit), on the optimiser's own state, so ``opt.state_dict()`` is what
    ``opt.step()`` would leave. Any other optimiser or option goes through ``opt.step()``.
    """
    if not plain_optimizer(opt):
        opt.step()
        return
    with torch.no_grad():
        adam = isinstance(opt, torch.optim.Adam)
        for group in opt.param_groups:
            lr = group["lr"]
            params = [p for p in group["params"] if p.grad is not None]
            if not params:
                continue
            grads = [p.grad for p in params]
            if not adam:
                torch._foreach_add_(params, grads, alpha=-lr)
                continue
            # torch's single-tensor Adam, elementwise, on every parameter at once (the
            # _foreach ops do the same arithmetic per element: the same bits)
            beta1, beta2 = group["betas"]
            states = [opt.state[p] for p in params]
            for p, state in zip(params, states, strict=True):
                if len(state) == 0:
                    state["step"] = torch.tensor(0.0, dtype=_torch_optimizer._get_scalar_dtype())
                    state["exp_avg"] = torch.zeros_like(p, memory_format=torch.preserve_format)
                    state["exp_avg_sq"] = torch.zeros_like(p, memory_format=torch.preserve_format)
            steps = [st["step"] for st in states]
            exp_avgs = [st["exp_avg"] for st in states]
            exp_avg_sqs = [st["exp_avg_sq"] for st in states]
            torch._foreach_add_(steps, 1.0)
            torch._foreach_lerp_(exp_avgs, grads, 1 - beta1)
            torch._foreach_mul_(exp_avg_sqs, beta2)
            torch._foreach_addcmul_(exp_avg_sqs, grads, grads, value=1 - beta2)
            counts = [t.item() for t in steps]
            if len(set(counts)) == 1:
                groups_by_step = [(counts[0], list(range(len(params))))]
            else:  # parameters that missed steps (no gradient then): each its own count
                groups_by_step = [
                    (c, [i for i, v in enumerate(counts) if v == c]) for c in set(counts)
                ]
            for step, idx in groups_by_step:
                bias_correction1 = 1 - beta1**step
                bias_correction2 = 1 - beta2**step
                step_size = lr / bias_correction1
                sqs = [exp_avg_sqs[i] for i in idx]
                denom = torch._foreach_sqrt(sqs)
                torch._foreach_div_(denom, bias_correction2**0.5)
                torch._foreach_add_(denom, group["eps"])
                torch._foreach_addcdiv_(
                    [params[i] for i in idx], [exp_avgs[i] for i in idx], denom, value=-step_size
                )


def scaled_errors(model: ChokeModel, batch: Batch) -> torch.Tensor:
    """(prediction - measurement) / rate scale per sample [W, N], zero where padded."""
    q = model.forward_batch(batch)
    e = (q - batch.y) / model.y_scale.unsqueeze(1)
    return torch.where(batch.mask, e, torch.zeros_like(e))


def per_well_loss(
    model: ChokeModel,
    batch: Batch,
    noise: float,
    physical_only: bool,
    n: torch.Tensor | None = None,
) -> torch.Tensor:
    """MAP objective per well [W]: mean squared scaled error + sigma^2/N prior penalty.

    ``n``: ``batch.count()`` as floats, when the caller steps many times on one batch."""
    n = batch.count().to(DTYPE) if n is None else n
    n_safe = n.clamp(min=1.0)
    e = scaled_errors(model, batch)
    mse = (e**2).sum(1) / n_safe
    prior = model.prior_penalty(physical_only=physical_only) * noise**2 / n_safe
    return torch.where(n > 0, mse + prior, torch.zeros_like(mse))


class MapObjective:
    """The per-well MAP objective of ``model`` on one batch, ready to be differentiated many
    times (the E steps of an online update are on one measurement): the mean squared scaled
    error over ``n_data`` samples (default ``n``, as floats) plus the prior penalty weighted
    by sigma^2 / ``n``; zero for a well with ``n`` = 0.

    A model with closed-form gradients (``model.rate_vjp``) is stepped without autograd,
    whose per-call machinery costs more than the arithmetic on these small tensors, and
    what depends on the batch alone is taken once here; any other model goes through
    autograd (:func:`per_well_loss`'s objective): the same numbers up to rounding.
    """

    def __init__(
        self,
        model: ChokeModel,
        batch: Batch,
        noise: float,
        physical_only: bool,
        n: torch.Tensor,
        n_data: torch.Tensor | None = None,
    ) -> None:
        self.model, self.batch, self.noise, self.physical_only = model, batch, noise, physical_only
        self.n = n
        self.n_data = n if n_data is None else n_data
        with torch.no_grad():
            self.has = n > 0
            self.scale = model.y_scale.unsqueeze(1)
            self.n_safe = self.n_data.clamp(min=1.0)
            self.weight = torch.where(self.has, noise**2 / n.clamp(min=1.0), 0.0)
            # d loss / d rate = e * this (e the scaled error, zero where padded)
            self.d_factor = torch.where(self.has, 2.0 / self.n_safe, 0.0).unsqueeze(1) / self.scale

    def gradients_(self, params: list[torch.nn.Parameter]) -> torch.Tensor:
        """Set every parameter's ``.grad`` to the gradient of the objective's sum; returns
        the objective per well [W] (no graph)."""
        model, batch = self.model, self.batch
        closed = model.rate_vjp(batch)
        if closed is None:
            zero_grad_(params)
            e = scaled_errors(model, batch)
            mse = (e**2).sum(1) / self.n_safe
            prior = model.prior_penalty(physical_only=self.physical_only) * self.weight
            loss = torch.where(self.has, mse + prior, torch.zeros_like(mse))
            loss.sum().backward()
            return loss.detach()
        q, pullback = closed
        with torch.no_grad():
            e = torch.where(batch.mask, (q - batch.y) / self.scale, 0.0)
            loss = (e * e).sum(1) / self.n_safe
            loss = loss + model.prior_penalty(physical_only=self.physical_only) * self.weight
            loss = torch.where(self.has, loss, 0.0)
            grads = pullback(e * self.d_factor)
            for pid, g in model.prior_gradients(self.weight, self.physical_only).items():
                grads[pid] = grads[pid] + g if pid in grads else g
            for p in params:
                got = grads.get(id(p))
                p.grad = torch.zeros_like(p) if got is None else got.reshape(p.shape)
        return loss


def map_gradients_(
    model: ChokeModel,
    params: list[torch.nn.Parameter],
    batch: Batch,
    noise: float,
    physical_only: bool,
    n: torch.Tensor,
    n_data: torch.Tensor | None = None,
) -> torch.Tensor:
    """``MapObjective(model, batch, noise, physical_only, n, n_data).gradients_(params)``:
    the per-well MAP objective [W] (no graph), every parameter's ``.grad`` set."""
    return MapObjective(model, batch, noise, physical_only, n, n_data).gradients_(params)


def well_generators(wells: list[str], seed: int) -> list[torch.Generator]:
    """One random stream per well, keyed by its name: a well's mini-batches are the same
    whether it is trained alone (the service) or with the whole field (the study)."""
    return [torch.Generator().manual_seed(zlib.crc32(w.encode()) ^ seed) for w in wells]


def _minibatch(batch: Batch, size: int, gens: list[torch.Generator]) -> tuple[Batch, torch.Tensor]:
    """A random mini-batch of ``size`` samples per well (with replacement), and the full counts.

    Samples of a batch are left-aligned per well, so a uniform index below the well's
    count picks one of its samples. A well with at most ``size`` samples uses all of them.
    """
    counts = batch.count()
    if size <= 0 or int(counts.max()) <= size:
        return batch, counts
    rows = []
    for j, gen in enumerate(gens):
        if int(counts[j]) > size:
            u = torch.rand(size, generator=gen, dtype=DTYPE)
            rows.append(torch.floor(u * float(counts[j])).to(torch.int64))
        else:
            rows.append(torch.arange(size, dtype=torch.int64))
    idx = torch.stack(rows)
    has = (idx < counts.unsqueeze(1)) & (counts > 0).unsqueeze(1)
    idx = torch.minimum(idx, (counts - 1).clamp(min=0).unsqueeze(1))
    x = torch.gather(batch.x, 1, idx.unsqueeze(-1).expand(-1, -1, batch.x.shape[-1]))
    assert batch.well_test is not None and batch.extra is not None
    ex = torch.gather(batch.extra, 1, idx.unsqueeze(-1).expand(-1, -1, batch.extra.shape[-1]))
    return Batch(
        batch.wells,
        x,
        torch.gather(batch.y, 1, idx),
        has.clone(),
        torch.gather(batch.time_ns, 1, idx),
        torch.gather(batch.row, 1, idx),
        torch.gather(batch.well_test, 1, idx),
        ex,
        batch.extra_names,
    ), counts


class _Sampler:
    """:func:`_minibatch` for many iterations, drawn and gathered a chunk of iterations at a
    time: the same random numbers in the same order (a well's stream drawn in one call is
    its draws one at a time, concatenated), so the same mini-batches, at a fraction of the
    per-iteration calls. :meth:`finish` leaves every generator where :func:`_minibatch`
    would have after the iterations taken, so a later pass continues the same streams."""

    #: samples per chunk and well at most, summed over wells (bounds the chunk's memory)
    _CHUNK_SAMPLES = 1 << 20

    def __init__(self, batch: Batch, size: int, gens: list[torch.Generator]) -> None:
        self.batch, self.size, self.gens = batch, size, gens
        self.counts = batch.count()
        self.full = size <= 0 or int(self.counts.max()) <= size
        # a full batch draws nothing (size 0 means the whole batch at every step)
        self.draws = (
            [] if self.full else [j for j in range(len(gens)) if int(self.counts[j]) > size]
        )
        self.start = {j: gens[j].get_state() for j in self.draws} if not self.full else {}
        self.chunk = max(1, min(16, self._CHUNK_SAMPLES // max(batch.n_wells * size, 1)))
        self.taken = 0
        self._queue: list[Batch] = []
        self._rows: tuple[torch.Tensor, ...] | None = None  # take()'s last draw

    def _draw(self, c: int) -> tuple[torch.Tensor, torch.Tensor]:
        """The rows of ``c`` iterations' mini-batches [W, c size] (each well's draws from
        its own stream, or all its rows when they fit in one), clamped into its samples,
        and which of them are samples (``has``)."""
        size, counts = self.size, self.counts
        rows = []
        for j, gen in enumerate(self.gens):
            if int(counts[j]) > size:
                u = torch.rand(size * c, generator=gen, dtype=DTYPE)
                rows.append(torch.floor(u * float(counts[j])).to(torch.int64))
            else:
                rows.append(torch.arange(size, dtype=torch.int64).repeat(c))
        idx = torch.stack(rows)
        has = (idx < counts.unsqueeze(1)) & (counts > 0).unsqueeze(1)
        return torch.minimum(idx, (counts - 1).clamp(min=0).unsqueeze(1)), has

    def _refill(self) -> None:
        size, c, batch = self.size, self.chunk, self.batch
        idx, has = self._draw(c)
        assert batch.well_test is not None and batch.extra is not None
        x = torch.gather(batch.x, 1, idx.unsqueeze(-1).expand(-1, -1, batch.x.shape[-1]))
        ex = torch.gather(batch.extra, 1, idx.unsqueeze(-1).expand(-1, -1, batch.extra.shape[-1]))
        y = torch.gather(batch.y, 1, idx)
        t = torch.gather(batch.time_ns, 1, idx)
        r = torch.gather(batch.row, 1, idx)
        wt = torch.gather(batch.well_test, 1, idx)
        for i in range(c):
            sl = slice(i * size, (i + 1) * size)
            self._queue.append(
                Batch(
                    batch.wells,
                    x[:, sl],
                    y[:, sl],
                    has[:, sl],
                    t[:, sl],
                    r[:, sl],
                    wt[:, sl],
                    ex[:, sl],
                    batch.extra_names,
                )
            )
        self._queue.reverse()

    def take(self, limit: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, int, bool]:
        """The next iterations' mini-batches at once, for a compiled loop: ``x`` [W, c size,
        6], ``y`` and ``has`` [W, c size] (iteration i in columns [i size, (i + 1) size)),
        c (at most ``limit``), and False; or, when every well fits in one batch, the whole
        batch for ``limit`` iterations and True. The same draws as :meth:`next`."""
        batch = self.batch
        if self.full:
            return batch.x, batch.y, batch.mask, max(int(limit), 0), True
        assert not self._queue, "take() and next() do not mix"
        c = max(1, min(int(limit), self.chunk))
        idx, has = self._draw(c)
        x = torch.gather(batch.x, 1, idx.unsqueeze(-1).expand(-1, -1, batch.x.shape[-1]))
        self.taken += c
        y = torch.gather(batch.y, 1, idx)
        self._rows = (idx, has, x, y)
        return x, y, has, c, False

    def taken_batch(self) -> Batch:
        """The samples of the last :meth:`take` as one batch [W, c size] (every column of
        it: times, well tests, feature columns, for a model with effects), or the whole
        batch when every well fits in one."""
        if self.full or self._rows is None:
            return self.batch
        idx, has, x, y = self._rows
        batch = self.batch
        assert batch.well_test is not None and batch.extra is not None
        ex = torch.gather(batch.extra, 1, idx.unsqueeze(-1).expand(-1, -1, batch.extra.shape[-1]))
        return Batch(
            batch.wells,
            x,
            y,
            has,
            torch.gather(batch.time_ns, 1, idx),
            torch.gather(batch.row, 1, idx),
            torch.gather(batch.well_test, 1, idx),
            ex,
            batch.extra_names,
        )

    def next(self) -> tuple[Batch, torch.Tensor]:
        """The next iteration's mini-batch and the full counts per well."""
        if self.full:
            return self.batch, self.counts
        if not self._queue:
            self._refill()
        self.taken += 1
        return self._queue.pop(), self.counts

    def finish(self) -> None:
        """Rewind the generators to just after the iterations taken (the chunk drew ahead)."""
        for j in self.draws:
            gen = self.gens[j]
            gen.set_state(self.start[j])
            if self.taken:
                torch.rand(self.size * self.taken, generator=gen, dtype=DTYPE)
        self._queue = []


def _map_step_gradients(
    model: ChokeModel,
    params: list[torch.nn.Parameter],
    sampler: _Sampler,
    settings: TrainSettings,
) -> torch.Tensor:
    """Per-well MAP objective [W] on the next mini-batch, gradients set
    (:func:`map_gradients_`); the prior is weighted by the full count."""
    mb, counts = sampler.next()
    n = counts.to(DTYPE)
    return map_gradients_(model, params, mb, settings.noise, False, n, n_data=mb.count().to(DTYPE))


def _compiled_fit(
    model: ChokeModel, params: list[torch.nn.Parameter], opt: torch.optim.Optimizer
) -> Any:
    """:class:`vfm_core.learning.kernels.FitSteps` for ``model`` when the kernels compute its
    training steps and ``params`` are exactly the ones they train; else None."""
    from vfm_core.learning import kernels

    if os.environ.get("VFM_FIT_KERNEL", "1") == "0":
        return None
    if model.shared:  # the plain mtl: the field's steps together (kernels.MtlFitSteps)
        if not kernels.plain_mtl(model) or kernels._lazy("mtl_fit_steps") is None:
            return None
        ordered = kernels.mtl_parameters(model)
        if len(ordered) != len(params) or {id(p) for p in ordered} != {id(p) for p in params}:
            return None
        return kernels.MtlFitSteps(model, ordered, opt)
    own = kernels.fit_parameters(model)
    if own is None or {id(p) for p in own} != {id(p) for p in params}:
        return None
    if len(own) != len(params):
        return None
    return kernels.FitSteps(model, own, opt)


def _split_latest(batch: Batch, fraction: float) -> tuple[Batch, Batch, torch.Tensor]:
    """Hold out the latest ``fraction`` of each well's samples (by time) for early stopping."""
    counts = batch.count()
    n_val = torch.floor(counts.to(DTYPE) * fraction).to(torch.int64)
    n_val = torch.where(counts >= 5, n_val.clamp(min=1), torch.zeros_like(n_val))
    rank = torch.cumsum(batch.mask.to(torch.int64), dim=1) - 1
    is_val = batch.mask & (rank >= (counts - n_val).unsqueeze(1))
    return batch.select(batch.mask & ~is_val), batch.select(is_val), n_val > 0


def _snapshot(params: list[torch.nn.Parameter]) -> list[torch.Tensor]:
    return [p.detach().clone() for p in params]


def split_parameters(
    model: ChokeModel,
) -> tuple[list[torch.nn.Parameter], list[torch.nn.Parameter]]:
    """The model's parameters with a leading well dimension, and the shared ones."""
    per_well = model.per_well_parameters()
    ids = set(map(id, per_well))
    return per_well, [p for p in model.parameters() if id(p) not in ids]


def clip_per_well_(
    model: ChokeModel,
    max_norm: float,
    parameters: tuple[list[torch.nn.Parameter], list[torch.nn.Parameter]] | None = None,
) -> None:
    """Scale each well's gradient down to norm ``max_norm`` (wells stay independent).

    ``parameters``: :func:`split_parameters` of the model, when the caller steps often."""
    per_well, shared_all = split_parameters(model) if parameters is None else parameters
    grads = [p.grad for p in per_well if p.grad is not None]
    if grads:
        n_w = grads[0].shape[0]
        flat = (
            grads[0].reshape(n_w, -1)
            if len(grads) == 1
            else torch.cat([g.reshape(n_w, -1) for g in grads], dim=1)
        )
        sq = (flat * flat).sum(1)
        scale = (max_norm / (torch.sqrt(sq) + 1e-12)).clamp(max=1.0)
        torch._foreach_mul_(grads, [scale.reshape(-1, *([1] * (g.dim() - 1))) for g in grads])
    shared = [p for p in shared_all if p.grad is not None]
    if shared:
        torch.nn.utils.clip_grad_norm_(shared, max_norm)


#: blocks in a row without improvement that end a retrain (see ``TrainSettings.retrain_tol``)
_RETRAIN_PATIENCE = 2


@dataclass
class _Fit:
    """What the two passes of :func:`fit_batch` share: the model, its trainable parameters
    (``groups``: :func:`split_parameters`), the settings, each well's random stream, the
    time limit (``time.monotonic()``; None: none) and whether it was reached."""

    model: ChokeModel
    params: list[torch.nn.Parameter]
    groups: tuple[list[torch.nn.Parameter], list[torch.nn.Parameter]]
    settings: TrainSettings
    gens: list[torch.Generator]
    deadline: float | None
    timed_out: bool = False

    def optimiser(self) -> tuple[torch.optim.Optimizer, Any]:
        """A fresh optimiser over the parameters and its learning-rate schedule (or None)."""
        s = self.settings
        return make_optimizer(self.params, s.optimizer, s.lr, s.schedule_power)

    def compiled(self, opt: torch.optim.Optimizer, sched: Any) -> Any:
        """The kernels' compiled steps for ``opt`` (:func:`_compiled_fit`), or None where
        they do not take them (a time limit, a schedule, an optimiser with hooks)."""
        if self.deadline is not None or sched is not None or not plain_optimizer(opt):
            return None
        return _compiled_fit(self.model, self.params, opt)

    def step(self, sampler: _Sampler, opt: torch.optim.Optimizer, sched: Any) -> torch.Tensor:
        """One MAP step on the next mini-batch (gradients, each well's clipping, the
        optimiser's step, the schedule, projection); returns the per-well objective [W]."""
        loss = _map_step_gradients(self.model, self.params, sampler, self.settings)
        clip_per_well_(self.model, self.settings.max_grad_norm, self.groups)
        optimizer_step_(opt)
        if sched is not None:
            sched.step()
        self.model.project_()
        return loss

    def out_of_time(self) -> bool:
        """Whether the time limit has passed."""
        return self.deadline is not None and time.monotonic() > self.deadline


def _iteration_plan(
    model: ChokeModel,
    batch: Batch,
    settings: TrainSettings,
    iterations: torch.Tensor | None,
    rechoose: torch.Tensor | None,
    has_val: torch.Tensor,
) -> tuple[TrainSettings, torch.Tensor | None, torch.Tensor, torch.Tensor]:
    """``(settings, iterations, best_iter, has_val)`` before the passes: the iteration
    counts given (an initial fit without early stopping runs ``max_iter`` in full), each
    well's count to start from, and which wells early stopping searches a count for."""
    n_w = batch.n_wells
    best_iter = torch.full((n_w,), settings.default_iter, dtype=torch.int64)
    # a periodic retrain (warm start, the iteration counts given) may stop on convergence;
    # an initial fit without early stopping runs its max_iter in full ("to convergence")
    if iterations is None and not settings.early_stopping:
        iterations = torch.full((n_w,), settings.max_iter, dtype=torch.int64)
        settings = replace(
            settings, retrain_max_iter=max(settings.retrain_max_iter, settings.max_iter)
        )
    if iterations is not None:
        fallback = torch.full_like(iterations, settings.default_iter)
        best_iter = torch.where(iterations > 0, iterations, fallback).clamp(
            max=settings.retrain_max_iter
        )
        if rechoose is None or not settings.early_stopping:
            has_val = torch.zeros_like(has_val)
        else:
            again = rechoose & (batch.count() > 0)
            has_val = has_val & (again.any() if model.shared else again)
    return settings, iterations, best_iter, has_val


def _validation_loss(model: ChokeModel, val: Batch, has_val: torch.Tensor) -> torch.Tensor:
    """Mean squared scaled error on ``val`` per well [W] (for shared parameters the sum over
    the wells with a held-out slice, for every well: one early-stopping decision)."""
    with torch.no_grad():
        v = (scaled_errors(model, val) ** 2).sum(1) / val.count().clamp(min=1)
        if model.shared:  # one early-stopping decision for shared parameters
            total = torch.where(has_val, v, torch.zeros_like(v)).sum()
            v = torch.full_like(v, float(total))
    return v


def _choose_iterations(
    fit: _Fit,
    train: Batch,
    val: Batch,
    has_val: torch.Tensor,
    best_iter: torch.Tensor,
    retrain: bool,
) -> torch.Tensor:
    """Pass 1: each ``has_val`` well's iteration count chosen by early stopping on its
    held-out latest slice ``val`` (training on ``train``); the other wells keep
    ``best_iter``. The parameters are put back where they started."""
    s = fit.settings
    start = _snapshot(fit.params)
    given = best_iter.clone()
    opt, sched = fit.optimiser()
    n_w = len(best_iter)
    best_loss = torch.full((n_w,), float("inf"), dtype=DTYPE)
    since = torch.zeros(n_w, dtype=torch.int64)
    # a retrain that chooses some wells' counts again leaves the others' random streams
    # where they were: their pass 2 is the one they would have had without the search
    kept = (
        [(g, g.get_state()) for g, v in zip(fit.gens, has_val.tolist(), strict=True) if not v]
        if retrain
        else []
    )
    sampler = _Sampler(train, s.batch_size, fit.gens)
    # a retrain runs at most retrain_max_iter: looking further for its count is waste
    search = min(s.max_iter, s.retrain_max_iter) if retrain else s.max_iter
    compiled = fit.compiled(opt, sched)
    if compiled is not None:  # the same steps without a torch call each (kernels.FitSteps)
        best_iter = compiled.search(
            sampler, val, has_val, best_iter, search, s.patience, s.noise, s.max_grad_norm
        )
        search = 0  # done: the loop below has nothing left to run
    for k in range(1, search + 1):
        fit.step(sampler, opt, sched)
        v = _validation_loss(fit.model, val, has_val)
        improved = has_val & (v < best_loss - 1e-12)
        best_loss = torch.where(improved, v, best_loss)
        best_iter = torch.where(improved, torch.full_like(best_iter, k), best_iter)
        since = torch.where(improved, torch.zeros_like(since), since + 1)
        if bool((since[has_val] >= s.patience).all()):
            break
        if fit.out_of_time():
            fit.timed_out = True
            break
    sampler.finish()  # pass 2 continues each well's random stream
    for gen, state in kept:
        gen.set_state(state)
    for p, s0 in zip(fit.params, start, strict=True):
        p.data.copy_(s0)
    return torch.where(has_val, best_iter, given)


@dataclass
class _Convergence:
    """A retrain's stop on convergence: the per-well objective summed over blocks of
    ``check`` steps; a well stops once :data:`_RETRAIN_PATIENCE` blocks in a row improved
    its best block mean by less than ``tol`` (relative; one decision for shared parameters)."""

    n_wells: int
    check: int
    tol: float
    shared: bool

    def __post_init__(self) -> None:
        self.block = torch.zeros(self.n_wells, dtype=DTYPE)
        self.best_block = torch.full((self.n_wells,), float("inf"), dtype=DTYPE)
        self.stale = torch.zeros(self.n_wells, dtype=torch.int64)

    def after_step(
        self, k: int, loss: torch.Tensor, best_iter: torch.Tensor, total_iter: int
    ) -> tuple[torch.Tensor, int]:
        """After step ``k`` with per-well objective ``loss``: ``(best_iter, total_iter)``,
        the wells that converged stopping at ``k``."""
        self.block += loss.detach()
        if k % self.check == 0 and k < total_iter:
            mean = self.block / self.check
            if self.shared:  # one decision for shared parameters, as in early stopping
                mean = torch.full_like(mean, float(mean.sum()))
            improved = mean < self.best_block * (1.0 - self.tol)
            self.best_block = torch.minimum(self.best_block, mean)
            self.stale = torch.where(improved, torch.zeros_like(self.stale), self.stale + 1)
            stop = (self.stale >= _RETRAIN_PATIENCE) & (best_iter > k)
            if bool(stop.any()):
                best_iter = torch.where(stop, torch.full_like(best_iter, k), best_iter)
                total_iter = int(best_iter.max())
            self.block.zero_()
        return best_iter, total_iter


def _train_to_counts(
    fit: _Fit, batch: Batch, best_iter: torch.Tensor, retrain: bool
) -> torch.Tensor:
    """Pass 2: from the start, on all of ``batch``, each well for its count ``best_iter``
    (a retrain also stops a well once it has converged; the time limit stops every well
    still running); each well ends at its own count. Returns the counts run."""
    model, s, params = fit.model, fit.settings, fit.params
    if model.shared:
        best_iter = torch.full_like(best_iter, int(best_iter.max()))
    per_well = set(map(id, model.per_well_parameters()))
    opt, sched = fit.optimiser()
    final = _snapshot(params)
    total_iter = int(best_iter.max())
    # a retrain (warm start) also stops each well once its objective has converged
    check = max(int(s.retrain_check), 1)
    sampler = _Sampler(batch, s.batch_size, fit.gens)
    # on mini-batches the blocks' means are noisy: only an exact objective stops a retrain
    converge = retrain and s.retrain_tol > 0 and total_iter > 2 * check and sampler.full
    watch = _Convergence(len(best_iter), check, s.retrain_tol, model.shared)
    compiled = fit.compiled(opt, sched)
    if compiled is not None:  # the same steps without a torch call each (kernels.FitSteps)
        stops = (check, s.retrain_tol, _RETRAIN_PATIENCE) if converge else None
        best_iter = compiled.run(sampler, best_iter, s.noise, s.max_grad_norm, stops)
        total_iter = 0  # each well stopped at its own count: nothing to restore below
    for k in range(1, total_iter + 1):
        loss = fit.step(sampler, opt, sched)
        if converge:
            best_iter, total_iter = watch.after_step(k, loss, best_iter, total_iter)
        if k < total_iter and fit.out_of_time():
            # out of time: every well still running stops here, where it is
            fit.timed_out = True
            best_iter = best_iter.clamp(max=k)
            total_iter = k
        done = best_iter == k
        if bool(done.any()):
            for p, f in zip(params, final, strict=True):
                if id(p) in per_well:
                    f[done] = p.detach()[done]
        if k >= total_iter:
            break
    for p, f in zip(params, final, strict=True):
        if id(p) in per_well and compiled is None:
            # wells that stopped early keep their snapshot; the rest end at total_iter
            keep = best_iter < total_iter
            p.data[keep] = f[keep]
    return best_iter


def fit_batch(
    model: ChokeModel,
    batch: Batch,
    settings: TrainSettings,
    iterations: torch.Tensor | None = None,
    wells: torch.Tensor | None = None,
    rechoose: torch.Tensor | None = None,
) -> dict[str, Any]:
    """MAP-train ``model`` on ``batch`` from its current parameters (a warm start).

    With ``iterations`` [W] given (a periodic retrain), early stopping is skipped and each
    well runs that many iterations (capped by ``retrain_max_iter``), or, when the data fit
    in one batch, fewer once its objective has converged (``retrain_tol``: running on only
    costs time). ``wells`` [W] (bool)
    retrains only those wells (the others keep their parameters; shared parameters always
    train). ``rechoose`` [W] (bool, with ``iterations``): wells whose iteration count this
    retrain chooses again by early stopping, as the initial fit did (from the warm start, on
    the latest slice held out). Returns a summary with ``iterations``, the count per well
    run, ``chosen``, early stopping's choice per well (the count given where it did not
    run), and ``searched``, the wells it ran for [W] (bool), for later retrains.
    """
    deadline = time.monotonic() + settings.time_budget_s if settings.time_budget_s > 0 else None
    if wells is not None and not model.shared:
        # the other wells are not this fit's to touch, their set-up included: in the study a
        # refit reads the memory up to its own time, which for a well that runs behind in its
        # rounds holds measurements it has not reached (a young well was set up on its own
        # later well tests, and its first forecast was its measurement)
        batch = batch.select(batch.mask & wells.unsqueeze(1))
    model.setup(batch)
    if model.gradient_free:
        model.observe(batch)
        return {"iterations": torch.zeros(batch.n_wells, dtype=torch.int64)}
    if int(batch.count().sum()) == 0:
        return {"iterations": torch.zeros(batch.n_wells, dtype=torch.int64)}
    params = [p for p in model.parameters() if p.requires_grad]
    groups = split_parameters(model)
    gens = well_generators(batch.wells, settings.seed)
    train, val, has_val = _split_latest(batch, settings.val_fraction)
    retrain = iterations is not None
    settings, iterations, best_iter, has_val = _iteration_plan(
        model, batch, settings, iterations, rechoose, has_val
    )
    fit = _Fit(model, params, groups, settings, gens, deadline)
    # pass 1: find the best iteration count on the held-out latest slice
    if bool(has_val.any()):
        best_iter = _choose_iterations(fit, train, val, has_val, best_iter, retrain)
    chosen = (
        torch.where(has_val, best_iter, iterations)
        if retrain and iterations is not None
        else best_iter.clone()
    )
    if retrain:
        best_iter = best_iter.clamp(max=settings.retrain_max_iter)
    # pass 2: from the same start, on all data, each well for its chosen iteration count
    best_iter = _train_to_counts(fit, batch, best_iter, retrain)
    return {
        "iterations": best_iter,
        "chosen": chosen,
        "searched": has_val,
        "timed_out": fit.timed_out,
    }


def settings_from_dict(base: Any, overrides: dict[str, Any]) -> Any:
    """Apply JSON overrides to a settings dataclass, with a clear error for unknown keys."""
    valid = set(asdict(base))
    unknown = set(overrides) - valid
    if unknown:
        raise ConfigError(f"Unknown settings {sorted(unknown)}; valid ones are {sorted(valid)}.")
    return replace(base, **overrides)
