"""A nonstationary well-field simulator with optional hidden effects and a known truth.

It writes observations in the format of :mod:`vfm_core.schema` for a field of wells whose
true rates come from the Sachdeva choke model of :mod:`vfm_core.physics`, so learning,
drift handling and diagnosis can be tested against an answer that is known exactly. The
field is shaped after the paper's data (section 3, "Available data", and Table C3): about
26-27 thousand rows over ten wells and five years, MPFM readings every few hours and well
tests at irregular intervals, wells that start late, shut-ins and data gaps.

What happens to a well (ranges are drawn once per well, uniformly; see ``_RANGES``)
------------------------------------------------------------------------------------

* **History**: about 40 % of the wells start with the field, the others between 5 % and
  58 % of the horizon (up to late 2018 for 2016-2021, as in the paper); all run to the end.
* **Inputs drift** (the paper's "virtual drift"): the static wellhead pressure declines
  exponentially from 80-180 bar to 30-60 % of that after five years of production, with a
  slow random wander; the flowing pressure ``p_up`` lies 3-12 % lower at full opening
  (drawdown grows with the opening). ``p_down`` (the manifold) sits at 15-40 bar (capped at
  70 % of the well's lowest flowing ``p_up``), wanders slowly, has a few step changes of
  the separator set point, and always stays at least 3 bar below ``p_up``. ``t_up`` starts
  at 45-80 degC, rises with water cut, falls when the rate falls, and has a small season.
  The water cut (water share of the liquid mass) rises along a logistic curve from 0-20 %
  to 40-80 %; the gas-oil mass ratio rises as the pressure falls (free gas out of
  solution, ~ (p0/p)^0.1..0.6), so the gas mass fraction starts at 2-30 % and drifts.
  Day-to-day noise sits on every input (``truth["wells"][w]["noise"]``).
* **Operators** hold a plateau: the target rate is the plain model's rate at an initial
  opening of 0.25-0.6. Every 1-4 weeks (and after every shut-in) they set the choke to the
  opening that gives the target on the *true* model, hidden effects included (a vectorised
  bisection on ``u``; the rate is monotone in ``u``), in steps of 0.5 %. Once the choke is
  fully open (``plateau_end`` in the truth) the rate declines. About six times a year they
  move the choke by hand (x0.6..1.3) for hours to days (step tests, manual changes).
* **Downtime**: shut-ins (1-4 a year, median 4 days, up to 45 days) and historian gaps
  (0.5-2 a year, median 2 days, and with probability 0.3 one gap of 1-3 months) leave
  no rows. MPFM outages (0.75-2 a year, median 7 days) leave rows with sensors but no rate
  (empty ``q_total`` and ``source``).
* **Sampling**: MPFM rows at gamma-distributed intervals (shape 1.5) with a per-well mean
  of 10-16 h, at least 30 minutes apart. Well tests (source ``well_test``) at intervals drawn
  from the average of the paper's Table C3 (48 % under two weeks, 19 % two weeks to a
  month, 21 % one to two months, 5 % two to three, 4.5 % three to six, 1.7 % six to nine,
  0.8 % nine to twelve months); a test that falls into downtime is done just after it.
* **Meters**: an MPFM reading is ``q_true * mpfm_factor * (1 + e)`` with ``e`` white,
  relative standard deviation 2-5 % (per well), and ``mpfm_factor`` a slow random walk of
  0.3-1 % per square-root year (normal meter drift, not a hidden effect; with the
  ``mpfm_bias`` effect its bias and drift multiply in). A well test reads
  ``q_true * (1 + e)`` with 0.8-1.2 % relative noise and no drift. The optional ``q_gas``,
  ``q_oil`` and ``q_water`` columns split the measured total by the true phase shares.

The truth
---------

``q_true`` (Sm3/h) is ``physics.choke_mass_flow(C_D A_2(u), ...) *
physics.standard_volume_per_mass(...)`` on the row's own (recorded) inputs, with the well's
true parameters: rho_oil 800-880 kg/m3, rho_wat 1000-1035 kg/m3, kappa 1.25-1.31, M_gas
0.017-0.024 kg/mol, p_cr 0.5-0.6, C_D 0.75-0.9 and a bore of 40-100 mm; a linear valve,
ideal gas, no slip and constant p_cr and C_D, unless a hidden effect (see
:data:`HIDDEN_EFFECTS`) changes one of these. Without hidden effects the plain mechanistic
model with the well's parameters reproduces ``q_true`` to rounding. Each hidden effect's
size is measured on the rows themselves (the truth with and without it, same inputs) and
stored in ``truth["hidden"][name]["size"]``.

Another truth (``physics``): with ``physics="bernoulli"`` or ``"gilbert"`` the row's
truth is :func:`vfm_core.sim_physics.choke_rates` instead (a Bernoulli choke with Simpson's
multiplier, a fixed critical ratio and a Hall-Yarborough real gas; or the Gilbert-type bean
correlations), on the same inputs and with the same per-well draws; the operators aim at
that physics' own rate at the initial opening. ``valves`` gives the wells valve
characteristics in turn and ``gas_lift`` puts a share of the wells on gas lift (lift gas
adds to the gas-oil ratio at the choke from a random start). The truth JSON's ``physics``
block names the physics, its references and these options. The defaults reproduce the
Sachdeva field as it was before these options, file for file.

The simulator is calibrated for horizons of about 1-10 years; much longer runs deplete
the wells to a few bar (every row still passes the loader's filters).

Random streams are spawned per well and per purpose from ``numpy.random.SeedSequence``,
so the same seed gives identical frames, and adding a hidden effect leaves every random
draw unchanged (inputs still change where operators react to the changed true rate).
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import torch
from scipy.signal import lfilter
from scipy.special import expit
from tqdm import tqdm

from vfm_core import physics, schema, sim_physics, units
from vfm_core.errors import ConfigError
from vfm_core.fileio import write_with
from vfm_core.timeutil import utc_timestamp

__all__ = [
    "ParamSpec",
    "EffectSpec",
    "HIDDEN_EFFECTS",
    "parse_hidden",
    "SimulatedField",
    "simulate_field",
    "parse_valves",
    "write_field",
    "truth_paths",
    "load_truth",
    "TRUTH_SAMPLE_COLUMNS",
]

ParamValue = float | str

DAYS_PER_YEAR = 365.25
HOURS_PER_YEAR = DAYS_PER_YEAR * 24.0

#: Columns of ``SimulatedField.truth_samples``, in order.
TRUTH_SAMPLE_COLUMNS: tuple[str, ...] = (
    "time",
    "well",
    "q_true",
    "q_gas_true",
    "q_oil_true",
    "q_water_true",
    "c_d_true",
    "area_m2",
    "z_true",
    "p_cr_true",
    "mpfm_factor",
)

# --- hidden-effect registry ------------------------------------------------------------


@dataclass(frozen=True)
class ParamSpec:
    """One parameter of a hidden effect: its default, meaning and valid values.

    Numeric parameters are floats within ``[low, high]``; a parameter with ``choices``
    takes one of those names (or its 0-based index in ``choices``).
    """

    default: ParamValue
    meaning: str
    unit: str = "-"
    low: float = -math.inf
    high: float = math.inf
    choices: tuple[str, ...] = ()

    def describe(self) -> str:
        if self.choices:
            valid = " | ".join(self.choices)
        else:
            valid = f"{self.low:g}..{self.high:g} {self.unit}".rstrip()
        return f"{self.meaning} (default {self.default}; {valid})"

    def parse(self, effect: str, name: str, value: Any) -> ParamValue:
        """``value`` (text or number) as a checked float or choice name."""
        if self.choices:
            text = str(value).strip()
            if text in self.choices:
                return text
            try:
                index = int(float(text))
            except ValueError:
                index = -1
            if 0 <= index < len(self.choices) and float(text) == index:
                return self.choices[index]
            raise ConfigError(
                f"Hidden effect '{effect}': '{text}' is not a valid {name}; choose one of "
                f"{', '.join(self.choices)} (or its index 0..{len(self.choices) - 1})."
            )
        try:
            number = float(value)
        except (TypeError, ValueError):
            number = math.nan
        if not (math.isfinite(number) and self.low <= number <= self.high):
            raise ConfigError(
                f"Hidden effect '{effect}': {name}={value!r} is not valid; give a number in "
                f"{self.low:g}..{self.high:g} ({self.meaning}, {self.unit})."
            )
        return number


@dataclass(frozen=True)
class EffectSpec:
    """A hidden effect: what it is, which way it moves the data, and its parameters."""

    name: str
    description: str
    direction: str
    params: Mapping[str, ParamSpec] = field(default_factory=dict)

    def defaults(self) -> dict[str, ParamValue]:
        return {key: spec.default for key, spec in self.params.items()}

    def resolve(self, given: Mapping[str, Any]) -> dict[str, ParamValue]:
        """Defaults overridden by ``given``; unknown names raise ConfigError."""
        out = self.defaults()
        for key, value in given.items():
            if key not in self.params:
                valid = "; ".join(f"{k}: {s.describe()}" for k, s in self.params.items())
                raise ConfigError(
                    f"Hidden effect '{self.name}' has no parameter '{key}'. "
                    + (f"Valid parameters: {valid}." if valid else "It takes no parameters.")
                )
            out[key] = self.params[key].parse(self.name, key, value)
        return out


_VALVE_FAMILIES = tuple(name for name in physics.AREA_FUNCTIONS)

#: The hidden effects by name. Each changes the truth (or the MPFM) in a documented
#: direction; ``simulate_field`` measures how much and stores it in the truth JSON.
HIDDEN_EFFECTS: dict[str, EffectSpec] = {
    spec.name: spec
    for spec in (
        EffectSpec(
            "erosion",
            "Choke wear: the effective C_D grows with cumulative throughput (or time), "
            "plus an optional sudden step at a sand event in the second half of the history.",
            "Rate up over time at fixed inputs (c_d_true rises); the step moves it up at once.",
            {
                "rate": ParamSpec(
                    0.04,
                    "relative C_D growth per year-equivalent of the well's nominal throughput "
                    "(target rate for one year), or per year with basis=time",
                    "1/yr",
                    0.0,
                    1.0,
                ),
                "basis": ParamSpec(
                    "throughput", "what wear grows with", choices=("throughput", "time")
                ),
                "step": ParamSpec(
                    0.0, "relative C_D step at the sand event (0.1 = +10 %)", "-", -0.5, 2.0
                ),
                "onset": ParamSpec(
                    "start",
                    "when wear begins: at the well's start, or at the sand event (the truth's "
                    "sand_event: wear that starts inside the data)",
                    choices=("start", "event"),
                ),
            },
        ),
        EffectSpec(
            "valve",
            "The true valve characteristic A_2(u)/A_max is not linear.",
            "At fixed u the rate is A_family(u)/u times the linear one: lower for "
            "equal_percentage and convex, higher for quick_opening, lower below u=0.5 and "
            "higher above it for sigmoid; operators open the choke further to compensate.",
            {
                "family": ParamSpec(
                    "equal_percentage",
                    "valve family of physics.AREA_FUNCTIONS",
                    choices=_VALVE_FAMILIES,
                ),
            },
        ),
        EffectSpec(
            "real_gas",
            "Real gas: the upstream gas density uses Z = physics.z_factor_papay(p_up, t_up, M).",
            "Rate up where Z < 1 (denser gas, about 1/sqrt(Z) for gas-dominated flow); the "
            "effect shrinks as the pressure falls.",
        ),
        EffectSpec(
            "slip",
            "Phase slip: throat mixture density with Simpson's slip ratio "
            "(physics.choke_mass_flux(..., slip=True)).",
            "Rate up (slip lowers the momentum specific volume at the throat).",
        ),
        EffectSpec(
            "mpfm_bias",
            "The MPFM is biased and drifts against the well tests: "
            "mpfm_factor = 1 + bias + drift * years since the onset (the well's start, or "
            "with onset=event a time the truth records per well: a meter that starts to "
            "read off).",
            "MPFM readings above the well tests for positive bias/drift, the gap growing "
            "with time; well tests and the true rate are unaffected.",
            {
                "bias": ParamSpec(0.06, "relative MPFM bias from the onset on", "-", -0.5, 1.0),
                "drift": ParamSpec(0.03, "relative MPFM drift", "1/yr", -0.2, 0.2),
                "onset": ParamSpec(
                    "start",
                    "when the bias and drift begin: at the well's start, or at a time drawn "
                    "per well in the second half of its life (the truth's meter_event)",
                    choices=("start", "event"),
                ),
            },
        ),
        EffectSpec(
            "critical_ratio",
            "p_cr is solved per sample from Sachdeva's implicit equation "
            "(physics.sachdeva_critical_ratio), not a constant.",
            "Rate up or equal: Sachdeva's ratio maximises the throat mass flux, so any other "
            "constant ratio gives less choked flow; large at low gas fractions where the "
            "solved ratio is well below 0.5.",
        ),
    )
}


def parse_hidden(specs: Sequence[str]) -> dict[str, dict[str, ParamValue]]:
    """Parse hidden-effect specs from the command line into ``{name: parameters}``.

    Each string holds one or more effects separated by commas; an effect is a name with
    optional ``:key=value`` parameters, e.g. ``"erosion:rate=0.06:step=0.1"``,
    ``"erosion,real_gas"``, ``"valve:family=sigmoid"``. ``"none"`` means no effect and may
    not be combined with others. Every parameter is filled in (defaults where not given);
    numeric values are floats, choice values (``basis``, ``family``) names. An unknown
    name or parameter raises :class:`ConfigError` listing the valid ones.
    """
    if isinstance(specs, str):
        specs = [specs]
    chosen: dict[str, dict[str, ParamValue]] = {}
    saw_none = False
    for spec in specs:
        for item in str(spec).split(","):
            item = item.strip()
            if not item:
                continue
            name, *pairs = (part.strip() for part in item.split(":"))
            if name == "none":
                if pairs:
                    raise ConfigError("The hidden effect 'none' takes no parameters.")
                saw_none = True
                continue
            given: dict[str, str] = {}
            for pair in pairs:
                key, sep, value = pair.partition("=")
                if not sep or not key.strip() or not value.strip():
                    raise ConfigError(
                        f"Cannot read '{pair}' in hidden effect '{item}'; write parameters as "
                        f"name:key=value, e.g. erosion:rate=0.06:step=0.1."
                    )
                given[key.strip()] = value.strip()
            if name in chosen:
                raise ConfigError(
                    f"The hidden effect '{name}' is given twice; give it once, with all its "
                    f"parameters."
                )
            chosen[name] = _effect(name).resolve(given)
    if saw_none and chosen:
        raise ConfigError(
            f"'none' cannot be combined with other hidden effects ({', '.join(chosen)}); "
            f"give either none or a list of effects."
        )
    return chosen


def _effect(name: str) -> EffectSpec:
    try:
        return HIDDEN_EFFECTS[name]
    except KeyError:
        raise ConfigError(
            f"Unknown hidden effect '{name}'; choose from none, {', '.join(HIDDEN_EFFECTS)}."
        ) from None


def _resolve_hidden(
    hidden: Mapping[str, Mapping[str, Any]] | Sequence[str],
) -> dict[str, dict[str, ParamValue]]:
    if isinstance(hidden, Mapping):
        names = set(hidden)
        if "none" in names:
            if names - {"none"}:
                raise ConfigError(
                    "'none' cannot be combined with other hidden effects; give either none "
                    "or a list of effects."
                )
            return {}
        return {name: _effect(name).resolve(params or {}) for name, params in hidden.items()}
    return parse_hidden(hidden)


# --- physical ranges of the per-well draws ------------------------------------------------

#: (low, high) of every uniform per-well draw, in the units named in the key.
_RANGES: dict[str, tuple[float, float]] = {
    # Mechanistic parameters (shared/notes/choke-physics.md, "Typical priors").
    "rho_oil": (800.0, 880.0),  # kg/m3
    "rho_wat": (1000.0, 1035.0),  # kg/m3
    "kappa": (1.25, 1.31),  # -
    "m_gas": (0.017, 0.024),  # kg/mol
    "p_cr": (0.5, 0.6),  # -
    "c_d": (0.75, 0.9),  # -
    "bore_diameter_mm": (40.0, 100.0),  # mm
    # Reservoir and wellhead.
    "p_static0_bar": (80.0, 180.0),  # static wellhead pressure at the well's start, bar
    "remaining_after_5y": (0.3, 0.6),  # share of p_static0 left after five years
    "drawdown_full_open": (0.03, 0.12),  # relative drop of p_up at u = 1
    "p_down_bar": (15.0, 40.0),  # manifold pressure level, bar
    "t_up0_degc": (45.0, 80.0),  # wellhead temperature at the start, degC
    "t_per_water_cut_degc": (0.0, 10.0),  # warming per unit rise of water cut, degC
    "t_per_rate_degc": (4.0, 12.0),  # warming per unit of rate / target rate, degC
    "t_season_degc": (0.5, 2.0),  # amplitude of the yearly cycle, degC
    # Fluids.
    "water_cut0": (0.0, 0.2),  # water share of liquid mass at the start
    "water_cut1": (0.4, 0.8),  # ... late in life
    "water_cut_mid_years": (1.0, 6.0),  # time of the logistic's midpoint after the start
    "water_cut_width_years": (0.3, 1.2),  # logistic width
    "eta_gas0": (0.02, 0.3),  # gas mass fraction at the start
    "gor_pressure_exponent": (0.1, 0.6),  # gas-oil ratio ~ (p0 / p_static)^exponent
    # Operations and sampling.
    "initial_choke": (0.25, 0.6),  # opening that defines the plateau (target) rate
    "operator_interval_days": (7.0, 28.0),  # mean time between choke adjustments
    # Mean time between MPFM rows, h; stratified over the wells of a field (see
    # _field_layout) so the default field reliably lands near the paper's row count.
    "mpfm_interval_hours": (10.0, 16.0),
    "shut_ins_per_year": (1.0, 4.0),
    "data_gaps_per_year": (0.5, 2.0),
    "mpfm_outages_per_year": (0.75, 2.0),
    # Meter and sensor noise.
    "mpfm_noise_rel": (0.02, 0.05),  # relative std of one MPFM reading
    "mpfm_drift_per_sqrt_year": (0.003, 0.01),  # random-walk std after one year
    "well_test_noise_rel": (0.008, 0.012),  # relative std of one well test
    "p_up_noise_rel": (0.002, 0.006),  # day-to-day relative noise of p_up
}

#: Intervals between well tests, days, and their probabilities: the average over the ten
#: wells of the paper's Table C3 (the last bin "9m-1y" is kept rare).
_WELL_TEST_BINS: tuple[tuple[float, float, float], ...] = (
    (0.5, 14.0, 0.48),
    (14.0, 30.4, 0.19),
    (30.4, 61.0, 0.21),
    (61.0, 91.0, 0.05),
    (91.0, 183.0, 0.045),
    (183.0, 274.0, 0.017),
    (274.0, 365.0, 0.008),
)

#: Lift gas injected on a gas-lifted well, kg of gas per kg of produced liquid (low, high).
_LIFT_GAS_PER_LIQUID = (0.03, 0.15)

_GRID_DAYS = 0.25  # resolution of the slow processes and the operator's view, days
_CHOKE_STEPS = 200  # choke positions are set in steps of 1/200 = 0.5 %
_U_MIN = 0.02  # the smallest opening the operators use
_P_DOWN_MARGIN_BAR = 3.0  # p_down stays at least this far below p_up
_MIN_MPFM_GAP_HOURS = 0.5
_STREAMS = (
    "params",
    "life",
    "sampling",
    "well_tests",
    "processes",
    "operations",
    "row_noise",
    "meter",
    "effects",
    "gas_lift",
)


# --- the truth on tensors ---------------------------------------------------------------


@dataclass(frozen=True)
class _Active:
    """Which hidden physics is switched on for one evaluation."""

    family: str = "linear"
    real_gas: bool = False
    slip: bool = False
    critical_ratio: bool = False
    physics: str = sim_physics.DEFAULT_PHYSICS


@dataclass(frozen=True)
class _Fluid:
    rho_oil: float
    rho_wat: float
    kappa: float
    m_gas: float
    p_cr: float
    c_d: float
    a_max_m2: float
    well_index: int = 0


def _tensor(values: Any) -> torch.Tensor:
    return torch.as_tensor(np.asarray(values, dtype=np.float64), dtype=torch.float64)


def _choke_truth(
    fluid: _Fluid,
    active: _Active,
    inputs: Mapping[str, np.ndarray],
    c_d: np.ndarray | float,
    *,
    phases: bool = False,
    critical_iterations: int = 60,
) -> dict[str, np.ndarray]:
    """Noise-free rates (Sm3/h), effective area (m2), Z and p_cr for a batch of samples.

    ``inputs`` holds ``u`` (-), ``p_up_bar``, ``p_down_bar`` (bar), ``t_up_degc`` (degC),
    ``eta_gas`` and ``eta_oil`` (-); ``c_d`` is the true discharge coefficient.
    ``critical_iterations`` bisection steps solve Sachdeva's critical ratio (when that
    effect is on); the operators' own searches use fewer, the truth of a row the default.
    Physics other than Sachdeva's come from :func:`sim_physics.choke_rates`.
    """
    if active.physics != sim_physics.DEFAULT_PHYSICS:
        return _other_truth(fluid, active, inputs, c_d, phases=phases)
    p1 = units.bar_to_pa(_tensor(inputs["p_up_bar"]))
    p2 = units.bar_to_pa(_tensor(inputs["p_down_bar"]))
    t1 = units.degc_to_k(_tensor(inputs["t_up_degc"]))
    eg = _tensor(inputs["eta_gas"])
    eo = _tensor(inputs["eta_oil"])
    fraction = physics.area_fraction(_tensor(inputs["u"]), active.family)
    area = _tensor(c_d) * fluid.a_max_m2 * fraction
    if active.real_gas:
        z = physics.z_factor_papay(p1, t1, fluid.m_gas)
    else:
        z = torch.ones_like(p1)
    if active.critical_ratio:
        rho_g1 = physics.gas_density(p1, t1, fluid.m_gas, z)
        v_liq = physics.liquid_specific_volume(eg, eo, fluid.rho_oil, fluid.rho_wat)
        p_cr = physics.sachdeva_critical_ratio(
            eg, rho_g1, v_liq, fluid.kappa, iterations=critical_iterations
        )
    else:
        p_cr = torch.full_like(p1, fluid.p_cr)
    mdot = physics.choke_mass_flow(
        area,
        p1,
        p2,
        t1,
        eg,
        eo,
        rho_oil=fluid.rho_oil,
        rho_wat=fluid.rho_wat,
        kappa=fluid.kappa,
        m_gas=fluid.m_gas,
        p_cr=p_cr,
        z=z,
        slip=active.slip,
    )
    per_kg = physics.standard_volume_per_mass(
        eg, eo, rho_oil=fluid.rho_oil, rho_wat=fluid.rho_wat, m_gas=fluid.m_gas
    )
    out = {"q": units.per_s_to_per_h(mdot * per_kg).numpy()}
    if phases:
        q_gas, q_oil, q_wat = physics.phase_rates(
            mdot, eg, eo, rho_oil=fluid.rho_oil, rho_wat=fluid.rho_wat, m_gas=fluid.m_gas
        )
        out.update(
            q_gas=units.per_s_to_per_h(q_gas).numpy(),
            q_oil=units.per_s_to_per_h(q_oil).numpy(),
            q_water=units.per_s_to_per_h(q_wat).numpy(),
            area=area.numpy(),
            z=z.numpy(),
            p_cr=p_cr.numpy(),
        )
    return out


def _other_truth(
    fluid: _Fluid,
    active: _Active,
    inputs: Mapping[str, np.ndarray],
    c_d: np.ndarray | float,
    *,
    phases: bool = False,
) -> dict[str, np.ndarray]:
    """:func:`_choke_truth` for a physics of :mod:`vfm_core.sim_physics` (same outputs)."""
    fraction = physics.area_fraction(_tensor(inputs["u"]), active.family).numpy()
    area = np.asarray(c_d, dtype=np.float64) * fluid.a_max_m2 * fraction
    well = sim_physics.WellConstants(
        rho_oil=fluid.rho_oil,
        rho_wat=fluid.rho_wat,
        m_gas=fluid.m_gas,
        p_cr=fluid.p_cr,
        c_d=fluid.c_d,
        well_index=fluid.well_index,
    )
    si = {
        "area_eff_m2": area,
        "p_up_pa": units.bar_to_pa(np.asarray(inputs["p_up_bar"], dtype=np.float64)),
        "p_down_pa": units.bar_to_pa(np.asarray(inputs["p_down_bar"], dtype=np.float64)),
        "t_up_k": units.degc_to_k(np.asarray(inputs["t_up_degc"], dtype=np.float64)),
        "eta_gas": np.asarray(inputs["eta_gas"], dtype=np.float64),
        "eta_oil": np.asarray(inputs["eta_oil"], dtype=np.float64),
    }
    rates = sim_physics.choke_rates(active.physics, well, si)
    out = {"q": units.per_s_to_per_h(rates.q_total)}
    if phases:
        out.update(
            q_gas=units.per_s_to_per_h(rates.q_gas),
            q_oil=units.per_s_to_per_h(rates.q_oil),
            q_water=units.per_s_to_per_h(rates.q_wat),
            area=area,
            z=rates.z,
            p_cr=rates.p_cr,
        )
    return out


# --- small numeric helpers --------------------------------------------------------------


def _uniform(rng: np.random.Generator, key: str) -> float:
    low, high = _RANGES[key]
    return float(rng.uniform(low, high))


def _ou(rng: np.random.Generator, n: int, std: float, corr_days: float) -> np.ndarray:
    """A stationary Ornstein-Uhlenbeck path on the grid (AR(1) with lag _GRID_DAYS)."""
    a = math.exp(-_GRID_DAYS / corr_days)
    eps = rng.standard_normal(n)
    first = std * eps[0]
    rest = lfilter([std * math.sqrt(1.0 - a * a)], [1.0, -a], eps[1:], zi=[a * first])[0]
    return np.concatenate([[first], rest])


def _poisson_intervals(
    rng: np.random.Generator,
    t0: float,
    t1: float,
    per_year: float,
    median_days: float,
    sigma: float,
    bounds: tuple[float, float],
) -> np.ndarray:
    """Random [start, end) intervals (days) of lognormal length, starting at a Poisson rate."""
    count = int(rng.poisson(per_year * max(t1 - t0, 0.0) / DAYS_PER_YEAR))
    starts = np.sort(rng.uniform(t0, t1, count)) if t1 > t0 else np.zeros(0)
    lengths = np.clip(median_days * np.exp(sigma * rng.standard_normal(count)), *bounds)
    return np.column_stack([starts, np.minimum(starts + lengths, t1)])


def _merge(intervals: np.ndarray) -> np.ndarray:
    if len(intervals) == 0:
        return np.zeros((0, 2))
    ordered = intervals[np.argsort(intervals[:, 0])]
    merged = [list(ordered[0])]
    for start, end in ordered[1:]:
        if start <= merged[-1][1]:
            merged[-1][1] = max(merged[-1][1], end)
        else:
            merged.append([start, end])
    return np.asarray(merged, dtype=np.float64)


def _inside(times: np.ndarray, intervals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Whether each time lies in one of the merged ``intervals``, and that interval's index."""
    if len(intervals) == 0:
        return np.zeros(len(times), dtype=bool), np.zeros(len(times), dtype=np.int64)
    index = np.searchsorted(intervals[:, 0], times, side="right") - 1
    hit = (index >= 0) & (times < intervals[np.maximum(index, 0), 1])
    return hit, np.maximum(index, 0)


