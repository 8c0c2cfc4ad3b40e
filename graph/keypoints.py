"""2D keypoints from DeepLabCut: one :class:`Keypoints` per camera.

Readers: DeepLabCut CSV (single-animal 3-row header, multi-animal 4-row header) and DeepLabCut H5,
read with h5py only: the PyTables attributes in those files are pickles, and an uploaded file must
never execute code, so nothing here unpickles.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


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

    def __post_init__(self) -> None:
        self.xy = np.asarray(self.xy, dtype=np.float64)
        self.likelihood = np.asarray(self.likelihood, dtype=np.float64)

    @property
    def frames(self) -> int:
        return self.xy.shape[0]
