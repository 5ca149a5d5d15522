"""The steady-state choke models of the paper, batched over wells.

Registry names (``MODELS``): ``last`` (benchmark), ``lr``, ``nn``, ``mtl``, ``mm``, ``hem``
and ``ham``. Every model implements one small protocol:

- ``setup(batch)``: statistics taken from training data (input normalisation, the rate
  scale, the choke's full-open area of the mechanistic models); wells already set up are
  left alone, so it can be called again as new wells appear.
- ``forward(x) -> q``: predicted total rate [W, N] in Sm3/h for inputs [W, N, 6] in file
  units (see :mod:`vfm_core.data`).
- ``prior_penalty(physical_only)``: sum over parameters of ((theta - mu)/sigma)^2 per well,
  the negative log Gaussian prior of MAP training (He initialisation's variance is the
  prior of network weights, centred on zero).
- ``project_()``: clamp physical parameters into their bounds after each step.
- ``observe(batch)``: learning without gradients (the ``last`` benchmark only).
- ``physical_parameters()``: named physical parameters in SI units, per well.
- ``state_dict()`` / ``load_state_dict()`` hold tensors only; hyperparameters are the
  constructor's keyword arguments (``model.hyper``, JSON). No pickle anywhere.

Every model but ``mtl`` has its own parameters per well, stacked along a leading well
dimension, so one optimiser step updates all wells at once and independently (the losses
of different wells never share a parameter). ``mtl`` shares its network across wells and
keeps a small vector beta_j per well.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, ClassVar

import torch
from torch import nn

from vfm_core import physics as ph
from vfm_core.data import DTYPE, Batch
from vfm_core.errors import ConfigError
from vfm_core.units import bar_to_pa, degc_to_k

__all__ = [
    "MODELS",
    "PHYSICAL_NAMES",
    "ChokeModel",
    "LastValue",
    "LinearRegression",
    "NeuralNet",
    "MultiTask",
    "Mechanistic",
    "HybridError",
    "HybridArea",
    "make_model",
    "save_model",
    "load_model",
]

#: The mechanistic parameters theta_MM, in this order (see :data:`vfm_core.physics.PRIORS`).
PHYSICAL_NAMES: tuple[str, ...] = ("rho_oil", "rho_wat", "kappa", "m_gas", "p_cr", "c_d")


class ChokeModel(nn.Module):
    """Abstract base of all models; see the module docstring for the protocol."""

    name: ClassVar[str] = ""
    #: True when parameters are shared across wells (early stopping is then global).
    shared: ClassVar[bool] = False
    #: True when the model learns by ``observe`` rather than by gradients.
    gradient_free: ClassVar[bool] = False

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

    #: extra per-sample feature columns the model needs (see :class:`vfm_core.data.Batch`)
    extra_columns: tuple[str, ...] = ()

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


# --- building blocks ----------------------------------------------------------------------
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
            z = torch.baddbmm(b.unsqueeze(1), z, w)
            if i < n - 1:
                z = torch.relu(z)
        return z.squeeze(-1)

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

    def __init__(self, n_wells: int, names: Sequence[str] | Mapping[str, ph.Prior]) -> None:
        super().__init__()
        # names of vfm_core.physics.PRIORS, or a mapping name -> Prior (an effect's own)
        table = names if isinstance(names, Mapping) else {n: ph.PRIORS[n] for n in names}
        self.names = tuple(table)
        priors = [table[n] for n in self.names]
        self.register_buffer("mu", torch.tensor([p.mean for p in priors], dtype=DTYPE))
        self.register_buffer("sigma", torch.tensor([p.std for p in priors], dtype=DTYPE))
        self.register_buffer(
            "z_low", torch.tensor([(p.low - p.mean) / p.std for p in priors], dtype=DTYPE)
        )
        self.register_buffer(
            "z_high", torch.tensor([(p.high - p.mean) / p.std for p in priors], dtype=DTYPE)
        )
        self.z = nn.Parameter(torch.zeros(n_wells, len(self.names), dtype=DTYPE))

    def values(self) -> dict[str, torch.Tensor]:
        theta = self.mu + self.sigma * self.z
        return {n: theta[:, i] for i, n in enumerate(self.names)}

    def penalty(self) -> torch.Tensor:
        return (self.z**2).sum(dim=1)

    def project_(self) -> None:
        with torch.no_grad():
            self.z.copy_(torch.maximum(torch.minimum(self.z, self.z_high), self.z_low))


def mechanistic_rate(
    x: torch.Tensor, theta: dict[str, torch.Tensor], area: torch.Tensor
) -> torch.Tensor:
    """Sachdeva total rate at standard conditions, Sm3/h.

    ``x`` [W, N, 6] in file units; ``theta`` values [W]; ``area`` [W, N] effective flow
    area C_D A_2 in m2.
    """
    u, p_up, p_down, t_up, eta_gas, eta_oil = x.unbind(-1)
    th = {k: v.unsqueeze(1) for k, v in theta.items()}
    mdot = ph.choke_mass_flow(
        area,
        bar_to_pa(p_up),
        bar_to_pa(p_down),
        degc_to_k(t_up),
        eta_gas,
        eta_oil,
        rho_oil=th["rho_oil"],
        rho_wat=th["rho_wat"],
        kappa=th["kappa"],
        m_gas=th["m_gas"],
        p_cr=th["p_cr"],
    )
    per_kg = ph.standard_volume_per_mass(
        eta_gas, eta_oil, rho_oil=th["rho_oil"], rho_wat=th["rho_wat"], m_gas=th["m_gas"]
    )
    return mdot * per_kg * 3600.0


# --- the models -----------------------------------------------------------------------------
class LastValue(ChokeModel):
    """Benchmark: the last measured rate of the well (independent of the inputs)."""

    name = "last"
    gradient_free = True

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


class LinearRegression(ChokeModel):
    """q = y_scale (w . x_norm + b): a line through the normalised inputs.

    Prior: w ~ N(0, 1), b ~ N(1, 1) (the rate scale is the training median).
    """

    name = "lr"

    def __init__(self, wells: Sequence[str], *, seed: int = 0) -> None:
        super().__init__(wells, seed=seed)
        n = len(self.wells)
        self.w = nn.Parameter(torch.zeros(n, 6, dtype=DTYPE))
        self.b = nn.Parameter(torch.ones(n, dtype=DTYPE))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        z = self.normalise(x)
        return self.y_scale.unsqueeze(1) * ((z * self.w.unsqueeze(1)).sum(-1) + self.b.unsqueeze(1))

    def prior_penalty(self, physical_only: bool = False) -> torch.Tensor:
        if physical_only:
            return super().prior_penalty()
        return (self.w**2).sum(1) + (self.b - 1.0) ** 2


class NeuralNet(ChokeModel):
    """q = y_scale (1 + MLP(x_norm)): a ReLU network per well (paper eq. nn-model)."""

    name = "nn"

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


class MultiTask(ChokeModel):
    """Multi-task learning (paper eq. mtl-model): beta_j per well + a shared pre-activation ResNet.

    z1 = W01 x + W02 beta_j + b0; r_l = W_l2 a(W_l1 a(z_l) + b_l1) + b_l2; z_{l+1} = z_l + r_l;
    q = y_scale_j (1 + W_out z_{L+1} + b_out). Inputs are normalised with statistics of the
    whole field, so the shared network sees one input space; beta_j ~ N(0, 1).
    """

    name = "mtl"
    shared = True

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
        h = torch.cat([z, beta], dim=-1) @ self.w_in + self.b_in
        for w1, b1, w2, b2 in zip(self.w1, self.b1, self.w2, self.b2, strict=True):
            h = h + torch.relu(torch.relu(h) @ w1 + b1) @ w2 + b2
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


class Mechanistic(ChokeModel):
    """The Sachdeva choke model (paper eq. MM) with learned rho_oil, rho_wat, kappa, M_gas, p_cr, C_D.

    The valve is linear, A_2(u) = A_max u. A_max, the full-open flow area, is not in the
    observation format; it is set once per well from its training data so that the model
    at the prior means matches the median measured rate (the choke size is a fixed
    property of the well, C_D keeps its physical prior).
    """

    name = "mm"
    physical_names: ClassVar[tuple[str, ...]] = PHYSICAL_NAMES

    def __init__(self, wells: Sequence[str], *, seed: int = 0) -> None:
        super().__init__(wells, seed=seed)
        n = len(self.wells)
        self.phys = PhysicalParameters(n, self.physical_names)
        self.register_buffer("a_max", torch.ones(n, dtype=DTYPE))

    def _prior_theta(self) -> dict[str, torch.Tensor]:
        n = len(self.wells)
        return {k: torch.full((n,), ph.PRIORS[k].mean, dtype=DTYPE) for k in PHYSICAL_NAMES}

    def _setup_new(self, batch: Batch, new: torch.Tensor) -> None:
        theta = self._prior_theta()
        unit = mechanistic_rate(batch.x, theta, theta["c_d"].unsqueeze(1) * batch.x[..., 0])
        ratio = torch.where(
            batch.mask & (unit > 0), batch.y / unit, torch.full_like(unit, float("nan"))
        )
        a_max = torch.nanmedian(ratio, dim=1).values
        self.a_max[new] = torch.where(
            torch.isfinite(a_max[new]), a_max[new], torch.ones_like(a_max[new])
        )

    def theta(self) -> dict[str, torch.Tensor]:
        values = self._prior_theta()
        values.update(self.phys.values())
        return values

    def area(self, x: torch.Tensor, theta: dict[str, torch.Tensor]) -> torch.Tensor:
        """Effective flow area C_D A_max u, m2, [W, N]."""
        return (theta["c_d"] * self.a_max).unsqueeze(1) * x[..., 0]

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        theta = self.theta()
        return mechanistic_rate(x, theta, self.area(x, theta))

    def prior_penalty(self, physical_only: bool = False) -> torch.Tensor:
        return self.phys.penalty()

    def project_(self) -> None:
        self.phys.project_()

    def physical_parameters(self) -> dict[str, torch.Tensor]:
        with torch.no_grad():
            out = {k: v.detach().clone() for k, v in self.phys.values().items()}
        out["a_max"] = self.a_max.clone()
        return out


class HybridError(Mechanistic):
    """Hybrid error model: q = MM(x) + y_scale MLP(x_norm) (paper section 'Hybrid error model')."""

    name = "hem"

    def __init__(
        self, wells: Sequence[str], *, seed: int = 0, hidden: Sequence[int] = (16,)
    ) -> None:
        super().__init__(wells, seed=seed)
        self.hyper["hidden"] = list(hidden)
        self.net = WellMLP(len(self.wells), [6, *hidden, 1], self._gen)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return super().forward(x) + self.y_scale.unsqueeze(1) * self.net(self.normalise(x))

    def prior_penalty(self, physical_only: bool = False) -> torch.Tensor:
        base = self.phys.penalty()
        return base if physical_only else base + self.net.prior_penalty()


class HybridArea(Mechanistic):
    """Hybrid area model: A_2 = A_max u C_D0 exp(MLP(x)), the network replacing C_D (paper 'HAM').

    The network sees all six inputs, since the effective area depends on the fluid too.
    C_D0 is the prior mean of C_D; an untrained network gives the plain MM.
    """

    name = "ham"
    physical_names = ("rho_oil", "rho_wat", "kappa", "m_gas", "p_cr")

    def __init__(
        self, wells: Sequence[str], *, seed: int = 0, hidden: Sequence[int] = (16,)
    ) -> None:
        super().__init__(wells, seed=seed)
        self.hyper["hidden"] = list(hidden)
        self.net = WellMLP(len(self.wells), [6, *hidden, 1], self._gen)

    def area(self, x: torch.Tensor, theta: dict[str, torch.Tensor]) -> torch.Tensor:
        factor = torch.exp(self.net(self.normalise(x)))
        return (ph.PRIORS["c_d"].mean * self.a_max).unsqueeze(1) * x[..., 0] * factor

    def prior_penalty(self, physical_only: bool = False) -> torch.Tensor:
        base = self.phys.penalty()
        return base if physical_only else base + self.net.prior_penalty()


MODELS: dict[str, type[ChokeModel]] = {
    cls.name: cls
    for cls in (
        LastValue,
        LinearRegression,
        NeuralNet,
        MultiTask,
        Mechanistic,
        HybridError,
        HybridArea,
    )
}


def make_model(name: str, wells: Sequence[str], **hyper: Any) -> ChokeModel:
    """Build a registered model by name; an unknown name lists the valid ones."""
    try:
        cls = MODELS[name]
    except KeyError:
        raise ConfigError(f"Unknown model '{name}'; choose one of {', '.join(MODELS)}.") from None
    try:
        return cls(wells, **hyper)
    except TypeError as exc:
        raise ConfigError(f"Invalid settings {hyper} for model '{name}': {exc}.") from None


def save_model(model: ChokeModel, path: str | Path) -> Path:
    """Save a model's tensors and hyperparameters to one file, without pickle.

    The file holds only a dict of strings, lists and tensors and is read back with
    ``torch.load(weights_only=True)``, which refuses anything that could run code.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    payload = {
        "format": "vfm-model/1",
        "name": model.name,
        "wells": list(model.wells),
        "hyper": json.dumps(model.hyper),
        "state": {k: v.detach().clone() for k, v in model.state_dict().items()},
    }
    tmp = path.with_name(path.name + ".tmp")
    torch.save(payload, tmp)
    os.replace(tmp, path)
    return path


def load_model(path: str | Path) -> ChokeModel:
    """Load a model written by :func:`save_model` (tensors only, never pickle)."""
    try:
        payload = torch.load(Path(path), weights_only=True)
    except FileNotFoundError:
        raise ConfigError(f"No model file at {path}.") from None
    except Exception as exc:  # a corrupt file or one that is not a vfm model
        raise ConfigError(f"{path} is not a readable VFM model file: {exc}") from None
    if not isinstance(payload, dict) or payload.get("format") != "vfm-model/1":
        raise ConfigError(f"{path} is not a VFM model file (format vfm-model/1).")
    hyper = json.loads(payload["hyper"])
    if "effects" in hyper:
        from vfm_core.effects import make_effect_model

        effects = hyper.pop("effects")
        model = make_effect_model(payload["name"].split("+")[0], payload["wells"], effects, **hyper)
    else:
        model = make_model(payload["name"], payload["wells"], **hyper)
    model.load_state_dict(payload["state"])
    return model
