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

Two things the per-frame points get wrong when they are noisy (a wide rig of low resolution, where
each point is 80-100 mm off):

* **The points are denoised over time before the inverse kinematics** (:func:`denoise_points`: a
  running median over about :data:`DENOISE_SECONDS`, a frame's spike of outliers or a swap gone).
  Fitted to the raw points, the IK folded the tail back onto its joint limits in a frame of bad
  points and kept it folded for 130 frames; the smoother cannot climb out of such a branch (its
  motion prior holds the whole stretch on it).
* **The body's size is measured without the noise's bias** (:func:`body_scale`). A distance between
  two noisy points is longer, on average, than the bone: ``|L + e|`` with ``e`` the two points'
  errors. The median of ``|L + e|`` over the run, with ``e ~ N(0, tau^2 I)``, is that of a
  noncentral chi with three degrees of freedom, ``tau m(L / tau)``; ``tau`` per marker from the third
  differences of its triangulated track (white noise of sd ``t`` gives third differences of sd
  ``sqrt(20) t``; a smooth motion's are far smaller at the frame rates of pose cameras), and
  ``L`` solved from the observed median. With 80 mm of noise the plain median put a cheetah of the
  model's size at 1.16x (the eyes' 66 mm apart at 132 mm), and the smoother, started there, ended in a
  basin twice the error of the one it reached from the true size.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from graph.solve import kernels
from graph.solve.problem import Problem

IK_ITERATIONS = 5  # Gauss-Newton steps per frame: the smoother refines the start; with 5 instead of 15
# the 3D error of fte (body and clocks estimated) on 20 simulated runs of two rigs moved by 0.04 mm at most
DENOISE_SECONDS = 0.04  # the running median's span over the points before the IK (5 frames at 120 fps)
DENOISE_MAX_FRAMES = 15  # and at most this many frames (a high frame rate's points are no noisier a frame)


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
    Xn = denoise_points(X, prob.options.fps)
    return kernels.inverse_kinematics(q0, Xn, anchor, smooth, lower, upper, 0.05, IK_ITERATIONS, *a.kernel_args())


def denoise_points(X: np.ndarray, fps: float) -> np.ndarray:
    """Triangulated points ``X`` (N, M, 3) through a running median along time over ``2h + 1``
    frames, ``h = round(fps DENOISE_SECONDS / 2)`` (at most :data:`DENOISE_MAX_FRAMES`): gaps
    interpolated for the median, NaN again where ``X`` had none. Fewer than 3 frames in the window,
    or in the run: ``X`` as it is."""
    X = np.where(np.isfinite(X), X, np.nan)
    h = min(int(round(fps * DENOISE_SECONDS / 2)), DENOISE_MAX_FRAMES // 2)
    if h < 1 or X.shape[0] < 2 * h + 1:
        return X
    seen = np.isfinite(X).all(axis=-1, keepdims=True)
    return np.where(seen, running(fill_gaps(X), 2 * h + 1), np.nan)


_LAMBDA = np.linspace(0.0, 40.0, 801)


def _chi3_cdf(r: np.ndarray, lam: np.ndarray) -> np.ndarray:
    """``P(|lam e + Z| <= r)`` for ``Z ~ N(0, I_3)`` and a unit ``e`` (the noncentral chi of three
    degrees of freedom): ``Phi(r - lam) + Phi(r + lam) - 1 + (phi(r + lam) - phi(r - lam)) / lam``, and
    its limit ``erf(r / sqrt 2) - sqrt(2 / pi) r exp(-r^2 / 2)`` at ``lam = 0``."""
    from math import erf

    erf_v = np.vectorize(erf, otypes=[float])
    Phi = lambda x: 0.5 * (1.0 + erf_v(x / math.sqrt(2.0)))  # noqa: E731
    phi = lambda x: np.exp(-0.5 * x * x) / math.sqrt(2.0 * math.pi)  # noqa: E731
    small = lam < 1e-6
    lam_s = np.where(small, 1.0, lam)
    general = Phi(r - lam) + Phi(r + lam) - 1.0 + (phi(r + lam_s) - phi(r - lam_s)) / lam_s
    at_zero = erf_v(r / math.sqrt(2.0)) - math.sqrt(2.0 / math.pi) * r * np.exp(-0.5 * r * r)
    return np.where(small, at_zero, general)


def _chi3_medians() -> np.ndarray:
    """The median of ``|lam e + Z|`` at each ``lam`` of ``_LAMBDA``, by bisection on the CDF."""
    lo, hi = np.maximum(_LAMBDA - 6.0, 0.0), _LAMBDA + 6.0
    for _ in range(50):
        mid = 0.5 * (lo + hi)
        below = _chi3_cdf(mid, _LAMBDA) < 0.5
        lo, hi = np.where(below, mid, lo), np.where(below, hi, mid)
    return 0.5 * (lo + hi)


_MEDIANS: list[np.ndarray] = []  # the table, computed when first asked for


def unbiased_length(median: float, tau: float) -> float:
    """The length ``L`` whose distance ``|L e + n|`` under noise ``n ~ N(0, tau^2 I_3)`` has the
    observed ``median``: ``tau m^{-1}(median / tau)`` (``m`` the noncentral chi's median, 1.54 at 0;
    beyond its table's ``L = 40 tau`` the bias is under 0.1 % and ``median`` is taken as it is). NaN
    when the median is no longer than the noise alone makes it (the bone is not measured)."""
    if not (tau > 0 and math.isfinite(tau)):
        return median
    if not _MEDIANS:
        _MEDIANS.append(_chi3_medians())
    table = _MEDIANS[0]
    m = median / tau
    if m >= table[-1]:
        return median
    if m <= table[0]:
        return math.nan
    return float(np.interp(m, table, _LAMBDA)) * tau


def track_noise(X: np.ndarray) -> np.ndarray:
    """Each marker's noise sd per axis (M,) from its track ``X`` (N, M, 3): the third differences'
    robust spread (1.4826 MAD) over ``sqrt(20)``, averaged over the axes in variance; NaN with fewer
    than 10 third differences."""
    d3 = X[3:] - 3 * X[2:-1] + 3 * X[1:-2] - X[:-3]
    out = np.full(X.shape[1], np.nan)
    for m in range(X.shape[1]):
        d = d3[:, m][np.isfinite(d3[:, m]).all(axis=-1)]
        if len(d) >= 10:
            mad = 1.4826 * np.median(np.abs(d - np.median(d, axis=0)), axis=0)
            out[m] = math.sqrt(float(np.mean(mad**2)) / 20.0)
    return out


def body_scale(skeleton, X: np.ndarray, scale_range: tuple[float, float]) -> float:
    """The animal's overall size against the skeleton's: the median over its bones of
    :func:`unbiased_length` (of the median triangulated length ``median_n |X_a - X_b|``, with the
    noise ``tau^2 = t_a^2 + t_b^2`` from :func:`track_noise`) over the model's length at the zero pose,
    clipped to ``scale_range``; 1 when no bone is measured. Bones seen in fewer than 10 frames, or
    shorter than 1 mm in the model, are left out."""
    if not skeleton.bones:
        return 1.0
    model = skeleton.positions(np.zeros(skeleton.n_params))
    idx = {m: i for i, m in enumerate(skeleton.markers)}
    t = track_noise(X)
    ratios = []
    for a, b in skeleton.bones:
        d = np.linalg.norm(X[:, idx[a]] - X[:, idx[b]], axis=-1)
        d = d[np.isfinite(d)]
        L = float(np.linalg.norm(model[idx[a]] - model[idx[b]]))
        if len(d) < 10 or L <= 1e-3:
            continue
        tau = math.hypot(t[idx[a]], t[idx[b]])
        length = unbiased_length(float(np.median(d)), tau) if math.isfinite(tau) else float(np.median(d))
        if math.isfinite(length):
            ratios.append(length / L)
    return float(np.clip(np.median(ratios), *scale_range)) if ratios else 1.0


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
