"""Truth physics for the simulator that is not the project's Sachdeva model.

Every accuracy figure of the learners was first measured on fields whose truth is the same
Sachdeva choke model that ``mm`` and the hybrids carry inside (:mod:`vfm_core.physics`).
This module gives :func:`vfm_core.simulate.simulate_field` other truths, written from the
literature and sharing no code with :mod:`vfm_core.physics`, so that a learner can be
judged on physics it was not built for (``vfm simulate --physics NAME``):

``sachdeva``
    The default: :mod:`vfm_core.physics` (not here; listed so the registry is complete).

``bernoulli``
    An incompressible orifice (Bernoulli) equation for the two-phase mixture with the
    two-phase multiplier of Simpson, Rooney and Gratton (1983), a fixed critical pressure
    ratio, and a real gas (Hall and Yarborough 1973/1974, pseudo-critical properties of
    Standing 1977). Oil and water are incompressible. See :func:`bernoulli_mass_flow`.

``gilbert``
    The empirical critical-flow correlations of Gilbert (1954), Ros (1960), Baxendell
    (1958) and Achong (1961), ``p_up = A R^B q_L / S^C`` in field units, one set of
    coefficients per well in turn, with a smooth sub-critical reduction above the critical
    ratio. See :func:`gilbert_liquid_rate`.

Everything here works in SI units on float64 numpy arrays: pressures in Pa (absolute),
temperatures in K, densities in kg/m3, areas in m2, mass flows in kg/s, standard volumes in
Sm3 (101325 Pa, 288.15 K). The field units of the empirical correlations are converted at
their boundary only.

References
----------
- H. C. Simpson, D. H. Rooney, E. Gratton (1983): Two-phase flow through gate valves and
  orifice plates. Int. Conf. Physical Modelling of Multiphase Flow, Coventry, BHRA.
  Slip ratio S = (rho_L/rho_G)^(1/6) and the orifice two-phase multiplier
  Phi = [1 + x (S - 1)] [1 + x (S^5 - 1)].
- D. Chisholm (1967): Pressure gradients during the flow of incompressible two-phase
  mixtures through pipes, venturis and orifice plates. Brit. Chem. Eng. 12, 454-457 (the
  separated-flow momentum form [1 + x (S - 1)] [1 + x (rho_L/(S rho_G) - 1)] of which
  Simpson's multiplier is the case S = (rho_L/rho_G)^(1/6)).
- K. R. Hall, L. Yarborough (1973): A new equation of state for Z-factor calculations.
  Oil & Gas J. 71(25), 82-92; (1974) How to solve equation of state for Z-factors.
  Oil & Gas J. 72(7), 86-88.
- M. B. Standing (1977): Volumetric and Phase Behavior of Oil Field Hydrocarbon Systems,
  SPE, Dallas (pseudo-critical temperature and pressure of natural gas from its gravity).
- W. E. Gilbert (1954): Flowing and gas-lift well performance. API Drilling and Production
  Practice, 126-157. N. C. J. Ros (1960): An analysis of critical simultaneous gas/liquid
  flow through a restriction and its application to flowmetering. Appl. Sci. Res. 9,
  374-388. P. B. Baxendell (1958): Producing wells on casing flow - an analysis of flowing
  pressure gradients. Trans. AIME 213, 202-206. I. Achong (1961): Revised bean performance
  formula for Lake Maracaibo wells. Shell internal report. Coefficients as tabulated in
  J. P. Brill, H. Mukherjee (1999): Multiphase Flow in Wells, SPE Monograph 17, ch. 5.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from vfm_core.errors import ConfigError

__all__ = [
    "PhysicsSpec",
    "TRUTH_PHYSICS",
    "DEFAULT_PHYSICS",
    "physics_spec",
    "GilbertCoefficients",
    "GILBERT_CORRELATIONS",
    "WellConstants",
    "ChokeRates",
    "pseudo_critical_standing",
    "z_factor_hall_yarborough",
    "simpson_multiplier",
    "bernoulli_mass_flow",
    "gilbert_liquid_rate",
    "subcritical_factor",
    "choke_rates",
]

#: Universal gas constant, J/(mol K).
R_GAS = 8.314462618
#: Standard conditions of the target rates: 101325 Pa and 288.15 K (15 degC).
P_SC_PA = 101325.0
T_SC_K = 288.15
#: Molar mass of dry air, kg/mol (gas specific gravity = M_gas / M_AIR).
M_AIR = 0.0289647

_PA_PER_PSI = 6894.757293168
_M_PER_INCH = 0.0254
_M3_PER_BBL = 0.158987294928
#: scf/STB per Sm3/Sm3 (35.3147 ft3 per m3 over 6.28981 bbl per m3).
_SCF_PER_STB_PER_SM3_PER_SM3 = (1.0 / 0.3048**3) * _M3_PER_BBL
_SECONDS_PER_DAY = 86400.0


# --- the registry -------------------------------------------------------------------------


@dataclass(frozen=True)
class PhysicsSpec:
    """One truth physics of the simulator: its name, what it is, and where it comes from."""

    name: str
    description: str
    references: tuple[str, ...]
    critical_ratio: str


DEFAULT_PHYSICS = "sachdeva"

#: The simulator's truth physics by name (``vfm simulate --physics NAME``).
TRUTH_PHYSICS: dict[str, PhysicsSpec] = {
    spec.name: spec
    for spec in (
        PhysicsSpec(
            "sachdeva",
            "Sachdeva et al. (1986) homogeneous two-phase choke model with isentropic gas "
            "expansion, ideal gas (vfm_core.physics, the model mm carries).",
            ("Sachdeva, Schmidt, Brill, Blais (1986), SPE 15657",),
            "the well's constant p_cr (0.5-0.6), or Sachdeva's solved ratio with the "
            "critical_ratio hidden effect",
        ),
        PhysicsSpec(
            "bernoulli",
            "Bernoulli orifice equation for the two-phase mixture, mdot = C_D A(u) "
            "sqrt(2 rho_L dp / Phi), with Simpson's two-phase multiplier Phi, dp = p_up (1 - "
            "max(p_down/p_up, p_cr)), real gas by Hall-Yarborough (Standing's "
            "pseudo-critical properties), incompressible oil and water.",
            (
                "Simpson, Rooney, Gratton (1983), two-phase flow through gate valves and "
                "orifice plates",
                "Chisholm (1967), Brit. Chem. Eng. 12, 454-457",
                "Hall, Yarborough (1973, 1974), Oil & Gas J.",
                "Standing (1977), Volumetric and Phase Behavior of Oil Field Hydrocarbon Systems",
            ),
            "the well's constant p_cr (0.5-0.6): flow is choked (flat in p_down) below it",
        ),
        PhysicsSpec(
            "gilbert",
            "Empirical critical-flow bean correlations p_up = A R^B q_L / S^C (Gilbert, Ros, "
            "Baxendell, Achong; one per well in turn), liquid rate q_L from the upstream "
            "pressure, the gas-liquid ratio R and the bean size S, with an elliptic "
            "sub-critical reduction above p_down/p_up = 0.588.",
            (
                "Gilbert (1954), API Drilling and Production Practice, 126-157",
                "Ros (1960), Appl. Sci. Res. 9, 374-388",
                "Baxendell (1958), Trans. AIME 213, 202-206",
                "Achong (1961), Shell report",
                "Brill, Mukherjee (1999), Multiphase Flow in Wells, SPE Monograph 17",
            ),
            "0.588 (Gilbert's condition p_up >= 1.7 p_down) for every well",
        ),
    )
}


def physics_spec(name: str) -> PhysicsSpec:
    """The :class:`PhysicsSpec` called ``name``; an unknown name raises ConfigError."""
    try:
        return TRUTH_PHYSICS[str(name)]
    except KeyError:
        raise ConfigError(
            f"Unknown simulator physics '{name}'; choose one of {', '.join(TRUTH_PHYSICS)}."
        ) from None


# --- gas: real-gas density ---------------------------------------------------------------


def pseudo_critical_standing(m_gas: float) -> tuple[float, float]:
    """Pseudo-critical temperature (K) and pressure (Pa) of a natural gas of molar mass
    ``m_gas`` (kg/mol), by Standing's (1977) correlation for natural gas systems:
    T_pc = 168 + 325 g - 12.5 g^2 (degR), p_pc = 677 + 15 g - 37.5 g^2 (psia), with the
    gas specific gravity g = M_gas / M_air."""
    gravity = m_gas / M_AIR
    t_pc_rankine = 168.0 + 325.0 * gravity - 12.5 * gravity**2
    p_pc_psia = 677.0 + 15.0 * gravity - 37.5 * gravity**2
    return t_pc_rankine * 5.0 / 9.0, p_pc_psia * _PA_PER_PSI


def _hall_yarborough_residual(
    y: np.ndarray, a_ppr: np.ndarray, t: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """F(y) of Hall and Yarborough's equation and dF/dy (y: reduced density, t = 1/T_pr)."""
    c2 = 14.76 * t - 9.76 * t**2 + 4.58 * t**3
    c3 = 90.7 * t - 242.2 * t**2 + 42.4 * t**3
    e = 2.18 + 2.82 * t
    one = 1.0 - y
    f = -a_ppr + (y + y**2 + y**3 - y**4) / one**3 - c2 * y**2 + c3 * y**e
    df = (
        (1.0 + 4.0 * y + 4.0 * y**2 - 4.0 * y**3 + y**4) / one**4
        - 2.0 * c2 * y
        + e * c3 * y ** (e - 1.0)
    )
    return f, df


