"""Many wells' predictions in one call (``predict_many``) equal the one-by-one predictions.

Two identical sets of learners are fitted and streamed side by side: one predicts each
sample with ``WellLearner.predict``, the other all wells' samples of a step with
``predict_many``; both learn the same measurements in between. Every per-well model, with
effects, and every streaming method (``pbl`` retrains inside the stream, ``bayes`` gives
intervals) must give the same numbers to 1e-12 relative, and the learners' state (version,
retrains, features) must stay the same.
"""

from __future__ import annotations

import copy
import math
from dataclasses import replace
from datetime import datetime
from typing import Any

import pandas as pd
import pytest
import torch

from vfm_core.data import target_mask
from vfm_core.learning import DEFAULT_TRAIN, parse_method, streaming
from vfm_core.learning.streaming import WellLearner, predict_many
from vfm_core.models import MODELS
from vfm_core.schema import INPUT_COLUMNS
from vfm_core.simulate import simulate_field

WELLS = 3
HISTORY = 80
STREAM = 45

#: (model, effects): every per-well model, and effect models that read features, the
#: sample's time and the measurement source
SPECS: list[tuple[str, tuple[str, ...]]] = [
    *((m, ()) for m in MODELS if not MODELS[m].shared),
    ("mm", ("erosion", "valve")),
    ("hem", ("erosion_time",)),
    ("ham", ("mpfm_bias", "real_gas")),
]
#: every method the streaming learner runs (``pbl:auto`` is offline only today)
METHODS = [m for m in ("ol", "pbl:14d", "pbl:auto", "bayes") if parse_method(m).streaming]


@pytest.fixture(scope="module")
def field() -> pd.DataFrame:
    frame = simulate_field(wells=WELLS, years=0.7, seed=5, hidden=["erosion"]).observations
    return frame[target_mask(frame, "all")]


def _rows(field: pd.DataFrame, well: str) -> pd.DataFrame:
    return field[field["well"] == well].reset_index(drop=True)


def _fitted(field: pd.DataFrame, model: str, effects: tuple[str, ...], method: str) -> list[Any]:
    learners = []
    for j in range(WELLS):
        well = f"W{j + 1:02d}"
        rows = _rows(field, well).iloc[:HISTORY]
        learner = WellLearner(
            well,
            model,
            method,
            train=replace(DEFAULT_TRAIN[model], max_iter=40, patience=10),
            effects=effects,
        )
        learner.fit_history(
            torch.tensor(rows[list(INPUT_COLUMNS)].to_numpy()),
            torch.tensor(rows["q_total"].to_numpy()),
            torch.tensor(pd.DatetimeIndex(rows["time"]).as_unit("ns").asi8),
        )
        learners.append(learner)
    return learners


