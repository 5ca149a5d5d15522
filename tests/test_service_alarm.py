"""The residual alarm in the service: GET /wells/{well}, /metrics, the store, the events, and
the same alarms as the offline detector over the same predictions.

The well runs ``mm`` with a retrain period longer than the data (``pbl:3650d``): fitted on
its first measurement, it predicts the same rate at the same inputs until the end, so the
residuals are the meter's own scatter (3 %) until the measured rate steps up by 12 % on
day 70 (a change the model does not follow).
"""

from __future__ import annotations

import asyncio
import logging
from datetime import datetime, timedelta
from pathlib import Path

import httpx
import numpy as np
import pandas as pd
import pytest
from alarm_support import INPUTS, T0, fixed_model_service, send_readings, wait_learned

from replay.client import FieldClient, sample_of
from service.app import Service
from service.config import load_settings
from service.http import create_app
from service.testing import wait_until
from vfm_core.errors import ConfigError
from vfm_core.residual_alarm import alarms_from_predictions
from vfm_core.timeutil import iso, to_ns

pytestmark = pytest.mark.timeout(180)

STEP_DAY = 70
DAYS = 90


def http_get(service: Service, path: str) -> httpx.Response:
    app = create_app(service)

    async def go() -> httpx.Response:
        transport = httpx.ASGITransport(app=app)
        async with httpx.AsyncClient(transport=transport, base_url="http://test") as client:
            return await client.get(path)

    return asyncio.run(go())


def send_field(client: FieldClient, seed: int) -> list[datetime]:
    """Two MPFM readings a day with 3 % noise around 1000 Sm3/h, +12 % from STEP_DAY."""
    return send_readings(client, lambda day: 1.12 if day >= STEP_DAY else 1.0, DAYS, seed)


def test_a_step_raises_the_residual_alarm_everywhere_it_is_shown(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.INFO, logger="vfm.service.engine")
    with fixed_model_service(tmp_path) as (service, client):
        assert service.engine is not None
        sub = service.engine.observer.subscribe("W01")
        times = send_field(client, seed=2)
        store = service.store
        assert store is not None
        wait_learned(service, len(times))
        view = http_get(service, "/wells/W01").json()
        alarm = view["residual_alarm"]
        assert alarm["enabled"] and alarm["active"]
        assert alarm["direction"] == "high" and alarm["source"] == "mpfm"
        assert alarm["statistic"] == pytest.approx(alarm["threshold"])  # capped while active
        since = pd.Timestamp(alarm["since"])
        step = pd.Timestamp(T0 + timedelta(days=STEP_DAY))
        assert step <= since <= step + pd.Timedelta(days=4), since
        (event,) = alarm["events"]
        assert event["start"] == alarm["since"] and event["end"] is None
        assert event["small"] is False and event["typical_error"] > 0.01, event
        assert event["statistic"] > event["threshold"]
        assert alarm["streams"]["mpfm"]["ready"] and alarm["streams"]["mpfm"]["periods"] >= 80
        # a 12 % step at 3 % meter noise is no small alarm: its size against the meter's
        # usual error before it (the mean of |N(0, 3 %)|, about 2.4 %)
        assert alarm["small"] is False and alarm["shift"] > 0.06, alarm
        assert 1.5 < alarm["typical_error_percent"] < 3.5, alarm
        assert alarm["streams"]["mpfm"]["small"] is False
        # the T^2 input test stays, under its old field and keys (inputs never moved here)
        assert {"enabled", "detected", "active", "events"} <= set(view["drift"])
        # /metrics: the gauge and the counter
        text = http_get(service, "/metrics").text
        assert 'vfm_well_residual_alarm_active{well="W01"} 1.0' in text
        assert 'vfm_well_residual_alarms_total{well="W01"} 1.0' in text
        assert 'vfm_well_residual_alarm_small{well="W01"} 0.0' in text
        # the store row, the live event, the log line
        with store.reader() as con:
            rows = con.execute(
                "SELECT time_ns, source, kind, direction FROM residual_alarms WHERE well = 'W01'"
            ).fetchall()
        assert rows == [(to_ns(since.to_pydatetime()), "mpfm", "start", "high")]
        events, _ = sub.take()
        (live,) = [e for e in events if e["type"] == "alarm"]
        assert (live["kind"], live["time"], live["direction"]) == ("start", alarm["since"], "high")
        assert any("Residual alarm on W01" in r.getMessage() for r in caplog.records)

        # the service's alarms are the offline detector's over the same predictions
        learned = store.history("W01", 0, 2**62, 10_000)[1]
        predictions = pd.DataFrame(
            {
                "time": pd.to_datetime([m.time_ns for m in learned], utc=True),
                "well": "W01",
                "source": [m.source for m in learned],
                "predicted": [m.predicted for m in learned],
                "measured": [m.q_total for m in learned],
            }
        )
        offline = alarms_from_predictions(predictions, flush=False)
        assert [(a["source"], iso(to_ns(a["start"].to_pydatetime()))) for a in offline] == [
            ("mpfm", alarm["since"])
        ]


def test_the_residual_alarm_can_be_switched_off(tmp_path: Path) -> None:
    with fixed_model_service(tmp_path, residual_alarm={"enabled": False}) as (service, client):
        client.send_sample("W01", sample_of(T0, INPUTS))
        engine = service.engine
        assert engine is not None
        wait_until(lambda: engine.has_well("W01"), 10, "W01 to be created")
        view = http_get(service, "/wells/W01").json()
        assert view["residual_alarm"] == {"enabled": False, "active": False, "note": "disabled"}
        assert (
            'vfm_well_residual_alarm_active{well="W01"}' not in http_get(service, "/metrics").text
        )


