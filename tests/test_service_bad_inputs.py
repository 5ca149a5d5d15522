"""Bad input over Zenoh, in memory and over HTTP: never a crash, never a corrupted model,
each counted by reason.

Also the bearer-token rules of the mutating endpoint.
"""

from __future__ import annotations

import asyncio
import json
import math
from collections import Counter
from collections.abc import Iterator
from datetime import UTC, datetime, timedelta
from typing import Any

import httpx
import pytest

from replay.client import FieldClient, ZenohBus
from service.app import Service, running
from service.http import create_app
from service.testing import loopback_settings
from service.transport import MemoryTransport
from vfm_core.observations import validate_frame
from vfm_core.simulate import simulate_field

pytestmark = pytest.mark.timeout(180)

TOKEN = "bad-input-test-token-0123456789"
AUTH = {"Authorization": f"Bearer {TOKEN}"}


def _sample(t: datetime, **changes: Any) -> dict[str, Any]:
    data: dict[str, Any] = {
        "time": t.isoformat(),
        "choke": 0.4,
        "p_up": 120.0,
        "p_down": 30.0,
        "t_up": 60.0,
        "eta_gas": 0.1,
        "eta_oil": 0.6,
    }
    data.update(changes)
    return {k: v for k, v in data.items() if v is not ...}


class Env:
    def __init__(self, http: httpx.Client, client: FieldClient, level: float) -> None:
        self.http = http
        self.client = client
        #: the well's typical measured rate, Sm3/h: good measurements lie near it (a rate
        #: far from the well's recent ones is refused as implausible)
        self.q = level

    def put(self, key: str, payload: bytes | str | dict[str, Any]) -> None:
        self.client.put_raw(key, json.dumps(payload) if isinstance(payload, dict) else payload)

    def rejected(self) -> Counter[str]:
        return Counter(self.http.get("/health").json()["rejected"])


@pytest.fixture(scope="module", params=["memory", "zenoh"])
def env(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Env]:
    """The service with bad inputs sent in memory (the engine's receiving path without a
    network) and over Zenoh: the same checks must hold on both."""
    folder = tmp_path_factory.mktemp(f"bad-{request.param}")
    frame = validate_frame(simulate_field(wells=1, years=1, seed=0).observations).frame
    data = folder / "field.parquet"
    frame.to_parquet(data)
    settings = loopback_settings(
        folder,
        model={"name": "mm", "method": "ol", "history": str(data)},
        http={"token": TOKEN},
        inputs={"unknown_wells": "reject", "pending_timeout_s": 1.0},
    )
    memory = MemoryTransport(settings.prefix) if request.param == "memory" else None
    with running(settings, memory) as svc:
        bus = memory or ZenohBus.connect(svc.locators, block_wait_before_close_ms=60_000)
        try:
            with (
                httpx.Client(base_url=svc.http_url, timeout=30) as http,
                FieldClient(bus, settings.prefix, match_timeout=10.0) as client,
            ):
                client.wait_for_service("W01")  # and let the service see our subscriber
                yield Env(http, client, float(frame["q_total"].median()))
        finally:
            if memory is None:
                bus.close()  # type: ignore[attr-defined]


def _wait_for_prediction(env: Env, t: datetime) -> float:
    return env.client.wait_for_prediction("W01", t, timeout=20.0)


