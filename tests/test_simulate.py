"""The simulator: a plausible cheetah run on the real AcinoSet rig and DeepLabCut-like detections."""

from __future__ import annotations

import copy
import json

import numpy as np
import pytest

from graph.app.cli import main
from graph.io.calibration import load_calibration
from graph.io.keypoints import read_keypoints
from graph.io.results import read_anipose_csv
from graph.simulate import (
    GOOD_LIKELIHOOD,
    LOW_LIKELIHOOD,
    ObservationModel,
    load_truth,
    observe,
    rig_stage,
    simulate_run,
)
from graph.skeleton import left_right_pairs, load_skeleton

# the run of the ``run`` fixture (tests/conftest.py)
SIMULATION = dict(frames=240, fps=120.0, noise=5.0, outliers=0.1, outlier_std=100.0, seed=7)


def test_stage_of_the_acinoset_rig(rig):
    stage = rig_stage(rig)
    # every camera's image "down" is world -z: z is up, to within a few degrees
    assert stage.tilt_deg < 4.0
    heights = np.array([c.center[2] for c in rig.cameras])
    assert stage.ground_z == pytest.approx(heights.mean() - 0.5)
    # the middle of the common view lies between the two rows of cameras
    centres = np.array([c.center[:2] for c in rig.cameras])
    assert np.linalg.norm(stage.centre - centres.mean(axis=0)) < 1.0
    assert stage.cameras_seeing_all == 6
    # the track runs along the rows (cameras 1-3 on one side): within 15 degrees of their line
    row = centres[2] - centres[0]
    cos = abs(stage.track @ row) / np.linalg.norm(row)
    assert cos > np.cos(np.radians(15))
    assert 4.0 < stage.half_length < 10.0


def test_same_seed_same_run_other_seed_other_run(rig):
    a = simulate_run(rig, frames=30, seed=3, swaps=0.05, dropouts=1)
    b = simulate_run(rig, frames=30, seed=3, swaps=0.05, dropouts=1)
    c = simulate_run(rig, frames=30, seed=4, swaps=0.05, dropouts=1)
    np.testing.assert_array_equal(a.positions, b.positions)
    for ka, kb in zip(a.keypoints, b.keypoints):
        np.testing.assert_array_equal(ka.xy, kb.xy)
        np.testing.assert_array_equal(ka.likelihood, kb.likelihood)
    assert not np.allclose(a.positions, c.positions)


def test_a_noise_seed_keeps_the_truth_and_draws_new_detections(rig):
    kw = dict(frames=40, noise=5.0, outliers=0.1, seed=3)
    plain = simulate_run(rig, **kw)
    a = simulate_run(rig, noise_seed=0, **kw)
    a2 = simulate_run(rig, noise_seed=0, **kw)
    b = simulate_run(rig, noise_seed=1, **kw)
    for other in (a, b):  # one truth for every detection set
        np.testing.assert_array_equal(other.positions, plain.positions)
        np.testing.assert_array_equal(other.params, plain.params)
        np.testing.assert_array_equal(other.projections, plain.projections)
    for ka, ka2 in zip(a.keypoints, a2.keypoints):  # reproducible
        np.testing.assert_array_equal(ka.xy, ka2.xy)
    det_plain, det_a, det_b = (np.stack([k.xy for k in r.keypoints]) for r in (plain, a, b))
    assert not np.allclose(det_a, det_b) and not np.allclose(det_a, det_plain)
    assert not np.array_equal(a.outlier, b.outlier)
    # independent noise: the two sets' inlier errors are uncorrelated, each still 5 px
    good = ~a.outlier & ~b.outlier & a.visible
    ea, eb = (det_a - a.projections)[good], (det_b - b.projections)[good]
    assert ea.std() == pytest.approx(5.0, rel=0.05) and eb.std() == pytest.approx(5.0, rel=0.05)
    assert abs(np.corrcoef(ea.ravel(), eb.ravel())[0, 1]) < 0.05
    assert plain.noise_seed is None and a.noise_seed == 0


