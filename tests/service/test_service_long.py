"""A long job (over ``window_frames``, or 4,000 frames) solved by a real embedded server as the command
solves it, streamed: the inputs staged a camera at a time, the CSV and H5 written as the windows finish.
The files are the ones the library's in-memory windows give, the report names the windows, and the page's
view holds the run (every frame of a run this short: ``frame_step`` 1)."""

from __future__ import annotations

import json
import re
import time
import warnings

import numpy as np
import pytest
from servers import Server, add_user, make_run, submit, wait_finished

from graph.api import solve
from graph.io.calibration import load_calibration
from graph.io.keypoints import read_keypoints
from graph.io.results import read_result, write_anipose_csv
from graph.types import SolveOptions

FRAMES = 1500
CORE = 500


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    return make_run(tmp_path_factory.mktemp("long_job"), frames=FRAMES, cameras=4, seed=3)


@pytest.fixture(scope="module")
def job(tmp_path_factory, run):
    data = tmp_path_factory.mktemp("long_job_data")
    token = add_user(data, "alice")
    srv = Server(data, data.parent / "long_job_server.log").start()
    try:
        with srv.client(token) as c:
            r = submit(c, run, {"method": "fte", "window_frames": CORE})
            assert r.status_code == 202, r.text
            said = set()  # the progress's words while it ran
            deadline = time.time() + 300
            while (j := c.get(f"/v1/jobs/{r.json()['id']}").json())["status"] in ("queued", "running"):
                assert time.time() < deadline, j
                said.add((j["progress"] or {}).get("detail"))
                time.sleep(0.05)
            done = wait_finished(c, r.json()["id"], timeout=10)
            assert done["status"] == "succeeded", done
            assert done["progress"]["detail"] is None  # the words were the run's
            yield c, done, data, said
    finally:
        srv.stop()


def test_a_long_job_is_solved_in_windows_as_the_library_solves_it(job, run, tmp_path):
    client, done, _, _ = job
    csv = client.get(done["links"]["result"]["csv"])
    assert csv.status_code == 200
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        whole = solve([read_keypoints(p) for p in run.cams], load_calibration(run.calibration),
                      SolveOptions(fps=run.fps, window_frames=CORE))
    write_anipose_csv(tmp_path / "library.csv", whole)
    assert csv.content == (tmp_path / "library.csv").read_bytes()

    h5 = tmp_path / "job.h5"
    h5.write_bytes(client.get(done["links"]["result"]["h5"]).content)
    res = read_result(h5)
    assert np.array_equal(res.positions, whole.positions, equal_nan=True)
    assert np.array_equal(res.std, whole.std, equal_nan=True)

    report = client.get(done["links"]["result"]["report"]).json()
    assert report["windows"]["count"] == FRAMES // CORE and report["frames"] == FRAMES
    # the server's second slot was free: a helper process came (test_service_embedded_windows.py says more)
    assert sum(report["windows"]["solved_by"].values()) == FRAMES // CORE
    assert sum(report["windows"]["staged_by"].values()) == len(run.cams)  # each camera staged once, between them
    for w in report["warnings"]:
        assert "/" not in w, f"a server path in a warning: {w}"


def test_a_long_jobs_progress_says_its_windows_done_and_the_time_left(job):
    said = job[3]
    windows = sorted(d for d in said if d and d.startswith("window "))
    assert windows, f"no window in the progress's words: {said}"
    n = FRAMES // CORE
    for d in windows:
        k = re.fullmatch(rf"window (\d+) of {n}, \d+ s left", d)
        assert k is not None and 1 <= int(k[1]) <= n, windows


def test_the_page_view_of_a_long_job(job):
    client, done, _, _ = job
    view = client.get(done["links"]["result"]["json"])
    assert view.status_code == 200
    payload = json.loads(view.content)
    assert payload["frame_step"] == 1 and payload["frames"] == FRAMES and len(payload["positions"]) == FRAMES
    assert payload["report"]["windows"]["core_frames"] == CORE


def test_the_page_view_of_a_longer_job_holds_every_kth_frame(job, monkeypatch, tmp_path):
    """Over :data:`service.run.worker.PAGE_FRAMES` frames (here set to 700: every 3rd of 1500), the page's
    view holds every k-th frame of the run at 1/k of its frame rate, and says k (``frame_step``)."""
    from service.run import worker
    from service.settings import Settings
    from service.store.jobfiles import INPUT, job_dir

    _, done, data, _ = job
    monkeypatch.setattr(worker, "PAGE_FRAMES", 700)
    input_dir = job_dir(Settings(data_dir=data).jobs_dir, done["id"]) / INPUT
    report = worker.solve_streamed_job(input_dir, tmp_path, worker.ThrottledProgress(lambda *a: True, 1.0))
    assert report is not None and report["frames"] == FRAMES
    payload = json.loads((tmp_path / "result.json").read_text())
    assert payload["frame_step"] == 3 and payload["frames"] == FRAMES // 3
    assert payload["fps"] == pytest.approx(done["options"]["fps"] / 3)
    full = read_result(tmp_path / "result.h5")
    assert np.allclose(np.array(payload["positions"][1], dtype=float), full.positions[3], atol=1e-4, equal_nan=True)
