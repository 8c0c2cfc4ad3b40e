"""Full Trajectory Estimation (``--method fte``): the whole run as one factor graph.

Variables: the pose ``q_n`` (P,) of every frame n (GTSAM key n). The cost is

    F(q) = sum_n sum_{c,m} rho(|pi_c(p_m(q_n)) - z_ncm| / sigma)             kinematic projection
         + 1/2 sum_n || (q_{n+3} - 3 q_{n+2} + 3 q_{n+1} - q_n) / sigma_3 ||^2  constant acceleration
         + 1/2 sum_n || (q_n - q0_n) / sigma_prior ||^2                      a weak anchor (sigma 10)

subject to the joint bounds. ``rho`` is the AcinoSet redescending loss (:mod:`graph.solve.robust`).
The third difference is the constant-acceleration model with white jerk: with the paper's
discretisation ``q_{n+1} = q_n + h qdot_n + h^2/2 qddot_n``, ``qddot_{n+1} = qddot_n + w_n``, the third
difference of q is ``h^2/2 (w_{n+1} + w_n)``, so ``sigma_3 = h^2 sigma_w`` with ``sigma_w`` the
skeleton's per-parameter process noise.

Solver: Levenberg-Marquardt driven from Python. Each iteration linearises the measurement part
of all frames in one compiled call (:func:`graph.solve.kernels.all_normals`: the IRLS-weighted normal
equations ``H_n, g_n`` of every frame). The damped system is the :class:`gtsam.GaussianFactorGraph`
of :meth:`TrajectoryProblem.linear_graph`:

* one ``HessianFactor`` per frame: the frame's normal equations, the anchor and the Marquardt
  damping ``lambda I`` (see :class:`TrajectoryCost`);
* one 4-key linear motion factor per window of four frames (a ``GaussianConditional`` over
  ``q_{n+3} | q_n, q_{n+1}, q_{n+2}``, as a ``JacobianFactor`` kept in Hessian form: the Python
  ``JacobianFactor`` constructors stop at three keys);

and is solved as GTSAM eliminates that graph (banded, natural ordering: the Bayes net of the chain,
then back substitution), by a compiled block Cholesky of the same matrix in the same order
(:meth:`TrajectoryProblem.solve_chain`, equal to GTSAM's solution to 1e-9 in the tests): building
the graph from Python cost more than eliminating it. Free points without bones are independent
chains, solved by LAPACK's banded Cholesky (:meth:`TrajectoryProblem.solve_chains`). Steps are
clipped to the bounds. Graduated robustness: the first step (:data:`STRETCHED_STEPS`) uses the
loss with its knots a, b, c stretched by 4, so that detections far from a rough start are not
rejected before the pose comes to them.

Uncertainty: the marginal covariance ``Sigma_n`` of each ``q_n`` under the final (undamped)
linearisation, the Bayes tree's numbers in one compiled pass (:mod:`graph.solve.marginals`), and
per-marker ``Sigma_p = J_p Sigma_n J_p^T``.
"""

from __future__ import annotations

import math
import time
from typing import Any, Generic, NamedTuple, TypeVar

import gtsam
import numpy as np

from graph import kinematics
from graph.compiled import for_items
from graph.errors import InputError
from graph.skeleton import left_right_pairs
from graph.solve import kernels
from graph.solve.initial import initial_poses
from graph.solve.marginals import chain_band, chain_marginals, solve_band
from graph.solve.noise import scatter_px
from graph.solve.problem import AUTO_RANGE_PX, Problem
from graph.solve.result import build_result
from graph.solve.robust import OUTLIER_S
from graph.solve.robust import A as RA
from graph.solve.robust import B as RB
from graph.solve.robust import C as RC
from graph.solve.smoothing import MAX_STIFFNESS, stiffest_scale
from graph.solve.swaps import exchange, exchanged
from graph.solve.triangulate import robust_points
from graph.types import Progress, ProgressCallback, Result

PRIOR_SIGMA = 10.0
BONE_SIGMA_FRACTION = 0.05


class IndefiniteSystem(RuntimeError):
    """A step's damped system is numerically not positive definite (its Cholesky factorisation
    failed): :func:`optimise` then damps more, as for a step that did not lower the cost."""


class Estimate(NamedTuple):
    """What a solved trajectory gives: marker positions (N, M, 3), their 3D sd (N, M, 3; NaN
    without uncertainty), each parameter's sd (N, P, or None) and report fields of its own."""

    positions: np.ndarray
    std: np.ndarray
    params_std: np.ndarray | None
    report: dict | None = None


class Normals(NamedTuple):
    """The robust measurement cost of every frame at a trajectory, from :meth:`TrajectoryProblem.normals`."""

    H: np.ndarray  # (N, P, P) Gauss-Newton information of each frame
    g: np.ndarray  # (N, P) gradient of each frame's cost
    uv: np.ndarray  # (N, C, M, 2) reprojections
    s: np.ndarray  # (N, C, M) normalised residuals |r| / sigma
    w: np.ndarray  # (N, C, M) IRLS weights
    cost: np.ndarray  # (N,) data cost of each frame


StateT = TypeVar("StateT")  # what the optimiser steps: the trajectory Q (N, P), or a richer problem's state
NormalsT = TypeVar("NormalsT")  # the measurement cost's normal equations at a state