def _soft_limits(x: np.ndarray, low: float, high: float, width: float = 5.0) -> np.ndarray:
    """``x`` bent smoothly into (low, high) within ``width`` of either limit (no flat tops)."""
    upper, lower = high - width, low + width
    x = np.where(x > upper, upper + width * np.tanh((x - upper) / width), x)
    return np.where(x < lower, lower - width * np.tanh((lower - x) / width), x)


def _round_choke(u: np.ndarray) -> np.ndarray:
    # Dividing (not multiplying by 0.005) gives the shortest decimal, e.g. 0.575 exactly.
    return np.clip(np.round(u * _CHOKE_STEPS) / _CHOKE_STEPS, _U_MIN, 1.0)


def _slope_per_year(years: np.ndarray, values: np.ndarray) -> float:
    if len(years) < 3 or np.ptp(years) < 1e-6:
        return 0.0
    return float(np.polyfit(years, values, 1)[0])


# --- one well -----------------------------------------------------------------------------


@dataclass
class _WellResult:
    rows: pd.DataFrame  # observations of this well, without time conversion (t_days)
    samples: dict[str, np.ndarray]
    truth: dict[str, Any]
    # For the measured size of each effect: the truth with that effect removed.
    q_without: dict[str, np.ndarray]
    q_plain: np.ndarray
    years_since_start: np.ndarray
    is_mpfm: np.ndarray


