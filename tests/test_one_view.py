"""A bodypart confidently seen by one camera only: no crash, and no position made up for it."""

from dataclasses import replace

import numpy as np
import pytest

from graph.api import SolveOptions, solve
from graph.simulate import simulate_run


def _one_camera(run, marker: int, frames=slice(None)):
    out = []
    for c, kp in enumerate(run.keypoints):
        lik = kp.likelihood.copy()
        if c > 0:
            lik[frames, marker] = 0.0
        out.append(replace(kp, likelihood=lik))
    return out


@pytest.mark.parametrize("method", ["fte", "ekf"])
@pytest.mark.parametrize("skeleton", ["cheetah", "points"])
def test_a_marker_one_camera_sees_is_listed_and_never_invented(rig, method, skeleton):
    run = simulate_run(rig, frames=80, seed=1)
    m = run.markers.index("neck_base")
    result = solve(_one_camera(run, m), rig, SolveOptions(method=method, fps=run.fps, skeleton=skeleton))
    assert "neck_base" in result.report.unconstrained_markers
    if skeleton == "points":
        assert np.isnan(result.positions[:, m]).all()
    else:  # held by the skeleton: the kinematic chain places it
        err = np.linalg.norm(result.positions[:, m] - run.positions[:, m], axis=-1)
        assert np.nanmean(err) < 0.02
    others = [j for j in range(len(run.markers)) if j != m]
    assert np.isfinite(result.positions[:, others]).all()


def test_free_points_have_no_estimate_in_frames_one_camera_sees(rig):
    run = simulate_run(rig, frames=80, seed=2)
    m = run.markers.index("tail1")
    result = solve(_one_camera(run, m, slice(20, 50)), rig, SolveOptions(fps=run.fps, skeleton="points"))
    assert np.isnan(result.positions[20:50, m]).all()
    assert np.isfinite(result.positions[:20, m]).all() and np.isfinite(result.positions[50:, m]).all()
    assert any("fewer than two cameras" in w for w in result.report.warnings)
