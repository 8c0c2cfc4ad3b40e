"""The job table and the users: one SQLite file in the data dir, the service's record of truth.

SQLite in WAL mode lets the API answer reads while solves write their progress. Every state change
of a job is one short ``BEGIN IMMEDIATE`` transaction, so a crash leaves each row either before or
after the change, never half-way.

A job's life::

    queued --claim--> running --finish--> succeeded | failed
       ^                 |
       +---interrupt-----+   (the process running it died: again, or failed after max_attempts)
    queued | running --cancel--> cancelled

A run of a job holds a *lease* (``lease_until``) that its owner renews, and a ``run_token``
naming that run. Writes from a run (progress, the result) only apply while the row is ``running``
with the same token: a run that was given up for lost, or cancelled, cannot overwrite a newer one.

Tokens: ``acn_<key id>_<secret>``. The table holds the key id and SHA-256 of the secret (the
secret is 256 random bits, so a plain hash suffices); a lookup finds the row by key id and compares
the hashes with :func:`hmac.compare_digest`, in constant time.
"""

from __future__ import annotations

import hashlib
import hmac
import json
import re
import secrets
import sqlite3
import threading
import time
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterator, Literal, get_args

JobStatus = Literal["queued", "running", "succeeded", "failed", "cancelled"]  # the one list of job states
STATUSES: tuple[str, ...] = get_args(JobStatus)
ACTIVE: tuple[str, ...] = ("queued", "running")
FINISHED: tuple[str, ...] = tuple(s for s in STATUSES if s not in ACTIVE)

# The stages of a run the service records itself, around the solver's own (graph.types.STAGES,
# reported by the solve as it goes; service.models.STAGES publishes the whole sequence):
COMPILING = "compiling"  # queued while the server compiles its solver, once after an install (set here)
STARTING = "starting"  # claimed, its process starting (set here)
READING = "reading"  # reading the input files (service.worker)
WRITING = "writing"  # writing the result files (service.worker)
RENDERING = "rendering videos"  # drawing the result over the job's videos, when it has some (service.worker)
DONE = "done"  # the result is stored (set here)


def _sql_in(statuses: tuple[str, ...]) -> str:
    """``('a', 'b')``: a constant list of states for SQL's ``IN``."""
    return "(" + ", ".join(f"'{s}'" for s in statuses) + ")"


_ACTIVE_IN = _sql_in(ACTIVE)
_FINISHED_IN = _sql_in(FINISHED)
# the progress of a run that ended with the status given twice as parameters: complete if it succeeded
_ENDED_PROGRESS = (f"fraction = CASE WHEN ? = 'succeeded' THEN 1.0 ELSE fraction END, "
                   f"stage = CASE WHEN ? = 'succeeded' THEN '{DONE}' ELSE stage END")

USER_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._@-]{0,63}$")
TOKEN_PREFIX = "acn"
_DUMMY_HASH = hashlib.sha256(b"no such key").hexdigest()

