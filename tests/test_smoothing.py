"""motion_scale="auto": the marginal likelihood of the smoothing, checked against dense algebra,
and recovered on simulated runs whose true smoothness and noise are known."""

from __future__ import annotations

import math

import numpy as np
import pytest

from graph.api import SolveOptions, solve
from graph.io.calibration import default_rig_path, load_calibration
from graph.simulate import random_jerk_run, simulate_run
from graph.skeleton import POINTS_PROCESS_NOISE
from graph.solve.smoothing import STENCILS, ChainEvidence, GroupEvidence, best_scale, difference_gram, motion_band


def _dk(N: int, order: int = 3) -> np.ndarray:
    D = np.zeros((N - order, N))
    for j in range(N - order):
        D[j, j:j + order + 1] = STENCILS[order]
    return D


def _d3(N: int) -> np.ndarray:
    return _dk(N, 3)


@pytest.mark.parametrize("order", [1, 2, 3])
def test_difference_gram_is_dense_dkt_dk(order):
    N = 9
    G = _dk(N, order).T @ _dk(N, order)
    T = difference_gram(N, order)
    for L in range(4):
        np.testing.assert_allclose(T[L, :N - L], np.diagonal(G, -L), atol=0)


def test_motion_band_of_chains_of_mixed_orders_is_the_dense_prior():
    """Three chains of orders 1, 3, 2 (d = 2, their own weights c): the band holds
    sum_i c_gi Dk^T Dk on each chain's block, in LAPACK's lower band form."""
    N, d = 7, 2
    orders = np.array([1, 3, 2])
    c = np.array([[1.0, 2.0], [3.0, 0.5], [0.25, 4.0]])
    ab = motion_band(c, N, orders)
    dense = np.zeros((3 * N * d, 3 * N * d))
    for g, k in enumerate(orders):
        block = sum(c[g, i] * np.kron(_dk(N, k).T @ _dk(N, k), np.diag(np.eye(d)[i])) for i in range(d))
        dense[g * N * d:(g + 1) * N * d, g * N * d:(g + 1) * N * d] = block
    for L in range(ab.shape[0]):
        np.testing.assert_allclose(ab[L, :3 * N * d - L], np.diagonal(dense, -L), atol=0)


@pytest.mark.parametrize("order", [3, 2, 1])
def test_evidence_equals_the_dense_gaussian_evidence(order):
    """For a quadratic data term the banded evidence is the Gaussian marginal likelihood computed
    densely (the detections y ~ N(x, H^-1), the anchor x0 ~ N(x, I/w), x from the motion prior,
    made proper by a tiny eps I whose normaliser does not depend on s), up to a constant."""
    rng = np.random.default_rng(4)
    N, d = 12, 2
    A = rng.normal(size=(N, d, d))
    H = np.einsum("nij,nkj->nik", A, A) + 0.5 * np.eye(d)  # per-frame information
    x = rng.normal(size=(N, d))  # where the quadratic is taken
    y = x + rng.normal(scale=0.3, size=(N, d))  # its minimum
    g = np.einsum("nij,nj->ni", H, x - y)  # gradient at x of 1/2 (x-y)^T H (x-y)
    x0 = y + rng.normal(scale=0.5, size=(N, d))
    w, sigma, eps = 0.05, np.array([0.4, 1.3]), 1e-7
    ev = GroupEvidence(H, g, x, x0, w, sigma, order)
    Hd = np.zeros((N * d, N * d))
    for n in range(N):
        Hd[n * d:(n + 1) * d, n * d:(n + 1) * d] = H[n]
    D = _dk(N, order)
    R = np.block([[np.linalg.inv(Hd), np.zeros((N * d, N * d))], [np.zeros((N * d, N * d)), np.eye(N * d) / w]])
    B = np.vstack([np.eye(N * d), np.eye(N * d)])
    z = np.concatenate([y.ravel(), x0.ravel()])

    def dense(s):
        c = 1.0 / (s * sigma) ** 2
        Am = sum(c[i] * np.kron(D.T @ D, np.diag(np.eye(d)[i])) for i in range(d))
        P = np.linalg.inv(Am + eps * np.eye(N * d))
        S = B @ P @ B.T + R
        # N(0, (Am + eps I)^-1)'s normaliser det(Am + eps I)^(1/2) is pdet(Am)^(1/2) eps^(kd/2) to first
        # order: the improper prior's pdet times a constant, which the differences below cancel
        return -0.5 * z @ np.linalg.solve(S, z) - 0.5 * np.linalg.slogdet(S)[1]

    scales = [0.05, 0.3, 1.0, 4.0]
    ours = np.array([ev(s) for s in scales])
    ref = np.array([dense(s) for s in scales])
    np.testing.assert_allclose(ours - ours[0], ref - ref[0], rtol=1e-5, atol=1e-4)
    s_best = best_scale(ev, lo=1e-3, hi=1e3)
    assert ev(s_best) >= max(ev(s_best * 1.1), ev(s_best / 1.1))


