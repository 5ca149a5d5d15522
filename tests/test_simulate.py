"""The field simulator: its truth against hand-checked choke equations, its noise and timing
against the paper's data, every hidden effect against its documented direction and size,
and its files against the observation loader."""

from __future__ import annotations

import json
import math
import time

import numpy as np
import pandas as pd
import pytest
import torch

from vfm_core import physics
from vfm_core.errors import ConfigError
from vfm_core.observations import load_observations
from vfm_core.simulate import (
    HIDDEN_EFFECTS,
    TRUTH_SAMPLE_COLUMNS,
    SimulatedField,
    load_truth,
    parse_hidden,
    simulate_field,
    truth_paths,
    write_field,
)

INPUTS = ["choke", "p_up", "p_down", "t_up", "eta_gas", "eta_oil"]
SMALL = dict(wells=3, years=1.5, seed=7)


# --- an independent, math-only Sachdeva model (shared/notes/choke-physics.md) -------------


def sachdeva_rate(
    *,
    area_m2: float,
    p1_bar: float,
    p2_bar: float,
    t1_degc: float,
    eta_gas: float,
    eta_oil: float,
    rho_oil: float,
    rho_wat: float,
    kappa: float,
    m_gas: float,
    p_cr: float,
) -> tuple[float, float]:
    """Mass flow (kg/s) and standard-condition total rate (Sm3/h), steps 1-6 of the note."""
    r_gas = 8.314462618
    p1, p2, t1 = p1_bar * 1e5, p2_bar * 1e5, t1_degc + 273.15
    eta_wat = 1.0 - eta_gas - eta_oil
    rho_l = (1.0 - eta_gas) / (eta_oil / rho_oil + eta_wat / rho_wat)  # step 1
    rho_g1 = p1 * m_gas / (r_gas * t1)  # step 2
    p_r = max(p2 / p1, p_cr)  # step 3
    rho_g2 = rho_g1 * p_r ** (1.0 / kappa)  # step 4
    rho_2 = 1.0 / (eta_gas / rho_g2 + (1.0 - eta_gas) / rho_l)
    bracket = (1.0 - eta_gas) * (1.0 - p_r) / rho_l + eta_gas * kappa / (kappa - 1.0) * (
        1.0 / rho_g1 - p_r / rho_g2
    )
    mdot = area_m2 * math.sqrt(2.0 * p1 * rho_2**2 * bracket)  # step 5
    rho_gas_sc = 101325.0 * m_gas / (r_gas * 288.15)
    q = mdot * (eta_gas / rho_gas_sc + eta_oil / rho_oil + eta_wat / rho_wat)  # step 6
    return mdot, q * 3600.0


def plain_rate(field: SimulatedField) -> np.ndarray:
    """The plain mechanistic model (linear valve, Z=1, no slip, constant p_cr and C_D) with
    each well's true parameters, on the field's own recorded inputs, Sm3/h."""
    obs = field.observations
    out = np.full(len(obs), np.nan)
    for well, info in field.truth["wells"].items():
        rows = (obs["well"] == well).to_numpy()

        def col(name: str, rows: np.ndarray = rows) -> torch.Tensor:
            return torch.tensor(obs.loc[rows, name].to_numpy(), dtype=torch.float64)

        fluid = {k: info[k] for k in ("rho_oil", "rho_wat", "m_gas")}
        mdot = physics.choke_mass_flow(
            info["c_d"] * info["a_max_m2"] * col("choke"),
            col("p_up") * 1e5,
            col("p_down") * 1e5,
            col("t_up") + 273.15,
            col("eta_gas"),
            col("eta_oil"),
            kappa=info["kappa"],
            p_cr=info["p_cr"],
            **fluid,
        )
        per_kg = physics.standard_volume_per_mass(col("eta_gas"), col("eta_oil"), **fluid)
        out[rows] = (mdot * per_kg * 3600.0).numpy()
    return out


