"""The small interface every backend implements.

The job table (:class:`service.store.Store`) is the record of truth; a backend only runs what the
table says is queued and reports back into it. A job is in the table and its files are in the data
dir before :meth:`Backend.submit` is called, so a backend that loses a submission (a crash in
between) finds it again in the table when it starts.
"""

from __future__ import annotations

import logging
import threading
import time
from abc import ABC, abstractmethod

from service.settings import Settings
from service.store import Store, StoreFull

log = logging.getLogger("acinoset.service")


class Backend(ABC):
    """A backend dispatches from one thread of its own: :meth:`_tick` every :attr:`TICK` seconds,
    or at once when woken (``self._wake.set()``).

    While the job table cannot be written for want of room (:class:`StoreFull` from a tick), each
    tick tries again, and the log says so once when it starts and once when it ends, not a
    traceback a tick. Every :attr:`RESERVE_CHECK_S` seconds the table's reserve is made again if it
    was spent and the disk has room (:meth:`service.store.database.Database.keep_reserve`)."""

    name: str
    TICK: float
    RESERVE_CHECK_S = 5.0

    def __init__(self, settings: Settings, store: Store):
        self.settings = settings
        self.store = store
        self._wake = threading.Event()
        self._halt = threading.Event()
        self._thread: threading.Thread | None = None
        self._table_full = False  # the table cannot be written for want of room
        self._reserve_checked = 0.0

    # -- the dispatch thread -----------------------------------------------------------------

    def _adopt(self) -> None:
        """Take over the table's active jobs (:meth:`service.store.Store.adopt`)."""
        counts = self.store.adopt(self.name, "the service stopped while it ran")
        if any(counts.values()):
            log.warning("recovered jobs from the last run: %s", counts)

    def _start_thread(self, name: str) -> None:
        self._thread = threading.Thread(target=self._loop, name=name, daemon=True)
        self._thread.start()

    def _stop_thread(self) -> None:
        self._halt.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join(timeout=10)

    def _thread_alive(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def _loop(self) -> None:
        while not self._halt.is_set():
            self._wake.wait(timeout=self.TICK)
            self._wake.clear()
            if self._halt.is_set():
                break
            self._guarded_tick()

    def _guarded_tick(self) -> None:
        try:
            self._tick()
        except StoreFull as e:
            if not self._table_full:
                log.error("the disk is full: %s; jobs wait, and runs that end are recorded once there is room", e)
            self._table_full = True
            time.sleep(0.5)
            return
        if self._table_full:
            log.warning("the job table can be written again")
            self._table_full = False
        if time.monotonic() - self._reserve_checked >= self.RESERVE_CHECK_S:
            self._reserve_checked = time.monotonic()
            self.store.keep_reserve()

    @abstractmethod
    def _tick(self) -> None:
        """One pass of the dispatch thread; it must not raise but :class:`StoreFull` (log and carry on)."""

    # -- what the app calls ------------------------------------------------------------------

    @abstractmethod
    def start(self) -> None:
        """Take over the table's active jobs (re-queue interrupted runs) and start dispatching."""

    @abstractmethod
    def stop(self) -> None:
        """Stop dispatching. Runs this process owns are stopped and queued again."""

    @abstractmethod
    def submit(self, job_id: str) -> None:
        """A new queued job is in the table."""

    @abstractmethod
    def cancel(self, job_id: str, run_token: str | None) -> None:
        """The table already says cancelled: stop the run, if any, for real."""

    @abstractmethod
    def health(self) -> dict:
        """``{"ok": bool, "workers": int, "detail": str | None}``."""
