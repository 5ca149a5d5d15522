"""The service learns a batch's measurements of many wells in one call, with the results of
learning each at once.

Several wells with a history are replayed through the engine (in-memory transport) as
fast as the receive queue takes them, a measurement with every sample (like a replay of
daily MPFM data): the worker's batches then hold several wells' measurements. The same
replay runs twice, with the learning steps deferred and batched
(:func:`vfm_core.learning.streaming.learn_many`) and with each learned at once
(``Learning.batch_learns = False``, the one-by-one path), with ``mm`` and ``ham`` learning
online (``ol``) and ``mm`` with ``bayes`` (its intervals too): every stored prediction, every
learned measurement's version and the prediction at its sample must be the same (to
1e-12 relative), and the batched run must really have learned several wells in one call.
Some wells' measurements arrive before their sample (they wait, and are learned when the
sample comes); one well test goes over the engine's HTTP path with a waiting caller.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pytest

import service.engine.learning as engine_learning
from replay.client import sample_of
from service.app import Service
from service.engine.learning import Learning
from service.store import HistorySample
from service.testing import loopback_settings, wait_until
from service.transport import MemoryTransport
from vfm_core.data import target_mask
from vfm_core.learning import streaming
from vfm_core.messages import Measurement
from vfm_core.observations import validate_frame
from vfm_core.schema import INPUT_COLUMNS
from vfm_core.simulate import simulate_field

pytestmark = pytest.mark.timeout(300)

WELLS = 5
HISTORY = 100
LIVE = 40


@pytest.fixture(scope="module")
def field() -> pd.DataFrame:
    frame = validate_frame(simulate_field(wells=WELLS, years=1, seed=2).observations).frame
    return frame[target_mask(frame, "all")].reset_index(drop=True)


def _replay(
    folder: Path,
    field: pd.DataFrame,
    model: str,
    method: str,
    batched: bool,
    monkeypatch: pytest.MonkeyPatch,
) -> tuple[dict[str, Any], list[int], dict[str, int]]:
    """Replay the live rows through a fresh engine; the store's samples and measurements
    per well, the sizes of the learning calls, and the event counters."""
    monkeypatch.setattr(Learning, "batch_learns", batched)
    sizes: list[int] = []
    real = streaming.learn_many

    def counted(learners: list[Any], *args: Any, **kwargs: Any) -> list[Any]:
        sizes.append(len({id(lrn) for lrn in learners}))
        return real(learners, *args, **kwargs)

    monkeypatch.setattr(engine_learning, "learn_many", counted)
    group = streaming._learn_group

    def stacked(members: list[Any], key: Any, results: list[Any]) -> list[Any]:
        rest = group(members, key, results)
        sizes.append(-(len(members) - len(rest)))  # (negative: wells stacked in one update)
        return rest

    if batched:
        monkeypatch.setattr(streaming, "_learn_group", stacked)
    wells = sorted(field["well"].unique())
    history = pd.concat([field[field["well"] == w].iloc[:HISTORY] for w in wells])
    path = folder / "history.parquet"
    history.to_parquet(path)
    settings = loopback_settings(
        folder, model={"name": model, "method": method, "history": str(path)}
    )
    bus = MemoryTransport(settings.prefix, capacity=8192, keep=16)
    service = Service(settings, bus)
    service.start()
    try:
        assert bus.matching(f"{settings.prefix}/{wells[0]}/sensors", 30.0)
        live = {w: field[field["well"] == w].iloc[HISTORY : HISTORY + LIVE] for w in wells}
        for step in range(LIVE):
            for j, well in enumerate(wells):
                row = live[well].iloc[step]
                when = row["time"].to_pydatetime()
                sample = sample_of(when, row[list(INPUT_COLUMNS)].to_numpy(dtype=float))
                measurement = Measurement(time=when, q_total=float(row["q_total"]))
                keys = [
                    (f"{settings.prefix}/{well}/sensors", sample.model_dump_json()),
                    (
                        f"{settings.prefix}/{well}/measurements/mpfm",
                        measurement.model_dump_json(),
                    ),
                ]
                if j % 2 == 1:  # this well's readings come before their samples
                    keys.reverse()
                for key, payload in keys:
                    bus.put(key, payload.encode())
        store = service.store
        assert store is not None

        def learned() -> bool:
            return all(
                sum(m.status == "learned" for m in store.history(w, 0, 2**62, 10_000)[1]) == LIVE
                for w in wells
            )

        wait_until(learned, 120.0, "every measurement learned")
        # a well test with a waiting caller: answered with the predictions before and after
        row = live[wells[0]].iloc[-1]
        engine = service.engine
        assert engine is not None
        answer = engine.submit_well_test(
            wells[0], Measurement(time=row["time"].to_pydatetime(), q_total=1.1 * row["q_total"])
        ).result(timeout=60)
        result = {w: store.history(w, 0, 2**62, 10_000) for w in wells}
        counters = service.counters.snapshot()
    finally:
        service.stop()
    result["answer"] = answer
    return result, sizes, counters["events"]


def _same(a: float | None, b: float | None) -> bool:
    if a is None or b is None:
        return a is b
    return math.isclose(a, b, rel_tol=1e-12, abs_tol=1e-300) or (math.isnan(a) and math.isnan(b))


@pytest.mark.parametrize(("model", "method"), [("mm", "ol"), ("ham", "ol"), ("mm", "bayes")])
def test_batched_learning_in_the_service_equals_learning_one_by_one(
    tmp_path: Path, field: pd.DataFrame, model: str, method: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    (tmp_path / "one").mkdir()
    (tmp_path / "many").mkdir()
    one, one_sizes, one_events = _replay(tmp_path / "one", field, model, method, False, monkeypatch)
    many, sizes, events = _replay(tmp_path / "many", field, model, method, True, monkeypatch)
    assert one_sizes == []  # the one-by-one run never batched
    calls = [n for n in sizes if n > 0]
    stacked = [-n for n in sizes if n < 0]
    # several wells learned in one call, most of the time, in one stacked update
    assert max(calls) > 1 and sum(n > 1 for n in calls) >= LIVE // 2, calls
    assert max(stacked) > 1 and sum(stacked) > WELLS * LIVE // 2, stacked
    assert sum(calls) == WELLS * LIVE + 1  # every learn once (the well test too)
    assert events.get("internal errors", 0) == one_events.get("internal errors", 0) == 0
    for well in sorted(field["well"].unique()):
        (s1, m1), (s2, m2) = one[well], many[well]
        assert len(s1) == len(s2) == LIVE
        for a, b in zip(s1, s2, strict=True):
            assert a.time_ns == b.time_ns and a.version == b.version
            for name in HistorySample._fields[8:]:  # the rates, version and interval
                assert _same(getattr(a, name), getattr(b, name)), (well, a.time_ns, name)
        assert [m.q_total is not None for m in m1] == [True] * len(m1)
        assert len(m1) == len(m2) >= LIVE
        for a, b in zip(m1, m2, strict=True):
            assert (a.time_ns, a.source, a.status, a.sample_time_ns, a.version_after) == (
                b.time_ns,
                b.source,
                b.status,
                b.sample_time_ns,
                b.version_after,
            )
            assert _same(a.predicted, b.predicted), (well, a.time_ns)
        # the model learned: each learned measurement moved the version on (bayes may
        # refuse an outlier)
        versions = [m.version_after for m in m2 if m.source == "mpfm"]
        assert versions == sorted(versions)
        assert len(set(versions)) == LIVE if method == "ol" else len(set(versions)) > LIVE // 2
    a1, a2 = one["answer"], many["answer"]
    assert a1.status == a2.status == "learned" and a1.model_changed == a2.model_changed
    assert (a1.version_before, a1.version_after) == (a2.version_before, a2.version_after)
    for key in a1.before:
        assert _same(a1.before[key], a2.before[key]) and _same(a1.after[key], a2.after[key])
    if a2.model_changed:
        assert a2.after["q_total"] != a2.before["q_total"]
    assert np.isfinite([s.q_total for s in many[sorted(many)[0]][0] if s.q_total]).all()
