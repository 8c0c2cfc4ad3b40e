"""Incremental estimation (``--method ekf``): a GTSAM fixed-lag smoother fed one frame at a time.

This stands in for the paper's Extended Kalman Filter and works on a stream: :class:`OnlineSmoother`
takes one frame's detections per :meth:`~OnlineSmoother.push` and returns that frame's causal
estimate at once; :meth:`~OnlineSmoother.finish` returns the lag-smoothed trajectory.

Per frame n:

1. **Predict** with the constant-acceleration model: ``q^-_n = 3 q_{n-1} - 3 q_{n-2} + q_{n-3}``.
2. **Refine** the new pose on its own frame (a few damped Gauss-Newton steps on the robust
   reprojection cost plus ``1/2 |(q - q^-_n) / sigma_pred|^2``). The redescending loss does the outlier
   rejection: a detection beyond c = 20 sigma from the refined pose gets no weight, one beyond
   b = 10 sigma almost none (the paper's EKF gates innovations at 3 sigma instead).
3. **Update** an ``IncrementalFixedLagSmoother`` (iSAM2 inside, lag ``lag_seconds``) with the frame's
   measurement factor linearised at the refined pose (a ``HessianFactor`` wrapped as a
   ``LinearContainerFactor``, so GTSAM never calls back into Python) and the 4-key
   constant-acceleration factor linking it to the three frames before.
4. **Relinearise** every ``RELINEARISE_EVERY`` frames: the measurement factor of each frame in the
   window whose smoothed pose has moved is replaced by one linearised there (with its robust
   weights recomputed), in the same iSAM2 update. A factor kept at the causal pose for good makes
   the smoothed trajectory one Gauss-Newton step from the causal one: about 1.7x the batch error,
   with standard deviations 2x too narrow; relinearised, the lag-smoothed trajectory is within a few
   per cent of ``fte`` (bench/RESULTS.md).
5. **Restart a lost marker.** After a stretch with fewer cameras the estimate can end far enough
   from a marker that the redescending loss rejects every camera's detection of it (weight 0,
   beyond c), and the prediction keeps it lost while every camera sees it. A marker that
   :data:`RESTART_VIEWS` cameras or more see, all rejected, is lost: the frame is refined again from
   a pose with the lost markers where the cameras triangulate them (the prediction weighted by
   :data:`RESTART_PRIOR` only), and that pose is kept when it lowers the frame's robust cost by
   :data:`RESTART_GAIN` a lost marker. The report counts the frames restarted. On
   ``bench/bench_dropout.py``'s seed 1 the tail tip stayed 0.7 m off for 1,200 frames without it
   (ekf 2.3x fte's error after the drop-outs), 1.07x with it.

6. **No depth, no stream.** Where no marker is seen by two cameras for at least the lag, the
   stream has only its motion model for depth, and what it gives there depends on rounding: on
   ``bench/bench_dropout.py``'s runs (camera 3 alone for 500 frames) 0.001 px of jitter moved its
   error there between 0.1 and 2 m. Holding those frames in the window until two cameras see
   again, or a convex loss on them, did not steady it (bench/RESULTS.md, section 28). So each such
   stretch is solved after the stream as one ``fte`` batch over it and :data:`BATCH_MARGIN_SECONDS`
   either side, with the stream's body and motion model; the smoothed trajectory takes the batch's
   poses over the stretch and into each margin up to the frame where the two agree best (the stream
   can go astray on the way into the stretch or come back slowly after it), the causal estimates stay
   the stream's, and the report says so.

The first few frames are solved as a small batch (:mod:`graph.solve.fte`) to start from a good pose: a
per-frame start from nothing diverges. With ``motion_scale="auto"`` the batch is the first
``SHARED_START_SECONDS`` (or a quarter of a shorter run) and fits the motion model's scales
(:func:`graph.solve.fte.fit_motion`, the marginal likelihood), which the stream then keeps. The default
process noise is a cheetah's, some 10^4 times too loose for a fly's legs: with it every frame is
its own triangulation, and the lag-smoothed and causal trajectories equal fte's to 1e-11 m.
"""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass, replace

import gtsam
import numpy as np