class TrajectoryCost(Generic[StateT, NormalsT]):
    """The FTE cost for one :class:`graph.solve.problem.Problem`, and its Gauss-Newton systems.

    The linear systems are written in absolute form, for the new trajectory ``Q'`` rather than
    the step: the motion factors ``D3 Q' = 0`` are then constant and built once, and only the
    per-frame factors change between iterations. For frame n with normal equations ``H, g``
    (gradient of the robust cost, see :func:`graph.solve.kernels.frame_normal`) the frame's quadratic
    model ``1/2 d^T H d + g^T d`` with ``d = q' - q`` becomes the ``HessianFactor``

        G = H + I/sigma_prior^2 + lambda I,    gvec = H q - g + q0/sigma_prior^2 + lambda q

    (GTSAM's Hessian factor is ``1/2 x^T G x - x^T gvec + f/2``).

    ``sigma_px`` is the detection noise the loss scales by: the problem's, until
    :func:`remeasure_noise` measures it again on the smoother's residuals.
    """

    def __init__(self, prob: Problem, Q0: np.ndarray, bone_len: np.ndarray | None = None):
        self.prob = prob
        self.sigma_px = prob.sigma_px
        sk = prob.skeleton
        self.sk_args = sk.arrays.kernel_args()
        self.intr, self.Rc, self.tc = prob.packed_cameras()
        self.meas = np.nan_to_num(prob.meas)
        self.valid = prob.valid
        # the pairs of markers a tracker may swap (graph.solve.swaps), the detections as given, which
        # (frame, camera, pair) are taken as swapped and how many, and the share of pairs swapped used
        self.pairs = np.array(left_right_pairs(prob.markers), dtype=np.int64).reshape(-1, 2)
        self.deciding_swaps = bool(len(self.pairs)) and prob.options.robust and prob.options.swap_rate != 0
        self.given = (self.meas, self.valid)
        self.swapped = np.zeros((prob.frames, prob.cameras, len(self.pairs)), dtype=bool)
        self.side_swaps = 0
        self.swap_rate: float | None = None
        self.Q0 = Q0
        N, P = Q0.shape
        self.N, self.P = N, P
        # the third difference's sd per parameter at motion scale 1, and the scale of each group
        # (motion_scale "auto" starts at 1 and is fitted: :func:`refit_motion`)
        self.base_sigma3 = sk.process_noise * prob.dt**2
        self.sigma3 = self.base_sigma3.copy()  # each group's scale applied below (set_motion_scales)
        self.bones = sk.bone_index if sk.kind == "points" else np.zeros((0, 2), dtype=np.int64)
        if bone_len is None:
            bone_len = np.zeros(len(self.bones))
        self.bone_len = bone_len
        self.bone_sigma = np.maximum(BONE_SIGMA_FRACTION * bone_len, 1e-3)
        # Variables: one GTSAM key per frame and parameter group. A kinematic skeleton is one group
        # (every parameter moves together), and so are free points joined by bone terms: one key
        # per frame keeps the graph a chain, eliminated in time order (per-marker keys coupled by
        # bones leave a fill-reducing ordering with cliques of hundreds of dimensions, whose
        # marginals cost 20x more). Free points without bones are one group per marker: a set of
        # independent small chains.
        if sk.kind == "points" and not any(a != b for a, b in self.bones):
            self.groups = [np.arange(3 * m, 3 * m + 3) for m in range(len(sk.markers))]
        else:
            self.groups = [np.arange(P)]
        # each group's scale of the process noise ("auto" starts at 1) and the order of its motion
        # prior: on its k-th differences (3: constant acceleration, the paper's model; "auto" starts at
        # 3 and is chosen by fit_motion); one for all, or per group as a report gives them
        self.set_motion_scales(self._per_group(prob.options.motion_scale, "motion_scale", 1.0, float),
                               self._per_group(prob.options.motion_order, "motion_order", 3, int))
        # free points without bones: independent chains, solved by banded Cholesky (solve_linear)
        self.chains = len(self.groups) > 1
        # the stiffest smoothing a fit may choose (graph.solve.smoothing.stiffest_scale); ekf's stream, which
        # GTSAM eliminates with all markers in one key, takes GTSAM_MAX_STIFFNESS
        self.max_stiffness = MAX_STIFFNESS
        self.indefinite_steps = 0  # steps whose system was numerically indefinite, damped more (optimise)
        self.ridge = 0.0  # the marginals' ridge, relative (graph.solve.marginals.ridged_marginals; 0: none)
        self._motion_graph: list | None = None
        self._motion_band: np.ndarray | None = None
        self._kept_normals: tuple | None = None  # (state, stretch, sigma_px, normals): normals_at
        self._ordering = gtsam.Ordering()
        for k in range(len(self.groups) * N):
            self._ordering.push_back(k)

    def key(self, n: int, group: int) -> int:
        return group * self.N + n

    def _per_group(self, value, option: str, auto, kind) -> np.ndarray:
        """``value`` of ``option`` for each group: one for all, ``auto`` for "auto", or a
        ``{group: value}`` map (a report's motion_scales / motion_orders) naming exactly this solve's
        groups (:meth:`group_names`); :class:`InputError` naming the difference otherwise."""
        if not isinstance(value, dict):
            return np.full(len(self.groups), auto if value == "auto" else kind(value))
        names = self.group_names()
        missing = [n for n in names if n not in value]
        extra = [n for n in value if n not in names]
        if missing or extra:
            few = lambda xs: ", ".join(xs[:6]) + (", ..." if len(xs) > 6 else "")  # noqa: E731
            wrong = [f"missing {few(missing)}"] * bool(missing) + [f"unknown {few(extra)}"] * bool(extra)
            raise InputError(f"{option} gives a value per group, but not for this solve's groups ({few(names)}): "
                             f"{'; '.join(wrong)} (a report of a run with the same markers and skeleton gives "
                             "the right ones)")
        return np.array([kind(value[n]) for n in names])

    @property
    def sigma_cm(self) -> np.ndarray:
        """The detection noise of each camera and marker (C, M) at the current ``sigma_px``."""
        return self.prob.sigma_cm(self.sigma_px)

    def set_motion_scales(self, scales: np.ndarray, orders: np.ndarray | None = None) -> None:
        """Each group's process noise scaled by its entry of ``scales`` (and its prior's order set
        to its entry of ``orders``, if given); the motion factors anew."""
        if orders is not None:
            self.orders = np.asarray(orders, dtype=np.int64).copy()
        self.motion_scales = np.asarray(scales, dtype=np.float64).copy()
        sigma3 = self.base_sigma3.copy()
        for s, idx in zip(self.motion_scales, self.groups):
            sigma3[idx] = sigma3[idx] * s
        self.sigma3 = sigma3
        self._motion_graph = self._motion_band = None

    def bound_stiffness(self, H: np.ndarray) -> str | None:
        """Raise each group's motion scale to at least :func:`graph.solve.smoothing.stiffest_scale` of
        its data information ``H`` (N, P, P): the motion's precision ``1 / (s sigma_3)^2`` at most
        ``max_stiffness`` times the median per-frame information of the group's parameters.

        A fitted scale never goes past that bound; a given one, or the skeleton's own process noise
        at a high frame rate (``sigma_3`` scales with ``dt^2``: at 10 kHz it is 5000 times smaller
        than at 120 fps, its precision 2.5e7 times larger), can ask for more, and then the chain's
        information ``K = H + w I + c D^T D`` keeps too few of double precision's digits to tell the
        trajectory from a polynomial: its Cholesky fails, or succeeds and returns a trajectory metres
        off (measured: a given scale of 1e-7 at 60 fps failed in every solver; free points at 10 kHz
        came back 3.9 m off). Returns a one-line warning naming how many groups were raised, or None."""
        w = 1.0 / PRIOR_SIGMA**2
        lo = np.array([stiffest_scale(np.ascontiguousarray(H[:, idx][:, :, idx]), self.base_sigma3[idx], w,
                                      self.max_stiffness) for idx in self.groups])
        raised = self.motion_scales < lo
        if not raised.any():
            return None
        old = self.motion_scales.copy()
        self.set_motion_scales(np.maximum(self.motion_scales, lo))
        k = int(raised.sum())
        return (f"the motion model asked for is stiffer than the detections can support for {k} of "
                f"{len(self.groups)} parameter groups (at {self.prob.options.fps:g} fps): its scale was raised "
                f"from {float(np.min(old[raised])):.3g} to {float(np.min(lo[raised])):.3g}, where the motion's "
                f"precision is {self.max_stiffness:.0e} times the data's; fit it (--motion-scale auto) or give a "
                f"larger scale")

    @property
    def _motion(self) -> list:
        """The motion factors of GTSAM's graph (:meth:`_motion_factors`), built when first asked for."""
        if self._motion_graph is None:
            self._motion_graph = self._motion_factors()
        return self._motion_graph

    def group_names(self) -> list[str]:
        """A name per group: the marker's for free points without bones, else ``all``."""
        if len(self.groups) == 1:
            return ["all"]
        return list(self.prob.skeleton.markers)

    def _motion_factors(self) -> list:
        """``(q_{n+3} - 3 q_{n+2} + 3 q_{n+1} - q_n) / sigma_3 = 0`` per group (the k-th difference
        of the group's order k): a GaussianConditional on ``q_{n+k}`` given the k before it, as a
        (k+1)-key JacobianFactor, kept in Hessian form (elimination is then Cholesky throughout, a
        third faster than mixing in QR)."""
        from graph.solve.smoothing import STENCILS

        out = []
        for gi, idx in enumerate(self.groups):
            # whitened by hand (unit noise): GTSAM takes a sigma below 1e-9 for a hard constraint, and a
            # small animal in metres, smoothed hard, has third differences that small
            eye = np.diag(1.0 / self.sigma3[idx])
            model = gtsam.noiseModel.Unit.Create(len(idx))
            zero = np.zeros(len(idx))
            k = [self.key(n, gi) for n in range(self.N)]
            order = int(self.orders[gi])
            st = STENCILS[order]
            out += [gtsam.HessianFactor(gtsam.JacobianFactor(gtsam.GaussianConditional(
                        [(k[n + order], st[order] * eye)] + [(k[n + a], st[a] * eye) for a in range(order)],
                        1, zero, model)))
                    for n in range(self.N - order)]
        return out

    def normals_at(self, X: StateT, stretch: float = 1.0) -> NormalsT:
        """:meth:`normals` at the state ``X``, or the last ones computed here if they were at this
        very state object, stretch and noise: the optimiser's final evaluation serves the motion
        fit, the noise's measurement and the result at its optimum, without a kernel call each.
        States are never changed in place (a step makes a new one)."""
        kept = self._kept_normals
        if kept is not None and kept[0] is X and kept[1] == stretch and kept[2] == self.sigma_px:
            return kept[3]
        nrm = self.normals(X, stretch)
        self._kept_normals = (X, stretch, self.sigma_px, nrm)
        return nrm

    def scatter(self, X: StateT) -> float:
        """The detection noise measured on the residuals at ``X`` of the detections the solve uses
        (px; :func:`graph.solve.noise.scatter_px`; NaN with none)."""
        nrm: Any = self.normals_at(X)  # every problem's normals have the residuals s
        s = nrm.s
        return scatter_px(np.where(self.valid & np.isfinite(s), s * self.sigma_px, np.nan))

    def motion_residuals(self, Q) -> np.ndarray:
        """Each group's k-th differences whitened, ``Dk q / sigma_3`` (third differences for the
        constant-acceleration model): (N-3, P) when every group is of order 3, else all of them
        flattened."""
        if np.all(self.orders == 3):
            return (Q[3:] - 3 * Q[2:-1] + 3 * Q[1:-2] - Q[:-3]) / self.sigma3
        return np.concatenate([(np.diff(Q[:, idx], int(k), axis=0) / self.sigma3[idx]).ravel()
                               for k, idx in zip(self.orders, self.groups)])

    def motion_cost(self, Q) -> float:
        """``1/2 sum |Dk q / sigma_3|^2`` over :meth:`motion_residuals`."""
        m = self.motion_residuals(Q)
        return 0.5 * float(np.sum(m * m))

    def cost(self, Q, data_cost):
        pr = (Q - self.Q0) / PRIOR_SIGMA
        return float(data_cost.sum() + self.motion_cost(Q) + 0.5 * np.sum(pr * pr))

    def linear_graph(self, Q, H, g, lam: float) -> gtsam.GaussianFactorGraph:
        """The damped Gauss-Newton system at Q over the new trajectory Q'.

        Each group's block of G with its part of gvec is one HessianFactor per frame (groups share
        no terms within a frame: see ``groups``)."""
        graph = gtsam.GaussianFactorGraph()
        for f in self._motion:
            graph.push_back(f)
        w = 1.0 / PRIOR_SIGMA**2
        G = H + (w + lam) * np.eye(self.P)
        gv = np.einsum("npq,nq->np", H, Q) - g + w * self.Q0 + lam * Q
        if len(self.groups) == 1:
            for n in range(self.N):
                graph.add(gtsam.HessianFactor(n, G[n], gv[n], 0.0))
            return graph
        for gi, idx in enumerate(self.groups):
            a, b = idx[0], idx[-1] + 1
            Gg, gg = G[:, a:b, a:b], gv[:, a:b]
            for n in range(self.N):
                graph.add(gtsam.HessianFactor(self.key(n, gi), Gg[n], gg[n], 0.0))
        return graph

    def _solution(self, vv: gtsam.VectorValues) -> np.ndarray:
        if len(self.groups) == 1:
            return np.stack([vv.at(n) for n in range(self.N)])
        Q = np.empty((self.N, self.P))
        for gi, idx in enumerate(self.groups):
            Q[:, idx] = np.stack([vv.at(self.key(n, gi)) for n in range(self.N)])
        return Q

    def solve_linear(self, Q, H, g, lam: float) -> np.ndarray:
        """The minimiser Q' of the damped system at Q: for independent chains :meth:`solve_chains`,
        else the compiled elimination of the one chain (:meth:`solve_chain`); both equal GTSAM's
        elimination of :meth:`linear_graph` (tests)."""
        if self.chains:
            return self.solve_chains(Q, H, g, lam)
        return self.solve_chain(Q, H, g, lam)

    def solve_chain(self, Q, H, g, lam: float) -> np.ndarray:
        """The damped system of :meth:`linear_graph` for one group, by the block Cholesky
        factorisation of its chain in time order and two substitutions
        (:func:`graph.solve.marginals.chain_forward`, :func:`~graph.solve.marginals.chain_backward`), compiled:
        the elimination GTSAM makes of the same graph, in the same order, without building the
        graph's N + N - k factors (motion factors that took 22 ms to build at 150 frames, and 10 ms a
        step to eliminate where this takes 5: bench/RESULTS.md, section 13c)."""
        w = 1.0 / PRIOR_SIGMA**2
        band = self.chain_band(H + (w + lam) * np.eye(self.P))
        rhs = np.einsum("npq,nq->np", H, Q) - g + w * self.Q0 + lam * Q
        try:
            return solve_band([band], [np.zeros((self.N, self.P, 0))], [rhs], np.zeros((0, 0)), np.zeros(0))[0][0]
        except np.linalg.LinAlgError as e:
            raise IndefiniteSystem(f"the smoother's system is not positive definite: {e}") from None

    def chain_band(self, G: np.ndarray) -> np.ndarray:
        """The one group's information as chain blocks (:func:`graph.solve.marginals.chain_band`): the
        per-frame ``G`` (N, P, P) and the motion prior of the group's order."""
        from graph.solve.smoothing import STENCILS

        return chain_band(np.ascontiguousarray(G), 1.0 / self.sigma3**2, STENCILS[int(self.orders[0])])

    def solve_chains(self, Q, H, g, lam: float) -> np.ndarray:
        """The same system as :meth:`linear_graph` for free points without bones, whose markers are
        independent chains, by LAPACK's banded Cholesky on all chains at once
        (:func:`graph.solve.smoothing.solve_chains`): ``K Q'_g = gvec_g`` per chain g, with
        ``K = blockdiag(H_n + (w + lambda) I) + D3^T D3 / sigma_3^2`` (bandwidth 4 frames).

        Why not GTSAM's elimination here: with the smoothing fitted to a slow animal
        (``motion_scale="auto"``, the fly's legs) the motion's precision is up to 1e7 times the
        data's. GTSAM eliminates each chain's last four frames as one 12-dimensional clique, and its
        dense Cholesky there declared the system indeterminate, though K's condition number was
        about 2e10 and LAPACK factors the same matrix (measured: bench/RESULTS.md, section 12).
        The elimination order is the same, frame by frame, so the numbers are GTSAM's otherwise
        (tests), in a few milliseconds instead of a graph of N (M + 1) factors per iteration."""
        from graph.solve.smoothing import data_band, motion_band, solve_chains

        idx = np.stack(self.groups)  # (G, d)
        w = 1.0 / PRIOR_SIGMA**2
        Hg = np.stack([H[:, i][:, :, i] for i in idx])  # (G, N, d, d)
        if self._motion_band is None:
            self._motion_band = motion_band(1.0 / self.sigma3[idx] ** 2, self.N, self.orders)
        rhs = np.einsum("npq,nq->np", H, Q) - g + w * self.Q0 + lam * Q  # (N, P); H couples no groups
        rhs = np.stack([rhs[:, i] for i in idx]).ravel()
        try:
            x = solve_chains(data_band(Hg, w + lam) + self._motion_band, rhs)
        except np.linalg.LinAlgError as e:
            raise IndefiniteSystem(f"the smoother's system is not positive definite: {e}") from None
        Qn = np.empty_like(Q)
        Qn[:, idx.ravel()] = x.reshape(len(idx), self.N, -1).transpose(1, 0, 2).reshape(self.N, -1)
        return Qn

    # the state interface :func:`optimise` drives, each problem's own: :class:`TrajectoryProblem`'s
    # state is the trajectory Q, a problem with more unknowns has a state of its own

    def normals(self, X: StateT, stretch: float = 1.0) -> NormalsT:
        """The robust measurement cost of every frame at ``X``, with the loss's knots stretched by ``stretch``."""
        raise NotImplementedError

    def step(self, X: StateT, normals: NormalsT, lam: float) -> StateT:
        """The damped Gauss-Newton step from ``X``, clipped to the bounds."""
        raise NotImplementedError

    @staticmethod
    def change(X: StateT, Xn: StateT) -> float:
        """The largest change of an unknown from ``X`` to ``Xn``."""
        raise NotImplementedError

    def poses(self, X: StateT) -> np.ndarray:
        """The trajectory Q (N, P) of ``X``."""
        raise NotImplementedError

    def estimate(self, X: StateT, normals: NormalsT, uncertainty: bool) -> Estimate:
        """Markers at ``X`` and, with ``uncertainty``, their sds."""
        raise NotImplementedError

    def marginal_covariances(self, H: np.ndarray) -> np.ndarray:
        """Marginal covariance of each frame's pose (N, P, P) at the optimum, from the undamped
        information (``H`` from :meth:`normals` there, the anchor and the motion factors) by
        :func:`graph.solve.marginals.chain_marginals`, one chain per group: for free points without bones
        the per-marker blocks (markers are then independent chains, so the covariance between them
        is zero). The same numbers as GTSAM's Bayes tree of :meth:`linear_graph` (tests)."""
        G = H + np.eye(self.P)[None] / PRIOR_SIGMA**2
        w2 = 1.0 / self.sigma3**2
        from graph.solve.smoothing import STENCILS

        if len(self.groups) == 1:
            S, ridge = chain_marginals(G, w2, STENCILS[int(self.orders[0])])
            self.ridge = max(self.ridge, ridge)
            return S
        S = np.zeros((self.N, self.P, self.P))
        for order, idx in zip(self.orders, self.groups):
            a, b = idx[0], idx[-1] + 1
            S[:, a:b, a:b], ridge = chain_marginals(np.ascontiguousarray(G[:, a:b, a:b]), w2[a:b],
                                                    STENCILS[int(order)])
            self.ridge = max(self.ridge, ridge)
        return S


