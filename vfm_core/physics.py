"""The Sachdeva homogeneous two-phase choke model, in SI units, on torch tensors.

This is the mechanistic model (MM) of the paper (Hotvedt et al., passive learning for
nonstationary VFM, eq. MM) in the notation of ``shared/notes/choke-physics.md``. The same
functions serve the simulator (as the truth), the learnable ``mm``/``hem``/``ham`` models
(autograd flows through every argument) and the diagnosis effects, so the physics is
written once.

Units, everywhere in this module:

=============  =============================================  ===========
name           meaning                                        unit
=============  =============================================  ===========
area           effective flow area C_D * A_2(u) or A_2(u)     m2
p_up, p_down   upstream / downstream pressure, absolute       Pa
t_up           upstream temperature                           K
eta_gas/oil    gas / oil mass fraction (water = 1 - both)     -
rho_oil/wat    oil / water density                            kg/m3
kappa          gas heat-capacity ratio (polytropic exponent)  -
m_gas          gas molar mass                                 kg/mol
p_cr           critical pressure ratio p2/p1 of choked flow   -
mass flow      mdot                                           kg/s
volume rate    at standard conditions (101325 Pa, 288.15 K)   Sm3/s
=============  =============================================  ===========

Arguments broadcast against each other, so one call evaluates a batch of samples with
scalar or per-sample parameters.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import torch

__all__ = [
    "DTYPE",
    "R_GAS",
    "P_SC",
    "T_SC",
    "M_AIR",
    "ChokeParameters",
    "PRIORS",
    "gas_density",
    "gas_density_standard",
    "liquid_specific_volume",
    "choke_mass_flux",
    "choke_mass_flow",
    "standard_volume_per_mass",
    "phase_rates",
    "z_factor_papay",
    "simpson_slip",
    "sachdeva_critical_ratio",
    "AREA_FUNCTIONS",
    "area_fraction",
    "choke_area_m2",
]

#: The floating-point type of every tensor in the VFM (the physics needs the precision).
DTYPE = torch.float64

#: Universal gas constant, J/(mol K).
R_GAS = 8.314462618
#: Standard conditions: pressure in Pa and temperature in K.
P_SC = 101_325.0
T_SC = 288.15
#: Molar mass of air, kg/mol (for gas specific gravity).
M_AIR = 0.028965

Tensorish = torch.Tensor | float


def _t(x: Tensorish) -> torch.Tensor:
    return x if isinstance(x, torch.Tensor) else torch.as_tensor(x, dtype=DTYPE)


@dataclass(frozen=True)
class Prior:
    """A Gaussian prior N(mean, std^2) with hard physical bounds [low, high] (SI units).

    ``drift``: how far the parameter of a real well may wander in a year, in prior standard
    deviations per square root of a year (the process noise of a Bayesian filter: a random
    walk of variance (drift std)^2 per year). The rule: what wells change over months (the
    discharge coefficient: wear and deposits; the densities and the gas molar mass, as
    water cut and gas composition change) a good part of its prior range, 0.25-0.5; constants
    of the fluid and the structural parameters of effects (slopes, exponents), 0.05.
    """

    mean: float
    std: float
    low: float
    high: float
    unit: str
    meaning: str
    drift: float = 0.05


#: Priors of the mechanistic parameters (shared/notes/choke-physics.md, "Typical priors").
#: The standard deviation is a quarter of the typical range, so the range is about +-2 sd;
#: the bounds are wider physical limits that learning may never cross.
PRIORS: dict[str, Prior] = {
    "rho_oil": Prior(840.0, 20.0, 650.0, 1000.0, "kg/m3", "oil density", 0.25),
    "rho_wat": Prior(1017.5, 8.0, 990.0, 1100.0, "kg/m3", "water density", 0.25),
    "kappa": Prior(1.28, 0.015, 1.05, 1.67, "-", "gas heat-capacity ratio", 0.05),
    "m_gas": Prior(0.0205, 0.0018, 0.016, 0.040, "kg/mol", "gas molar mass", 0.25),
    "p_cr": Prior(0.55, 0.05, 0.2, 0.95, "-", "critical pressure ratio p_down/p_up", 0.05),
    "c_d": Prior(0.825, 0.04, 0.3, 1.5, "-", "discharge coefficient", 0.5),
}


@dataclass(frozen=True)
class ChokeParameters:
    """The mechanistic parameters theta_MM of one well (SI units, see module table)."""

    rho_oil: float = PRIORS["rho_oil"].mean
    rho_wat: float = PRIORS["rho_wat"].mean
    kappa: float = PRIORS["kappa"].mean
    m_gas: float = PRIORS["m_gas"].mean
    p_cr: float = PRIORS["p_cr"].mean
    c_d: float = PRIORS["c_d"].mean


def gas_density(
    p_pa: Tensorish, t_k: Tensorish, m_gas: Tensorish, z: Tensorish = 1.0
) -> torch.Tensor:
    """Gas density rho = p M / (Z R T), kg/m3."""
    return _t(p_pa) * _t(m_gas) / (_t(z) * R_GAS * _t(t_k))


def gas_density_standard(m_gas: Tensorish) -> torch.Tensor:
    """Gas density at standard conditions (101325 Pa, 288.15 K, Z = 1), kg/m3."""
    return gas_density(P_SC, T_SC, m_gas)


def liquid_specific_volume(
    eta_gas: Tensorish, eta_oil: Tensorish, rho_oil: Tensorish, rho_wat: Tensorish
) -> torch.Tensor:
    """Liquid volume per kg of *mixture*, (1 - eta_gas)/rho_L = eta_oil/rho_oil + eta_wat/rho_wat, m3/kg.

    Written this way it stays finite when the mixture holds no liquid (eta_gas = 1).
    """
    eta_wat = 1.0 - _t(eta_gas) - _t(eta_oil)
    return _t(eta_oil) / _t(rho_oil) + eta_wat / _t(rho_wat)


def simpson_slip(rho_liquid: Tensorish, rho_gas: Tensorish) -> torch.Tensor:
    """Simpson's slip ratio s = (rho_L / rho_g)^(1/6), dimensionless, >= 1 for rho_L >= rho_g."""
    return (_t(rho_liquid) / _t(rho_gas)) ** (1.0 / 6.0)