def years_since_start(field: SimulatedField) -> np.ndarray:
    obs = field.observations
    starts = obs["well"].map({w: pd.Timestamp(i["start"]) for w, i in field.truth["wells"].items()})
    return ((obs["time"] - starts) / pd.Timedelta(days=365.25)).to_numpy()


@pytest.fixture(scope="module")
def plain_field() -> SimulatedField:
    return simulate_field(**SMALL)


# --- the truth ------------------------------------------------------------------------------


def test_hand_worked_example() -> None:
    mdot, q = sachdeva_rate(
        area_m2=0.85 * 0.5 * math.pi / 4 * 0.05**2,
        p1_bar=100.0,
        p2_bar=30.0,
        t1_degc=70.0,
        eta_gas=0.1,
        eta_oil=0.6,
        rho_oil=850.0,
        rho_wat=1025.0,
        kappa=1.3,
        m_gas=0.02,
        p_cr=0.55,
    )
    assert mdot == pytest.approx(40.43, rel=1e-3)
    assert q == pytest.approx(17_354, rel=1e-3)


def test_truth_matches_independent_choke_equations(plain_field: SimulatedField) -> None:
    obs, samples = plain_field.observations, plain_field.truth_samples
    rows = np.linspace(0, len(obs) - 1, 7).astype(int)
    for i in rows:
        row = obs.iloc[i]
        info = plain_field.truth["wells"][row["well"]]
        mdot, q = sachdeva_rate(
            area_m2=info["c_d"] * info["a_max_m2"] * row["choke"],
            p1_bar=row["p_up"],
            p2_bar=row["p_down"],
            t1_degc=row["t_up"],
            eta_gas=row["eta_gas"],
            eta_oil=row["eta_oil"],
            **{k: info[k] for k in ("rho_oil", "rho_wat", "kappa", "m_gas", "p_cr")},
        )
        assert samples["q_true"].iloc[i] == pytest.approx(q, rel=1e-9)
        phases = samples[["q_gas_true", "q_oil_true", "q_water_true"]].iloc[i].sum()
        assert phases == pytest.approx(q, rel=1e-9)
        assert samples["area_m2"].iloc[i] == pytest.approx(
            info["c_d"] * info["a_max_m2"] * row["choke"], rel=1e-12
        )


def test_none_is_the_plain_model(plain_field: SimulatedField) -> None:
    np.testing.assert_allclose(
        plain_field.truth_samples["q_true"], plain_rate(plain_field), rtol=1e-9
    )
    samples = plain_field.truth_samples
    assert (samples["z_true"] == 1.0).all()
    for well, info in plain_field.truth["wells"].items():
        rows = samples["well"] == well
        assert (samples.loc[rows, "c_d_true"] == info["c_d"]).all()
        assert (samples.loc[rows, "p_cr_true"] == info["p_cr"]).all()
    assert plain_field.truth["hidden"] == {}
    named_none = simulate_field(**SMALL, hidden=["none"])
    pd.testing.assert_frame_equal(named_none.observations, plain_field.observations)


# --- shape of the data ----------------------------------------------------------------------


def test_rows_are_physical_ordered_and_aligned(plain_field: SimulatedField) -> None:
    obs, samples = plain_field.observations, plain_field.truth_samples
    assert list(samples.columns) == list(TRUTH_SAMPLE_COLUMNS)
    assert (samples["time"] == obs["time"]).all() and (samples["well"] == obs["well"]).all()
    assert np.isfinite(obs[INPUTS].to_numpy()).all()
    assert ((obs["choke"] > 0) & (obs["choke"] <= 1)).all()
    assert (obs["p_down"] <= obs["p_up"] - 3.0 + 1e-9).all()
    assert obs["p_down"].min() > 0 and obs["t_up"].between(35, 95).all()
    assert (obs["eta_gas"] > 0).all() and (obs["eta_oil"] > 0).all()
    assert (obs["eta_gas"] + obs["eta_oil"] <= 1.0).all()
    has_rate = obs["q_total"].notna()
    assert (has_rate == (obs["source"] != "")).all()
    assert set(obs["source"]) == {"mpfm", "well_test", ""}
    order = obs.sort_values(["time", "well"], kind="stable").index
    assert (order == obs.index).all()
    assert not obs.duplicated(["well", "time", "source"]).any()
    phase_sum = obs.loc[has_rate, ["q_gas", "q_oil", "q_water"]].sum(axis=1)
    np.testing.assert_allclose(phase_sum, obs.loc[has_rate, "q_total"], rtol=1e-12)
    json.dumps(plain_field.truth, allow_nan=False)  # serialisable as it is