def test_settings_are_checked_with_a_sentence() -> None:
    settings = load_settings(residual_alarm={"arl0": 3000, "k": 0.25})
    assert (settings.residual_alarm.arl0, settings.residual_alarm.k) == (3000, 0.25)
    with pytest.raises(ConfigError, match=r"min_periods \(400\) must not exceed"):
        load_settings(residual_alarm={"min_periods": 400, "window": 100})
    with pytest.raises(ConfigError, match="arl0"):
        load_settings(residual_alarm={"arl0": 1})


def test_a_restart_resumes_the_residual_alarm(tmp_path: Path) -> None:
    """The detectors go into the well's checkpoint: after a clean stop and a start, the alarm
    is still active with its start, and the stream tests at once (no new self-starting
    period of ``min_periods``); the well's latest prediction is the one before the stop."""
    with fixed_model_service(tmp_path) as (service, client):
        times = send_field(client, seed=2)
        wait_learned(service, len(times))
        view = http_get(service, "/wells/W01").json()
    before = view["residual_alarm"]
    assert before["active"]
    with fixed_model_service(tmp_path) as (service, _):
        again = http_get(service, "/wells/W01").json()
    after = again["residual_alarm"]
    assert after["active"] and after["since"] == before["since"]
    # the latest prediction (the field view's interval width) is read back from the store,
    # not "-" until the next sample (walk56)
    assert view["latest_prediction"] is not None
    assert again["latest_prediction"] == view["latest_prediction"]
    assert after["direction"] == before["direction"]
    assert after["events"] == before["events"]
    mpfm = after["streams"]["mpfm"]
    assert mpfm["ready"] and mpfm["periods"] == before["streams"]["mpfm"]["periods"]


def test_a_model_change_ends_the_alarm_and_the_new_model_is_tested_afresh(
    tmp_path: Path,
) -> None:
    """An alarm active when the operator changes the model ends there ("ended by a model
    change": end and closed ``reset``, a store row, the gauge back to 0); the new model's
    residuals are a new stream, not judged against the old model's level: after 20 more
    days its MPFM stream has 19 closed periods and is not yet tested (``min_periods`` 30), and no
    alarm began after the change."""
    token = "alarm-change-token-0123456789"
    with fixed_model_service(tmp_path, http=True, token=token) as (service, client):
        times = send_field(client, seed=2)
        wait_learned(service, len(times))
        with httpx.Client(base_url=service.http_url, timeout=120) as http:
            assert http.get("/wells/W01").json()["residual_alarm"]["active"]
            changed = http.put(
                "/wells/W01/model",
                json={"method": "ol", "confirm_worse": True},
                headers={"Authorization": f"Bearer {token}"},
            )
            assert changed.status_code == 200, changed.text
            alarm = http.get("/wells/W01").json()["residual_alarm"]
            assert not alarm["active"] and alarm["streams"] == {}
            (event,) = alarm["events"]
            assert (event["end"], event["closed"]) == ("reset", "reset")
            assert 'vfm_well_residual_alarm_active{well="W01"} 0.0' in http.get("/metrics").text
            later = send_readings(
                client, lambda day: 1.12, 20, seed=3, start=T0 + timedelta(days=DAYS)
            )
            wait_learned(service, len(times) + len(later))
            after = http.get("/wells/W01").json()["residual_alarm"]
        store = service.store
        assert store is not None
        with store.reader() as con:
            kinds = con.execute(
                "SELECT source, kind FROM residual_alarms WHERE well = 'W01' ORDER BY time_ns"
            ).fetchall()
    assert kinds == [("mpfm", "start"), ("mpfm", "end")]
    # 19 closed periods (the 20th day is still open); the old stream had 89
    assert after["streams"]["mpfm"]["periods"] == 19 and not after["streams"]["mpfm"]["ready"]
    assert len(after["events"]) == 1 and not after["active"]


def test_a_lasting_alarm_closes_as_accepted_and_an_old_saved_detector_resumes() -> None:
    """The well's alarm with the default settings: MPFM readings 6 % below the model from day
    40, for good. The alarm's end comes 30 days after its start, as ``closed: accepted``.
    A state saved before s46 (no ``accept_periods``) resumes under the current settings
    instead of starting afresh."""
    from service.config import ResidualAlarmSettings
    from service.engine.residual_alarms import WellResidualAlarm

    rng = np.random.default_rng(9)
    alarm = WellResidualAlarm(ResidualAlarmSettings())
    transitions = []
    for day in range(120):
        t = to_ns(T0 + timedelta(days=day, hours=12))
        q = 1000.0 * (0.94 if day >= 40 else 1.0) * float(np.exp(0.02 * rng.standard_normal()))
        transitions += [
            (k, e["start"], dict(e)) for k, _, e in alarm.update("mpfm", q, 1000.0, None, t)
        ]
        if day == 60:
            saved = alarm.state()
    kinds = [(kind, event["direction"], event["closed"]) for kind, _, event in transitions]
    assert kinds == [("start", "low", None), ("end", "low", "accepted")]
    (event,) = alarm.events
    start = pd.Timestamp(event["start"])
    assert start - pd.Timestamp(T0 + timedelta(days=40)) <= pd.Timedelta(days=4)
    assert pd.Timestamp(event["end"]) - start == pd.Timedelta(days=30)
    assert alarm.view()["accept_periods"] == 30 and not alarm.view()["active"]
    # the state of day 60 as a service before s46 saved it
    del saved["detectors"]["mpfm"]["accept_periods"], saved["detectors"]["mpfm"]["post"]
    for event in saved["events"]:
        event.pop("closed", None)
    resumed = WellResidualAlarm(ResidualAlarmSettings())
    resumed.restore(saved)
    assert resumed.active and resumed.detectors["mpfm"].accept_periods == 30
    assert resumed.detectors["mpfm"].n_periods == 60
