"""One long job's windows shared with the workers that are idle, on either backend.

A long run is solved in windows (:mod:`graph.solve.windows`): what every frame shares is settled
once, then each window is solved on its own with those values held, and the windows' kept frames
are written in order. The job's own process (the *parent*) settles the run, publishes the *plan*
on a :class:`Board` and asks for *helpers*; a helper solves windows until none is left; the parent
solves windows too while it waits, and takes the windows in order.

The board is where they meet: Redis on the RQ backend (:class:`service.run.redis_windows.RedisBoard`,
workers on any machine), the job's own folder on the embedded one
(:class:`service.run.folder_windows.FolderBoard`, helper processes the server starts in its free
slots). What it holds:

* the *plan*: ``{"options", "sigma_px", "settled_on", "spans"}`` (the held options, the noise, the
  settled stretch, each window's frames ``[lo, hi)``);
* the *claims*: window -> who solves it (the parent, or a helper ``<helper>@<worker>``), set once;
  a window whose helper is gone (its heartbeat older than :data:`BEAT_TTL_S`) is taken over by the
  parent;
* *next*: the window the parent takes next; a helper claims windows at most :data:`LOOKAHEAD` after
  it, so that at most ``LOOKAHEAD + 1`` results wait on the board, and the parent holds at most
  ``LOOKAHEAD`` windows it solved ahead (a window's result: about 11 MB at 2,400 frames of six
  cameras and 20 markers);
* each window's result once solved (its ``result.h5``, :func:`graph.io.results.write_h5`, and
  ``valid.npy``, the confident detections: :func:`write_window`);
* *stop*: set when the parent ends; a helper stops at its next window.

The answer does not depend on who solved which window when the workers run the same build on the
same kind of CPU (tested on one machine): a window's result is a function of the run's frames and the
plan, and its arrays travel as float64 in HDF5. A helper leaves when other jobs wait for a worker (a
long job does not hold idle workers from them). Nothing from a board is unpickled.
"""

from __future__ import annotations

import dataclasses
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, Protocol

import numpy as np

BEAT_S = 2.0  # a helper's heartbeat period
BEAT_TTL_S = 30.0  # a heartbeat older than this: the helper is gone (a long kernel call may delay a beat)
LOOKAHEAD = 6  # windows a helper may solve past the one the parent takes next (results waiting on the board)
POLL_S = 0.05

WINDOW_FILES = ("result.h5", "valid.npy")  # one window's result on a board
PARENT = "parent"  # a claim of the job's own process where the backend names no worker (staging)


class Board(Protocol):
    """Where a long job's parent and its helpers meet (module docstring)."""

    def publish(self, plan: dict, windows: int, me: str) -> None:
        """The parent: a retried run's claims and results gone, *next* 0, then the plan."""

    def plan(self) -> dict | None:
        """The plan, once published (None before, and once the parent ended)."""

    def claim(self, k: int, who: str) -> bool:
        """Window k claimed by ``who``, if no one had it."""

    def owner(self, k: int) -> str | None:
        """Who claimed window k."""

    def take_over(self, k: int, who: str) -> None:
        """Window k claimed by ``who`` (the parent), whoever had it."""

    def all_claimed(self, windows: int) -> bool:
        """Whether every one of the ``windows`` is claimed."""

    def set_next(self, k: int) -> None: ...

    def next(self) -> int: ...

    def put(self, k: int, result, valid: np.ndarray) -> None:
        """Window k's result, for the parent."""

    def take(self, k: int) -> tuple[Any, np.ndarray] | None:
        """Window k's result, off the board, if a helper put it there."""

    def finished(self, k: int) -> bool:
        """Whether window k's result is on the board."""

    def beat(self, who: str) -> None:
        """``who`` is alive (for :data:`BEAT_TTL_S`)."""

    def alive(self, who: str) -> bool: ...

    def leave(self, who: str) -> None:
        """``who`` is gone (its heartbeat removed)."""

    def stop(self) -> None:
        """The parent ended: the helpers stop."""

    def stopped(self) -> bool: ...

    def parent_running(self) -> bool:
        """Whether the parent is still running (a parent killed sets no *stop*)."""

    def clear(self, windows: int) -> None:
        """The plan, claims, results and staging claims gone (the parent ended)."""

    def begin(self) -> None:
        """The parent, before it asks for helpers: a retried run's *stop* and staging claims gone."""

    # the run's cameras staged together (:func:`stage_together`)

    def together(self, before_staging: bool) -> bool:
        """The parent, asking for helpers: whether they are to stage the cameras with it (they can if
        invited ``before_staging`` and they see its folder); if so the board says so to them
        (:meth:`staging_together`)."""

    def staging_together(self) -> bool:
        """Whether the helpers stage the cameras with the parent."""

    def claim_camera(self, c: int, who: str) -> int:
        """Camera c claimed by ``who``: 1, or 0 if another had it, or -1 if the staging is over (the
        run ended: its board cleared)."""

    def camera_owner(self, c: int) -> str | None: ...

    def take_over_camera(self, c: int, owner: str, who: str) -> bool:
        """Camera c claimed by ``who`` if ``owner`` still has it (one taker wins)."""


