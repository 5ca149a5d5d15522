"""Issue 41's fixes on the real service (in-memory transport, the HTTP app over ASGI).

* A body declared as anything but JSON is refused with 415 and a sentence, on every
  endpoint that takes a body, and counted as ``not declared JSON`` like any refused input
  (``GET /health``, ``vfm_inputs_rejected_total``); the token is checked first.
* One rule for wells over HTTP: a well is known exactly when ``GET /wells`` lists it. A
  well not listed gets 404 from every endpoint, in create mode too, and also while it is
  being created from its first Zenoh message; once listed, every endpoint takes it (a well
  test, and a model change that is then refused for another reason, not as unknown).
* The pending limit (``inputs.pending_max``): a measurement beyond it settles the oldest
  waiting one (event ``pending forced``), which is learned if a sample lies within the
  tolerance; nothing is refused for it, so no reason exists for it.
* The series the shipped alerts read (docker/alerts.yml): every refusal reason and trial
  outcome at 0 from the start, predictions per well, the MPFM against the latest well test.
"""

from __future__ import annotations

import asyncio
import json
from collections.abc import Iterator
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

import httpx
import pytest

from replay.client import FieldClient, sample_of
from service.app import Service
from service.errors import REASONS
from service.http import create_app
from service.testing import loopback_settings, wait_until
from service.transport import MemoryTransport
from vfm_core.messages import Measurement

pytestmark = pytest.mark.timeout(120)

TOKEN = "issue-41-test-token-0123456789"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
T0 = datetime(2020, 3, 1, 6, 0, tzinfo=UTC)
INPUTS = (0.4, 120.0, 30.0, 60.0, 0.1, 0.6)  # fraction, bar a, bar a, degC, -, -


class Rig:
    """A started service with its field client and an HTTP client over ASGI."""

    def __init__(self, folder: Path, **overrides: Any) -> None:
        settings = loopback_settings(folder, http={"token": TOKEN}, **overrides)
        self.bus = MemoryTransport(settings.prefix)
        self.service = Service(settings, self.bus)
        self.service.start()
        self.app = create_app(self.service)
        self.field = FieldClient(self.bus, settings.prefix)

    def request(self, method: str, path: str, **kwargs: Any) -> httpx.Response:
        async def go() -> httpx.Response:
            transport = httpx.ASGITransport(app=self.app)
            async with httpx.AsyncClient(transport=transport, base_url="http://t") as client:
                return await client.request(method, path, **kwargs)

        return asyncio.run(go())

    def rejected(self) -> dict[str, int]:
        return dict(self.service.counters.snapshot()["rejected"])

    def metric(self, line_start: str) -> float:
        text = self.request("GET", "/metrics").text
        found = [ln for ln in text.splitlines() if ln.startswith(line_start + " ")]
        assert len(found) == 1, line_start
        return float(found[0].rsplit(" ", 1)[1])

    def close(self) -> None:
        self.field.close()
        self.service.stop()


@pytest.fixture
def rig(tmp_path: Path) -> Iterator[Rig]:
    r = Rig(tmp_path)
    try:
        yield r
    finally:
        r.close()


def _new_well(rig: Rig, well: str, when: datetime = T0) -> None:
    """Create ``well`` from its first Zenoh sample (create mode, the default)."""
    rig.field.send_sample(well, sample_of(when, INPUTS))
    engine = rig.service.engine
    assert engine is not None
    wait_until(lambda: engine.has_well(well), 20, f"{well} created")


