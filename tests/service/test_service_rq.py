"""The RQ backend with real processes: Debian's redis-server (append-only file on), the server with
``--backend rq`` and two ``worker`` processes. Workers hand results back through Redis; the job table
stays the record."""

from __future__ import annotations

import os
import signal
import time

import numpy as np
import pytest
from servers import (
    ENV,
    Pool,
    Redis,
    Server,
    acinoset,
    add_user,
    have_redis,
    make_run,
    rq_server,
    submit_ok,
    wait_dead,
    wait_finished,
    wait_for,
    wait_solving,
    worker,
)

pytestmark = pytest.mark.skipif(not have_redis(), reason="needs Debian's redis-server (.ci/run installs it)")

LONG = {"method": "fte", "skeleton": "cheetah"}
FAST = {"method": "tri", "skeleton": "points", "fps": 120.0}


@pytest.fixture(scope="module")
def pool(tmp_path_factory):
    base = tmp_path_factory.mktemp("rq")
    p = Pool(base)
    p.start_redis()
    token = add_user(base / "data", "gina")
    p.server = Server(base / "data", base / "server.log", backend="rq", redis_url=p.redis.url, env=ENV).start()
    p.start_workers()
    p.token = token
    yield p
    p.server.stop()
    p.stop()


@pytest.fixture
def client(pool):
    with pool.server.client(pool.token) as c:
        yield c


def test_rq_round_trip_gives_the_embedded_result(pool, client, small_run, tmp_path):
    ids = [submit_ok(client, small_run, {"method": "fte", "skeleton": "cheetah", "fps": small_run.fps})
           for _ in range(4)]
    done = [wait_finished(client, j) for j in ids]
    assert [d["status"] for d in done] == ["succeeded"] * 4, done
    assert {d["worker"] for d in done} <= {"w1", "w2"} and all(d["attempts"] == 1 for d in done)
    csvs = {client.get(f"/v1/jobs/{j}/result").content for j in ids}
    assert len(csvs) == 1
    # the same upload solved by the embedded backend gives the same bytes
    data = tmp_path / "emb"
    token = add_user(data, "h")
    emb = Server(data, tmp_path / "emb.log", workers=1, env={"ACINOSET_WARM_START": "0"}).start()
    try:
        with emb.client(token) as c:
            j = submit_ok(c, small_run, {"method": "fte", "skeleton": "cheetah", "fps": small_run.fps})
            assert wait_finished(c, j)["status"] == "succeeded"
            assert c.get(f"/v1/jobs/{j}/result").content == csvs.pop()
    finally:
        emb.stop()
    health = client.get("/healthz").json()
    assert health["backend"] == "rq" and health["workers"] == 2 and health["status"] == "ok"
    # results live in the data dir; Redis keeps nothing of finished jobs
    import redis as redis_lib

    r = redis_lib.Redis.from_url(pool.redis.url)
    left = [k for k in r.keys("rq:job:*") + r.keys("acinoset:*") if any(j.encode() in k for j in ids)]
    assert left == []


def test_rq_workers_run_no_function_but_the_projects(pool, client, small_run, tmp_path):
    """Anyone who can write to Redis can enqueue an RQ job naming any importable function (os.system
    with a command of their choice), the JSON serializer notwithstanding. The project's workers fail
    such a job without running it, and go on serving real ones."""
    import redis as redis_lib
    from rq import Queue
    from rq.job import Job as RQJob
    from rq.serializers import JSONSerializer

    marker = tmp_path / "ran"
    conn = redis_lib.Redis.from_url(pool.redis.url)
    queue = Queue("acinoset", connection=conn, serializer=JSONSerializer)
    foreign = [queue.enqueue("os.system", f"touch {marker}"), queue.enqueue("builtins.print", "hello")]
    deadline = time.time() + 60
    while time.time() < deadline and not all(j.get_status(refresh=True) == "failed" for j in foreign):
        time.sleep(0.1)
    assert [j.get_status(refresh=True) for j in foreign] == ["failed", "failed"]
    assert not marker.exists()
    assert "refused" in (RQJob.fetch(foreign[0].id, connection=conn, serializer=JSONSerializer).exc_info or "")
    job = submit_ok(client, small_run, {"method": "tri", "skeleton": "points", "fps": small_run.fps})
    assert wait_finished(client, job)["status"] == "succeeded"


