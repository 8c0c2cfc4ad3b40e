"""The REST API against a real embedded server (uvicorn in a subprocess on a loopback port)."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import httpx
import numpy as np
import pytest
from servers import PY, ROOT, Server, add_user, server_with_users, submit, submit_ok, wait_finished


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    data = tmp_path_factory.mktemp("api_data")
    srv = server_with_users(data, data.parent / "api_server.log", admins=("root",))
    yield srv
    srv.stop()


@pytest.fixture
def root(server):
    with server.client(server.tokens["root"]) as c:
        yield c


FAST = {"method": "tri", "skeleton": "points", "fps": 120.0}


# -- tokens ----------------------------------------------------------------------------------------

def test_every_v1_call_needs_a_valid_token(server, small_run):
    with server.client() as anon, server.client("acn_0123456789ab_not-a-real-secret") as forged:
        for c in (anon, forged):
            for method, path in [("GET", "/v1/jobs"), ("GET", "/v1/jobs/" + "0" * 32), ("GET", "/v1/skeletons"),
                                 ("DELETE", "/v1/jobs/" + "0" * 32), ("GET", "/v1/me")]:
                r = c.request(method, path)
                assert r.status_code == 401, (method, path, r.text)
                assert r.headers["www-authenticate"] == "Bearer"
                assert isinstance(r.json()["detail"], str) and r.json()["detail"]
            r = submit(c, small_run, FAST)  # refused from the headers, before the body is read
            assert r.status_code == 401 and "token" in r.json()["detail"]
        assert "Authorization: Bearer" in anon.get("/v1/jobs").json()["detail"]
        assert forged.get("/v1/jobs").json()["detail"] == "invalid or revoked token"


# -- the round trip --------------------------------------------------------------------------------

def test_a_simulated_run_through_rest_gives_the_cli_csv(alice, small_run, tmp_path):
    opts = {"method": "fte", "skeleton": "cheetah", "fps": small_run.fps}
    r = submit(alice, small_run, opts)
    assert r.status_code == 202, r.text
    job = r.json()
    assert job["status"] == "queued" and r.headers["location"] == job["links"]["self"] == f"/v1/jobs/{job['id']}"
    assert job["inputs"]["cameras"] == 6 and job["inputs"]["frames"] == small_run.frames
    assert [k["name"] for k in job["inputs"]["keypoints"]] == [p.name for p in small_run.cams]
    done = wait_finished(alice, job["id"])
    assert done["status"] == "succeeded", done
    assert done["progress"]["fraction"] == 1.0 and done["attempts"] == 1
    assert done["result"]["frames"] == small_run.frames and done["result"]["markers"] == 20
    assert done["timings"]["run_seconds"] > 0 and done["timings"]["finished_at"]

    rest_csv = alice.get(done["links"]["result"]["csv"])
    assert rest_csv.status_code == 200 and rest_csv.headers["content-type"].startswith("text/csv")
    cli_csv = tmp_path / "cli.csv"
    cli = subprocess.run([PY, "-m", "graph.app.cli", "solve", *map(str, small_run.cams), "--calibration",
                          str(small_run.calibration), "--method", "fte", "--skeleton", "cheetah",
                          "--fps", str(small_run.fps), "--out", str(cli_csv)], cwd=ROOT, capture_output=True, text=True)
    assert cli.returncode == 0, cli.stderr
    assert rest_csv.content == cli_csv.read_bytes()

    from graph.io.results import read_anipose_csv, read_result

    h5 = tmp_path / "rest.h5"
    h5.write_bytes(alice.get(f"/v1/jobs/{job['id']}/result", params={"format": "h5"}).content)
    res = read_result(h5)
    pts = read_anipose_csv(cli_csv)
    assert res.positions.shape == (small_run.frames, 20, 3)
    as_json = alice.get(f"/v1/jobs/{job['id']}/result", params={"format": "json"}).json()
    pos = np.array([[[np.nan if v is None else v for v in xyz] for xyz in frame] for frame in as_json["positions"]])
    np.testing.assert_allclose(pos, res.positions, atol=1e-5, equal_nan=True)  # 10 um steps
    assert as_json["markers"] == res.markers
    np.testing.assert_allclose(pts.positions, res.positions, atol=1e-5, equal_nan=True)
    report = alice.get(f"/v1/jobs/{job['id']}/result", params={"format": "report"}).json()
    assert report["frames"] == small_run.frames and report["method"] == "fte"


def test_smoothing_fitted_to_the_data(alice, small_run):
    """motion_scale "auto": the job takes it and its report gives the scale fitted per marker."""
    r = submit(alice, small_run, {"method": "fte", "skeleton": "points", "motion_scale": "auto"})
    assert r.status_code == 202, r.text
    assert r.json()["options"]["motion_scale"] == "auto"
    done = wait_finished(alice, r.json()["id"])
    assert done["status"] == "succeeded", done
    report = alice.get(f"/v1/jobs/{done['id']}/result", params={"format": "report"}).json()
    assert report["motion_scales"] and all(v > 0 for v in report["motion_scales"].values())


def test_an_acinoset_json_calibration_works_too(alice, small_run):
    r = submit(alice, small_run, FAST, calibration=small_run.scene)
    assert r.status_code == 202, r.text
    assert wait_finished(alice, r.json()["id"])["status"] == "succeeded"


def test_detection_noise_measured_from_the_data(alice, small_run):
    r = submit(alice, small_run, {**FAST, "measurement_std_px": "auto"})
    assert r.status_code == 202, r.text
    assert r.json()["options"]["measurement_std_px"] == "auto"
    done = wait_finished(alice, r.json()["id"])
    assert done["status"] == "succeeded", done
    report = alice.get(f"/v1/jobs/{done['id']}/result", params={"format": "report"}).json()
    assert 4.0 < report["sigma_px"] < 5.5 and report["noise_px"] > 0  # the simulation adds 5 px noise
    assert not any("standard deviations are about" in w for w in report["warnings"])


# -- users see their own jobs ----------------------------------------------------------------------

def test_users_see_only_their_own_jobs_and_admins_see_all(alice, bob, root, small_run):
    job_id = submit_ok(alice, small_run, FAST)
    for path in (f"/v1/jobs/{job_id}", f"/v1/jobs/{job_id}/result"):
        r = bob.get(path)
        assert r.status_code == 404 and r.json()["detail"] == f"no job {job_id}"
    assert bob.delete(f"/v1/jobs/{job_id}").status_code == 404
    assert job_id not in [j["id"] for j in bob.get("/v1/jobs").json()["jobs"]]
    assert bob.get("/v1/jobs", params={"owner": "alice"}).status_code == 403
    assert job_id in [j["id"] for j in alice.get("/v1/jobs").json()["jobs"]]
    seen = root.get("/v1/jobs", params={"owner": "alice", "limit": 500}).json()
    assert job_id in [j["id"] for j in seen["jobs"]] and {j["owner"] for j in seen["jobs"]} == {"alice"}
    assert root.get(f"/v1/jobs/{job_id}").json()["owner"] == "alice"
    wait_finished(alice, job_id)
    assert bob.get(f"/v1/jobs/{job_id}").status_code == 404  # still not bob's after it finished


def test_list_filters_by_status_and_pages(bob, small_run):
    ids = [submit_ok(bob, small_run, FAST) for _ in range(3)]
    for i in ids:
        wait_finished(bob, i)
    page1 = bob.get("/v1/jobs", params={"limit": 2, "status": "succeeded"}).json()
    assert len(page1["jobs"]) == 2 and page1["total"] >= 3 and page1["next_cursor"]
    assert page1["next"].startswith("/v1/jobs?") and "cursor=" in page1["next"]
    page2 = bob.get(page1["next"]).json()
    got = [j["id"] for j in page1["jobs"] + page2["jobs"]]
    assert got[:3] == ids[::-1] and len(set(got)) == len(got)
    assert all(j["status"] == "succeeded" for j in page1["jobs"] + page2["jobs"])
    assert bob.get("/v1/jobs", params={"status": "cancelled"}).json()["total"] == 0
    bad = bob.get("/v1/jobs", params={"status": "done"})
    assert bad.status_code == 422 and "status" in bad.json()["detail"]


def test_result_before_success_is_409_and_delete_removes_files(server, alice, small_run):
    job_id = submit_ok(alice, small_run, {"method": "fte", "skeleton": "points"})
    r = alice.get(f"/v1/jobs/{job_id}/result")
    assert r.status_code in (409, 200)
    if r.status_code == 409:
        assert "its result is ready when it succeeded" in r.json()["detail"]
    assert wait_finished(alice, job_id)["status"] == "succeeded"
    job_dir = server.data_dir / "jobs" / job_id
    assert (job_dir / "result" / "result.csv").is_file()
    assert alice.delete(f"/v1/jobs/{job_id}").status_code == 204
    assert not job_dir.exists()
    assert alice.get(f"/v1/jobs/{job_id}").status_code == 404
    assert alice.get("/v1/jobs/not-a-job-id").status_code == 404
    assert alice.get("/v1/jobs/../../etc/passwd").status_code == 404


def test_reference_endpoints(server, alice):
    sk = {s["name"]: s for s in alice.get("/v1/skeletons").json()}
    assert {"cheetah", "points"} <= set(sk)
    assert sk["cheetah"]["kind"] == "kinematic" and "nose" in sk["cheetah"]["markers"]
    assert sk["cheetah"]["parameters"] == 25
    me = alice.get("/v1/me").json()
    assert me["name"] == "alice" and me["admin"] is False and me["limits"]["max_frames"] > 0
    with server.client() as anon:
        health = anon.get("/healthz").json()
        assert health["status"] == "ok" and health["backend"] == "embedded" and health["workers"] == 2
        metrics = anon.get("/metrics")
        assert metrics.headers["content-type"].startswith("text/plain")
        text = metrics.text
        assert 'acinoset_jobs{status="succeeded"}' in text and "acinoset_solve_seconds_count" in text
        assert anon.get("/no/such/page").json()["detail"]


# -- bad uploads -----------------------------------------------------------------------------------

def _upload(client, files: list[tuple[str, str, bytes]], options=None):
    data = {"options": options if isinstance(options, str) else json.dumps(options or FAST)}
    return client.post("/v1/jobs", files=[(field, (name, content, "application/octet-stream"))
                                          for field, name, content in files], data=data)


def _files(run, cams=None, cal=None):
    out = [("keypoints", p.name, p.read_bytes()) for p in (cams or run.cams)]
    out.append(("calibration", (cal or run.calibration).name, (cal or run.calibration).read_bytes()))
    return out


def _bad_cases(run):
    csv = run.cams[0].read_bytes()
    lines = csv.decode().splitlines()
    short = ("\n".join(lines[: len(lines) - 5]) + "\n").encode()
    return {
        "garbage keypoints": (_files(run)[:2] + [("keypoints", "cam3.csv", b"\x00\x01 not a csv at all")]
                              + _files(run)[3:], FAST, "cam3.csv"),
        "keypoints with no data rows": ([("keypoints", "cam1.csv", b"scorer,a\nbodyparts,b\ncoords,x\n")]
                                        + _files(run)[1:], FAST, "cam1.csv"),
        "garbage calibration": (_files(run)[:-1] + [("calibration", "calib.toml", b"this = [is not toml")], FAST,
                                "calib.toml"),
        "empty calibration": (_files(run)[:-1] + [("calibration", "calib.json", b"")], FAST, "calib.json"),
        "a camera too few": (_files(run, cams=run.cams[:-1]), FAST, "6 cameras"),
        "frames differ": (_files(run)[:1] + [("keypoints", "cam2.csv", short)] + _files(run)[2:], FAST, "frames"),
        "options not json": (_files(run), "{method: tri", "options: not valid JSON"),
        "options not an object": (_files(run), "[1, 2]", "options: must be a JSON object"),
        "unknown option": (_files(run), {"methd": "tri"}, "unknown option 'methd'"),
        "bad method": (_files(run), {"method": "magic"}, "options: method"),
        "bad fps": (_files(run), {"method": "tri", "fps": -3}, "fps must be between"),
        "bad noise": (_files(run), {"method": "tri", "measurement_std_px": "loud"},
                      "options: measurement_std_px: must be a positive number of pixels or 'auto'"),
        "bad motion scale": (_files(run), {"method": "tri", "motion_scale": "smooth"},
                             "options: motion_scale: must be a positive number, 'auto', or {group: positive number}"),
        "bad motion scale map": (_files(run), {"method": "fte", "motion_scale": {"nose": -1}},
                                 "motion_scale must be positive and at most 1e+06 (or one such per group)"),
        "skeleton as a server path": (_files(run), {"skeleton": "/etc/passwd"}, "unknown skeleton '/etc/passwd'"),
        "no calibration": (_files(run)[:-1], FAST, "calibration"),
        "no keypoints": (_files(run)[-1:], FAST, "keypoints"),
    }


def test_every_bad_upload_is_422_naming_the_problem(server, alice, small_run):
    jobs_before = set((server.data_dir / "jobs").iterdir())
    for case, (files, options, expected) in _bad_cases(small_run).items():
        r = _upload(alice, files, options)
        assert r.status_code == 422, (case, r.status_code, r.text)
        detail = r.json()["detail"]
        assert isinstance(detail, str) and "\n" not in detail and "Traceback" not in detail, (case, detail)
        assert expected in detail, (case, detail)
    # nothing was queued or left behind
    assert set((server.data_dir / "jobs").iterdir()) == jobs_before


def test_uploaded_names_cannot_leave_the_job_directory(server, alice, small_run):
    files = [("keypoints", f"../../../../tmp/evil{i}.csv", p.read_bytes()) for i, p in enumerate(small_run.cams)]
    files.append(("calibration", "/etc/acinoset-calibration.toml", small_run.calibration.read_bytes()))
    r = _upload(alice, files)
    assert r.status_code == 202, r.text
    job = r.json()
    assert [k["name"] for k in job["inputs"]["keypoints"]] == [f"evil{i}.csv" for i in range(6)]
    assert job["inputs"]["calibration"]["name"] == "acinoset-calibration.toml"
    job_dir = (server.data_dir / "jobs" / job["id"]).resolve()
    stored = [p for p in job_dir.rglob("*") if p.is_file()]
    assert all(p.resolve().is_relative_to(job_dir) for p in stored)
    assert not Path("/tmp/evil0.csv").exists() and not Path("/etc/acinoset-calibration.toml").exists()
    assert wait_finished(alice, job["id"])["status"] == "succeeded"


# -- limits ----------------------------------------------------------------------------------------

def test_upload_and_frame_limits_answer_413(tmp_path, small_run):
    from graph.camera import Calibration
    from graph.io.calibration import load_calibration, write_anipose_toml

    data = tmp_path / "data"
    token = add_user(data, "carol")
    cam_bytes = sum(p.stat().st_size for p in small_run.cams)
    env = {"ACINOSET_MAX_UPLOAD_BYTES": str(cam_bytes // 2), "ACINOSET_MAX_FRAMES": "50", "ACINOSET_WARM_START": "0"}
    one_cam = tmp_path / "one.toml"
    write_anipose_toml(one_cam, Calibration(cameras=load_calibration(small_run.calibration).cameras[:1]))
    srv = Server(data, tmp_path / "server.log", workers=1, env=env).start()
    try:
        with srv.client(token) as c:
            r = submit(c, small_run, FAST)
            assert r.status_code == 413 and "MiB per job" in r.json()["detail"], r.text
            r = submit(c, small_run, FAST, calibration=one_cam, cams=small_run.cams[:1])
            assert r.status_code == 413, r.text
            assert r.json()["detail"] == ("cam1.csv: more than 50 frames; at most 50 frames per file on this "
                                          "server (ACINOSET_MAX_FRAMES)")
            assert c.get("/v1/jobs").json()["total"] == 0
    finally:
        srv.stop()


def test_too_many_active_jobs_answer_429(tmp_path, small_run, long_run):
    data = tmp_path / "data"
    token = add_user(data, "dave")
    env = {"ACINOSET_MAX_ACTIVE_JOBS_PER_USER": "1", "ACINOSET_WARM_START": "0"}
    srv = Server(data, tmp_path / "server.log", workers=1, env=env).start()
    try:
        with srv.client(token) as c:
            first = submit_ok(c, long_run, {"method": "fte", "skeleton": "cheetah"})
            r = submit(c, small_run, FAST)
            assert c.get(f"/v1/jobs/{first}").json()["status"] in ("queued", "running")
            assert r.status_code == 429, r.text
            assert r.json()["detail"].startswith("you have 1 queued or running jobs")
            assert c.delete(f"/v1/jobs/{first}").json()["status"] == "cancelled"
            assert submit(c, small_run, FAST).status_code == 202
    finally:
        srv.stop()


# -- DeepLabCut H5 ---------------------------------------------------------------------------------

def _dlc_h5(path: Path, kp) -> None:
    """An H5 file the way DeepLabCut's analyze_videos writes it (pandas, PyTables 'table' format)."""
    import pandas as pd

    cols = pd.MultiIndex.from_tuples([("DLC_resnet50", b, c) for b in kp.bodyparts for c in ("x", "y", "likelihood")],
                                     names=["scorer", "bodyparts", "coords"])
    values = np.concatenate([kp.xy, kp.likelihood[..., None]], axis=-1).reshape(kp.frames, -1)
    pd.DataFrame(values, columns=cols).to_hdf(path, key="df_with_missing", format="table", mode="w")