def test_bad_zenoh_inputs_are_counted_by_reason_and_harmless(env: Env) -> None:
    before_state = env.http.get("/wells/W01").json()
    before = env.rejected()
    t0 = datetime(2017, 6, 1, tzinfo=UTC)
    good = _sample(t0)
    env.put("vfm/W01/sensors", good)
    _wait_for_prediction(env, t0)
    earlier = t0 - timedelta(hours=1)
    future = datetime.now(UTC) + timedelta(days=3)
    corpus: list[tuple[str, bytes | str | dict[str, Any], str]] = [
        ("vfm/W01/sensors", b"{not json", "malformed JSON"),
        ("vfm/W01/sensors", b"[1, 2, 3]", "not a JSON object"),
        ("vfm/W01/sensors", _sample(t0 + timedelta(minutes=1), p_up=...), "missing field"),
        ("vfm/W01/sensors", _sample(t0 + timedelta(minutes=1), choke="half"), "wrong type"),
        (
            "vfm/W01/sensors",
            json.dumps(_sample(t0 + timedelta(minutes=1), p_up=float("nan"))),
            "not finite",
        ),
        (
            "vfm/W01/sensors",
            json.dumps(_sample(t0 + timedelta(minutes=1), t_up=float("inf"))),
            "not finite",
        ),
        # (an input outside its physical span, a negative pressure, a choke or a fraction
        # outside 0..1, is an out_of_range instrument fault, not refused: test_sensor_fallback)
        (
            "vfm/W01/sensors",
            _sample(t0 + timedelta(minutes=1), p_up=0.0),
            "negative or zero pressure",
        ),
        ("vfm/W01/sensors", _sample(t0 + timedelta(minutes=1), p_down=130.0), "p_down >= p_up"),
        (
            "vfm/W01/sensors",
            _sample(t0 + timedelta(minutes=1), eta_gas=0.5, eta_oil=0.7),
            "fractions sum above 1",
        ),
        ("vfm/W01/sensors", _sample(future), "time in the future"),
        ("vfm/W01/sensors", _sample(earlier), "time going backwards"),
        ("vfm/W01/sensors", good, "duplicate"),
        ("vfm/W01/measurements/mpfm", {"time": t0.isoformat(), "q_total": -5.0}, "negative rate"),
        (
            "vfm/W01/measurements/mpfm",
            {"time": (t0 - timedelta(days=30)).isoformat(), "q_total": env.q},
            "no sensor sample within tolerance",
        ),
        (
            "vfm/W01/measurements/guess",
            {"time": t0.isoformat(), "q_total": env.q},
            "unknown source",
        ),
        ("vfm/W01/sensors/extra", good, "unparseable key"),
        ("vfm/W01", good, "unparseable key"),
        ("vfm/NOPE/sensors", _sample(t0), "unknown well"),
        (
            "vfm/W01/measurements/mpfm",
            {"time": future.isoformat(), "q_total": env.q},
            "time in the future",
        ),
    ]
    for key, payload, _ in corpus:
        env.put(key, payload)
    # a valid measurement, then the same again: the second is a duplicate
    env.put("vfm/W01/measurements/mpfm", {"time": t0.isoformat(), "q_total": env.q})
    env.put("vfm/W01/measurements/mpfm", {"time": t0.isoformat(), "q_total": env.q})
    # a sentinel: once it is answered, everything before it was handled
    t1 = t0 + timedelta(minutes=10)
    env.put("vfm/W01/sensors", _sample(t1))
    _wait_for_prediction(env, t1)
    expected = Counter(reason for _, _, reason in corpus) + Counter({"duplicate": 1})
    got = env.rejected() - before
    assert got == expected
    # nothing bad reached the model: exactly one update (the valid measurement)
    after_state = env.http.get("/wells/W01").json()
    assert after_state["version"] == before_state["version"] + 1
    assert all(math.isfinite(p["value"]) for p in after_state["parameters"].values())
    health = env.http.get("/health").json()
    assert health["status"] == "ok" and health["events"].get("internal errors", 0) == 0


