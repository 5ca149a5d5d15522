"""The learning methods' group operations (issue 37): each method owns its batching.

``group_key`` / ``predict_group`` and ``learn_key`` / ``learn_group`` of
:class:`vfm_core.learning.LearningMethod`: a method of one's own, written without them, is
grouped for predictions by the default (its model alone) and learns one well at a time;
with a ``learn_group`` of its own, ``learn_many`` calls it once for the group and the
wells end where learning one by one leaves them. The model-side attributes the methods
read (``train_defaults``, ``online_defaults``, ``compiled_as``, ``stack_key``) are checked
against what the registry promises.
"""

from __future__ import annotations

import copy
from collections.abc import Sequence
from dataclasses import replace
from typing import Any

import pandas as pd
import pytest
import torch

from vfm_core.data import Batch, target_mask
from vfm_core.learning import (
    DEFAULT_ONLINE,
    DEFAULT_TRAIN,
    METHODS,
    LearningMethod,
    Memory,
    OnlineLearning,
    OnlineSettings,
    TrainSettings,
    register,
)
from vfm_core.learning.stacking import stacked_rates
from vfm_core.learning.streaming import WellLearner, learn_many, predict_many
from vfm_core.models import MODELS, Mechanistic, make_model
from vfm_core.schema import INPUT_COLUMNS
from vfm_core.simulate import simulate_field

pytestmark = pytest.mark.timeout(300)

WELLS = 3
HISTORY = 50


@pytest.fixture(scope="module")
def field() -> pd.DataFrame:
    frame = simulate_field(wells=WELLS, years=0.5, seed=11, hidden=["erosion"]).observations
    return frame[target_mask(frame, "all")]


def _rows(field: pd.DataFrame, well: str) -> pd.DataFrame:
    return field[field["well"] == well].reset_index(drop=True)


def _fitted(field: pd.DataFrame, method: str, model: str = "mm") -> list[WellLearner]:
    learners = []
    for j in range(WELLS):
        well = f"W{j + 1:02d}"
        rows = _rows(field, well).iloc[: HISTORY + 7 * j]
        learner = WellLearner(
            well, model, method, train=replace(DEFAULT_TRAIN[model], max_iter=30, patience=10)
        )
        learner.fit_history(
            torch.tensor(rows[list(INPUT_COLUMNS)].to_numpy()),
            torch.tensor(rows["q_total"].to_numpy()),
            torch.tensor(pd.DatetimeIndex(rows["time"]).as_unit("ns").asi8),
        )
        learners.append(learner)
    return learners


# -- a method of one's own ---------------------------------------------------------------------
class _Nudge(LearningMethod):
    """A test method: each measurement moves ``mm``'s C_D a small fixed step towards it."""

    key = "test-nudge"
    kind = "test"
    summary = "a fixed step of C_D towards each measurement"
    example = "test-nudge"

    def _learn(self, batch: Batch, memory: Memory | None) -> torch.Tensor:
        model = self.model
        model.setup(batch)
        live = model.ready & (batch.count() > 0)
        if bool(live.any()):
            q = model.predict_batch(batch)[:, 0]
            step = torch.full_like(q, 1e-3)  # C_D in prior standard deviations
            up = torch.where(batch.y[:, 0] > q, step, -step)
            with torch.no_grad():
                model.phys.z[:, -1] += torch.where(live, up, torch.zeros_like(up))
        return live


class _GroupedNudge(_Nudge):
    """The same method, learning its wells in one call (and counting the calls)."""

    key = "test-nudge-grouped"
    example = "test-nudge-grouped"
    calls: list[int] = []

    def learn_key(self) -> Any:
        return ("nudge", self.model.stack_key())

    @classmethod
    def learn_group(
        cls,
        methods: Sequence[LearningMethod],
        batches: Sequence[Batch],
        memories: Sequence[Memory | None],
    ) -> list[bool | None]:
        cls.calls.append(len(methods))
        # the first well is left to learn by itself (None), the others learn here
        return [None] + [
            bool(m._learn(b, mem).any())
            for m, b, mem in zip(methods[1:], batches[1:], memories[1:], strict=True)
        ]


@pytest.fixture(scope="module", autouse=True)
def _registered() -> Any:
    for cls in (_Nudge, _GroupedNudge):
        register(cls)
    yield
    for cls in (_Nudge, _GroupedNudge):
        METHODS.pop(cls.key, None)


