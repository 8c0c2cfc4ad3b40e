"""Worker processes that solve a long run's windows side by side (:class:`graph.solve.windows.Windows`
with ``jobs`` > 1), and a worker's share of the cores.

A pool of ``jobs`` processes forked from a server that imported the solver once (``forkserver``: no
process that ran a compiled parallel kernel is forked), each given the run's frames once, at its
start (a :class:`graph.solve.windows.Staged` source: the staged folder's path, the rig, the settled
stretch's problem as the template of every window), then windows by their frames. The compiled kernels
write one output per index, so a window's answer is the same whatever the threads or process.
"""

from __future__ import annotations

import multiprocessing
import os
from concurrent.futures import ProcessPoolExecutor
from typing import Any

_SOURCE: Any = None  # a worker's run (a graph.solve.windows.Frames), set at its start


def share_cores(threads: int) -> None:
    """A worker's share of the cores: the compiled kernels' threads, so that N workers do not each
    start a thread per core."""
    from graph.compiled import use_threads

    use_threads(threads)


def window_pool(source: Any, jobs: int) -> ProcessPoolExecutor:
    """``jobs`` worker processes holding ``source``, each with its share of the cores."""
    ctx = multiprocessing.get_context("forkserver")
    ctx.set_forkserver_preload(["graph.solve.windows"])
    threads = max(1, (os.cpu_count() or 1) // jobs)
    return ProcessPoolExecutor(max_workers=jobs, mp_context=ctx, initializer=_start, initargs=(source, threads))


def _start(source: Any, threads: int) -> None:
    global _SOURCE
    share_cores(threads)
    _SOURCE = source


def worker_source() -> Any:
    """The run this worker process was given."""
    if _SOURCE is None:
        raise RuntimeError("not a window worker (graph.solve.workers.window_pool)")
    return _SOURCE
