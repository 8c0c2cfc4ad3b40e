"""The job table as the mirror of a queue that runs elsewhere (RQ, :mod:`service.backends.rq`): the
table stays the record of truth, and records what the queue reports of each run.

The run token is the id of the RQ job that runs the current attempt(s): a report about another RQ
job (one the table gave up on, or a cancelled job's) changes nothing.
"""

from __future__ import annotations

import time
from typing import Callable

from service.store.jobs import JobStore
from service.store.records import ACTIVE_IN, ENDED_PROGRESS, STARTING, ErrorKind, to_json


class MirrorStore(JobStore):
    """What a remote queue reports of a job's runs."""

    def assign_run(self, job_id: str, token: str) -> bool:
        with self.transaction() as db:
            return db.execute(f"UPDATE jobs SET run_token = ?, updated_at = ? WHERE id = ? AND status IN {ACTIVE_IN}",
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
                "iteration = COALESCE(?, iteration, 0), cost = COALESCE(?, cost), "
                "detail = CASE WHEN ? THEN ? ELSE detail END "
                f"WHERE id = ? AND run_token = ? AND status IN {ACTIVE_IN}",
                (attempts, worker, started_at, now + lease_seconds, now, p.get("stage"), p.get("fraction"),
                 p.get("iteration"), p.get("cost"), progress is not None, p.get("detail"), job_id, token))

    def mirror_requeued(self, job_id: str, token: str, attempts: int, note: str | None = None) -> None:
        """The queue took the job back (its worker died and RQ retries it)."""
        now = time.time()
        with self.transaction() as db:
            db.execute("UPDATE jobs SET status = 'queued', attempts = MAX(attempts, ?), updated_at = ?, "
                       "lease_until = NULL, worker = NULL, stage = NULL, fraction = NULL, iteration = NULL, "
                       "cost = NULL, detail = NULL, interruption = COALESCE(?, interruption) "
                       f"WHERE id = ? AND run_token = ? AND status IN {ACTIVE_IN}",
                       (attempts, now, note, job_id, token))

    def mirror_finished(self, job_id: str, token: str, status: str, attempts: int, *, summary: dict | None = None,
                        error: str | None = None, solve_seconds: float | None = None, worker: str | None = None,
                        error_kind: ErrorKind | None = None, commit: Callable[[], None] | None = None) -> bool:
        """A remote run ended. ``commit`` stores the result files, inside the transaction."""
        assert status in ("succeeded", "failed")
        now = time.time()
        with self.transaction() as db:
            if not db.execute(f"SELECT 1 FROM jobs WHERE id = ? AND run_token = ? AND status IN {ACTIVE_IN}",
                              (job_id, token)).fetchone():
                return False
            if commit is not None:
                commit()
            db.execute(
                "UPDATE jobs SET status = ?, attempts = MAX(attempts, ?, 1), finished_at = ?, updated_at = ?, "
                "started_at = COALESCE(started_at, ?), lease_until = NULL, summary = ?, error = ?, error_kind = ?, "
                f"solve_seconds = ?, worker = COALESCE(?, worker), {ENDED_PROGRESS} WHERE id = ?",
                (status, attempts, now, now, now - (solve_seconds or 0.0), to_json(summary) if summary else None,
                 error, (error_kind or "internal") if status == "failed" else None,
                 solve_seconds if status == "succeeded" else None, worker, status, status, job_id))
        return True
