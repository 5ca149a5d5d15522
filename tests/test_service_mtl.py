"""``mtl`` live: the field-wide model through the service agrees with ``vfm evaluate``.

The real engine (store in tmp_path, the in-memory transport, the shared field client)
fits ``mtl`` on the history file of a three-well field and is then fed the rest of the
file day by day, in time order (each day's messages are all handled before the next
day's are sent: the order a live field's messages keep when the service keeps up). The
predictions it publishes must be those of :func:`vfm_core.jobs.study.run_prequential`
on the same file, to float noise, with ``ol`` (day rounds) and with ``pbl`` (retrains on
the study's calendar). A restart (after a clean stop, and after a stop that wrote no
final checkpoint, so that recovery re-learns from the store) continues with the same
numbers. A change of one well's model to or from ``mtl`` is refused with a sentence.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pytest

from replay.client import FieldClient
from service.app import Service
from service.config import Settings
from service.engine import Engine
from service.engine.checkpoints import Checkpoints
from service.errors import InvalidRequest
from service.store import Store
from service.testing import loopback_settings, study_settings, wait_until
from service.transport import MemoryTransport
from vfm_core.data import target_mask
from vfm_core.jobs.study import mape, run_prequential
from vfm_core.learning import DEFAULT_TRAIN
from vfm_core.messages import Measurement
from vfm_core.observations import validate_frame
from vfm_core.simulate import simulate_field

pytestmark = pytest.mark.timeout(300)

SPLIT = "2016-10-01"
#: a short initial fit, the same for the service and the study (the test is about agreement)
TRAIN = {"max_iter": 80, "patience": 10}


@pytest.fixture(scope="module")
def field(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, pd.DataFrame]:
    folder = tmp_path_factory.mktemp("mtl")
    frame = validate_frame(simulate_field(wells=3, years=1, seed=3).observations).frame
    data = folder / "field.parquet"
    frame.to_parquet(data)
    return data, frame


def _settings(folder: Path, data: Path, method: str, **overrides: Any) -> Settings:
    return study_settings(folder, data, "mtl", method, SPLIT, TRAIN, review=True, **overrides)


@contextmanager
def _serving(settings: Settings) -> Iterator[tuple[Service, FieldClient]]:
    bus = MemoryTransport(settings.prefix)
    service = Service(settings, bus)
    service.start()
    try:
        with FieldClient(bus, settings.prefix) as client:
            client.wait_for_service("W01")
            yield service, client
    finally:
        service.stop()


def _feed(service: Service, client: FieldClient, rows: pd.DataFrame) -> None:
    """Send the rows day by day; each day's messages are handled before the next day's go."""
    counters = service.counters
    base = counters.snapshot()
    sensors0 = base["accepted"].get("sensors", 0)
    learned0 = base["events"].get("learned", 0)
    sent_samples = sent_measurements = 0
    for _, day in rows.groupby(rows["time"].dt.floor("D"), sort=True):
        sent = client.stream(day)
        sent_samples += len(sent.samples)
        sent_measurements += sent.measurements

        def handled(s: int = sent_samples, m: int = sent_measurements) -> bool:
            snap = counters.snapshot()
            return (
                snap["accepted"].get("sensors", 0) - sensors0 >= s
                and snap["events"].get("learned", 0) - learned0 >= m
            )

        wait_until(handled, 60, "the day's messages to be handled")


def _received(client: FieldClient, study: pd.DataFrame) -> list[tuple[str, int]]:
    """The study's (well, time ns) keys, once the client has received a prediction for each
    (they are published after the service counts the sample handled: wait for them)."""
    keys = [(w, t.value) for w, t in zip(study["well"], study["time"], strict=True)]
    wait_until(lambda: all(k in client.predictions for k in keys), 30, "every prediction")
    return keys


def _streamed(client: FieldClient, study: pd.DataFrame) -> np.ndarray:
    return np.array([client.predictions[k] for k in _received(client, study)])


def _study(frame: pd.DataFrame, method: str) -> pd.DataFrame:
    train = replace(DEFAULT_TRAIN["mtl"], **TRAIN)
    return run_prequential(frame, "mtl", method, split=SPLIT, train=train).predictions


def _live(frame: pd.DataFrame) -> pd.DataFrame:
    return frame[frame["time"] >= pd.Timestamp(SPLIT, tz="UTC")].reset_index(drop=True)


@pytest.mark.parametrize("method", ["ol", "pbl:14d"])
def test_streamed_mtl_agrees_with_the_study(
    tmp_path: Path, field: tuple[Path, pd.DataFrame], method: str
) -> None:
    data, frame = field
    study = _study(frame, method)
    with _serving(_settings(tmp_path, data, method)) as (service, client):
        _feed(service, client, _live(frame))
        streamed = _streamed(client, study)
        engine = service.engine
        assert engine is not None
        views = {w: engine.well_view(w) for w in ("W01", "W02", "W03")}
    np.testing.assert_allclose(streamed, study["predicted"].to_numpy(), rtol=1e-9)
    served, offline = mape(streamed, study["measured"]), mape(study["predicted"], study["measured"])
    assert served == pytest.approx(offline, rel=1e-9)
    print(f"mtl {method}: MAPE streamed {served:.4f} % = offline {offline:.4f} %")
    # every well of the field answers with the same (field-wide) model and version
    assert {(v["model"], v["method"]) for v in views.values()} == {("mtl", method)}
    assert len({v["version"] for v in views.values()}) == 1
    assert all(v["ready"] for v in views.values())


@pytest.mark.parametrize("final_checkpoint", [True, False])
def test_a_restart_continues_with_the_same_numbers(
    tmp_path: Path,
    field: tuple[Path, pd.DataFrame],
    final_checkpoint: bool,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Half the live period, a stop (with its final checkpoint, or without one: the store
    holds an older snapshot and the rest is re-learned), a new engine on the same store,
    the other half: the predictions of an uninterrupted run."""
    data, frame = field
    study = _study(frame, "ol")
    live = _live(frame)
    days = live["time"].dt.floor("D")
    half = days < days.unique()[len(days.unique()) // 2]
    settings = _settings(tmp_path, data, "ol", store={"checkpoint_every": 7})
    boundary = days.unique()[len(days.unique()) // 2]
    with _serving(settings) as (service, client):
        _feed(service, client, live[half])
        _received(client, study[study["time"].dt.floor("D") < boundary])
        first = dict(client.predictions)
        engine = service.engine
        assert engine is not None
        before = engine.well_view("W02")
        if not final_checkpoint:
            monkeypatch.setattr(Checkpoints, "final_ops", lambda self, wells: [])
    monkeypatch.undo()
    saved = _newest_snapshot(settings)
    if final_checkpoint:
        assert saved == before["version"]
    else:  # an older snapshot: what came after it is re-learned from the store
        assert 0 < saved < before["version"]
    with _serving(settings) as (service, client):
        engine = service.engine
        assert engine is not None
        after = engine.well_view("W02")
        assert (after["version"], after["measurements_remembered"]) == (
            before["version"],
            before["measurements_remembered"],
        )
        _feed(service, client, live[~half])
        _received(client, study[study["time"].dt.floor("D") >= boundary])
        second = dict(client.predictions)
    both = {**first, **second}
    keys = [(w, t.value) for w, t in zip(study["well"], study["time"], strict=True)]
    got = np.array([both[k] for k in keys])
    np.testing.assert_allclose(got, study["predicted"].to_numpy(), rtol=1e-9)


def _newest_snapshot(settings: Settings) -> int:
    """The field version of the newest checkpoint row of any well in the store."""
    store = Store(settings.store.path)
    try:
        rows = [store.latest_checkpoint(w) for w in ("W01", "W02", "W03")]
    finally:
        store.close()
    return max(r.version for r in rows if r is not None)


def test_a_model_change_to_or_from_mtl_is_refused(
    tmp_path: Path, field: tuple[Path, pd.DataFrame]
) -> None:
    data, frame = field
    with _serving(_settings(tmp_path / "mtl", data, "ol")) as (service, client):
        engine: Engine | None = service.engine
        assert engine is not None
        with pytest.raises(InvalidRequest, match="field-wide model mtl"):
            engine.change_model("W01", model="mm")
        # a well test is stored and held with its day's round (the answer says so)
        day = _live(frame).head(6)
        _feed(service, client, day)
        at = day[day["well"] == "W01"]["time"].iloc[-1]
        result = engine.submit_well_test(
            "W01", Measurement(time=at.to_pydatetime(), q_total=float(day["q_total"].iloc[0]))
        ).result(30)
        assert (result.status, result.model_changed) == ("learned", False)
        assert "when the day ends" in result.message
    per_well = loopback_settings(
        tmp_path / "mm",
        model={"name": "mm", "method": "ol", "history": str(data), "history_until": SPLIT},
    )
    with _serving(per_well) as (service, _):
        engine = service.engine
        assert engine is not None
        with pytest.raises(InvalidRequest, match="'mtl' is field-wide"):
            engine.change_model("W01", model="mtl")


def test_mtl_predicts_a_well_first_seen_live_after_its_first_day(
    tmp_path: Path, field: tuple[Path, pd.DataFrame]
) -> None:
    """W03 is not in the history file: first seen live, it joins the field at its prior
    and is answered once its first day's measurements have been learned."""
    data, frame = field
    history = frame[frame["well"] != "W03"]
    path = tmp_path / "history.parquet"
    history.to_parquet(path)
    live = _live(frame).head(60)
    with _serving(_settings(tmp_path, path, "ol")) as (service, client):
        _feed(service, client, live)
        engine = service.engine
        assert engine is not None
        assert engine.well_view("W03")["ready"]
        w3 = live[(live["well"] == "W03") & target_mask(live, "all")]
        first_day = w3["time"].dt.floor("D") == w3["time"].dt.floor("D").iloc[0]
        wait_until(
            lambda: all((("W03", t.value) in client.predictions) for t in w3["time"][~first_day]),
            30,
            "W03's predictions after its first day",
        )
        assert not any(("W03", t.value) in client.predictions for t in w3["time"][first_day])
        got = [client.predictions[("W03", t.value)] for t in w3["time"][~first_day]]
    assert mape(got, w3["q_total"][~first_day]) < 20.0


def test_a_purged_well_used_again_starts_afresh_and_survives_a_restart(
    tmp_path: Path, field: tuple[Path, pd.DataFrame], monkeypatch: pytest.MonkeyPatch
) -> None:
    """W03 is purged (DELETE /wells/W03?purge=true) and its id used again: it starts at its
    prior with nothing remembered, and a restart (without a final checkpoint, so the store's
    rows are re-learned) gives back what it has learned since."""
    data, frame = field
    live = _live(frame)
    days = live["time"].dt.floor("D")
    first, second, third = (
        days < days.unique()[10],
        (days >= days.unique()[10]) & (days < days.unique()[30]),
        days >= days.unique()[30],
    )
    settings = _settings(tmp_path, data, "ol", store={"checkpoint_every": 5})
    with _serving(settings) as (service, client):
        engine = service.engine
        assert engine is not None
        _feed(service, client, live[first])
        engine.retire_well("W03", purge=True)
        _feed(service, client, live[second])
        w3 = live[second & (live["well"] == "W03").to_numpy() & target_mask(live, "all")]
        view = engine.well_view("W03")
        assert view["measurements_remembered"] == len(w3) and view["ready"]
        monkeypatch.setattr(Checkpoints, "final_ops", lambda self, wells: [])
    monkeypatch.undo()
    with _serving(settings) as (service, client):
        engine = service.engine
        assert engine is not None
        again = engine.well_view("W03")
        assert again["measurements_remembered"] == len(w3)
        assert again["version"] == view["version"]
        _feed(service, client, live[third].head(30))
        assert engine.well_view("W03")["ready"]