def test_pose_is_plausible_smooth_and_inside_the_joint_bounds(run):
    sk = load_skeleton("cheetah")
    q = run.params
    assert q.shape == (240, sk.n_params)
    assert np.all(q > sk.lower) and np.all(q < sk.upper)
    np.testing.assert_allclose(run.positions, sk.positions(q))
    names = sk.param_names
    front_knees = q[:, [names.index("theta_7"), names.index("theta_9")]]
    back_knees = q[:, [names.index("theta_11"), names.index("theta_13")]]
    assert np.all(front_knees < 0) and np.all(back_knees > 0)
    # the legs really move: each shoulder and hip swings through more than 0.6 rad
    for p in ("theta_6", "theta_8", "theta_10", "theta_12"):
        assert np.ptp(q[:, names.index(p)]) > 0.6
    # head between 0.55 and 0.7 m above the ground
    h = q[:, names.index("z_0")] - run.stage.ground_z
    assert h.min() > 0.55 and h.max() < 0.7
    # feet stay near or above the ground, the back stays above the feet
    assert run.positions[..., 2].min() > run.stage.ground_z - 0.05
    # smooth: the third difference of every marker (the constant-acceleration model's residual)
    # stays under 3 mm per frame at 120 fps
    assert np.abs(np.diff(run.positions, 3, axis=0)).max() < 3e-3
    # speed of a few m/s, and the head faces where it goes
    v = np.gradient(q[:, :2], axis=0) * run.fps
    speed = np.linalg.norm(v, axis=1)
    assert 1.5 < speed.min() and speed.max() < 6.0
    nose = run.positions[:, run.markers.index("nose"), :2] - q[:, :2]
    cos = (v * nose).sum(1) / speed / np.linalg.norm(nose, axis=1)
    assert cos.min() > 0.95


def test_the_animal_stays_in_every_view_even_on_a_long_run(rig):
    long = simulate_run(rig, frames=2000, seed=11, noise=0.0, outliers=0.0)
    assert long.visible.mean() > 0.99
    # it comes round again rather than running off the stage
    xy = long.params[:, :2]
    assert np.linalg.norm(xy - long.stage.centre, axis=1).max() < long.stage.half_length


def test_noise_outliers_and_likelihoods_follow_the_protocol(run):
    det = np.stack([k.xy for k in run.keypoints])
    lik = np.stack([k.likelihood for k in run.keypoints])
    assert det.shape == (6, 240, 20, 2)
    seen = np.isfinite(det).all(axis=-1)
    good = seen & ~run.outlier
    r = (det - run.projections)[good]
    assert r.std() == pytest.approx(5.0, rel=0.03)
    assert abs(r.mean()) < 0.1
    n = seen.sum()
    assert run.outlier.sum() / n == pytest.approx(0.1, abs=0.01)
    off = (det - run.projections)[run.outlier]
    assert off.std() == pytest.approx(np.hypot(100.0, 5.0), rel=0.06)
    assert lik[good].min() >= GOOD_LIKELIHOOD[0] and lik[good].max() <= GOOD_LIKELIHOOD[1]
    confident = lik[run.outlier] >= GOOD_LIKELIHOOD[0]
    assert confident.mean() == pytest.approx(0.3, abs=0.05)
    low = lik[run.outlier][~confident]
    assert low.min() >= LOW_LIKELIHOOD[0] and low.max() <= LOW_LIKELIHOOD[1]
    assert not run.swapped.any() and not run.dropout.any()


def test_the_paper_protocol_with_zero_noise_gives_exact_projections(rig):
    clean = simulate_run(rig, frames=20, noise=0.0, outliers=0.0, seed=1)
    det = np.stack([k.xy for k in clean.keypoints])
    np.testing.assert_array_equal(det, clean.projections)
    np.testing.assert_allclose(clean.projections, rig.project(clean.positions))


