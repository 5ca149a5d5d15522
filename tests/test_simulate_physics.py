"""The simulator's second and third truth physics (vfm_core.sim_physics, `--physics`):
hand-checked numbers, limits, monotonicity, the choked regime, the per-well options (valves,
gas lift), the CLI, and the default (Sachdeva) field unchanged byte for byte."""

from __future__ import annotations

import hashlib
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pytest
import torch

from vfm_core import physics, sim_physics
from vfm_core.cli import main
from vfm_core.errors import ConfigError
from vfm_core.observations import load_observations
from vfm_core.simulate import load_truth, parse_valves, simulate_field, write_field

SMALL = dict(wells=3, years=1.0, seed=13)


def _inputs(**over: float | np.ndarray) -> dict[str, np.ndarray]:
    """SI inputs of choke_rates; defaults of the hand-worked bernoulli case."""
    base = {
        "area_eff_m2": 0.8 * math.pi / 4.0 * 0.05**2 * 0.5,
        "p_up_pa": 50e5,
        "p_down_pa": 20e5,
        "t_up_k": 333.15,
        "eta_gas": 0.05,
        "eta_oil": 0.60,
    }
    base.update(over)
    shape = np.broadcast_shapes(*(np.shape(v) for v in base.values()))
    return {k: np.broadcast_to(np.asarray(v, dtype=np.float64), shape) for k, v in base.items()}


WELL = sim_physics.WellConstants(rho_oil=850.0, rho_wat=1020.0, m_gas=0.020, p_cr=0.55, c_d=0.8)


# --- hand-checked numbers ---------------------------------------------------------------


def test_bernoulli_hand_worked_example() -> None:
    """One case worked by hand (tolerance 0.05 %, the digits below carry five figures).

    Inputs: p_up 50 bar, p_down 20 bar, t_up 60 degC (333.15 K), eta_gas 0.05, eta_oil
    0.60 (eta_wat 0.35), rho_oil 850, rho_wat 1020 kg/m3, M_gas 0.020 kg/mol, p_cr 0.55,
    C_D 0.8, a 50 mm bore half open (linear valve).

    1. Liquid: rho_L = 0.95 / (0.60/850 + 0.35/1020) = 0.95 / 1.04902e-3 = 905.61 kg/m3.
    2. Standing (1977), gravity g = 0.020/0.0289647 = 0.69050: T_pc = 168 + 325 g -
       12.5 g^2 = 386.45 degR = 214.70 K; p_pc = 677 + 15 g - 37.5 g^2 = 669.48 psia =
       46.159 bar; T_pr = 1.5517, p_pr = 1.0832. Hall-Yarborough: Z = 0.90688 (the
       Standing-Katz chart reads about 0.91 there; checked below by the residual).
    3. rho_G = p M / (Z R T) = 50e5 * 0.020 / (0.90688 * 8.31446 * 333.15) = 39.809 kg/m3.
    4. Simpson: S = (905.61/39.809)^(1/6) = 1.6833; Phi = (1 + 0.05 * 0.6833) *
       (1 + 0.05 * (1.6833^5 - 1)) = 1.0342 * 1.6257 = 1.6813.
    5. p_down/p_up = 0.4 < 0.55: choked, dp = 50e5 * (1 - 0.55) = 22.5e5 Pa.
    6. C_D A = 0.8 * pi/4 * 0.05^2 * 0.5 = 7.8540e-4 m2;
       mdot = 7.8540e-4 * sqrt(2 * 905.61 * 22.5e5 / 1.6813) = 38.668 kg/s.
    7. rho_gas,sc = 101325 * 0.020 / (8.31446 * 288.15) = 0.84585 kg/Sm3;
       Q = 3600 * 38.668 * (0.05/0.84585 + 0.60/850 + 0.35/1020)
         = 8228.6 + 98.26 + 47.77 = 8374.6 Sm3/h.
    """
    z = float(sim_physics.z_factor_hall_yarborough(50e5, 333.15, 0.020))
    assert z == pytest.approx(0.90688, rel=5e-5)
    t_pc, p_pc = sim_physics.pseudo_critical_standing(0.020)
    assert t_pc == pytest.approx(214.70, rel=5e-5)
    assert p_pc == pytest.approx(46.159e5, rel=5e-5)
    rates = sim_physics.choke_rates("bernoulli", WELL, _inputs())
    per_h = 3600.0
    assert float(rates.q_gas[()]) * per_h == pytest.approx(8228.6, rel=5e-4)
    assert float(rates.q_oil[()]) * per_h == pytest.approx(98.26, rel=5e-4)
    assert float(rates.q_wat[()]) * per_h == pytest.approx(47.77, rel=5e-4)
    assert float(rates.q_total[()]) * per_h == pytest.approx(8374.6, rel=5e-4)
    assert float(rates.z[()]) == pytest.approx(0.90688, rel=5e-5)
    mdot, _ = sim_physics.bernoulli_mass_flow(
        7.8540e-4, 50e5, 20e5, 333.15, 0.05, 0.60, rho_oil=850, rho_wat=1020, m_gas=0.02, p_cr=0.55
    )
    assert float(mdot) == pytest.approx(38.668, rel=5e-4)


