"""The solvers' own guarantees: gradients of the compiled cost, joint bounds at the solution,
degenerate data reported rather than crashing, and the report's fields."""

import warnings
from dataclasses import replace

import numpy as np
import pytest

from graph.api import SolveOptions, solve
from graph.simulate import simulate_run
from graph.solve.fte import TrajectoryProblem
from graph.solve.problem import build
from graph.solve.robust import redescending

# the run of the ``run`` fixture (tests/conftest.py)
SIMULATION = dict(frames=90, fps=120, noise=3.0, outliers=0.1, outlier_std=100, seed=11)


def test_redescending_loss_pieces():
    s = np.array([0.0, 2.0, 3.0, 5.0, 10.0, 15.0, 20.0, 50.0])
    rho, w = redescending(s)
    assert rho[1] == pytest.approx(2.0)  # s^2/2
    assert rho[3] == pytest.approx(3 * 5 - 4.5)  # a s - a^2/2
    assert rho[-1] == pytest.approx(40.5) and rho[-2] == pytest.approx(40.5)
    assert w[1] == 1.0 and w[3] == pytest.approx(3 / 5) and w[-1] == 0.0
    # continuous, with a continuous derivative (w s) at the knots
    eps = 1e-7
    for knot in (3.0, 10.0, 20.0):
        lo, hi = redescending(np.array([knot - eps, knot + eps]))
        assert abs(lo[1] - lo[0]) < 1e-5
        assert abs(hi[0] * (knot - eps) - hi[1] * (knot + eps)) < 1e-5


def test_kernel_gradient_matches_finite_differences(run):
    prob = build(run.keypoints, run.calibration, SolveOptions(method="fte"))
    Q = run.params[:3] + 0.01
    # the problem is frozen
    prob = replace(prob, meas=prob.meas[:3], valid=prob.valid[:3], likelihood=prob.likelihood[:3])
    tp = TrajectoryProblem(prob, Q)
    H, g, _, s, w, cost = tp.normals(Q)
    eps = 1e-6
    for n in range(3):
        num = np.zeros(25)
        for j in range(25):
            Qp, Qm = Q.copy(), Q.copy()
            Qp[n, j] += eps
            Qm[n, j] -= eps
            num[j] = (tp.normals(Qp)[5][n] - tp.normals(Qm)[5][n]) / (2 * eps)
        assert np.allclose(g[n], num, rtol=1e-4, atol=1e-3 * np.abs(num).max())
        assert np.allclose(H[n], H[n].T)
        assert np.linalg.eigvalsh(H[n]).min() > -1e-9


def test_fte_respects_joint_bounds_and_reports(run):
    res = solve(run.keypoints, run.calibration, SolveOptions(method="fte", fps=run.fps))
    from graph.skeleton import load_skeleton

    sk = load_skeleton("cheetah")
    assert (res.params >= sk.lower - 1e-3).all() and (res.params <= sk.upper + 1e-3).all()
    err = np.linalg.norm(res.positions - run.positions, axis=-1)
    assert np.nanmean(err) < 0.02
    assert np.isfinite(res.std).all() and (res.std > 0).all()
    assert res.rates.shape == res.params.shape
    r = res.report.to_dict()
    for key in ("method", "frames", "cameras", "seconds", "iterations", "cost", "reprojection_rmse_px"):
        assert key in r
    assert r["frames"] == 90 and r["cameras"] == 6 and r["iterations"] >= 1
    assert set(r["seconds"]) >= {"total", "init", "solve"}
    assert r["reprojection_rmse_px"] < 6


def test_degenerate_data_is_reported_not_fatal(run):
    kps = [k for k in run.keypoints]
    # the tail tip is seen by one camera only, and camera 2 is blind for the first second
    for c, k in enumerate(kps):
        j = k.bodyparts.index("tail2")
        if c > 0:
            k.likelihood[:, j] = 0.0
    kps[1].likelihood[:] = 0.0
    for method in ("tri", "fte", "ekf"):
        res = solve(kps, run.calibration, SolveOptions(method=method, fps=run.fps))
        assert "tail2" in res.report.unconstrained_markers
        if method == "tri":
            assert np.isnan(res.positions[:, res.markers.index("tail2")]).all()
        else:  # the skeleton carries it
            assert np.isfinite(res.positions).all()
        others = [m for m in range(len(res.markers)) if res.markers[m] != "tail2"]
        err = np.linalg.norm(res.positions[:, others] - run.positions[:, others], axis=-1)
        assert np.nanmedian(err) < 0.05, method


