"""One camera's parameters as files give them: the checks of each field (the camera matrix ``K``, the
distortion ``d``, a rotation ``R``, a translation ``t``, the image size), shared by the rig files of
:mod:`graph.io.calibration`, and AcinoSet's camera JSON, one camera's intrinsics (what
``acinoset calibrate intrinsics`` writes, and ``calibrate extrinsics --intrinsics`` and the service's
calibrations read)::

    {"camera_resolution": [W, H], "k": 3x3, "d": [the model's coefficients],
     "model": a name of graph.camera.CAMERA_MODELS, "rms_px": ...}

Every check raises :class:`graph.errors.InputError` with one line naming the field and the file.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from graph.camera import CAMERA_MODELS, FISHEYE, PINHOLE, Camera
from graph.errors import InputError

ROTATION_TOLERANCE = 1e-5  # max |R^T R - I| and |det R - 1| accepted (files rounded to ~6 digits pass)


def load_camera_json(path: str | Path) -> Camera:
    """A camera from AcinoSet's camera JSON (``camera_resolution``, ``k``, ``d``; ``model`` if written by
    acinoset, else fisheye for 4 coefficients and pinhole otherwise), at the origin (``R = I``, ``t = 0``)."""
    p = Path(path)
    try:
        doc = json.loads(p.read_text(encoding="utf-8-sig"))
    except FileNotFoundError:
        raise InputError("no such file", p) from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise InputError(f"not a camera JSON ({e})", p) from None
    if not isinstance(doc, dict) or "k" not in doc or "d" not in doc:
        raise InputError('not a camera JSON: needs "k" (3x3) and "d"', p)
    K = intrinsic_matrix(doc["k"], "k", p)
    d = float_array(doc["d"], "d", p).ravel()
    model = doc.get("model", FISHEYE if d.size == 4 else PINHOLE)
    spec = CAMERA_MODELS.get(model) if isinstance(model, str) else None
    if spec is None or spec.coefficient_problem(d.size):
        raise InputError(f"d: {d.size} coefficients do not fit the {model} model", p)
    size = image_size(doc["camera_resolution"], "camera_resolution", p) if "camera_resolution" in doc else (0, 0)
    return Camera(K=K, dist=d, R=np.eye(3), t=np.zeros(3), model=model, size=size, name=p.stem)


def float_array(value, what: str, path: Path) -> np.ndarray:
    """``value`` as an array of finite float64 (a field ``what`` of the file ``path``)."""
    try:
        a = np.asarray(value, dtype=np.float64)
    except OverflowError:  # an integer beyond any float (1 and 400 zeros)
        raise InputError(f"{what}: a number too large for a float", path) from None
    except (TypeError, ValueError):
        raise InputError(f"{what}: expected numbers in a regular array", path) from None
    if not np.all(np.isfinite(a)):
        raise InputError(f"{what}: contains NaN or infinite values", path)
    return a


def intrinsic_matrix(value, what: str, path: Path) -> np.ndarray:
    """``K = [[fx, s, cx], [0, fy, cy], [0, 0, 1]]`` with ``fx, fy > 0``; the camera models here
    have no skew, so ``s`` must be (numerically) zero."""
    K = float_array(value, what, path)
    if K.shape != (3, 3):
        raise InputError(f"{what}: camera matrix must be 3x3, got shape {shape_text(K)}", path)
    if not (K[0, 0] > 0 and K[1, 1] > 0):
        raise InputError(f"{what}: focal lengths must be positive (fx={K[0, 0]:g}, fy={K[1, 1]:g})", path)
    if not np.allclose(K[2], [0.0, 0.0, 1.0], atol=1e-9) or abs(K[1, 0]) > 1e-9:
        raise InputError(f"{what}: not a camera matrix (last row must be [0, 0, 1])", path)
    if abs(K[0, 1]) > 1e-6 * K[0, 0]:
        raise InputError(f"{what}: skew {K[0, 1]:g} is not supported (OpenCV models have none)", path)
    return K


def rotation_matrix(value, what: str, path: Path) -> np.ndarray:
    """Accept ``R`` when ``|R^T R - I| <= tol`` and ``|det R - 1| <= tol``; return the nearest
    rotation ``U V^T`` (from ``R = U S V^T``) so rounding in the file does not leak into the solver."""
    R = float_array(value, what, path)
    if R.shape != (3, 3):
        raise InputError(f"{what}: rotation must be 3x3, got shape {shape_text(R)}", path)
    ortho = float(np.abs(R.T @ R - np.eye(3)).max())
    det = float(np.linalg.det(R))
    if ortho > ROTATION_TOLERANCE or abs(det - 1.0) > ROTATION_TOLERANCE:
        raise InputError(f"{what}: not a rotation matrix (max |R^T R - I| = {ortho:.2g}, det = {det:.6g})", path)
    if ortho > 1e-12:
        U, _, Vt = np.linalg.svd(R)
        R = U @ Vt
    return R


def vector3(value, what: str, path: Path) -> np.ndarray:
    """Three numbers (a 3-vector, a 3x1 or a 1x3 array) as a 3-vector."""
    v = float_array(value, what, path)
    if v.size != 3 or v.ndim > 2:
        raise InputError(f"{what}: expected 3 numbers, got shape {shape_text(v)}", path)
    return v.ravel()


def image_size(value, what: str, path: Path) -> tuple[int, int]:
    """``[width, height]`` in whole, positive pixels."""
    s = float_array(value, what, path).ravel()
    if s.size != 2 or not np.all(s > 0) or not np.all(s == np.round(s)):
        raise InputError(f"{what}: expected [width, height] in whole pixels, got {value!r}", path)
    return int(s[0]), int(s[1])


def shape_text(a: np.ndarray) -> str:
    """``3x1``: an array's shape as an error message gives it."""
    return "x".join(str(n) for n in a.shape) or "scalar"
