"""A 3D view of the estimate, drawn headless with OpenCV: no OpenGL, no matplotlib per frame.

Two virtual pinhole cameras look at the run from the side of its path, ``ELEVATION_DEG`` above the
horizontal (``up`` is +z unless told otherwise: the cheetah model's world):

* the scene camera frames the whole path and every rig camera (a square with its name) over a
  ground grid of 1 m squares, with the path of the animal's centre for the last second;
* the close-up camera follows the animal's centre (a second of moving average), framed on the
  animal, over a grid of 25 cm squares; it fills the lower right of the view.

A virtual camera is world-to-camera ``X_c = R X + t`` with ``R``'s rows the camera's right, down and
forward axes; its pixels are ``u = K X_c / Z_c`` (``cv2.projectPoints`` without distortion). Its
focal length and centre are chosen after placing it: every point to be framed is projected with
``K = I`` and ``f, c`` scale that box into the picture with a margin. Bones are drawn far to near,
thicker when nearer, so the near legs cover the far ones.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import cv2
import numpy as np

from graph.video.draw import SHIFT, bone_color

ELEVATION_DEG = 25.0
BACKGROUND = (38, 32, 30)  # BGR
GRID = (80, 74, 70)
CAMERA = (200, 200, 200)
PATH = (120, 200, 120)
TRAIL_SECONDS = 1.0
INSET = 0.4  # the close-up's share of the view's width and height
MAX_GRID_LINES = 200  # a ground grid's lines each way, at most


@dataclass
class VirtualCamera:
    K: np.ndarray  # (3, 3)
    R: np.ndarray  # (3, 3) rows: right, down, forward
    t: np.ndarray  # (3,)

    def project(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixels (..., 2) and depths (...) of world points (..., 3) (NaN stays NaN)."""
        X = np.asarray(X, dtype=np.float64)
        flat = X.reshape(-1, 3)
        depth = flat @ self.R[2] + self.t[2]
        uv = np.full((len(flat), 2), np.nan)
        ok = np.isfinite(flat).all(axis=1) & (depth > 1e-6)
        if ok.any():
            rvec, _ = cv2.Rodrigues(self.R)
            pts, _ = cv2.projectPoints(flat[ok].reshape(-1, 1, 3), rvec, self.t, self.K, None)
            uv[ok] = pts.reshape(-1, 2)
        return uv.reshape(X.shape[:-1] + (2,)), depth.reshape(X.shape[:-1])


def look_from(centre: np.ndarray, forward: np.ndarray, up: np.ndarray,
              distance: float) -> tuple[np.ndarray, np.ndarray]:
    """``R, t`` of a camera ``distance`` behind ``centre`` along ``forward`` with ``up`` up."""
    f = forward / np.linalg.norm(forward)
    right = np.cross(f, up)
    right /= np.linalg.norm(right)
    down = np.cross(f, right)
    R = np.stack([right, down, f])
    eye = centre - distance * f
    return R, -R @ eye


def fit_intrinsics(R: np.ndarray, t: np.ndarray, points: np.ndarray, size: tuple[int, int],
                   margin: float = 0.08, bottom: float = 0.0) -> np.ndarray:
    """``K`` that frames ``points`` (K, 3) in an image of ``size`` (w, h) with the same focal length
    on both axes (module docstring), leaving the lowest ``bottom`` fraction of the height free."""
    w, h = size[0], size[1] * (1 - bottom)
    Xc = points @ R.T + t
    Xc = Xc[Xc[:, 2] > 1e-6]
    x, y = Xc[:, 0] / Xc[:, 2], Xc[:, 1] / Xc[:, 2]
    span_x, span_y = max(np.ptp(x), 1e-6), max(np.ptp(y), 1e-6)
    f = min(w * (1 - 2 * margin) / span_x, h * (1 - 2 * margin) / span_y)
    cx = w / 2 - f * (x.min() + x.max()) / 2
    cy = h / 2 - f * (y.min() + y.max()) / 2
    return np.array([[f, 0, cx], [0, f, cy], [0, 0, 1.0]])


