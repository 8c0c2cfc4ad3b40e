"""The calibration page in a real browser: a calibration of AcinoSet's Ex1 pair, submitted through
the API, shows its status, its quality per camera and its three figures, drawn (under the
Content-Security-Policy: the figures come with the token, as blob: images)."""

from __future__ import annotations

import io
import json
import re
from pathlib import Path

import httpx
import numpy as np
from shared_data import ACINOSET_CALIB

DATA = ACINOSET_CALIB


def _calibrate(base: str, token: str) -> str:
    files = [("detections", (f"points_cam{n}.json", (DATA / "Ex1_static" / f"points_cam{n}.json").read_bytes(),
                             "application/json")) for n in (3, 4)]
    files += [("intrinsics", (f"camera_{n}.json", (DATA / "intrinsic_calib_2021" / f"camera_{n}.json").read_bytes(),
                              "application/json")) for n in (3, 4)]
    r = httpx.post(f"{base}/v1/calibrations", files=files, headers={"Authorization": f"Bearer {token}"},
                   data={"board": "checkerboard:9x6:0.031", "options": json.dumps({"label": "static pair"})})
    assert r.status_code == 202, r.text
    return r.json()["id"]


def sign_in(page, token: str) -> None:
    page.goto("/login")
    page.get_by_label("API token").fill(token)
    page.get_by_role("button", name="Sign in").click()
    page.wait_for_url(re.compile(r"/$"))


def test_the_calibration_page_shows_quality_and_figures(page, server):
    from PIL import Image

    base, token = server
    cal_id = _calibrate(base, token)
    sign_in(page, token)
    page.goto(f"/calibrations/{cal_id}")
    page.locator("body[data-ready=true]").wait_for(timeout=240_000)
    assert page.locator("#cal-status [data-status=succeeded]").count() == 1
    assert "succeeded" in page.locator("#cal-status").inner_text()
    rows = page.locator("#cal-cameras tr")
    assert rows.count() == 2 and rows.nth(0).locator("th").inner_text() == "cam1"
    baselines = page.locator("dt", has_text="Baselines").locator("xpath=following-sibling::dd[1]").inner_text()
    assert re.search(r"cam1-cam2: 0\.39\d\d m", baselines), baselines
    figures = page.locator("#figure-list figure img")
    assert figures.count() == 3
    for k in range(3):
        img = figures.nth(k)
        assert img.get_attribute("src").startswith("blob:") and img.get_attribute("alt")
        assert img.evaluate("i => i.complete && i.naturalWidth > 300")
        drawn = np.asarray(Image.open(io.BytesIO(img.screenshot())).convert("L"))
        assert (drawn < 200).mean() > 0.01  # something is drawn, not a blank box
    assert page.get_by_role("button", name=re.compile(r"^Download calibration\.toml")).is_visible()


