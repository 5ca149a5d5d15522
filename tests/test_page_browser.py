"""The workbench page in a real browser: Playwright for Python driving Debian's chromium.

A real ``vfm serve`` (a subprocess: Zenoh on a free loopback port, HTTP on another, a
temporary store) is fitted on the first months of a small simulated field (three wells, an
eroding choke on W01) and fed the rest by a replay over Zenoh while the page is open. The
page is checked as a user would use it: the field view lists every well, the well chart
gains points as the replay streams, a diagnosis runs from the page and shows its verdict,
applying the candidate it offers first changes the model shown and puts a marker on the
chart, the change's trial against the replaced model (its shadow) shows both errors and
ends, "apply" of a change its held-out check calls worse asks the user before confirming,
a rollback button brings the first model back,
``/docs`` renders its operations with every non-loopback request blocked, ``/metrics``
parses, and the browser's console stays free of errors throughout.

Screenshots go to ``$VFM_SCREENSHOTS`` (default ``tests/artifacts/``, ignored by git).
Skipped, with the reason, when ``/usr/bin/chromium`` or the ``playwright`` package is
missing (``.ci/run`` installs chromium; ``make test`` installs playwright with the dev
extra). Never run ``playwright install``: it downloads a browser build of its own.
"""

from __future__ import annotations

import threading
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

import httpx
import pandas as pd
import pytest
from browser_support import SHOTS, Page, browser_marks, open_page

from replay.replayer import ReplayResult, replay_frame
from service.testing import ServeProcess
from vfm_core.meter_check import steady_span
from vfm_core.observations import validate_frame
from vfm_core.simulate import simulate_field

pytestmark = browser_marks(300)

SPLIT = "2016-02-01"
MID = "2016-09-01"
END = "2016-12-01"
TOKEN = "browser-test-token-0123456789"
#: wall time the replay of SPLIT..MID takes, s (the page is watched meanwhile)
REPLAY_S = 25.0


@dataclass
class Served:
    proc: ServeProcess
    frame: pd.DataFrame
    replay: list[ReplayResult] = field(default_factory=list)
    thread: threading.Thread | None = None


@pytest.fixture(scope="module")
def served(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Served]:
    folder = tmp_path_factory.mktemp("page")
    sim = simulate_field(wells=3, years=1.0, seed=4, hidden=["erosion:rate=0.5"])
    frame = validate_frame(sim.observations).frame
    frame = frame[frame["time"] < pd.Timestamp(END, tz="UTC")].reset_index(drop=True)
    data = folder / "field.parquet"
    frame.to_parquet(data)
    config = folder / "vfm.toml"
    config.write_text(
        f"""
[model]
name = "mm"
method = "bayes"
history = "{data}"
history_until = "{SPLIT}"
[zenoh]
listen = ["tcp/127.0.0.1:0"]
[http]
port = 0
token = "{TOKEN}"
[store]
path = "{folder / "store.sqlite"}"
synchronous = "normal"
# the page's loop as before the well-test review: this fast-eroding field's MPFM and well
# tests part by 30 %, so a well test may be held (held tests are walked through in
# tests/test_well_test_review_browser.py)
[well_test_review]
enabled = false
"""
    )
    proc = ServeProcess(config, folder / "serve.log").start(timeout=180)
    try:
        yield Served(proc, frame)
    finally:
        proc.stop()


def _replay(served: Served, frame: pd.DataFrame, speed: float | None) -> None:
    served.replay.append(
        replay_frame(
            frame,
            connect=[served.proc.zenoh],
            start=SPLIT,
            speed=speed,
            progress=False,
            idle_timeout=3.0,
        )
    )


def _start_replay(served: Served) -> None:
    """SPLIT..MID in about REPLAY_S seconds, on a thread of its own."""
    first = served.frame[served.frame["time"] < pd.Timestamp(MID, tz="UTC")]
    span_s = (pd.Timestamp(MID, tz="UTC") - pd.Timestamp(SPLIT, tz="UTC")).total_seconds()

    def run() -> None:
        _replay(served, first, span_s / REPLAY_S)

    served.thread = threading.Thread(target=run, name="replay", daemon=True)
    served.thread.start()


@pytest.fixture(scope="module")
def browser_page(served: Served) -> Iterator[tuple[Page, list[str]]]:
    with open_page() as opened:
        yield opened


def _points(page: Page) -> int:
    return int(page.evaluate("window.vfm.preds.length"))


