"""``--method tri``: every marker of every frame triangulated on its own (:mod:`graph.solve.triangulate`),
with its 3D standard deviations from the refinement's information ``sigma^2 H^-1``."""

from __future__ import annotations

import time

import numpy as np

from graph.solve.problem import Problem
from graph.solve.result import build_result
from graph.solve.robust import OUTLIER_S
from graph.solve.triangulate import triangulate
from graph.types import Progress, ProgressCallback, Result


def solve_tri(prob: Problem, progress: ProgressCallback | None = None) -> Result:
    """Triangulate every marker of every frame independently."""
    t0 = time.perf_counter()
    if progress:
        progress(Progress(stage="triangulate", fraction=0.0))
    X, cov, uv, s = triangulate(prob.calibration, prob.meas, prob.valid, prob.sigma_px)
    std = np.sqrt(np.maximum(np.diagonal(cov, axis1=-2, axis2=-1), 0.0))
    few = prob.views() < prob.options.min_views  # NaN already where fewer than two cameras see it
    X[few], std[few] = np.nan, np.nan
    seconds = time.perf_counter() - t0
    if progress:
        progress(Progress(stage="done", fraction=1.0))
    return build_result(prob, "tri", positions=X, std=std, reprojections=uv, s=s, outlier=s >= OUTLIER_S,
                        seconds={"init": 0.0, "solve": seconds}, iterations=1)
