"""A well with scheduled retrains: its single samples that come before the next retrain is
due share one prediction call, with the answers of predicting them one by one.

``pbl`` (and ``bayes``'s refresh of a hybrid that learns from well tests) retrains a well's
model at its first sample at or after the due time. Before, any such well sent each of
its single samples to a call of its own once a sample of it waited in the batch. Now a
sample joins the call when it comes before the retrain is due
(:func:`vfm_core.learning.streaming.model_fixed_when_predicting` with its time). The same
fast replay of single samples (retrains due within it) runs with the rule and with the
rule before it: every stored prediction must be the same (to 1e-12 relative), the retrains
must have run, and with the rule some call must hold several samples of one well.
"""

from __future__ import annotations

import math
from collections import Counter
from pathlib import Path
from typing import Any

import pandas as pd
import pytest

import service.engine.learning as engine_learning
import service.engine.worker as engine_worker
from replay.client import sample_of
from service.app import Service
from service.testing import loopback_settings, wait_until
from service.transport import MemoryTransport
from vfm_core.data import target_mask
from vfm_core.learning import streaming
from vfm_core.observations import validate_frame
from vfm_core.schema import INPUT_COLUMNS
from vfm_core.simulate import simulate_field

pytestmark = pytest.mark.timeout(300)

WELLS = 2
HISTORY = 80
LIVE = 60


@pytest.fixture(scope="module")
def field() -> pd.DataFrame:
    frame = validate_frame(simulate_field(wells=WELLS, years=1, seed=4).observations).frame
    return frame[target_mask(frame, "all")].reset_index(drop=True)


def _replay(
    folder: Path, field: pd.DataFrame, grouped: bool, monkeypatch: pytest.MonkeyPatch
) -> tuple[dict[str, list[Any]], list[Counter[str]], int]:
    """The live rows' samples sent as fast as the queue takes them; the stored predictions
    per well, the wells of each prediction call, and the retrains run."""
    if not grouped:  # the rule before: a well with a scheduled retrain never groups
        real_fixed = streaming.model_fixed_when_predicting

        def fixed(learner: Any, until_ns: int | None = None) -> bool:
            return real_fixed(learner) if until_ns is not None else real_fixed(learner, until_ns)

        monkeypatch.setattr(engine_worker, "model_fixed_when_predicting", fixed)
    calls: list[Counter[str]] = []
    real_many = engine_learning.predict_many

    def counted(learners: list[Any], *args: Any, **kwargs: Any) -> list[Any]:
        calls.append(Counter(str(lrn.well) for lrn in learners))
        return real_many(learners, *args, **kwargs)

    monkeypatch.setattr(engine_learning, "predict_many", counted)
    folder.mkdir()
    wells = sorted(field["well"].unique())
    history = pd.concat([field[field["well"] == w].iloc[:HISTORY] for w in wells])
    path = folder / "history.parquet"
    history.to_parquet(path)
    settings = loopback_settings(
        folder, model={"name": "mm", "method": "pbl:7d", "history": str(path)}
    )
    bus = MemoryTransport(settings.prefix, capacity=8192, keep=16)
    service = Service(settings, bus)
    service.start()
    try:
        assert bus.matching(f"{settings.prefix}/{wells[0]}/sensors", 30.0)
        engine = service.engine
        assert engine is not None
        learners = {w: engine._wells[w].learner for w in wells}
        before = {w: learners[w].method.next_due() for w in wells}
        for well in wells:  # each well's samples in a row: the worker's batches hold several
            for _, row in field[field["well"] == well].iloc[HISTORY : HISTORY + LIVE].iterrows():
                sample = sample_of(row["time"].to_pydatetime(), row[list(INPUT_COLUMNS)])
                bus.put(f"{settings.prefix}/{well}/sensors", sample.model_dump_json().encode())
        store = service.store
        assert store is not None
        wait_until(
            lambda: all(len(store.history(w, 0, 2**62, 10_000)[0]) == LIVE for w in wells),
            120.0,
            "every sample predicted",
        )
        stored = {w: store.history(w, 0, 2**62, 10_000)[0] for w in wells}
        retrains = sum(learners[w].method.next_due() != before[w] for w in wells)
    finally:
        service.stop()
    return stored, calls, retrains


def _same(a: float | None, b: float | None) -> bool:
    if a is None or b is None:
        return a is b
    return math.isclose(a, b, rel_tol=1e-12) or (math.isnan(a) and math.isnan(b))


def test_samples_before_a_due_retrain_share_a_call_with_the_same_answers(
    tmp_path: Path, field: pd.DataFrame, monkeypatch: pytest.MonkeyPatch
) -> None:
    with monkeypatch.context() as m:
        one, calls_one, retrains_one = _replay(tmp_path / "one", field, False, m)
    with monkeypatch.context() as m:
        many, calls_many, retrains_many = _replay(tmp_path / "many", field, True, m)
    # the retrains ran within the replay, in both
    assert retrains_one == retrains_many == WELLS
    # before: never two samples of one well in a call; now: some call holds several
    assert max(max(c.values()) for c in calls_one) == 1
    assert max(max(c.values()) for c in calls_many) > 1
    assert len(calls_many) < len(calls_one)
    for well in one:
        assert [s.time_ns for s in one[well]] == [s.time_ns for s in many[well]]
        for a, b in zip(one[well], many[well], strict=True):
            assert _same(a.q_total, b.q_total), (well, a, b)
            assert _same(a.q_gas, b.q_gas) and _same(a.q_oil, b.q_oil), (well, a, b)
