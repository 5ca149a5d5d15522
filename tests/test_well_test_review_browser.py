"""Well tests held for review on the workbench page, in a real browser (Playwright driving
Debian's chromium): the held well test is listed under the rate chart with its rate, the
model's and z, the field view and the well's alarms say one is held, and its accept button
(with the token typed at the top) learns it: the list empties and the version goes up.

The service runs ``last`` + ``ol`` (the latest learned rate) on daily MPFM readings around
1000 Sm3/h (2 % noise, seeded); the well test is 30 % below, with no MPFM reading within 24 h.
Skipped, with the reason, when ``/usr/bin/chromium`` or ``playwright`` is missing (CI sets
``VFM_REQUIRE_BROWSER=1``: there a missing browser fails).
"""

from __future__ import annotations

import math
from datetime import UTC, datetime, timedelta
from pathlib import Path

import httpx
import numpy as np
from browser_support import SHOTS, browser_marks, open_page

from replay.client import FieldClient, sample_of
from service.app import running
from service.testing import loopback_settings, wait_until
from service.transport import MemoryTransport
from vfm_core.messages import Measurement
from vfm_core.timeutil import iso, to_ns

pytestmark = browser_marks(180)

T0 = datetime(2022, 2, 1, 6, 0, tzinfo=UTC)
INPUTS = (0.4, 120.0, 30.0, 60.0, 0.1, 0.6)  # fraction, bar a, bar a, degC, -, -
TOKEN = "review-browser-token-0123456789"


def test_a_held_well_test_is_listed_and_accepted_on_the_page(tmp_path: Path) -> None:
    settings = loopback_settings(
        tmp_path, model={"name": "last", "method": "ol"}, http={"token": TOKEN}
    )
    bus = MemoryTransport(settings.prefix)
    rng = np.random.default_rng(31)
    with (
        running(settings, bus) as svc,
        httpx.Client(base_url=svc.http_url, timeout=60) as http,
        FieldClient(bus, settings.prefix) as client,
    ):
        client.wait_for_service("W01")
        times = [T0 + timedelta(days=i) for i in range(20)]
        for t in times:
            client.send_sample("W01", sample_of(t, INPUTS))
            q = 1000.0 * math.exp(0.02 * float(rng.standard_normal()))
            client.send_measurement("W01", "mpfm", Measurement(time=t, q_total=q))
        when = times[-1] + timedelta(days=2)
        client.send_sample("W01", sample_of(when, INPUTS))
        level = client.wait_for_prediction("W01", when)
        wait_until(lambda: http.get("/wells/W01").json()["version"] == 20, 30, "the readings")
        posted = http.post(
            "/wells/W01/well-tests",
            json={"time": iso(to_ns(when)), "q_total": 0.7 * level},
            headers={"Authorization": f"Bearer {TOKEN}"},
        )
        assert posted.status_code == 202 and posted.json()["status"] == "review", posted.text

        with open_page(console=False) as (page, errors):
            page.goto(svc.http_url + "/#well=W01")
            item = page.locator(f'#well-review li[data-time="{iso(to_ns(when))}"]')
            item.wait_for()
            text = item.inner_text()
            assert f"{0.7 * level:.0f} Sm3/h" in text and f"model {level:.0f} Sm3/h" in text, text
            assert "MPFM none near" in text
            alarms = page.locator("#well-alarms").inner_text()
            assert "1 well test(s) held for review" in alarms
            # held is stored, not refused: counted apart from the refused inputs, as a note
            # (a count since the start, in grey), not as an alarm
            notes = page.locator("#well-notes").inner_text()
            assert "held since the service started (stored, not learned): held for review (1)" in (
                notes
            )
            assert "held since" not in alarms and "refused" not in alarms + notes, alarms
            # the field view: the count in grey under the well's alarms, not among them
            page.goto(svc.http_url + "/")
            note = page.locator('#field-table tr[data-well="W01"] .note')
            note.wait_for()
            assert "held for review (1)" in note.inner_text()
            cell = note.locator("xpath=..").inner_text()
            assert cell.index("1 well test(s) held for review") < cell.index("held since"), cell
            page.goto(svc.http_url + "/#well=W01")
            item.wait_for()
            # nor the page's banner of refused inputs (the service refused nothing here)
            assert page.locator("#banner").is_hidden()
            page.screenshot(path=str(SHOTS / "well-test-review.png"), full_page=True)
            # without the token the page says so and sends nothing
            item.locator('button[data-decision="accept"]').click()
            assert "API token" in page.locator("#review-result").inner_text()
            assert http.get("/wells/W01").json()["held_for_review"] != []
            page.fill("#token", TOKEN)
            item.locator('button[data-decision="accept"]').click()
            page.wait_for_function(
                "document.querySelector('#review-result').textContent.startsWith('Accepted')"
            )
            assert "version 20 \u2192 21" in page.locator("#review-result").inner_text()
            page.wait_for_selector("#well-review", state="hidden")
        view = http.get("/wells/W01").json()
        assert view["held_for_review"] == [] and view["version"] == 21
        assert not errors, errors