@dataclass
class _Meters:
    """What one well's meters recorded: ``q_meas`` (Sm3/h; NaN on rows without a rate),
    ``source`` per row, ``is_mpfm`` (rows with an MPFM rate), the MPFM's drift factor
    ``base_factor`` and its full factor ``mpfm_factor`` (1 off its rows), ``years`` since
    the well's start."""

    q_meas: np.ndarray
    source: np.ndarray
    is_mpfm: np.ndarray
    base_factor: np.ndarray
    mpfm_factor: np.ndarray
    years: np.ndarray


class _Well:
    """Simulates one well; every random draw comes from a named per-well stream."""

    def __init__(
        self,
        name: str,
        index: int,
        seed: int,
        t_start: float,
        t_end: float,
        hidden: Mapping[str, Mapping[str, ParamValue]],
        sampling_quantile: float,
        *,
        physics_name: str = sim_physics.DEFAULT_PHYSICS,
        valve_family: str | None = None,
        gas_lift: bool = False,
        sample_every_days: float | None = None,
    ) -> None:
        self.name = name
        self._sampling_quantile = sampling_quantile
        # synchronised sampling (vfm_core.separator_sim): rows at every multiple of this
        # many days after the field's origin plus a quarter day (06:00), for all wells alike
        self._sample_every_days = sample_every_days
        self.t0 = t_start
        self.t1 = t_end
        self.hidden = hidden
        self._seed = seed
        self._index = index
        self.cumulative: np.ndarray | None = None
        if valve_family is None:
            valve_family = str(hidden["valve"]["family"]) if "valve" in hidden else "linear"
        self.active = _Active(
            family=valve_family,
            real_gas="real_gas" in hidden,
            slip="slip" in hidden,
            critical_ratio="critical_ratio" in hidden,
            physics=physics_name,
        )
        self.gas_lift = gas_lift
        self.lift: dict[str, Any] | None = None

    def rng(self, stream: str) -> np.random.Generator:
        key = (1, self._index, _STREAMS.index(stream))
        return np.random.default_rng(np.random.SeedSequence(self._seed, spawn_key=key))

    # ---- the whole well ----

    def run(self) -> _WellResult:
        self._draw_parameters()
        self._draw_life()
        self._build_processes()
        self._operate()
        return self._observe()

    def _draw_parameters(self) -> None:
        rng = self.rng("params")
        d = {key: _uniform(rng, key) for key in _RANGES}
        low, high = _RANGES["mpfm_interval_hours"]
        d["mpfm_interval_hours"] = low + (high - low) * self._sampling_quantile
        self.draw = d
        self.fluid = _Fluid(
            rho_oil=d["rho_oil"],
            rho_wat=d["rho_wat"],
            kappa=d["kappa"],
            m_gas=d["m_gas"],
            p_cr=d["p_cr"],
            c_d=d["c_d"],
            a_max_m2=physics.choke_area_m2(d["bore_diameter_mm"] / 1000.0),
            well_index=self._index,
        )
        self.decline_per_year = -math.log(d["remaining_after_5y"]) / 5.0
        duration_years = (self.t1 - self.t0) / DAYS_PER_YEAR
        lowest_static = d["p_static0_bar"] * math.exp(-self.decline_per_year * duration_years)
        # Slow wander (3 sd of 1.5 %) and row noise are left room for.
        lowest_flowing = lowest_static * (1.0 - d["drawdown_full_open"]) * 0.95
        self.p_down_level = min(d["p_down_bar"], 0.7 * lowest_flowing)
        wc0 = d["water_cut0"]
        w0 = wc0 / (1.0 - wc0)
        self.gor0 = d["eta_gas0"] * (1.0 + w0) / (1.0 - d["eta_gas0"])

    def _draw_life(self) -> None:
        rng = self.rng("life")
        d = self.draw
        t0, t1 = self.t0, self.t1
        shut = _poisson_intervals(rng, t0 + 3.0, t1, d["shut_ins_per_year"], 4.0, 0.9, (0.5, 45))
        gaps = _poisson_intervals(rng, t0 + 1.0, t1, d["data_gaps_per_year"], 2.0, 0.9, (0.25, 20))
        long_start = rng.uniform(t0, t1)
        long_length = rng.uniform(30.0, 91.0)
        if rng.uniform() < 0.3 and t1 - t0 > 365.0:
            gaps = np.vstack([gaps, [[long_start, min(long_start + long_length, t1)]]])
        outages = _poisson_intervals(rng, t0, t1, d["mpfm_outages_per_year"], 7.0, 0.7, (1.0, 40.0))
        self.shut_ins = _merge(shut)
        self.data_gaps = _merge(gaps)
        self.no_rows = _merge(np.vstack([self.shut_ins, self.data_gaps]))
        self.outages = _merge(outages)

    def _build_processes(self) -> None:
        """Slow processes on a grid of _GRID_DAYS: pressure, temperature, fluid shares."""
        rng = self.rng("processes")
        d = self.draw
        grid = np.arange(self.t0, self.t1 + _GRID_DAYS, _GRID_DAYS)
        n = len(grid)
        years = (grid - self.t0) / DAYS_PER_YEAR
        self.grid = grid
        trend = d["p_static0_bar"] * np.exp(-self.decline_per_year * years)
        self.p_static = trend * (1.0 + _ou(rng, n, 0.015, 30.0))
        # Separator set-point changes: 0-3 steps of +-5..15 % at random times.
        steps = int(rng.integers(0, 4))
        when = rng.uniform(self.t0, self.t1, steps)
        size = rng.uniform(0.05, 0.15, steps) * rng.choice([-1.0, 1.0], steps)
        factor = np.ones(n)
        for t_step, s in zip(when, size, strict=True):
            factor *= np.where(grid >= t_step, 1.0 + s, 1.0)
        p_down = self.p_down_level * factor * (1.0 + _ou(rng, n, 0.03, 20.0))
        # Set points stay near the drawn range: at most 10 % above it, 40 % below the level.
        self.p_down_smooth = np.clip(
            p_down, 0.6 * self.p_down_level, 1.1 * _RANGES["p_down_bar"][1]
        )
        wc_mid = self.t0 + d["water_cut_mid_years"] * DAYS_PER_YEAR
        wc_width = d["water_cut_width_years"] * DAYS_PER_YEAR
        logistic = expit((grid - wc_mid) / wc_width)
        logistic0 = expit((self.t0 - wc_mid) / wc_width)
        # Shifted so the curve starts at water_cut0 at the well's start.
        shape = (logistic - logistic0) / (1.0 - logistic0)
        wc = d["water_cut0"] + (d["water_cut1"] - d["water_cut0"]) * shape
        self.water_cut = np.clip(wc + _ou(rng, n, 0.01, 30.0), 0.0, 0.95)
        self.gor = (
            self.gor0
            * (d["p_static0_bar"] / trend) ** d["gor_pressure_exponent"]
            * np.exp(_ou(rng, n, 0.03, 20.0))
        )
        phase = rng.uniform(0.0, 2.0 * math.pi)
        self.t_base = (
            d["t_up0_degc"]
            + d["t_per_water_cut_degc"] * (self.water_cut - d["water_cut0"])
            + d["t_season_degc"] * np.sin(2.0 * math.pi * grid / DAYS_PER_YEAR + phase)
            + _ou(rng, n, 1.0, 10.0)
        )
        self.flowing = ~_inside(grid, self.shut_ins)[0]
        if self.gas_lift:
            self._add_gas_lift()

    def _add_gas_lift(self) -> None:
        """Lift gas injected into the well reaches the choke: it adds to the gas-oil ratio.

        The injection starts at the well's start (probability 0.3) or at a random time in
        the first half of its life, at 0.03-0.15 kg of lift gas per kg of liquid, and is
        changed 0-3 times by x0.7..1.3 (from its own random stream, so the other draws stay
        as they are). The recorded ``eta_gas`` includes the lift gas, as an MPFM at the
        choke measures it; the wellhead pressure is left as it is (no well model here).
        """
        rng = self.rng("gas_lift")
        grid = self.grid
        span = self.t1 - self.t0
        from_start = bool(rng.uniform() < 0.3)
        t_lift = self.t0 if from_start else self.t0 + rng.uniform(0.0, 0.5) * span
        low, high = _LIFT_GAS_PER_LIQUID
        ratio0 = float(rng.uniform(low, high))
        changes = int(rng.integers(0, 4))
        when = np.sort(rng.uniform(t_lift, self.t1, changes))
        factors = rng.uniform(0.7, 1.3, changes)
        ratio = np.where(grid >= t_lift, ratio0, 0.0)
        for t_change, factor in zip(when, factors, strict=True):
            ratio = np.where(grid >= t_change, ratio * factor, ratio)
        water_oil = self.water_cut / (1.0 - self.water_cut)
        self.gor = self.gor + ratio * (1.0 + water_oil)
        self.lift = {
            "start_day": float(t_lift),
            "gas_per_liquid_kg_kg": ratio0,
            "changes": [[float(t), float(f)] for t, f in zip(when, factors, strict=True)],
        }

    # ---- operations ----

    def _fractions(self, gor: np.ndarray, water_cut: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Gas and oil mass fractions from the gas-oil and water-liquid mass ratios."""
        water_oil = water_cut / (1.0 - water_cut)
        total = 1.0 + gor + water_oil
        eta_gas = np.clip(gor / total, 0.002, 0.98)
        eta_oil = (1.0 - eta_gas) / (1.0 + water_oil)
        return eta_gas, eta_oil

    def _c_d_at(self, t: np.ndarray) -> np.ndarray:
        """True C_D at times ``t`` (days), erosion included.

        With basis=throughput the wear is the cumulative produced volume (Sm3, from the
        previous operating pass, linear between grid points) over the well's nominal
        throughput, the target rate for one year; with onset=event both count from the
        sand event on (none before it).
        """
        c_d = np.full(len(t), self.fluid.c_d)
        spec = self.hidden.get("erosion")
        if spec is None:
            return c_d
        begins = self.sand_event if spec.get("onset") == "event" else self.t0
        if spec["basis"] == "time":
            worn = np.maximum(t - begins, 0.0) / DAYS_PER_YEAR
        elif self.cumulative is None:
            worn = np.zeros(len(t))
        else:
            produced = np.interp(t, self.grid, self.cumulative)
            if begins > self.t0:  # the volume produced since the onset
                produced = np.maximum(produced - np.interp(begins, self.grid, self.cumulative), 0)
            worn = produced / (self.target * HOURS_PER_YEAR)
        c_d = c_d * (1.0 + float(spec["rate"]) * worn)
        return c_d * np.where(t >= self.sand_event, 1.0 + float(spec["step"]), 1.0)

    def _state(self, t: np.ndarray, u: np.ndarray, t_up: np.ndarray) -> dict[str, np.ndarray]:
        """Noise-free inputs at times ``t`` for openings ``u`` (the operator's view)."""
        p_static = np.interp(t, self.grid, self.p_static)
        p_up = p_static * (1.0 - self.draw["drawdown_full_open"] * u)
        p_down = np.minimum(np.interp(t, self.grid, self.p_down_smooth), p_up - _P_DOWN_MARGIN_BAR)
        eta_gas, eta_oil = self._fractions(
            np.interp(t, self.grid, self.gor), np.interp(t, self.grid, self.water_cut)
        )
        return {
            "u": u,
            "p_up_bar": p_up,
            "p_down_bar": p_down,
            "t_up_degc": t_up,
            "eta_gas": eta_gas,
            "eta_oil": eta_oil,
        }

    def _true_rate(self, state: dict[str, np.ndarray], c_d: np.ndarray) -> np.ndarray:
        """The true rate as the operators see it (Sm3/h); y_c to about 1e-12 is plenty."""
        truth = _choke_truth(self.fluid, self.active, state, c_d, critical_iterations=40)
        return truth["q"]

    def _decide(self, t: np.ndarray, c_d: np.ndarray, t_up: np.ndarray) -> np.ndarray:
        """Openings that give the target rate on the true model (bisection on u)."""
        lo = np.full(len(t), _U_MIN)
        hi = np.ones(len(t))
        q_open = self._true_rate(self._state(t, hi, t_up), c_d)
        for _ in range(22):  # 1e-7 in u; openings are set in steps of 0.005
            mid = 0.5 * (lo + hi)
            low_rate = self._true_rate(self._state(t, mid, t_up), c_d) < self.target
            lo = np.where(low_rate, mid, lo)
            hi = np.where(low_rate, hi, mid)
        u = np.where(q_open <= self.target, 1.0, 0.5 * (lo + hi))
        return _round_choke(u)

    def _schedule(self, t: np.ndarray) -> np.ndarray:
        index = np.clip(np.searchsorted(self.t_decide, t, side="right") - 1, 0, None)
        u = self.u_decide[index]
        hit, which = _inside(t, self.deviations[:, :2]) if len(self.deviations) else (None, None)
        if hit is not None and hit.any():
            u = np.where(hit, _round_choke(u * self.deviations[which, 2]), u)
        return u

    def _operate(self) -> None:
        rng = self.rng("operations")
        d = self.draw
        # Decision times: every 1-4 weeks (per-well mean, +-50 %) and after each shut-in.
        mean_gap = d["operator_interval_days"]
        n_max = int((self.t1 - self.t0) / (0.5 * mean_gap)) + 2
        gaps = mean_gap * rng.uniform(0.5, 1.5, n_max)
        regular = self.t0 + np.concatenate([[0.0], np.cumsum(gaps)])
        regular = regular[regular < self.t1]
        restarts = self.shut_ins[:, 1][self.shut_ins[:, 1] < self.t1]
        t_dec = np.unique(np.concatenate([regular, restarts]))
        self.t_decide = t_dec[~_inside(t_dec, self.shut_ins)[0] | (t_dec == self.t0)]
        # Manual changes and step tests: ~6 a year, 2 h to 10 days, opening x0.6..1.3.
        dev = _poisson_intervals(rng, self.t0, self.t1, 6.0, 1.0, 1.0, (2.0 / 24.0, 10.0))
        dev_factor = rng.uniform(0.6, 1.3, len(dev))
        keep = np.ones(len(dev), dtype=bool)
        if len(dev):
            keep[1:] = dev[1:, 0] >= np.maximum.accumulate(dev[:, 1])[:-1]  # no overlaps
        self.deviations = np.column_stack([dev, dev_factor])[keep]
        events = self.rng("effects").uniform(0.5, 1, 2)  # the sand event's, then the meter's
        self.sand_event = self.t0 + (self.t1 - self.t0) * float(events[0])
        self.meter_event = self.t0 + (self.t1 - self.t0) * float(events[1])

        # The target: the plain model's rate at the initial opening and start state.
        t_first = np.array([self.t0])
        plain = _Active(physics=self.active.physics)
        u0 = np.array([_round_choke(np.array([d["initial_choke"]]))[0]])
        start = self._state(t_first, u0, self.t_base[:1])
        self.target = float(_choke_truth(self.fluid, plain, start, self.fluid.c_d)["q"][0])

        # Rates, temperature and wear depend on each other; three passes settle them.
        grid = self.grid
        rate_ratio = np.ones(len(grid))
        self.cumulative = None
        for _ in range(3):
            self.t_up_smooth = _soft_limits(
                self.t_base + d["t_per_rate_degc"] * (np.clip(rate_ratio, 0.0, 1.5) - 1.0),
                40.0,
                90.0,
            )
            t_up_dec = np.interp(self.t_decide, grid, self.t_up_smooth)
            self.u_decide = self._decide(self.t_decide, self._c_d_at(self.t_decide), t_up_dec)
            u_grid = self._schedule(grid)
            state = self._state(grid, u_grid, self.t_up_smooth)
            q_grid = self._true_rate(state, self._c_d_at(grid))
            rate_ratio = q_grid / self.target
            produced = q_grid * self.flowing * _GRID_DAYS * 24.0
            self.cumulative = np.concatenate([[0.0], np.cumsum(produced[:-1])])

    # ---- rows and meters ----

    def _row_times(self) -> tuple[np.ndarray, np.ndarray]:
        """Times (days) of MPFM rows and of well-test rows, none inside downtime."""
        rng = self.rng("sampling")
        mean_h = self.draw["mpfm_interval_hours"]
        span_h = (self.t1 - self.t0) * 24.0
        n = int(span_h / mean_h * 1.3) + 50
        gaps_h = np.maximum(rng.gamma(1.5, mean_h / 1.5, n), _MIN_MPFM_GAP_HOURS)
        while gaps_h.sum() < span_h:
            more = rng.gamma(1.5, mean_h / 1.5, n)
            gaps_h = np.concatenate([gaps_h, np.maximum(more, _MIN_MPFM_GAP_HOURS)])
        t_mpfm = self.t0 + np.cumsum(gaps_h) / 24.0
        if self._sample_every_days is not None:  # the draws above keep the streams aligned
            every = self._sample_every_days
            t_mpfm = np.arange(math.ceil((self.t0 - 0.25) / every), (self.t1 - 0.25) / every)
            t_mpfm = t_mpfm * every + 0.25
            t_mpfm = t_mpfm[t_mpfm >= self.t0]
        t_mpfm = t_mpfm[t_mpfm < self.t1]
        t_mpfm = t_mpfm[~_inside(t_mpfm, self.no_rows)[0]]

        rng = self.rng("well_tests")
        lows, highs, probs = (np.array(c) for c in zip(*_WELL_TEST_BINS, strict=True))
        n = int((self.t1 - self.t0) / 7.0) + 10
        which = rng.choice(len(probs), size=n, p=probs / probs.sum())
        gaps_d = rng.uniform(lows[which], highs[which])
        after_downtime = rng.uniform(0.25, 2.0, n)
        t_test = self.t0 + rng.uniform(1.0, 14.0) + np.concatenate([[0.0], np.cumsum(gaps_d)])
        t_test = t_test[:n]
        # A test planned during downtime is done shortly after the well is back.
        hit, index = _inside(t_test, self.no_rows)
        if len(self.no_rows):
            t_test = np.where(hit, self.no_rows[index, 1] + after_downtime[: len(t_test)], t_test)
        t_test = np.unique(t_test[t_test < self.t1])
        t_test = t_test[~_inside(t_test, self.no_rows)[0]]
        if len(t_test) > 1:  # at least 6 h between tests after the moves
            t_test = t_test[np.concatenate([[True], np.diff(t_test) >= 0.25])]
        return t_mpfm, t_test

    def _observation_times(self) -> tuple[np.ndarray, np.ndarray]:
        """Times (days, whole seconds) of the well's rows in order, and which are well tests."""
        t_mpfm, t_test = self._row_times()
        t = np.concatenate([t_mpfm, t_test])
        is_test = np.concatenate([np.zeros(len(t_mpfm), bool), np.ones(len(t_test), bool)])
        # Whole seconds, as a historian stores them.
        t = np.round(t * 86400.0) / 86400.0
        order = np.lexsort((is_test, t))
        return t[order], is_test[order]

    def _sensor_readings(self, t: np.ndarray) -> dict[str, np.ndarray]:
        """The recorded inputs at times ``t`` (days): the operated state with sensor noise,
        rounded as a historian stores them (bar, degC; the inputs of :func:`_choke_truth`)."""
        d = self.draw
        rng = self.rng("row_noise")
        noise = rng.standard_normal((5, len(t)))
        u = self._schedule(t)
        p_static = np.interp(t, self.grid, self.p_static)
        p_up = p_static * (1.0 - d["drawdown_full_open"] * u)
        p_up = np.round(p_up * (1.0 + d["p_up_noise_rel"] * noise[0]), 3)
        p_down = np.interp(t, self.grid, self.p_down_smooth) + 0.15 * noise[1]
        p_down = np.round(np.minimum(p_down, p_up - _P_DOWN_MARGIN_BAR), 3)
        t_up = np.round(np.interp(t, self.grid, self.t_up_smooth) + 0.2 * noise[2], 3)
        gor = np.interp(t, self.grid, self.gor) * (1.0 + 0.015 * noise[3])
        water_cut = np.clip(np.interp(t, self.grid, self.water_cut) + 0.005 * noise[4], 0.0, 0.95)
        eta_gas, eta_oil = self._fractions(gor, water_cut)
        eta_gas, eta_oil = np.round(eta_gas, 7), np.round(eta_oil, 7)
        eta_oil = np.minimum(eta_oil, 1.0 - eta_gas)
        return {
            "u": u,
            "p_up_bar": p_up,
            "p_down_bar": p_down,
            "t_up_degc": t_up,
            "eta_gas": eta_gas,
            "eta_oil": eta_oil,
        }

    def _meter_readings(self, t: np.ndarray, is_test: np.ndarray, q_true: np.ndarray) -> _Meters:
        """What the MPFM (drifting, with its noise and any hidden bias; none in an outage)
        and the well tests measure of the true rates ``q_true`` (Sm3/h) at times ``t``."""
        d = self.draw
        n = len(t)
        rng = self.rng("meter")
        drift_steps = rng.standard_normal(len(self.grid)) * d["mpfm_drift_per_sqrt_year"]
        drift_walk = np.cumsum(drift_steps * math.sqrt(_GRID_DAYS / DAYS_PER_YEAR))
        drift_walk -= drift_walk[0]
        meter_noise = rng.standard_normal(n)
        years = (t - self.t0) / DAYS_PER_YEAR
        base_factor = 1.0 + np.interp(t, self.grid, drift_walk)
        factor = base_factor.copy()
        if "mpfm_bias" in self.hidden:
            spec = self.hidden["mpfm_bias"]
            if spec.get("onset") == "event":
                on = np.maximum(t - self.meter_event, 0.0) / DAYS_PER_YEAR
                step = np.where(t >= self.meter_event, float(spec["bias"]), 0.0)
                factor = factor * (1.0 + step + float(spec["drift"]) * on)
            else:
                factor = factor * (1.0 + float(spec["bias"]) + float(spec["drift"]) * years)
        in_outage = _inside(t, self.outages)[0]
        is_mpfm = ~is_test & ~in_outage
        q_meas = np.full(n, np.nan)
        q_meas[is_mpfm] = (q_true * factor * (1.0 + d["mpfm_noise_rel"] * meter_noise))[is_mpfm]
        q_meas[is_test] = (q_true * (1.0 + d["well_test_noise_rel"] * meter_noise))[is_test]
        return _Meters(
            q_meas=q_meas,
            source=np.where(is_mpfm, schema.MPFM, np.where(is_test, schema.WELL_TEST, "")),
            is_mpfm=is_mpfm,
            base_factor=base_factor,
            mpfm_factor=np.where(is_mpfm, factor, 1.0),
            years=years,
        )

    def _rates_without_each_effect(
        self, inputs: dict[str, np.ndarray], c_d: np.ndarray, meters: _Meters
    ) -> dict[str, np.ndarray]:
        """Per hidden effect, the true rates (Sm3/h) of the same rows without it (for
        ``mpfm_bias`` the MPFM's factor without the bias), for the effects' measured sizes."""
        q_without: dict[str, np.ndarray] = {}
        for effect in self.hidden:
            if effect == "mpfm_bias":
                q_without[effect] = np.where(meters.is_mpfm, meters.base_factor, 1.0)
                continue
            active = self.active
            c_d_eff = c_d
            if effect == "erosion":
                c_d_eff = np.full(len(c_d), self.fluid.c_d)
            elif effect == "valve":
                active = replace(active, family="linear")
            else:
                active = replace(
                    active,
                    real_gas=active.real_gas and effect != "real_gas",
                    slip=active.slip and effect != "slip",
                    critical_ratio=active.critical_ratio and effect != "critical_ratio",
                )
            q_without[effect] = _choke_truth(self.fluid, active, inputs, c_d_eff)["q"]
        return q_without

    def _observe(self) -> _WellResult:
        """The well's observation rows, their noise-free truth, and the truth JSON part."""
        t, is_test = self._observation_times()
        inputs = self._sensor_readings(t)
        c_d = self._c_d_at(t)
        truth = _choke_truth(self.fluid, self.active, inputs, c_d, phases=True)
        q_true = truth["q"]
        meters = self._meter_readings(t, is_test, q_true)
        q_meas = meters.q_meas
        rows = pd.DataFrame(
            {
                "t_days": t,
                schema.WELL: self.name,
                "choke": inputs["u"],
                "p_up": inputs["p_up_bar"],
                "p_down": inputs["p_down_bar"],
                "t_up": inputs["t_up_degc"],
                "eta_gas": inputs["eta_gas"],
                "eta_oil": inputs["eta_oil"],
                schema.TARGET: q_meas,
                schema.SOURCE: meters.source,
                "q_gas": q_meas * truth["q_gas"] / q_true,
                "q_oil": q_meas * truth["q_oil"] / q_true,
                "q_water": q_meas * truth["q_water"] / q_true,
            }
        )
        samples = {
            "q_true": q_true,
            "q_gas_true": truth["q_gas"],
            "q_oil_true": truth["q_oil"],
            "q_water_true": truth["q_water"],
            "c_d_true": c_d,
            "area_m2": truth["area"],
            "z_true": truth["z"],
            "p_cr_true": truth["p_cr"],
            "mpfm_factor": meters.mpfm_factor,
        }
        return _WellResult(
            rows=rows,
            samples=samples,
            truth=self._truth(meters.is_mpfm, is_test),
            q_without=self._rates_without_each_effect(inputs, c_d, meters),
            q_plain=_choke_truth(self.fluid, _Active(), inputs, self.fluid.c_d)["q"],
            years_since_start=meters.years,
            is_mpfm=meters.is_mpfm,
        )

    def _fluid_truth(self) -> dict[str, float]:
        """The well's true fluid and choke constants (densities kg/m3, m_gas kg/mol, kappa,
        p_cr and c_d dimensionless, a_max_m2 m2)."""
        f = self.fluid
        return {
            "rho_oil": f.rho_oil,
            "rho_wat": f.rho_wat,
            "kappa": f.kappa,
            "m_gas": f.m_gas,
            "p_cr": f.p_cr,
            "c_d": f.c_d,
            "a_max_m2": f.a_max_m2,
        }

    def _noise_truth(self) -> dict[str, float]:
        """The sizes of the meters' and sensors' noise (relative, bar, degC, absolute)."""
        d = self.draw
        return {
            "mpfm_rel": d["mpfm_noise_rel"],
            "mpfm_drift_per_sqrt_year": d["mpfm_drift_per_sqrt_year"],
            "well_test_rel": d["well_test_noise_rel"],
            "p_up_rel": d["p_up_noise_rel"],
            "p_down_bar": 0.15,
            "t_up_degc": 0.2,
            "gor_rel": 0.015,
            "water_cut_abs": 0.005,
        }

    def _truth(
        self,
        is_mpfm: np.ndarray,
        is_test: np.ndarray,
    ) -> dict[str, Any]:
        """The well's true parameters and history for the truth JSON (times in days)."""
        d = self.draw
        # The plateau ends where the operators' own setting (not a manual change) is fully open.
        full_open = self.t_decide[self.u_decide >= 1.0]
        out: dict[str, Any] = {
            "start_day": self.t0,
            "end_day": self.t1,
            **self._fluid_truth(),
            "bore_diameter_mm": d["bore_diameter_mm"],
            "valve_family": self.active.family,
            "z": "papay" if self.active.real_gas else 1.0,
            "slip": "simpson" if self.active.slip else "none",
            "critical_ratio": "sachdeva" if self.active.critical_ratio else "constant",
            "target_rate_sm3h": self.target,
            "initial_choke": float(_round_choke(np.array([d["initial_choke"]]))[0]),
            "plateau_end_day": float(full_open[0]) if len(full_open) else None,
            "reservoir": {
                "p_static0_bar": d["p_static0_bar"],
                "remaining_after_5y": d["remaining_after_5y"],
                "decline_per_year": self.decline_per_year,
                "drawdown_full_open": d["drawdown_full_open"],
            },
            "p_down_level_bar": self.p_down_level,
            "temperature": {
                key: d[key]
                for key in (
                    "t_up0_degc",
                    "t_per_water_cut_degc",
                    "t_per_rate_degc",
                    "t_season_degc",
                )
            },
            "fluids": {
                key: d[key]
                for key in (
                    "water_cut0",
                    "water_cut1",
                    "water_cut_mid_years",
                    "water_cut_width_years",
                    "eta_gas0",
                    "gor_pressure_exponent",
                )
            },
            "operations": {
                "operator_interval_days": d["operator_interval_days"],
                "choke_adjustments": len(self.t_decide),
                "manual_changes": len(self.deviations),
            },
            "noise": self._noise_truth(),
            "sampling": {
                "mpfm_interval_hours": d["mpfm_interval_hours"],
                "rows_mpfm": int(is_mpfm.sum()),
                "rows_well_test": int(is_test.sum()),
                "rows_without_rate": int((~is_mpfm & ~is_test).sum()),
            },
            "shut_ins_days": self.shut_ins.tolist(),
            "data_gaps_days": self.data_gaps.tolist(),
            "mpfm_outages_days": self.outages.tolist(),
        }
        if "erosion" in self.hidden:
            out["sand_event_day"] = self.sand_event
        if self.hidden.get("mpfm_bias", {}).get("onset") == "event":
            out["meter_event_day"] = self.meter_event
        return out


# --- the field ----------------------------------------------------------------------------


@dataclass
class SimulatedField:
    """A simulated field: observations, the noise-free truth per row, and the true parameters.

    ``observations`` follows :mod:`vfm_core.schema` (plus ``q_gas``/``q_oil``/``q_water``),
    sorted by (time, well). ``truth_samples`` has one row per observation row, in the same
    order, with the columns of :data:`TRUTH_SAMPLE_COLUMNS` (rates in Sm3/h, area in m2).
    ``truth`` is JSON-serialisable: the arguments, the hidden effects with their
    parameters, directions and measured sizes, and every well's true parameters.
    """

    observations: pd.DataFrame
    truth_samples: pd.DataFrame
    truth: dict[str, Any]

    def summary(self) -> str:
        """One line for people: rows, wells, years, rows per source and the hidden effects."""
        sources = self.observations[schema.SOURCE].replace("", "(no rate)").value_counts()
        per_source = ", ".join(f"{k}: {v:,}" for k, v in sources.items())
        hidden = ", ".join(self.truth["hidden"]) or "none"
        return (
            f"{len(self.observations):,} rows from {self.truth['n_wells']} wells over "
            f"{self.truth['years']:g} years ({per_source}); hidden effects: {hidden}."
        )


def _stratified(rng: np.random.Generator, n: int) -> np.ndarray:
    """``n`` uniform(0, 1) draws, one in each of n equal strata, in random order."""
    return rng.permutation((np.arange(n) + rng.uniform(0.0, 1.0, n)) / n)


def _field_layout(
    rng: np.random.Generator, wells: int, horizon_days: float
) -> tuple[np.ndarray, np.ndarray]:
    """Start day and MPFM sampling quantile of every well.

    About 40 % of the wells start with the field; the others start between 5 % and 58 % of
    the horizon (2016-01-01 .. late 2018 for five years, as in the paper). Both are spread
    over strata, so the field's row count varies little from seed to seed.
    """
    early = max(1, round(0.4 * wells))
    late = wells - early
    offsets = 0.05 + 0.53 * np.sort(_stratified(rng, late))
    starts = np.concatenate([np.zeros(early), offsets * horizon_days])
    return starts[rng.permutation(wells)], _stratified(rng, wells)


def _check_size(seed: int, wells: int, years: float) -> None:
    """Refuse a seed, well count or span outside what the simulator takes, with a sentence."""
    if isinstance(seed, bool) or int(seed) != seed or seed < 0:
        raise ConfigError(f"seed must be a whole number of at least 0, not {seed!r}.")
    if int(wells) != wells or wells < 1:
        raise ConfigError(f"wells must be a whole number of at least 1, not {wells!r}.")
    if not (math.isfinite(years) and 1.0 / 12.0 <= years <= 50.0):
        raise ConfigError(f"years must lie between 1/12 and 50, not {years!r}.")


def _check_options(
    effects: Mapping[str, Any], families: Sequence[str], gas_lift: float | Any
) -> None:
    """Refuse valve families beside the hidden ``valve`` effect, and a gas-lift share
    outside 0..1, with a sentence."""
    if families and "valve" in effects:
        raise ConfigError(
            "Give the valve characteristic either per well (valves) or as the hidden effect "
            "'valve' for every well, not both."
        )
    if not (isinstance(gas_lift, int | float) and math.isfinite(gas_lift) and 0 <= gas_lift <= 1):
        raise ConfigError(
            f"gas_lift is the share of wells on gas lift; give a number in 0..1, not {gas_lift!r}."
        )


def _field_span(start: str, years: float) -> tuple[pd.Timestamp, pd.Timestamp, float]:
    """``(t_origin, t_end, horizon_days)`` of a field that starts on ``start`` and runs for
    ``years`` years (whole years end on the same calendar day)."""
    try:
        t_origin = utc_timestamp(start)
    except ValueError:
        raise ConfigError(f"start '{start}' is not a date; give e.g. 2016-01-01.") from None
    # Whole years end on the same calendar day (2016-01-01 + 5 years = 2021-01-01).
    whole = int(years)
    t_end = t_origin + pd.DateOffset(years=whole)
    t_end += pd.Timedelta(days=(years - whole) * DAYS_PER_YEAR)
    return t_origin, t_end, (t_end - t_origin) / pd.Timedelta(days=1)


def _day_to_iso(t_origin: pd.Timestamp) -> Callable[[float], str]:
    """What turns days since ``t_origin`` into an ISO 8601 time (UTC, whole seconds)."""

    def iso(day: float) -> str:
        return (t_origin + pd.Timedelta(seconds=round(day * 86400.0))).isoformat()

    return iso


def _field_frames(
    results: Sequence[_WellResult], t_origin: pd.Timestamp
) -> tuple[pd.DataFrame, pd.DataFrame, np.ndarray]:
    """``(observations, truth_samples, order)``: the wells' rows sorted by (time, well),
    keeping each well's own order on ties (MPFM before well test); ``order`` the rows'
    places in the wells' rows one after the other."""
    rows = pd.concat([r.rows for r in results], ignore_index=True)
    samples = pd.DataFrame(
        {k: np.concatenate([r.samples[k] for r in results]) for k in TRUTH_SAMPLE_COLUMNS[2:]}
    )
    well_codes = np.concatenate([np.full(len(r.rows), j) for j, r in enumerate(results)])
    # Sort by (time, well), keeping the per-well order (MPFM before well test) on ties.
    order = np.lexsort((np.arange(len(rows)), well_codes, rows["t_days"].to_numpy()))
    rows = rows.iloc[order].reset_index(drop=True)
    samples = samples.iloc[order].reset_index(drop=True)
    seconds = np.round(rows.pop("t_days").to_numpy() * 86400.0).astype(np.int64)
    time = pd.Series(t_origin + pd.to_timedelta(seconds, unit="s")).dt.as_unit("ns")
    observations = pd.concat([time.rename(schema.TIME), rows], axis=1)
    samples.insert(0, schema.WELL, observations[schema.WELL].to_numpy())
    samples.insert(0, schema.TIME, time)
    return observations, samples, order


def _wells_truth(
    names: Sequence[str], results: Sequence[_WellResult], iso: Callable[[float], str]
) -> dict[str, Any]:
    """Every well's truth JSON with its days turned into times by ``iso``."""
    per_well: dict[str, Any] = {}
    for name, r in zip(names, results, strict=True):
        info = dict(r.truth)
        info["start"] = iso(info.pop("start_day"))
        info["end"] = iso(info.pop("end_day"))
        for key in ("shut_ins_days", "data_gaps_days", "mpfm_outages_days"):
            info[key.removesuffix("_days")] = [[iso(a), iso(b)] for a, b in info.pop(key)]
        for key in ("sand_event", "meter_event"):
            if f"{key}_day" in info:
                info[key] = iso(info.pop(f"{key}_day"))
        end_day = info.pop("plateau_end_day")
        info["plateau_end"] = iso(end_day) if end_day is not None else None
        per_well[name] = info
    return per_well


def simulate_field(
    *,
    wells: int = 10,
    years: float = 5.0,
    seed: int = 0,
    hidden: Mapping[str, Mapping[str, Any]] | Sequence[str] = (),
    start: str = "2016-01-01",
    progress: bool = False,
    physics: str = sim_physics.DEFAULT_PHYSICS,
    valves: Sequence[str] | str = (),
    gas_lift: float = 0.0,
    sample_every_days: float | None = None,
) -> SimulatedField:
    """Simulate ``wells`` wells from ``start`` for ``years`` years (see the module docstring).

    ``hidden`` names the hidden effects, as CLI strings (``["erosion:rate=0.06", "slip"]``,
    see :func:`parse_hidden`) or as ``{name: {parameter: value}}`` (missing parameters take
    their defaults). ``physics`` names the truth (:data:`sim_physics.TRUTH_PHYSICS`);
    ``valves`` gives the wells' valve characteristics in turn (see :func:`parse_valves`);
    ``gas_lift`` is the share (0..1) of wells on gas lift. ``sample_every_days`` puts every
    well's sensor rows on one synchronised grid (that many days apart, at 06:00 UTC) instead
    of the MPFM's own times (see :mod:`vfm_core.separator_sim`). The same arguments give
    identical frames; the defaults give the same frames as before these options existed.
    """
    _check_size(seed, wells, years)
    effects = _resolve_hidden(hidden)
    spec = sim_physics.physics_spec(physics)
    _check_physics_effects(spec.name, effects)
    families = parse_valves(valves)
    _check_options(effects, families, gas_lift)
    t_origin, t_end, horizon = _field_span(start, years)
    field_rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(0,)))
    starts, sampling = _field_layout(field_rng, int(wells), horizon)
    width = max(2, len(str(int(wells))))
    names = [f"W{j + 1:0{width}d}" for j in range(int(wells))]

    lifted = _lifted_wells(seed, int(wells), float(gas_lift))
    well_objects: list[_Well] = []
    results: list[_WellResult] = []
    for j in tqdm(range(int(wells)), desc="simulating wells", disable=not progress):
        well = _Well(
            names[j],
            j,
            seed,
            float(starts[j]),
            horizon,
            effects,
            float(sampling[j]),
            physics_name=spec.name,
            valve_family=families[j % len(families)] if families else None,
            gas_lift=bool(lifted[j]),
            sample_every_days=sample_every_days,
        )
        results.append(well.run())
        well_objects.append(well)

    observations, samples, order = _field_frames(results, t_origin)
    iso = _day_to_iso(t_origin)
    hidden_truth, combined = _measured_sizes(effects, results, order, samples)
    truth: dict[str, Any] = {
        "format": "vfm-simulated-field/1",
        "seed": int(seed),
        "n_wells": int(wells),
        "years": float(years),
        "start": t_origin.isoformat(),
        "end": t_end.isoformat(),
        "rows": int(len(observations)),
        "rows_per_source": {
            (k or "none"): int(v)
            for k, v in observations[schema.SOURCE].value_counts().sort_index().items()
        },
        "hidden": hidden_truth,
        "truth_versus_plain_model": combined,
        "wells": _wells_truth(names, results, iso),
        "ranges": {key: list(value) for key, value in _RANGES.items()},
        "physics": _physics_truth(spec, families, float(gas_lift), names, well_objects, iso),
    }
    return SimulatedField(observations=observations, truth_samples=samples, truth=_jsonable(truth))