def test_rq_behind_a_password(tmp_path, small_run):
    """Redis with requirepass, as docker/compose.yaml runs it: the server and a worker given the
    password in the URL solve a job; a worker without it is refused in one line; the password is
    in no log line and no answer."""
    password = "pw-" + os.urandom(8).hex()
    redis = Redis(tmp_path / "redis", tmp_path / "redis.log", config=("--requirepass", password)).start()
    url = f"redis://:{password}@127.0.0.1:{redis.port}/0"
    procs = [redis]
    try:
        token = add_user(tmp_path / "data", "pia")
        srv = Server(tmp_path / "data", tmp_path / "server.log", backend="rq", redis_url=url, env=ENV).start()
        procs.append(srv)
        procs.append(worker(url, tmp_path / "w1.log", "w1").start())
        no_password = acinoset("worker", "--redis-url", url.replace(f":{password}@", ""), "--burst")
        assert no_password.returncode != 0 and "cannot reach Redis at redis://127.0.0.1" in no_password.stderr
        assert password not in no_password.stderr + no_password.stdout
        with srv.client(token) as c:
            job = submit_ok(c, small_run, {"method": "tri", "skeleton": "points", "fps": small_run.fps})
            assert wait_finished(c, job)["status"] == "succeeded"
            assert password not in c.get("/healthz").text
        for p in procs[1:]:
            assert password not in p.log()
    finally:
        for p in reversed(procs):
            p.stop(10)


def test_rq_files_larger_than_a_redis_value_go_and_come_back_in_chunks(pool, client, tmp_path_factory):
    """This Redis takes no value over 1 MB (a lab's footage and labelled videos are well over the
    512 MB of its default): a job whose upload and results are megabytes each reaches the worker and
    comes back in chunks, and Redis keeps nothing of it afterwards (no chunk, no partial list)."""
    import redis as redis_lib

    from graph.io.results import read_result
    from service.store.jobfiles import input_archive, job_dir, pack_files, written_outputs

    big = make_run(tmp_path_factory.mktemp("big_run"), frames=3000, cameras=3, seed=4)
    job_id = submit_ok(client, big, {**FAST, "fps": big.fps})
    done = wait_finished(client, job_id)
    assert done["status"] == "succeeded", done
    folder = job_dir(pool.server.data_dir / "jobs", job_id)
    assert len(input_archive(folder / "input")) > 2_000_000
    assert len(pack_files(folder / "result", written_outputs(folder / "result"))) > 2_000_000
    r = client.get(f"/v1/jobs/{job_id}/result")
    assert r.status_code == 200 and r.content == (folder / "result" / "result.csv").read_bytes()
    res = read_result(folder / "result" / "result.h5")
    assert res.positions.shape[0] == 3000 and np.isfinite(res.positions).mean() > 0.9
    left = redis_lib.Redis.from_url(pool.redis.url).keys(f"acinoset:*{job_id}*")
    assert left == []


def test_rq_cancel_stops_the_work_horse(pool, client, long_run):
    job_id = submit_ok(client, long_run, LONG)
    job = wait_solving(client, job_id)
    _, horse = pool.busy_worker(job["worker"])
    r = client.delete(f"/v1/jobs/{job_id}")
    assert r.status_code == 200 and r.json()["status"] == "cancelled"
    assert wait_dead(horse, 10), "the work horse still runs after the cancel"
    time.sleep(1.5)
    assert client.get(f"/v1/jobs/{job_id}").json()["status"] == "cancelled"
    # the workers are free again
    assert wait_finished(client, submit_ok(client, long_run, FAST))["status"] == "succeeded"


def test_rq_a_killed_work_horse_is_retried(pool, client, long_run):
    job_id = submit_ok(client, long_run, LONG)
    job = wait_solving(client, job_id)
    _, horse = pool.busy_worker(job["worker"])
    os.kill(horse, signal.SIGKILL)
    done = wait_finished(client, job_id)
    assert done["status"] == "succeeded" and done["attempts"] == 2, done


