"""The monitoring files of ``docker/`` against Prometheus's own tools and the service's metrics.

* ``promtool check config docker/prometheus.yml`` (which also checks the rule file it
  loads), ``promtool check rules docker/alerts.yml`` and ``promtool test rules`` on the
  alerts' unit tests (``docker/alerts_test.yml``, ``docker/alerts_baseline_test.yml``):
  Debian's ``prometheus`` package ships ``promtool``. Without it these tests skip, unless
  ``VFM_REQUIRE_PROMETHEUS`` is set (CI sets it), and then they fail.
* Every alert has a unit test where it fires and one where it stays silent, a severity, a
  summary and a runbook sentence, and a row in docs/guide/monitoring.md with its ``for``.
* Every metric named by an alert or by a query of the Grafana dashboard
  (``docker/grafana-dashboard.json``) is exported by the service: the names are read from
  the ``GET /metrics`` of a started service (every family is there, with no wells too), so
  a renamed metric fails here. Names with a colon must be recorded by a rule of
  ``alerts.yml``; ``up`` and ``ALERTS`` are Prometheus's own series.
"""

from __future__ import annotations

import asyncio
import json
import os
import re
import shutil
import subprocess
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest
import yaml
from prometheus_client.parser import text_string_to_metric_families

from service.app import Service
from service.http import create_app
from service.testing import loopback_settings
from service.transport import MemoryTransport

pytestmark = pytest.mark.timeout(120)

ROOT = Path(__file__).resolve().parents[1]
DOCKER = ROOT / "docker"
ALERTS = DOCKER / "alerts.yml"
UNIT_TESTS = (DOCKER / "alerts_test.yml", DOCKER / "alerts_baseline_test.yml")
DASHBOARD = DOCKER / "grafana-dashboard.json"
MONITORING_DOC = ROOT / "docs" / "guide" / "monitoring.md"

#: series Prometheus makes itself: the scrape's health and the alerts' state
PROMETHEUS_OWN = frozenset({"up", "ALERTS", "ALERTS_FOR_STATE"})

#: PromQL words that look like names: operators, modifiers and literals
_KEYWORDS = frozenset(
    "and or unless by without on ignoring group_left group_right offset bool inf nan "
    "atan2 start end".split()
)


def promtool() -> str:
    """The path of ``promtool``; skip (or fail with ``VFM_REQUIRE_PROMETHEUS``) without it."""
    found = shutil.which("promtool")
    if found is None:
        why = (
            "promtool is not installed (Debian: apt-get install prometheus); "
            "VFM_REQUIRE_PROMETHEUS makes this a failure"
        )
        if os.environ.get("VFM_REQUIRE_PROMETHEUS"):
            pytest.fail(why.split(";")[0] + ", and VFM_REQUIRE_PROMETHEUS is set.")
        pytest.skip(why)
    return found