@pytest.mark.parametrize("process_noise, noise_px", [(0.1, 2.0), (0.5, 4.0)])
def test_auto_recovers_the_true_smoothness_and_noise(process_noise, noise_px):
    """Free points moving exactly as the motion model says (graph.simulate.random_jerk_run):
    motion_scale and measurement_std_px 'auto' find the true process noise and detection noise
    within 20 %, and the fitted smoothing is nearer the truth than the default's."""
    cal = load_calibration(default_rig_path())
    run = random_jerk_run(cal, frames=300, process_noise=process_noise, noise=noise_px, seed=2)
    auto = solve(run.keypoints, cal, SolveOptions(skeleton="points", fps=run.fps, motion_scale="auto",
                                                  measurement_std_px="auto"))
    scales = auto.report.motion_scales
    assert set(scales) == set(run.markers)
    fitted = np.array(list(scales.values())) * POINTS_PROCESS_NOISE
    assert np.median(fitted) == pytest.approx(process_noise, rel=0.2)
    assert np.all(np.abs(np.log(fitted / process_noise)) < math.log(1.5))  # every marker within 1.5x
    assert auto.report.sigma_px == pytest.approx(noise_px, rel=0.2)
    fixed = solve(run.keypoints, cal, SolveOptions(skeleton="points", fps=run.fps, measurement_std_px="auto",
                                                   motion_scale=1.0))
    err = lambda r: float(np.nanmean(np.linalg.norm(r.positions - run.positions, axis=-1)))  # noqa: E731
    assert err(auto) < err(fixed)
    assert fixed.report.motion_scales is None


def test_the_default_smoothing_is_fitted_for_free_points_only():
    """No motion_scale given: fte on free points fits it (the scales are reported); with bones, on a
    kinematic skeleton and in ekf it is the fixed 1."""
    cal = load_calibration(default_rig_path())
    run = random_jerk_run(cal, frames=60, process_noise=0.3, noise=2.0, seed=4)
    free = solve(run.keypoints, cal, SolveOptions(skeleton="points", fps=run.fps, uncertainty=False))
    assert set(free.report.motion_scales) == set(run.markers)
    bones = solve(run.keypoints, cal, SolveOptions(skeleton="points", fps=run.fps, uncertainty=False,
                                                   bone_lengths=[(run.markers[0], run.markers[1])]))
    assert bones.report.motion_scales is None
    ekf = solve(run.keypoints, cal, SolveOptions(method="ekf", skeleton="points", fps=run.fps, uncertainty=False))
    assert ekf.report.motion_scales is None
    assert SolveOptions().motion_scale is None


def test_auto_on_a_kinematic_skeleton_and_its_limits():
    """A kinematic skeleton gets one scale ('all'), reported and finite; the option takes only
    positive numbers or 'auto'."""
    cal = load_calibration(default_rig_path())
    run = simulate_run(cal, frames=60, seed=5, outliers=0.0)
    r = solve(run.keypoints, cal, SolveOptions(fps=run.fps, motion_scale="auto", uncertainty=False))
    assert list(r.report.motion_scales) == ["all"]
    assert 1e-6 <= r.report.motion_scales["all"] <= 1e6
    assert r.report.to_dict()["motion_scales"] == r.report.motion_scales
    for bad in ("fast", 0.0, -1.0):
        with pytest.raises(ValueError, match="motion_scale"):
            SolveOptions(motion_scale=bad)


