"""Many wells' updates in one call (``learn_many``) equal one-by-one learning.

Two identical sets of learners are fitted, then fed the same measurements in rounds: one
learns each with ``WellLearner.learn``, the other each round's with ``learn_many``. The
wells have different histories and different numbers of earlier updates (so Adam's step
counts, hence its bias corrections, differ between the wells of one call). Every per-well
model, with effects, with ``ol`` (Adam and SGD) and with ``bayes``, must leave the same
parameters, optimiser or filter states, versions and later predictions (with their
intervals), to 1e-12 relative; and the stacked update must really have run (its calls
are counted).
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
from vfm_core.learning import DEFAULT_ONLINE, DEFAULT_TRAIN, OnlineSettings, streaming
from vfm_core.learning.streaming import WellLearner, learn_many, predict_many
from vfm_core.models import MODELS
from vfm_core.schema import INPUT_COLUMNS
from vfm_core.simulate import simulate_field

WELLS = 3
HISTORY = 60
ROUNDS = 12

#: (model, effects): every per-well gradient model, and one whose effect reads features
#: and has no closed-form gradient (autograd)
SPECS: list[tuple[str, tuple[str, ...]]] = [
    *((m, ()) for m in MODELS if not MODELS[m].shared and not MODELS[m].gradient_free),
    ("mm", ("erosion",)),
]
#: ``ol`` with Adam, ``ol`` with SGD, and ``bayes``
SETTINGS = ["adam", "sgd", "bayes"]


@pytest.fixture(scope="module")
def field() -> pd.DataFrame:
    frame = simulate_field(wells=WELLS, years=0.7, seed=5, hidden=["erosion"]).observations
    return frame[target_mask(frame, "all")]


def _rows(field: pd.DataFrame, well: str) -> pd.DataFrame:
    return field[field["well"] == well].reset_index(drop=True)


def _online(model: str, optimizer: str) -> OnlineSettings:
    """The model's online defaults with ``optimizer`` (a rate either optimiser moves with)."""
    base = DEFAULT_ONLINE[model]
    return replace(base, optimizer=optimizer, lr=1e-3 if optimizer == "adam" else base.lr)


def _fitted(
    field: pd.DataFrame,
    model: str,
    effects: tuple[str, ...] = (),
    method: str = "ol",
    online: OnlineSettings | None = None,
) -> list[WellLearner]:
    """One learner per well, fitted on histories of different lengths, then each given a
    different number of updates (0, 1, 2, ...) so their optimiser step counts differ."""
    learners = []
    for j in range(WELLS):
        well = f"W{j + 1:02d}"
        rows = _rows(field, well).iloc[: HISTORY + 10 * j]
        learner = WellLearner(
            well,
            model,
            method,
            train=replace(DEFAULT_TRAIN[model], max_iter=40, patience=10),
            online=online,
            effects=effects,
        )
        learner.fit_history(
            torch.tensor(rows[list(INPUT_COLUMNS)].to_numpy()),
            torch.tensor(rows["q_total"].to_numpy()),
            torch.tensor(pd.DatetimeIndex(rows["time"]).as_unit("ns").asi8),
        )
        for _, row in _rows(field, well).iloc[HISTORY + 10 * j :].iloc[:j].iterrows():
            learner.learn(row[list(INPUT_COLUMNS)].tolist(), row["q_total"], row["time"])
        learners.append(learner)
    return learners


def _stream(field: pd.DataFrame, j: int) -> pd.DataFrame:
    """Well ``j``'s rows after its history and its earlier updates."""
    return _rows(field, f"W{j + 1:02d}").iloc[HISTORY + 11 * j :].reset_index(drop=True)


def _close_tensors(a: torch.Tensor, b: torch.Tensor, what: str) -> None:
    assert a.shape == b.shape and a.dtype == b.dtype, what
    if a.dtype.is_floating_point:
        torch.testing.assert_close(b, a, rtol=1e-12, atol=1e-300, equal_nan=True, msg=what)
    else:
        assert torch.equal(a, b), what


