"""The job table and the users: one SQLite file in the data dir, the service's record of truth.

One :class:`Store` for its callers, made of one part per concern over the same connections
(:class:`service.store.database.Database`):

* :mod:`service.store.users`: users and their tokens;
* :mod:`service.store.jobs`: jobs (solves and calibrations alike): submit, read, list, cancel, delete;
* :mod:`service.store.leases`: the run of a job from this server's queue, under a lease;
* :mod:`service.store.mirror`: the runs of a queue elsewhere (RQ), as it reports them;
* :mod:`service.store.schema`: the tables, as numbered migrations;
* :mod:`service.store.records`: the states of a job, and a user and a job as read;
* :mod:`service.store.errors`: :class:`StoreError` and its kinds, the only errors the table raises.
"""

from __future__ import annotations

from service.store.errors import QuotaExceeded, StoreBusy, StoreCorrupt, StoreError, StoreFull, StoreRefused
from service.store.leases import LeaseStore
from service.store.mirror import MirrorStore
from service.store.records import (
    ACTIVE,
    COMPILING,
    DONE,
    FINISHED,
    READING,
    RENDERING,
    STARTING,
    STATUSES,
    WRITING,
    ErrorKind,
    Job,
    JobStatus,
    User,
)
from service.store.users import TOKEN_PREFIX, USER_NAME, UserStore, hash_secret

__all__ = ["ACTIVE", "COMPILING", "DONE", "FINISHED", "READING", "RENDERING", "STARTING", "STATUSES", "TOKEN_PREFIX",
           "USER_NAME", "WRITING", "ErrorKind", "Job", "JobStatus", "QuotaExceeded", "Store", "StoreBusy",
           "StoreCorrupt", "StoreError", "StoreFull", "StoreRefused", "User", "hash_secret"]


class Store(UserStore, LeaseStore, MirrorStore):
    """The SQLite job table and users. Safe to share between threads (one connection per thread)
    and between processes (SQLite's own locking; each process opens its own :class:`Store`)."""
