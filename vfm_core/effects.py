"""Candidate physical effects that extend the mechanistic choke models.

An *effect* is a small documented physical term with named parameters (SI units, Gaussian
priors, hard bounds) that modifies the Sachdeva forward computation through one or more
hooks. The physics models take effects as a constructor argument
(``make_model("mm", wells, effects=["erosion"])``, :mod:`vfm_core.models.physical`) and
keep one set of effect parameters per well, standardised like the mechanistic ones
(theta = mu + sigma z; the prior penalty is sum z^2; bounds clamp z). This module knows
only the physics: it never imports a model. A prior mean is the documented physics where the literature
fixes the size (Papay's Z, Simpson's slip, Sachdeva's critical ratio: strength 1) and
*off* where only the data can tell the size (wear, valve shape, meter bias); A_max is
set with every effect at its prior mean, so an extended model starts level with the data.

Writing your own effect
-----------------------
Subclass :class:`Effect`, give it a ``name``, a ``parameters`` dict of
:class:`vfm_core.physics.Prior` and implement any of the hooks below; each returns a
tensor [W, N] (or [W, 1]) or ``None`` for "no change". ``p`` maps the effect's parameter
names to their values [W, 1] in SI units; ``inputs`` is an :class:`EffectInputs`.

============================  ==============================================================
hook                          what it changes
============================  ==============================================================
``area_factor(inputs, p)``    multiplies the effective flow area C_D A_2(u) (wear, valve)
``gas_z(inputs, p)``          upstream gas compressibility Z (1 = ideal gas)
``slip(inputs, p)``           exponent w on Simpson's two-phase slip multiplier (0 = none)
``critical_ratio(inputs, p)`` the critical pressure ratio p_cr per sample
``output_factor(inputs, p)``  multiplies the predicted (measured) rate (meter bias, ...)
============================  ==============================================================

Features an effect needs beyond the six inputs are columns named in ``extra_columns``;
``features(frame)`` computes them (the standard ones: ``years_on``, ``throughput_years``,
``water_cut``, see :func:`standard_features`). Reference a class of your own as
``module:Class`` (importable from PYTHONPATH) wherever an effect name is accepted.

Public surface: :data:`EFFECTS`, :data:`DEFAULT_CANDIDATES`, :class:`Effect`,
:class:`EffectInputs`, :func:`resolve_effect`, :func:`resolve_effects`,
:func:`effect_spec`, :func:`add_features`, :func:`standard_features`.
"""

from __future__ import annotations

import importlib
import math
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import ClassVar

import numpy as np
import pandas as pd
import torch

from vfm_core import physics as ph
from vfm_core.errors import ConfigError
from vfm_core.features import standard_features
from vfm_core.physics import DTYPE, Prior
from vfm_core.timeutil import utc_timestamp
from vfm_core.units import bar_to_pa, degc_to_k

__all__ = [
    "fixed_effect",
    "Prior",
    "Effect",
    "EffectInputs",
    "CompiledFactor",
    "Erosion",
    "ErosionTime",
    "Valve",
    "ValveFamily",
    "RealGas",
    "Slip",
    "CriticalRatio",
    "MeterBias",
    "EFFECTS",
    "DEFAULT_CANDIDATES",
    "standard_features",
    "add_features",
    "resolve_effect",
    "resolve_effects",
    "effect_spec",
]


def add_features(frame: pd.DataFrame, effects: Sequence[str | type[Effect]]) -> pd.DataFrame:
    """A copy of ``frame`` with every extra column the ``effects`` need (input not mutated)."""
    out = frame.copy()
    classes = {c.name: c for c in (resolve_effect(e) for e in effects)}
    for cls in classes.values():
        missing = [c for c in cls.extra_columns if c not in out.columns]
        if missing:
            feats = cls.features(out)
            for col in missing:
                if col not in feats.columns:
                    raise ConfigError(
                        f"Effect '{cls.name}' needs the column '{col}' but its features() "
                        "did not compute it; return every name of extra_columns."
                    )
                out[col] = feats[col].to_numpy()
    return out


# --- the protocol ---------------------------------------------------------------------------
@dataclass
class EffectInputs:
    """What an effect's hooks see, all [W, N] tensors in SI units (see :mod:`vfm_core.physics`).

    ``theta``: the base model's mechanistic parameters [W, 1]; ``z``: the upstream gas
    compressibility after the ``gas_z`` hooks; ``u_ref``: each well's median training
    opening [W, 1]; ``extra``: the batch's feature columns by name.
    """

    u: torch.Tensor
    p_up: torch.Tensor
    p_down: torch.Tensor
    t_up: torch.Tensor
    eta_gas: torch.Tensor
    eta_oil: torch.Tensor
    theta: dict[str, torch.Tensor]
    well_test: torch.Tensor
    u_ref: torch.Tensor
    extra: dict[str, torch.Tensor] = field(default_factory=dict)
    z: torch.Tensor | float = 1.0
    time_ns: torch.Tensor | None = None

    def feature(self, name: str) -> torch.Tensor:
        """A feature column [W, N] by name; a clear error if the batch lacks it."""
        try:
            return self.extra[name]
        except KeyError:
            raise ConfigError(
                f"The feature '{name}' is not in this batch (it has {sorted(self.extra)}); "
                "list it in the effect's extra_columns."
            ) from None

    @property
    def water_cut(self) -> torch.Tensor:
        """Water share of the liquid mass, -."""
        wat = 1.0 - self.eta_gas - self.eta_oil
        return torch.clamp(wat / torch.clamp(self.eta_oil + wat, min=1e-9), 0.0, 1.0)