def write_window(folder: Path, result, valid: np.ndarray) -> None:
    """One window's result as :data:`WINDOW_FILES` in ``folder``."""
    from graph.io.results import write_h5

    write_h5(folder / WINDOW_FILES[0], result)
    np.save(folder / WINDOW_FILES[1], valid, allow_pickle=False)


def read_window(folder: Path) -> tuple[Any, np.ndarray]:
    """One window's result, as :func:`write_window` wrote it."""
    from graph.io.results import read_result

    return read_result(folder / WINDOW_FILES[0]), np.load(folder / WINDOW_FILES[1], allow_pickle=False)


def plan_of(settled, spans: list[tuple[int, int]]) -> dict:
    """The plan (module docstring) of a run's settled values and windows, as JSON values."""
    from graph.types import jsonable

    return {"options": jsonable(dataclasses.asdict(settled.options)), "sigma_px": float(settled.sigma_px),
            "settled_on": [settled.start, settled.stop], "spans": [list(s) for s in spans]}


def _options_from(d: dict, skeleton: str):
    """The plan's held options, with this process's own path of the job's skeleton file."""
    from pydantic import TypeAdapter

    from graph.types import SolveOptions

    return TypeAdapter(SolveOptions).validate_python({**d, "skeleton": skeleton})


def worker_of(claimant: str, parent: str) -> str:
    """The worker a claim names: ``parent`` for :data:`PARENT`, ``<helper>@<worker>``'s worker for a helper's."""
    return parent if claimant == PARENT else claimant.rpartition("@")[2]


class SharedWindows:
    """The parent's side: a :data:`graph.solve.windows.WindowSolver` that shares the windows with
    helpers (module docstring) on ``board``. ``me`` names the parent's worker; ``enqueue(n)`` asks for
    ``n`` helpers and returns their names; ``idle()`` counts the workers free to help; ``drop(names)``
    withdraws the helpers asked for that have not started (the run ended). ``solved``: each worker's
    windows, once done; ``staged``: each worker's cameras, when the backend stages them together
    (:meth:`stage`)."""

    def __init__(self, board: Board, me: str, enqueue: Callable[[int], list[str]], idle: Callable[[], int],
                 drop: Callable[[list[str]], None] | None = None):
        self.board, self.me, self.enqueue, self.idle, self.drop = board, me, enqueue, idle, drop
        self.helpers: list[str] = []
        self.invited = False
        self.together = False  # the helpers stage the cameras with the parent (:meth:`stage`)
        self.solved: Counter[str] = Counter()
        self.staged: Counter[str] = Counter()

    def __call__(self, source, spans: list[tuple[int, int]], settled) -> Iterator[tuple[Any, Any]]:
        from graph.solve.windows import solve_window

        n = len(spans)
        options, sigma_px = settled.options, settled.sigma_px
        self.board.publish(plan_of(settled, spans), n, self.me)
        self.invite(n)
        ahead: dict[int, tuple[Any, Any]] = {}

        def mine(k: int) -> tuple[Any, Any]:
            self.solved[self.me] += 1
            lo, hi = spans[k]
            return solve_window(source, lo, hi, options, sigma_px)

        try:
            for k in range(n):
                self.board.set_next(k)
                yield self._take(k, n, ahead, mine)
        finally:
            self.board.stop()
            self._end(n)

    def invite(self, windows: int, before_staging: bool = False) -> None:
        """Ask for a helper for each idle worker, at most ``windows - 1``, once. Called as soon as the
        run is known to be long (before it is settled), so that the helpers get ready meanwhile;
        called again when the windows start, it does nothing. ``before_staging``: the helpers may
        stage the run's cameras with the parent, where the backend can (:meth:`stage`)."""
        if self.invited:
            return
        self.invited = True
        self.board.begin()
        helpers = min(max(0, self.idle()), windows - 1)
        if helpers > 0:
            self.together = self.board.together(before_staging)
            self.helpers = list(self.enqueue(helpers))

    def stage(self, paths: list[str], folder: Path, read):
        """The run's cameras staged with the helpers (:func:`stage_together`; only when
        :attr:`together`); ``staged``: each worker's cameras."""
        run = stage_together(self.board, PARENT, paths, folder, read)
        for c in range(len(paths)):
            owner = self.board.camera_owner(c)
            if owner is not None:
                self.staged[worker_of(owner, self.me)] += 1
        return run

    def close(self) -> None:
        """The run ended (solved, failed, or found short): the helpers invited stop, those not started
        are dropped."""
        if self.invited:
            try:
                self.board.stop()
                self._end(0)
            except Exception:  # noqa: BLE001 - the board is gone (Redis down): its keys expire, the helpers end with the parent
                pass

    def _take(self, k: int, n: int, ahead: dict, mine) -> tuple[Any, Any]:
        """Window k: solved ahead here, done by a helper, claimed now and solved here, or (its helper
        gone) taken over; while its helper works, a later window is solved here meanwhile."""
        b = self.board
        while True:
            if k in ahead:
                return ahead.pop(k)
            got = b.take(k)
            if got is not None:
                self.solved[worker_of(str(b.owner(k)), self.me)] += 1
                return got
            if b.claim(k, self.me):
                return mine(k)
            who = str(b.owner(k))
            if who == self.me or not b.alive(who):
                if b.finished(k):  # finished as its heartbeat ran out
                    continue
                b.take_over(k, self.me)  # its helper is gone: solved here
                return mine(k)
            j = next((j for j in range(k + 1, min(n, k + 1 + LOOKAHEAD)) if j not in ahead
                      and b.owner(j) is None), None)
            if j is not None and b.claim(j, self.me):
                ahead[j] = mine(j)
                continue
            time.sleep(POLL_S)

    def _end(self, n: int) -> None:
        """The helpers not started are dropped; the board is cleared (a helper still solving finds
        *stop*)."""
        if self.drop is not None and self.helpers:
            self.drop(self.helpers)
        self.board.clear(n)


