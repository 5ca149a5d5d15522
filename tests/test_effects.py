"""Candidate effects: each hook checked against the physics by hand, the protocol, the registry."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch

from vfm_core import physics as ph
from vfm_core.checks import EFFECT_CHECKS, check_effect
from vfm_core.data import make_batch
from vfm_core.effects import (
    DEFAULT_CANDIDATES,
    EFFECTS,
    Effect,
    Prior,
    add_features,
    resolve_effect,
    standard_features,
)
from vfm_core.errors import ConfigError
from vfm_core.jobs.study import mape, run_prequential
from vfm_core.models import Mechanistic, make_model
from vfm_core.simulate import simulate_field

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


@pytest.fixture(scope="module")
def small() -> pd.DataFrame:
    field = simulate_field(wells=2, years=1.0, seed=3, start="2018-07-01")
    return add_features(field.observations, list(EFFECTS))


def _batch(frame: pd.DataFrame, model: object) -> object:
    wells = sorted(frame["well"].unique())
    rows = np.flatnonzero(frame["source"].isin(["mpfm", "well_test"]).to_numpy())[:400]
    return make_batch(frame, wells, rows, extra_columns=model.extra_columns)  # type: ignore[attr-defined]


def _fitted_pair(frame: pd.DataFrame, effects: list[str]) -> tuple[Mechanistic, object, object]:
    wells = sorted(frame["well"].unique())
    ext = make_model("mm", wells, effects=effects)
    batch = _batch(frame, ext)
    ext.setup(batch)  # type: ignore[arg-type]
    base = Mechanistic(wells)
    base.setup(batch)  # type: ignore[arg-type]
    return base, ext, batch


def test_registry_names_and_errors() -> None:
    assert set(DEFAULT_CANDIDATES) <= set(EFFECTS)
    assert {"valve_equal_percentage", "valve_sigmoid", "erosion_time"} <= set(EFFECTS)
    with pytest.raises(ConfigError, match="choose one of"):
        resolve_effect("erosoin")
    with pytest.raises(ConfigError, match="Cannot import"):
        resolve_effect("no_such_module_xyz:Thing")
    with pytest.raises(ConfigError, match="Effect subclass"):
        resolve_effect("vfm_core.physics:Prior")
    with pytest.raises(ConfigError, match="extend the models"):
        make_model("nn", ["A"], effects=["erosion"])
    with pytest.raises(ConfigError, match="twice"):
        make_model("mm", ["A"], effects=["erosion", "erosion"])


def test_user_class_by_module_path(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.syspath_prepend(str(EXAMPLES))
    cls = resolve_effect("my_effects:WaterCutCurve")
    assert issubclass(cls, Effect) and cls.name == "water_cut_curve"
    sys.modules.pop("my_effects", None)


def test_effects_off_at_prior_give_the_base_model(small: pd.DataFrame) -> None:
    # erosion, valve and meter bias are off at their prior means: exactly the plain mm
    base, ext, batch = _fitted_pair(small, ["erosion", "valve", "mpfm_bias"])
    q_base = base.predict_batch(batch)  # type: ignore[arg-type]
    q_ext = ext.predict_batch(batch)  # type: ignore[arg-type]
    assert torch.allclose(q_base, q_ext, rtol=1e-10)
    assert float(ext.prior_penalty().detach().abs().max()) == 0.0


def test_real_gas_slip_critical_match_physics_at_strength_one(small: pd.DataFrame) -> None:
    wells = sorted(small["well"].unique())
    for name, kwargs in [("real_gas", "z"), ("slip", "slip"), ("critical_ratio", "p_cr")]:
        ext = make_model("mm", wells, effects=[name])
        batch = _batch(small, ext)
        ext.setup(batch)  # type: ignore[arg-type]
        theta = {k: v.unsqueeze(1) for k, v in ext.theta().items()}
        u, p_up, p_down, t_up, eg, eo = batch.x.unbind(-1)  # type: ignore[attr-defined]
        p1, p2, t1 = p_up * 1e5, p_down * 1e5, t_up + 273.15
        kw = dict(
            rho_oil=theta["rho_oil"],
            rho_wat=theta["rho_wat"],
            kappa=theta["kappa"],
            m_gas=theta["m_gas"],
            p_cr=theta["p_cr"],
        )
        if kwargs == "z":
            kw["z"] = ph.z_factor_papay(p1, t1, theta["m_gas"])
        elif kwargs == "slip":
            kw["slip"] = True
        else:
            rho_g1 = ph.gas_density(p1, t1, theta["m_gas"])
            v_liq = ph.liquid_specific_volume(eg, eo, theta["rho_oil"], theta["rho_wat"])
            kw["p_cr"] = ph.sachdeva_critical_ratio(
                eg, rho_g1, v_liq, theta["kappa"], iterations=30
            )
        area = (theta["c_d"] * ext.a_max.unsqueeze(1)) * u  # type: ignore[attr-defined]
        expected = (
            area
            * ph.choke_mass_flux(p1, p2, t1, eg, eo, **kw)
            * ph.standard_volume_per_mass(
                eg, eo, rho_oil=theta["rho_oil"], rho_wat=theta["rho_wat"], m_gas=theta["m_gas"]
            )
            * 3600
        )
        got = ext.predict_batch(batch)  # type: ignore[arg-type]
        assert torch.allclose(got, expected, rtol=1e-9), name


def test_erosion_and_meter_bias_by_hand(small: pd.DataFrame) -> None:
    base, ext, batch = _fitted_pair(small, ["erosion", "mpfm_bias"])
    with torch.no_grad():
        ext.effect_params["erosion"].z[:] = 1.0  # rate = 0.05 per year-equivalent  # type: ignore[index]
        ext.effect_params["mpfm_bias"].z[:, 0] = 1.2  # bias = +6 %  # type: ignore[index]
    ratio = ext.predict_batch(batch) / base.predict_batch(batch)  # type: ignore[arg-type]
    worn = 1.0 + 0.05 * batch.extra[..., list(batch.extra_names).index("throughput_years")]  # type: ignore[attr-defined]
    meter = torch.where(batch.well_test, torch.ones_like(worn), torch.full_like(worn, 1.06))  # type: ignore[attr-defined]
    assert torch.allclose(ratio, worn * meter, rtol=1e-9)
    params = ext.physical_parameters()
    assert params["erosion.rate"][0] == pytest.approx(0.05)
    assert params["mpfm_bias.bias"][0] == pytest.approx(0.06)


def test_valve_curve_monotone_and_anchored(small: pd.DataFrame) -> None:
    _, ext, batch = _fitted_pair(small, ["valve"])
    valve = ext.effects[0]  # type: ignore[attr-defined]
    u = torch.linspace(0.01, 1.0, 200, dtype=torch.float64).unsqueeze(0)
    slopes = torch.exp(torch.tensor([[-2.0, -1.0, 0.0, 0.5, 1.0, 2.0]], dtype=torch.float64))
    curve = valve._curve(u, slopes)
    assert bool((curve.diff(dim=1) > 0).all())
    # at the well's median opening the factor is 1 whatever the shape
    z = torch.zeros(1, 1, dtype=torch.float64)
    p = {f"log_slope_{k + 1}": z + float(k) - 2.0 for k in range(6)}

    class Inputs:
        u_ref = torch.tensor([[0.4]], dtype=torch.float64)

    Inputs.u = Inputs.u_ref  # type: ignore[attr-defined]
    assert float(valve.area_factor(Inputs, p)) == pytest.approx(1.0)


def test_projection_keeps_bounds_and_gradients_flow(small: pd.DataFrame) -> None:
    _, ext, batch = _fitted_pair(small, ["erosion", "real_gas", "slip"])
    q = ext.forward_batch(batch)  # type: ignore[arg-type]
    q.sum().backward()
    for name in ("erosion", "real_gas", "slip"):
        grad = ext.effect_params[name].z.grad  # type: ignore[index]
        assert grad is not None and bool(torch.isfinite(grad).all()) and float(grad.abs().sum()) > 0
    with torch.no_grad():
        ext.effect_params["erosion"].z[:] = -5.0  # type: ignore[index]
    ext.project_()
    assert float(ext.physical_parameters()["erosion.rate"].min()) == 0.0  # wear never shrinks


#: every registered effect (``suggest`` with the driver it needs), and a user's class
CONTRACT = [
    *(("suggest:driver=t_up" if name == "suggest" else name) for name in EFFECTS),
    "my_effects:TemperatureScale",
]
CASES = [(effect, check) for effect in CONTRACT for check in EFFECT_CHECKS]


@pytest.mark.parametrize(
    ("effect", "check"),
    CASES,
    ids=[f"{e}-{c.__name__.removeprefix('check_effect_')}" for e, c in CASES],
)
def test_effect_contract(effect: str, check, monkeypatch: pytest.MonkeyPatch) -> None:
    """The public check suite (vfm_core.checks) over every effect: a valid prior; mm, hem
    and ham take it (name, finite rates, its parameters reported, rebuilt from their
    hyperparameters); gradients reach its parameters and the projection keeps them
    in bounds; and the model contract of mm with it, fast paths included (one stacked
    update of many wells equals each well's own)."""
    monkeypatch.syspath_prepend(str(EXAMPLES))
    assert check_effect(effect, checks=[check]) == [check.__name__]
    sys.modules.pop("my_effects", None)


def test_the_effect_checks_can_fail() -> None:
    """An effect whose parameter never reaches the rate is caught."""
    from vfm_core.checks import check_effect_gradients_and_bounds

    class Idle(Effect):
        name = "idle"
        parameters = {"k": Prior(0.0, 0.1, -1.0, 1.0, "-", "a scale nothing uses")}

        def output_factor(self, inputs, p):  # type: ignore[no-untyped-def]
            return torch.ones_like(inputs.u) + 0.0 * p["k"].detach()

    with pytest.raises(AssertionError, match="no (finite )?gradient reaches its parameters"):
        check_effect(Idle, checks=[check_effect_gradients_and_bounds])


def test_hem_and_ham_take_effects(small: pd.DataFrame) -> None:
    wells = sorted(small["well"].unique())
    for base in ("hem", "ham"):
        model = make_model(base, wells, effects=["erosion", "real_gas"])
        batch = _batch(small, model)
        model.setup(batch)  # type: ignore[arg-type]
        q = model.predict_batch(batch)  # type: ignore[arg-type]
        assert bool(torch.isfinite(q).all())
        assert "erosion.rate" in model.physical_parameters()
        assert model.name == f"{base}+erosion+real_gas"


def test_features_use_only_the_past_and_do_not_mutate(small: pd.DataFrame) -> None:
    frame = small.drop(columns=["years_on", "throughput_years"])
    before = frame.copy()
    feats = standard_features(frame)
    pd.testing.assert_frame_equal(frame, before)
    # changing a row's own measured rate does not change its throughput
    changed = frame.copy()
    k = int(
        np.flatnonzero(changed["q_total"].notna().to_numpy())[-50]
    )  # after the 90-day scale window
    changed.loc[changed.index[k], "q_total"] *= 10.0
    assert (
        standard_features(changed)["throughput_years"].iloc[k] == feats["throughput_years"].iloc[k]
    )
    assert (feats.groupby(frame["well"])["throughput_years"].diff().dropna() >= 0).all()


def test_plain_forward_refuses_when_features_are_needed(small: pd.DataFrame) -> None:
    _, ext, batch = _fitted_pair(small, ["erosion"])
    with pytest.raises(ConfigError, match="forward_batch"):
        ext.forward(batch.x)  # type: ignore[attr-defined]
    _, gas, batch2 = _fitted_pair(small, ["real_gas"])
    assert torch.allclose(gas.predict(batch2.x), gas.predict_batch(batch2))  # type: ignore[attr-defined]


def test_factory_runs_prequentially_and_learns_hidden_wear() -> None:
    field = simulate_field(
        wells=2, years=2.0, seed=5, start="2017-01-01", hidden=["erosion:rate=0.15"]
    )
    frame = add_features(field.observations, ["erosion"])
    kw = dict(split="2018-01-01", method="pbl:3650d")
    base = run_prequential(frame, "mm", **kw)  # type: ignore[arg-type]
    ext = run_prequential(frame, "mm", effects=["erosion"], **kw)  # type: ignore[arg-type]
    assert mape(ext.predictions.predicted, ext.predictions.measured) < mape(
        base.predictions.predicted, base.predictions.measured
    )
    assert float(ext.final_model.physical_parameters()["erosion.rate"].min()) > 0.05  # type: ignore[union-attr]


def test_a_user_effect_needs_a_valid_prior() -> None:
    class Broken(Effect):
        name = "broken"
        parameters = {"x": Prior(0.0, 0.0, -1.0, 1.0, "-", "nothing")}

    with pytest.raises(ConfigError, match="std > 0"):
        resolve_effect(Broken)


def test_hyper_names_rebuild_the_model(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.syspath_prepend(str(EXAMPLES))
    model = make_model("mm", ["A"], effects=["erosion", "my_effects:TemperatureScale"])
    assert model.hyper["effects"] == ["erosion", "my_effects:TemperatureScale"]
    again = make_model("mm", ["A"], effects=model.hyper["effects"])
    assert list(again.state_dict()) == list(model.state_dict())
    sys.modules.pop("my_effects", None)


# --- effects in the streaming learner (the service) ---------------------------------------------
def test_feature_tracker_matches_the_offline_features() -> None:
    from vfm_core.features import FeatureTracker

    frame = simulate_field(wells=1, years=1.0, seed=5, start="2018-01-01").observations
    tracker = FeatureTracker()
    got = []
    for row in frame.itertuples():
        t = pd.Timestamp(row.time).value
        got.append(tracker.advance(t, row.eta_gas, row.eta_oil))
        if np.isfinite(row.q_total):
            tracker.measured(t, row.q_total)
    ref = standard_features(frame)[list(FeatureTracker.names)].to_numpy()
    # after the first 90 days (whose median rate sets the throughput scale) they agree exactly
    late = (frame["time"] > pd.Timestamp("2018-04-02", tz="UTC")).to_numpy()
    np.testing.assert_allclose(np.asarray(got)[late], ref[late], rtol=1e-9, atol=1e-12)
    assert ref[late, 1].max() > 0.5  # throughput really grows
    # and a tracker built from the frame continues where the stream is
    rebuilt, feats = FeatureTracker.from_frame(frame)
    np.testing.assert_allclose(feats, ref)
    assert rebuilt.state()["cumulative"] == pytest.approx(tracker.state()["cumulative"])
    # a history shorter than 90 days, then the stream: the same features once 90 days are over
    early = (frame["time"] < pd.Timestamp("2018-03-01", tz="UTC")).to_numpy()
    short, _ = FeatureTracker.from_frame(frame[early])
    assert short.scale is None
    rest = []
    for row in frame[~early].itertuples():
        t = pd.Timestamp(row.time).value
        rest.append(short.advance(t, row.eta_gas, row.eta_oil))
        if np.isfinite(row.q_total):
            short.measured(t, row.q_total)
    np.testing.assert_allclose(np.asarray(rest)[late[~early]], ref[late], rtol=1e-9, atol=1e-12)


def test_feature_tracker_scale_is_the_median_of_the_early_rates_so_far() -> None:
    """In a well's first 90 days the throughput scale is the median of the rates measured so
    far: exactly ``np.median`` of them after every measurement (odd and even counts, equal
    rates, rates out of order), through a state round trip, and then fixed."""
    from vfm_core.features import FeatureTracker

    rng = np.random.default_rng(3)
    rates = np.concatenate([rng.lognormal(4.0, 0.5, 300), [55.0] * 7, rng.uniform(1, 9, 40)])
    rng.shuffle(rates)
    tracker = FeatureTracker()
    t0 = 1_500_000_000 * 10**9
    seen: list[float] = []
    for i, q in enumerate(rates):
        t = t0 + i * 600 * 10**9  # every 10 minutes: all within the first 90 days
        tracker.advance(t, 0.1, 0.8)
        tracker.measured(t, float(q))
        seen.append(float(q))
        assert tracker._scale() == float(np.median(seen)), i
        if i == 150:
            tracker = FeatureTracker.from_state(tracker.state())
            assert tracker._scale() == float(np.median(seen))
    tracker.measured(t0, float("nan"))  # not a rate: ignored
    assert tracker._scale() == float(np.median(seen))
    # the 90 days end: the scale is fixed at the median of the early rates
    tracker.advance(t0 + 91 * 86400 * 10**9, 0.1, 0.8)
    assert tracker.scale == float(np.median(seen))
    tracker.measured(t0 + 91 * 86400 * 10**9, 1e6)
    assert tracker._scale() == float(np.median(seen))


def test_feature_tracker_advances_a_block_as_row_by_row() -> None:
    """``advance_many`` (a block of samples between measurements) gives the features and
    the state that ``advance`` row by row gives: across the 90-day mark that fixes the
    scale, over a gap longer than 48 h, and with a step backwards in time."""
    from vfm_core.features import FeatureTracker

    rng = np.random.default_rng(3)
    day = 24 * 3600 * 10**9
    times = np.cumsum(rng.integers(1, 3 * day, size=200)).astype(np.int64)
    times[50] = times[49] - day  # a step backwards integrates nothing
    times[120:] += 5 * day  # a gap longer than 48 h
    gas, oil = rng.uniform(0, 0.5, 200), rng.uniform(0, 0.4, 200)
    rows, block = FeatureTracker(), FeatureTracker()
    got: list[np.ndarray] = []
    want: list[list[float]] = []
    start = 0
    for stop in (1, 30, 31, 90, 160, 200):  # a measurement after each block
        want += [
            rows.advance(int(t), g, o)
            for t, g, o in zip(times[start:stop], gas[start:stop], oil[start:stop], strict=True)
        ]
        got.append(block.advance_many(times[start:stop], gas[start:stop], oil[start:stop]))
        q = float(rng.uniform(50, 150))
        rows.measured(int(times[stop - 1]), q)
        block.measured(int(times[stop - 1]), q)
        start = stop
    np.testing.assert_array_equal(np.concatenate(got), np.asarray(want))
    assert block.state() == rows.state()
    assert rows.scale is not None and np.asarray(want)[:, 1].max() > 0.1  # both rules ran
    assert FeatureTracker().advance_many(times[:0], gas[:0], oil[:0]).shape == (0, 3)


def test_streaming_learner_with_an_effect_learns_the_wear() -> None:
    from vfm_core.learning.streaming import WellLearner

    frame = simulate_field(
        wells=1, years=1.5, seed=2, start="2017-01-01", hidden=["erosion:rate=0.3"]
    ).observations
    split = pd.Timestamp("2017-06-01", tz="UTC")
    cols = ["choke", "p_up", "p_down", "t_up", "eta_gas", "eta_oil"]
    hist = frame[(frame["time"] < split) & frame["q_total"].notna()]
    errors: dict[str, float] = {}
    learners = {}
    for effects in ([], ["erosion"]):
        learner = WellLearner("W01", "mm", "pbl:3650d", effects=effects)
        learner.fit_history(
            torch.tensor(hist[cols].to_numpy()),
            torch.tensor(hist["q_total"].to_numpy()),
            torch.tensor(pd.DatetimeIndex(hist["time"]).as_unit("ns").asi8),
        )
        ape = []
        for row in frame[frame["time"] >= split].itertuples():
            inputs = [getattr(row, c) for c in cols]
            q = learner.predict(inputs, when=row.time)["q_total"]
            if np.isfinite(row.q_total):
                ape.append(abs(q - row.q_total) / row.q_total)
                learner.learn(inputs, row.q_total, row.time, row.source)
        errors[learner.name] = 100 * float(np.mean(ape))
        learners[learner.name] = learner
    # fitted once on five months: only the model with wear extrapolates it
    assert errors["mm+erosion"] < 0.5 * errors["mm"], errors
    ext = learners["mm+erosion"]
    assert ext.physical_parameters()["erosion.rate"]["value"] > 0.1
    # a checkpoint brings the effect model back, with the same predictions
    back = WellLearner.restore(ext.checkpoint())
    sample = [0.5, 60.0, 20.0, 70.0, 0.1, 0.6]
    assert back.name == "mm+erosion" and back.predict(sample) == ext.predict(sample)
    # another model on the same history: compared on the latest fifth, version moves on
    new, scores = learners["mm"].refit_as(effects=["erosion"])
    assert new.name == "mm+erosion" and new.version == learners["mm"].version + 1
    assert new.remembered == learners["mm"].remembered
    assert scores["after"] < 0.5 * scores["before"], scores


def test_effect_settings_are_read_and_checked() -> None:
    from vfm_core.effects import effect_spec

    class Scaled(Effect):
        name = "scaled"
        parameters = {"k": Prior(0.0, 0.1, -1.0, 1.0, "-", "a scale")}
        settings = {"basis": "what the scale applies to"}
        basis = "rate"

    cls = resolve_effect(Scaled)
    assert cls is Scaled
    configured = Scaled.configure(basis="pressure")
    assert configured.basis == "pressure" and issubclass(configured, Scaled)
    assert effect_spec(configured).endswith("Scaled:basis=pressure")
    step = resolve_effect("erosion:step_at=2019-06-01T12:30")
    assert effect_spec(step) == "erosion:step_at=2019-06-01T12:30"
    assert resolve_effect(effect_spec(step)).step_at_ns == pd.Timestamp("2019-06-01T12:30Z").value
    assert "step" in step.parameters and "step" not in EFFECTS["erosion"].parameters
    for bad, message in (
        ("erosion:step_at=", "is not a date"),
        ("erosion:step_at=soon", "is not a date"),
        ("erosion:size=0.1", "has no setting size; its settings: step_at"),
        ("real_gas:z=2", "has no setting z; its settings: none .or a parameter to fix: strength"),
        ("real_gas:strength=5", r"strength='5' must be a number in \[-1, 3\]\.$"),
        ("erosion:rate=2", r"rate='2' must be a number in \[0, 1\] 1/yr-eq\.$"),
        ("valve_equal_percentage:weight=much", "must be a number"),
        ("a:b:c", "Cannot read the effect"),
    ):
        with pytest.raises(ConfigError, match=message):
            resolve_effect(bad)


def test_a_parameter_fixed_in_the_spec_is_shared_and_not_learned(small: pd.DataFrame) -> None:
    from vfm_core.effects import effect_spec, fixed_effect

    cls = resolve_effect("valve_equal_percentage:weight=0.8")
    assert effect_spec(cls) == "valve_equal_percentage:weight=0.8"
    assert cls.parameters["weight"].mean == 0.8 and cls.parameters["weight"].std < 1e-6
    assert cls().compiled_factor() is not None  # pinned, not removed: the kernels apply
    assert effect_spec(resolve_effect(effect_spec(cls))) == effect_spec(cls)
    assert effect_spec(fixed_effect(cls, {})) == effect_spec(cls)  # fixing again keeps it
    step = resolve_effect("erosion:step_at=2019-06-01:rate=0.1")
    assert effect_spec(step) == "erosion:step_at=2019-06-01T00:00:rate=0.1"
    assert step.parameters["step"].std == 0.1  # the step is still learned
    wells = sorted(small["well"].unique())
    learned = make_model("mm", wells, effects=["valve_equal_percentage"])
    fixed = make_model("mm", wells, effects=[cls])
    batch = _batch(small, learned)
    learned.setup(batch)  # type: ignore[arg-type]
    fixed.setup(batch)  # type: ignore[arg-type]
    with torch.no_grad():  # the learned one at 0.8 in every well (theta = mu + sigma z)
        learned.effect_block("valve_equal_percentage").z.fill_(0.8 / 0.5)
        learned.a_max.copy_(fixed.a_max)
    q_learned = learned.predict_batch(batch)  # type: ignore[arg-type]
    q_fixed = fixed.predict_batch(batch)  # type: ignore[arg-type]
    assert torch.allclose(q_learned, q_fixed, rtol=1e-10)
    plain = make_model("mm", wells)
    plain.setup(batch)  # type: ignore[arg-type]
    assert not torch.allclose(plain.predict_batch(batch), q_fixed, rtol=1e-3)  # type: ignore[arg-type]