@dataclass(frozen=True)
class CompiledFactor:
    """How the compiled kernels (:mod:`vfm_core.learning.kernels`) compute an effect that
    multiplies the rate (its ``area_factor`` or ``output_factor``; ``suggest`` through
    columns it computes itself) or one of the library's three that change the flux (real
    gas, slip, the critical ratio), with the same arithmetic: ``code`` one of the constants
    below, ``column`` the feature column it reads (or None), ``settings`` up to two integers
    (a knot count, a family's index, a step time in ns, a form). An effect returns one from :meth:`Effect.compiled_factor`; any other
    effect runs the torch path (the same numbers, slower)."""

    EROSION: ClassVar[int] = 1  # max(1 + p0 x, 0.05) [* max(1 + p1 [t >= settings[1]], 0.05)]
    VALVE: ClassVar[int] = 2  # Valve's piecewise-linear curve, settings[0] knots
    FAMILY: ClassVar[int] = 3  # ValveFamily, settings[0] the index in AREA_FUNCTIONS
    BIAS: ClassVar[int] = 4  # MeterBias: 1 + p0 + p1 x on MPFM rows, 1 on well tests
    #: the two that change the flux itself (their factor is 1; the kernels compute the
    #: flux with them, ``_mm_numba.flux_rate_grad``); at most one of each in a model
    GAS: ClassVar[int] = 5  # RealGas: Z = max(1 + p0 (Z_Papay - 1), 0.2)
    SLIP: ClassVar[int] = 6  # Slip: the flux times (G_Simpson / G)^p0
    #: Suggest: a factor of per-sample columns the effect computes (its
    #: ``compiled_columns``, two per effect, after the batch's features): settings[0] the form,
    #: 0 max(1 + p0 c0, 0.05), 1 exp(clamp(p0 c0, -5, 5)), 2 1 + p0 c0 + p1 c1, 3 c0 (fixed)
    SUGGEST: ClassVar[int] = 7
    #: CriticalRatio: p_cr + p0 (y_c - p_cr) in the flux, y_c Sachdeva's solved ratio (no
    #: gradient through it, as the torch hook); not beside RealGas (y_c would need its Z)
    CRITICAL: ClassVar[int] = 8

    code: int
    column: str | None = None
    settings: tuple[int, int] = (0, 0)


_HOOKS = ("area_factor", "gas_z", "slip", "critical_ratio", "output_factor")


def _hooks_of(effect: Effect, owner: type[Effect]) -> bool:
    """True when every hook of ``effect`` is ``owner``'s or the base class's: a subclass
    that rewrites a hook has other arithmetic than the compiled form of ``owner``."""
    cls = type(effect)
    return all(
        getattr(cls, h) is getattr(owner, h) or getattr(cls, h) is getattr(Effect, h)
        for h in _HOOKS
    )


class Effect:
    """Base class of a candidate effect; see the module docstring for the protocol.

    Hyperparameters (if any) are the ``__init__`` keyword arguments; learned values live
    in the model, not in the effect.
    """

    name: ClassVar[str] = ""
    description: ClassVar[str] = ""
    parameters: ClassVar[Mapping[str, Prior]] = {}
    extra_columns: ClassVar[tuple[str, ...]] = ()
    #: Settings the effect accepts as ``name:key=value`` (key -> what it means); none by default.
    settings: ClassVar[Mapping[str, str]] = {}
    #: How to name this (configured) effect so it can be rebuilt; default ``name``.
    spec: ClassVar[str] = ""
    #: True when the effect treats MPFM readings and well tests differently (a meter bias)
    uses_source: ClassVar[bool] = False
    #: True for physics of the flow law or the fluid (slip, real gas, the critical ratio):
    #: its parameters correct a correlation that is the same at every well, so the wells'
    #: fitted values should agree within their uncertainty; False for what belongs to one
    #: well's hardware or meter (wear, its valve, its MPFM), which differs from well to well.
    #: The diagnosis uses it to tell a field-wide fit from one that does a well's job
    #: (:func:`vfm_core.jobs.diagnose_rivals.consistency`).
    field_wide: ClassVar[bool] = False

    @classmethod
    def configure(cls, **values: str) -> type[Effect]:
        """A subclass with the given settings (text values from ``name:key=value``).

        By default each setting becomes a class attribute of that name holding the text;
        override to parse values (see :class:`Erosion`). A key that names one of the
        effect's parameters (and no setting) fixes it, shared by every well
        (:func:`fixed_effect`: ``valve_equal_percentage:weight=0.99``).
        """
        fixed = {k: v for k, v in values.items() if k in cls.parameters and k not in cls.settings}
        if fixed:  # name:parameter=value fixes a parameter (shared by every well)
            rest = {k: v for k, v in values.items() if k not in fixed}
            return fixed_effect(cls.configure(**rest) if rest else cls, _numbers(cls, fixed))
        unknown = sorted(set(values) - set(cls.settings))
        if unknown:
            known = ", ".join(f"{k} ({v})" for k, v in cls.settings.items()) or "none"
            raise ConfigError(
                f"Effect '{cls.name}' has no setting {', '.join(unknown)}; its settings: {known} "
                f"(or a parameter to fix: {', '.join(cls.parameters) or 'none'})."
            )
        if not values:
            return cls
        text = ":".join(f"{k}={v}" for k, v in values.items())
        base = cls.spec or (
            cls.name if EFFECTS.get(cls.name) is cls else f"{cls.__module__}:{cls.__qualname__}"
        )
        return type(
            f"{cls.__name__}Configured",
            (cls,),
            {**values, "spec": f"{base}:{text}", "__module__": cls.__module__},
        )

    @classmethod
    def features(cls, frame: pd.DataFrame) -> pd.DataFrame:
        """The ``extra_columns`` for every row of ``frame`` (default: standard features)."""
        return standard_features(frame)

    def area_factor(self, inputs: EffectInputs, p: dict[str, torch.Tensor]) -> torch.Tensor | None:
        return None

    def gas_z(self, inputs: EffectInputs, p: dict[str, torch.Tensor]) -> torch.Tensor | None:
        return None

    def slip(self, inputs: EffectInputs, p: dict[str, torch.Tensor]) -> torch.Tensor | None:
        return None

    def critical_ratio(
        self, inputs: EffectInputs, p: dict[str, torch.Tensor]
    ) -> torch.Tensor | None:
        return None

    def output_factor(
        self, inputs: EffectInputs, p: dict[str, torch.Tensor]
    ) -> torch.Tensor | None:
        return None

    def compiled_factor(self) -> CompiledFactor | None:
        """The compiled form of this effect (:class:`CompiledFactor`), or None (the default:
        a model with this effect learns and predicts through torch). Only for an effect
        that multiplies the rate, or the library's real gas and slip, with exactly the
        arithmetic of its hooks."""
        return None

    def describe(self, values: Mapping[str, float]) -> str:
        """One sentence on the fitted values (field medians, SI units)."""
        parts = [
            f"{k} = {v:.4g} {self.parameters[k].unit}".rstrip() + f" ({self.parameters[k].meaning})"
            for k, v in values.items()
            if k in self.parameters
        ]
        return f"{self.name}: " + "; ".join(parts) + "."