def test_ekf_fits_the_motion_over_its_start_and_stays_a_filter():
    """With the default process noise far too loose for the animal (a cheetah's for points that
    barely move), every frame is its own triangulation and ekf's causal, lag-smoothed and fte's
    trajectories agree to 1e-11 m (the real fly recording did). With 'auto' the ekf fits the
    scales over its start (a quarter of a short run) near fte's, keeps them for the stream, and its
    causal estimate is a filter's: off the smoothed one, which is near fte's."""
    cal = load_calibration(default_rig_path())
    run = random_jerk_run(cal, frames=240, process_noise=0.02, noise=2.0, markers=4, seed=3)
    kw = dict(skeleton="points", fps=run.fps, uncertainty=False)
    fte = solve(run.keypoints, cal, SolveOptions(motion_scale="auto", **kw))
    ekf = solve(run.keypoints, cal, SolveOptions(method="ekf", motion_scale="auto", **kw))
    ratio = np.array(list(ekf.report.motion_scales.values())) / np.array(list(fte.report.motion_scales.values()))
    # this run is smoother than either solver's stiffest smoothing: both fits end at their bounds,
    # sqrt(MAX_STIFFNESS / GTSAM_MAX_STIFFNESS) = 3.16 apart (test_the_stiffest_smoothing_is_the_solvers_bound)
    assert np.all(np.abs(np.log(ratio)) < math.log(3.5)), ratio
    gap = lambda a, b: float(np.nanmedian(np.linalg.norm(a - b, axis=-1)))  # noqa: E731
    causal = gap(ekf.causal_positions, ekf.positions)
    # (2x, not 3x, since ekf's smoothing is its bound's, 3.16x looser than fte's: see above)
    assert causal > 2 * gap(ekf.positions, fte.positions)
    err = lambda r: float(np.nanmean(np.linalg.norm(r.positions - run.positions, axis=-1)))  # noqa: E731
    loose = solve(run.keypoints, cal, SolveOptions(method="ekf", **kw))
    assert err(ekf) < 0.8 * err(loose)


def test_independent_chains_solve_as_gtsam_and_at_the_stiffest_fitted_smoothing():
    """Free points without bones are independent chains, solved by banded Cholesky: the same
    solution as GTSAM's elimination of the same linear graph; and at the stiffest smoothing the fit
    may choose (graph.solve.smoothing.stiffest_scale), with a marker unseen for 40 frames, the solve
    needs no retry and equals a dense solve of the same system."""
    from graph.solve import problem
    from graph.solve.fte import PRIOR_SIGMA, TrajectoryProblem, optimise
    from graph.solve.initial import initial_poses
    from graph.solve.smoothing import stiffest_scale
    from graph.solve.triangulate import robust_points

    cal = load_calibration(default_rig_path())
    run = random_jerk_run(cal, frames=80, markers=3, seed=1)
    for k in run.keypoints:
        k.xy[20:60, 1] = np.nan  # p2 unseen by every camera
    prob = problem.build(run.keypoints, cal, SolveOptions(skeleton="points", fps=run.fps, motion_scale="auto"))
    X, _, _ = robust_points(prob.calibration, prob.meas, prob.valid, prob.sigma_px)
    tp = TrajectoryProblem(prob, np.zeros((prob.frames, prob.skeleton.n_params)), None)
    tp.Q0 = initial_poses(prob, X)
    assert tp.chains and tp._motion_graph is None  # no GTSAM factors built for the chains
    nrm = tp.normals(tp.Q0)
    ours = tp.solve_linear(tp.Q0, nrm.H, nrm.g, 1e-3)
    theirs = tp._solution(tp.linear_graph(tp.Q0, nrm.H, nrm.g, 1e-3).optimize(tp._ordering))
    np.testing.assert_allclose(ours, theirs, rtol=0, atol=1e-9 * np.abs(theirs).max())

    w = 1.0 / PRIOR_SIGMA**2
    lo = np.array([stiffest_scale(nrm.H[:, i][:, :, i], tp.base_sigma3[i], w) for i in tp.groups])
    tp.set_motion_scales(lo)
    ours = tp.solve_linear(tp.Q0, nrm.H, nrm.g, 0.0)
    N, P = tp.N, tp.P
    K = np.zeros((N * P, N * P))
    for n in range(N):
        K[n * P:(n + 1) * P, n * P:(n + 1) * P] = nrm.H[n] + w * np.eye(P)
    D = np.kron(_d3(N), np.eye(P)) / tp.sigma3[None].repeat(N - 3, 0).ravel()[:, None]
    K += D.T @ D
    rhs = (np.einsum("npq,nq->np", nrm.H, tp.Q0) - nrm.g + w * tp.Q0).ravel()
    dense = np.linalg.solve(K, rhs).reshape(N, P)
    assert np.abs(ours - dense).max() <= 1e-6 * np.abs(dense).max()
    Q, _, _ = optimise(tp, tp.Q0.copy(), 20, stretches=(1.0,))
    assert np.isfinite(Q).all()


