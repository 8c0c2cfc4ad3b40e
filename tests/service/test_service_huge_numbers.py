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
