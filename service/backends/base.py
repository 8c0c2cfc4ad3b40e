"""The small interface every backend implements.

The job table (:class:`service.store.Store`) is the record of truth; a backend only runs what the
table says is queued and reports back into it. A job is in the table and its files are in the data
dir before :meth:`Backend.submit` is called, so a backend that loses a submission (a crash in
between) finds it again in the table when it starts.
"""

from __future__ import annotations

import logging
import threading
from abc import ABC, abstractmethod

from service.settings import Settings
from service.store import Store

log = logging.getLogger("acinoset.service")


class Backend(ABC):
    """A backend dispatches from one thread of its own: :meth:`_tick` every :attr:`TICK` seconds,
    or at once when woken (``self._wake.set()``)."""

    name: str
    TICK: float

    def __init__(self, settings: Settings, store: Store):
        self.settings = settings
        self.store = store
        self._wake = threading.Event()
        self._halt = threading.Event()
        self._thread: threading.Thread | None = None

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
            self._tick()

    @abstractmethod
    def _tick(self) -> None:
        """One pass of the dispatch thread; it must not raise (log and carry on)."""

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