def test_a_body_not_declared_json_is_refused_on_every_endpoint(rig: Rig) -> None:
    _new_well(rig, "W01")
    body = json.dumps({"time": T0.isoformat(), "q_total": 100.0})
    before = rig.rejected()
    cases = [
        ("POST", "/wells/W01/well-tests", "text/plain"),
        ("POST", "/wells/W01/well-tests", "application/x-www-form-urlencoded"),
        ("POST", "/wells/W01/well-tests", "text/plain; charset=utf-8"),
        ("PUT", "/wells/W01/model", "text/plain"),
        ("POST", "/wells/W01/model/rollback", "application/xml"),
        ("POST", "/wells/W01/diagnosis", "multipart/form-data; boundary=x"),
    ]
    for method, path, content_type in cases:
        r = rig.request(method, path, content=body, headers={**AUTH, "content-type": content_type})
        assert r.status_code == 415, (method, path, content_type, r.text)
        out = r.json()
        assert out["reason"] == "not declared JSON"
        assert out["detail"].endswith(".") and "application/json" in out["detail"]
        assert content_type.split(";")[0] in out["detail"]
    after = rig.rejected()
    assert after.get("not declared JSON", 0) - before.get("not declared JSON", 0) == len(cases)
    health = rig.request("GET", "/health").json()
    assert health["rejected"]["not declared JSON"] == len(cases)
    assert rig.metric('vfm_inputs_rejected_total{reason="not declared JSON"}') == len(cases)
    assert "not declared JSON" in REASONS
    # the token comes first: without it, 401 whatever the body
    r = rig.request(
        "POST", "/wells/W01/well-tests", content=body, headers={"content-type": "text/plain"}
    )
    assert r.status_code == 401
    # JSON, with parameters or as a +json type, or with no Content-Type at all, is read
    for headers in (
        {"content-type": "application/json; charset=utf-8"},
        {"content-type": "Application/JSON"},
        {},
    ):
        t = T0 + timedelta(seconds=len(headers) + (10 if "charset" in str(headers) else 0))
        ok = rig.request(
            "POST",
            "/wells/W01/well-tests",
            content=json.dumps({"time": t.isoformat(), "q_total": 100.0}),
            headers={**AUTH, **headers},
        )
        assert ok.status_code in (200, 202), (headers, ok.text)
    # a body-less request is not refused for its Content-Type
    r = rig.request("DELETE", "/wells/NOPE", headers={**AUTH, "content-type": "text/plain"})
    assert r.status_code == 404


def _all_well_endpoints(rig: Rig, well: str) -> dict[str, int]:
    """The status of every endpoint about ``well`` (mutating ones with the token)."""
    test = {"time": (T0 + timedelta(minutes=5)).isoformat(), "q_total": 100.0}
    calls: list[tuple[str, str, dict[str, Any]]] = [
        ("GET", f"/wells/{well}", {}),
        ("GET", f"/wells/{well}/history", {}),
        ("GET", f"/wells/{well}/history.csv", {}),
        ("GET", f"/wells/{well}/parameters", {}),
        ("GET", f"/wells/{well}/model/versions", {}),
        ("POST", f"/wells/{well}/well-tests", {"json": test}),
        ("PUT", f"/wells/{well}/model", {"json": {}}),
        ("POST", f"/wells/{well}/model/rollback", {"json": {"version": 1}}),
        ("POST", f"/wells/{well}/diagnosis", {"json": {"candidates": ["bogus"]}}),
    ]
    out = {}
    for method, path, kwargs in calls:
        r = rig.request(method, path, headers=AUTH, **kwargs)
        out[f"{method} {path}"] = r.status_code
        if r.status_code == 404:
            assert "not" in r.json()["detail"] and r.json()["detail"].endswith(".")
    return out


@pytest.mark.parametrize("mode", ["create", "reject"])
def test_one_rule_for_wells_over_http(tmp_path: Path, mode: str) -> None:
    rig = Rig(tmp_path, inputs={"unknown_wells": mode})
    try:
        engine = rig.service.engine
        assert engine is not None
        before = rig.rejected().get("unknown well", 0)
        statuses = _all_well_endpoints(rig, "GHOST")
        assert set(statuses.values()) == {404}, statuses
        assert rig.rejected().get("unknown well", 0) - before == 1  # the well test's input
        assert rig.request("GET", "/wells").json() == []
        assert not engine.has_well("GHOST")  # nothing was created by HTTP
        if mode == "reject":
            return
        # a well admitted from Zenoh but not built yet: not listed, so 404 everywhere
        engine._registry.admit("NEWBIE")  # what the receiver does with its first message
        statuses = _all_well_endpoints(rig, "NEWBIE")
        assert set(statuses.values()) == {404}, statuses
        # its first sample is handled: listed, and every endpoint takes it
        _new_well(rig, "NEWBIE")
        assert [w["well"] for w in rig.request("GET", "/wells").json()] == ["NEWBIE"]
        statuses = _all_well_endpoints(rig, "NEWBIE")
        assert 404 not in statuses.values(), statuses
        assert statuses["POST /wells/NEWBIE/well-tests"] in (200, 202)
        assert statuses["PUT /wells/NEWBIE/model"] == 422  # too few measurements to fit
    finally:
        rig.close()