def z_factor_hall_yarborough(
    p_pa: np.ndarray | float, t_k: np.ndarray | float, m_gas: float
) -> np.ndarray:
    """Gas compressibility factor Z(p, T) by Hall and Yarborough (1973), dimensionless.

    With t = T_pc / T and the pseudo-reduced pressure p_pr = p / p_pc (Standing's
    pseudo-critical properties, :func:`pseudo_critical_standing`), the reduced density y
    solves F(y) = -A p_pr + (y + y^2 + y^3 - y^4)/(1 - y)^3 - (14.76 t - 9.76 t^2 +
    4.58 t^3) y^2 + (90.7 t - 242.2 t^2 + 42.4 t^3) y^(2.18 + 2.82 t) = 0 with
    A = 0.06125 t exp(-1.2 (1 - t)^2), and Z = A p_pr / y. Solved by Newton's method from
    y = A p_pr (Z = 1), as Hall and Yarborough (1974) recommend, kept inside (0, 1).
    A fit to the Standing-Katz chart, valid for 1.2 <= T_pr <= 3 and p_pr <= 20 (wellhead
    conditions are T_pr 1.4-1.8, p_pr below 5).
    """
    t_pc, p_pc = pseudo_critical_standing(m_gas)
    p_pr = np.asarray(p_pa, dtype=np.float64) / p_pc
    t = t_pc / np.asarray(t_k, dtype=np.float64)
    a_ppr = 0.06125 * t * np.exp(-1.2 * (1.0 - t) ** 2) * p_pr
    a_ppr, t = np.broadcast_arrays(a_ppr, t)
    y = np.clip(a_ppr, 1e-12, 0.5)
    for _ in range(50):
        f, df = _hall_yarborough_residual(y, a_ppr, t)
        step = f / df
        y = np.clip(y - step, 1e-12, 0.95)
        if np.all(np.abs(step) <= 1e-13 * np.maximum(y, 1e-12)):
            break
    return np.where(a_ppr > 0.0, a_ppr / y, 1.0)


