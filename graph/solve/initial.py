"""Initial trajectories for the smoothers: good starts matter more than the solver.

From robust triangulation ``X`` (N, M, 3):

* **Root path.** For a kinematic skeleton the root point (the cheetah's head) is not a marker; it is
  estimated as the mean of the markers hanging directly off it (eyes and nose). Gaps are filled by
  linear interpolation, then the path is smoothed with a running median (outlier-proof) followed by
  a short moving average.
* **Yaw from heading.** The forward direction is taken from the markers' centroid to the root
  (the head leads the body), falling back to the direction of travel; ``psi = atan2(f_y, f_x)``
  because a passive ``rot_z(psi)`` maps the body's x axis to ``(cos psi, sin psi, 0)``. Unwrapped and
  median-filtered over time.
* **Joint angles** by per-frame inverse kinematics on the triangulated points (Huber loss, bounds),
  each frame started from, and weakly pulled towards, the previous one
  (:func:`graph.solve.kernels.inverse_kinematics`).
* A *points* skeleton starts from the triangulated points themselves, gaps interpolated.
"""

from __future__ import annotations

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from graph.solve import kernels
from graph.solve.problem import Problem

IK_ITERATIONS = 5  # Gauss-Newton steps per frame: the smoother refines the start; with 5 instead of 15
# the 3D error of fte (body and clocks estimated) on 20 simulated runs of two rigs moved by 0.04 mm at most


def fill_gaps(x: np.ndarray) -> np.ndarray:
    """Linear interpolation over NaN along axis 0 (constant beyond the ends); all-NaN columns stay NaN."""
    x = np.array(x, dtype=np.float64, copy=True)
    flat = x.reshape(x.shape[0], -1)
    t = np.arange(x.shape[0])
    for j in range(flat.shape[1]):
        ok = np.isfinite(flat[:, j])
        if ok.any() and not ok.all():
            flat[:, j] = np.interp(t, t[ok], flat[ok, j])
    return flat.reshape(x.shape)


def running(x: np.ndarray, size: int, statistic=np.median) -> np.ndarray:
    """``statistic`` (median or mean) over a centred window of odd ``size`` along axis 0, the ends
    repeated beyond the data (scipy.ndimage's ``mode="nearest"``):
    ``y_n = stat(x_{n-h}, ..., x_{n+h})``, ``h = size // 2``, ``x_k = x_0`` for ``k < 0`` and
    ``x_{N-1}`` for ``k >= N``. (numpy alone: scipy.ndimage costs a second to import.)"""
    h = size // 2
    padded = np.concatenate([np.repeat(x[:1], h, axis=0), x, np.repeat(x[-1:], h, axis=0)])
    return statistic(sliding_window_view(padded, size, axis=0), axis=-1)


def smooth_path(x: np.ndarray, median: int = 9, mean: int = 5) -> np.ndarray:
    """Robust smoothing along time: running median then moving average (axis 0)."""
    x = fill_gaps(x)
    if x.shape[0] >= median:
        x = running(x, median)
    if x.shape[0] >= mean:
        x = running(x, mean, np.mean)
    return x


def initial_poses(prob: Problem, X: np.ndarray) -> np.ndarray:
    """Initial pose parameters (N, P) from triangulated markers ``X`` (N, M, 3)."""
    sk = prob.skeleton
    a = sk.arrays
    N, M = X.shape[:2]
    P = sk.n_params
    if sk.kind == "points":
        Xf = fill_gaps(X)
        centroid = np.nanmean(Xf.reshape(-1, 3), axis=0) if np.isfinite(Xf).any() else np.zeros(3)
        Xf = np.where(np.isfinite(Xf), Xf, centroid)
        return Xf.reshape(N, 3 * M)

    q0 = np.zeros((N, P))
    lower, upper = sk.lower, sk.upper
    # start every angle at 0, or at the middle of its range when 0 is outside or on the edge
    bounded = np.isfinite(lower) & np.isfinite(upper)
    mid = np.where(bounded, 0.5 * (np.where(bounded, lower, 0.0) + np.where(bounded, upper, 0.0)), 0.0)
    edge = (lower >= -1e-9) | (upper <= 1e-9)
    q0[:] = np.where(edge, mid, 0.0)

    root_pt = int(np.flatnonzero(a.pt_base < 0)[0])
    marker_of_point = {int(p): m for m, p in enumerate(a.marker_point)}
    if root_pt in marker_of_point:
        root = X[:, marker_of_point[root_pt]]
    else:
        kids = [marker_of_point[int(k)] for k in np.flatnonzero(a.pt_base == root_pt) if int(k) in marker_of_point]
        root = _nanmean(X[:, kids], axis=1) if kids else np.full((N, 3), np.nan)
    if not np.isfinite(root).any():  # the root's markers never seen: use the centroid of everything
        root = _nanmean(X, axis=1)
    if not np.isfinite(root).any():
        root = np.zeros((N, 3))
    root = smooth_path(root)
    q0[:, a.pt_root[root_pt]] = root

    yaw_param = _root_yaw_param(sk)
    if yaw_param is not None:
        centroid = _nanmean(X, axis=1)
        fwd = root - fill_gaps(centroid)
        travel = np.gradient(root, axis=0)
        usable = np.isfinite(fwd).all(-1, keepdims=True) & (np.linalg.norm(fwd[:, :2], axis=-1, keepdims=True) > 0.05)
        fwd = np.where(usable, fwd, travel)
        psi = np.unwrap(np.arctan2(fwd[:, 1], fwd[:, 0]))
        if N >= 9:
            psi = running(psi, 9)
        q0[:, yaw_param] = psi

    anchor = np.zeros(P)
    # a weak pull (sigma 10 m) to the smoothed path: it holds the root only where its markers are
    # unseen (the mean of the head's markers is not the head's origin, so a stronger pull bends
    # every joint to make up for it)
    anchor[a.pt_root[root_pt]] = 0.1
    smooth = np.full(P, 0.05)  # 0.1 rad from the previous frame costs as much as 5 mm of misfit
    smooth[a.pt_root[root_pt]] = 0.0
    Xn = np.where(np.isfinite(X), X, np.nan)
    return kernels.inverse_kinematics(q0, Xn, anchor, smooth, lower, upper, 0.05, IK_ITERATIONS, *a.kernel_args())


def _nanmean(x: np.ndarray, axis: int) -> np.ndarray:
    """Mean over finite values; NaN where there are none (without numpy's warning)."""
    ok = np.isfinite(x)
    n = ok.sum(axis=axis)
    total = np.where(ok, x, 0.0).sum(axis=axis)
    return np.where(n > 0, total / np.maximum(n, 1), np.nan)


def _root_yaw_param(sk) -> int | None:
    """The parameter of the z rotation of the first segment hanging from the world, if any."""
    a = sk.arrays
    for k in range(len(a.seg_parent)):
        if a.seg_parent[k] < 0:
            for j in range(3):
                if a.seg_axis[k, j] == 2:
                    return int(a.seg_param[k, j])
    return None
