"""What the browser tests share: Debian's chromium driven by Playwright for Python.

Each browser test file marks itself with :func:`browser_marks` (skipped, with the reason,
where ``/usr/bin/chromium`` or the ``playwright`` package is missing; a failure instead
where CI sets ``VFM_REQUIRE_BROWSER=1``) and opens its page with :func:`open_page`, which
collects the page's errors (console errors too, unless ``console=False``). Screenshots go
to :data:`SHOTS` (``$VFM_SCREENSHOTS``, default ``tests/artifacts/``, ignored by git).
Never run ``playwright install``: it downloads a browser build of its own.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest

CHROMIUM = Path("/usr/bin/chromium")
try:
    from playwright.sync_api import Page, sync_playwright
except ImportError:  # pragma: no cover - depends on the machine
    Page = Any  # type: ignore[assignment,misc]
    sync_playwright = None  # type: ignore[assignment]

#: CI sets this: there, a missing browser is a failure, not a skip
REQUIRED = os.environ.get("VFM_REQUIRE_BROWSER") == "1"
SHOTS = Path(os.environ.get("VFM_SCREENSHOTS", Path(__file__).parent / "artifacts"))

__all__ = ["CHROMIUM", "REQUIRED", "SHOTS", "Page", "browser_marks", "open_page"]


def browser_marks(timeout_s: float) -> list[pytest.MarkDecorator]:
    """A browser test file's ``pytestmark``: its timeout and the two skips."""
    return [
        pytest.mark.timeout(timeout_s),
        pytest.mark.skipif(
            not REQUIRED and not CHROMIUM.exists(),
            reason="the browser tests need /usr/bin/chromium (apt-get install -y chromium)",
        ),
        pytest.mark.skipif(
            not REQUIRED and sync_playwright is None,
            reason="the browser tests need Playwright for Python (pip install -e '.[dev]')",
        ),
    ]


@contextmanager
def open_page(console: bool = True) -> Iterator[tuple[Page, list[str]]]:
    """A page of a headless chromium (1400 x 1000, 30 s default timeout) and the list its
    errors go to (uncaught exceptions; console errors too with ``console``)."""
    SHOTS.mkdir(parents=True, exist_ok=True)
    assert sync_playwright is not None
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=str(CHROMIUM), args=["--no-sandbox"])
        try:
            page = browser.new_page(viewport={"width": 1400, "height": 1000})
            errors: list[str] = []
            if console:
                page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
            page.on("pageerror", lambda e: errors.append(str(e)))
            page.set_default_timeout(30_000)
            yield page, errors
        finally:
            browser.close()
