"""Calibration jobs on a real embedded server: AcinoSet's own Ex1 detections in, a rig out, and a
solve job that names the calibration by id."""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import pytest
from servers import Redis, Server, add_user, have_redis, server_with_users, wait_finished, worker
from shared_data import ACINOSET_CALIB, SLEAP_MINIMAL

from graph.io.calibration import load_calibration

DATA = ACINOSET_CALIB
EX1 = [DATA / "Ex1_static" / f"points_cam{n}.json" for n in (3, 4)]
INTRINSICS = [DATA / "intrinsic_calib_2021" / f"camera_{n}.json" for n in (3, 4)]
SBA_BASELINE_M = 0.3924  # AcinoSet's bundle-adjusted scene of the pair (SOURCE.md)


def board_spec() -> str:
    """The board as the detections files describe it: 9x6 inner corners, the square length they give."""
    doc = json.loads(EX1[0].read_text())
    cols, rows = doc["board_shape"]
    return f"checkerboard:{cols}x{rows}:{doc['board_square_len']}"


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    data = tmp_path_factory.mktemp("calibration_data")
    srv = server_with_users(data, data.parent / "calibration_server.log")
    yield srv
    srv.stop()


def post_calibration(client, detections=EX1, intrinsics=INTRINSICS, board=None, options=None):
    files = [("detections", (p.name, p.read_bytes(), "application/json")) for p in detections]
    files += [("intrinsics", (p.name, p.read_bytes(), "application/json")) for p in intrinsics]
    return client.post("/v1/calibrations", files=files,
                       data={"board": board or board_spec(), "options": json.dumps(options or {})})


def wait_calibration(client, cal_id: str, timeout: float = 300) -> dict:
    deadline = time.time() + timeout
    while time.time() < deadline:
        r = client.get(f"/v1/calibrations/{cal_id}")
        assert r.status_code == 200, r.text
        if r.json()["status"] not in ("queued", "running"):
            return r.json()
        time.sleep(0.1)
    raise AssertionError(f"calibration {cal_id} still {r.json()['status']} after {timeout} s")


@pytest.fixture(scope="module")
def ex1(server):
    """Alice's calibration of AcinoSet's static pair, finished."""
    with server.client(server.tokens["alice"]) as c:
        r = post_calibration(c, options={"label": "Ex1 static pair"})
        assert r.status_code == 202, r.text
        assert r.headers["location"] == f"/v1/calibrations/{r.json()['id']}"
        return wait_calibration(c, r.json()["id"])


def test_ex1_detections_give_acinoset_baseline(ex1, alice, tmp_path):
    from graph.io.calibration import load_calibration

    assert ex1["status"] == "succeeded", ex1["error"]
    assert ex1["label"] == "Ex1 static pair" and ex1["options"]["board"] == "checkerboard:9x6:0.031"
    assert ex1["inputs"]["cameras"] == 2 and [d["views"] for d in ex1["inputs"]["detections"]] == [10, 10]
    rep = ex1["report"]
    assert abs(rep["baselines_m"]["cam1-cam2"] - SBA_BASELINE_M) <= 0.01 * SBA_BASELINE_M, rep["baselines_m"]
    assert rep["rms_px"] <= 1.5 and [c["views_used"] for c in rep["cameras"]] == [10, 10]
    assert sorted(ex1["links"]) == sorted(["self", "cancel", "page", "calibration.toml", "scene.json", "report.json",
                                           "rig.png", "residuals.png", "coverage.png"])
    for name in ("calibration.toml", "scene.json"):  # read back with the library's own readers
        r = alice.get(ex1["links"][name])
        assert r.status_code == 200, r.text
        (tmp_path / name).write_bytes(r.content)
        cal = load_calibration(tmp_path / name)
        assert len(cal) == 2
        baseline = np.linalg.norm(cal.cameras[0].center - cal.cameras[1].center)
        assert abs(baseline - rep["baselines_m"]["cam1-cam2"]) < 1e-6
    assert alice.get(ex1["links"]["report.json"]).json()["rms_px"] == pytest.approx(rep["rms_px"])
    for name in ("rig.png", "residuals.png", "coverage.png"):
        r = alice.get(ex1["links"][name])
        assert r.status_code == 200 and r.headers["content-type"] == "image/png"
        assert r.content.startswith(b"\x89PNG\r\n\x1a\n") and len(r.content) > 5000