def _same_learner(a: WellLearner, b: WellLearner) -> None:
    """Parameters, optimiser state, counters, memory and features all equal."""
    assert (a.version, a.n_updates, a.last_update) == (b.version, b.n_updates, b.last_update)
    sa, sb = a.model.state_dict(), b.model.state_dict()
    assert sa.keys() == sb.keys()
    for key in sa:
        _close_tensors(sa[key], sb[key], f"{a.well} {key}")
    ma, mb = a.method.state_dict(), b.method.state_dict()
    assert ma.keys() == mb.keys()
    assert ma.get("updates") == mb.get("updates")
    oa, ob = ma.get("optimizer") or {}, mb.get("optimizer") or {}
    assert oa.get("param_groups") == ob.get("param_groups")
    states_a, states_b = oa.get("state", {}), ob.get("state", {})
    assert states_a.keys() == states_b.keys()
    for pid in states_a:
        assert states_a[pid].keys() == states_b[pid].keys()
        for key in states_a[pid]:
            _close_tensors(states_a[pid][key], states_b[pid][key], f"{a.well} opt {pid} {key}")
    assert a.features.state() == b.features.state()
    assert len(a.memory) == len(b.memory)
    for key, value in a.memory.state().items():
        if isinstance(value, torch.Tensor):
            _close_tensors(value, b.memory.state()[key], f"{a.well} memory {key}")


def _same_filter(a: WellLearner, b: WellLearner) -> None:
    """``bayes``: the filter's state (covariance, noise, calibration, counters) equal."""
    sa, sb = a.method.state_dict(), b.method.state_dict()
    assert sa.keys() == sb.keys()
    # the covariance to 1e-12 of its largest entry: a network's batched matrix products
    # round in the last bits by batch size, and an entry near zero is a cancellation
    scale = float(sa["P"].abs().max())
    torch.testing.assert_close(sb["P"], sa["P"], rtol=0, atol=1e-12 * scale, msg=f"{a.well} P")
    for key in ("last", "noise", "h", "started", "run", "scale"):
        _close_tensors(sa[key], sb[key], f"{a.well} bayes {key}")
    assert sa["counts"].keys() == sb["counts"].keys()
    for key in sa["counts"]:
        _close_tensors(sa["counts"][key], sb["counts"][key], f"{a.well} bayes count {key}")


def _close(a: dict[str, float | None], b: dict[str, float | None]) -> None:
    assert a.keys() == b.keys()
    for key in a:
        x, y = a[key], b[key]
        if x is None or y is None or math.isnan(x):
            assert x is y or (x is not None and y is not None and math.isnan(y)), (key, x, y)
        else:
            assert y == pytest.approx(x, rel=1e-12, abs=1e-300), (key, x, y)