def stage_together(board: Board, me: str, paths: list[str], folder: Path, read):
    """The job's cameras ``paths`` staged in ``folder`` (made by the parent before it asked for
    helpers), where the parent and its helpers both see it, between them: each camera claimed by one
    (:meth:`Board.claim_camera`; ``me`` is :data:`PARENT` for the parent) and staged by it
    (:func:`graph.io.staged.stage_camera`), the others waited for; a camera whose claimant is gone (a
    helper's heartbeat expired, the parent no longer running) is taken over by one of those waiting
    and staged again. The run (:meth:`graph.io.staged.StagedRun.gather`), or None: a file holds
    several individuals, or (a helper's) the job ended or stopped first; RuntimeError when the parent
    finds its staging claims gone."""
    from graph.io.staged import StagedRun, stage_camera

    def ended() -> bool:
        return me != PARENT and (board.stopped() or not board.parent_running() or not folder.is_dir())

    def over() -> None:
        if me == PARENT:
            raise RuntimeError("the run's staging claims are gone from its board (expired, or deleted)")

    for c, path in enumerate(paths):
        if ended():
            return None
        got = board.claim_camera(c, me)
        if got == -1:
            return over()
        if got == 1:
            stage_camera(path, folder, c, read)
    run = StagedRun(folder)
    while missing := run.unstaged(len(paths)):
        if ended():
            return None
        for c in missing:
            owner = board.camera_owner(c)
            if owner is None:
                return over()
            gone = not board.parent_running() if owner == PARENT else not board.alive(owner)
            if gone and board.take_over_camera(c, owner, me):
                stage_camera(paths[c], folder, c, read)
        time.sleep(POLL_S)
    return StagedRun.gather(folder, len(paths))


def wait_for_plan(board: Board, others_waiting: Callable[[], bool] = lambda: False,
                  poll: float = 0.2) -> dict | None:
    """The plan, once the parent has published it; None if the parent stops or ends first, or
    ``others_waiting()`` says other jobs wait for this worker."""
    while True:
        plan = board.plan()
        if plan is not None:
            return plan
        if board.stopped() or not board.parent_running() or others_waiting():
            return None
        time.sleep(poll)


def help_with_windows(board: Board, me: str, stage: Callable[[], Any], calibration, options,
                      others_waiting: Callable[[], bool]) -> int:
    """A helper's side: the job's run staged (``stage()``, a :class:`graph.io.staged.StagedRun` or
    None when the job ended first; the helper's heartbeat beats meanwhile), then the job's windows
    solved until none is left to claim, the parent stops, or ``others_waiting()`` says other jobs wait
    for a worker; ``me`` names it in the claims (``<helper>@<worker>``), ``calibration`` and
    ``options`` are the job's. Returns the windows it solved."""
    from graph.solve.windows import Staged, solve_window

    stopped = threading.Event()

    def beat() -> None:
        while not stopped.is_set():
            board.beat(me)
            stopped.wait(BEAT_S)

    board.beat(me)  # alive before its first claim
    beating = threading.Thread(target=beat, name="window-helper-heartbeat", daemon=True)
    beating.start()
    try:
        run = stage()
        plan = None if run is None else wait_for_plan(board, others_waiting)
        if plan is None:
            return 0
        held = _options_from(plan["options"], options.skeleton)
        spans = [(int(lo), int(hi)) for lo, hi in plan["spans"]]
        source = Staged(run, calibration, options)
        s0, s1 = plan["settled_on"]
        source.stretch(int(s0), int(s1), dataclasses.replace(options, window_frames=0))  # the windows' template
        solved = 0
        while not board.stopped() and board.parent_running():
            if others_waiting() or board.plan() is None:  # the parent ended: its claims are gone
                break
            nxt = board.next()
            k = next((j for j in range(nxt, min(len(spans), nxt + 1 + LOOKAHEAD)) if board.claim(j, me)), None)
            if k is None:
                if board.all_claimed(len(spans)):
                    break
                time.sleep(POLL_S)
                continue
            lo, hi = spans[k]
            result, valid = solve_window(source, lo, hi, held, float(plan["sigma_px"]))
            board.put(k, result, valid)
            solved += 1
        return solved
    finally:
        stopped.set()
        beating.join(timeout=BEAT_S + 1)
        board.leave(me)