from graph.skeleton import Skeleton
from graph.solve import kernels
from graph.solve.fte import PRIOR_SIGMA, TrajectoryProblem, bone_lengths, optimise, refit_motion, trajectory_result
from graph.solve.initial import initial_poses
from graph.solve.joint import shares_unknowns, solve_fte_joint
from graph.solve.problem import Problem, frames_of
from graph.solve.robust import A as RA
from graph.solve.robust import B as RB
from graph.solve.robust import C as RC
from graph.solve.smoothing import GTSAM_MAX_STIFFNESS
from graph.solve.sync import between_frames_on_reference_clock, off_reference_clock, on_camera_clocks
from graph.solve.triangulate import robust_points
from graph.types import Progress, ProgressCallback, Result

START_FRAMES = 10
REFINE_STEPS = 3
RESTART_VIEWS = 3  # a marker this many cameras see, all rejected, is lost (two could be two outliers)
RESTART_PRIOR = 1e-4  # the prediction's weight in a restart's refinement (the prediction is what was lost)
RESTART_GAIN = 1.0  # a restart is kept when it lowers the frame's robust cost by this much a lost marker
RELINEARISE_EVERY = 10  # frames between relinearisations of the measurement factors in the window
RELINEARISE_TOL = 1e-3  # a frame is relinearised when its estimate moved more than this (any parameter)
BATCH_MARGIN_SECONDS = 2.0  # step 6: the frames either side of a stretch without depth in its batch


@dataclass
class _Frame:
    """What a frame in the window needs to be linearised again."""

    meas: np.ndarray  # (C, M, 2), NaN as 0
    valid: np.ndarray  # (C, M)
    anchor: np.ndarray  # its weak anchor: a start frame's batch pose, a streamed frame's causal one
    q_lin: np.ndarray  # the pose its measurement factor is linearised at
    index: int = -1  # that factor's slot in the smoother