def test_gilbert_hand_worked_example() -> None:
    """Gilbert (1954): p_up 100 bar absolute = (100e5 - 101325)/6894.757 = 1435.68 psig;
    a 1 inch bean = 64/64 in; GLR 100 Sm3/Sm3 = 100 * 5.6146 = 561.46 scf/STB;
    p_down 30 bar (ratio 0.3 < 0.588, critical flow).
    q_L = 1435.68 * 64^1.89 / (10 * 561.46^0.546) = 1435.68 * 2591.7 / (10 * 31.700)
        = 11738 STB/d = 11738 * 0.158987 / 24 = 77.76 Sm3/h (tolerance 0.05 %).
    """
    q = sim_physics.gilbert_liquid_rate(100e5, 30e5, 0.0254, 100.0)
    assert float(q) * 3600.0 == pytest.approx(77.76, rel=5e-4)
    # Ros's coefficients (a 17.4, b 0.5, c 2.0): 1435.68 * 4096 / (17.4 * 23.695)
    # = 14263 STB/d = 94.48 Sm3/h.
    ros = sim_physics.GILBERT_CORRELATIONS[1]
    q_ros = sim_physics.gilbert_liquid_rate(100e5, 30e5, 0.0254, 100.0, ros)
    assert float(q_ros) * 3600.0 == pytest.approx(94.48, rel=5e-4)


def test_hall_yarborough_solves_its_equation_and_agrees_with_papay() -> None:
    p = np.linspace(1e5, 200e5, 40)[:, None]
    t = np.linspace(313.15, 363.15, 5)[None, :]
    z = sim_physics.z_factor_hall_yarborough(p, t, 0.020)
    t_pc, p_pc = sim_physics.pseudo_critical_standing(0.020)
    tt = t_pc / t
    a_ppr = 0.06125 * tt * np.exp(-1.2 * (1.0 - tt) ** 2) * p / p_pc
    residual, _ = sim_physics._hall_yarborough_residual(
        a_ppr / z, a_ppr, np.broadcast_to(tt, z.shape)
    )
    assert np.abs(residual).max() < 1e-10
    # Z -> 1 as p -> 0 (1 bar: within 0.5 %); a real gas at wellhead conditions has Z < 1.
    assert np.all(np.abs(z[0] - 1.0) < 5e-3)
    assert np.all(z[1:] < 1.0)
    # Papay's correlation (vfm_core.physics, another fit to the same Standing-Katz chart, with
    # Sutton's pseudo-critical properties) agrees within 6 % over wellhead conditions.
    papay = physics.z_factor_papay(
        torch.as_tensor(np.broadcast_to(p, z.shape).copy()),
        torch.as_tensor(np.broadcast_to(t, z.shape).copy()),
        0.020,
    ).numpy()
    assert np.abs(z / papay - 1.0).max() < 0.06


