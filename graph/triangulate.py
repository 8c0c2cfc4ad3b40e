"""Robust multi-view triangulation (``--method tri``).

For every frame and marker, with the views at or above the likelihood threshold:

1. Normalised image coordinates ``(x, y)`` by undistorting each detection (OpenCV).
2. Linear (DLT) triangulation. With ``P = [R | t]`` each view gives two rows
   ``x P_3 - P_1`` and ``y P_3 - P_2`` of ``A [X; 1] = 0``; we solve the inhomogeneous least squares
   ``A[:, :3] X = -A[:, 3]``. Candidates: all views together and every pair of views; the candidate
   with the lowest robust (Cauchy) reprojection cost over all views is kept, which survives a
   confident outlier in any one view.
3. Robust refinement: Gauss-Newton with Cauchy IRLS weights ``w = 1/(1 + s^2)``, ``s = |r|/sigma``::

       H = sum_c w_c J_c^T J_c,   g = sum_c w_c J_c^T r_c,   X <- X - H^-1 g

   and the 3D covariance ``sigma^2 H^-1`` at the end.

Everything is vectorised over all N*M points at once.
"""

from __future__ import annotations

import itertools
import time

import numpy as np

from graph.camera import Calibration, undistort_points
from graph.robust import OUTLIER_S, cauchy_weight


def triangulate(calibration: Calibration, meas: np.ndarray, valid: np.ndarray, sigma_px: float = 5.0,
                iterations: int = 10):
    """Robust 3D points from pixels ``meas`` (N, C, M, 2) and ``valid`` (N, C, M).

    Returns ``X`` (N, M, 3) (NaN with fewer than two views), ``cov`` (N, M, 3, 3),
    ``uv`` reprojections (C, N, M, 2) and ``s`` normalised residuals (N, C, M) (NaN where not valid).
    """
    N, C, M, _ = meas.shape
    K = N * M
    z = meas.transpose(1, 0, 2, 3).reshape(C, K, 2)
    ok = valid.transpose(1, 0, 2).reshape(C, K)
    norm = np.stack([undistort_points(cam, z[c]) for c, cam in enumerate(calibration.cameras)])
    ok = ok & np.isfinite(norm).all(-1)
    Pm = np.stack([np.hstack([cam.R, cam.t[:, None]]) for cam in calibration.cameras])  # (C, 3, 4)
    # DLT rows per view: (C, K, 2, 4)
    rows = np.stack([norm[..., 0:1] * Pm[:, None, 2, :] - Pm[:, None, 0, :],
                     norm[..., 1:2] * Pm[:, None, 2, :] - Pm[:, None, 1, :]], axis=2)
    rows = np.nan_to_num(rows)
    nviews = ok.sum(0)
    can = nviews >= 2

    def dlt(mask):  # mask (C, K)
        Aw = rows * mask[..., None, None]
        A3 = Aw[..., :3].transpose(1, 0, 2, 3).reshape(K, 2 * C, 3)
        b = -Aw[..., 3].transpose(1, 0, 2).reshape(K, 2 * C)
        H = np.einsum("kri,krj->kij", A3, A3) + 1e-12 * np.eye(3)
        g = np.einsum("kri,kr->ki", A3, b)
        return np.linalg.solve(H, g[..., None])[..., 0]

    def cauchy_cost(X):
        uv = np.stack([cam.project(X) for cam in calibration.cameras])
        s2 = np.sum((uv - z) ** 2, -1) / sigma_px**2
        cost = np.where(ok & np.isfinite(s2), np.log1p(np.nan_to_num(s2, nan=1e12)), 0.0)
        # a point behind a camera that saw it costs as a gross outlier
        cost = np.where(ok & ~np.isfinite(s2), np.log1p(1e12), cost)
        return cost.sum(0)

    X = dlt(ok)
    best = cauchy_cost(X)
    multi = nviews >= 3
    if multi.any() and C >= 3:
        for a, b in itertools.combinations(range(C), 2):
            pair = np.zeros_like(ok)
            pair[a], pair[b] = ok[a], ok[b]
            sel = multi & pair[a] & pair[b]
            if not sel.any():
                continue
            Xp = dlt(pair)
            cst = cauchy_cost(Xp)
            better = sel & (cst < best)
            X[better], best[better] = Xp[better], cst[better]

    for _ in range(iterations):
        H = np.zeros((K, 3, 3))
        g = np.zeros((K, 3))
        for c, cam in enumerate(calibration.cameras):
            uv, J = cam.project_with_jacobian(X)
            r = uv - z[c]
            good = ok[c] & np.isfinite(r).all(-1)
            w = np.where(good, cauchy_weight(np.linalg.norm(np.nan_to_num(r), axis=-1) / sigma_px), 0.0)
            J = np.nan_to_num(J)
            H += w[:, None, None] * np.einsum("kri,krj->kij", J, J)
            g += w[:, None] * np.einsum("kri,kr->ki", J, np.nan_to_num(r))
        H += 1e-9 * np.eye(3)
        step = np.linalg.solve(H, g[..., None])[..., 0]
        X = X - np.where(can[:, None], step, 0.0)
        if np.nanmax(np.abs(step[can]), initial=0.0) < 1e-7:
            break
    cov = sigma_px**2 * np.linalg.inv(H)
    X[~can] = np.nan
    cov[~can] = np.nan
    uv = np.stack([cam.project(X) for cam in calibration.cameras])  # (C, K, 2)
    s = np.where(ok, np.linalg.norm(uv - z, axis=-1) / sigma_px, np.nan)
    return (X.reshape(N, M, 3), cov.reshape(N, M, 3, 3), uv.reshape(C, N, M, 2),
            s.reshape(C, N, M).transpose(1, 0, 2))


def solve_tri(prob, progress=None):
    """``--method tri``: triangulate every marker of every frame independently."""
    from graph.result import build_result

    t0 = time.perf_counter()
    if progress:
        progress(_progress("triangulate", 0.0))
    X, cov, uv, s = triangulate(prob.calibration, prob.meas, prob.valid, prob.sigma_px)
    std = np.sqrt(np.maximum(np.diagonal(cov, axis1=-2, axis2=-1), 0.0))
    seconds = time.perf_counter() - t0
    if progress:
        progress(_progress("done", 1.0))
    return build_result(prob, "tri", positions=X, std=std, reprojections=uv, s=s, outlier=s >= OUTLIER_S,
                        seconds={"init": 0.0, "solve": seconds}, iterations=1)


def _progress(stage, fraction, iteration=0, cost=float("nan")):
    from graph.api import Progress

    return Progress(stage=stage, fraction=fraction, iteration=iteration, cost=cost)