def test_calibrate_on_the_form_then_solve_with_it(page, server, simulated_run, tmp_path):
    """The calibration form sends the board and each camera's detections in camera order; the list
    shows the result, and its "use in a new job" link preselects it on the job form, which sends it
    as calibration_id (the server then checks the keypoints against that two-camera rig)."""
    from playwright.sync_api import expect

    base, token = server
    sign_in(page, token)
    page.get_by_role("link", name="Calibrations", exact=True).click()
    page.get_by_role("link", name="New calibration").click()
    page.wait_for_url(re.compile(r"/calibrations/new$"))
    assert page.locator("#board-spec").inner_text() == "checkerboard:9x6:0.031"  # the defaults: Ex1's board
    page.get_by_label("Detection files, one per camera").set_input_files(
        [str(DATA / "Ex1_static" / f"points_cam{n}.json") for n in (4, 3)])  # numeric order: cam3 first
    assert page.locator("#view-list li").nth(0).inner_text().startswith("camera 1")
    assert "points_cam3.json" in page.locator("#view-list li").nth(0).inner_text()
    page.get_by_label("Intrinsics (optional), one file per camera").set_input_files(
        [str(DATA / "intrinsic_calib_2021" / f"camera_{n}.json") for n in (3, 4)])
    page.get_by_label("Label (optional)").fill("pair from the form")
    page.get_by_role("button", name="Calibrate").click()
    page.wait_for_url(re.compile(r"/calibrations/[0-9a-f]{32}$"))
    cal_id = page.url.rsplit("/", 1)[1]
    page.locator("body[data-ready=true]").wait_for(timeout=240_000)
    assert page.locator("#cal-status [data-status=succeeded]").count() == 1
    facts = page.locator("#cal-facts").inner_text()
    assert "checkerboard:9x6:0.031" in facts and "pair from the form" in facts
    assert "camera 1: points_cam3.json" in facts and "camera 2: points_cam4.json" in facts

    page.get_by_role("link", name="All calibrations").click()
    row = page.locator(f"tr[data-calibration='{cal_id}']")
    row.wait_for()
    assert row.get_attribute("data-status") == "succeeded" and "pair from the form" in row.inner_text()
    assert re.search(r"RMS \d+\.\d\d px", row.inner_text())
    row.get_by_role("link", name=re.compile("Use calibration .* in a new job")).click()
    page.wait_for_url(re.compile(rf"/jobs/new\?calibration={cal_id}$"))
    picker = page.get_by_label("or a calibration made on this server")
    expect(picker).to_have_value(cal_id)
    assert "pair from the form" in picker.locator("option:checked").inner_text()
    page.get_by_label("Keypoint files, one per camera").set_input_files(
        [str(simulated_run / f"cam{i}.csv") for i in range(1, 7)])
    page.get_by_label("Calibration file").set_input_files(str(simulated_run / "calibration.toml"))
    page.get_by_role("button", name="Submit job").click()
    assert "not both" in page.locator("#submit-error").inner_text()
    page.get_by_label("Calibration file").set_input_files([])
    page.get_by_role("button", name="Submit job").click()
    alert = page.locator("#submit-error")
    expect(alert).to_contain_text("keypoint files", timeout=60_000)
    assert "2 cameras" in alert.inner_text() and "6 keypoint files" in alert.inner_text(), alert.inner_text()
    assert page.url.endswith(f"/jobs/new?calibration={cal_id}")

    # two cameras' points that fit the rig: the job solves with it, and its page links back to it
    pair = _points_seen_by(base, token, cal_id, tmp_path)
    page.goto(f"/jobs/new?calibration={cal_id}")
    expect(picker).to_have_value(cal_id)
    page.get_by_label("Keypoint files, one per camera").set_input_files([str(p) for p in pair])
    page.get_by_role("radio", name=re.compile("^tri:")).check()
    page.get_by_label("Skeleton", exact=True).select_option("points")
    page.get_by_role("button", name="Submit job").click()
    page.wait_for_url(re.compile(r"/jobs/[0-9a-f]{32}$"))
    link = page.locator("#job-facts a", has_text=f"calibration {cal_id[:8]}")
    expect(link).to_have_attribute("href", f"/calibrations/{cal_id}")
    assert page.page_errors == []


def _points_seen_by(base: str, token: str, cal_id: str, tmp: Path) -> list[Path]:
    """Two DeepLabCut CSVs of points 2-3 m in front of calibration ``cal_id``'s pair, projected
    through the rig the server made (1 px noise)."""
    from graph.io.calibration import load_calibration
    from graph.io.keypoints import Keypoints, write_dlc_csv

    r = httpx.get(f"{base}/v1/calibrations/{cal_id}/calibration.toml", headers={"Authorization": f"Bearer {token}"})
    assert r.status_code == 200, r.text
    (tmp / "pair.toml").write_bytes(r.content)
    cal = load_calibration(tmp / "pair.toml")
    rng = np.random.default_rng(5)
    c0 = cal.cameras[0]
    truth = c0.center + 2.5 * c0.R[2] + rng.uniform(-0.3, 0.3, size=(20, 3, 3))
    out = []
    for cam, name in zip(cal.cameras, cal.names):
        uv = cam.project(truth) + rng.normal(0, 1.0, size=truth.shape[:2] + (2,))
        out.append(tmp / f"{name}.csv")
        write_dlc_csv(out[-1], Keypoints([f"p{i}" for i in range(3)], uv, np.ones(truth.shape[:2])))
    return out