class OnlineSmoother:
    """A fixed-lag smoother over poses, fed frame by frame after a batch start.

    ``tp`` supplies the cameras, skeleton and noise levels (a :class:`graph.solve.fte.TrajectoryProblem`
    over the start frames); ``Q_start`` (S, P) is the batch solution of those frames.
    """

    def __init__(self, tp: TrajectoryProblem, Q_start: np.ndarray, lag_frames: int):
        self.tp = tp
        self.P = tp.P
        self.lag = max(lag_frames, 4)
        params = gtsam.ISAM2Params()
        params.setRelinearizeThreshold(1e-3)
        self.smoother = gtsam.IncrementalFixedLagSmoother(float(self.lag), params)
        self.eye = np.eye(self.P)
        # the motion factor whitened by hand, as fte's: GTSAM takes a sigma below 1e-9 for a hard
        # constraint, which a small animal in metres, smoothed hard, reaches
        self.motion_w = np.diag(1.0 / tp.sigma3)
        self.motion_model = gtsam.noiseModel.Unit.Create(self.P)
        self.sigma_pred = np.maximum(tp.sigma3 * 20.0, 1e-3)
        self.history: list[np.ndarray] = []  # the latest estimate of every frame so far
        self.window: dict[int, _Frame] = {}  # frames whose measurement factor can still be relinearised
        self.n = 0
        self.restarts = 0  # frames whose pose was restarted from their triangulation (step 5)
        graph = gtsam.NonlinearFactorGraph()
        values = gtsam.Values()
        stamps = {}
        placed = []
        H, g, *_ = tp.normals(Q_start)
        for k, q in enumerate(Q_start):
            placed.append((k, self._add_frame_factors(graph, k, H[k], g[k], q, anchor=q)))
            self.window[k] = _Frame(tp.meas[k], tp.valid[k], q.copy(), q.copy())
            values.insert(k, q)
            stamps[k] = float(k)
            self.history.append(q.copy())
        self.n = len(Q_start)
        self._update(graph, values, stamps, [], placed)
        self._read_window()

    def _update(self, graph, values, stamps, remove: list[int], placed: list[tuple[int, int]]) -> None:
        """One smoother update; ``placed`` pairs each frame with its measurement factor's position in
        ``graph``, whose slot in the smoother is kept for a later relinearisation."""
        self.smoother.update(graph, values, stamps, remove)
        slots = self.smoother.getISAM2Result().getNewFactorsIndices()
        for k, pos in placed:
            self.window[k].index = int(slots[pos])
        for k in [k for k in self.window if k <= self.n - self.lag]:
            del self.window[k]  # marginalised (or about to be): its factor is no longer ours

    def _refine(self, q, q_pred, meas, valid, ip):
        """A few damped Gauss-Newton steps from ``q`` on the frame's robust cost plus the prediction's
        ``1/2 ip (q - q_pred)^2``."""
        tp = self.tp
        for _ in range(REFINE_STEPS):
            Hf, gf = self._normal(q, meas, valid)
            step = np.linalg.solve(Hf + np.diag(ip) + 1e-6 * self.eye, gf + ip * (q - q_pred))
            q = np.clip(q - step, tp.prob.skeleton.lower, tp.prob.skeleton.upper)
            if np.max(np.abs(step)) < 1e-6:
                break
        return q

    def _diagnose(self, q, meas, valid):
        """The frame's robust cost at ``q`` and each detection's IRLS weight (C, M)."""
        tp = self.tp
        C, M = valid.shape
        w = np.zeros((C, M))
        cost = kernels.frame_normal(q, meas, valid, tp.intr, tp.Rc, tp.tc, tp.sigma_cm, tp.prob.options.robust,
                                    RA, RB, RC, *tp.sk_args, tp.bones, tp.bone_len, tp.bone_sigma,
                                    np.zeros((self.P, self.P)), np.zeros(self.P), np.zeros((C, M, 2)),
                                    np.zeros((C, M)), w)
        return float(cost), w

    def _cost(self, q, meas, valid) -> float:
        return self._diagnose(q, meas, valid)[0]

    def _lost(self, q, meas, valid) -> np.ndarray:
        """(M,) markers the estimate has lost: seen by at least :data:`RESTART_VIEWS` cameras, every one
        of whose detections the robust loss rejects outright (weight 0: beyond c)."""
        _, w = self._diagnose(q, meas, valid)
        seen = valid.sum(axis=0)
        return (seen >= RESTART_VIEWS) & ~((w > 0) & valid).any(axis=0)

    def _restart(self, q, meas, valid, lost) -> np.ndarray:
        """A pose whose ``lost`` markers are where this frame's cameras triangulate them, the others
        where ``q`` puts them."""
        tp = self.tp
        sk = tp.prob.skeleton
        X, _, _ = robust_points(tp.prob.calibration, np.where(valid[..., None], meas, np.nan)[None], valid[None],
                                tp.prob.sigma_px)
        X = X[0]
        here = sk.positions(q[None])[0] if sk.kind != "points" else q.reshape(-1, 3)
        X = np.where((lost & np.isfinite(X).all(-1))[:, None], X, here)
        if sk.kind == "points":
            return X.reshape(-1)
        two = replace(tp.prob, meas=tp.prob.meas[:2], valid=tp.prob.valid[:2], likelihood=tp.prob.likelihood[:2])
        return np.clip(initial_poses(two, np.stack([X, X]))[0], sk.lower, sk.upper)  # two frames: it takes rates

    def _normal(self, q, meas, valid):
        """The robust measurement cost's Gauss-Newton ``H, g`` of one frame at ``q``."""
        tp = self.tp
        C, M = valid.shape
        Hf, gf = np.zeros((self.P, self.P)), np.zeros(self.P)
        kernels.frame_normal(q, meas, valid, tp.intr, tp.Rc, tp.tc, tp.sigma_cm, tp.prob.options.robust,
                             RA, RB, RC, *tp.sk_args, tp.bones, tp.bone_len, tp.bone_sigma, Hf, gf,
                             np.zeros((C, M, 2)), np.zeros((C, M)), np.zeros((C, M)))
        return Hf, gf

    def _relinearise(self, graph) -> tuple[list[int], list[tuple[int, int]]]:
        """New measurement factors, at their current estimates, for the window's frames that moved
        (every RELINEARISE_EVERY updates: a removed factor makes iSAM2 eliminate the window again,
        so one update that takes them all is cheaper than a share in every update); returns the
        slots of the factors they replace and the new factors' positions in ``graph``."""
        remove, placed = [], []
        for k, f in self.window.items():
            if k <= self.n - self.lag + 1 or f.index < 0:
                continue
            q = self.history[k]
            if np.max(np.abs(q - f.q_lin)) < RELINEARISE_TOL:
                continue
            H, g = self._normal(q, f.meas, f.valid)
            remove.append(f.index)
            placed.append((k, self._measurement_factor(graph, k, H, g, q, f.anchor)))
            f.q_lin = q.copy()
        return remove, placed

    def _zero_values(self, keys) -> gtsam.Values:
        v = gtsam.Values()
        for k in keys:
            v.insert(k, np.zeros(self.P))
        return v

    def _measurement_factor(self, graph, n, H, g, q, anchor) -> int:
        """Frame n's measurement cost linearised at ``q``, in absolute form (see TrajectoryProblem),
        with fte's weak anchor (sigma PRIOR_SIGMA) to ``anchor``: a start frame's batch pose, a
        streamed frame's causal one. It keeps the system determinate where the detections do not
        (a free point seen by one camera has no depth); appended to ``graph``, returns its position."""
        w = 1.0 / PRIOR_SIGMA**2
        G = H + w * self.eye
        gv = H @ q - g + w * anchor
        pos = graph.size()
        graph.push_back(gtsam.LinearContainerFactor(gtsam.HessianFactor(n, G, gv, 0.0), self._zero_values([n])))
        return pos

    def _add_frame_factors(self, graph, n, H, g, q, anchor) -> int:
        """Frame n's linearised measurement factor and the motion factor ending at n; returns the
        measurement factor's position in ``graph``."""
        pos = self._measurement_factor(graph, n, H, g, q, anchor)
        if n >= 3:
            w = self.motion_w
            cond = gtsam.GaussianConditional([(n, w), (n - 3, -w), (n - 2, 3 * w), (n - 1, -3 * w)], 1,
                                             np.zeros(self.P), self.motion_model)
            graph.push_back(gtsam.LinearContainerFactor(gtsam.JacobianFactor(cond),
                                                        self._zero_values([n - 3, n - 2, n - 1, n])))
        return pos

    def _read_window(self):
        est = self.smoother.calculateEstimate()
        for k in range(max(0, self.n - self.lag - 1), self.n):
            if est.exists(k):
                self.history[k] = est.atVector(k)

    def push(self, meas: np.ndarray, valid: np.ndarray) -> np.ndarray:
        """Add frame n's detections (C, M, 2) and validity (C, M); return its causal pose (P,)."""
        tp = self.tp
        h = self.history
        n = self.n
        q_pred = 3 * h[n - 1] - 3 * h[n - 2] + h[n - 3]
        q_pred = np.clip(q_pred, tp.prob.skeleton.lower, tp.prob.skeleton.upper)
        meas = np.nan_to_num(meas)
        ip = 1.0 / self.sigma_pred**2
        q = self._refine(q_pred, q_pred, meas, valid, ip)
        lost = self._lost(q, meas, valid)
        if lost.any():  # step 5 of the module docstring: the markers restarted from this frame's triangulation
            q_alt = self._refine(self._restart(q, meas, valid, lost), q_pred, meas, valid, ip * RESTART_PRIOR)
            if self._cost(q_alt, meas, valid) < self._cost(q, meas, valid) - RESTART_GAIN * lost.sum():
                q = q_alt
                self.restarts += 1
        Hf, gf = self._normal(q, meas, valid)
        graph = gtsam.NonlinearFactorGraph()
        placed = [(n, self._add_frame_factors(graph, n, Hf, gf, q, anchor=q))]
        self.window[n] = _Frame(meas, valid.copy(), q.copy(), q.copy())
        remove: list[int] = []
        if n % RELINEARISE_EVERY == 0:
            remove, more = self._relinearise(graph)
            placed += more
        values = gtsam.Values()
        values.insert(n, q)
        self.history.append(q)
        self.n = n + 1
        self._update(graph, values, {n: float(n)}, remove, placed)
        self._read_window()
        return self.history[n]

    def finish(self) -> np.ndarray:
        """The lag-smoothed trajectory (N, P): each frame as last estimated inside the window."""
        self._read_window()
        return np.stack(self.history)


