"""Inputs that do not fit together are named, not solved into a silent wrong answer: keypoint files
in another order than the calibration's cameras, detections that half the cameras' views reject,
and a frame rate the motion says is wrong."""

from __future__ import annotations

import subprocess
import sys
import warnings
from dataclasses import replace

import numpy as np
import pytest
from shared_data import EKS_FLY

from graph.api import SolveOptions, solve
from graph.errors import InputError
from graph.solve.problem import camera_order_from_names, check_camera_order
from graph.solve.result import implausible_motion

SIMULATION = dict(frames=90, seed=3)


def _solve(kps, rig, **options):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return solve(kps, rig, SolveOptions(**options))


def test_file_names_give_the_camera_order_only_when_they_say_it():
    names = ["Cam-A", "Cam-B", "Cam-C"]
    assert camera_order_from_names(["x/camA.rng1.csv", "camB.csv", "CAM_C.h5"], names) == [0, 1, 2]
    assert camera_order_from_names(["camB.csv", "camA.csv", "camC.csv"], names) == [1, 0, 2]
    assert camera_order_from_names(["left.csv", "camA.csv", "camC.csv"], names) is None  # one says nothing
    assert camera_order_from_names(["a.csv", "b.csv", "c.csv"], ["A", "B", "C"]) is None  # too short to tell
    # cam1 is inside cam10's name: the longer one wins
    tens = [f"cam{i}" for i in range(1, 12)]
    files = [f"{n}.csv" for n in tens]
    assert camera_order_from_names(files, tens) == list(range(11))
    check_camera_order(["camA.csv", "camB.csv", "camC.csv"], names)  # in order: nothing said
    with pytest.raises(InputError, match="given as camera 1 .Cam-A. but its name says Cam-B"):
        check_camera_order(["camB.csv", "camA.csv", "camC.csv"], names)


def test_the_command_refuses_files_named_for_other_cameras(tmp_path):
    fly = EKS_FLY
    if not fly.is_dir():
        pytest.skip("the shared real recording is not beside the project")
    proc = subprocess.run([sys.executable, "-m", "graph.app.cli", "solve", str(fly / "camB.rng1.csv"),
                           str(fly / "camA.rng1.csv"), str(fly / "camC.rng1.csv"), "--calibration",
                           str(fly / "calibration.toml"), "--method", "tri", "--skeleton", "points", "--fps", "300",
                           "--out", str(tmp_path / "x.csv")], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "camB.rng1.csv" in lines[0] and "camera order" in lines[0]
    assert not (tmp_path / "x.csv").exists()


@pytest.mark.parametrize("method,skeleton", [("tri", "points"), ("fte", "cheetah")])
def test_swapped_cameras_are_flagged_with_the_likely_cause_not_more_noise(rig, run, method, skeleton):
    right = _solve(run.keypoints, rig, method=method, skeleton=skeleton, fps=run.fps)
    assert not any("do not fit" in w for w in right.report.warnings)
    swapped = [replace(k, source="") for k in (run.keypoints[1], run.keypoints[0], *run.keypoints[2:])]
    wrong = _solve(swapped, rig, method=method, skeleton=skeleton, fps=run.fps)
    fit = [w for w in wrong.report.warnings if "do not fit" in w]
    assert len(fit) == 1 and "camera order" in fit[0]
    assert "cam1" in fit[0] and "cam2" in fit[0] and "cam3" not in fit[0]
    assert not any("set the detection noise" in w for w in wrong.report.warnings)


def test_tri_warns_when_the_noise_assumed_is_far_off(rig, run):
    result = _solve(run.keypoints, rig, method="tri", skeleton="points", fps=run.fps, measurement_std_px=40.0)
    assert any("set the detection noise" in w for w in result.report.warnings)


def test_a_frame_rate_the_motion_contradicts_is_named(rig, run):
    truth = run.positions
    assert implausible_motion(truth, run.fps) is None
    slow = implausible_motion(truth, run.fps / 100)  # 1.2 typed for 120
    assert slow is not None and "higher than 1.2" in slow
    fast = implausible_motion(truth, run.fps * 50)
    assert fast is not None and "lower than 6000" in fast
    still = np.repeat(truth[:1], 30, axis=0)
    assert implausible_motion(still, run.fps) is None
    result = _solve(run.keypoints, rig, method="tri", skeleton="points", fps=run.fps / 100)
    assert any("is the frame rate higher" in w for w in result.report.warnings)


def test_compiling_a_kernel_is_said_once_and_loading_one_says_nothing():
    from numba import njit

    from graph.progress import compile_notice

    @njit
    def twice(x):
        return 2 * x

    said: list[str] = []
    with compile_notice(said.append):
        twice(1.0)
        twice(2.0)
        twice(3)  # a new signature compiles again, but the user was told already
    assert len(said) == 2 and "compiling" in said[0]
    assert said[1].startswith("kernels compiled in ") and said[1].endswith(" s (cached for later runs)")
    said.clear()
    with compile_notice(said.append):
        twice(4.0)  # compiled: nothing to say
    assert said == []
