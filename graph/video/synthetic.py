"""Footage of a simulated run: what each camera of the rig would film of the simulated animal.

The background is the ground plane seen through the camera's own model (fisheye or pinhole): every
pixel's ray (``graph.camera.undistort_points``, at a quarter of the resolution and interpolated) is
cut with the ground ``z = ground_z`` at ``X = C + s d`` (``C`` the camera centre, ``d = R^T (x, y, 1)``,
``s = (ground_z - C_z) / d_z > 0``) and coloured from a tiling texture of earth tones at 2 cm a texel
(several octaves of smoothed noise), fading to a haze colour with distance (no aliasing near the
horizon); rays that miss the ground see a sky gradient. A mild sensor noise (from a small bank,
so it changes every frame) keeps the codec's work realistic.

The animal is drawn from its true markers at that camera's frames (its own clock): each bone a
thick line, ``width_m * f / depth`` pixels wide (torso, neck, legs, tail and head of their own
widths), far bones first, over its shadow straight below on the ground. The footage goes through
:class:`graph.video.codec.FrameWriter` (H.264, ``yuv420p``) at a camera's bitrate (a GoPro's 60 Mbit/s at
2704x1520 and 120 fps: ``CAMERA_BITS_PER_PIXEL``), so decoding it costs what real footage costs.
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable

import cv2
import numpy as np

from graph.camera import Camera, undistort_points
from graph.video.codec import FrameWriter

TEXEL_M = 0.02
TEXTURE_PX = 1024  # the texture tiles every 20.48 m
HAZE_FROM_M, HAZE_TO_M = 8.0, 40.0
SKY_TOP, SKY_LOW = (235, 200, 150), (245, 235, 220)  # BGR
HAZE = (150, 175, 185)
FUR, FUR_EDGE = (70, 150, 215), (30, 60, 95)
NOISE_FRAMES = 4
SENSOR_NOISE = 12  # the noise's range in grey levels (uniform, sd 3.5): footage of a real camera's bitrate
CAMERA_BITS_PER_PIXEL = 0.12  # a GoPro's 60 Mbit/s at 2704x1520 and 120 fps, at any size and rate


def _width_m(a: str, b: str) -> float:
    """How wide a bone between markers ``a`` and ``b`` is drawn (metres)."""
    names = (a + " " + b).lower()
    if "tail" in names and "tail_base" not in (a, b):
        return 0.05
    if any(k in names for k in ("spine", "tail_base", "neck_base")) and not any(
            k in names for k in ("shoulder", "hip")):
        return 0.2
    if any(k in names for k in ("eye", "nose", "head")):
        return 0.07
    if any(k in names for k in ("shoulder", "hip")):
        return 0.1
    return 0.05


def ground_texture(seed: int = 0) -> np.ndarray:
    """A tiling (TEXTURE_PX square) BGR texture of dry ground: octaves of smoothed noise."""
    rng = np.random.default_rng(seed)
    acc = np.zeros((TEXTURE_PX, TEXTURE_PX), np.float32)
    for cells, weight in ((8, 0.45), (32, 0.25), (128, 0.15), (512, 0.15)):
        small = rng.standard_normal((cells, cells)).astype(np.float32)
        tiled = np.tile(small, (3, 3))  # interpolate across the tile's edges so it wraps seamlessly
        big = cv2.resize(tiled, (3 * TEXTURE_PX, 3 * TEXTURE_PX), interpolation=cv2.INTER_CUBIC)
        acc += weight * big[TEXTURE_PX:2 * TEXTURE_PX, TEXTURE_PX:2 * TEXTURE_PX]
    acc = (acc - acc.mean()) / (acc.std() + 1e-9)
    t = np.clip(0.5 + 0.22 * acc, 0, 1)[..., None]
    dark, light = np.array([60, 95, 120], np.float32), np.array([135, 180, 205], np.float32)
    return (dark + t * (light - dark)).astype(np.uint8)


def camera_background(camera: Camera, ground_z: float, texture: np.ndarray) -> np.ndarray:
    """The still picture of the ground and sky that ``camera`` films (module docstring), BGR."""
    W, H = camera.size
    step = 4
    us, vs = np.meshgrid(np.arange(0, W + step, step, dtype=np.float64), np.arange(0, H + step, step, dtype=np.float64))
    xy = undistort_points(camera, np.stack([us, vs], axis=-1))
    d = np.concatenate([xy, np.ones(xy.shape[:-1] + (1,))], axis=-1) @ camera.R  # R^T d_c, row-wise
    C = camera.center
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (ground_z - C[2]) / d[..., 2]
    hit = np.isfinite(s) & (s > 0)
    s = np.where(hit, s, 0.0)

    def up(a):
        a = np.where(np.isfinite(a), a, 0.0).astype(np.float32)
        return cv2.resize(a, (us.shape[1] * step, us.shape[0] * step), interpolation=cv2.INTER_LINEAR)[:H, :W]

    map_x = up((C[0] + s * d[..., 0]) / TEXEL_M) % TEXTURE_PX
    map_y = up((C[1] + s * d[..., 1]) / TEXEL_M) % TEXTURE_PX
    ground = cv2.remap(texture, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)
    dist = np.where(hit, s * np.linalg.norm(d, axis=-1), HAZE_TO_M)
    haze = np.clip((up(dist) - HAZE_FROM_M) / (HAZE_TO_M - HAZE_FROM_M), 0, 1)
    out = cv2.blendLinear(ground, np.full_like(ground, HAZE), np.ascontiguousarray(1 - haze), haze)
    rows = np.linspace(0, 1, H, dtype=np.float32)[:, None, None]
    sky = (np.array(SKY_TOP, np.float32) * (1 - rows) + np.array(SKY_LOW, np.float32) * rows).astype(np.uint8)
    cv2.copyTo(np.ascontiguousarray(np.broadcast_to(sky, (H, W, 3))), (up(~hit) > 0.5).astype(np.uint8), out)
    return out


class AnimalPainter:
    """Draws the animal (and its shadow) of one frame into a camera's picture."""

    def __init__(self, camera: Camera, markers: list[str], bones: list[tuple[str, str]], ground_z: float):
        self.camera, self.ground_z = camera, ground_z
        index = {m: i for i, m in enumerate(markers)}
        self.bones = [(index[a], index[b], _width_m(a, b)) for a, b in bones if a in index and b in index]
        self.head = [index[m] for m in ("l_eye", "r_eye", "nose") if m in index]

    def draw(self, img: np.ndarray, X: np.ndarray) -> None:
        cam = self.camera
        f = float(cam.K[0, 0])
        with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
            uv = cam.project(X)
            shadow = X.copy()
            shadow[:, 2] = self.ground_z
            suv = cam.project(shadow)
        depth = X @ cam.R[2] + cam.t[2]
        self._shadow(img, suv, f, shadow @ cam.R[2] + cam.t[2])
        order = sorted(self.bones, key=lambda b: -(depth[b[0]] + depth[b[1]]))
        for i, j, w in order:
            if not (np.isfinite(uv[[i, j]]).all() and depth[i] > 0.05 and depth[j] > 0.05):
                continue
            px = max(2, int(round(w * f / ((depth[i] + depth[j]) / 2))))
            p, q = _pt(uv[i]), _pt(uv[j])
            cv2.line(img, p, q, FUR_EDGE, px + 2, cv2.LINE_AA)
            cv2.line(img, p, q, FUR, px, cv2.LINE_AA)
        if self.head and np.isfinite(uv[self.head]).all():
            c = uv[self.head].mean(axis=0)
            r = max(2, int(round(0.06 * f / max(float(depth[self.head].mean()), 0.05))))
            cv2.circle(img, _pt(c), r + 1, FUR_EDGE, -1, cv2.LINE_AA)
            cv2.circle(img, _pt(c), r, FUR, -1, cv2.LINE_AA)

    def _shadow(self, img: np.ndarray, suv: np.ndarray, f: float, depth: np.ndarray) -> None:
        ok = np.isfinite(suv).all(axis=1) & (depth > 0.05)
        if not ok.any():
            return
        H, W = img.shape[:2]
        lo = np.clip(np.floor(suv[ok].min(0)) - 60, 0, [W, H]).astype(int)
        hi = np.clip(np.ceil(suv[ok].max(0)) + 60, 0, [W, H]).astype(int)
        if (hi <= lo).any():
            return
        mask = np.zeros((hi[1] - lo[1], hi[0] - lo[0]), np.uint8)
        for i, j, w in self.bones:
            if ok[i] and ok[j]:
                px = max(2, int(round(w * f / ((depth[i] + depth[j]) / 2))))
                cv2.line(mask, _pt(suv[i] - lo), _pt(suv[j] - lo), 255, px, cv2.LINE_AA)
        roi = img[lo[1]:hi[1], lo[0]:hi[0]]
        shade = 1.0 - 0.35 * (cv2.GaussianBlur(mask, (0, 0), 3).astype(np.float32) / 255.0)
        roi[:] = (roi.astype(np.float32) * shade[..., None]).astype(np.uint8)


