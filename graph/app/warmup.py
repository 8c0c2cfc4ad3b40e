"""Compile the solver's kernels before the first timed or served solve.

numba compiles the compiled kernels (:mod:`graph.solve.kernels`, :mod:`graph.solve.marginals`,
:mod:`graph.kinematics`) the first time a process uses them (about half a minute on a 2-core machine
for every method together: :mod:`graph.compiled`) and caches them on disk (``cache=True``): a later
process loads them in well under a second. :func:`warm_up` pays that cost on a tiny simulated run,
so that a demo's timings and a server's first job measure the solve alone.

From a cold cache the work is split over two processes that compile different kernels: a child
(``python -m graph.app.warmup marginals fte/points``) compiles the chain's marginals (a third of the
whole, and used only at the end of a solve: :func:`compile_marginals`), then runs the method this
process runs last, while this process runs every method. Each reaches what the other compiled after
it was cached (numba writes each cache file whole, by a rename, and a process loads a kernel from the
cache when it first calls it). Then this process waits for the child and runs every method once
more, from the cache. A warm cache (the kernels' index files are there) skips the child: its start
alone would cost a second. Measured from an empty cache on 2 cores: 19.1-19.3 s (the child compiling
the marginals alone: 21.3-24.2 s; one process: 32 s).
"""

from __future__ import annotations

import logging
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, cast

import numpy as np

from graph.api import solve
from graph.io.calibration import default_rig_path, load_calibration
from graph.simulate import simulate_run
from graph.types import Method, SolveOptions

log = logging.getLogger("acinoset")

WARM_UP_RUNS: tuple[tuple[Method, str], ...] = (("tri", "points"), ("fte", "cheetah"), ("fte", "points"),
                                                ("ekf", "cheetah"))
MARGINALS = "marginals"  # the child's argument for compile_marginals
# what the child compiles from a cold cache: the marginals, then the run this process reaches last (its
# kernels that this process has compiled by then the child loads from the cache, and the others it
# compiles first for this process to load)
CHILD = (MARGINALS, "fte/points")
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


def compile_marginals() -> None:
    """Call every kernel of :mod:`graph.solve.marginals` on a tiny chain (six frames of two
    parameters, one shared unknown), with the argument types the solvers pass them: float64 arrays,
    C-contiguous, so that a solve then loads them from the cache."""
    from graph.solve import marginals

    n, d, g = 6, 2, 1
    info = np.tile(np.eye(d), (n, 1, 1))
    w2 = np.ones(d)
    marginals.chain_marginals(info, w2, marginals.D3)
    band = marginals.chain_band(info, w2, marginals.D3)
    coupling = np.full((n, d, g), 0.1)
    marginals.banded_marginals(band, coupling, np.eye(g))
    marginals.information_taken(band, coupling)
    marginals.solve_band([band.copy()], [coupling], [np.ones((n, d))], np.eye(g), np.ones(g))


def _start_child() -> subprocess.Popen | None:
    try:
        return subprocess.Popen([sys.executable, "-m", "graph.app.warmup", *CHILD], stdin=subprocess.DEVNULL,
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
    _runs(WARM_UP_RUNS, run)
    if child is not None:
        try:
            child.wait(timeout=CHILD_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            log.debug("warm-up child still compiling after %.0f s", CHILD_TIMEOUT_S)
        _runs(WARM_UP_RUNS, run)  # from the cache: whatever this process did not compile itself
    return time.perf_counter() - t0


def main(argv: list[str]) -> int:
    """The child: ``marginals`` (:func:`compile_marginals`), or the runs named ``method/skeleton`` on
    the warm-up's simulated run."""
    specs: list[tuple[Method, str]] = []
    for a in argv:
        if a == MARGINALS:
            try:
                compile_marginals()
            except Exception as e:  # noqa: BLE001 - a warm-up never fails
                log.debug("warm-up %s: %s", a, e)
            continue
        method, _, skeleton = a.partition("/")
        specs.append((cast(Method, method), skeleton))
    if specs:
        _runs(specs, simulate_run(load_calibration(default_rig_path()), frames=12, seed=0))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
