"""A real browser for the console tests: Debian's Chromium driven by Playwright for Python.

Playwright cannot download its own browser here, so it is pointed at the system's Chromium
(`tests/ensure_browser.sh`, run by `make test`, installs it). A missing browser or driver fails the
test with what to do: a console test that skips would prove nothing on a machine without one.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import pytest

CANDIDATES = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")


def chromium_path() -> str:
    """The browser to drive: ``GEOMATCH_CHROMIUM`` when set, else the first Chromium on PATH."""
    given = os.environ.get("GEOMATCH_CHROMIUM")
    if given:
        if not Path(given).is_file():
            pytest.fail(f"GEOMATCH_CHROMIUM={given} is not a file")
        return given
    for name in CANDIDATES:
        found = shutil.which(name)
        if found:
            return found
    pytest.fail(
        "no Chromium found (looked for chromium, chromium-browser, google-chrome on PATH): the web "
        "console's tests need a real browser. Install it with `tests/ensure_browser.sh` (apt-get "
        "install chromium; `make test` runs it), or set GEOMATCH_CHROMIUM to a Chromium binary."
    )


def require_playwright() -> None:
    try:
        import playwright.sync_api  # noqa: F401
    except ImportError as e:
        pytest.fail(f"Playwright for Python is not installed ({e}): pip install -e '.[dev]'")
