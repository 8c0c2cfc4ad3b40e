"""A server is not ready before it can serve: while its forkserver compiles the solver (about 1-2
minutes after an install, 7 minutes on a busy 2-core machine), /healthz says ``starting`` (503) and
queued jobs say ``compiling``; before, /healthz said ok and the first job sat in ``starting`` with no
word for as long."""

from __future__ import annotations

import time

from servers import Server, add_user, submit_ok, wait_finished

from service.backends.embedded import EmbeddedBackend
from service.settings import Settings
from service.store import Store


def test_no_job_starts_and_health_is_not_ready_until_the_forkserver_is_up(tmp_path):
    settings = Settings(data_dir=tmp_path, workers=1, warm_start=True)
    store = Store(settings.db_path)
    owner, _ = store.add_user("hal")
    store.insert_job("0" * 32, owner.id, "embedded", {}, {}, max_attempts=3)
    backend = EmbeddedBackend(settings, store)  # not started: its forkserver is not up
    health = backend.health()
    assert health["ready"] is False
    backend._thread_alive = lambda: True  # the scheduler thread's part of health, as when it runs
    assert "compiled" in backend.health()["detail"]
    backend._fill()
    job = store.job("0" * 32)
    assert job.status == "queued" and job.stage == "compiling" and not backend._runs


def test_a_real_server_says_starting_until_it_can_run_a_job(tmp_path, small_run):
    data = tmp_path / "data"
    token = add_user(data, "ida")
    srv = Server(data, tmp_path / "server.log", workers=1).start(ready=(200, 503))
    try:
        with srv.client(token) as c:
            job = submit_ok(c, small_run, {"method": "tri", "skeleton": "points"})
            seen = []
            deadline = time.time() + 900
            time.sleep(0.5)  # the scheduler's next tick marks the queued job
            while time.time() < deadline:
                j = c.get(f"/v1/jobs/{job}").json()  # first: if health still says starting after, so did the job
                h = c.get("/healthz")
                seen.append((h.json()["status"], j["status"], (j["progress"] or {}).get("stage")))
                if h.status_code == 200:
                    break
                assert h.status_code == 503 and h.json()["status"] == "starting" and not h.json()["ready"]
                assert j["status"] == "queued" and j["progress"]["stage"] == "compiling", j
                time.sleep(0.2)
            assert c.get("/healthz").json()["ready"] is True, seen
            assert wait_finished(c, job)["status"] == "succeeded"
    finally:
        srv.stop()