def test_the_pending_limit_settles_the_oldest_and_refuses_nothing(tmp_path: Path) -> None:
    rig = Rig(tmp_path, inputs={"pending_max": 2, "pending_timeout_s": 3600})
    try:
        _new_well(rig, "P1")
        engine = rig.service.engine
        assert engine is not None
        version = engine.wells["P1"].learner.version
        # three MPFM readings after the well's only sample: each waits for a later sample
        for k in (1, 2, 3):
            m = Measurement(time=T0 + timedelta(seconds=10 * k), q_total=100.0 + k)
            rig.field.send_measurement("P1", "mpfm", m)
        counters = rig.service.counters
        wait_until(
            lambda: counters.snapshot()["accepted"].get("measurements", 0) == 3, 20, "3 stored"
        )
        wait_until(lambda: engine.pending_measurements() == 2, 20, "two waiting")
        assert counters.snapshot()["events"].get("pending forced") == 1
        assert rig.rejected() == {}  # the limit refuses nothing
        # the oldest was settled with the sample 10 s before it: learned from. The counters
        # and the pending list move when the worker handles the reading; the store only
        # once its batch commits, after the learning step (the first one of a process takes
        # a second): wait for the commit, not for the counters
        first = (T0 + timedelta(seconds=10)).isoformat().replace("+00:00", "Z")

        def stored() -> dict[str, str]:
            history = rig.request("GET", "/wells/P1/history").json()
            return {m["time"]: m["status"] for m in history["measurements"]}

        wait_until(lambda: stored().get(first, "pending") != "pending", 20, "the oldest stored")
        status = stored()
        assert status.pop(first) == "learned", status
        assert set(status.values()) == {"pending"}, status
        assert engine.wells["P1"].learner.version == version + 1
        # no reason exists for a limit that refuses nothing
        assert not [r for r in REASONS if "pending" in r]
    finally:
        rig.close()


def test_the_metrics_the_alerts_read(rig: Rig) -> None:
    """The series docker/alerts.yml needs: every refusal reason and trial outcome from the
    start (at 0), predictions per well, and the MPFM against the latest well test."""
    for reason in REASONS:
        assert rig.metric(f'vfm_inputs_rejected_total{{reason="{reason}"}}') == 0.0
    for outcome in ("kept", "rolled_back", "superseded", "interrupted"):
        assert rig.metric(f'vfm_trials_total{{outcome="{outcome}"}}') == 0.0
    _new_well(rig, "M1")
    assert rig.metric('vfm_well_predictions_total{well="M1"}') == 0.0  # no model yet
    # an MPFM reading of 100 Sm3/h at the first sample makes the well ready
    rig.field.send_measurement("M1", "mpfm", Measurement(time=T0, q_total=100.0))
    for k in (1, 2, 3):
        rig.field.send_sample("M1", sample_of(T0 + timedelta(minutes=k), INPUTS))
    wait_until(
        lambda: rig.metric('vfm_well_predictions_total{well="M1"}') == 3.0, 20, "3 predictions"
    )
    assert "vfm_well_mpfm_alarm_active{" not in rig.request("GET", "/metrics").text
    # a well test of 150 Sm3/h an hour later: the MPFM reads a third below it
    test = {"time": (T0 + timedelta(hours=1)).isoformat(), "q_total": 150.0}
    r = rig.request("POST", "/wells/M1/well-tests", json=test, headers=AUTH)
    assert r.status_code == 202, r.text
    assert rig.metric('vfm_well_mpfm_alarm_active{well="M1"}') == 1.0
    diff = rig.metric('vfm_well_mpfm_difference_ratio{well="M1"}')
    assert diff == pytest.approx((100.0 - 150.0) / 150.0)
    # a later well test that agrees ends it
    test = {"time": (T0 + timedelta(hours=2)).isoformat(), "q_total": 104.0}
    assert rig.request("POST", "/wells/M1/well-tests", json=test, headers=AUTH).status_code == 202
    assert rig.metric('vfm_well_mpfm_alarm_active{well="M1"}') == 0.0
