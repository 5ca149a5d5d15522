"""The workbench's HTTP side: the page and /docs from the package, /metrics, live events
(server-sent), the CSV export, and diagnosis jobs (start, progress, done, 409, 401, 404).

One service (``mm`` + ``ol``, fitted on the first months of a simulated well with an eroding
choke) runs on its in-memory transport; the rest of the well is replayed into it.
"""

from __future__ import annotations

import json
import re
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
import pandas as pd
import pytest
from prometheus_client.parser import text_string_to_metric_families

from replay.replayer import replay_frame
from service.app import running
from service.diagnosis import DiagnosisJobs
from service.engine.observe import Observer
from service.errors import InvalidRequest, NotAllowed
from service.http.diagnosis import request_base
from service.store import InsertMeasurement, InsertSample, MarkLearned, SampleRow
from service.testing import loopback_settings
from service.transport import MemoryTransport
from vfm_core.observations import validate_frame
from vfm_core.simulate import simulate_field
from vfm_core.timeutil import iso

pytestmark = pytest.mark.timeout(300)

SPLIT = "2016-04-01"
TOKEN = "workbench-test-token-0123456789"
AUTH = {"Authorization": f"Bearer {TOKEN}"}


@dataclass
class Live:
    http: httpx.Client
    bus: MemoryTransport
    frame: pd.DataFrame
    folder: Path


@pytest.fixture(scope="module")
def live(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Live]:
    folder = tmp_path_factory.mktemp("workbench")
    sim = simulate_field(wells=1, years=1.0, seed=4, hidden=["erosion:rate=0.4"])
    frame = validate_frame(sim.observations).frame
    data = folder / "field.parquet"
    frame.to_parquet(data)
    settings = loopback_settings(
        folder,
        model={"name": "mm", "method": "ol", "history": str(data), "history_until": SPLIT},
        http={"token": TOKEN},
    )
    bus = MemoryTransport(settings.prefix)
    with running(settings, bus) as svc, httpx.Client(base_url=svc.http_url, timeout=60) as http:
        yield Live(http, bus, frame, folder)


def _replay(live: Live, start: str, end: str | None = None) -> None:
    rows = live.frame
    if end is not None:
        rows = rows[rows["time"] < pd.Timestamp(end, tz="UTC")]
    replay_frame(rows, bus=live.bus, start=start, progress=False, idle_timeout=2.0)


def test_page_and_docs_come_from_the_package(live: Live) -> None:
    page = live.http.get("/")
    assert page.status_code == 200 and "vfm workbench" in page.text
    docs = live.http.get("/docs")
    assert docs.status_code == 200
    assert not re.search(r"https?://", docs.text), "the docs page must not load anything remote"
    assets = re.findall(r'(?:src|href)="(/static/[^"]+)"', docs.text + page.text)
    assert {"/static/vendor/swagger-ui-bundle.js", "/static/vendor/uPlot.iife.min.js"} <= set(
        assets
    )
    for asset in assets:
        r = live.http.get(asset)
        assert r.status_code == 200 and len(r.content) > 100, asset
    assert "SwaggerUIBundle" in live.http.get("/static/vendor/swagger-ui-bundle.js").text
    assert live.http.get("/static/vendor/uPlot.LICENSE").status_code == 200
    assert live.http.get("/static/vendor/swagger-ui-dist.LICENSE").status_code == 200
    assert live.http.get("/redoc").status_code == 404  # it would load from a CDN


def test_live_events_stream_what_is_stored(live: Live) -> None:
    events: list[tuple[str, dict[str, Any]]] = []
    connected = threading.Event()

    def listen() -> None:
        with live.http.stream("GET", "/events", params={"well": "W01"}, timeout=30) as r:
            assert r.headers["content-type"].startswith("text/event-stream")
            kind = None
            for line in r.iter_lines():
                connected.set()
                if line.startswith("event: "):
                    kind = line[7:]
                elif line.startswith("data: ") and kind is not None:
                    events.append((kind, json.loads(line[6:])))
                    if sum(k == "learned" for k, _ in events) >= 5:
                        return

    reader = threading.Thread(target=listen, daemon=True)
    reader.start()
    assert connected.wait(10)
    _replay(live, SPLIT, "2016-05-01")
    reader.join(30)
    kinds = {k for k, _ in events}
    assert {"prediction", "measurement", "learned"} <= kinds, kinds
    pred = next(e for k, e in events if k == "prediction")
    assert pred["well"] == "W01" and pred["q_total"] > 0 and pred["time"].startswith("2016-04")
    learned = next(e for k, e in events if k == "learned")
    assert learned["predicted"] > 0 and learned["q_total"] > 0
    assert live.http.get("/events", params={"well": "W99"}).status_code == 404