def test_default_field_resembles_the_paper() -> None:
    started = time.perf_counter()
    field = simulate_field()
    seconds = time.perf_counter() - started
    obs = field.observations
    counts = obs["source"].value_counts().to_dict()
    print(f"default field: {len(obs):,} rows in {seconds:.2f} s; per source {counts}")
    assert 25_000 <= len(obs) <= 30_000
    assert seconds < 30
    assert 0.005 < counts.get("", 0) / len(obs) < 0.06  # MPFM outages: a few percent
    starts = pd.to_datetime([info["start"] for info in field.truth["wells"].values()])
    assert (starts == pd.Timestamp("2016-01-01", tz="UTC")).sum() >= 2
    assert starts.max() > pd.Timestamp("2017-06-01", tz="UTC")
    assert starts.max() < pd.Timestamp("2019-01-01", tz="UTC")
    assert obs["time"].max() < pd.Timestamp("2021-01-01", tz="UTC")
    # Virtual drift: pressures fall and water cut rises over the history.
    first = obs[obs["time"] < "2017-01-01"]
    last = obs[obs["time"] >= "2020-01-01"]
    assert last["p_up"].mean() < 0.8 * first["p_up"].mean()
    assert (1 - last["eta_gas"] - last["eta_oil"]).mean() > (
        1 - first["eta_gas"] - first["eta_oil"]
    ).mean()
    assert last["choke"].mean() > first["choke"].mean()  # operators open up to hold rate


def test_same_seed_same_field_other_seed_other_field(plain_field: SimulatedField) -> None:
    again = simulate_field(**SMALL)
    pd.testing.assert_frame_equal(again.observations, plain_field.observations)
    pd.testing.assert_frame_equal(again.truth_samples, plain_field.truth_samples)
    assert again.truth == plain_field.truth
    other = simulate_field(**{**SMALL, "seed": SMALL["seed"] + 1})
    assert len(other.observations) != len(plain_field.observations) or not np.allclose(
        other.observations["p_up"], plain_field.observations["p_up"]
    )
    assert other.truth["wells"]["W01"]["c_d"] != plain_field.truth["wells"]["W01"]["c_d"]


def test_effects_keep_the_random_streams(plain_field: SimulatedField) -> None:
    # Row times and fluid shares do not depend on the truth, so they stay identical.
    field = simulate_field(**SMALL, hidden=["erosion,valve,real_gas,slip,critical_ratio"])
    for column in ("time", "well", "source", "eta_gas", "eta_oil"):
        pd.testing.assert_series_equal(field.observations[column], plain_field.observations[column])


# --- measurement noise and sampling -----------------------------------------------------------


def test_measurement_noise_levels() -> None:
    field = simulate_field(wells=3, years=2.0, seed=11)
    obs, samples = field.observations, field.truth_samples
    mpfm = (obs["source"] == "mpfm").to_numpy()
    test = (obs["source"] == "well_test").to_numpy()
    q_true = samples["q_true"].to_numpy()
    rel = obs["q_total"].to_numpy() / q_true - 1.0
    white = obs["q_total"].to_numpy() / (q_true * samples["mpfm_factor"].to_numpy()) - 1.0
    assert 0.02 <= rel[mpfm].std() <= 0.06
    assert 0.005 <= rel[test].std() <= 0.02
    assert (samples.loc[~mpfm, "mpfm_factor"] == 1.0).all()
    for well, info in field.truth["wells"].items():
        rows = mpfm & (obs["well"] == well).to_numpy()
        assert 0.02 <= info["noise"]["mpfm_rel"] <= 0.05
        assert white[rows].std() == pytest.approx(info["noise"]["mpfm_rel"], rel=0.1)
    # Normal meter drift stays small: under ~2 % per year.
    assert np.abs(samples.loc[mpfm, "mpfm_factor"] - 1.0).max() < 0.04