def _numbers(cls: type[Effect], values: Mapping[str, str]) -> dict[str, float]:
    """The fixed parameter values of ``name:parameter=value`` (text), checked: finite and
    within the parameter's bounds (SI units, as the parameter's prior)."""
    out: dict[str, float] = {}
    for key, text in values.items():
        try:
            value = float(text)
        except ValueError:
            value = math.nan
        prior = cls.parameters[key]
        if not (math.isfinite(value) and prior.low <= value <= prior.high):
            unit = "" if prior.unit in ("", "-") else f" {prior.unit}"  # "-": dimensionless
            raise ConfigError(
                f"Effect '{cls.name}': {key}='{text}' must be a number in "
                f"[{prior.low:g}, {prior.high:g}]{unit}."
            )
        out[key] = value
    return out


#: The prior standard deviation of a fixed parameter (SI units): the parameter stays in the
#: model (so the compiled forms apply and the spec rebuilds it) but cannot move.
FIXED_STD = 1e-9


def fixed_effect(cls: type[Effect], values: Mapping[str, float]) -> type[Effect]:
    """``cls`` with the parameters in ``values`` fixed (SI units, one value shared by every
    well): each is pinned by a prior of mean the value and sd :data:`FIXED_STD`, so
    nothing is learned for it (theta = mu + sigma z moves by 1e-9 z at most) while the
    model computes as with ``cls`` (its compiled forms too). Its spec
    ``name:parameter=value`` rebuilds it (``valve_equal_percentage:weight=0.99``).

    What ``vfm diagnose`` replays on a hybrid (``ham``, ``hem``) for an effect acting
    through an input its network sees: the effect as identified on the mechanistic core,
    the network learning what is left (:func:`vfm_core.jobs.diagnose.core_form`)."""
    unknown = sorted(set(values) - set(cls.parameters))
    if unknown:
        raise ConfigError(f"Effect '{cls.name}' has no parameter {', '.join(unknown)}.")
    fixed = {**getattr(cls, "fixed_values", {}), **{k: float(v) for k, v in values.items()}}
    text = "".join(f":{k}={v:.6g}" for k, v in fixed.items())
    base = getattr(cls, "unfixed_spec", "") or effect_spec(cls)
    return type(
        f"{cls.__name__}Fixed",
        (cls,),
        {
            "parameters": {
                k: replace(p, mean=fixed[k], std=FIXED_STD) if k in fixed else p
                for k, p in cls.parameters.items()
            },
            "fixed_values": fixed,
            "unfixed_spec": base,
            "spec": f"{base}{text}",
            "__module__": cls.__module__,
        },
    )


# --- the library ------------------------------------------------------------------------------
class Erosion(Effect):
    """Choke wear: C_D A grows linearly with cumulative throughput, factor 1 + rate * V/V_year.

    Optionally with a sudden step at a known date (a sand event, a choke change or repair,
    from the well's log): ``erosion:step_at=2019-06-01`` multiplies the area by
    1 + step from that time on and learns ``step`` as well.
    """

    name = "erosion"
    description = (
        "Choke wear: the effective flow area grows in proportion to the cumulative produced "
        "volume (in year-equivalents of the well's early rate), optionally with a step at a date."
    )
    parameters = {
        "rate": Prior(0.0, 0.05, 0.0, 1.0, "1/yr-eq", "relative C_D growth per year of throughput"),
    }
    extra_columns = ("throughput_years",)
    basis = "throughput_years"
    settings = {"step_at": "date and time (UTC) of a sudden C_D step, e.g. 2019-06-01"}
    step_at_ns: ClassVar[int | None] = None

    @classmethod
    def configure(cls, **values: str) -> type[Effect]:
        unknown = sorted(set(values) - set(cls.settings))
        if unknown:
            return super().configure(**values)  # says which settings exist
        if "step_at" not in values:
            return cls
        try:
            when = pd.Timestamp(values["step_at"])
            if pd.isna(when):
                raise ValueError("no date")
        except (ValueError, TypeError):
            raise ConfigError(
                f"Effect '{cls.name}': step_at='{values['step_at']}' is not a date "
                "(use e.g. step_at=2019-06-01 or 2019-06-01T12:00)."
            ) from None
        when = utc_timestamp(when)
        text = when.strftime("%Y-%m-%dT%H:%M")
        return type(
            f"{cls.__name__}Step",
            (cls,),
            {
                "parameters": {
                    **cls.parameters,
                    "step": Prior(0.0, 0.1, -0.5, 2.0, "-", f"relative C_D step at {text} UTC"),
                },
                "step_at_ns": int(when.value),
                "spec": f"{cls.name}:step_at={text}",
                "__module__": cls.__module__,
            },
        )

    def area_factor(self, inputs: EffectInputs, p: dict[str, torch.Tensor]) -> torch.Tensor:
        factor = torch.clamp(1.0 + p["rate"] * inputs.feature(self.basis), min=0.05)
        if self.step_at_ns is not None:
            if inputs.time_ns is None:
                raise ConfigError(f"Effect '{self.spec}' needs each sample's time.")
            after = (inputs.time_ns >= self.step_at_ns).to(factor.dtype)
            factor = factor * torch.clamp(1.0 + p["step"] * after, min=0.05)
        return factor

    def compiled_factor(self) -> CompiledFactor | None:
        if not _hooks_of(self, Erosion) or list(self.parameters)[:1] != ["rate"]:
            return None
        step = self.step_at_ns is not None
        return CompiledFactor(
            CompiledFactor.EROSION, self.basis, (int(step), int(self.step_at_ns or 0))
        )

    def describe(self, values: Mapping[str, float]) -> str:
        unit = (
            "per year-equivalent of throughput" if self.basis == "throughput_years" else "per year"
        )
        text = f"C_D grows {100 * values['rate']:.2g} % {unit} (choke wear)"
        if self.step_at_ns is not None and "step" in values:
            when = pd.Timestamp(self.step_at_ns, tz="UTC").strftime("%Y-%m-%d %H:%M")
            text += f", and steps by {100 * values['step']:+.2g} % at {when} UTC"
        return text + "."


