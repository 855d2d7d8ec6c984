"""Headless Chromium for the report tests: where it is, how it starts, how a page opens.

``make test`` installs Chromium where it may (root with apt-get, scripts/setup_system.sh). There a
missing browser is a failure of the install, not a reason to skip the browser tests; elsewhere (a
developer's machine without root) the tests skip and say what to install.
"""

from __future__ import annotations

import contextlib
import os
import shutil
from collections.abc import Iterator
from pathlib import Path

import pytest

CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
HAVE_CHROMIUM = Path(CHROMIUM).exists()
ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
        "--disable-dev-shm-usage", "--no-first-run", "--disable-extensions"]
INSTALL_HINT = "apt-get install chromium, or run scripts/setup_system.sh"


def _installable() -> bool:
    return hasattr(os, "geteuid") and os.geteuid() == 0 and shutil.which("apt-get") is not None


def require_chromium() -> None:
    """Fail where the install step should have provided Chromium, skip elsewhere when it is missing."""
    if HAVE_CHROMIUM:
        return
    if _installable():
        pytest.fail(f"headless Chromium missing at {CHROMIUM} although this machine could install it: "
                    f"scripts/setup_system.sh did not run or failed ({INSTALL_HINT})")
    pytest.skip(f"headless Chromium not installed ({INSTALL_HINT})")


@contextlib.contextmanager
def launched() -> Iterator[object]:
    """A playwright Chromium browser on the system's Chromium (requires it, see :func:`require_chromium`)."""
    require_chromium()
    try:  # a dev dependency (make test installs it): missing is a broken install, not a reason to skip
        from playwright import sync_api
    except ImportError as e:
        pytest.fail(f"playwright missing from the test environment ({e}): pip install -e '.[dev]'")
    with sync_api.sync_playwright() as pw:
        b = pw.chromium.launch(executable_path=CHROMIUM, args=ARGS, headless=True)
        try:
            yield b
        finally:
            b.close()


def open_page(browser, path: Path, viewport: tuple[int, int] = (1400, 1000), wait_load: bool = False):  # noqa: ANN001, ANN201
    """The page at ``path`` once the report says it is ready, and the list of problems seen: console errors,
    page errors and any request that is not to a local file or data URI (the report is one offline file)."""
    page = browser.new_page(viewport={"width": viewport[0], "height": viewport[1]})
    problems: list[str] = []
    page.on("console", lambda m: problems.append(f"console {m.type}: {m.text}") if m.type == "error" else None)
    page.on("pageerror", lambda e: problems.append(f"page error: {e}"))
    page.on("request", lambda r: problems.append(f"request: {r.url}")
            if not r.url.startswith(("file:", "data:")) else None)
    page.goto(path.resolve().as_uri())
    page.wait_for_selector('body[data-ready="1"]', timeout=15000)
    if wait_load:
        page.wait_for_load_state("load")
    return page, problems