def test_a_motion_model_far_looser_than_the_motion_is_named():
    """A process noise far above what the detections resolve (as a cheetah's on a fly's legs, or
    here a scale of 10^4 on a cheetah run) smooths nothing, and the report says so; at the default,
    or fitted, it says nothing."""
    cal = load_calibration(default_rig_path())
    run = simulate_run(cal, frames=120, seed=6)
    for skeleton in ("cheetah", "points"):
        kw = dict(skeleton=skeleton, fps=run.fps, uncertainty=False)
        loose = solve(run.keypoints, cal, SolveOptions(motion_scale=1e4, **kw))
        assert any("looser than the motion" in w for w in loose.report.warnings)
        for scale in (1.0, "auto"):
            r = solve(run.keypoints, cal, SolveOptions(motion_scale=scale, **kw))
            assert not any("looser than the motion" in w for w in r.report.warnings)


def test_the_stiffest_smoothing_is_the_solvers_bound():
    """A run smoother than the stiffest smoothing the fit may choose: fte's chains (LAPACK's banded
    Cholesky) stop at MAX_STIFFNESS times the data's information, ekf's stream (GTSAM, whose clique
    Cholesky gives up at a 2^24 spread of pivots) at GTSAM_MAX_STIFFNESS, so its scales are
    sqrt(MAX_STIFFNESS / GTSAM_MAX_STIFFNESS) looser; both solve."""
    from graph.solve.smoothing import GTSAM_MAX_STIFFNESS, MAX_STIFFNESS

    cal = load_calibration(default_rig_path())
    run = random_jerk_run(cal, frames=240, process_noise=1e-4, noise=2.0, markers=4, seed=3)
    kw = dict(skeleton="points", fps=run.fps, uncertainty=False, motion_scale="auto")
    fte = solve(run.keypoints, cal, SolveOptions(**kw))
    ekf = solve(run.keypoints, cal, SolveOptions(method="ekf", **kw))
    ratio = np.array(list(ekf.report.motion_scales.values())) / np.array(list(fte.report.motion_scales.values()))
    np.testing.assert_allclose(ratio, math.sqrt(MAX_STIFFNESS / GTSAM_MAX_STIFFNESS), rtol=0.1)
    assert np.isfinite(fte.positions).all() and np.isfinite(ekf.positions).all()


@pytest.mark.parametrize("order, process_noise", [(1, 0.002), (3, 0.5)])
def test_auto_order_finds_the_order_the_points_moved_by(order, process_noise):
    """Free points whose k-th differences are white (graph.simulate.random_jerk_run: a random walk
    for k = 1, constant acceleration's model for k = 3), 2 px noise: motion_order 'auto' chooses k
    for every marker (the fractional Bayes factor; the plain evidence is defined only up to a
    constant of the order), reports it, and is as accurate as the true order given."""
    cal = load_calibration(default_rig_path())
    run = random_jerk_run(cal, frames=300, process_noise=process_noise, noise=2.0, seed=2, order=order)
    kw = dict(skeleton="points", fps=run.fps, motion_scale="auto", uncertainty=False)
    auto = solve(run.keypoints, cal, SolveOptions(motion_order="auto", **kw))
    assert auto.report.motion_orders == {m: order for m in run.markers}
    given = solve(run.keypoints, cal, SolveOptions(motion_order=order, **kw))
    err = lambda r: float(np.nanmean(np.linalg.norm(r.positions - run.positions, axis=-1)))  # noqa: E731
    assert err(auto) == pytest.approx(err(given), rel=0.02)
    assert given.report.motion_orders == {m: order for m in run.markers}  # the order the scales are for
    other = solve(run.keypoints, cal, SolveOptions(motion_order=4 - order, **kw))
    assert err(auto) < err(other)


