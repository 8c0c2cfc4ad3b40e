"""``POST /v1/batches``: an Anipose project in one upload, a job per trial, a batch status; against a
real embedded server. Each trial's job gives what ``acinoset anipose`` writes for it."""

from __future__ import annotations

import io
import time
import zipfile
from pathlib import Path

import numpy as np
import pytest
from servers import Server, add_user

pytest.importorskip("tables")


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    data = tmp_path_factory.mktemp("batch_data")
    srv = Server(data, data.parent / "batch_server.log").start()
    srv.tokens = {"alice": add_user(data, "alice"), "bob": add_user(data, "bob")}
    yield srv
    srv.stop()


def zipped(root: Path) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as z:
        for p in sorted(root.rglob("*")):
            if p.is_file():
                z.write(p, (Path(root.name) / p.relative_to(root)).as_posix())  # one top folder
    return buf.getvalue()


def wait_batch(client, url: str, timeout: float = 300.0) -> dict:
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout:
        b = client.get(url).json()
        if b["status"] != "running":
            return b
        time.sleep(0.5)
    raise AssertionError(f"batch still running after {timeout} s: {b}")


def test_a_project_becomes_a_job_per_trial(server, tmp_path):
    from graph.anipose import load_project, run_project
    from graph.anipose.simulate import write_dlc_h5, write_project
    from graph.io.results import read_result

    root = write_project(tmp_path / "project", frames=40, optim=False,
                         extra_config="\n[cameras.B]\noffset = [12, -7]\n")
    bad = root / "2026-12-01" / "pose-2d"
    for cam in "AB":
        write_dlc_h5(bad / f"broken_{cam}.h5", ["nose"], np.zeros((40, 1, 2)), np.ones((40, 1)))
    (bad / "broken_C.h5").write_bytes(b"not HDF5")
    archive = zipped(root)
    with server.client(server.tokens["alice"]) as alice, server.client(server.tokens["bob"]) as bob:
        r = alice.post("/v1/batches", files={"project": ("project.zip", archive, "application/zip")},
                       data={"options": '{"motion_scale": 1.0}'})
        assert r.status_code == 202, r.text
        batch = r.json()
        assert r.headers["location"] == batch["links"]["self"] == f"/v1/batches/{batch['id']}"
        assert [t["trial"] for t in batch["trials"]] == ["2026-11-30/run1", "2026-11-30/run2",
                                                         "2026-12-01/broken", "2026-12-01/run3"]
        broken = batch["trials"][2]
        assert broken["status"] == "refused" and broken["job_id"] is None and "broken_C.h5" in broken["error"]
        assert any(k.startswith("[triangulation] scale_smooth") for k in batch["ignored"])
        done = wait_batch(alice, batch["links"]["self"])
        assert done["status"] == "partial" and done["counts"]["succeeded"] == 3 and done["counts"]["refused"] == 1
        assert bob.get(batch["links"]["self"]).status_code == 404  # another user's batch

        outcomes = run_project(load_project(root))  # what acinoset anipose writes for the same project
        assert [o.status for o in outcomes] == ["solved", "solved", "failed", "solved"]
        for t, o in zip(done["trials"], outcomes):
            if t["status"] != "succeeded":
                continue
            assert alice.get(t["link"]).json()["options"]["method"] == "tri"
            h5 = tmp_path / f"{t['job_id']}.h5"
            h5.write_bytes(alice.get(f"{t['link']}/result", params={"format": "h5"}).content)
            ours, cli = read_result(h5), read_result(o.trial.h5)
            assert ours.markers == cli.markers
            np.testing.assert_allclose(ours.positions, cli.positions, atol=1e-9, rtol=0)

        for files, fragment in (({"project": ("p.zip", b"not a zip", "application/zip")}, "not a zip archive"),
                                ({"project": ("p.zip", zipped(bad), "application/zip")}, "no config.toml")):
            r = alice.post("/v1/batches", files=files)
            assert r.status_code == 422 and fragment in r.json()["detail"], r.text