SHARED_START_SECONDS = 2.0  # the batch that estimates the body and the clocks for the ekf (a 1 s one
# timed the cameras wrongly in a test run)
MOTION_START_SHARE = 0.25  # the motion model's scales: at most this share of a run shorter than that


def motion_start_frames(frames: int, fps: float) -> int:
    """The frames of the ekf's start batch that fits the motion model (``motion_scale="auto"``):
    the first :data:`SHARED_START_SECONDS`, or the first :data:`MOTION_START_SHARE` of a run too
    short for that (a 500-frame recording at 300 fps would otherwise be one batch: fte, not a
    filter), and at least :data:`START_FRAMES`."""
    return min(frames, max(START_FRAMES, min(int(round(SHARED_START_SECONDS * fps)),
                                             int(MOTION_START_SHARE * frames))))


def solve_ekf(prob: Problem, progress: ProgressCallback | None = None) -> Result:
    """``--method ekf``: batch start on the first frames, then one smoother update per frame.

    With the body or the clocks to estimate, the first :data:`SHARED_START_SECONDS` are solved as
    one joint batch first (:func:`graph.solve.joint.solve_fte_joint`); the stream then runs on that
    body, each camera's detections interpolated between its own frames to the reference clock's
    (:func:`graph.solve.sync.between_frames_on_reference_clock`; on the nearest frame, 1.4-1.7x fte's
    error with clocks 0.2-0.4 frame apart). Given lengths and offsets are used the same way."""
    if shares_unknowns(prob):
        return _ekf_with_shared(prob, progress)
    return _ekf(prob, progress)


