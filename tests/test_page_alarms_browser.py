"""Residual alarms on the workbench page, in a real browser (Playwright driving Debian's
chromium), against the service fed a well whose measured rate moves and whose model does not.

The well (:mod:`alarm_support`: ``mm`` fitted once, ``pbl:3650d``; two MPFM readings a day
with 3 % scatter) reads 12 % high for four days from day 32 and 12 % low for good from day 70,
106 days in all, its choke wandering between 0.540 and 0.542. The service's residual alarm
(default settings: tested from day 30, an alarm still active after 30 periods accepted as the
new level) raises an alarm on the bump, which clears once the readings come back (on most
noise draws; on some it lasts 30 days and is accepted: the test takes what the service says),
and one on the step, which is accepted 30 days after it began. The page must list both under
the rate chart (meter, side of the model, span, how each ended, the ``data-closed`` and
``data-active`` attributes), name the accepted one when its band on the chart is hovered,
and label the residual chart's choke axis with distinct ticks.

Screenshots go to ``$VFM_SCREENSHOTS`` (default ``tests/artifacts/``, ignored by git).
Skipped, with the reason, when ``/usr/bin/chromium`` or the ``playwright`` package is
missing (CI sets ``VFM_REQUIRE_BROWSER=1``: there a missing browser fails).
"""

from __future__ import annotations

from datetime import timedelta
from pathlib import Path
from typing import Any

import httpx
import pandas as pd
from alarm_support import INPUTS, T0, fixed_model_service, send_readings, wait_learned
from browser_support import SHOTS, Page, browser_marks, open_page

pytestmark = browser_marks(180)

BUMP = (32, 36)  # days 12 % high
STEP = 70  # 12 % low from this day on
DAYS = 106
CHOKE = (0.54, 0.002)  # the choke (fraction) and how far above it it wanders


def level(day: int) -> float:
    return 1.12 if BUMP[0] <= day < BUMP[1] else 0.88 if day >= STEP else 1.0


def minute(iso: str) -> str:
    return iso[:16].replace("T", " ")


def expected_text(event: dict[str, Any], accept_periods: int) -> str:
    """The list line the page should show for a closed event, in the words of the brief."""
    side = {"high": "above", "low": "below"}[event["direction"]]
    how = {
        "cleared": "cleared: the residuals came back",
        "accepted": f"accepted as the new level after {accept_periods} periods: "
        "the alarm restarts from it",
    }[event["closed"]]
    shift = event.get("shift")  # its size at the raise (s51), where known
    by = "" if shift is None else f" (a shift of {100 * shift:+.1f} %)"
    onset = (event.get("onset") or "")[:10]  # the change's onset, where days before the raise
    began = f" (the change began about {onset})" if onset and onset < event["start"][:10] else ""
    return (
        f"{event['source'].upper()} {side} the model{by} "
        f"{minute(event['start'])} to {minute(event['end'])} UTC{began}: {how}"
    )


def hover_band(page: Page, span: dict[str, Any]) -> None:
    """Move the mouse to the middle of a band drawn on the rate chart (canvas pixels)."""
    box = page.locator("#rate-chart .u-over").bounding_box()
    assert box is not None
    left, top = page.evaluate("[window.vfm.charts.rate.bbox.left, window.vfm.charts.rate.bbox.top]")
    dpr = page.evaluate("devicePixelRatio")
    x = box["x"] + ((span["x0"] + span["x1"]) / 2 - left) / dpr
    y = box["y"] + ((span["y0"] + span["y1"]) / 2 - top) / dpr
    page.mouse.move(x, y)


