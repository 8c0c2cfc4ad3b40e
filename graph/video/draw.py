"""Drawing the estimate over one camera's frame, in the frame's own ``yuv420p`` planes.

Each shape is drawn twice with OpenCV: into the luma plane at full resolution and into the two
chroma planes at half (coordinates and thickness halved), with the colour converted once by the
BT.601 video-range matrix that ffmpeg and OpenCV assume for untagged ``yuv420p``::

    Y = 16  + ( 65.481 R + 128.553 G +  24.966 B)        (R, G, B in [0, 1])
    U = 128 + (-37.797 R -  74.203 G + 112.0   B)
    V = 128 + (112.0   R -  93.786 G -  18.214 B)

so a frame is never converted to BGR and back (that would cost more than the encode).

What a camera's frame shows (:func:`draw_camera_frame`), only where the camera has an estimate:

* the DeepLabCut detections, one colour per marker, the disc's radius growing with the likelihood
  (a ring where the likelihood is under the solve's threshold: the solver did not use it);
* over them, the estimate reprojected into the camera as the skeleton's bones (left side blue,
  right side red, the midline yellow) with a white dot at each marker;
* a red cross on each detection the robust loss rejected as an outlier;
* the camera's name and the frame number.
"""

from __future__ import annotations

import colorsys
import functools
import math
from dataclasses import dataclass

import cv2
import numpy as np

from graph.video.codec import YuvFrame

SHIFT = 4  # OpenCV's fixed-point drawing: coordinates carry 4 fractional bits (1/16 px)
LEFT = (235, 150, 40)  # BGR
RIGHT = (60, 60, 235)
MIDDLE = (40, 215, 245)
OUTLIER = (0, 0, 255)
TEXT = (255, 255, 255)


@functools.lru_cache(maxsize=256)
def yuv(color: tuple[int, int, int]) -> tuple[int, int, int]:
    """A BGR colour as BT.601 video-range (Y, U, V) (module docstring)."""
    b, g, r = (c / 255.0 for c in color)
    y = 16 + 65.481 * r + 128.553 * g + 24.966 * b
    u = 128 - 37.797 * r - 74.203 * g + 112.0 * b
    v = 128 + 112.0 * r - 93.786 * g - 18.214 * b
    def byte(c: float) -> int:
        return int(round(min(max(c, 0), 255)))

    return byte(y), byte(u), byte(v)


def _fixed(p) -> tuple[int, int]:
    """Pixel coordinates as OpenCV's fixed point (``SHIFT`` fractional bits), rounded."""
    return math.floor(p[0] * (1 << SHIFT) + 0.5), math.floor(p[1] * (1 << SHIFT) + 0.5)


