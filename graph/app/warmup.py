"""Compile the solver's kernels before the first timed or served solve.

numba compiles the compiled kernels (:mod:`graph.solve.kernels`) the first time a process uses them
(about a minute on a 2-core machine for every method together) and caches them on disk
(``cache=True``): a later process loads them in well under a second. :func:`warm_up` pays that cost
on a tiny simulated run, so that a demo's timings and a server's first job measure the solve alone.

From a cold cache the work is split over two processes: a child (``python -m graph.app.warmup
ekf/cheetah``) compiles what ``ekf`` needs while this process compiles the other methods, then waits
for it and runs ``ekf`` itself from the cache the child wrote (numba writes each cache file whole,
by a rename). Measured on this 2-core machine from an empty cache: 46 s against 73-75 s in one
process, and every kernel cached after it (a warm-up then takes 0.5 s). A warm cache (the kernels'
index files are there) skips the child: its start alone would cost a second.
"""

from __future__ import annotations

import logging
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, cast

from graph.api import solve
from graph.io.calibration import default_rig_path, load_calibration
from graph.simulate import simulate_run
from graph.types import Method, SolveOptions

log = logging.getLogger("acinoset")

WARM_UP_RUNS: tuple[tuple[Method, str], ...] = (("tri", "points"), ("fte", "points"), ("fte", "cheetah"),
                                                ("ekf", "cheetah"))
CHILD_RUNS: tuple[tuple[Method, str], ...] = (("ekf", "cheetah"),)  # compiled by the child from a cold cache
CHILD_TIMEOUT_S = 900.0  # a child that takes longer is left to finish alone; this process compiles for itself


def kernels_cached() -> bool:
    """Whether numba's cache holds the largest kernel already (its index file exists): then the
    others were cached with it. False when it cannot tell (the cache's layout is numba's own)."""
    try:
        from graph.solve import kernels

        cache: Any = getattr(kernels.window_normals, "_cache")
        return Path(cache._cache_file._index_path).exists()
    except Exception:  # noqa: BLE001 - numba's internals moved: treat the cache as cold
        return False


def _runs(specs, run) -> None:
    for method, skeleton in specs:
        try:
            solve(run.keypoints, run.calibration, SolveOptions(method=method, skeleton=skeleton, fps=run.fps,
                                                               max_iterations=2))
        except Exception as e:  # noqa: BLE001
            log.debug("warm-up %s/%s: %s", method, skeleton, e)


def _start_child() -> subprocess.Popen | None:
    args = [f"{m}/{s}" for m, s in CHILD_RUNS]
    try:
        return subprocess.Popen([sys.executable, "-m", "graph.app.warmup", *args], stdin=subprocess.DEVNULL,
                                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    except OSError as e:
        log.debug("warm-up child: %s", e)
        return None


def warm_up() -> float:
    """Run tiny solves with every method on a simulated run; return the seconds it took.

    Never raises: a failed warm-up only means the first real solve compiles for itself."""
    t0 = time.perf_counter()
    child = None if kernels_cached() else _start_child()
    run = simulate_run(load_calibration(default_rig_path()), frames=12, seed=0)
    _runs([r for r in WARM_UP_RUNS if child is None or r not in CHILD_RUNS], run)
    if child is not None:
        try:
            child.wait(timeout=CHILD_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            log.debug("warm-up child still compiling after %.0f s", CHILD_TIMEOUT_S)
        _runs([r for r in WARM_UP_RUNS if r in CHILD_RUNS], run)
    return time.perf_counter() - t0


def main(argv: list[str]) -> int:
    """The child: the runs named ``method/skeleton`` on the warm-up's simulated run."""
    specs: list[tuple[Method, str]] = []
    for a in argv:
        method, _, skeleton = a.partition("/")
        specs.append((cast(Method, method), skeleton))
    _runs(specs, simulate_run(load_calibration(default_rig_path()), frames=12, seed=0))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
