"""Schemathesis against the real server: openapi.yaml is what the server does.

``schemathesis run`` in a subprocess against ``python -m service serve`` on a loopback port, with a
user's token, every check, a fixed seed and a time budget (the run stops after MAX_SECONDS). It found
the mismatches fixed with this test: a cursor the spec allowed and the server refused, ``since``
accepting a bare number the spec calls a date-time, an empty list of keypoint files the spec allowed,
a skeleton form field declared nullable (so "null" as text), and 405s whose Allow named one method.
The 422 of a well-formed submission whose files the readers refuse is expected
(tests/service/schemathesis.toml).
"""

from __future__ import annotations

import subprocess
import time
from pathlib import Path

import pytest
from servers import PY, ROOT, Server, add_user

pytest.importorskip("schemathesis", reason="the contract test needs schemathesis (pip install -e .[test])")

MAX_SECONDS = 50
CONFIG = Path(__file__).with_name("schemathesis.toml")


@pytest.mark.slow  # over 12 s here
def test_the_running_server_keeps_its_openapi_contract(tmp_path):
    data = tmp_path / "data"
    token = add_user(data, "sam")
    srv = Server(data, tmp_path / "server.log", workers=1, env={"ACINOSET_WARM_START": "0"}).start(ready=(200,))
    try:
        t0 = time.time()
        run = subprocess.run(
            [PY, "-m", "schemathesis.cli", "--config-file", str(CONFIG), "run", f"{srv.url}/openapi.json",
             "-H", f"Authorization: Bearer {token}", "--checks", "all", "--max-time", str(MAX_SECONDS),
             "--seed", "1", "--no-color", "--generation-database", "none", "--report-dir", str(tmp_path / "report"),
             "--wait-for-schema", "10", "--request-timeout", "30"],
            cwd=ROOT, capture_output=True, text=True, timeout=MAX_SECONDS + 120)
        took = time.time() - t0
        assert run.returncode == 0, run.stdout[-8000:] + run.stderr[-2000:]
        assert " passed" in run.stdout and "failed" not in run.stdout.split("SUMMARY")[-1], run.stdout[-3000:]
        assert took < MAX_SECONDS + 60
        log = srv.log()
        assert "Traceback" not in log and "unhandled error" not in log, log[-4000:]
    finally:
        srv.stop()