class TrajectoryProblem(TrajectoryCost[np.ndarray, Normals]):
    """:class:`TrajectoryCost` with the poses alone unknown: the state is the trajectory Q (N, P)."""

    def normals(self, Q: np.ndarray, stretch: float = 1.0) -> Normals:
        """The robust measurement cost of every frame at ``Q``, with the loss's knots stretched by ``stretch``."""
        kernel = for_items(kernels.all_normals, len(Q))
        return Normals(*kernel(Q, self.meas, self.valid, self.intr, self.Rc, self.tc, self.sigma_cm,
                               self.prob.options.robust, RA * stretch, RB * stretch, RC * stretch,
                               *self.sk_args, self.bones, self.bone_len, self.bone_sigma))

    def step(self, Q: np.ndarray, normals: Normals, lam: float) -> np.ndarray:
        """The damped Gauss-Newton step from ``Q``, clipped to the joint bounds."""
        sk = self.prob.skeleton
        return np.clip(self.solve_linear(Q, normals.H, normals.g, lam), sk.lower, sk.upper)

    @staticmethod
    def change(Q: np.ndarray, Qn: np.ndarray) -> float:
        return float(np.max(np.abs(Qn - Q)))

    def poses(self, Q: np.ndarray) -> np.ndarray:
        return Q

    def estimate(self, Q: np.ndarray, normals: Normals, uncertainty: bool) -> Estimate:
        """Markers at ``Q`` by forward kinematics and, with ``uncertainty``, the marginal covariance
        ``Sigma_n`` of every pose (:meth:`marginal_covariances`), each marker's 3D sd
        (:func:`marker_std`) and each parameter's ``sqrt(diag Sigma_n)``."""
        pos, dpos = kinematics.fk_jacobian_batch(Q, *self.sk_args)
        if not uncertainty:
            return Estimate(pos, np.full(pos.shape, np.nan), None)
        Sigma = self.marginal_covariances(normals.H)
        return Estimate(pos, marker_std(dpos, Sigma), np.sqrt(np.maximum(np.diagonal(Sigma, axis1=-2, axis2=-1), 0.0)))


