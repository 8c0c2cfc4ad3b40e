"""A long job's windows shared with helper processes of the embedded backend, through the job's folder.

On the embedded backend every process runs on the server's machine: the job's process (the parent)
and the helper processes the server starts for it in its free slots
(:class:`service.backends.embedded.EmbeddedBackend`) meet in a folder of the run's scratch
(:func:`service.store.jobfiles.windows_board`), a :class:`~service.run.shared_windows.Board` made of
files, each written whole (a temporary name, then a rename or link):

* ``wanted``: how many helpers the parent asks for (the server reads it); ``parent``: its pid;
* ``plan.json``, ``next``, ``stop``;
* ``claims/<k>``: who solves window k (created by a hard link, which fails if it exists: one claim);
* ``staging/<c>``: who stages camera c, when the helpers stage the cameras with the parent (the
  folder is there while they do: :func:`~service.run.shared_windows.stage_together`);
* ``alive/<who>``: a helper's heartbeat (its pid; gone when the file is older than
  :data:`~service.run.shared_windows.BEAT_TTL_S` or the process has ended);
* ``done/<k>/``: window k's result (:func:`~service.run.shared_windows.write_window`).

The run's cameras are staged beside the board, by the parent and its helpers between them (or by the
parent alone, :meth:`graph.io.staged.StagedRun.save`, when it asked for helpers only after), and
read from there by the helpers; the folder goes with the run's scratch when the run ends.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from graph.app.processes import pid_alive
from service.run.shared_windows import BEAT_TTL_S, read_window, write_window


class FolderBoard:
    """The :class:`~service.run.shared_windows.Board` of one embedded run in ``folder`` (module docstring)."""

    def __init__(self, folder: Path):
        self.folder = Path(folder)

    # -- files written whole ---------------------------------------------------------------------

    def _temporary(self, text: str) -> Path:
        """``text`` in a new file of the board's, under a temporary name."""
        fd, tmp = tempfile.mkstemp(prefix=".", dir=self.folder)
        with os.fdopen(fd, "w") as f:
            f.write(text)
        return Path(tmp)

    def _write(self, name: str, text: str) -> None:
        tmp = self._temporary(text)
        try:
            os.replace(tmp, self.folder / name)
        except BaseException:
            tmp.unlink(missing_ok=True)
            raise

    def _read(self, name: str) -> str | None:
        try:
            return (self.folder / name).read_text()
        except (FileNotFoundError, NotADirectoryError):
            return None

    # -- the server's side -------------------------------------------------------------------------

    def want(self, helpers: int) -> None:
        """The parent asks for ``helpers`` helper processes."""
        for sub in ("claims", "alive", "done"):
            (self.folder / sub).mkdir(parents=True, exist_ok=True)
        self._write("parent", str(os.getpid()))
        self._write("wanted", str(int(helpers)))

    def wanted(self) -> int:
        """How many helpers the parent asks for now: none once it stopped, or every window is claimed."""
        text = self._read("wanted")
        if text is None or self.stopped():
            return 0
        plan = self.plan()
        if plan is not None and self.all_claimed(len(plan["spans"])):
            return 0
        try:
            return max(0, int(text))
        except ValueError:
            return 0

    # -- the board -----------------------------------------------------------------------------

    def publish(self, plan: dict, windows: int, me: str) -> None:
        for sub in ("claims", "done"):
            shutil.rmtree(self.folder / sub, ignore_errors=True)
            (self.folder / sub).mkdir(parents=True)
        (self.folder / "alive").mkdir(parents=True, exist_ok=True)
        self.set_next(0)
        self._write("plan.json", json.dumps(plan))

    def plan(self) -> dict | None:
        text = self._read("plan.json")
        return None if text is None else json.loads(text)

    def _link(self, name: str, who: str) -> bool:
        """``name`` made, holding ``who``, unless it exists (a hard link: made whole, at most once)."""
        tmp = self._temporary(who)
        try:
            os.link(tmp, self.folder / name)
            return True
        except FileExistsError:
            return False
        finally:
            tmp.unlink()

    def claim(self, k: int, who: str) -> bool:
        return self._link(f"claims/{k}", who)

    def owner(self, k: int) -> str | None:
        return self._read(f"claims/{k}")

    def take_over(self, k: int, who: str) -> None:
        self._write(f"claims/{k}", who)

    def all_claimed(self, windows: int) -> bool:
        try:
            return len(os.listdir(self.folder / "claims")) >= windows
        except FileNotFoundError:
            return False

    def set_next(self, k: int) -> None:
        self._write("next", str(k))

    def next(self) -> int:
        text = self._read("next")
        return int(text) if text else 0

    def put(self, k: int, result, valid: np.ndarray) -> None:
        tmp = Path(tempfile.mkdtemp(prefix=f".{k}-", dir=self.folder / "done"))
        try:
            write_window(tmp, result, valid)
            os.rename(tmp, self.folder / "done" / str(k))
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise

    def take(self, k: int) -> tuple[Any, np.ndarray] | None:
        done = self.folder / "done" / str(k)
        if not done.is_dir():
            return None
        got = read_window(done)
        shutil.rmtree(done, ignore_errors=True)
        return got

    def finished(self, k: int) -> bool:
        return (self.folder / "done" / str(k)).is_dir()

    def beat(self, who: str) -> None:
        if self.stopped():  # the run ended: nothing new in a folder on its way out
            return
        try:
            self._write(f"alive/{who}", str(os.getpid()))
        except FileNotFoundError:  # the run ended: its folder went
            pass

    def alive(self, who: str) -> bool:
        path = self.folder / "alive" / who
        try:
            fresh = time.time() - path.stat().st_mtime < BEAT_TTL_S
            return fresh and pid_alive(int(path.read_text()))
        except (OSError, ValueError):
            return False

    def leave(self, who: str) -> None:
        (self.folder / "alive" / who).unlink(missing_ok=True)

    def stop(self) -> None:
        if self.folder.is_dir():
            self._write("stop", "1")

    def stopped(self) -> bool:
        return (self.folder / "stop").exists() or not self.folder.is_dir()

    def parent_running(self) -> bool:
        text = self._read("parent")
        return text is not None and text.isdigit() and pid_alive(int(text))

    def clear(self, windows: int) -> None:
        for sub in ("claims", "done", "staging"):
            shutil.rmtree(self.folder / sub, ignore_errors=True)
        for name in ("plan.json", "next"):
            (self.folder / name).unlink(missing_ok=True)

    # -- the cameras staged together ---------------------------------------------------------------

    def begin(self) -> None:
        (self.folder / "stop").unlink(missing_ok=True)
        shutil.rmtree(self.folder / "staging", ignore_errors=True)

    def together(self, before_staging: bool) -> bool:
        if before_staging:
            (self.folder / "staging").mkdir(parents=True)
        return before_staging

    def staging_together(self) -> bool:
        return (self.folder / "staging").is_dir()

    def claim_camera(self, c: int, who: str) -> int:
        try:
            return 1 if self._link(f"staging/{c}", who) else 0
        except FileNotFoundError:  # the staging is over: the run's board went
            return -1

    def camera_owner(self, c: int) -> str | None:
        return self._read(f"staging/{c}")

    def take_over_camera(self, c: int, owner: str, who: str) -> bool:
        import fcntl

        try:
            with open(self.folder / "staging" / ".lock", "a") as lock:
                fcntl.flock(lock, fcntl.LOCK_EX)  # compare and set: one taker wins
                if self.camera_owner(c) != owner:
                    return False
                self._write(f"staging/{c}", who)
                return True
        except FileNotFoundError:
            return False