def parse_valves(valves: Sequence[str] | str) -> list[str]:
    """Valve characteristics given to the wells in turn (W01 the first, W02 the second...).

    Names of :data:`vfm_core.physics.AREA_FUNCTIONS`, comma-separated or as a list;
    ``mixed`` stands for all of them in their registry order. Empty: every well's valve
    is linear (or the ``valve`` hidden effect's family). An unknown name raises
    ConfigError listing the valid ones.
    """
    items = [valves] if isinstance(valves, str) else list(valves)
    out: list[str] = []
    for item in items:
        for name in str(item).split(","):
            name = name.strip()
            if not name:
                continue
            if name == "mixed":
                out.extend(physics.AREA_FUNCTIONS)
            elif name in physics.AREA_FUNCTIONS:
                out.append(name)
            else:
                raise ConfigError(
                    f"Unknown valve characteristic '{name}'; choose from "
                    f"{', '.join(physics.AREA_FUNCTIONS)}, or mixed (all of them in turn)."
                )
    return out


#: Hidden effects that change the Sachdeva truth only (the other physics have their own gas
#: law, slip and critical ratio built in).
_SACHDEVA_ONLY_EFFECTS = ("real_gas", "slip", "critical_ratio")


def _check_physics_effects(name: str, effects: Mapping[str, Any]) -> None:
    if name == sim_physics.DEFAULT_PHYSICS:
        return
    clash = [e for e in effects if e in _SACHDEVA_ONLY_EFFECTS]
    if clash:
        raise ConfigError(
            f"The hidden effect(s) {', '.join(clash)} change the Sachdeva truth only; the "
            f"'{name}' physics has its own gas law, slip and critical ratio. Use them with "
            f"--physics sachdeva, or choose from erosion, valve, mpfm_bias with '{name}'."
        )