def test_the_workbench_in_a_browser(served: Served, browser_page: tuple[Page, list[str]]) -> None:
    page, errors = browser_page
    url = served.proc.http_url
    _start_replay(served)

    # the field view lists every well, with its model
    page.goto(url + "/")
    wells = sorted(served.frame["well"].unique())
    for well in wells:
        page.wait_for_selector(f'#field-table tr[data-well="{well}"]')
    assert page.locator("#field-table tbody tr").count() == len(wells)
    assert "mm" in page.locator('#field-table tr[data-well="W01"]').inner_text()
    # the input counts say they run since the service started (a restart begins them anew)
    summary = page.locator("#inputs-summary").inner_text()
    assert (
        summary.startswith("Inputs since the service started at ") and " UTC: accepted " in summary
    )
    page.wait_for_function("document.querySelector('#live').classList.contains('on')")
    page.screenshot(path=str(SHOTS / "field.png"), full_page=True)

    # the well chart gains points as the replay streams
    page.click('#field-table tr[data-well="W01"] a')
    page.wait_for_selector("#rate-chart canvas")
    page.wait_for_function("window.vfm.preds.length > 0")
    first = _points(page)
    page.wait_for_function(f"window.vfm.preds.length > {first + 5}", timeout=30_000)
    # the chart is redrawn every 0.5 s (app.js draw): it shows the new points by then
    page.wait_for_function(f"window.vfm.charts.rate.data[0].length > {first}", timeout=5_000)
    # bayes gives every prediction its 90 % interval: the band has both edges, around it
    band = page.evaluate(
        "window.vfm.preds.filter(p => p.lo != null && p.hi != null && p.lo < p.q && p.q < p.hi)"
        ".length / window.vfm.preds.length"
    )
    assert band > 0.9, band
    legend = page.evaluate(
        "Array.from(document.querySelectorAll('#rate-chart .u-legend .u-series')).slice(1, 3)"
        ".map(r => [r.textContent, getComputedStyle(r).display])"
    )
    assert [(t[:3], d != "none") for t, d in legend] == [("p05", True), ("p95", True)], legend
    # the parameter chart: c_d over time, every point inside its band value +- 2 sd
    page.wait_for_function(
        "window.vfm.paramName === 'c_d' && window.vfm.charts.param"
        " && window.vfm.charts.param.data[0].length >= 3",
        timeout=30_000,
    )
    points, banded = page.evaluate(
        "(() => { const d = window.vfm.charts.param.data; let b = 0;"
        " for (let i = 0; i < d[0].length; i++)"
        "   if (d[2][i] != null && d[2][i] < d[1][i] && d[1][i] < d[3][i]) b++;"
        " return [d[0].length, b]; })()"
    )
    assert banded == points >= 3, (points, banded)
    page.screenshot(path=str(SHOTS / "well.png"), full_page=True)
    assert served.thread is not None
    served.thread.join(120)  # the diagnosis reads the history stored so far

    # a diagnosis runs from the page (token typed, kept in memory) and shows its verdict;
    # what it names is the diagnosis's business (tested elsewhere): the loop below applies
    # whichever candidate it offers first
    dialogs: list[str] = []
    answer = {"accept": True}

    def on_dialog(dialog: Any) -> None:
        dialogs.append(dialog.message)
        dialog.accept() if answer["accept"] else dialog.dismiss()

    page.on("dialog", on_dialog)
    page.fill("#token", TOKEN)
    page.fill("#diag-candidates", "erosion")
    page.uncheck("#diag-suggest")
    page.click("#diag-run")
    page.wait_for_function(
        "document.querySelector('#diag-verdict').textContent.length > 20"
        " || document.querySelector('#diag-status').classList.contains('error')",
        timeout=240_000,
    )
    status = page.locator("#diag-status").inner_text()
    assert "error" not in (page.locator("#diag-status").get_attribute("class") or ""), status
    verdict = page.locator("#diag-verdict").inner_text()
    assert page.locator("#diag-candidates-table button.apply").count() == 1, verdict
    # the verdict in one line above its sentence: its kind and what it names
    headline = page.locator("#diag-headline").inner_text()
    said = page.evaluate("window.vfm.diagnosed.verdict")
    words = {"effect": f"add {said['effect']}", "carried": "carried", "driver": "depends on"}
    assert headline.startswith("Verdict: ") and words[said["kind"]] in headline, (headline, said)
    if said["kind"] == "effect":
        assert f"{said['live']['change']:+.2f} points" in headline, headline
    # the candidate's trial forecast (its backtest against the shadow) has a column of its
    # own, this well's figure with its interval, as the diagnosis gives it
    forecast = page.evaluate(
        "(() => { const d = window.vfm.diagnosed, c = d.candidates.find(x => x.effect === 'erosion');"
        " const t = c.tests.trial; return (t.per_well || {})[(d.pool || {}).focus] || t; })()"
    )
    assert forecast["change"] is not None and forecast["low"] is not None, forecast
    assert "trial forecast" in page.locator("#diag-candidates-table thead").inner_text()
    cell = page.locator("#diag-candidates-table tbody tr td.trial").first.inner_text()
    assert f"{forecast['change']:.2f}" in cell and f"{forecast['low']:.2f}" in cell, (
        cell,
        forecast,
    )
    page.screenshot(path=str(SHOTS / "diagnosis.png"), full_page=True)

    # applying it (confirmed if its held-out check says worse) changes the model shown,
    # puts a marker on the chart and starts a trial against plain mm as the shadow
    button = page.locator("#diag-candidates-table button.apply").first
    assert button.get_attribute("data-spec")
    button.click()
    page.wait_for_function(  # the model name says which effect (and its settings) it got
        "document.querySelector('#well-model').dataset.model.startsWith('mm+')", timeout=120_000
    )
    applied = page.locator("#well-model").get_attribute("data-model")
    page.wait_for_function("window.vfm.markers.some(m => m.kind === 'model')")
    assert applied in page.locator("#change-result").inner_text()
    assert all("worse" in d and "confirm_worse" not in d for d in dialogs), dialogs
    trial_line = page.locator("#well-trial")
    page.wait_for_function(
        "document.querySelector('#well-trial').dataset.outcome === 'running'", timeout=15_000
    )
    assert f"Trial of {applied} against its shadow mm" in trial_line.inner_text()
    # the replaced model is kept as an earlier version, with a rollback button
    page.wait_for_selector("#versions-table button.rollback")
    assert "mm" in page.locator("#versions-table tbody tr").first.inner_text()
    # the parameter history marks the change
    page.wait_for_function(
        "window.vfm.params && window.vfm.params.model_changes.length >= 1", timeout=30_000
    )

    # the rest of the field streams in: errors of the new model right of the marker, and
    # the trial (30 days of data) ends with both errors on the page, as the API gives them
    marker = page.evaluate("window.vfm.markers.find(m => m.kind === 'model').t")
    _replay(served, served.frame[served.frame["time"] >= pd.Timestamp(MID, tz="UTC")], None)
    page.wait_for_function(
        f"window.vfm.meas.filter(m => m.predicted != null && m.t > {marker}).length >= 10"
    )
    page.wait_for_function(
        "['kept', 'rolled_back'].includes(document.querySelector('#well-trial').dataset.outcome)",
        timeout=30_000,
    )
    trial = httpx.get(served.proc.http_url + "/wells/W01", timeout=10).json()["trial"]
    assert trial["n"] >= 10 and trial["mape"] is not None and trial["shadow_mape"] is not None
    shown = trial_line.inner_text()
    assert f"MAPE {trial['mape']:.2f} % against the shadow's {trial['shadow_mape']:.2f} %" in shown
    assert f"over {trial['n']} paired" in shown and "Rule:" in shown
    page.wait_for_timeout(1200)  # one redraw
    page.screenshot(path=str(SHOTS / "change.png"), full_page=True)
    assert errors == [], errors
    # a change that predates the chart's window gets no marker (one at the window's left
    # edge would date it wrongly); a window that holds it marks it again
    page.select_option("#span", "7")
    page.wait_for_function(f"window.vfm.preds.length > 0 && window.vfm.preds[0].t > {marker}")
    assert page.evaluate("window.vfm.markers.filter(m => m.kind === 'model').length") == 0
    page.select_option("#span", "180")
    page.wait_for_function(
        f"window.vfm.preds.length > 0 && window.vfm.preds[0].t < {marker}"
        " && window.vfm.markers.some(m => m.kind === 'model')"
    )

    # "apply" of a change its held-out check calls worse asks first. Which candidate the
    # diagnosis offers, and how its check comes out, is not fixed; so the page is handed the
    # service's own refusal of a deliberately worse change for its next request (on
    # another, eroding, well: erosion added, then taken away again), then the user's
    # answer decides
    auth = {"Authorization": f"Bearer {TOKEN}"}
    w02 = served.proc.http_url + "/wells/W02/model"
    added = httpx.put(w02, json={"effects": ["erosion"]}, headers=auth, timeout=120)
    assert added.status_code == 200, added.text
    refusal = httpx.put(w02, json={"effects": []}, headers=auth, timeout=120)
    assert refusal.status_code == 409 and "confirm_worse" in refusal.text, refusal.text
    bodies: list[Any] = []

    def refuse_once(route: Any) -> None:
        bodies.append(route.request.post_data_json)
        if len(bodies) == 1:
            route.fulfill(status=409, body=refusal.text, content_type="application/json")
        else:
            route.continue_()

    model_before = page.locator("#well-model").get_attribute("data-model")
    page.route("**/wells/W01/model", refuse_once)
    try:
        answer["accept"] = False  # cancelled: nothing is sent again, nothing changes
        page.evaluate(
            "(s) => { const b = document.createElement('button'); b.dataset.spec = s; applyEffect(b); }",
            "erosion_time",
        )
        page.wait_for_function(
            "document.querySelector('#change-result').textContent.startsWith('Not applied')"
        )
        assert (
            len(bodies) == 1
            and page.locator("#well-model").get_attribute("data-model") == model_before
        )
        bodies.clear()
        answer["accept"] = True  # confirmed: sent again with confirm_worse, applied
        page.evaluate(
            "(s) => { const b = document.createElement('button'); b.dataset.spec = s; applyEffect(b); }",
            "erosion_time",
        )
        page.wait_for_function(
            "document.querySelector('#well-model').dataset.model.endsWith('+erosion_time')",
            timeout=120_000,
        )
    finally:
        page.unroute("**/wells/W01/model")
    assert [b.get("confirm_worse") for b in bodies] == [None, True], bodies
    assert len(dialogs) >= 2 and "worse" in dialogs[-1] and " %" in dialogs[-1], dialogs
    # the browser logs each refused request; one per question asked, nothing else
    conflicts = [e for e in errors if "status of 409 (Conflict)" in e]
    assert len(conflicts) == len(dialogs), (conflicts, dialogs)
    errors[:] = [e for e in errors if e not in conflicts]

    # one click brings the first model (plain mm) back
    page.wait_for_function(
        "document.querySelectorAll('#versions-table button.rollback').length >= 2", timeout=15_000
    )
    versions = httpx.get(served.proc.http_url + "/wells/W01", timeout=10).json()["versions"]
    first = versions[-1]
    assert first["model"] == "mm", versions
    rollback = page.locator(f'#versions-table button.rollback[data-version="{first["version"]}"]')
    answer["accept"] = False  # cancelled: nothing is sent, the model stays
    rollback.click()
    page.wait_for_function(
        "document.querySelector('#rollback-result').textContent === 'Not rolled back.'"
    )
    assert page.locator("#well-model").get_attribute("data-model") != "mm"
    answer["accept"] = True
    rollback.click()
    page.wait_for_function(
        "document.querySelector('#well-model').dataset.model === 'mm'", timeout=120_000
    )
    assert "Rolled back" in page.locator("#rollback-result").inner_text()
    # asked first: a rollback replaces the live model at once
    assert dialogs[-1].startswith(f"Roll W01 back to version {first['version']} (mm)?"), dialogs
    page.screenshot(path=str(SHOTS / "rollback.png"), full_page=True)

    # a well test far below the MPFM readings near it, posted from the page: an alarm
    w01 = served.frame[served.frame["well"] == "W01"]
    mpfm = w01[w01["source"] == "mpfm"]
    last = mpfm["time"].iloc[-1]
    # the readings the service compares: within 24 h and at the well test's choke
    ns = w01["time"].astype("int64").to_numpy()
    lo, hi = steady_span(ns, w01["choke"].to_numpy(dtype=float), last.value)
    at = (mpfm["time"] - last).abs() <= pd.Timedelta("24h")
    at &= mpfm["time"].astype("int64").between(lo, hi)
    near = mpfm[at]["q_total"].median()
    page.fill("#wt-time", last.strftime("%Y-%m-%dT%H:%M:%SZ"))
    page.fill("#wt-rate", f"{0.7 * near:.1f}")
    page.click("#well-test-form button")
    page.wait_for_function(
        "document.querySelector('#wt-result').textContent.includes('Prediction')"
    )
    page.wait_for_function(
        "document.querySelector('#well-alarms').textContent.includes('MPFM reads 43 % above')",
        timeout=15_000,
    )

    # the field view shows the new model and the alarm too
    page.goto(url + "/#")
    page.wait_for_function(
        "document.querySelector('#field-table tr[data-well=\"W01\"]')"
        " && document.querySelector('#field-table tr[data-well=\"W01\"]').innerText.includes('mm')"
        " && document.querySelector('#field-table tr[data-well=\"W01\"]').innerText.includes('MPFM reads')"
    )
    assert "MPFM reads" not in page.locator('#field-table tr[data-well="W02"]').inner_text()
    # opened after the replay (no live prediction since): the interval column still gives
    # each bayes well's latest 90 % interval width, from GET /wells/{well}
    page.reload()
    page.wait_for_selector('#field-table tr[data-well="W02"]')
    assert page.evaluate("Object.keys(window.vfm.latest).length") == 0  # none live
    width = page.locator('#field-table tr[data-well="W02"] td').nth(6).inner_text()
    latest = httpx.get(served.proc.http_url + "/wells/W02", timeout=10).json()
    latest = latest["latest_prediction"]
    expected = 100 * (latest["q_total_p95"] - latest["q_total_p05"]) / latest["q_total"]
    assert width != "\u2013" and 0.5 * expected < float(width) < 2 * expected, (width, latest)
    # an empty band is no interval (a method without intervals whose rate does not move
    # across a stand-in's span, p_down in critical flow): a dash, not a certain-looking 0.0
    cell = '#field-table tr[data-well="W02"] td'
    page.evaluate(
        "() => { window.vfm.latest.W02 = {q_total: 100, q_total_p05: 100, q_total_p95: 100};"
        " renderField(); }"
    )
    assert page.locator(cell).nth(6).inner_text() == "\u2013"
    page.evaluate("() => { delete window.vfm.latest.W02; renderField(); }")
    assert page.locator(cell).nth(6).inner_text() == width
    page.screenshot(path=str(SHOTS / "field-alarm.png"), full_page=True)

    # nothing of the replay was lost on the way (a well that starts after the split has no
    # model until its first measurement: its first sample alone goes unanswered)
    missing = [r.missing for r in served.replay]
    assert missing[0] <= len(wells) and missing[1] == 0, (missing, served.replay)
    assert errors == [], errors


