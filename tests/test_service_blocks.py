"""Sensor blocks: many samples of a well in one message, answered with one prediction block.

The engine's real path through the in-memory transport (as ``test_service_engine``). A
block must be answered exactly as its samples sent one by one: the same predictions, the
same stored rows, the same learning from the measurements in between (including a
measurement that waits for a sample of the next block, which makes the well take that
block's rows one by one). A row that breaks a rule is refused alone, with the reason and
sentence the same values get as one sample; a block that is not arrays of one length, or
is too long, is refused whole.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pytest

from replay.client import FieldClient, sample_of
from service.app import Service
from service.errors import InvalidRequest
from service.inputs import parse_sensor, parse_sensor_block
from service.testing import loopback_settings, wait_until
from service.transport import MemoryTransport
from vfm_core.data import target_mask
from vfm_core.messages import Measurement, PredictionBlock, sensor_block
from vfm_core.observations import validate_frame
from vfm_core.simulate import simulate_field
from vfm_core.timeutil import to_ns

pytestmark = pytest.mark.timeout(180)

INPUTS = (0.4, 120.0, 30.0, 60.0, 0.1, 0.6)  # fraction, bar a, bar a, degC, -, -
COLUMNS = ["choke", "p_up", "p_down", "t_up", "eta_gas", "eta_oil"]


@pytest.fixture(scope="module")
def field(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, pd.DataFrame]:
    """A history file of two wells (their first 60 measured days) and the days after."""
    frame = validate_frame(simulate_field(wells=2, years=0.5, seed=7).observations).frame
    frame = frame[target_mask(frame, "all")].reset_index(drop=True)
    first = frame.groupby("well")["time"].transform("min")
    early = frame["time"] < first + pd.Timedelta(days=60)
    path = tmp_path_factory.mktemp("blocks") / "history.parquet"
    frame[early].to_parquet(path)
    return path, frame[~early].reset_index(drop=True)


@contextmanager
def service(folder: Path, **overrides: Any) -> Iterator[tuple[Service, FieldClient]]:
    settings = loopback_settings(folder, **overrides)
    bus = MemoryTransport(settings.prefix)
    svc = Service(settings, bus)
    svc.start()
    try:
        with FieldClient(bus, settings.prefix) as client:
            client.wait_for_service("W01")
            yield svc, client
    finally:
        svc.stop()


def _stream(
    folder: Path,
    history: Path,
    later: pd.DataFrame,
    as_block: Callable[[str, int], bool],
    early_measurement: bool,
) -> tuple[dict[tuple[str, int], float], dict[str, list[Any]], dict[str, Any]]:
    """Send the wells' later rows in parts of 8 samples, the wells in turn, each part
    followed by the MPFM readings of every 4th of its samples: a part as 8 messages, or as
    one block where ``as_block(well, part)``. The service answers what it knows when a
    sample arrives, so both kinds of messages in the same order must give the same
    answers. Returns the predictions, the stored samples and measurements, and the
    counters. With ``early_measurement``, one reading is sent before the part that holds
    its sample (it waits for that sample)."""
    with service(folder, model={"name": "mm", "method": "ol", "history": str(history)}) as (
        svc,
        client,
    ):
        wells = {str(w): rows.iloc[:24] for w, rows in later.groupby("well")}
        expected = 0
        for k, first in enumerate(range(0, 24, 8)):
            for well, rows in wells.items():
                part = [
                    sample_of(t, x)
                    for t, x in zip(
                        rows["time"].iloc[first : first + 8],
                        rows[COLUMNS].to_numpy()[first : first + 8],
                        strict=True,
                    )
                ]
                measured = [
                    Measurement(time=s.time, q_total=float(q))
                    for i, (s, q) in enumerate(
                        zip(part, rows["q_total"].iloc[first : first + 8], strict=True)
                    )
                    if (first + i) % 4 == 1
                ]
                if early_measurement and first == 8:
                    client.send_measurement(well, "mpfm", measured.pop(0))
                if as_block(well, k):
                    client.send_block(well, part)
                else:
                    for sample in part:
                        client.send_sample(well, sample)
                for m in measured:
                    client.send_measurement(well, "mpfm", m)
                expected += len(part)
        wait_until(lambda: client.count >= expected, 60, "every prediction")
        learned = lambda: sum(  # noqa: E731
            m.status == "learned"
            for w in ("W01", "W02")
            for m in svc.store.history(w, 0, 2**62, 1000)[1]  # type: ignore[union-attr]
        )
        wait_until(lambda: learned() == 12, 30, "every measurement learned")
        stored = {w: svc.store.history(w, 0, 2**62, 1000) for w in ("W01", "W02")}  # type: ignore[union-attr]
        return dict(client.predictions), stored, svc.counters.snapshot()


@pytest.mark.parametrize("early_measurement", [False, True], ids=["after", "waiting"])
def test_a_block_is_answered_as_its_samples_one_by_one(
    tmp_path: Path,
    field: tuple[Path, pd.DataFrame],
    early_measurement: bool,
    predict_block_calls: list[int],
) -> None:
    history, later = field
    calls = predict_block_calls
    one = _stream(tmp_path / "one", history, later, lambda well, k: False, early_measurement)
    assert calls == []
    # W02 sends blocks, W01 a block, then 8 samples, then a block
    many = _stream(
        tmp_path / "many",
        history,
        later,
        lambda well, k: well == "W02" or k != 1,
        early_measurement,
    )
    # each block in one model call, but one a measurement waits in (its rows one by one)
    assert calls == [8] * (4 if early_measurement else 5)
    assert len(one[0]) == len(many[0]) == 48
    assert one[0].keys() == many[0].keys()
    for key, q in one[0].items():
        assert many[0][key] == pytest.approx(q, rel=1e-12), key
    for well in ("W01", "W02"):
        samples_one, measured_one = one[1][well]
        samples_many, measured_many = many[1][well]
        assert len(samples_many) == len(samples_one) == 24
        for a, b in zip(samples_one, samples_many, strict=True):
            assert a.time_ns == b.time_ns and a.version == b.version
            assert b.q_total == pytest.approx(a.q_total, rel=1e-12)
            assert b.q_oil == pytest.approx(a.q_oil, rel=1e-12)
        # the same measurements were learned, after the same samples, with the same result
        assert [(m.status, m.sample_time_ns, m.version_after) for m in measured_one] == [
            (m.status, m.sample_time_ns, m.version_after) for m in measured_many
        ]
        assert measured_one[-1].version_after > measured_one[0].version_after  # it learned
    assert one[2]["accepted"] == many[2]["accepted"] == {"sensors": 48, "measurements": 12}
    assert many[2]["rejected"] == {}


def _block(times: list[str], rows: list[tuple[Any, ...]]) -> dict[str, Any]:
    data: dict[str, Any] = {"time": times}
    for j, name in enumerate(COLUMNS):
        data[name] = [r[j] for r in rows]
    return data


def test_rows_that_break_a_rule_are_refused_alone(tmp_path: Path) -> None:
    t = [datetime(2020, 3, 1, 6, m, tzinfo=UTC) for m in range(8)]
    stamps = [x.isoformat() for x in t]
    rows: list[tuple[Any, ...]] = [INPUTS] * 8
    rows[0] = (0.5, 120.0, 30.0, 60.0, 0.1, 0.6)  # at the time of the sample sent before
    rows[1] = (0.4, 30.0, 120.0, 60.0, 0.1, 0.6)  # p_down above p_up
    rows[3] = (0.4, 120.0, 30.0, 60.0, "x", 0.6)  # text where a number belongs
    stamps[5] = stamps[4]  # the row before it, again
    stamps[6] = "yesterday"  # not a time
    with service(tmp_path, model={"name": "last", "method": "ol"}) as (svc, client):
        client.send_measurement("W01", "mpfm", Measurement(time=t[0], q_total=900.0))
        client.send_sample("W01", sample_of(t[0], INPUTS))
        wait_until(
            lambda: client.count == 0 and svc.counters.snapshot()["accepted"].get("sensors") == 1,
            20,
            "the first sample",
        )
        client.put_raw("vfm/W01/sensors", json.dumps(_block(stamps, rows)))
        wait_until(lambda: client.count >= 3, 20, "the block's answers")
        snap = svc.counters.snapshot()
        assert snap["rejected"] == {
            "time going backwards": 1,  # row 0: not after the sample sent before
            "p_down >= p_up": 1,
            "wrong type": 2,  # rows 3 and 6
            "duplicate": 1,  # row 5 repeats row 4
        }
        assert snap["accepted"]["sensors"] == 1 + 3  # rows 2, 4, 7
        samples, _ = svc.store.history("W01", 0, 2**62, 100)  # type: ignore[union-attr]
        assert [s.time_ns for s in samples] == [to_ns(t[i]) for i in (0, 2, 4, 7)]
        assert client.prediction("W01", t[7]) == 900.0  # model last: the latest measured rate


def test_a_block_that_is_not_arrays_of_one_length_or_too_long_is_refused_whole(
    tmp_path: Path,
) -> None:
    stamps = [datetime(2020, 3, 1, 6, m, tzinfo=UTC).isoformat() for m in range(5)]
    short = _block(stamps, [INPUTS] * 5)
    short["choke"] = short["choke"][:4]
    scalar = _block(stamps, [INPUTS] * 5)
    scalar["p_up"] = 120.0
    with service(
        tmp_path, model={"name": "last", "method": "ol"}, inputs={"max_block_samples": 4}
    ) as (svc, client):
        client.put_raw("vfm/W01/sensors", json.dumps(short))
        client.put_raw("vfm/W01/sensors", json.dumps(scalar))
        client.put_raw("vfm/W01/sensors", json.dumps(_block(stamps, [INPUTS] * 5)))
        client.put_raw("vfm/W01/sensors", json.dumps({"time": stamps}))
        wait_until(lambda: sum(svc.counters.snapshot()["rejected"].values()) == 4, 20, "refusals")
        assert svc.counters.snapshot()["rejected"] == {
            "malformed block": 2,
            "block too large": 1,
            "missing field": 1,
        }
        assert svc.counters.snapshot()["accepted"].get("sensors", 0) == 0


def test_a_refused_row_gets_the_sentence_of_one_sample() -> None:
    """The block's check runs on columns; a row it flags is judged as one sample."""
    stamps = ["2020-03-01T06:00:00Z", "2020-03-01T06:01:00+01:00", "2020-03-01T06:02:00"]
    rows: list[tuple[Any, ...]] = [INPUTS, (1.5, 120.0, 30.0, 60.0, 0.1, 0.6), INPUTS]
    rows.append((0.4, 120.0, 30.0, float("nan"), 0.1, 0.6))
    stamps.append("2020-03-01T06:03:00Z")
    data = _block(stamps, rows)
    block = parse_sensor_block(
        data, 100, lambda when, what: None, 0, to_ns(datetime(2100, 1, 1, tzinfo=UTC))
    )
    assert [i for i, _ in block.refused] == [1, 3]
    for i, error in block.refused:
        with pytest.raises(InvalidRequest) as single:
            parse_sensor({name: data[name][i] for name in data})
        assert (error.reason, error.message) == (single.value.reason, single.value.message)
    # the offset is honoured, a naive time is UTC, the inputs are the rows' own
    assert block.times_ns.tolist() == [
        to_ns(datetime(2020, 3, 1, 6, 0, tzinfo=UTC)),
        to_ns(datetime(2020, 3, 1, 6, 2, tzinfo=UTC)),
    ]
    np.testing.assert_array_equal(block.inputs, [INPUTS, INPUTS])
    # the row before 06:00 UTC (06:01+01:00 is 05:01 UTC) was refused for its choke first


