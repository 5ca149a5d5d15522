"""One contract suite over every registered learning method (``vfm_core.learning.METHODS``).

A new method passes these by registering itself with an ``example`` text; nothing here
names a method, except where a test checks a property that only some methods promise
(``per_measurement``, ``intervals``, ``streaming``).
"""

from __future__ import annotations

import io

import numpy as np
import pandas as pd
import pytest
import torch

from vfm_core.data import Batch, make_batch, target_mask
from vfm_core.errors import ConfigError
from vfm_core.jobs.study import run_prequential, wells_of
from vfm_core.learning import METHODS, NEVER, FrameMemory, LearningMethod, parse_method
from vfm_core.models import MODELS, make_model
from vfm_core.schema import INPUT_COLUMNS
from vfm_core.simulate import simulate_field
from vfm_core.streaming import WellLearner

EXAMPLES = [cls.example for cls in METHODS.values()]
SPLIT = pd.Timestamp("2019-01-01", tz="UTC")


@pytest.fixture(scope="module")
def field() -> pd.DataFrame:
    return simulate_field(wells=2, years=1.6, seed=11, start="2017-09-01").observations


def _setup(field: pd.DataFrame, text: str, model: str = "mm", seed: int = 0):
    """A method bound to a fitted model, its memory and the test rows as rounds."""
    is_target = target_mask(field, "all")
    wells = wells_of(field)
    m = make_model(model, wells, seed=seed)
    method = parse_method(text).bind(m)
    memory = FrameMemory(field, is_target, wells)
    method.fit(memory.batch(SPLIT.value))
    method.start(SPLIT.value)
    rows = np.flatnonzero(is_target & (field["time"] >= SPLIT).to_numpy())
    test = make_batch(field, wells, rows)
    return method, memory, test


def _now(rb: Batch) -> torch.Tensor:
    t = torch.where(rb.mask, rb.time_ns, torch.full_like(rb.time_ns, NEVER))
    return t.min(dim=1).values


def _stream(method: LearningMethod, memory, test: Batch, k0: int, k1: int) -> list[torch.Tensor]:
    """Predict-then-learn columns k0..k1 of the test batch; the predictions."""
    out = []
    for k in range(k0, k1):
        rb = test.column(k)
        method.retrain_due(memory, _now(rb))
        out.append(method.predict(rb).mean)
        method.on_measurement(rb, memory)
    return out


@pytest.mark.parametrize("text", EXAMPLES)
def test_text_names_the_method_and_parses_back(text: str) -> None:
    method = parse_method(text)
    assert str(method) == text and method.text == text
    assert type(parse_method(method)) is type(method)  # a fresh, unbound copy
    assert method.key in METHODS and method.kind
    with pytest.raises(ConfigError, match="unknown option|needs|not a positive"):
        parse_method(f"{method.key}:nonsense=1")


def test_an_unknown_method_lists_the_valid_ones() -> None:
    with pytest.raises(ConfigError) as err:
        parse_method("kalman")
    for key in METHODS:
        assert key in str(err.value)


@pytest.mark.parametrize("text", EXAMPLES)
def test_predict_before_fit_is_nan_and_after_finite(text: str, field) -> None:
    wells = wells_of(field)
    method = parse_method(text).bind(make_model("mm", wells))
    rows = np.flatnonzero(target_mask(field, "all"))
    batch = make_batch(field, wells, rows[:50])
    assert torch.isnan(method.predict(batch).mean).all()
    method, _, test = _setup(field, text)
    forecast = method.predict(test)
    assert torch.isfinite(forecast.mean[test.mask]).all()
    if method.intervals:
        assert forecast.std is not None and (forecast.std[test.mask] > 0).all()
    else:
        assert forecast.std is None


@pytest.mark.parametrize("model", list(MODELS))
@pytest.mark.parametrize("text", EXAMPLES)
def test_every_method_runs_every_model(text: str, model: str, field) -> None:
    """Every method binds to every registered model, including one without parameters to
    filter (the benchmark ``last``), predicts, and learns without error."""
    method, memory, test = _setup(field, text, model=model)
    out = _stream(method, memory, test, 0, min(5, test.time_ns.shape[1]))
    for k, pred in enumerate(out):
        assert torch.isfinite(pred[test.mask[:, k]]).all()