def _close(a: dict[str, float | None], b: dict[str, float | None]) -> None:
    assert a.keys() == b.keys()
    for key in a:
        x, y = a[key], b[key]
        if x is None or y is None or math.isnan(x):
            assert x is y or (x is not None and y is not None and math.isnan(y)), (key, x, y)
        else:
            assert y == pytest.approx(x, rel=1e-12, abs=1e-300), (key, x, y)


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize(("model", "effects"), SPECS, ids=["+".join([m, *e]) for m, e in SPECS])
def test_predict_many_equals_one_by_one(
    field: pd.DataFrame,
    model: str,
    effects: tuple[str, ...],
    method: str,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    stacked_calls: list[int] = []
    group = streaming._predict_group

    def counted(members: list[Any], results: list[Any]) -> None:
        group(members, results)  # an error here would fall back to one-by-one: not counted
        stacked_calls.append(len(members))

    monkeypatch.setattr(streaming, "_predict_group", counted)
    one = _fitted(field, model, effects, method)
    many = copy.deepcopy(one)
    # a learner that has seen nothing answers None, and stays in its place
    one.append(WellLearner("W99", model, method, effects=effects))
    many.append(copy.deepcopy(one[-1]))
    streams = [_rows(field, f"W{j + 1:02d}").iloc[HISTORY : HISTORY + STREAM] for j in range(WELLS)]
    answered = 0
    for step in range(STREAM):
        xs: list[list[float]] = []
        whens: list[datetime] = []
        for j in range(WELLS):
            row = streams[j].iloc[step]
            xs.append(row[list(INPUT_COLUMNS)].tolist())
            whens.append(row["time"])
        xs.append(xs[0])
        whens.append(whens[0])
        expected = [lrn.predict(x, when=w) for lrn, x, w in zip(one, xs, whens, strict=True)]
        got = predict_many(many, xs, whens)
        for a, b in zip(expected, got, strict=True):
            assert isinstance(b, dict)
            _close(a, b)
        assert got[-1]["q_total"] is None
        answered += sum(r["q_total"] is not None for r in expected)
        for j in range(WELLS):  # both sets learn the same measurements
            if step % 3 == j % 3:
                row = streams[j].iloc[step]
                for lrn in (one[j], many[j]):
                    lrn.learn(row[list(INPUT_COLUMNS)].tolist(), row["q_total"], row["time"])
    assert answered == WELLS * STREAM
    # the wells were predicted in one call per step, not one by one
    assert stacked_calls == [WELLS] * STREAM
    for a, b in zip(one, many, strict=True):
        assert (a.version, a.method.n_retrains, a.features.state()) == (
            b.version,
            b.method.n_retrains,
            b.features.state(),
        )
    if method == "pbl:14d" and not MODELS[model].gradient_free:  # retrains in the stream
        assert one[0].method.n_retrains > 0
    if method == "bayes" and MODELS[model].key != "last":
        assert got[0]["q_total_p95"] is not None


def test_a_learner_twice_in_one_call_is_answered_in_order(field: pd.DataFrame) -> None:
    """Its second sample may retrain it (pbl): the first is answered before that."""
    one = _fitted(field, "mm", (), "pbl:14d")
    many = copy.deepcopy(one)
    rows = _rows(field, "W01").iloc[HISTORY : HISTORY + 40]
    xs = [r[list(INPUT_COLUMNS)].tolist() for _, r in rows.iterrows()]
    whens = list(rows["time"])
    for i in range(0, 40, 2):  # measurements for the retrains to learn from
        one[0].learn(xs[i], rows["q_total"].iloc[i], whens[i])
        many[0].learn(xs[i], rows["q_total"].iloc[i], whens[i])
    later = [w + pd.Timedelta(days=30 * k) for k, w in enumerate(whens[-3:], start=1)]
    expected = [one[0].predict(x, when=w) for x, w in zip(xs[-3:], later, strict=True)]
    got = predict_many([many[0]] * 3, xs[-3:], later)
    assert one[0].method.n_retrains == many[0].method.n_retrains > 0
    for a, b in zip(expected, got, strict=True):
        assert isinstance(b, dict)
        _close(a, b)
    assert expected[0]["q_total"] != expected[-1]["q_total"]  # a retrain ran in between


class _Facade:
    """Another kind of per-well learner (e.g. a field-wide model's well): its own predict."""

    def __init__(self) -> None:
        self.calls = 0

    def predict(self, inputs: Any, when: datetime | None = None) -> dict[str, float | None]:
        self.calls += 1
        return {"q_total": 1.0 + self.calls}


def test_other_learners_answer_through_their_own_predict_and_errors_stay_in_place(
    field: pd.DataFrame,
) -> None:
    learners = _fitted(field, "mm", (), "ol")
    facade = _Facade()
    row = _rows(field, "W01").iloc[HISTORY]
    x, when = row[list(INPUT_COLUMNS)].tolist(), row["time"]
    got = predict_many(
        [learners[0], facade, learners[1]], [x, x, [1.0, 2.0]], [when] * 3, return_exceptions=True
    )
    assert isinstance(got[0], dict) and got[0]["q_total"] is not None
    assert got[1] == {"q_total": 2.0} and facade.calls == 1
    assert isinstance(got[2], RuntimeError)  # two inputs instead of six
    with pytest.raises(RuntimeError):
        predict_many([learners[1]], [[1.0, 2.0]], [when])

    # a subclass with its own predict answers through it (e.g. an interval added)
    class Wrapped(WellLearner):
        def predict(self, inputs: Any, when: datetime | None = None) -> dict[str, float | None]:
            return {**super().predict(inputs, when), "q_total_std": 1.0}

    wrapped = Wrapped("W01", "mm", "ol")
    wrapped.__dict__.update(copy.deepcopy(learners[0]).__dict__)
    (answer,) = predict_many([wrapped], [x], [when])
    assert isinstance(answer, dict) and answer["q_total_std"] == 1.0
    assert not streaming.model_fixed_when_predicting(wrapped)
    with pytest.raises(ValueError, match="one input row and one time per learner"):
        predict_many([learners[0], learners[1]], [x], [when])


@pytest.mark.parametrize("method", ["ol", "bayes"])
def test_a_wells_consecutive_samples_share_one_call_when_its_model_cannot_change(
    field: pd.DataFrame, method: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A flooding well: with no scheduled retrains its samples are predicted together."""
    one = _fitted(field, "mm", ("erosion",), method)
    many = copy.deepcopy(one)
    stacked_calls: list[int] = []
    group = streaming._predict_group

    def counted(members: list[Any], results: list[Any]) -> None:
        group(members, results)
        stacked_calls.append(len(members))

    monkeypatch.setattr(streaming, "_predict_group", counted)
    rows = _rows(field, "W01").iloc[HISTORY : HISTORY + 5]
    xs = [r[list(INPUT_COLUMNS)].tolist() for _, r in rows.iterrows()]
    whens = list(rows["time"])
    expected = [one[0].predict(x, when=w) for x, w in zip(xs, whens, strict=True)]
    got = predict_many([many[0]] * 5, xs, whens)
    assert stacked_calls == [5]
    for a, b in zip(expected, got, strict=True):
        assert isinstance(b, dict)
        _close(a, b)
    # the features moved sample by sample (cumulative throughput at each sample's time)
    assert one[0].features.state() == many[0].features.state()
    assert streaming.model_fixed_when_predicting(many[0])
    assert not streaming.model_fixed_when_predicting(_fitted(field, "mm", (), "pbl:14d")[0])


#: the methods whose model predicting cannot change: a block is predicted in one call
BLOCK_METHODS = [m for m in METHODS if m in ("ol", "bayes")]


@pytest.mark.parametrize("method", BLOCK_METHODS)
@pytest.mark.parametrize(("model", "effects"), SPECS, ids=["+".join([m, *e]) for m, e in SPECS])
def test_predict_block_equals_one_by_one(
    field: pd.DataFrame, model: str, effects: tuple[str, ...], method: str
) -> None:
    """A block of one well's samples (the service's sensor blocks) in one model call gives
    what predicting them one by one gives, and leaves the same features behind."""
    one = _fitted(field, model, effects, method)[:1]
    block = copy.deepcopy(one[0])
    rows = _rows(field, "W01").iloc[HISTORY : HISTORY + STREAM]
    xs = rows[list(INPUT_COLUMNS)].to_numpy()
    ns = pd.DatetimeIndex(rows["time"]).as_unit("ns").asi8
    expected = [one[0].predict(list(x), when=w) for x, w in zip(xs, rows["time"], strict=True)]
    got = block.predict_block(xs, ns)
    assert set(got) == {k for k, v in expected[0].items() if v is not None}
    for i, a in enumerate(expected):
        _close(
            {k: v for k, v in a.items() if v is not None},
            {k: float(got[k][i]) for k in got},
        )
    assert block.features.state() == one[0].features.state()


def test_predict_block_refuses_a_model_that_may_retrain_while_predicting(
    field: pd.DataFrame,
) -> None:
    """A scheduled retrain runs at the first sample at or after its due time: a block that
    ends before it is predicted in one call (as one by one), one that reaches it is
    refused (the service then takes its rows one by one)."""
    learner = _fitted(field, "mm", (), "pbl:14d")[0]
    due = learner.method.next_due()
    assert due is not None
    rows = _rows(field, "W01").iloc[HISTORY:]
    ns = pd.DatetimeIndex(rows["time"]).as_unit("ns").asi8
    xs = rows[list(INPUT_COLUMNS)].to_numpy()
    early = int((ns < due).sum())
    assert 2 <= early < len(ns)
    one = copy.deepcopy(learner)
    expected = [
        one.predict(list(x), when=w) for x, w in zip(xs[:early], rows["time"], strict=False)
    ]
    got = learner.predict_block(xs[:early], ns[:early])
    for i, a in enumerate(expected):
        _close({k: v for k, v in a.items() if v is not None}, {k: float(got[k][i]) for k in got})
    assert streaming.model_fixed_when_predicting(learner, int(ns[early - 1]))
    assert not streaming.model_fixed_when_predicting(learner, int(ns[early]))
    with pytest.raises(ValueError, match="retrained on a schedule"):
        learner.predict_block(xs[early : early + 3], ns[early : early + 3])
    with pytest.raises(ValueError, match="not ready"):
        WellLearner("W99", "mm", "ol").predict_block(
            rows[list(INPUT_COLUMNS)].to_numpy(), pd.DatetimeIndex(rows["time"]).as_unit("ns").asi8
        )
