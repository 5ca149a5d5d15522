"""One contract suite over every registered model and learner."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
import torch

from vfm_core.data import make_batch, target_mask
from vfm_core.errors import ConfigError
from vfm_core.learners import (
    DEFAULT_ONLINE,
    DEFAULT_TRAIN,
    OnlineLearner,
    fit_batch,
    parse_method,
)
from vfm_core.models import MODELS, load_model, make_model, save_model
from vfm_core.simulate import simulate_field
from vfm_core.jobs.study import wells_of


@pytest.fixture(scope="module")
def field() -> pd.DataFrame:
    return simulate_field(wells=3, years=1.5, seed=3, start="2018-01-01").observations


@pytest.fixture(scope="module")
def train_batch(field: pd.DataFrame):
    rows = np.flatnonzero(target_mask(field, "all") & (field["time"] < "2018-12-01").to_numpy())
    return make_batch(field, wells_of(field), rows)


def _quick(model_name: str):
    from dataclasses import replace

    return replace(DEFAULT_TRAIN[model_name], max_iter=30, patience=10, default_iter=20)


@pytest.mark.parametrize("name", list(MODELS))
def test_predict_before_learning(name: str, train_batch) -> None:
    model = make_model(name, train_batch.wells, seed=0)
    before = model.predict(train_batch.x)
    assert before.shape == train_batch.y.shape
    assert torch.isnan(before).all(), "a model with no data must say so (NaN), not guess"
    model.setup(train_batch)  # statistics only, no learning
    q = model.predict(train_batch.x)
    assert torch.isfinite(q[train_batch.mask]).all()
    assert (q[train_batch.mask] > 0).all()


@pytest.mark.parametrize("name", list(MODELS))
def test_input_not_mutated(name: str, train_batch) -> None:
    x = train_batch.x.clone()
    y = train_batch.y.clone()
    model = make_model(name, train_batch.wells, seed=0)
    fit_batch(model, train_batch, _quick(name))
    model.predict(train_batch.x)
    torch.testing.assert_close(train_batch.x, x, rtol=0, atol=0)
    torch.testing.assert_close(train_batch.y, y, rtol=0, atol=0)


@pytest.mark.parametrize("name", list(MODELS))
def test_save_load_keeps_predictions(name: str, train_batch, tmp_path) -> None:
    model = make_model(name, train_batch.wells, seed=1)
    fit_batch(model, train_batch, _quick(name))
    path = save_model(model, tmp_path / f"{name}.pt")
    # the file is a plain tensor archive: torch refuses pickled objects with weights_only
    torch.load(path, weights_only=True)
    loaded = load_model(path)
    torch.testing.assert_close(
        loaded.predict(train_batch.x), model.predict(train_batch.x), rtol=0, atol=0, equal_nan=True
    )


@pytest.mark.parametrize("name", list(MODELS))
def test_same_seed_same_result(name: str, train_batch) -> None:
    preds = []
    for _ in range(2):
        model = make_model(name, train_batch.wells, seed=7)
        fit_batch(model, train_batch, _quick(name))
        preds.append(model.predict(train_batch.x))
    torch.testing.assert_close(preds[0], preds[1], rtol=0, atol=0, equal_nan=True)


@pytest.mark.parametrize("name", list(MODELS))
def test_one_online_step_lowers_error_on_that_observation(name: str, train_batch, field) -> None:
    model = make_model(name, train_batch.wells, seed=0)
    fit_batch(model, train_batch, _quick(name))
    # a new observation per well, 10 % above what the model predicts (a clear surprise)
    rows = np.flatnonzero(target_mask(field, "all") & (field["time"] >= "2019-01-01").to_numpy())
    new = make_batch(field, train_batch.wells, rows)
    one = new.select(torch.cumsum(new.mask.long(), 1) == 1)
    pred = model.predict(one.x)
    one.y = torch.where(one.mask, pred * 1.10, one.y)
    err_before = (model.predict(one.x) - one.y).abs()[one.mask]
    OnlineLearner(model, DEFAULT_ONLINE[name]).learn(one)
    err_after = (model.predict(one.x) - one.y).abs()[one.mask]
    assert (err_after < err_before).all(), f"{name}: {err_before} -> {err_after}"


@pytest.mark.parametrize("name", [n for n in MODELS if not MODELS[n].gradient_free])
def test_batch_fit_learns_a_shift(name: str, train_batch) -> None:
    """Set up on the data, then fit to targets 15 % higher: the error must at least halve."""
    from dataclasses import replace

    model = make_model(name, train_batch.wells, seed=0)
    model.setup(train_batch)
    shifted = replace(train_batch, y=train_batch.y * 1.15)
    m = train_batch.mask

    def err() -> float:
        q = model.predict(shifted.x)
        return float(((q - shifted.y).abs() / shifted.y.abs())[m].mean())

    before = err()
    fit_batch(model, shifted, DEFAULT_TRAIN[name])
    assert err() < 0.5 * before, (before, err())


def test_wells_are_independent_in_online_learning(train_batch, field) -> None:
    """A measurement of one well must not move another well's model (Adam momentum included)."""
    model = make_model("mm", train_batch.wells, seed=0)
    fit_batch(model, train_batch, _quick("mm"))
    learner = OnlineLearner(model, DEFAULT_ONLINE["mm"])
    rows = np.flatnonzero(target_mask(field, "all") & (field["time"] >= "2019-01-01").to_numpy())
    new = make_batch(field, train_batch.wells, rows)
    first = new.select(torch.cumsum(new.mask.long(), 1) == 1)
    learner.learn(first)  # all wells learn once (optimiser state now has momentum)
    z_before = model.phys.z.detach().clone()
    only_first_well = first.select(torch.arange(first.n_wells).unsqueeze(1) == 0)
    learner.learn(only_first_well)
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
    assert m.period == pd.Timedelta(days=14) and m.window == pd.Timedelta(days=365)
