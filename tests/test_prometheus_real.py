"""The real Prometheus against the real service, on loopback.

Debian's ``prometheus`` binary scrapes a running ``vfm serve`` (a subprocess, Zenoh on a
free loopback port, its store in a temporary folder) every second and evaluates the shipped
rules (``docker/alerts.yml``) every second. The field side is the replay tool's client over
Zenoh: two new wells, each made ready by one MPFM reading, then a sensor sample each every
0.2 s. The test reads Prometheus's HTTP API:

* a series per well (``vfm_well_predictions_total{well}`` and the other per-well families),
  and the service up;
* every rule of ``alerts.yml`` loaded and evaluated without error on the real series;
* every query of the Grafana dashboard accepted by Prometheus's parser;
* ``VfmWellStarved``: W02's samples stop, W01's go on; the alert fires for W02 alone, and
  resolves once W02's samples come back.

The starvation alert is the shipped rule with a test-sized window: its ``[15m]`` and
``offset 15m`` become 6 s and its ``for: 1m`` 2 s, in a rules file written from the shipped
one (every other rule as shipped; every group evaluated every second). Without the ``prometheus`` binary the test skips, unless
``VFM_REQUIRE_PROMETHEUS`` is set (CI sets it), and then it fails.
"""

from __future__ import annotations

import json
import os
import shutil
import socket
import subprocess
import threading
import time
from collections.abc import Callable, Iterator
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

import httpx
import pytest
import yaml

from replay.client import FieldClient, ZenohBus, sample_of
from service.testing import ServeProcess, wait_until
from vfm_core.messages import Measurement

pytestmark = pytest.mark.timeout(240)

ROOT = Path(__file__).resolve().parents[1]
ALERTS = ROOT / "docker" / "alerts.yml"
DASHBOARD = ROOT / "docker" / "grafana-dashboard.json"
TOKEN = "prometheus-real-test-token-0123"
T0 = datetime(2021, 1, 1, tzinfo=UTC)
INPUTS = {
    "W01": (0.4, 120.0, 30.0, 60.0, 0.1, 0.6),  # fraction, bar a, bar a, degC, -, -
    "W02": (0.5, 110.0, 35.0, 65.0, 0.2, 0.5),
}
#: the test's window of VfmWellStarved (the shipped one: 15 min), s
STARVED_S = 6
#: each well's predictions per second over the last 5 s, where positive
_RATE = "rate(vfm_well_predictions_total[5s]) > 0"


def prometheus_binary() -> str:
    found = shutil.which("prometheus")
    if found is None:
        why = (
            "the prometheus binary is not installed (Debian: apt-get install prometheus); "
            "VFM_REQUIRE_PROMETHEUS makes this a failure"
        )
        if os.environ.get("VFM_REQUIRE_PROMETHEUS"):
            pytest.fail(why.split(";")[0] + ", and VFM_REQUIRE_PROMETHEUS is set.")
        pytest.skip(why)
    return found


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def write_test_rules(path: Path) -> None:
    """The shipped rules with VfmWellStarved's window and ``for`` made test-sized, and
    every group evaluated every second."""
    doc = yaml.safe_load(ALERTS.read_text("utf-8"))
    starved = [r for g in doc["groups"] for r in g["rules"] if r.get("alert") == "VfmWellStarved"]
    assert len(starved) == 1
    rule = starved[0]
    expr = (
        rule["expr"]
        .replace("[15m]", f"[{STARVED_S}s]")
        .replace("offset 15m", f"offset {STARVED_S}s")
    )
    assert expr != rule["expr"] and "15m" not in expr, "VfmWellStarved's window moved"
    rule["expr"], rule["for"] = expr, "2s"
    for group in doc["groups"]:  # the recording group too (1 min as shipped)
        group["interval"] = "1s"
    path.write_text(yaml.safe_dump(doc, sort_keys=False), "utf-8")


class Feeder:
    """Sends each well's next sensor sample every ``period_s`` (data times a minute apart)
    while the well is in ``wells``."""

    def __init__(self, client: FieldClient, period_s: float = 0.2) -> None:
        self.client = client
        self.period_s = period_s
        self.wells = set(INPUTS)
        self.sent: dict[str, int] = dict.fromkeys(INPUTS, 0)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="feeder", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(self.period_s):
            for well in sorted(self.wells):
                self.sent[well] += 1
                when = T0 + timedelta(minutes=self.sent[well])
                self.client.send_sample(well, sample_of(when, INPUTS[well]))

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(10)


@pytest.fixture
def service(tmp_path: Path) -> Iterator[ServeProcess]:
    prometheus_binary()  # skip (or fail) before starting anything
    cfg = tmp_path / "vfm.toml"
    cfg.write_text(
        f"""
[zenoh]
listen = ["tcp/127.0.0.1:0"]
[http]
port = 0
token = "{TOKEN}"
[store]
path = "{tmp_path / "store.sqlite"}"
synchronous = "normal"
"""
    )
    proc = ServeProcess(cfg, tmp_path / "serve.log")
    proc.start()
    try:
        yield proc
    finally:
        proc.stop()


