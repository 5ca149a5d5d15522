"""The Sachdeva choke model against numbers worked by hand and against its own limits."""

from __future__ import annotations

import math

import pytest
import torch

from vfm_core import physics as ph

# A worked example in SI units (hand calculation, shared/notes/choke-physics.md):
# u = 0.5 of a 50 mm bore, C_D = 0.85, p1 = 100 bar, p2 = 30 bar, T1 = 70 degC,
# eta_gas = 0.1, eta_oil = 0.6, rho_oil = 850, rho_wat = 1025, kappa = 1.3, M = 0.02, p_cr = 0.55.
#   rho_g1 = 1e7 * 0.02 / (8.3145 * 343.15)                 = 70.10 kg/m3
#   p_r    = max(0.3, 0.55)                                   = 0.55 (choked)
#   rho_g2 = 70.10 * 0.55**(1/1.3)                            = 44.28 kg/m3
#   v_liq  = 0.6/850 + 0.3/1025                               = 9.986e-4 m3/kg
#   1/rho2 = 0.1/44.28 + 9.986e-4                             = 3.257e-3 -> rho2 = 307.1
#   energy = 9.986e-4*0.45 + 0.1*1.3/0.3*(1-0.55**(0.3/1.3))/70.10 = 1.2455e-3 m3/kg
#   G      = 307.1 * sqrt(2 * 1e7 * 1.2455e-3)                = 48,470 kg/(m2 s)
#   mdot   = 0.85 * 0.5 * pi/4 * 0.05**2 * G                  = 40.4 kg/s
#   Q      = mdot * (0.1/0.8459 + 9.986e-4) * 3600            = 17,350 Sm3/h
EXAMPLE = dict(rho_oil=850.0, rho_wat=1025.0, kappa=1.3, m_gas=0.02, p_cr=0.55)
AREA = 0.85 * 0.5 * math.pi / 4 * 0.05**2


def test_worked_example_mass_flow_and_rate() -> None:
    mdot = ph.choke_mass_flow(AREA, 1e7, 3e6, 343.15, 0.1, 0.6, **EXAMPLE)
    assert float(mdot) == pytest.approx(40.43, rel=2e-3)
    per_kg = ph.standard_volume_per_mass(0.1, 0.6, rho_oil=850.0, rho_wat=1025.0, m_gas=0.02)
    assert float(mdot * per_kg * 3600) == pytest.approx(17_354, rel=2e-3)


def test_standard_gas_density_by_hand() -> None:
    # 101325 * 0.02 / (8.3145 * 288.15) = 0.8458 kg/Sm3
    assert float(ph.gas_density_standard(0.02)) == pytest.approx(0.8458, rel=1e-3)


def test_phase_rates_sum_to_total() -> None:
    mdot = torch.tensor(40.0, dtype=torch.float64)
    q = ph.phase_rates(mdot, 0.1, 0.6, rho_oil=850.0, rho_wat=1025.0, m_gas=0.02)
    total = mdot * ph.standard_volume_per_mass(0.1, 0.6, rho_oil=850.0, rho_wat=1025.0, m_gas=0.02)
    assert float(sum(q)) == pytest.approx(float(total), rel=1e-12)
    assert float(q[1]) == pytest.approx(40.0 * 0.6 / 850.0, rel=1e-12)  # oil, Sm3/s


def test_pure_liquid_limit_is_bernoulli() -> None:
    # eta_gas -> 0: G = rho_L sqrt(2 (p1 - p2) / rho_L) = sqrt(2 rho_L dp), p_cr irrelevant
    # for the liquid term only when the throat sees p2, so put p2 above p_cr * p1.
    g = ph.choke_mass_flux(
        1e7, 7e6, 330.0, 0.0, 1.0, rho_oil=850.0, rho_wat=1025.0, kappa=1.3, m_gas=0.02, p_cr=0.55
    )
    assert float(g) == pytest.approx(math.sqrt(2 * 850.0 * 3e6), rel=1e-12)


def test_pure_gas_limit_is_isentropic_nozzle() -> None:
    # eta_gas = 1: G = rho_g2 sqrt(2 k/(k-1) p1/rho_g1 (1 - r^((k-1)/k))), the ideal-gas nozzle.
    k, m, t1, p1, r = 1.3, 0.02, 330.0, 1e7, 0.8
    rho1 = p1 * m / (ph.R_GAS * t1)
    rho2 = rho1 * r ** (1 / k)
    expected = rho2 * math.sqrt(2 * k / (k - 1) * p1 / rho1 * (1 - r ** ((k - 1) / k)))
    g = ph.choke_mass_flux(
        p1, r * p1, t1, 1.0, 0.0, rho_oil=850.0, rho_wat=1025.0, kappa=k, m_gas=m, p_cr=0.5
    )
    assert float(g) == pytest.approx(expected, rel=1e-12)


