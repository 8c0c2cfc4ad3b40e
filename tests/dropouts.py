"""bench/bench_dropout.py's long camera drop-outs set in a simulated run's detections, for the tests of
ekf through them: four cameras blind for a stretch, then camera 3 alone."""

from __future__ import annotations

import dataclasses

import numpy as np

FOUR_BLIND = (0, 3, 4, 5)  # cameras 1, 4, 5, 6: no detections in the first stretch
ONLY = 2  # camera 3: the only one seeing the second


def with_dropouts(run, four_from: int, only_from: int, only_to: int):
    """The run's detections with cameras 1, 4, 5 and 6 blind for frames ``[four_from, only_from)`` and
    every camera but camera 3 blind for ``[only_from, only_to)`` (xy NaN, likelihood 0, as a detector that
    found nothing writes them); returns them and the two stretches' frame masks."""
    idx = np.arange(run.frames)
    four, only = (idx >= four_from) & (idx < only_from), (idx >= only_from) & (idx < only_to)
    keypoints = []
    for c, kp in enumerate(run.keypoints):
        blind = (four if c in FOUR_BLIND else np.zeros_like(four)) | (only if c != ONLY else np.zeros_like(only))
        xy, lik = kp.xy.copy(), kp.likelihood.copy()
        xy[blind], lik[blind] = np.nan, 0.0
        keypoints.append(dataclasses.replace(kp, xy=xy, likelihood=lik))
    return keypoints, four, only
