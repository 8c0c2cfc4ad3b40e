"""A full disk does not wedge the service: a real server whose data dir is on a small tmpfs, filled
up. Before: submit and DELETE answered 500, /healthz said ok, and a job whose run ended while the
table could not be written stayed ``running`` with no process until a restart."""

from __future__ import annotations

import multiprocessing
import subprocess
from pathlib import Path

import pytest
from servers import Server, add_user, submit, submit_ok, wait_finished

from service.backends.embedded import EmbeddedBackend, _Run
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
    backend._tick()  # the write fails: the run must stay watched
    assert store.job(job.id).status == "running"
    backend._tick()
    assert store.job(job.id).status == "queued"
    assert "exited with status 1" in store.job(job.id).interruption
    assert job.id not in backend._runs


def _exit_1() -> None:
    raise SystemExit(1)
