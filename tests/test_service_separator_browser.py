"""The workbench's separator section in a real browser (Playwright driving Debian's chromium).

A service with its real HTTP server (inputs over the in-memory transport; model ``last``,
whose predictions are the latest measured rates) serves one separator of two wells; two
readings of its total arrive. The page's field view must show the separator with its
measured total against the sum of its wells' predictions and the residual, and a chart of
its readings, with no console error. Skipped as the other browser tests are when chromium
or Playwright is missing.
"""

from __future__ import annotations

import json
from datetime import UTC, datetime, timedelta
from pathlib import Path

import httpx
from browser_support import SHOTS, browser_marks, open_page

from replay.client import FieldClient, sample_of
from service.app import running
from service.engine.separators import reading_key
from service.testing import loopback_settings, wait_until
from service.transport import MemoryTransport
from vfm_core.messages import Measurement

pytestmark = browser_marks(120)

T0 = datetime(2020, 3, 1, 6, 0, tzinfo=UTC)
SAMPLE = (0.4, 120.0, 30.0, 60.0, 0.1, 0.6)  # fraction, bar a, bar a, degC, -, -


def test_the_page_shows_each_separators_total_against_its_wells(tmp_path: Path) -> None:
    settings = loopback_settings(
        tmp_path,
        model={"name": "last", "method": "ol"},
        separators={"members": {"SEP": ["W01", "W02"]}},
    )
    bus = MemoryTransport(settings.prefix)
    with running(settings, bus) as svc, FieldClient(bus, settings.prefix) as field:
        for well, rate in (("W01", 100.0), ("W02", 200.0)):
            field.send_measurement(well, "mpfm", Measurement(time=T0, q_total=rate))
        for k, total in ((1, 320.0), (2, 330.0)):  # two readings, each at the wells' samples
            at = T0 + timedelta(minutes=k)
            for well in ("W01", "W02"):
                field.send_sample(well, sample_of(at, SAMPLE))
            body = json.dumps({"time": at.isoformat(), "q_total": total})
            field.put_raw(reading_key(settings.prefix, "SEP"), body)
        with httpx.Client(base_url=svc.http_url, timeout=10) as http:
            wait_until(
                lambda: http.get("/separators/SEP").json()["readings"]["unused"] == 2,
                20,
                "the two readings",
            )
        with open_page() as (page, errors):
            page.goto(svc.http_url + "/")
            row = page.locator("#separators-table tbody tr[data-separator='SEP']")
            row.wait_for()
            cells = row.locator("td").all_inner_texts()
            assert cells[:2] == ["SEP", "W01, W02"]
            assert cells[3:7] == ["330", "300", "30", "9.09"]  # measured, sum, residual, %
            page.locator("#separator-charts canvas").first.wait_for()
            assert page.locator("#separator-charts .u-title").first.inner_text() == "SEP"
            page.locator("#separators").screenshot(path=str(SHOTS / "separators.png"))
            # no line across a stretch without readings (walk57: a two-month gap drawn
            # straight): a point of nulls where the spacing exceeds 3 times the median's
            broken = page.evaluate(
                "() => breakGaps([[0, 86400, 172800, 259200, 5443200, 5529600],"
                " [1, 2, 3, 4, 5, 6], [1, 2, 3, null, 5, 6]])"
            )
            assert broken == [
                [0, 86400, 172800, 259200, 2851200, 5443200, 5529600],
                [1, 2, 3, 4, None, 5, 6],
                [1, 2, 3, None, None, 5, 6],
            ], broken
            assert errors == []
