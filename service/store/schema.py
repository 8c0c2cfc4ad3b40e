"""The job table's schema, as numbered migrations. SQLite's ``PRAGMA user_version`` (an integer in
the file's header, 0 in a new file) is the number of migrations the file has had.

Opening the table (:class:`service.store.database.Database`) applies those it has not had, in order,
in one ``BEGIN IMMEDIATE`` transaction with the new version: a crash leaves the file before them or
after, and of several processes opening it at once one migrates and the others find it done. A file
with a version above :data:`VERSION` was written by a newer release and is refused.

Migration 1 is the schema as it was when versions began (users, tokens, jobs and its indexes).
Files from before then are at version 0 and already hold those tables, some without the columns
added to ``jobs`` over time: so migration 1 creates only what is missing, and migrations 2 and 3
add a column only where it is missing (in a new file, migration 1 made it). From 4 on a migration
changes a file of a known version and need not check.
"""

from __future__ import annotations

import sqlite3
from pathlib import Path
from typing import Callable

from service.store.errors import StoreError

_TABLES = (
    """CREATE TABLE IF NOT EXISTS users (
        id          INTEGER PRIMARY KEY AUTOINCREMENT,
        name        TEXT NOT NULL UNIQUE,
        is_admin    INTEGER NOT NULL DEFAULT 0,
        disabled    INTEGER NOT NULL DEFAULT 0,
        created_at  REAL NOT NULL
    )""",
    """CREATE TABLE IF NOT EXISTS tokens (
        key_id         TEXT PRIMARY KEY,
        user_id        INTEGER NOT NULL REFERENCES users(id),
        secret_sha256  TEXT NOT NULL,
        created_at     REAL NOT NULL
    )""",
    """CREATE TABLE IF NOT EXISTS jobs (
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
    )""",
    "CREATE INDEX IF NOT EXISTS jobs_by_status ON jobs(status, seq)",
    "CREATE INDEX IF NOT EXISTS jobs_by_owner ON jobs(owner_id, seq)",
)


def _create_tables(db: sqlite3.Connection) -> None:
    for statement in _TABLES:
        db.execute(statement)


def _add_column(table: str, name: str, kind: str) -> Callable[[sqlite3.Connection], None]:
    """A migration adding ``table.name`` unless the table has it already."""
    def add(db: sqlite3.Connection) -> None:
        if name not in {row[1] for row in db.execute(f"PRAGMA table_info({table})")}:
            db.execute(f"ALTER TABLE {table} ADD COLUMN {name} {kind}")
    return add


# Migration n is MIGRATIONS[n - 1]: what it does, and the step. Append only; never edit a released one.
MIGRATIONS: tuple[tuple[str, Callable[[sqlite3.Connection], None]], ...] = (
    ("users, tokens and jobs, with the jobs' indexes", _create_tables),
    ("jobs.label: the submitter's name for a job", _add_column("jobs", "label", "TEXT")),
    ("jobs.error_kind: why a failed job failed", _add_column("jobs", "error_kind", "TEXT")),
    ("jobs.detail: where a running job's stage is, in words", _add_column("jobs", "detail", "TEXT")),
)
VERSION = len(MIGRATIONS)


def version(db: sqlite3.Connection) -> int:
    """The number of migrations the open file has had."""
    return int(db.execute("PRAGMA user_version").fetchone()[0])


def migrate(db: sqlite3.Connection, path: Path) -> list[int]:
    """Apply the migrations the file has not had, inside the caller's write transaction, and set its
    version to :data:`VERSION`; the numbers applied. :class:`StoreError` for a newer file."""
    have = version(db)
    if have > VERSION:
        raise StoreError(f"job table {path}: schema version {have} is newer than this release's {VERSION}; "
                         "run the release that wrote it")
    applied = []
    for number in range(have + 1, VERSION + 1):
        MIGRATIONS[number - 1][1](db)
        applied.append(number)
    if applied:
        db.execute(f"PRAGMA user_version = {VERSION:d}")
    return applied