def test_a_solve_job_names_the_calibration(ex1, alice, bob, tmp_path):
    """Points moving 2-3 m in front of the calibrated pair, projected through the downloaded rig with
    1 px noise and solved with the calibration named by id: they come back where they were."""
    from graph.io.calibration import load_calibration
    from graph.io.keypoints import Keypoints, write_dlc_csv
    from graph.io.results import read_result

    (tmp_path / "calibration.toml").write_bytes(alice.get(ex1["links"]["calibration.toml"]).content)
    cal = load_calibration(tmp_path / "calibration.toml")
    rng = np.random.default_rng(3)
    c0 = cal.cameras[0]
    ahead = c0.center + 2.5 * c0.R[2]  # 2.5 m along camera 1's optical axis
    truth = ahead + rng.uniform(-0.3, 0.3, size=(30, 4, 3))  # 30 frames, 4 points
    cams = []
    for cam, name in zip(cal.cameras, cal.names):
        uv = cam.project(truth) + rng.normal(0, 1.0, size=truth.shape[:2] + (2,))
        assert np.all((uv > 0) & (uv < cam.size)), "the points must be in both images"
        cams.append(tmp_path / f"{name}.csv")
        write_dlc_csv(cams[-1], Keypoints([f"p{i}" for i in range(4)], uv, np.ones(truth.shape[:2])))
    files = [("keypoints", (p.name, p.read_bytes(), "text/csv")) for p in cams]
    options = {"options": json.dumps({"method": "tri", "skeleton": "points", "fps": 120})}

    r = alice.post("/v1/jobs", files=files, data={**options, "calibration_id": ex1["id"]})
    assert r.status_code == 202, r.text
    job = wait_finished(alice, r.json()["id"])
    assert job["status"] == "succeeded", job["error"]
    assert job["inputs"]["cameras"] == 2 and job["inputs"]["calibration"]["name"] == "calibration.toml"
    assert job["inputs"]["calibration_id"] == ex1["id"]  # the job says which calibration it used
    h5 = tmp_path / "result.h5"
    h5.write_bytes(alice.get(f"/v1/jobs/{job['id']}/result", params={"format": "h5"}).content)
    res = read_result(h5)
    assert res.markers == [f"p{i}" for i in range(4)]
    err = np.linalg.norm(res.positions - truth, axis=-1)
    assert np.median(err) < 0.02, np.median(err)  # metres: the named rig is the one solved with

    # only the owner's calibrations: bob cannot use or see alice's
    r = bob.post("/v1/jobs", files=files, data={**options, "calibration_id": ex1["id"]})
    assert r.status_code == 404 and ex1["id"] in r.json()["detail"]
    # a file and an id, or neither: one of them
    both = files + [("calibration", ("c.toml", (tmp_path / "calibration.toml").read_bytes(), "text/plain"))]
    for f, d in ((both, {**options, "calibration_id": ex1["id"]}), (files, options)):
        r = alice.post("/v1/jobs", files=f, data=d)
        assert r.status_code == 422 and "calibration_id" in r.json()["detail"], r.text


def test_other_users_get_404(ex1, bob, alice):
    cal_id = ex1["id"]
    for method, path in [("GET", f"/v1/calibrations/{cal_id}"), ("GET", f"/v1/calibrations/{cal_id}/calibration.toml"),
                         ("DELETE", f"/v1/calibrations/{cal_id}")]:
        r = bob.request(method, path)
        assert r.status_code == 404, (method, path, r.text)
        assert r.json()["detail"] == f"no calibration {cal_id}"
    # a calibration is not a solve job: the job endpoints do not show it, even to its owner
    assert alice.get(f"/v1/jobs/{cal_id}").status_code == 404
    assert cal_id not in [j["id"] for j in alice.get("/v1/jobs").json()["jobs"]]
    assert alice.get(f"/v1/calibrations/{cal_id}").status_code == 200
    # the list: alice's own calibrations, none of them for bob
    mine = alice.get("/v1/calibrations", params={"status": "succeeded"}).json()
    assert cal_id in [c["id"] for c in mine["calibrations"]] and mine["total"] >= 1
    assert all(c["owner"] == "alice" for c in mine["calibrations"])
    assert bob.get("/v1/calibrations").json() == {"calibrations": [], "total": 0, "next_cursor": None}