def test_prediction_block_parses_into_single_predictions() -> None:
    payload = sensor_block(
        [sample_of(datetime(2020, 1, 1, tzinfo=UTC) + timedelta(seconds=s), INPUTS) for s in (0, 1)]
    )
    data = json.loads(payload)
    assert data["time"] == ["2020-01-01T00:00:00Z", "2020-01-01T00:00:01Z"]
    assert data["p_up"] == [120.0, 120.0]
    block = PredictionBlock.model_validate(
        {
            "time": data["time"],
            "q_total": [10.0, 11.0],
            "q_gas": [1.0, 1.0],
            "q_oil": [2.0, 2.0],
            "q_water": [7.0, 8.0],
            "model": "mm",
            "version": 3,
        }
    )
    rows = block.predictions()
    assert [p.q_total for p in rows] == [10.0, 11.0] and rows[1].q_total_p05 is None
    with pytest.raises(ValueError, match="at least one"):
        sensor_block([])


def test_a_block_reads_each_time_as_one_sample_does() -> None:
    """Times are read by the same parser as one sample's (pydantic): the same rows pass,
    at the same times, and the others get one sample's reason (a number is read as Unix
    seconds; a text that is not ISO 8601 is refused; an integer too large for any time
    refuses its row, not the block)."""
    texts: list[Any] = [
        "2020-03-01T06:00:00Z",
        "2020-03-01T06:00:00+01:00",
        "2020-03-01T06:00:00",
        "2020-03-01T06:00:00.000123Z",
        "2024",
        1_600_000_000,
        "20240101",
        "now",
        "2024-01",
        "2024/01/01",
        " 2024-01-01T00:00:00",
        "2020-03-01T06:00:00Z ",
        10**400,
        "",
    ]
    data = _block(texts, [INPUTS] * len(texts))
    latest = to_ns(datetime(2100, 1, 1, tzinfo=UTC))

    def check_time(when: datetime, what: str) -> None:
        if not 0 <= to_ns(when) <= latest:
            raise InvalidRequest("out of range", "time out of range")

    block = parse_sensor_block(data, 100, check_time, 0, latest)
    refused = dict(block.refused)
    accepted = iter(block.times_ns.tolist())
    for i in range(len(texts)):
        row = {name: data[name][i] for name in data}
        try:
            sample = parse_sensor(row)
            check_time(sample.time, "sample")
        except InvalidRequest as single:
            assert i in refused, (texts[i], "the block took a row one sample is refused for")
            assert (refused[i].reason, refused[i].message) == (single.reason, single.message)
            continue
        assert i not in refused, (texts[i], refused.get(i))
        assert next(accepted) == to_ns(sample.time), texts[i]
    # "now" and the huge integer are refused, "2024" is Unix seconds, as for one sample
    assert 7 in refused and 12 in refused and 4 not in refused
    assert refused[12].reason == "not finite"


