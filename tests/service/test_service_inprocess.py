"""The quick answers of the API in this process (fastapi's TestClient, the app's lifespan run): health,
tokens, unknown jobs, bad options and the spec. The real-server tests beside these cover the rest."""

from __future__ import annotations

import json
import os
import time

import numpy as np
import pytest
from fastapi.testclient import TestClient
from servers import add_user
from shared_data import EKS_FLY, needs

import graph
from service.app import create_app
from service.openapi import spec
from service.settings import Settings


@pytest.fixture(scope="module")
def app_client(tmp_path_factory):
    """A TestClient on an embedded app with its own data dir and one user (``tokens["ada"]``)."""
    data = tmp_path_factory.mktemp("inprocess_data")
    tokens = {"ada": add_user(data, "ada"), "root": add_user(data, "root", admin=True)}
    app = create_app(Settings(data_dir=data, workers=1, upload_readers=0, warm_start=False))
    environ = dict(os.environ)  # the app sets up its solve processes' environment in this process
    try:
        with TestClient(app) as client:
            client.tokens = tokens
            yield client
    finally:  # later tests of this process compile kernels: numba rereads its settings from it
        os.environ.clear()
        os.environ.update(environ)


def _auth(client, name: str) -> dict:
    return {"Authorization": f"Bearer {client.tokens[name]}"}


def test_healthz_is_public_and_reports_an_idle_embedded_backend(app_client):
    r = app_client.get("/healthz")
    deadline = time.time() + 60
    while r.status_code == 503 and r.json()["status"] == "starting" and time.time() < deadline:
        assert r.json()["ready"] is False and r.json()["detail"]  # not ready until its solve processes are
        time.sleep(0.2)
        r = app_client.get("/healthz")
    assert r.status_code == 200, r.text
    body = r.json()
    assert body["status"] == "ok" and body["ready"] is True and body["backend"] == "embedded"
    assert body["version"] == graph.__version__
    assert body["workers"] == 1 and body["running"] == 0 and body["queued"] == 0
    assert body["oldest_queued_seconds"] is None
    assert 0 < body["disk"]["free_bytes"] <= body["disk"]["total_bytes"]


def test_no_token_or_a_forged_one_is_401_with_a_bearer_challenge(app_client):
    missing = app_client.get("/v1/jobs")
    assert missing.status_code == 401
    assert missing.headers["www-authenticate"] == "Bearer"
    assert "Authorization: Bearer TOKEN" in missing.json()["detail"]
    forged = app_client.get("/v1/jobs", headers={"Authorization": "Bearer acn_0123456789ab_not-a-real-secret"})
    assert forged.status_code == 401 and forged.json()["detail"] == "invalid or revoked token"
    # a scheme other than Bearer is no token at all
    basic = app_client.get("/v1/me", headers={"Authorization": f"Basic {app_client.tokens['ada']}"})
    assert basic.status_code == 401 and basic.json()["detail"].startswith("missing token")


def test_me_names_the_caller_and_the_limits(app_client):
    ada = app_client.get("/v1/me", headers=_auth(app_client, "ada")).json()
    assert ada["name"] == "ada" and ada["admin"] is False and ada["active_jobs"] == 0
    assert ada["limits"]["max_frames"] == Settings.model_fields["max_frames"].default
    assert app_client.get("/v1/me", headers=_auth(app_client, "root")).json()["admin"] is True


def test_an_unknown_job_is_404_naming_it(app_client):
    job_id = "0123456789abcdef0123456789abcdef"
    for path in (f"/v1/jobs/{job_id}", f"/v1/jobs/{job_id}/result"):
        r = app_client.get(path, headers=_auth(app_client, "ada"))
        assert r.status_code == 404, (path, r.text)
        assert r.json()["detail"] == f"no job {job_id}"
    assert app_client.delete(f"/v1/jobs/{job_id}", headers=_auth(app_client, "ada")).status_code == 404


