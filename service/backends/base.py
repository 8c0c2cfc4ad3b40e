"""The small interface every backend implements.

The job table (:class:`service.store.Store`) is the record of truth; a backend only runs what the
table says is queued and reports back into it. A job is in the table and its files are in the data
dir before :meth:`Backend.submit` is called, so a backend that loses a submission (a crash in
between) finds it again in the table when it starts.
"""

from __future__ import annotations

import logging
from abc import ABC, abstractmethod

from service.settings import Settings
from service.store import Store

log = logging.getLogger("acinoset.service")


class Backend(ABC):
    name: str

    def __init__(self, settings: Settings, store: Store):
        self.settings = settings
        self.store = store

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
