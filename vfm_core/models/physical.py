"""The physics-based models: the Sachdeva choke model ``mm`` and its two hybrids ``hem`` and
``ham``, each optionally extended with physical effects (:mod:`vfm_core.effects`).

Effects are a constructor argument: ``make_model("mm", wells, effects=["erosion"])`` is the
mechanistic model whose effective area grows with throughput, named ``mm+erosion``. Each
effect keeps one set of parameters per well, standardised like the mechanistic ones
(theta = mu + sigma z; the prior penalty is sum z^2; bounds clamp z), and changes the
Sachdeva computation through its hooks (area factor, gas Z, slip, critical ratio, output
factor). With no effects the computation is exactly the plain model's.

Units: inputs in file units (fraction, bar a, bar a, degC, -, -) converted to SI here;
parameters in SI (kg/m3, -, kg/mol); rates in Sm3/h.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any, ClassVar, cast

import numpy as np
import torch
from torch import nn

from vfm_core import physics as ph
from vfm_core.data import DTYPE, Batch
from vfm_core.effects import CompiledFactor, Effect, EffectInputs, effect_spec, resolve_effects
from vfm_core.errors import ConfigError
from vfm_core.models.base import (
    ChokeModel,
    FilterBlock,
    Gradients,
    PhysicalParameters,
    Pullback,
    WellMLP,
)
from vfm_core.units import bar_to_pa, degc_to_k

__all__ = ["PHYSICAL_NAMES", "Mechanistic", "HybridError", "HybridArea", "mechanistic_rate"]

#: The mechanistic parameters theta_MM, in this order (see :data:`vfm_core.physics.PRIORS`).
PHYSICAL_NAMES: tuple[str, ...] = ("rho_oil", "rho_wat", "kappa", "m_gas", "p_cr", "c_d")

_SECONDS_PER_HOUR = 3600.0


def _sachdeva_rate(
    inputs: EffectInputs,
    area: torch.Tensor,
    effects: Sequence[Effect],
    values: dict[str, dict[str, torch.Tensor]],
) -> torch.Tensor:
    """Sachdeva total rate at standard conditions, Sm3/h [W, N], with every effect applied.

    ``inputs`` in SI units with ``theta`` [W, 1]; ``area`` [W, N] is the effective flow
    area C_D A_2(u), m2, before the effects' area factors; ``values`` the effects'
    parameters [W, 1] by effect name.
    """
    z: torch.Tensor | float = 1.0
    for e in effects:
        f = e.area_factor(inputs, values[e.name])
        area = area if f is None else area * f
        gz = e.gas_z(inputs, values[e.name])
        z = z if gz is None else z * gz
    inputs.z = z
    th = inputs.theta
    p_cr: torch.Tensor = th["p_cr"]
    slip_w: torch.Tensor | None = None
    for e in effects:
        pc = e.critical_ratio(inputs, values[e.name])
        p_cr = p_cr if pc is None else pc
        w = e.slip(inputs, values[e.name])
        if w is not None:
            slip_w = w if slip_w is None else slip_w + w
    args = (inputs.p_up, inputs.p_down, inputs.t_up, inputs.eta_gas, inputs.eta_oil)
    kw: dict[str, Any] = dict(
        rho_oil=th["rho_oil"],
        rho_wat=th["rho_wat"],
        kappa=th["kappa"],
        m_gas=th["m_gas"],
        p_cr=torch.clamp(p_cr, 0.05, 0.99),
        z=z,
    )
    flux = ph.choke_mass_flux(*args, **kw)
    if slip_w is not None:
        flux_slip = ph.choke_mass_flux(*args, slip=True, **kw)
        ratio = torch.clamp(flux_slip, min=1e-12) / torch.clamp(flux, min=1e-12)
        flux = flux * torch.exp(slip_w * torch.log(ratio))
    per_kg = ph.standard_volume_per_mass(
        inputs.eta_gas,
        inputs.eta_oil,
        rho_oil=th["rho_oil"],
        rho_wat=th["rho_wat"],
        m_gas=th["m_gas"],
    )
    q = area * flux * per_kg * _SECONDS_PER_HOUR
    for e in effects:
        f = e.output_factor(inputs, values[e.name])
        q = q if f is None else q * f
    return q


def _si_inputs(
    batch: Batch, theta: dict[str, torch.Tensor], u_ref: torch.Tensor | None
) -> EffectInputs:
    """What the physics and the effects' hooks see: SI inputs [W, N], parameters [W, 1]."""
    u, p_up, p_down, t_up, eta_gas, eta_oil = batch.x.unbind(-1)
    assert batch.extra is not None and batch.well_test is not None
    w = batch.x.shape[0]
    return EffectInputs(
        u=u,
        p_up=bar_to_pa(p_up),
        p_down=bar_to_pa(p_down),
        t_up=degc_to_k(t_up),
        eta_gas=eta_gas,
        eta_oil=eta_oil,
        theta={k: v.unsqueeze(1) for k, v in theta.items()},
        well_test=batch.well_test,
        u_ref=(u_ref if u_ref is not None else torch.full((w,), 0.5, dtype=DTYPE)).unsqueeze(1),
        extra={n: batch.extra[..., i] for i, n in enumerate(batch.extra_names)},
        time_ns=batch.time_ns,
    )


