"""The body's proportions and the cameras' clocks estimated with the trajectory (graph.solve.joint,
graph.solve.sync)."""

import json
import subprocess
import sys
from dataclasses import replace

import numpy as np
import pytest

from graph.api import SolveOptions, solve
from graph.simulate import simulate_run
from graph.solve.fte import TrajectoryProblem
from graph.solve.joint import JointState, JointTrajectoryProblem, SharedUnknowns
from graph.solve.problem import build
from graph.solve.sync import coarse_offsets

OFFSETS = [0.0, 0.4, -0.9, 1.3, -0.3, 0.7]


def _problem(run, **options):
    return build(run.keypoints, run.calibration, SolveOptions(fps=run.fps, **options))


def _unknowns(prob, groups=True, cameras=True):
    sk = prob.skeleton
    g = list(range(len(sk.length_groups))) if groups else []
    c = list(range(1, prob.cameras)) if cameras else []
    G = len(g) + len(c)
    return SharedUnknowns(groups=g, bones=[], offset_cameras=c, mean=np.zeros(G), sd=np.ones(G),
                          lower=np.full(G, -5.0), upper=np.full(G, 5.0), scales=np.ones(len(sk.length_groups)),
                          tau=np.zeros(prob.cameras))


def _total_cost(jp, X):
    return jp.normals(X).cost.sum()


def test_length_and_offset_jacobians_match_finite_differences(rig):
    """The gradient of the data cost with respect to W (log lengths, offsets) and the poses, from
    the kernel's normal equations, equals central differences of the cost (plain least squares,
    so the cost is smooth)."""
    run = simulate_run(rig, frames=8, seed=3, outliers=0.0)
    prob = _problem(run, robust=False)
    u = _unknowns(prob)
    jp = JointTrajectoryProblem(prob, run.params.copy(), u)
    rng = np.random.default_rng(0)
    W = np.r_[rng.normal(0, 0.05, len(u.groups)), 0.3, 0.45, 0.6, 0.2, 0.75]
    Q = run.params + rng.normal(0, 0.01, run.params.shape)
    X = JointState(Q, W)
    nrm = jp.normals(X)
    eps = 1e-6
    for k in range(len(W)):
        Wp, Wm = W.copy(), W.copy()
        Wp[k] += eps
        Wm[k] -= eps
        num = (_total_cost(jp, JointState(Q, Wp)) - _total_cost(jp, JointState(Q, Wm))) / (2 * eps)
        assert num == pytest.approx(nrm.gW[k], rel=1e-4, abs=1e-4), k
    # the poses: frame n's gradient gathers its own window and the window before (interpolation)
    for n, p in [(2, 0), (3, 5), (4, 17), (5, 24)]:
        Qp, Qm = Q.copy(), Q.copy()
        Qp[n, p] += eps
        Qm[n, p] -= eps
        num = (_total_cost(jp, JointState(Qp, W)) - _total_cost(jp, JointState(Qm, W))) / (2 * eps)
        assert num == pytest.approx(nrm.g[n, p], rel=1e-4, abs=1e-4), (n, p)


def test_whole_frame_offsets_give_the_neighbouring_frames_projection(rig):
    """A camera one frame late sees at its frame m the pose of frame m+1: the interpolated
    projection at an integer offset is the neighbouring frame's own."""
    run = simulate_run(rig, frames=12, seed=4)
    prob = _problem(run)
    u = _unknowns(prob, groups=False)
    jp = JointTrajectoryProblem(prob, run.params.copy(), u)
    W = np.array([1.0, -2.0, 0.0, 3.0, 1.0])  # cameras 2..6
    uv = jp.normals(JointState(run.params, W)).uv
    plain = TrajectoryProblem(prob, run.params.copy()).normals(run.params).uv  # (N, C, M, 2)
    for c, tau in enumerate([0, 1, -2, 0, 3, 1]):
        for m in range(3, 8):
            np.testing.assert_allclose(uv[m, c], plain[m + tau, c], atol=1e-9, equal_nan=True)


def _run_error(result, run):
    return float(np.nanmean(np.linalg.norm(result.positions - run.positions, axis=-1)))


