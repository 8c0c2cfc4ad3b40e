"""A real server and a real browser for the page tests.

The server is ``python -m service serve`` on a free loopback port with its own data dir and one
user made with ``python -m service users add``; the browser is Debian's Chromium driven by
playwright, with no network beyond this machine.
"""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import pytest
from servers import PY, ROOT, Server, acinoset

CHROMIUM = os.environ.get("ACINOSET_TEST_CHROMIUM") or shutil.which("chromium") or "/usr/bin/chromium"

playwright_api = pytest.importorskip("playwright.sync_api", reason="the browser tests need the playwright package")
if not Path(CHROMIUM).exists():
    pytest.skip(f"the browser tests need Chromium ({CHROMIUM} not found; apt-get install chromium)",
                allow_module_level=True)


@pytest.fixture(scope="session")
def server(tmp_path_factory):
    """``(base_url, token)`` of a running server; stopped at the end of the session."""
    data = tmp_path_factory.mktemp("server-data")
    made = acinoset("users", "add", "biologist", "--data-dir", str(data))
    assert made.returncode == 0, made.stderr
    token = made.stdout.strip().splitlines()[-1].strip()
    srv = Server(data, data / "server.log", workers=1).start(ready=(200,))
    yield srv.url, token
    srv.stop(timeout=15)


@pytest.fixture(scope="session")
def simulated_run(tmp_path_factory) -> Path:
    """Six cameras' DeepLabCut CSVs and the calibration of a simulated run on the AcinoSet rig."""
    out = tmp_path_factory.mktemp("sim")
    done = subprocess.run([PY, "-m", "graph.app.cli", "simulate", "--frames", "60", "--seed", "5", "--out", str(out)],
                          cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    return out


@pytest.fixture(scope="session")
def browser():
    with playwright_api.sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, headless=True,
                              args=["--no-sandbox", "--disable-background-networking", "--disable-dev-shm-usage",
                                    "--disable-component-update", "--no-first-run"])
        yield b
        b.close()


@pytest.fixture
def page(browser, server):
    """A fresh browser context (empty localStorage) whose requests may go only to the test server."""
    base, _ = server
    ctx = browser.new_context(base_url=base, viewport={"width": 1280, "height": 900}, accept_downloads=True)
    outside: list[str] = []

    def guard(route):
        url = route.request.url
        if url.startswith(base) or url.startswith("blob:") or url.startswith("data:"):
            route.continue_()
        else:
            outside.append(url)
            route.abort()

    ctx.route("**/*", guard)
    pg = ctx.new_page()
    errors: list[str] = []
    pg.on("pageerror", lambda e: errors.append(str(e)))
    pg.outside_requests = outside
    pg.page_errors = errors
    yield pg
    ctx.close()
    assert not errors, f"JavaScript errors on the page: {errors}"
    assert not outside, f"the page tried to reach outside the server: {outside}"
