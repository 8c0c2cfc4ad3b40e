"""A long run solved in windows (graph.solve.windows): the same answer as the whole solve, at every
frame and at the seams, in memory bounded by the window."""

import json
import subprocess
import sys
import warnings
from dataclasses import replace

import numpy as np
import pytest

from graph.api import solve
from graph.simulate import simulate_run, write_run
from graph.solve import problem, windows
from graph.solve.joint import solve_fte_joint
from graph.types import SolveOptions

FRAMES = 1200
CORE = 300


@pytest.fixture(scope="module")
def slow_run(rig):
    """A walking cheetah: 10 s at 120 fps, the paper's noise and outliers."""
    return simulate_run(rig, frames=FRAMES, fps=120, seed=4, speed=1.0)


def _mm(a, b) -> np.ndarray:
    return np.linalg.norm(a - b, axis=-1) * 1000


@pytest.mark.parametrize("options", [
    dict(skeleton="cheetah"),  # the body estimated (held from the settled stretch)
    dict(skeleton="points", motion_scale="auto"),  # each marker's smoothing fitted (held)
    dict(skeleton="cheetah", sync="estimate", measurement_std_px="auto"),  # clocks and noise held
], ids=["cheetah-body", "points-auto", "cheetah-sync-noise"])
def test_windows_equal_the_whole_solve_with_the_same_held_values(rig, slow_run, options):
    """Four windows of 300 frames, each solved with 200 frames either side: every frame's position
    within 0.1 mm (the issue's seam target) and its sd within 0.01 mm of the whole run solved at once
    with the values the windows hold, the seams' frames included."""
    prob = problem.build(slow_run.keypoints, rig, SolveOptions(fps=120, **options))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        st = windows.settle(prob, windows.SETTLE_FRAMES)
        whole = solve_fte_joint(replace(prob, options=st.options, sigma_px=st.sigma_px))
        r = windows.solve_in_windows(prob, CORE, settled=st)
    assert st.held, "the settled stretch held nothing"
    assert r.report.windows["count"] == FRAMES // CORE
    assert r.report.swap_rate == st.held["swap_rate"] == st.result.report.swap_rate  # the rate every window held
    d = _mm(r.positions, whole.positions)
    seams = np.r_[[k * CORE + i for k in range(1, FRAMES // CORE) for i in (-1, 0)]]
    assert np.isfinite(d).all()
    assert np.max(d) <= 0.1, f"largest difference {np.max(d):.4f} mm at frame {np.argmax(d.max(axis=1))}"
    assert np.max(d[seams]) <= 0.1
    assert np.nanmax(np.abs(r.std - whole.std)) * 1000 <= 0.01
    truth_err = np.nanmean(_mm(r.positions, slow_run.positions))
    whole_err = np.nanmean(_mm(whole.positions, slow_run.positions))
    assert truth_err <= 1.01 * whole_err


@pytest.mark.parametrize("options", [
    dict(skeleton="cheetah"),  # the body estimated (held from the settled stretch)
    dict(skeleton="points", motion_scale="auto"),  # each marker's smoothing fitted (held)
], ids=["cheetah-body", "points-auto"])
def test_ekf_in_windows_equals_the_whole_stream_with_the_same_held_values(rig, slow_run, options):
    """``ekf`` in windows (its memory bounded by the window's, as fte's): each later window's
    stream starts from fte over its first 100 frames, runs 200 and its lag more before its core, and
    its lag ends within the margin after, so every frame is within 0.1 mm of the whole run streamed at once with
    the values the windows hold (measured: 0.035 mm), its sd within 0.01 mm, and the causal estimates
    are kept too."""
    from graph.solve.online import solve_ekf

    prob = problem.build(slow_run.keypoints, rig, SolveOptions(fps=120, method="ekf", **options))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        st = windows.settle(prob, windows.SETTLE_FRAMES)
        whole = solve_ekf(replace(prob, options=st.options, sigma_px=st.sigma_px))
        r = windows.solve_in_windows(prob, CORE, settled=st)
    assert r.report.method == "ekf" and r.report.windows["count"] == FRAMES // CORE
    d = _mm(r.positions, whole.positions)
    assert np.isfinite(d).all()
    assert np.max(d) <= 0.1, f"largest difference {np.max(d):.4f} mm at frame {np.argmax(d.max(axis=1))}"
    assert np.nanmax(np.abs(r.std - whole.std)) * 1000 <= 0.01
    assert r.causal_positions is not None and r.causal_positions.shape == whole.causal_positions.shape
    later = slice(CORE, None)  # a window's causal estimates start at its own stream's start
    assert np.nanmax(_mm(r.causal_positions[later], whole.causal_positions[later])) <= 1.0


def test_windows_through_the_api_are_reported_and_as_accurate(rig, slow_run):
    """``window_frames`` through :func:`graph.api.solve`: the report names the windows, the values
    held and where they were settled (all 1200 frames here: shorter than the settled stretch); the 3D
    error equals the whole solve's within 2 %."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        whole = solve(slow_run.keypoints, rig, SolveOptions(fps=120, window_frames=0))
        r = solve(slow_run.keypoints, rig, SolveOptions(fps=120, window_frames=CORE))
    assert whole.report.windows is None
    w = r.report.windows
    assert w["count"] == 4 and w["core_frames"] == CORE and w["margin_frames"] == windows.MARGIN_FRAMES
    assert w["held"]["body"] == "given" and set(w["held"]["body_lengths"]) == set(r.report.body_lengths)
    a, b = np.nanmean(_mm(r.positions, slow_run.positions)), np.nanmean(_mm(whole.positions, slow_run.positions))
    assert a <= 1.02 * b, (a, b)
    assert r.positions.shape == whole.positions.shape and r.reprojections.shape == whole.reprojections.shape
    assert np.array_equal(r.ncams, whole.ncams)
    report = r.report.to_dict()
    json.dumps(report)  # the report is JSON


def test_best_seen_stretch_is_where_the_cameras_see_most():
    valid = np.zeros((100, 2, 3), dtype=bool)
    valid[60:90] = True
    seen = valid.sum(axis=(1, 2))
    assert windows.best_seen(seen, 40) in (50, 60)
    assert windows.best_seen(seen, 200) == 0


@pytest.mark.parametrize("value", [5, -1, 1.5, True])
def test_window_frames_out_of_range_is_refused(value):
    with pytest.raises(ValueError, match="window_frames"):
        SolveOptions(window_frames=value)


def test_the_command_takes_window_frames_and_refuses_a_tiny_one(rig, slow_run, tmp_path):
    """``acinoset solve --window-frames``: a tiny window is one line, not a traceback; a good one
    writes the windows into the report."""
    write_run(replace(slow_run, keypoints=[replace(k, xy=k.xy[:400], likelihood=k.likelihood[:400])
                                           for k in slow_run.keypoints]), tmp_path)
    cams = [str(tmp_path / f"{n}.csv") for n in rig.names]
    base = [sys.executable, "-m", "graph.app.cli", "solve", *cams, "--calibration", str(tmp_path / "calibration.toml"),
            "--fps", "120", "--out", str(tmp_path / "out.csv"), "--report", str(tmp_path / "report.json")]
    bad = subprocess.run(base + ["--window-frames", "5"], capture_output=True, text=True)
    assert bad.returncode != 0 and "window_frames" in bad.stderr and "Traceback" not in bad.stderr
    ok = subprocess.run(base + ["--window-frames", "150"], capture_output=True, text=True)
    assert ok.returncode == 0, ok.stderr
    report = json.loads((tmp_path / "report.json").read_text())
    assert report["windows"]["count"] == 3