#: a carried verdict as the page gets it, cut to what the panel reads: the field's live test
#: beyond chance but below the minimum, this well's (W01) outage change above zero beyond
#: chance (a page walk on a sigmoid-valve field, seed 5402, W02, had these figures)
CARRIED: dict[str, Any] = {
    "elapsed_s": 1,
    "report": None,
    "diagnosis": {
        "model": "ham",
        "method": "bayes",
        "base_effects": [],
        "pool": {"focus": "W01", "wells": ["W01", "W02"]},
        "verdict": {
            "kind": "carried",
            "effect": "valve_sigmoid",
            "text": "carried.",
            "live": {"change": -0.02},
        },
        "fdr": {"procedure": "Benjamini-Hochberg", "tests": 8, "family": 8, "rejected": 2},
        "candidates": [
            {
                "effect": "valve_sigmoid",
                "replayed": True,
                "offer": False,
                "raises_error": False,
                "meaning": "A sigmoid valve.",
                "warnings": ["w1 at its bound.", "w2 at its bound."],
                "tests": {
                    "fit_once": {"change": -1.1, "rejected": True, "per_well": {}},
                    "live": {
                        "change": -0.07,
                        "low": -0.12,
                        "high": -0.03,
                        "p_value": 0.004,
                        "q_value": 0.03,
                        "n_blocks": 62,
                        "rejected": True,
                        "per_well": {
                            "W01": {
                                "change": -0.02,
                                "low": -0.06,
                                "high": 0.02,
                                "mape": 4.03,
                                "base_mape": 4.05,
                                "p_value": 0.18,
                                "n_blocks": 13,
                            }
                        },
                    },
                    "outage": {
                        "change": -0.05,
                        "low": -0.19,
                        "high": 0.06,
                        "per_well": {"W01": {"change": 0.14, "low": 0.04, "high": 0.23}},
                    },
                },
            }
        ],
    },
}


