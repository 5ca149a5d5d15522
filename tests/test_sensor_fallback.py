"""Keep predicting, learn nothing wrong (issue 39, item 3): while an input is flagged the
service predicts with its fallback (vfm_core.sensor_faults.WellSensorFaults.fallbacks) and a
widened interval, learns nothing from the measurements at its samples, says so in the
message and ``GET /wells/{well}``, keeps the raw values, and uses the reading again once the
fault ends; the fallback's state survives a checkpoint.

The simulated field (seed 5527, one well, 1.7 years, p_up frozen for 75 days from day 420,
after a year of the input's history) is used by no other test and set no threshold: the
fallback's rules follow from the input's own history (see the module). With a fault after
less than a year (the same seed, day 330 of 1.4 years) the well's decline did not stand out
of its noise: the stand-in was then the frozen reading itself, no better and no worse.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pytest
from http_support import http_get

from vfm_core.faults_sim import inject_fault
from vfm_core.sensor_faults import (
    SENSORS,
    Fallback,
    WellSensorFaults,
    fallback_points,
    widened_rates,
)

WELL = "W01"
FAULT_DAYS = 75.0


@pytest.fixture(scope="module")
def field() -> tuple[pd.DataFrame, pd.DataFrame, pd.DataFrame, dict[str, Any]]:
    """One well's clean rows, the same with p_up frozen for 75 days from day 420, the true
    rates (aligned with the rows), and the injected fault's truth."""
    from vfm_core.simulate import simulate_field

    sim = simulate_field(wells=1, years=1.7, seed=5527)
    obs = sim.observations.reset_index(drop=True)
    truth = sim.truth_samples.reset_index(drop=True)
    start = pd.to_datetime(obs["time"], utc=True).iloc[0] + pd.Timedelta(days=420)
    bad, fault = inject_fault(obs, WELL, "p_up", "frozen", start, days=FAULT_DAYS)
    return obs, bad, truth, fault


def ns(times: pd.Series) -> np.ndarray:
    return pd.to_datetime(times, utc=True).dt.as_unit("ns").astype("int64").to_numpy()


# -- the detector's fallback (pure) --------------------------------------------------------------
def feed(det: WellSensorFaults, frame: pd.DataFrame, upto: int | None = None) -> None:
    times, rows = ns(frame["time"])[:upto], frame[list(SENSORS)].to_numpy(float)[:upto]
    for t, row in zip(times, rows, strict=True):
        det.update(int(t), row.tolist())


def test_the_fallback_is_nearer_the_true_input_than_the_frozen_reading(field: Any) -> None:
    """Over the frozen rows after detection: the stand-in's error on p_up is below the
    frozen reading's, and its 90 % span holds the true p_up more often than not."""
    obs, bad, _, _ = field
    det = WellSensorFaults()
    times, rows = ns(bad["time"]), bad[list(SENSORS)].to_numpy(float)
    true_p_up = obs["p_up"].to_numpy(float)
    fb_err, frozen_err, inside = [], [], []
    for k, (t, row) in enumerate(zip(times, rows, strict=True)):
        det.update(int(t), row.tolist())
        used = det.fallbacks(int(t), row.tolist())
        if used:
            (f,) = used
            assert (f.sensor, f.kind, f.measured) == ("p_up", "frozen", row[1])
            fb_err.append(abs(f.value - true_p_up[k]))
            frozen_err.append(abs(row[1] - true_p_up[k]))
            inside.append(f.low <= true_p_up[k] <= f.high)
    assert len(fb_err) > 50, "the frozen p_up was found and stood in for"
    assert np.mean(fb_err) < np.mean(frozen_err), (np.mean(fb_err), np.mean(frozen_err))
    assert np.mean(inside) > 0.5
    assert det.fallbacks(int(times[-1]), rows[-1].tolist()) == []  # ended: the reading again