def choke_mass_flux(
    p_up: Tensorish,
    p_down: Tensorish,
    t_up: Tensorish,
    eta_gas: Tensorish,
    eta_oil: Tensorish,
    *,
    rho_oil: Tensorish,
    rho_wat: Tensorish,
    kappa: Tensorish,
    m_gas: Tensorish,
    p_cr: Tensorish,
    z: Tensorish = 1.0,
    slip: bool = False,
) -> torch.Tensor:
    """Mass flux through the choke throat per unit effective area, kg/(m2 s).

    Sachdeva (1986), homogeneous flow::

        G = rho_2 sqrt(2 p1 [ (1-eta_g)(1-p_r)/rho_L + eta_g k/(k-1) (1/rho_g1 - p_r/rho_g2) ])

    with p_r = max(p2/p1, p_cr), rho_g1 = p1 M/(Z R T1), rho_g2 = rho_g1 p_r^(1/k) and
    1/rho_2 = eta_g/rho_g2 + (1-eta_g)/rho_L. ``z`` is the upstream gas compressibility
    (1 = ideal gas). With ``slip=True`` the throat mixture density uses the momentum
    specific volume with Simpson's slip ratio s = (rho_L/rho_g2)^(1/6):
    v = (x/rho_g2 + s (1-x)/rho_L)(x + (1-x)/s), which is 1/rho_2 for s = 1.
    """
    params = (rho_oil, rho_wat, kappa, m_gas, p_cr, z)
    inputs = (p_up, p_down, t_up, eta_gas, eta_oil)
    if (
        not slip
        and torch.is_grad_enabled()
        and not any(isinstance(v, torch.Tensor) and v.requires_grad for v in inputs)
        and any(isinstance(v, torch.Tensor) and v.requires_grad for v in params)
    ):
        # learning: the same flux, with its gradient in closed form (one autograd node
        # instead of some forty, see _FluxFunction)
        return _FluxFunction.apply(*(_t(v) for v in inputs + params))
    return _flux(
        p_up, p_down, t_up, eta_gas, eta_oil, rho_oil, rho_wat, kappa, m_gas, p_cr, z, slip
    )[0]