def test_rq_a_dead_worker_machine_loses_no_job(pool, client, long_run):
    job_id = submit_ok(client, long_run, LONG)
    job = wait_solving(client, job_id)
    name = job["worker"]
    pool.kill_worker(name)
    done = wait_finished(client, job_id, timeout=240)
    assert done["status"] == "succeeded" and done["attempts"] == 2, done
    assert done["worker"] != name
    assert f"worker {name} stopped responding" in done["interruption"]
    pool.start_workers([name + "b"])


@pytest.mark.slow  # over 12 s here
def test_rq_kill_9_of_everything_loses_nothing(tmp_path, long_run, small_run):
    pool = Pool(tmp_path)
    pool.start_redis()
    token = add_user(tmp_path / "data", "ivan")
    srv = Server(tmp_path / "data", tmp_path / "server1.log", backend="rq", redis_url=pool.redis.url, env=ENV).start()
    pool.start_workers()
    try:
        with srv.client(token) as c:
            long_ids = [submit_ok(c, long_run, LONG) for _ in range(2)]
            short_ids = [submit_ok(c, small_run, FAST) for _ in range(4)]
            for j in long_ids:
                wait_solving(c, j)
        # everything at once: the server, both workers with their horses, and Redis
        for name in list(pool.workers):
            pool.kill_worker(name)
        srv.kill9()
        pool.redis.kill9()

        pool.redis_back()
        srv = Server(tmp_path / "data", tmp_path / "server2.log", backend="rq", redis_url=pool.redis.url,
                     env=ENV).start()
        pool.workers = {}
        pool.start_workers(["w3", "w4"])  # w1, w2 stay registered in Redis until their names expire
        with srv.client(token) as c:
            finished = [wait_finished(c, j, timeout=240) for j in long_ids + short_ids]
            assert [f["status"] for f in finished] == ["succeeded"] * 6, finished
            for f in finished[:2]:
                assert f["attempts"] == 2, f
            listed = c.get("/v1/jobs").json()
            assert listed["total"] == 6
            for j in long_ids + short_ids:
                assert c.get(f"/v1/jobs/{j}/result", params={"format": "h5"}).status_code == 200
    finally:
        srv.stop()
        pool.stop()


def test_rq_jobs_wait_in_the_table_while_redis_is_down(tmp_path, small_run):
    pool, token, srv = rq_server(tmp_path, "judy")
    try:
        pool.redis.kill9()
        with srv.client(token) as c:
            assert c.get("/healthz").status_code == 503
            job_id = submit_ok(c, small_run, FAST)  # accepted: the table is the record
            pool.redis_back()
            pool.start_workers(["w1"])
            assert wait_finished(c, job_id)["status"] == "succeeded"
            wait_for(c, job_id, lambda j: True)
            assert c.get("/healthz").json()["status"] == "ok"
    finally:
        srv.stop()
        pool.stop()


def test_rq_a_job_whose_files_cannot_be_read_fails_alone(tmp_path, small_run):
    """Two jobs wait in the table while Redis is down; one of them loses a stored input file. When
    Redis is back, that one fails saying why, and the other runs (an exception of one job's
    enqueue had ended every dispatch pass, holding back the jobs picked after it)."""
    from service.store.jobfiles import job_dir

    pool, token, srv = rq_server(tmp_path, "kim")
    try:
        pool.redis.kill9()
        with srv.client(token) as c:
            broken, fine = submit_ok(c, small_run, FAST), submit_ok(c, small_run, FAST)
            lost = next((job_dir(tmp_path / "data" / "jobs", broken) / "input" / "keypoints").rglob("*.csv"))
            lost.unlink()
            pool.redis_back()
            pool.start_workers(["w1"])
            assert wait_finished(c, fine)["status"] == "succeeded"
            failed = wait_finished(c, broken)
            assert failed["status"] == "failed" and failed["error_kind"] == "internal", failed
            assert failed["error"].startswith("the job's stored input files cannot be read: FileNotFoundError")
            assert lost.name in failed["error"] and "\n" not in failed["error"]
    finally:
        srv.stop()
        pool.stop()


