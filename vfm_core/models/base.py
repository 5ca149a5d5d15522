"""The model protocol every choke model implements, and the parameter blocks models share.

A model is an ``nn.Module`` batched over wells: well j's parameters sit at index j of a
leading well dimension (except the shared network of ``mtl``), so one optimiser step
updates every well at once and independently. The protocol:

- ``setup(batch)``: statistics taken from training data (input normalisation, the rate
  scale, the choke's full-open area of the mechanistic models); wells already set up are
  left alone, so it can be called again as new wells appear.
- ``forward_batch(batch) -> q``: predicted total rate [W, N] in Sm3/h for a
  :class:`vfm_core.data.Batch` (inputs in file units, plus time, source and feature
  columns for the models that need them); ``forward(x)`` for the six inputs alone.
- ``predict(x)`` / ``predict_batch(batch)``: the same without gradients, NaN for wells
  not set up yet (a model with no data says so instead of guessing).
- ``prior_penalty(physical_only)``: sum over parameters of ((theta - mu)/sigma)^2 per
  well, the negative log Gaussian prior of MAP training (He initialisation's variance is
  the prior of network weights, centred on zero).
- ``project_()``: clamp physical parameters into their bounds after each step.
- ``observe(batch)``: learning without gradients (the ``last`` benchmark only).
- ``physical_parameters()``: named physical parameters in SI units, per well.
- ``filter_blocks()``: the per-well parameters a Bayesian learning method tracks, with
  their prior variances, their drift per year and their SI scale (:class:`FilterBlock`).
- ``state_dict()`` / ``load_state_dict()`` hold tensors only; hyperparameters are the
  constructor's keyword arguments (``model.hyper``, JSON). No pickle anywhere.
- Optional, for speed: ``rate_vjp(batch)`` gives the rate with its gradient in closed form
  (a pullback from d loss / d rate to every parameter's gradient) and
  ``prior_gradients(weight, physical_only)`` the prior penalty's; the learners then step
  without autograd (:func:`vfm_core.learning.training.map_gradients_`). A model without
  them (the default ``None``), or with effects, is differentiated by autograd, the same
  numbers up to rounding (``tests/test_learning_speed.py`` checks every model).
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Hashable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, ClassVar

import torch
from torch import nn

from vfm_core import physics as ph
from vfm_core.data import DTYPE, Batch
from vfm_core.models.linalg import matmul

__all__ = [
    "ChokeModel",
    "WellMLP",
    "PhysicalParameters",
    "FilterBlock",
    "make_block",
    "N_INPUTS",
    "Gradients",
    "Pullback",
]

#: parameter gradients by ``id(parameter)`` (a parameter absent has gradient zero)
Gradients = dict[int, torch.Tensor]
#: from d loss / d rate [W, N] (per sample, Sm3/h) to the parameters' gradients
Pullback = Callable[[torch.Tensor], Gradients]

#: the six inputs of every model, in vfm_core.schema.INPUT_COLUMNS order
N_INPUTS = 6


#: drift of a network's output layer per square root of a year, in its own units (for
#: ``ham`` the bias is the log of the area factor, elsewhere a share of the median rate):
#: the level a few percent a year, the slopes a tenth of that
HEAD_DRIFT_BIAS = 0.025
HEAD_DRIFT_WEIGHT = 0.0025


@dataclass(frozen=True)
class FilterBlock:
    """Per-well parameters a Bayesian learning method tracks: every element of ``param[j]``.

    ``labels``: one name per element (``c_d``, ``erosion.rate``, ``head.bias``);
    ``prior_var``: each element's prior variance (its own units); ``drift``: its random-walk
    standard deviation per square root of a year (own units); ``scale``: SI units per unit
    of the element (a standardised physical parameter: its prior sd), or 0 where the
    element has no physical meaning (network weights); ``start_var``: its variance when a
    filter starts a well that has no fit (its first measurement): the prior variance, but 0
    for the output weights of a hybrid's network (see :meth:`WellMLP.head_blocks`).
    """

    param: nn.Parameter
    labels: tuple[str, ...]
    prior_var: torch.Tensor
    drift: torch.Tensor
    scale: torch.Tensor
    start_var: torch.Tensor

    @property
    def size(self) -> int:
        return len(self.labels)


def make_block(
    param: nn.Parameter,
    labels: Sequence[str],
    prior_var: Any,
    drift: Any,
    scale: Any = 0.0,
    start_var: Any = None,
) -> FilterBlock:
    """A :class:`FilterBlock`; ``start_var`` None: the prior variance."""
    k = len(labels)

    def vec(v: Any) -> torch.Tensor:
        t = torch.as_tensor(v, dtype=DTYPE)
        return t.expand(k).clone() if t.dim() == 0 else t.reshape(k).clone()

    start = prior_var if start_var is None else start_var
    return FilterBlock(param, tuple(labels), vec(prior_var), vec(drift), vec(scale), vec(start))


class ChokeModel(nn.Module):
    """Abstract base of all models; see the module docstring for the protocol."""

    #: registry name (``mm``); an instance's :attr:`name` adds its effects (``mm+erosion``)
    key: ClassVar[str] = ""
    #: True when parameters are shared across wells (early stopping is then global).
    shared: ClassVar[bool] = False
    #: True when the model learns by ``observe`` rather than by gradients.
    gradient_free: ClassVar[bool] = False
    #: the model's batch-training settings where they differ from
    #: :class:`vfm_core.learning.TrainSettings`' defaults (field: value): the paper's
    #: Tables B.1-B.2 adapted to this implementation's scaling (physical parameters in
    #: prior standard deviations, rates scaled by the well's median). The learning methods
    #: start from them (:data:`vfm_core.learning.DEFAULT_TRAIN` lists them by name);
    #: ``vfm tune`` on your own data improves on them.
    train_defaults: ClassVar[Mapping[str, Any]] = {}
    #: the model's online-learning (``ol``) settings where they differ from
    #: :class:`vfm_core.learning.OnlineSettings`' defaults, chosen by
    #: ``vfm tune --grid small --methods ol`` on a development field (``vfm simulate
    #: --seed 1``), never on the field the study reports (seed 0)
    online_defaults: ClassVar[Mapping[str, Any]] = {}
    # buffers (registered in __init__), per well: set up, the rate scale, input statistics
    ready: torch.Tensor
    y_scale: torch.Tensor
    x_mean: torch.Tensor
    x_std: torch.Tensor

    def __init__(self, wells: Sequence[str], *, seed: int = 0) -> None:
        super().__init__()
        self.wells = list(wells)
        self.hyper: dict[str, Any] = {"seed": seed}
        self._gen = torch.Generator().manual_seed(seed)
        n = len(self.wells)
        self.register_buffer("ready", torch.zeros(n, dtype=torch.bool))
        self.register_buffer("y_scale", torch.ones(n, dtype=DTYPE))
        self.register_buffer("x_mean", torch.zeros(n, 6, dtype=DTYPE))
        self.register_buffer("x_std", torch.ones(n, 6, dtype=DTYPE))

    @property
    def name(self) -> str:
        """The model's full name: the registry name, plus its effects if any (``mm+erosion``)."""
        return self.key

    #: extra per-sample feature columns the model needs (see :class:`vfm_core.data.Batch`)
    extra_columns: tuple[str, ...] = ()
    #: True when predictions depend on the measurement source (a meter bias, say)
    needs_source: bool = False

    # -- set-up from training data -------------------------------------------------------
    def setup(self, batch: Batch) -> None:
        """Take normalisation statistics for wells that have data and are not set up yet."""
        counts = batch.count()
        new = (~self.ready) & (counts > 0)
        if not bool(new.any()):
            return
        m = batch.mask.unsqueeze(-1).to(DTYPE)
        n = counts.clamp(min=1).to(DTYPE).unsqueeze(-1)
        mean = (batch.x * m).sum(1) / n
        var = (((batch.x - mean.unsqueeze(1)) ** 2) * m).sum(1) / n
        std = var.sqrt()
        # a feature that never moved in training gets unit scale (nothing to normalise)
        std = torch.where(std > 1e-9 * (mean.abs() + 1.0), std, torch.ones_like(std))
        y = torch.where(batch.mask, batch.y, torch.full_like(batch.y, float("nan")))
        y_med = torch.nanmedian(y, dim=1).values
        self.x_mean[new] = mean[new]
        self.x_std[new] = std[new]
        self.y_scale[new] = torch.where(y_med[new] > 0, y_med[new], torch.ones_like(y_med[new]))
        self._setup_new(batch, new)
        self.ready |= new

    def _setup_new(self, batch: Batch, new: torch.Tensor) -> None:
        """Model-specific set-up of the wells in ``new`` (mask [W])."""

    def normalise(self, x: torch.Tensor) -> torch.Tensor:
        return (x - self.x_mean.unsqueeze(1)) / self.x_std.unsqueeze(1)

    # -- protocol ------------------------------------------------------------------------
    def forward(self, x: torch.Tensor) -> torch.Tensor:  # pragma: no cover - abstract
        raise NotImplementedError(f"{type(self).__name__} must implement forward().")

    def predict(self, x: torch.Tensor) -> torch.Tensor:
        """Predicted total rate [W, N], Sm3/h, without gradients; NaN for wells not set up."""
        with torch.no_grad():
            q = self.forward(x)
        return torch.where(self.ready.unsqueeze(1), q, torch.full_like(q, float("nan")))

    def forward_batch(self, batch: Batch) -> torch.Tensor:
        """Rates for a whole batch. Models that need more than the six inputs (time, the
        measurement source, extra features) override this; the learners call it."""
        return self.forward(batch.x)

    def predict_batch(self, batch: Batch) -> torch.Tensor:
        """:meth:`predict` for a batch (see :meth:`forward_batch`)."""
        with torch.no_grad():
            q = self.forward_batch(batch)
        return torch.where(self.ready.unsqueeze(1), q, torch.full_like(q, float("nan")))

    def prior_penalty(self, physical_only: bool = False) -> torch.Tensor:
        """Sum of squared standardised deviations from the prior means, per well [W]."""
        return torch.zeros(len(self.wells), dtype=DTYPE)

    def project_(self) -> None:
        """Clamp parameters into their physical bounds (after an optimiser step)."""

    def observe(self, batch: Batch) -> None:
        """Learn from measurements without gradients (only the ``last`` benchmark does)."""

    def physical_parameters(self) -> dict[str, torch.Tensor]:
        """Named physical parameters per well [W], SI units (empty for data-driven models)."""
        return {}

    def per_well_parameters(self) -> list[torch.nn.Parameter]:
        """Parameters with a leading well dimension (all of them unless shared)."""
        return [] if self.shared else list(self.parameters())

    def compiled_as(self) -> str | None:
        """Which compiled arithmetic of :mod:`vfm_core.learning.kernels` computes exactly
        this model (``mm``, ``hem``, ``ham``, ``nn``, ``lr``, ``mtl``), or None: torch runs
        it. Only the exact class that declares it answers (a subclass may change the rate),
        without effects, in float64 and in the shape the kernels were written for; whether
        the kernels are enabled is theirs to say."""
        return None

    def stack_key(self) -> Hashable:
        """What another model must share with this one for the two to run as one
        multi-well model (:mod:`vfm_core.learning.stacking`): the class, the feature
        columns and the hyperparameters but the seed (it only draws the initial
        parameters, which stacking replaces). Kept: the hyperparameters do not change."""
        key = self.__dict__.get("_stack_key")
        if key is None:
            hyper = {k: v for k, v in self.hyper.items() if k != "seed"}
            key = (
                type(self),
                json.dumps(hyper, sort_keys=True, default=str),
                tuple(self.extra_columns),
            )
            self.__dict__["_stack_key"] = key
        return key

    def filter_blocks(self) -> list[FilterBlock]:
        """What a Bayesian learning method tracks per well (see :class:`FilterBlock`); a
        model without per-well parameters (the ``last`` benchmark) has none."""
        return []

    # -- closed-form gradients (optional) -------------------------------------------------
    def rate_vjp(self, batch: Batch) -> tuple[torch.Tensor, Pullback] | None:
        """The rate of :meth:`forward_batch` [W, N] (Sm3/h, computed without a graph) and
        its pullback, or None when the model has no closed form (autograd is used).

        Only the exact class that implements it may answer: a subclass that changes the
        rate must not inherit its parent's gradient (see :meth:`_own_closed_form`)."""
        return None

    def prior_gradients(self, weight: torch.Tensor, physical_only: bool) -> Gradients:
        """Gradients of ``sum_j weight[j] prior_penalty(physical_only)[j]`` by parameter id
        (needed only by a model whose :meth:`rate_vjp` answers)."""
        return {}

    def _own_closed_form(self, cls: type) -> bool:
        """True when this model is exactly ``cls`` (its closed form applies)."""
        return type(self) is cls


