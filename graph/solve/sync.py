"""The cameras' clocks: per-camera time offsets, found in whole frames before the joint solve.

Camera c's frame ``m`` was taken at time ``m + tau_c`` frames on the trajectory's clock (camera 1's:
``tau_1 = 0``). The joint solve (:mod:`graph.solve.joint`) refines every ``tau_c`` below a frame with the
trajectory; it needs a start within about a frame, which this module finds for offsets of any size
from the calibration alone.

Whole frames, by epipolar geometry. Two cameras a and c see a marker at the same instant when
camera c's frame ``n + d`` pairs with camera a's frame n, ``d = tau_a - tau_c``. For such a pair the
normalised image points satisfy ``x_c^T E x_a = 0`` with the essential matrix ``E = [t]_x R`` of
the relative pose (``R = R_c R_a^T``, ``t = t_c - R t_a``); their Sampson distance

    e = (x_c^T E x_a)^2 / ((E x_a)_1^2 + (E x_a)_2^2 + (E^T x_c)_1^2 + (E^T x_c)_2^2)

grows with the motion between the two instants. For every lag ``d`` within ``max_lag`` the median
of ``sqrt(e)`` over the markers both cameras saw confidently (in every frame, or every k-th of a
long run: about :data:`PAIRS_PER_LAG` of them) is the lag's cost; the best lag is
refined below a frame by a parabola through it and its neighbours. A lag is *decisive* when its
cost is below :data:`DECISIVE` times the median cost of all lags: an animal that stands still, or a
pair that shares too few detections, leaves every lag alike, and the offset stays at 0. Cameras are
placed one at a time, each against the placed camera it shares most detections with.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from graph.camera import Calibration, undistort_points

DECISIVE = 0.6  # a lag counts when its cost is below this fraction of the median lag's
MIN_PAIRS = 30  # co-detections a lag needs to be scored
PAIRS_PER_LAG = 4000  # a lag's median is taken over about this many co-detections (frames strided)


@dataclass
class CoarseOffsets:
    """Per-camera offsets (C,) in frames (camera 1 = 0) and whether each was decided by the data."""

    frames: np.ndarray
    decided: np.ndarray  # (C,) bool; camera 1 is True
    against: list[int]  # the camera each was placed against (-1 for camera 1)


def default_max_lag(frames: int, fps: float) -> int:
    """Lags searched either way: a quarter of a second, at least 10 frames, at most a third of the run."""
    return int(max(1, min(max(10, round(0.25 * fps)), frames // 3)))


def _essential(calibration: Calibration, a: int, c: int) -> np.ndarray:
    ca, cc = calibration.cameras[a], calibration.cameras[c]
    R = cc.R @ ca.R.T
    t = cc.t - R @ ca.t
    tx = np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])
    return tx @ R


def lag_costs(xa: np.ndarray, xc: np.ndarray, E: np.ndarray, lags: np.ndarray) -> np.ndarray:
    """Median Sampson distance (normalised units) of camera a's points ``xa`` (N, M, 2) paired with
    camera c's ``xc`` (N, M, 2) ``d`` frames later, for each lag d; NaN where too few pairs
    (:func:`graph.solve.lag_sampson`, every ``max(1, N M / PAIRS_PER_LAG)``-th frame)."""
    N, M = xa.shape[:2]
    return lag_sampson(np.ascontiguousarray(xa, dtype=np.float64), np.ascontiguousarray(xc, dtype=np.float64),
                               np.ascontiguousarray(E, dtype=np.float64), np.asarray(lags, dtype=np.int64),
                               max(1, N * M // PAIRS_PER_LAG), MIN_PAIRS)


def _best_lag(costs: np.ndarray, lags: np.ndarray) -> tuple[float, bool]:
    """The best lag, below a frame by a parabola through its neighbours, and whether it is decisive."""
    if not np.isfinite(costs).any():
        return 0.0, False
    i = int(np.nanargmin(costs))
    decisive = bool(costs[i] < DECISIVE * np.nanmedian(costs))
    lag = float(lags[i])
    if 0 < i < len(costs) - 1 and np.isfinite(costs[i - 1:i + 2]).all():
        c0, c1, c2 = costs[i - 1:i + 2]
        curv = c0 - 2 * c1 + c2
        if curv > 0:
            lag += float(np.clip(0.5 * (c0 - c2) / curv, -0.5, 0.5))
    return lag, decisive


def coarse_offsets(calibration: Calibration, meas: np.ndarray, valid: np.ndarray, fps: float,
                   max_lag: int | None = None) -> CoarseOffsets:
    """Each camera's offset from detections ``meas`` (N, C, M, 2) where ``valid`` (N, C, M)
    (module docstring). A camera whose best lag is not decisive keeps 0."""
    N, C = meas.shape[:2]
    max_lag = default_max_lag(N, fps) if max_lag is None else max_lag
    lags = np.arange(-max_lag, max_lag + 1)
    norm = np.stack([undistort_points(cam, np.where(valid[:, c, :, None], meas[:, c], np.nan))
                     for c, cam in enumerate(calibration.cameras)], axis=1)  # (N, C, M, 2)
    seen = np.isfinite(norm).all(-1)  # (N, C, M)
    tau = np.zeros(C)
    decided = np.zeros(C, dtype=bool)
    decided[0] = True
    against = [-1] * C
    placed = [0]
    todo = list(range(1, C))
    shared = np.einsum("nam,ncm->ac", seen.astype(float), seen.astype(float))
    while todo:
        # the unplaced camera sharing most detections with a placed one goes next
        c, a = max(((c, a) for c in todo for a in placed), key=lambda ca: shared[ca[1], ca[0]])
        lag, ok = _best_lag(lag_costs(norm[:, a], norm[:, c], _essential(calibration, a, c), lags), lags)
        # camera c's frame n + lag pairs with camera a's frame n: tau_c = tau_a - lag
        tau[c] = tau[a] - lag if ok else tau[a] if decided[a] else 0.0
        decided[c] = ok and decided[a]
        against[c] = a
        placed.append(c)
        todo.remove(c)
    return CoarseOffsets(frames=tau, decided=decided, against=against)


def shift_and_fraction(tau: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Camera frame ``m`` is at time ``m + tau`` = window ``n + f``: ``m = n + shift``,
    ``shift = -floor(tau)``, ``f = tau - floor(tau)`` in [0, 1) (what
    :func:`graph.solve.kernels.window_normals` takes)."""
    whole = np.floor(tau)
    return (-whole).astype(np.int64), (tau - whole).astype(np.float64)