def test_rq_a_result_that_cannot_be_read_fails_its_job_alone(tmp_path, long_run, small_run):
    """A worker's result archive that cannot be unpacked (overwritten here while the server is
    stopped with SIGSTOP): that job fails saying why, and the server goes on collecting and
    dispatching the others (the exception had ended every pass at that row: the job stayed
    'running' and every later job 'queued')."""
    import redis as redis_lib
    from rq.job import Job as RQJob
    from rq.serializers import JSONSerializer

    from service.store.jobfiles import put_archive, result_key

    pool, token, srv = rq_server(tmp_path, "lee")
    pool.start_workers(["w1"])
    r = redis_lib.Redis.from_url(pool.redis.url)
    try:
        with srv.client(token) as c:
            broken = submit_ok(c, long_run, LONG)
            wait_solving(c, broken)
            os.kill(srv.pid, signal.SIGSTOP)
            try:
                rq_id = f"{broken}-1"
                deadline = time.time() + 120
                while RQJob.fetch(rq_id, connection=r, serializer=JSONSerializer).get_status() != "finished":
                    assert time.time() < deadline, "the worker did not finish"
                    time.sleep(0.1)
                put_archive(r, result_key(rq_id), b"not a zip archive")
            finally:
                os.kill(srv.pid, signal.SIGCONT)
            after = submit_ok(c, small_run, FAST)
            assert wait_finished(c, after)["status"] == "succeeded"
            failed = wait_finished(c, broken)
            assert failed["status"] == "failed", failed
            assert failed["error"].startswith("the run's result files could not be stored: BadZipFile"), failed
            assert r.keys(f"acinoset:*{broken}*") == []
    finally:
        srv.stop()
        pool.stop()


@pytest.mark.slow  # over 12 s here
def test_rq_queue_is_fair_between_users(tmp_path, long_run):
    """One worker, one user's five jobs queued first: another user's job, submitted after them,
    does not wait for all five (Redis is handed only a few jobs at a time, the fewest-jobs user's
    first)."""
    pool = Pool(tmp_path)
    pool.start_redis()
    busy = add_user(tmp_path / "data", "busy")
    late = add_user(tmp_path / "data", "late")
    srv = Server(tmp_path / "data", tmp_path / "server.log", backend="rq", redis_url=pool.redis.url, env=ENV).start()
    try:
        pool.start_workers(["w1"])
        with srv.client(busy) as a, srv.client(late) as b:
            mine = [submit_ok(a, long_run, LONG) for _ in range(5)]
            other = submit_ok(b, long_run, LONG)
            done = {j: wait_finished(a, j) for j in mine}
            done[other] = wait_finished(b, other)
        assert all(d["status"] == "succeeded" for d in done.values()), done
        order = sorted(done, key=lambda j: done[j]["timings"]["started_at"])
        assert order.index(other) <= 3, [done[j]["owner"] for j in order]
    finally:
        srv.stop()
        pool.stop()


def test_rq_a_job_of_two_animals_brings_each_ones_files_back(pool, client, tmp_path):
    """Several individuals on the RQ backend: a worker hands back each one's folder (the result
    whitelist knows them), and each one's CSV is what the same upload gives the embedded server."""
    import json

    from group_files import write_dlc_multi

    from graph.io.calibration import write_anipose_toml
    from graph.simulate import ring_rig
    from graph.simulate_group import simulate_group

    rig = ring_rig(4)
    run = simulate_group(rig, animals=2, frames=200, seed=13)
    write_anipose_toml(tmp_path / "calibration.toml", rig)
    cams = [write_dlc_multi(tmp_path / f"cam{c + 1}.csv", t, ["dam", "cub"]) for c, t in enumerate(run.tracks)]

    def post(c):
        files = [("keypoints", (p.name, p.read_bytes(), "text/csv")) for p in cams]
        files.append(("calibration", ("calibration.toml", (tmp_path / "calibration.toml").read_bytes(), "text/plain")))
        r = c.post("/v1/jobs", files=files, data={"options": json.dumps(FAST | {"fps": 60.0})})
        assert r.status_code == 202, r.text
        job = wait_finished(c, r.json()["id"])
        assert job["status"] == "succeeded", job
        return {n: c.get(links["csv"]).content for n, links in job["links"]["individuals"].items()}

    over_rq = post(client)
    assert set(over_rq) == {"cub", "dam"} and all(len(v) > 1000 for v in over_rq.values())
    data = tmp_path / "emb"
    token = add_user(data, "h")
    emb = Server(data, tmp_path / "emb.log", workers=1, env={"ACINOSET_WARM_START": "0"}).start()
    try:
        with emb.client(token) as c:
            assert post(c) == over_rq
    finally:
        emb.stop()
