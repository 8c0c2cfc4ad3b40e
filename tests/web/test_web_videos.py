"""The job page's videos in a real browser: a job submitted with its cameras' videos plays its
labelled video, the 3D playback's Play button plays it too, the frame slider seeks it to the same
frame, and the frame picker shows one camera's frame as drawn by the server."""

from __future__ import annotations

import re
import time

import httpx
import pytest
from servers import make_filmed_run, submit_with_videos, wait_finished

pytest.importorskip("imageio_ffmpeg", reason="videos need the video extra")

FRAMES = 30
# one video frame as pixels on a canvas: what the browser decoded at its current time
GRAB = """(v) => { const c = document.createElement('canvas');
  c.width = v.videoWidth; c.height = v.videoHeight; const g = c.getContext('2d'); g.drawImage(v, 0, 0);
  return Array.from(g.getImageData(0, 0, c.width, c.height).data); }"""


@pytest.fixture(scope="module")
def video_job(server, tmp_path_factory):
    base, token = server
    run, videos = make_filmed_run(tmp_path_factory.mktemp("filmed"), FRAMES)
    with httpx.Client(base_url=base, headers={"Authorization": f"Bearer {token}"}, timeout=60) as c:
        r = submit_with_videos(c, run, videos=videos)
        assert r.status_code == 202, r.text
        done = wait_finished(c, r.json()["id"], timeout=300)
    assert done["status"] == "succeeded", done
    return done, run


def _until(page, predicate: str, timeout: float = 15.0) -> None:
    """Poll ``predicate`` (a JavaScript function of no arguments) until it is true: the page's CSP
    forbids the string evaluation wait_for_function does for a function given as text."""
    deadline = time.time() + timeout
    while not page.evaluate(predicate):
        if time.time() > deadline:
            raise AssertionError(f"not true after {timeout} s: {predicate}")
        time.sleep(0.05)


VIDEO = "document.querySelector('[data-testid=job-video]')"


def _sign_in(page, token: str) -> None:
    page.goto("/login")
    page.get_by_label("API token").fill(token)
    page.get_by_role("button", name="Sign in").click()
    page.wait_for_url(re.compile(r"/$"))


@pytest.mark.slow  # over 12 s here
def test_the_job_video_plays_and_follows_the_slider(page, server, video_job):
    import numpy as np

    _, token = server
    job, run = video_job
    _sign_in(page, token)
    page.goto(f"/jobs/{job['id']}")
    page.locator("#result[data-ready=true]").wait_for(timeout=60_000)
    video = page.get_by_test_id("job-video")
    video.wait_for()
    _until(page, f"() => {VIDEO}.readyState >= 2", 30)
    assert video.get_attribute("data-view") == "1"
    assert abs(video.evaluate("v => v.duration") - FRAMES / run.fps) < 2 / run.fps

    # The 3D view's Play button plays the video; Pause stops both.
    page.get_by_role("button", name="▶ Play").click()
    _until(page, f"() => !{VIDEO}.paused && {VIDEO}.currentTime > 0.2")
    page.get_by_role("button", name="❚❚ Pause").click()
    _until(page, f"() => {VIDEO}.paused")

    # Moving the slider seeks the video to that frame's time, and the picture changes.
    slider = page.get_by_label("Frame", exact=True)
    frames = {}
    for n in (3, 25):
        slider.fill(str(n))
        _until(page, f"() => !{VIDEO}.seeking && Math.abs({VIDEO}.currentTime - {(n + 0.5) / run.fps}) < 1e-3 "
                     f"&& {VIDEO}.readyState >= 2")
        page.wait_for_timeout(100)
        frames[n] = np.array(video.evaluate(GRAB), dtype=np.int16)
    assert frames[3].size > 0
    assert (np.abs(frames[3] - frames[25]) > 40).mean() > 0.005, "the video shows the same picture at frames 3 and 25"
    assert page.get_by_test_id("plot3d").get_attribute("data-frame") == "25"

    # Seeking the video itself moves the slider.
    video.evaluate(f"v => {{ v.currentTime = {(12 + 0.5) / run.fps}; }}")
    _until(page, "() => document.querySelector('[data-testid=plot3d]').dataset.frame === '12'")

    # The other videos are offered: each camera, the 3D view and the grid.
    options = page.locator("#video-view option").all_inner_texts()
    assert len(options) == 5 and options[-2:] == ["3D view", "All views (grid)"]
    page.locator("#video-view").select_option("combined")
    _until(page, f"() => {VIDEO}.dataset.view === 'combined' && {VIDEO}.readyState >= 2 && !{VIDEO}.seeking")
    assert abs(video.evaluate("v => v.currentTime") - 12.5 / run.fps) < 1e-3

    # The frame picker: camera 2's frame 12 drawn by the server.
    page.locator("#picker-camera").select_option("2")
    page.get_by_role("button", name="Slider's frame").click()
    assert page.locator("#picker-frame").input_value() == "12"
    page.get_by_test_id("picker-show").click()
    _until(page, "() => { const i = document.querySelector('[data-testid=picker-image]');"
                 " return !i.hidden && i.complete && i.naturalWidth > 0; }", 20)
    assert page.get_by_test_id("picker-image").evaluate("i => [i.naturalWidth, i.naturalHeight]") == [270, 152]


def test_the_form_sends_the_videos_in_camera_order(page, server, video_job, tmp_path):
    """The submit form takes one video per camera (matched by name order, whatever order they were
    chosen in) and refuses a count that does not match the keypoint files."""
    _, token = server
    _, run = video_job
    videos = sorted(run.dir.glob("cam*.mp4"))
    _sign_in(page, token)
    page.goto("/jobs/new")
    page.get_by_label("Keypoint files, one per camera").set_input_files([str(p) for p in run.cams])
    page.get_by_label("Calibration file").set_input_files(str(run.calibration))
    page.get_by_role("radio", name=re.compile("^tri:")).check()
    page.get_by_label("Frame rate (frames per second)").fill(str(run.fps))
    page.get_by_label("Videos (optional)").set_input_files([str(videos[1]), str(videos[0])])
    page.get_by_role("button", name="Submit job").click()
    assert "2 videos for 3 keypoint files" in page.get_by_role("alert").first.inner_text()
    page.get_by_label("Videos (optional)").set_input_files([str(videos[2]), str(videos[0]), str(videos[1])])
    page.get_by_role("button", name="Submit job").click()
    page.wait_for_url(re.compile(r"/jobs/[0-9a-f]{32}$"))
    job_id = page.url.rsplit("/", 1)[1]
    base, _ = server
    with httpx.Client(base_url=base, headers={"Authorization": f"Bearer {token}"}, timeout=60) as c:
        job = c.get(f"/v1/jobs/{job_id}").json()
    assert [v["name"] for v in job["inputs"]["videos"]] == ["cam1.mp4", "cam2.mp4", "cam3.mp4"]
