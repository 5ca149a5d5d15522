"""``bayes:cal_pool=on`` in the service: the wells' one-well filters share one pool.

With ``cal_pool=on`` each well's well-test variance factor takes its prior from the other
wells' errors (:mod:`vfm_core.learning.bayes`). ``vfm evaluate`` runs one filter over all
the wells, in time order; the service runs one filter a well, and its engine gives the
filters of one model and method a shared :class:`~vfm_core.learning.bayes.CalibrationPool`
(:mod:`service.engine.pools`). A four-well field with well tests only (case 2) is fitted
on its history before the split and replayed after it through the real engine (in-memory
transport), each well test learned before anything later is sent (the order of a live
field), with a restart half-way (a clean stop, then a new engine on the same store: the
pool is rebuilt from the checkpoints). Every well test's prediction and 90 % interval must
be the study's (``run_prequential`` with ``targets="well_test"``, the same model, method,
split and fit) to 1e-9, and the intervals must differ from those of ``cal_pool=off`` (what
the service gave before it shared a pool: each filter alone has the stated prior).
"""

from __future__ import annotations

import logging
import re
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pytest

from replay.client import FieldClient, sample_of
from service.app import Service
from service.engine.checkpoints import Checkpoints
from service.engine.pools import Pools
from service.testing import study_settings, wait_until
from service.transport import MemoryTransport
from vfm_core.jobs.study import run_prequential
from vfm_core.learning import DEFAULT_TRAIN
from vfm_core.learning.streaming import WellLearner
from vfm_core.messages import Measurement
from vfm_core.observations import validate_frame
from vfm_core.schema import INPUT_COLUMNS
from vfm_core.simulate import simulate_field

pytestmark = pytest.mark.timeout(300)

SPLIT = "2016-09-01"
METHOD = "bayes:cal_pool=on"
#: a short initial fit, the same for the service and the study (the test is about agreement)
TRAIN = {"max_iter": 100, "early_stopping": False}


@pytest.fixture(scope="module")
def field() -> pd.DataFrame:
    """Four wells over two years; the well tests are the only measurements (case 2)."""
    frame = validate_frame(simulate_field(wells=4, years=2, seed=11).observations).frame
    return frame[frame["source"] == "well_test"].reset_index(drop=True)


def _study(frame: pd.DataFrame, method: str) -> pd.DataFrame:
    train = replace(DEFAULT_TRAIN["mm"], **TRAIN)
    run = run_prequential(frame, "mm", method, targets="well_test", split=SPLIT, train=train)
    return run.predictions.sort_values(["time", "well"]).reset_index(drop=True)


def _feed(service: Service, bus: MemoryTransport, rows: pd.DataFrame) -> None:
    """Each well test's sample and measurement, in time order; each learned before the next."""
    counters = service.counters
    learned0 = counters.snapshot()["events"].get("learned", 0)
    with FieldClient(bus, service.settings.prefix) as client:
        client.wait_for_service(str(rows["well"].iloc[0]))
        for n, r in enumerate(rows.itertuples(), start=1):
            when = r.time.to_pydatetime()
            client.send_sample(r.well, sample_of(when, [getattr(r, c) for c in INPUT_COLUMNS]))
            client.send_measurement(r.well, "well_test", Measurement(time=when, q_total=r.q_total))
            wait_until(
                lambda n=n: counters.snapshot()["events"].get("learned", 0) - learned0 >= n,
                60,
                "the well test learned",
            )


def _served(service: Service, wells: list[str]) -> pd.DataFrame:
    """The stored prediction and 90 % interval at each well test's sample."""
    store = service.store
    assert store is not None
    rows = []
    for well in wells:
        samples, _ = store.history(well, 0, 2**62, 10_000)
        rows += [(well, s.time_ns, s.q_total, s.q_total_p05, s.q_total_p95) for s in samples]
    out = pd.DataFrame(rows, columns=["well", "time_ns", "predicted", "p05", "p95"])
    out["time"] = pd.to_datetime(out["time_ns"], utc=True)
    return out


def _run(settings: Any, rows: pd.DataFrame, wells: list[str]) -> tuple[pd.DataFrame, dict]:
    bus = MemoryTransport(settings.prefix)
    service = Service(settings, bus)
    service.start()
    try:
        _feed(service, bus, rows)
        engine = service.engine
        assert engine is not None
        pooled = engine._learning.pools.members()
        return _served(service, wells), pooled
    finally:
        service.stop()