def test_rows_out_of_order_are_judged_as_one_by_one(tmp_path: Path) -> None:
    """Each row is judged against the well's previous accepted sample, as if sent alone:
    a row refused does not become the reference for the next one."""
    t = {k: datetime(2020, 3, 1, 6, 0, tzinfo=UTC) + timedelta(seconds=k) for k in range(20)}
    a, b, c = INPUTS, (0.5, *INPUTS[1:]), (0.6, *INPUTS[1:])
    rows = [(t[9], a), (t[9], a), (t[11], b), (t[11], b), (t[10], c), (t[12], b)]
    results = []
    for as_block in (False, True):
        with service(tmp_path / str(as_block), model={"name": "last", "method": "ol"}) as (
            svc,
            client,
        ):
            client.send_sample("W01", sample_of(t[10], INPUTS))
            samples = [sample_of(when, x) for when, x in rows]
            if as_block:
                client.send_block("W01", samples)
            else:
                for sample in samples:
                    client.send_sample("W01", sample)
            wait_until(
                lambda: sum(svc.counters.snapshot()["rejected"].values()) == 4, 20, "refusals"
            )
            stored = svc.store.history("W01", 0, 2**62, 100)[0]  # type: ignore[union-attr]
            results.append((svc.counters.snapshot()["rejected"], [s.time_ns for s in stored]))
    assert results[0] == results[1]
    assert results[0] == (
        {"time going backwards": 3, "duplicate": 1},
        [to_ns(t[10]), to_ns(t[11]), to_ns(t[12])],
    )