def _moving_average(X: np.ndarray, window: int) -> np.ndarray:
    """Moving average over frames of (N, 3) with NaN gaps filled from the nearest estimate."""
    ok = np.isfinite(X).all(axis=1)
    if not ok.any():
        return np.zeros_like(X)
    idx = np.arange(len(X))
    filled = np.stack([np.interp(idx, idx[ok], X[ok, k]) for k in range(3)], axis=1)
    if window <= 1:
        return filled
    kernel = np.ones(window) / window
    pad = window // 2
    padded = np.pad(filled, ((pad, window - 1 - pad), (0, 0)), mode="edge")
    return np.stack([np.convolve(padded[:, k], kernel, mode="valid") for k in range(3)], axis=1)


class SceneView:
    """Renders frame ``n`` of a run as a BGR image of ``size`` (module docstring)."""

    def __init__(self, positions: np.ndarray, markers: list[str], bones: list[tuple[int, int]],
                 camera_centers: np.ndarray | None, camera_names: list[str], fps: float,
                 size: tuple[int, int] = (1280, 720), up: np.ndarray | None = None, title: str = "",
                 bone_colors: list[tuple[int, int, int]] | None = None):
        self.positions = np.asarray(positions, dtype=np.float64)
        self.markers, self.bones, self.fps, self.size, self.title = markers, bones, fps, size, title
        self.up = np.array([0.0, 0.0, 1.0]) if up is None else np.asarray(up, float) / np.linalg.norm(up)
        self.colors = bone_colors or [bone_color(markers[i], markers[j]) for i, j in bones]
        w, h = size
        self.unit = max(w / 1280.0, 0.4)
        finite = self.positions[np.isfinite(self.positions).all(axis=-1)]
        if not len(finite):
            finite = np.zeros((1, 3))
        self.centre_path = _moving_average(np.nanmean(np.where(np.isfinite(self.positions), self.positions, np.nan),
                                                      axis=1) if len(self.positions) else np.zeros((0, 3)),
                                           max(1, int(round(fps))))
        with np.errstate(invalid="ignore"):
            self.centre_now = np.nanmean(self.positions, axis=1) if len(self.positions) else np.zeros((0, 3))
        heights = finite @ self.up
        self.ground = float(np.percentile(heights, 1)) if len(heights) else 0.0
        # horizontal axes: e1 along the path's longest horizontal extent, e2 across it
        flat = finite - np.outer(finite @ self.up, self.up)
        centre = np.median(finite, axis=0)
        d = flat - flat.mean(axis=0)
        e1 = np.linalg.svd(d, full_matrices=False)[2][0] if len(d) > 2 and np.ptp(d) > 1e-9 else _any_perp(self.up)
        e1 = e1 - (e1 @ self.up) * self.up
        e1 /= np.linalg.norm(e1)
        self.e1, self.e2 = e1, np.cross(self.up, e1)
        el = np.radians(ELEVATION_DEG)
        self.forward = np.cos(el) * self.e2 - np.sin(el) * self.up  # look across the path, down a little
        cams = np.asarray(camera_centers, dtype=np.float64) if camera_centers is not None else np.zeros((0, 3))
        self.camera_centers, self.camera_names = cams, list(camera_names)
        framed = np.concatenate([finite[:: max(1, len(finite) // 2000)], cams[np.isfinite(cams).all(axis=1)]])
        radius = float(np.max(np.linalg.norm(framed - centre, axis=1))) + 1.0
        R, t = look_from(centre, self.forward, self.up, 3.0 * radius)
        # the close-up takes the lower right: the scene is framed above it, so no camera hides under it
        self.scene = VirtualCamera(fit_intrinsics(R, t, framed, size, bottom=INSET), R, t)
        # the close-up: framed on the animal's extent, a third of the view
        # (the median frame's: one frame with a wild marker must not zoom every frame out)
        with np.errstate(invalid="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            per_frame = np.nanmax(np.ptp(self.positions, axis=1), axis=-1) if len(self.positions) else np.array([])
            extent = float(np.nanmedian(per_frame)) if np.isfinite(per_frame).any() else 1.0
        self.animal = float(max(extent, 0.2)) if np.isfinite(extent) else 1.0
        self.inset = (int(w * INSET) // 2 * 2, int(h * INSET) // 2 * 2)
        self._inset_background = np.full((self.inset[1], self.inset[0], 3), BACKGROUND, np.uint8)
        self._background = self._draw_static()

    # ------------------------------------------------------------------------------- static layer

    def _grid_lines(self, centre: np.ndarray, half: float, step: float, pieces: int = 4) -> np.ndarray:
        """Segments (L, 2, 3) of a ground grid round ``centre``, each side of a square in ``pieces``
        (so a line crossing behind the camera is dropped in pieces, not drawn through infinity;
        the close-up's grid is all in front of its camera and takes whole lines)."""
        c = centre - (centre @ self.up - self.ground) * self.up
        o1, o2 = np.floor((c @ self.e1) / step) * step, np.floor((c @ self.e2) / step) * step
        base = c - (c @ self.e1) * self.e1 - (c @ self.e2) * self.e2
        step = max(step, 2 * half / MAX_GRID_LINES)  # a far-flung estimate must not ask for millions of lines
        ticks = np.arange(-half, half + step / 2, step)
        sub = np.linspace(-half, half, int(round(2 * half / step)) * pieces + 1 if pieces else 2)
        segs = []
        for a, b, oa, ob in ((self.e1, self.e2, o1, o2), (self.e2, self.e1, o2, o1)):
            for k in ticks:
                p = base + (oa + k) * a + (ob + sub)[:, None] * b
                segs.append(np.stack([p[:-1], p[1:]], axis=1))
        return np.concatenate(segs)

    def _draw_segments(self, img, cam: VirtualCamera, segs: np.ndarray, color, thickness: int) -> None:
        uv, depth = cam.project(segs)
        ok = np.isfinite(uv).all(axis=(-1, -2)) & (depth > 1e-3).all(axis=-1)
        lim = 4 * max(img.shape)
        ok &= (np.abs(uv) < lim).all(axis=(-1, -2))
        pts = np.round(uv[ok] * (1 << SHIFT)).astype(np.int32)
        if len(pts):
            cv2.polylines(img, list(pts), False, color, thickness, cv2.LINE_AA, SHIFT)

    def _draw_static(self) -> np.ndarray:
        w, h = self.size
        img = np.full((h, w, 3), BACKGROUND, np.uint8)
        finite = self.positions[np.isfinite(self.positions).all(axis=-1)]
        centre = np.median(finite, axis=0) if len(finite) else np.zeros(3)
        span = np.concatenate([finite, self.camera_centers]) if len(finite) else self.camera_centers
        plane = np.stack([self.e1, self.e2]).T
        half = float(np.ceil(np.max(np.abs((span - centre) @ plane)) + 1.0)) if len(span) else 5.0
        self._draw_segments(img, self.scene, self._grid_lines(centre, min(half, 60.0), 1.0), GRID, 1)
        uv, _ = self.scene.project(self.camera_centers)
        s = max(3, int(round(5 * self.unit)))
        for (x, y), name in zip(uv, self.camera_names):
            if np.isfinite(x) and np.isfinite(y):
                cv2.rectangle(img, (int(x) - s, int(y) - s), (int(x) + s, int(y) + s), CAMERA, -1)
                cv2.putText(img, name, (int(x) + 2 * s, int(y) + s), cv2.FONT_HERSHEY_SIMPLEX,
                            0.5 * self.unit, CAMERA, 1, cv2.LINE_AA)
        if self.title:
            cv2.putText(img, self.title, (int(12 * self.unit), int(28 * self.unit)), cv2.FONT_HERSHEY_SIMPLEX,
                        0.6 * self.unit, (230, 230, 230), max(1, int(self.unit)), cv2.LINE_AA)
        return img

    # ------------------------------------------------------------------------------------ a frame

    def _draw_skeleton(self, img, cam: VirtualCamera, X: np.ndarray, scale: float) -> None:
        uv, depth = cam.project(X)
        ok = np.isfinite(uv).all(axis=-1)
        order = []
        for k, (i, j) in enumerate(self.bones):
            if ok[i] and ok[j]:
                order.append((-(depth[i] + depth[j]) / 2, k))
        near = float(np.nanmin(depth[ok])) if ok.any() else 1.0
        for _, k in sorted(order):
            i, j = self.bones[k]
            d = (depth[i] + depth[j]) / 2
            th = max(1, int(round(scale * near / d)))
            cv2.line(img, _fx(uv[i]), _fx(uv[j]), self.colors[k], th, cv2.LINE_AA, SHIFT)
        for m in np.flatnonzero(ok):
            cv2.circle(img, _fx(uv[m]), int(max(1.5, scale * 0.6) * (1 << SHIFT)), (245, 245, 245), -1,
                       cv2.LINE_AA, SHIFT)

    def render(self, n: int) -> np.ndarray:
        """Frame ``n`` (BGR, ``size``); beyond the run or without an estimate, the scene alone."""
        img = self._background.copy()
        w, h = self.size
        inside = 0 <= n < len(self.positions)
        X = self.positions[n] if inside else np.full((len(self.markers), 3), np.nan)
        if inside:
            lo = max(0, n - int(round(TRAIL_SECONDS * self.fps)))
            trail = self.centre_now[lo:n + 1]
            trail = trail[np.isfinite(trail).all(axis=1)]
            if len(trail) > 1:
                uv, _ = self.scene.project(trail)
                cv2.polylines(img, [np.round(uv * (1 << SHIFT)).astype(np.int32)], False, PATH,
                              max(1, int(round(self.unit))), cv2.LINE_AA, SHIFT)
        self._draw_skeleton(img, self.scene, X, 2.0 * self.unit)
        # the close-up, in the lower right
        iw, ih = self.inset
        sub = self._inset_background.copy()
        follow = self.centre_path[min(max(n, 0), len(self.centre_path) - 1)] if len(self.centre_path) else np.zeros(3)
        R, t = look_from(follow, self.forward, self.up, 4.0 * self.animal)
        box = follow + np.array([[a, b, c] for a in (-1, 1) for b in (-1, 1) for c in (-1, 1)]) * (0.6 * self.animal)
        close = VirtualCamera(fit_intrinsics(R, t, box, (iw, ih), margin=0.02), R, t)
        self._draw_segments(sub, close, self._grid_lines(follow, 2.0 * self.animal, 0.25, pieces=0), GRID, 1)
        self._draw_skeleton(sub, close, X, 3.0 * self.unit)
        cv2.rectangle(sub, (0, 0), (iw - 1, ih - 1), (110, 110, 110), 1)
        img[h - ih:, w - iw:] = sub
        label = f"frame {n}  t = {n / self.fps:.3f} s" if inside else f"frame {n}"
        cv2.putText(img, label, (int(12 * self.unit), h - int(14 * self.unit)), cv2.FONT_HERSHEY_SIMPLEX,
                    0.55 * self.unit, (230, 230, 230), max(1, int(self.unit)), cv2.LINE_AA)
        return img


def _fx(p) -> tuple[int, int]:
    return int(round(p[0] * (1 << SHIFT))), int(round(p[1] * (1 << SHIFT)))


def _any_perp(v: np.ndarray) -> np.ndarray:
    a = np.array([1.0, 0.0, 0.0]) if abs(v[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    return a - (a @ v) * v