def test_frames_with_nothing_seen_twice(rig):
    run = simulate_run(rig, frames=60, fps=120, noise=2.0, outliers=0.0, seed=5)
    for k in run.keypoints[1:]:
        k.likelihood[20:30] = 0.0
    res = solve(run.keypoints, run.calibration, SolveOptions(method="fte", fps=run.fps))
    assert res.report.unconstrained_frames == list(range(20, 30))
    err = np.linalg.norm(res.positions - run.positions, axis=-1)
    assert np.isfinite(err).all() and np.median(err[20:30]) < 0.1  # bridged by the motion model


@pytest.mark.parametrize("method", ["tri", "fte", "ekf"])
def test_points_skeleton_any_bodyparts(rig, method):
    parts = ["nose", "l_eye", "r_eye", "neck_base", "spine", "tail_base"]
    run = simulate_run(rig, frames=60, fps=120, noise=3.0, outliers=0.05, seed=2, bodyparts=parts)
    res = solve(run.keypoints, run.calibration,
                SolveOptions(method=method, skeleton="points", fps=run.fps,
                             bone_lengths=[("neck_base", "spine"), ("spine", "tail_base")]))
    assert res.markers == parts
    err = np.linalg.norm(res.positions - run.positions, axis=-1)
    assert np.nanmedian(err) < 0.03


def test_ekf_reports_per_frame_time_and_causal_estimates(run):
    res = solve(run.keypoints, run.calibration, SolveOptions(method="ekf", fps=run.fps))
    pf = res.report.per_frame_ms
    assert pf["median"] > 0 and pf["p95"] >= pf["median"]
    assert res.causal_positions.shape == res.positions.shape
    causal = np.nanmean(np.linalg.norm(res.causal_positions - run.positions, axis=-1))
    smooth = np.nanmean(np.linalg.norm(res.positions - run.positions, axis=-1))
    assert smooth < 0.03 and causal < 0.05


def test_millimetre_calibration_is_recognised(rig, run):
    from dataclasses import replace

    mm = replace(rig, cameras=[replace(c, t=c.t * 1000.0) for c in rig.cameras], source="calibration.toml")
    with pytest.warns(UserWarning, match="millimetres"):
        res = solve(run.keypoints, mm, SolveOptions(method="tri", fps=run.fps))
    assert any("millimetres" in w for w in res.report.warnings)
    err = np.linalg.norm(res.positions - run.positions, axis=-1)
    assert np.nanmedian(err) < 0.05  # metres, as if the rig had been given in metres
    same = solve(run.keypoints, mm, SolveOptions(method="tri", fps=run.fps, calibration_units="mm"))
    assert np.allclose(same.positions, res.positions, equal_nan=True)


def test_uncertainty_can_be_skipped(run):
    res = solve(run.keypoints, run.calibration, SolveOptions(method="fte", fps=run.fps, uncertainty=False))
    assert np.isnan(res.std).all() and np.isfinite(res.positions).all()
    assert "uncertainty" in res.report.seconds


def test_initial_poses_from_exact_points_are_exact(rig):
    """Inverse kinematics on the true 3D points gives back the true pose: under a millimetre on
    average (the weak pull towards the previous frame, and the 5-frame running median the points go
    through first, cost at most a few millimetres where the legs swing fastest: 4 without the median,
    5.6 with it)."""
    from graph.solve.initial import initial_poses

    run = simulate_run(rig, frames=120, fps=120, noise=0.0, outliers=0.0, seed=2)
    prob = build(run.keypoints, run.calibration, SolveOptions(method="fte", fps=run.fps))
    X = np.full((run.frames, len(prob.skeleton.markers), 3), np.nan)
    X[:, [prob.skeleton.markers.index(m) for m in run.markers]] = run.positions
    Q = initial_poses(prob, X)
    err = np.linalg.norm(prob.skeleton.positions(Q) - X, axis=-1)
    assert np.nanmean(err) < 1e-3 and np.nanmax(err) < 7e-3, \
        f"{np.nanmean(err) * 1000:.1f}, {np.nanmax(err) * 1000:.1f} mm"