def _flux(
    p_up: Tensorish,
    p_down: Tensorish,
    t_up: Tensorish,
    eta_gas: Tensorish,
    eta_oil: Tensorish,
    rho_oil: Tensorish,
    rho_wat: Tensorish,
    kappa: Tensorish,
    m_gas: Tensorish,
    p_cr: Tensorish,
    z: Tensorish,
    slip: bool,
) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """:func:`choke_mass_flux`, kg/(m2 s), and the intermediates its gradient needs."""
    p1 = _t(p_up)
    p_ratio = torch.maximum(_t(p_down) / p1, _t(p_cr))
    k = _t(kappa)
    x = _t(eta_gas)
    rho_g1 = gas_density(p1, t_up, m_gas, z)
    v_liq = liquid_specific_volume(x, eta_oil, rho_oil, rho_wat)
    # p_r / rho_g2 = p_r^(1 - 1/k) / rho_g1; the bracket of the gas term is then
    # (1 - p_r^((k-1)/k)) / rho_g1, which is positive for p_r < 1.
    expansion = 1.0 - p_ratio ** ((k - 1.0) / k)
    energy = v_liq * (1.0 - p_ratio) + x * k / (k - 1.0) * expansion / rho_g1
    rho_g2 = rho_g1 * p_ratio ** (1.0 / k)
    v_mix = x / rho_g2 + v_liq
    if slip:
        liquid_fraction = 1.0 - x
        liquid = liquid_fraction > 1e-9
        # a dry gas has no slip; its unchosen branch is kept finite (rho_L = rho_g), or
        # torch.where's zero gradient times the root's infinite slope at 0 would be NaN
        rho_liquid = torch.where(liquid, liquid_fraction / torch.clamp(v_liq, min=1e-12), rho_g2)
        s = torch.where(liquid, simpson_slip(rho_liquid, rho_g2), torch.ones_like(v_mix))
        v_mix = (x / rho_g2 + s * v_liq) * (x + liquid_fraction / s)
    head = 2.0 * p1 * energy
    flux = torch.sqrt(torch.clamp(head, min=0.0)) / v_mix
    parts = dict(
        p_ratio=p_ratio,
        k=k,
        x=x,
        rho_g1=rho_g1,
        v_liq=v_liq,
        expansion=expansion,
        energy=energy,
        v_mix=v_mix,
        head=head,
    )
    return flux, parts