def test_bad_http_inputs_are_counted_by_reason(env: Env) -> None:
    before = env.rejected()
    t0 = datetime(2017, 7, 1, tzinfo=UTC)
    env.put("vfm/W01/sensors", _sample(t0))
    _wait_for_prediction(env, t0)
    post = "/wells/W01/well-tests"
    cases: list[tuple[str, Any, int, str | None]] = [
        (post, b"{oops", 422, "malformed JSON"),
        (post, {"time": t0.isoformat()}, 422, "missing field"),
        (post, {"time": t0.isoformat(), "q_total": "lots"}, 422, "wrong type"),
        (post, {"time": "last tuesday", "q_total": env.q}, 422, "wrong type"),
        (post, {"time": t0.isoformat(), "q_total": -1.0}, 422, "negative rate"),
        (post, b'{"time": "2017-07-01T00:00:00Z", "q_total": NaN}', 422, "not finite"),
        (
            post,
            {"time": (datetime.now(UTC) + timedelta(days=2)).isoformat(), "q_total": env.q},
            422,
            "time in the future",
        ),
        (
            post,
            {"time": (t0 - timedelta(days=40)).isoformat(), "q_total": env.q},
            422,
            "no sensor sample within tolerance",
        ),
        (
            "/wells/NOPE/well-tests",
            {"time": t0.isoformat(), "q_total": env.q},
            404,
            "unknown well",
        ),
    ]
    for path, body, status, reason in cases:
        kwargs = {"content": body} if isinstance(body, bytes) else {"json": body}
        r = env.http.post(path, headers={**AUTH, "content-type": "application/json"}, **kwargs)
        assert r.status_code == status, (body, r.text)
        out = r.json()
        assert out["reason"] == reason and out["detail"].endswith("."), out
    ok = env.http.post(post, json={"time": t0.isoformat(), "q_total": env.q * 1.05}, headers=AUTH)
    assert ok.status_code == 200 and ok.json()["status"] == "learned", ok.text
    dup = env.http.post(post, json={"time": t0.isoformat(), "q_total": env.q * 1.05}, headers=AUTH)
    assert dup.status_code == 409 and dup.json()["reason"] == "duplicate"
    expected = Counter(reason for *_, reason in cases if reason) + Counter({"duplicate": 1})
    assert env.rejected() - before == expected
    # reads answer with sentences too
    r = env.http.get("/wells/W01/history", params={"start": "yesterday"})
    assert r.status_code == 422 and "ISO 8601" in r.json()["detail"]
    assert env.http.get("/wells/NOPE").status_code == 404


def test_token_rules(env: Env) -> None:
    t0 = datetime(2017, 8, 1, tzinfo=UTC)
    env.put("vfm/W01/sensors", _sample(t0))
    _wait_for_prediction(env, t0)
    body = {"time": t0.isoformat(), "q_total": env.q * 0.95}
    missing = env.http.post("/wells/W01/well-tests", json=body)
    assert missing.status_code == 401 and missing.headers["www-authenticate"] == "Bearer"
    wrong = env.http.post(
        "/wells/W01/well-tests", json=body, headers={"Authorization": "Bearer nope"}
    )
    assert wrong.status_code == 401 and "bearer token" in wrong.json()["detail"]
    right = env.http.post("/wells/W01/well-tests", json=body, headers=AUTH)
    assert right.status_code == 200, right.text
    result = right.json()
    assert result["stored"] and result["version_after"] == result["version_before"] + 1
    assert result["paired_sample_time"] == t0.isoformat().replace("+00:00", "Z")


def test_no_token_configured_refuses_with_how_to(tmp_path) -> None:
    """Without http.token the mutating endpoint is off (403), with a sentence saying how to set one."""
    service = Service(loopback_settings(tmp_path))  # not started: the token check comes first
    app = create_app(service)

    async def calls() -> tuple[httpx.Response, httpx.Response, httpx.Response]:
        transport = httpx.ASGITransport(app=app)
        async with httpx.AsyncClient(transport=transport, base_url="http://test") as client:
            post = await client.post(
                "/wells/W01/well-tests",
                headers=AUTH,
                json={"time": "2020-01-01T00:00:00Z", "q_total": 1.0},
            )
            return post, await client.get("/health"), await client.get("/openapi.json")

    r, health, docs = asyncio.run(calls())
    assert r.status_code == 403
    assert "VFM_HTTP__TOKEN" in r.json()["detail"] and "http.token" in r.json()["detail"]
    assert health.json()["status"] == "starting"
    paths = docs.json()["paths"]
    assert {
        "/health",
        "/wells",
        "/wells/{well}",
        "/wells/{well}/history",
        "/wells/{well}/well-tests",
    } <= set(paths)
