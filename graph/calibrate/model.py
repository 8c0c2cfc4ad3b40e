"""Projection of points in a camera's frame with its Jacobians, for the bundle adjustment.

Intrinsics as one vector ``theta = [fx, fy, cx, cy, d...]``, ``d`` the model's distortion
coefficients (:attr:`graph.camera.CameraModel.coefficients`):

* fisheye (OpenCV, 8): ``[fx, fy, cx, cy, k1, k2, k3, k4]``
* pinhole (OpenCV radial-tangential, 9): ``[fx, fy, cx, cy, k1, k2, p1, p2, k3]``

With ``x = X/Z, y = Y/Z`` and the distorted ``(x', y')`` of :mod:`graph.camera`, pixels are
``u = fx x' + cx, v = fy y' + cy``, so ``d(u, v)/d(fx, fy, cx, cy) = [[x', 0, 1, 0], [0, y', 0, 1]]``;
the derivatives with respect to the distortion coefficients are each model's
(:attr:`graph.camera.CameraModel.coefficient_jacobian`):

* fisheye, ``r = |(x, y)|, th = atan r``: ``d x'/d k_i = x th^(2i+1) / r`` (and y alike), i = 1..4;
* pinhole, ``r2 = x^2 + y^2``: ``d(x', y')/d k1 = (x, y) r2``, ``/d k2 = (x, y) r2^2``,
  ``/d k3 = (x, y) r2^3``, ``/d p1 = (2xy, r2 + 2y^2)``, ``/d p2 = (r2 + 2x^2, 2xy)``.
"""

from __future__ import annotations

import numpy as np

from graph.camera import CAMERA_MODELS, Camera, camera_model

# the length of theta per model, and the longest
N_INTRINSICS = {name: 4 + m.n_coefficients for name, m in CAMERA_MODELS.items()}
MAX_INTRINSICS = max(N_INTRINSICS.values())
HELD = 1e-6  # the prior sd of an intrinsic held (relative for the focal lengths, else in its units)
# What of a lens a board calibration fits: "full", every entry of theta; "k1", Anipose's lens: one focal
# length, the principal point at the image's centre and the first radial coefficient alone
LENSES = ("full", "k1")


def lens_with_intrinsics(lens: str) -> str | None:
    """Why ``lens`` cannot go with intrinsics given rather than calibrated here (the lens is what those
    fit), or None for ``"full"``: the refusal of the library, the command line and the service."""
    if lens == "full":
        return None
    return "lens is what the intrinsics calibrated here fit: with intrinsics given, leave it out"


def held_lens(theta: np.ndarray, size: tuple[int, int], lens: str) -> tuple[np.ndarray, np.ndarray] | None:
    """The lens ``lens`` (:data:`LENSES`) as a start ``theta0`` and a stiff prior ``(theta0, L)`` on
    ``theta`` (:class:`graph.calibrate.bundle.Settings`), or None for ``"full"`` (nothing held).

    For ``"k1"``, from a calibration ``theta`` of the whole model: ``theta0`` has ``fx = fy = f``, their
    mean, the principal point ``((w - 1) / 2, (h - 1) / 2)`` (the image's centre in OpenCV's pixel
    convention), ``k1`` as calibrated and every other coefficient 0; the whitened rows of ``L (theta -
    theta0)`` are ``(fx - fy) / (f HELD)``, ``(cx - cx0) / HELD``, ``(cy - cy0) / HELD`` and ``d_j / HELD``
    for each coefficient after ``k1``; ``f`` and ``k1`` are free (rows of zeros)."""
    if lens == "full":
        return None
    if lens != "k1":
        raise ValueError(f"unknown lens {lens!r} ({', '.join(LENSES)})")
    n = len(theta)
    f = 0.5 * (theta[0] + theta[1])
    theta0 = np.zeros(n)
    theta0[:5] = f, f, (size[0] - 1) / 2.0, (size[1] - 1) / 2.0, theta[4]
    L = np.zeros((n, n))
    L[0, :2] = np.array([1.0, -1.0]) / (f * HELD)
    L[2, 2] = L[3, 3] = 1.0 / HELD
    for j in range(5, n):
        L[j, j] = 1.0 / HELD
    return theta0, L


def intrinsics_of(camera: Camera) -> np.ndarray:
    K = camera.K
    return np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2], *camera.dist], dtype=np.float64)


def camera_with(theta: np.ndarray, model: str, size: tuple[int, int], name: str = "",
                R: np.ndarray | None = None, t: np.ndarray | None = None) -> Camera:
    K = np.array([[theta[0], 0.0, theta[2]], [0.0, theta[1], theta[3]], [0.0, 0.0, 1.0]])
    return Camera(K=K, dist=np.asarray(theta[4:]), R=np.eye(3) if R is None else R,
                  t=np.zeros(3) if t is None else t, model=model, size=size, name=name)


def project(theta: np.ndarray, model: str, Xc: np.ndarray, jacobians: bool = True):
    """Pixels (M, 2) of camera-frame points ``Xc`` (M, 3); with ``jacobians``, also
    ``d uv / d Xc`` (M, 2, 3) and ``d uv / d theta`` (M, 2, P)."""
    Xc = np.asarray(Xc, dtype=np.float64)
    z = Xc[:, 2]
    x, y = Xc[:, 0] / z, Xc[:, 1] / z
    fx, fy, cx, cy = theta[:4]
    d = np.asarray(theta[4:])
    spec = camera_model(model)
    xd, yd, D = spec.distort(x, y, d, jacobians)
    uv = np.stack([fx * xd + cx, fy * yd + cy], axis=1)
    if not jacobians:
        return uv
    M = len(Xc)
    dn = np.zeros((M, 2, 3))
    dn[:, 0, 0] = 1 / z
    dn[:, 0, 2] = -x / z
    dn[:, 1, 1] = 1 / z
    dn[:, 1, 2] = -y / z
    J_X = np.matmul(D, dn)
    J_X[:, 0] *= fx
    J_X[:, 1] *= fy
    J_t = np.zeros((M, 2, N_INTRINSICS[model]))
    J_t[:, 0, 0] = xd
    J_t[:, 1, 1] = yd
    J_t[:, 0, 2] = 1.0
    J_t[:, 1, 3] = 1.0
    J_t[:, :, 4:] = spec.coefficient_jacobian(x, y, d, fx, fy)
    return uv, J_X, J_t