def test_fractional_evidence_does_not_depend_on_the_anchor_width():
    """The order comparison's verdict is the data's: the anchor's precision w, the only other
    proper part of the prior, changes the fractional Bayes factor between orders by little."""
    rng = np.random.default_rng(7)
    N, d = 200, 1
    t = np.arange(N) / N
    y = np.sin(6 * t)[:, None] + rng.normal(scale=0.01, size=(N, d))
    H = np.full((N, d, d), 1e4)
    x = y.copy()
    g = np.zeros((N, d))
    verdicts = []
    for w in (1e-4, 1e-2, 1.0):
        values = [ChainEvidence(H[None], g[None], x[None], y[None], w, np.ones((1, d)), np.array([k])).across_orders(
            np.array([s])) for k, s in ((1, 0.1), (3, 1e-3))]
        verdicts.append(float(values[1][0] - values[0][0]))
    assert max(verdicts) - min(verdicts) < 0.05 * abs(verdicts[0])


def test_motion_order_options():
    """motion_order takes 1, 2, 3 or 'auto'; other methods keep 3; 'auto' needs the scale fitted."""
    for bad in (0, 4, "fast", True):
        with pytest.raises(ValueError, match="motion_order"):
            SolveOptions(motion_order=bad)
    with pytest.raises(ValueError, match="motion_order"):
        SolveOptions(method="ekf", motion_order=1)
    cal = load_calibration(default_rig_path())
    run = random_jerk_run(cal, frames=40, markers=2, seed=1)
    with pytest.raises(ValueError, match="motion_scale 'auto'"):
        solve(run.keypoints, cal, SolveOptions(skeleton="points", fps=run.fps, motion_scale=1.0, motion_order="auto"))


def test_fitted_smoothing_given_back_solves_the_same_run_without_fitting():
    """A report's motion_scales and motion_orders given back as options (a lab fits one run and
    solves the rest of the session with its smoothing) land on the trajectory the fit solved, at a
    fraction of the time; a map that does not name this solve's groups is refused, naming them."""
    import time

    from graph.errors import InputError

    cal = load_calibration(default_rig_path())
    run = random_jerk_run(cal, frames=300, process_noise=0.002, noise=2.0, seed=4, order=1)
    kw = dict(skeleton="points", fps=run.fps, uncertainty=False)
    t0 = time.perf_counter()
    fitted = solve(run.keypoints, cal, SolveOptions(motion_scale="auto", motion_order="auto", **kw))
    t1 = time.perf_counter()
    given = solve(run.keypoints, cal, SolveOptions(motion_scale=fitted.report.motion_scales,
                                                   motion_order=fitted.report.motion_orders, **kw))
    t2 = time.perf_counter()
    assert set(fitted.report.motion_orders.values()) == {1}
    assert given.report.motion_scales is None  # given, not fitted
    err = lambda r: float(np.nanmean(np.linalg.norm(r.positions - run.positions, axis=-1)))  # noqa: E731
    assert err(given) == pytest.approx(err(fitted), rel=0.02)
    assert np.nanmax(np.abs(given.positions - fitted.positions)) < 0.1 * err(fitted)
    assert t2 - t1 < t1 - t0
    wrong = {f"{m}_x": s for m, s in fitted.report.motion_scales.items()}
    with pytest.raises(InputError, match="missing .*; unknown "):
        solve(run.keypoints, cal, SolveOptions(motion_scale=wrong, **kw))