SMALL_GAINS = 2  # accepted steps in a row, each gaining under tol, that end an optimisation
# Steps at most in each stretched stage of the graduated robust loss. One: its first step takes the
# start to the detections (the cost falls 100-1000x), the next ones gained little or failed. Measured
# against 3 (the value before) on 94 simulated runs (bench/bench_graduated.py: the paper table's 12
# conditions with the body estimated and the model's, the body and clocks conditions of both rigs,
# realistic outliers with the cheetah, free points and ekf; bench/RESULTS.md, section 13): the same
# 3D error (mean change -0.00 %, worst +0.11 %), 7.0 steps a solve instead of 8.6, 17 % less time.
STRETCHED_STEPS = 1


OPTIMISE_TOL = 1e-4  # a relative gain under this ends an optimisation (optimise)


def optimise(tp: TrajectoryCost[StateT, Any], X: StateT, max_iterations: int = 50, progress=None,
             stretches=(4.0, 1.0), tol: float = OPTIMISE_TOL):
    """Levenberg-Marquardt with bound clipping and graduated robustness, on the state ``X`` of
    ``tp`` (the trajectory Q, or a subclass's). Returns (X, iterations, cost).

    Converged: a relative gain under ``tol`` from an undamped step (one that needed more damping to
    succeed says nothing, alone, of the optimum's nearness), or from :data:`SMALL_GAINS` accepted
    steps in a row, damped or not. The cost is not smooth everywhere (the redescending loss's
    pieces, the joint limits, an offset crossing a whole frame, where a camera's first or last
    frame leaves the trajectory): near such a kink every undamped step overshoots and the damped
    one gains a few 1e-7, which, before that second rule, went on to the iteration limit (20-30
    iterations of an ``fte`` with the clocks estimated and the offsets near 0, against 6)."""
    it_total = 0
    cost = np.inf
    budget = [min(STRETCHED_STEPS, max_iterations)] * (len(stretches) - 1) + [max_iterations]
    total_budget = sum(budget)
    for stretch, iters in zip(stretches, budget):
        lam = 1e-3
        small = 0
        nrm = tp.normals_at(X, stretch)
        cost = tp.cost(X, nrm.cost)
        for _ in range(iters):
            it_total += 1
            improved = False
            # a stretched stage only has to bring the pose near the detections: it ends at its
            # first failed step instead of raising the damping until one succeeds
            for _try in range(10 if stretch == stretches[-1] else 1):
                try:
                    Xn = tp.step(X, nrm, lam)
                except IndefiniteSystem:  # numerically indefinite at this damping: damp more
                    tp.indefinite_steps += 1
                    lam *= 10.0
                    continue
                nrm_n = tp.normals_at(Xn, stretch)
                new_cost = tp.cost(Xn, nrm_n.cost)
                if new_cost <= cost:
                    improved = True
                    break
                lam *= 10.0
            if not improved:
                break
            step = tp.change(X, Xn)
            rel = (cost - new_cost) / max(cost, 1e-12)
            X, nrm, cost = Xn, nrm_n, new_cost
            lam = max(lam / 10.0, 1e-6)
            if progress:
                progress(Progress(stage="optimise", fraction=0.1 + 0.85 * min(1.0, it_total / total_budget),
                                  iteration=it_total, cost=cost))
            small = small + 1 if rel < tol else 0
            if (rel < tol and _try == 0) or small >= SMALL_GAINS or step < 1e-6:
                break
    return X, it_total, cost


