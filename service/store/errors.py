"""What the job table cannot do: one family of exceptions, raised from inside :mod:`service.store`
(no ``sqlite3`` error leaves the package; nothing outside it needs to know the table is SQLite)::

    StoreError            the table could not do what was asked
    +-- StoreRefused      a request refused for its content: unknown user, name taken, bad name
    +-- QuotaExceeded     the owner already has the most active jobs allowed
    +-- StoreFull         SQLITE_FULL: the disk holding the file is full (its log cannot grow)
    +-- StoreBusy         SQLITE_BUSY or SQLITE_LOCKED: another writer held the file past the busy timeout
    +-- StoreCorrupt      SQLITE_CORRUPT or SQLITE_NOTADB: the file is not a sound database

Each carries one line naming the file; the SQLite error it stands for is its ``__cause__``.
They pickle (a single message argument), like :mod:`service.errors`'.
"""

from __future__ import annotations

import sqlite3
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator


class StoreError(Exception):
    """The job table could not do what was asked."""


class StoreRefused(StoreError, ValueError):
    """A user-management request that cannot be done (unknown user, name taken, bad name)."""


class QuotaExceeded(StoreError):
    """The owner already has the most active jobs allowed."""


class StoreFull(StoreError):
    """The disk holding the job table is full: a write cannot grow the file or its log."""


class StoreBusy(StoreError):
    """Another connection held the job table locked for longer than the busy timeout."""


class StoreCorrupt(StoreError):
    """The job table's file is damaged, or not a database."""


_BY_CODE: dict[int, type[StoreError]] = {
    sqlite3.SQLITE_FULL: StoreFull,
    sqlite3.SQLITE_BUSY: StoreBusy,
    sqlite3.SQLITE_LOCKED: StoreBusy,
    sqlite3.SQLITE_CORRUPT: StoreCorrupt,
    sqlite3.SQLITE_NOTADB: StoreCorrupt,
}


def store_error(e: sqlite3.Error, path: Path) -> StoreError:
    """The :class:`StoreError` that ``e`` stands for, by SQLite's primary result code (the low byte
    of the extended code); the message when no code came with it (SQLite's texts for these codes)."""
    code = getattr(e, "sqlite_errorcode", None)
    kind = _BY_CODE.get(code & 0xFF) if isinstance(code, int) else None
    text = str(e)
    if kind is None:
        kind = (StoreFull if "disk is full" in text else StoreBusy if "database is locked" in text
                else StoreCorrupt if "malformed" in text or "not a database" in text else StoreError)
    return kind(f"job table {path}: {text}")


@contextmanager
def translated(path: Path) -> Iterator[None]:
    """Raise any ``sqlite3`` error of the block as its :class:`StoreError`; anything else unchanged."""
    try:
        yield
    except sqlite3.Error as e:
        raise store_error(e, path) from e