@pytest.mark.parametrize("case, status, fragment", [
    ("spec", 422, "board: "),
    ("shape", 422, "does not match the board"),
    ("one camera", 422, "at least two cameras"),
    ("not json", 422, "points_cam4.json: not valid JSON"),
    ("intrinsics", 422, "2 cameras"),
    ("model", 422, "model must be one of fisheye, pinhole"),
    ("lens", 422, "lens must be one of full, k1"),
    ("lens with intrinsics", 422, "lens is what the intrinsics calibrated here fit"),
])
def test_bad_uploads_are_one_line_4xx(alice, tmp_path, case, status, fragment):
    kwargs = {}
    if case == "spec":
        kwargs["board"] = "checkerboard:9by6:0.031"
    elif case == "shape":
        kwargs["board"] = "checkerboard:8x6:0.031"
    elif case == "one camera":
        kwargs.update(detections=EX1[:1], intrinsics=[])
    elif case == "not json":
        bad = tmp_path / "points_cam4.json"
        bad.write_text("{not json")
        kwargs["detections"] = [EX1[0], bad]
    elif case == "intrinsics":
        kwargs["intrinsics"] = INTRINSICS[:1]
    elif case == "model":
        kwargs["options"] = {"model": "orthographic"}
    elif case == "lens":
        kwargs["options"] = {"lens": "k2"}
    elif case == "lens with intrinsics":
        kwargs["options"] = {"lens": "k1"}
    r = post_calibration(alice, **kwargs)
    assert r.status_code == status, r.text
    detail = r.json()["detail"]
    assert fragment in detail and "\n" not in detail and "/" not in detail.split(":", 1)[0], detail


def test_a_huge_option_value_is_refused_in_a_short_line(alice):
    """A 100 kB value of an option is named, not echoed whole, in the refusal."""
    for name in ("lens", "model", "origin", "every"):
        r = post_calibration(alice, options={name: "k1" * 50_000})
        assert r.status_code == 422 and name in r.json()["detail"] and len(r.json()["detail"]) < 300, r.text[:300]


def test_cameras_with_no_shared_view_fail_with_the_reason(alice, tmp_path):
    """Accepted (each file is fine on its own), then failed by the solve with its one-line reason."""
    doc = json.loads(EX1[1].read_text())
    doc["points"] = {f"{int(k.split('.')[0]) + 1_000_000}.png": v for k, v in doc["points"].items()}  # none shared
    apart = tmp_path / "points_cam4.json"
    apart.write_text(json.dumps(doc))
    r = post_calibration(alice, detections=[EX1[0], apart])
    assert r.status_code == 202, r.text
    cal = wait_calibration(alice, r.json()["id"])
    assert cal["status"] == "failed" and cal["error_kind"] == "input", cal
    assert "cam1" in cal["error"] and "cam2" in cal["error"] and "\n" not in cal["error"]
    assert alice.get(f"/v1/calibrations/{cal['id']}/calibration.toml").status_code == 409
    assert alice.delete(f"/v1/calibrations/{cal['id']}").status_code == 204
    assert alice.get(f"/v1/calibrations/{cal['id']}").status_code == 404


@pytest.mark.skipif(not have_redis(), reason="needs Debian's redis-server (.ci/run installs it)")
@pytest.mark.slow  # over 12 s here
def test_a_calibration_runs_on_an_rq_worker(tmp_path, ex1, alice):
    """The inputs travel to an RQ worker and the rig's files back: the same files as the embedded run."""
    redis = Redis(tmp_path / "redis", tmp_path / "redis.log").start()
    procs = [redis]
    try:
        token = add_user(tmp_path / "data", "rita")
        procs.append(Server(tmp_path / "data", tmp_path / "server.log", backend="rq", redis_url=redis.url).start())
        procs.append(worker(redis.url, tmp_path / "w1.log", "w1").start())
        with procs[1].client(token) as c:
            r = post_calibration(c)
            assert r.status_code == 202, r.text
            cal = wait_calibration(c, r.json()["id"])
            assert cal["status"] == "succeeded" and cal["worker"] == "w1", cal
            assert sorted(cal["links"]) == sorted(ex1["links"])
            assert cal["report"]["baselines_m"] == pytest.approx(ex1["report"]["baselines_m"], rel=1e-6)
            for name in ("calibration.toml", "scene.json"):
                assert c.get(cal["links"][name]).content == alice.get(ex1["links"][name]).content
            # videos travel too, and the board is found on the worker
            videos, baseline = _film_board(tmp_path, 20)
            r = c.post("/v1/calibrations",
                       files=[("videos", (p.name, p.read_bytes(), "video/x-msvideo")) for p in videos],
                       data={"board": "checkerboard:9x6:0.05", "options": json.dumps({"model": "pinhole"})})
            assert r.status_code == 202, r.text
            cal = wait_calibration(c, r.json()["id"])
            assert cal["status"] == "succeeded" and cal["worker"] == "w1", cal
            assert abs(cal["report"]["baselines_m"]["cam1-cam2"] - baseline) < 0.03 * baseline
    finally:
        for p in reversed(procs):
            p.stop(10)