def test_time_between_well_tests_follows_table_c3() -> None:
    field = simulate_field(wells=4, years=4.0, seed=5)
    obs = field.observations
    gaps = np.concatenate(
        [
            np.diff(group["time"].to_numpy()) / np.timedelta64(1, "D")
            for _, group in obs[obs["source"] == "well_test"].groupby("well")
        ]
    )
    assert len(gaps) > 100
    assert 0.35 <= np.mean(gaps < 14) <= 0.65
    assert 0.2 <= np.mean((gaps >= 30) & (gaps < 61)) + np.mean((gaps >= 14) & (gaps < 30)) <= 0.6
    assert gaps.max() < 400


# --- hidden effects -------------------------------------------------------------------------


def relative_change(field: SimulatedField) -> np.ndarray:
    return field.truth_samples["q_true"].to_numpy() / plain_rate(field) - 1.0


def assert_size_recorded(field: SimulatedField, name: str, change: np.ndarray) -> None:
    size = field.truth["hidden"][name]["size"]
    assert size["mean_abs_rel_change"] == pytest.approx(np.mean(np.abs(change)), rel=1e-9)
    assert size["max_abs_rel_change"] == pytest.approx(np.max(np.abs(change)), rel=1e-9)


def test_erosion_grows_with_throughput() -> None:
    field = simulate_field(**SMALL, hidden=["erosion"])
    change = relative_change(field)
    c_d0 = field.observations["well"].map({w: i["c_d"] for w, i in field.truth["wells"].items()})
    wear = field.truth_samples["c_d_true"].to_numpy() / c_d0.to_numpy() - 1.0
    np.testing.assert_allclose(change, wear, atol=1e-12)  # the rate scales with C_D
    assert (change >= 0).all()
    for well in field.truth["wells"]:
        rows = (field.observations["well"] == well).to_numpy()
        assert (np.diff(wear[rows]) >= -1e-15).all()  # never heals
    size = field.truth["hidden"]["erosion"]["size"]
    assert 0.5 * 0.04 <= size["c_d_change_per_year"] <= 1.1 * 0.04
    assert field.truth["hidden"]["erosion"]["params"] == {
        "rate": 0.04,
        "basis": "throughput",
        "step": 0.0,
        "onset": "start",
    }
    assert_size_recorded(field, "erosion", change)


def test_erosion_on_time_with_a_sand_event() -> None:
    field = simulate_field(**SMALL, hidden=["erosion:basis=time:rate=0.05:step=0.1"])
    years = years_since_start(field)
    obs = field.observations
    for well, info in field.truth["wells"].items():
        rows = (obs["well"] == well).to_numpy()
        event = pd.Timestamp(info["sand_event"])
        start, end = pd.Timestamp(info["start"]), pd.Timestamp(info["end"])
        assert start + (end - start) / 2 <= event <= end
        after = (obs.loc[rows, "time"] >= event).to_numpy()
        expected = info["c_d"] * (1 + 0.05 * years[rows]) * np.where(after, 1.1, 1.0)
        np.testing.assert_allclose(field.truth_samples.loc[rows, "c_d_true"], expected, rtol=1e-9)
    assert field.truth["hidden"]["erosion"]["size"]["c_d_change_per_year"] > 0.05


