"""A full disk does not wedge the service: a real server whose data dir is on a small tmpfs, filled
up. Before: submit and DELETE answered 500, /healthz said ok, and a job whose run ended while the
table could not be written stayed ``running`` with no process until a restart."""

from __future__ import annotations

import multiprocessing
import subprocess
import time
from pathlib import Path

import pytest
from servers import Server, add_user, make_run, submit, submit_ok, wait_finished, wait_solving

from service.backends.embedded import EmbeddedBackend, _Run
from service.errors import DISK_FULL
from service.settings import Settings
from service.store import Store, StoreFull

FAST = {"method": "tri", "skeleton": "points", "fps": 120.0}


@pytest.fixture
def small_disk(tmp_path):
    """A 40 MiB tmpfs (needs the right to mount, as root in CI; skipped otherwise)."""
    mnt = tmp_path / "disk"
    mnt.mkdir()
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=40m,mode=0700", "tmpfs", str(mnt)], capture_output=True)
    if r.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {r.stderr.decode().strip()}")
    yield mnt
    subprocess.run(["umount", "-l", str(mnt)], check=False)


def _fill(disk: Path) -> Path:
    filler = disk / "filler"
    with open(filler, "wb", buffering=0) as f:
        for size in (1 << 20, 4096, 512):
            try:
                while True:
                    f.write(b"\0" * size)
            except OSError:
                pass
    return filler


def test_a_full_disk_answers_507_lets_delete_free_space_and_health_says_so(small_disk, small_run):
    data = small_disk / "data"
    token = add_user(data, "dora")
    env = {"ACINOSET_WARM_START": "0", "ACINOSET_MIN_FREE_BYTES": "0"}
    srv = Server(data, small_disk.parent / "server.log", workers=1, env=env).start(ready=(200,))
    try:
        with srv.client(token) as c:
            done = [submit_ok(c, small_run, FAST) for _ in range(2)]
            assert all(wait_finished(c, j)["status"] == "succeeded" for j in done)
            filler = _fill(small_disk)
            r = submit(c, small_run, FAST)
            assert r.status_code == 507, r.text
            assert "disk is" in r.json()["detail"] and "full" in r.json()["detail"]
            health = c.get("/healthz")
            assert health.status_code == 503 and health.json()["status"] == "degraded"
            assert "disk" in health.json()["detail"] and health.json()["disk"]["free_bytes"] == 0
            # a user can still free space: the finished job goes, files and record
            r = c.delete(f"/v1/jobs/{done[0]}")
            assert r.status_code == 204, r.text
            assert c.get(f"/v1/jobs/{done[0]}").status_code == 404
            assert not (data / "jobs" / done[0]).exists()
            assert c.get(f"/v1/jobs/{done[1]}").json()["status"] == "succeeded"
            filler.unlink()
            assert c.get("/healthz").json()["status"] == "ok"
            again = submit_ok(c, small_run, FAST)
            assert wait_finished(c, again)["status"] == "succeeded"
        assert "Traceback" not in srv.log()
    finally:
        srv.stop()


def test_storage_quotas_answer_413_per_user_and_507_in_total(tmp_path, small_run):
    data = tmp_path / "data"
    tokens = {n: add_user(data, n) for n in ("ed", "flo")}
    upload = sum(p.stat().st_size for p in small_run.cams) + small_run.calibration.stat().st_size
    env = {"ACINOSET_WARM_START": "0", "ACINOSET_MAX_STORAGE_BYTES_PER_USER": str(int(upload * 1.5)),
           "ACINOSET_MAX_STORAGE_BYTES": str(int(upload * 2.5))}
    srv = Server(data, tmp_path / "server.log", workers=1, env=env).start()
    try:
        with srv.client(tokens["ed"]) as ed, srv.client(tokens["flo"]) as flo:
            first = submit_ok(ed, small_run, FAST)
            r = submit(ed, small_run, FAST)  # refused from the announced length, before the body is read
            assert r.status_code == 413, r.text
            assert "ACINOSET_MAX_STORAGE_BYTES_PER_USER" in r.json()["detail"]
            assert submit(flo, small_run, FAST).status_code == 202  # another user has room of their own
            r = submit(flo, small_run, FAST)
            assert r.status_code in (413, 507), r.text
            wait_finished(ed, first)
            # everyone's storage is full now, whoever asks
            ed.delete(f"/v1/jobs/{first}")
            r = submit(ed, small_run, FAST)
            assert r.status_code == 202, r.text
            r = submit(flo, small_run, FAST)
            assert r.status_code == 507 and "ACINOSET_MAX_STORAGE_BYTES" in r.json()["detail"], r.text
    finally:
        srv.stop()


