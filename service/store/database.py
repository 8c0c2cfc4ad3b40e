"""The job table's file: one SQLite database in the data dir, its connections and transactions.
The parts of :class:`service.store.Store` (users, jobs, leases, the queue mirror) all read and
write through :class:`Database`.

SQLite in WAL mode lets the API answer reads while solves write their progress. Every change is
one short ``BEGIN IMMEDIATE`` transaction (the write lock taken at once, so two writers never
deadlock upgrading a read lock), so a crash leaves each row either before or after the change,
never half-way. Every ``sqlite3`` error of a read or a transaction is raised as its
:class:`service.store.errors.StoreError`.

A full disk: beside the file the server keeps a *reserve*, a file of :data:`RESERVE_BYTES`
(:meth:`Database.keep_reserve`). The first transaction that fails for want of room
(:class:`~service.store.errors.StoreFull`) deletes it, so the next one (the record of a job failed
by the full disk, say) has room to commit; the reserve is made again once the disk has room.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import sqlite3
import threading
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

from service.store import schema
from service.store.errors import StoreFull, translated

BUSY_TIMEOUT_SECONDS = 30.0  # how long a write waits for another's lock before StoreBusy
RESERVE_BYTES = 1 << 20  # room for some hundred small transactions once the disk is full


class Database:
    """The open job table. Safe to share between threads (one connection per thread) and between
    processes (SQLite's own locking; each process opens its own). Opening it migrates the file to
    this release's schema (:mod:`service.store.schema`)."""

    def __init__(self, path: str | Path, busy_timeout: float = BUSY_TIMEOUT_SECONDS):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._busy_timeout = busy_timeout
        self._local = threading.local()
        with self.reading() as db:
            current = schema.version(db) == schema.VERSION
        if not current:
            with self.transaction() as db:
                schema.migrate(db, self.path)

    def _db(self) -> sqlite3.Connection:
        """This thread's connection (opened on first use); call inside :meth:`reading` or :meth:`transaction`."""
        db = getattr(self._local, "db", None)
        if db is None:
            db = sqlite3.connect(self.path, timeout=self._busy_timeout, isolation_level=None,
                                 check_same_thread=False)
            try:
                db.execute("PRAGMA journal_mode=WAL")
                db.execute("PRAGMA synchronous=NORMAL")  # in WAL: durable against a process crash
                db.execute(f"PRAGMA busy_timeout={int(self._busy_timeout * 1000)}")
                db.execute("PRAGMA foreign_keys=ON")
            except BaseException:
                db.close()
                raise
            self._local.db = db
        return db

    @contextmanager
    def reading(self) -> Iterator[sqlite3.Connection]:
        """The connection for reads outside a transaction (each statement sees one snapshot)."""
        with translated(self.path):
            yield self._db()

    @contextmanager
    def transaction(self) -> Iterator[sqlite3.Connection]:
        """One write transaction, taken at once (``BEGIN IMMEDIATE``) so it never deadlocks on upgrade.
        Anything raised inside rolls it back; a failed commit too (SQLite may keep the transaction
        open after one: the next would find it and fail to begin)."""
        try:
            with translated(self.path):
                db = self._db()
                db.execute("BEGIN IMMEDIATE")
                try:
                    yield db
                    db.execute("COMMIT")
                except BaseException:
                    _rollback(db)
                    raise
        except StoreFull:
            self.release_reserve()
            raise

    @property
    def reserve(self) -> Path:
        return self.path.with_name(self.path.name + ".reserve")

    def release_reserve(self) -> None:
        """Delete the reserve (the disk is full), if there is one."""
        with contextlib.suppress(OSError):
            self.reserve.unlink()

    def keep_reserve(self) -> bool:
        """Make the reserve if it is missing and the disk has room for it four times over; whether
        it is there. Written whole under a temporary name, then renamed: never a part of one."""
        if self.reserve.exists():
            return True
        try:
            if shutil.disk_usage(self.path.parent).free < 4 * RESERVE_BYTES:
                return False
            part = self.reserve.with_name(self.reserve.name + ".part")
            try:
                with open(part, "wb") as f:
                    f.write(b"\0" * RESERVE_BYTES)
                    f.flush()
                    os.fsync(f.fileno())
                os.replace(part, self.reserve)
            finally:
                part.unlink(missing_ok=True)
        except OSError:
            return False
        return True

    def close(self) -> None:
        """Close this thread's connection (the next use opens another)."""
        db = getattr(self._local, "db", None)
        if db is not None:
            with translated(self.path):
                db.close()
            self._local.db = None


def _rollback(db: sqlite3.Connection) -> None:
    """Roll back the open transaction, if SQLite has not already (after SQLITE_FULL it may have): the
    error that caused it is the one to raise, not the rollback's."""
    if db.in_transaction:
        with contextlib.suppress(sqlite3.Error):
            db.execute("ROLLBACK")