class _FluxFunction(torch.autograd.Function):
    """The homogeneous (no-slip) choke mass flux with its gradient in closed form with
    respect to the fluid parameters (rho_oil, rho_wat, kappa, m_gas, p_cr, z); the
    measured inputs (pressures, temperature, fractions) carry no gradient here.

    With E the energy bracket, v the liquid volume per kg of mixture, rho_g1 the upstream
    gas density, p_r the pressure ratio and v_mix = x p_r^(-1/k) / rho_g1 + v,
    G = sqrt(2 p1 E) / v_mix, so d log G = dE / (2 E) - d v_mix / v_mix, with
    dE/dv = 1 - p_r, dE/drho_g1 = -x k/(k-1) (1 - p_r^a) / rho_g1^2 (a = (k-1)/k),
    dE/dp_r = -v - x p_r^(a-1) / rho_g1,
    dE/dk = -x [(1 - p_r^a)/(k-1)^2 + p_r^a ln(p_r) / (k (k-1))] / rho_g1, and
    v_mix's: 1, -g/rho_g1, -g/(k p_r), g ln(p_r)/k^2 with g = x p_r^(-1/k) / rho_g1;
    then v through the densities, rho_g1 through M_gas (rho_g1/M) and Z (-rho_g1/Z), p_r
    through p_cr where p_cr is above p_down/p_up. Zero where the bracket is not positive
    (no flow), as the clamp gives.
    """

    @staticmethod
    def forward(  # type: ignore[override]
        ctx: Any,
        p_up: torch.Tensor,
        p_down: torch.Tensor,
        t_up: torch.Tensor,
        eta_gas: torch.Tensor,
        eta_oil: torch.Tensor,
        rho_oil: torch.Tensor,
        rho_wat: torch.Tensor,
        kappa: torch.Tensor,
        m_gas: torch.Tensor,
        p_cr: torch.Tensor,
        z: torch.Tensor,
    ) -> torch.Tensor:
        flux, parts = _flux(
            p_up, p_down, t_up, eta_gas, eta_oil, rho_oil, rho_wat, kappa, m_gas, p_cr, z, False
        )
        ctx.save_for_backward(p_up, p_down, eta_oil, rho_oil, rho_wat, m_gas, p_cr, z, flux)
        ctx.parts = parts
        return flux

    @staticmethod
    def backward(ctx: Any, grad: torch.Tensor) -> tuple[torch.Tensor | None, ...]:  # type: ignore[override]
        p_up, p_down, eta_oil, rho_oil, rho_wat, m_gas, p_cr, z, flux = ctx.saved_tensors
        d = flux_vjp(ctx.parts, grad, flux, p_up, p_down, eta_oil, rho_oil, rho_wat, m_gas, p_cr, z)

        def reduce(value: torch.Tensor, like: torch.Tensor, needed: bool) -> torch.Tensor | None:
            return value.sum_to_size(like.shape) if needed else None

        need = ctx.needs_input_grad
        return (
            None,
            None,
            None,
            None,
            None,
            reduce(d["rho_oil"], rho_oil, need[5]),
            reduce(d["rho_wat"], rho_wat, need[6]),
            reduce(d["kappa"], ctx.parts["k"], need[7]),
            reduce(d["m_gas"], m_gas, need[8]),
            reduce(d["p_cr"], p_cr, need[9]),
            reduce(d["z"], z, need[10]),
        )


def flux_vjp(
    parts: dict[str, torch.Tensor],
    grad: torch.Tensor,
    flux: torch.Tensor,
    p_up: torch.Tensor,
    p_down: torch.Tensor,
    eta_oil: torch.Tensor,
    rho_oil: torch.Tensor,
    rho_wat: torch.Tensor,
    m_gas: torch.Tensor,
    p_cr: torch.Tensor,
    z: torch.Tensor | float,
) -> dict[str, torch.Tensor]:
    """``grad`` (d loss / d flux, per sample) times the flux's closed-form derivatives
    (see :class:`_FluxFunction`): d loss / d rho_oil, rho_wat, kappa, m_gas, p_cr, z, per
    sample (not yet summed to the parameters' shapes). ``parts``: :func:`_flux`'s."""
    pr, k, x = parts["p_ratio"], parts["k"], parts["x"]
    rho_g1, v, energy, v_mix = parts["rho_g1"], parts["v_liq"], parts["energy"], parts["v_mix"]
    flowing = parts["head"] > 0
    # dG = G (dE / 2E - dv_mix / v_mix), G's factor per unit of E and of v_mix
    safe_e = torch.where(flowing, energy, torch.ones_like(energy))
    g_e = torch.where(flowing, grad * flux * 0.5 / safe_e, torch.zeros_like(flux))
    g_m = torch.where(flowing, -grad * flux / v_mix, torch.zeros_like(flux))
    pra = 1.0 - parts["expansion"]  # p_r^a
    gas = x * pr ** (-1.0 / k) / rho_g1  # x / rho_g2
    log_pr = torch.log(pr)
    d_v = g_e * (1.0 - pr) + g_m
    d_rho_g1 = g_e * (-x * k / (k - 1.0) * parts["expansion"] / rho_g1**2) - g_m * gas / rho_g1
    d_pr = g_e * (-v - x * pra / pr / rho_g1) - g_m * gas / (k * pr)
    d_k = (
        g_e * (-x * (parts["expansion"] / (k - 1.0) ** 2 + pra * log_pr / (k * (k - 1.0))) / rho_g1)
        + g_m * gas * log_pr / k**2
    )
    eta_wat = 1.0 - x - eta_oil
    ratio = p_down / p_up
    at_cr = torch.where(
        p_cr > ratio,
        torch.ones_like(d_pr),
        torch.where(p_cr == ratio, torch.full_like(d_pr, 0.5), torch.zeros_like(d_pr)),
    )
    return {
        "rho_oil": d_v * (-eta_oil / rho_oil**2),
        "rho_wat": d_v * (-eta_wat / rho_wat**2),
        "kappa": d_k,
        "m_gas": d_rho_g1 * rho_g1 / m_gas,
        "p_cr": d_pr * at_cr,
        "z": d_rho_g1 * (-rho_g1 / z),
    }