def _lifted_wells(seed: int, wells: int, share: float) -> np.ndarray:
    """Which wells are on gas lift: round(share * wells) of them (at least one for a
    positive share), chosen from a field stream of their own."""
    lifted = np.zeros(wells, dtype=bool)
    if share <= 0.0:
        return lifted
    count = min(wells, max(1, round(share * wells)))
    rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(2,)))
    lifted[rng.permutation(wells)[:count]] = True
    return lifted


def _physics_truth(
    spec: sim_physics.PhysicsSpec,
    families: Sequence[str],
    gas_lift: float,
    names: Sequence[str],
    wells: Sequence[_Well],
    iso: Any,
) -> dict[str, Any]:
    """The truth JSON's ``physics`` block: which truth, its references and the well options."""
    out: dict[str, Any] = {
        "name": spec.name,
        "description": spec.description,
        "references": list(spec.references),
        "critical_ratio": spec.critical_ratio,
        "valves": {n: w.active.family for n, w in zip(names, wells, strict=True)},
        "valves_given": list(families),
        "gas_lift_share": gas_lift,
        "gas_lift": {},
    }
    if spec.name == "gilbert":
        out["gilbert_correlation"] = {
            n: sim_physics.gilbert_correlation(w.fluid.well_index).name
            for n, w in zip(names, wells, strict=True)
        }
    for n, w in zip(names, wells, strict=True):
        if w.lift is not None:
            lift = dict(w.lift)
            lift["start"] = iso(lift.pop("start_day"))
            lift["changes"] = [[iso(t), f] for t, f in lift["changes"]]
            out["gas_lift"][n] = lift
    return out


