"""Candidate physical effects that extend the mechanistic choke models, and the models they make.

An *effect* is a small documented physical term with named parameters (SI units, Gaussian
priors, hard bounds) that modifies the Sachdeva forward computation through one or more
hooks. :class:`EffectModel` composes a list of effects into ``mm``, ``hem`` or ``ham``
with autograd, keeping one set of effect parameters per well, standardised like
:class:`vfm_core.models.PhysicalParameters` (theta = mu + sigma z; the prior penalty is
sum z^2; bounds clamp z). A prior mean is the documented physics where the literature
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
:class:`EffectInputs`, :func:`resolve_effect`, :func:`effect_model_factory`,
:func:`add_features`, :func:`standard_features`, :func:`make_effect_model`.
"""

from __future__ import annotations

import importlib
import math
import re
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np
import pandas as pd
import torch
from torch import nn

from vfm_core import physics as ph
from vfm_core.data import DTYPE, Batch
from vfm_core.errors import ConfigError
from vfm_core.models import ChokeModel, HybridArea, HybridError, Mechanistic, PhysicalParameters
from vfm_core.physics import Prior
from vfm_core.schema import TARGET, TIME, WELL
from vfm_core.units import bar_to_pa, degc_to_k

__all__ = [
    "Prior",
    "Effect",
    "EffectInputs",
    "EffectParameters",
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
    "STANDARD_FEATURES",
    "standard_features",
    "add_features",
    "resolve_effect",
    "resolve_effects",
    "effect_spec",
    "FeatureTracker",
    "make_effect_model",
    "effect_model_factory",
]

HOURS_PER_YEAR = 365.25 * 24.0
#: Longest time step (hours) integrated into the cumulative throughput: longer gaps
#: between rows are shut-ins or historian gaps, not production.
_MAX_STEP_HOURS = 48.0


# --- features ---------------------------------------------------------------------------
#: Names of the features :func:`standard_features` computes, with their units.
STANDARD_FEATURES: dict[str, str] = {
    "years_on": "years since the well's first row (yr)",
    "throughput_years": "cumulative produced standard volume over one year of the well's "
    "early median rate (year-equivalents, -)",
    "water_cut": "water share of the liquid mass, eta_wat / (eta_oil + eta_wat) (-)",
}


def standard_features(frame: pd.DataFrame) -> pd.DataFrame:
    """Per-row features effects and diagnosis use, indexed like ``frame``.

    ``throughput_years`` integrates the last measured rate (forward-filled, so a row never
    sees its own measurement) over time per well, gaps longer than 48 h counted as 48 h,
    divided by the well's median measured rate in its first 90 days times one year.
    """
    out = pd.DataFrame(index=frame.index)
    t = pd.to_datetime(frame[TIME], utc=True)
    hours = (t - t.min()).dt.total_seconds().to_numpy() / 3600.0
    wells = frame[WELL].astype(str).to_numpy()
    q = pd.to_numeric(frame[TARGET], errors="coerce").to_numpy(dtype=float)
    years_on = np.zeros(len(frame))
    throughput = np.zeros(len(frame))
    for well in pd.unique(wells):
        idx = np.flatnonzero(wells == well)
        idx = idx[np.argsort(hours[idx], kind="stable")]
        h = hours[idx]
        years_on[idx] = (h - h[0]) / HOURS_PER_YEAR
        rate = pd.Series(q[idx]).ffill().fillna(0.0).to_numpy()
        dt = np.clip(np.diff(h, prepend=h[0]), 0.0, _MAX_STEP_HOURS)
        prev_rate = np.concatenate([[0.0], rate[:-1]])
        cumulative = np.cumsum(prev_rate * dt)
        early = q[idx][(h - h[0]) <= 90 * 24.0]
        early = early[np.isfinite(early) & (early > 0)]
        finite = q[idx][np.isfinite(q[idx]) & (q[idx] > 0)]
        scale = np.median(early) if len(early) else (np.median(finite) if len(finite) else 1.0)
        throughput[idx] = cumulative / (scale * HOURS_PER_YEAR)
    out["years_on"] = years_on
    out["throughput_years"] = throughput
    oil = frame["eta_oil"].to_numpy(dtype=float)
    wat = 1.0 - frame["eta_gas"].to_numpy(dtype=float) - oil
    out["water_cut"] = np.clip(wat / np.clip(oil + wat, 1e-9, None), 0.0, 1.0)
    return out


