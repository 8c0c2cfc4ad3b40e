"""Jobs in the table: submit, read, list, count, cancel, delete. (A run of a job, on this server's
queue, is :mod:`service.store.leases`; on a queue elsewhere, :mod:`service.store.mirror`.)

A calibration is a job whose options say ``"kind": "calibration"``; a solve's options have no kind.
"""

from __future__ import annotations

import re
import sqlite3
import time

from service.store.database import Database
from service.store.errors import QuotaExceeded
from service.store.records import ACTIVE_IN, FINISHED_IN, JOB_SELECT, STATUSES, Job, job_from_row, to_json


def count_active(db: sqlite3.Connection, owner_id: int) -> int:
    """How many queued and running jobs the owner has."""
    return db.execute(f"SELECT COUNT(*) FROM jobs WHERE owner_id = ? AND status IN {ACTIVE_IN}",
                      (owner_id,)).fetchone()[0]


def counts(db: sqlite3.Connection, owner_id: int | None) -> dict[str, int]:
    """Jobs per state that has any: one owner's, or everyone's (``owner_id=None``)."""
    rows = (db.execute("SELECT status, COUNT(*) FROM jobs WHERE owner_id = ? GROUP BY status", (owner_id,))
            if owner_id is not None else db.execute("SELECT status, COUNT(*) FROM jobs GROUP BY status"))
    return {status: int(n) for status, n in rows.fetchall()}