def choke_mass_flow(area: Tensorish, *args: Tensorish, **kwargs: Tensorish | bool) -> torch.Tensor:
    """Mass flow mdot = area * mass flux, kg/s; ``area`` is C_D A_2(u) in m2.

    The other arguments are those of :func:`choke_mass_flux`.
    """
    return _t(area) * choke_mass_flux(*args, **kwargs)  # type: ignore[arg-type]


def standard_volume_per_mass(
    eta_gas: Tensorish,
    eta_oil: Tensorish,
    *,
    rho_oil: Tensorish,
    rho_wat: Tensorish,
    m_gas: Tensorish,
) -> torch.Tensor:
    """Total volume at standard conditions per kg of mixture, Sm3/kg.

    Q = mdot (eta_gas/rho_gas_sc + eta_oil/rho_oil + eta_wat/rho_wat).
    """
    return _t(eta_gas) / gas_density_standard(m_gas) + liquid_specific_volume(
        eta_gas, eta_oil, rho_oil, rho_wat
    )


def phase_rates(
    mass_flow: Tensorish,
    eta_gas: Tensorish,
    eta_oil: Tensorish,
    *,
    rho_oil: Tensorish,
    rho_wat: Tensorish,
    m_gas: Tensorish,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Gas, oil and water rates at standard conditions from the mass flow, each Sm3/s."""
    mdot = _t(mass_flow)
    q_gas = mdot * _t(eta_gas) / gas_density_standard(m_gas)
    q_oil = mdot * _t(eta_oil) / _t(rho_oil)
    q_wat = mdot * (1.0 - _t(eta_gas) - _t(eta_oil)) / _t(rho_wat)
    return q_gas, q_oil, q_wat


def z_factor_papay(p_pa: Tensorish, t_k: Tensorish, m_gas: Tensorish) -> torch.Tensor:
    """Natural-gas compressibility Z(p, T) by Papay's correlation, dimensionless.

    Pseudo-critical properties from Sutton's correlation for the gas specific gravity
    gamma = M_gas / M_air: Tpc = 169.2 + 349.5 gamma - 74.0 gamma^2 (degR),
    ppc = 756.8 - 131.0 gamma - 3.6 gamma^2 (psia). Then with Tpr = T/Tpc and
    ppr = p/ppc: Z = 1 - 3.52 ppr / 10^(0.9813 Tpr) + 0.274 ppr^2 / 10^(0.8157 Tpr).
    Valid roughly for ppr < 8 and 1.2 < Tpr < 3 (wellhead conditions).
    """
    gamma = _t(m_gas) / M_AIR
    t_pc = (169.2 + 349.5 * gamma - 74.0 * gamma**2) * (5.0 / 9.0)  # degR -> K
    p_pc = (756.8 - 131.0 * gamma - 3.6 * gamma**2) * 6894.757293168  # psia -> Pa
    t_pr = _t(t_k) / t_pc
    p_pr = _t(p_pa) / p_pc
    return 1.0 - 3.52 * p_pr / 10.0 ** (0.9813 * t_pr) + 0.274 * p_pr**2 / 10.0 ** (0.8157 * t_pr)


def sachdeva_critical_ratio(
    eta_gas: Tensorish,
    rho_g1: Tensorish,
    v_liq: Tensorish,
    kappa: Tensorish,
    n: Tensorish | None = None,
    *,
    iterations: int = 60,
) -> torch.Tensor:
    """Critical pressure ratio y_c of Sachdeva's implicit equation, solved by bisection.

    y = [(k/(k-1) + a (1-y)) / (k/(k-1) + n/2 + n b + (n/2) b^2)]^(k/(k-1)),
    a = (1-x) rho_g1 / (x rho_L), b = (1-x) rho_g2 / (x rho_L), rho_g2 = rho_g1 y^(1/k),
    with x = eta_gas and (1-x)/rho_L = ``v_liq`` (m3 of liquid per kg of mixture).
    The bracket (1e-4, 0.9999) is searched by bisection, which always converges (plain
    fixed-point iteration diverges for eta_gas below about 0.01). No gradient flows
    through the result. ``n`` defaults to kappa.
    """
    with torch.no_grad():
        x = torch.clamp(_t(eta_gas), min=1e-9)
        k = _t(kappa)
        n_ = k if n is None else _t(n)
        rho1 = _t(rho_g1)
        vl = _t(v_liq)
        kk = k / (k - 1.0)
        a = vl * rho1 / x

        def residual(y: torch.Tensor) -> torch.Tensor:
            b = a * y ** (1.0 / k)
            rhs = ((kk + a * (1.0 - y)) / (kk + n_ / 2.0 + n_ * b + n_ / 2.0 * b**2)) ** kk
            return rhs - y

        shape = torch.broadcast_shapes(x.shape, k.shape, rho1.shape, vl.shape)
        lo = torch.full(shape, 1e-4, dtype=torch.float64)
        hi = torch.full(shape, 0.9999, dtype=torch.float64)
        # residual(lo) > 0 and residual(hi) < 0 for all physical inputs.
        for _ in range(iterations):
            mid = 0.5 * (lo + hi)
            positive = residual(mid) > 0
            lo = torch.where(positive, mid, lo)
            hi = torch.where(positive, hi, mid)
        return 0.5 * (lo + hi)


def _equal_percentage(u: torch.Tensor, rangeability: float = 30.0) -> torch.Tensor:
    # R^(u-1) reaches 1/R at u = 0; shifted so that A(0) = 0 and A(1) = 1.
    return (rangeability ** (u - 1.0) - 1.0 / rangeability) / (1.0 - 1.0 / rangeability)


def _quick_opening(u: torch.Tensor, power: float = 0.6) -> torch.Tensor:
    return torch.clamp(u, min=0.0) ** power


def _convex(u: torch.Tensor) -> torch.Tensor:
    return 0.25 * u + 0.75 * u**2


def _sigmoid_like(u: torch.Tensor, power: float = 1.5) -> torch.Tensor:
    uc = torch.clamp(u, 0.0, 1.0)
    return uc**power / (uc**power + (1.0 - uc) ** power)


def _linear(u: torch.Tensor) -> torch.Tensor:
    return u


#: Valve characteristics A_2(u)/A_max for the opening u in [0, 1]; each is 0 at u = 0
#: and 1 at u = 1 and monotone in between.
AREA_FUNCTIONS: dict[str, Callable[..., torch.Tensor]] = {
    "linear": _linear,
    "equal_percentage": _equal_percentage,
    "quick_opening": _quick_opening,
    "convex": _convex,
    "sigmoid": _sigmoid_like,
}


def area_fraction(u: Tensorish, family: str = "linear", **shape: float) -> torch.Tensor:
    """A_2(u)/A_max for a named valve family (see :data:`AREA_FUNCTIONS`)."""
    try:
        fn = AREA_FUNCTIONS[family]
    except KeyError:
        from vfm_core.errors import ConfigError

        raise ConfigError(
            f"Unknown valve characteristic '{family}'; choose one of {sorted(AREA_FUNCTIONS)}."
        ) from None
    return fn(_t(u), **shape)


def choke_area_m2(diameter_m: float) -> float:
    """Full-open flow area of a round choke bore of the given diameter (m), m2."""
    return math.pi / 4.0 * diameter_m**2
