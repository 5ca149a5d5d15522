"""The data-driven models of the paper: the ``last`` benchmark, linear regression, a neural
network per well and the multi-task network shared by all wells (``lr``, ``nn``, ``mtl``).

All predict the total rate at standard conditions (Sm3/h) from the six inputs in file units
(see :mod:`vfm_core.models.base` for the protocol).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import nn

from vfm_core.data import DTYPE, Batch
from vfm_core.errors import ConfigError
from vfm_core.models.base import (
    HEAD_DRIFT_BIAS,
    HEAD_DRIFT_WEIGHT,
    ChokeModel,
    FilterBlock,
    Gradients,
    Pullback,
    WellMLP,
    make_block,
)
from vfm_core.models.linalg import matmul
from vfm_core.schema import INPUT_COLUMNS
from vfm_core.units import KELVIN_OFFSET

__all__ = ["LastValue", "LinearRegression", "NeuralNet", "MultiTask"]


class LastValue(ChokeModel):
    """Benchmark: the last measured rate of the well (independent of the inputs)."""

    key = "last"
    gradient_free = True
    last_y: torch.Tensor  # buffer: each well's last measured rate, Sm3/h (NaN: none yet)

    def __init__(self, wells: Sequence[str], *, seed: int = 0) -> None:
        super().__init__(wells, seed=seed)
        self.register_buffer("last_y", torch.full((len(self.wells),), float("nan"), dtype=DTYPE))

    def setup(self, batch: Batch) -> None:
        super().setup(batch)
        self.observe(batch)

    def observe(self, batch: Batch) -> None:
        counts = batch.count()
        has = counts > 0
        idx = (counts - 1).clamp(min=0)
        latest = batch.y.gather(1, idx.unsqueeze(1)).squeeze(1)
        self.last_y.copy_(torch.where(has, latest, self.last_y))
        self.ready |= has

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.last_y.unsqueeze(1).expand(x.shape[0], x.shape[1])


#: each input's offset from its file unit to an absolute scale, in INPUT_COLUMNS order:
#: t_up degC -> K; the choke and the mass fractions (0..1) and the pressures (bar
#: absolute) are absolute already
_ABSOLUTE_OFFSET = tuple(KELVIN_OFFSET if c == "t_up" else 0.0 for c in INPUT_COLUMNS)
#: what ``lr``'s slope prior is stated in (:class:`LinearRegression`'s ``slopes``)
SLOPE_PRIORS: tuple[str, ...] = ("elasticity", "spread")


class LinearRegression(ChokeModel):
    """q = y_scale (w . x_norm + b): a line through the normalised inputs (x_norm = (x -
    mean) / sd over the well's training rows).

    Prior: b ~ N(1, 1) (the rate scale is the training median) and, per slope, by
    ``slopes``:

    - ``elasticity`` (the default): the elasticity e = d ln q / d ln x at the well's mean,
      e = w |mean| / sd (inputs in absolute units: temperature in K), is N(0, 1): of order
      one, as the choke law says (the rate about proportional to the choke's area, to
      p_up in critical flow, about independent of p_down; the simulator's wells fitted on
      every MPFM reading give 0.9-1.1 to the choke, 0.7-0.9 to p_up; docs/guide/bayes.md,
      session 53). So w ~ N(0, (sd / |mean|)^2): the same prior for every well in physical
      units, whatever the spread of its history, and a well fitted on a few well tests over
      a narrow range keeps its slopes of a physical size instead of extrapolating a steep
      line off that range. Where an input's spread exceeds its magnitude (a fraction near
      zero) the prior is the ``spread`` one: never weaker than before.
    - ``spread``: w ~ N(0, 1), a rate change of one median per sd of the well's own history:
      as wide in physical units as that history is narrow. With ``early_stopping=True`` in
      the training settings this is ``lr`` before session 53 (measured: wells with 8 or
      fewer well tests before the split covered 81 % of their 90 % intervals in case 2,
      errors of 30-60 % once their inputs left that range).

    The precision of each slope's prior is the buffer ``w_prec`` [W, 6] (1 for ``spread``),
    set with the normalisation when a well is set up. The batch fit runs to the MAP (no early
    stopping: the prior is the regulariser; stopped early, a fit in the spread's coordinates
    ends before the prior has acted, and its slopes are as free as before).
    """

    key = "lr"
    #: no early stopping: the fit is the MAP of the stated prior (see the class docstring)
    train_defaults = {"lr": 0.05, "early_stopping": False}
    online_defaults = {"optimizer": "sgd", "lr": 1e-4, "steps": 10}
    w_prec: torch.Tensor  # buffer: each slope's prior precision, per well [W, 6]

    def __init__(self, wells: Sequence[str], *, seed: int = 0, slopes: str = "elasticity") -> None:
        if slopes not in SLOPE_PRIORS:
            raise ConfigError(
                f"lr's slope prior is stated as one of {', '.join(SLOPE_PRIORS)}, not '{slopes}'."
            )
        super().__init__(wells, seed=seed)
        if slopes != "elasticity":  # the default stays out of hyper, as before
            self.hyper["slopes"] = slopes
        self.slopes = slopes
        n = len(self.wells)
        self.w = nn.Parameter(torch.zeros(n, 6, dtype=DTYPE))
        self.b = nn.Parameter(torch.ones(n, dtype=DTYPE))
        self.register_buffer("w_prec", torch.ones(n, 6, dtype=DTYPE))

    def _setup_new(self, batch: Batch, new: torch.Tensor) -> None:
        """With ``slopes="elasticity"``, each new well's slope precisions (|mean| / sd)^2,
        |mean| in absolute units and at least the spread sd."""
        if self.slopes != "elasticity":
            return
        magnitude = (self.x_mean[new] + torch.tensor(_ABSOLUTE_OFFSET, dtype=DTYPE)).abs()
        spread = self.x_std[new]
        self.w_prec[new] = (torch.maximum(magnitude, spread) / spread) ** 2

    def _load_from_state_dict(  # type: ignore[no-untyped-def]
        self, state_dict, prefix, *args, **kwargs
    ) -> None:
        """A file saved before ``w_prec`` existed was fitted under the ``spread`` prior: it
        loads with precision 1."""
        key = prefix + "w_prec"
        if key not in state_dict and prefix + "w" in state_dict:
            state_dict[key] = torch.ones_like(state_dict[prefix + "w"])
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        z = self.normalise(x)
        return self.y_scale.unsqueeze(1) * ((z * self.w.unsqueeze(1)).sum(-1) + self.b.unsqueeze(1))

    def prior_penalty(self, physical_only: bool = False) -> torch.Tensor:
        if physical_only:
            return super().prior_penalty()
        return (self.w_prec * self.w**2).sum(1) + (self.b - 1.0) ** 2

    def compiled_as(self) -> str | None:
        """``lr`` for exactly this class in float64 (see :meth:`ChokeModel.compiled_as`)."""
        plain = type(self) is LinearRegression
        return "lr" if plain and self.w.dtype == self.b.dtype == torch.float64 else None

    def rate_vjp(self, batch: Batch) -> tuple[torch.Tensor, Pullback] | None:
        if not self._own_closed_form(LinearRegression):
            return None
        with torch.no_grad():
            z = self.normalise(batch.x)
            scale = self.y_scale.unsqueeze(1)
            q = scale * ((z * self.w.unsqueeze(1)).sum(-1) + self.b.unsqueeze(1))

        def pullback(grad: torch.Tensor) -> Gradients:
            g = grad * scale
            return {id(self.w): (g.unsqueeze(-1) * z).sum(1), id(self.b): g.sum(1)}

        return q, pullback

    def prior_gradients(self, weight: torch.Tensor, physical_only: bool) -> Gradients:
        if physical_only:
            return {}
        k = 2.0 * weight
        return {
            id(self.w): k.unsqueeze(1) * self.w_prec * self.w.detach(),
            id(self.b): k * (self.b.detach() - 1.0),
        }

    def filter_blocks(self) -> list[FilterBlock]:
        """Slopes and level, in units of the well's median rate (prior variance 1)."""
        return [
            make_block(self.w, [f"w.{c}" for c in INPUT_COLUMNS], 1.0, HEAD_DRIFT_WEIGHT),
            make_block(self.b, ["level"], 1.0, HEAD_DRIFT_BIAS),
        ]