@pytest.mark.parametrize("basis", ["time", "throughput"])
def test_wear_that_starts_at_the_sand_event(basis: str) -> None:
    """onset=event: C_D is the well's own until its sand event, then grows with the time
    (or the volume) since it."""
    field = simulate_field(**SMALL, hidden=[f"erosion:basis={basis}:rate=0.3:onset=event"])
    obs, c_d_true = field.observations, field.truth_samples["c_d_true"].to_numpy()
    for well, info in field.truth["wells"].items():
        rows = (obs["well"] == well).to_numpy()
        days = (obs.loc[rows, "time"] - pd.Timestamp(info["sand_event"])) / pd.Timedelta(days=1)
        before, after = (days < 0).to_numpy(), (days > 30).to_numpy()
        np.testing.assert_allclose(c_d_true[rows][before], info["c_d"], rtol=1e-12)
        assert (c_d_true[rows][after] > info["c_d"]).all()
        if basis == "time":
            expected = info["c_d"] * (1 + 0.3 * np.maximum(days.to_numpy(), 0) / 365.25)
            np.testing.assert_allclose(c_d_true[rows], expected, rtol=1e-8)


@pytest.mark.parametrize("family", ["equal_percentage", "sigmoid", "2"])
def test_valve_characteristic(family: str) -> None:
    spec = [] if family == "equal_percentage" else [f"valve:family={family}"]
    field = simulate_field(**SMALL, hidden=spec or ["valve"])
    name = field.truth["hidden"]["valve"]["params"]["family"]
    assert name == {"2": list(physics.AREA_FUNCTIONS)[2]}.get(family, family)
    assert all(info["valve_family"] == name for info in field.truth["wells"].values())
    u = field.observations["choke"].to_numpy()
    fraction = physics.area_fraction(torch.tensor(u, dtype=torch.float64), name).numpy()
    change = relative_change(field)
    np.testing.assert_allclose(change + 1.0, fraction / u, rtol=1e-9)
    below = u < 1.0
    if name in ("equal_percentage", "convex"):
        assert (change[below] < 0).all()
    elif name == "quick_opening":
        assert (change[below] > 0).all()
    else:  # sigmoid: below linear under half open, above over it
        assert (change[u < 0.5] < 0).all() and (change[(u > 0.5) & below] > 0).all()
    assert_size_recorded(field, "valve", change)


def test_real_gas_raises_the_rate_where_z_below_one() -> None:
    field = simulate_field(**SMALL, hidden=["real_gas"])
    z = field.truth_samples["z_true"].to_numpy()
    ratio = relative_change(field) + 1.0
    assert (z < 1).all() and (z > 0.7).all()
    # Gas-dominated flow: mass flux ~ sqrt(rho_g1) ~ 1/sqrt(Z); the liquid share dilutes it.
    assert (ratio > 1.0).all()
    assert (ratio <= 1.0 / np.sqrt(z) + 1e-12).all()
    assert (ratio >= 0.95 / np.sqrt(z)).all()
    assert_size_recorded(field, "real_gas", ratio - 1.0)


def test_slip_raises_the_rate() -> None:
    field = simulate_field(**SMALL, hidden=["slip"])
    change = relative_change(field)
    assert (change > 0).all()
    assert 0.05 < field.truth["hidden"]["slip"]["size"]["mean_rel_change"] < 0.6
    assert_size_recorded(field, "slip", change)


def test_critical_ratio_never_lowers_the_rate() -> None:
    field = simulate_field(**SMALL, hidden=["critical_ratio"])
    obs, samples = field.observations, field.truth_samples
    change = relative_change(field)
    p_cr = samples["p_cr_true"].to_numpy()
    assert ((p_cr > 0.1) & (p_cr < 0.9)).all() and np.ptp(p_cr) > 0.01
    assert (change >= -1e-12).all()
    constant = obs["well"].map({w: i["p_cr"] for w, i in field.truth["wells"].items()})
    unchoked = (obs["p_down"] / obs["p_up"]).to_numpy() >= np.maximum(p_cr, constant)
    np.testing.assert_allclose(change[unchoked], 0.0, atol=1e-12)
    assert (change[~unchoked] > 0).any()
    assert_size_recorded(field, "critical_ratio", change)


