"""A camera's pose found again from the other cameras' points (resection), for a rig with a camera that is off.

A camera whose entry in the calibration is wrong (bumped, or a copy of another camera's, as in
SLEAP's minimal session) sits far from where its detections put it, further than a bundle
adjustment started from it can travel, and its detections are all trimmed as mistakes before the
adjustment starts. So before the adjustment, each camera ``c`` is posed again from the others:

1. the points the other cameras triangulate (:func:`graph.solve.triangulate.robust_points`, with
   ``c``'s detections left out, two or more places), and ``c``'s confident detections of them,
   undistorted with ``c``'s own intrinsics to normalised coordinates ``x``;
2. the pose ``(R, t)`` with ``x ~ pi(R X + t)`` by ``cv2.solvePnPRansac`` (EPnP on minimal sets,
   inliers within :data:`RANSAC_PX` pixels at the camera's focal length), then refined on the
   inliers by ``cv2.solvePnPRefineLM``.

A camera is off when its detections sit further from the others' points than the adjustment's
trimming keeps (:data:`graph.calibrate.bundle.HUBER_SIGMAS` noise sd, the noise measured on every
camera's errors at once as ``median |e| / sqrt(2 ln 2)``): a camera only a little off is left to
the adjustment, which moves it with every other camera at once, and a good camera is not
re-posed from a small object's points, whose pose is ambiguous (the mouse's near-planar body
admits a pose turned tens of degrees that predicts it almost as well). An off camera's pose found
replaces the old one only when it predicts the camera's detections on the held-out frames
(points from the other cameras again) at least ``min_gain`` better. The points are in the old
rig's world frame and scale, so a re-posed camera is too. Off cameras are taken worst first, each
re-posed camera in place before the next is judged: a camera far off spoils no other camera's
resection once it is mended.
"""

from __future__ import annotations

import numpy as np

from graph.calibrate.bundle import HUBER_SIGMAS
from graph.camera import Calibration, Camera, undistort_points
from graph.solve.noise import RAYLEIGH_MEDIAN

RANSAC_PX = 8.0  # a detection within this many pixels of the pose's prediction supports it
MIN_POINTS = 12  # points seen by the camera and triangulated by the others, to pose it at all


def others_points(calibration: Calibration, meas: np.ndarray, valid: np.ndarray, c: int) -> np.ndarray:
    """The points (N, M, 3) the cameras other than ``c`` triangulate (NaN where fewer than two places
    see them)."""
    from graph.solve.triangulate import robust_points

    others = valid.copy()
    others[:, c] = False
    X, _, _ = robust_points(calibration, meas, others)
    return X