@pytest.mark.parametrize("seed", [1, 2])
def test_fte_keeps_the_tail_on_one_branch_through_many_outliers(rig, seed):
    """20 % confident outliers: these runs once ended with the tail 0.1-0.15 m off (the start
    flipped the tail's two equivalent (psi, theta) between frames and turned the yaw by a full
    turn); every marker must now be recovered to under 15 mm on average."""
    run = simulate_run(rig, frames=200, fps=120, noise=2.0, outliers=0.2, outlier_std=100, seed=seed,
                       confident_outliers=1.0)
    res = solve(run.keypoints, run.calibration, SolveOptions(method="fte", fps=run.fps, uncertainty=False))
    per_marker = np.nanmean(np.linalg.norm(res.positions - run.positions, axis=-1), axis=0)
    assert per_marker.max() < 0.015, dict(zip(run.markers, (per_marker * 1000).round(1)))


@pytest.mark.parametrize("skeleton,bones", [("cheetah", False), ("points", True), ("points", False)])
def test_marginal_covariances_are_the_bayes_trees(rig, skeleton, bones):
    """The compiled chain recursion gives GTSAM's numbers: the Bayes tree of the same undamped
    linear graph, queried frame by frame (long enough for rounding to show if it compounded)."""
    from graph.solve import fte
    from graph.solve.initial import initial_poses
    from graph.solve.triangulate import triangulate

    run = simulate_run(rig, frames=150, fps=120, noise=5.0, outliers=0.1, outlier_std=100, seed=4)
    opts = SolveOptions(method="fte", fps=run.fps, skeleton=skeleton,
                        bone_lengths=list(run.bones) if bones else None)
    prob = build(run.keypoints, run.calibration, opts)
    X, _, _, _ = triangulate(prob.calibration, prob.meas, prob.valid, prob.sigma_px)
    tp = TrajectoryProblem(prob, initial_poses(prob, X), fte.bone_lengths(prob, X) if skeleton == "points" else None)
    Q, _, _ = fte.optimise(tp, tp.Q0.copy(), 50)
    H, g, _, _, _, _ = tp.normals(Q, 1.0)
    ours = tp.marginal_covariances(H)
    bt = tp.linear_graph(Q, H, g, 0.0).eliminateMultifrontal(tp._ordering)
    for gi, idx in enumerate(tp.groups):
        a, b = idx[0], idx[-1] + 1
        theirs = np.stack([bt.marginalCovariance(tp.key(n, gi)) for n in range(tp.N)])
        assert np.abs(ours[:, a:b, a:b] - theirs).max() <= 1e-7 * np.abs(theirs).max()
    assert np.all(np.linalg.eigvalsh(ours[:, :3, :3]) > 0)