def _ekf_with_shared(prob: Problem, progress: ProgressCallback | None) -> Result:
    t0 = time.perf_counter()
    o = prob.options
    S = min(prob.frames, max(START_FRAMES, int(round(SHARED_START_SECONDS * o.fps))))
    first = replace(prob, meas=prob.meas[:S], likelihood=prob.likelihood[:S], valid=prob.valid[:S])
    start = solve_fte_joint(first)
    rep = start.report
    tau = np.asarray(rep.time_offsets_frames if rep.time_offsets_frames is not None else np.zeros(prob.cameras))
    sk = prob.skeleton
    if rep.body_lengths and sk.kind != "points":
        sk = sk.scaled(sk.scales_for({g: v["length_m"] for g, v in rep.body_lengths.items()}))
    meas, valid = between_frames_on_reference_clock(prob.meas, prob.valid, tau)
    lik, _ = between_frames_on_reference_clock(prob.likelihood[..., None], prob.valid, tau)
    stream = replace(prob, skeleton=sk, meas=meas, valid=valid, likelihood=np.nan_to_num(lik[..., 0]),
                     options=replace(o, body="model", sync="given", time_offsets=None))
    result = _ekf(stream, progress)
    if np.any(tau != 0):  # back on each camera's own clock (none: the stream's were the cameras' own)
        # the trajectory where each camera's frames were taken, projected and set against its detections
        # as given; the outlier flags from the nearest reference frame
        X = on_camera_clocks(result.positions, tau)
        result.reprojections = np.stack([cam.project(X[c]) for c, cam in enumerate(prob.calibration.cameras)])
        result.detections, result.likelihood = prob.meas.transpose(1, 0, 2, 3), prob.likelihood.transpose(1, 0, 2)
        result.residuals = np.where(prob.valid.transpose(1, 0, 2),
                                    np.linalg.norm(result.reprojections - result.detections, axis=-1), np.nan)
        result.outlier = off_reference_clock(result.outlier, tau)
    result.options = o
    for field_name in ("body_lengths", "time_offsets_frames", "time_offsets_std_frames", "offsets_not_identified"):
        setattr(result.report, field_name, getattr(rep, field_name))
    result.report.warnings += [w for w in rep.warnings if w not in result.report.warnings]
    # the shared start's time is init's too: what this took beyond the stream's own phases
    # ("total" is the caller's, set after)
    seconds = result.report.seconds
    seconds["init"] += time.perf_counter() - t0 - sum(v for k, v in seconds.items() if k != "total")
    return result


def _whole_run(prob: Problem, tp: TrajectoryProblem, done: np.ndarray) -> tuple[np.ndarray, int]:
    """The whole run's smoothed trajectory (fte's optimiser, the motion scales of ``tp``), started
    from the stream's poses ``done`` for its first frames and from the robust triangulation's after:
    what ekf returns when GTSAM's stream cannot eliminate its system. Returns (Q, iterations)."""
    X, _, _ = robust_points(prob.calibration, prob.meas, prob.valid, prob.sigma_px)
    Q0 = initial_poses(prob, X)
    Q0[:len(done)] = done
    whole = TrajectoryProblem(prob, Q0, tp.bone_len)
    whole.set_motion_scales(tp.motion_scales)
    whole.bound_stiffness(whole.normals_at(Q0).H)
    Q, iterations, _ = optimise(whole, Q0.copy(), prob.options.max_iterations)
    tp.indefinite_steps += whole.indefinite_steps
    return Q, iterations