def test_flow_is_frozen_below_critical_ratio() -> None:
    kw = dict(rho_oil=850.0, rho_wat=1025.0, kappa=1.3, m_gas=0.02, p_cr=0.55)
    choked = [float(ph.choke_mass_flux(1e7, p2, 340.0, 0.2, 0.5, **kw)) for p2 in (1e6, 3e6, 5.5e6)]
    assert choked[0] == pytest.approx(choked[1], rel=1e-12) == pytest.approx(choked[2], rel=1e-12)
    sub = float(ph.choke_mass_flux(1e7, 7e6, 340.0, 0.2, 0.5, **kw))
    assert sub < choked[0]


def test_sachdeva_critical_ratio_pure_gas_limit_and_continuity() -> None:
    # eta_gas -> 1 gives the isentropic critical ratio (2/(k+1))^(k/(k-1)) = 0.5457 for k = 1.3.
    k = 1.3
    y = ph.sachdeva_critical_ratio(torch.tensor([1.0 - 1e-9]), 70.0, 1e-12, k)
    assert float(y) == pytest.approx((2 / (k + 1)) ** (k / (k - 1)), rel=1e-4)
    # The root satisfies the implicit equation, and the ratio falls as liquid is added.
    x = torch.tensor([0.005, 0.05, 0.2, 0.8], dtype=torch.float64)
    rho1, v_liq = 70.0, (1 - x) / 900.0
    y = ph.sachdeva_critical_ratio(x, rho1, v_liq, k)
    a = v_liq * rho1 / x
    b = a * y ** (1 / k)
    kk = k / (k - 1)
    rhs = ((kk + a * (1 - y)) / (kk + k / 2 + k * b + k / 2 * b**2)) ** kk
    torch.testing.assert_close(rhs, y, rtol=1e-9, atol=1e-12)
    assert torch.all(y.diff() > 0)


def test_papay_z_factor_hand_value() -> None:
    # gamma = 0.02/0.028965 = 0.6905; Tpc = 208.4 K, ppc = 45.83 bar; Tpr = 1.647, ppr = 2.182
    # Z = 1 - 3.52*2.182/10^(0.9813*1.647) + 0.274*2.182^2/10^(0.8157*1.647) = 0.873
    assert float(ph.z_factor_papay(1e7, 343.15, 0.02)) == pytest.approx(0.873, abs=2e-3)
    assert float(ph.z_factor_papay(1e5, 343.15, 0.02)) == pytest.approx(1.0, abs=5e-3)


def test_slip_increases_mass_flux_and_vanishes_without_liquid() -> None:
    kw = dict(rho_oil=850.0, rho_wat=1025.0, kappa=1.3, m_gas=0.02, p_cr=0.55)
    plain = ph.choke_mass_flux(1e7, 3e6, 343.15, 0.1, 0.6, **kw)
    slipped = ph.choke_mass_flux(1e7, 3e6, 343.15, 0.1, 0.6, slip=True, **kw)
    assert float(slipped) > float(plain)
    gas_only = [ph.choke_mass_flux(1e7, 3e6, 343.15, 1.0, 0.0, slip=s, **kw) for s in (False, True)]
    assert float(gas_only[0]) == pytest.approx(float(gas_only[1]), rel=1e-12)


@pytest.mark.parametrize("family", sorted(ph.AREA_FUNCTIONS))
def test_area_functions_are_monotone_from_zero_to_one(family: str) -> None:
    u = torch.linspace(0, 1, 101, dtype=torch.float64)
    a = ph.area_fraction(u, family)
    assert float(a[0]) == pytest.approx(0.0, abs=1e-12)
    assert float(a[-1]) == pytest.approx(1.0, abs=1e-12)
    assert torch.all(a.diff() >= 0)


def test_unknown_area_family_lists_choices() -> None:
    from vfm_core.errors import ConfigError

    with pytest.raises(ConfigError, match="equal_percentage"):
        ph.area_fraction(0.5, "butterfly")


def test_gradients_flow_to_every_parameter() -> None:
    params = {
        k: torch.tensor(v, dtype=torch.float64, requires_grad=True)
        for k, v in dict(rho_oil=850.0, rho_wat=1025.0, kappa=1.3, m_gas=0.02, p_cr=0.55).items()
    }
    g = ph.choke_mass_flux(1e7, 3e6, 343.15, 0.1, 0.6, **params)
    g.backward()
    for name, p in params.items():
        assert p.grad is not None and torch.isfinite(p.grad) and float(p.grad) != 0.0, name
