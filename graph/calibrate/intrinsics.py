"""Intrinsic calibration of one camera from its board views.

1. A start from OpenCV, the model's :attr:`graph.camera.CameraModel.opencv_calibrate`:
   ``cv2.fisheye.calibrate`` (flags RECOMPUTE_EXTRINSIC, CHECK_COND, FIX_SKEW; a view OpenCV finds
   ill-conditioned is dropped and named, and the rest calibrated again) or ``cv2.calibrateCamera``
   (k1, k2, p1, p2, k3).
2. The bundle adjustment of :mod:`graph.calibrate.bundle` with the camera fixed at the origin, its
   intrinsics free (the board's known geometry anchors them, focal length included) and one pose per
   view, under Huber's loss; views whose error stands out (:func:`outlier_views`) are dropped and
   named, and the rest solved again; last, one least-squares solve of the views kept. With the lens
   ``"k1"`` (Anipose's: one focal length, the principal point at the image's centre, radial k1 alone)
   OpenCV's whole-model calibration is the start and the rest of theta is held by a stiff prior
   (:func:`graph.calibrate.model.held_lens`).

The per-view error, the share of the image the views cover and the intrinsics' covariance (the prior
the extrinsic calibration may refine them under) come with the result.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from graph.calibrate import bundle
from graph.calibrate.board import CHARUCO, Board
from graph.calibrate.model import LENSES, camera_with, held_lens
from graph.calibrate.poses import board_in_camera
from graph.calibrate.views import BoardViews
from graph.camera import CAMERA_MODELS, FISHEYE, Camera, IllConditionedView, camera_model, model_names
from graph.errors import InputError

MIN_VIEWS = 3  # views needed for intrinsics: OpenCV's minimum for a planar board
MIN_CORNERS = 6  # corners a view needs to count (a ChArUco board partly hidden)
VIEW_OUTLIER_Z = 5.0  # a view whose error is this many robust sd above the median view's ...
VIEW_OUTLIER_FACTOR = 2.0  # ... and more than this many times the median view's is dropped
COVERAGE_CELLS = 64  # the image is cut into this many columns (and rows in proportion) to measure coverage


@dataclass
class IntrinsicsResult:
    """One camera's intrinsics (``camera.R = I, t = 0``), how well they fit, and on what."""

    camera: Camera
    rms_px: float
    views_used: list[str]
    views_dropped: dict[str, str]
    view_rms_px: dict[str, float]
    coverage: float
    covariance: np.ndarray
    sigma_px: float
    iterations: int = 0
    seconds: float = 0.0
    coverage_map: np.ndarray | None = field(default=None, repr=False)

    def to_dict(self) -> dict:
        c = self.camera
        std = np.sqrt(np.diag(self.covariance))
        return {"name": c.name, "model": c.model, "camera_resolution": list(c.size),
                "k": c.K.tolist(), "d": c.dist.reshape(-1, 1).tolist(),
                "rms_px": self.rms_px, "sigma_px": self.sigma_px, "coverage": self.coverage,
                "views_used": len(self.views_used), "views_dropped": [
                    {"frame": f, "reason": r} for f, r in self.views_dropped.items()],
                "view_rms_px": self.view_rms_px, "std": {"fx": std[0], "fy": std[1], "cx": std[2], "cy": std[3],
                                                        "d": std[4:].tolist()},
                "iterations": self.iterations, "seconds": self.seconds}


def usable_views(views: BoardViews, board: Board) -> tuple[list[int], dict[str, str]]:
    """Indices of views with enough corners, and the others named with the reason."""
    need = board.n_corners if board.kind != CHARUCO else MIN_CORNERS
    keep, dropped = [], {}
    for i, f in enumerate(views.frames):
        n = int(np.isfinite(views.corners[i]).all(axis=1).sum())
        if n >= need:
            keep.append(i)
        else:
            dropped[f] = f"{n} corners, fewer than {need}"
    return keep, dropped


