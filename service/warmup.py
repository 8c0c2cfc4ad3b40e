"""Importing this module compiles the solver once, so the processes forked afterwards start warm.

The embedded backend's forkserver and ``acinoset worker`` import it before forking solves: numba
compiles the kernels (about 6 s the first time, then loads them from its cache in well under a
second), and each forked solve inherits them instead of loading them again. It never raises: a
failed warm-up only means the first solve of each process compiles for itself.
"""

from __future__ import annotations

import logging
import time

log = logging.getLogger("acinoset.service")


def warm_up() -> float:
    """Run tiny solves with every method on a simulated run; return the seconds it took."""
    t0 = time.perf_counter()
    try:
        from graph.api import SolveOptions, solve
        from graph.calibration import default_rig_path, load_calibration
        from graph.simulate import simulate_run

        run = simulate_run(load_calibration(default_rig_path()), frames=12, seed=0)
        for method, skeleton in (("tri", "points"), ("fte", "points"), ("fte", "cheetah"), ("ekf", "cheetah")):
            try:
                solve(run.keypoints, run.calibration, SolveOptions(method=method, skeleton=skeleton, fps=run.fps,
                                                                   max_iterations=2))
            except Exception as e:  # noqa: BLE001
                log.debug("warm-up %s/%s: %s", method, skeleton, e)
    except Exception as e:  # noqa: BLE001 - the simulator may not be importable here
        log.debug("warm-up skipped: %s", e)
    return time.perf_counter() - t0


_seconds = warm_up()