def test_residual_alarms_listed_and_named_on_the_page(tmp_path: Path) -> None:
    inputs = (CHOKE[0], *INPUTS[1:])
    with (
        fixed_model_service(tmp_path, http=True) as (service, client),
        open_page() as (page, errors),
    ):
        times = send_readings(client, level, DAYS, seed=5, inputs=inputs, choke_spread=CHOKE[1])
        wait_learned(service, len(times), 90)
        alarm = httpx.get(service.http_url + "/wells/W01", timeout=30).json()["residual_alarm"]
        events, accept = alarm["events"], alarm["accept_periods"]
        assert accept == 30 and not alarm["active"], alarm
        # the step's alarm: below the model, begun within days of the step, accepted 30 days on
        stepped = pd.Timestamp(T0 + timedelta(days=STEP))
        (step,) = [e for e in events if pd.Timestamp(e["start"]) >= stepped]
        assert (step["direction"], step["closed"]) == ("low", "accepted"), events
        start, end = pd.Timestamp(step["start"]), pd.Timestamp(step["end"])
        assert stepped <= start <= stepped + pd.Timedelta(days=4), step
        assert end - start == pd.Timedelta(days=accept), step
        # the change's onset (the CUSUM's change point): at the step, at or before the raise
        onset = pd.Timestamp(step["onset"])
        assert stepped - pd.Timedelta(days=1) <= onset <= start, step
        # here it lies days before the raise, so the step's line names it (expected_text)
        assert onset.date() < start.date(), step
        # the bump's: above the model; cleared or (on some noise draws) accepted
        assert events[0]["direction"] == "high" and events[0]["closed"] in ("cleared", "accepted")
        assert all(e["end"] is not None for e in events), events

        page.goto(service.http_url + "/#well=W01")
        page.wait_for_selector("#rate-chart canvas")
        page.wait_for_function("window.vfm.preds.length > 0")
        items = page.locator("#well-residual-alarms li")
        items.first.wait_for()
        # newest first, one line per event, each in plain words with its span and ending
        assert items.count() == len(events)
        for item, event in zip(items.all(), reversed(events), strict=True):
            assert item.inner_text() == expected_text(event, accept), (item.inner_text(), event)
            assert item.get_attribute("data-closed") == event["closed"]
            assert item.get_attribute("data-active") == "false"
            assert item.get_attribute("data-start") == event["start"]
        assert (
            "a period: a day of MPFM readings" in page.locator("#well-residual-alarms").inner_text()
        )
        # a view that did not change redraws nothing (the line is the same node after a render)
        assert page.evaluate(
            "(() => { const li = document.querySelector('#well-residual-alarms li');"
            " renderAlarms(window.vfm.view);"
            " return li === document.querySelector('#well-residual-alarms li'); })()"
        )

        # the step's band on the rate chart: hovering it names the alarm with the same words
        page.wait_for_function(
            "(window.vfm.charts.rate.alarmSpans || []).some(s => s.closed === 'accepted'"
            f" && s.start === {step['start']!r})"
        )
        (span,) = page.evaluate(
            "window.vfm.charts.rate.alarmSpans.filter(s => s.start === "
            f"{step['start']!r}).map(s => ({{x0: s.x0, x1: s.x1, y0: s.y0, y1: s.y1}}))"
        )
        assert span["x1"] - span["x0"] > 50, span  # 30 of the chart's 106 days
        hover_band(page, span)
        title = "Residual alarm: " + expected_text(step, accept)
        page.wait_for_function(f"document.querySelector('#rate-chart .u-over').title === {title!r}")
        page.screenshot(path=str(SHOTS / "well-alarms.png"))
        page.mouse.move(0, 0)

        # the residual chart's choke axis: ticks 0.0005 apart need four decimals, all distinct
        ticks, splits = page.evaluate(
            "[window.vfm.charts.residual.axes[0]._values, window.vfm.charts.residual.axes[0]._splits]"
        )
        labels = [t for t in ticks if t]
        assert len(labels) >= 3 and len(set(labels)) == len(labels), labels
        # each label is its tick's value (not rounded to a neighbour's)
        assert all(abs(float(t) - v) < 1e-9 for t, v in zip(ticks, splits, strict=True) if t)
        page.locator("#residual-chart").screenshot(path=str(SHOTS / "residual-axis.png"))
        assert max(len(t.split(".")[1]) if "." in t else 0 for t in labels) >= 4, labels

        # the two other endings, in the page's own words (no such event in this run)
        reset = page.evaluate(
            "alarmText({source: 'well_test', direction: 'high', start: '2021-06-01T03:00:00+00:00',"
            " end: 'reset', closed: null}, 30)"
        )
        assert (
            reset == "well tests above the model from 2021-06-01 03:00 UTC: ended by a model change"
        )
        active = page.evaluate(
            "alarmText({source: 'mpfm', direction: 'low', start: '2021-06-01T03:00:00+00:00',"
            " end: null, closed: null}, 30)"
        )
        assert active == (
            "MPFM below the model since 2021-06-01 03:00 UTC "
            "(active; accepted as the new level if it lasts 30 periods)"
        )
        sized = page.evaluate(
            "alarmText({source: 'mpfm', direction: 'low', start: '2021-06-01T03:00:00+00:00',"
            " end: null, closed: null, shift: -0.0634}, 30)"
        )
        assert sized.startswith(
            "MPFM below the model (a shift of -6.3 %) since 2021-06-01 03:00 UTC"
        )
        # a small one (the service's event.small: under the meter's usual error before it)
        small = page.evaluate(
            "alarmText({source: 'mpfm', direction: 'high', start: '2021-06-01T03:00:00+00:00',"
            " end: '2021-06-09T03:00:00+00:00', closed: 'cleared', shift: 0.009,"
            " typical_error: 0.024, small: true}, 30)"
        )
        assert small.startswith(
            "MPFM above the model (a small shift of +0.9 %, under the usual error of 2.4 % "
            "before it) 2021-06-01 03:00 to 2021-06-09 03:00 UTC"
        ), small
        assert errors == [], errors