def opencv_start(views: BoardViews, board: Board, model: str, keep: list[int]) -> tuple[np.ndarray, list[int], dict]:
    """OpenCV's calibration of the views ``keep``: intrinsics theta, the views kept and those OpenCV
    found ill-conditioned (named)."""
    import cv2

    obj_all = board.object_points()
    spec = camera_model(model)
    n = spec.n_coefficients
    dropped: dict[str, str] = {}
    keep = list(keep)
    size = tuple(int(s) for s in views.image_size)
    while True:
        if len(keep) < MIN_VIEWS:
            raise InputError(f"too few board views to calibrate: {len(keep)} usable, at least {MIN_VIEWS} needed",
                             views.source or views.name)
        objs, imgs = [], []
        for i in keep:
            ok = np.isfinite(views.corners[i]).all(axis=1)
            objs.append(np.ascontiguousarray(obj_all[ok], dtype=np.float64).reshape(1, -1, 3))
            imgs.append(np.ascontiguousarray(views.corners[i][ok], dtype=np.float64).reshape(1, -1, 2))
        crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-10)
        try:
            K, D = spec.opencv_calibrate(objs, imgs, size, crit)
        except IllConditionedView as e:
            bad = keep.pop(e.index)
            dropped[views.frames[bad]] = "ill-conditioned (board too far, too small or too frontal)"
            continue
        except cv2.error as e:
            raise InputError(f"OpenCV could not calibrate these views ({' '.join(str(e).split())[-120:]})",
                             views.source or views.name) from None
        theta = np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2], *np.pad(np.ravel(D), (0, n))[:n]], dtype=np.float64)
        return theta, keep, dropped


def observations(views_list: list[BoardViews], board: Board, which: list[list[int]], cams: list[int],
                 boards: list[list[int]]) -> bundle.Observations:
    """Observations of the views ``which[c]`` of ``views_list[c]`` (camera ``cams[c]``), the k-th of them
    seeing board pose ``boards[c][k]``. Views are numbered in that order."""
    obj = board.object_points()
    view, cam, brd, uv, pts = [], [], [], [], []
    v = 0
    for views, idx, c, bs in zip(views_list, which, cams, boards):
        for i, b in zip(idx, bs):
            ok = np.isfinite(views.corners[i]).all(axis=1)
            uv.append(views.corners[i][ok])
            pts.append(obj[ok])
            view.append(np.full(int(ok.sum()), v))
            cam.append(c)
            brd.append(b)
            v += 1
    return bundle.Observations(np.concatenate(view), np.array(cam), np.array(brd), np.concatenate(uv),
                               np.concatenate(pts))


def outlier_views(rms: np.ndarray) -> np.ndarray:
    """Views (bool (V,)) whose RMS error stands out from the others': more than
    :data:`VIEW_OUTLIER_Z` robust standard deviations (``1.4826 MAD``) above the median view's, and
    more than :data:`VIEW_OUTLIER_FACTOR` times it. Views that fit a little worse than most (a board
    at the edge of a lens, a frame slightly out of sync) stay; a wrong detection does not."""
    if len(rms) < 3:
        return np.zeros(len(rms), bool)
    med = float(np.median(rms))
    mad = 1.4826 * float(np.median(np.abs(rms - med)))
    return (rms > med + VIEW_OUTLIER_Z * mad) & (rms > VIEW_OUTLIER_FACTOR * med)


def coverage(views: BoardViews, keep: list[int]) -> tuple[float, np.ndarray]:
    """The share of the image inside the outline (convex hull) of at least one view's corners, on a
    grid of :data:`COVERAGE_CELLS` columns; and that grid (rows, cols) counting the views over each cell."""
    import cv2

    W, H = views.image_size
    cols = COVERAGE_CELLS
    rows = max(1, round(cols * H / W))
    grid = np.zeros((rows, cols), np.int32)
    for i in keep:
        pts = views.corners[i][np.isfinite(views.corners[i]).all(axis=1)]
        if len(pts) < 3:
            continue
        cell = np.stack([pts[:, 0] * cols / W, pts[:, 1] * rows / H], axis=1).astype(np.float32)
        hull = cv2.convexHull(cell).reshape(-1, 2)
        mask = np.zeros((rows, cols), np.uint8)
        cv2.fillConvexPoly(mask, np.round(hull).astype(np.int32), 1)
        grid += mask
    return float((grid > 0).mean()), grid