def test_dlc_h5_uploads_solve_like_the_csvs(alice, small_run, tmp_path):
    pytest.importorskip("tables")
    from graph.io.keypoints import read_keypoints

    h5s = []
    for p in small_run.cams:
        h5 = tmp_path / f"{p.stem}DLC_resnet50.h5"
        _dlc_h5(h5, read_keypoints(p))
        h5s.append(h5)
    by_h5 = submit(alice, small_run, FAST, cams=h5s)
    by_csv = submit(alice, small_run, FAST)
    assert by_h5.status_code == 202, by_h5.text
    assert [k["name"] for k in by_h5.json()["inputs"]["keypoints"]] == [p.name for p in h5s]
    a, b = (wait_finished(alice, r.json()["id"]) for r in (by_h5, by_csv))
    assert a["status"] == b["status"] == "succeeded"
    assert alice.get(f"/v1/jobs/{a['id']}/result").content == alice.get(f"/v1/jobs/{b['id']}/result").content


def test_an_h5_upload_carrying_a_pickle_is_refused_without_running_it(alice, small_run, tmp_path):
    pytest.importorskip("tables")
    import h5py

    from graph.io.keypoints import read_keypoints

    marker = tmp_path / "pwned"
    evil = tmp_path / "evil.h5"
    _dlc_h5(evil, read_keypoints(small_run.cams[0]))
    payload = np.bytes_(f"cos\nsystem\n(Vtouch {marker}\ntR.".encode())
    with h5py.File(evil, "r+") as f:
        f["df_with_missing/table"].attrs["values_block_0_kind"] = payload
    r = submit(alice, small_run, FAST, cams=[evil, *small_run.cams[1:]])
    detail = r.json()["detail"]
    assert r.status_code == 422 and detail.startswith("evil.h5: ") and "would run code" in detail
    assert not marker.exists()