@pytest.mark.parametrize("name,kw", [
    ("proportions", dict(body_variation=0.15)),
    ("juvenile", dict(body_scale=0.8)),
    ("offsets", dict(time_offsets=OFFSETS)),
    ("all", dict(body_scale=0.85, body_variation=0.15, time_offsets=OFFSETS)),
])
def test_simulated_conditions_recover_lengths_and_offsets(rig, name, kw):
    run = simulate_run(rig, frames=240, seed=5, **kw)
    opts = dict(body="estimate" if "body_scale" in kw or "body_variation" in kw else "model",
                sync="estimate" if "time_offsets" in kw else "given")
    result = solve(run.keypoints, run.calibration, SolveOptions(fps=run.fps, **opts))
    rep = result.report
    if opts["body"] == "estimate":
        # the groups whose markers are seen well: every length but the eyes' spacing (6 cm apart,
        # a few pixels in these cameras) within 5 % of the truth
        for group, true in run.true_lengths.items():
            got = rep.body_lengths[group]
            assert got["std_m"] > 0 and got["model_m"] > 0
            if group != "eye":
                assert got["length_m"] == pytest.approx(true, rel=0.05), group
    if opts["sync"] == "estimate":
        np.testing.assert_allclose(rep.time_offsets_frames, run.time_offsets, atol=0.15)
        assert rep.time_offsets_frames[0] == 0.0
        assert all(s < 0.2 for s in rep.time_offsets_std_frames[1:])
        assert rep.offsets_not_identified == []
    # against the same solver given the truth (the oracle): within 1.2x of its 3D error
    oracle = solve(run.keypoints, run.calibration, SolveOptions(
        fps=run.fps, body="given" if opts["body"] == "estimate" else "model",
        body_lengths=run.true_lengths if opts["body"] == "estimate" else None,
        time_offsets=list(run.time_offsets)))
    assert _run_error(result, run) <= 1.2 * _run_error(oracle, run) + 1e-3


def test_a_still_animal_leaves_the_offsets_at_zero_unidentified(rig):
    """Every frame the same pose (fresh noise per frame): the motion cannot time the cameras."""
    run = simulate_run(rig, frames=120, seed=6, outliers=0.0)
    rng = np.random.default_rng(1)
    still = []
    for kp in run.keypoints:
        xy = np.repeat(kp.xy[:1], run.frames, axis=0) + rng.normal(0, 3.0, kp.xy.shape)
        lik = np.repeat(kp.likelihood[:1], run.frames, axis=0)
        still.append(replace(kp, xy=xy, likelihood=lik))
    coarse = coarse_offsets(run.calibration, _problem(run).meas, _problem(run).valid, run.fps)
    assert coarse.decided.any()  # the moving run times its cameras
    moving = build(still, run.calibration, SolveOptions(fps=run.fps))
    coarse = coarse_offsets(moving.calibration, moving.meas, moving.valid, run.fps)
    assert not coarse.decided[1:].any() and np.all(coarse.frames == 0)
    result = solve(still, run.calibration, SolveOptions(fps=run.fps, sync="estimate"))
    rep = result.report
    assert np.all(np.abs(rep.time_offsets_frames) < 0.3)
    assert set(rep.offsets_not_identified) == set(run.calibration.names[1:])
    assert any("time offsets" in w for w in rep.warnings)


def test_exact_model_in_sync_costs_little(rig):
    """Where the model is exact and the clocks agree, estimating both costs at most 10 % accuracy."""
    run = simulate_run(rig, frames=240, seed=7)
    plain = solve(run.keypoints, run.calibration, SolveOptions(fps=run.fps))
    both = solve(run.keypoints, run.calibration, SolveOptions(fps=run.fps, body="estimate", sync="estimate"))
    assert _run_error(both, run) <= 1.1 * _run_error(plain, run)


def test_given_body_must_name_the_skeletons_lengths(rig):
    run = simulate_run(rig, frames=20, seed=8)
    from graph.errors import InputError

    with pytest.raises(InputError, match="not a length of the cheetah skeleton: tail9"):
        solve(run.keypoints, run.calibration, SolveOptions(fps=run.fps, body="given", body_lengths={"tail9": 0.3}))
    with pytest.raises(ValueError, match="body_lengths"):
        SolveOptions(body="given")
    with pytest.raises(ValueError, match="sync must be"):
        SolveOptions(sync="maybe")


def _cli(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "graph.app.cli", *map(str, args)], capture_output=True, text=True,
                          cwd=cwd, timeout=600)