class ErosionTime(Erosion):
    """Choke wear growing with time on stream: factor 1 + rate * years since the well's start."""

    name = "erosion_time"
    description = (
        "Choke wear: the effective flow area grows linearly with years since the well's start."
    )
    parameters = {"rate": Prior(0.0, 0.05, 0.0, 1.0, "1/yr", "relative C_D growth per year")}
    extra_columns = ("years_on",)
    basis = "years_on"


class Valve(Effect):
    """A learned monotone valve characteristic A_2(u) replacing the linear one.

    A_2 is piecewise linear on ``knots`` equal intervals of u with slopes exp(log_slope_k)
    (positive, so A_2 is monotone), scaled to equal the linear valve at the well's median
    training opening (the level stays with C_D and A_max). All slopes equal = linear.
    """

    name = "valve"
    description = "Valve characteristic: a learned monotone area curve A_2(u) instead of linear."
    knots: ClassVar[int] = 6
    parameters = {
        f"log_slope_{k + 1}": Prior(
            0.0,
            1.0,
            -4.0,
            4.0,
            "-",
            f"log relative valve gain for u in [{k / 6:.2f}, {(k + 1) / 6:.2f}]",
        )
        for k in range(6)
    }

    def _curve(self, u: torch.Tensor, slopes: torch.Tensor) -> torch.Tensor:
        # slopes [W, K]; A(u) = sum_k slope_k * overlap(u, interval k)
        k = slopes.shape[-1]
        lo = torch.arange(k, dtype=DTYPE) / k
        overlap = torch.clamp(u.unsqueeze(-1) - lo, min=0.0, max=1.0 / k)
        return (overlap * slopes.unsqueeze(1)).sum(-1)

    def area_factor(self, inputs: EffectInputs, p: dict[str, torch.Tensor]) -> torch.Tensor:
        slopes = torch.exp(torch.cat([p[f"log_slope_{k + 1}"] for k in range(self.knots)], dim=-1))
        u = torch.clamp(inputs.u, 1e-3, 1.0)
        a_u = self._curve(u, slopes)
        a_ref = self._curve(torch.clamp(inputs.u_ref, 1e-3, 1.0), slopes)
        return a_u / torch.clamp(a_ref, min=1e-9) * inputs.u_ref / u

    def compiled_factor(self) -> CompiledFactor | None:
        names = [f"log_slope_{k + 1}" for k in range(self.knots)]
        if not _hooks_of(self, Valve) or list(self.parameters) != names:
            return None
        return CompiledFactor(CompiledFactor.VALVE, None, (self.knots, 0))

    def describe(self, values: Mapping[str, float]) -> str:
        gains = [math.exp(values[f"log_slope_{k + 1}"]) for k in range(self.knots)]
        text = ", ".join(f"{g:.2g}" for g in gains)
        return f"Valve gain dA/du relative to linear, from closed to open: {text}."


class ValveFamily(Effect):
    """A named valve family of :data:`vfm_core.physics.AREA_FUNCTIONS`, blended with linear.

    A_2 = (1 - w) u + w A_family(u), scaled to the linear valve at the median opening;
    w = 1 is the family, 0 linear. Subclasses set ``family``; see :func:`resolve_effect`
    (``valve_<family>``).
    """

    family: ClassVar[str] = "equal_percentage"
    parameters = {"weight": Prior(0.0, 0.5, -0.5, 1.5, "-", "share of the named valve family")}

    def area_factor(self, inputs: EffectInputs, p: dict[str, torch.Tensor]) -> torch.Tensor:
        def curve(u: torch.Tensor) -> torch.Tensor:
            return (1.0 - p["weight"]) * u + p["weight"] * ph.area_fraction(u, self.family)

        u = torch.clamp(inputs.u, 1e-3, 1.0)
        ref = torch.clamp(inputs.u_ref, 1e-3, 1.0)
        return curve(u) / torch.clamp(curve(ref), min=1e-9) * ref / u

    def compiled_factor(self) -> CompiledFactor | None:
        if (
            not _hooks_of(self, ValveFamily)
            or self.family not in _COMPILED_FAMILIES
            or list(self.parameters) != ["weight"]
        ):
            return None
        index = _COMPILED_FAMILIES.index(self.family)
        return CompiledFactor(CompiledFactor.FAMILY, None, (index, 0))

    def describe(self, values: Mapping[str, float]) -> str:
        w = values["weight"]
        family = self.family.replace("_", " ")
        return (
            f"The valve's area curve is {w:.2f} x the {family} curve + {1.0 - w:.2f} x linear "
            f"(1 would be the {family} family itself, 0 the linear valve)."
        )


#: the valve families the kernels compute (``_mm_numba.valve_family``, by index here),
#: with physics.AREA_FUNCTIONS' default shapes
_COMPILED_FAMILIES = ("linear", "equal_percentage", "quick_opening", "convex", "sigmoid")