def _round(field: pd.DataFrame, k: int) -> tuple[list[list[float]], list[float], list[Any]]:
    rows = [_rows(field, f"W{j + 1:02d}").iloc[HISTORY + 7 * j + k] for j in range(WELLS)]
    return (
        [r[list(INPUT_COLUMNS)].tolist() for r in rows],
        [float(r["q_total"]) for r in rows],
        [r["time"] for r in rows],
    )


@pytest.mark.parametrize("method", ["test-nudge", "test-nudge-grouped"])
def test_a_method_of_ones_own_in_many_wells_calls_equals_one_by_one(
    field: pd.DataFrame, method: str
) -> None:
    one = _fitted(field, method)
    many = copy.deepcopy(one)
    _GroupedNudge.calls.clear()
    closer = []
    for k in range(6):
        xs, qs, whens = _round(field, k)
        before = [lrn.predict(x, w)["q_total"] for lrn, x, w in zip(one, xs, whens, strict=True)]
        expected = [lrn.learn(x, q, w) for lrn, x, q, w in zip(one, xs, qs, whens, strict=True)]
        after = [lrn.predict(x, w)["q_total"] for lrn, x, w in zip(one, xs, whens, strict=True)]
        closer += [abs(q - a) < abs(q - b) for q, a, b in zip(qs, after, before, strict=True)]  # type: ignore[operator]
        assert learn_many(many, xs, qs, whens) == expected
        later = _round(field, k + 1)
        answers = predict_many(many, later[0], later[2])
        for lrn, x, w, got in zip(one, later[0], later[2], answers, strict=True):
            want = lrn.predict(x, w)
            assert got.keys() == want.keys() and want["q_total"] is not None
            for key, value in want.items():
                assert got[key] == (None if value is None else pytest.approx(value, rel=1e-12))
    for a, b in zip(one, many, strict=True):
        torch.testing.assert_close(b.model.phys.z, a.model.phys.z, rtol=1e-12, atol=0)
        assert (a.version, a.n_updates) == (b.version, b.n_updates)
    # the method learned: each measurement moved its well's rate towards it
    assert all(closer), closer
    assert _GroupedNudge.calls == ([WELLS] * 6 if method == "test-nudge-grouped" else [])


def test_the_defaults_group_predictions_by_model_and_learn_alone(field: pd.DataFrame) -> None:
    learners = _fitted(field, "test-nudge")
    keys = {lrn.method.group_key() for lrn in learners}
    assert len(keys) == 1 and None not in keys
    assert all(lrn.method.learn_key() is None for lrn in learners)
    methods = [lrn.method for lrn in learners]
    batches = [Batch(["W"], *_one_sample()) for _ in methods]
    assert LearningMethod.learn_group(methods, batches, [None] * WELLS) == [None] * WELLS
    # another model specification: another group; a subclass's own predict: never grouped
    other = WellLearner("W09", "mm", "test-nudge", effects=["erosion"])
    assert other.method.group_key() not in keys

    class OwnPredict(_Nudge):
        def predict(self, batch: Batch) -> Any:
            return super().predict(batch)

    assert OwnPredict("x").bind(make_model("mm", ["W"])).group_key() is None


def _one_sample() -> tuple[torch.Tensor, ...]:
    x = torch.tensor([[[30e5, 20e5, 350.0, 0.5, 0.2, 0.7]]], dtype=torch.float64)
    return (
        x,
        torch.ones(1, 1, dtype=torch.float64),
        torch.ones(1, 1, dtype=torch.bool),
        torch.zeros(1, 1, dtype=torch.int64),
        torch.zeros(1, 1, dtype=torch.int64),
    )


def test_ol_and_bayes_group_only_what_stacks(field: pd.DataFrame) -> None:
    ol = _fitted(field, "ol")
    assert len({lrn.method.learn_key() for lrn in ol}) == 1
    # other online settings, a schedule, a subclass: another group or none
    other = WellLearner("W09", "mm", "ol", online=replace(DEFAULT_ONLINE["mm"], lr=5e-3))
    assert other.method.learn_key() not in {ol[0].method.learn_key()}
    scheduled = WellLearner("W09", "mm", "ol", online=OnlineSettings(schedule_power=0.5))
    assert scheduled.method.learn_key() is None

    class MyOnline(OnlineLearning):
        pass

    assert MyOnline("ol").bind(make_model("mm", ["W"])).learn_key() is None
    bayes = _fitted(field, "bayes")
    assert len({lrn.method.group_key() for lrn in bayes}) == 1
    assert len({lrn.method.learn_key() for lrn in bayes}) == 1
    drift = WellLearner("W09", "mm", "bayes:drift=2")
    assert drift.method.learn_key() != bayes[0].method.learn_key()
    assert drift.method.group_key() != bayes[0].method.group_key()


