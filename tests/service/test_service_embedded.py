"""The embedded backend survives: cancel really stops a solve, a killed solve process is run again
(a bounded number of times), and kill -9 of the whole service loses no job."""

from __future__ import annotations

import os
import signal
import time

import pytest
from servers import Server, add_user, pid_alive, submit_ok, wait_dead, wait_finished, wait_for, wait_solving

LONG = {"method": "fte", "skeleton": "cheetah"}
FAST = {"method": "tri", "skeleton": "points", "fps": 120.0}


def _pid(job: dict) -> int:
    return int(job["worker"].rsplit(":", 1)[1])


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    data = tmp_path_factory.mktemp("embedded_data")
    token = add_user(data, "erin")
    srv = Server(data, data.parent / "embedded_server.log", workers=2).start()
    srv.token = token
    yield srv
    srv.stop()


@pytest.fixture
def client(server):
    with server.client(server.token) as c:
        yield c


def test_cancel_stops_the_running_solve_and_skips_a_queued_one(server, client, long_run):
    a = submit_ok(client, long_run, LONG)
    b = submit_ok(client, long_run, LONG)
    c = submit_ok(client, long_run, LONG)  # two workers: c waits in the queue
    running = wait_solving(client, a)
    pid = _pid(running)
    assert pid_alive(pid)
    # the queued one first, while both workers are busy: once a is cancelled its worker takes c at once
    queued = client.get(f"/v1/jobs/{c}").json()
    if queued["status"] == "queued":
        assert client.delete(f"/v1/jobs/{c}").json()["status"] == "cancelled"
        time.sleep(1.0)
        assert client.get(f"/v1/jobs/{c}").json()["attempts"] == 0  # it never ran
    else:
        client.delete(f"/v1/jobs/{c}")
    r = client.delete(f"/v1/jobs/{a}")
    assert r.status_code == 200 and r.json()["status"] == "cancelled"
    assert wait_dead(pid, 5), "the solve process still runs after the cancel"
    client.delete(f"/v1/jobs/{b}")
    for j in (a, b, c):
        assert client.get(f"/v1/jobs/{j}").json()["status"] == "cancelled"
    # a cancelled job is finished: DELETE again removes it and its files
    assert client.delete(f"/v1/jobs/{a}").status_code == 204
    assert not (server.data_dir / "jobs" / a).exists()
    assert client.get("/healthz").json()["running"] == 0


def test_a_killed_solve_process_runs_again(client, long_run):
    job_id = submit_ok(client, long_run, LONG)
    first = wait_solving(client, job_id)
    os.kill(_pid(first), signal.SIGKILL)
    done = wait_finished(client, job_id)
    assert done["status"] == "succeeded", done
    assert done["attempts"] == 2
    assert done["interruption"] == "attempt 1 of 3 interrupted: the solve process was killed (SIGKILL)"
    assert _pid(done) != _pid(first)
    assert client.get("/healthz").json()["status"] == "ok"


def test_a_job_whose_process_keeps_dying_fails_after_max_attempts(client, long_run):
    job_id = submit_ok(client, long_run, LONG)
    pids = []
    for attempt in (1, 2, 3):
        job = wait_for(client, job_id, lambda j, n=attempt: j["attempts"] == n and j["status"] == "running"
                       and j["worker"] and not j["worker"].endswith(":starting"), 120, f"on attempt {attempt}")
        pids.append(_pid(job))
        os.kill(pids[-1], signal.SIGKILL)
    failed = wait_finished(client, job_id)
    assert failed["status"] == "failed" and failed["attempts"] == 3
    assert failed["error"] == "gave up after 3 interrupted attempts; last: the solve process was killed (SIGKILL)"
    assert len(set(pids)) == 3


@pytest.mark.slow  # over 12 s here
def test_kill_9_of_the_whole_service_loses_nothing(tmp_path, long_run, small_run):
    data = tmp_path / "data"
    token = add_user(data, "frank")
    srv = Server(data, tmp_path / "server1.log", workers=2).start()
    with srv.client(token) as c:
        long_ids = [submit_ok(c, long_run, LONG) for _ in range(2)]
        short_ids = [submit_ok(c, small_run, FAST) for _ in range(4)]
        solving = [wait_solving(c, j) for j in long_ids]
    solve_pids = [_pid(j) for j in solving]
    # kill -9 the server process alone: its solve processes must not outlive it
    os.kill(srv.pid, signal.SIGKILL)
    srv.p.wait(timeout=10)
    for pid in solve_pids:
        assert wait_dead(pid, 10), f"solve process {pid} outlived its server"
    srv.kill9()  # and anything else of its process group

    srv2 = Server(data, tmp_path / "server2.log", workers=2).start()
    try:
        with srv2.client(token) as c:
            finished = [wait_finished(c, j, timeout=240) for j in long_ids + short_ids]
            assert [j["status"] for j in finished] == ["succeeded"] * 6, finished
            for j in finished[:2]:
                assert j["attempts"] == 2 and "the service stopped while it ran" in j["interruption"]
            for j in finished[2:]:
                assert j["attempts"] in (1, 2)
            listed = c.get("/v1/jobs", params={"limit": 100}).json()
            assert listed["total"] == 6 and sorted(j["id"] for j in listed["jobs"]) == sorted(long_ids + short_ids)
            for j in long_ids + short_ids:
                assert c.get(f"/v1/jobs/{j}/result").status_code == 200
    finally:
        srv2.stop()
    # no half-written result or upload was left behind
    leftovers = [p for p in (data / "jobs").rglob("*") if p.name.endswith(".tmp") or p.name.startswith(".upload-")]
    assert leftovers == []


@pytest.mark.slow  # over 12 s here
def test_an_orderly_stop_gives_running_jobs_back_without_using_an_attempt(tmp_path, long_run):
    data = tmp_path / "data"
    token = add_user(data, "mia")
    srv = Server(data, tmp_path / "server1.log", workers=1).start()
    with srv.client(token) as c:
        job_id = submit_ok(c, long_run, LONG)
        pid = _pid(wait_solving(c, job_id))
    # SIGTERM: uvicorn shuts down in order (then exits with the signal's status), the backend stops its runs
    assert srv.stop() in (0, -signal.SIGTERM)
    assert "leaked" not in srv.log()
    assert wait_dead(pid, 10)
    srv2 = Server(data, tmp_path / "server2.log", workers=1).start()
    try:
        with srv2.client(token) as c:
            done = wait_finished(c, job_id)
            assert done["status"] == "succeeded" and done["attempts"] == 1, done
            assert done["interruption"] == "the service was stopped while it ran; it runs again"
    finally:
        srv2.stop()


def test_a_solve_over_the_time_limit_fails(tmp_path, long_run):
    data = tmp_path / "data"
    token = add_user(data, "noa")
    srv = Server(data, tmp_path / "server.log", workers=1,
                 env={"ACINOSET_JOB_TIMEOUT_SECONDS": "1.5", "ACINOSET_WARM_START": "0"}).start()
    try:
        with srv.client(token) as c:
            job_id = submit_ok(c, long_run, LONG)
            pid = _pid(wait_for(c, job_id, lambda j: j["status"] == "running" and j["worker"]
                                and not j["worker"].endswith(":starting"), 60))
            done = wait_finished(c, job_id, 60)
            assert done["status"] == "failed" and done["attempts"] == 1
            assert done["error"] == "the solve ran longer than the time limit of 1.5 s"
            assert wait_dead(pid, 5)
    finally:
        srv.stop()