class NeuralNet(ChokeModel):
    """q = y_scale (1 + MLP(x_norm)): a ReLU network per well (paper eq. nn-model)."""

    key = "nn"
    train_defaults = {"lr": 3e-3}
    online_defaults = {"optimizer": "sgd", "lr": 1e-4, "steps": 10}

    def __init__(
        self, wells: Sequence[str], *, seed: int = 0, hidden: Sequence[int] = (32, 32)
    ) -> None:
        super().__init__(wells, seed=seed)
        self.hyper["hidden"] = list(hidden)
        self.net = WellMLP(len(self.wells), [6, *hidden, 1], self._gen)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.y_scale.unsqueeze(1) * (1.0 + self.net(self.normalise(x)))

    def prior_penalty(self, physical_only: bool = False) -> torch.Tensor:
        return super().prior_penalty() if physical_only else self.net.prior_penalty()

    def compiled_as(self) -> str | None:
        """``nn`` for exactly this class with two hidden layers on the six inputs, in
        float64 (see :meth:`ChokeModel.compiled_as`)."""
        if type(self) is not NeuralNet:
            return None
        weights = self.net.weights
        plain = (
            len(weights) == 3
            and weights[0].shape[1] == 6
            and weights[2].shape[2] == 1
            and all(w.dtype == torch.float64 for w in weights)
        )
        return "nn" if plain else None

    def rate_vjp(self, batch: Batch) -> tuple[torch.Tensor, Pullback] | None:
        if not self._own_closed_form(NeuralNet):
            return None
        with torch.no_grad():
            out, cache = self.net.forward_cached(self.normalise(batch.x))
            scale = self.y_scale.unsqueeze(1)
            q = scale * (1.0 + out)
        return q, lambda grad: self.net.pullback(cache, grad * scale)

    def prior_gradients(self, weight: torch.Tensor, physical_only: bool) -> Gradients:
        return {} if physical_only else self.net.prior_gradients(weight)

    def filter_blocks(self) -> list[FilterBlock]:
        """The output layer (last-layer Bayesian learning; the layers below stay as fitted)."""
        return self.net.head_blocks("head")


