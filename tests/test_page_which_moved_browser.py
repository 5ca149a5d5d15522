"""The workbench names which meter moved beside a residual alarm on the MPFM's stream, in a
real browser (Playwright driving Debian's chromium).

The well of :mod:`test_service_which_moved` (``mm`` fitted once, two MPFM readings a day and a
well test a week): its MPFM reads 12 % high from day 70 while the well tests stay. The
well's alarm line must carry the residual alarm and, after it, ``which_moved``'s sentence
("... the meter moved, not the well"), as ``GET /wells/{well}`` gives it.

Screenshots go to ``$VFM_SCREENSHOTS`` (default ``tests/artifacts/``, ignored by git).
Skipped, with the reason, when ``/usr/bin/chromium`` or the ``playwright`` package is
missing (CI sets ``VFM_REQUIRE_BROWSER=1``: there a missing browser fails).
"""

from __future__ import annotations

from pathlib import Path

import httpx
from alarm_support import fixed_model_service
from browser_support import SHOTS, browser_marks, open_page
from test_service_which_moved import STEP_DAY, send_field, wait_learned_all

pytestmark = browser_marks(180)


def test_the_page_says_the_meter_moved(tmp_path: Path) -> None:
    with (
        fixed_model_service(tmp_path, http=True) as (service, client),
        open_page() as (page, errors),
    ):
        wait_learned_all(service, send_field(client, meter_moved=True, seed=3))
        view = httpx.get(service.http_url + "/wells/W01", timeout=30).json()
        moved = view["residual_alarm"]["which_moved"]
        assert moved["moved"] == "meter", moved
        page.goto(service.http_url + "/#well=W01")
        line = page.locator("#well-alarms")
        line.wait_for()
        page.wait_for_function(
            "document.querySelector('#well-alarms').textContent.includes('the meter moved')"
        )
        text = line.inner_text()
        since = view["residual_alarm"]["since"][:10]
        by = f"(a shift of {100 * view['residual_alarm']['shift']:+.1f} %)"  # its size
        onset = view["residual_alarm"]["onset"][:10]  # the change began before the raise
        began = f" (the change began about {onset})" if onset < since else ""
        line_text = (
            f"residual alarm: MPFM above the model {by} since {since}{began}; {moved['text']}"
        )
        assert line_text in text
        page.screenshot(path=str(SHOTS / "which-moved.png"))
        assert not errors, errors


def test_before_the_next_well_test_the_page_says_when_it_is_due(tmp_path: Path) -> None:
    """The data stop three days after the step, before the next well test: the alarm line
    says that the next well test tells which moved, and when it is due."""
    with (
        fixed_model_service(tmp_path, http=True) as (service, client),
        open_page() as (page, errors),
    ):
        wait_learned_all(service, send_field(client, True, seed=3, days=STEP_DAY + 3))
        view = httpx.get(service.http_url + "/wells/W01", timeout=30).json()
        waiting = view["residual_alarm"]["awaiting_well_test"]
        assert waiting is not None and waiting["due"].startswith("2021-07-13"), waiting
        page.goto(service.http_url + "/#well=W01")
        page.locator("#well-alarms").wait_for()
        page.wait_for_function(
            "document.querySelector('#well-alarms').textContent.includes('due about 2021-07-13')"
        )
        text = page.locator("#well-alarms").inner_text()
        assert waiting["text"] in text and "the meter moved" not in text
        page.screenshot(path=str(SHOTS / "which-moved-awaiting.png"))
        assert not errors, errors