@pytest.mark.parametrize("text", EXAMPLES)
def test_input_not_mutated(text: str, field) -> None:
    method, memory, test = _setup(field, text)
    before = [t.clone() for t in (test.x, test.y, test.mask, test.time_ns)]
    _stream(method, memory, test, 0, 20)
    for a, b in zip(before, (test.x, test.y, test.mask, test.time_ns), strict=True):
        assert torch.equal(a, b)


@pytest.mark.parametrize("text", EXAMPLES)
def test_state_round_trip_continues_identically(text: str, field) -> None:
    """A copy restored from state_dict (through torch.save, weights_only) learns the same."""
    method, memory, test = _setup(field, text)
    _stream(method, memory, test, 0, 40)
    buf = io.BytesIO()
    torch.save({"model": method.model.state_dict(), "method": method.state_dict()}, buf)
    saved = torch.load(io.BytesIO(buf.getvalue()), weights_only=True)
    twin_model = make_model("mm", method.model.wells)
    twin_model.load_state_dict(saved["model"])
    twin = parse_method(text).bind(twin_model)
    twin.load_state_dict(saved["method"])
    a = _stream(method, memory, test, 40, 120)
    b = _stream(twin, memory, test, 40, 120)
    for x, y in zip(a, b, strict=True):
        torch.testing.assert_close(x, y, rtol=0, atol=0, equal_nan=True)
    assert twin.next_due() == method.next_due()


@pytest.mark.parametrize("text", EXAMPLES)
def test_same_seed_same_result(text: str, field) -> None:
    runs = []
    for _ in range(2):
        method, memory, test = _setup(field, text, seed=3)
        runs.append(torch.stack(_stream(method, memory, test, 0, 60)))
    torch.testing.assert_close(runs[0], runs[1], rtol=0, atol=0, equal_nan=True)


@pytest.mark.parametrize("text", EXAMPLES)
def test_wells_are_independent(text: str, field) -> None:
    """Well 1 predicts the same whether or not well 0 received measurements."""
    results = []
    for feed_well0 in (True, False):
        method, memory, test = _setup(field, text)
        if not feed_well0:
            keep = torch.arange(test.n_wells).unsqueeze(1) != 0
            test = test.select(keep)
        results.append(torch.stack(_stream(method, memory, test, 0, 80))[:, 1])
    torch.testing.assert_close(results[0], results[1], rtol=0, atol=0, equal_nan=True)


@pytest.mark.parametrize("text", EXAMPLES)
def test_learning_moves_the_prediction_towards_a_shifted_well(text: str, field) -> None:
    """Measurements 20 % above the model (inputs shifted too, as a changed well's are):
    after they are learned and every retrain that falls due has run, the error at those
    inputs is smaller than before."""
    method, memory, test = _setup(field, text)
    first = test.select(torch.cumsum(test.mask.long(), 1) <= 60)
    shifted = first.x.clone()
    shifted[..., 0] = torch.clamp(shifted[..., 0] + 0.15, max=1.0)  # choke opened
    probe = Batch(first.wells, shifted, first.y, first.mask, first.time_ns, first.row)
    target = method.predict(probe).mean * 1.2
    err_before = float(((method.predict(probe).mean - target).abs() / target)[first.mask].mean())
    # the shifted measurements, as the memory of a retrain will see them
    frame = field.copy()
    rows = first.row[first.mask].numpy()
    frame.loc[frame.index[rows], "choke"] = shifted[first.mask][:, 0].numpy()
    frame.loc[frame.index[rows], "q_total"] = target[first.mask].numpy()
    memory = FrameMemory(frame, target_mask(frame, "all"), first.wells)
    live = Batch(first.wells, shifted, target, first.mask, first.time_ns, first.row)
    for k in range(live.x.shape[1]):
        rb = live.column(k)
        method.retrain_due(memory, _now(rb))
        method.on_measurement(rb, memory)
    later = int(first.time_ns[first.mask].max()) + 1
    due = method.next_due()
    method.retrain_due(memory, torch.full((live.n_wells,), max(later, due or 0), dtype=torch.int64))
    err_after = float(((method.predict(probe).mean - target).abs() / target)[first.mask].mean())
    assert err_after < 0.9 * err_before, (err_before, err_after)


