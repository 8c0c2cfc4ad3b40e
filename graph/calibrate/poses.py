"""Starting poses: the board in each camera by PnP, and rigid transforms averaged robustly.

A pose here is ``(R, t)`` mapping the source frame into the target frame, ``X_target = R X_src + t``.
"""

from __future__ import annotations

import numpy as np

from graph.camera import Camera, undistort_points


def compose(a: tuple, b: tuple) -> tuple[np.ndarray, np.ndarray]:
    """``a o b``: first ``b``, then ``a``."""
    return a[0] @ b[0], a[0] @ b[1] + a[1]


def inverse(a: tuple) -> tuple[np.ndarray, np.ndarray]:
    return a[0].T, -a[0].T @ a[1]


def rotation_angle(R: np.ndarray) -> float:
    """The angle (radians) of a rotation, ``atan2(|vee(R - R^T)| / 2, (trace R - 1) / 2)`` (accurate near 0,
    where ``acos`` of the cosine alone loses half the digits)."""
    s = 0.5 * np.linalg.norm([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    return float(np.arctan2(s, (np.trace(R) - 1.0) / 2.0))


def board_in_camera(camera: Camera, uv: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """The board's pose in the camera (``X_c = R p + t``) from its corners ``uv`` (K, 2) and board
    points (K, 3): undistort to normalised coordinates (any model), then ``cv2.solvePnP`` with an
    identity camera matrix (IPPE for planar boards, refined iteratively). None if it fails."""
    import cv2

    ok = np.isfinite(uv).all(axis=1)
    if ok.sum() < 4:
        return None
    xy = undistort_points(camera, np.ascontiguousarray(uv[ok]))
    obj = np.ascontiguousarray(points[ok], dtype=np.float64)
    img = np.ascontiguousarray(xy, dtype=np.float64).reshape(-1, 1, 2)
    if not np.isfinite(img).all():
        return None
    try:
        found, rvec, tvec = cv2.solvePnP(obj, img, np.eye(3), None, flags=cv2.SOLVEPNP_IPPE)
        if found:
            found, rvec, tvec = cv2.solvePnP(obj, img, np.eye(3), None, rvec, tvec, useExtrinsicGuess=True,
                                             flags=cv2.SOLVEPNP_ITERATIVE)
    except cv2.error:
        return None
    if not found:
        return None
    R, _ = cv2.Rodrigues(rvec)
    t = tvec.ravel()
    if t[2] <= 0:
        return None
    return R, t


def medoid(poses: list[tuple[np.ndarray, np.ndarray]], scale: float) -> int:
    """The index of the pose closest to all others: the smallest median of
    ``angle(R_a^T R_b) + |t_a - t_b| / scale`` (``scale`` a length, to compare metres with radians).
    A robust average: a few wrong poses cannot move it."""
    n = len(poses)
    if n <= 2:
        return 0
    D = np.zeros((n, n))
    for a in range(n):
        for b in range(a + 1, n):
            d = rotation_angle(poses[a][0].T @ poses[b][0]) + np.linalg.norm(poses[a][1] - poses[b][1]) / scale
            D[a, b] = D[b, a] = d
    return int(np.argmin(np.median(D, axis=1)))
