"""Synthetic calibrations with a known truth: board views seen through a rig, and board images.

Board views (:func:`rig_views`): ``n_views`` poses of a board standing near the middle of the rig
(the point closest to every camera's optical axis), each turned to face a random direction and tilted
by up to 30 degrees; a camera sees a view when the board faces it (its normal within 70 degrees of
the direction to the camera) and every corner falls inside its image. Only views that two or more
cameras see are kept. Each corner gets Gaussian noise ``noise_px`` per coordinate; a share
``missing`` of corners is lost (NaN, as a partly hidden ChArUco board); ``bad_views`` views of
single cameras are wrong detections (the corners listed in reverse order, a real failure of
checkerboard detectors).

Board images (:func:`render_board`): the board printed on white, warped into a pinhole camera by the
homography of its pose, blurred a little and with grey noise; the true corners come with it.
"""

from __future__ import annotations

import math

import numpy as np

from graph.calibrate.board import CHARUCO, Board, charuco_board
from graph.calibrate.views import BoardViews
from graph.camera import FISHEYE, PINHOLE, Calibration, Camera

# the simulated lenses' distortion per model (a model not named here: none)
LENS_DISTORTION = {FISHEYE: (0.05, -0.01, 0.002, 0.0), PINHOLE: (-0.05, 0.01, 0.0, 0.0, 0.0)}


def rig_centre(calibration: Calibration) -> np.ndarray:
    """The point closest (least squares) to every camera's optical axis."""
    A = np.zeros((3, 3))
    b = np.zeros(3)
    for c in calibration.cameras:
        d = c.R[2]
        P = np.eye(3) - np.outer(d, d)
        A += P
        b += P @ c.center
    return np.linalg.solve(A, b)


def dome_rig(cameras: int = 6, radius: float = 3.0, height: float = 2.5, size: tuple[int, int] = (1920, 1080),
             focal_px: float = 1000.0, model: str = "fisheye") -> Calibration:
    """A lab's rig: ``cameras`` cameras (fisheye, or pinhole with a little radial distortion) evenly on
    a ring of ``radius`` m, ``height`` m up, all looking at the floor's centre (a board lying face up
    there is seen by every camera)."""

    cams = []
    for k in range(cameras):
        a = 2 * math.pi * k / cameras
        C = np.array([radius * math.cos(a), radius * math.sin(a), height])
        fwd = _unit(-C)
        right = _unit(np.cross(fwd, [0.0, 0.0, 1.0]))
        R = np.stack([right, np.cross(fwd, right), fwd])
        K = np.array([[focal_px, 0, size[0] / 2 + 3.0 * k], [0, focal_px, size[1] / 2 - 2.0 * k], [0, 0, 1]])
        dist = np.array(LENS_DISTORTION.get(model, ()), dtype=np.float64)
        cams.append(Camera(K=K, dist=dist, R=R, t=-R @ C, model=model, size=size, name=f"cam{k + 1}"))
    return Calibration(cams, source=f"dome of {cameras}")