def _valve_family(family: str) -> type[Effect]:
    return type(
        f"Valve_{family}",
        (ValveFamily,),
        {
            "name": f"valve_{family}",
            "family": family,
            "description": f"Valve characteristic: the {family} family of physics.AREA_FUNCTIONS.",
        },
    )


class RealGas(Effect):
    """Real gas: upstream Z = 1 + strength (Z_Papay(p_up, t_up, M_gas) - 1); strength 1 is Papay."""

    name = "real_gas"
    field_wide = True
    description = (
        "Real-gas compressibility Z(p_up, t_up) by Papay's correlation in the gas density."
    )
    parameters = {"strength": Prior(1.0, 0.5, -1.0, 3.0, "-", "share of Papay's Z - 1 (1 = full)")}

    def gas_z(self, inputs: EffectInputs, p: dict[str, torch.Tensor]) -> torch.Tensor:
        z = ph.z_factor_papay(inputs.p_up, inputs.t_up, inputs.theta["m_gas"])
        return torch.clamp(1.0 + p["strength"] * (z - 1.0), min=0.2)

    def compiled_factor(self) -> CompiledFactor | None:
        if not _hooks_of(self, RealGas) or list(self.parameters) != ["strength"]:
            return None
        return CompiledFactor(CompiledFactor.GAS)

    def describe(self, values: Mapping[str, float]) -> str:
        return f"Gas density follows {100 * values['strength']:.0f} % of Papay's real-gas Z - 1 (Z < 1 means denser gas)."


class Slip(Effect):
    """Phase slip: the mass flux times (G_Simpson / G_homogeneous)^exponent; exponent 1 is Simpson."""

    name = "slip"
    field_wide = True
    description = "Two-phase slip at the throat: a learned exponent on Simpson's slip multiplier."
    parameters = {
        "exponent": Prior(1.0, 0.5, -2.0, 4.0, "-", "exponent on Simpson's slip multiplier")
    }

    def slip(self, inputs: EffectInputs, p: dict[str, torch.Tensor]) -> torch.Tensor:
        return p["exponent"]

    def compiled_factor(self) -> CompiledFactor | None:
        if not _hooks_of(self, Slip) or list(self.parameters) != ["exponent"]:
            return None
        return CompiledFactor(CompiledFactor.SLIP)

    def describe(self, values: Mapping[str, float]) -> str:
        return f"Phase slip at {values['exponent']:.2g} x Simpson's multiplier (in the exponent; 1 = Simpson, 0 = homogeneous)."


class CriticalRatio(Effect):
    """Critical flow: p_cr moves from the constant parameter towards Sachdeva's solved ratio."""

    name = "critical_ratio"
    field_wide = True
    description = (
        "Critical (choked) flow at Sachdeva's solved critical ratio instead of a constant."
    )
    parameters = {
        "weight": Prior(1.0, 0.5, -0.5, 1.5, "-", "share of Sachdeva's solved ratio in p_cr")
    }

    def critical_ratio(self, inputs: EffectInputs, p: dict[str, torch.Tensor]) -> torch.Tensor:
        th = inputs.theta
        rho_g1 = ph.gas_density(inputs.p_up, inputs.t_up, th["m_gas"], inputs.z)
        v_liq = ph.liquid_specific_volume(
            inputs.eta_gas, inputs.eta_oil, th["rho_oil"], th["rho_wat"]
        )
        y_c = ph.sachdeva_critical_ratio(inputs.eta_gas, rho_g1, v_liq, th["kappa"], iterations=30)
        return th["p_cr"] + p["weight"] * (y_c - th["p_cr"])

    def compiled_factor(self) -> CompiledFactor | None:
        if not _hooks_of(self, CriticalRatio) or list(self.parameters) != ["weight"]:
            return None
        return CompiledFactor(CompiledFactor.CRITICAL)

    def describe(self, values: Mapping[str, float]) -> str:
        return f"p_cr is {100 * values['weight']:.0f} % Sachdeva's solved critical ratio."


class MeterBias(Effect):
    """MPFM bias against well tests: MPFM rows read factor 1 + bias + drift * years_on."""

    name = "mpfm_bias"
    description = (
        "Meter bias: the MPFM reads 1 + bias + drift * t against the well tests (MPFM rows only)."
    )
    parameters = {
        "bias": Prior(0.0, 0.05, -0.5, 1.0, "-", "relative MPFM bias at the well's start", 0.5),
        "drift": Prior(0.0, 0.02, -0.2, 0.2, "1/yr", "relative MPFM drift per year"),
    }
    extra_columns = ("years_on",)
    uses_source = True

    def output_factor(self, inputs: EffectInputs, p: dict[str, torch.Tensor]) -> torch.Tensor:
        factor = 1.0 + p["bias"] + p["drift"] * inputs.feature("years_on")
        return torch.where(inputs.well_test, torch.ones_like(factor), factor)

    def compiled_factor(self) -> CompiledFactor | None:
        if not _hooks_of(self, MeterBias) or list(self.parameters) != ["bias", "drift"]:
            return None
        return CompiledFactor(CompiledFactor.BIAS, "years_on")

    def describe(self, values: Mapping[str, float]) -> str:
        bias, drift = values["bias"], values["drift"]
        word = "high" if bias >= 0 else "low"
        return (
            f"The MPFM reads {100 * abs(bias):.1f} % {word} against well tests at the well's start, "
            f"drifting {100 * drift:+.1f} %/year."
        )


#: The library by name. Valve families are also available as ``valve_<family>``.
_LIBRARY: tuple[type[Effect], ...] = (
    Erosion,
    ErosionTime,
    Valve,
    RealGas,
    Slip,
    CriticalRatio,
    MeterBias,
    *(_valve_family(f) for f in ph.AREA_FUNCTIONS if f != "linear"),
)
EFFECTS: dict[str, type[Effect]] = {cls.name: cls for cls in _LIBRARY}
#: What ``vfm diagnose`` tries by default (one per physical effect).
DEFAULT_CANDIDATES: tuple[str, ...] = (
    "erosion",
    "valve",
    "real_gas",
    "slip",
    "critical_ratio",
    "mpfm_bias",
)


