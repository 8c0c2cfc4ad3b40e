"""Ensembles of pose models: combined per camera, their spread weighing cameras and markers."""

from __future__ import annotations

import numpy as np
import pytest

from graph.api import SolveOptions, solve
from graph.camera import Calibration
from graph.errors import InputError
from graph.io.calibration import default_rig_path, load_calibration
from graph.io.keypoints import Keypoints
from graph.simulate import simulate_run
from graph.solve.ensemble import combine, relative_noise

NAN = float("nan")


def test_combine_by_hand():
    a = Keypoints(["p", "q"], np.array([[[0.0, 0.0], [10.0, 10.0]]]), np.array([[0.9, 0.8]]), source="a.csv")
    b = Keypoints(["p", "q"], np.array([[[2.0, 4.0], [NAN, NAN]]]), np.array([[0.7, 0.0]]), source="b.csv")
    k = combine([a, b])
    np.testing.assert_allclose(k.xy, [[[1.0, 2.0], [10.0, 10.0]]])  # the median of two is their mean
    np.testing.assert_allclose(k.likelihood, [[0.8, 0.4]])
    # sd per coordinate about the mean: sqrt(((1+4) + (1+4)) / (2 (2-1))) = sqrt(5); one member: none
    np.testing.assert_allclose(k.spread_px, [[np.sqrt(5.0), NAN]])
    assert k.source == "a.csv+b.csv" and combine([a]) is a
    with pytest.raises(InputError, match="different bodyparts"):
        combine([a, Keypoints(["p", "r"], a.xy, a.likelihood)])


def test_relative_noise_by_hand():
    spread = np.array([[[1.0, 2.0], [4.0, NAN]], [[1.0, 2.0], [4.0, NAN]], [[3.0, 2.0], [4.0, NAN]]])  # (N=3, C=2, M=2)
    valid = np.ones((3, 2, 2), dtype=bool)
    rel = relative_noise(spread, valid)
    np.testing.assert_allclose(rel, [[0.5, 1.0], [2.0, 1.0]])  # medians 1, 2, 4 over the median 2; no spread: 1
    assert relative_noise(np.full((3, 2, 2), NAN), valid) is None


def test_an_ensemble_weighs_the_noisy_camera_down():
    """Two members of one simulated run whose first camera is 4x noisier in both: the combined
    observation finds that camera's noise relative to the others', and the 3D error against the
    truth is lower than the same median without weighing (and than one member)."""
    rig = load_calibration(default_rig_path())
    cal = Calibration(cameras=rig.cameras[:3])
    members = [simulate_run(cal, frames=120, noise=1.0, outliers=0.0, seed=7, noise_seed=k) for k in range(2)]
    rng = np.random.default_rng(3)
    for m in members:
        m.keypoints[0].xy = m.keypoints[0].xy + rng.normal(0.0, 4.0, m.keypoints[0].xy.shape)
    combined = [combine([m.keypoints[c] for m in members]) for c in range(3)]
    plain = [Keypoints(k.bodyparts, k.xy, k.likelihood) for k in combined]  # no spread: every camera alike
    opts = SolveOptions(skeleton="points", fps=members[0].fps, motion_scale=1.0)
    r = solve(combined, cal, opts)
    rel = r.report.relative_noise
    assert rel[cal.names[0]] > 2.5 * max(rel[cal.names[1]], rel[cal.names[2]])
    truth = members[0].positions
    err = lambda res: float(np.nanmean(np.linalg.norm(res.positions - truth, axis=-1)))  # noqa: E731
    assert err(r) < 0.85 * err(solve(plain, cal, opts))
    assert err(r) < err(solve(members[0].keypoints, cal, opts))
    assert solve(plain, cal, opts).report.relative_noise is None