def rig_views(calibration: Calibration, board: Board, n_views: int = 40, noise_px: float = 0.3,
              missing: float = 0.0, bad_views: int = 0, spread: float = 1.5, seed: int = 0,
              face_up: bool = False):
    """Board views of every camera of ``calibration`` (see the module) and the true board poses
    ``{frame: (R, t)}`` (board to world). ``face_up``: the board lies face up (tilted up to 30
    degrees) instead of standing, for rigs that look down (:func:`dome_rig`)."""
    rng = np.random.default_rng(seed)
    centre = rig_centre(calibration)
    obj = board.object_points()
    mid = obj.mean(axis=0)
    up = -np.mean([c.R[1] for c in calibration.cameras], axis=0)
    up /= np.linalg.norm(up)
    frames: list[str] = []
    truth: dict[str, tuple] = {}
    seen: list[dict[str, np.ndarray]] = [{} for _ in calibration.cameras]
    tries = 0
    while len(frames) < n_views and tries < 100 * n_views:
        tries += 1
        facing = _unit(np.cross(up, rng.normal(size=3)))  # a horizontal direction
        normal = _tilt(facing, up, rng.uniform(-30, 30), rng.uniform(-30, 30))
        if face_up:
            normal = _unit(up + math.tan(math.radians(rng.uniform(0, 30))) * facing)
        # board frame: z into the board (away from the cameras it faces), y down the rows
        z = -normal
        y = _unit(-up - np.dot(-up, z) * z)
        x = np.cross(y, z)
        R = np.stack([x, y, z], axis=1)
        spin = np.radians(rng.uniform(-20, 20))
        R = R @ np.array([[math.cos(spin), -math.sin(spin), 0], [math.sin(spin), math.cos(spin), 0], [0, 0, 1]])
        t = centre + rng.uniform(-spread, spread, 3) * np.array([1, 1, 0.3]) - R @ mid
        X = obj @ R.T + t
        views = {}
        for i, cam in enumerate(calibration.cameras):
            to_cam = _unit(cam.center - X.mean(axis=0))
            if np.dot(to_cam, normal) < math.cos(math.radians(70)):
                continue
            uv = cam.project(X)
            W, H = cam.size
            if not (np.isfinite(uv).all() and (uv[:, 0] >= 0).all() and (uv[:, 0] < W).all()
                    and (uv[:, 1] >= 0).all() and (uv[:, 1] < H).all()):
                continue
            views[i] = uv
        if len(views) < 2:
            continue
        name = str(len(frames) * 10)
        frames.append(name)
        truth[name] = (R, t)
        for i, uv in views.items():
            z = uv + rng.normal(0.0, noise_px, uv.shape)
            if missing > 0:
                z[rng.random(len(z)) < missing] = np.nan
            seen[i][name] = z
    pairs = [(i, f) for i, d in enumerate(seen) for f in d]
    for k in rng.choice(len(pairs), size=min(bad_views, len(pairs)), replace=False):
        i, f = pairs[k]
        seen[i][f] = seen[i][f][::-1].copy()
    out = []
    for i, cam in enumerate(calibration.cameras):
        names = [f for f in frames if f in seen[i]]
        corners = np.stack([seen[i][f] for f in names]) if names else np.zeros((0, board.n_corners, 2))
        out.append(BoardViews(cam.name or f"cam{i + 1}", cam.size, names, corners, f"simulated {cam.name}",
                              board.corner_grid, board.square))
    return out, truth


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


def _tilt(direction: np.ndarray, up: np.ndarray, pitch_deg: float, yaw_deg: float) -> np.ndarray:
    side = _unit(np.cross(up, direction))
    d = math.cos(math.radians(pitch_deg)) * direction + math.sin(math.radians(pitch_deg)) * up
    return _unit(math.cos(math.radians(yaw_deg)) * d + math.sin(math.radians(yaw_deg)) * side)


def board_image(board: Board, px_per_square: int = 40) -> tuple[np.ndarray, np.ndarray]:
    """The printed board (grey, uint8) and the homography ``Hb`` (3x3) from board metres (x, y) to its
    pixels."""
    if board.kind == CHARUCO:
        margin = px_per_square // 2
        W, H = board.cols * px_per_square + 2 * margin, board.rows * px_per_square + 2 * margin
        img = charuco_board(board).generateImage((W, H), marginSize=margin)
    else:
        margin = px_per_square
        sq_x, sq_y = board.cols + 1, board.rows + 1
        W, H = sq_x * px_per_square + 2 * margin, sq_y * px_per_square + 2 * margin
        img = np.full((H, W), 255, np.uint8)
        for r in range(sq_y):
            for c in range(sq_x):
                if (r + c) % 2 == 0:
                    y0, x0 = margin + r * px_per_square, margin + c * px_per_square
                    img[y0:y0 + px_per_square, x0:x0 + px_per_square] = 0
        margin += px_per_square  # the first inner corner is one square in
    s = px_per_square / board.square
    Hb = np.array([[s, 0, margin - 0.5], [0, s, margin - 0.5], [0, 0, 1.0]])  # pixel centres at integers
    return img, Hb


def render_board(camera: Camera, board: Board, R: np.ndarray, t: np.ndarray, noise: float = 2.0,
                 seed: int = 0, px_per_square: int = 40) -> tuple[np.ndarray, np.ndarray]:
    """A grey image (H, W) of the board at pose ``X_c = R p + t`` in a pinhole ``camera`` (no
    distortion), and its true corners (N, 2)."""
    import cv2

    img, Hb = board_image(board, px_per_square)
    K = camera.K
    Hc = K @ np.column_stack([R[:, 0], R[:, 1], t])  # board metres (x, y, 1) -> image pixels
    H = Hc @ np.linalg.inv(Hb)
    W, Hh = camera.size
    out = cv2.warpPerspective(img, H, (W, Hh), flags=cv2.INTER_LINEAR, borderValue=160)
    out = cv2.GaussianBlur(out, (3, 3), 0.7)
    rng = np.random.default_rng(seed)
    out = np.clip(out.astype(np.float64) + rng.normal(0, noise, out.shape), 0, 255).astype(np.uint8)
    obj = board.object_points()
    p = np.column_stack([obj[:, :2], np.ones(len(obj))]) @ Hc.T
    return out, p[:, :2] / p[:, 2:]