NOISE_TOLERANCE = 0.1  # re-solve when the measured noise moved by more than this fraction
NOISE_ROUNDS = 2


def remeasure_noise(tp: TrajectoryCost[Any, Any], Q: np.ndarray, cost: float, max_iterations: int):
    """``measurement_std_px="auto"``: measure the noise again on the smoother's own residuals
    (:func:`graph.solve.noise.scatter_px`; the trajectory's fit takes few degrees of freedom per
    detection, so no correction) and, while it differs from the sigma solved with by more than
    ``NOISE_TOLERANCE``, solve again from ``Q`` (whose cost is ``cost``) with it. Returns
    (Q, iterations, cost)."""
    iterations = 0
    for _ in range(NOISE_ROUNDS):
        sigma = tp.scatter(Q)
        if not np.isfinite(sigma) or abs(sigma / tp.sigma_px - 1.0) <= NOISE_TOLERANCE:
            break
        tp.sigma_px = float(np.clip(sigma, *AUTO_RANGE_PX))
        Q, more, cost = optimise(tp, Q, max_iterations, stretches=(1.0,))
        iterations += more
    return Q, iterations, cost


SWAP_ROUNDS = 3  # decisions on the left/right pairs, each followed by a solve when one changed


def settle_swaps(tp: TrajectoryCost[StateT, Any], X: StateT, cost: float, max_iterations: int):
    """The left/right pairs the tracker swapped (:mod:`graph.solve.swaps`), decided at the robust
    optimum ``X`` (whose cost is ``cost``) and, where a decision changed, solved again and decided
    again, until none changes (at most :data:`SWAP_ROUNDS` times). Deciding where the stretched stage
    of the loss ended instead, to save the solve again, was measured and not kept: from that rough
    state the decisions cost more solves than they saved, and accuracy (the accuracy table's hard
    regime, seed 6 of 8, went to 16.5 mm; bench/RESULTS.md, section 23). A decision moves a few
    frames, whose gain is a tiny share of the whole run's cost: each solve's tolerance is the
    optimiser's times the share of frames moved (at the whole run's, a run of 1,200 frames stopped
    0.5 mm short of where the same frames solved in a window of 700 ended). Sets ``tp.side_swaps``
    and ``tp.swap_rate``. Returns (X, iterations, cost)."""
    iterations = 0
    if not tp.deciding_swaps:
        return X, iterations, cost
    for _ in range(SWAP_ROUNDS):
        moved = decide_swaps(tp, X)
        if not moved.any():
            break
        # converged when the gain is small next to the cost of the frames moved, not the whole run's
        X, more, cost = optimise(tp, X, max_iterations, stretches=(1.0,), tol=OPTIMISE_TOL * moved.mean())
        iterations += more
    return X, iterations, cost


