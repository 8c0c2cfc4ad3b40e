"""Compile the solver's kernels before the first timed or served solve.

numba compiles the compiled kernels (:mod:`graph.solve.kernels`) the first time a process uses them
(about a minute on a 2-core machine for every method together) and caches them on disk
(``cache=True``): a later process loads them in well under a second. :func:`warm_up` pays that cost
on a tiny simulated run, so that a demo's timings and a server's first job measure the solve alone.
"""

from __future__ import annotations

import logging
import time

from graph.api import solve
from graph.io.calibration import default_rig_path, load_calibration
from graph.simulate import simulate_run
from graph.types import Method, SolveOptions

log = logging.getLogger("acinoset")

WARM_UP_RUNS: tuple[tuple[Method, str], ...] = (("tri", "points"), ("fte", "points"), ("fte", "cheetah"),
                                                ("ekf", "cheetah"))


def warm_up() -> float:
    """Run tiny solves with every method on a simulated run; return the seconds it took.

    Never raises: a failed warm-up only means the first real solve compiles for itself."""
    t0 = time.perf_counter()
    run = simulate_run(load_calibration(default_rig_path()), frames=12, seed=0)
    for method, skeleton in WARM_UP_RUNS:
        try:
            solve(run.keypoints, run.calibration, SolveOptions(method=method, skeleton=skeleton, fps=run.fps,
                                                               max_iterations=2))
        except Exception as e:  # noqa: BLE001
            log.debug("warm-up %s/%s: %s", method, skeleton, e)
    return time.perf_counter() - t0