@pytest.mark.parametrize("final_checkpoint", [True, False])
def test_the_service_pools_the_wells_as_the_study_does(
    tmp_path: Path,
    field: pd.DataFrame,
    final_checkpoint: bool,
    monkeypatch: pytest.MonkeyPatch,
    caplog: pytest.LogCaptureFixture,
) -> None:
    study, alone = _study(field, METHOD), _study(field, "bayes:cal_pool=off")
    data = tmp_path / "field.parquet"
    field.to_parquet(data)
    store = {"checkpoint_every": 3}
    settings = study_settings(tmp_path, data, "mm", METHOD, SPLIT, TRAIN, store=store)
    live = field[field["time"] >= pd.Timestamp(SPLIT, tz="UTC")]
    half = live["time"] < live["time"].iloc[len(live) // 2]
    wells = sorted(field["well"].unique())
    if not final_checkpoint:  # a crash: each well restarts from its own older checkpoint
        monkeypatch.setattr(Checkpoints, "final_ops", lambda self, wells: [])
    _, pooled = _run(settings, live[half], wells)
    monkeypatch.undo()
    assert pooled == {w: len(wells) for w in wells}  # one pool for the four wells
    # a restart: the pool rebuilt from the checkpoints (the store holds both halves)
    with caplog.at_level(logging.INFO, logger="vfm.service.engine"):
        served, _ = _run(settings, live[~half], wells)
    relearned = [
        int(m.group(1))
        for r in caplog.records
        if (m := re.search(r"(\d+) measurement\(s\) re-learned", r.getMessage()))
    ]
    assert len(relearned) == 1 and (relearned[0] > 0) != final_checkpoint, relearned
    both = study.merge(served, on=["time", "well"], suffixes=("", "_svc"))
    assert len(both) == len(study) > 40
    for mine, theirs in (
        ("predicted_svc", "predicted"),
        ("p05", "predicted_p05"),
        ("p95", "predicted_p95"),
    ):
        np.testing.assert_allclose(both[mine], both[theirs], rtol=1e-9)
    # the pool moved the intervals (the predictions are the filters' own, the same)
    np.testing.assert_allclose(alone["predicted"], study["predicted"], rtol=1e-12)
    moved = np.abs(np.log(study["predicted_p95"] / alone["predicted_p95"]))
    print(f"mean |log p95 ratio| pooled vs alone: {moved.mean():.4f}, max {moved.max():.4f}")
    assert float(moved.mean()) > 1e-3 and float(moved.max()) > 1e-2


def test_the_wells_of_one_model_and_method_share_a_pool_and_a_replaced_learner_leaves() -> None:
    """The engine's pools: one per model and method; a learner replaced (a trial's shadow
    runs on) reads and publishes no more; a well whose new learner does not pool, or that is
    retired, leaves its pool; ``cal_pool=off`` and ``ol`` join none."""
    pools = Pools()
    learners = {w: WellLearner(w, "mm", METHOD) for w in ("W1", "W2", "W3")}
    for well, learner in learners.items():
        pools.join(well, learner)
    other = WellLearner("W4", "mm", f"{METHOD}:drift=2")  # another method text
    pools.join("W4", other)
    assert pools.members() == {"W1": 3, "W2": 3, "W3": 3, "W4": 1}
    pool = learners["W1"].method._pool  # type: ignore[attr-defined]
    assert pool is not None and learners["W2"].method._pool is pool  # type: ignore[attr-defined]
    assert other.method._pool is not pool  # type: ignore[attr-defined]
    new = WellLearner("W1", "mm", METHOD)
    pools.join("W1", new)  # a model change: the old learner may run on as a shadow
    assert new.method._pool is pool and learners["W1"].method._pool is None  # type: ignore[attr-defined]
    pools.join("W2", WellLearner("W2", "mm", "bayes"))  # to cal_pool=off: W2 leaves
    assert learners["W2"].method._pool is None  # type: ignore[attr-defined]
    pools.leave("W3")
    assert pools.members() == {"W1": 1, "W4": 1}
    pools.join("W5", WellLearner("W5", "mm", "bayes:cal_pool=off"))
    pools.join("W6", WellLearner("W6", "mm", "ol"))
    assert pools.members() == {"W1": 1, "W4": 1}