#: name or module:Class, then optional :key=value settings (values may hold ':', e.g. times)
_SPEC = re.compile(r"([A-Za-z_][\w.]*(?::[A-Za-z_]\w*(?=:|$))?)((?::[A-Za-z_]\w*=.*)?)")


def resolve_effect(name_or_path: str | type[Effect]) -> type[Effect]:
    """An effect class from a registry name or ``module:Class`` (importable from PYTHONPATH),
    optionally followed by settings ``:key=value`` (e.g. ``erosion:step_at=2019-06-01``)."""
    values: dict[str, str] = {}
    if isinstance(name_or_path, type):
        cls = name_or_path
    else:
        raw = str(name_or_path).strip()
        m = _SPEC.fullmatch(raw)
        if m is None:
            raise ConfigError(
                f"Cannot read the effect '{name_or_path}'; write name, name:key=value or "
                "module:Class (settings as :key=value after either)."
            )
        text = m.group(1)
        for item in re.split(r":(?=[A-Za-z_]\w*=)", m.group(2))[1:]:
            key, _, value = item.partition("=")
            values[key.strip()] = value.strip()
        if ":" in text:
            module_name, _, attr = text.partition(":")
            try:
                module = importlib.import_module(module_name)
            except ImportError as exc:
                raise ConfigError(
                    f"Cannot import the module '{module_name}' of effect '{text}' ({exc}); "
                    "put it on PYTHONPATH or install it."
                ) from None
            found = getattr(module, attr, None)
            if found is None:
                raise ConfigError(
                    f"The module '{module_name}' has no class '{attr}' (effect '{text}')."
                )
            cls = found
        else:
            try:
                cls = EFFECTS[text]
            except KeyError:
                raise ConfigError(
                    f"Unknown effect '{text}'; choose one of {', '.join(EFFECTS)} "
                    "or give your own class as module:Class."
                ) from None
    if not (isinstance(cls, type) and issubclass(cls, Effect)):
        raise ConfigError(
            f"'{name_or_path}' is not an Effect subclass; derive it from vfm_core.effects.Effect."
        )
    if not cls.name or not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", cls.name):
        raise ConfigError(
            f"Effect class {cls.__name__} needs a name made of letters, digits and '_'."
        )
    if values:
        cls = cls.configure(**values)
    for key, prior in cls.parameters.items():
        if not (prior.std > 0 and prior.low <= prior.mean <= prior.high):
            raise ConfigError(
                f"Effect '{cls.name}': parameter '{key}' needs std > 0 and low <= mean <= high."
            )
    return cls


def effect_spec(cls: type[Effect]) -> str:
    """The text that rebuilds ``cls`` through :func:`resolve_effect`."""
    if cls.spec and cls.spec != cls.name:
        return cls.spec
    if EFFECTS.get(cls.name) is cls:
        return cls.name
    return f"{cls.__module__}:{cls.__qualname__}"


def resolve_effects(effects: Sequence[str | type[Effect]] | str) -> list[type[Effect]]:
    """Resolve a list (or comma-separated text) of effects; duplicates are an error."""
    if isinstance(effects, str):
        effects = [e for e in effects.split(",") if e.strip()]
    classes = [resolve_effect(e) for e in effects]
    names = [c.name for c in classes]
    if len(set(names)) != len(names):
        raise ConfigError(f"Effects {names} name one effect twice; give each once.")
    return classes


# --- a generic correction: what `vfm diagnose` suggests for an effect outside the library ---
@dataclass(frozen=True)
class SuggestDriver:
    """A variable a :class:`Suggest` correction may depend on: its unit, the step its
    coefficient is given per (``scale``, in ``unit``), that step in words, and its default
    reference value (where the correction is 1)."""

    unit: str
    scale: float
    step: str
    x0: float


#: The drivers a suggested correction can use: the six inputs, p_down/p_up, the water cut,
#: the standard features (``years_on``, ``throughput_years``) and the time of year; every one
#: of them the streaming service can compute sample by sample.
SUGGEST_DRIVERS: dict[str, SuggestDriver] = {
    "choke": SuggestDriver("fraction", 0.1, "0.1", 0.5),
    "p_up": SuggestDriver("bar", 10.0, "10 bar", 100.0),
    "p_down": SuggestDriver("bar", 10.0, "10 bar", 30.0),
    "p_ratio": SuggestDriver("p_down/p_up", 0.1, "0.1", 0.5),
    "t_up": SuggestDriver("degC", 10.0, "10 K", 60.0),
    "eta_gas": SuggestDriver("-", 0.1, "0.1", 0.1),
    "eta_oil": SuggestDriver("-", 0.1, "0.1", 0.5),
    "water_cut": SuggestDriver("-", 0.1, "0.1", 0.3),
    "years_on": SuggestDriver("yr", 1.0, "year", 0.0),
    "throughput_years": SuggestDriver("yr-eq", 1.0, "year-equivalent", 0.0),
    "day_of_year": SuggestDriver("day", 365.25, "year", 0.0),
}
_SUGGEST_FORMS = ("linear", "log", "season")
_NS_PER_DAY = 86_400e9


def _suggest_driver_and_form(values: Mapping[str, str], default: str) -> tuple[str, str]:
    """The driver and form of a ``suggest`` setting (``values``, text), checked: a known
    driver, and the season form exactly for ``day_of_year``."""
    driver = values.get("driver", default)
    if driver not in SUGGEST_DRIVERS:
        raise ConfigError(
            f"Effect 'suggest': driver='{driver}' is not one of {', '.join(SUGGEST_DRIVERS)}; "
            "write e.g. suggest:driver=t_up."
        )
    form = values.get("form", "season" if driver == "day_of_year" else "linear")
    if form not in _SUGGEST_FORMS or (form == "season") != (driver == "day_of_year"):
        raise ConfigError(
            f"Effect 'suggest': form='{form}' does not suit driver '{driver}'; use "
            + ("form=season." if driver == "day_of_year" else "form=linear or form=log.")
        )
    return driver, form