def decide_swaps(tp: TrajectoryCost[StateT, Any], X: StateT) -> np.ndarray:
    """Decide every left/right pair at ``X`` from the detections as given (:func:`graph.solve.swaps.exchanged`)
    and solve on with them from now (``tp.meas``, ``tp.valid``; ``tp.side_swaps``, ``tp.swap_rate``). The
    hypotheses are compared at the detection noise measured on the residuals at ``X``
    (:func:`graph.solve.noise.scatter_px`), whatever noise the solve assumes: at 10 px solved as 5 px,
    the noise alone made pairs look swapped on runs that had none (the paper table's 10 px cells:
    10.2 mm against 9.4 without swaps decided).
    Returns the frames (N,) whose detections a decision changed."""
    nrm = tp.normals_at(X)
    measured = tp.scatter(X)
    scale = measured / tp.sigma_px if np.isfinite(measured) and measured > 0 else 1.0
    swap, tp.swap_rate = exchanged(nrm.uv, tp.given[0], tp.given[1], tp.sigma_cm * scale, tp.pairs,
                                   tp.prob.options.swap_rate)
    moved = (swap != tp.swapped).any(axis=(1, 2))
    if moved.any():
        tp.swapped = swap
        tp.meas, tp.valid = exchange(*tp.given, swap, tp.pairs)
        tp._kept_normals = None  # the same state, other detections
    tp.side_swaps = int(swap.sum())
    return moved


MOTION_TOLERANCE = 0.1  # solve again when a scale moved by more than this fraction
MOTION_ROUNDS = 2  # fits at an optimum, each followed by a solve when it moved


def fit_motion(tp: TrajectoryCost[Any, Any], X, choose_orders: bool = False) -> float:
    """Set each group's motion scale to the one of largest marginal likelihood given the data's
    quadratic model at ``X`` (:func:`graph.solve.smoothing.fit_motion_scales`), and with
    ``choose_orders`` its prior's order first (1, 2 or 3, by the evidence compared across orders).
    The evidence solves the linearised smoother for every scale tried, so ``X`` need not be its
    optimum: a start near the data will do. Returns how far the scales moved (largest
    ``|log(new / old)|``; infinite when an order changed).

    The orders are compared at the detection noise measured on the residuals at ``X``
    (:func:`graph.solve.noise.scatter_px`), whatever noise the solve assumes: the data's information and
    gradient scale as ``1 / sigma^2``, so the comparison takes ``H`` and ``g`` times
    ``(sigma_px / measured)^2``. At a noise stated too small the evidence prefers a low order (a
    first-order walk follows the noise the data then claim as signal): on the simulated cheetah as
    free points at 10 px, solved assuming 5 px, it chose the first order for every marker, 2.6x the
    3D error of the third (bench/RESULTS.md, section 12d)."""
    from graph.solve.smoothing import ORDERS, fit_motion_scales

    nrm = tp.normals_at(X)
    fit_args = (tp.poses(X), tp.Q0, PRIOR_SIGMA, tp.base_sigma3, tp.groups)
    orders = tp.orders
    if choose_orders:
        measured = tp.scatter(X)
        r = (tp.sigma_px / measured) ** 2 if np.isfinite(measured) and measured > 0 else 1.0
        orders = fit_motion_scales(nrm.H * r, nrm.g * r, *fit_args, max_stiffness=tp.max_stiffness,
                                   candidates=ORDERS).orders
    fit = fit_motion_scales(nrm.H, nrm.g, *fit_args, start=tp.motion_scales if np.all(orders == tp.orders) else None,
                            max_stiffness=tp.max_stiffness, orders=orders)
    moved = float(np.max(np.abs(np.log(fit.scales / tp.motion_scales))))
    if np.any(orders != tp.orders):
        moved = math.inf
    tp.set_motion_scales(fit.scales, orders)
    return moved