@pytest.mark.parametrize("text", [c.example for c in METHODS.values() if c.streaming])
def test_streaming_learner_reproduces_the_study(text: str) -> None:
    """One well through WellLearner sample by sample = run_prequential on the same file."""
    one = simulate_field(
        wells=1, years=1.2, seed=9, start="2018-04-01", hidden=["erosion"]
    ).observations
    study = run_prequential(one, "mm", text, targets="all", split=SPLIT)
    rows = one[target_mask(one, "all")]
    hist, live = rows[rows["time"] < SPLIT], rows[rows["time"] >= SPLIT]
    learner = WellLearner("W01", "mm", text)
    learner.fit_history(
        torch.tensor(hist[list(INPUT_COLUMNS)].to_numpy()),
        torch.tensor(hist["q_total"].to_numpy()),
        torch.tensor(pd.DatetimeIndex(hist["time"]).as_unit("ns").asi8),
        well_test=torch.tensor((hist["source"] == "well_test").to_numpy()),
    )
    learner.method.start(SPLIT.value)  # the study's calendar
    predicted = []
    for _, row in live.iterrows():
        inputs = row[list(INPUT_COLUMNS)].tolist()
        predicted.append(learner.predict(inputs, when=row["time"])["q_total"])
        learner.learn(inputs, row["q_total"], row["time"], row["source"])
    np.testing.assert_allclose(predicted, study.predictions["predicted"].to_numpy(), rtol=1e-6)


def test_methods_the_service_cannot_run_are_refused_by_the_streaming_learner() -> None:
    for cls in METHODS.values():
        if not cls.streaming:
            with pytest.raises(ConfigError, match="cannot run"):
                WellLearner("W1", "mm", cls.example)


def test_a_retrain_chooses_a_stale_iteration_count_again() -> None:
    """A count chosen by early stopping on few measurements (here one step, as a young
    well's few measurements can give) is chosen again by early stopping once the well holds
    twice as many; the retrain then fits the eroded choke better than one that keeps the
    stale count, and a count chosen on enough measurements is kept."""
    from vfm_core.learning.method import RECHOOSE_GROWTH

    frame = simulate_field(
        wells=2, years=2.0, seed=3, start="2017-01-01", hidden=["erosion"]
    ).observations
    is_target = target_mask(frame, "all")
    wells = wells_of(frame)
    memory = FrameMemory(frame, is_target, wells)
    start = pd.Timestamp("2017-07-01", tz="UTC").value
    end = int(frame["time"].max().value) + 1
    recent = np.flatnonzero(
        is_target & (frame["time"] >= frame["time"].max() - pd.Timedelta("90D"))
    )
    probe = make_batch(frame, wells, recent)

    def retrained(*chosen_on: int) -> tuple[LearningMethod, float]:
        method = parse_method("pbl:30d").bind(make_model("mm", wells))
        method.fit(memory.batch(start))
        method.iterations = torch.ones(len(wells), dtype=torch.int64)
        method.chosen_on = torch.tensor(chosen_on, dtype=torch.int64)
        method.retrain(memory, end)
        q = method.predict(probe).mean
        return method, float(((q - probe.y).abs() / probe.y)[probe.mask].mean())

    counts = memory.batch(end).count()
    enough = int(counts.max()) // RECHOOSE_GROWTH + 1
    stale, err_stale = retrained(1, 1)
    kept, err_kept = retrained(enough, enough)
    assert torch.equal(stale.chosen_on, counts) and bool((stale.iterations > 1).all())
    assert bool((kept.iterations == 1).all())  # chosen on more than half: not stale yet
    assert err_stale < 0.8 * err_kept, (err_stale, err_kept)
    # choosing one well's count again leaves the other's retrain as it was, to the bit
    one, _ = retrained(1, enough)
    assert int(one.iterations[0]) > 1 and int(one.iterations[1]) == 1
    z_one, z_kept = one.model.phys.z.detach(), kept.model.phys.z.detach()  # type: ignore[union-attr]
    assert torch.equal(z_one[1], z_kept[1]) and not torch.equal(z_one[0], z_kept[0])