def test_simpson_multiplier_limits() -> None:
    rho_l, rho_g = 900.0, 40.0
    assert float(sim_physics.simpson_multiplier(0.0, rho_l, rho_g)) == pytest.approx(1.0)
    # All gas: the gas-only pressure drop at the same mass flux, rho_L / rho_G times the liquid's.
    assert float(sim_physics.simpson_multiplier(1.0, rho_l, rho_g)) == pytest.approx(rho_l / rho_g)
    x = np.linspace(0.0, 1.0, 101)
    assert np.all(np.diff(sim_physics.simpson_multiplier(x, rho_l, rho_g)) > 0)


def test_bernoulli_limits_are_the_single_phase_orifice() -> None:
    area = 1e-3
    # All liquid (water): mdot = C_D A sqrt(2 rho dp).
    liquid = sim_physics.choke_rates(
        "bernoulli", WELL, _inputs(area_eff_m2=area, eta_gas=0.0, eta_oil=0.0, p_down_pa=40e5)
    )
    expected = area * math.sqrt(2.0 * 1020.0 * 10e5) / 1020.0
    assert float(liquid.q_total[()]) == pytest.approx(expected, rel=1e-12)
    # All gas: mdot = C_D A sqrt(2 rho_G dp) with the real-gas density.
    gas = sim_physics.choke_rates(
        "bernoulli", WELL, _inputs(area_eff_m2=area, eta_gas=1.0, eta_oil=0.0, p_down_pa=40e5)
    )
    z = float(sim_physics.z_factor_hall_yarborough(50e5, 333.15, 0.020))
    rho_g = 50e5 * 0.020 / (z * sim_physics.R_GAS * 333.15)
    rho_sc = sim_physics.P_SC_PA * 0.020 / (sim_physics.R_GAS * sim_physics.T_SC_K)
    assert float(gas.q_total[()]) == pytest.approx(
        area * math.sqrt(2.0 * rho_g * 10e5) / rho_sc, rel=1e-9
    )


# --- shape of the physics ---------------------------------------------------------------


@pytest.mark.parametrize("name", ["bernoulli", "gilbert"])
def test_rate_rises_with_dp_and_is_flat_when_choked(name: str) -> None:
    critical = 0.55 if name == "bernoulli" else sim_physics.GILBERT_CRITICAL_RATIO
    ratio = np.linspace(0.05, 0.999, 400)
    rates = sim_physics.choke_rates(name, WELL, _inputs(p_down_pa=50e5 * ratio)).q_total
    sub = ratio > critical + 1e-9
    assert np.all(np.diff(rates[sub]) < 0)  # less dp (higher p_down): less flow
    assert np.all(rates[sub] < rates[0])
    # Choked: the same rate for every p_down below the critical ratio.
    choked = rates[ratio <= critical]
    assert len(choked) > 50
    assert np.ptp(choked) <= 1e-12 * choked.max()
    # ... and continuous at the critical ratio.
    edge = sim_physics.choke_rates(name, WELL, _inputs(p_down_pa=50e5 * (critical + 1e-7)))
    assert float(edge.q_total[()]) == pytest.approx(float(choked[-1]), rel=1e-3)
    # More upstream pressure at a fixed p_down: more flow.
    p_up = np.linspace(25e5, 150e5, 100)
    more = sim_physics.choke_rates(name, WELL, _inputs(p_up_pa=p_up)).q_total
    assert np.all(np.diff(more) > 0)


@pytest.mark.parametrize("name", ["bernoulli", "gilbert"])
@pytest.mark.parametrize("family", list(physics.AREA_FUNCTIONS))
def test_rate_rises_with_opening(name: str, family: str) -> None:
    u = np.linspace(0.02, 1.0, 99)
    fraction = physics.area_fraction(torch.as_tensor(u), family).numpy()
    area = 0.8 * math.pi / 4.0 * 0.05**2 * fraction
    for ratio in (0.3, 0.8):  # choked and not
        q = sim_physics.choke_rates(
            name, WELL, _inputs(area_eff_m2=area, p_down_pa=50e5 * ratio)
        ).q_total
        assert np.all(np.diff(q) > 0)


