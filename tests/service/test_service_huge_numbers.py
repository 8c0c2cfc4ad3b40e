"""Numbers no reader foresaw, sent to a real server (security issue 25: each was a 500, 'internal
error'): integers of hundreds or thousands of digits, Infinity, text where a number belongs, arrays
nested 100,000 deep. Each must be a 422 whose one-line detail names the field or the file."""

from __future__ import annotations

import json
import re

import pytest
from servers import Server, add_user, make_run

BIG = "1" + "0" * 400  # beyond any float
HUGE = "1" + "0" * 5000  # beyond Python's 4300-digit limit for int(str)
DEEP = "[" * 100_000 + "]" * 100_000


@pytest.fixture(scope="module")
def client(tmp_path_factory):
    base = tmp_path_factory.mktemp("huge")
    run = make_run(base / "run", frames=20, cameras=3)
    token = add_user(base / "data", "eve")
    srv = Server(base / "data", base / "server.log").start()
    yield srv, token, run
    srv.stop()


def _job(client, options: str | None = None, calibration: bytes | None = None):
    srv, token, run = client
    files = [("keypoints", (p.name, p.read_bytes(), "text/csv")) for p in run.cams]
    files.append(("calibration", ("calibration.toml", calibration or run.calibration.read_bytes(), "text/plain")))
    with srv.client(token) as c:  # a client each: the server may close a refused upload's connection
        return c.post("/v1/jobs", files=files, data={"options": options or '{"fps": 120, "method": "tri"}'})


def _calibration(client, board: str, detections: str = "{}"):
    srv, token, _ = client
    files = [("detections", (f"points_cam{k}.json", detections.encode(), "application/json")) for k in (1, 2)]
    with srv.client(token) as c:
        return c.post("/v1/calibrations", files=files, data={"board": board})


def _matrix_entry(client, value: str) -> bytes:
    text = client[2].calibration.read_text()
    m = re.search(r"matrix = \[\[ *([-0-9.e]+)", text)
    assert m, text[:200]
    return (text[: m.start(1)] + value + text[m.end(1):]).encode()


GOOD = {"board_shape": [9, 6], "board_square_len": 0.03, "camera_resolution": [1920, 1080], "points": {}}


def _detections(**change) -> str:
    return json.dumps({**GOOD, **change}).replace('"INF"', "Infinity")


CASES = {
    "options fps of 5000 digits": (lambda c: _job(c, options='{"fps": ' + HUGE + ', "method": "tri"}'),
                                   "options: a number with thousands of digits"),
    "a calibration matrix entry of 401 digits": (lambda c: _job(c, calibration=_matrix_entry(c, BIG)),
                                                 "calibration.toml: [cam_0] matrix: a number too large"),
    "a calibration matrix entry of 5001 digits": (lambda c: _job(c, calibration=_matrix_entry(c, HUGE)),
                                                  "calibration.toml: not a calibration file: a number with"),
    "a board of 5001 digits": (lambda c: _calibration(c, f"checkerboard:{HUGE}x6:0.031"), "at most 1000"),
    "a board of 401 digits": (lambda c: _calibration(c, f"checkerboard:{BIG}x6:0.031"), "at most 1000"),
    "camera_resolution Infinity": (lambda c: _calibration(c, "checkerboard:9x6:0.03",
                                                          _detections(camera_resolution=["INF", 1080])),
                                   "points_cam1.json: camera_resolution: expected [width, height]"),
    "camera_resolution text": (lambda c: _calibration(c, "checkerboard:9x6:0.03",
                                                      _detections(camera_resolution=["a", "b"])),
                               "points_cam1.json: camera_resolution: expected [width, height]"),
    "board_shape text": (lambda c: _calibration(c, "checkerboard:9x6:0.03", _detections(board_shape="9x6")),
                         "points_cam1.json: board_shape: expected [COLS, ROWS]"),
    "points nested 100,000 deep": (lambda c: _calibration(c, "checkerboard:9x6:0.03",
                                                          _detections(points="DEEP").replace('"DEEP"', DEEP)),
                                   "points_cam1.json: not a detections file: arrays nested too deeply"),
    "camera_resolution of 5001 digits": (lambda c: _calibration(c, "checkerboard:9x6:0.03",
                                                                _detections(camera_resolution="HUGE")
                                                                .replace('"HUGE"', f"[{HUGE}, 1080]")),
                                         "points_cam1.json: not a detections file: a number with thousands"),
}


@pytest.mark.parametrize("case", list(CASES))
def test_a_number_no_reader_foresaw_is_a_422_naming_it(client, case):
    send, words = CASES[case]
    r = send(client)
    assert r.status_code == 422, (case, r.status_code, r.text[:300])
    detail = r.json()["detail"]
    assert words in detail and "\n" not in detail and "internal error" not in detail, (case, detail)


# -- a detections file too large to parse in the process that serves everyone ----------------------

def _peak_rss(pid: int) -> int:
    status = open(f"/proc/{pid}/status").read()
    return int(next(line for line in status.splitlines() if line.startswith("VmHWM:")).split()[1]) * 1024


def test_a_calibrations_detections_are_parsed_outside_the_api_process(client):
    """Two cameras' detections of 20,000 views each (22 MB of JSON, 2 million corners): parsed in the
    API process, its peak memory rose by hundreds of MB (the Python objects of the whole file); read
    in the upload readers' processes, by little more than the streamed copy's buffers. The files are
    real detections files (they calibrate) and the job is accepted."""
    import numpy as np

    srv, token, _ = client
    rng = np.random.default_rng(0)
    corners = np.mgrid[0:9, 0:6].T.reshape(-1, 2) * 40.0 + 300.0
    views = {f"{n}.png": (corners + rng.normal(0, 0.3, corners.shape)).reshape(6, 9, 2).round(3).tolist()
             for n in range(20_000)}
    text = json.dumps({**GOOD, "points": views}).encode()
    assert len(text) > 20e6
    files = [("detections", (f"points_cam{k}.json", text, "application/json")) for k in (1, 2)]
    del views
    open(f"/proc/{srv.pid}/clear_refs", "w").write("5")  # the peak starts again from now
    before = _peak_rss(srv.pid)
    with srv.client(token) as c:
        r = c.post("/v1/calibrations", files=files, data={"board": "checkerboard:9x6:0.03"}, timeout=300)
        assert r.status_code == 202, r.text[:300]
        grew = _peak_rss(srv.pid) - before
        assert c.delete(f"/v1/calibrations/{r.json()['id']}").status_code in (200, 204)
    described = r.json()["inputs"]["detections"]
    assert [d["views"] for d in described] == [20_000, 20_000]
    assert grew < 64 * 2**20, f"the API process's peak memory grew by {grew / 2**20:.0f} MiB"
