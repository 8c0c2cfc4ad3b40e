"""Labelled videos of a solved run: each camera's own footage with the estimate drawn on it, a 3D
view, and optionally one grid of them all, written in one streaming pass over the videos.

Frames and clocks. The result holds, per camera, the reprojections, detections and outlier flags of
that camera's own frames (``Result.reprojections[c, m]`` is camera c's frame m), so each camera's
video is drawn frame by frame as it is. The 3D view is on the reference clock (camera 1's, the
result's frame n). The cameras' clocks may differ: camera c's frame m was taken at reference time
``m + tau_c`` (``report.time_offsets_frames``, when the solve estimated or was given them), so
the grid's frame n shows camera c's frame ``m = n - round(tau_c)`` (the one nearest in time) beside
the 3D view of frame n; a camera with no such frame shows a blank tile.

Memory. Every video is decoded and encoded by ffmpeg processes one frame at a time
(:mod:`graph.video.codec`), and only ``CAMERAS_AT_ONCE`` cameras at a time (an ffmpeg decoder and
encoder of 2704x1520 frames hold about 300 MB between them, whatever the length); the grid is drawn
in a second pass from each camera's tiles, kept as small temporary videos, one tile at a time.
Nothing grows with the length of the video but the result's own arrays.

Output (in ``out``): ``<video stem>_labeled.mp4`` per camera at the input's size and rate,
``3d.mp4`` (the 3D view, ``SCENE_SIZE``) and, with ``combined``, ``combined.mp4``; the same number
of frames as the input (or as ``frames`` asks).
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import tempfile
import time
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import cv2
import numpy as np

from graph.errors import InputError
from graph.types import Result, together
from graph.video.codec import FrameReader, FrameWriter, VideoInfo, YuvFrame, probe, read_frame
from graph.video.draw import CameraOverlay, Painter, Style, draw_camera_frame, marker_colors
from graph.video.scene import SceneView

SCENE_SIZE = (1280, 720)
GRID_WIDTH = 1920  # the combined grid's width at most
TILE_WIDTH = 640  # a tile's width at most
FPS_TOLERANCE = 0.01  # relative difference of frame rates that gets a warning
CAMERAS_AT_ONCE = 2  # cameras decoded and encoded together (bench/RESULTS.md: memory against speed)
TILE_CRF = 18  # the grid's tiles, kept between the passes as small H.264 videos

Progress = Callable[[int, int], None]  # (frames done, frames in all)


@dataclass
class RenderedVideos:
    """What :func:`render_videos` wrote."""

    cameras: list[Path]
    scene: Path | None
    combined: Path | None
    frames: int
    fps: float
    first_frame: int
    seconds: float
    camera_frames_per_second: float
    offsets_frames: list[int] = field(default_factory=list)

    @property
    def paths(self) -> list[Path]:
        return [*self.cameras, *(p for p in (self.scene, self.combined) if p is not None)]


def camera_overlays(result: Result) -> list[CameraOverlay]:
    """One :class:`CameraOverlay` per camera of ``result``."""
    index = {m: i for i, m in enumerate(result.markers)}
    bones = [(index[a], index[b]) for a, b in result.bones if a in index and b in index]
    out = []
    for c, name in enumerate(result.camera_names):
        out.append(CameraOverlay(
            name=name, markers=list(result.markers), bones=bones,
            reprojections=np.asarray(result.reprojections[c], dtype=np.float64),
            detections=None if result.detections is None else np.asarray(result.detections[c], dtype=np.float64),
            likelihood=None if result.likelihood is None else np.asarray(result.likelihood[c], dtype=np.float64),
            outlier=np.asarray(result.outlier[c], dtype=bool),
            threshold=float(result.options.likelihood_threshold)))
    return out


def group_overlays(group: Sequence[tuple[str, Result]]):
    """Each camera's overlays (one an individual, each with its own colour when several) and the 3D
    view's parts: every individual's markers side by side (``positions`` (N, sum M, 3), ``markers``
    named ``<individual> <marker>``, ``bones`` into them and their colours; None: by side)."""
    if len(group) == 1:
        r = group[0][1]
        index = {m: i for i, m in enumerate(r.markers)}
        pairs = [(index[x], index[y]) for x, y in r.bones if x in index and y in index]
        return [[o] for o in camera_overlays(r)], (r.positions, list(r.markers), pairs, None)
    tints = marker_colors(len(group))
    per_camera: list[list[CameraOverlay]] = [[] for _ in group[0][1].camera_names]
    for k, (name, r) in enumerate(group):
        for c, o in enumerate(camera_overlays(r)):
            per_camera[c].append(dataclasses.replace(o, tint=tints[k], label=name, title=k == 0))
    joined = together(group)
    index = {m: i for i, m in enumerate(joined.markers)}
    bones = [(index[x], index[y]) for x, y in joined.bones if x in index and y in index]
    owner = np.repeat(np.arange(len(group)), [len(r.markers) for _, r in group])  # each joined marker's individual
    colors = [tints[int(owner[i])] for i, _ in bones]
    return per_camera, (np.asarray(joined.positions, dtype=np.float64), list(joined.markers), bones, colors)


def frame_offsets(result: Result) -> list[int]:
    """Each camera's clock offset in whole frames, ``round(tau_c)`` (module docstring); zeros when
    the result has none."""
    tau = result.report.time_offsets_frames
    C = len(result.camera_names)
    if not tau or len(tau) != C:
        return [0] * C
    return [int(round(float(t))) if t is not None and math.isfinite(float(t)) else 0 for t in tau]


def parse_frames(text: str | None, frames: int) -> tuple[int, int]:
    """``A:B`` (Python's slice: frames A to B-1; either may be left out) within ``frames``."""
    if text is None:
        return 0, frames
    parts = text.split(":")
    try:
        if len(parts) != 2:
            raise ValueError
        a = int(parts[0]) if parts[0].strip() else 0
        b = int(parts[1]) if parts[1].strip() else frames
    except ValueError:
        raise InputError(f"--frames takes A:B (frames A to B-1), not {text!r}") from None
    if a < 0 or b > frames or a >= b:
        raise InputError(f"--frames {text}: the videos have frames 0 to {frames - 1}; give 0 <= A < B <= {frames}")
    return a, b


def check_videos(result: Result, videos: Sequence[str | Path]) -> list[VideoInfo]:
    """Probe ``videos`` and check they fit ``result``: one per camera, each with the result's
    number of frames (one-line :class:`InputError` otherwise)."""
    C = len(result.camera_names)
    if len(videos) != C:
        raise InputError(f"{len(videos)} video(s) given for a result of {C} cameras "
                         f"({', '.join(result.camera_names)}): one per camera, in that order")
    infos = [probe(v) for v in videos]
    N = result.positions.shape[0]
    for info in infos:
        if info.frames != N:
            raise InputError(f"has {info.frames} frames but the result has {N} (one estimate per video frame: "
                             "give the videos the keypoints came from)", info.path)
        if abs(info.fps - result.fps) > FPS_TOLERANCE * result.fps:
            warnings.warn(f"{Path(info.path).name}: {info.fps:g} fps, the result was solved at {result.fps:g} fps; "
                          "the output keeps the video's rate", UserWarning, stacklevel=3)
    return infos


def output_names(infos: list[VideoInfo]) -> list[str]:
    """``<stem>_labeled.mp4`` per video; numbered when two videos share a stem."""
    stems = [Path(i.path).stem for i in infos]
    if len(set(stems)) < len(stems):
        stems = [f"{c + 1}_{s}" for c, s in enumerate(stems)]
    return [f"{s}_labeled.mp4" for s in stems]


class Grid:
    """The combined view: C camera tiles and the 3D view in ``cols x rows`` equal tiles."""

    def __init__(self, infos: list[VideoInfo], tiles: int):
        self.cols = math.ceil(math.sqrt(tiles))
        self.rows = math.ceil(tiles / self.cols)
        w0, h0 = infos[0].even_size
        tw = min(TILE_WIDTH, GRID_WIDTH // self.cols) // 2 * 2
        th = max(2, int(round(tw * h0 / w0)) // 2 * 2)
        self.tile = (tw, th)
        self.fits = [self._fit(*i.even_size) for i in infos]
        self.width, self.height = tw * self.cols, th * self.rows

    def _fit(self, w: int, h: int) -> tuple[int, int]:
        tw, th = self.tile
        s = min(tw / w, th / h)
        return max(2, int(w * s) // 2 * 2), max(2, int(h * s) // 2 * 2)

    def shrink(self, frame: YuvFrame, c: int) -> YuvFrame:
        """Camera ``c``'s frame at its tile's size (area averaging)."""
        w, h = self.fits[c]
        out = YuvFrame(w, h)
        cv2.resize(frame.y, (w, h), dst=out.y, interpolation=cv2.INTER_AREA)
        cv2.resize(frame.u, (w // 2, h // 2), dst=out.u, interpolation=cv2.INTER_AREA)
        cv2.resize(frame.v, (w // 2, h // 2), dst=out.v, interpolation=cv2.INTER_AREA)
        return out

    def blank(self) -> YuvFrame:
        f = YuvFrame(self.width, self.height)
        f.y[:] = 16
        f.u[:] = 128
        f.v[:] = 128
        return f

    def place(self, canvas: YuvFrame, k: int, tile: YuvFrame) -> None:
        """Put ``tile`` centred in slot ``k`` (row-major)."""
        tw, th = self.tile
        x0 = (k % self.cols) * tw + (tw - tile.width) // 2 // 2 * 2
        y0 = (k // self.cols) * th + (th - tile.height) // 2 // 2 * 2
        canvas.y[y0:y0 + tile.height, x0:x0 + tile.width] = tile.y
        canvas.u[y0 // 2:(y0 + tile.height) // 2, x0 // 2:(x0 + tile.width) // 2] = tile.u
        canvas.v[y0 // 2:(y0 + tile.height) // 2, x0 // 2:(x0 + tile.width) // 2] = tile.v

    def label(self, canvas: YuvFrame, k: int, text: str) -> None:
        tw, th = self.tile
        Painter(canvas).text(((k % self.cols) * tw + 10, (k // self.cols) * th + th // 2), text, 0.5)


def render_videos(result: Result | Sequence[tuple[str, Result]], videos: Sequence[str | Path], out: str | Path,
                  frames: str | None = None, combined: bool = False, up: np.ndarray | None = None,
                  progress: Progress | None = None, scene_size: tuple[int, int] = SCENE_SIZE,
                  cameras_at_once: int = CAMERAS_AT_ONCE) -> RenderedVideos:
    """Write the labelled videos of ``result`` over ``videos`` (one per camera, in the result's
    order) into the folder ``out`` (module docstring). ``frames`` is ``"A:B"`` (default: all).
    ``result`` may be several individuals solved together, ``(name, result)`` pairs of the same
    cameras and frames: each is drawn in a colour of its own (bones, detections, its name beside it),
    and the 3D view holds them all.

    Two passes. First the cameras, ``cameras_at_once`` at a time (each a decoder and an encoder of
    full frames, some 300 MB at 2704x1520: this bounds the memory), each frame drawn and written to
    its labelled video and, for the grid, shrunk to a tile and written to a small temporary video.
    Then the 3D view and the grid, frame by frame on the reference clock, from the tiles' videos.
    ``progress(done, total)`` counts camera-frames and 3D frames."""
    t0 = time.perf_counter()
    individuals = [("", result)] if isinstance(result, Result) else list(result)
    first = individuals[0][1]
    infos = check_videos(first, videos)
    for name, r in individuals[1:]:
        if r.camera_names != first.camera_names or r.positions.shape[0] != first.positions.shape[0]:
            raise InputError(f"individual {name!r} was solved on other cameras or frames than "
                             f"{individuals[0][0]!r}")
    a, b = parse_frames(frames, infos[0].frames)
    count = b - a
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    overlays, scene_parts = group_overlays(individuals)
    offsets = frame_offsets(first)
    fps = infos[0].fps
    C = len(infos)
    title = (f"{first.method} estimate, {first.skeleton} skeleton" if len(individuals) == 1 else
             f"{first.method} estimate, {len(individuals)} individuals: {', '.join(n for n, _ in individuals)}")

    def scene_of(size):
        positions, markers, bones, colors = scene_parts
        return SceneView(positions, markers, bones, first.camera_centers, list(first.camera_names), first.fps,
                         size=size, up=up, title=title, bone_colors=colors)

    grid = Grid(infos, C + 1) if combined else None
    paths = [out / name for name in output_names(infos)]
    scene_path = out / "3d.mp4"
    combined_path = out / "combined.mp4"
    grid_path = combined_path if grid else None
    total, done = (C + 1) * count, 0

    def tick():
        nonlocal done
        done += 1
        if progress is not None:
            progress(done, total)

    with tempfile.TemporaryDirectory(prefix=".tiles-", dir=out) as tmp:
        tile_paths = [Path(tmp) / f"{c}.mp4" for c in range(C)]
        # pass 1: the cameras' labelled videos (and their tiles)
        step = max(1, int(cameras_at_once))
        for group in [list(range(C))[i:i + step] for i in range(0, C, step)]:
            with contextlib.ExitStack() as stack:
                readers = {c: stack.enter_context(FrameReader(infos[c], start=a, count=count)) for c in group}
                writers = {c: stack.enter_context(FrameWriter(paths[c], *infos[c].even_size, fps)) for c in group}
                tiles = {c: stack.enter_context(FrameWriter(tile_paths[c], *grid.fits[c], fps, crf=TILE_CRF))
                         for c in group} if grid else {}
                styles = {c: Style.for_width(infos[c].even_size[0]) for c in group}
                for i in range(count):
                    for c in group:
                        frame = readers[c].read()
                        if frame is None:
                            raise InputError(f"ended after {readers[c].frames_read} of {count} frames (from frame "
                                             f"{a}): the file is shorter than its container says", infos[c].path)
                        for overlay in overlays[c]:
                            draw_camera_frame(frame, overlay, a + i, styles[c])
                        writers[c].write(frame)
                        if grid:
                            tiles[c].write(grid.shrink(frame, c))
                        tick()
        # pass 2: the 3D view and the grid, on the reference clock
        scene = scene_of(scene_size)
        grid_scene = scene_of(grid.tile) if grid else None
        with contextlib.ExitStack() as stack:
            scene_writer = stack.enter_context(FrameWriter(scene_path, *scene_size, fps))
            if grid:
                grid_writer = stack.enter_context(FrameWriter(combined_path, grid.width, grid.height, fps))
                streams = [stack.enter_context(TileStream(p, a, count)) for p in tile_paths]
            for n in range(a, b):
                scene_writer.write(YuvFrame.from_bgr(scene.render(n)))
                if grid and grid_scene is not None:
                    canvas = grid.blank()
                    for c in range(C):
                        m = n - offsets[c]  # camera c's frame nearest in time to reference frame n
                        tile = streams[c].frame(m)
                        if tile is not None:
                            grid.place(canvas, c, tile)
                        else:
                            grid.label(canvas, c, f"{first.camera_names[c]}: no frame {m}")
                    grid.place(canvas, C, YuvFrame.from_bgr(grid_scene.render(n)))
                    grid_writer.write(canvas)
                tick()
    seconds = time.perf_counter() - t0
    return RenderedVideos(cameras=paths, scene=scene_path, combined=grid_path, frames=count, fps=fps,
                          first_frame=a, seconds=seconds, camera_frames_per_second=C * count / max(seconds, 1e-9),
                          offsets_frames=offsets)


class TileStream:
    """A camera's tiles (frames ``first .. first+count-1``) read forward on demand: ``frame(m)``
    is tile m, or None outside those frames. The grid asks for them in increasing order, so only
    the last tile is kept."""

    def __init__(self, path: Path, first: int, count: int):
        self.first, self.count = first, count
        self.reader = FrameReader(probe(path))
        self.kept: dict[int, YuvFrame] = {}
        self.next = first
        self.lowest = first

    def frame(self, m: int) -> YuvFrame | None:
        if not self.first <= m < self.first + self.count:
            return None
        while self.next <= m:
            tile = self.reader.read()
            if tile is None:
                return None
            self.kept[self.next] = tile.copy()
            self.next += 1
        for old in [k for k in self.kept if k < m]:  # the grid asks for m, m+1, ... from now on
            del self.kept[old]
        return self.kept.get(m)

    def close(self) -> None:
        self.reader.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def camera_frame_png(result: Result, camera: int, video: str | Path, frame: int, path: str | Path) -> Path:
    """One camera's frame of ``video`` with the estimate drawn on it (as in the labelled videos),
    written as a PNG. ``camera`` counts from 0, in the result's camera order."""
    C = len(result.camera_names)
    if not 0 <= camera < C:
        raise InputError(f"the result has cameras 1 to {C} ({', '.join(result.camera_names)}), not camera {camera + 1}")
    info = probe(video)
    N = result.positions.shape[0]
    if info.frames != N:
        raise InputError(f"has {info.frames} frames but the result has {N} (one estimate per video frame)", video)
    if not 0 <= frame < N:
        raise InputError(f"--frame {frame}: the run has frames 0 to {N - 1}")
    image = read_frame(info, frame)
    draw_camera_frame(image, camera_overlays(result)[camera], frame, Style.for_width(image.width))
    path = Path(path)
    if not cv2.imwrite(str(path), image.to_bgr()[: info.height, : info.width]):
        raise InputError("could not be written as a PNG", path)
    return path