class WellMLP(nn.Module):
    """One ReLU multilayer perceptron per well, evaluated in one batched call.

    Weights are [W, fan_in, fan_out]; hidden layers use He initialisation, the output
    layer starts at zero (the prior mean), so an untrained network adds nothing.
    """

    def __init__(self, n_wells: int, sizes: Sequence[int], gen: torch.Generator) -> None:
        super().__init__()
        self.weights = nn.ParameterList()
        self.biases = nn.ParameterList()
        for i, (fan_in, fan_out) in enumerate(zip(sizes[:-1], sizes[1:], strict=True)):
            last = i == len(sizes) - 2
            w = torch.randn(n_wells, fan_in, fan_out, generator=gen, dtype=DTYPE)
            w = torch.zeros_like(w) if last else w * math.sqrt(2.0 / fan_in)
            self.weights.append(nn.Parameter(w))
            self.biases.append(nn.Parameter(torch.zeros(n_wells, fan_out, dtype=DTYPE)))

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        n = len(self.weights)
        for i, (w, b) in enumerate(zip(self.weights, self.biases, strict=True)):
            z = matmul(z, w, b.unsqueeze(1))
            if i < n - 1:
                z = torch.relu(z)
        return z.squeeze(-1)

    def forward_cached(self, z: torch.Tensor) -> tuple[torch.Tensor, list[torch.Tensor]]:
        """:meth:`forward` [W, N] and what :meth:`pullback` needs (each layer's input and
        pre-activation)."""
        n = len(self.weights)
        cache = []
        for i, (w, b) in enumerate(zip(self.weights, self.biases, strict=True)):
            a = matmul(z, w, b.unsqueeze(1))
            cache += [z, a]
            z = torch.relu(a) if i < n - 1 else a
        return z.squeeze(-1), cache

    def pullback(self, cache: list[torch.Tensor], grad: torch.Tensor) -> Gradients:
        """Gradients of every weight and bias from d loss / d output [W, N] (backpropagation
        written out: the same numbers as autograd's, without its per-call machinery)."""
        out: Gradients = {}
        delta = grad.unsqueeze(-1)
        for i in range(len(self.weights) - 1, -1, -1):
            z, a = cache[2 * i], cache[2 * i + 1]
            if i < len(self.weights) - 1:
                delta = torch.ops.aten.threshold_backward(delta, a, 0.0)  # ReLU's, as autograd
            w = self.weights[i]
            out[id(w)] = matmul(z.transpose(1, 2), delta)
            out[id(self.biases[i])] = delta.sum(1)
            if i > 0:
                delta = matmul(delta, w.transpose(1, 2))
        return out

    def prior_gradients(self, weight: torch.Tensor) -> Gradients:
        """Gradients of ``sum_j weight[j] prior_penalty()[j]``."""
        out: Gradients = {}
        k = weight.reshape(-1, 1, 1)
        for w, b in zip(self.weights, self.biases, strict=True):
            he_var = 2.0 / w.shape[1]
            out[id(w)] = (2.0 / he_var) * k * w.detach()
            out[id(b)] = 2.0 * weight.unsqueeze(1) * b.detach()
        return out

    def head_blocks(self, prefix: str = "head", correction: bool = False) -> list[FilterBlock]:
        """The output layer as filter blocks: its weights (prior variance 2/fan_in, He) and
        its bias (prior variance 1); the layers below stay as fitted.

        ``correction``: the network corrects a mechanistic model that stands without it (the
        hybrids). A filter then starts a well that has no fit with the output weights at
        their prior mean (0) and no variance, the bias at its prior (``start_var``). Why:
        such a well's lower layers are their random initial draws, on inputs standardised
        by its one sample (no spread: unit scale in file units), so the He prior on the
        output weights, a prior over area functions only for standardised inputs and
        fitted features, spans nothing physical: measured on a simulated well, a log-rate
        standard deviation of 5 (median over its samples) after its first well test, which
        let every later measurement, a separator's total above all, move the weights along
        features that mean nothing. The well is the mechanistic model with a learned level
        until a fit gives the features a meaning (``bayes``'s refit, ``refresh``, starts
        the filter again from the fit). A network that is the whole model (``nn``) keeps
        the prior: it has nothing else to learn with."""
        w, b = self.weights[-1], self.biases[-1]
        fan_in = int(w.shape[1])
        return [
            make_block(
                w,
                [f"{prefix}.w{i}" for i in range(fan_in)],
                2.0 / fan_in,
                HEAD_DRIFT_WEIGHT,
                start_var=0.0 if correction else None,
            ),
            make_block(b, [f"{prefix}.bias"], 1.0, HEAD_DRIFT_BIAS),
        ]

    def prior_penalty(self) -> torch.Tensor:
        total = torch.zeros(self.weights[0].shape[0], dtype=DTYPE)
        for w, b in zip(self.weights, self.biases, strict=True):
            he_var = 2.0 / w.shape[1]
            total = total + (w**2).sum(dim=(1, 2)) / he_var + (b**2).sum(dim=1)
        return total