def test_a_run_that_ended_while_the_table_could_not_be_written_is_requeued_later(tmp_path):
    """``EmbeddedBackend._reap`` forgot the run before recording its end: when that write failed
    (the disk full), the job stayed ``running`` with no process until a restart."""

    class FullOnce(Store):
        failures = 1

        def interrupt(self, job_id, token, reason):
            if self.failures:
                self.failures -= 1
                raise StoreFull(f"job table {self.path}: database or disk is full")
            return super().interrupt(job_id, token, reason)

    settings = Settings(data_dir=tmp_path, workers=1, warm_start=False)
    store = FullOnce(settings.db_path)
    owner, _ = store.add_user("gus")
    store.insert_job("0" * 32, owner.id, "embedded", {}, {}, max_attempts=3)
    job = store.claim_next("test:1", 30, "embedded")
    dead = multiprocessing.get_context("fork").Process(target=_exit_1)
    dead.start()
    dead.join()
    backend = EmbeddedBackend(settings, store)
    backend._runs[job.id] = _Run(job.id, job.run_token, dead, 0.0)
    backend._guarded_tick()  # the write fails: the run must stay watched
    assert store.job(job.id).status == "running"
    backend._guarded_tick()
    assert store.job(job.id).status == "queued"
    assert "exited with status 1" in store.job(job.id).interruption
    assert job.id not in backend._runs


def _exit_1() -> None:
    raise SystemExit(1)


def test_a_job_running_when_the_disk_fills_fails_at_once_naming_the_disk(small_disk, tmp_path, long_run):
    """The disk fills while a solve runs. Before: the job stayed ``running`` with no process while
    the disk was full, the scheduler logged a traceback every 0.75 s (150 of them), and once space
    returned the job ran again or failed as 'interrupted'. Now it fails within seconds, saying the
    disk is full, the log says so a few times (not once a tick, no traceback), and once the disk
    has room the table's reserve is made again and a new job runs."""
    small = make_run(tmp_path / "small", frames=60, cameras=3, seed=1)
    data = small_disk / "data"
    token = add_user(data, "dora")
    env = {"ACINOSET_WARM_START": "0", "ACINOSET_MIN_FREE_BYTES": "0"}
    srv = Server(data, tmp_path / "server.log", workers=1, env=env).start(ready=(200,))
    reserve = Path(f"{Settings(data_dir=data).db_path}.reserve")
    try:
        with srv.client(token) as c:
            job_id = submit_ok(c, long_run, {"method": "fte", "skeleton": "cheetah"})
            wait_solving(c, job_id, 60)
            assert reserve.exists()  # made by the scheduler within its first seconds
            filler = _fill(small_disk)
            done = wait_finished(c, job_id, 60)
            assert done["status"] == "failed" and done["attempts"] == 1, done
            assert done["error"] == DISK_FULL and done["error_kind"] == "limit"
            filler.unlink()
            again = submit_ok(c, small, FAST)
            assert wait_finished(c, again)["status"] == "succeeded"
            deadline = time.monotonic() + 30
            while not reserve.exists() and time.monotonic() < deadline:
                time.sleep(0.2)
            assert reserve.exists() and reserve.stat().st_size > 0
        log = srv.log()
        assert "Traceback" not in log, log[-3000:]
        assert sum("disk is full" in line for line in log.splitlines()) <= 4, log[-3000:]
    finally:
        srv.stop()


def test_a_run_that_could_not_record_its_disk_full_failure_is_failed_by_the_scheduler(tmp_path, caplog):
    """A job process that exits with EXIT_DISK_FULL (the disk full, its own record of the failure
    not written): the scheduler fails the job naming the disk, not queued again, once the table
    can be written; while it cannot, the log says so once, not once a tick."""
    from service.errors import EXIT_DISK_FULL

    class FullTwice(Store):
        failures = 2

        def finish(self, job_id, token, status, **kw):
            if self.failures:
                self.failures -= 1
                raise StoreFull(f"job table {self.path}: database or disk is full")
            return super().finish(job_id, token, status, **kw)

    settings = Settings(data_dir=tmp_path, workers=1, warm_start=False)
    store = FullTwice(settings.db_path)
    owner, _ = store.add_user("gus")
    store.insert_job("1" * 32, owner.id, "embedded", {}, {}, max_attempts=3)
    job = store.claim_next("test:1", 30, "embedded")
    dead = multiprocessing.get_context("fork").Process(target=_exit_with, args=(EXIT_DISK_FULL,))
    dead.start()
    dead.join()
    backend = EmbeddedBackend(settings, store)
    backend._runs[job.id] = _Run(job.id, job.run_token, dead, 0.0)
    with caplog.at_level("WARNING", logger="acinoset.service"):
        backend._guarded_tick()
        backend._guarded_tick()
        assert store.job(job.id).status == "running" and job.id in backend._runs
        backend._guarded_tick()
    done = store.job(job.id)
    assert done.status == "failed" and done.error == DISK_FULL and done.error_kind == "limit"
    assert job.id not in backend._runs
    said = [r.getMessage() for r in caplog.records]
    assert sum("the disk is full" in m for m in said) == 1 and not any(r.exc_info for r in caplog.records)
    assert any("can be written again" in m for m in said)


def _exit_with(code: int) -> None:
    raise SystemExit(code)