def _measured_sizes(
    effects: Mapping[str, Mapping[str, ParamValue]],
    results: Sequence[_WellResult],
    order: np.ndarray,
    samples: pd.DataFrame,
) -> tuple[dict[str, Any], dict[str, Any]]:
    """Each effect's parameters, direction and measured size; and the truth versus the
    plain mechanistic model. ``order`` maps the wells' concatenated rows to ``samples``."""
    years_since = np.concatenate([r.years_since_start for r in results])[order]
    is_mpfm = np.concatenate([r.is_mpfm for r in results])[order]
    wells_sorted = np.concatenate([np.full(len(r.rows), j) for j, r in enumerate(results)])[order]
    q_true = samples["q_true"].to_numpy()
    hidden_truth: dict[str, Any] = {}
    for effect, params in effects.items():
        spec = HIDDEN_EFFECTS[effect]
        without = np.concatenate([r.q_without[effect] for r in results])[order]
        if effect == "mpfm_bias":
            ratio = samples["mpfm_factor"].to_numpy()[is_mpfm] / without[is_mpfm]
            size = _size(ratio, years_since[is_mpfm], wells_sorted[is_mpfm])
            size["basis"] = "mpfm_factor with / without the bias, on MPFM rows"
        else:
            size = _size(q_true / without, years_since, wells_sorted)
            size["basis"] = "q_true with / without the effect, same rows and inputs"
        if effect == "erosion":
            c_d0 = np.array([results[w].truth["c_d"] for w in wells_sorted])
            growth = samples["c_d_true"].to_numpy() / c_d0 - 1.0
            size["c_d_change_per_year"] = _mean_slope(years_since, growth, wells_sorted)
            size["c_d_max_rel_change"] = float(growth.max()) if len(growth) else 0.0
        hidden_truth[effect] = {
            "params": dict(params),
            "description": spec.description,
            "direction": spec.direction,
            "size": size,
        }
    q_plain = np.concatenate([r.q_plain for r in results])[order]
    combined = _size(q_true / q_plain, years_since, wells_sorted)
    combined["basis"] = "q_true versus the plain mechanistic model with the wells' parameters"
    return hidden_truth, combined