def test_markers_trial_line_and_candidates_read_as_they_should(
    served: Served, browser_page: tuple[Page, list[str]]
) -> None:
    """What a page walk on fields the project did not tune on (s54, walk54) found misleading,
    read back from the page's own functions on given data: retrain markers only since the
    change to the pbl method the well runs (not every step of the bayes method before it),
    a model change placed at its data time and not pinned to the window's left edge when it
    came before the window, a change of the method alone labelled with the method, the trial
    line's small p printed as it is (not 0.000) and not read as the chance that the shadow
    is better, an ended trial's end date; a carried verdict's "add anyway" withheld (and the
    headline saying so) where this well's outage error rises beyond chance, offered (and the
    headline not saying "nothing offered") where it does not; the rejected tests named; the
    candidates' table inside its panel at 1280 px."""
    page, errors = browser_page
    page.set_viewport_size({"width": 1400, "height": 1000})
    page.goto(served.proc.http_url + "/#well=W01")
    page.wait_for_selector("#rate-chart canvas")
    page.wait_for_function("window.vfm.view && window.vfm.view.well === 'W01'")
    t0 = 1_500_000_000  # s
    marks = page.evaluate(
        """(t0) => {
          const saved = window.vfm.preds;
          // bayes steps v1..v5, the change to pbl at v6 (its data time t0 + 45), a retrain at v7
          window.vfm.preds = [1, 2, 3, 4, 5, 6, 6, 7, 7].map((v, i) => ({ t: t0 + 10 * i, version: v }));
          const iso = (s) => new Date(s * 1000).toISOString();
          const view = { method: "pbl:182d", last_sample_time: iso(t0 + 80),
            model_changes: [{ model_before: "mm", model_after: "mm", method: "pbl:182d", version_before: 5, version_after: 6 }],
            versions: [{ version: 5, method: "bayes", replaced: iso(t0 + 45) }] };
          const inside = markersFromView(view);
          // the same change seen in a window that starts after it, its version kept or not
          window.vfm.preds = [6, 6, 7].map((v, i) => ({ t: t0 + 100 + 10 * i, version: v }));
          const after = markersFromView(view);
          const gone = markersFromView({ ...view, versions: [] });
          window.vfm.preds = saved;
          const pick = (ms) => ms.map((m) => [m.kind, m.t - t0, m.label]);
          return [pick(inside), pick(after), pick(gone)];
        }""",
        t0,
    )
    assert marks[0] == [["model", 45, "\u2192 mm (pbl:182d)"], ["retrain", 70, "retrain"]], marks
    assert marks[1] == marks[2] == [["retrain", 120, "retrain"]], marks
    # a parameter the specification sets reads "fixed", not "± 0.0000" (walk56: an applied
    # verdict's valve weight on ham showed a learned-looking sd of 1e-10)
    sds = page.evaluate(
        """() => { const saved = window.vfm.view;
          window.vfm.view = { parameters: {
            rho_oil: { value: 840.1, unit: "kg/m3", std: 10.6, low: 650, high: 1000, fixed: false },
            "valve_equal_percentage.weight": { value: 1.006, unit: "-", std: null, low: -0.5,
                                               high: 1.5, fixed: true } } };
          renderParams();
          const cells = [...document.querySelectorAll("#params tbody tr")].map((r) => r.cells[2].textContent);
          window.vfm.view = saved; renderParams(); return cells; }"""
    )
    assert sds == ["10.6000", "fixed"], sds
    # the field table gives an alarm's follow-up in a few words (walk56: a 300-character
    # sentence filled the cell); the well's page keeps the sentence
    texts = page.evaluate(
        """() => { const alarm = { active: true, direction: "low", source: "mpfm", shift: -0.028,
            since: "2018-11-09T00:00:00+00:00", onset: "2018-10-18T00:00:00+00:00",
            which_moved: { moved: "unclear", text: "the MPFM reads -0.6 % on average against the 2 well tests since the alarm began" } };
          const wait = { ...alarm, which_moved: null, awaiting_well_test: { due: "2018-04-20T00:00:00+00:00",
            overdue: true, text: "no well test since the alarm (last 2018-03-25, overdue since 2018-04-20, usually 26 days)" } };
          const v = (ra) => ({ well: "W9", ready: true, residual_alarm: ra });
          return [alarmsOf(v(alarm), true), alarmsOf(v(alarm)), alarmsOf(v(wait), true)]; }"""
    )
    brief, full, waiting = texts
    assert brief[1] == "the well tests cannot tell yet which moved", brief
    assert full[1].startswith("the MPFM reads -0.6 %"), full
    assert waiting[1] == "next well test overdue since 2018-04-20", waiting
    assert brief[0] == full[0] and brief[0].startswith("residual alarm: MPFM below the model"), (
        brief
    )
    # ... and in plain text beside the red alarm (walk56: "cannot tell yet" read as urgent,
    # when it means "wait for the next well test"); an overdue well test in the warning colour
    colours = page.evaluate(
        """() => { const saved = state.wells;
          const ra = { active: true, direction: "low", source: "mpfm", shift: -0.028,
            since: "2018-11-09T00:00:00+00:00", which_moved: { moved: "unclear", text: "..." } };
          const late = { ...ra, which_moved: null, awaiting_well_test: { due: "2018-04-20T00:00:00+00:00",
            overdue: true, text: "no well test since the alarm" } };
          state.wells = { W8: { well: "W8", ready: true, residual_alarm: ra },
                          W9: { well: "W9", ready: true, residual_alarm: late } };
          renderField();
          const cell = (w) => document.querySelector(`#field-table tr[data-well="${w}"]`).cells[8];
          const colour = (el) => getComputedStyle(el).color;
          const out = ["W8", "W9"].map((w) => { const c = cell(w), f = c.querySelector(".follow-up");
            return [colour(c), f ? colour(f) : null, f ? f.textContent : null]; });
          state.wells = saved; renderField(); return out; }"""
    )
    red = colours[0][0]
    assert colours[1][0] == red, colours  # the alarm itself stays red
    assert colours[0][1] not in (None, red), colours
    assert colours[0][2] == "the well tests cannot tell yet which moved", colours
    assert colours[1][1] not in (None, red, colours[0][1]), colours
    assert colours[1][2] == "next well test overdue since 2018-04-20", colours
    line = page.evaluate(
        """() => { renderTrial({ trial: { model: "mm", shadow_model: "mm", method: "pbl:182d",
            shadow_method: "bayes", since: "2018-01-01T00:00:00+00:00", ended: "2018-02-01T00:00:00+00:00",
            n: 38, mape: 5.13, shadow_mape: 1.81, p_value: 1.49e-7, outcome: "rolled_back" } });
          const s = document.querySelector("#well-trial").textContent; renderTrial(window.vfm.view); return s; }"""
    )
    assert "p 1.5e-07" in line and "p 0.000" not in line and "p 1.5e-07 that" not in line, line
    assert "from 2018-01-01T00:00:00Z to 2018-02-01T00:00:00Z" in line, line
    # a kept trial whose model a rollback has replaced since says so
    line = page.evaluate(
        """() => { renderTrial({ trial: { model: "mm+slip", shadow_model: "mm", version: 7, n: 55,
            since: "2018-01-01T00:00:00+00:00", ended: "2018-02-01T00:00:00+00:00", outcome: "kept" },
            model_changes: [{ kind: "change", model_after: "mm+slip", method: "bayes", version_after: 7 },
                            { kind: "rollback", model_after: "mm", method: "bayes", version_after: 90 }] });
          const s = document.querySelector("#well-trial").textContent; renderTrial(window.vfm.view); return s; }"""
    )
    assert line.endswith(
        "Since then rolled back to mm (bayes), version 90: mm+slip no longer runs."
    ), line

    def shown(carried: dict[str, Any]) -> tuple[str, int, str, str]:
        page.evaluate("(j) => showDiagnosis(j)", carried)
        return (
            page.locator("#diag-headline").inner_text(),
            page.locator("#diag-candidates-table button.apply").count(),
            page.locator("#diag-candidates-table tbody tr").first.inner_text(),
            page.locator("#diag-drivers").inner_text(),
        )

    headline, buttons, row, drivers = shown(CARRIED)
    assert buttons == 0 and "nothing offered" in headline, (headline, row)
    assert "raises this well's outage error (+0.14 [0.04, 0.23] points, beyond chance)" in row, row
    assert "w1 at its bound; w2 at its bound." in row, row
    # asked to confirm a change its held-out check calls worse, the user reads the
    # diagnosis's own figure beside it, and which of the two decides
    beside = page.evaluate("(d) => diagnosisBeside(d, 'valve_sigmoid')", CARRIED["diagnosis"])
    assert (
        "live MAPE 4.05 % -> 4.03 %" in beside and "the trial against the shadow decides" in beside
    )
    assert page.evaluate("(d) => diagnosisBeside(d, 'slip')", CARRIED["diagnosis"]) == ""
    assert "2 of 8 tests rejected: valve_sigmoid (fit-once: field; live: field)." in drivers, (
        drivers
    )
    level = {**CARRIED, "diagnosis": {**CARRIED["diagnosis"]}}
    cand = {**CARRIED["diagnosis"]["candidates"][0]}
    cand["tests"] = {
        **cand["tests"],
        "outage": {
            "change": -0.05,
            "low": -0.19,
            "high": 0.06,
            "per_well": {"W01": {"change": 0.05, "low": -0.04, "high": 0.13}},
        },
    }
    level["diagnosis"]["candidates"] = [cand]
    headline, buttons, row, _ = shown(level)
    assert buttons == 1 and "add anyway" in row, row
    assert "nothing offered" not in headline and "not offered for accuracy" in headline, headline
    # a parameter to read on a mechanistic model; on a hybrid the network takes up what
    # the parameter would read, and the page says so
    for model, says, title_says in (
        ("mm", "adds it as a parameter to read", "a physical parameter to read"),
        ("ham", "may leave near its prior", "on a hybrid the network takes up the same misfit"),
    ):
        headline, buttons, row, _ = shown(
            {**level, "diagnosis": {**level["diagnosis"], "model": model}}
        )
        title = page.locator("#diag-candidates-table button.apply").first.get_attribute("title")
        assert buttons == 1 and says in headline and title_says in title, (headline, title)
    # the table stays inside its panel on a 1280 px window (it ran 120 px past it); the
    # page is opened at that width (charts drawn at 1400 px keep their width on a resize)
    page.set_viewport_size({"width": 1280, "height": 1000})
    page.reload()
    page.wait_for_function("window.vfm.view && window.vfm.view.well === 'W01'")
    shown(level)
    panel, table, doc = page.evaluate(
        """() => [document.querySelector('#diagnosis').getBoundingClientRect().right,
                  document.querySelector('#diag-candidates-table').getBoundingClientRect().right,
                  document.documentElement.scrollWidth]"""
    )
    assert table <= panel and doc <= 1280, (panel, table, doc)
    page.set_viewport_size({"width": 1400, "height": 1000})
    assert errors == [], errors