def standard_scale(q: np.ndarray, time_ns: np.ndarray, first_ns: int) -> float:
    """The throughput scale of :func:`standard_features`: the median measured rate (Sm3/h)
    of the well's first 90 days (else of all its rows; 1 without any)."""
    ok = np.isfinite(q) & (q > 0)
    early = ok & (time_ns - first_ns <= int(90 * 24 * 3600 * 1e9))
    if early.any():
        return float(np.median(q[early]))
    return float(np.median(q[ok])) if ok.any() else 1.0


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


class FeatureTracker:
    """The standard features of one well, kept up to date one row at a time (the service).

    Follows :func:`standard_features` row by row: ``advance(t)`` integrates the last measured
    rate up to ``t`` (steps capped at 48 h, never backwards) and returns the features at
    ``t``; ``measured(t, q)`` then records the row's own rate, which only later rows see.
    The throughput scale is the median measured rate of the well's first 90 days; until 90
    days have passed it is the median so far (offline, the whole 90 days are known at once).
    State is plain numbers (:meth:`state` / :meth:`from_state`), for checkpoints.
    """

    names: ClassVar[tuple[str, ...]] = tuple(STANDARD_FEATURES)
    _EARLY_NS: ClassVar[int] = int(90 * 24 * 3600 * 1e9)

    def __init__(self) -> None:
        self.first_ns: int | None = None
        self.last_ns: int | None = None
        self.last_rate = 0.0
        self.cumulative = 0.0  # Sm3 (rate x hours)
        self.early: list[float] = []
        self.scale: float | None = None  # fixed once the first 90 days are over
        self._median: float | None = None  # median of ``early``, cached until it changes

    def _scale(self) -> float:
        if self.scale is not None:
            return self.scale
        if self._median is None:
            self._median = float(np.median(self.early)) if self.early else 1.0
        return self._median

    def advance(self, time_ns: int, eta_gas: float, eta_oil: float) -> list[float]:
        """Features at ``time_ns`` for a row with these mass fractions, in :attr:`names` order."""
        if self.first_ns is None:
            self.first_ns = self.last_ns = time_ns
        assert self.last_ns is not None
        if time_ns > self.last_ns:
            hours = min((time_ns - self.last_ns) / 3.6e12, _MAX_STEP_HOURS)
            self.cumulative += self.last_rate * hours
            self.last_ns = time_ns
        if self.scale is None and time_ns - self.first_ns > self._EARLY_NS and self.early:
            self.scale = float(np.median(self.early))
        wat = 1.0 - eta_gas - eta_oil
        values = {
            "years_on": max(time_ns - self.first_ns, 0) / 3.6e12 / HOURS_PER_YEAR,
            "throughput_years": self.cumulative / (self._scale() * HOURS_PER_YEAR),
            "water_cut": min(max(wat / max(eta_oil + wat, 1e-9), 0.0), 1.0),
        }
        return [values[n] for n in self.names]

    def measured(self, time_ns: int, q_total: float) -> None:
        """Record a measured rate (Sm3/h) at ``time_ns`` (after :meth:`advance` for that row)."""
        if not (math.isfinite(q_total) and q_total > 0):
            return
        if self.first_ns is None:
            self.first_ns = self.last_ns = time_ns
        if self.scale is None and time_ns - self.first_ns <= self._EARLY_NS:
            self.early.append(float(q_total))
            self._median = None
        self.last_rate = float(q_total)

    @classmethod
    def from_frame(cls, frame: pd.DataFrame) -> tuple[FeatureTracker, np.ndarray]:
        """A tracker that has seen one well's rows (time order) and those rows' features [N, k]."""
        feats = standard_features(frame)
        tr = cls()
        if frame.empty:
            return tr, np.zeros((0, len(cls.names)))
        ns = pd.DatetimeIndex(pd.to_datetime(frame[TIME], utc=True)).as_unit("ns").asi8
        q = pd.to_numeric(frame[TARGET], errors="coerce").to_numpy(dtype=float)
        order = np.argsort(ns, kind="stable")
        tr.first_ns, tr.last_ns = int(ns[order[0]]), int(ns[order[-1]])
        ok = np.isfinite(q) & (q > 0)
        early = ok & (ns - tr.first_ns <= cls._EARLY_NS)
        if tr.last_ns - tr.first_ns <= cls._EARLY_NS:  # the first 90 days are not over yet
            tr.scale = None
            tr.early = [float(v) for v in q[order][early[order]]]
        else:
            tr.scale = standard_scale(q, ns, tr.first_ns)
        if ok.any():
            tr.last_rate = float(q[order][ok[order]][-1])
        last = order[-1]
        tr.cumulative = (
            float(feats["throughput_years"].to_numpy()[last])
            * standard_scale(q, ns, tr.first_ns)
            * HOURS_PER_YEAR
        )
        return tr, feats[list(cls.names)].to_numpy(dtype=float)

    def state(self) -> dict[str, Any]:
        return {
            "first_ns": self.first_ns,
            "last_ns": self.last_ns,
            "last_rate": self.last_rate,
            "cumulative": self.cumulative,
            "early": list(self.early),
            "scale": self.scale,
        }

    @classmethod
    def from_state(cls, state: Mapping[str, Any]) -> FeatureTracker:
        tr = cls()
        tr.first_ns = state.get("first_ns")
        tr.last_ns = state.get("last_ns")
        tr.last_rate = float(state.get("last_rate", 0.0))
        tr.cumulative = float(state.get("cumulative", 0.0))
        tr.early = [float(v) for v in state.get("early", [])]
        scale = state.get("scale")
        tr.scale = None if scale is None else float(scale)
        return tr


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

    @classmethod
    def configure(cls, **values: str) -> type[Effect]:
        """A subclass with the given settings (text values from ``name:key=value``).

        By default each setting becomes a class attribute of that name holding the text;
        override to parse values (see :class:`Erosion`).
        """
        unknown = sorted(set(values) - set(cls.settings))
        if unknown:
            known = ", ".join(f"{k} ({v})" for k, v in cls.settings.items()) or "none"
            raise ConfigError(
                f"Effect '{cls.name}' has no setting {', '.join(unknown)}; its settings: {known}."
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

    def describe(self, values: Mapping[str, float]) -> str:
        """One sentence on the fitted values (field medians, SI units)."""
        parts = [
            f"{k} = {v:.4g} {self.parameters[k].unit}".rstrip() + f" ({self.parameters[k].meaning})"
            for k, v in values.items()
            if k in self.parameters
        ]
        return f"{self.name}: " + "; ".join(parts) + "."


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
        when = when.tz_localize("UTC") if when.tzinfo is None else when.tz_convert("UTC")
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
    description = (
        "Real-gas compressibility Z(p_up, t_up) by Papay's correlation in the gas density."
    )
    parameters = {"strength": Prior(1.0, 0.5, -1.0, 3.0, "-", "share of Papay's Z - 1 (1 = full)")}

    def gas_z(self, inputs: EffectInputs, p: dict[str, torch.Tensor]) -> torch.Tensor:
        z = ph.z_factor_papay(inputs.p_up, inputs.t_up, inputs.theta["m_gas"])
        return torch.clamp(1.0 + p["strength"] * (z - 1.0), min=0.2)

    def describe(self, values: Mapping[str, float]) -> str:
        return f"Gas density follows {100 * values['strength']:.0f} % of Papay's real-gas Z - 1 (Z < 1 means denser gas)."


class Slip(Effect):
    """Phase slip: the mass flux times (G_Simpson / G_homogeneous)^exponent; exponent 1 is Simpson."""

    name = "slip"
    description = "Two-phase slip at the throat: a learned exponent on Simpson's slip multiplier."
    parameters = {
        "exponent": Prior(1.0, 0.5, -2.0, 4.0, "-", "exponent on Simpson's slip multiplier")
    }

    def slip(self, inputs: EffectInputs, p: dict[str, torch.Tensor]) -> torch.Tensor:
        return p["exponent"]

    def describe(self, values: Mapping[str, float]) -> str:
        return f"Phase slip at {values['exponent']:.2g} x Simpson's multiplier (in the exponent; 1 = Simpson, 0 = homogeneous)."


class CriticalRatio(Effect):
    """Critical flow: p_cr moves from the constant parameter towards Sachdeva's solved ratio."""

    name = "critical_ratio"
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

    def describe(self, values: Mapping[str, float]) -> str:
        return f"p_cr is {100 * values['weight']:.0f} % Sachdeva's solved critical ratio."


class MeterBias(Effect):
    """MPFM bias against well tests: MPFM rows read factor 1 + bias + drift * years_on."""

    name = "mpfm_bias"
    description = (
        "Meter bias: the MPFM reads 1 + bias + drift * t against the well tests (MPFM rows only)."
    )
    parameters = {
        "bias": Prior(0.0, 0.05, -0.5, 1.0, "-", "relative MPFM bias at the well's start"),
        "drift": Prior(0.0, 0.02, -0.2, 0.2, "1/yr", "relative MPFM drift per year"),
    }
    extra_columns = ("years_on",)

    def output_factor(self, inputs: EffectInputs, p: dict[str, torch.Tensor]) -> torch.Tensor:
        factor = 1.0 + p["bias"] + p["drift"] * inputs.feature("years_on")
        return torch.where(inputs.well_test, torch.ones_like(factor), factor)

    def describe(self, values: Mapping[str, float]) -> str:
        bias, drift = values["bias"], values["drift"]
        word = "high" if bias >= 0 else "low"
        return (
            f"The MPFM reads {100 * abs(bias):.1f} % {word} against well tests at the well's start, "
            f"drifting {100 * drift:+.1f} %/year."
        )


#: The library by name. Valve families are also available as ``valve_<family>``.
EFFECTS: dict[str, type[Effect]] = {
    cls.name: cls
    for cls in (
        Erosion,
        ErosionTime,
        Valve,
        RealGas,
        Slip,
        CriticalRatio,
        MeterBias,
        *(_valve_family(f) for f in ph.AREA_FUNCTIONS if f != "linear"),
    )
}
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
            cls = getattr(module, attr, None)
            if cls is None:
                raise ConfigError(
                    f"The module '{module_name}' has no class '{attr}' (effect '{text}')."
                )
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


# --- parameters and the model -----------------------------------------------------------------
def EffectParameters(n_wells: int, priors: Mapping[str, Prior]) -> PhysicalParameters:  # noqa: N802
    """One effect's parameters per well, standardised like the mechanistic ones (theta = mu + sigma z)."""
    return PhysicalParameters(n_wells, priors)


class _EffectMixin:
    """Composes effects into a Mechanistic-family model; see :func:`make_effect_model`."""

    effects: list[Effect]
    effect_params: nn.ModuleDict

    def _init_effects(self, effects: Sequence[type[Effect]]) -> None:
        model: Any = self
        n = len(model.wells)
        self.effects = [cls() for cls in effects]
        self.effect_params = nn.ModuleDict(
            {e.name: EffectParameters(n, e.parameters) for e in self.effects}
        )
        model.register_buffer("u_ref", torch.full((n,), 0.5, dtype=DTYPE))
        columns: list[str] = []
        for e in self.effects:
            columns += [c for c in e.extra_columns if c not in columns]
        model.extra_columns = tuple(columns)
        # how to rebuild the model (JSON): registry names, or module:Class for a user's own
        model.hyper["effects"] = [effect_spec(type(e)) for e in self.effects]
        model.name = "+".join([model.base_name, *(e.name for e in self.effects)])

    def effect_values(self) -> dict[str, dict[str, torch.Tensor]]:
        return {e.name: self.effect_params[e.name].values() for e in self.effects}

    def _inputs(self, batch: Batch, theta: dict[str, torch.Tensor]) -> EffectInputs:
        model: Any = self
        u, p_up, p_down, t_up, eta_gas, eta_oil = batch.x.unbind(-1)
        assert batch.extra is not None and batch.well_test is not None
        extra = {n: batch.extra[..., i] for i, n in enumerate(batch.extra_names)}
        return EffectInputs(
            u=u,
            p_up=bar_to_pa(p_up),
            p_down=bar_to_pa(p_down),
            t_up=degc_to_k(t_up),
            eta_gas=eta_gas,
            eta_oil=eta_oil,
            theta={k: v.unsqueeze(1) for k, v in theta.items()},
            well_test=batch.well_test,
            u_ref=model.u_ref.unsqueeze(1),
            extra=extra,
            time_ns=batch.time_ns,
        )

    def _effect_rate(self, batch: Batch) -> torch.Tensor:
        """The mechanistic rate with every effect applied, Sm3/h [W, N]."""
        model: Any = self
        theta = model.theta()
        inputs = self._inputs(batch, theta)
        values = {
            k: {n: v.unsqueeze(1) for n, v in d.items()} for k, d in self.effect_values().items()
        }
        area = model.area(batch.x, theta)
        z: torch.Tensor | float = 1.0
        for e in self.effects:
            f = e.area_factor(inputs, values[e.name])
            area = area if f is None else area * f
            gz = e.gas_z(inputs, values[e.name])
            z = z if gz is None else z * gz
        inputs.z = z
        th = inputs.theta
        p_cr: torch.Tensor = th["p_cr"]
        slip_w: torch.Tensor | None = None
        for e in self.effects:
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
        q = area * flux * per_kg * 3600.0
        for e in self.effects:
            f = e.output_factor(inputs, values[e.name])
            q = q if f is None else q * f
        return q

    def _setup_new(self, batch: Batch, new: torch.Tensor) -> None:
        model: Any = self
        with torch.no_grad():
            u = torch.where(batch.mask, batch.x[..., 0], torch.full_like(batch.y, float("nan")))
            u_med = torch.nanmedian(u, dim=1).values
            model.u_ref[new] = torch.where(
                torch.isfinite(u_med[new]), u_med[new], torch.full_like(u_med[new], 0.5)
            )
            # A_max: the model at prior means (effects off) matches the median measured rate
            saved_a, saved_z = (
                model.a_max.clone(),
                [p.z.detach().clone() for p in self.effect_params.values()],
            )
            saved_phys = model.phys.z.detach().clone()
            model.a_max[new] = 1.0
            model.phys.z[new] = 0.0
            for p in self.effect_params.values():
                p.z[new] = 0.0
            unit = self._effect_rate(batch)
            ratio = torch.where(
                batch.mask & (unit > 0), batch.y / unit, torch.full_like(unit, float("nan"))
            )
            a_max = torch.nanmedian(ratio, dim=1).values
            model.a_max.copy_(saved_a)
            model.phys.z.copy_(saved_phys)
            for p, s in zip(self.effect_params.values(), saved_z, strict=True):
                p.z.copy_(s)
            model.a_max[new] = torch.where(
                torch.isfinite(a_max[new]), a_max[new], torch.ones_like(a_max[new])
            )

    def _effect_penalty(self) -> torch.Tensor:
        model: Any = self
        total = torch.zeros(len(model.wells), dtype=DTYPE)
        for p in self.effect_params.values():
            total = total + p.penalty()
        return total

    def _project_effects(self) -> None:
        for p in self.effect_params.values():
            p.project_()

    def prior_penalty(self, physical_only: bool = False) -> torch.Tensor:
        """The base model's prior penalty plus the effects' (sum of z^2), per well."""
        return super().prior_penalty(physical_only) + self._effect_penalty()  # type: ignore[misc]

    def project_(self) -> None:
        model: Any = self
        model.phys.project_()
        self._project_effects()

    def physical_parameters(self) -> dict[str, torch.Tensor]:
        return {**Mechanistic.physical_parameters(self), **self._effect_physical()}  # type: ignore[arg-type]

    def _effect_physical(self) -> dict[str, torch.Tensor]:
        out: dict[str, torch.Tensor] = {}
        with torch.no_grad():
            for e in self.effects:
                for n, v in self.effect_params[e.name].values().items():
                    out[f"{e.name}.{n}"] = v.detach().clone()
        return out

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        model: Any = self
        if model.extra_columns or any(isinstance(e, MeterBias) for e in self.effects):
            raise ConfigError(
                f"The model {model.name} needs per-sample features or the measurement source; "
                "call forward_batch(batch) with a batch from make_batch(..., extra_columns=model.extra_columns)."
            )
        n = x.shape[1]
        w = len(model.wells)
        batch = Batch(
            model.wells,
            x,
            torch.zeros(w, n, dtype=DTYPE),
            torch.ones(w, n, dtype=torch.bool),
            torch.zeros(w, n, dtype=torch.int64),
            torch.zeros(w, n, dtype=torch.int64),
        )
        return model.forward_batch(batch)


class EffectMechanistic(_EffectMixin, Mechanistic):
    """``mm`` extended with effects (see the module docstring)."""

    base_name = "mm"

    def __init__(
        self, wells: Sequence[str], *, effects: Sequence[type[Effect]] = (), seed: int = 0
    ) -> None:
        Mechanistic.__init__(self, wells, seed=seed)
        self._init_effects(effects)

    def forward_batch(self, batch: Batch) -> torch.Tensor:
        return self._effect_rate(batch)


class EffectHybridError(_EffectMixin, HybridError):
    """``hem`` extended with effects: the network still adds to the extended mechanistic rate."""

    base_name = "hem"

    def __init__(
        self,
        wells: Sequence[str],
        *,
        effects: Sequence[type[Effect]] = (),
        seed: int = 0,
        hidden: Sequence[int] = (16,),
    ) -> None:
        HybridError.__init__(self, wells, seed=seed, hidden=hidden)
        self._init_effects(effects)

    def forward_batch(self, batch: Batch) -> torch.Tensor:
        return self._effect_rate(batch) + self.y_scale.unsqueeze(1) * self.net(
            self.normalise(batch.x)
        )


class EffectHybridArea(_EffectMixin, HybridArea):
    """``ham`` extended with effects: the area network multiplies the effects' area factors."""

    base_name = "ham"

    def __init__(
        self,
        wells: Sequence[str],
        *,
        effects: Sequence[type[Effect]] = (),
        seed: int = 0,
        hidden: Sequence[int] = (16,),
    ) -> None:
        HybridArea.__init__(self, wells, seed=seed, hidden=hidden)
        self._init_effects(effects)

    def forward_batch(self, batch: Batch) -> torch.Tensor:
        return self._effect_rate(batch)


_BASES: dict[str, type[ChokeModel]] = {
    "mm": EffectMechanistic,
    "hem": EffectHybridError,
    "ham": EffectHybridArea,
}


def make_effect_model(
    base: str, wells: Sequence[str], effects: Sequence[str | type[Effect]], **hyper: Any
) -> ChokeModel:
    """Build ``base`` (mm, hem or ham) extended with ``effects`` for ``wells``."""
    try:
        cls = _BASES[base]
    except KeyError:
        raise ConfigError(f"Effects extend the models {', '.join(_BASES)}, not '{base}'.") from None
    return cls(list(wells), effects=resolve_effects(effects), **hyper)


def effect_model_factory(
    base: str, effects: Sequence[str | type[Effect]], **hyper: Any
) -> Callable[[list[str]], ChokeModel]:
    """A ``model_factory`` for :func:`vfm_core.jobs.study.run_prequential`: wells -> extended model.

    Names are resolved now, so a typo fails before any training. The frame given to
    ``run_prequential`` must hold the effects' columns: pass it through :func:`add_features`.
    """
    classes = resolve_effects(effects)
    if base not in _BASES:
        raise ConfigError(f"Effects extend the models {', '.join(_BASES)}, not '{base}'.")

    def factory(wells: list[str]) -> ChokeModel:
        return make_effect_model(base, wells, classes, **hyper)

    return factory