def test_left_right_swaps_trade_the_partners_detections(rig):
    sw = simulate_run(rig, frames=120, noise=0.0, outliers=0.0, swaps=0.1, seed=5)
    pairs = left_right_pairs(sw.markers)
    assert len(pairs) == 7  # eyes, shoulders, front knees and ankles, hips, back knees and ankles
    assert ("l_eye", "r_eye") in [(sw.markers[i], sw.markers[j]) for i, j in pairs]
    det = np.stack([k.xy for k in sw.keypoints])
    lik = np.stack([k.likelihood for k in sw.keypoints])
    hits = 0
    for i, j in pairs:
        s = sw.swapped[:, :, i]
        assert np.array_equal(s, sw.swapped[:, :, j])
        np.testing.assert_array_equal(det[:, :, i][s], sw.projections[:, :, j][s])
        np.testing.assert_array_equal(det[:, :, j][s], sw.projections[:, :, i][s])
        assert (lik[:, :, i][s] >= GOOD_LIKELIHOOD[0]).all()  # DLC is sure of its mistake
        np.testing.assert_array_equal(det[:, :, i][~s], sw.projections[:, :, i][~s])
        hits += int(s.sum())
    assert hits / (6 * 120 * len(pairs)) == pytest.approx(0.1, abs=0.02)


def test_a_dropout_blinds_one_camera_for_a_stretch(rig):
    d = simulate_run(rig, frames=100, fps=100.0, dropouts=1, dropout_seconds=0.2, seed=2)
    cams, frames = np.nonzero(d.dropout.any(axis=2))
    assert len(set(cams.tolist())) == 1 and len(frames) == 20
    assert np.ptp(frames) == 19  # one contiguous stretch of 0.2 s
    c = cams[0]
    kp = d.keypoints[c]
    assert np.isnan(kp.xy[frames]).all() and (kp.likelihood[frames] == 0).all()
    others = [k for i, k in enumerate(d.keypoints) if i != c]
    assert all(np.isfinite(k.xy[frames]).all() for k in others)


def test_markers_outside_the_image_are_missing(rig, run):
    narrow = copy.deepcopy(rig)
    cam = narrow.cameras[0]
    cut = int(cam.K[0, 2])
    cam.size = (cut, cam.size[1])  # camera 1 keeps only the left half of its image
    model = ObservationModel(noise_px=0.0, outlier_rate=0.0)
    kps, proj, *_ = observe(narrow, run.positions, run.markers, run.fps, model, np.random.default_rng(0))
    full = rig.project(run.positions)[0]
    outside = full[..., 0] >= cut
    assert 0 < outside.mean() < 1  # the run crosses the cut
    kp = kps[0]
    assert np.isnan(kp.xy[outside]).all() and (kp.likelihood[outside] == 0).all()
    assert np.isnan(proj[0][outside]).all()
    np.testing.assert_array_equal(kp.xy[~outside], full[~outside])
    assert all(np.isfinite(k.xy).all() for k in kps[1:])


def test_points_variant_keeps_the_bodyparts_asked_for(rig):
    parts = ["nose", "l_eye", "r_eye", "spine", "tail_base"]
    sub = simulate_run(rig, frames=10, seed=0, bodyparts=parts)
    full = simulate_run(rig, frames=10, seed=0)
    assert sub.markers == parts
    assert all(k.bodyparts == parts for k in sub.keypoints)
    np.testing.assert_array_equal(sub.positions, full.positions[:, [full.markers.index(p) for p in parts]])
    assert ("nose", "l_eye") in sub.bones and all(a in parts and b in parts for a, b in sub.bones)
    with pytest.raises(ValueError, match="paw"):
        simulate_run(rig, frames=10, bodyparts=["nose", "paw"])


def test_bad_settings_are_refused(rig):
    with pytest.raises(ValueError, match="outlier rate"):
        simulate_run(rig, frames=10, outliers=1.5)
    with pytest.raises(ValueError, match="frames"):
        simulate_run(rig, frames=0)