def _film_board(out: Path, views: int) -> tuple[list[Path], float]:
    """Two pinhole cameras 0.3 m apart, toed in, filming a 9x6 board moved through the space they share
    (rendered frames, MJPG AVI): the videos and the true baseline."""
    import cv2

    from graph.calibrate import parse_board
    from graph.calibrate.simulate import render_board, rig_views
    from graph.camera import PINHOLE, Calibration, Camera

    def camera(x: float, yaw_deg: float) -> Camera:
        c, s = np.cos(np.radians(yaw_deg)), np.sin(np.radians(yaw_deg))
        R = np.array([[c, 0, -s], [0, 1, 0], [s, 0, c]])
        return Camera(K=[[600, 0, 320], [0, 600, 240], [0, 0, 1]], dist=np.zeros(5), R=R, t=-R @ [x, 0, 0],
                      model=PINHOLE, size=(640, 480))

    board = parse_board("checkerboard:9x6:0.05")
    rig = Calibration(cameras=[camera(0.0, 4), camera(0.3, -4)])
    _, poses = rig_views(rig, board, n_views=views, noise_px=0.0, seed=1)
    paths = []
    for i, cam in enumerate(rig.cameras):
        paths.append(out / f"cam{i + 1}.avi")
        writer = cv2.VideoWriter(str(paths[-1]), cv2.VideoWriter_fourcc(*"MJPG"), 30, (640, 480), isColor=False)
        for k, (Rw, tw) in enumerate(poses.values()):
            writer.write(render_board(cam, board, cam.R @ Rw, cam.R @ tw + cam.t, seed=k)[0])
        writer.release()
    return paths, float(np.linalg.norm(rig.cameras[0].center - rig.cameras[1].center))


def test_a_calibration_from_videos(alice, tmp_path):
    """Short videos instead of detections: the server finds the board in every frame and calibrates
    the pinhole pair (intrinsics too) to its true baseline within 2 %."""
    videos, baseline = _film_board(tmp_path, 30)
    files = [("videos", (p.name, p.read_bytes(), "video/x-msvideo")) for p in videos]
    r = alice.post("/v1/calibrations", files=files,
                   data={"board": "checkerboard:9x6:0.05", "options": json.dumps({"model": "pinhole"})})
    assert r.status_code == 202, r.text
    assert [v["frames"] for v in r.json()["inputs"]["videos"]] == [30, 30]
    cal = wait_calibration(alice, r.json()["id"])
    assert cal["status"] == "succeeded", cal["error"]
    rep = cal["report"]
    assert abs(rep["baselines_m"]["cam1-cam2"] - baseline) < 0.02 * baseline, rep["baselines_m"]
    assert rep["rms_px"] < 1.0 and rep["frames_used"] >= 10
    assert "scene.json" not in cal["links"]  # AcinoSet's scene holds fisheye cameras only
    assert alice.get(cal["links"]["calibration.toml"]).status_code == 200
    # Anipose's lens asked for: the rig's cameras have one focal length, centred, and k1 alone
    r = alice.post("/v1/calibrations", files=files, data={"board": "checkerboard:9x6:0.05",
                                                          "options": json.dumps({"model": "pinhole", "lens": "k1"})})
    cal = wait_calibration(alice, r.json()["id"])
    assert cal["status"] == "succeeded" and cal["options"]["lens"] == "k1", cal
    toml = tmp_path / "k1.toml"
    toml.write_bytes(alice.get(cal["links"]["calibration.toml"]).content)
    for cam in load_calibration(toml).cameras:
        w, h = cam.size
        assert cam.K[0, 0] == pytest.approx(cam.K[1, 1], rel=1e-5) and np.allclose(cam.dist[1:], 0, atol=1e-5)
        assert np.allclose(cam.K[:2, 2], [(w - 1) / 2, (h - 1) / 2], atol=1e-3), cam.K
    assert abs(cal["report"]["baselines_m"]["cam1-cam2"] - baseline) < 0.02 * baseline
    # a file that is not a video, and videos with detections: one-line 422s
    bad = tmp_path / "cam2.avi"
    bad.write_bytes(b"not a video at all")
    files = [("videos", (p.name, p.read_bytes(), "video/x-msvideo")) for p in (videos[0], bad)]
    r = alice.post("/v1/calibrations", files=files, data={"board": "checkerboard:9x6:0.05"})
    assert r.status_code == 422 and r.json()["detail"] == "cam2.avi: not a video OpenCV can read", r.text
    files = [("videos", (p.name, p.read_bytes(), "video/x-msvideo")) for p in videos]
    files += [("detections", (p.name, p.read_bytes(), "application/json")) for p in EX1]
    r = alice.post("/v1/calibrations", files=files, data={"board": board_spec()})
    assert r.status_code == 422 and "not both" in r.json()["detail"], r.text


