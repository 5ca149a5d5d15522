"""One contract suite over every registered model, the physics models with effects included."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
import torch

from vfm_core.data import make_batch, target_mask
from vfm_core.effects import add_features
from vfm_core.errors import ConfigError
from vfm_core.jobs.study import wells_of
from vfm_core.learning import DEFAULT_TRAIN, fit_batch, parse_method
from vfm_core.models import MODELS, load_model, make_model, save_model
from vfm_core.simulate import simulate_field

#: every registered model, and physics models with effects (built through the registry)
SPECS: list[tuple[str, tuple[str, ...]]] = [(name, ()) for name in MODELS] + [
    ("mm", ("erosion",)),
    ("hem", ("valve",)),
    ("ham", ("mpfm_bias", "real_gas")),
]
IDS = ["+".join([name, *effects]) for name, effects in SPECS]


@pytest.fixture(scope="module")
def field() -> pd.DataFrame:
    frame = simulate_field(wells=3, years=1.5, seed=3, start="2018-01-01").observations
    return add_features(frame, ["erosion", "mpfm_bias"])


def _batch(field: pd.DataFrame, rows: np.ndarray, model) -> object:
    return make_batch(field, wells_of(field), rows, extra_columns=model.extra_columns)


def _model(spec: tuple[str, tuple[str, ...]], wells: list[str], seed: int = 0):
    name, effects = spec
    return make_model(name, wells, seed=seed, effects=effects)


@pytest.fixture(scope="module")
def train_rows(field: pd.DataFrame) -> np.ndarray:
    return np.flatnonzero(target_mask(field, "all") & (field["time"] < "2018-12-01").to_numpy())


@pytest.fixture(scope="module")
def train_batch(field: pd.DataFrame, train_rows: np.ndarray):
    return make_batch(field, wells_of(field), train_rows)


def _quick(model_name: str):
    from dataclasses import replace

    return replace(DEFAULT_TRAIN[model_name], max_iter=30, patience=10, default_iter=20)


@pytest.mark.parametrize("spec", SPECS, ids=IDS)
def test_predict_before_learning(spec, field, train_rows) -> None:
    model = _model(spec, wells_of(field))
    batch = _batch(field, train_rows, model)
    before = model.predict_batch(batch)
    assert before.shape == batch.y.shape
    assert torch.isnan(before).all(), "a model with no data must say so (NaN), not guess"
    model.setup(batch)  # statistics only, no learning
    q = model.predict_batch(batch)
    assert torch.isfinite(q[batch.mask]).all()
    assert (q[batch.mask] > 0).all()


@pytest.mark.parametrize("spec", SPECS, ids=IDS)
def test_input_not_mutated(spec, field, train_rows) -> None:
    model = _model(spec, wells_of(field))
    batch = _batch(field, train_rows, model)
    x, y, extra = batch.x.clone(), batch.y.clone(), batch.extra.clone()
    fit_batch(model, batch, _quick(spec[0]))
    model.predict_batch(batch)
    torch.testing.assert_close(batch.x, x, rtol=0, atol=0)
    torch.testing.assert_close(batch.y, y, rtol=0, atol=0)
    torch.testing.assert_close(batch.extra, extra, rtol=0, atol=0)


@pytest.mark.parametrize("spec", SPECS, ids=IDS)
def test_save_load_keeps_predictions(spec, field, train_rows, tmp_path) -> None:
    model = _model(spec, wells_of(field), seed=1)
    batch = _batch(field, train_rows, model)
    fit_batch(model, batch, _quick(spec[0]))
    path = save_model(model, tmp_path / "model.pt")
    # the file is a plain tensor archive: torch refuses pickled objects with weights_only
    torch.load(path, weights_only=True)
    loaded = load_model(path)
    assert loaded.name == model.name
    torch.testing.assert_close(
        loaded.predict_batch(batch), model.predict_batch(batch), rtol=0, atol=0, equal_nan=True
    )


@pytest.mark.parametrize("spec", SPECS, ids=IDS)
def test_same_seed_same_result(spec, field, train_rows) -> None:
    preds = []
    for _ in range(2):
        model = _model(spec, wells_of(field), seed=7)
        batch = _batch(field, train_rows, model)
        fit_batch(model, batch, _quick(spec[0]))
        preds.append(model.predict_batch(batch))
    torch.testing.assert_close(preds[0], preds[1], rtol=0, atol=0, equal_nan=True)


@pytest.mark.parametrize("spec", SPECS, ids=IDS)
def test_one_online_step_lowers_error_on_that_observation(spec, field, train_rows) -> None:
    wells = wells_of(field)
    model = _model(spec, wells)
    fit_batch(model, _batch(field, train_rows, model), _quick(spec[0]))
    # a new observation per well, 10 % above what the model predicts (a clear surprise)
    rows = np.flatnonzero(target_mask(field, "all") & (field["time"] >= "2019-01-01").to_numpy())
    new = _batch(field, rows, model)
    one = new.select(torch.cumsum(new.mask.long(), 1) == 1)
    pred = model.predict_batch(one)
    one.y = torch.where(one.mask, pred * 1.10, one.y)
    err_before = (model.predict_batch(one) - one.y).abs()[one.mask]
    parse_method("ol").bind(model).on_measurement(one)
    err_after = (model.predict_batch(one) - one.y).abs()[one.mask]
    assert (err_after < err_before).all(), f"{spec}: {err_before} -> {err_after}"


@pytest.mark.parametrize(
    "spec",
    [s for s in SPECS if not MODELS[s[0]].gradient_free],
    ids=lambda s: "+".join([s[0], *s[1]]),
)
def test_batch_fit_learns_a_shift(spec, field, train_rows) -> None:
    """Set up on the data, then fit to targets 15 % higher: the error must at least halve."""
    from dataclasses import replace

    model = _model(spec, wells_of(field))
    batch = _batch(field, train_rows, model)
    model.setup(batch)
    shifted = replace(batch, y=batch.y * 1.15)
    m = batch.mask

    def err() -> float:
        q = model.predict_batch(shifted)
        return float(((q - shifted.y).abs() / shifted.y.abs())[m].mean())

    before = err()
    fit_batch(model, shifted, DEFAULT_TRAIN[spec[0]])
    assert err() < 0.5 * before, (before, err())


def test_effects_are_a_constructor_argument_of_the_physics_models_only() -> None:
    model = make_model("ham", ["A"], effects=["erosion"], hidden=[8])
    assert model.name == "ham+erosion" and model.key == "ham"
    assert model.hyper["effects"] == ["erosion"] and model.extra_columns == ("throughput_years",)
    with pytest.raises(ConfigError, match="extend the models"):
        make_model("nn", ["A"], effects=["erosion"])
    with pytest.raises(ConfigError, match="twice"):
        make_model("mm", ["A"], effects=["erosion", "erosion"])


def test_wells_are_independent_in_online_learning(train_batch, field) -> None:
    """A measurement of one well must not move another well's model (Adam momentum included)."""
    model = make_model("mm", train_batch.wells, seed=0)
    fit_batch(model, train_batch, _quick("mm"))
    learner = parse_method("ol").bind(model)
    rows = np.flatnonzero(target_mask(field, "all") & (field["time"] >= "2019-01-01").to_numpy())
    new = make_batch(field, train_batch.wells, rows)
    first = new.select(torch.cumsum(new.mask.long(), 1) == 1)
    learner.on_measurement(first)  # all wells learn once (optimiser state now has momentum)
    z_before = model.phys.z.detach().clone()
    only_first_well = first.select(torch.arange(first.n_wells).unsqueeze(1) == 0)
    learner.on_measurement(only_first_well)
    z_after = model.phys.z.detach()
    assert not torch.equal(z_after[0], z_before[0])
    torch.testing.assert_close(z_after[1:], z_before[1:], rtol=0, atol=0)


def test_physical_parameters_stay_in_bounds(train_batch) -> None:
    from dataclasses import replace

    from vfm_core.physics import PRIORS

    model = make_model("mm", train_batch.wells, seed=0)
    model.setup(train_batch)
    # a wildly wrong target and a huge step: the parameters hit their bounds, not beyond
    wrong = replace(train_batch, y=train_batch.y * 50.0)
    fit_batch(model, wrong, replace(DEFAULT_TRAIN["mm"], lr=5.0, max_iter=50, patience=50))
    for name, values in model.physical_parameters().items():
        if name in PRIORS:
            assert (values >= PRIORS[name].low - 1e-9).all() and (
                values <= PRIORS[name].high + 1e-9
            ).all(), name


def test_unknown_names_list_the_valid_ones() -> None:
    with pytest.raises(ConfigError, match="mm"):
        make_model("gbm", ["W1"])
    with pytest.raises(ConfigError, match="pbl:<period>"):
        parse_method("pbl")
    with pytest.raises(ConfigError, match="positive time span"):
        parse_method("pbl:soon")
    m = parse_method("pbl:14d:window=365d")
    assert m.period == pd.Timedelta(days=14) and m.window == pd.Timedelta(days=365)  # type: ignore[attr-defined]