@pytest.mark.parametrize("options, says", [
    ("{not json", "options: not valid JSON"),
    ("[1, 2]", "options: must be a JSON object"),
    (json.dumps({"methd": "fte"}), "options: unknown option 'methd'"),
    (json.dumps({"swap_rate": "often"}), "options: swap_rate: must be 'auto' or a share from 0 to below 0.5"),
    (json.dumps({"swap_rate": 0.7}), "options: swap_rate must be 'auto' or a share from 0 to below 0.5, not 0.7"),
])
def test_bad_options_are_422_before_any_file_is_read(app_client, options, says):
    files = [("keypoints", ("cam1.csv", b"not read", "text/csv")),
             ("calibration", ("calibration.toml", b"not read either", "application/octet-stream"))]
    r = app_client.post("/v1/jobs", headers=_auth(app_client, "ada"), files=files, data={"options": options})
    assert r.status_code == 422, r.text
    assert r.json()["detail"].startswith(says), r.json()
    # nothing was stored: the caller still has no jobs
    assert app_client.get("/v1/jobs", headers=_auth(app_client, "ada")).json()["total"] == 0


def test_the_served_spec_is_the_generated_one_and_docs_are_html(app_client):
    r = app_client.get("/openapi.json")
    assert r.status_code == 200
    assert r.json() == spec()
    assert {"/v1/jobs", "/v1/jobs/{job_id}", "/healthz"} <= set(r.json()["paths"])
    docs = app_client.get("/docs")
    assert docs.status_code == 200 and docs.headers["content-type"].startswith("text/html")


@pytest.mark.parametrize("options, says", [
    ('{"motion_scale": NaN}', "options: motion_scale"),
    ('{"fps": Infinity}', "options: fps"),
    ('{"measurement_std_px": -Infinity}', "options: measurement_std_px"),
    ('{"lag_seconds": -1}', "options: lag_seconds"),
    ('{"max_iterations": 1000000000000}', "options: max_iterations"),
])
def test_nan_infinite_or_impossible_options_are_422_and_leave_nothing(app_client, options, says):
    """Issue item 7: NaN passed validation, the job row failed to write (500) and the upload stayed on disk."""
    jobs_dir = app_client.app.state.settings.jobs_dir
    before = set(jobs_dir.iterdir())
    files = [("keypoints", ("cam1.csv", b"not read", "text/csv")),
             ("calibration", ("calibration.toml", b"not read either", "application/octet-stream"))]
    r = app_client.post("/v1/jobs", headers=_auth(app_client, "ada"), files=files, data={"options": options})
    assert r.status_code == 422, r.text
    assert r.json()["detail"].startswith(says), r.json()
    assert set(jobs_dir.iterdir()) == before


FLY = EKS_FLY


def _fly_files() -> list:
    files = [("keypoints", (f"cam{x}.csv", (FLY / f"cam{x}.rng1.csv").read_bytes(), "text/csv")) for x in "ABC"]
    files.append(("calibration", ("calibration.toml", (FLY / "calibration.toml").read_bytes(), "text/plain")))
    return files


@needs(FLY)
def test_a_skeleton_matching_no_bodypart_is_refused_at_upload_with_the_points_hint(app_client):
    """Issue item 5: the fly's legs under the cheetah skeleton were accepted (202) and failed 0.4 s later."""
    jobs_dir = app_client.app.state.settings.jobs_dir
    before = set(jobs_dir.iterdir())
    r = app_client.post("/v1/jobs", headers=_auth(app_client, "ada"), files=_fly_files(),
                        data={"options": json.dumps({"method": "tri", "skeleton": "cheetah"})})
    assert r.status_code == 422, r.text
    detail = r.json()["detail"]
    assert "matches a marker of the cheetah skeleton" in detail and '"skeleton": "points"' in detail
    assert "L1A" in detail  # the file's bodyparts, so the user sees why
    assert set(jobs_dir.iterdir()) == before
    # the same files with the points skeleton are accepted
    ok = app_client.post("/v1/jobs", headers=_auth(app_client, "ada"), files=_fly_files(),
                         data={"options": json.dumps({"method": "tri", "skeleton": "points", "fps": 300})})
    assert ok.status_code == 202, ok.text
    app_client.delete(f"/v1/jobs/{ok.json()['id']}", headers=_auth(app_client, "ada"))