SCHEMA = """
CREATE TABLE IF NOT EXISTS users (
    id          INTEGER PRIMARY KEY AUTOINCREMENT,
    name        TEXT NOT NULL UNIQUE,
    is_admin    INTEGER NOT NULL DEFAULT 0,
    disabled    INTEGER NOT NULL DEFAULT 0,
    created_at  REAL NOT NULL
);
CREATE TABLE IF NOT EXISTS tokens (
    key_id         TEXT PRIMARY KEY,
    user_id        INTEGER NOT NULL REFERENCES users(id),
    secret_sha256  TEXT NOT NULL,
    created_at     REAL NOT NULL
);
CREATE TABLE IF NOT EXISTS jobs (
    seq            INTEGER PRIMARY KEY AUTOINCREMENT,
    id             TEXT NOT NULL UNIQUE,
    owner_id       INTEGER NOT NULL REFERENCES users(id),
    status         TEXT NOT NULL,
    backend        TEXT NOT NULL,
    created_at     REAL NOT NULL,
    started_at     REAL,
    finished_at    REAL,
    updated_at     REAL NOT NULL,
    attempts       INTEGER NOT NULL DEFAULT 0,
    max_attempts   INTEGER NOT NULL,
    lease_until    REAL,
    worker         TEXT,
    run_token      TEXT,
    options        TEXT NOT NULL,
    inputs         TEXT NOT NULL,
    stage          TEXT,
    fraction       REAL,
    iteration      INTEGER,
    cost           REAL,
    error          TEXT,
    interruption   TEXT,
    summary        TEXT,
    solve_seconds  REAL,
    label          TEXT,
    error_kind     TEXT
);
CREATE INDEX IF NOT EXISTS jobs_by_status ON jobs(status, seq);
CREATE INDEX IF NOT EXISTS jobs_by_owner ON jobs(owner_id, seq);
"""
# Columns added since the first release, for job tables made before them (ALTER TABLE ... ADD COLUMN).
ADDED_COLUMNS = {"label": "TEXT", "error_kind": "TEXT"}
# Why a failed job failed: its input (a file or option the solver refuses), a limit of this server,
# runs that kept being interrupted, or an error of the software itself.
ErrorKind = Literal["input", "limit", "interrupted", "internal"]


class StoreError(ValueError):
    """A user-management request that cannot be done (unknown user, name taken, bad name)."""


class QuotaExceeded(Exception):
    """The owner already has the most active jobs allowed."""


@dataclass
class User:
    id: int
    name: str
    is_admin: bool
    disabled: bool
    created_at: float
    token_key: str = ""  # the key id of the token it signed in with (a media link names it)


@dataclass
class Job:
    """One row of the job table."""

    seq: int
    id: str
    owner_id: int
    owner: str
    status: JobStatus
    backend: str
    created_at: float
    started_at: float | None
    finished_at: float | None
    updated_at: float
    attempts: int
    max_attempts: int
    lease_until: float | None
    worker: str | None
    run_token: str | None
    options: dict
    inputs: dict
    stage: str | None
    fraction: float | None
    iteration: int | None
    cost: float | None
    error: str | None
    interruption: str | None
    summary: dict | None
    solve_seconds: float | None
    label: str | None = None
    error_kind: str | None = None

    @property
    def active(self) -> bool:
        return self.status in ACTIVE


_JOB_COLUMNS = ("j.seq, j.id, j.owner_id, u.name, j.status, j.backend, j.created_at, j.started_at, "
                "j.finished_at, j.updated_at, j.attempts, j.max_attempts, j.lease_until, j.worker, "
                "j.run_token, j.options, j.inputs, j.stage, j.fraction, j.iteration, j.cost, j.error, "
                "j.interruption, j.summary, j.solve_seconds, j.label, j.error_kind")
_JOB_SELECT = f"SELECT {_JOB_COLUMNS} FROM jobs j JOIN users u ON u.id = j.owner_id"


def _job(row) -> Job:
    r = list(row)
    r[15] = json.loads(r[15])
    r[16] = json.loads(r[16])
    r[23] = json.loads(r[23]) if r[23] else None
    return Job(*r)


def _json(x) -> str:
    return json.dumps(x, separators=(",", ":"), allow_nan=False)


def _count_active(db: sqlite3.Connection, owner_id: int) -> int:
    return db.execute(f"SELECT COUNT(*) FROM jobs WHERE owner_id = ? AND status IN {_ACTIVE_IN}",
                      (owner_id,)).fetchone()[0]


def _counts(db: sqlite3.Connection, owner_id: int | None) -> dict[str, int]:
    """Jobs per state that has any: one owner's, or everyone's (``owner_id=None``)."""
    rows = (db.execute("SELECT status, COUNT(*) FROM jobs WHERE owner_id = ? GROUP BY status", (owner_id,))
            if owner_id is not None else db.execute("SELECT status, COUNT(*) FROM jobs GROUP BY status"))
    return {status: int(n) for status, n in rows.fetchall()}