def _gas_density(p_pa: np.ndarray, t_k: np.ndarray, m_gas: float, z: np.ndarray) -> np.ndarray:
    """Real-gas density rho_G = p M / (Z R T), kg/m3."""
    return p_pa * m_gas / (z * R_GAS * t_k)


def _gas_density_standard(m_gas: float) -> float:
    """Gas density at standard conditions (ideal gas there), kg/Sm3."""
    return P_SC_PA * m_gas / (R_GAS * T_SC_K)


# --- liquids ------------------------------------------------------------------------------


def _liquid_density(
    eta_gas: np.ndarray, eta_oil: np.ndarray, rho_oil: float, rho_wat: float
) -> np.ndarray:
    """Density of the incompressible oil-water liquid, kg/m3, from the mass fractions
    (rho_oil where there is no liquid: it then cancels out of every rate)."""
    eta_wat = np.clip(1.0 - eta_gas - eta_oil, 0.0, 1.0)
    volume = eta_oil / rho_oil + eta_wat / rho_wat  # m3 of liquid per kg of mixture
    has_liquid = volume > 1e-15
    return np.where(has_liquid, (1.0 - eta_gas) / np.where(has_liquid, volume, 1.0), rho_oil)


# --- bernoulli ---------------------------------------------------------------------------


