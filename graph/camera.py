"""Camera models, one :class:`CameraModel` entry per model in :data:`CAMERA_MODELS`, and the
calibrated :class:`Camera` and :class:`Calibration`.

World to camera: ``X_c = R X_w + t`` (metres). Normalised coordinates ``x = X_c/Z_c, y = Y_c/Z_c``;
each model maps them to distorted ones ``(x', y')``, and pixels are ``u = fx x' + cx, v = fy y' + cy``.

Fisheye (``cv2.fisheye``; 4 coefficients k1..k4), with ``r = sqrt(x^2 + y^2)`` and ``theta = atan(r)``::

    theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8)
    x' = (theta_d / r) x,   y' = (theta_d / r) y

Pinhole (``cv2.projectPoints``; 5 coefficients k1, k2, p1, p2, k3), with ``r2 = x^2 + y^2``::

    radial = 1 + k1 r2 + k2 r2^2 + k3 r2^3
    x' = x radial + 2 p1 x y + p2 (r2 + 2 x^2)
    y' = y radial + p1 (r2 + 2 y^2) + 2 p2 x y

A model's entry holds everything the rest of the library asks of it: its name, the integer code
the compiled kernels branch on (intrinsics packed as ``[code, fx, fy, cx, cy, d_0 .. d_{S-1}]``,
``S =`` :data:`DISTORTION_SLOTS`), its distortion coefficients, the distortion with its Jacobians,
OpenCV's projection (the definition the distortion reproduces), inverse and calibration, and the
keys that mark it in an Anipose ``calibration.toml``. The same maths runs compiled in
:mod:`graph.solve.kernels` (one branch per code); this module is the readable reference and the
vectorised numpy path used by readers, the simulator, metrics and the calibration.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

# the units a calibration's translations may be in, as metres per unit ("auto": read from the file or guessed)
CALIBRATION_UNITS: dict[str, float] = {"auto": 0.0, "m": 1.0, "cm": 0.01, "mm": 0.001}

FISHEYE = "fisheye"
PINHOLE = "pinhole"


class IllConditionedView(Exception):
    """OpenCV's calibration found board view ``index`` (of those it was given) ill-conditioned."""

    def __init__(self, index: int) -> None:
        super().__init__(f"view {index} is ill-conditioned")
        self.index = index


@dataclass(frozen=True)
class CameraModel:
    """One camera model: what every part of the library needs to know of it.

    * ``code``: the model's number in packed intrinsics (:meth:`Camera.packed`), the branch the
      compiled :func:`graph.solve.kernels.project_point` takes; never reused.
    * ``coefficients``: the names of its distortion coefficients, in order (``Camera.dist``).
    * ``min_coefficients``: the fewest a calibration file may give (the rest are zero).
    * ``summary``: the coefficients in words, for file descriptions.
    * ``distort(x, y, d, jacobian)``: ``(x', y')`` of normalised ``(x, y)`` and, with ``jacobian``,
      ``d(x', y')/d(x, y)`` (..., 2, 2) (else None).
    * ``coefficient_jacobian(x, y, d, fx, fy)``: ``d(u, v)/d(coefficients)`` (M, 2, n).
    * ``opencv_project(Xc, K, d)``: OpenCV's pixels (N, 2) of camera-frame points (N, 3), the
      definition ``distort`` reproduces.
    * ``undistort(pts, K, d)``: OpenCV's inverse, pixels (N, 1, 2) to normalised coordinates (N, 1, 2).
    * ``opencv_calibrate(objs, imgs, size, criteria)``: OpenCV's intrinsic calibration from board
      views (per view, points (1, P, 3) and pixels (1, P, 2), float64), ``(K, D)``; raises
      :class:`IllConditionedView` for a view it can name as the trouble.
    * ``anipose_keys``: the ``(key, value)`` pairs that mark the model in an Anipose table (none:
      aniposelib's default, the pinhole).
    """

    name: str
    code: int
    coefficients: tuple[str, ...]
    min_coefficients: int
    summary: str
    distort: Callable
    coefficient_jacobian: Callable
    opencv_project: Callable
    undistort: Callable
    opencv_calibrate: Callable
    anipose_keys: tuple[tuple[str, object], ...] = ()

    @property
    def n_coefficients(self) -> int:
        return len(self.coefficients)

    def coefficient_problem(self, n: int) -> str | None:
        """Why ``n`` distortion coefficients (as read from a file) do not fit this model, or None."""
        top = self.n_coefficients
        if self.min_coefficients <= n <= top:
            return None
        if self.min_coefficients == top:
            return f"{self.name} needs {top} coefficients, got {n}"
        span = f"up to {top}" if self.min_coefficients == 0 else f"{self.min_coefficients} to {top}"
        return f"{self.name} takes {span} coefficients ({', '.join(self.coefficients)}), got {n}"


