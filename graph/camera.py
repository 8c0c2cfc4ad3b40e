"""Camera models: OpenCV fisheye (4 coefficients) and OpenCV pinhole with radial-tangential distortion.

World to camera: ``X_c = R X_w + t`` (metres). Normalised coordinates ``x = X_c/Z_c, y = Y_c/Z_c``.

Fisheye (``cv2.fisheye``), with ``r = sqrt(x^2 + y^2)`` and ``theta = atan(r)``::

    theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8)
    x' = (theta_d / r) x,   y' = (theta_d / r) y

Pinhole (``cv2.projectPoints``), with ``r2 = x^2 + y^2``::

    radial = 1 + k1 r2 + k2 r2^2 + k3 r2^3
    x' = x radial + 2 p1 x y + p2 (r2 + 2 x^2)
    y' = y radial + p1 (r2 + 2 y^2) + 2 p2 x y

Pixels: ``u = fx x' + cx, v = fy y' + cy``.

The same maths runs compiled in :mod:`graph.solve.kernels`; this module is the readable reference and
the vectorised numpy path used by readers, the simulator and metrics.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

# the units a calibration's translations may be in, as metres per unit ("auto": read from the file or guessed)
CALIBRATION_UNITS: dict[str, float] = {"auto": 0.0, "m": 1.0, "cm": 0.01, "mm": 0.001}

FISHEYE = "fisheye"
PINHOLE = "pinhole"


@dataclass
class Camera:
    """One calibrated camera.

    ``dist`` holds 4 fisheye coefficients (k1..k4) or 5 pinhole ones (k1, k2, p1, p2, k3).
    ``size`` is (width, height) in pixels.
    """

    K: np.ndarray
    dist: np.ndarray
    R: np.ndarray
    t: np.ndarray
    model: str = FISHEYE
    size: tuple[int, int] = (0, 0)
    name: str = ""

    def __post_init__(self) -> None:
        self.K = np.asarray(self.K, dtype=np.float64).reshape(3, 3)
        self.R = np.asarray(self.R, dtype=np.float64).reshape(3, 3)
        self.t = np.asarray(self.t, dtype=np.float64).reshape(3)
        d = np.asarray(self.dist, dtype=np.float64).ravel()
        if self.model == FISHEYE:
            self.dist = np.pad(d, (0, max(0, 4 - d.size)))[:4]
        elif self.model == PINHOLE:
            self.dist = np.pad(d, (0, max(0, 5 - d.size)))[:5]
        else:
            raise ValueError(f"unknown camera model {self.model!r}")
        self.size = (int(self.size[0]), int(self.size[1]))

    @property
    def center(self) -> np.ndarray:
        """Camera centre in world coordinates, ``-R^T t``."""
        return -self.R.T @ self.t

    def packed(self) -> np.ndarray:
        """Intrinsics as one vector for the compiled kernels:
        ``[model(0 fisheye, 1 pinhole), fx, fy, cx, cy, d0..d4]``."""
        d = np.zeros(5)
        d[: self.dist.size] = self.dist
        return np.array([0.0 if self.model == FISHEYE else 1.0,
                         self.K[0, 0], self.K[1, 1], self.K[0, 2], self.K[1, 2], *d])

    def project(self, X: np.ndarray) -> np.ndarray:
        """Project world points ``X`` (..., 3) to pixels (..., 2). Points behind the camera give NaN."""
        uv, _ = self.project_with_jacobian(X, jacobian=False)
        return uv

    def project_with_jacobian(self, X: np.ndarray, jacobian: bool = True):
        """Pixels (..., 2) and, if asked, ``d uv / d X_w`` (..., 2, 3)."""
        X = np.asarray(X, dtype=np.float64)
        Xc = X @ self.R.T + self.t
        z = Xc[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            x = Xc[..., 0] / z
            y = Xc[..., 1] / z
        fx, fy = self.K[0, 0], self.K[1, 1]
        cx, cy = self.K[0, 2], self.K[1, 2]
        if self.model == FISHEYE:
            xd, yd, dxd = _fisheye_distort(x, y, self.dist, jacobian)
        else:
            xd, yd, dxd = _radtan_distort(x, y, self.dist, jacobian)
        uv = np.stack([fx * xd + cx, fy * yd + cy], axis=-1)
        uv[z <= 0] = np.nan
        if not jacobian:
            return uv, None
        # d(x, y)/d Xc
        dn = np.zeros(X.shape[:-1] + (2, 3))
        with np.errstate(divide="ignore", invalid="ignore"):
            dn[..., 0, 0] = 1 / z
            dn[..., 0, 2] = -x / z
            dn[..., 1, 1] = 1 / z
            dn[..., 1, 2] = -y / z
        F = np.array([[fx, 0.0], [0.0, fy]])
        J = F @ dxd @ dn @ self.R
        return uv, J


def _fisheye_distort(x, y, d, jacobian):
    """Fisheye distortion of normalised coordinates and its 2x2 Jacobian."""
    k1, k2, k3, k4 = d
    r2 = x * x + y * y
    r = np.sqrt(r2)
    th = np.arctan(r)
    th2 = th * th
    poly = 1 + th2 * (k1 + th2 * (k2 + th2 * (k3 + th2 * k4)))
    thd = th * poly
    small = r < 1e-12
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.where(small, 1.0, thd / np.where(small, 1.0, r))
    xd, yd = s * x, s * y
    if not jacobian:
        return xd, yd, None
    dthd_dth = 1 + th2 * (3 * k1 + th2 * (5 * k2 + th2 * (7 * k3 + th2 * 9 * k4)))
    dth_dr = 1 / (1 + r2)
    with np.errstate(divide="ignore", invalid="ignore"):
        # s = thd / r; ds/dr = (dthd/dr * r - thd) / r^2; dr/dx = x / r
        ds_dr_over_r = np.where(small, 0.0, (dthd_dth * dth_dr * r - thd) / np.where(small, 1.0, r2 * r))
    D = np.empty(np.shape(x) + (2, 2))
    D[..., 0, 0] = s + x * x * ds_dr_over_r
    D[..., 0, 1] = x * y * ds_dr_over_r
    D[..., 1, 0] = x * y * ds_dr_over_r
    D[..., 1, 1] = s + y * y * ds_dr_over_r
    return xd, yd, D


def _radtan_distort(x, y, d, jacobian):
    """Radial-tangential distortion of normalised coordinates and its 2x2 Jacobian."""
    k1, k2, p1, p2, k3 = d
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    if not jacobian:
        return xd, yd, None
    drad_dr2 = k1 + r2 * (2 * k2 + 3 * k3 * r2)
    D = np.empty(np.shape(x) + (2, 2))
    D[..., 0, 0] = radial + 2 * x * x * drad_dr2 + 2 * p1 * y + 6 * p2 * x
    D[..., 0, 1] = 2 * x * y * drad_dr2 + 2 * p1 * x + 2 * p2 * y
    D[..., 1, 0] = 2 * x * y * drad_dr2 + 2 * p1 * x + 2 * p2 * y
    D[..., 1, 1] = radial + 2 * y * y * drad_dr2 + 6 * p1 * y + 2 * p2 * x
    return xd, yd, D


def undistort_points(camera: Camera, uv: np.ndarray) -> np.ndarray:
    """Pixels (..., 2) to normalised image coordinates (..., 2) with OpenCV's iterative inverse."""
    import cv2

    uv = np.asarray(uv, dtype=np.float64)
    shape = uv.shape
    pts = uv.reshape(-1, 1, 2)
    out = np.full_like(pts, np.nan)
    ok = np.isfinite(pts).all(axis=-1).ravel()
    if ok.any():
        if camera.model == FISHEYE:
            und = cv2.fisheye.undistortPoints(pts[ok], camera.K, camera.dist.reshape(4, 1))
        else:
            und = cv2.undistortPoints(pts[ok], camera.K, camera.dist.reshape(-1, 1),
                                      criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12))
        out[ok] = und
    return out.reshape(shape)


@dataclass
class Calibration:
    """A rig of cameras in one world frame (metres), in the order keypoint files are given."""

    cameras: list[Camera]
    source: str = ""
    metadata: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.cameras)

    @property
    def names(self) -> list[str]:
        return [c.name or f"cam{i + 1}" for i, c in enumerate(self.cameras)]

    def packed(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Intrinsics (C, 10), rotations (C, 3, 3), translations (C, 3) for the kernels."""
        return (np.stack([c.packed() for c in self.cameras]),
                np.stack([c.R for c in self.cameras]),
                np.stack([c.t for c in self.cameras]))

    def project(self, X: np.ndarray) -> np.ndarray:
        """World points (..., 3) to pixels in every camera (C, ..., 2)."""
        return np.stack([c.project(X) for c in self.cameras])
