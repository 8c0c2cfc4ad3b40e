"""The reader's data types: one camera's detections (:class:`Keypoints`) and what a reader accepts
(:class:`ReadLimits`). Below every reader (:mod:`graph.io.keypoints`, :mod:`graph.io.sleap`), which
import them from here; :mod:`graph.io.keypoints` re-exports them."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from graph.errors import TooLargeInput
from graph.types import MAX_INDIVIDUALS


@dataclass(frozen=True)
class ReadLimits:
    """What a reader accepts, checked before the data are read. ``max_bodyparts`` counts each
    individual's bodyparts of a multi-animal file (a file may hold at most ``3 * max_bodyparts``
    data columns). None: no limit."""

    max_frames: int | None = None
    max_bodyparts: int | None = None

    @property
    def max_columns(self) -> int | None:
        return None if self.max_bodyparts is None else 3 * self.max_bodyparts

    def check_frames(self, frames: int, path: Path, counting: bool = False) -> None:
        """``frames`` declared (or, ``counting``, read so far) against ``max_frames``."""
        if self.max_frames is not None and frames > self.max_frames:
            said = f"more than {self.max_frames}" if counting else str(frames)
            raise TooLargeInput(f"{said} frames; at most {self.max_frames} frames per file", path, "frames")

    def check_columns(self, columns: int, path: Path) -> None:
        if self.max_columns is not None and columns > self.max_columns:
            raise TooLargeInput(f"{columns} data columns (about {columns // 3} bodyparts); at most "
                                f"{self.max_bodyparts} bodyparts ({self.max_columns} columns) per file", path,
                                "bodyparts")


NO_LIMITS = ReadLimits()
EVERY = "\x00every individual"  # a reader's ``individual``: all of them, as Tracks (no name can be this)
MAX_SLOTS = MAX_INDIVIDUALS  # individuals read at once from one file


@dataclass
class Keypoints:
    """One camera's detections: N frames, M bodyparts.

    ``xy`` (N, M, 2) pixels, NaN where missing; ``likelihood`` (N, M) in [0, 1], 0 where missing.
    """

    bodyparts: list[str]
    xy: np.ndarray
    likelihood: np.ndarray
    scorer: str = "acinoset"
    source: str = ""
    spread_px: np.ndarray | None = None  # (N, M) an ensemble's disagreement (graph.solve.ensemble), else None
    fps: float | None = None  # the frame rate the file records (SLEAP's may; DeepLabCut's never do), else None

    def __post_init__(self) -> None:
        self.xy = np.asarray(self.xy, dtype=np.float64)
        self.likelihood = np.asarray(self.likelihood, dtype=np.float64)
        if self.spread_px is not None:
            self.spread_px = np.asarray(self.spread_px, dtype=np.float64)

    @property
    def frames(self) -> int:
        return self.xy.shape[0]


@dataclass
class Tracks:
    """One camera's detections of several individuals: N frames, K slots, M bodyparts.

    A slot is what the 2D tracker calls one individual (a DeepLabCut individual, a SLEAP track);
    ``names`` (K,) name them. ``identified``: the slots carry identities across frames (a tracker's
    tracks); False where they do not (OpenPose's people, in each frame's own order).
    ``xy`` (N, K, M, 2) pixels, NaN where missing; ``likelihood`` (N, K, M) in [0, 1], 0 where missing.
    """

    bodyparts: list[str]
    names: list[str]
    xy: np.ndarray
    likelihood: np.ndarray
    identified: bool = True
    scorer: str = "acinoset"
    source: str = ""
    fps: float | None = None

    def __post_init__(self) -> None:
        self.xy = np.asarray(self.xy, dtype=np.float64)
        self.likelihood = np.asarray(self.likelihood, dtype=np.float64)

    @property
    def frames(self) -> int:
        return self.xy.shape[0]

    @property
    def slots(self) -> int:
        return self.xy.shape[1]

    def slot(self, k: int) -> Keypoints:
        """Slot ``k`` alone, as the single-individual :class:`Keypoints`."""
        return Keypoints(bodyparts=list(self.bodyparts), xy=self.xy[:, k].copy(),
                         likelihood=self.likelihood[:, k].copy(), scorer=self.scorer, source=self.source, fps=self.fps)


def as_tracks(keypoints: Keypoints) -> Tracks:
    """A single individual's detections as :class:`Tracks` of one slot."""
    return Tracks(bodyparts=list(keypoints.bodyparts), names=[""], xy=keypoints.xy[:, None],
                  likelihood=keypoints.likelihood[:, None], scorer=keypoints.scorer, source=keypoints.source,
                  fps=keypoints.fps)