def test_the_fallback_state_survives_a_checkpoint_and_an_old_one_restores(field: Any) -> None:
    _, bad, _, fault = field
    t_bad = ns(bad["time"])
    upto = int(np.searchsorted(t_bad, pd.Timestamp(fault["start"]).value)) + 40
    det = WellSensorFaults()
    feed(det, bad, upto)
    t, row = int(t_bad[upto]), bad[list(SENSORS)].to_numpy(float)[upto].tolist()
    want = det.fallbacks(t, row)
    assert [f.sensor for f in want] == ["p_up"]
    saved = json.loads(json.dumps(det.state()))
    again = WellSensorFaults()
    assert again.restore(saved)
    assert again.fallbacks(t, row) == want
    # the next samples go on the same way on both
    feed(det, bad.iloc[upto : upto + 30])
    feed(again, bad.iloc[upto : upto + 30])
    t2, row2 = int(t_bad[upto + 30]), bad[list(SENSORS)].to_numpy(float)[upto + 30].tolist()
    assert again.fallbacks(t2, row2) == det.fallbacks(t2, row2)
    # a checkpoint of before the fallback existed: no levels, no anchors; it still restores
    # and stands in (the anchor is made from what the detectors hold)
    old = {k: v for k, v in saved.items() if k not in ("levels", "anchors")}
    older = WellSensorFaults()
    assert older.restore(old)
    (f,) = older.fallbacks(t, row)
    assert f.sensor == "p_up" and math.isfinite(f.value) and f.spread > 0


def test_the_widened_interval_covers_every_point_s_interval() -> None:
    f = Fallback("p_up", "frozen", 1, 100.0, 2.0, 96.7, 103.3, 105.0, 0)
    points = fallback_points([0.5, 105.0, 30.0, 60.0, 0.1, 0.6], [f])
    assert [p[1] for p in points] == [100.0, 96.7, 103.3]
    rates = [
        {"q_total": 100.0, "q_total_std": 5.0, "q_total_p05": 92.0, "q_total_p95": 108.0},
        {"q_total": 90.0, "q_total_std": 5.0, "q_total_p05": 82.0, "q_total_p95": 98.0},
        {"q_total": 110.0, "q_total_std": 5.0, "q_total_p05": 102.0, "q_total_p95": 118.0},
    ]
    out = widened_rates(rates)
    assert (out["q_total"], out["q_total_p05"], out["q_total_p95"]) == (100.0, 82.0, 118.0)
    assert out["q_total_std"] == pytest.approx(math.hypot(5.0, 20.0 / (2 * 1.6448536)), 1e-6)
    plain = widened_rates([{"q_total": r["q_total"]} for r in rates])  # no intervals (ol)
    assert (plain["q_total_p05"], plain["q_total_p95"]) == (90.0, 110.0)
    assert plain.get("q_total_std") is None


# -- through the service ----------------------------------------------------------------------
@contextmanager
def running(folder: Path) -> Iterator[tuple[Any, Any, dict[int, dict[str, Any]]]]:
    """A loopback service (mm with bayes) and a client; the prediction messages by time."""
    from replay.client import FieldClient
    from service.app import Service
    from service.testing import loopback_settings
    from service.transport import MemoryTransport

    settings = loopback_settings(folder, model={"name": "mm", "method": "bayes"})
    bus = MemoryTransport(settings.prefix)
    service = Service(settings, bus)
    messages: dict[int, dict[str, Any]] = {}

    def on_message(key: str, payload: bytes) -> None:
        data = json.loads(payload)
        messages[pd.Timestamp(data["time"]).value] = data

    service.start()
    unsubscribe = bus.subscribe(f"{settings.prefix}/{WELL}/prediction", on_message)
    try:
        with FieldClient(bus, settings.prefix) as client:
            client.wait_for_service(WELL)
            yield service, client, messages
    finally:
        unsubscribe()
        service.stop()


def send(client: Any, service: Any, rows: pd.DataFrame, messages: dict[int, Any]) -> None:
    """The rows' samples, each followed by its measurement (if any); wait for all, and for
    the last row's prediction message (published after its commit)."""
    from replay.client import sample_of
    from service.testing import wait_until
    from vfm_core.messages import Measurement

    for row in rows.itertuples(index=False):
        when = pd.Timestamp(row.time).to_pydatetime()
        client.send_sample(WELL, sample_of(when, [getattr(row, s) for s in SENSORS]))
        if row.source:
            client.send_measurement(
                WELL, str(row.source), Measurement(time=when, q_total=float(row.q_total))
            )
    engine = service.engine
    last = pd.Timestamp(rows["time"].iloc[-1]).value

    def done() -> bool:
        st = engine.wells.get(WELL)
        return st is not None and st.last_time_ns == last and not st.pending

    wait_until(done, 60, "every row to be handled")
    wait_until(lambda: last in messages, 30, "the last prediction message")