@pytest.mark.slow  # over 12 s here
def test_cli_body_and_sync_round_trip(tmp_path, rig):
    """--body estimate writes the lengths; a second run of the same animal takes them back
    (--body REPORT); --time-offsets and --sync estimate; bad values are one line, exit 2."""
    sim = _cli("simulate", "--frames", "150", "--seed", "3", "--out", tmp_path / "run")
    assert sim.returncode == 0, sim.stderr
    cams = sorted((tmp_path / "run").glob("cam*.csv"))
    cal = tmp_path / "run" / "calibration.toml"
    rep = tmp_path / "report.json"
    first = _cli("solve", *cams, "--calibration", cal, "--fps", "120", "--body", "estimate", "--sync", "estimate",
                 "--out", tmp_path / "a.csv", "--report", rep, "--h5", tmp_path / "a.h5")
    assert first.returncode == 0, first.stderr
    report = json.loads(rep.read_text())
    assert set(report["body_lengths"]["spine"]) == {"length_m", "std_m", "model_m"}
    assert report["body_lengths"]["spine"]["length_m"] == pytest.approx(0.37, rel=0.05)
    assert len(report["time_offsets_frames"]) == 6 and report["time_offsets_frames"][0] == 0
    import h5py

    with h5py.File(tmp_path / "a.h5") as f:
        names = [n.decode() if isinstance(n, bytes) else n for n in f["body_lengths/names"][()]]
        assert "spine" in names and f["time_offsets_frames"].shape == (6,)
    for body in (rep, tmp_path / "a.h5"):
        again = _cli("solve", *cams, "--calibration", cal, "--fps", "120", "--body", body, "--out", tmp_path / "b.csv",
                     "--report", tmp_path / "b.json")
        assert again.returncode == 0, again.stderr
        got = json.loads((tmp_path / "b.json").read_text())["body_lengths"]["spine"]
        assert got["length_m"] == pytest.approx(report["body_lengths"]["spine"]["length_m"], rel=1e-9)
    given = _cli("solve", *cams, "--calibration", cal, "--fps", "120", "--time-offsets", "0,0,0,0,0,0.5",
                 "--out", tmp_path / "c.csv", "--report", tmp_path / "c.json")
    assert given.returncode == 0, given.stderr
    assert json.loads((tmp_path / "c.json").read_text())["time_offsets_frames"][5] == 0.5
    for bad, words in ((["--time-offsets", "0,x"], "--time-offsets takes numbers"),
                       (["--time-offsets", "0,1"], "time_offsets: 2 given for 6 cameras"),
                       (["--body", tmp_path / "a.csv"], "a.csv: not JSON"),
                       (["--sync", "later"], "invalid choice")):
        proc = _cli("solve", *cams, "--calibration", cal, "--fps", "120", *bad, "--out", tmp_path / "d.csv")
        assert proc.returncode == 2, proc.stderr
        lines = proc.stderr.strip().splitlines()
        assert len(lines) == 1 and words in lines[0], proc.stderr


def _solved_to_the_last_bit(graph, ordering, like):
    """The solution of a linear graph (VectorValues shaped as ``like``), refined from a float64 solve
    of its dense Hessian with residuals in extended precision; and the float64 floor of any solve,
    ``cond(H) eps max|x|``."""
    import gtsam

    H, eta = graph.hessian(ordering)
    x = np.linalg.solve(H, eta)
    for _ in range(3):
        r = eta.astype(np.longdouble) - H.astype(np.longdouble) @ x.astype(np.longdouble)
        x = x + np.linalg.solve(H, r.astype(np.float64))
    out, at = gtsam.VectorValues(), 0
    for i in range(ordering.size()):
        key = ordering.at(i)
        d = like.at(key).shape[0]
        out.insert(key, x[at:at + d])
        at += d
    return out, np.linalg.cond(H) * np.finfo(float).eps * np.abs(x).max()


@pytest.mark.slow  # over 12 s here
def test_the_compiled_joint_step_is_gtsams_elimination(rig):
    """With the body's lengths and the clocks estimated (the frames coupled to their neighbours by
    the offsets, every frame to W): the compiled step solves the same system as GTSAM's elimination
    of the same graph, on the cheetah and on free points whose markers are separate chains sharing
    W. Both are held to the system's solution refined in extended precision, within float64's floor
    for it (``cond(H) eps max|x|``; the system's condition is about 2e7, so ours and GTSAM's can
    differ by a few 1e-9 of W, either nearer the exact one)."""
    import gtsam

    from graph.solve import joint

    taken = []
    original = joint.JointTrajectoryProblem.step

    def step(self, X, nrm, lam):
        if not taken:
            taken.append((self, X, nrm, lam))
        return original(self, X, nrm, lam)

    run = simulate_run(rig, frames=60, seed=3, time_offsets=[0.0, 0.4, -1.3, 0.0, 2.6, 0.0])
    for skeleton in ("cheetah", "points"):
        taken.clear()
        joint.JointTrajectoryProblem.step = step
        try:
            solve(run.keypoints, rig, SolveOptions(fps=run.fps, skeleton=skeleton, sync="estimate", uncertainty=False,
                                                   max_iterations=3))
        finally:
            joint.JointTrajectoryProblem.step = original
        tp, X, nrm, lam = taken[0]
        assert np.any(nrm.Hx) and tp.G > 0
        ours = tp.step(X, nrm, lam)
        graph = tp.joint_graph(X, nrm, lam)
        vv = graph.optimize(tp._ordering)
        exact, floor = _solved_to_the_last_bit(graph, tp._ordering, vv)
        sk = tp.prob.skeleton
        for solved in (ours, vv):
            Q, W = (solved.Q, solved.W) if solved is ours else (tp._solution(solved), solved.at(tp.w_key))
            Q_exact = np.clip(tp._solution(exact), sk.lower, sk.upper)
            assert np.abs(np.clip(Q, sk.lower, sk.upper) - Q_exact).max() <= floor
            assert np.abs(np.clip(W, tp.unknowns.lower, tp.unknowns.upper)
                          - np.clip(exact.at(tp.w_key), tp.unknowns.lower, tp.unknowns.upper)).max() <= floor
        assert 0 < floor < 1e-7
        assert isinstance(vv, gtsam.VectorValues)