def test_mpfm_bias_moves_only_the_mpfm(plain_field: SimulatedField) -> None:
    field = simulate_field(**SMALL, hidden=["mpfm_bias"])
    obs, base = field.observations, plain_field.observations
    pd.testing.assert_frame_equal(
        obs[["time", "well", "source", *INPUTS]], base[["time", "well", "source", *INPUTS]]
    )
    pd.testing.assert_frame_equal(
        field.truth_samples.drop(columns="mpfm_factor"),
        plain_field.truth_samples.drop(columns="mpfm_factor"),
    )
    mpfm = (obs["source"] == "mpfm").to_numpy()
    test = (obs["source"] == "well_test").to_numpy()
    np.testing.assert_array_equal(obs.loc[test, "q_total"], base.loc[test, "q_total"])
    ratio = obs["q_total"].to_numpy()[mpfm] / base["q_total"].to_numpy()[mpfm]
    np.testing.assert_allclose(ratio, 1.0 + 0.06 + 0.03 * years_since_start(field)[mpfm], rtol=1e-9)
    size = field.truth["hidden"]["mpfm_bias"]["size"]
    assert size["rel_change_per_year"] == pytest.approx(0.03, rel=1e-6)
    assert size["fraction_up"] == 1.0 and size["mean_rel_change"] >= 0.06


def test_a_meter_that_starts_to_read_off(plain_field: SimulatedField) -> None:
    """onset=event: the MPFM reads as before until the truth's meter_event, then 1 + bias +
    drift * years since it; the well tests and the sand event's draw stay as they were."""
    field = simulate_field(**SMALL, hidden=["mpfm_bias:bias=0.1:drift=0.2:onset=event"])
    obs, base = field.observations, plain_field.observations
    mpfm = (obs["source"] == "mpfm").to_numpy()
    test = (obs["source"] == "well_test").to_numpy()
    np.testing.assert_array_equal(obs.loc[test, "q_total"], base.loc[test, "q_total"])
    ratio = obs["q_total"].to_numpy() / base["q_total"].to_numpy()
    for well, info in field.truth["wells"].items():
        event = pd.Timestamp(info["meter_event"])
        start, end = pd.Timestamp(info["start"]), pd.Timestamp(info["end"])
        assert start + (end - start) / 2 <= event <= end
        rows = (obs["well"] == well).to_numpy() & mpfm
        days = ((obs["time"] - event) / pd.Timedelta(days=1)).to_numpy()
        on = np.maximum(days, 0.0) / 365.25
        expected = np.where(days >= 0, 1.1 + 0.2 * on, 1.0)
        # rtol 1e-8: the recorded meter_event is rounded to the second (0.2/yr: 6e-9 a second)
        np.testing.assert_allclose(ratio[rows], expected[rows], rtol=1e-8)
    assert field.truth["hidden"]["mpfm_bias"]["params"]["onset"] == "event"
    assert "meter_event" not in plain_field.truth["wells"]["W01"]


def test_hidden_as_mapping_fills_defaults() -> None:
    field = simulate_field(wells=1, years=0.5, hidden={"erosion": {"rate": 0.1}, "slip": {}})
    assert field.truth["hidden"]["erosion"]["params"] == {
        "rate": 0.1,
        "basis": "throughput",
        "step": 0.0,
        "onset": "start",
    }
    assert set(field.truth["hidden"]) == {"erosion", "slip"}
    for spec in HIDDEN_EFFECTS.values():
        assert spec.description and spec.direction


# --- files ------------------------------------------------------------------------------------


@pytest.mark.parametrize("suffix", [".parquet", ".csv"])
def test_write_load_round_trip(tmp_path, suffix: str) -> None:
    field = simulate_field(wells=2, years=0.5, seed=3, hidden=["erosion:step=0.1", "mpfm_bias"])
    out = tmp_path / f"field{suffix}"
    written = write_field(field, out)
    json_path, samples_path = truth_paths(out)
    assert written == [out, json_path, samples_path]
    assert json_path.name == "field.truth.json"
    assert samples_path.name == f"field.truth{suffix}"
    loaded = load_observations(out)
    assert loaded.removed == {} and loaded.n_read == len(field.observations)
    assert not loaded.reordered
    pd.testing.assert_frame_equal(loaded.frame, field.observations, check_exact=False, rtol=1e-12)
    truth, samples = load_truth(out)
    assert truth == field.truth
    pd.testing.assert_frame_equal(samples, field.truth_samples, check_exact=False, rtol=1e-12)


