"""Compiled kernels that loop over many frames or points: one compiled serially, its twin in parallel.

numba compiles a kernel the first time a process calls it and caches it on disk. A ``parallel=True``
kernel (its ``prange`` loops split over threads) takes about three times as long to compile as the
same kernel compiled serially, and on a short run it is no faster (the threads' start and join cost
what they save). Measured on a 2-core machine from an empty cache, every method's kernels: 65 s with
the four loop kernels parallel, 42 s serial (at numba's default level, below); solves of 200 frames
as fast serially (fte 0.155 s against 0.171 s); of 7,200 frames 1.33x slower serially (fte 7.3 s
against 5.5 s, tri 1.2 s against 0.6 s).

The kernels are compiled at LLVM's optimisation level 1 (``NUMBA_OPT``, unless set; :mod:`graph`
sets it before numba is imported; no fast-math, so LLVM may not reorder floating point): measured on
the same machine, every method's kernels compile in 33.5 s at level 1 against 46.0 s at numba's
default 3, the solves' results are bit for bit the same (tri, ekf and fte, positions and sds, 200
and 1,000 frames) and as fast (fte of 2,000 frames 1.15 s against 1.20 s, of 7,200 frames 5.9 s
against 5.8 s); level 0 is 13x slower to run.

So each loop kernel is written once, decorated with :func:`loop_kernel`: the module's name is the
serial kernel, compiled at its first call; its parallel twin, the same source compiled with
``parallel=True`` and cached under its own name, is compiled only when a call is given at least
:data:`PARALLEL_ITEMS` frames with more than one thread to run them (:func:`for_items`). A run of
fewer frames, the demo and the job service (one thread per solve) never compile the twins.
"""

from __future__ import annotations

import types
from typing import Any

import numba
from numba import njit

# frames from which a loop kernel runs in parallel. fte of 20 markers on 2 cores, serial against
# parallel: 100 frames 0.08 / 0.13 s, 200 0.19 / 0.17 s, 400 0.34 / 0.28 s, 1,000 0.82 / 0.64 s,
# 2,000 1.87 / 1.60 s, 7,200 7.3 / 5.5 s. Compiling the twins costs 22 s once (fte with the body
# estimated), which a run of a thousand frames would not earn back in a hundred solves: the twins
# are for the long runs (a window of a streamed run is 2,400 frames), where the threads pay
PARALLEL_ITEMS = 2000

_TWINS: dict[int, Any] = {}  # id(serial dispatcher) -> its parallel twin, once compiled
_threads: int | None = None  # set by use_threads; else numba's configured count


def loop_kernel(f):
    """``f`` compiled serially (cached); :func:`for_items` gives its parallel twin for large calls."""
    return njit(cache=True)(f)


def use_threads(threads: int) -> None:
    """Run the parallel twins on ``threads`` threads (at most numba's configured count); one thread
    means the serial kernels alone."""
    global _threads
    _threads = max(1, min(threads, numba.config.NUMBA_NUM_THREADS))  # type: ignore[attr-defined]
    numba.set_num_threads(_threads)


def threads() -> int:
    """The threads a parallel twin would run on: :func:`use_threads`'s, else numba's configured
    count (``NUMBA_NUM_THREADS``, the cores by default; asking numba itself would start its threads)."""
    return _threads if _threads is not None else int(numba.config.NUMBA_NUM_THREADS)  # type: ignore[attr-defined]


def for_items(kernel, items: int):
    """``kernel`` (made by :func:`loop_kernel`) for a call over ``items`` frames: its
    parallel twin when ``items >= PARALLEL_ITEMS`` and more than one thread may run it, else itself."""
    if items < PARALLEL_ITEMS or threads() < 2:
        return kernel
    twin = _TWINS.get(id(kernel))
    if twin is None:
        f = kernel.py_func  # the Python function both are compiled from
        g = types.FunctionType(f.__code__, f.__globals__, f.__name__, f.__defaults__, f.__closure__)
        g.__qualname__ = f"{f.__qualname__}_parallel"  # numba's cache file is named after it
        g.__doc__ = f.__doc__
        twin = _TWINS[id(kernel)] = njit(cache=True, parallel=True)(g)
    return twin
