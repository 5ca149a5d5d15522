"""One contract suite over every registered model, the physics models with effects included."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
import torch

from vfm_core.checks import check_model, model_checks_for
from vfm_core.data import make_batch, target_mask
from vfm_core.effects import add_features
from vfm_core.errors import ConfigError
from vfm_core.jobs.study import wells_of
from vfm_core.learning import DEFAULT_TRAIN, fit_batch, parse_method
from vfm_core.models import MODELS, make_model
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


def _quick(model_name: str):
    from dataclasses import replace

    return replace(DEFAULT_TRAIN[model_name], max_iter=30, patience=10, default_iter=20)


@pytest.fixture(scope="module")
def train_rows(field: pd.DataFrame) -> np.ndarray:
    return np.flatnonzero(target_mask(field, "all") & (field["time"] < "2018-12-01").to_numpy())


@pytest.fixture(scope="module")
def train_batch(field: pd.DataFrame, train_rows: np.ndarray):
    return make_batch(field, wells_of(field), train_rows)


#: (spec, check) for every spec and every check of vfm_core.checks that applies to it
CASES = [(spec, check) for spec in SPECS for check in model_checks_for(spec[0], spec[1])]


@pytest.mark.parametrize(
    ("spec", "check"),
    CASES,
    ids=[f"{'+'.join([s[0], *s[1]])}-{c.__name__.removeprefix('check_model_')}" for s, c in CASES],
)
def test_model_contract(spec, check, field) -> None:
    """The public check suite (vfm_core.checks) over every registered model and the
    physics models with effects: NaN before learning, inputs unchanged, a model file
    predicts the same, same seed same fit, one online step lowers the error, a batch fit
    follows a shift, and the fast paths (stacked and compiled updates) equal the plain one."""
    assert check_model(spec[0], effects=spec[1], checks=[check], frame=field) == [check.__name__]


def test_the_model_checks_can_fail(field) -> None:
    """A model that changes its input, and one that guesses before learning, are caught."""
    from vfm_core.checks import (
        check_model_input_not_mutated,
        check_model_predicts_nan_before_learning,
    )

    def meddling(wells, seed):
        model = make_model("lr", wells, seed=seed)
        plain = model.predict_batch

        def predict_batch(batch):
            batch.y.mul_(1.0 + 1e-9)
            return plain(batch)

        model.predict_batch = predict_batch
        return model

    with pytest.raises(AssertionError, match="changed batch.y"):
        check_model(meddling, checks=[check_model_input_not_mutated], frame=field)

    def guessing(wells, seed):
        model = make_model("lr", wells, seed=seed)
        plain = model.predict_batch
        model.predict_batch = lambda batch: torch.nan_to_num(plain(batch), nan=1.0)
        return model

    with pytest.raises(AssertionError, match="must say so"):
        check_model(guessing, checks=[check_model_predicts_nan_before_learning], frame=field)


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