def test_simulate_command_writes_files_the_solver_reads(tmp_path, capsys):
    out = tmp_path / "sim"
    code = main(["simulate", "--frames", "40", "--fps", "120", "--noise", "2", "--outliers", "0.1",
                 "--outlier-std", "50", "--swaps", "0.01", "--dropouts", "1", "--seed", "9", "--out", str(out)])
    assert code == 0
    assert "simulated 40 frames, 6 cameras, 20 markers" in capsys.readouterr().out
    names = sorted(p.name for p in out.iterdir())
    assert names == ["acinoset_2019_rig.json", "calibration.toml", "cam1.csv", "cam2.csv", "cam3.csv",
                     "cam4.csv", "cam5.csv", "cam6.csv", "simulation.json", "truth.csv", "truth.npz"]
    rig_json = load_calibration(out / "acinoset_2019_rig.json")
    rig_toml = load_calibration(out / "calibration.toml")
    X = np.array([[1.0, 6.0, 0.4], [2.5, 7.0, 0.1]])
    np.testing.assert_allclose(rig_toml.project(X), rig_json.project(X), atol=1e-6)
    # the same run again in memory: the files hold exactly its detections and truth
    again = simulate_run(rig_json, frames=40, fps=120, noise=2, outliers=0.1, outlier_std=50, swaps=0.01,
                         dropouts=1, seed=9)
    for c, kp in enumerate(again.keypoints):
        read = read_keypoints(out / f"cam{c + 1}.csv")
        assert read.bodyparts == again.markers
        np.testing.assert_array_equal(read.xy, kp.xy)
        np.testing.assert_array_equal(read.likelihood, kp.likelihood)
    markers, positions = load_truth(out / "truth.npz")
    assert markers == again.markers
    np.testing.assert_array_equal(positions, again.positions)
    table = read_anipose_csv(out / "truth.csv")
    assert table.markers == again.markers
    np.testing.assert_array_equal(table.positions, again.positions)
    meta = json.loads((out / "simulation.json").read_text())
    assert meta["frames"] == 40 and meta["observation"]["outlier_rate"] == 0.1
    assert meta["dropped"] == int(again.dropout.sum()) > 0


def test_simulate_command_draws_the_animal_and_the_clocks_it_is_told(tmp_path, capsys):
    out = tmp_path / "sim"
    code = main(["simulate", "--frames", "30", "--seed", "4", "--body-scale", "0.8", "--body-variation", "0.1",
                 "--time-offsets", "0,0.5,-1,0.3,0,1.2", "--out", str(out)])
    assert code == 0
    again = simulate_run(load_calibration(out / "acinoset_2019_rig.json"), frames=30, seed=4, body_scale=0.8,
                         body_variation=0.1, time_offsets=[0, 0.5, -1, 0.3, 0, 1.2])
    meta = json.loads((out / "simulation.json").read_text())
    assert meta["time_offsets_frames"] == [0, 0.5, -1, 0.3, 0, 1.2]
    assert meta["true_lengths_m"] == pytest.approx(again.true_lengths)
    model = load_skeleton("cheetah")
    ratios = np.array([meta["true_lengths_m"][g] / L for g, L in zip(model.length_groups, model.model_lengths)])
    assert np.all((ratios > 0.8 * 0.9 - 1e-9) & (ratios < 0.8 * 1.1 + 1e-9)) and ratios.std() > 0.01
    for c, kp in enumerate(again.keypoints):
        np.testing.assert_array_equal(read_keypoints(out / f"cam{c + 1}.csv").xy, kp.xy)


@pytest.mark.parametrize("argv, message", [
    (["--rig", "missing.json"], "missing.json: no such file"),
    (["--time-offsets", "0,1"], "gives 2 offsets for 6 cameras"),
    (["--body-scale", "-1"], "--body-scale must be positive"),
    (["--frames", "0"], "--frames must be at least 1"),
    (["--outliers", "2"], "outlier rate must be in [0, 1]"),
])
def test_simulate_command_bad_input_is_one_line(tmp_path, capsys, argv, message):
    code = main(["simulate", "--out", str(tmp_path / "o"), *argv])
    err = capsys.readouterr().err
    assert code == 2
    assert message in err
    assert err.count("\n") == 1 and "Traceback" not in err