def camera_model(name: str) -> CameraModel:
    """The registry entry of the model called ``name`` (ValueError for an unknown one)."""
    try:
        return CAMERA_MODELS[name]
    except (KeyError, TypeError):
        raise ValueError(f"unknown camera model {name!r}") from None


def model_names() -> str:
    """The models' names in words: ``"fisheye or pinhole"``."""
    return " or ".join(CAMERA_MODELS)


@dataclass
class Camera:
    """One calibrated camera.

    ``model`` names its :class:`CameraModel`; ``dist`` holds that model's coefficients (fisheye:
    k1..k4; pinhole: k1, k2, p1, p2, k3), padded with zeros or cut to their number.
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
        n = camera_model(self.model).n_coefficients
        self.dist = np.pad(d, (0, max(0, n - d.size)))[:n]
        self.size = (int(self.size[0]), int(self.size[1]))

    @property
    def camera_model(self) -> CameraModel:
        """This camera's model's registry entry."""
        return CAMERA_MODELS[self.model]

    @property
    def center(self) -> np.ndarray:
        """Camera centre in world coordinates, ``-R^T t``."""
        return -self.R.T @ self.t

    def packed(self) -> np.ndarray:
        """Intrinsics as one vector for the compiled kernels: ``[code, fx, fy, cx, cy, d_0 .. d_{S-1}]``
        (the model's :attr:`CameraModel.code`, its coefficients zero-padded to :data:`DISTORTION_SLOTS`)."""
        d = np.zeros(DISTORTION_SLOTS)
        d[: self.dist.size] = self.dist
        return np.array([float(self.camera_model.code),
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
        xd, yd, dxd = self.camera_model.distort(x, y, self.dist, jacobian)
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


def undistort_points(camera: Camera, uv: np.ndarray) -> np.ndarray:
    """Pixels (..., 2) to normalised image coordinates (..., 2) with OpenCV's iterative inverse of the
    camera's model (:attr:`CameraModel.undistort`)."""
    uv = np.asarray(uv, dtype=np.float64)
    shape = uv.shape
    pts = uv.reshape(-1, 1, 2)
    out = np.full_like(pts, np.nan)
    ok = np.isfinite(pts).all(axis=-1).ravel()
    if ok.any():
        out[ok] = camera.camera_model.undistort(pts[ok], camera.K, camera.dist)
    return out.reshape(shape)


def opencv_fisheye_flag(name: str) -> int:
    """A fisheye flag by name: ``cv2.fisheye.CALIB_*`` in OpenCV 4, ``cv2.CALIB_*`` in OpenCV 5."""
    import cv2

    value = getattr(cv2.fisheye, name, None)
    return int(value if value is not None else getattr(cv2, name))


# ------------------------------------------------------------------------------------------ fisheye


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


def _fisheye_coefficient_jacobian(x, y, d, fx, fy):
    """``d(u, v)/d k_i = (fx x, fy y) th^(2i+1) / r``, i = 1..4 (``th / r -> 1`` at the centre)."""
    r = np.hypot(x, y)
    th = np.arctan(r)
    small = r < 1e-12
    ratio = np.where(small, 1.0, th / np.where(small, 1.0, r))
    J = np.empty(np.shape(x) + (2, 4))
    for i in range(4):
        g = ratio * th ** (2 * i + 2)
        J[..., 0, i] = fx * x * g
        J[..., 1, i] = fy * y * g
    return J


def _fisheye_opencv_project(Xc, K, d):
    import cv2

    zero = np.zeros(3)
    return cv2.fisheye.projectPoints(np.asarray(Xc, np.float64).reshape(-1, 1, 3), zero, zero, K, d)[0].reshape(-1, 2)


def _fisheye_undistort(pts, K, d):
    import cv2

    return cv2.fisheye.undistortPoints(pts, K, d.reshape(-1, 1))


def _fisheye_calibrate(objs, imgs, size, criteria):
    """``cv2.fisheye.calibrate`` with RECOMPUTE_EXTRINSIC, CHECK_COND and FIX_SKEW; the view OpenCV
    names ill-conditioned raises :class:`IllConditionedView`."""
    import cv2

    flags = (opencv_fisheye_flag("CALIB_RECOMPUTE_EXTRINSIC") | opencv_fisheye_flag("CALIB_CHECK_COND")
             | opencv_fisheye_flag("CALIB_FIX_SKEW"))
    try:
        _, K, D, _, _ = cv2.fisheye.calibrate(objs, imgs, size, None, None, flags=flags, criteria=criteria)
    except cv2.error as e:
        m = re.search(r"input array (\d+)", str(e))
        if m and int(m.group(1)) < len(objs):
            raise IllConditionedView(int(m.group(1))) from None
        raise
    return K, D


# ------------------------------------------------------------------------------------------ pinhole


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


def _radtan_coefficient_jacobian(x, y, d, fx, fy):
    """``d(u, v)/d k1 = (fx x, fy y) r2``, ``/d k2 = (fx x, fy y) r2^2``, ``/d k3 = (fx x, fy y) r2^3``,
    ``/d p1 = (2 fx x y, fy (r2 + 2 y^2))``, ``/d p2 = (fx (r2 + 2 x^2), 2 fy x y)``."""
    J = np.empty(np.shape(x) + (2, 5))
    r2 = x * x + y * y
    for col, p in ((0, r2), (1, r2 * r2), (4, r2 ** 3)):
        J[..., 0, col] = fx * x * p
        J[..., 1, col] = fy * y * p
    J[..., 0, 2] = fx * 2 * x * y
    J[..., 1, 2] = fy * (r2 + 2 * y * y)
    J[..., 0, 3] = fx * (r2 + 2 * x * x)
    J[..., 1, 3] = fy * 2 * x * y
    return J


def _radtan_opencv_project(Xc, K, d):
    import cv2

    zero = np.zeros(3)
    return cv2.projectPoints(np.asarray(Xc, np.float64).reshape(-1, 1, 3), zero, zero, K, d)[0].reshape(-1, 2)


def _radtan_undistort(pts, K, d):
    import cv2

    return cv2.undistortPoints(pts, K, d.reshape(-1, 1),
                               criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12))


def _radtan_calibrate(objs, imgs, size, criteria):
    """``cv2.calibrateCamera`` (k1, k2, p1, p2, k3), on float32 points as it wants them."""
    import cv2

    objs = [o.reshape(-1, 3).astype(np.float32) for o in objs]
    imgs = [m.reshape(-1, 1, 2).astype(np.float32) for m in imgs]
    _, K, D, _, _ = cv2.calibrateCamera(objs, imgs, size, None, None, criteria=criteria)
    return K, D


# ----------------------------------------------------------------------------------------- registry


CAMERA_MODELS: dict[str, CameraModel] = {m.name: m for m in (
    CameraModel(FISHEYE, 0, ("k1", "k2", "k3", "k4"), 4, "k1..k4 (OpenCV fisheye)", _fisheye_distort,
                _fisheye_coefficient_jacobian, _fisheye_opencv_project, _fisheye_undistort, _fisheye_calibrate,
                anipose_keys=(("fisheye", True),)),
    CameraModel(PINHOLE, 1, ("k1", "k2", "p1", "p2", "k3"), 0, "k1, k2, p1, p2, k3 (OpenCV)", _radtan_distort,
                _radtan_coefficient_jacobian, _radtan_opencv_project, _radtan_undistort, _radtan_calibrate),
)}

# distortion coefficients in packed intrinsics: the most any model has
PLACE_TOLERANCE = 1e-6  # centres this close, relative to the rig's extent, are one place (Calibration.places)
DISTORTION_SLOTS = max(m.n_coefficients for m in CAMERA_MODELS.values())


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

    def places(self) -> np.ndarray:
        """An index per camera (C,), shared by cameras at one place: centres within
        :data:`PLACE_TOLERANCE` of the rig's extent (its largest distance between two centres) of
        each other. Two views from one place are one ray: together they fix no depth (a calibration
        entry copied from another camera's puts two cameras there)."""
        c = np.stack([cam.center for cam in self.cameras])
        d = np.linalg.norm(c[:, None] - c[None], axis=-1)
        place = np.arange(len(c))
        for i in range(len(c)):
            near = np.flatnonzero(d[i, :i] <= PLACE_TOLERANCE * d.max())
            if near.size:
                place[i] = place[near[0]]
        return place

    def places_seeing(self, valid: np.ndarray) -> np.ndarray:
        """How many places (:meth:`places`) saw each marker in each frame, from ``valid`` (N, C, M): (N, M)."""
        places = self.places()
        if len(np.unique(places)) == len(places):
            return valid.sum(axis=1)
        return np.sum([valid[:, places == p].any(axis=1) for p in np.unique(places)], axis=0)

    def same_places(self) -> str | None:
        """A one-line note naming the cameras at one place (:meth:`places`), or None when each has its own."""
        places = self.places()
        groups = [[n for n, q in zip(self.names, places) if q == p] for p in np.unique(places)]
        shared = [g for g in groups if len(g) > 1]
        if not shared:
            return None
        return (f"cameras {'; '.join(' and '.join(g) for g in shared)} are at one place in the calibration (the same "
                "centre): views from one place fix no depth, so they count as one view there (an entry copied from "
                "another camera's?)")
