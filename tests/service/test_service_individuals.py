"""A job of several animals through a real embedded server: multi-animal DeepLabCut files in, each
camera's detections assigned to individuals by geometry, each one's result downloaded by name, the
job's report saying who is who."""

from __future__ import annotations

import json
from urllib.parse import quote

import numpy as np
import pytest
from group_files import write_dlc_multi
from servers import Server, add_user, wait_finished

from graph.io.calibration import write_anipose_toml
from graph.io.results import read_anipose_csv
from graph.metrics import group_error
from graph.simulate import ring_rig
from graph.simulate_group import simulate_group

NAMES = ["dam", "cub #2"]  # a name that needs quoting in a link


@pytest.fixture(scope="module")
def pair(tmp_path_factory):
    folder = tmp_path_factory.mktemp("pair_files")
    rig = ring_rig(4)
    run = simulate_group(rig, animals=2, frames=300, seed=11)
    write_anipose_toml(folder / "calibration.toml", rig)
    cams = [write_dlc_multi(folder / f"cam{c + 1}.csv", t, NAMES) for c, t in enumerate(run.tracks)]
    return run, cams, folder / "calibration.toml"


@pytest.fixture(scope="module")
def client(tmp_path_factory):
    data = tmp_path_factory.mktemp("individuals_data")
    token = add_user(data, "alice")
    srv = Server(data, data.parent / "individuals_server.log").start()
    with srv.client(token) as c:
        yield c
    srv.stop()


def post(client, cams, calibration, options: dict):
    files = [("keypoints", (p.name, p.read_bytes(), "text/csv")) for p in cams]
    files.append(("calibration", (calibration.name, calibration.read_bytes(), "application/octet-stream")))
    return client.post("/v1/jobs", files=files, data={"options": json.dumps(options)})


@pytest.fixture(scope="module")
def done(client, pair):
    _, cams, calibration = pair
    r = post(client, cams, calibration, {"method": "fte", "skeleton": "points", "fps": 60})
    assert r.status_code == 202, r.text
    assert r.json()["inputs"]["individuals"] == 2
    job = wait_finished(client, r.json()["id"], timeout=300)
    assert job["status"] == "succeeded", job
    return job


def test_each_individual_is_solved_and_downloaded_by_name(client, pair, done):
    run, _, _ = pair
    identity = done["result"]["identity"]
    assert sorted(identity["individuals"]) == sorted(NAMES) and identity["count"] == "found"
    assert set(identity["switches_corrected"]) == {"cam1", "cam2", "cam3", "cam4"}
    links = done["links"]["individuals"]
    assert set(links) == set(NAMES)
    assert links["cub #2"]["csv"] == f"/v1/jobs/{done['id']}/result?format=csv&individual={quote('cub #2', safe='')}"
    est = []
    for name in identity["individuals"]:
        r = client.get(links[name]["csv"])
        assert r.status_code == 200, r.text
        safe = "cub_2" if name == "cub #2" else name
        assert r.headers["content-disposition"].endswith(f'filename="{done["id"]}.{safe}.csv"')
        path = pair[2].parent / f"got.{safe}.csv"
        path.write_bytes(r.content)
        est.append(read_anipose_csv(path).positions)
    g = group_error(np.stack(est), run.positions, run.markers)
    assert g.switches == 0 and max(e.mean_mm for e in g.errors) < 8


def test_the_report_is_the_jobs_and_each_format_is_each_ones(client, done):
    report = client.get(f"/v1/jobs/{done['id']}/result?format=report")
    assert report.status_code == 200
    doc = report.json()
    assert set(doc["individuals"]) == set(NAMES) and doc["identity"] == done["result"]["identity"]
    for fmt in ("h5", "json", "trc"):
        r = client.get(done["links"]["individuals"]["dam"][fmt])
        assert r.status_code == 200, (fmt, r.text)
    own = client.get(done["links"]["individuals"]["dam"]["report"]).json()
    assert own["method"] == "fte" and own["frames"] == 300 and "identity" not in own


def test_an_individuals_nwb_is_its_own_subject(client, done, tmp_path):
    """NWB holds one subject a file: each individual's export is one, named as movement names it."""
    pynwb = pytest.importorskip("pynwb")
    pytest.importorskip("ndx_pose")
    r = client.get(done["links"]["individuals"]["cub #2"]["nwb"])
    assert r.status_code == 200, r.text
    path = tmp_path / "cub.nwb"
    path.write_bytes(r.content)
    with pynwb.NWBHDF5IO(str(path), "r") as io:
        nwb = io.read()
        assert nwb.subject.subject_id == "cub #2" and nwb.identifier == "cub #2"
        assert "PoseEstimation" in nwb.processing["behavior"].data_interfaces


def test_the_jobs_view_holds_them_all(client, done):
    """The job's own result.json (what its page draws at first): every individual side by side."""
    assert set(done["links"]["result"]) == {"json", "report", "h5"}
    r = client.get(done["links"]["result"]["json"])
    assert r.status_code == 200, r.text
    payload = r.json()
    names = [i["name"] for i in payload["individuals"]]
    assert sorted(names) == sorted(NAMES)
    assert [i["markers"] for i in payload["individuals"]] == [[0, 12], [12, 12]]
    assert len(payload["markers"]) == 24 and payload["markers"][0].startswith(f"{names[0]} ")
    assert len(payload["positions"]) == 300 and len(payload["positions"][0]) == 24


def test_the_jobs_h5_has_an_individuals_axis(client, done, tmp_path):
    """The job's own result.h5: every individual on one axis, each equal to its own H5."""
    from graph.io.results import read_individuals, read_result

    r = client.get(done["links"]["result"]["h5"])
    assert r.status_code == 200, r.text
    path = tmp_path / "all.h5"
    path.write_bytes(r.content)
    assert read_individuals(path) == done["result"]["identity"]["individuals"]
    own = tmp_path / "dam.h5"
    own.write_bytes(client.get(done["links"]["individuals"]["dam"]["h5"]).content)
    np.testing.assert_array_equal(read_result(path, individual="dam").positions, read_result(own).positions)


def test_a_download_that_names_no_one_or_no_one_known(client, done):
    r = client.get(f"/v1/jobs/{done['id']}/result?format=csv")
    assert r.status_code == 422 and "give individual=NAME" in r.json()["detail"]
    assert "dam" in r.json()["detail"] and "\n" not in r.json()["detail"]
    r = client.get(f"/v1/jobs/{done['id']}/result?format=csv&individual=nobody")
    assert r.status_code == 404 and "no individual 'nobody'" in r.json()["detail"]


def test_the_count_is_an_option(client, pair):
    _, cams, calibration = pair
    r = post(client, cams, calibration, {"method": "tri", "skeleton": "points", "fps": 60, "individuals": 0})
    assert r.status_code == 422 and "individuals" in r.json()["detail"]
    r = post(client, cams, calibration, {"method": "tri", "skeleton": "points", "fps": 60, "individual": "dam"})
    assert r.status_code == 202, r.text
    one = wait_finished(client, r.json()["id"], timeout=300)
    assert one["status"] == "succeeded" and one["result"].get("identity") is None
    assert one["links"]["individuals"] is None
    assert client.get(one["links"]["result"]["csv"]).status_code == 200
    r = client.get(one["links"]["result"]["csv"] + "&individual=dam")
    assert r.status_code == 422 and "solved one individual" in r.json()["detail"]
