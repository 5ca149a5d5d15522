"""The HTTP layer alone, against a stand-in engine injected through its dependencies.

``create_app`` takes any service that offers settings, counters, engine, store and
health; the routers get the engine through ``get_engine``, which a test overrides. Each
domain error the engine raises comes back with the status of the one table and the body
``{"detail": ..., "reason": ...}``.
"""

from __future__ import annotations

import asyncio
from concurrent.futures import Future
from pathlib import Path
from typing import Any

import httpx
import pytest

from service.engine import Engine, WellTestResult
from service.errors import (
    Busy,
    Conflict,
    Duplicate,
    InvalidRequest,
    NotAllowed,
    ServiceError,
    Starting,
    Stopping,
    UnknownWell,
)
from service.http import create_app
from service.http.deps import get_engine
from service.inputs import Counters
from service.store import Store
from service.testing import loopback_settings

pytestmark = pytest.mark.timeout(60)

TOKEN = "http-layer-test-token-0123456789"
AUTH = {"Authorization": f"Bearer {TOKEN}"}


class StubService:
    """A service that has not started: settings and counters, no engine or store yet."""

    engine: Engine | None = None
    store: Store | None = None

    def __init__(self, folder: Path, token: str | None = TOKEN) -> None:
        self.settings = loopback_settings(folder, http={"token": token})
        self.counters = Counters()

    def health(self) -> dict[str, Any]:  # not called here
        raise NotImplementedError


class FakeEngine:
    """Answers like the engine; ``error`` is raised by the calls that change something."""

    def __init__(self, error: ServiceError | None = None) -> None:
        self.error = error

    def well_summaries(self) -> list[dict[str, Any]]:
        return [
            {
                "well": "W01",
                "model": "mm",
                "method": "ol",
                "ready": True,
                "version": 3,
                "n_updates": 3,
                "last_update": None,
            }
        ]

    def change_model(self, well: str, *args: Any, **kwargs: Any) -> dict[str, Any]:
        assert self.error is not None
        raise self.error

    def submit_well_test(self, well: str, measurement: Any) -> Future[WellTestResult]:
        if self.error is not None:
            raise self.error
        fut: Future[WellTestResult] = Future()
        fut.set_result(
            WellTestResult(well, "2020-01-01T00:00:00Z", measurement.q_total, "pending", "Stored.")
        )
        return fut


def _call(
    service: StubService, engine: FakeEngine | None, method: str, path: str, **kw: Any
) -> httpx.Response:
    app = create_app(service)
    if engine is not None:
        app.dependency_overrides[get_engine] = lambda: engine

    async def go() -> httpx.Response:
        transport = httpx.ASGITransport(app=app)
        async with httpx.AsyncClient(transport=transport, base_url="http://test") as client:
            return await client.request(method, path, **kw)

    return asyncio.run(go())


@pytest.mark.parametrize(
    ("error", "status"),
    [
        (InvalidRequest("Unknown effect 'x'.", None), 422),
        (UnknownWell("The well 'W09' is not known.", None), 404),
        (Conflict("A model change of W01 is already running.", None), 409),
        (NotAllowed("The module is not allowed.", None), 403),
        (Busy("The service is busy.", None), 503),
        (Starting("The service is starting.", None), 503),
        (Stopping("The service is stopping.", None), 503),
    ],
)
def test_domain_errors_map_to_statuses(tmp_path: Path, error: ServiceError, status: int) -> None:
    r = _call(
        StubService(tmp_path), FakeEngine(error), "PUT", "/wells/W01/model", json={}, headers=AUTH
    )
    assert r.status_code == status
    assert r.json() == {"detail": error.message, "reason": None}


def test_refusals_of_inputs_carry_their_reason_and_are_counted(tmp_path: Path) -> None:
    service = StubService(tmp_path)
    body = {"time": "2020-01-01T00:00:00Z", "q_total": 5.0}
    error = Duplicate("The well_test measurement of W01 arrived before.", "duplicate")
    r = _call(service, FakeEngine(error), "POST", "/wells/W01/well-tests", json=body, headers=AUTH)
    assert r.status_code == 409 and r.json() == {"detail": error.message, "reason": "duplicate"}
    assert service.counters.snapshot()["rejected"] == {"duplicate": 1}
    ok = _call(service, FakeEngine(), "POST", "/wells/W01/well-tests", json=body, headers=AUTH)
    assert ok.status_code == 202 and ok.json()["status"] == "pending"


def test_the_token_comes_first(tmp_path: Path) -> None:
    engine = FakeEngine(Busy("never reached"))
    missing = _call(StubService(tmp_path), engine, "PUT", "/wells/W01/model", json={})
    assert missing.status_code == 401 and missing.headers["www-authenticate"] == "Bearer"
    assert missing.json()["reason"] is None
    off = _call(
        StubService(tmp_path, token=None), engine, "PUT", "/wells/W01/model", json={}, headers=AUTH
    )
    assert off.status_code == 403 and "VFM_HTTP__TOKEN" in off.json()["detail"]


def test_reads_before_the_service_started(tmp_path: Path) -> None:
    service = StubService(tmp_path)
    assert _call(service, None, "GET", "/wells").json() == []
    assert _call(service, None, "GET", "/wells/W01").status_code == 404
    assert _call(service, None, "GET", "/wells/W01/history").status_code == 404
    started = _call(service, None, "PUT", "/wells/W01/model", json={}, headers=AUTH)
    assert started.status_code == 503 and "starting" in started.json()["detail"]
    assert _call(service, FakeEngine(), "GET", "/wells").json()[0]["version"] == 3