def _pt(p) -> tuple[int, int]:
    return int(np.clip(round(float(p[0])), -100000, 100000)), int(np.clip(round(float(p[1])), -100000, 100000))


def write_simulated_videos(run, out: str | Path, names: list[str] | None = None,
                           progress: Callable[[int, int], None] | None = None, seed: int = 0) -> list[Path]:
    """Render ``run`` (a :class:`graph.simulate.SimulatedRun`) as one H.264 MP4 per camera in
    ``out`` (``<camera name>.mp4``, or ``names``), each camera on its own clock; returns the paths."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    cams = run.calibration.cameras
    names = names or [f"{n}.mp4" for n in run.calibration.names]
    texture = ground_texture(seed)
    rng = np.random.default_rng(seed + 1)
    paths = []
    total = len(cams) * run.frames
    for c, cam in enumerate(cams):
        W, H = cam.size
        if W <= 0 or H <= 0:
            raise ValueError(f"camera {cam.name or c + 1} has no image size in the calibration")
        if W % 2 or H % 2:
            raise ValueError(f"camera {cam.name or c + 1}: H.264 in yuv420p needs even image sizes, not {W}x{H}")
        background = camera_background(cam, run.stage.ground_z, texture)
        noise = [rng.integers(0, SENSOR_NOISE + 1, size=(H, W, 3), dtype=np.uint8) for _ in range(NOISE_FRAMES)]
        centre = np.full((H, W, 3), SENSOR_NOISE // 2, dtype=np.uint8)  # the noise's mean, taken off again
        painter = AnimalPainter(cam, run.markers, run.bones, run.stage.ground_z)
        X = run.camera_positions(c)
        path = out / names[c]
        bitrate = CAMERA_BITS_PER_PIXEL * W * H * run.fps
        with FrameWriter(path, W, H, run.fps, bitrate=bitrate, preset="veryfast", threads=2) as writer:
            for n in range(run.frames):
                img = background.copy()
                painter.draw(img, X[n])
                cv2.add(img, noise[n % NOISE_FRAMES], dst=img)
                cv2.subtract(img, centre, dst=img)
                writer.write(img)
                if progress is not None:
                    progress(c * run.frames + n + 1, total)
        paths.append(path)
    return paths


def scaled_rig(calibration, factor: float):
    """The same rig filming at ``factor`` times the resolution: each camera's ``fx, fy, cx, cy``
    scaled (distortion acts on normalised coordinates and stays), sizes rounded to even pixels.
    Small footage for tests and quick looks."""
    import copy

    from graph.camera import Calibration

    cams = []
    for cam in calibration.cameras:
        c = copy.deepcopy(cam)
        c.K = cam.K.copy()
        c.K[:2] *= factor
        c.size = (int(round(cam.size[0] * factor)) // 2 * 2, int(round(cam.size[1] * factor)) // 2 * 2)
        cams.append(c)
    return Calibration(cams, source=f"{calibration.source} x{factor:g}", metadata=dict(calibration.metadata))
