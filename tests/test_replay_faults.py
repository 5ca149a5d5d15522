"""``vfm replay`` sends a reading outside its physical span as it is (issue 39): the service
sees the ``out_of_range`` fault ``vfm evaluate`` sees.

A short simulated field (one well, 0.6 years, seed 11) with ``p_down`` at -1 bar a for 10
days (``vfm_core.faults_sim.inject_fault``, as ``vfm simulate --fault``) is replayed into a
service fitted on its first 120 days. With fault detection on, the service raises the fault
(start at the first bad row, end at the next good one), stores the raw -1, stands in for
it (every sample answered) and holds the paired measurements. With detection off, it
refuses those samples with their counted reason and answers every other one. A row with
another problem (a zero pressure) is still removed by the replay's loader and counted in
its summary. No threshold: the span is the physical one (``DEFAULT_RANGES``).
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pandas as pd
import pytest
from http_support import http_get

from replay.client import FieldClient, sample_of
from replay.replayer import ReplayResult, replay_frame
from vfm_core.faults_sim import inject_fault
from vfm_core.observations import load_observations, save_observations

pytestmark = pytest.mark.timeout(180)

WELL = "W01"


@pytest.fixture(scope="module")
def field(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """The faulty field's file, its rows as the replay loads them, the fault's truth, the
    replay's start (30 days before the fault; the service learns the rows before it)."""
    from vfm_core.simulate import simulate_field

    folder = tmp_path_factory.mktemp("replay_faults")
    obs = simulate_field(wells=1, years=0.6, seed=11).observations
    first = pd.to_datetime(obs["time"], utc=True).iloc[0]
    bad, truth = inject_fault(
        obs, WELL, "p_down", "out_of_range", first + pd.Timedelta(days=150), days=10
    )
    data = save_observations(bad, folder / "field.csv")
    frame = load_observations(data, keep_out_of_range=True).frame
    split = str((first + pd.Timedelta(days=120)).date())
    return {"data": data, "frame": frame, "truth": truth, "split": split, "bad": bad}


def _settings(folder: Path, field: dict[str, Any], enabled: bool, **extra: Any) -> Any:
    from service.testing import loopback_settings

    model = {"name": "mm", "method": "ol", "history": str(field["data"])}
    model["history_until"] = field["split"]
    return loopback_settings(folder, model=model, sensor_faults={"enabled": enabled}, **extra)


@contextmanager
def in_memory(folder: Path, field: dict[str, Any], enabled: bool) -> Iterator[tuple[Any, Any]]:
    """An in-process service on the in-memory transport, and that transport."""
    from service.app import Service
    from service.transport import MemoryTransport

    settings = _settings(folder, field, enabled)
    bus = MemoryTransport(settings.prefix)
    service = Service(settings, bus)
    service.start()
    try:
        yield service, bus
    finally:
        service.stop()


def _ns(times: Any) -> np.ndarray:
    return pd.to_datetime(pd.Series(times), utc=True).dt.as_unit("ns").astype("int64").to_numpy()


def _fault_rows(field: dict[str, Any]) -> pd.DataFrame:
    frame = field["frame"]
    return frame[(frame["well"] == WELL) & (frame["p_down"] < 0)]


def _replay(bus: Any, field: dict[str, Any]) -> ReplayResult:
    return replay_frame(
        field["frame"], bus=bus, start=field["split"], progress=False, idle_timeout=3.0
    )


def test_the_replay_keeps_the_rows_out_of_span_and_only_those(field: dict[str, Any]) -> None:
    """The loader keeps the rows out of span raw; sample_of sends them only when asked."""
    rows = _fault_rows(field)
    assert len(rows) == field["truth"]["rows"] and (rows["p_down"] == -1.0).all()
    when = rows["time"].iloc[0].to_pydatetime()
    values = rows[["choke", "p_up", "p_down", "t_up", "eta_gas", "eta_oil"]].iloc[0].tolist()
    assert sample_of(when, values, out_of_span=True).p_down == -1.0
    with pytest.raises(ValueError):  # pydantic's ValidationError: strict by default
        sample_of(when, values)
    with pytest.raises(ValueError):  # a zero pressure lies inside the span: still refused
        sample_of(when, [*values[:2], 0.0, *values[3:]], out_of_span=True)
    with pytest.raises(ValueError):  # nor is a missing reading a reading out of span
        sample_of(when, [*values[:1], float("nan"), *values[2:]], out_of_span=True)


