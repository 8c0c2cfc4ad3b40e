"""The detection noise a solve advises is one a held-out camera accepts: on the fly recording the
residuals' scatter (1.4 px) leaves a held-out camera's detections outside their 90 % ellipse far more
than 10 % of the time, so it is not advised; triangulation is advised the noise its held-out
prediction accepts."""

from __future__ import annotations

import re
import warnings

import pytest
from shared_data import EKS_FLY

from graph.api import SolveOptions, solve
from graph.io.calibration import default_rig_path, load_calibration
from graph.io.keypoints import read_keypoints
from graph.metrics import leave_one_camera_out
from graph.simulate import simulate_run
from graph.solve import disagreement, problem

FLY = EKS_FLY
ADVICE = re.compile(r"set the detection noise to ([\d.]+) px")


@pytest.fixture(scope="module")
def fly():
    if not FLY.is_dir():
        pytest.skip("the fly recording is not on this machine")
    return [read_keypoints(FLY / f"cam{x}.rng1.csv") for x in "ABC"], load_calibration(FLY / "calibration.toml")


def _scatter_warning(result) -> str:
    (said,) = [w for w in result.report.warnings if "the detections scatter" in w]
    return said


def test_the_held_out_noise_is_the_simulated_noise():
    rig = load_calibration(default_rig_path())
    for noise in (2.0, 10.0):
        run = simulate_run(rig, frames=150, noise=noise, outliers=0.0, seed=3)
        prob = problem.build(run.keypoints, rig, SolveOptions(fps=run.fps))
        assert disagreement.held_out_noise(prob.calibration, prob.meas, prob.valid) == pytest.approx(noise, rel=0.1)


def test_a_smoother_is_not_advised_the_scatter(fly):
    kps, cal = fly
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        result = solve(kps, cal, SolveOptions(method="fte", skeleton="points", fps=300.0))
    said = _scatter_warning(result)
    assert result.report.noise_px < 2.0 and f"scatter {result.report.noise_px:.1f} px" in said
    assert "set the detection noise" not in said and "evaluate loco" in said, said


def test_triangulation_is_advised_a_noise_its_held_out_cameras_accept(fly):
    kps, cal = fly
    options = SolveOptions(method="tri", skeleton="points", fps=300.0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        result = solve(kps, cal, options)
        advised = float(ADVICE.search(_scatter_warning(result)).group(1))
        assert result.report.noise_px < advised < 5.0 / 1.5
        at_advice = leave_one_camera_out(kps, cal, SolveOptions(**{**options.to_dict(), "measurement_std_px": advised}))
        at_scatter = leave_one_camera_out(kps, cal, SolveOptions(**{**options.to_dict(),
                                                                    "measurement_std_px": result.report.noise_px}))
    assert 0.85 <= at_advice.within_90 <= 0.95, at_advice.within_90
    assert at_scatter.within_90 < 0.82, at_scatter.within_90  # what following the scatter gave