def test_physics_differ_from_sachdeva_in_shape_not_only_scale() -> None:
    """The new truths are not Sachdeva times a constant: their ratio to Sachdeva moves with
    the gas fraction by more than a few percent (else they would test nothing new)."""
    eta_gas = np.linspace(0.02, 0.3, 8)
    inputs = _inputs(eta_gas=eta_gas, eta_oil=0.6 * (1.0 - eta_gas))
    sachdeva_mdot = physics.choke_mass_flow(
        torch.as_tensor(inputs["area_eff_m2"].copy()),
        torch.as_tensor(inputs["p_up_pa"].copy()),
        torch.as_tensor(inputs["p_down_pa"].copy()),
        torch.as_tensor(inputs["t_up_k"].copy()),
        torch.as_tensor(eta_gas),
        torch.as_tensor(inputs["eta_oil"].copy()),
        rho_oil=850.0,
        rho_wat=1020.0,
        kappa=1.28,
        m_gas=0.020,
        p_cr=0.55,
    )
    per_kg = physics.standard_volume_per_mass(
        torch.as_tensor(eta_gas),
        torch.as_tensor(inputs["eta_oil"].copy()),
        rho_oil=850.0,
        rho_wat=1020.0,
        m_gas=0.020,
    )
    q_sachdeva = (sachdeva_mdot * per_kg).numpy()
    for name in ("bernoulli", "gilbert"):
        ratio = sim_physics.choke_rates(name, WELL, inputs).q_total / q_sachdeva
        assert ratio.max() / ratio.min() > 1.05, name


# --- the simulator with --physics ---------------------------------------------------------


