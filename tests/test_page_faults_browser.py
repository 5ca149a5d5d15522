"""Instrument faults on the workbench page, in a real browser (Playwright driving Debian's
chromium), against a service fed by a replay of a simulated field with injected faults.

Two wells (``mm`` + ``ol``, fitted on the first six weeks): ``W01``'s ``p_down`` freezes
from 2016-05-01 to the end (a fault still active), ``W02``'s ``t_up`` freezes for ten days
in May (a fault that ended). The detectors (``vfm_core.sensor_faults``) must find both
through the service; the page must then show them where a user looks: a purple band on
the well's charts over each fault's span (drawn on the canvas: its pixels are read back),
the fault's sensor, kind and evidence on hover and in the list line under the rate chart,
the band appearing live while the replay streams, and an alarm in the field view for the
active fault only.

Screenshots go to ``$VFM_SCREENSHOTS`` (default ``tests/artifacts/``, ignored by git).
Skipped, with the reason, when ``/usr/bin/chromium`` or the ``playwright`` package is
missing (CI sets ``VFM_REQUIRE_BROWSER=1``: there a missing browser fails). Never run
``playwright install``: it downloads a browser build of its own.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import httpx
import pandas as pd
import pytest
from browser_support import SHOTS, Page, browser_marks, open_page

from replay.replayer import replay_frame
from service.app import running
from service.testing import loopback_settings
from service.transport import MemoryTransport
from vfm_core.faults_sim import inject_fault
from vfm_core.observations import validate_frame
from vfm_core.simulate import simulate_field

pytestmark = browser_marks(240)

SPLIT = "2016-02-15"  # the model is fitted on the history before it; the rest is replayed
BEFORE = "2016-04-25"  # the first replay stops here, before any injected fault
TOKEN = "faults-browser-token-0123456789"
#: the band's colour (rgba(106,27,154,0.8), app.js MARK_COLORS.fault) over the white chart
PURPLE = (106 * 0.8 + 255 * 0.2, 27 * 0.8 + 255 * 0.2, 154 * 0.8 + 255 * 0.2)


@dataclass
class Served:
    http: httpx.Client
    url: str
    bus: MemoryTransport
    frame: pd.DataFrame
    truth: dict[str, dict[str, Any]]


@pytest.fixture(scope="module")
def served(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Served]:
    folder = tmp_path_factory.mktemp("page-faults")
    # seed 21: both wells have rows from January (a frozen run needs 50 samples of history)
    sim = simulate_field(wells=2, years=0.5, seed=21)
    frame = validate_frame(sim.observations).frame
    frame, w01 = inject_fault(frame, "W01", "p_down", "frozen", "2016-05-01")
    frame, w02 = inject_fault(frame, "W02", "t_up", "frozen", "2016-05-10", days=10)
    data = folder / "field.parquet"
    frame.to_parquet(data)
    settings = loopback_settings(
        folder,
        model={"name": "mm", "method": "ol", "history": str(data), "history_until": SPLIT},
        http={"token": TOKEN},
    )
    bus = MemoryTransport(settings.prefix)
    with running(settings, bus) as svc, httpx.Client(base_url=svc.http_url, timeout=60) as http:
        yield Served(http, svc.http_url, bus, frame, {"W01": w01, "W02": w02})


@pytest.fixture(scope="module")
def browser_page() -> Iterator[tuple[Page, list[str]]]:
    with open_page() as opened:
        yield opened


def _replay(served: Served, start: str, end: str | None = None) -> None:
    rows = served.frame
    if end is not None:
        rows = rows[rows["time"] < pd.Timestamp(end, tz="UTC")]
    replay_frame(rows, bus=served.bus, start=start, progress=False, idle_timeout=2.0)


def _fault(served: Served, well: str, sensor: str, kind: str) -> dict[str, Any]:
    faults = served.http.get(f"/wells/{well}").json()["sensor_faults"]
    found = [f for f in faults if f["sensor"] == sensor and f["kind"] == kind]
    assert len(found) == 1, faults
    return found[0]


def _spans(page: Page, chart: str) -> list[dict[str, Any]]:
    return page.evaluate(
        f"(window.vfm.charts.{chart}.faultSpans || []).map(s => ({{sensor: s.sensor, kind: s.kind,"
        " start: s.start, end: s.end, x0: s.x0, x1: s.x1, y0: s.y0, y1: s.y1,"
        f" right: window.vfm.charts.{chart}.bbox.left + window.vfm.charts.{chart}.bbox.width}}))"
    )


def _colours(page: Page, chart: str, span: dict[str, Any]) -> list[list[float]]:
    """The canvas pixels along the middle of a drawn band (nine points across it), as the
    page shows them: composed over the white chart background (the canvas is transparent)."""
    return page.evaluate(
        f"""(s) => {{
        const ctx = window.vfm.charts.{chart}.ctx, y = Math.round((s.y0 + s.y1) / 2), out = [];
        for (let i = 1; i <= 9; i++) {{
          const x = Math.round(s.x0 + (s.x1 - s.x0) * i / 10);
          const [r, g, b, a] = ctx.getImageData(x, y, 1, 1).data;
          out.push([r, g, b].map(c => c * a / 255 + 255 * (1 - a / 255)));
        }}
        return out; }}""",
        span,
    )


#: the rate chart's legend rows of p05 and p95 (row 0 is the time)
LEGEND_ROWS = "Array.from(document.querySelectorAll('#rate-chart .u-legend .u-series')).slice(1, 3)"


def _purple(rgb: list[float]) -> bool:
    return all(abs(c - p) <= 12 for c, p in zip(rgb, PURPLE, strict=True))


def test_faults_on_the_charts_and_in_the_field_view(
    served: Served, browser_page: tuple[Page, list[str]]
) -> None:
    page, errors = browser_page
    url = served.url

    # before the faults: the well's page shows no frozen p_down, no band for it
    _replay(served, SPLIT, BEFORE)
    page.goto(url + "/#well=W01")
    page.wait_for_selector("#rate-chart canvas")
    page.wait_for_function("window.vfm.preds.length > 0")
    assert page.locator('#well-faults li[data-sensor="p_down"][data-kind="frozen"]').count() == 0
    assert not [s for s in _spans(page, "rate") if s["sensor"] == "p_down"]
    # ol gives no interval: the legend does not list p05 and p95 (they would equal the
    # prediction), and no band is drawn
    assert page.evaluate("window.vfm.preds.every(p => !(p.hi > p.lo))")
    page.wait_for_function(LEGEND_ROWS + ".every(r => getComputedStyle(r).display === 'none')")
    assert page.evaluate("window.vfm.charts.rate.data[1].every(v => v == null)")

    # the rest streams in while the page is open: the fault arrives with the well's view
    # (refreshed every 5 s), its line under the chart and its band on both charts
    _replay(served, BEFORE)
    fault = _fault(served, "W01", "p_down", "frozen")
    truth = served.truth["W01"]
    assert fault["end"] is None  # still frozen at the end of the data
    # the run starts at the last reading before the injection (the value it froze at)
    lag = pd.Timestamp(fault["start"]) - pd.Timestamp(truth["start"])
    assert pd.Timedelta(days=-3) <= lag <= pd.Timedelta(0), (fault, truth)
    item = page.locator('#well-faults li[data-sensor="p_down"][data-kind="frozen"]')
    item.wait_for(timeout=15_000)
    assert item.get_attribute("data-active") == "true"
    text = item.inner_text()
    assert fault["evidence"] in text and "since " + fault["start"][:10] in text, text
    assert "(active)" in text
    assert (
        "instrument fault: p_down frozen since " + fault["start"][:10]
        in page.locator("#well-alarms").inner_text()
    )
    # the stand-in's line says what it did to the interval at the latest prediction: with
    # ol the interval is the rates across the stand-in's span, empty where the rate does
    # not depend on p_down (critical flow): then it says nothing was widened
    last = page.evaluate("window.vfm.latest['W01']")
    said = (
        "interval widened to"
        if last["q_total_p95"] > last["q_total_p05"]
        else "does not move across the stand-in's span here (nothing to widen)"
    )
    page.wait_for_function(
        f"document.querySelector('#well-alarms').innerText.includes({said!r})", timeout=15_000
    )
    page.wait_for_function(
        "['rate', 'error'].every(c => (window.vfm.charts[c].faultSpans || [])"
        ".some(s => s.sensor === 'p_down' && s.kind === 'frozen'))"
    )
    for chart in ("rate", "error"):
        (span,) = [s for s in _spans(page, chart) if s["sensor"] == "p_down"]
        assert span["start"] == fault["start"] and span["end"] is None, span
        # active: the band runs from the fault's start to the chart's right edge
        assert span["x1"] - span["x0"] > 20 and abs(span["x1"] - span["right"]) < 1, span
        colours = _colours(page, chart, span)
        assert sum(_purple(c) for c in colours) >= 7, (chart, colours)

    # hovering the band names the fault (the overlay's title), no text is drawn on the chart
    box = page.locator("#rate-chart .u-over").bounding_box()
    assert box is not None
    (span,) = [s for s in _spans(page, "rate") if s["sensor"] == "p_down"]
    bbox = page.evaluate("[window.vfm.charts.rate.bbox.left, window.vfm.charts.rate.bbox.top]")
    dpr = page.evaluate("devicePixelRatio")
    x = box["x"] + ((span["x0"] + span["x1"]) / 2 - bbox[0]) / dpr
    y = box["y"] + ((span["y0"] + span["y1"]) / 2 - bbox[1]) / dpr
    page.mouse.move(x, y)
    page.wait_for_function(
        "document.querySelector('#rate-chart .u-over').title.includes('p_down frozen')"
    )
    assert fault["evidence"] in (page.locator("#rate-chart .u-over").get_attribute("title") or "")
    page.mouse.move(x, y + 80)  # off the band: the title goes
    page.wait_for_function("document.querySelector('#rate-chart .u-over').title === ''")
    page.screenshot(path=str(SHOTS / "well-fault.png"))

    # a fault that ended: a band over its span only, a past line, no alarm
    ended = _fault(served, "W02", "t_up", "frozen")
    assert ended["end"] is not None, ended
    page.goto(url + "/#well=W02")
    item = page.locator('#well-faults li[data-sensor="t_up"][data-kind="frozen"]')
    item.wait_for()
    assert item.get_attribute("data-active") == "false"
    assert ended["end"][:16].replace("T", " ") in item.inner_text()
    page.wait_for_function(
        "window.vfm.well === 'W02' && (window.vfm.charts.rate.faultSpans || [])"
        ".some(s => s.sensor === 't_up')"
    )
    (span,) = [s for s in _spans(page, "rate") if s["sensor"] == "t_up"]
    assert 2 < span["x1"] - span["x0"] and span["x1"] < span["right"] - 20, span
    assert sum(_purple(c) for c in _colours(page, "rate", span)) >= 7
    assert "t_up frozen" not in page.locator("#well-alarms").inner_text()
    page.screenshot(path=str(SHOTS / "well-fault-ended.png"))

    # the field view: an alarm for the active fault, with its evidence on hover; none for
    # the one that ended
    page.goto(url + "/#")
    w01 = page.locator('#field-table tr[data-well="W01"] td').last
    page.wait_for_function(
        "(document.querySelector('#field-table tr[data-well=\"W01\"]') || {innerText: ''})"
        ".innerText.includes('instrument fault: p_down frozen')"
    )
    assert fault["evidence"] in (w01.get_attribute("title") or "")
    w02 = page.locator('#field-table tr[data-well="W02"]').inner_text()
    assert "t_up frozen" not in w02, w02
    page.screenshot(path=str(SHOTS / "field-fault.png"))
    assert errors == [], errors