@pytest.mark.timeout(120)
def test_the_service_predicts_with_the_fallback_and_learns_nothing_wrong(
    field: Any, tmp_path: Path
) -> None:
    obs, bad, truth, fault = field
    t_all = ns(bad["time"])
    end = pd.Timestamp(fault["end"]).value
    cut = int(np.searchsorted(t_all, end, side="right"))  # the rows up to the fault's last
    with running(tmp_path) as (service, client, messages):
        send(client, service, bad.iloc[:cut], messages)
        st = service.engine.wells[WELL]
        (event,) = [e for e in st.sensor_faults.events if e.sensor == "p_up"]
        assert event.kind == "frozen" and event.end_ns is None
        view = http_get(service, f"/wells/{WELL}")
        assert [(f["sensor"], f["kind"]) for f in view["fallback"]] == [("p_up", "frozen")]

        # the samples from the fault's detection to its end, as stored and published
        inside = (t_all >= event.detected_ns) & (t_all <= end)
        times = t_all[inside]
        samples = {s.time_ns: s for s in service.store.history(WELL, 0, 2**62, 100_000)[0]}
        raw = bad[list(SENSORS)].to_numpy(float)[inside]
        clean = obs[inside]
        # nothing dropped: the raw (frozen) values are stored as they came
        assert [samples[int(t)].p_up for t in times] == raw[:, 1].tolist()
        # learn nothing wrong: the model did not change over the fault, every measurement
        # at its samples is held, and there are some
        during = st.learner.version
        assert {samples[int(t)].version for t in times} == {during}
        statuses = {m.time_ns: m.status for m in service.store.history(WELL, 0, 2**62, 100_000)[1]}
        held = [statuses[int(t)] for t in times if int(t) in statuses]
        assert len(held) > 20 and set(held) == {"held"}
        for t in times:
            fb = messages[int(t)]["fallback"]
            assert fb is not None and fb[0]["sensor"] == "p_up" and fb[0]["kind"] == "frozen"
        # the held MPFM rates witnessed the input (Learning.follow_rate): the stand-in moved
        # off the history's (kept with the detectors, so in the checkpoint)
        track = st.sensor_faults.tracks["p_up/frozen"]
        assert track[0] != 0.0 and track[2] > event.detected_ns

        # the same model without the fallback (the reading as it came, its own interval)
        # and at the true inputs (the best this model can do: the truth of the input's part)
        plain = [st.learner.predict(list(r)) for r in raw]
        at_truth = np.array(
            [st.learner.predict(list(r))["q_total"] for r in clean[list(SENSORS)].to_numpy(float)]
        )
        q_true = truth["q_true"].to_numpy(float)[inside]
        with_fb = np.array([[samples[int(t)].q_total, samples[int(t)].q_total_p05,
                             samples[int(t)].q_total_p95] for t in times])  # fmt: skip
        without = np.array([[p["q_total"], p["q_total_p05"], p["q_total_p95"]] for p in plain])
        added_with = np.mean(np.abs(with_fb[:, 0] - at_truth) / at_truth)
        added_without = np.mean(np.abs(without[:, 0] - at_truth) / at_truth)
        err_with = np.mean(np.abs(with_fb[:, 0] - q_true) / q_true)
        err_without = np.mean(np.abs(without[:, 0] - q_true) / q_true)
        numbers = (added_with, added_without, err_with, err_without)
        assert added_with < added_without, numbers  # the error the fault adds fell
        width_with = np.mean(with_fb[:, 2] - with_fb[:, 1])
        width_without = np.mean(without[:, 2] - without[:, 1])
        assert width_with > width_without
        # the interval is that of a well test's reading: held against the true rate and the
        # model's rate at the true inputs, the widened one covers them more often
        for target in (q_true, at_truth):
            cover_with = np.mean((with_fb[:, 1] <= target) & (target <= with_fb[:, 2]))
            cover_without = np.mean((without[:, 1] <= target) & (target <= without[:, 2]))
            assert cover_with > cover_without, (cover_with, cover_without, numbers)

        # the fault ends: the reading is used again, the message and the view say so
        after = bad.iloc[cut : cut + 60]
        send(client, service, after, messages)
        assert event.end_ns is not None
        later = ns(after["time"])
        later = later[later >= event.end_ns]
        assert len(later) > 30
        assert all(messages[int(t)]["fallback"] is None for t in later)
        assert http_get(service, f"/wells/{WELL}")["fallback"] is None
        measured = service.store.history(WELL, 0, 2**62, 100_000)[1]
        assert any(m.status == "learned" and m.time_ns > event.end_ns for m in measured)
        assert st.learner.version > during  # learning resumed: the model moves again
        # one more sample, without a measurement: its prediction is the model's at its reading
        probe = bad.iloc[[cut + 60]].assign(source="")
        send(client, service, probe, messages)
        t_probe = int(ns(probe["time"])[0])
        stored = {s.time_ns: s for s in service.store.history(WELL, 0, 2**62, 100_000)[0]}
        again = st.learner.predict(probe[list(SENSORS)].to_numpy(float)[0].tolist())
        assert stored[t_probe].q_total == pytest.approx(again["q_total"], rel=1e-9)
        assert stored[t_probe].q_total_p95 == pytest.approx(again["q_total_p95"], rel=1e-9)