def _mean_slope(years: np.ndarray, values: np.ndarray, wells: np.ndarray) -> float:
    slopes = [
        _slope_per_year(years[wells == w], values[wells == w])
        for w in np.unique(wells)
        if np.sum(wells == w) > 2 and np.ptp(years[wells == w]) > 0.1
    ]
    return float(np.mean(slopes)) if slopes else 0.0


def _size(ratio: np.ndarray, years: np.ndarray, wells: np.ndarray) -> dict[str, Any]:
    """Measured size of an effect from ``ratio`` = with / without, per row."""
    change = ratio - 1.0
    if len(change) == 0:
        return {"rows": 0}
    return {
        "rows": int(len(change)),
        "mean_abs_rel_change": float(np.mean(np.abs(change))),
        "max_abs_rel_change": float(np.max(np.abs(change))),
        "mean_rel_change": float(np.mean(change)),
        "fraction_up": float(np.mean(change > 0)),
        "rel_change_per_year": _mean_slope(years, change, wells),
    }


def _jsonable(value: Any) -> Any:
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


# --- files --------------------------------------------------------------------------------


def _is_csv(out: Path) -> bool:
    return out.name.lower().endswith((".csv", ".csv.gz"))


def truth_paths(out: str | os.PathLike[str]) -> tuple[Path, Path]:
    """Where the truth of an observation file ``out`` lives: ``(<stem>.truth.json,
    <stem>.truth.parquet)``, or ``<stem>.truth.csv`` when ``out`` is CSV."""
    path = Path(out)
    name = path.name
    for suffix in (".csv.gz", ".csv", ".parquet", ".pq"):
        if name.lower().endswith(suffix):
            name = name[: -len(suffix)]
            break
    else:
        name = path.stem
    samples_suffix = ".truth.csv" if _is_csv(path) else ".truth.parquet"
    return path.with_name(name + ".truth.json"), path.with_name(name + samples_suffix)