#: a verdict's text as the diagnosis wrote it on a walk (s54, seed 5421, W01): 683 characters
LONG_VERDICT = (
    "No candidate explains the residual for W01: none lowers the live or the outage error beyond "
    "chance (Benjamini-Hochberg at q = 0.05 over the diagnosis's tests): what is left (live MAPE "
    "3.55 %; noise floor about 2.29 %) is measurement noise, meter drift and what bayes follows. "
    "Suggestive, not established: the fit-once evidence points at slip:exponent=1.04077 (-0.31 "
    "points, p = 0.0035, q = 0.076), beyond chance for its own test (p < 0.05) but not over all "
    "the diagnosis's tests (q); nothing is named for it. A diagnosis over more months of data may "
    "decide. Not tested: valve (the choke hardly moves (largest P5-P95 span 0.050 in one well), "
    "so a valve curve cannot be told from C_D)."
)


def test_verdict_folds_small_alarms_and_charts_follow_the_window(
    served: Served, browser_page: tuple[Page, list[str]]
) -> None:
    """What the s54 walk still found misleading on the page: a verdict of 700-2,600 characters
    of bold (now its first sentence, the rest folded under "the evidence", no sentence cut at a
    decimal); a residual alarm of a +0.5 % shift in the same red as a 6 % one (now "small", in
    the warning colour, where the shift is under the well's rolling MAPE); the apply line's
    held-out check not saying that it replays each model's method; and charts that kept the
    width they were drawn at when the window narrowed (the page scrolled sideways)."""
    page, errors = browser_page
    page.set_viewport_size({"width": 1600, "height": 1000})
    page.goto(served.proc.http_url + "/#well=W01")
    page.wait_for_selector("#rate-chart canvas")
    page.wait_for_function("window.vfm.view && window.vfm.view.well === 'W01'")
    page.evaluate("(t) => renderVerdictText(t)", LONG_VERDICT)
    first = page.locator("#diag-verdict").inner_text()
    assert first.startswith("No candidate explains") and first.endswith("what bayes follows."), (
        first
    )
    more = page.locator("#diag-verdict-more")
    assert more.is_visible() and more.get_attribute("open") is None
    assert more.locator("summary").inner_text() == "the evidence (3 more sentences)"
    paragraphs = more.locator("p").all_text_contents()
    assert paragraphs[0].startswith("Suggestive") and "exponent=1.04077" in paragraphs[0]
    assert " ".join([first, *paragraphs]) == LONG_VERDICT
    more.locator("summary").click()
    assert more.get_attribute("open") is not None and more.locator("p").first.is_visible()
    page.locator("#diagnosis").screenshot(path=str(SHOTS / "verdict-folded.png"))
    page.evaluate("renderVerdictText('Noise: nothing is missing.')")
    assert page.locator("#diag-verdict").inner_text() == "Noise: nothing is missing."
    assert not more.is_visible()

    def header(shift: float, small: bool | None) -> tuple[str, str, int]:
        return tuple(  # type: ignore[return-value]
            page.evaluate(
                """([shift, small]) => {
                  const saved = state.view;
                  // the residual alarm alone (this well's other alarms set aside), sized by
                  // the service (residual_alarm.small, typical_error_percent)
                  state.view = { ...saved, parameters: {}, mpfm_check: null, pending_measurements: 0,
                    ready: true, rolling_mape: { value: 2.2, n: 40 },
                    residual_alarm: { active: true, shift, direction: "high", source: "mpfm",
                                      since: "2018-03-01T00:00:00+00:00", events: [],
                                      small, typical_error_percent: 2.2,
                                      awaiting_well_test: { text: "no well test since the alarm" } } };
                  renderWellHeader();
                  const el = document.querySelector("#well-alarms");
                  const out = [el.className, el.innerText, el.querySelectorAll(".small-shift").length];
                  state.view = saved; renderWellHeader();
                  return out;
                }""",
                [shift, small],
            )
        )

    cls, text, spans = header(0.005, True)
    assert cls == "warn" and spans == 1, (cls, text)
    assert "small residual alarm: MPFM above the model (a shift of +0.5 %)" in text, text
    assert "under the model's usual error of 2.2 % before it" in text, text
    # its follow-up (no well test yet) is part of it, in the same colour (a walk showed it
    # in red beside the amber alarm), and its band on the charts is amber too
    assert "before it); no well test since the alarm" in text, text
    assert page.evaluate(
        "[alarmFill({ small: true }), alarmFill({ small: false }), alarmFill({})]"
    ) == [
        "rgba(178,106,0,0.75)",
        "rgba(179,38,30,0.75)",
        "rgba(179,38,30,0.75)",
    ]
    for shift, small in ((0.06, False), (0.005, None)):
        cls, text, spans = header(shift, small)
        assert cls == "alarm" and spans == 0 and "small" not in text, (shift, small, text)
    line = page.evaluate(
        """() => changedLine({ model_before: "mm", model_after: "mm+erosion", version_before: 3,
            version_after: 4, holdout: { before: 3.09, after: 2.57, protocol: "replayed" } })"""
    )
    assert "latest fifth of the history, each model learning with its own method" in line, line
    assert "3.09 % before, 2.57 % after" in line, line
    # drawn at 1600 px, then the window narrows to 1150 (still two columns): every chart
    # follows its column, and the page does not scroll sideways
    page.set_viewport_size({"width": 1150, "height": 1000})
    page.wait_for_function(
        "document.querySelector('#residual-chart canvas').getBoundingClientRect().right"
        " <= document.querySelector('#residual-chart').closest('section').getBoundingClientRect().right"
    )
    spans = page.evaluate(
        """() => [...document.querySelectorAll('.chart canvas')].filter((c) => c.offsetParent)
            .map((c) => [c.closest('.chart').id, c.getBoundingClientRect().right,
                         c.closest('section, main').getBoundingClientRect().right])"""
    )
    assert len(spans) >= 3, spans
    assert all(right <= edge + 1 for _, right, edge in spans), spans
    assert page.evaluate("document.documentElement.scrollWidth") <= 1150
    page.screenshot(path=str(SHOTS / "narrowed.png"), full_page=True)
    page.set_viewport_size({"width": 1400, "height": 1000})
    assert errors == [], errors