class Painter:
    """Shapes drawn into a :class:`YuvFrame`'s three planes (luma full size, chroma half)."""

    def __init__(self, frame: YuvFrame):
        self.frame = frame

    def line(self, p0, p1, color, thickness: int) -> None:
        Y, U, V = yuv(color)
        f = self.frame
        a, b = _fixed(p0), _fixed(p1)
        cv2.line(f.y, a, b, Y, thickness, cv2.LINE_AA, SHIFT)
        a, b = (a[0] >> 1, a[1] >> 1), (b[0] >> 1, b[1] >> 1)  # the same point at half the resolution
        tc = thickness // 2 + 1  # a chroma sample covers 2x2 pixels: a line thinner than 2 would miss some
        cv2.line(f.u, a, b, U, tc, cv2.LINE_8, SHIFT)
        cv2.line(f.v, a, b, V, tc, cv2.LINE_8, SHIFT)

    def circle(self, c, radius: float, color, thickness: int = -1) -> None:
        """A disc (``thickness`` -1) or a ring."""
        Y, U, V = yuv(color)
        f = self.frame
        a = _fixed(c)
        r = math.floor(radius * (1 << SHIFT) + 0.5)
        cv2.circle(f.y, a, r, Y, thickness, cv2.LINE_AA, SHIFT)
        tc = thickness if thickness < 0 else thickness // 2 + 1
        a = (a[0] >> 1, a[1] >> 1)
        cv2.circle(f.u, a, r >> 1, U, tc, cv2.LINE_8, SHIFT)
        cv2.circle(f.v, a, r >> 1, V, tc, cv2.LINE_8, SHIFT)

    def cross(self, c, size: float, color, thickness: int) -> None:
        x, y = c
        self.line((x - size, y - size), (x + size, y + size), color, thickness)
        self.line((x - size, y + size), (x + size, y - size), color, thickness)

    def text(self, origin, text: str, scale: float, color=TEXT) -> None:
        """Text with a dark outline (luma), neutral in the chroma planes."""
        f = self.frame
        th = max(1, int(round(scale * 2)))
        org = (int(origin[0]), int(origin[1]))
        cv2.putText(f.y, text, org, cv2.FONT_HERSHEY_SIMPLEX, scale, 16, th + 2 * max(1, th // 2), cv2.LINE_AA)
        cv2.putText(f.y, text, org, cv2.FONT_HERSHEY_SIMPLEX, scale, yuv(color)[0], th, cv2.LINE_AA)
        half = (org[0] // 2, org[1] // 2)
        for plane in (f.u, f.v):
            cv2.putText(plane, text, half, cv2.FONT_HERSHEY_SIMPLEX, scale / 2, 128, max(1, th), cv2.LINE_8)


def side_of(name: str) -> str:
    """'left', 'right' or 'middle' from a marker's name (``l_``/``r_`` prefixes, ``_l``/``_r``
    suffixes, or the words left and right)."""
    n = name.lower()
    if n.startswith(("l_", "left")) or n.endswith(("_l", "left")):
        return "left"
    if n.startswith(("r_", "right")) or n.endswith(("_r", "right")):
        return "right"
    return "middle"


def bone_color(a: str, b: str) -> tuple[int, int, int]:
    """Blue for a bone of the left side, red for the right, yellow for the midline."""
    sides = {side_of(a), side_of(b)}
    if sides == {"left"} or sides == {"left", "middle"}:
        return LEFT
    if sides == {"right"} or sides == {"right", "middle"}:
        return RIGHT
    return MIDDLE


def marker_colors(count: int) -> list[tuple[int, int, int]]:
    """``count`` distinguishable BGR colours, round the hue circle."""
    out = []
    for i in range(count):
        r, g, b = colorsys.hsv_to_rgb(i / max(count, 1), 0.85, 1.0)
        out.append((int(b * 255), int(g * 255), int(r * 255)))
    return out


@dataclass(frozen=True)
class Style:
    """Sizes in pixels for a frame ``width`` wide: a 2704-pixel GoPro frame gets 3-pixel bones."""

    bone: int
    joint: float
    detection: float  # the radius of a detection of likelihood 1
    text: float

    @classmethod
    def for_width(cls, width: int) -> "Style":
        unit = max(width / 1000.0, 0.5)
        return cls(bone=max(2, int(round(1.1 * unit))), joint=max(1.5, 1.3 * unit),
                   detection=max(2.5, 3.2 * unit), text=max(0.35, 0.45 * unit))


@dataclass
class CameraOverlay:
    """What is drawn on one camera's frames: arrays of the result for that camera, per its frame.

    ``reprojections`` (N, M, 2), ``detections`` (N, M, 2) or None, ``likelihood`` (N, M) or None,
    ``outlier`` (N, M) bool; ``bones`` as index pairs into the markers.
    """

    name: str
    markers: list[str]
    bones: list[tuple[int, int]]
    reprojections: np.ndarray
    detections: np.ndarray | None
    likelihood: np.ndarray | None
    outlier: np.ndarray
    threshold: float = 0.5
    # one of several individuals: its colour for every bone and detection, its name beside it, and
    # whether this overlay writes the camera's title (the first individual's does)
    tint: tuple[int, int, int] | None = None
    label: str = ""
    title: bool = True

    def __post_init__(self) -> None:
        if self.tint is not None:
            self.bone_colors = [self.tint] * len(self.bones)
            self.colors = [self.tint] * len(self.markers)
        else:
            self.bone_colors = [bone_color(self.markers[i], self.markers[j]) for i, j in self.bones]
            self.colors = marker_colors(len(self.markers))
        self.has_estimate = np.isfinite(self.reprojections).all(axis=-1).any(axis=-1)  # (N,)

    @property
    def frames(self) -> int:
        return self.reprojections.shape[0]


def draw_camera_frame(frame: YuvFrame, overlay: CameraOverlay, n: int, style: Style | None = None) -> bool:
    """Draw ``overlay``'s frame ``n`` into ``frame`` (module docstring). A frame without an estimate
    (or beyond the result) is left as it is; returns whether anything was drawn."""
    if not (0 <= n < overlay.frames) or not overlay.has_estimate[n]:
        return False
    style = style or Style.for_width(frame.width)
    paint = Painter(frame)
    uv_n = overlay.reprojections[n]
    ok = np.isfinite(uv_n).all(axis=-1).tolist()
    uv = uv_n.tolist()
    if overlay.detections is not None:
        z_n = overlay.detections[n]
        lik = (np.clip(overlay.likelihood[n], 0.0, 1.0) if overlay.likelihood is not None
               else np.ones(len(z_n))).tolist()
        seen = np.isfinite(z_n).all(axis=-1)
        z = z_n.tolist()
        for m in np.flatnonzero(seen).tolist():
            p = lik[m]
            radius = style.detection * (0.35 + 0.65 * p)
            used = p >= overlay.threshold
            paint.circle(z[m], radius + 1, (0, 0, 0), -1 if used else max(1, style.bone))
            paint.circle(z[m], radius, overlay.colors[m], -1 if used else max(1, style.bone - 1))
    for (i, j), color in zip(overlay.bones, overlay.bone_colors):
        if ok[i] and ok[j]:
            paint.line(uv[i], uv[j], color, style.bone)
    for m, visible in enumerate(ok):
        if visible:
            paint.circle(uv[m], style.joint, (255, 255, 255))
    if overlay.detections is not None:
        for m in np.flatnonzero(seen & overlay.outlier[n]).tolist():
            paint.cross(z[m], style.detection * 1.4, OUTLIER, style.bone)
    if overlay.label:
        top = min((m for m, visible in enumerate(ok) if visible), key=lambda m: uv[m][1])  # above the highest joint
        paint.text((uv[top][0] + style.detection, uv[top][1] - 2 * style.detection), overlay.label, style.text,
                   overlay.tint or TEXT)
    if overlay.title:
        paint.text((8 * style.text / 0.45, 30 * style.text / 0.45), f"{overlay.name}  frame {n}", style.text)
    return True
