"""The job table's file across releases and failures: a file written before numbered migrations opens,
is migrated in place and reads back whole; a newer one is refused; SQLite's errors come out of the
store as :class:`service.store.StoreError` kinds, whatever the call.

``data/acinoset-617d80a.db`` was written by the job table of commit 617d80a (``service/store.py``,
one class, columns added through a list, no schema version), with its own calls::

    ada, ada_token = s.add_user("ada", admin=True); bob, bob_token = s.add_user("bob")
    s.add_user("cy"); s.disable_user("cy")
    "a" * 32: bob's solve, label "trial 1", claimed, progress ("triangulating", 0.5, 2, 1.5),
              succeeded with summary {"frames": 10, "warnings": ["one camera saw little"]}
    "b" * 32: ada's calibration (options kind "calibration"), label "rig", succeeded with
              summary {"rms_px": 0.4, "files": ["calibration.toml"]}
    "c" * 32: bob's solve (method fte), failed with error_kind "input"
    "d" * 32: bob's solve, queued
"""

from __future__ import annotations

import shutil
import sqlite3
from pathlib import Path

import pytest

from service.errors import storage_full
from service.store import Store, StoreBusy, StoreCorrupt, StoreError, StoreFull
from service.store.schema import VERSION

BEFORE_MIGRATIONS = Path(__file__).parent / "data" / "acinoset-617d80a.db"
ADA_TOKEN = "acn_a70cf0eb5ffe_76CV6HAigQi7PYvv8HUx9fI3j_kCwQ1MduhmLjBlfp8"
BOB_TOKEN = "acn_5c4ae6f8541b_P7G5LVhay40x7rRbtrVpTTpbE6nJZYiBAZXBbPp3cw4"
INPUTS = {"cameras": 1, "frames": 1, "bodyparts": ["a"], "keypoints": [{"name": "c.csv", "bytes": 1}],
          "calibration": {"name": "c.toml", "bytes": 1}}


def _raw(path: Path) -> sqlite3.Connection:
    return sqlite3.connect(path, isolation_level=None)


def _schema(path: Path) -> dict[str, set]:
    """Each table's and index's columns: (name, type, not null, default, primary key) per column."""
    db = _raw(path)
    try:
        names = db.execute("SELECT type, name FROM sqlite_master WHERE name NOT LIKE 'sqlite_%'").fetchall()
        out = {}
        for kind, name in names:
            info = db.execute(f"PRAGMA {'table' if kind == 'table' else 'index'}_info({name})").fetchall()
            out[f"{kind} {name}"] = {tuple(r[1:]) if kind == "table" else tuple(r) for r in info}
        return out
    finally:
        db.close()


def _version(path: Path) -> int:
    db = _raw(path)
    try:
        return db.execute("PRAGMA user_version").fetchone()[0]
    finally:
        db.close()


def test_a_table_from_before_migrations_is_migrated_in_place_and_reads_back_whole(tmp_path):
    path = tmp_path / "acinoset.db"
    shutil.copyfile(BEFORE_MIGRATIONS, path)
    assert _version(path) == 0
    store = Store(path)
    assert _version(path) == VERSION
    assert _schema(path) == _schema(Store(tmp_path / "new" / "acinoset.db").path)

    # users and tokens
    users = {u.name: (u, counts) for u, counts in store.users()}
    assert set(users) == {"ada", "bob", "cy"}
    assert users["ada"][0].is_admin and not users["bob"][0].is_admin and users["cy"][0].disabled
    assert users["bob"][1] == {"succeeded": 1, "failed": 1, "queued": 1} and users["ada"][1] == {"succeeded": 1}
    assert store.authenticate(ADA_TOKEN).name == "ada" and store.authenticate(BOB_TOKEN).name == "bob"
    assert store.token_holder(BOB_TOKEN.split("_")[1]).name == "bob"
    assert store.authenticate(BOB_TOKEN[:-1] + ("A" if BOB_TOKEN[-1] != "A" else "B")) is None

    # jobs: a solve that succeeded, one that failed, one queued; a calibration
    solve = store.job("a" * 32)
    assert (solve.owner, solve.status, solve.label, solve.stage, solve.fraction) == ("bob", "succeeded", "trial 1",
                                                                                     "done", 1.0)
    assert solve.options == {"method": "tri", "skeleton": "points"} and solve.inputs["frames"] == 10
    assert solve.summary == {"frames": 10, "warnings": ["one camera saw little"]} and solve.attempts == 1
    assert solve.solve_seconds is not None and solve.started_at <= solve.finished_at
    failed = store.job("c" * 32)
    assert failed.status == "failed" and failed.error_kind == "input" and "3 cameras" in failed.error
    solves, total = store.jobs(None)
    assert total == 3 and [j.id for j in solves] == ["d" * 32, "c" * 32, "a" * 32]
    assert [j.id for j in store.jobs(None, warnings=True)[0]] == ["a" * 32]
    calibrations, n = store.jobs(None, kind="calibration")
    assert n == 1 and calibrations[0].id == "b" * 32 and calibrations[0].owner == "ada"
    assert calibrations[0].summary["rms_px"] == 0.4 and calibrations[0].label == "rig"

    # and it goes on working: the queued job runs, a new one is stored with the columns added since
    run = store.claim_next("w:2", 30, "embedded")
    assert run.id == "d" * 32 and run.attempts == 1
    assert store.finish(run.id, run.run_token, "failed", error="bad", error_kind="limit")
    assert store.job(run.id).error_kind == "limit"
    added = store.insert_job("e" * 32, users["bob"][0].id, "embedded", {"method": "tri"}, INPUTS, 3, label="new")
    assert added.label == "new" and added.seq > solve.seq
    store.close()
    assert Store(path).job("e" * 32).label == "new" and _version(path) == VERSION  # opening again: nothing to do


