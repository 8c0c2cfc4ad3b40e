"""Calibration boards: the spec a user types and the board's corners in its own frame.

Specs::

    checkerboard:COLSxROWS:SQUARE_M                   inner corners, square side in metres
    charuco:SQUARESXxSQUARESY:SQUARE_M:MARKER_M:DICT  squares, square and marker sides, ArUco dictionary

Corner order is OpenCV's. A checkerboard of ``COLS x ROWS`` inner corners (``patternSize=(COLS, ROWS)``
for ``cv2.findChessboardCorners``) lists its corners row by row::

    corner i = r * COLS + c   at   (c * s, r * s, 0),   0 <= c < COLS, 0 <= r < ROWS

(AcinoSet's ``mgrid[0:COLS, 0:ROWS].T.reshape(-1, 2) * s``). A ChArUco board of ``SX x SY`` squares has
``(SX-1) x (SY-1)`` inner corners; corner id ``i = r * (SX-1) + c`` lies at ``((c+1) s, (r+1) s, 0)``,
as ``cv2.aruco.CharucoBoard.getChessboardCorners`` gives them. The board frame has x along a row, y
down the rows and z = x cross y, into the board as seen by a camera that reads it the right way up.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np

from graph.errors import InputError

CHECKERBOARD = "checkerboard"
CHARUCO = "charuco"

SQUARE_LOOKS_LIKE_MM = 1.0  # a square side of a metre or more is almost surely given in millimetres

_SIZE = re.compile(r"^(\d+)x(\d+)$", re.IGNORECASE)


@dataclass(frozen=True)
class Board:
    """A planar calibration board. ``cols x rows`` are inner corners for a checkerboard and squares
    for a ChArUco board; lengths are in metres."""

    kind: str
    cols: int
    rows: int
    square: float
    marker: float = 0.0
    dictionary: str = ""

    @property
    def corner_grid(self) -> tuple[int, int]:
        """(columns, rows) of the corners that are detected."""
        if self.kind == CHARUCO:
            return self.cols - 1, self.rows - 1
        return self.cols, self.rows

    @property
    def n_corners(self) -> int:
        c, r = self.corner_grid
        return c * r

    def object_points(self) -> np.ndarray:
        """The corners (N, 3) in the board frame, metres, in OpenCV's order (see the module)."""
        c, r = self.corner_grid
        off = 1.0 if self.kind == CHARUCO else 0.0
        cc, rr = np.meshgrid(np.arange(c, dtype=float), np.arange(r, dtype=float))
        return np.stack([(cc.ravel() + off) * self.square, (rr.ravel() + off) * self.square,
                         np.zeros(c * r)], axis=1)

    @property
    def spec(self) -> str:
        if self.kind == CHARUCO:
            return f"charuco:{self.cols}x{self.rows}:{self.square:g}:{self.marker:g}:{self.dictionary}"
        return f"checkerboard:{self.cols}x{self.rows}:{self.square:g}"

    def looks_like_mm(self) -> bool:
        """True when the square side is implausible in metres (a board with 1 m squares)."""
        return self.square >= SQUARE_LOOKS_LIKE_MM


def parse_board(spec: str) -> Board:
    """A :class:`Board` from its spec; :class:`InputError` naming the spec when it is malformed."""
    parts = [p.strip() for p in str(spec).split(":")]
    kind = parts[0].lower()
    usage = ("expected checkerboard:COLSxROWS:SQUARE_M or charuco:SQUARESXxSQUARESY:SQUARE_M:MARKER_M:DICT, "
             f"got {spec!r}")
    if kind == CHECKERBOARD and len(parts) == 3:
        cols, rows = _grid(parts[1], usage)
        if cols < 2 or rows < 2:
            raise InputError(f"board {spec!r}: a checkerboard needs at least 2x2 inner corners")
        if cols == rows:
            raise InputError(f"board {spec!r}: a square checkerboard has no defined orientation; "
                             "use one with different numbers of inner corners across and down")
        return Board(CHECKERBOARD, cols, rows, _length(parts[2], "square side", spec))
    if kind == CHARUCO and len(parts) == 5:
        cols, rows = _grid(parts[1], usage)
        if cols < 3 or rows < 3:
            raise InputError(f"board {spec!r}: a ChArUco board needs at least 3x3 squares")
        square = _length(parts[2], "square side", spec)
        marker = _length(parts[3], "marker side", spec)
        if marker >= square:
            raise InputError(f"board {spec!r}: the marker ({marker:g}) must be smaller than the square ({square:g})")
        name = parts[4].upper()
        name = name if name.startswith("DICT_") else "DICT_" + name
        import cv2

        if not hasattr(cv2, "aruco") or not hasattr(cv2.aruco, name):
            raise InputError(f"board {spec!r}: unknown ArUco dictionary {parts[4]!r} (e.g. DICT_4X4_50)")
        return Board(CHARUCO, cols, rows, square, marker, name)
    raise InputError(f"board: {usage}")


MAX_SIDE = 1000  # squares or inner corners along one side of a board


def _grid(text: str, usage: str) -> tuple[int, int]:
    m = _SIZE.match(text)
    if not m:
        raise InputError(f"board: {usage}")
    if any(len(g) > 6 or int(g) > MAX_SIDE for g in m.groups()):
        raise InputError(f"board: at most {MAX_SIDE} squares or corners a side, got {text[:40]!r}")
    return int(m.group(1)), int(m.group(2))


def _length(text: str, what: str, spec: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise InputError(f"board {spec!r}: {what} {text!r} is not a number") from None
    if not (v > 0 and np.isfinite(v)):
        raise InputError(f"board {spec!r}: {what} must be a positive length in metres")
    return v


def charuco_board(board: Board):
    """The OpenCV ``CharucoBoard`` of a ChArUco :class:`Board` (OpenCV 4.7 or later)."""
    import cv2

    dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, board.dictionary))
    return cv2.aruco.CharucoBoard((board.cols, board.rows), board.square, board.marker, dictionary)