def test_docs_render_offline(served: Served, browser_page: tuple[Page, list[str]]) -> None:
    page, errors = browser_page
    outside: list[str] = []

    def only_loopback(route: Any) -> None:
        if route.request.url.startswith(("http://127.0.0.1", "data:", "blob:")):
            route.continue_()
        else:
            outside.append(route.request.url)
            route.abort()

    page.route("**/*", only_loopback)
    try:
        page.goto(served.proc.http_url + "/docs")
        page.wait_for_selector(".opblock", timeout=30_000)
        assert page.locator(".opblock").count() >= 10
        assert page.get_by_text("/wells/{well}/diagnosis").count() >= 1
        page.screenshot(path=str(SHOTS / "docs.png"), full_page=False)
    finally:
        page.unroute("**/*")
    assert outside == [], outside
    assert errors == [], errors


def test_metrics_parse(served: Served) -> None:
    """``/metrics`` against the well views after the page's walk (the first test of this
    module replays the field and applies a change: run alone, nothing has been served)."""
    from prometheus_client.parser import text_string_to_metric_families

    if not served.replay:
        pytest.skip("needs the replay of test_the_workbench_in_a_browser (run the module)")

    text = httpx.get(served.proc.http_url + "/metrics", timeout=10).text
    families = {f.name: f for f in text_string_to_metric_families(text)}
    mape = {s.labels["well"]: s.value for s in families["vfm_well_rolling_mape_percent"].samples}
    # a well whose model changed after the replay has no rolling error yet (it restarts)
    views = {
        w: httpx.get(f"{served.proc.http_url}/wells/{w}", timeout=10).json()
        for w in served.frame["well"].unique()
    }
    rolling = {w: v["rolling_mape"]["value"] for w, v in views.items()}
    assert mape == pytest.approx({w: x for w, x in rolling.items() if x is not None}), mape
    assert len(mape) >= 2 and all(0 <= v < 100 for v in mape.values()), mape
    # the trials side by side: the new model's error and its shadow's, per well
    trial = {
        (s.labels["well"], s.labels["role"]): s.value
        for s in families["vfm_well_trial_mape_percent"].samples
    }
    for w, v in views.items():
        t = v["trial"]
        if t is not None and t["mape"] is not None:
            assert trial[(w, "model")] == pytest.approx(t["mape"]), (w, t)
            assert trial[(w, "shadow")] == pytest.approx(t["shadow_mape"]), (w, t)
    ended = {s.labels["outcome"]: s.value for s in families["vfm_trials"].samples}
    assert ended.get("kept", 0) + ended.get("rolled_back", 0) >= 1, ended  # W01's first
    latency = families["vfm_prediction_latency_seconds"]
    count = next(s.value for s in latency.samples if s.name.endswith("_count"))
    assert count > 0
