"""The result view of a long run, as the job service gives it (every k-th frame, ``frame_step`` k, at 1/k
of the frame rate): in a real browser its frames are named by the run's frame numbers and the summary
says how many it shows."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
from pathlib import Path

from graph.io.results import read_result
from graph.viewer.playback import playback_html

ROOT = Path(__file__).resolve().parents[2]
STEP = 3


def test_a_view_of_every_kth_frame_names_the_runs_frames(browser, simulated_run, tmp_path):
    cams = [str(simulated_run / f"cam{i}.csv") for i in range(1, 7)]
    h5 = tmp_path / "run.h5"
    solved = subprocess.run([sys.executable, "-m", "graph.app.cli", "solve", *cams, "--calibration",
                             str(simulated_run / "calibration.toml"), "--method", "tri", "--fps", "120", "--out",
                             str(tmp_path / "run.csv"), "--h5", str(h5)],
                            cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert solved.returncode == 0, solved.stderr
    view = read_result(h5, step=STEP)
    page = playback_html(dataclasses.replace(view, fps=view.fps / STEP))
    head, tail = page.split('id="payload">', 1)
    payload, rest = tail.split("</script>", 1)
    data = json.loads(payload)
    assert data["frames"] == 20 and data["report"]["frames"] == 60
    data["frame_step"] = STEP  # as service.run.worker.solve_streamed_job writes it
    html = tmp_path / "view.html"
    html.write_text(head + 'id="payload">' + json.dumps(data) + "</script>" + rest, encoding="utf-8")

    ctx = browser.new_context(viewport={"width": 1280, "height": 900}, offline=True)
    pg = ctx.new_page()
    errors: list[str] = []
    pg.on("pageerror", lambda e: errors.append(str(e)))
    pg.goto(html.as_uri())
    pg.locator("#result[data-ready=true]").wait_for(timeout=60_000)
    status = pg.get_by_test_id("frame-status")
    assert status.inner_text().startswith("Frame 0 of 59 (0.000 s)")
    pg.get_by_role("button", name="Next frame").click()
    assert status.inner_text().startswith("Frame 3 of 59 (0.025 s)"), status.inner_text()
    facts = pg.locator("dl.facts").inner_text()
    assert "60 at 120 fps" in facts and "one frame in 3 shown (20)" in facts, facts
    ctx.close()
    assert not errors, errors