def refit_motion(tp: TrajectoryCost[StateT, Any], X: StateT, cost: float, max_iterations: int):
    """``motion_scale="auto"`` at the smoother's optimum ``X``: fit the scales again
    (:func:`fit_motion`) and, if one moved by more than ``MOTION_TOLERANCE``, solve again, up to
    ``MOTION_ROUNDS`` times. The fit and the solve are a fixed-point iteration: a trajectory solved
    with too loose a model follows the noise, and the evidence at it asks for a looser model still,
    so from a loose start each round moves only part of the way. A fit at the start (the initial
    poses, per-frame and noisy) was such a start: 20-40x looser than the answer on the simulated
    cheetah at 10 px, still 2-10x off after two rounds. The first solve with the skeleton's own
    process noise is a better one (there two rounds end within 2 %; bench/RESULTS.md, section 12),
    and costs a fit less. Each fit warm-starts from the scales before. With ``motion_order="auto"``
    the first fit also chooses each group's order (the later ones keep it). Returns (X, iterations,
    cost)."""
    iterations = 0
    choose = tp.prob.options.motion_order == "auto"
    for _ in range(MOTION_ROUNDS):
        moved = fit_motion(tp, X, choose_orders=choose)
        choose = False
        if moved <= np.log1p(MOTION_TOLERANCE):
            break
        X, more, cost = optimise(tp, X, max_iterations, stretches=(1.0,))
        iterations += more
    return X, iterations, cost


def marker_std(dpos: np.ndarray, Sigma: np.ndarray) -> np.ndarray:
    """Per-marker 3D standard deviations (N, M, 3) from the pose covariances ``Sigma`` (N, P, P)
    and the marker Jacobians ``dpos`` (N, M, 3, P): the square roots of diag(J_p Sigma_n J_p^T),
    each the row of ``J_p Sigma_n`` dotted with the row of ``J_p``."""
    var = np.einsum("nmip,nmip->nmi", np.matmul(dpos, Sigma[:, None]), dpos)
    return np.sqrt(np.maximum(var, 0.0))


def bone_lengths(prob: Problem, X: np.ndarray) -> np.ndarray:
    """Median length of each bone over the triangulated frames (0 where never seen)."""
    bones = prob.skeleton.bone_index
    if len(bones) == 0:
        return np.zeros(0)
    d = np.linalg.norm(X[:, bones[:, 0]] - X[:, bones[:, 1]], axis=-1)
    with np.errstate(invalid="ignore"):
        L = np.nanmedian(np.where(np.isfinite(d), d, np.nan), axis=0) if np.isfinite(d).any() else np.zeros(len(bones))
    return np.nan_to_num(L)


def solve_fte(prob: Problem, progress: ProgressCallback | None = None) -> Result:
    """``--method fte``: triangulate, initialise, then optimise the whole trajectory."""
    t0 = time.perf_counter()
    if progress:
        progress(Progress(stage="initialise", fraction=0.0))
    X, _, _ = robust_points(prob.calibration, prob.meas, prob.valid, prob.sigma_px)
    bl = bone_lengths(prob, X) if prob.skeleton.kind == "points" else None
    tp = TrajectoryProblem(prob, initial_poses(prob, X), bl)  # Q0: the weak anchor's target
    return solve_from(tp, tp.Q0.copy(), t0, progress)


def solve_from(tp: TrajectoryCost[Any, Any], X0, t0: float, progress: ProgressCallback | None = None) -> Result:
    """The rest of an ``fte`` solve from the start ``X0`` of ``tp`` (begun at ``t0``): optimise
    (graduated when robust), measure the noise again when asked, fit the motion model at the
    optimum when asked (:func:`refit_motion`; the first solve uses the skeleton's process noise),
    and the result with its uncertainty."""
    o = tp.prob.options
    notes = []
    stiff = tp.bound_stiffness(tp.normals_at(X0).H)  # a fit starts from scale 1: bounded too, without a word
    if stiff and o.motion_scale != "auto":
        notes.append(stiff)
    t_init = time.perf_counter() - t0
    if progress:
        progress(Progress(stage="optimise", fraction=0.1))
    X, iterations, cost = optimise(tp, X0, o.max_iterations, progress, stretches=(4.0, 1.0) if o.robust else (1.0,))
    X, more, cost = settle_swaps(tp, X, cost, o.max_iterations)
    iterations += more
    # the motion model first: the noise measured about a trajectory smoothed by the skeleton's own
    # process noise (for a slow animal far too loose: every frame its own triangulation) comes out too small
    if o.motion_scale == "auto":
        X, more, cost = refit_motion(tp, X, cost, o.max_iterations)
        iterations += more
    if o.measurement_std_px == "auto":
        X, more, cost = remeasure_noise(tp, X, cost, o.max_iterations)
        iterations += more
        if o.motion_scale == "auto" and more:  # solved with a new noise: the evidence moved with it
            X, more, cost = refit_motion(tp, X, cost, o.max_iterations)
            iterations += more
    t_solve = time.perf_counter() - t0 - t_init
    if progress:
        progress(Progress(stage="uncertainty", fraction=0.95, iteration=iterations, cost=cost))
    result = trajectory_result(tp, X, "fte", seconds={"init": t_init, "solve": t_solve}, iterations=iterations,
                               cost=cost, notes=notes)
    if progress:
        progress(Progress(stage="done", fraction=1.0, iteration=iterations, cost=cost))
    return result