def calibrate_intrinsics(views: BoardViews, board: Board, model: str = FISHEYE, lens: str = "full") -> IntrinsicsResult:
    """Intrinsics of one camera from its board views (see the module); ``lens`` what of the lens is fitted
    (:data:`graph.calibrate.model.LENSES`)."""
    if model not in CAMERA_MODELS:
        raise InputError(f"unknown camera model {model!r} ({model_names()})")
    if lens not in LENSES:
        raise InputError(f"unknown lens {lens!r} ({', '.join(LENSES)})")
    keep, dropped = usable_views(views, board)
    theta, keep, more = opencv_start(views, board, model, keep)
    dropped.update(more)
    held = held_lens(theta, views.image_size, lens)
    if held is not None:
        theta = held[0]
    camera = camera_with(theta, model, views.image_size, views.name)
    poses, kept = [], []
    for i in keep:
        p = board_in_camera(camera, views.corners[i], board.object_points())
        if p is None:
            dropped[views.frames[i]] = "no pose of the board fits these corners"
        else:
            poses.append(p)
            kept.append(i)
    keep = kept
    rig = bundle.Rig([model], [theta], np.eye(3)[None], np.zeros((1, 3)),
                     np.stack([p[0] for p in poses]), np.stack([p[1] for p in poses]))
    while True:
        if len(keep) < MIN_VIEWS:
            raise InputError(f"too few board views to calibrate: {len(keep)} usable, at least {MIN_VIEWS} needed",
                             views.source or views.name)
        obs = observations([views], board, [keep], [0], [list(range(len(keep)))])
        sigma = bundle.noise_sigma(bundle.residuals(rig, obs, jacobians=False))
        settings = bundle.Settings(fixed_cams=frozenset({0}), free_intrinsics={0: held},
                                   huber_px=bundle.HUBER_SIGMAS * sigma)
        sol = bundle.solve(rig, obs, settings)
        sigma = bundle.noise_sigma(sol.residuals)
        rms = bundle.view_rms(sol.residuals, obs)
        bad = outlier_views(rms)
        rig = sol.rig
        if not bad.any():
            break
        for v in np.flatnonzero(bad):
            dropped[views.frames[keep[v]]] = f"outlier: {rms[v]:.2f} px RMS, median view {np.median(rms):.2f} px"
        good = ~bad
        keep = [k for k, g in zip(keep, good) if g]
        rig = bundle.Rig(rig.models, rig.intrinsics, rig.R_cam, rig.t_cam, rig.R_board[good], rig.t_board[good])
    # the kept views, polished by least squares: the estimate OpenCV's calibration makes, on views the
    # robust rounds have cleared (Huber's loss leaves the RMS a hair above its least-squares minimum)
    final = bundle.Settings(fixed_cams=frozenset({0}), free_intrinsics={0: held})
    sol = bundle.solve(rig, obs, final)
    rig = sol.rig
    sigma = bundle.noise_sigma(sol.residuals)
    rms = bundle.view_rms(sol.residuals, obs)
    theta = rig.intrinsics[0]
    # the boards' poses marginalised in numpy: GTSAM's marginals refuse the stiff rows of a held lens
    cov = bundle.camera_covariance(rig, obs, final, sigma)[0]
    cover, grid = coverage(views, keep)
    e = sol.residuals
    return IntrinsicsResult(
        camera=camera_with(theta, model, views.image_size, views.name),
        rms_px=float(np.sqrt((e * e).sum(axis=1).mean())), views_used=[views.frames[i] for i in keep],
        views_dropped=dropped, view_rms_px={views.frames[i]: float(r) for i, r in zip(keep, rms)},
        coverage=cover, covariance=cov, sigma_px=sigma, iterations=sol.iterations, seconds=sol.seconds,
        coverage_map=grid)