def pose_from_points(camera: Camera, X: np.ndarray, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """``(R, t)`` of ``camera`` (world to camera) from world points ``X`` (K, 3) and its pixels ``uv``
    (K, 2) (step 2 of the module); None when fewer than :data:`MIN_POINTS` pairs or RANSAC finds no
    pose in front of the camera."""
    import cv2

    xy = undistort_points(camera, uv)
    ok = np.isfinite(xy).all(axis=1) & np.isfinite(X).all(axis=1)
    if ok.sum() < MIN_POINTS:
        return None
    obj = np.ascontiguousarray(X[ok], dtype=np.float64)
    img = np.ascontiguousarray(xy[ok], dtype=np.float64).reshape(-1, 1, 2)
    threshold = RANSAC_PX / float(np.sqrt(camera.K[0, 0] * camera.K[1, 1]))
    try:
        found, rvec, tvec, inliers = cv2.solvePnPRansac(obj, img, np.eye(3), None, reprojectionError=threshold,
                                                        iterationsCount=500, confidence=0.999,
                                                        flags=cv2.SOLVEPNP_EPNP)
        if not found or inliers is None or len(inliers) < MIN_POINTS // 2:
            return None
        keep = inliers.ravel()
        rvec, tvec = cv2.solvePnPRefineLM(obj[keep], img[keep], np.eye(3), None, rvec, tvec)
    except cv2.error:
        return None
    R, _ = cv2.Rodrigues(rvec)
    t = tvec.ravel()
    if np.median((obj[keep] @ R.T + t)[:, 2]) <= 0:
        return None
    return R, t


def with_pose(calibration: Calibration, c: int, R: np.ndarray, t: np.ndarray) -> Calibration:
    cams = list(calibration.cameras)
    old = cams[c]
    cams[c] = Camera(K=old.K, dist=old.dist, R=R, t=t, model=old.model, size=old.size, name=old.name)
    return Calibration(cams, source=calibration.source, metadata=dict(calibration.metadata))


def camera_error(camera: Camera, X: np.ndarray, meas_c: np.ndarray, valid_c: np.ndarray) -> float:
    """The median distance (px) between ``camera``'s confident detections ``meas_c`` (N, M, 2) and its
    projections of the points ``X`` (N, M, 3); NaN when none are comparable."""
    use = valid_c & np.isfinite(X).all(axis=-1)
    if not use.any():
        return float("nan")
    return float(np.nanmedian(np.linalg.norm(camera.project(X[use]) - meas_c[use], axis=-1)))


def errors(calibration: Calibration, meas: np.ndarray, valid: np.ndarray) -> tuple[np.ndarray, list[np.ndarray]]:
    """Each camera's detection errors against the others' points: the median per camera (C,) (NaN
    where none) and the errors themselves, one array per camera."""
    out = []
    for c, cam in enumerate(calibration.cameras):
        X = others_points(calibration, meas, valid, c)
        use = valid[:, c] & np.isfinite(X).all(axis=-1)
        out.append(np.linalg.norm(cam.project(X[use]) - meas[:, c][use], axis=-1))
    medians = np.array([float(np.nanmedian(e)) if np.isfinite(e).any() else np.nan for e in out])
    return medians, out


def off_camera(calibration: Calibration, meas: np.ndarray, valid: np.ndarray) -> int | None:
    """The camera furthest off, when its median error is beyond the trimming (see the module)."""
    medians, each = errors(calibration, meas, valid)
    pooled = np.concatenate(each)
    pooled = pooled[np.isfinite(pooled)]
    if not len(pooled) or not np.isfinite(medians).any():
        return None
    sigma = float(np.median(pooled)) / RAYLEIGH_MEDIAN
    worst = int(np.nanargmax(medians))
    return worst if medians[worst] > HUBER_SIGMAS * sigma else None


def repose_off_cameras(calibration: Calibration, meas: np.ndarray, valid: np.ndarray, fit: np.ndarray,
                       held: np.ndarray, min_gain: float) -> tuple[Calibration, list[dict]]:
    """The module's procedure: the rig with every off camera posed again, and for each camera re-posed
    ``{"camera", "old_px", "new_px"}`` (its median error on the held-out frames before and after)."""
    reposed: list[dict] = []
    rig = calibration
    tried: set[int] = set()
    while len(tried) < len(calibration):
        c = off_camera(rig, meas[fit], valid[fit])
        if c is None or c in tried:
            break
        tried.add(c)
        pts = others_points(rig, meas, valid, c)
        cam = rig.cameras[c]
        use = valid[:, c] & fit[:, None]
        pose = pose_from_points(cam, pts[use], meas[:, c][use])
        if pose is None:
            continue
        trial = with_pose(rig, c, *pose)
        old_px = camera_error(cam, pts[held], meas[held][:, c], valid[held][:, c])
        new_px = camera_error(trial.cameras[c], pts[held], meas[held][:, c], valid[held][:, c])
        if not (np.isfinite(new_px) and new_px <= (1 - min_gain) * old_px):
            break
        rig = trial
        reposed.append({"camera": c, "old_px": old_px, "new_px": new_px})
    return rig, reposed