def _plain_batch(x: torch.Tensor) -> Batch:
    """A batch of the six inputs alone (every sample valid, no time, no features)."""
    w, n = x.shape[0], x.shape[1]
    return Batch(
        [str(j) for j in range(w)],
        x,
        torch.zeros(w, n, dtype=DTYPE),
        torch.ones(w, n, dtype=torch.bool),
        torch.zeros(w, n, dtype=torch.int64),
        torch.zeros(w, n, dtype=torch.int64),
    )


def mechanistic_rate(
    x: torch.Tensor, theta: dict[str, torch.Tensor], area: torch.Tensor
) -> torch.Tensor:
    """Sachdeva total rate at standard conditions, Sm3/h [W, N], without effects.

    ``x`` [W, N, 6] in file units; ``theta`` values [W]; ``area`` [W, N] effective flow
    area C_D A_2 in m2.
    """
    return _sachdeva_rate(_si_inputs(_plain_batch(x), theta, None), area, (), {})


def _sachdeva_vjp(
    batch: Batch, theta: dict[str, torch.Tensor], area: torch.Tensor
) -> tuple[torch.Tensor, Callable[[torch.Tensor], tuple[dict[str, torch.Tensor], torch.Tensor]]]:
    """:func:`_sachdeva_rate` without effects [W, N] (Sm3/h, no graph) and its pullback:
    from d loss / d rate [W, N] to d loss / d theta [W] (SI, by name) and d loss / d area
    [W, N], in closed form (the flux's derivatives are :func:`vfm_core.physics.flux_vjp`)."""
    i = _si_inputs(batch, theta, None)
    th = i.theta
    p_cr = th["p_cr"]
    p_cr_used = torch.clamp(p_cr, 0.05, 0.99)
    flux, parts = ph._flux(
        i.p_up,
        i.p_down,
        i.t_up,
        i.eta_gas,
        i.eta_oil,
        th["rho_oil"],
        th["rho_wat"],
        th["kappa"],
        th["m_gas"],
        p_cr_used,
        1.0,
        False,
    )
    gas_sc = i.eta_gas / ph.gas_density_standard(th["m_gas"])  # Sm3 of gas per kg
    per_kg = gas_sc + ph.liquid_specific_volume(i.eta_gas, i.eta_oil, th["rho_oil"], th["rho_wat"])
    unit = flux * per_kg * _SECONDS_PER_HOUR
    q = area * flux * per_kg * _SECONDS_PER_HOUR  # in _sachdeva_rate's order: the same numbers

    def pullback(grad: torch.Tensor) -> tuple[dict[str, torch.Tensor], torch.Tensor]:
        g_flux = grad * area * per_kg * _SECONDS_PER_HOUR
        d = ph.flux_vjp(
            parts,
            g_flux,
            flux,
            i.p_up,
            i.p_down,
            i.eta_oil,
            th["rho_oil"],
            th["rho_wat"],
            th["m_gas"],
            p_cr_used,
            1.0,
        )
        g_kg = grad * area * flux * _SECONDS_PER_HOUR
        eta_wat = 1.0 - i.eta_gas - i.eta_oil
        inside = ((p_cr >= 0.05) & (p_cr <= 0.99)).to(DTYPE)  # the clamp's gradient
        d_theta = {
            "rho_oil": (d["rho_oil"] - g_kg * i.eta_oil / th["rho_oil"] ** 2).sum(1),
            "rho_wat": (d["rho_wat"] - g_kg * eta_wat / th["rho_wat"] ** 2).sum(1),
            "kappa": d["kappa"].sum(1),
            "m_gas": (d["m_gas"] - g_kg * gas_sc / th["m_gas"]).sum(1),
            "p_cr": (d["p_cr"] * inside).sum(1),
        }
        return d_theta, grad * unit

    return q, pullback