@pytest.mark.parametrize("skeleton,order", [("cheetah", 3), ("points", 3), ("points", 1)])
def test_the_compiled_chain_solve_is_gtsams_elimination(rig, skeleton, order):
    """One group (the cheetah, or free points joined by bones): the damped step by the compiled
    block Cholesky equals GTSAM's elimination of the same linear graph, in each order."""
    from graph.solve import fte
    from graph.solve.initial import initial_poses
    from graph.solve.triangulate import triangulate

    run = simulate_run(rig, frames=150, fps=120, noise=5.0, outliers=0.1, outlier_std=100, seed=4)
    opts = SolveOptions(method="fte", fps=run.fps, skeleton=skeleton, motion_order=order,
                        bone_lengths=list(run.bones) if skeleton == "points" else None)
    prob = build(run.keypoints, run.calibration, opts)
    X, _, _, _ = triangulate(prob.calibration, prob.meas, prob.valid, prob.sigma_px)
    tp = TrajectoryProblem(prob, initial_poses(prob, X), fte.bone_lengths(prob, X) if skeleton == "points" else None)
    assert not tp.chains and tp._motion_graph is None  # GTSAM's factors are not built to solve
    nrm = tp.normals(tp.Q0, 4.0)
    for lam in (1e-3, 0.0):
        ours = tp.solve_linear(tp.Q0, nrm.H, nrm.g, lam)
        theirs = tp._solution(tp.linear_graph(tp.Q0, nrm.H, nrm.g, lam).optimize(tp._ordering))
        assert np.abs(ours - theirs).max() <= 1e-9 * np.abs(theirs).max()


def test_running_median_and_mean_equal_scipy_ndimage_with_nearest_ends():
    from scipy.ndimage import median_filter, uniform_filter1d

    from graph.solve.initial import running

    rng = np.random.default_rng(0)
    for shape in [(3,), (30,), (50, 3), (40, 20, 3)]:
        x = rng.normal(size=shape)
        np.testing.assert_array_equal(running(x, 9), median_filter(x, size=(9,) + (1,) * (x.ndim - 1), mode="nearest"))
        np.testing.assert_allclose(running(x, 5, np.mean), uniform_filter1d(x, 5, axis=0, mode="nearest"), atol=1e-12)


def test_the_start_leaves_a_wrong_tail_branch_a_frame_of_outliers_put_it_on():
    """A ring-rig run in which one frame's badly triangulated tail tip used to fold the start's tail
    back for the next 190 frames (tip 0.2-0.35 m off, while the triangulation was within 4 cm):
    the inverse kinematics restarts a frame that fits its points badly."""
    from dataclasses import replace

    from graph.simulate import ring_rig
    from graph.solve import problem
    from graph.solve.initial import initial_poses
    from graph.solve.sync import on_reference_clock
    from graph.solve.triangulate import robust_points

    cal = ring_rig()
    offsets = [0.0, -1.3296629253961518, 0.0006468124238119266, 0.6361422587418959]  # the bench's draw, seed 1
    run = simulate_run(cal, frames=300, fps=90.0, seed=1, confident_outliers=1.0, body_scale=0.814407438450299,
                       body_variation=0.15, time_offsets=offsets)
    prob = problem.build(run.keypoints, cal, SolveOptions(fps=90.0, body="given", body_lengths=run.true_lengths,
                                                          time_offsets=offsets))
    meas, valid = on_reference_clock(prob.meas, prob.valid, np.round(offsets))
    X, _, _ = robust_points(cal, meas, valid, prob.sigma_px)
    sk = prob.skeleton.scaled(prob.skeleton.scales_for(run.true_lengths))
    Q0 = initial_poses(replace(prob, skeleton=sk, meas=meas, valid=valid), X)
    tip = run.markers.index("tail2")
    start = np.linalg.norm(sk.positions(Q0)[:, tip] - run.positions[:, tip], axis=-1)
    tri = np.linalg.norm(X[:, tip] - run.positions[:, tip], axis=-1)
    good = tri < 0.04
    assert good.sum() > 250
    assert np.percentile(start[good], 95) < 0.06, np.percentile(start[good], 95)


@pytest.mark.parametrize("length_over_noise", [0.5, 1.5, 4.0, 20.0])
def test_a_bone_measured_between_noisy_points_is_not_longer_than_the_bone(length_over_noise):
    """The median of ``|L e + n|``, ``n ~ N(0, tau^2 I_3)``, is longer than ``L`` (at ``L = tau``
    by some 60 %); :func:`unbiased_length` gives ``L`` back from it (within the sample's own
    scatter), and NaN where the distances are no longer than the noise alone makes them."""
    from graph.solve.initial import unbiased_length

    tau, L = 0.08, 0.08 * length_over_noise
    n = np.random.default_rng(int(length_over_noise * 10)).normal(0, tau, (200_000, 3))
    d = np.linalg.norm(np.array([L, 0.0, 0.0]) + n, axis=1)
    assert np.median(d) > L * 1.001
    assert unbiased_length(float(np.median(d)), tau) == pytest.approx(L, rel=0.02, abs=0.002)
    assert np.isnan(unbiased_length(0.9 * tau, tau))


