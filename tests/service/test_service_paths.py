"""No server path in anything a user downloads (security issue 25: the NWB's reference-frame text,
result.h5's calibration source and the job page's warnings carried ``<data dir>/jobs/<id>/input/...``).
Two real jobs on an embedded server: a cheetah run with an uploaded skeleton file, and SLEAP's session
(its calibration in millimetres, one camera disagreeing: both warned of, naming the files); every
download format and the job's own answer are searched for the data dir."""

from __future__ import annotations

import json

import pytest
from servers import ROOT, Server, add_user, wait_finished
from shared_data import SLEAP_MINIMAL, needs

SESSION = SLEAP_MINIMAL


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    data = tmp_path_factory.mktemp("paths_data")
    token = add_user(data, "alice")
    srv = Server(data, data.parent / "paths_server.log").start()
    with srv.client(token) as c:
        yield c, data
    srv.stop()


def _downloads(client, done) -> dict[str, bytes]:
    out = {fmt: client.get(href).content for fmt, href in done["links"]["result"].items()}
    out["job"] = client.get(done["links"]["self"]).content
    return out


def _job(client, files, options) -> dict:
    r = client.post("/v1/jobs", files=files, data={"options": json.dumps(options)})
    assert r.status_code == 202, r.text
    done = wait_finished(client, r.json()["id"])
    assert done["status"] == "succeeded", done
    return done


def test_an_uploaded_skeleton_and_calibration_are_named_by_their_file_names(server, small_run):
    client, data = server
    skeleton = ROOT / "graph" / "skeletons" / "cheetah.toml"
    files = [("keypoints", (p.name, p.read_bytes(), "text/csv")) for p in small_run.cams]
    files.append(("calibration", (small_run.calibration.name, small_run.calibration.read_bytes(), "text/plain")))
    files.append(("skeleton", ("my_cheetah.toml", skeleton.read_bytes(), "text/plain")))
    done = _job(client, files, {"method": "tri", "fps": small_run.fps})
    got = _downloads(client, done)
    assert set(got) >= {"csv", "h5", "json", "report", "nwb", "trc", "c3d", "csv-var", "job"}
    for fmt, content in got.items():
        assert str(data).encode() not in content, fmt
        assert b"/input/" not in content, fmt


@needs(SESSION)
def test_warnings_that_name_the_inputs_name_them_without_the_server_path(server):
    client, data = server
    files = [("keypoints", (f"{c}.analysis.h5", (SESSION / c / f"minimal_{c}_proofread.analysis.h5").read_bytes(),
                            "application/x-hdf5")) for c in ("back", "mid", "side", "top")]
    files.append(("calibration", ("calibration.toml", (SESSION / "calibration.toml").read_bytes(), "text/plain")))
    done = _job(client, files, {"method": "tri", "skeleton": "points", "fps": 30, "likelihood_threshold": 0})
    warnings = done["result"]["warnings"]
    assert any(w.startswith("calibration.toml: cameras are 93 units") for w in warnings), warnings
    got = _downloads(client, done)
    report = json.loads(got["report"])
    assert any(w.startswith("calibration.toml: cameras are 93 units") for w in report["warnings"]), report
    for fmt, content in got.items():
        assert str(data).encode() not in content, fmt
        assert b"/input/" not in content, fmt