# What `simulate_field(wells=3, years=0.5, seed=20261, hidden=...)` writes, as it wrote it
# before --physics existed. Until 2026-11-27 this was a SHA-256 of each file's bytes, which
# held across dependency upgrades but not across machines: on an AMD EPYC host torch's
# vectorised math gives other last bits than on the host the hashes were taken on (the same
# packages, the same code; pandas, numpy and scipy of the earlier versions gave the same
# new bytes). The default path of the simulator had not changed since (the hashes passed
# on that code in CI), so the figures below, taken from it on 2026-11-27, are the pre-physics
# output: the text columns (times, wells, sources) exactly, by hash, every numeric column by
# its sum and its sum of squares, and the truth's structure (keys, texts, integers) by hash
# with the sum and the absolute sum of its floats. Floats are compared at a relative 1e-7: a
# changed random stream, effect or formula moves a column's sums far more; last bits, and a
# rounded reading that flips its last digit, move them far less. The truth's structure hash
# of the all-effects field was retaken once since, for a parameter added with its default.
_TEXT = {
    "time": "3b8d2d3e46204df4",
    "well": "f0b80f0db2cb0df3",
    "source": "8ed778ff9a45d996",
}
_BEFORE: dict[tuple[str, ...], dict[str, Any]] = {
    (): {
        "obs": {
            "rows": 887,
            **_TEXT,
            "choke": (404.65, 191.148),
            "p_up": (126366.565, 18059107.700325),
            "p_down": (23725.365, 663644.177925),
            "t_up": (54675.329, 3548539.827507),
            "eta_gas": (151.3037404, 35.519217887148436),
            "eta_oil": (649.8906553, 480.7079420061609),
            "q_total": (81753594.45298544, 9938545992690.928),
            "q_gas": (81302185.81439237, 9869981376234.121),
            "q_oil": (405468.446242859, 216822908.62056792),
            "q_water": (45940.19235020206, 3303399.573375622),
        },
        "samples": {
            "rows": 887,
            "time": _TEXT["time"],
            "well": _TEXT["well"],
            "q_true": (82886019.27379669, 9982481235694.055),
            "q_gas_true": (82425888.41438645, 9913340325094.254),
            "q_oil_true": (413267.8405371779, 221643031.71199882),
            "q_water_true": (46863.01887307001, 3386283.1703747795),
            "c_d_true": (683.1448159234778, 526.9943718618541),
            "area_m2": (2.0787930102592886, 0.004920320613233562),
            "z_true": (887.0, 887.0),
            "p_cr_true": (465.1257563486532, 244.05416459609154),
            "mpfm_factor": (886.8025091580107, 886.6124067675584),
        },
        "truth": ("6f568a939242dfcf", 176, 308430.78593310335, 308430.78593310335),
    },
    (
        "erosion:step=0.1",
        "valve:family=sigmoid",
        "real_gas",
        "slip",
        "mpfm_bias",
        "critical_ratio",
    ): {
        "obs": {
            "rows": 887,
            **_TEXT,
            "choke": (347.33, 138.0596),
            "p_up": (126845.124, 18196551.67665),
            "p_down": (23725.365, 663644.177925),
            "t_up": (54680.577, 3549572.361161),
            "eta_gas": (151.3037404, 35.519217887148436),
            "eta_oil": (649.8906553, 480.7079420061609),
            "q_total": (87240841.99592729, 11342322434783.328),
            "q_gas": (86758644.30953191, 11263962599411.57),
            "q_oil": (433111.66348451964, 248351070.77408037),
            "q_water": (49086.022910847954, 3784545.41941578),
        },
        "samples": {
            "rows": 887,
            "time": _TEXT["time"],
            "well": _TEXT["well"],
            "q_true": (82865464.70833002, 10004856220999.488),
            "q_gas_true": (82404092.9875661, 9935349701453.547),
            "q_oil_true": (414356.72432340187, 223991281.3880694),
            "q_water_true": (47014.9964405255, 3424862.4136022506),
            "c_d_true": (704.2813929600184, 560.5194355262065),
            "area_m2": (1.6106352159634936, 0.002965731581992412),
            "z_true": (760.9934572203936, 652.9938713060546),
            "p_cr_true": (396.3723888566288, 181.76083129767477),
            "mpfm_factor": (942.9989074042152, 1002.719238624092),
        },
        # the structure's hash moved in session 49 when the erosion and mpfm_bias effects
        # got their `onset` parameter (params gain "onset": "start"); the floats did not
        "truth": ("cf6f7950e1d897cf", 209, 308437.30328188895, 308437.5864147293),
    },
}


def _csv_fingerprint(path: Path) -> dict[str, Any]:
    """Rows, each text column's hash (16 hex digits), each numeric column's sum and sum of
    squares (NaN left out)."""
    frame = pd.read_csv(path)
    out: dict[str, Any] = {"rows": len(frame)}
    for name in frame.columns:
        if pd.api.types.is_numeric_dtype(frame[name]):
            v = frame[name].to_numpy(dtype=float)
            out[name] = (float(np.nansum(v)), float(np.nansum(v * v)))
        else:
            text = "\n".join(map(str, frame[name].tolist()))
            out[name] = hashlib.sha256(text.encode()).hexdigest()[:16]
    return out


def _truth_fingerprint(truth: Any) -> tuple[str, int, float, float]:
    """The truth's structure with every float replaced by a mark (hashed, 16 hex digits),
    and its floats' count, sum and absolute sum."""
    floats: list[float] = []

    def shape(o: Any) -> Any:
        if isinstance(o, float):
            floats.append(o)
            return "<float>"
        if isinstance(o, dict):
            return {k: shape(o[k]) for k in sorted(o)}
        if isinstance(o, list):
            return [shape(v) for v in o]
        return o

    text = json.dumps(shape(truth), sort_keys=True)
    digest = hashlib.sha256(text.encode()).hexdigest()[:16]
    return digest, len(floats), math.fsum(floats), math.fsum(abs(x) for x in floats)


def _same(got: dict[str, Any], want: dict[str, Any]) -> None:
    assert sorted(got) == sorted(want)
    for key, value in want.items():
        if isinstance(value, tuple):
            assert got[key] == pytest.approx(value, rel=1e-7), key
        else:
            assert got[key] == value, key