def test_a_prediction_block_writes_what_is_not_finite_as_null() -> None:
    from service.engine.worker import _json_floats

    assert _json_floats(np.array([1.5, np.nan, np.inf])) == [1.5, None, None]
    assert _json_floats(np.array([1.0, 2.0])) == [1.0, 2.0]
    block = PredictionBlock.model_validate(
        {
            "time": ["2020-01-01T00:00:00Z"],
            "q_total": [10.0],
            "q_gas": [1.0],
            "q_oil": [2.0],
            "q_water": [7.0],
            "model": "mm",
            "version": 3,
            "q_total_std": [None],
            "q_total_p05": [None],
            "q_total_p95": [None],
        }
    )
    assert block.predictions()[0].q_total_std is None


def test_a_failed_block_call_leaves_the_features_as_they_were(
    field: tuple[Path, pd.DataFrame], monkeypatch: pytest.MonkeyPatch
) -> None:
    from dataclasses import replace

    import torch

    from vfm_core.learning import DEFAULT_TRAIN
    from vfm_core.learning.streaming import WellLearner

    history, later = field
    rows = pd.read_parquet(history)
    rows = rows[rows["well"] == "W01"]
    learner = WellLearner("W01", "mm", "ol", train=replace(DEFAULT_TRAIN["mm"], max_iter=20))
    learner.fit_history(
        torch.tensor(rows[COLUMNS].to_numpy()),
        torch.tensor(rows["q_total"].to_numpy()),
        torch.tensor(pd.DatetimeIndex(rows["time"]).as_unit("ns").asi8),
    )
    part = later[later["well"] == "W01"].iloc[:5]
    before = learner.features.state()

    def fail(*args: Any) -> Any:
        raise RuntimeError("the model call failed")

    monkeypatch.setattr(learner, "_block_answer", fail)
    with pytest.raises(RuntimeError):
        learner.predict_block(
            part[COLUMNS].to_numpy(), pd.DatetimeIndex(part["time"]).as_unit("ns").asi8
        )
    assert learner.features.state() == before