def test_the_calibration_form_says_why_the_server_refused(page, server):
    """A board the server refuses (a square checkerboard has no orientation) is named on the form in
    one line, and no calibration is made."""
    from playwright.sync_api import expect

    base, token = server
    sign_in(page, token)
    page.goto("/calibrations/new")
    before = httpx.get(f"{base}/v1/calibrations", headers={"Authorization": f"Bearer {token}"}).json()["total"]
    page.get_by_label("Inner corners down").fill("9")
    assert page.locator("#board-spec").inner_text() == "checkerboard:9x9:0.031"
    page.get_by_label("Detection files, one per camera").set_input_files(
        [str(DATA / "Ex1_static" / f"points_cam{n}.json") for n in (3, 4)])
    page.get_by_role("button", name="Calibrate").click()
    alert = page.locator("#submit-error")
    expect(alert).to_contain_text("square checkerboard", timeout=60_000)
    assert alert.inner_text().startswith("The calibration was not submitted:") and "\n" not in alert.inner_text()
    assert page.url.endswith("/calibrations/new")
    after = httpx.get(f"{base}/v1/calibrations", headers={"Authorization": f"Bearer {token}"}).json()["total"]
    assert after == before


def test_a_refinement_page_shows_each_cameras_change(page, server):
    """A refinement of SLEAP's shipped rig from its own job's keypoints: the page says the rig was
    refined, lists each camera's leave-one-out error before and after and which camera was posed
    again (side), and draws the cameras before and after."""
    from PIL import Image
    from shared_data import SLEAP_MINIMAL

    base, token = server
    auth = {"Authorization": f"Bearer {token}"}
    cams = ("back", "mid", "side", "top")
    files = [("keypoints", (f"{c}.slp", (SLEAP_MINIMAL / c / f"minimal_{c}_proofread.slp").read_bytes(),
                            "application/octet-stream")) for c in cams]
    files.append(("calibration", ("calibration.toml", (SLEAP_MINIMAL / "calibration.toml").read_bytes(), "text/plain")))
    r = httpx.post(f"{base}/v1/jobs", files=files, headers=auth,
                   data={"options": json.dumps({"method": "tri", "skeleton": "points", "fps": 30})})
    assert r.status_code == 202, r.text
    r = httpx.post(f"{base}/v1/jobs/{r.json()['id']}/refinement", headers=auth,
                   data={"options": json.dumps({"likelihood": 0.01})})
    assert r.status_code == 202, r.text
    sign_in(page, token)
    page.goto(f"/calibrations/{r.json()['id']}")
    page.locator("body[data-ready=true]").wait_for(timeout=240_000)
    assert page.locator("#cal-status [data-status=succeeded]").count() == 1
    verdict = page.locator("dt", has_text="Verdict").locator("xpath=following-sibling::dd[1]").inner_text()
    assert verdict.startswith("refined"), verdict
    assert "posed again" in page.locator("#cal-head").inner_text()
    rows = page.locator("#cal-cameras tr")
    assert rows.count() == 4 and rows.nth(2).locator("th").inner_text() == "side"
    posed_again = [rows.nth(k).locator("td").nth(5).inner_text() for k in range(4)]
    assert posed_again == ["no", "no", "yes", "no"], posed_again
    assert rows.nth(1).locator("td").last.inner_text() == "yes"  # mid held where it was
    before, after = (float(rows.nth(2).locator("td").nth(k).inner_text()) for k in (0, 1))
    assert before > 80 and after < 20, (before, after)
    assert "side was off" in page.locator("#cal-alert").inner_text()
    img = page.locator("#figure-list figure img")
    assert img.count() == 1 and img.evaluate("i => i.complete && i.naturalWidth > 300")
    drawn = np.asarray(Image.open(io.BytesIO(img.screenshot())).convert("L"))
    assert (drawn < 200).mean() > 0.01