def test_a_slow_client_loses_the_oldest_events_not_the_worker() -> None:
    observer = Observer(window=10, client_capacity=3)
    sub = observer.subscribe("W01")
    sample = SampleRow(1, (0.5, 100.0, 30.0, 60.0, 0.9, 0.05), 10.0)
    for t in range(1, 6):
        observer.committed(
            [InsertSample("W01", t, sample.inputs, 0, 10.0, 1.0, 2.0, 7.0, 1, 1.0, 9.0, 11.0)]
        )
    got, dropped = sub.take()
    assert [e["time"] for e in got] == [iso(t) for t in (3, 4, 5)]  # the newest kept
    assert dropped == 2
    assert observer.dropped == 2
    # coverage: a measurement inside p05..p95 of the prediction at its sample, then one outside
    observer.committed(
        [
            InsertMeasurement("W01", 5, "mpfm", 10.5, 0, "zenoh"),
            MarkLearned("W01", "mpfm", 5, 1, SampleRow(5, sample.inputs, 10.0), 2),
            InsertMeasurement("W01", 6, "mpfm", 20.0, 0, "zenoh"),
            MarkLearned("W01", "mpfm", 6, 2, SampleRow(5, sample.inputs, 10.0), 3),
        ]
    )
    assert observer.coverage() == {"W01": (0.5, 2)}
    observer.unsubscribe(sub)
    assert observer.subscribers == 0


def test_metrics_parse_with_the_prometheus_parser(live: Live) -> None:
    _replay(live, "2016-05-01", "2016-07-01")
    live.http.post("/wells/W01/well-tests", json={"time": "bad"}, headers=AUTH)  # a refusal
    text = live.http.get("/metrics").text
    families = {f.name: f for f in text_string_to_metric_families(text)}
    value = {
        name: {tuple(sorted(s.labels.items())): s.value for s in families[name].samples}
        for name in families
    }
    mape = value["vfm_well_rolling_mape_percent"][(("well", "W01"),)]
    assert 0 < mape < 50
    assert value["vfm_inputs_accepted"][(("kind", "sensors"),)] > 100
    assert sum(value["vfm_inputs_rejected"].values()) >= 1
    versions = value["vfm_well_model_version"]
    assert next(iter(versions)) == (("method", "ol"), ("model", "mm"), ("well", "W01"))
    assert value["vfm_queue_depth"] and "vfm_well_drift_events" in value
    latency = families["vfm_prediction_latency_seconds"]
    assert latency.type == "histogram"
    count = next(s.value for s in latency.samples if s.name.endswith("_count"))
    assert count > 100
    # ol gives no interval: no coverage series rather than a made-up one
    assert value["vfm_well_interval_coverage_ratio"] == {}


def test_history_csv_for_the_page(live: Live) -> None:
    r = live.http.get("/wells/W01/history.csv", params={"start": SPLIT, "end": "2016-05-01"})
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/csv")
    assert 'filename="W01-history.csv"' in r.headers["content-disposition"]
    lines = r.text.splitlines()
    assert lines[0].startswith("#") and "predicted" in lines[1]
    assert len(lines) > 20


