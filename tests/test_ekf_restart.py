"""ekf after long camera drop-outs: a marker the stream lost while fewer cameras saw it is taken up
again once three cameras or more see it (bench/bench_dropout.py's protocol, the seed on which the
tail tip stayed 0.7 m off for 1,200 frames on one machine), and the report says so.

Whether the stream loses a marker on that seed depends on the machine's rounding: on an Intel Xeon it
lost the tail tip and restarted it (1,214 frames over 100 mm without the restart, 29 with it); on an
AMD EPYC it never lost it (11 frames over 100 mm, no restart). So the test holds the outcome, which
both meet, and says whether the stream restarted. A marker made to jump in every camera at once (1-2 m,
all markers or one) is followed within ten frames without a restart, so it does not force one."""

from __future__ import annotations

import numpy as np
import pytest
from dropouts import with_dropouts

from graph.api import SolveOptions, solve
from graph.simulate import simulate_run


@pytest.mark.slow  # about 15 s
def test_a_marker_lost_after_the_drop_outs_is_taken_up_again(rig):
    run = simulate_run(rig, frames=7200, fps=120.0, noise=5.0, outliers=0.1, outlier_std=100.0, seed=1,
                       confident_outliers=1.0, speed=1.0)
    keypoints, _, _ = with_dropouts(run, 1000, 3000, 3500)
    idx = np.arange(run.frames)
    result = solve(keypoints, rig, SolveOptions(method="ekf", fps=run.fps))
    err = np.linalg.norm(result.positions - run.positions, axis=-1)  # (N, M) metres
    after = idx >= 3500
    far = int((np.nanmax(err[after], axis=1) > 0.1).sum())
    assert far <= 60, far  # 1,214 frames with a marker over 100 mm off before the restart
    assert np.nanmean(err[after]) < 0.0065, np.nanmean(err[after])  # fte 4.95 mm; 11.5 mm before
    restarted = [w for w in result.report.warnings if "restarted them from the frame's triangulation" in w]
    print(f"{far} frames with a marker over 100 mm off after the drop-outs; restarted: {restarted or 'no'}")

