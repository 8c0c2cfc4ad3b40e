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

DATA = Path(__file__).resolve().parents[1] / "data" / "acinoset_calib"


def _calibrate(base: str, token: str) -> str:
    files = [("detections", (f"points_cam{n}.json", (DATA / "Ex1_static" / f"points_cam{n}.json").read_bytes(),
                             "application/json")) for n in (3, 4)]
    files += [("intrinsics", (f"camera_{n}.json", (DATA / "intrinsic_calib_2021" / f"camera_{n}.json").read_bytes(),
                              "application/json")) for n in (3, 4)]
    r = httpx.post(f"{base}/v1/calibrations", files=files, headers={"Authorization": f"Bearer {token}"},
                   data={"board": "checkerboard:9x6:0.031", "options": json.dumps({"label": "static pair"})})
    assert r.status_code == 202, r.text
    return r.json()["id"]


def test_the_calibration_page_shows_quality_and_figures(page, server):
    from PIL import Image

    base, token = server
    cal_id = _calibrate(base, token)
    page.goto("/login")
    page.get_by_label("API token").fill(token)
    page.get_by_role("button", name="Sign in").click()
    page.wait_for_url(re.compile(r"/$"))
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
