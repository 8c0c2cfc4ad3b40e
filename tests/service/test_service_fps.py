"""A job's frame rate, as the command line's --fps: required in the options unless the uploaded files
record one (SLEAP's analysis files may; DeepLabCut's never do), and the job's options say which was used."""

from __future__ import annotations

import json
import os
from pathlib import Path

import h5py
import pytest
from fastapi.testclient import TestClient
from servers import add_user
from shared_data import SLEAP_MINIMAL

from service.app import create_app
from service.settings import Settings

SESSION = SLEAP_MINIMAL
CAMERAS = ("back", "mid", "side", "top")


@pytest.fixture(scope="module")
def client(tmp_path_factory):
    data = tmp_path_factory.mktemp("fps_data")
    token = add_user(data, "ada")
    app = create_app(Settings(data_dir=data, workers=1, upload_readers=0, warm_start=False))
    environ = dict(os.environ)
    try:
        with TestClient(app) as c:
            c.headers["Authorization"] = f"Bearer {token}"
            yield c
    finally:
        os.environ.clear()
        os.environ.update(environ)


def _post(client, cams: list[Path], calibration: Path, options: dict):
    files = [("keypoints", (p.name, p.read_bytes(), "application/octet-stream")) for p in cams]
    files.append(("calibration", (calibration.name, calibration.read_bytes(), "text/plain")))
    return client.post("/v1/jobs", files=files, data={"options": json.dumps(options)})


def test_a_job_without_a_frame_rate_is_refused_unless_its_files_record_one(client, small_run, tmp_path):
    jobs_dir = client.app.state.settings.jobs_dir
    before = set(jobs_dir.iterdir())
    r = _post(client, small_run.cams, small_run.calibration, {"method": "tri"})
    assert r.status_code == 422 and r.json()["detail"].startswith("options: fps is required"), r.text
    assert set(jobs_dir.iterdir()) == before
    given = _post(client, small_run.cams, small_run.calibration, {"method": "tri", "fps": small_run.fps})
    assert given.status_code == 202 and given.json()["options"]["fps"] == small_run.fps, given.text
    if not SESSION.is_dir():
        pytest.skip("the SLEAP session is not on this machine")
    recorded = []
    for c in CAMERAS:
        path = tmp_path / f"minimal_{c}.analysis.h5"
        path.write_bytes((SESSION / c / f"minimal_{c}_proofread.analysis.h5").read_bytes())
        with h5py.File(path, "r+") as f:
            f.attrs["fps"] = 30.0
        recorded.append(path)
    own = _post(client, recorded, SESSION / "calibration.toml", {"method": "tri", "skeleton": "points"})
    assert own.status_code == 202 and own.json()["options"]["fps"] == 30.0, own.text
    plain = [SESSION / c / f"minimal_{c}_proofread.analysis.h5" for c in CAMERAS]
    refused = _post(client, plain, SESSION / "calibration.toml", {"method": "tri", "skeleton": "points"})
    assert refused.status_code == 422 and "fps is required" in refused.json()["detail"], refused.text