def on_reference_clock(meas: np.ndarray, valid: np.ndarray, tau: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The detections re-indexed to the nearest frame of the reference clock: camera c's frame
    ``n - round(tau_c)`` as frame n (NaN, not valid, where that frame does not exist). For the
    triangulation that starts a solve."""
    N, C = meas.shape[:2]
    out = np.full_like(meas, np.nan)
    ok = np.zeros_like(valid)
    for c in range(C):
        k = int(round(float(tau[c])))
        lo, hi = max(0, k), min(N, N + k)  # frames n whose camera frame n - k exists
        if hi > lo:
            out[lo:hi, c] = meas[lo - k:hi - k, c]
            ok[lo:hi, c] = valid[lo - k:hi - k, c]
    return out, ok


def between_frames_on_reference_clock(meas: np.ndarray, valid: np.ndarray,
                                      tau: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The detections (N, C, M, 2) at the reference clock's frames, each camera's interpolated between
    its own frames: reference frame n is camera c's time ``t = n - tau_c``, between its frames
    ``f = floor(t)`` and ``f + 1``, and with ``w = t - f``

        x_n = (1 - w) x_f + w x_(f+1)          (both valid)
        x_n = x_f  if w <= 1/2,  x_(f+1) if w > 1/2   (one of them valid: the nearer, or none)

    A marker moving smoothly is off by its acceleration times ``w (1 - w) / 2`` frames squared, far
    below a pixel; the nearest frame (:func:`on_reference_clock`) leaves it off by its speed times up
    to half a frame (on the simulated cheetah at 4 m/s and 120 fps, up to 17 mm). For ``ekf``'s
    stream, which takes one frame of every camera at a time."""
    N, C = meas.shape[:2]
    out = np.full_like(meas, np.nan)
    ok = np.zeros_like(valid)
    t = np.arange(N)[:, None] - np.asarray(tau, dtype=np.float64)[None, :]  # (N, C) camera times
    f = np.floor(t).astype(np.int64)
    w = t - f
    cams = np.arange(C)[None, :]
    a_in, b_in = (f >= 0) & (f < N), (f + 1 >= 0) & (f + 1 < N)
    fa, fb = np.clip(f, 0, N - 1), np.clip(f + 1, 0, N - 1)
    va = valid[fa, cams] & a_in[..., None]
    vb = valid[fb, cams] & b_in[..., None]
    W = w[..., None]
    both, only_a, only_b = va & vb, va & ~vb & (W <= 0.5), vb & ~va & (W > 0.5)
    xa, xb = meas[fa, cams], meas[fb, cams]
    out[both] = ((1 - W[..., None]) * xa + W[..., None] * xb)[both]
    out[only_a], out[only_b] = xa[only_a], xb[only_b]
    ok[:] = both | only_a | only_b
    return out, ok


def on_camera_clocks(positions: np.ndarray, tau: np.ndarray) -> np.ndarray:
    """Positions (N, M, 3) on the reference clock at each camera's own frames (C, N, M, 3): camera c's
    frame j is reference time ``t = j + tau_c``, and with ``f = floor(t)``, ``w = t - f``,
    ``X = (1 - w) X_f + w X_(f+1)`` (NaN where ``t`` is outside the run). The inverse of
    :func:`between_frames_on_reference_clock`, for what is drawn over each camera's frames."""
    N = positions.shape[0]
    out = np.full((len(tau),) + positions.shape, np.nan)
    for c, tc in enumerate(np.asarray(tau, dtype=np.float64)):
        t = np.arange(N) + tc
        f = np.floor(t).astype(np.int64)
        w = (t - f)[:, None, None]
        inside = (t >= 0) & (t <= N - 1)
        fa, fb = np.clip(f, 0, N - 1), np.clip(f + 1, 0, N - 1)
        out[c, inside] = ((1 - w) * positions[fa] + w * positions[fb])[inside]
    return out


def off_reference_clock(a: np.ndarray, tau: np.ndarray) -> np.ndarray:
    """The inverse of :func:`on_reference_clock` for per-camera arrays (C, N, ...): what stands at
    reference frame n goes back to camera frame ``n - round(tau_c)`` (NaN or False where none)."""
    out = np.full_like(a, False if a.dtype == bool else np.nan)
    N = a.shape[1]
    for c in range(a.shape[0]):
        k = int(round(float(tau[c])))
        lo, hi = max(0, k), min(N, N + k)
        if hi > lo:
            out[c, lo - k:hi - k] = a[c, lo:hi]
    return out


@njit(cache=True)
def lag_sampson(xa, xc, E, lags, stride, min_pairs):
    """For each lag d of ``lags``, the median over camera a's frames n (every ``stride``-th) and
    markers of the Sampson distance of ``xa[n]`` (normalised points, (N, M, 2), NaN where unseen)
    paired with camera c's ``xc[n + d]`` under the essential matrix ``E`` (:mod:`graph.solve.sync`)::

        sqrt(e),  e = (x_c^T E x_a)^2 / ((E x_a)_1^2 + (E x_a)_2^2 + (E^T x_c)_1^2 + (E^T x_c)_2^2)

    NaN for a lag with fewer than ``min_pairs`` pairs."""
    N, M = xa.shape[0], xa.shape[1]
    out = np.full(lags.shape[0], np.nan)
    buf = np.empty(((N + stride - 1) // stride + 1) * M)
    for i in range(lags.shape[0]):
        d = lags[i]
        k = 0
        for n in range(max(0, -d), min(N, N - d), stride):
            for m in range(M):
                ax, ay = xa[n, m, 0], xa[n, m, 1]
                cx, cy = xc[n + d, m, 0], xc[n + d, m, 1]
                if not (np.isfinite(ax) and np.isfinite(ay) and np.isfinite(cx) and np.isfinite(cy)):
                    continue
                e0 = E[0, 0] * ax + E[0, 1] * ay + E[0, 2]
                e1 = E[1, 0] * ax + E[1, 1] * ay + E[1, 2]
                e2 = E[2, 0] * ax + E[2, 1] * ay + E[2, 2]
                f0 = E[0, 0] * cx + E[1, 0] * cy + E[2, 0]
                f1 = E[0, 1] * cx + E[1, 1] * cy + E[2, 1]
                num = cx * e0 + cy * e1 + e2
                den = e0 * e0 + e1 * e1 + f0 * f0 + f1 * f1
                buf[k] = np.sqrt(num * num / max(den, 1e-300))
                k += 1
        if k >= min_pairs:
            out[i] = np.median(buf[:k])
    return out
