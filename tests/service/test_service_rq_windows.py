"""One long job over several RQ workers (real redis-server, server and workers): the job's windows are
shared with the worker that is idle, and the answer is the one the library gives, byte for byte, whoever
solved which window; a helper killed mid-run costs time, not the answer. The same with the data dir
shared with the workers: the job's files go by path, none through Redis."""

from __future__ import annotations

import os
import signal
import time

import pytest
from servers import children, have_redis, library_csv, make_run, rq_server, submit, wait_finished

pytestmark = pytest.mark.skipif(not have_redis(), reason="needs Debian's redis-server (.ci/run installs it)")

FRAMES = 6000
CORE = 500


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    return make_run(tmp_path_factory.mktemp("shared_run"), frames=FRAMES, cameras=4, seed=5)


@pytest.fixture(scope="module")
def library(run, tmp_path_factory):
    return library_csv(run, CORE, tmp_path_factory.mktemp("shared_library"))


class Rig:
    """redis-server, a server on the RQ backend and two workers (``shared``: the data dir theirs too)."""

    def __init__(self, base, shared: bool = False):
        self.pool, self.token, self.server = rq_server(base, "alice", shared)
        self.pool.start_workers(data_dir=base / "data" if shared else None)
        self.pool.wait_idle()  # both there when a job starts: it invites a helper for each idle worker
        self.workers = self.pool.workers

    def stop(self):
        self.server.stop()
        self.pool.stop()


@pytest.fixture
def rig(tmp_path):
    r = Rig(tmp_path)
    yield r
    r.stop()


def _job(rig, run):
    with rig.server.client(rig.token) as c:
        r = submit(c, run, {"method": "fte", "window_frames": CORE})
        assert r.status_code == 202, r.text
        return r.json()["id"]


def test_a_long_job_is_shared_by_two_workers_with_the_librarys_answer(rig, run, library):
    job = _job(rig, run)
    with rig.server.client(rig.token) as c:
        done = wait_finished(c, job, timeout=600)
        assert done["status"] == "succeeded", done
        report = c.get(done["links"]["result"]["report"]).json()
        csv = c.get(done["links"]["result"]["csv"]).content
    solved_by = report["windows"]["solved_by"]
    assert sum(solved_by.values()) == report["windows"]["count"] == FRAMES // CORE
    assert sorted(solved_by) == ["w1", "w2"], solved_by  # each worker solved windows
    assert csv == library


@pytest.mark.slow  # a helper killed: its window waits for its heartbeat to run out (30 s)
def test_a_helper_killed_mid_run_costs_time_not_the_answer(rig, run, library):
    job = _job(rig, run)
    # the helper: the worker whose work horse started second
    deadline = time.time() + 120
    helper = None
    while time.time() < deadline and helper is None:
        busy = {n: children(w.pid) for n, w in rig.workers.items()}
        if all(busy.values()):
            time.sleep(3.0)  # the helper has staged the run and is solving windows
            helper = max(busy, key=lambda n: busy[n][0])
        time.sleep(0.05)
    assert helper is not None, "the second worker never started a helper"
    for pid in children(rig.workers[helper].pid):
        os.kill(pid, signal.SIGKILL)
    with rig.server.client(rig.token) as c:
        done = wait_finished(c, job, timeout=600)
        assert done["status"] == "succeeded", done
        csv = c.get(done["links"]["result"]["csv"]).content
    assert csv == library