def write_field(field: SimulatedField, out: str | os.PathLike[str]) -> list[Path]:
    """Write the observations to ``out`` (CSV or Parquet by suffix) and the truth beside it.

    Returns ``[observations, <stem>.truth.json, <stem>.truth.parquet|.csv]``. Each file is
    written atomically.
    """
    from vfm_core.observations import save_observations

    path = Path(out)
    json_path, samples_path = truth_paths(path)
    written = [save_observations(field.observations, path)]

    def write_json(temp: Path) -> None:
        temp.write_text(json.dumps(field.truth, indent=2, allow_nan=False) + "\n", encoding="utf-8")

    def write_samples(temp: Path) -> None:
        samples = field.truth_samples
        if _is_csv(path):
            text = samples.copy()
            text[schema.TIME] = samples[schema.TIME].dt.strftime("%Y-%m-%dT%H:%M:%SZ")
            text.to_csv(temp, index=False, lineterminator="\n")
        else:
            samples.to_parquet(temp, index=False)

    write_with(json_path, write_json)
    write_with(samples_path, write_samples)
    return [*written, json_path, samples_path]


def load_truth(out: str | os.PathLike[str]) -> tuple[dict[str, Any], pd.DataFrame]:
    """Read back the truth written by :func:`write_field` for the observation file ``out``."""
    json_path, samples_path = truth_paths(out)
    for p in (json_path, samples_path):
        if not p.exists():
            raise ConfigError(
                f"The truth file {p} does not exist; it is written by write_field next to "
                f"the observations (simulate a field first)."
            )
    truth = json.loads(json_path.read_text(encoding="utf-8"))
    if samples_path.name.endswith(".csv"):
        samples = pd.read_csv(samples_path, dtype={schema.WELL: str})
    else:
        samples = pd.read_parquet(samples_path)
    samples[schema.TIME] = pd.to_datetime(samples[schema.TIME], utc=True).dt.as_unit("ns")
    return truth, samples
