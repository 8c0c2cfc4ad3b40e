"""Result downloads in the export formats (``GET /v1/jobs/{id}/result?format=nwb|trc|c3d|csv-var``),
against a real embedded server: the same files ``acinoset export`` (graph.export) writes from the job's H5 and
calibration, read back with their own readers."""

from __future__ import annotations

import numpy as np
import pytest
from servers import Server, add_user, submit, wait_finished

EXPORTS = ("nwb", "trc", "c3d", "csv-var")


@pytest.fixture(scope="module")
def job(tmp_path_factory, small_run):
    data = tmp_path_factory.mktemp("export_data")
    token = add_user(data, "alice")
    srv = Server(data, data.parent / "export_server.log").start()
    with srv.client(token) as c:
        r = submit(c, small_run, {"method": "tri", "skeleton": "points", "fps": small_run.fps})
        assert r.status_code == 202, r.text
        done = wait_finished(c, r.json()["id"])
        assert done["status"] == "succeeded", done
        yield c, done
    srv.stop()


def test_the_job_offers_the_export_formats(job):
    _, done = job
    for fmt in EXPORTS:
        assert done["links"]["result"][fmt] == f"/v1/jobs/{done['id']}/result?format={fmt}"
        assert fmt in done["result"]["formats"]


def test_the_formats_are_listed_as_the_library_declares_them(job):
    """GET /v1/formats, which the job page names its buttons and files from: every download, the
    exports as graph.export declares them, and those offered are the job's links."""
    from graph.export import REGISTRY

    client, done = job
    r = client.get("/v1/formats")
    assert r.status_code == 200, r.text
    listed = {f["name"]: f for f in r.json()}
    assert list(listed) == ["csv", "h5", "json", "report", *REGISTRY]
    for name, f in REGISTRY.items():
        assert listed[name] == {"name": name, "label": f.label, "description": f.help, "extension": f.extension,
                                "media_type": f.media_type, "export": True, "offered": True}
    assert listed["report"]["extension"] == ".report.json" and listed["csv"]["export"] is False
    assert [name for name, f in listed.items() if f["offered"]] == list(done["links"]["result"])


def test_each_export_is_what_the_command_writes(job, small_run, tmp_path):
    client, done = job
    formats = {f["name"]: f for f in client.get("/v1/formats").json()}
    h5 = tmp_path / "job.h5"
    h5.write_bytes(client.get(done["links"]["result"]["h5"]).content)
    from graph.export import export
    from graph.io.results import read_result

    res = read_result(h5)
    from graph.io.results import read_calibration

    assert read_calibration(h5).names == res.camera_names  # the job's H5 carries its rig
    for fmt in EXPORTS:
        r = client.get(done["links"]["result"][fmt])
        assert r.status_code == 200, r.text
        ext = formats[fmt]["extension"]
        assert ext == {"csv-var": ".var.csv"}.get(fmt, f".{fmt}")  # the file names downloads have had
        assert r.headers["content-disposition"].endswith(f'filename="{done["id"]}{ext}"')
        assert r.headers["content-type"].split(";")[0] == formats[fmt]["media_type"]
        got = tmp_path / f"rest{ext}"
        got.write_bytes(r.content)
        mine = export(h5, fmt, tmp_path / f"lib{ext}", calibration=small_run.calibration)
        if fmt == "csv-var":
            assert got.read_bytes() == mine.read_bytes()
        elif fmt == "trc":  # the header's first line names the file
            assert got.read_text().split("\n")[1:] == mine.read_text().split("\n")[1:]
        elif fmt == "c3d":
            import ezc3d

            a, b = ezc3d.c3d(str(got)), ezc3d.c3d(str(mine))
            assert list(a["parameters"]["POINT"]["LABELS"]["value"]) == res.markers
            np.testing.assert_array_equal(a["data"]["points"], b["data"]["points"])
            np.testing.assert_array_equal(a["data"]["meta_points"]["residuals"], b["data"]["meta_points"]["residuals"])
        else:
            import pynwb

            with pynwb.NWBHDF5IO(str(got), "r", load_namespaces=True) as io:
                nwb = io.read()
                pose = nwb.processing["behavior"]["PoseEstimation"]
                assert sorted(pose.pose_estimation_series) == sorted(res.markers)  # a group: read back by name
                assert list(pose.skeleton.nodes[:]) == res.markers  # the order
                np.testing.assert_allclose(pose.pose_estimation_series[res.markers[0]].data[:],
                                           res.positions[:, 0], atol=1e-6)
                assert len(nwb.devices) == len(res.camera_names)
    again = client.get(done["links"]["result"]["trc"])  # made once, then served
    assert again.content == (tmp_path / "rest.trc").read_bytes()