def simpson_multiplier(
    x: np.ndarray | float, rho_liquid: np.ndarray | float, rho_gas: np.ndarray | float
) -> np.ndarray:
    """Simpson's (1983) orifice two-phase multiplier Phi = dp_TP / dp_LO, dimensionless.

    Phi = [1 + x (S - 1)] [1 + x (S^5 - 1)] with the slip ratio S = (rho_L / rho_G)^(1/6)
    and ``x`` the gas mass fraction: the pressure drop of the mixture over that of the same
    mass flux as all liquid. It is 1 for x = 0 and rho_L / rho_G for x = 1 (all gas).
    """
    s = (np.asarray(rho_liquid, dtype=np.float64) / np.asarray(rho_gas, dtype=np.float64)) ** (
        1.0 / 6.0
    )
    x = np.asarray(x, dtype=np.float64)
    return (1.0 + x * (s - 1.0)) * (1.0 + x * (s**5 - 1.0))


def bernoulli_mass_flow(
    area_eff_m2: np.ndarray | float,
    p_up_pa: np.ndarray | float,
    p_down_pa: np.ndarray | float,
    t_up_k: np.ndarray | float,
    eta_gas: np.ndarray | float,
    eta_oil: np.ndarray | float,
    *,
    rho_oil: float,
    rho_wat: float,
    m_gas: float,
    p_cr: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Mass flow (kg/s) through a choke by Bernoulli's equation with Simpson's multiplier,
    and the gas Z-factor used.

    mdot = C_D A(u) sqrt(2 rho_L dp / Phi), with ``area_eff_m2`` = C_D A(u) (m2);
    dp = p_up (1 - max(p_down/p_up, p_cr)) (Pa): below the critical ratio ``p_cr`` the
    flow is choked and no longer depends on p_down; rho_L the incompressible liquid
    density from the mass fractions; Phi = :func:`simpson_multiplier` at the upstream gas
    density rho_G = p_up M / (Z R T_up) with Z by Hall-Yarborough
    (:func:`z_factor_hall_yarborough`). No gas expansion through the throat (the
    incompressible orifice equation applied to the mixture at upstream density).
    """
    p1 = np.asarray(p_up_pa, dtype=np.float64)
    p2 = np.asarray(p_down_pa, dtype=np.float64)
    t1 = np.asarray(t_up_k, dtype=np.float64)
    x = np.asarray(eta_gas, dtype=np.float64)
    z = z_factor_hall_yarborough(p1, t1, m_gas)
    rho_g = _gas_density(p1, t1, m_gas, z)
    rho_l = _liquid_density(x, np.asarray(eta_oil, dtype=np.float64), rho_oil, rho_wat)
    ratio = np.clip(p2 / p1, p_cr, 1.0)
    dp = p1 * (1.0 - ratio)
    phi = simpson_multiplier(x, rho_l, rho_g)
    mdot = np.asarray(area_eff_m2, dtype=np.float64) * np.sqrt(2.0 * rho_l * dp / phi)
    return mdot, z


# --- gilbert-type correlations ----------------------------------------------------------


@dataclass(frozen=True)
class GilbertCoefficients:
    """p_up (psig) = a R^b q_L / S^c with R in scf/STB, q_L in STB/d, S in 1/64 inch."""

    name: str
    a: float
    b: float
    c: float


#: The four classic bean correlations (Brill and Mukherjee 1999, table 5.1, R in scf/STB).
GILBERT_CORRELATIONS: tuple[GilbertCoefficients, ...] = (
    GilbertCoefficients("gilbert", 10.0, 0.546, 1.89),
    GilbertCoefficients("ros", 17.40, 0.500, 2.00),
    GilbertCoefficients("baxendell", 9.56, 0.546, 1.93),
    GilbertCoefficients("achong", 3.82, 0.650, 1.88),
)

#: Gilbert's condition for critical flow: p_up >= 1.7 p_down, i.e. p_down/p_up <= 0.588.
GILBERT_CRITICAL_RATIO = 1.0 / 1.7

#: Lowest gas-liquid ratio the correlations are used at, Sm3/Sm3 (R^b -> 0 would make the
#: rate unbounded; the correlations were fitted to gassy wells, R of hundreds of scf/STB).
_GLR_MIN = 1.0


def subcritical_factor(ratio: np.ndarray | float, critical: float) -> np.ndarray:
    """Share of the critical rate that flows at the pressure ratio p_down/p_up, 0..1.

    1 at and below ``critical`` (choked flow), sqrt(1 - ((r - r_c)/(1 - r_c))^2) above it:
    an ellipse that joins the critical rate with zero slope and reaches 0 at r = 1. Not from
    a reference: a smooth, monotone assumption, since Gilbert-type correlations hold for
    critical flow only.
    """
    r = np.clip(np.asarray(ratio, dtype=np.float64), critical, 1.0)
    excess = (r - critical) / (1.0 - critical)
    return np.sqrt(np.clip(1.0 - excess**2, 0.0, 1.0))


def gilbert_liquid_rate(
    p_up_pa: np.ndarray | float,
    p_down_pa: np.ndarray | float,
    bean_m: np.ndarray | float,
    glr_sm3_sm3: np.ndarray | float,
    coefficients: GilbertCoefficients = GILBERT_CORRELATIONS[0],
) -> np.ndarray:
    """Liquid rate at standard conditions, Sm3/s, of a Gilbert-type bean correlation.

    q_L = (p_up - p_atm) S^c / (a R^b) in field units (psig, 1/64 inch, scf/STB, STB/d),
    converted from and to SI here, times :func:`subcritical_factor` of p_down/p_up with the
    critical ratio 0.588. ``bean_m`` is the bean (choke) diameter in m, ``glr_sm3_sm3`` the
    gas-liquid ratio at standard conditions (Sm3 gas per Sm3 liquid).
    """
    p1 = np.asarray(p_up_pa, dtype=np.float64)
    p2 = np.asarray(p_down_pa, dtype=np.float64)
    p_psig = np.maximum(p1 - P_SC_PA, 0.0) / _PA_PER_PSI
    bean_64ths = np.asarray(bean_m, dtype=np.float64) / _M_PER_INCH * 64.0
    glr = np.maximum(np.asarray(glr_sm3_sm3, dtype=np.float64), _GLR_MIN)
    r_scf_stb = glr * _SCF_PER_STB_PER_SM3_PER_SM3
    co = coefficients
    q_stb_d = p_psig * bean_64ths**co.c / (co.a * r_scf_stb**co.b)
    q_sm3_s = q_stb_d * _M3_PER_BBL / _SECONDS_PER_DAY
    return q_sm3_s * subcritical_factor(p2 / p1, GILBERT_CRITICAL_RATIO)


# --- one entry point for the simulator -------------------------------------------------


@dataclass(frozen=True)
class WellConstants:
    """What a truth physics needs to know of one well (SI units).

    ``c_d`` is the well's nominal discharge coefficient (the effective area the simulator
    passes in is C_D A(u), erosion included); ``well_index`` picks the Gilbert-type
    correlation (in turn over :data:`GILBERT_CORRELATIONS`).
    """

    rho_oil: float  # kg/m3
    rho_wat: float  # kg/m3
    m_gas: float  # kg/mol
    p_cr: float  # -
    c_d: float  # -
    well_index: int = 0


@dataclass(frozen=True)
class ChokeRates:
    """Noise-free rates at standard conditions (Sm3/s) and the Z and critical ratio used."""

    q_gas: np.ndarray
    q_oil: np.ndarray
    q_wat: np.ndarray
    z: np.ndarray
    p_cr: np.ndarray

    @property
    def q_total(self) -> np.ndarray:
        return self.q_gas + self.q_oil + self.q_wat


def _phases_from_mass(
    mdot: np.ndarray, eta_gas: np.ndarray, eta_oil: np.ndarray, well: WellConstants
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    eta_wat = np.clip(1.0 - eta_gas - eta_oil, 0.0, 1.0)
    return (
        mdot * eta_gas / _gas_density_standard(well.m_gas),
        mdot * eta_oil / well.rho_oil,
        mdot * eta_wat / well.rho_wat,
    )


def gilbert_correlation(well_index: int) -> GilbertCoefficients:
    """The Gilbert-type correlation of the well with 0-based index ``well_index``."""
    return GILBERT_CORRELATIONS[well_index % len(GILBERT_CORRELATIONS)]


def choke_rates(
    name: str,
    well: WellConstants,
    inputs: Mapping[str, np.ndarray],
) -> ChokeRates:
    """Phase rates (Sm3/s) of the truth physics ``name`` (not ``sachdeva``) for a batch.

    ``inputs`` (SI): ``area_eff_m2`` (C_D A(u), m2), ``p_up_pa``, ``p_down_pa`` (Pa,
    absolute), ``t_up_k`` (K), ``eta_gas``, ``eta_oil`` (mass fractions, -).
    """
    spec = physics_spec(name)
    p1 = np.asarray(inputs["p_up_pa"], dtype=np.float64)
    p2 = np.asarray(inputs["p_down_pa"], dtype=np.float64)
    t1 = np.asarray(inputs["t_up_k"], dtype=np.float64)
    eg = np.asarray(inputs["eta_gas"], dtype=np.float64)
    eo = np.asarray(inputs["eta_oil"], dtype=np.float64)
    area = np.asarray(inputs["area_eff_m2"], dtype=np.float64)
    if spec.name == "bernoulli":
        mdot, z = bernoulli_mass_flow(
            area,
            p1,
            p2,
            t1,
            eg,
            eo,
            rho_oil=well.rho_oil,
            rho_wat=well.rho_wat,
            m_gas=well.m_gas,
            p_cr=well.p_cr,
        )
        q_gas, q_oil, q_wat = _phases_from_mass(mdot, eg, eo, well)
        return ChokeRates(q_gas, q_oil, q_wat, z, np.full_like(p1, well.p_cr))
    if spec.name == "gilbert":
        # The bean: the round hole of the geometric area C_D A(u) / C_D,nominal, so wear
        # (a growing effective area) widens the bean as it does in a real choke.
        bean = np.sqrt(4.0 * np.maximum(area, 0.0) / (math.pi * well.c_d))
        eta_wat = np.clip(1.0 - eg - eo, 0.0, 1.0)
        v_liquid = eo / well.rho_oil + eta_wat / well.rho_wat  # Sm3 liquid per kg mixture
        v_gas = eg / _gas_density_standard(well.m_gas)  # Sm3 gas per kg mixture
        glr = v_gas / np.maximum(v_liquid, 1e-12)
        q_liquid = gilbert_liquid_rate(p1, p2, bean, glr, gilbert_correlation(well.well_index))
        share_oil = (eo / well.rho_oil) / np.maximum(v_liquid, 1e-12)
        q_gas = q_liquid * glr
        return ChokeRates(
            q_gas,
            q_liquid * share_oil,
            q_liquid * (1.0 - share_oil),
            np.full_like(p1, math.nan),
            np.full_like(p1, GILBERT_CRITICAL_RATIO),
        )
    raise ConfigError(
        f"The physics '{name}' is computed by vfm_core.simulate itself, not by choke_rates; "
        f"choose one of {', '.join(n for n in TRUTH_PHYSICS if n != DEFAULT_PHYSICS)}."
    )