def test_a_shared_data_dir_sends_no_file_through_redis(tmp_path, run, library):
    """The server and its workers share the data dir: while the job runs Redis holds none of its
    files, the workers write the results beside the inputs, and the answer is the same bytes."""
    from redis import Redis

    from service.store.jobfiles import input_key, result_key

    rig = Rig(tmp_path, shared=True)
    try:
        job = _job(rig, run)
        redis = Redis.from_url(rig.pool.redis.url)
        files = []
        with rig.server.client(rig.token) as c:
            while (status := c.get(f"/v1/jobs/{job}").json()["status"]) in ("queued", "running"):
                files += [k for prefix in (input_key(""), result_key("")) for k in redis.scan_iter(match=prefix + "*")]
                time.sleep(0.2)
            done = wait_finished(c, job, timeout=60)
            assert done["status"] == "succeeded", done
            report = c.get(done["links"]["result"]["report"]).json()
            csv = c.get(done["links"]["result"]["csv"]).content
        assert status == "succeeded" and files == []
        assert sorted(report["windows"]["solved_by"]) == ["w1", "w2"]
        # the cameras staged once, in the job's folder, by whichever worker claimed each
        assert sum(report["windows"]["staged_by"].values()) == 4 and set(report["windows"]["staged_by"]) <= {"w1", "w2"}
        assert csv == library
        assert not list((tmp_path / "data" / "jobs" / job).glob("result.*.tmp"))  # installed, nothing left
    finally:
        rig.stop()


def test_a_worker_that_does_not_see_the_shared_data_dir_says_so(tmp_path, run):
    pool, token, server = rq_server(tmp_path, "alice", shared=True)
    try:
        pool.start_workers(["w1"], data_dir=tmp_path / "elsewhere")
        with server.client(token) as c:
            r = submit(c, run, {"method": "tri"})
            done = wait_finished(c, r.json()["id"], timeout=120)
        assert done["status"] == "failed"
        assert "does not see the server's data dir" in done["error"] and "\n" not in done["error"], done["error"]
    finally:
        server.stop()
        pool.stop()


def test_cameras_staged_together_survive_a_helper_that_died_and_a_job_that_ended(tmp_path, run):
    """The staging protocol against a real redis-server: a camera claimed by a helper whose heartbeat is
    gone is taken over by the work horse (one taker) and the run comes out whole; a helper that comes
    after the job's keys went, or whose job's folder is gone, stages nothing and makes no folder."""
    from redis import Redis as RedisClient
    from rq.job import Job
    from rq.serializers import JSONSerializer
    from servers import Redis

    from graph.io.keypoints import read_blocks
    from graph.io.staged import StagedRun
    from service.run.redis_windows import TOGETHER, Keys, RedisBoard
    from service.run.shared_windows import PARENT, stage_together

    server = Redis(tmp_path / "redis", tmp_path / "redis.log").start()
    try:
        r = RedisClient.from_url(server.url)
        token, paths = "job-token", [str(p) for p in run.cams]
        parent = Job.create("os.getpid", id=token, connection=r, serializer=JSONSerializer)
        parent.save()
        parent.set_status("started")  # the job's work horse is running
        k_, board = Keys(token), RedisBoard(r, token, ttl=60, shared=True)
        folder = tmp_path / "result.tmp" / "staged"
        folder.mkdir(parents=True)
        r.hset(k_.staging, mapping={TOGETHER: 1, "1": "helper-1@w2"})  # camera 2 claimed, its helper dead
        got = stage_together(board, PARENT, paths, folder, read_blocks)
        assert isinstance(got, StagedRun) and len(got.cameras) == len(paths) and got.frames == run.frames
        assert r.hget(k_.staging, "1") == PARENT.encode()  # taken over, by one
        assert StagedRun(folder).unstaged(len(paths)) == []

        r.delete(k_.staging)  # the job ended: its keys are gone
        late = tmp_path / "late"
        late.mkdir()
        assert stage_together(board, "helper-2@w2", paths, late, read_blocks) is None
        assert list(late.iterdir()) == []
        with pytest.raises(RuntimeError, match="staging claims are gone"):
            stage_together(board, PARENT, paths, late, read_blocks)

        r.hset(k_.staging, TOGETHER, 1)
        gone = tmp_path / "removed" / "staged"
        assert stage_together(board, "helper-3@w2", paths, gone, read_blocks) is None
        assert not gone.parent.exists()
    finally:
        server.stop()
