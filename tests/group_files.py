"""Multi-animal keypoint files as the trackers write them, for the tests of several individuals."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from graph.io.keypoint_types import Tracks


def write_dlc_multi(path: Path, t: Tracks, names: list[str] | None = None) -> Path:
    """A multi-animal DeepLabCut CSV as DeepLabCut writes it (pandas, the 4-level column index)."""
    pd = pytest.importorskip("pandas")
    cols, data = [], []
    for k, name in enumerate(names or t.names):
        for m, bp in enumerate(t.bodyparts):
            for j, coord in enumerate(("x", "y", "likelihood")):
                cols.append(("DLC_resnet50_groupDec4shuffle1_100000", name, bp, coord))
                data.append(t.xy[:, k, m, j] if j < 2 else t.likelihood[:, k, m])
    index = pd.MultiIndex.from_tuples(cols, names=["scorer", "individuals", "bodyparts", "coords"])
    pd.DataFrame(np.stack(data, axis=1), columns=index).to_csv(path)
    return path