@pytest.mark.parametrize("hidden", list(_BEFORE), ids=["plain", "all-effects"])
def test_default_physics_unchanged_byte_for_byte(tmp_path, hidden: tuple[str, ...]) -> None:
    field = simulate_field(wells=3, years=0.5, seed=20261, hidden=list(hidden))
    obs, truth_json, samples = write_field(field, tmp_path / "field.csv")
    want = _BEFORE[hidden]
    _same(_csv_fingerprint(obs), want["obs"])
    _same(_csv_fingerprint(samples), want["samples"])
    truth = json.loads(truth_json.read_text(encoding="utf-8"))
    assert truth.pop("physics")["name"] == "sachdeva"
    digest, n, total, size = _truth_fingerprint(truth)
    assert (digest, n) == want["truth"][:2]
    assert (total, size) == pytest.approx(want["truth"][2:], rel=1e-7)
    explicit = simulate_field(
        wells=3, years=0.5, seed=20261, hidden=list(hidden), physics="sachdeva"
    )
    pd.testing.assert_frame_equal(explicit.observations, field.observations)


@pytest.fixture(scope="module")
def fields() -> dict[str, object]:
    return {
        name: simulate_field(**SMALL, physics=name) for name in ("sachdeva", "bernoulli", "gilbert")
    }


@pytest.mark.parametrize("name", ["bernoulli", "gilbert"])
def test_field_of_other_physics(fields, name: str) -> None:
    field = fields[name]
    plain = fields["sachdeva"]
    obs = field.observations
    # Same format: columns, dtypes, row times (the sampling does not depend on the truth).
    assert list(obs.columns) == list(plain.observations.columns)
    assert (obs.dtypes == plain.observations.dtypes).all()
    pd.testing.assert_series_equal(obs["time"], plain.observations["time"])
    assert field.truth["physics"]["name"] == name
    assert field.truth["physics"]["references"]
    # The truth is this physics on the rows' own inputs.
    wells = field.truth["wells"]
    samples = field.truth_samples
    for k, well in enumerate(sorted(wells)):
        info = wells[well]
        rows = (obs["well"] == well).to_numpy()
        sub = obs[rows]
        constants = sim_physics.WellConstants(
            info["rho_oil"], info["rho_wat"], info["m_gas"], info["p_cr"], info["c_d"], k
        )
        fraction = sub["choke"].to_numpy()  # linear valve
        si = {
            "area_eff_m2": info["c_d"] * info["a_max_m2"] * fraction,
            "p_up_pa": sub["p_up"].to_numpy() * 1e5,
            "p_down_pa": sub["p_down"].to_numpy() * 1e5,
            "t_up_k": sub["t_up"].to_numpy() + 273.15,
            "eta_gas": sub["eta_gas"].to_numpy(),
            "eta_oil": sub["eta_oil"].to_numpy(),
        }
        expected = sim_physics.choke_rates(name, constants, si).q_total * 3600.0
        np.testing.assert_allclose(samples.loc[rows, "q_true"], expected, rtol=1e-10)
    # Not the Sachdeva truth: the rates differ from the plain mechanistic model.
    assert field.truth["truth_versus_plain_model"]["mean_abs_rel_change"] > 0.02
    # Measurements are noisy readings of this truth (MPFM within a few percent).
    mpfm = (obs["source"] == "mpfm").to_numpy()
    rel = obs.loc[mpfm, "q_total"].to_numpy() / samples.loc[mpfm, "q_true"].to_numpy() - 1.0
    assert 0.01 < np.std(rel) < 0.08


def test_operators_hold_the_new_truth_on_plateau(fields) -> None:
    """Operators aim at the chosen physics' own rate: the target is that physics at the
    initial opening, so openings stay in range (not all pinned open or shut)."""
    for name in ("bernoulli", "gilbert"):
        choke = fields[name].observations["choke"]
        assert 0.05 < choke.median() < 0.95