def test_a_jobs_rig_refined_from_its_keypoints(alice, bob, tmp_path):
    """SLEAP's minimal session as a solve job (its four proofread .slp and the shipped rig, whose side
    entry is a copy of top's), then ``POST /v1/jobs/{id}/refinement`` naming the job: side is posed
    again and every camera predicts the mouse from the others better; the rig it writes reads in
    aniposelib. Bob cannot refine Alice's job; bad options are one line."""
    from aniposelib.cameras import CameraGroup

    from graph.io.calibration import load_calibration

    cams = ("back", "mid", "side", "top")
    files = [("keypoints", (f"{c}.slp", (SLEAP_MINIMAL / c / f"minimal_{c}_proofread.slp").read_bytes(),
                            "application/octet-stream")) for c in cams]
    files.append(("calibration", ("calibration.toml", (SLEAP_MINIMAL / "calibration.toml").read_bytes(), "text/plain")))
    r = alice.post("/v1/jobs", files=files,
                   data={"options": json.dumps({"method": "tri", "skeleton": "points", "fps": 30})})
    assert r.status_code == 202, r.text
    job_id = r.json()["id"]

    r = alice.post(f"/v1/jobs/{job_id}/refinement", data={"options": json.dumps(
        {"likelihood": 0.01, "label": "mended side"})})
    assert r.status_code == 202, r.text
    assert r.headers["location"] == f"/v1/calibrations/{r.json()['id']}"
    cal = wait_calibration(alice, r.json()["id"])
    assert cal["status"] == "succeeded", cal["error"]
    assert cal["inputs"]["refined_from"] == job_id and len(cal["inputs"]["keypoints"]) == 4
    assert cal["label"] == "mended side" and cal["options"]["refine"] is True
    rep = cal["report"]
    assert rep["accepted"] and [c["re_posed"] for c in rep["cameras"]] == [False, False, True, False]
    old, new = rep["leave_one_out_px"]["old"], rep["leave_one_out_px"]["new"]
    assert all(n < o for n, o in zip(new, old)) and new[2] < 20, (old, new)
    assert {"calibration.toml", "report.json", "rig.png"} <= set(cal["links"])
    (tmp_path / "refined.toml").write_bytes(alice.get(cal["links"]["calibration.toml"]).content)
    group = CameraGroup.load(str(tmp_path / "refined.toml"))  # the field's own reader
    assert group.get_names() == list(cams)
    ours = load_calibration(tmp_path / "refined.toml")
    assert np.linalg.norm(ours.cameras[2].center - ours.cameras[3].center) > 100  # side is no longer top (mm)
    png = alice.get(cal["links"]["rig.png"])
    assert png.status_code == 200 and png.content[:8] == b"\x89PNG\r\n\x1a\n"

    r = bob.post(f"/v1/jobs/{job_id}/refinement")
    assert r.status_code == 404 and job_id in r.json()["detail"]
    for bad, fragment in (({"likelihood": 2}, "likelihood"), ({"refine_intrinsics": ["zoom"]}, "refine_intrinsics"),
                          ({"every": 2}, "unknown option"),
                          ({"refine_intrinsics": ["x" * 100_000]}, "refine_intrinsics")):
        r = alice.post(f"/v1/jobs/{job_id}/refinement", data={"options": json.dumps(bad)})
        assert r.status_code == 422 and fragment in r.json()["detail"] and "\n" not in r.json()["detail"], r.text
        assert len(r.json()["detail"]) < 300  # the value quoted, not echoed whole
    for other in ("0" * 32, job_id[:-1], "..%2F" + job_id):
        r = alice.post(f"/v1/jobs/{other}/refinement")
        assert r.status_code == 404, r.text