def _depthless_stretches(valid: np.ndarray, shortest: int) -> list[tuple[int, int]]:
    """The stretches ``[a, b)`` of at least ``shortest`` frames in which no marker is seen by two
    cameras (``valid`` (N, C, M)): the stream has no depth there but its motion model's."""
    deep = (valid.sum(axis=1) >= 2).any(axis=1)
    out, a = [], None
    for n, d in enumerate(np.append(deep, True)):
        if not d and a is None:
            a = n
        elif d and a is not None:
            if n - a >= shortest:
                out.append((a, n))
            a = None
    return out


def _batch_through(prob: Problem, tp: TrajectoryProblem, lo: int, hi: int) -> tuple[np.ndarray, int]:
    """Frames ``[lo, hi)`` (a stretch without depth and its margins) solved by ``fte`` with the stream's
    body and motion model (scales and orders held). Returns the poses and the iterations."""
    names = tp.group_names()
    held = replace(prob.options, method="fte", window_frames=0, uncertainty=False,  # the run's sds: from Q after
                   motion_scale={g: float(v) for g, v in zip(names, tp.motion_scales)},
                   motion_order={g: int(k) for g, k in zip(names, tp.orders)})
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the run's warnings are the stream's; the report names the batch
        res = solve_fte_joint(replace(frames_of(prob, lo, hi, held), start_poses=None))
    assert res.params is not None
    return res.params, res.report.iterations


def _seams(skeleton: Skeleton, stream: np.ndarray, batch: np.ndarray, free: int, a: int, b: int) -> tuple[int, int]:
    """Where the poses ``batch`` (``stream``'s frames, ``[lo, hi)`` of the run) take over from the
    stream around the stretch ``[a, b)`` (frames of ``batch``): in each margin, the frame where the two
    trajectories' markers are nearest (their mean distance), so that the seam jumps least; not before
    frame ``free`` (the stream's start frames are not the stream's to give up). The stream may have
    gone astray in a margin too, into the stretch or slow to come back after it (on bench_dropout's
    seed 2, 31-126 mm over the 300 frames before it, about 5 mm from the batch); the batch, which saw
    the whole margin, is the reference there."""
    d = np.linalg.norm(skeleton.positions(stream) - skeleton.positions(batch), axis=-1).mean(axis=-1)
    first = free + int(np.argmin(d[free:a])) if a > free else a
    last = b + int(np.argmin(d[b:])) if len(d) > b else b
    return first, last


def _through_depthless(prob: Problem, tp: TrajectoryProblem, Q: np.ndarray, S: int, lag: int,
                       notes: list[str]) -> int:
    """Step 6 of the module docstring: the stretches of ``prob`` longer than ``lag`` frames that no two
    cameras see, from the stream's start frames ``S`` on, given the poses of an ``fte`` batch in the
    smoothed trajectory ``Q`` (in place), and a note for the report. Returns the batches' iterations."""
    margin = max(lag, int(round(BATCH_MARGIN_SECONDS * prob.options.fps)))  # frames with depth either side
    depthless = [(max(a, S), b) for a, b in _depthless_stretches(prob.valid, lag) if b > S]
    iterations = 0
    for a, b in depthless:
        lo, hi = max(0, a - margin), min(prob.frames, b + margin)
        batch, more = _batch_through(prob, tp, lo, hi)
        first, last = _seams(prob.skeleton, Q[lo:hi], batch, max(S - lo, 0), a - lo, b - lo)
        Q[lo + first:lo + last] = batch[first:last]
        iterations += more
    if depthless:
        notes.append(f"{len(depthless)} stretch(es) no two cameras saw ({sum(b - a for a, b in depthless)} frames, "
                     f"the longest {max(b - a for a, b in depthless)}) are fte's: each solved as one batch with "
                     f"{margin} frames either side, whose poses are taken up to where they and the stream's agree "
                     "best (the stream has no depth there; its causal estimates are the stream's)")
    return iterations