def test_diagnosis_job_lifecycle(live: Live) -> None:
    body = {"candidates": ["erosion"], "suggest": False}
    assert live.http.post("/wells/W01/diagnosis", json=body).status_code == 401
    unknown = live.http.post("/wells/W99/diagnosis", json=body, headers=AUTH)
    assert unknown.status_code == 404 and "W99" in unknown.json()["detail"]
    typo = live.http.post("/wells/W01/diagnosis", json={"candidates": ["erosoin"]}, headers=AUTH)
    assert typo.status_code == 422 and "erosoin" in typo.json()["detail"]
    bad_model = live.http.post("/wells/W01/diagnosis", json={"model": "nn"}, headers=AUTH)
    assert bad_model.status_code == 422 and "mm, hem or ham" in bad_model.json()["detail"]

    _replay(live, "2016-07-01")  # the whole year is stored
    started = live.http.post("/wells/W01/diagnosis", json=body, headers=AUTH)
    assert started.status_code == 202, started.text
    job = started.json()["job"]
    second = live.http.post("/wells/W01/diagnosis", json=body, headers=AUTH)
    assert second.status_code == 409 and job in second.json()["detail"]

    state, seen = _finished(live, job)
    assert state["state"] == "done", state
    assert any(0 < p < 1 for p in seen), seen  # progress was reported on the way
    assert seen == sorted(seen)
    diag = state["diagnosis"]
    assert {"verdict", "candidates", "baseline", "drivers"} <= set(diag)
    assert [c["spec"] for c in diag["candidates"]] == ["erosion"]
    assert diag["base_effects"] == [] and state["request"]["base_effects"] == []
    # one error: the replay starts where the service started (its history joined in front
    # of the store, the split at history_until), so its baseline is the error the service
    # recorded on the same measurements
    assert any("joined in front of the store" in n for n in diag["notes"]), diag["notes"]
    assert diag["live"]["n"] == diag["live"]["service_n"] > 20
    assert diag["live"]["mape"] == pytest.approx(diag["live"]["service_mape"], rel=0.02)
    report = live.http.get(state["report"])
    assert report.status_code == 200 and "<html" in report.text.lower()
    assert live.http.get("/diagnosis/nope").status_code == 404

    # the loop's next turn: add what it found, and the next diagnosis starts from the model
    # as it runs now (its effects), so it looks for what is still missing
    changed = live.http.put("/wells/W01/model", json={"effects": ["erosion"]}, headers=AUTH)
    assert changed.status_code == 200, changed.text
    assert live.http.get("/wells/W01").json()["effects"] == ["erosion"]
    bad = live.http.post("/wells/W01/diagnosis", json={"base_effects": ["erosoin"]}, headers=AUTH)
    assert bad.status_code == 422 and "erosoin" in bad.json()["detail"]
    again = live.http.post(
        "/wells/W01/diagnosis",
        json={"candidates": ["erosion", "slip"], "suggest": False},
        headers=AUTH,
    )
    assert again.status_code == 202  # once done, the next one may start
    state, _ = _finished(live, again.json()["job"])
    assert state["state"] == "done", state
    diag = state["diagnosis"]
    assert diag["base_effects"] == ["erosion"] and state["request"]["base_effects"] == ["erosion"]
    assert [c["spec"] for c in diag["candidates"]] == ["slip"]
    assert [s["effect"] for s in diag["skipped"]] == ["erosion"]
    assert "already in the model" in diag["skipped"][0]["reason"]
    assert "mm+erosion" in diag["drivers_on"]
    assert state["request"]["model"] == live.http.get("/wells/W01").json()["base_model"] == "mm"


def test_a_diagnosis_request_starts_from_the_model_the_well_runs() -> None:
    """Without a model or base effects a diagnosis takes the well's: its physics model with
    the effects it has; a model the diagnosis cannot take (nn, last, ...) gives bare mm; a
    base model other than the well's starts without effects; what a request gives wins."""
    ham = {"base_model": "ham", "effects": ["erosion", "slip"]}
    assert request_base(ham, None, None) == ("ham", ["erosion", "slip"], True)
    assert request_base(ham, "ham", None) == ("ham", ["erosion", "slip"], True)
    assert request_base(ham, "mm", None) == ("mm", [], True)
    assert request_base(ham, None, []) == ("ham", [], False)
    assert request_base(ham, "hem", ["valve"]) == ("hem", ["valve"], False)
    assert request_base({"base_model": "nn", "effects": []}, None, None) == ("mm", [], True)
    assert request_base({}, None, None) == ("mm", [], True)  # a well without a model yet


def _finished(live: Live, job: str) -> tuple[dict[str, Any], list[float]]:
    """The job's last state once done or failed (or after 4 minutes), and its progress."""
    seen: list[float] = []
    deadline = time.monotonic() + 240
    while time.monotonic() < deadline:
        state = live.http.get(f"/diagnosis/{job}").json()
        seen.append(state["progress"])
        if state["state"] in ("done", "failed"):
            break
        time.sleep(0.3)
    return state, seen


def test_a_wells_own_effect_module_is_no_reason_to_refuse_its_diagnosis(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """An effect class set by the configuration (``model.effects``) need not be in
    ``model.effect_modules``, which governs what HTTP may name. As the well's own base it is
    accepted; named in a request body, the same module is refused (403)."""
    monkeypatch.syspath_prepend(str(Path(__file__).resolve().parents[1] / "examples"))
    jobs = DiagnosisJobs(loopback_settings(tmp_path))
    own = ["my_effects:TemperatureScale"]
    assert jobs.check("mm", None, None, own, base_from_model=True) is None
    with pytest.raises(NotAllowed, match="base effect 'my_effects:TemperatureScale'"):
        jobs.check("mm", None, None, own)
    with pytest.raises(NotAllowed, match="candidate"):
        jobs.check("mm", own, None, own, base_from_model=True)
    with pytest.raises(InvalidRequest, match="erosoin"):
        jobs.check("mm", None, None, ["erosoin"], base_from_model=True)