class PhysicalParameters(nn.Module):
    """The mechanistic parameters as standardised offsets z: theta = mu + sigma z.

    Learning in z keeps every parameter on the same scale for SGD and Adam, and the prior
    penalty is simply sum(z^2). Bounds from :data:`vfm_core.physics.PRIORS`.
    """

    # buffers (registered in __init__): the priors' means and sds, the bounds in z
    mu: torch.Tensor
    sigma: torch.Tensor
    z_low: torch.Tensor
    z_high: torch.Tensor

    def __init__(self, n_wells: int, names: Sequence[str] | Mapping[str, ph.Prior]) -> None:
        super().__init__()
        # names of vfm_core.physics.PRIORS, or a mapping name -> Prior (an effect's own)
        table = names if isinstance(names, Mapping) else {n: ph.PRIORS[n] for n in names}
        self.names = tuple(table)
        priors = [table[n] for n in self.names]
        self.drifts = {
            n: float(getattr(p, "drift", 0.05)) for n, p in zip(self.names, priors, strict=True)
        }
        self.register_buffer("mu", torch.tensor([p.mean for p in priors], dtype=DTYPE))
        self.register_buffer("sigma", torch.tensor([p.std for p in priors], dtype=DTYPE))
        self.register_buffer(
            "z_low", torch.tensor([(p.low - p.mean) / p.std for p in priors], dtype=DTYPE)
        )
        self.register_buffer(
            "z_high", torch.tensor([(p.high - p.mean) / p.std for p in priors], dtype=DTYPE)
        )
        self.z = nn.Parameter(torch.zeros(n_wells, len(self.names), dtype=DTYPE))

    def filter_block(self, prefix: str = "") -> FilterBlock:
        """All parameters as one filter block, in standardised units (prior variance 1,
        drift from each prior, SI scale = prior sd)."""
        return make_block(
            self.z,
            [f"{prefix}{n}" for n in self.names],
            1.0,
            [self.drifts[n] for n in self.names],
            self.sigma,
        )

    def values(self) -> dict[str, torch.Tensor]:
        theta = self.mu + self.sigma * self.z
        return {n: theta[:, i] for i, n in enumerate(self.names)}

    def penalty(self) -> torch.Tensor:
        return (self.z**2).sum(dim=1)

    def penalty_gradients(self, weight: torch.Tensor) -> Gradients:
        """Gradient of ``sum_j weight[j] penalty()[j]``."""
        return {id(self.z): 2.0 * weight.unsqueeze(1) * self.z.detach()}

    def project_(self) -> None:
        with torch.no_grad():
            self.z.copy_(torch.maximum(torch.minimum(self.z, self.z_high), self.z_low))
