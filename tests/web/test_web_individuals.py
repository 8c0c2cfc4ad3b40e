"""A job of two animals in a real browser: the job page says who is who and how many 2D identity
switches were corrected, draws the first individual and then the one picked, and downloads each
one's files under their own names."""

from __future__ import annotations

import json
import re

import httpx
from group_files import write_dlc_multi
from test_web_pages import SOLVE_TIMEOUT_MS, _sign_in

from graph.io.calibration import write_anipose_toml
from graph.simulate import ring_rig
from graph.simulate_group import simulate_group


def test_the_job_page_of_two_animals(page, server, tmp_path):
    base, token = server
    rig = ring_rig(4)
    run = simulate_group(rig, animals=2, frames=120, seed=12)
    write_anipose_toml(tmp_path / "calibration.toml", rig)
    cams = [write_dlc_multi(tmp_path / f"cam{c + 1}.csv", t, ["dam", "cub"]) for c, t in enumerate(run.tracks)]
    files = [("keypoints", (p.name, p.read_bytes(), "text/csv")) for p in cams]
    files.append(("calibration", ("calibration.toml", (tmp_path / "calibration.toml").read_bytes(), "text/plain")))
    r = httpx.post(f"{base}/v1/jobs", headers={"Authorization": f"Bearer {token}"}, files=files,
                   data={"options": json.dumps({"method": "tri", "skeleton": "points", "fps": 60})}, timeout=60)
    assert r.status_code == 202, r.text
    job_id = r.json()["id"]

    _sign_in(page, token)
    page.goto(f"/jobs/{job_id}")
    page.locator("#job-status [data-status=succeeded]").wait_for(timeout=SOLVE_TIMEOUT_MS)
    page.locator("#result[data-ready=true]").wait_for(timeout=60_000)
    who = page.locator("dt", has_text="Individuals").locator("xpath=following-sibling::dd[1]").inner_text()
    assert who == "cub, dam (found in the files)", who
    switches = page.locator("dt", has_text="2D identity switches corrected").locator(
        "xpath=following-sibling::dd[1]").inner_text()
    assert re.fullmatch(r"cam1 \d+, cam2 \d+, cam3 \d+, cam4 \d+", switches), switches

    # at first every individual in one 3D view, each one's bones in a colour of its own
    names = page.evaluate("() => Array.from(document.querySelectorAll('.js-plotly-plot')).flatMap("
                          "(p) => (p.data || []).map((t) => t.name))")
    assert "bones, dam" in names and "bones, cub" in names and "bones, left side" not in names, names
    colors = page.evaluate("() => Array.from(document.querySelectorAll('.js-plotly-plot')).flatMap((p) => (p.data"
                           " || []).filter((t) => (t.name || '').startsWith('bones, ')).map((t) => t.line.color))")
    assert len(set(colors)) == 2, colors

    with page.expect_response(lambda resp: "individual=dam" in resp.url and "format=json" in resp.url) as got:
        page.get_by_label("Individual to draw").select_option("dam")
    assert got.value.status == 200
    page.locator("#result[data-ready=true]").wait_for(timeout=60_000)

    group = page.locator(".individual-downloads[data-individual=dam]")
    assert group.locator("h3").inner_text() == "dam"
    with page.expect_download() as dl:
        group.get_by_role("button", name=re.compile(r"^Download CSV")).click()
    assert dl.value.suggested_filename == f"{job_id}.dam.csv"
    header = open(dl.value.path(), encoding="utf-8").readline().split(",")
    assert {"nose_x", "tail_tip_z", "fnum\n"} <= set(header)
    with page.expect_download() as dl:
        page.locator("#download-buttons > button[data-format=report]").click()
    assert dl.value.suggested_filename == f"{job_id}.report.json"
    assert set(json.loads(open(dl.value.path(), encoding="utf-8").read())["individuals"]) == {"cub", "dam"}
    assert not page.page_errors and not page.outside_requests