@pytest.fixture
def prometheus(tmp_path: Path, service: ServeProcess) -> Iterator[str]:
    binary = prometheus_binary()
    rules = tmp_path / "alerts.yml"
    write_test_rules(rules)
    target = service.http_url.removeprefix("http://").rstrip("/")
    config = tmp_path / "prometheus.yml"
    config.write_text(
        yaml.safe_dump(
            {
                "global": {"scrape_interval": "1s", "evaluation_interval": "1s"},
                "rule_files": [str(rules)],
                "scrape_configs": [
                    {
                        "job_name": "vfm",
                        "metrics_path": "/metrics",
                        "static_configs": [{"targets": [target]}],
                    }
                ],
            }
        ),
        "utf-8",
    )
    port = free_port()
    log = (tmp_path / "prometheus.log").open("w", encoding="utf-8")
    proc = subprocess.Popen(
        [
            binary,
            f"--config.file={config}",
            f"--storage.tsdb.path={tmp_path / 'tsdb'}",
            f"--web.listen-address=127.0.0.1:{port}",
            "--log.level=warn",
        ],
        stdout=log,
        stderr=subprocess.STDOUT,
    )
    url = f"http://127.0.0.1:{port}"
    try:

        def ready() -> bool:
            if proc.poll() is not None:
                raise AssertionError(
                    "prometheus ended: " + (tmp_path / "prometheus.log").read_text()[-2000:]
                )
            try:
                return httpx.get(f"{url}/-/ready", timeout=1).status_code == 200
            except httpx.HTTPError:
                return False

        wait_until(ready, 30, "Prometheus to be ready")
        yield url
    finally:
        proc.terminate()
        try:
            proc.wait(15)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5)
        log.close()


def _api(url: str, path: str, **params: str) -> Any:
    r = httpx.get(f"{url}/api/v1/{path}", params=params, timeout=10)
    body = r.json()
    assert body["status"] == "success", (path, params, body)
    return body["data"]


def _query(url: str, expr: str) -> list[dict[str, Any]]:
    data = _api(url, "query", query=expr)
    assert data["resultType"] == "vector", data
    return list(data["result"])


def _firing(url: str, alert: str) -> set[str]:
    """The wells for which ``alert`` fires now."""
    return {
        a["labels"].get("well", "")
        for a in _api(url, "alerts")["alerts"]
        if a["labels"]["alertname"] == alert and a["state"] == "firing"
    }


def _eventually(check: Callable[[], bool], timeout: float, what: str) -> None:
    wait_until(check, timeout, what, interval=0.25)


def test_prometheus_scrapes_the_service_and_alerts_on_a_starved_well(
    service: ServeProcess, prometheus: str
) -> None:
    url = prometheus
    started = time.monotonic()
    bus = ZenohBus.connect([service.zenoh])
    feeder: Feeder | None = None
    try:
        with FieldClient(bus, "vfm") as client:
            # two new wells, each made ready by an MPFM reading at its first sample
            for well, inputs in INPUTS.items():
                client.send_sample(well, sample_of(T0, inputs))
                client.send_measurement(well, "mpfm", Measurement(time=T0, q_total=1000.0))
            feeder = Feeder(client)
            feeder.start()

            # a series per well, from the scrapes of the running service
            def both_wells() -> bool:
                got = _query(url, "vfm_well_predictions_total > 0")
                return {s["metric"].get("well") for s in got} == set(INPUTS)

            _eventually(both_wells, 60, "a predictions series per well in Prometheus")
            for family in ("vfm_well_samples_total", "vfm_well_model_version"):
                got = {s["metric"]["well"] for s in _query(url, family)}
                assert got == set(INPUTS), (family, got)
            up = _query(url, 'up{job="vfm"}')
            assert [s["value"][1] for s in up] == ["1"]

            # every shipped rule loaded and evaluated on the real series without an error
            def rules_evaluated() -> bool:
                rules = [r for g in _api(url, "rules")["groups"] for r in g["rules"]]
                return len(rules) == _count_rules() and all(
                    r["health"] == "ok" and r.get("lastEvaluation", "").startswith("20")
                    for r in rules
                )

            _eventually(rules_evaluated, 20, "every rule evaluated without an error")

            # every dashboard query parses and runs on the real Prometheus
            dashboard = json.loads(DASHBOARD.read_text("utf-8"))
            for panel in dashboard["panels"]:
                for target in panel["targets"]:
                    _api(url, "query", query=target["expr"])  # status success
            _eventually(
                lambda: {s["metric"]["well"] for s in _query(url, _RATE)} == set(INPUTS),
                20,
                "a positive prediction rate per well",
            )

            assert _firing(url, "VfmWellStarved") == set()
            # W02 starves; W01 goes on
            feeder.wells.discard("W02")
            stopped = time.monotonic()
            _eventually(
                lambda: "W02" in _firing(url, "VfmWellStarved"),
                STARVED_S + 25,
                "VfmWellStarved to fire for W02",
            )
            fired_after = time.monotonic() - stopped
            assert _firing(url, "VfmWellStarved") == {"W02"}
            assert fired_after >= STARVED_S  # not before its window had passed
            alert = next(
                a
                for a in _api(url, "alerts")["alerts"]
                if a["labels"]["alertname"] == "VfmWellStarved"
            )
            assert alert["labels"]["severity"] == "critical"
            assert alert["annotations"]["runbook"].startswith("Look at GET /wells/W02 ")
            # W02's samples come back: resolved
            feeder.wells.add("W02")
            _eventually(
                lambda: _firing(url, "VfmWellStarved") == set(),
                20,
                "VfmWellStarved to resolve once W02 predicts again",
            )
            predictions = {
                s["metric"]["well"]: float(s["value"][1])
                for s in _query(url, "vfm_well_predictions_total")
            }
            assert predictions["W01"] > predictions["W02"] > 0
    finally:
        if feeder is not None:
            feeder.stop()
        bus.close()
    print(f"prometheus test: {time.monotonic() - started:.1f} s after both started")


def _count_rules() -> int:
    doc = yaml.safe_load(ALERTS.read_text("utf-8"))
    return sum(len(g["rules"]) for g in doc["groups"])