def _ekf(prob: Problem, progress: ProgressCallback | None) -> Result:
    t0 = time.perf_counter()
    if progress:
        progress(Progress(stage="initialise", fraction=0.0))
    N = prob.frames
    auto = prob.options.motion_scale == "auto"
    # the batch start sees the first frames only, as a stream would; to fit the motion model
    # ("auto") it takes motion_start_frames; given the first poses (a long run's window continuing the
    # stream before it), the stream starts from them
    given = prob.start_poses
    S = len(given) if given is not None else (
        motion_start_frames(N, prob.options.fps) if auto else min(N, START_FRAMES))
    sub = replace(prob, meas=prob.meas[:S], likelihood=prob.likelihood[:S], valid=prob.valid[:S])
    X, _, _ = robust_points(sub.calibration, sub.meas, sub.valid, sub.sigma_px)
    Q0 = initial_poses(sub, X) if given is None else np.array(given, dtype=np.float64)
    tp = TrajectoryProblem(sub, Q0, bone_lengths(sub, X) if sub.skeleton.kind == "points" else None)
    tp.max_stiffness = GTSAM_MAX_STIFFNESS  # the stream (OnlineSmoother) eliminates on GTSAM, all markers together
    stiff = tp.bound_stiffness(tp.normals_at(Q0).H)  # as fte (solve_from): a fit's start of scale 1 too
    notes = [stiff] if stiff and not auto else []
    Q_start, iters, cost = (Q0, 0, float("nan")) if given is not None else optimise(tp, Q0.copy(), 30)
    if auto and given is None:  # the scales of largest marginal likelihood over the start (fitted at its
        # optimum, as fte), kept for the stream
        Q_start, more, _ = refit_motion(tp, Q_start, cost, 30)
        iters += more
    t_init = time.perf_counter() - t0
    causal = np.zeros((N, prob.skeleton.n_params))
    causal[:S] = Q_start
    per_frame = []
    Q = Q_start
    if N > S:
        n = S
        try:
            sm = OnlineSmoother(tp, Q_start, int(round(prob.options.lag_seconds * prob.options.fps)))
            every = max(1, (N - S) // 50)
            for n in range(S, N):
                t1 = time.perf_counter()
                causal[n] = sm.push(prob.meas[n], prob.valid[n])
                per_frame.append(time.perf_counter() - t1)
                if progress and (n - S) % every == 0:
                    progress(Progress(stage="filter", fraction=0.1 + 0.85 * (n - S) / (N - S), iteration=n))
            Q = sm.finish()
            if sm.restarts:
                notes.append(f"the stream lost markers that three cameras or more saw and restarted them from the "
                             f"frame's triangulation in {sm.restarts} of {N - S} frames (after a stretch with "
                             "fewer cameras, typically); fte solves the whole run at once and needs no restart")
        except RuntimeError as e:
            if "Indeterminate" not in str(e):
                raise
            Q, more = _whole_run(prob, tp, causal[:n])
            iters += more
            causal[n:] = Q[n:]
            notes.append(f"the stream's elimination (GTSAM's iSAM2) found its system indeterminate at frame {n} "
                         f"(a motion model far stiffer than the data, {prob.options.fps:g} fps, or a long stretch "
                         "without two cameras): the trajectory is the whole run's smoother's (as fte), and from "
                         "that frame on so are the causal estimates")
        else:
            iters += _through_depthless(prob, tp, Q, S, sm.lag, notes)
    t_solve = time.perf_counter() - t0 - t_init
    ms = np.array(per_frame) * 1000.0
    per_frame_ms = ({"median": float(np.median(ms)), "p95": float(np.percentile(ms, 95)), "max": float(ms.max())}
                    if len(ms) else {"median": float("nan"), "p95": float("nan"), "max": float("nan")})
    # per-marker std from the marginals of the whole run's information at the smoothed trajectory
    # (the chain of graph.solve.marginals, as fte); a per-frame inverse with the motion prior as a stiff
    # local term had claimed 4-9x too little spread
    whole = TrajectoryProblem(prob, Q, tp.bone_len)
    whole.set_motion_scales(tp.motion_scales)  # fitted, or given and bounded (bound_stiffness)
    whole.indefinite_steps = tp.indefinite_steps
    result = trajectory_result(whole, Q, "ekf",
                               seconds={"init": t_init, "solve": t_solve}, iterations=N - S + iters,
                               causal=causal, per_frame_ms=per_frame_ms, notes=notes)
    if progress:
        progress(Progress(stage="done", fraction=1.0, iteration=N))
    return result