@pytest.mark.timeout(120)
def test_the_service_takes_a_reading_out_of_its_span_and_stands_in_for_it(
    field: Any, tmp_path: Path
) -> None:
    """A p_down of -1 bar a and a choke of 1.5 (transmitters out of their span; refused as
    bad input before) are taken: stored raw, raised as ``out_of_range`` faults in ``GET
    /wells/{well}`` (sensor, start, end, evidence), predicted with a stand-in for that input
    (near the rate at the good samples around), and the measurements paired with them are
    held, not learned. A zero pressure (inside the span) is still refused."""
    from service.testing import wait_until
    from vfm_core.messages import measurement_key, sensors_key
    from vfm_core.timeutil import iso

    obs, _, _, _ = field
    with running(tmp_path) as (service, client, messages):
        send(client, service, obs.iloc[:80], messages)
        row = obs.iloc[80]
        t = pd.Timestamp(row["time"])
        prefix = service.settings.prefix
        sent = []
        for i, changes in enumerate(({"p_down": -1.0}, {"choke": 1.5}, {"p_down": 0.0}, {})):
            when = t + pd.Timedelta(minutes=i + 1)
            data = {"time": when.isoformat(), **{s: float(row[s]) for s in SENSORS}, **changes}
            client.put_raw(sensors_key(prefix, WELL), json.dumps(data))
            if changes != {"p_down": 0.0}:  # (a rate there would pair with a sample nearby)
                rate = {"time": when.isoformat(), "q_total": float(row["q_total"])}
                client.put_raw(measurement_key(prefix, WELL, "mpfm"), json.dumps(rate))
            sent.append(when.value)
        st = service.engine.wells[WELL]
        wait_until(lambda: st.last_time_ns == sent[-1] and not st.pending, 30, "the samples")
        wait_until(lambda: sent[-1] in messages, 30, "the last prediction")
        view = http_get(service, f"/wells/{WELL}")
        ranged = [f for f in view["sensor_faults"] if f["kind"] == "out_of_range"]
        assert [(f["sensor"], f["start"], f["end"]) for f in ranged] == [
            ("p_down", iso(sent[0]), iso(sent[1])),
            ("choke", iso(sent[1]), iso(sent[3])),  # the zero-pressure sample was refused
        ]
        assert "p_down read -1 bar, outside its physical span" in ranged[0]["evidence"]
        assert view["rejected"] == {"sensor fault at the sample": 2, "negative or zero pressure": 1}
        good = messages[sent[3]]["q_total"]
        for t_ns, sensor, raw in ((sent[0], "p_down", -1.0), (sent[1], "choke", 1.5)):
            (fb,) = messages[t_ns]["fallback"]
            assert (fb["sensor"], fb["kind"], fb["measured"]) == (sensor, "out_of_range", raw)
            assert messages[t_ns]["q_total"] == pytest.approx(good, rel=0.1)
        assert messages[sent[3]]["fallback"] is None
        samples, measured = service.store.history(WELL, 0, 2**62, 100_000)
        stored = {s.time_ns: s for s in samples}
        assert stored[sent[0]].p_down == -1.0 and stored[sent[1]].choke == 1.5  # raw values
        assert sent[2] not in stored
        status = {m.time_ns: m.status for m in measured}
        assert [status[t_ns] for t_ns in (*sent[:2], sent[3])] == ["held", "held", "learned"]
