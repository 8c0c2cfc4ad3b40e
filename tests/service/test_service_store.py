"""The job table on a real SQLite file: tokens, the life of a job, fencing, recovery."""

from __future__ import annotations

import sqlite3
import time

import pytest

from service.store import QuotaExceeded, Store, StoreError

INPUTS = {"cameras": 1, "frames": 1, "bodyparts": ["a"], "keypoints": [{"name": "c.csv", "bytes": 1}],
          "calibration": {"name": "c.toml", "bytes": 1}}


@pytest.fixture
def store(tmp_path) -> Store:
    return Store(tmp_path / "acinoset.db")


def _job(store: Store, owner_id: int, n: int, max_attempts: int = 3) -> str:
    job_id = f"{n:032x}"
    store.insert_job(job_id, owner_id, "embedded", {"method": "tri"}, INPUTS, max_attempts)
    return job_id


def test_tokens_are_stored_hashed_and_checked(store, tmp_path):
    user, token = store.add_user("alice", admin=True)
    assert token.startswith("acn_")
    raw = sqlite3.connect(tmp_path / "acinoset.db").execute("SELECT key_id, secret_sha256 FROM tokens").fetchall()
    secret = token.split("_", 2)[2]
    assert len(raw) == 1 and secret not in raw[0][1] and token not in raw[0][1]
    assert store.authenticate(token).name == "alice"
    assert store.authenticate(token[:-1] + ("A" if token[-1] != "A" else "B")) is None
    assert store.authenticate("acn_000000000000_" + secret) is None  # right secret, wrong key id
    assert store.authenticate("nonsense") is None
    assert store.authenticate("") is None


def test_new_token_revokes_the_old_and_remove_disables(store):
    _, old = store.add_user("bob")
    new = store.new_token("bob")
    assert store.authenticate(old) is None and store.authenticate(new).name == "bob"
    uid = store.user("bob").id
    a = _job(store, uid, 1)
    assert store.disable_user("bob") == 1
    assert store.authenticate(new) is None
    assert store.job(a).status == "cancelled"
    with pytest.raises(StoreError, match="already exists"):
        store.add_user("bob")
    with pytest.raises(StoreError, match="bad user name"):
        store.add_user("../etc")
    with pytest.raises(StoreError, match="no user"):
        store.new_token("nobody")
    # a removed user stays removed: a new token does not bring it back unless asked to (issue item 11)
    with pytest.raises(StoreError, match="was removed; give --enable"):
        store.new_token("bob")
    assert store.user("bob").disabled
    again = store.new_token("bob", enable=True)
    assert store.authenticate(again).name == "bob" and not store.user("bob").disabled


def test_claim_is_fair_between_users(store):
    a, _ = store.add_user("a")
    b, _ = store.add_user("b")
    a_jobs = [_job(store, a.id, i) for i in range(3)]
    b_job = _job(store, b.id, 10)
    first = store.claim_next("w", 30, "embedded")
    assert first.id == a_jobs[0] and first.status == "running" and first.attempts == 1
    # a has one running: b's single job goes before a's second one
    assert store.claim_next("w", 30, "embedded").id == b_job
    assert store.claim_next("w", 30, "embedded").id == a_jobs[1]


def test_a_stale_run_cannot_write(store):
    u, _ = store.add_user("u")
    j = _job(store, u.id, 1)
    run1 = store.claim_next("w", 30, "embedded")
    assert store.report_progress(j, run1.run_token, "solve", 0.5, 3, 1.0, "window 2 of 5, 30 s left")
    assert store.job(j).detail == "window 2 of 5, 30 s left"
    assert store.interrupt(j, run1.run_token, "killed") == "queued"
    assert store.job(j).detail is None  # the words were the run's
    run2 = store.claim_next("w", 30, "embedded")
    assert run2.attempts == 2 and run2.run_token != run1.run_token
    # the first run comes back from the dead: nothing it says is recorded
    assert not store.report_progress(j, run1.run_token, "solve", 0.9, 9, 1.0)
    committed = []
    assert not store.finish(j, run1.run_token, "succeeded", summary={}, commit=lambda: committed.append(1))
    assert committed == []
    assert store.finish(j, run2.run_token, "succeeded", summary={"frames": 1}, commit=lambda: committed.append(2))
    job = store.job(j)
    assert committed == [2] and job.status == "succeeded" and job.summary == {"frames": 1} and job.detail is None
    assert job.solve_seconds is not None and job.solve_seconds >= 0


def test_interrupted_runs_are_bounded(store):
    u, _ = store.add_user("u")
    j = _job(store, u.id, 1, max_attempts=2)
    assert store.interrupt(j, store.claim_next("w", 30, "embedded").run_token, "killed (SIGKILL)") == "queued"
    assert store.interrupt(j, store.claim_next("w", 30, "embedded").run_token, "killed (SIGKILL)") == "failed"
    job = store.job(j)
    assert job.status == "failed" and job.attempts == 2
    assert job.error == "gave up after 2 interrupted attempts; last: killed (SIGKILL)"
    assert store.claim_next("w", 30, "embedded") is None


def test_adopt_after_a_crash_requeues_running_jobs(store):
    u, _ = store.add_user("u")
    running = _job(store, u.id, 1)
    queued = _job(store, u.id, 2)
    store.claim_next("w", 30, "embedded")
    counts = store.adopt("embedded", "the service stopped while it ran")
    assert counts == {"requeued": 1, "failed": 0, "moved": 0}
    job = store.job(running)
    assert job.status == "queued" and job.attempts == 1
    assert job.interruption == "attempt 1 of 3 interrupted: the service stopped while it ran"
    assert store.job(queued).status == "queued"
    # moving to another backend takes the queued jobs along
    assert store.adopt("rq", "x")["moved"] == 2
    assert {j.backend for j in store.active_jobs()} == {"rq"}


def test_cancel_delete_and_quota(store):
    u, _ = store.add_user("u")
    a = _job(store, u.id, 1)
    assert store.delete(a) is False  # active jobs are cancelled first, not deleted
    assert store.cancel(a).status == "queued"
    assert store.cancel(a) is None
    assert store.job(a).status == "cancelled"
    assert store.delete(a) and store.job(a) is None
    _job(store, u.id, 2)
    with pytest.raises(QuotaExceeded):
        store.insert_job(f"{3:032x}", u.id, "embedded", {}, INPUTS, 3, max_active=1)


def test_list_pages_newest_first(store):
    u, _ = store.add_user("u")
    v, _ = store.add_user("v")
    ids = [_job(store, u.id, i) for i in range(5)]
    _job(store, v.id, 99)
    page, total = store.jobs(u.id, None, 2)
    assert total == 5 and [j.id for j in page] == ids[::-1][:2]
    page2, _ = store.jobs(u.id, None, 2, before_seq=page[-1].seq)
    assert [j.id for j in page2] == ids[::-1][2:4]
    everyone, total_all = store.jobs(None, ["queued"], 50)
    assert total_all == 6 and len(everyone) == 6


def test_metrics_histogram_counts_succeeded_solves(store):
    u, _ = store.add_user("u")
    j = _job(store, u.id, 1)
    run = store.claim_next("w", 30, "embedded")
    time.sleep(0.01)
    store.finish(j, run.run_token, "succeeded", summary={})
    counts, total, seconds = store.solve_seconds_histogram([0.001, 10.0])
    assert total == 1 and counts == [0, 1] and 0 < seconds < 10
    assert store.status_counts() == {"queued": 0, "running": 0, "succeeded": 1, "failed": 0, "cancelled": 0}