@pytest.mark.slow  # over 12 s here
def test_an_upload_after_the_api_threads_idled_out_is_read(alice, small_run):
    """The upload readers were spawned from whichever API thread submitted first and die with
    that thread (PR_SET_PDEATHSIG); the thread pool retires a thread idle for 10 s, so the next
    upload after a quiet spell found its readers killed: 422 'reading the upload crashed a reader'."""
    import time
    from concurrent.futures import ThreadPoolExecutor

    def busy() -> None:  # calls answered in the API's thread pool, at once: it grows, then retires the idle
        with ThreadPoolExecutor(8) as pool:
            assert all(r.status_code == 200 for r in pool.map(lambda _: alice.get("/v1/me"), range(16)))

    busy()
    first = submit(alice, small_run, FAST)
    assert first.status_code == 202, first.text
    busy()
    time.sleep(12)
    busy()
    second = submit(alice, small_run, FAST)
    assert second.status_code == 202, second.text


def test_an_address_guessing_tokens_is_refused_for_a_minute(tmp_path):
    """Tokens are 256-bit, but nothing slowed an address sending wrong ones (security issue 25, minor):
    past the limit every call from it is 429 with Retry-After, a valid token's too, for the minute."""
    data = tmp_path / "data"
    token = add_user(data, "ann")
    srv = Server(data, tmp_path / "server.log", env={"ACINOSET_MAX_TOKEN_FAILURES_PER_MINUTE": "5"}).start()
    try:
        with srv.client("x" * 43) as wrong, srv.client(token) as right:
            assert right.get("/v1/me").status_code == 200
            assert [wrong.get("/v1/me").status_code for _ in range(5)] == [401] * 5
            r = wrong.get("/v1/me")
            assert r.status_code == 429 and 50 <= int(r.headers["retry-after"]) <= 60, (r.status_code, r.headers)
            assert r.json()["detail"].startswith("too many invalid tokens from this address")
            assert right.get("/v1/me").status_code == 429
            assert httpx.get(srv.url + "/healthz", timeout=30).status_code in (200, 503)  # needs no token
    finally:
        srv.stop()