class Mechanistic(ChokeModel):
    """The Sachdeva choke model (paper eq. MM) with learned rho_oil, rho_wat, kappa, M_gas, p_cr, C_D.

    The valve is linear, A_2(u) = A_max u. A_max, the full-open flow area, is not in the
    observation format; it is set once per well from its training data so that the model
    at the prior means (effects included, at theirs) matches the median measured rate (the
    choke size is a fixed property of the well, C_D keeps its physical prior).

    ``effects``: registry names, ``name:key=value`` settings or ``module:Class`` of
    :class:`vfm_core.effects.Effect` subclasses, or the classes themselves.
    """

    key = "mm"
    train_defaults = {"lr": 3e-2}
    online_defaults = {"lr": 1e-3, "steps": 10}
    physical_names: ClassVar[tuple[str, ...]] = PHYSICAL_NAMES
    # buffers (registered in _build): each well's full-open area, m2, and, with valve
    # effects, its reference opening
    a_max: torch.Tensor
    u_ref: torch.Tensor

    def __init__(
        self,
        wells: Sequence[str],
        *,
        seed: int = 0,
        effects: Sequence[str | type[Effect]] = (),
    ) -> None:
        self._build(wells, seed, effects, hidden=None)

    def _build(
        self,
        wells: Sequence[str],
        seed: int,
        effects: Sequence[str | type[Effect]],
        hidden: Sequence[int] | None,
    ) -> None:
        """Parameters in a fixed order (the optimiser's and the state's): the mechanistic
        ones, the hybrid's network (``hidden`` layer sizes), then each effect's."""
        ChokeModel.__init__(self, wells, seed=seed)
        n = len(self.wells)
        self.phys = PhysicalParameters(n, self.physical_names)
        self.register_buffer("a_max", torch.ones(n, dtype=DTYPE))
        self.net: WellMLP | None = None
        if hidden is not None:
            self.hyper["hidden"] = list(hidden)
            self.net = WellMLP(n, [6, *hidden, 1], self._gen)
        classes = resolve_effects(list(effects))
        self.effects: list[Effect] = [cls() for cls in classes]
        self.effect_params = nn.ModuleDict(
            {e.name: PhysicalParameters(n, e.parameters) for e in self.effects}
        )
        if not self.effects:
            return
        # the reference opening of valve effects: each well's median training opening
        self.register_buffer("u_ref", torch.full((n,), 0.5, dtype=DTYPE))
        columns: list[str] = []
        for e in self.effects:
            columns += [c for c in e.extra_columns if c not in columns]
        self.extra_columns = tuple(columns)
        self.needs_source = any(e.uses_source for e in self.effects)
        # how to rebuild the model (JSON): registry names, or module:Class for a user's own
        self.hyper["effects"] = [effect_spec(c) for c in classes]

    @property
    def name(self) -> str:
        return "+".join([self.key, *(e.name for e in self.effects)])

    # -- parameters ----------------------------------------------------------------------
    def _prior_theta(self) -> dict[str, torch.Tensor]:
        n = len(self.wells)
        return {k: torch.full((n,), ph.PRIORS[k].mean, dtype=DTYPE) for k in PHYSICAL_NAMES}

    def theta(self) -> dict[str, torch.Tensor]:
        """The mechanistic parameters [W] in SI units (prior means for those not learned)."""
        learned = self.phys.values()
        if len(learned) == len(PHYSICAL_NAMES):
            return learned
        n = len(self.wells)
        values = {
            k: learned[k] if k in learned else torch.full((n,), ph.PRIORS[k].mean, dtype=DTYPE)
            for k in PHYSICAL_NAMES
        }
        return values

    def effect_block(self, name: str) -> PhysicalParameters:
        """The parameters of the effect ``name`` (one of :attr:`effects`)."""
        return cast(PhysicalParameters, self.effect_params[name])

    def effect_values(self) -> dict[str, dict[str, torch.Tensor]]:
        """Each effect's parameters [W] by effect and parameter name, SI units."""
        return {e.name: self.effect_block(e.name).values() for e in self.effects}

    # -- the rate ------------------------------------------------------------------------
    def area(self, x: torch.Tensor, theta: dict[str, torch.Tensor]) -> torch.Tensor:
        """Effective flow area C_D A_max u, m2, [W, N] (before effects)."""
        return (theta["c_d"] * self.a_max).unsqueeze(1) * x[..., 0]

    def _u_ref(self) -> torch.Tensor | None:
        return self.u_ref if self.effects else None

    def mechanistic(self, batch: Batch) -> torch.Tensor:
        """The Sachdeva rate with every effect applied, Sm3/h [W, N]."""
        theta = self.theta()
        inputs = _si_inputs(batch, theta, self._u_ref())
        values = {
            k: {n: v.unsqueeze(1) for n, v in d.items()} for k, d in self.effect_values().items()
        }
        return _sachdeva_rate(inputs, self.area(batch.x, theta), self.effects, values)

    def forward_batch(self, batch: Batch) -> torch.Tensor:
        return self.mechanistic(batch)

    def compiled_columns(self, batch: Batch) -> np.ndarray | None:
        """The per-sample columns [W, N, 2 S] the compiled forms of this model's ``suggest``
        effects read (:attr:`vfm_core.effects.CompiledFactor.SUGGEST`: each one's two, in the
        order of :attr:`effects`), computed by the effects themselves; None without one."""
        makers = self.__dict__.get("_vfm_column_makers")
        if makers is None:
            forms = [(e, e.compiled_factor()) for e in self.effects]
            makers = [e for e, f in forms if f is not None and f.code == CompiledFactor.SUGGEST]
            self.__dict__["_vfm_column_makers"] = makers
        if not makers:
            return None
        x, time_ns = batch.x.numpy(), batch.time_ns.numpy()
        ex = np.zeros((*x.shape[:2], 0)) if batch.extra is None else batch.extra.numpy()
        extra = {n: ex[..., i] for i, n in enumerate(batch.extra_names)}
        return np.concatenate(
            [e.compiled_columns(x, extra, time_ns) for e in makers],  # type: ignore[attr-defined]
            -1,
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.extra_columns or self.needs_source:
            raise ConfigError(
                f"The model {self.name} needs per-sample features or the measurement source; "
                "call forward_batch(batch) with a batch from "
                "make_batch(..., extra_columns=model.extra_columns)."
            )
        return self.forward_batch(_plain_batch(x))

    # -- set-up --------------------------------------------------------------------------
    def _setup_new(self, batch: Batch, new: torch.Tensor) -> None:
        with torch.no_grad():
            if self.effects:
                u = torch.where(batch.mask, batch.x[..., 0], torch.full_like(batch.y, float("nan")))
                u_med = torch.nanmedian(u, dim=1).values
                self.u_ref[new] = torch.where(
                    torch.isfinite(u_med[new]), u_med[new], torch.full_like(u_med[new], 0.5)
                )
            # A_max: the model at prior means (effects at theirs) matches the median rate
            theta = self._prior_theta()
            n = len(self.wells)
            values = {
                e.name: {
                    k: torch.full((n, 1), float(p.mean), dtype=DTYPE)
                    for k, p in e.parameters.items()
                }
                for e in self.effects
            }
            inputs = _si_inputs(batch, theta, self._u_ref())
            unit = _sachdeva_rate(
                inputs, theta["c_d"].unsqueeze(1) * batch.x[..., 0], self.effects, values
            )
            ratio = torch.where(
                batch.mask & (unit > 0), batch.y / unit, torch.full_like(unit, float("nan"))
            )
            a_max = torch.nanmedian(ratio, dim=1).values
            self.a_max[new] = torch.where(
                torch.isfinite(a_max[new]), a_max[new], torch.ones_like(a_max[new])
            )

    # -- prior and bounds ----------------------------------------------------------------
    def _effect_penalty(self) -> torch.Tensor:
        total = torch.zeros(len(self.wells), dtype=DTYPE)
        for p in map(self.effect_block, self.effect_params):
            total = total + p.penalty()
        return total

    def prior_penalty(self, physical_only: bool = False) -> torch.Tensor:
        base = self.phys.penalty()
        if self.net is not None and not physical_only:
            base = base + self.net.prior_penalty()
        return base + self._effect_penalty() if self.effects else base

    def project_(self) -> None:
        self.phys.project_()
        for p in map(self.effect_block, self.effect_params):
            p.project_()

    def physical_parameters(self) -> dict[str, torch.Tensor]:
        with torch.no_grad():
            out = {k: v.detach().clone() for k, v in self.phys.values().items()}
            out["a_max"] = self.a_max.clone()
            for e in self.effects:
                for n, v in self.effect_block(e.name).values().items():
                    out[f"{e.name}.{n}"] = v.detach().clone()
        return out

    def filter_blocks(self) -> list[FilterBlock]:
        """The mechanistic parameters, each effect's, and a hybrid's output layer."""
        blocks = [self.phys.filter_block()]
        blocks += [self.effect_block(e.name).filter_block(f"{e.name}.") for e in self.effects]
        if self.net is not None:
            blocks += self.net.head_blocks("head", correction=True)
        return blocks

    # -- closed-form gradients (no effects) ---------------------------------------------
    def compiled_as(self) -> str | None:
        """``mm`` for exactly this class without effects, its six parameters in the order
        of :data:`PHYSICAL_NAMES`, in float64 (see :meth:`ChokeModel.compiled_as`)."""
        return None if self.effects else self._compiled_shape()

    def compiled_with_effects(self) -> str | None:
        """What :meth:`compiled_as` would say of this model without its effects, when it
        has effects and every one of them has a compiled form
        (:meth:`vfm_core.effects.Effect.compiled_factor`: the effects that multiply the
        rate, real gas, slip, the critical ratio), at most one of those that change the flux
        per kind and not the critical ratio beside real gas; else None. The kernels then
        compute the model with its effects."""
        if not self.effects:
            return None
        compiled = self.__dict__.get("_vfm_compiled_effects")
        if compiled is None:
            forms = [e.compiled_factor() for e in self.effects]
            codes = [f.code for f in forms if f is not None]
            kinds = (CompiledFactor.GAS, CompiledFactor.SLIP, CompiledFactor.CRITICAL)
            flux = [c for c in codes if c in kinds]
            compiled = len(codes) == len(forms) and len(set(flux)) == len(flux)
            # the kernels solve the critical ratio with the ideal gas's density
            compiled &= not {CompiledFactor.GAS, CompiledFactor.CRITICAL} <= set(flux)
            self.__dict__["_vfm_compiled_effects"] = compiled
        return self._compiled_shape() if compiled else None

    def _compiled_shape(self) -> str | None:
        """The kernels' name of this model's shape, effects aside: ``mm`` for exactly this
        class, its six parameters in the order of :data:`PHYSICAL_NAMES`, in float64."""
        if type(self) is not Mechanistic:
            return None
        plain = tuple(self.phys.names) == PHYSICAL_NAMES and self.phys.z.dtype == torch.float64
        return "mm" if plain else None

    def _one_hidden_layer(self, n_phys: int) -> bool:
        """A hybrid the kernels compute (effects aside): a network of one hidden layer on the
        six inputs, the first ``n_phys`` physical parameters, all in float64."""
        if self.net is None:
            return False
        weights = self.net.weights
        names = tuple(self.phys.names)
        return (
            len(weights) == 2
            and weights[0].shape[1] == 6
            and weights[1].shape[2] == 1
            and names == PHYSICAL_NAMES[:n_phys]
            and weights[0].dtype == self.phys.z.dtype == torch.float64
        )

    def rate_vjp(self, batch: Batch) -> tuple[torch.Tensor, Pullback] | None:
        if self.effects or not self._own_closed_form(Mechanistic):
            return None
        with torch.no_grad():
            theta = self.theta()
            unit_area = self.a_max.unsqueeze(1) * batch.x[..., 0]  # A_max u, m2
            q, pull = _sachdeva_vjp(batch, theta, theta["c_d"].unsqueeze(1) * unit_area)

        def pullback(grad: torch.Tensor) -> Gradients:
            d_theta, d_area = pull(grad)
            d_theta["c_d"] = (d_area * unit_area).sum(1)
            return self._phys_gradients(d_theta)

        return q, pullback

    def _phys_gradients(self, d_theta: dict[str, torch.Tensor]) -> Gradients:
        """d loss / d z of the standardised parameters from d loss / d theta (SI)."""
        grads = torch.stack([d_theta[n] for n in self.phys.names], dim=1)
        return {id(self.phys.z): grads * self.phys.sigma}

    def prior_gradients(self, weight: torch.Tensor, physical_only: bool) -> Gradients:
        out = self.phys.penalty_gradients(weight)
        if self.net is not None and not physical_only:
            out.update(self.net.prior_gradients(weight))
        return out

    def physical_priors(self) -> dict[str, ph.Prior]:
        """The prior (mean, sd, bounds, unit) of every learned physical parameter, by the
        names of :meth:`physical_parameters` (``a_max`` is set, not learned: absent)."""
        out = {n: ph.PRIORS[n] for n in self.phys.names}
        for e in self.effects:
            out.update({f"{e.name}.{k}": p for k, p in e.parameters.items()})
        return out


class HybridError(Mechanistic):
    """Hybrid error model: q = MM(x) + y_scale MLP(x_norm) (paper section 'Hybrid error model').

    With effects, the network still adds to the extended mechanistic rate.
    """

    key = "hem"
    train_defaults = {"lr": 1e-2}
    online_defaults = {"lr": 1e-4, "steps": 1}

    def __init__(
        self,
        wells: Sequence[str],
        *,
        seed: int = 0,
        hidden: Sequence[int] = (16,),
        effects: Sequence[str | type[Effect]] = (),
    ) -> None:
        self._build(wells, seed, effects, hidden)

    def forward_batch(self, batch: Batch) -> torch.Tensor:
        assert self.net is not None
        return self.mechanistic(batch) + self.y_scale.unsqueeze(1) * self.net(
            self.normalise(batch.x)
        )

    def _compiled_shape(self) -> str | None:
        """``hem`` for exactly this class in the kernels' shape (one hidden layer on the six
        inputs, float64; see :meth:`ChokeModel.compiled_as`)."""
        return "hem" if type(self) is HybridError and self._one_hidden_layer(6) else None

    def rate_vjp(self, batch: Batch) -> tuple[torch.Tensor, Pullback] | None:
        if self.effects or not self._own_closed_form(HybridError):
            return None
        net = self.net
        assert net is not None
        with torch.no_grad():
            theta = self.theta()
            unit_area = self.a_max.unsqueeze(1) * batch.x[..., 0]
            q_mm, pull = _sachdeva_vjp(batch, theta, theta["c_d"].unsqueeze(1) * unit_area)
            out, cache = net.forward_cached(self.normalise(batch.x))
            scale = self.y_scale.unsqueeze(1)
            q = q_mm + scale * out

        def pullback(grad: torch.Tensor) -> Gradients:
            d_theta, d_area = pull(grad)
            d_theta["c_d"] = (d_area * unit_area).sum(1)
            grads = self._phys_gradients(d_theta)
            grads.update(net.pullback(cache, grad * scale))
            return grads

        return q, pullback


class HybridArea(Mechanistic):
    """Hybrid area model: A_2 = A_max u C_D0 exp(MLP(x)), the network replacing C_D (paper 'HAM').

    The network sees all six inputs, since the effective area depends on the fluid too.
    C_D0 is the prior mean of C_D; an untrained network gives the plain MM. With effects,
    the network's area factor multiplies the effects' area factors.
    """

    key = "ham"
    train_defaults = {"lr": 1e-2}
    online_defaults = {"lr": 1e-4, "steps": 1}
    physical_names = ("rho_oil", "rho_wat", "kappa", "m_gas", "p_cr")

    def __init__(
        self,
        wells: Sequence[str],
        *,
        seed: int = 0,
        hidden: Sequence[int] = (16,),
        effects: Sequence[str | type[Effect]] = (),
    ) -> None:
        self._build(wells, seed, effects, hidden)

    def area(self, x: torch.Tensor, theta: dict[str, torch.Tensor]) -> torch.Tensor:
        assert self.net is not None
        factor = torch.exp(self.net(self.normalise(x)))
        return (ph.PRIORS["c_d"].mean * self.a_max).unsqueeze(1) * x[..., 0] * factor

    def _compiled_shape(self) -> str | None:
        """``ham`` for exactly this class in the kernels' shape (one hidden layer on the six
        inputs, float64; see :meth:`ChokeModel.compiled_as`)."""
        return "ham" if type(self) is HybridArea and self._one_hidden_layer(5) else None

    def rate_vjp(self, batch: Batch) -> tuple[torch.Tensor, Pullback] | None:
        if self.effects or not self._own_closed_form(HybridArea):
            return None
        net = self.net
        assert net is not None
        with torch.no_grad():
            theta = self.theta()
            out, cache = net.forward_cached(self.normalise(batch.x))
            area = (ph.PRIORS["c_d"].mean * self.a_max).unsqueeze(1) * batch.x[..., 0]
            area = area * torch.exp(out)
            q, pull = _sachdeva_vjp(batch, theta, area)

        def pullback(grad: torch.Tensor) -> Gradients:
            d_theta, d_area = pull(grad)
            grads = self._phys_gradients(d_theta)
            grads.update(net.pullback(cache, d_area * area))
            return grads

        return q, pullback