def test_with_detection_on_the_service_raises_the_fault_and_holds(
    field: dict[str, Any], tmp_path: Path
) -> None:
    truth, rows = field["truth"], _fault_rows(field)
    t_bad = _ns(rows["time"])
    with in_memory(tmp_path, field, enabled=True) as (service, bus):
        result = _replay(bus, field)
        assert result.out_of_span == len(rows) and result.skipped == 0
        assert result.missing == 0  # stood in for: every sample answered
        assert f"{len(rows):,} sample(s) with an input outside its physical span" in (
            result.summary()
        )
        view = http_get(service, f"/wells/{WELL}")
        (fault,) = [f for f in view["sensor_faults"] if f["kind"] == "out_of_range"]
        assert fault["sensor"] == "p_down"
        assert pd.Timestamp(fault["start"]) == pd.Timestamp(truth["start"])
        times = field["frame"]["time"]
        after = times[times > pd.Timestamp(truth["end"])].iloc[0]  # the next good row
        assert pd.Timestamp(fault["end"]) == after
        samples, measurements = service.store.history(WELL, 0, 2**62, 100_000)
        stored = {s.time_ns: s.p_down for s in samples}
        assert [stored[int(t)] for t in t_bad] == [-1.0] * len(rows)  # the raw value kept
        status = {m.time_ns: m.status for m in measurements}
        assert {status[int(t)] for t in t_bad} == {"held"}  # not learned
        assert status[int(_ns([after])[0])] != "held"  # the fault ended: learned again
        _a_block_is_taken_too(service, bus, t_bad)


def _a_block_is_taken_too(service: Any, bus: Any, t_bad: np.ndarray) -> None:
    """A sensor block (after the file's end) with one sample out of span between good ones:
    taken raw, a second out_of_range fault from that sample to the next."""
    from service.testing import wait_until

    samples, _ = service.store.history(WELL, 0, 2**62, 100_000)
    last = samples[-1]
    good = [last.choke, last.p_up, last.p_down, last.t_up, last.eta_gas, last.eta_oil]
    t0 = pd.Timestamp(last.time_ns, tz="UTC") + pd.Timedelta(hours=1)
    when = [(t0 + pd.Timedelta(hours=k)).to_pydatetime() for k in range(3)]
    block = [
        sample_of(when[0], good),
        sample_of(when[1], [good[0], good[1], -1.0, *good[3:]], out_of_span=True),
        sample_of(when[2], good),
    ]
    with FieldClient(bus, "vfm") as client:
        client.send_block(WELL, block)
        for w in when:
            client.wait_for_prediction(WELL, w, timeout=30)
    wait_until(lambda: len(service.store.history(WELL, 0, 2**62, 100_000)[0]) == len(samples) + 3,
               30, "the block's samples to be stored")  # fmt: skip
    stored = {s.time_ns: s.p_down for s in service.store.history(WELL, 0, 2**62, 100_000)[0]}
    assert stored[int(_ns([when[1]])[0])] == -1.0
    view = http_get(service, f"/wells/{WELL}")
    ranged = [f for f in view["sensor_faults"] if f["kind"] == "out_of_range"]
    assert len(ranged) == 2
    assert pd.Timestamp(ranged[-1]["start"]) == pd.Timestamp(when[1])
    assert pd.Timestamp(ranged[-1]["end"]) == pd.Timestamp(when[2])


def test_with_detection_off_the_service_refuses_them_and_nothing_stalls(
    field: dict[str, Any], tmp_path: Path
) -> None:
    rows = _fault_rows(field)
    with in_memory(tmp_path, field, enabled=False) as (service, bus):
        result = _replay(bus, field)
        assert result.out_of_span == len(rows)
        # every other sample answered; exactly the refused ones got none, reason counted
        assert result.missing == len(rows)
        assert result.missing_samples[0] == (WELL, int(_ns(rows["time"])[0]))
        assert service.counters.rejected_of(WELL)["negative or zero pressure"] == len(rows)
        view = http_get(service, f"/wells/{WELL}")
        assert not view.get("sensor_faults")
        samples, _ = service.store.history(WELL, 0, 2**62, 100_000)
        assert min(s.p_down for s in samples) > 0


def test_vfm_replay_over_zenoh_sends_them_and_removes_other_problems(
    field: dict[str, Any], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The command line: the loader keeps the rows out of span and still removes a row with
    another problem (a zero p_up), with its reason in the output; the service over Zenoh
    raises the fault."""
    from service.app import running
    from vfm_core.cli import main

    bad = field["bad"].copy()
    late = pd.to_datetime(bad["time"], utc=True) > pd.Timestamp(field["truth"]["end"])
    zero = int(np.flatnonzero(late.to_numpy())[3])
    bad.loc[zero, "p_up"] = 0.0
    data = save_observations(bad, tmp_path / "field.csv")
    n = len(_fault_rows(field))
    with running(_settings(tmp_path, field, True)) as svc:
        argv = ["replay", str(data), "--connect", svc.locators[0], "--start", field["split"]]
        assert main([*argv, "--quiet", "--idle-timeout", "5"]) == 0
        text = capsys.readouterr().out
        assert "removed 1 (negative or zero pressure: 1)" in text
        assert f"input out of range: {n} rows kept with raw values" in text
        assert f"{n} sample(s) with an input outside its physical span were sent" in text
        view = httpx.get(f"{svc.http_url}/wells/{WELL}", timeout=10).json()
        (fault,) = [f for f in view["sensor_faults"] if f["kind"] == "out_of_range"]
        assert fault["sensor"] == "p_down"
        assert pd.Timestamp(fault["start"]) == pd.Timestamp(field["truth"]["start"])