class MultiTask(ChokeModel):
    """Multi-task learning (paper eq. mtl-model): beta_j per well + a shared pre-activation ResNet.

    z1 = W01 x + W02 beta_j + b0; r_l = W_l2 a(W_l1 a(z_l) + b_l1) + b_l2; z_{l+1} = z_l + r_l;
    q = y_scale_j (1 + W_out z_{L+1} + b_out). Inputs are normalised with statistics of the
    whole field, so the shared network sees one input space; beta_j ~ N(0, 1).
    """

    key = "mtl"
    shared = True
    train_defaults = {"lr": 3e-3}
    online_defaults = {"lr": 1e-4, "steps": 10}

    def __init__(
        self,
        wells: Sequence[str],
        *,
        seed: int = 0,
        width: int = 32,
        blocks: int = 2,
        task_dim: int = 4,
    ) -> None:
        super().__init__(wells, seed=seed)
        self.hyper.update(width=width, blocks=blocks, task_dim=task_dim)
        g = self._gen

        def he(fan_in: int, fan_out: int) -> nn.Parameter:
            return nn.Parameter(
                torch.randn(fan_in, fan_out, generator=g, dtype=DTYPE) * math.sqrt(2.0 / fan_in)
            )

        self.beta = nn.Parameter(torch.zeros(len(self.wells), task_dim, dtype=DTYPE))
        self.w_in = he(6 + task_dim, width)
        self.b_in = nn.Parameter(torch.zeros(width, dtype=DTYPE))
        self.w1 = nn.ParameterList([he(width, width) for _ in range(blocks)])
        self.b1 = nn.ParameterList(
            [nn.Parameter(torch.zeros(width, dtype=DTYPE)) for _ in range(blocks)]
        )
        self.w2 = nn.ParameterList([he(width, width) for _ in range(blocks)])
        self.b2 = nn.ParameterList(
            [nn.Parameter(torch.zeros(width, dtype=DTYPE)) for _ in range(blocks)]
        )
        self.w_out = nn.Parameter(torch.zeros(width, 1, dtype=DTYPE))
        self.b_out = nn.Parameter(torch.zeros(1, dtype=DTYPE))

    def _setup_new(self, batch: Batch, new: torch.Tensor) -> None:
        # one input normalisation for all wells, taken at the first set-up
        if bool(self.ready.any()):
            self.x_mean[new] = self.x_mean[self.ready][0]
            self.x_std[new] = self.x_std[self.ready][0]
            return
        m = batch.mask.unsqueeze(-1).to(DTYPE)
        n = m.sum()
        mean = (batch.x * m).sum((0, 1)) / n
        std = ((((batch.x - mean) ** 2) * m).sum((0, 1)) / n).sqrt().clamp(min=1e-9)
        self.x_mean[:] = mean
        self.x_std[:] = std

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        z = self.normalise(x)
        beta = self.beta.unsqueeze(1).expand(-1, x.shape[1], -1)
        h = matmul(torch.cat([z, beta], dim=-1), self.w_in, self.b_in)
        for w1, b1, w2, b2 in zip(self.w1, self.b1, self.w2, self.b2, strict=True):
            h = h + matmul(torch.relu(matmul(torch.relu(h), w1, b1)), w2, b2)
        out = (h @ self.w_out).squeeze(-1) + self.b_out
        return self.y_scale.unsqueeze(1) * (1.0 + out)

    def prior_penalty(self, physical_only: bool = False) -> torch.Tensor:
        n = len(self.wells)
        if physical_only:
            return torch.zeros(n, dtype=DTYPE)
        shared = torch.zeros((), dtype=DTYPE)
        for w in [self.w_in, *self.w1, *self.w2, self.w_out]:
            shared = shared + (w**2).sum() / (2.0 / w.shape[0])
        for b in [self.b_in, *self.b1, *self.b2, self.b_out]:
            shared = shared + (b**2).sum()
        # shared weights are charged once, spread evenly over the wells
        return (self.beta**2).sum(1) + shared / n

    def per_well_parameters(self) -> list[torch.nn.Parameter]:
        return [self.beta]

    def compiled_as(self) -> str | None:
        """``mtl`` for exactly this class with two residual blocks, in float64 (see
        :meth:`ChokeModel.compiled_as`)."""
        plain = (
            type(self) is MultiTask
            and len(self.w1) == len(self.w2) == 2
            and all(p.dtype == torch.float64 for p in self.parameters())
        )
        return "mtl" if plain else None

    def rate_vjp(self, batch: Batch) -> tuple[torch.Tensor, Pullback] | None:
        if not self._own_closed_form(MultiTask):
            return None
        with torch.no_grad():
            z = self.normalise(batch.x)
            beta = self.beta.unsqueeze(1).expand(-1, z.shape[1], -1)
            inp = torch.cat([z, beta], dim=-1)
            h = matmul(inp, self.w_in, self.b_in)
            cache = []
            for w1, b1, w2, b2 in zip(self.w1, self.b1, self.w2, self.b2, strict=True):
                u = matmul(torch.relu(h), w1, b1)
                cache.append((h, u))
                h = h + matmul(torch.relu(u), w2, b2)
            scale = self.y_scale.unsqueeze(1)
            q = scale * (1.0 + (h @ self.w_out).squeeze(-1) + self.b_out)

        def pullback(grad: torch.Tensor) -> Gradients:
            g = (grad * scale).unsqueeze(-1)  # d loss / d out [W, N, 1]
            width = h.shape[-1]
            out: Gradients = {
                id(self.w_out): h.reshape(-1, width).T @ g.reshape(-1, 1),
                id(self.b_out): g.sum().reshape(1),
            }
            dh = g @ self.w_out.detach().T
            blocks = list(zip(self.w1, self.b1, self.w2, self.b2, strict=True))
            for (w1, b1, w2, b2), (h_in, u) in zip(blocks[::-1], cache[::-1], strict=True):
                flat = dh.reshape(-1, width)
                out[id(w2)] = matmul(torch.relu(u).reshape(-1, width).T, flat)
                out[id(b2)] = flat.sum(0)
                du = matmul(dh, w2.detach().T) * (u > 0)
                du_flat = du.reshape(-1, width)
                out[id(w1)] = matmul(torch.relu(h_in).reshape(-1, width).T, du_flat)
                out[id(b1)] = du_flat.sum(0)
                dh = dh + matmul(du, w1.detach().T) * (h_in > 0)
            flat = dh.reshape(-1, width)
            out[id(self.w_in)] = matmul(inp.reshape(-1, inp.shape[-1]).T, flat)
            out[id(self.b_in)] = flat.sum(0)
            out[id(self.beta)] = (dh @ self.w_in.detach()[z.shape[-1] :].T).sum(1)
            return out

        return q, pullback

    def prior_gradients(self, weight: torch.Tensor, physical_only: bool) -> Gradients:
        if physical_only:
            return {}
        out: Gradients = {id(self.beta): 2.0 * weight.unsqueeze(1) * self.beta.detach()}
        shared = weight.sum() / len(self.wells)  # each well carries 1/W of the shared prior
        for w in [self.w_in, *self.w1, *self.w2, self.w_out]:
            out[id(w)] = (2.0 * shared / (2.0 / w.shape[0])) * w.detach()
        for b in [self.b_in, *self.b1, *self.b2, self.b_out]:
            out[id(b)] = 2.0 * shared * b.detach()
        return out

    def filter_blocks(self) -> list[FilterBlock]:
        """Each well's task vector beta_j (the shared network is no well's own: ``bayes``
        refits it on schedule, see :meth:`vfm_core.learning.bayes.BayesianFilter.retrain_due`)."""
        dim = int(self.beta.shape[1])
        return [make_block(self.beta, [f"beta.{i}" for i in range(dim)], 1.0, 0.05)]