def test_a_job_table_made_before_label_and_error_kind_gains_them(tmp_path):
    """The first release's jobs table had neither column (they came through ALTER TABLE since)."""
    path = tmp_path / "acinoset.db"
    fresh = _schema(Store(tmp_path / "new" / "acinoset.db").path)
    db = _raw(path)
    db.execute("CREATE TABLE users (id INTEGER PRIMARY KEY AUTOINCREMENT, name TEXT NOT NULL UNIQUE, "
               "is_admin INTEGER NOT NULL DEFAULT 0, disabled INTEGER NOT NULL DEFAULT 0, created_at REAL NOT NULL)")
    db.execute("CREATE TABLE tokens (key_id TEXT PRIMARY KEY, user_id INTEGER NOT NULL REFERENCES users(id), "
               "secret_sha256 TEXT NOT NULL, created_at REAL NOT NULL)")
    db.execute("CREATE TABLE jobs (seq INTEGER PRIMARY KEY AUTOINCREMENT, id TEXT NOT NULL UNIQUE, "
               "owner_id INTEGER NOT NULL REFERENCES users(id), status TEXT NOT NULL, backend TEXT NOT NULL, "
               "created_at REAL NOT NULL, started_at REAL, finished_at REAL, updated_at REAL NOT NULL, "
               "attempts INTEGER NOT NULL DEFAULT 0, max_attempts INTEGER NOT NULL, lease_until REAL, worker TEXT, "
               "run_token TEXT, options TEXT NOT NULL, inputs TEXT NOT NULL, stage TEXT, fraction REAL, "
               "iteration INTEGER, cost REAL, error TEXT, interruption TEXT, summary TEXT, solve_seconds REAL)")
    db.execute("INSERT INTO users(name, created_at) VALUES ('old', 1.0)")
    db.execute("INSERT INTO jobs(id, owner_id, status, backend, created_at, updated_at, max_attempts, options, inputs) "
               "VALUES ('f', 1, 'queued', 'embedded', 1.0, 1.0, 3, '{}', '{}')")
    db.close()
    store = Store(path)
    assert _schema(path) == fresh and _version(path) == VERSION
    job = store.job("f")
    assert job.owner == "old" and job.label is None and job.error_kind is None
    assert store.jobs(None)[1] == 1


def test_a_table_of_a_newer_release_is_refused(tmp_path):
    path = Store(tmp_path / "acinoset.db").path
    db = _raw(path)
    db.execute(f"PRAGMA user_version = {VERSION + 1}")
    db.close()
    with pytest.raises(StoreError, match=f"schema version {VERSION + 1} is newer than this release's {VERSION}"):
        Store(path)


def test_a_file_that_is_not_a_database_is_store_corrupt(tmp_path):
    path = tmp_path / "acinoset.db"
    path.write_bytes(b"these are not the pages of a database\n" * 200)
    with pytest.raises(StoreCorrupt, match="not a database"):
        Store(path)


def test_a_full_disk_is_store_full_and_the_table_goes_on_after_it(tmp_path):
    """SQLITE_FULL made real with SQLite's own page limit (the file may not grow): the failed write
    leaves nothing behind and the connection usable."""
    store = Store(tmp_path / "acinoset.db")
    user, token = store.add_user("dora")
    with store.transaction() as db:
        pages = db.execute("PRAGMA page_count").fetchone()[0]
        db.execute(f"PRAGMA max_page_count = {pages}")
    with pytest.raises(StoreFull, match="full") as raised:
        store.insert_job("1" * 32, user.id, "embedded", {"padding": "x" * 200_000}, INPUTS, 3)
    assert storage_full(raised.value) and not isinstance(raised.value, sqlite3.Error)
    assert store.job("1" * 32) is None and store.authenticate(token).name == "dora"
    with store.transaction() as db:
        db.execute("PRAGMA max_page_count = 1073741823")
    assert store.insert_job("1" * 32, user.id, "embedded", {"padding": "x" * 200_000}, INPUTS, 3).status == "queued"


def test_a_table_locked_past_the_busy_timeout_is_store_busy(tmp_path):
    path = Store(tmp_path / "acinoset.db").path
    holder = _raw(path)
    holder.execute("BEGIN IMMEDIATE")  # another process in the middle of a write
    try:
        store = Store(path, busy_timeout=0.2)
        assert store.users() == []  # readers are not held up (WAL)
        with pytest.raises(StoreBusy, match="locked"):
            store.add_user("eve")
    finally:
        holder.execute("ROLLBACK")
        holder.close()
    assert store.add_user("eve")[0].name == "eve"