def test_stacked_rates_equal_each_models_own(field: pd.DataFrame) -> None:
    for spec in ("mm", "ham"):
        learners = _fitted(field, "ol", model=spec)
        models = [lrn.model for lrn in learners]
        xs, _, _ = _round(field, 0)
        x = torch.tensor(xs, dtype=torch.float64).reshape(WELLS, 1, 6)
        batch = Batch(
            [lrn.well for lrn in learners],
            x,
            torch.zeros(WELLS, 1, dtype=torch.float64),
            torch.ones(WELLS, 1, dtype=torch.bool),
            torch.zeros(WELLS, 1, dtype=torch.int64),
            torch.zeros(WELLS, 1, dtype=torch.int64),
        )
        together = stacked_rates(models, batch)
        alone = torch.cat([m.predict(x[k : k + 1]) for k, m in enumerate(models)], 0)
        torch.testing.assert_close(together, alone, rtol=1e-12, atol=0)
        assert bool((together > 0).all())


# -- the models' attributes ----------------------------------------------------------------------
def test_per_model_defaults_are_the_models_attributes() -> None:
    for name, cls in MODELS.items():
        assert DEFAULT_TRAIN[name] == replace(TrainSettings(), **cls.train_defaults)
        assert DEFAULT_ONLINE[name] == replace(OnlineSettings(), **cls.online_defaults)
    # the values the study's figures were made with
    assert DEFAULT_TRAIN["mm"].lr == 3e-2 and DEFAULT_ONLINE["mm"].lr == 1e-3
    assert DEFAULT_ONLINE["hem"].steps == DEFAULT_ONLINE["ham"].steps == 1
    assert DEFAULT_ONLINE["nn"].optimizer == "sgd"


def test_compiled_as_only_for_the_exact_class_without_effects() -> None:
    wells = ["W01", "W02"]
    expected = {"mm": "mm", "hem": "hem", "ham": "ham", "nn": "nn", "lr": "lr", "mtl": "mtl"}
    for name in MODELS:
        assert make_model(name, wells).compiled_as() == expected.get(name), name
    assert make_model("mm", wells, effects=["erosion"]).compiled_as() is None
    assert make_model("hem", wells, hidden=[8, 8]).compiled_as() is None
    assert make_model("nn", wells, hidden=[16]).compiled_as() is None

    class MyMechanistic(Mechanistic):
        pass

    assert MyMechanistic(wells).compiled_as() is None


def test_stack_key_ignores_the_seed_only() -> None:
    a = make_model("hem", ["W01"], seed=1)
    assert a.stack_key() == make_model("hem", ["W02"], seed=2).stack_key()
    assert a.stack_key() != make_model("hem", ["W01"], hidden=[8]).stack_key()
    assert a.stack_key() != make_model("ham", ["W01"]).stack_key()
    erosion = make_model("mm", ["W01"], effects=["erosion"])
    assert erosion.stack_key() != make_model("mm", ["W01"]).stack_key()


def test_the_one_well_and_the_field_wide_learner_keep_one_protocol(field: pd.DataFrame) -> None:
    """``WellLearner`` and ``FieldWell`` both keep ``Learner`` (mypy checks the signatures;
    here the members), and a field-wide well answers through it as a well of its own."""
    from vfm_core.learning.field import FieldLearner
    from vfm_core.learning.streaming import Learner

    (well,) = _fitted(field, "ol")[:1]
    shared = FieldLearner("mtl", "ol", train=replace(DEFAULT_TRAIN["mtl"], max_iter=20))
    shared.add(["W01"])
    facade = shared.well("W01")
    for learner in (well, facade):
        assert isinstance(learner, Learner)
        assert learner.well == "W01"
    assert not isinstance(object(), Learner)
    rows = _rows(field, "W01").iloc[HISTORY]
    x = rows[list(INPUT_COLUMNS)].tolist()
    answer = well.predict(x, rows["time"])
    assert answer["q_total"] is not None and answer["q_total"] > 0
    assert facade.predict(x, rows["time"])["q_total"] is None  # the field has seen nothing