def _suggest_number(values: Mapping[str, str], key: str, default: float) -> float:
    """The finite number of setting ``key`` (text in ``values``), ``default`` without it."""
    text = values.get(key)
    if text is None:
        return default
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not math.isfinite(value):
        raise ConfigError(f"Effect 'suggest': {key}='{text}' is not a number.")
    return value


def _suggest_fixed(values: Mapping[str, str], form: str) -> dict[str, float]:
    """The fixed shared coefficients a ``suggest`` setting gives (k, or k_sin and k_cos for
    the season: all of them or none), empty when they are learned."""
    keys = ("k_sin", "k_cos") if form == "season" else ("k",)
    given = [k for k in ("k", "k_sin", "k_cos") if k in values]
    if given and sorted(given) != sorted(keys):
        raise ConfigError(
            f"Effect 'suggest' with form={form} fixes its coefficients with "
            f"{' and '.join(keys)} (all of them), not {', '.join(given)}."
        )
    return {k: _suggest_number(values, k, 0.0) for k in keys} if given else {}


def _suggest_priors(driver: str, form: str, step: str) -> dict[str, Prior]:
    """The learned coefficients of a ``suggest`` correction and their priors: k per
    ``step`` of the driver (linear, log), or the season's two amplitudes."""
    if form == "season":
        return {
            "k_sin": Prior(
                0.0, 0.05, -0.5, 0.5, "-", "amplitude of sin(2 pi d), d = year fraction"
            ),
            "k_cos": Prior(
                0.0, 0.05, -0.5, 0.5, "-", "amplitude of cos(2 pi d), d = year fraction"
            ),
        }
    word = "relative rate change" if form == "linear" else "log rate change"
    return {"k": Prior(0.0, 0.1, -1.0, 1.0, f"1/({step})", f"{word} per {step} of {driver}")}


