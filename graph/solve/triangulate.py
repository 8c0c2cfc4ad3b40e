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

import numpy as np

from graph.camera import Calibration, undistort_points
from graph.compiled import for_items
from graph.solve import kernels


def robust_points(calibration: Calibration, meas: np.ndarray, valid: np.ndarray, sigma_px: float = 5.0,
                  iterations: int = 10):
    """The triangulated points alone: ``X`` (N, M, 3), NaN with fewer than two views (views from
    one place, :meth:`graph.camera.Calibration.places`, count once), the Gauss-Newton information
    ``H`` (N*M, 3, 3) of each and the views used, ``ok`` (N*M, C). The per-point work runs compiled
    (:func:`graph.solve.kernels.triangulate_points`); the smoothers start from ``X``."""
    N, C, M, _ = meas.shape
    K = N * M
    z = meas.transpose(0, 2, 1, 3).reshape(K, C, 2)  # (K, C, 2)
    ok = valid.transpose(0, 2, 1).reshape(K, C)
    norm = np.stack([undistort_points(cam, z[:, c]) for c, cam in enumerate(calibration.cameras)], axis=1)
    ok = ok & np.isfinite(norm).all(-1) & np.isfinite(z).all(-1)
    Pm = np.stack([np.hstack([cam.R, cam.t[:, None]]) for cam in calibration.cameras])  # (C, 3, 4)
    intr, Rc, tc = calibration.packed()
    X, H = for_items(kernels.triangulate_points, N)(np.nan_to_num(norm), np.nan_to_num(z), ok, intr, Rc, tc, Pm,
                                      float(sigma_px), iterations)
    X = X.reshape(N, M, 3)
    X[calibration.places_seeing(valid) < 2] = np.nan  # two views from one place: one ray, no depth
    return X, H, ok


def triangulate(calibration: Calibration, meas: np.ndarray, valid: np.ndarray, sigma_px: float = 5.0,
                iterations: int = 10):
    """Robust 3D points from pixels ``meas`` (N, C, M, 2) and ``valid`` (N, C, M).

    Returns ``X`` (N, M, 3) (NaN with fewer than two views), ``cov`` (N, M, 3, 3),
    ``uv`` reprojections (C, N, M, 2) and ``s`` normalised residuals (N, C, M) (NaN where not valid).
    """
    N, C, M, _ = meas.shape
    K = N * M
    X, H, ok = robust_points(calibration, meas, valid, sigma_px, iterations)
    X = X.reshape(K, 3)
    z = meas.transpose(0, 2, 1, 3).reshape(K, C, 2)
    good = np.isfinite(X).all(-1)
    cov = np.full((K, 3, 3), np.nan)
    if good.any():
        cov[good] = sigma_px**2 * np.linalg.inv(H[good])
    uv = np.stack([cam.project(X) for cam in calibration.cameras])  # (C, K, 2)
    s = np.where(ok.T, np.linalg.norm(uv - z.transpose(1, 0, 2), axis=-1) / sigma_px, np.nan)  # (C, K)
    return (X.reshape(N, M, 3), cov.reshape(N, M, 3, 3), uv.reshape(C, N, M, 2),
            s.reshape(C, N, M).transpose(1, 0, 2))
