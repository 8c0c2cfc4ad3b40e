"""Board views: the corners one camera saw in each of its frames, read from a detections JSON.

AcinoSet's detections JSON (one camera)::

    {"board_shape": [COLS, ROWS], "board_square_len": 0.031,   (or "board_edge_len")
     "camera_resolution": [W, H],
     "points": {"610.png": [[[u, v], ...], ...], ...}}

The corners of a frame are nested lists in OpenCV's order (see :mod:`graph.calibrate.board`);
``reshape(-1, 2)`` gives them. A corner that was not detected (ChArUco) is ``null``. acinoset writes
its detection cache in the same layout, with a ``board`` spec and the source's identity added.
"""

from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from graph.calibrate.board import CHECKERBOARD, MAX_SIDE, Board
from graph.errors import InputError, unreadable


@dataclass
class BoardViews:
    """What one camera saw of the board.

    ``corners`` is (F, N, 2) pixels for F frames and the board's N corners, NaN where a corner was
    not found; ``frames`` names the frames (matched across cameras by :func:`frame_key`).
    """

    name: str
    image_size: tuple[int, int]
    frames: list[str]
    corners: np.ndarray
    source: str = ""
    board_shape: tuple[int, int] | None = None
    square: float | None = None
    meta: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.frames)

    def subset(self, keep: list[int]) -> "BoardViews":
        return BoardViews(self.name, self.image_size, [self.frames[i] for i in keep], self.corners[keep],
                          self.source, self.board_shape, self.square, dict(self.meta))


def frame_key(name: str) -> str:
    """The name frames are matched by across cameras: the last number in the frame's name without an
    image extension, else that name. ``"610.png"``, ``"610"`` and ``"img_0610.png"`` are the same
    instant, and so are ``"back-02242022135219-3.jpg"`` and ``"side-02242022135220-3.jpg"`` (a
    camera's name and its clock's time stamp before the shared index, as rigs that save one image
    per camera and trigger name them)."""
    p = Path(str(name))
    stem = p.stem if p.suffix.lower() in (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff") else str(name)
    numbers = _DIGITS.findall(stem)
    return str(int(numbers[-1])) if numbers else stem


_DIGITS = re.compile(r"\d+")


MAX_IMAGE_SIDE = 100_000  # pixels


def read_detections(path: str | Path, board: Board | None = None, name: str | None = None) -> BoardViews:
    """Read a detections JSON (AcinoSet's layout). With ``board``, its shape must agree with the
    file's ``board_shape``, and a file's square length that differs from the board's is an error."""
    path = Path(path)
    try:
        doc = json.loads(path.read_text(encoding="utf-8-sig"))
    except OSError as e:
        raise unreadable(e, path, "a detections file") from None
    except UnicodeDecodeError:
        raise InputError("not a detections file (binary, not UTF-8 text)", path) from None
    except json.JSONDecodeError as e:
        raise InputError(f"not valid JSON (line {e.lineno}: {e.msg})", path) from None
    except RecursionError:
        raise InputError("not a detections file: arrays nested too deeply", path) from None
    except ValueError:  # Python's limit on the digits of an integer (4300)
        raise InputError("not a detections file: a number with thousands of digits", path) from None
    if not isinstance(doc, dict) or not isinstance(doc.get("points"), dict):
        raise InputError('not a detections file: no "points" object of frame -> corners', path)
    shape = None
    if "board_shape" in doc:
        bs = doc["board_shape"]
        if not (isinstance(bs, list) and len(bs) == 2
                and all(_whole(v, MAX_SIDE) for v in bs)):
            raise InputError(f"board_shape: expected [COLS, ROWS], got {str(bs)[:80]!r}", path)
        s = np.asarray(bs)
        shape = (int(s[0]), int(s[1]))
    square = doc.get("board_square_len", doc.get("board_edge_len"))
    if square is not None and not (isinstance(square, (int, float)) and square > 0):
        raise InputError(f"board_square_len: expected a positive length, got {square!r}", path)
    if "camera_resolution" not in doc:
        raise InputError("camera_resolution missing ([width, height] of the images)", path)
    res = doc["camera_resolution"]
    if not (isinstance(res, list) and len(res) == 2
            and all(_whole(v, MAX_IMAGE_SIDE) for v in res)):
        raise InputError(f"camera_resolution: expected [width, height] in pixels (whole numbers up to "
                         f"{MAX_IMAGE_SIDE}), got {str(res)[:80]}", path)
    size = (int(res[0]), int(res[1]))
    n = None
    if board is not None:
        n = board.n_corners
        grid = board.corner_grid
        if shape is not None and board.kind == CHECKERBOARD and tuple(shape) != grid:
            raise InputError(f"board_shape {list(shape)} does not match the board {board.spec} "
                             f"({grid[0]}x{grid[1]} inner corners)", path)
        if square is not None and abs(float(square) - board.square) > 1e-6 * board.square:
            raise InputError(f"board_square_len {square} does not match the board's square {board.square:g} m", path)
    elif shape is not None:
        n = shape[0] * shape[1]
    frames, corners = [], []
    for frame, pts in doc["points"].items():
        try:
            a = np.array([[np.nan, np.nan] if p is None else p for p in _flatten_points(pts)], dtype=np.float64)
        except (TypeError, ValueError):
            raise InputError(f"frame {frame!r}: corners must be [u, v] pairs", path) from None
        a = a.reshape(-1, 2)
        if n is None:
            n = len(a)
        if len(a) != n:
            raise InputError(f"frame {frame!r}: {len(a)} corners, the board has {n}", path)
        frames.append(str(frame))
        corners.append(a)
    if not frames:
        raise InputError("no board views in the file (\"points\" is empty)", path)
    meta = {k: doc[k] for k in ("board", "source_size", "source_mtime", "every") if k in doc}
    return BoardViews(name or path.stem, size, frames, np.stack(corners), str(path), shape,
                      float(square) if square is not None else None, meta)


def _whole(v, most: int) -> bool:
    """A whole number from 1 to ``most`` (``1920`` or ``1920.0``; not a bool, infinity or text)."""
    return (isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v == int(v)
            and 0 < v <= most)


def _flatten_points(pts) -> list:
    """Nested corner lists ((C, R, 2), (N, 2) or (N, 1, 2)) to a list of [u, v] or None."""
    out: list = []

    def walk(x):
        if x is None:
            out.append(None)
        elif isinstance(x, list) and len(x) == 2 and all(isinstance(v, (int, float)) or v is None for v in x):
            out.append(None if any(v is None for v in x) else x)
        elif isinstance(x, list):
            for y in x:
                walk(y)
        else:
            raise TypeError

    walk(pts)
    return out


def write_detections(path: str | Path, views: BoardViews, board: Board, extra: dict | None = None) -> None:
    """Write ``views`` in AcinoSet's detections layout (missing corners as ``null``)."""
    points = {f: [None if not np.all(np.isfinite(p)) else [float(p[0]), float(p[1])] for p in c]
              for f, c in zip(views.frames, views.corners)}
    doc = {"board": board.spec, "board_shape": list(board.corner_grid), "board_square_len": board.square,
           "camera_resolution": list(views.image_size), **(extra or {}), "points": points}
    Path(path).write_text(json.dumps(doc) + "\n", encoding="utf-8")