@pytest.fixture
def stacked_sizes(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    """How many wells each stacked update held (a failure there would fall back one by one:
    not counted)."""
    sizes: list[int] = []
    group = streaming._learn_group

    def counted(members: list[Any], key: Any, results: list[Any]) -> list[Any]:
        rest = group(members, key, results)
        sizes.append(len(members) - len(rest))
        return rest

    monkeypatch.setattr(streaming, "_learn_group", counted)
    return sizes


@pytest.mark.parametrize("setting", SETTINGS)
@pytest.mark.parametrize(("model", "effects"), SPECS, ids=["+".join([m, *e]) for m, e in SPECS])
def test_learn_many_equals_one_by_one(
    field: pd.DataFrame,
    model: str,
    effects: tuple[str, ...],
    setting: str,
    stacked_sizes: list[int],
) -> None:
    if setting == "bayes":
        one = _fitted(field, model, effects, method="bayes")
    else:
        one = _fitted(field, model, effects, online=_online(model, setting))
    many = copy.deepcopy(one)
    if setting == "adam":  # the wells' Adam step counts differ going in
        steps = [
            [
                float(s["step"])
                for s in lrn.method.state_dict()["optimizer"].get("state", {}).values()
            ]
            for lrn in one
        ]
        assert len({tuple(s) for s in steps}) == WELLS
    streams = [_stream(field, j) for j in range(WELLS)]
    for r in range(ROUNDS):
        # every well most rounds; some rounds skip one; every fourth, W01 twice
        wells = [j for j in range(WELLS) if (r + j) % 5 != 4]
        if r % 4 == 1:
            wells.append(0)
        picks: list[tuple[int, pd.Series]] = []
        used = [0] * WELLS
        for j in wells:
            picks.append((j, streams[j].iloc[2 * r + used[j]]))
            used[j] += 1
        xs = [row[list(INPUT_COLUMNS)].tolist() for _, row in picks]
        qs = [float(row["q_total"]) for _, row in picks]
        whens: list[datetime] = [row["time"] for _, row in picks]
        sources = ["well_test" if (r + j) % 3 == 0 else "mpfm" for j, _ in picks]
        expected = [
            one[j].learn(x, q, w, s)
            for (j, _), x, q, w, s in zip(picks, xs, qs, whens, sources, strict=True)
        ]
        got = learn_many([many[j] for j, _ in picks], xs, qs, whens, sources)
        assert got == expected
        for a, b in zip(one, many, strict=True):
            _same_learner(a, b)
            if setting == "bayes":
                _same_filter(a, b)
        # the service's order on one thread: the wells' next samples predicted in one
        # stacked call, then the next round's stacked update (which must not be
        # disturbed by the prediction's use of the same stacked model)
        later = [streams[j].iloc[2 * r + 2] for j in range(WELLS)]
        xs_later = [row[list(INPUT_COLUMNS)].tolist() for row in later]
        whens_later = [row["time"] for row in later]
        answers = predict_many(many, xs_later, whens_later)
        for j in range(WELLS):
            _close(one[j].predict(xs_later[j], whens_later[j]), answers[j])
    if setting == "bayes" and one[0].method._dim == 0:  # nothing to filter: one by one
        assert stacked_sizes == []
        return
    assert stacked_sizes and max(stacked_sizes) == WELLS
    assert sum(stacked_sizes) >= ROUNDS * 2


def test_the_same_well_twice_waits_for_its_first_measurement(
    field: pd.DataFrame, stacked_sizes: list[int]
) -> None:
    one = _fitted(field, "mm")
    many = copy.deepcopy(one)
    rows = [_stream(field, j) for j in range(WELLS)]
    order = [0, 1, 0, 2, 0, 1]
    used = [0] * WELLS
    picks = []
    for j in order:
        picks.append((j, rows[j].iloc[used[j]]))
        used[j] += 1
    xs = [row[list(INPUT_COLUMNS)].tolist() for _, row in picks]
    qs = [float(row["q_total"]) for _, row in picks]
    whens = [row["time"] for _, row in picks]
    for (j, _), x, q, w in zip(picks, xs, qs, whens, strict=True):
        one[j].learn(x, q, w)
    assert learn_many([many[j] for j, _ in picks], xs, qs, whens) == [True] * len(picks)
    for a, b in zip(one, many, strict=True):
        _same_learner(a, b)
    # a call per run of distinct wells: [0, 1], [0, 2], [0, 1]
    assert stacked_sizes == [2, 2, 2]


class _Facade:
    """Another kind of learner (e.g. a field-wide model's well): its own learn."""

    def __init__(self) -> None:
        self.calls: list[tuple[float, str]] = []

    def learn(self, inputs: Any, q_total: float, when: datetime, source: str = "mpfm") -> bool:
        self.calls.append((q_total, source))
        return True


# ol with a learning-rate schedule warns in torch (its steps bypass optimizer.step()); as before
@pytest.mark.filterwarnings("ignore:Detected call of:UserWarning")
def test_a_mix_of_groups_and_learners_that_learn_one_by_one(
    field: pd.DataFrame, stacked_sizes: list[int]
) -> None:
    """Two stackable groups (mm, with a learner never fitted; ham), and learners that must
    learn through their own ``learn``: another method (pbl), a method alone in its group
    (bayes), a learning-rate schedule, a subclass, a facade; a bad input gets its error in
    its place, and the others still learn."""

    class Wrapped(WellLearner):
        def learn(self, *args: Any, **kwargs: Any) -> bool:
            self.wrapped_calls = getattr(self, "wrapped_calls", 0) + 1
            return super().learn(*args, **kwargs)

    mm = _fitted(field, "mm")
    ham = _fitted(field, "ham")
    pbl = _fitted(field, "mm", method="pbl:14d")[:1]
    bayes = _fitted(field, "mm", method="bayes")[:1]
    scheduled = _fitted(field, "mm", online=replace(DEFAULT_ONLINE["mm"], schedule_power=0.5))[:2]
    wrapped = Wrapped("W01", "mm", "ol")
    wrapped.__dict__.update(copy.deepcopy(mm[0]).__dict__)
    fresh = WellLearner("W02", "mm", "ol")  # never fitted: its first measurement sets it up
    one: list[Any] = [*mm, fresh, *ham, *pbl, *bayes, *scheduled, wrapped]
    many = copy.deepcopy(one)
    one.append(_Facade())
    many.append(_Facade())
    streams = [_stream(field, j) for j in range(WELLS)]
    for r in range(4):
        rows = [
            streams[int(lrn.well[1:]) - 1 if hasattr(lrn, "well") else 0].iloc[r] for lrn in one
        ]
        xs = [row[list(INPUT_COLUMNS)].tolist() for row in rows]
        qs = [float(row["q_total"]) for row in rows]
        whens = [row["time"] for row in rows]
        bad = len(one) - 3  # the second scheduled learner: two inputs instead of six
        xs[bad] = [1.0, 2.0]
        expected: list[Any] = []
        for lrn, x, q, w in zip(one, xs, qs, whens, strict=True):
            try:
                expected.append(lrn.learn(x, q, w))
            except Exception as exc:
                expected.append(type(exc))
        got = learn_many(many, xs, qs, whens, return_exceptions=True)
        assert [type(g) if isinstance(g, BaseException) else g for g in got] == expected
        assert isinstance(got[bad], RuntimeError)
        for a, b in zip(one[:-1], many[:-1], strict=True):
            _same_learner(a, b)
    assert many[-1].calls == one[-1].calls and len(many[-1].calls) == 4
    assert many[-2].wrapped_calls == 4
    # one stacked call per round for mm (with the fresh learner) and one for ham
    assert stacked_sizes == [WELLS + 1, WELLS] * 4
    assert many[WELLS].ready and many[WELLS].method.updates == 4
    with pytest.raises(RuntimeError):
        learn_many([many[0], many[bad]], [xs[0], [1.0, 2.0]], qs[:2], whens[:2])
    with pytest.raises(ValueError, match="one input row, rate and time"):
        learn_many(many[:2], xs[:1], qs[:2], whens[:2])


def test_learning_moves_the_model_toward_the_measurement(
    field: pd.DataFrame, stacked_sizes: list[int]
) -> None:
    """Wells whose true rate is well off their model's: the error on the learned
    measurement falls with every call."""
    learners = _fitted(field, "mm", online=replace(DEFAULT_ONLINE["mm"], lr=1e-2))
    rows = [_stream(field, j).iloc[0] for j in range(WELLS)]
    xs = [row[list(INPUT_COLUMNS)].tolist() for row in rows]
    whens = [row["time"] for row in rows]
    # the truth: 25 % above what the models predict now
    truth = [
        1.25 * lrn.predict(x, w)["q_total"] for lrn, x, w in zip(learners, xs, whens, strict=True)
    ]  # type: ignore[operator]

    def errors() -> list[float]:
        return [
            abs(lrn.predict(x, w)["q_total"] - q) / q  # type: ignore[operator]
            for lrn, x, w, q in zip(learners, xs, whens, truth, strict=True)
        ]

    before = errors()
    for k in range(1, 6):
        later = [w + pd.Timedelta(minutes=k) for w in whens]
        assert learn_many(learners, xs, truth, later) == [True] * WELLS
        after = errors()
        assert all(a < b for a, b in zip(after, before, strict=True)), (before, after)
        before = after
    assert max(before) < 0.2  # from 0.2 (25 % above is 20 % below the truth)
    assert stacked_sizes == [WELLS] * 5