class Suggest(Effect):
    """A generic multiplicative correction of the rate in one driver x (what ``vfm diagnose``
    suggests when no library effect explains the residual):

    * ``form=linear`` (default): q times 1 + k (x - x0)/scale;
    * ``form=log``: q times exp(k (x - x0)/scale);
    * ``form=season`` (``driver=day_of_year``): q times 1 + k_sin sin(2 pi d) + k_cos cos(2 pi d),
      d the fraction of the year since 1 January.

    Settings: ``driver`` (one of :data:`SUGGEST_DRIVERS`, required), ``form``, ``x0`` (the
    reference value in the driver's unit, where the factor is 1; per-well levels stay with
    C_D), ``scale`` (the step k is given per, in the driver's unit). Without ``k`` the
    coefficients are learned per well (prior N(0, 0.1^2) per step, bounds +-1); with ``k``
    (``k_sin``, ``k_cos`` for the season) they are fixed and shared by every well, nothing
    is learned. Example: ``suggest:driver=t_up:x0=60:scale=10`` learns per well the relative
    rate change per 10 K above 60 degC; ``...:k=0.068`` applies 6.8 % per 10 K to every well.
    """

    name = "suggest"
    description = "A generic multiplicative rate correction, linear or log-linear in one driver."
    settings = {
        "driver": "the variable: " + ", ".join(SUGGEST_DRIVERS),
        "form": "linear (default), log, or season (for day_of_year)",
        "x0": "reference value of the driver, in its unit (the factor is 1 there)",
        "scale": "the step the coefficient is given per, in the driver's unit",
        "k": "a fixed coefficient shared by all wells (linear, log); nothing is learned",
        "k_sin": "a fixed shared coefficient of sin(2 pi d) (season)",
        "k_cos": "a fixed shared coefficient of cos(2 pi d) (season)",
    }
    driver: ClassVar[str] = ""
    form: ClassVar[str] = "linear"
    x0: ClassVar[float] = 0.0
    scale: ClassVar[float] = 1.0
    step: ClassVar[str] = ""
    fixed: ClassVar[Mapping[str, float]] = {}
    parameters = {"k": Prior(0.0, 0.1, -1.0, 1.0, "-", "relative rate change per step")}

    @classmethod
    def configure(cls, **values: str) -> type[Effect]:
        unknown = sorted(set(values) - set(cls.settings))
        if unknown:
            return super().configure(**values)  # says which settings exist
        driver, form = _suggest_driver_and_form(values, cls.driver)
        spec = SUGGEST_DRIVERS[driver]
        x0 = _suggest_number(values, "x0", spec.x0)
        scale = _suggest_number(values, "scale", spec.scale)
        if scale <= 0:
            raise ConfigError(f"Effect 'suggest': scale must be positive, not {scale:g}.")
        fixed = _suggest_fixed(values, form)
        step = spec.step if scale == spec.scale else f"{scale:g} {spec.unit}"
        text = f"suggest:driver={driver}:form={form}"
        if form != "season":
            text += f":x0={x0:g}:scale={scale:g}"
        text += "".join(f":{k}={v:.6g}" for k, v in fixed.items())
        extra = (driver,) if driver in ("years_on", "throughput_years") else ()
        return type(
            "SuggestConfigured",
            (cls,),
            {
                "driver": driver,
                "form": form,
                "x0": x0,
                "scale": scale,
                "step": step,
                "fixed": fixed,
                "parameters": {} if fixed else _suggest_priors(driver, form, step),
                "extra_columns": extra,
                "spec": text,
                "__module__": cls.__module__,
            },
        )

    def __init__(self) -> None:
        if not self.driver:
            raise ConfigError(
                "The effect 'suggest' needs a driver: write e.g. suggest:driver=t_up "
                f"(drivers: {', '.join(SUGGEST_DRIVERS)})."
            )

    def driver_value(self, inputs: EffectInputs) -> torch.Tensor:
        """The driver in its own unit (degC, bar, fraction, years, ...), [W, N]."""
        name = self.driver
        if name == "choke":
            return inputs.u
        if name in ("p_up", "p_down"):
            return getattr(inputs, name) / 1e5
        if name == "p_ratio":
            return inputs.p_down / inputs.p_up
        if name == "t_up":
            return inputs.t_up - 273.15
        if name in ("eta_gas", "eta_oil"):
            return getattr(inputs, name)
        if name == "water_cut":
            return inputs.water_cut
        if name == "day_of_year":
            if inputs.time_ns is None:
                raise ConfigError(
                    "Effect 'suggest' with driver=day_of_year needs each sample's time."
                )
            days = inputs.time_ns.to(DTYPE) / _NS_PER_DAY
            return torch.remainder(days, 365.2425)  # 0 on 1 January (within a day)
        return inputs.feature(name)

    #: the form's code in the compiled factor (:attr:`CompiledFactor.SUGGEST`)
    _FORM_CODES: ClassVar[Mapping[str, int]] = {"linear": 0, "log": 1, "season": 2}

    def compiled_factor(self) -> CompiledFactor | None:
        if not _hooks_of(self, Suggest) or type(self).driver_value is not Suggest.driver_value:
            return None
        expected = [] if self.fixed else (["k_sin", "k_cos"] if self.form == "season" else ["k"])
        if list(self.parameters) != expected:
            return None
        form = 3 if self.fixed else self._FORM_CODES[self.form]
        return CompiledFactor(CompiledFactor.SUGGEST, None, (form, 0))

    def compiled_columns(
        self, x: np.ndarray, extra: Mapping[str, np.ndarray], time_ns: np.ndarray
    ) -> np.ndarray:
        """The two per-sample columns [W, N, 2] the compiled factor reads (see
        :attr:`CompiledFactor.SUGGEST`): the step (x - x0) / scale (linear, log), sin and cos
        of the phase (season), or the whole factor with fixed coefficients (the second
        column 0); from the six inputs ``x`` [W, N, 6] in file units (fraction, bar, bar,
        degC, -, -), the feature columns ``extra`` by name and the times ``time_ns`` [W, N].
        numpy with the arithmetic of :meth:`driver_value` and :meth:`output_factor` (a
        model computes them at every call; torch's dispatch would cost more than the
        kernel), compared with them in ``tests/test_effect_kernels.py``."""
        d = self._driver_array(x, extra, time_ns)
        out = np.zeros((*d.shape, 2))
        k = self.fixed
        if self.form == "season":
            phase = 2.0 * math.pi * d / 365.2425
            out[..., 0], out[..., 1] = np.sin(phase), np.cos(phase)
            if k:
                out[..., 0] = 1.0 + k["k_sin"] * out[..., 0] + k["k_cos"] * out[..., 1]
                out[..., 1] = 0.0
            return out
        out[..., 0] = (d - self.x0) / self.scale
        if k and self.form == "log":
            out[..., 0] = np.exp(np.clip(k["k"] * out[..., 0], -5.0, 5.0))
        elif k:
            out[..., 0] = np.maximum(1.0 + k["k"] * out[..., 0], 0.05)
        return out

    def _driver_array(
        self, x: np.ndarray, extra: Mapping[str, np.ndarray], time_ns: np.ndarray
    ) -> np.ndarray:
        """:meth:`driver_value` in numpy, from the inputs in file units (see
        :meth:`compiled_columns`)."""
        name = self.driver
        column = {"choke": 0, "eta_gas": 4, "eta_oil": 5}
        if name in column:
            return x[..., column[name]]
        if name in ("p_up", "p_down"):
            return bar_to_pa(x[..., 1 if name == "p_up" else 2]) / 1e5
        if name == "t_up":
            return degc_to_k(x[..., 3]) - 273.15
        with np.errstate(all="ignore"):  # padded samples give NaN, as in torch
            if name == "p_ratio":
                return bar_to_pa(x[..., 2]) / bar_to_pa(x[..., 1])
            if name == "water_cut":
                wat = 1.0 - x[..., 4] - x[..., 5]
                return np.clip(wat / np.maximum(x[..., 5] + wat, 1e-9), 0.0, 1.0)
        if name == "day_of_year":
            return np.remainder(time_ns.astype(np.float64) / _NS_PER_DAY, 365.2425)
        return extra[name]

    def output_factor(self, inputs: EffectInputs, p: dict[str, torch.Tensor]) -> torch.Tensor:
        values = {**{k: torch.tensor(v, dtype=DTYPE) for k, v in self.fixed.items()}, **p}
        x = self.driver_value(inputs)
        if self.form == "season":
            phase = 2.0 * math.pi * x / 365.2425
            return 1.0 + values["k_sin"] * torch.sin(phase) + values["k_cos"] * torch.cos(phase)
        step = (x - self.x0) / self.scale
        if self.form == "log":
            return torch.exp(torch.clamp(values["k"] * step, -5.0, 5.0))
        return torch.clamp(1.0 + values["k"] * step, min=0.05)

    def describe(self, values: Mapping[str, float]) -> str:
        v = {**self.fixed, **values}
        spec, step = SUGGEST_DRIVERS[self.driver], self.step
        if self.form == "season":
            amp = math.hypot(v.get("k_sin", 0.0), v.get("k_cos", 0.0))
            peak = math.atan2(v.get("k_sin", 0.0), v.get("k_cos", 0.0)) % (2 * math.pi)
            day = peak / (2 * math.pi) * 365.2425
            return (
                f"The rate swings +-{100 * amp:.2g} % over the year, highest about day {day:.0f}."
            )
        k = v.get("k", 0.0)
        where = f"{self.x0:g} {spec.unit}".rstrip()
        if self.form == "log":
            return (
                f"The rate times exp({k:+.3g} per {step} of {self.driver} from {where}) "
                f"({100 * math.expm1(k):+.2g} % per {step})."
            )
        return f"The rate times (1 {'+' if k >= 0 else '-'} {abs(k):.3g} per {step} of {self.driver} from {where})."


EFFECTS[Suggest.name] = Suggest
__all__ += ["Suggest", "SuggestDriver", "SUGGEST_DRIVERS"]
