"""Finding the board in images: checkerboards with sub-pixel refinement, ChArUco boards, from a
folder of images or a video (every N-th frame), with a cache so that a re-run skips detection.

Checkerboard: ``cv2.findChessboardCorners`` on the image shrunk to at most :data:`SEARCH_WIDTH`
pixels across (with ``CALIB_CB_FAST_CHECK``, so a frame without a board costs little), then
``cv2.cornerSubPix`` on the full-resolution image, in a window of about a third of the smallest
distance between neighbouring corners. ChArUco: ``cv2.aruco.CharucoDetector`` (OpenCV 4.7 or later);
corners it did not find are NaN.
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable, Iterator

import numpy as np

from graph.calibrate.board import CHARUCO, Board, charuco_board
from graph.calibrate.views import BoardViews, read_detections, write_detections
from graph.errors import InputError

SEARCH_WIDTH = 960  # px: boards are searched for at this width, refined at full resolution
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")
VIDEO_SUFFIXES = (".mp4", ".avi", ".mov", ".mkv", ".m4v", ".mpg", ".mpeg", ".webm", ".mts")
CACHE_SUFFIX = ".detections.json"


class Detector:
    """Detects one board in grey images: ``detector(gray) -> (N, 2) corners (NaN = missing) or None``."""

    def __init__(self, board: Board):
        import cv2

        self.board = board
        self._cv2 = cv2
        if board.kind == CHARUCO:
            if not hasattr(cv2.aruco, "CharucoDetector"):
                raise InputError("ChArUco detection needs OpenCV 4.7 or later")
            self._charuco = cv2.aruco.CharucoDetector(charuco_board(board))

    def __call__(self, gray: np.ndarray) -> np.ndarray | None:
        return self._charuco_corners(gray) if self.board.kind == CHARUCO else self._checker_corners(gray)

    def _checker_corners(self, gray: np.ndarray) -> np.ndarray | None:
        cv2 = self._cv2
        h, w = gray.shape[:2]
        scale = min(1.0, SEARCH_WIDTH / w)
        small = (cv2.resize(gray, (round(w * scale), round(h * scale)), interpolation=cv2.INTER_AREA)
                 if scale < 1 else gray)
        flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_FAST_CHECK
        found, corners = cv2.findChessboardCorners(small, self.board.corner_grid, flags=flags)
        if not found:
            return None
        corners = np.ascontiguousarray(corners.reshape(-1, 1, 2) / scale, dtype=np.float32)
        gap = _smallest_gap(corners.reshape(-1, 2), self.board.corner_grid)
        half = int(max(2, min(15, round(gap / 3))))
        crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_MAX_ITER, 30, 0.01)
        corners = cv2.cornerSubPix(gray, corners, (half, half), (-1, -1), crit)
        return corners.reshape(-1, 2).astype(np.float64)

    def _charuco_corners(self, gray: np.ndarray) -> np.ndarray | None:
        corners, ids, _, _ = self._charuco.detectBoard(gray)
        if ids is None or len(ids) < 4:
            return None
        out = np.full((self.board.n_corners, 2), np.nan)
        out[np.asarray(ids).ravel()] = np.asarray(corners).reshape(-1, 2)
        return out


def _smallest_gap(corners: np.ndarray, grid: tuple[int, int]) -> float:
    """The smallest distance between neighbouring corners of a (rows x cols) grid, pixels."""
    g = corners.reshape(grid[1], grid[0], 2)
    d = [np.linalg.norm(np.diff(g, axis=1), axis=-1).min(), np.linalg.norm(np.diff(g, axis=0), axis=-1).min()]
    return float(min(d))


Progress = Callable[[int, int], None]  # (done, total)


def detect_views(source: str | Path, board: Board, every: int = 1, cache: bool = True,
                 progress: Progress | None = None, name: str | None = None) -> BoardViews:
    """The board views of one camera from ``source``: a detections JSON (read as it is), a folder of
    images, or a video (every ``every``-th frame, named by its index). Detections of images and
    videos are cached beside the source in ``<source>.detections.json`` (keyed by the board, ``every``
    and the source's size and time stamp) and reused when they still match."""
    source = Path(source)
    if not source.exists():
        raise InputError("no such file or folder", source)
    if source.is_file() and source.suffix.lower() == ".json":
        return read_detections(source, board, name)
    key = {"board": board.spec, "every": int(every), **_identity(source)}
    cache_path = cache_path_for(source)
    if cache and cache_path.exists():
        try:
            views = read_detections(cache_path, board, name or source.stem)
            if all(views.meta.get(k) == v for k, v in key.items()):
                views.source = str(source)
                return views
        except InputError:
            pass  # a stale or broken cache is redone
    if source.is_dir():
        frames = _image_frames(source)
    elif source.suffix.lower() in VIDEO_SUFFIXES or source.suffix.lower() not in IMAGE_SUFFIXES:
        frames = _video_frames(source, every)
    else:
        raise InputError("a single image is not a source: give a folder of images, a video or a detections JSON",
                         source)
    detector = Detector(board)
    names, found, size = [], [], None
    for i, total, frame_name, gray in frames:
        if size is None:
            size = (gray.shape[1], gray.shape[0])
        elif size != (gray.shape[1], gray.shape[0]):
            raise InputError(f"{frame_name}: image size {gray.shape[1]}x{gray.shape[0]} differs from the first "
                             f"image's {size[0]}x{size[1]}", source)
        corners = detector(gray)
        if corners is not None:
            names.append(frame_name)
            found.append(corners)
        if progress is not None:
            progress(i + 1, total)
    if size is None:
        raise InputError("no images or frames could be read", source)
    if not found:
        raise InputError(f"no board found ({board.spec}) in any image", source)
    views = BoardViews(name or source.stem, size, names, np.stack(found), str(source),
                       board.corner_grid, board.square, dict(key))
    if cache:
        try:
            write_detections(cache_path, views, board, key)
        except OSError:
            pass  # a read-only source folder: no cache, the result stands
    return views


def cache_path_for(source: Path) -> Path:
    return source.with_name(source.name + CACHE_SUFFIX) if source.is_file() else source / ("board" + CACHE_SUFFIX)


def _identity(source: Path) -> dict:
    if source.is_dir():
        files = sorted(p for p in source.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
        return {"source_size": sum(p.stat().st_size for p in files),
                "source_mtime": max((p.stat().st_mtime for p in files), default=0.0)}
    st = source.stat()
    return {"source_size": st.st_size, "source_mtime": st.st_mtime}


def _image_frames(folder: Path) -> Iterator[tuple[int, int, str, np.ndarray]]:
    import cv2

    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    if not files:
        raise InputError("no images (.png, .jpg, ...) in the folder", folder)
    for i, p in enumerate(files):
        gray = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
        if gray is None:
            raise InputError(f"{p.name}: cannot read the image", folder)
        yield i, len(files), p.name, gray


def _video_frames(path: Path, every: int) -> Iterator[tuple[int, int, str, np.ndarray]]:
    """Every ``every``-th frame of a video, grey; frames in between are grabbed, not decoded."""
    import cv2

    if every < 1:
        raise InputError(f"--every must be at least 1, got {every}")
    cap = cv2.VideoCapture(str(path))
    if not cap.isOpened():
        raise InputError("not a video OpenCV can read", path)
    total = int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) or 0
    steps = max(1, (total + every - 1) // every) if total else 0
    index = 0
    try:
        while True:
            if index % every == 0:
                ok, frame = cap.read()
                if not ok:
                    break
                gray = frame if frame.ndim == 2 else cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY)
                yield index // every, max(steps, index // every + 1), str(index), gray
            elif not cap.grab():
                break
            index += 1
    finally:
        cap.release()
    if index == 0:
        raise InputError("the video has no frames OpenCV can decode", path)