def run_promtool(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([promtool(), *args], capture_output=True, text=True, timeout=90, cwd=ROOT)


def metric_names(expr: str) -> set[str]:
    """The metric names a PromQL expression reads (no functions, labels or keywords)."""
    text = re.sub(r'"(?:[^"\\]|\\.)*"|\'(?:[^\'\\]|\\.)*\'', '""', expr)  # strings
    text = re.sub(r"\{[^}]*\}", " ", text)  # label matchers
    text = re.sub(r"\[[^\]]*\]", " ", text)  # ranges and subqueries
    # label lists of by / without / on / ignoring / group_left / group_right
    text = re.sub(r"\b(by|without|on|ignoring|group_left|group_right)\s*\([^)]*\)", " ", text)
    names = set()
    for m in re.finditer(r"(?<![\w.])([a-zA-Z_:][a-zA-Z0-9_:]*)\s*(\()?", text):
        name, call = m.group(1), m.group(2)
        if call or name in _KEYWORDS:
            continue
        names.add(name)
    return names


def test_metric_names_reads_what_a_query_reads() -> None:
    expr = (
        'histogram_quantile(0.99, sum(rate(vfm_a_bucket{le!="x", y=~"z"}[5m])) by (le)) '
        "> on (job, instance) group_left () (0.8 * vfm_b) and vfm_c:avg1h offset 1d "
        "unless sum without (w) (increase(vfm_d_total[1h:5m]))"
    )
    assert metric_names(expr) == {"vfm_a_bucket", "vfm_b", "vfm_c:avg1h", "vfm_d_total"}


@pytest.fixture(scope="module")
def exported(tmp_path_factory: pytest.TempPathFactory) -> Iterator[set[str]]:
    """The sample names of a started service's GET /metrics (every family it exports)."""
    folder = tmp_path_factory.mktemp("metrics")
    settings = loopback_settings(folder)
    service = Service(settings, MemoryTransport(settings.prefix))
    service.start()
    try:

        async def get() -> httpx.Response:
            transport = httpx.ASGITransport(app=create_app(service))
            async with httpx.AsyncClient(transport=transport, base_url="http://t") as client:
                return await client.get("/metrics")

        response = asyncio.run(get())
    finally:
        service.stop()
    assert response.status_code == 200
    suffixes = {
        "counter": ("_total", "_created"),
        "gauge": ("",),
        "histogram": ("_bucket", "_count", "_sum", "_created"),
        "summary": ("", "_count", "_sum", "_created"),
    }
    names: set[str] = set()
    for family in text_string_to_metric_families(response.text):
        names.update(family.name + s for s in suffixes.get(family.type, ("",)))
    yield names


def test_the_service_exports_what_the_alerts_need(exported: set[str]) -> None:
    """Sanity of the fixture: the families an alert reads are there with no wells."""
    assert {
        "vfm_well_predictions_total",
        "vfm_well_rolling_mape_percent",
        "vfm_well_mpfm_alarm_active",
        "vfm_trials_total",
        "vfm_prediction_latency_seconds_bucket",
    } <= exported


def _rules() -> list[dict[str, Any]]:
    doc = yaml.safe_load(ALERTS.read_text("utf-8"))
    return [rule for group in doc["groups"] for rule in group["rules"]]


def _alerts() -> list[dict[str, Any]]:
    return [r for r in _rules() if "alert" in r]


def test_every_alert_reads_exported_metrics(exported: set[str]) -> None:
    recorded = {r["record"] for r in _rules() if "record" in r}
    for rule in _rules():
        for name in metric_names(rule["expr"]):
            ok = name in exported or name in recorded or name in PROMETHEUS_OWN
            assert ok, f"{rule.get('alert') or rule.get('record')} reads {name}, not exported"


def test_every_dashboard_query_reads_exported_metrics(exported: set[str]) -> None:
    dashboard = json.loads(DASHBOARD.read_text("utf-8"))
    exprs = dashboard_queries(dashboard)
    assert len(exprs) >= 10  # every panel's targets were found
    for panel, expr in exprs:
        names = metric_names(expr)
        assert names, f"panel {panel!r}: no metric in {expr!r}"
        for name in names:
            assert name in exported or name in PROMETHEUS_OWN, (
                f"panel {panel!r} queries {name}, which the service does not export"
            )


def dashboard_queries(dashboard: dict[str, Any]) -> list[tuple[str, str]]:
    """(panel title, PromQL) of every target, in rows too, and of the template variables."""
    out: list[tuple[str, str]] = []

    def panels(items: list[dict[str, Any]]) -> None:
        for panel in items:
            for target in panel.get("targets", []):
                if target.get("expr"):
                    out.append((panel.get("title", "?"), target["expr"]))
            panels(panel.get("panels", []))

    panels(dashboard.get("panels", []))
    for var in dashboard.get("templating", {}).get("list", []):
        query = var.get("query")
        if isinstance(query, dict):
            query = query.get("query")
        if var.get("type") == "query" and isinstance(query, str):
            out.append((f"variable {var.get('name')}", query))
    return out


def test_the_dashboard_uses_the_provisioned_data_source() -> None:
    source = yaml.safe_load((DOCKER / "grafana" / "datasource.yml").read_text("utf-8"))
    uid = source["datasources"][0]["uid"]
    dashboard = json.loads(DASHBOARD.read_text("utf-8"))
    ids = [p["id"] for p in dashboard["panels"]]
    assert len(ids) == len(set(ids))
    for panel in dashboard["panels"]:
        assert panel["datasource"]["uid"] == uid, panel["title"]
        for target in panel["targets"]:
            assert target["datasource"]["uid"] == uid, panel["title"]


def test_every_alert_has_labels_annotations_and_a_unit_test() -> None:
    fired: dict[str, int] = {}
    silent: dict[str, int] = {}
    for path in UNIT_TESTS:
        doc = yaml.safe_load(path.read_text("utf-8"))
        assert doc["rule_files"] == ["alerts.yml"]
        for case in doc["tests"]:
            for check in case.get("alert_rule_test", []):
                into = fired if check["exp_alerts"] else silent
                into[check["alertname"]] = into.get(check["alertname"], 0) + 1
    names = [a["alert"] for a in _alerts()]
    assert len(names) == len(set(names)) and len(names) >= 8
    for alert in _alerts():
        name = alert["alert"]
        assert alert["labels"]["severity"] in ("critical", "warning", "info"), name
        notes = alert["annotations"]
        for key in ("summary", "description", "runbook"):
            assert notes[key].endswith("."), (name, key)
        assert fired.get(name), f"no unit test where {name} fires"
        assert silent.get(name), f"no unit test where {name} stays silent"


def test_the_docs_list_every_alert_with_its_for() -> None:
    doc = MONITORING_DOC.read_text("utf-8")
    rows = {
        m.group(1): m.group(0)
        for m in re.finditer(r"^\| `(Vfm\w+)` \|.*$", doc, flags=re.MULTILINE)
    }
    for alert in _alerts():
        row = rows.get(alert["alert"])
        assert row is not None, f"{alert['alert']} is not in the alerts table of {MONITORING_DOC}"
        assert f"| {alert.get('for', '0m')} |" in row, (alert["alert"], alert.get("for"))
    assert set(rows) == {a["alert"] for a in _alerts()}  # no row for an alert that is gone


def test_promtool_checks_the_config_and_its_rules() -> None:
    config = run_promtool("check", "config", "docker/prometheus.yml")
    assert config.returncode == 0, config.stdout + config.stderr
    assert "alerts.yml" in config.stdout + config.stderr  # the rules were loaded and checked
    rules = run_promtool("check", "rules", "docker/alerts.yml")
    assert rules.returncode == 0, rules.stdout + rules.stderr
    n = len(_rules())
    assert f"SUCCESS: {n} rules found" in rules.stdout + rules.stderr


def test_promtool_unit_tests_of_the_alerts_pass() -> None:
    result = run_promtool("test", "rules", *(str(p.relative_to(ROOT)) for p in UNIT_TESTS))
    assert result.returncode == 0, result.stdout + result.stderr
    assert (result.stdout + result.stderr).count("SUCCESS") == len(UNIT_TESTS)


def test_promtool_unit_tests_can_fail(tmp_path: Path) -> None:
    """The unit tests check something: with the starved-well window widened to an hour,
    the well that stopped for 25 minutes no longer alerts, and promtool says so."""
    broken = ALERTS.read_text("utf-8").replace(
        "increase(vfm_well_predictions_total[15m])", "increase(vfm_well_predictions_total[1h])"
    )
    assert broken != ALERTS.read_text("utf-8")
    (tmp_path / "alerts.yml").write_text(broken, "utf-8")
    shutil.copy(UNIT_TESTS[0], tmp_path / "alerts_test.yml")
    result = run_promtool("test", "rules", str(tmp_path / "alerts_test.yml"))
    assert result.returncode != 0
    assert "VfmWellStarved" in result.stdout + result.stderr


def test_the_sensor_fault_alert_fires_on_the_faults_that_raise_an_alarm() -> None:
    """``VfmSensorFault`` fires on exactly the faults the service calls alarms (each fault's
    ``alarm`` in ``GET /wells/{well}``, the page's alarm line, a warning in the log):
    :data:`vfm_core.sensor_faults.ALARM_KINDS` and :data:`~vfm_core.sensor_faults.ALARM_FAULTS`."""
    from vfm_core.sensor_faults import ALARM_FAULTS, ALARM_KINDS, KINDS, SENSORS, raises_alarm

    (alert,) = [a for a in _alerts() if a["alert"] == "VfmSensorFault"]
    expr = alert["expr"]
    kinds = re.findall(r'\{kind=~"([^"]+)"\}', expr)
    assert len(kinds) == 1, expr
    assert set(kinds[0].split("|")) == set(ALARM_KINDS)
    pairs = set(re.findall(r'\{sensor="(\w+)", kind="(\w+)"\}', expr))
    assert pairs == set(ALARM_FAULTS), expr
    alarms = {(s, k) for s in SENSORS for k in KINDS if raises_alarm(s, k)}
    assert ("p_down", "offset") not in alarms and ("p_up", "spike") not in alarms
    assert ("choke", "offset") in alarms and ("t_up", "frozen") in alarms
