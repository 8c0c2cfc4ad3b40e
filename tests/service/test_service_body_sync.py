"""The body and the clocks as job options, on a real server: accepted, solved, reported."""

from __future__ import annotations

import pytest
from servers import Server, add_user, submit, submit_ok, wait_finished


@pytest.fixture(scope="module")
def client(tmp_path_factory):
    data = tmp_path_factory.mktemp("body_sync_data")
    token = add_user(data, "carol")
    srv = Server(data, data.parent / "body_sync_server.log").start()
    with srv.client(token) as c:
        yield c
    srv.stop()


def test_a_job_estimates_the_body_and_the_clocks(client, small_run):
    job_id = submit_ok(client, small_run, {"method": "fte", "fps": small_run.fps, "body": "estimate",
                                           "sync": "estimate"})
    job = wait_finished(client, job_id)
    assert job["status"] == "succeeded", job
    assert job["options"]["body"] == "estimate" and job["options"]["sync"] == "estimate"
    report = client.get(f"/v1/jobs/{job_id}/result", params={"format": "report"}).json()
    assert set(report["body_lengths"]["spine"]) == {"length_m", "std_m", "model_m"}
    assert len(report["time_offsets_frames"]) == 6 and report["time_offsets_frames"][0] == 0
    payload = client.get(f"/v1/jobs/{job_id}/result", params={"format": "json"}).json()
    assert payload["report"]["body_lengths"] == report["body_lengths"]
    # a body given to the next run of the same animal, and offsets given in frames
    lengths = {g: v["length_m"] for g, v in report["body_lengths"].items()}
    again = submit_ok(client, small_run, {"fps": small_run.fps, "body": "given", "body_lengths": lengths,
                                          "time_offsets": [0, 0, 0, 0, 0, 0.5]})
    job = wait_finished(client, again)
    assert job["status"] == "succeeded", job
    rep2 = client.get(f"/v1/jobs/{again}/result", params={"format": "report"}).json()
    assert rep2["body_lengths"]["spine"]["length_m"] == pytest.approx(lengths["spine"])
    assert rep2["time_offsets_frames"][5] == 0.5


@pytest.mark.parametrize("options,words", [
    ({"body": "guess"}, "body"),
    ({"body": "given"}, "body_lengths"),
    ({"sync": "later"}, "sync"),
    ({"time_offsets": ["a"]}, "time_offsets"),
])
def test_bad_body_and_clock_options_are_refused_at_upload(client, small_run, options, words):
    r = submit(client, small_run, options)
    assert r.status_code == 422, r.text
    assert words in r.json()["detail"] and "\n" not in r.json()["detail"]
