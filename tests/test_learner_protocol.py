"""What the ``Learner`` protocol says a learner can do, as each learner answers it.

The service asks these capabilities instead of branching on the class (issue 37; the
layout suite checks that no module under ``service/`` calls ``isinstance`` with a concrete
learner class): a well's own :class:`~vfm_core.learning.streaming.WellLearner` and a well of the
field-wide model (:class:`~vfm_core.learning.field.FieldWell`) must answer them as the
branches they replaced decided.
"""

from __future__ import annotations

from typing import Any

import pytest
import torch

from vfm_core.errors import ConfigError
from vfm_core.features import FeatureTracker
from vfm_core.learning.field import FieldLearner
from vfm_core.learning.streaming import Learner, WellLearner, learn_many, predict_many
from vfm_core.learning.streaming.learner import model_fixed_when_predicting, predicts_in_groups

pytestmark = pytest.mark.timeout(120)


def _rows(n: int) -> tuple[torch.Tensor, ...]:
    """``n`` plausible measured rows (inputs in file units, rates Sm3/h, daily times, ns)."""
    x = torch.tensor([[0.5, 100.0, 30.0, 60.0, 0.1, 0.6]], dtype=torch.float64).repeat(n, 1)
    y = torch.linspace(50.0, 60.0, n, dtype=torch.float64)
    t = torch.arange(n, dtype=torch.int64) * 86_400 * 10**9 + 1_700_000_000 * 10**9
    w = torch.zeros(n, dtype=torch.bool)
    e = torch.zeros(n, len(FeatureTracker.names), dtype=torch.float64)
    return x, y, t, w, e


def _field_well(method: str = "ol") -> tuple[FieldLearner, Any]:
    field = FieldLearner("mtl", method)
    field.add(["W01", "W02"])
    return field, field.well("W01")


def test_a_wells_own_learner_and_a_field_well_answer_the_capabilities() -> None:
    """Own model: not shared, checkpoint of its own, steps in groups. Field well: shared,
    the field as its checkpoint group (the same object for every well), steps alone."""
    own = WellLearner("W01", "mm", "ol")
    field, facade = _field_well()
    for learner in (own, facade):
        assert isinstance(learner, Learner)
    assert not own.shares_model and own.checkpoint_group is None
    assert own.predicts_in_groups and own.learns_in_groups
    assert predicts_in_groups(own) and model_fixed_when_predicting(own)
    assert facade.shares_model and facade.checkpoint_group is field
    assert field.well("W02").checkpoint_group is facade.checkpoint_group
    assert not facade.predicts_in_groups and not facade.learns_in_groups
    assert not predicts_in_groups(facade) and not model_fixed_when_predicting(facade)
    # a method without group updates (pbl stores and retrains) learns one by one
    assert not WellLearner("W01", "mm", "pbl:14d").learns_in_groups


def test_a_subclass_with_its_own_predict_or_learn_steps_alone() -> None:
    """The grouped path splits ``predict`` / ``learn`` into steps; a subclass that replaces
    either answers through its own (and an object without the capability, too)."""

    class OwnPredict(WellLearner):
        def predict(self, inputs: Any, when: Any = None) -> dict[str, float | None]:
            return super().predict(inputs, when)

    class OwnLearn(WellLearner):
        def learn(self, *args: Any, **kwargs: Any) -> bool:
            return super().learn(*args, **kwargs)

    a, b = OwnPredict("W01", "mm", "ol"), OwnLearn("W01", "mm", "ol")
    assert not a.predicts_in_groups and a.learns_in_groups
    assert b.predicts_in_groups and not b.learns_in_groups

    class Facade:
        calls = 0

        def predict(self, inputs: Any, when: Any = None) -> dict[str, float | None]:
            self.calls += 1
            return {"q_total": 1.0}

        def learn(self, *args: Any, **kwargs: Any) -> bool:
            self.calls += 1
            return True

    facade = Facade()
    assert not predicts_in_groups(facade)
    assert predict_many([facade], [[0.0] * 6], [None]) == [{"q_total": 1.0}]
    assert learn_many([facade], [[0.0] * 6], [1.0], [None]) == [True]
    assert facade.calls == 2


def test_a_predict_patched_onto_the_class_is_used(monkeypatch: pytest.MonkeyPatch) -> None:
    """A replacement patched onto ``WellLearner`` (as a test adds an interval) is a predict
    of its own: the grouped path, which would bypass it, is not taken."""
    learner = WellLearner("W01", "mm", "ol")
    assert learner.predicts_in_groups
    original = WellLearner.predict
    monkeypatch.setattr(WellLearner, "predict", lambda self, x, when=None: original(self, x, when))
    assert not learner.predicts_in_groups and not model_fixed_when_predicting(learner)
    monkeypatch.setattr(WellLearner, "learn", lambda self, *a, **k: True)
    assert not learner.learns_in_groups


def test_the_memory_bound_applies_to_a_wells_own_learner_only() -> None:
    """``remember_at_most`` keeps a well's latest rows; a field keeps every well's rows
    (its retrains refit the whole field on them)."""
    own = WellLearner("W01", "mm", "ol")
    _, facade = _field_well()
    rows = _rows(20)
    for learner in (own, facade):
        learner.memory.append(*rows)
        learner.remember_at_most(5)
    assert own.remembered == 5
    assert torch.equal(own.memory.y, rows[1][-5:])  # the latest five
    assert facade.remembered == 20
    own.remember_at_most(None)
    own.memory.append(*rows)
    assert own.remembered == 25


def test_renumbering_only_raises_a_version_and_a_field_well_refuses_it() -> None:
    own = WellLearner("W01", "mm", "ol")
    own.renumber(5)
    assert own.version == 5
    own.renumber(2)
    assert own.version == 5
    _, facade = _field_well()
    with pytest.raises(ConfigError, match="cannot be renumbered for one well"):
        facade.renumber(3)
    assert facade.version == 0


def test_a_field_well_refuses_what_only_a_wells_own_model_does() -> None:
    """A fit of one well alone and a block of samples in one call: refused with a sentence
    (the field is fitted whole; its samples go one by one, which the worker falls back to)."""
    _, facade = _field_well()
    x, y, t, _, _ = _rows(3)
    with pytest.raises(ConfigError, match="fitted on every well's history at once"):
        facade.fit_history(x, y, t)
    with pytest.raises(ConfigError, match="fitted on every well's history at once"):
        facade.adopt_fit(x, y, t, torch.zeros(1, dtype=torch.int64))
    with pytest.raises(ValueError, match="predicted one by one"):
        facade.predict_block(x.numpy(), t.numpy())
    assert facade.remembered == 0  # nothing was taken


def test_what_becomes_of_a_measurement_not_learned_at_once() -> None:
    """The sentences the service gives a well-test caller, as before the protocol had them."""
    assert WellLearner("W01", "mm", "pbl:14d").deferred_note() == (
        "Stored; the model keeps it for its next periodic retrain (method pbl:14d)."
    )
    assert _field_well("ol")[1].deferred_note() == (
        "Stored; the field-wide model learns it with the other wells' measurements of its "
        "day when the day ends."
    )
    assert _field_well("pbl:14d")[1].deferred_note() == (
        "Stored; the model keeps it for its next periodic retrain (method pbl:14d)."
    )