def test_a_keypoint_file_with_too_many_bodyparts_is_413_before_its_rows_are_read(app_client):
    """Issue item 6: a CSV with 1e6 columns was accepted and made every GET of its job 3.5 MB."""
    wide = 3 * 20_000
    csv = ("scorer" + ",s" * wide + "\nbodyparts" + "".join(f",b{j // 3}" for j in range(wide))
           + "\ncoords" + ",x,y,likelihood" * (wide // 3) + "\n0" + ",1" * wide + "\n").encode()
    files = [("keypoints", ("wide.csv", csv, "text/csv")),
             ("calibration", ("calibration.toml", b"not read", "application/octet-stream"))]
    r = app_client.post("/v1/jobs", headers=_auth(app_client, "ada"), files=files,
                        data={"options": json.dumps({"method": "tri", "skeleton": "points"})})
    assert r.status_code == 413, r.text
    assert r.json()["detail"].startswith("wide.csv: ") and "(ACINOSET_MAX_BODYPARTS)" in r.json()["detail"]


DEEP = 100_000


@pytest.mark.parametrize("field, name, content", [
    ("calibration", "calib.json", '{"cameras": ' + "[" * DEEP + "]" * DEEP + "}"),
    ("calibration", "calib.toml", "a = " + "[" * DEEP + "]" * DEEP + "\n"),
    ("calibration", "calib.toml", "a = " + "{b=" * 5000 + "1" + "}" * 5000 + "\n"),
    ("skeleton", "body.toml", "a = " + "[" * DEEP + "]" * DEEP + "\n"),
    ("options", None, '{"fps": ' + "[" * DEEP + "]" * DEEP + "}"),
])
def test_deeply_nested_files_and_options_are_422_not_a_recursion_error(app_client, small_run, field, name, content):
    """Issue item 10: each of these raised RecursionError (a 500 and about 200 KB of log)."""
    files = [("keypoints", (p.name, p.read_bytes(), "text/csv")) for p in small_run.cams]
    data = {"options": json.dumps({"method": "tri", "skeleton": "points"})}
    if field == "options":
        data = {"options": content}
    else:
        files.append((field, (name, content.encode(), "application/octet-stream")))
    if field != "calibration":
        files.append(("calibration", ("calibration.toml", small_run.calibration.read_bytes(), "text/plain")))
    r = app_client.post("/v1/jobs", headers=_auth(app_client, "ada"), files=files, data=data)
    assert r.status_code == 422, r.text
    assert r.json()["detail"] == (f"{name or 'options'}: arrays or tables nested too deeply "
                                  "(hundreds of levels inside each other)")


@pytest.mark.parametrize("cursor", ["9" * 19, "9" * 30, "9" * 5000, "-1", "1e3", "\u0661"])
def test_a_cursor_that_is_no_job_seq_is_422(app_client, cursor):
    """Issue item 10: 30 digits raised OverflowError in SQLite, 5000 digits a ValueError (500s)."""
    r = app_client.get("/v1/jobs", params={"cursor": cursor}, headers=_auth(app_client, "ada"))
    assert r.status_code == 422 and r.json()["detail"].startswith("cursor:"), r.text


@pytest.mark.parametrize("method, path, allow", [
    ("PUT", "/v1/jobs/0123456789abcdef0123456789abcdef", "DELETE, GET"),
    ("PATCH", "/v1/jobs", "GET, POST"),
    ("POST", "/healthz", "GET"),
])
def test_a_405_names_every_method_the_path_answers(app_client, method, path, allow):
    """Issue item 11: Starlette's Allow named the methods of the first route on the path only
    (PUT /v1/jobs/{id} said 'GET', not 'DELETE, GET')."""
    r = app_client.request(method, path, headers=_auth(app_client, "ada"))
    assert r.status_code == 405 and r.headers["allow"] == allow, (r.status_code, r.headers.get("allow"))
    assert r.json() == {"detail": "Method Not Allowed"}


def test_a_body_that_is_not_multipart_is_400_in_one_line(app_client):
    r = app_client.post("/v1/jobs", headers={**_auth(app_client, "ada"), "content-type": "multipart/form-data"},
                        content=b"--xx\r\nbroken")  # no boundary
    assert r.status_code == 400 and isinstance(r.json()["detail"], str), r.text


def _wait(client, job_id: str, timeout: float = 300) -> dict:
    deadline = time.time() + timeout
    while time.time() < deadline:
        job = client.get(f"/v1/jobs/{job_id}", headers=_auth(client, "root")).json()
        if job["status"] in ("succeeded", "failed", "cancelled"):
            return job
        time.sleep(0.2)
    raise AssertionError(f"job {job_id} did not finish: {job}")


def test_labels_filters_warnings_without_paths_and_what_failed(app_client, small_run, tmp_path):
    """Issue items 3 and 15: a run's label, a filter beyond status, 'succeeded with warnings', warnings
    that named the server's absolute paths, and a failed job that says whether its input was at fault."""
    from graph.io.keypoints import Keypoints, read_keypoints, write_dlc_csv

    lured = []  # each camera with one more bodypart, 'lure', which the cheetah skeleton does not have
    for p in small_run.cams:
        kp = read_keypoints(p)
        extra = Keypoints(bodyparts=kp.bodyparts + ["lure"], xy=np.concatenate([kp.xy, kp.xy[:, :1]], axis=1),
                          likelihood=np.concatenate([kp.likelihood, kp.likelihood[:, :1]], axis=1))
        write_dlc_csv(tmp_path / p.name, extra)
        lured.append(tmp_path / p.name)

    def post(cams, options):
        files = [("keypoints", (p.name, p.read_bytes(), "text/csv")) for p in cams]
        files.append(("calibration", ("calibration.toml", small_run.calibration.read_bytes(), "text/plain")))
        r = app_client.post("/v1/jobs", headers=_auth(app_client, "ada"), files=files,
                            data={"options": json.dumps({"fps": small_run.fps, **options})})
        assert r.status_code == 202, r.text
        return r.json()

    warned = post(lured, {"method": "tri", "skeleton": "cheetah", "label": "  cheetah 3,\trun 2 "})
    assert warned["label"] == "cheetah 3, run 2" and "label" not in warned["options"]
    clean = post(small_run.cams, {"method": "tri", "skeleton": "points", "label": "fly 1"})
    refused = post(small_run.cams, {"method": "tri", "skeleton": "points", "likelihood_threshold": 1.0})
    warned, clean, refused = (_wait(app_client, j["id"]) for j in (warned, clean, refused))

    assert warned["status"] == "succeeded" and warned["has_warnings"] is True
    text = " ".join(warned["result"]["warnings"])
    assert "lure" in text and "cam1.csv" in text
    assert str(app_client.app.state.settings.data_dir) not in text and "/input/" not in text
    assert clean["status"] == "succeeded" and clean["has_warnings"] is False
    assert refused["status"] == "failed" and refused["error_kind"] == "input", refused
    assert "/" not in (refused["error"] or "").replace("n/a", "")

    def listed(**params) -> list[str]:
        r = app_client.get("/v1/jobs", params=params, headers=_auth(app_client, "ada"))
        assert r.status_code == 200, r.text
        return [j["id"] for j in r.json()["jobs"]]

    assert listed(label="RUN 2") == [warned["id"]]
    assert listed(label="%") == [] and listed(label="_") == []  # no wildcards
    assert listed(warnings="true") == [warned["id"]]
    assert clean["id"] in listed(warnings="false") and warned["id"] not in listed(warnings="false")
    assert set(listed(method="tri")) >= {warned["id"], clean["id"], refused["id"]} and listed(method="fte") == []
    assert listed(since="2999-01-01T00:00:00Z") == [] and warned["id"] in listed(since="2000-01-01T00:00:00")
    bad = app_client.get("/v1/jobs", params={"method": "magic"}, headers=_auth(app_client, "ada"))
    assert bad.status_code == 422
    r = app_client.post("/v1/jobs", headers=_auth(app_client, "ada"),
                        data={"options": json.dumps({"label": "x" * 201})},
                        files=[("keypoints", ("a.csv", b"x", "text/csv")),
                               ("calibration", ("c.toml", b"x", "text/plain"))])
    assert r.status_code == 422 and "label must be at most 200" in r.json()["detail"]
