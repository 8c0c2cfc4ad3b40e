"""What the job table holds: the states and stages of a job, a user and a job as read, and the SQL
pieces the parts of :mod:`service.store` share to read and write them.

A job's life::

    queued --claim--> running --finish--> succeeded | failed
       ^                 |
       +---interrupt-----+   (the process running it died: again, or failed after max_attempts)
    queued | running --cancel--> cancelled
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from typing import Literal, get_args

JobStatus = Literal["queued", "running", "succeeded", "failed", "cancelled"]  # the one list of job states
STATUSES: tuple[str, ...] = get_args(JobStatus)
ACTIVE: tuple[str, ...] = ("queued", "running")
FINISHED: tuple[str, ...] = tuple(s for s in STATUSES if s not in ACTIVE)

# The stages of a run the service records itself, around the solver's own (graph.types.STAGES,
# reported by the solve as it goes; service.api.models.STAGES publishes the whole sequence):
COMPILING = "compiling"  # queued while the server compiles its solver, once after an install (set here)
STARTING = "starting"  # claimed, its process starting (set here)
READING = "reading"  # reading the input files (service.run.worker)
WRITING = "writing"  # writing the result files (service.run.worker)
RENDERING = "rendering videos"  # drawing the result over the job's videos, when it has some (service.run.worker)
DONE = "done"  # the result is stored (set here)

# Why a failed job failed: its input (a file or option the solver refuses), a limit of this server,
# runs that kept being interrupted, or an error of the software itself.
ErrorKind = Literal["input", "limit", "interrupted", "internal"]


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
    detail: str | None = None  # where the stage is, in words (a long run's windows done and the time left)

    @property
    def active(self) -> bool:
        return self.status in ACTIVE


def sql_in(statuses: tuple[str, ...]) -> str:
    """``('a', 'b')``: a constant list of states for SQL's ``IN``."""
    return "(" + ", ".join(f"'{s}'" for s in statuses) + ")"


ACTIVE_IN = sql_in(ACTIVE)
FINISHED_IN = sql_in(FINISHED)
# the progress of a run that ended with the status given twice as parameters: complete if it succeeded
ENDED_PROGRESS = (f"fraction = CASE WHEN ? = 'succeeded' THEN 1.0 ELSE fraction END, "
                  f"stage = CASE WHEN ? = 'succeeded' THEN '{DONE}' ELSE stage END, detail = NULL")

JOB_COLUMNS = ("j.seq, j.id, j.owner_id, u.name, j.status, j.backend, j.created_at, j.started_at, "
               "j.finished_at, j.updated_at, j.attempts, j.max_attempts, j.lease_until, j.worker, "
               "j.run_token, j.options, j.inputs, j.stage, j.fraction, j.iteration, j.cost, j.error, "
               "j.interruption, j.summary, j.solve_seconds, j.label, j.error_kind, j.detail")
JOB_SELECT = f"SELECT {JOB_COLUMNS} FROM jobs j JOIN users u ON u.id = j.owner_id"
USER_COLUMNS = "id, name, is_admin, disabled, created_at"


def job_from_row(row) -> Job:
    """A :class:`Job` from a row of :data:`JOB_SELECT` (options, inputs and summary decoded from JSON)."""
    r = list(row)
    r[15] = json.loads(r[15])
    r[16] = json.loads(r[16])
    r[23] = json.loads(r[23]) if r[23] else None
    return Job(*r)


def user_from_row(row, token_key: str = "") -> User:
    """A :class:`User` from a row of :data:`USER_COLUMNS`."""
    return User(row[0], row[1], bool(row[2]), bool(row[3]), row[4], token_key)


def to_json(x) -> str:
    """Compact JSON, refusing NaN and infinities (a column read back must parse as strict JSON)."""
    return json.dumps(x, separators=(",", ":"), allow_nan=False)
