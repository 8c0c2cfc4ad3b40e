"""The run of a job from this server's own queue (the embedded backend): claim, lease, progress, end.

A run of a job holds a *lease* (``lease_until``) that its owner renews, and a ``run_token``
naming that run. Writes from a run (progress, the result) only apply while the row is ``running``
with the same token: a run that was given up for lost, or cancelled, cannot overwrite a newer one.
"""

from __future__ import annotations

import secrets
import time
from typing import Callable

from service.store.jobs import JobStore
from service.store.records import ENDED_PROGRESS, STARTING, ErrorKind, Job, to_json


class LeaseStore(JobStore):
    """Runs of jobs: who holds one, until when, how far it got, and how it ended."""

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
                "cost = NULL, detail = NULL WHERE id = ?", (now, now, now + lease_seconds, worker, token, row[0]))
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
                        cost: float | None, detail: str | None = None) -> bool:
        """Record a run's progress. False when the run no longer owns the job (cancelled or superseded)."""
        with self.transaction() as db:
            return db.execute(
                "UPDATE jobs SET stage = ?, fraction = ?, iteration = ?, cost = ?, detail = ?, updated_at = ? "
                "WHERE id = ? AND run_token = ? AND status = 'running'",
                (stage, fraction, iteration, cost, detail, time.time(), job_id, token)).rowcount == 1

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
                f"error = ?, error_kind = ?, solve_seconds = ?, {ENDED_PROGRESS} WHERE id = ?",
                (status, now, now, to_json(summary) if summary is not None else None, error,
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
                           "run_token = NULL, error = ?, error_kind = 'interrupted', interruption = ?, detail = NULL "
                           "WHERE id = ?",
                           (now, now, f"gave up after {attempts} interrupted attempts; last: {reason}", note, job_id))
                return "failed"
            db.execute("UPDATE jobs SET status = 'queued', updated_at = ?, lease_until = NULL, run_token = NULL, "
                       "worker = NULL, stage = NULL, fraction = NULL, iteration = NULL, cost = NULL, detail = NULL, "
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
                "iteration = NULL, cost = NULL, detail = NULL, interruption = ? "
                "WHERE id = ? AND run_token = ? AND status = 'running'",
                (now, note, job_id, token)).rowcount == 1

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