LOOSE_MOTION = 0.01  # the smoothed motion's third differences under this share of the process noise


def loose_motion(residuals: np.ndarray) -> str | None:
    """A one-line warning when the motion model is far looser than the motion it smoothed: the
    median of the whitened differences ``residuals`` (:meth:`TrajectoryProblem.motion_residuals`:
    ``|q_{n+3} - 3 q_{n+2} + 3 q_{n+1} - q_n| / sigma_3``, or each group's k-th differences) under
    :data:`LOOSE_MOTION`. A model that fits has these near its own scale (0.12-0.14 on simulated
    cheetah runs, with the model's or free points); the cheetah's default process noise on a fly's
    legs gave 0.0014: the motion prior then carries no weight, every frame is its own
    triangulation, and ``ekf`` and ``fte`` return the same numbers."""
    d3 = np.abs(residuals)
    d3 = d3[np.isfinite(d3)]
    if d3.size < 10:
        return None
    ratio = float(np.median(d3))
    if ratio >= LOOSE_MOTION:
        return None
    return (f"the motion model is about {1 / max(ratio, 1e-12):.0f}x looser than the motion it smoothed, so it "
            f"smooths next to nothing (each frame is close to its own triangulation); fit it to the data with "
            f"motion_scale 'auto' (--motion-scale auto), or give a smaller motion scale")


BOUND_TOLERANCE = 1e-3  # a parameter this close to a joint limit counts as held by it


def trajectory_result(tp: TrajectoryCost[Any, Any], X, method: str, *, seconds: dict[str, float],
                      iterations: int, cost: float | None = None, causal: np.ndarray | None = None,
                      per_frame_ms: dict[str, float] | None = None, notes: list[str] | None = None) -> Result:
    """The :class:`Result` of a smoothed state ``X`` of ``tp`` (``fte`` and ``ekf``): markers by
    forward kinematics, reprojections and residuals at ``X``, and, when the options ask for it,
    the uncertainties (:meth:`TrajectoryProblem.estimate`). ``cost`` is computed at ``X`` when not
    given; ``causal`` (N, P) are an online method's per-frame poses. A free point never seen by
    two cameras has no estimate (NaN)."""
    prob = tp.prob
    t1 = time.perf_counter()
    normals = tp.normals_at(X)
    if cost is None:
        cost = tp.cost(X, normals.cost)
    Q = tp.poses(X)
    est = tp.estimate(X, normals, prob.options.uncertainty)
    pos, std, params_std = est.positions, est.std, est.params_std
    report = dict(est.report or {})
    if prob.options.motion_scale == "auto":  # with the order each scale was fitted for (chosen, or given)
        report["motion_scales"] = {name: float(v) for name, v in zip(tp.group_names(), tp.motion_scales)}
        report["motion_orders"] = {name: int(k) for name, k in zip(tp.group_names(), tp.orders)}
    loose = loose_motion(tp.motion_residuals(Q)) if prob.options.motion_scale != "auto" else None
    report["warnings"] = list(notes or []) + report.get("warnings", []) + ([loose] if loose else [])
    if tp.indefinite_steps:
        report["warnings"].append(f"{tp.indefinite_steps} optimiser steps met a numerically indefinite system and "
                                  "were damped more (a motion model far stiffer than the data, or a marker no camera "
                                  "pair sees for long)")
    if tp.ridge:
        report["warnings"].append(
            "the uncertainties met a numerically singular information (a point whose depth nothing but the weak "
            "anchor fixes, such as one seen only from one place) and " + (
                f"were computed with a ridge of {tp.ridge:.0e} of the largest information: their sd are a lower bound "
                "there" if np.isfinite(tp.ridge) else "could not be computed (sd NaN)"))
    causal_pos = prob.skeleton.positions(causal) if causal is not None else None
    views = prob.views()  # (N, M) cameras that saw each marker confidently
    few = views < prob.options.min_views  # left NaN on request (min_views)
    if prob.skeleton.kind == "points":
        # a free point no camera pair ever sees has no depth but the start's guess: no estimate. Elsewhere
        # a frame fewer than two cameras see is answered by the motion model (its sd grows through the gap:
        # the marginals), unless min_views asks for more; a point bones tie to others is held by them
        tied = np.zeros(len(prob.markers), dtype=bool)
        if len(prob.skeleton.bones):
            tied[np.unique(prob.skeleton.bone_index)] = True
        never = (views.max(axis=0) < 2) & ~tied
        few |= never[None]
        if len(prob.skeleton.bones):
            few &= ~(tied[None] & (views.max(axis=0) >= 2)[None])
        gaps = int(few.sum() - never.sum() * prob.frames)
        if gaps > 0:
            report["warnings"].append(f"{gaps} marker positions in frames that fewer than {prob.options.min_views} "
                                      "cameras see confidently are left without an estimate (NaN, min_views)")
    for a in (pos, std, causal_pos):
        if a is not None:
            a[few] = np.nan
    alone = (views < 2) & ~few
    report["motion_only_frames"] = {m: int(k) for m, k in zip(prob.markers, alone.sum(axis=0)) if k}
    report["side_swaps"], report["swap_rate"] = tp.side_swaps, tp.swap_rate
    sk = prob.skeleton
    active = int(np.sum((Q <= sk.lower + BOUND_TOLERANCE) | (Q >= sk.upper - BOUND_TOLERANCE)))
    s = normals.s
    return build_result(prob, method, positions=pos, std=std, reprojections=normals.uv.transpose(1, 0, 2, 3), s=s,
                        outlier=s >= OUTLIER_S, sigma_px=tp.sigma_px,
                        seconds={**seconds, "uncertainty": time.perf_counter() - t1}, iterations=iterations,
                        cost=cost, params=Q, params_std=params_std, causal_positions=causal_pos,
                        per_frame_ms=per_frame_ms, bounds_active=active, report=report)