class JobStore(Database):
    """The rows of the job table, as :class:`service.store.records.Job`."""

    def insert_job(self, job_id: str, owner_id: int, backend: str, options: dict, inputs: dict,
                   max_attempts: int, max_active: int | None = None, label: str | None = None) -> Job:
        """A new queued job; :class:`QuotaExceeded` if its owner already has ``max_active`` active jobs."""
        now = time.time()
        with self.transaction() as db:
            if max_active is not None and count_active(db, owner_id) >= max_active:
                raise QuotaExceeded()
            db.execute(
                "INSERT INTO jobs(id, owner_id, status, backend, created_at, updated_at, max_attempts, options, "
                "inputs, label) VALUES (?, ?, 'queued', ?, ?, ?, ?, ?, ?, ?)",
                (job_id, owner_id, backend, now, now, max_attempts, to_json(options), to_json(inputs), label))
        job = self.job(job_id)
        assert job is not None
        return job

    def job(self, job_id: str) -> Job | None:
        with self.reading() as db:
            row = db.execute(f"{JOB_SELECT} WHERE j.id = ?", (job_id,)).fetchone()
        return job_from_row(row) if row else None

    def jobs(self, owner_id: int | None = None, statuses: list[str] | None = None, limit: int = 50,
             before_seq: int | None = None, label: str | None = None, method: str | None = None,
             since: float | None = None, warnings: bool | None = None,
             kind: str | None = None) -> tuple[list[Job], int]:
        """Jobs newest first, and how many match in all, of one ``kind`` (options' ``kind``: None for
        solves, ``calibration``). ``owner_id=None``: everyone's. ``label``:
        those whose label contains it (any case); ``since``: submitted then or later (epoch s);
        ``warnings``: succeeded with (True) or without (False) warnings in their report."""
        where: list[str] = ["json_extract(j.options, '$.kind') IS ?"]
        args: list[object] = [kind]
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
        page_cond = cond
        page_args = list(args)
        if before_seq is not None:
            page_cond = (cond + " AND " if cond else " WHERE ") + "j.seq < ?"
            page_args.append(before_seq)
        with self.reading() as db:
            total = db.execute(f"SELECT COUNT(*) FROM jobs j{cond}", args).fetchone()[0]
            rows = db.execute(f"{JOB_SELECT}{page_cond} ORDER BY j.seq DESC LIMIT ?", [*page_args, limit]).fetchall()
        return [job_from_row(r) for r in rows], total

    def active_jobs(self, backend: str | None = None) -> list[Job]:
        cond = f"j.status IN {ACTIVE_IN}" + (" AND j.backend = ?" if backend else "")
        with self.reading() as db:
            rows = db.execute(f"{JOB_SELECT} WHERE {cond} ORDER BY j.seq", (backend,) if backend else ()).fetchall()
        return [job_from_row(r) for r in rows]

    def count_active(self, owner_id: int) -> int:
        with self.reading() as db:
            return count_active(db, owner_id)

    def job_counts(self, owner_id: int) -> dict[str, int]:
        """The owner's jobs in each state (every state, 0 for none)."""
        with self.reading() as db:
            found = counts(db, owner_id)
        return {s: found.get(s, 0) for s in STATUSES}

    def status_counts(self) -> dict[str, int]:
        """Everyone's jobs in each state (every state, 0 for none)."""
        with self.reading() as db:
            found = counts(db, None)
        return {s: found.get(s, 0) for s in STATUSES}

    def oldest_queued_at(self, backend: str | None = None) -> float | None:
        """When the job that has waited longest in the queue (of ``backend``, or any) was submitted
        (None: nothing queued)."""
        with self.reading() as db:
            if backend is None:
                return db.execute("SELECT MIN(created_at) FROM jobs WHERE status = 'queued'").fetchone()[0]
            return db.execute("SELECT MIN(created_at) FROM jobs WHERE status = 'queued' AND backend = ?",
                              (backend,)).fetchone()[0]

    def solve_seconds_histogram(self, buckets: list[float]) -> tuple[list[int], int, float]:
        """Cumulative counts of succeeded solves with ``solve_seconds <= b`` per bucket, count, sum."""
        sel = ", ".join(f"SUM(solve_seconds <= {float(b)!r})" for b in buckets)
        with self.reading() as db:
            row = db.execute(
                f"SELECT COUNT(*), COALESCE(SUM(solve_seconds), 0){', ' + sel if sel else ''} FROM jobs "
                "WHERE status = 'succeeded' AND solve_seconds IS NOT NULL").fetchone()
        return [int(x or 0) for x in row[2:]], int(row[0]), float(row[1])

    def all_job_ids(self) -> set[str]:
        with self.reading() as db:
            return {r[0] for r in db.execute("SELECT id FROM jobs").fetchall()}

    def job_ids_of(self, owner_id: int) -> list[str]:
        with self.reading() as db:
            return [r[0] for r in db.execute("SELECT id FROM jobs WHERE owner_id = ?", (owner_id,)).fetchall()]

    def cancel(self, job_id: str) -> Job | None:
        """Cancel a queued or running job. Returns the job as it was before, or None if it was not active."""
        before = self.job(job_id)
        now = time.time()
        with self.transaction() as db:
            n = db.execute("UPDATE jobs SET status = 'cancelled', finished_at = ?, updated_at = ?, lease_until = NULL, "
                           f"error = NULL, detail = NULL WHERE id = ? AND status IN {ACTIVE_IN}",
                           (now, now, job_id)).rowcount
        return before if n == 1 else None

    def finished_before(self, cutoff: float, owner_id: int | None = None) -> list[Job]:
        """Finished jobs (succeeded, failed, cancelled) that ended before ``cutoff`` (epoch s), oldest first."""
        cond = f"j.status IN {FINISHED_IN} AND COALESCE(j.finished_at, j.updated_at) < ?"
        args: list = [cutoff]
        if owner_id is not None:
            cond += " AND j.owner_id = ?"
            args.append(owner_id)
        with self.reading() as db:
            rows = db.execute(f"{JOB_SELECT} WHERE {cond} ORDER BY j.seq", args).fetchall()
        return [job_from_row(r) for r in rows]

    def delete(self, job_id: str) -> bool:
        """Remove a finished job's row."""
        with self.transaction() as db:
            return db.execute(f"DELETE FROM jobs WHERE id = ? AND status IN {FINISHED_IN}",
                              (job_id,)).rowcount == 1