def test_valves_per_well_and_gas_lift(tmp_path) -> None:
    base = simulate_field(wells=4, years=1.5, seed=13, physics="bernoulli")
    lifted = simulate_field(
        wells=4,
        years=1.5,
        seed=13,
        physics="bernoulli",
        valves=["linear,sigmoid"],
        gas_lift=0.5,
    )
    phys = lifted.truth["physics"]
    assert phys["valves"] == {"W01": "linear", "W02": "sigmoid", "W03": "linear", "W04": "sigmoid"}
    assert lifted.truth["wells"]["W02"]["valve_family"] == "sigmoid"
    assert len(phys["gas_lift"]) == 2
    for well, lift in phys["gas_lift"].items():
        start = pd.Timestamp(lift["start"])
        a = base.observations[(base.observations["well"] == well)]
        b = lifted.observations[(lifted.observations["well"] == well)]
        after_a = a[a["time"] >= start]["eta_gas"].to_numpy()
        after_b = b[b["time"] >= start]["eta_gas"].to_numpy()
        # Lift gas at the choke: a higher gas fraction once the injection starts ...
        assert np.median(after_b) > np.median(after_a) * 1.02
        before = b[b["time"] < start - pd.Timedelta(days=1)]["eta_gas"].to_numpy()
        if len(before):  # ... and the same one before (same random streams).
            ref = a[a["time"] < start - pd.Timedelta(days=1)]["eta_gas"].to_numpy()
            assert np.median(before) == pytest.approx(np.median(ref), rel=0.05)
    unlifted = [w for w in ("W01", "W02", "W03", "W04") if w not in phys["gas_lift"]]
    for well in unlifted:
        if well == "W01" or well == "W03":  # linear valve and no lift: the same well
            pd.testing.assert_frame_equal(
                base.observations[base.observations["well"] == well].reset_index(drop=True),
                lifted.observations[lifted.observations["well"] == well].reset_index(drop=True),
            )
    # The files keep their format and load.
    path = tmp_path / "lifted.parquet"
    write_field(lifted, path)
    assert len(load_observations(path).frame) == len(lifted.observations)
    truth, _ = load_truth(path)
    assert truth["physics"]["gas_lift_share"] == 0.5


def test_option_errors_list_the_choices() -> None:
    with pytest.raises(ConfigError, match="sachdeva, bernoulli, gilbert"):
        simulate_field(**SMALL, physics="ideal")
    with pytest.raises(ConfigError, match="linear, equal_percentage, quick_opening"):
        parse_valves("linear,butterfly")
    with pytest.raises(ConfigError, match="Sachdeva truth only"):
        simulate_field(**SMALL, physics="bernoulli", hidden=["slip"])
    with pytest.raises(ConfigError, match="not both"):
        simulate_field(**SMALL, valves="sigmoid", hidden=["valve"])
    with pytest.raises(ConfigError, match="0..1"):
        simulate_field(**SMALL, gas_lift=1.5)
    assert parse_valves("mixed") == list(physics.AREA_FUNCTIONS)


def test_cli_physics_option(tmp_path, capsys) -> None:
    out = tmp_path / "f.csv"
    argv = ["simulate", "--out", str(out), "--wells", "2", "--years", "0.5", "--seed", "13"]
    rc = main([*argv, "--physics", "gilbert", "--valves", "mixed", "--gas-lift", "0.5", "--quiet"])
    assert rc == 0
    truth, samples = load_truth(out)
    assert truth["physics"]["name"] == "gilbert"
    assert truth["physics"]["gilbert_correlation"] == {"W01": "gilbert", "W02": "ros"}
    assert truth["physics"]["valves"] == {"W01": "linear", "W02": "equal_percentage"}
    assert len(samples) == len(load_observations(out).frame)
    capsys.readouterr()
    rc = main([*argv, "--physics", "ideal_gas", "--quiet"])
    assert rc == 2
    err = capsys.readouterr().err
    assert "Unknown simulator physics 'ideal_gas'" in err
    assert "sachdeva, bernoulli, gilbert" in err