def hash_secret(secret: str) -> str:
    return hashlib.sha256(secret.encode("utf-8")).hexdigest()


class Store:
    """The SQLite job table and users. Safe to share between threads (one connection per thread)
    and between processes (SQLite's own locking; each process opens its own :class:`Store`)."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._local = threading.local()
        db = self._db()
        db.executescript(SCHEMA)
        have = {row[1] for row in db.execute("PRAGMA table_info(jobs)")}
        for name, kind in ADDED_COLUMNS.items():
            if name not in have:
                db.execute(f"ALTER TABLE jobs ADD COLUMN {name} {kind}")

    # -- connections -------------------------------------------------------------------------

    def _db(self) -> sqlite3.Connection:
        db = getattr(self._local, "db", None)
        if db is None:
            db = sqlite3.connect(self.path, timeout=30.0, isolation_level=None, check_same_thread=False)
            db.execute("PRAGMA journal_mode=WAL")
            db.execute("PRAGMA synchronous=NORMAL")  # in WAL: durable against a process crash
            db.execute("PRAGMA busy_timeout=30000")
            db.execute("PRAGMA foreign_keys=ON")
            self._local.db = db
        return db

    @contextmanager
    def transaction(self) -> Iterator[sqlite3.Connection]:
        """One write transaction, taken at once (``BEGIN IMMEDIATE``) so it never deadlocks on upgrade."""
        db = self._db()
        db.execute("BEGIN IMMEDIATE")
        try:
            yield db
        except BaseException:
            db.execute("ROLLBACK")
            raise
        else:
            db.execute("COMMIT")

    def close(self) -> None:
        db = getattr(self._local, "db", None)
        if db is not None:
            db.close()
            self._local.db = None

    # -- users -------------------------------------------------------------------------------

    def add_user(self, name: str, admin: bool = False) -> tuple[User, str]:
        """A new user and its first token (the token is returned once and never stored)."""
        if not USER_NAME.match(name):
            raise StoreError(f"bad user name {name!r}: use 1-64 letters, digits, '.', '_', '-', '@'")
        now = time.time()
        with self.transaction() as db:
            if db.execute("SELECT 1 FROM users WHERE name = ?", (name,)).fetchone():
                raise StoreError(f"user {name!r} already exists (use 'acinoset users token {name}' for a new token)")
            uid = db.execute("INSERT INTO users(name, is_admin, created_at) VALUES (?, ?, ?)",
                             (name, int(admin), now)).lastrowid
            token = self._new_token(db, uid, now)
        return User(uid, name, admin, False, now), token

    @staticmethod
    def _new_token(db: sqlite3.Connection, user_id: int, now: float) -> str:
        key_id = secrets.token_hex(6)
        secret = secrets.token_urlsafe(32)
        db.execute("INSERT INTO tokens(key_id, user_id, secret_sha256, created_at) VALUES (?, ?, ?, ?)",
                   (key_id, user_id, hash_secret(secret), now))
        return f"{TOKEN_PREFIX}_{key_id}_{secret}"

    def new_token(self, name: str, enable: bool = False) -> str:
        """Revoke a user's tokens and issue a new one. A removed user stays removed (:class:`StoreError`)
        unless ``enable``: a new token alone must not bring it back."""
        with self.transaction() as db:
            row = db.execute("SELECT disabled FROM users WHERE name = ?", (name,)).fetchone()
            if row and row[0] and not enable:
                raise StoreError(f"user {name!r} was removed; give --enable to let it sign in again with a new token")
            uid = self._revoke(db, name)
            db.execute("UPDATE users SET disabled = 0 WHERE id = ?", (uid,))
            return self._new_token(db, uid, time.time())

    @staticmethod
    def _revoke(db: sqlite3.Connection, name: str) -> int:
        """Delete the tokens of the user ``name``; its id."""
        row = db.execute("SELECT id FROM users WHERE name = ?", (name,)).fetchone()
        if not row:
            raise StoreError(f"no user {name!r}")
        db.execute("DELETE FROM tokens WHERE user_id = ?", (row[0],))
        return row[0]

    def disable_user(self, name: str) -> int:
        """Revoke a user's tokens and cancel its queued and running jobs; returns how many were cancelled.
        Its jobs stay in the table (admins can still read and delete them)."""
        now = time.time()
        with self.transaction() as db:
            uid = self._revoke(db, name)
            db.execute("UPDATE users SET disabled = 1 WHERE id = ?", (uid,))
            return db.execute(
                "UPDATE jobs SET status = 'cancelled', finished_at = ?, updated_at = ?, lease_until = NULL, "
                f"error = 'cancelled: the user was removed' WHERE owner_id = ? AND status IN {_ACTIVE_IN}",
                (now, now, uid)).rowcount

    def user(self, name: str) -> User | None:
        row = self._db().execute("SELECT id, name, is_admin, disabled, created_at FROM users WHERE name = ?",
                                 (name,)).fetchone()
        return User(row[0], row[1], bool(row[2]), bool(row[3]), row[4]) if row else None

    def users(self) -> list[tuple[User, dict[str, int]]]:
        """Every user with its job counts by status."""
        db = self._db()
        out = []
        for r in db.execute("SELECT id, name, is_admin, disabled, created_at FROM users ORDER BY name").fetchall():
            out.append((User(r[0], r[1], bool(r[2]), bool(r[3]), r[4]), _counts(db, r[0])))
        return out

    def authenticate(self, token: str) -> User | None:
        """The user a token belongs to, or None. Constant time in the secret."""
        parts = token.split("_", 2)
        if len(parts) != 3 or parts[0] != TOKEN_PREFIX:
            key_id, secret = "", token
        else:
            key_id, secret = parts[1], parts[2]
        row = self._db().execute(
            "SELECT t.secret_sha256, u.id, u.name, u.is_admin, u.disabled, u.created_at "
            "FROM tokens t JOIN users u ON u.id = t.user_id WHERE t.key_id = ?", (key_id,)).fetchone()
        expected = row[0] if row else _DUMMY_HASH
        ok = hmac.compare_digest(hash_secret(secret), expected)
        if not (ok and row) or row[4]:
            return None
        return User(row[1], row[2], bool(row[3]), bool(row[4]), row[5], key_id)

    def token_holder(self, key_id: str) -> User | None:
        """The user of the live token whose key id is ``key_id`` (a media link names it), or None
        once that token was revoked or its user removed."""
        row = self._db().execute(
            "SELECT u.id, u.name, u.is_admin, u.disabled, u.created_at "
            "FROM tokens t JOIN users u ON u.id = t.user_id WHERE t.key_id = ?", (key_id,)).fetchone()
        if not row or row[3]:
            return None
        return User(row[0], row[1], bool(row[2]), bool(row[3]), row[4], key_id)

    # -- jobs: submit, read, list ------------------------------------------------------------

    def insert_job(self, job_id: str, owner_id: int, backend: str, options: dict, inputs: dict,
                   max_attempts: int, max_active: int | None = None, label: str | None = None) -> Job:
        """A new queued job; :class:`QuotaExceeded` if its owner already has ``max_active`` active jobs."""
        now = time.time()
        with self.transaction() as db:
            if max_active is not None and _count_active(db, owner_id) >= max_active:
                raise QuotaExceeded()
            db.execute(
                "INSERT INTO jobs(id, owner_id, status, backend, created_at, updated_at, max_attempts, options, inputs, "
                "label) VALUES (?, ?, 'queued', ?, ?, ?, ?, ?, ?, ?)",
                (job_id, owner_id, backend, now, now, max_attempts, _json(options), _json(inputs), label))
        job = self.job(job_id)
        assert job is not None
        return job

    def job(self, job_id: str) -> Job | None:
        row = self._db().execute(f"{_JOB_SELECT} WHERE j.id = ?", (job_id,)).fetchone()
        return _job(row) if row else None

    def jobs(self, owner_id: int | None = None, statuses: list[str] | None = None, limit: int = 50,
             before_seq: int | None = None, label: str | None = None, method: str | None = None,
             since: float | None = None, warnings: bool | None = None,
             kind: str | None = None) -> tuple[list[Job], int]:
        """Jobs newest first, and how many match in all, of one ``kind`` (options' ``kind``: None for
        solves, ``calibration``). ``owner_id=None``: everyone's. ``label``:
        those whose label contains it (any case); ``since``: submitted then or later (epoch s);
        ``warnings``: succeeded with (True) or without (False) warnings in their report."""
        where, args = ["json_extract(j.options, '$.kind') IS ?"], [kind]
        if owner_id is not None:
            where.append("j.owner_id = ?")
            args.append(owner_id)
        if statuses:
            where.append(f"j.status IN ({','.join('?' * len(statuses))})")
            args.extend(statuses)
        if label:
            where.append("j.label LIKE ? ESCAPE '\\'")
            args.append("%" + re.sub(r"([%_\\])", r"\\\1", label) + "%")
        if method:
            where.append("json_extract(j.options, '$.method') = ?")
            args.append(method)
        if since is not None:
            where.append("j.created_at >= ?")
            args.append(since)
        if warnings is not None:
            has = "json_array_length(COALESCE(json_extract(j.summary, '$.warnings'), '[]')) > 0"
            where.append(f"j.status = 'succeeded' AND {'' if warnings else 'NOT '}{has}")
        cond = (" WHERE " + " AND ".join(where)) if where else ""
        db = self._db()
        total = db.execute(f"SELECT COUNT(*) FROM jobs j{cond}", args).fetchone()[0]
        page_cond = cond
        page_args = list(args)
        if before_seq is not None:
            page_cond = (cond + " AND " if cond else " WHERE ") + "j.seq < ?"
            page_args.append(before_seq)
        rows = db.execute(f"{_JOB_SELECT}{page_cond} ORDER BY j.seq DESC LIMIT ?", [*page_args, limit]).fetchall()
        return [_job(r) for r in rows], total

    def active_jobs(self, backend: str | None = None) -> list[Job]:
        cond = f"j.status IN {_ACTIVE_IN}" + (" AND j.backend = ?" if backend else "")
        rows = self._db().execute(f"{_JOB_SELECT} WHERE {cond} ORDER BY j.seq",
                                  (backend,) if backend else ()).fetchall()
        return [_job(r) for r in rows]

    def count_active(self, owner_id: int) -> int:
        return _count_active(self._db(), owner_id)

    def job_counts(self, owner_id: int) -> dict[str, int]:
        """The owner's jobs in each state (every state, 0 for none)."""
        counts = _counts(self._db(), owner_id)
        return {s: counts.get(s, 0) for s in STATUSES}

    def status_counts(self) -> dict[str, int]:
        """Everyone's jobs in each state (every state, 0 for none)."""
        counts = _counts(self._db(), None)
        return {s: counts.get(s, 0) for s in STATUSES}

    def oldest_queued_at(self) -> float | None:
        """When the job that has waited longest in the queue was submitted (None: nothing queued)."""
        return self._db().execute("SELECT MIN(created_at) FROM jobs WHERE status = 'queued'").fetchone()[0]

    def solve_seconds_histogram(self, buckets: list[float]) -> tuple[list[int], int, float]:
        """Cumulative counts of succeeded solves with ``solve_seconds <= b`` per bucket, count, sum."""
        sel = ", ".join(f"SUM(solve_seconds <= {float(b)!r})" for b in buckets)
        row = self._db().execute(
            f"SELECT COUNT(*), COALESCE(SUM(solve_seconds), 0){', ' + sel if sel else ''} FROM jobs "
            "WHERE status = 'succeeded' AND solve_seconds IS NOT NULL").fetchone()
        return [int(x or 0) for x in row[2:]], int(row[0]), float(row[1])

    def all_job_ids(self) -> set[str]:
        return {r[0] for r in self._db().execute("SELECT id FROM jobs").fetchall()}

    def job_ids_of(self, owner_id: int) -> list[str]:
        return [r[0] for r in self._db().execute("SELECT id FROM jobs WHERE owner_id = ?", (owner_id,)).fetchall()]

    # -- jobs: the run of a job --------------------------------------------------------------

    def claim_next(self, worker: str, lease_seconds: float, backend: str) -> Job | None:
        """Take the next queued job for a run: fair between users (the owner with the fewest running
        jobs first), then oldest first. Starts a new attempt with a fresh run token."""
        now = time.time()
        token = secrets.token_hex(8)
        with self.transaction() as db:
            row = db.execute(
                "SELECT j.id FROM jobs j WHERE j.status = 'queued' AND j.backend = ? ORDER BY "
                "(SELECT COUNT(*) FROM jobs r WHERE r.owner_id = j.owner_id AND r.status = 'running'), j.seq LIMIT 1",
                (backend,)).fetchone()
            if not row:
                return None
            db.execute(
                "UPDATE jobs SET status = 'running', attempts = attempts + 1, started_at = ?, updated_at = ?, "
                f"lease_until = ?, worker = ?, run_token = ?, stage = '{STARTING}', fraction = 0, iteration = 0, "
                "cost = NULL WHERE id = ?", (now, now, now + lease_seconds, worker, token, row[0]))
        return self.job(row[0])

    def mark_queued(self, backend: str, stage: str) -> None:
        """Say why the queued jobs wait (their progress stage) until one is claimed."""
        with self.transaction() as db:
            db.execute("UPDATE jobs SET stage = ? WHERE status = 'queued' AND backend = ? AND stage IS NULL",
                       (stage, backend))

    def renew_leases(self, tokens: list[str], lease_seconds: float) -> None:
        if not tokens:
            return
        now = time.time()
        with self.transaction() as db:
            db.execute(f"UPDATE jobs SET lease_until = ? WHERE status = 'running' AND run_token IN "
                       f"({','.join('?' * len(tokens))})", (now + lease_seconds, *tokens))

    def report_progress(self, job_id: str, token: str, stage: str, fraction: float, iteration: int,
                        cost: float | None) -> bool:
        """Record a run's progress. False when the run no longer owns the job (cancelled or superseded)."""
        with self.transaction() as db:
            return db.execute(
                "UPDATE jobs SET stage = ?, fraction = ?, iteration = ?, cost = ?, updated_at = ? "
                "WHERE id = ? AND run_token = ? AND status = 'running'",
                (stage, fraction, iteration, cost, time.time(), job_id, token)).rowcount == 1

    def finish(self, job_id: str, token: str, status: str, *, summary: dict | None = None,
               error: str | None = None, error_kind: ErrorKind | None = None,
               commit: Callable[[], None] | None = None) -> bool:
        """End a run as ``succeeded`` or ``failed``. ``commit`` (moving the result files in place)
        runs inside the transaction, only if the run still owns the job. False if it does not."""
        assert status in ("succeeded", "failed")
        now = time.time()
        with self.transaction() as db:
            row = db.execute("SELECT started_at FROM jobs WHERE id = ? AND run_token = ? AND status = 'running'",
                             (job_id, token)).fetchone()
            if not row:
                return False
            if commit is not None:
                commit()
            db.execute(
                "UPDATE jobs SET status = ?, finished_at = ?, updated_at = ?, lease_until = NULL, summary = ?, "
                f"error = ?, error_kind = ?, solve_seconds = ?, {_ENDED_PROGRESS} WHERE id = ?",
                (status, now, now, _json(summary) if summary is not None else None, error,
                 (error_kind or "internal") if status == "failed" else None,
                 (now - row[0]) if status == "succeeded" and row[0] else None, status, status, job_id))
        return True

    def interrupt(self, job_id: str, token: str | None, reason: str) -> str | None:
        """A run died without finishing: queue the job again, or fail it once ``max_attempts`` runs
        were interrupted. ``token=None`` matches any run. Returns the new status (None: not running)."""
        now = time.time()
        with self.transaction() as db:
            q = "SELECT attempts, max_attempts FROM jobs WHERE id = ? AND status = 'running'"
            args: tuple = (job_id,)
            if token is not None:
                q += " AND run_token = ?"
                args = (job_id, token)
            row = db.execute(q, args).fetchone()
            if not row:
                return None
            attempts, max_attempts = row
            note = f"attempt {attempts} of {max_attempts} interrupted: {reason}"
            if attempts >= max_attempts:
                db.execute("UPDATE jobs SET status = 'failed', finished_at = ?, updated_at = ?, lease_until = NULL, "
                           "run_token = NULL, error = ?, error_kind = 'interrupted', interruption = ? WHERE id = ?",
                           (now, now, f"gave up after {attempts} interrupted attempts; last: {reason}", note, job_id))
                return "failed"
            db.execute("UPDATE jobs SET status = 'queued', updated_at = ?, lease_until = NULL, run_token = NULL, "
                       "worker = NULL, stage = NULL, fraction = NULL, iteration = NULL, cost = NULL, "
                       "interruption = ? WHERE id = ?", (now, note, job_id))
            return "queued"

    def set_worker(self, job_id: str, token: str, worker: str) -> None:
        with self.transaction() as db:
            db.execute("UPDATE jobs SET worker = ? WHERE id = ? AND run_token = ?", (worker, job_id, token))

    def release(self, job_id: str, token: str, note: str) -> bool:
        """Put a run that this service stopped on purpose (an orderly shutdown) back in the queue
        without counting it as an attempt."""
        now = time.time()
        with self.transaction() as db:
            return db.execute(
                "UPDATE jobs SET status = 'queued', attempts = MAX(attempts - 1, 0), updated_at = ?, "
                "lease_until = NULL, run_token = NULL, worker = NULL, stage = NULL, fraction = NULL, "
                "iteration = NULL, cost = NULL, interruption = ? WHERE id = ? AND run_token = ? AND status = 'running'",
                (now, note, job_id, token)).rowcount == 1

    def cancel(self, job_id: str) -> Job | None:
        """Cancel a queued or running job. Returns the job as it was before, or None if it was not active."""
        before = self.job(job_id)
        now = time.time()
        with self.transaction() as db:
            n = db.execute("UPDATE jobs SET status = 'cancelled', finished_at = ?, updated_at = ?, lease_until = NULL, "
                           f"error = NULL WHERE id = ? AND status IN {_ACTIVE_IN}",
                           (now, now, job_id)).rowcount
        return before if n == 1 else None

    def finished_before(self, cutoff: float, owner_id: int | None = None) -> list[Job]:
        """Finished jobs (succeeded, failed, cancelled) that ended before ``cutoff`` (epoch s), oldest first."""
        cond = f"j.status IN {_FINISHED_IN} AND COALESCE(j.finished_at, j.updated_at) < ?"
        args: list = [cutoff]
        if owner_id is not None:
            cond += " AND j.owner_id = ?"
            args.append(owner_id)
        rows = self._db().execute(f"{_JOB_SELECT} WHERE {cond} ORDER BY j.seq", args).fetchall()
        return [_job(r) for r in rows]

    def delete(self, job_id: str) -> bool:
        """Remove a finished job's row."""
        with self.transaction() as db:
            return db.execute(f"DELETE FROM jobs WHERE id = ? AND status IN {_FINISHED_IN}",
                              (job_id,)).rowcount == 1

    # -- jobs: mirror of a queue that runs elsewhere (RQ) -------------------------------------
    # The run token is the id of the RQ job that runs the current attempt(s).

    def assign_run(self, job_id: str, token: str) -> bool:
        with self.transaction() as db:
            return db.execute(f"UPDATE jobs SET run_token = ?, updated_at = ? WHERE id = ? AND status IN {_ACTIVE_IN}",
                              (token, time.time(), job_id)).rowcount == 1

    def mirror_running(self, job_id: str, token: str, attempts: int, worker: str | None,
                       started_at: float | None, lease_seconds: float, progress: dict | None) -> None:
        """Record what a remote worker reports about a running job."""
        now = time.time()
        p = progress or {}
        with self.transaction() as db:
            db.execute(
                "UPDATE jobs SET status = 'running', attempts = MAX(attempts, ?), worker = COALESCE(?, worker), "
                "started_at = COALESCE(?, started_at), lease_until = ?, updated_at = ?, "
                f"stage = COALESCE(?, stage, '{STARTING}'), fraction = COALESCE(?, fraction, 0), "
                "iteration = COALESCE(?, iteration, 0), cost = COALESCE(?, cost) "
                f"WHERE id = ? AND run_token = ? AND status IN {_ACTIVE_IN}",
                (attempts, worker, started_at, now + lease_seconds, now, p.get("stage"), p.get("fraction"),
                 p.get("iteration"), p.get("cost"), job_id, token))

    def mirror_requeued(self, job_id: str, token: str, attempts: int, note: str | None = None) -> None:
        """The queue took the job back (its worker died and RQ retries it)."""
        now = time.time()
        with self.transaction() as db:
            db.execute("UPDATE jobs SET status = 'queued', attempts = MAX(attempts, ?), updated_at = ?, "
                       "lease_until = NULL, worker = NULL, stage = NULL, fraction = NULL, iteration = NULL, "
                       "cost = NULL, interruption = COALESCE(?, interruption) "
                       f"WHERE id = ? AND run_token = ? AND status IN {_ACTIVE_IN}",
                       (attempts, now, note, job_id, token))

    def mirror_finished(self, job_id: str, token: str, status: str, attempts: int, *, summary: dict | None = None,
                        error: str | None = None, solve_seconds: float | None = None, worker: str | None = None,
                        error_kind: ErrorKind | None = None, commit: Callable[[], None] | None = None) -> bool:
        """A remote run ended. ``commit`` stores the result files, inside the transaction."""
        assert status in ("succeeded", "failed")
        now = time.time()
        with self.transaction() as db:
            if not db.execute(f"SELECT 1 FROM jobs WHERE id = ? AND run_token = ? AND status IN {_ACTIVE_IN}",
                              (job_id, token)).fetchone():
                return False
            if commit is not None:
                commit()
            db.execute(
                "UPDATE jobs SET status = ?, attempts = MAX(attempts, ?, 1), finished_at = ?, updated_at = ?, "
                "started_at = COALESCE(started_at, ?), lease_until = NULL, summary = ?, error = ?, error_kind = ?, "
                f"solve_seconds = ?, worker = COALESCE(?, worker), {_ENDED_PROGRESS} WHERE id = ?",
                (status, attempts, now, now, now - (solve_seconds or 0.0), _json(summary) if summary else None,
                 error, (error_kind or "internal") if status == "failed" else None,
                 solve_seconds if status == "succeeded" else None, worker, status, status, job_id))
        return True

    def adopt(self, backend: str, reason: str) -> dict[str, int]:
        """At start-up: take over every active job for ``backend``. Runs that were going on when the
        service stopped are interrupted (queued again, or failed after their last attempt); jobs queued
        for another backend move to this one."""
        out = {"requeued": 0, "failed": 0, "moved": 0}
        for job in self.active_jobs():
            if job.backend != backend:
                with self.transaction() as db:
                    db.execute("UPDATE jobs SET backend = ? WHERE id = ?", (backend, job.id))
                out["moved"] += 1
            if job.status == "running" and (backend == "embedded" or job.backend != backend):
                status = self.interrupt(job.id, None, reason)
                if status == "queued":
                    out["requeued"] += 1
                elif status == "failed":
                    out["failed"] += 1
        return out