def test_load_truth_missing_file_says_what_to_do(tmp_path) -> None:
    with pytest.raises(ConfigError, match="write_field"):
        load_truth(tmp_path / "nothing.parquet")


# --- parse_hidden ----------------------------------------------------------------------------


def test_parse_hidden_forms() -> None:
    assert parse_hidden(["none"]) == {}
    assert parse_hidden([]) == {}
    assert set(parse_hidden(["erosion,real_gas"])) == {"erosion", "real_gas"}
    parsed = parse_hidden(["erosion:rate=0.06:step=0.1", "slip"])
    erosion = {"rate": 0.06, "basis": "throughput", "step": 0.1, "onset": "start"}
    assert parsed == {"erosion": erosion, "slip": {}}
    assert parse_hidden(["valve:family=sigmoid"])["valve"] == {"family": "sigmoid"}
    assert parse_hidden(["valve:family=1"])["valve"] == {"family": list(physics.AREA_FUNCTIONS)[1]}
    assert parse_hidden(["mpfm_bias:bias=-0.05"])["mpfm_bias"] == {
        "bias": -0.05,
        "drift": 0.03,
        "onset": "start",
    }


def test_parse_hidden_errors_name_the_valid_choices() -> None:
    with pytest.raises(ConfigError) as unknown:
        parse_hidden(["erosoin"])
    for name in ("none", *HIDDEN_EFFECTS):
        assert name in str(unknown.value)
    with pytest.raises(ConfigError, match="rate.*basis.*step"):
        parse_hidden(["erosion:speed=2"])
    with pytest.raises(ConfigError, match="takes no parameters"):
        parse_hidden(["slip:s=2"])
    with pytest.raises(ConfigError, match="cannot be combined"):
        parse_hidden(["none", "erosion"])
    with pytest.raises(ConfigError, match="equal_percentage"):
        parse_hidden(["valve:family=butterfly"])
    with pytest.raises(ConfigError, match="number in"):
        parse_hidden(["erosion:rate=fast"])
    with pytest.raises(ConfigError, match="twice"):
        parse_hidden(["erosion", "erosion:rate=0.1"])
    with pytest.raises(ConfigError, match="key=value"):
        parse_hidden(["erosion:rate"])
    with pytest.raises(ConfigError, match="Unknown hidden effect"):
        simulate_field(wells=1, years=0.5, hidden={"sand": {}})


def test_sample_every_puts_every_wells_samples_on_a_grid(tmp_path, capsys) -> None:
    """``vfm simulate --sample-every 7``: every well's sensor rows (the well tests keep their
    own times) a whole number of weeks apart (a field that logs weekly), the same frame as ``simulate_field(sample_every_days=7)``;
    a bad value and the separator (daily by definition) are refused with a sentence."""
    from vfm_core.cli import main

    out = tmp_path / "weekly.parquet"
    args = ["simulate", "--out", str(out), "--wells", "2", "--years", "1", "--seed", "5"]
    assert main([*args, "--sample-every", "7", "--quiet"]) == 0
    frame = pd.read_parquet(out)
    expected = simulate_field(wells=2, years=1, seed=5, sample_every_days=7).observations
    pd.testing.assert_frame_equal(frame.reset_index(drop=True), expected.reset_index(drop=True))
    for _, g in frame[frame["source"] != "well_test"].groupby("well"):
        gaps = g["time"].drop_duplicates().diff().dropna() / pd.Timedelta(days=7)
        assert len(gaps) > 20 and np.allclose(gaps, gaps.round()), gaps.describe()
    capsys.readouterr()
    assert main([*args, "--sample-every", "0"]) == 2
    assert "0.01 to 365" in capsys.readouterr().err
    assert main([*args, "--sample-every", "7", "--separator"]) == 2
    assert "does not go with --separator" in capsys.readouterr().err