def test_between_frames_on_the_reference_clock():
    """Camera c's detections at the reference frames ``n - tau_c``: exact for a marker moving at constant
    speed, the nearer frame where one of the two is missing, none where the nearer one is."""
    from graph.solve.sync import between_frames_on_reference_clock

    N, C, M = 10, 2, 1
    n = np.arange(N, dtype=float)
    meas = np.zeros((N, C, M, 2))
    meas[:, :, 0, 0] = 3.0 * n[:, None]  # x moves 3 px a frame in both cameras
    meas[:, :, 0, 1] = 7.0
    valid = np.ones((N, C, M), bool)
    valid[5, 1] = False
    out, ok = between_frames_on_reference_clock(meas, valid, np.array([0.0, 1.25]))
    assert np.allclose(out[:, 0, 0, 0], 3.0 * n) and ok[:, 0].all()
    # camera 2, reference frame n is its time n - 1.25: frames n - 2 and n - 1 at w = 0.75
    inside = [k for k in range(2, N) if k - 2 != 5 and k - 1 != 5]
    assert np.allclose(out[inside, 1, 0, 0], 3.0 * (n[inside] - 1.25)) and ok[inside, 1].all()
    assert not ok[0, 1].any() and np.isnan(out[0, 1]).all()  # time -1.25: before its first frame
    assert ok[1, 1, 0] and out[1, 1, 0, 0] == 0.0  # time -0.25: its frame 0, the nearer, alone
    # frame 5 missing: at k = 6 (frames 4 and 5, w = 0.75) the nearer is missing, at k = 7 (5 and 6) it is 6
    assert not ok[6, 1, 0] and ok[7, 1, 0] and out[7, 1, 0, 0] == 18.0
    # and back: positions moving at constant speed on the reference clock, at each camera's frames
    from graph.solve.sync import on_camera_clocks

    X = np.zeros((N, 1, 3))
    X[:, 0, 0] = 0.5 * n
    at = on_camera_clocks(X, np.array([0.0, 1.25, -0.5]))
    assert np.allclose(at[0, :, 0, 0], 0.5 * n)
    assert np.allclose(at[1, :8, 0, 0], 0.5 * (n[:8] + 1.25)) and np.isnan(at[1, 8:]).all()  # past the run's end
    assert np.isnan(at[2, 0]).all() and np.allclose(at[2, 1:, 0, 0], 0.5 * (n[1:] - 0.5))


def test_ekf_with_clocks_off_draws_on_each_cameras_own_frames(rig):
    """The stream takes detections interpolated to the reference clock; what is drawn over each camera's
    video is still that camera's own: its detections as given, and the trajectory projected where its
    frames were taken (0.24 px from the true projections at the median, as fte's; on the nearest
    reference frame it was 1.13 px), with the residuals against those detections."""
    run = simulate_run(rig, frames=240, fps=120.0, seed=5, noise=2.0, outliers=0.0,
                       time_offsets=[0, 0.4, -0.7, 1.3, 0.2, -0.3])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        r = solve(run.keypoints, rig, SolveOptions(fps=120.0, method="ekf", sync="estimate"))
    for c, k in enumerate(run.keypoints):
        assert np.array_equal(r.detections[c], k.xy, equal_nan=True) and np.array_equal(r.likelihood[c], k.likelihood)
    assert np.nanmedian(np.linalg.norm(r.reprojections - run.projections, axis=-1)) < 0.4
    ok = np.isfinite(r.residuals)
    assert ok.sum() > 0.9 * np.isfinite(r.detections).all(axis=-1).sum()
    assert np.allclose(r.residuals[ok], np.linalg.norm(r.reprojections - r.detections, axis=-1)[ok])
