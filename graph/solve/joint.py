"""The trajectory solved jointly with what every frame shares: the animal's proportions and the
cameras' clocks (``body="estimate"``, ``sync="estimate"``).

Unknowns: the poses ``q_n`` and one vector ``W`` shared by all frames:

* ``l_g``, the log scale of each length group g of a kinematic skeleton (:mod:`graph.skeleton`):
  offsets ``exp(l_g) u_k``; the prior ``l_g ~ N(0, LENGTH_PRIOR_SD^2)`` is a log-normal about the
  model's lengths, loose enough for a juvenile (0.75x is 1.3 sd) or a large male;
* ``log L_b``, the length of each bone of a points skeleton, about the triangulated medians
  (``BONE_PRIOR_SD``);
* ``tau_c``, the time offset (frames) of each camera but the first: camera c's frame m was taken at
  time ``m + tau_c``; its detections are projections of the pose interpolated between the two
  frames around that time (:func:`graph.solve.kernels.window_normals`). The prior ``N(tau0_c, 1)``
  centres each on the whole-frame search (:mod:`graph.solve.sync`).

The cost is ``fte``'s (:mod:`graph.solve.fte`) with the detections so evaluated, plus
``1/2 |(W - W0) / sd|^2``. Each Gauss-Newton system is one GTSAM graph
(:meth:`JointTrajectoryProblem.joint_graph`): per frame a ``HessianFactor`` on ``(q_n, q_{n+1}, W)``
(``(q_n, W)`` without time offsets), the motion factors, and one factor on ``W``, eliminated in time
order with ``W`` last: the arrow-head on the banded chain, linear in frames. The step makes that
elimination compiled, without building the graph (:meth:`JointTrajectoryProblem.step`,
:func:`graph.solve.marginals.chain_forward`; equal to GTSAM's to 1e-9 in the tests). The marginals, of
the poses and of ``W``, come from the same structure in one compiled pass
(:func:`graph.solve.marginals.banded_marginals`); a marker's sd includes the lengths' own uncertainty,
``Var p = [J_q J_l] Cov(q_n, l) [J_q J_l]^T``.

An offset is *not identified* when no whole-frame lag stands out for its camera (a still animal, a
camera that shares too little with the others: it then stays at its start, 0 or the one of the
camera it was placed against), or when the data shrink its prior sd by less than half; the report
names those cameras.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from typing import NamedTuple

import gtsam
import numpy as np

from graph import kinematics
from graph.compiled import for_items
from graph.errors import InputError
from graph.skeleton import KernelArgs
from graph.solve import kernels
from graph.solve.fte import PRIOR_SIGMA, Estimate, IndefiniteSystem, TrajectoryCost, bone_lengths, solve_from, solve_fte
from graph.solve.initial import body_scale, initial_poses
from graph.solve.marginals import chain_band, information_taken, ridged_marginals, solve_band
from graph.solve.problem import Problem
from graph.solve.robust import A as RA
from graph.solve.robust import B as RB
from graph.solve.robust import C as RC
from graph.solve.smoothing import STENCILS
from graph.solve.sync import coarse_offsets, on_reference_clock, shift_and_fraction
from graph.solve.triangulate import robust_points
from graph.types import Progress, ProgressCallback, Result

LENGTH_PRIOR_SD = 0.22  # log-normal sd of a length group's scale about the model's
BONE_PRIOR_SD = 0.5  # log-normal sd of a points skeleton's bone about its triangulated median
OFFSET_PRIOR_SD = 1.0  # frames, about the whole-frame search's offset
SCALE_RANGE = (0.4, 2.5)  # a length group's scale stays within these factors of the model's
OFFSET_RANGE = 2.0  # an offset stays within this many frames of its start
IDENTIFIED_SHRINK = 0.5  # an offset is identified when its sd is below this fraction of the prior's


@dataclass
class SharedUnknowns:
    """The layout of ``W``: [log scales of ``groups``, log lengths of ``bones``, offsets of
    ``offset_cameras``], with their prior means and sds and bounds; what stays fixed: ``scales``
    (G_all,) of every length group and ``tau`` (C,) of every camera."""

    groups: list[int]  # estimated length groups (indices into the skeleton's length_groups)
    bones: list[int]  # estimated bones (indices into the skeleton's bones)
    offset_cameras: list[int]
    mean: np.ndarray
    sd: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    scales: np.ndarray  # (G_all,) the length groups' scales when not estimated
    tau: np.ndarray  # (C,) the offsets when not estimated
    untimed: list[int] = field(default_factory=list)  # cameras whose offsets were to be estimated, but stay

    @property
    def size(self) -> int:
        return len(self.groups) + len(self.bones) + len(self.offset_cameras)

    def split(self, W: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Every length group's scale (G_all,), the estimated bones' lengths and every camera's offset (C,)."""
        a, b = len(self.groups), len(self.groups) + len(self.bones)
        scales = self.scales.copy()
        scales[self.groups] = np.exp(W[:a])
        tau = self.tau.copy()
        tau[self.offset_cameras] = W[b:]
        return scales, np.exp(W[a:b]), tau


class JointState(NamedTuple):
    Q: np.ndarray  # (N, P)
    W: np.ndarray  # (G,)


class JointNormals(NamedTuple):
    """The robust measurement cost at a :class:`JointState` (:func:`graph.solve.kernels.window_normals`,
    assembled per frame)."""

    H: np.ndarray  # (N, P, P) each frame's information
    Hx: np.ndarray  # (N, P, P) between frame n and n+1
    HW: np.ndarray  # (N, P, G) between frame n and W
    HWW: np.ndarray  # (G, G)
    g: np.ndarray  # (N, P)
    gW: np.ndarray  # (G,)
    uv: np.ndarray  # (N, C, M, 2)
    s: np.ndarray  # (N, C, M)
    w: np.ndarray
    cost: np.ndarray  # (N,)


def _marker_columns(pt_base: np.ndarray, marker_point: np.ndarray, pt_col: np.ndarray) -> np.ndarray:
    """The columns of W (length groups) on each marker's chain (M, D), padded with -1."""
    cols = []
    for k in marker_point:
        own, p = set(), int(k)
        while p >= 0:
            if pt_col[p] >= 0:
                own.add(int(pt_col[p]))
            p = int(pt_base[p])
        cols.append(sorted(own))
    out = np.full((len(cols), max(1, max((len(c) for c in cols), default=0))), -1, dtype=np.int64)
    for m, c in enumerate(cols):
        out[m, :len(c)] = c
    return out


class JointTrajectoryProblem(TrajectoryCost[JointState, JointNormals]):
    """:class:`graph.solve.fte.TrajectoryCost` with the shared unknowns ``W`` (module docstring).
    ``bone_len`` are the bones' starting lengths (their sds stay those of the start)."""

    def __init__(self, prob: Problem, Q0: np.ndarray, unknowns: SharedUnknowns, bone_len: np.ndarray | None = None):
        super().__init__(prob, Q0, bone_len)
        self.unknowns = unknowns
        sk = prob.skeleton
        self.G = unknowns.size
        self.base_offset = sk.arrays.pt_offset
        pg = sk.point_group if sk.point_group is not None else np.full(len(sk.arrays.pt_base), -1)
        self.point_group = pg
        col = {g: i for i, g in enumerate(unknowns.groups)}
        self.pt_col = np.array([col.get(int(g), -1) for g in pg], dtype=np.int64)
        self.marker_wdep = _marker_columns(sk.arrays.pt_base, sk.arrays.marker_point, self.pt_col)
        b0 = len(unknowns.groups)
        bcol = {b: b0 + i for i, b in enumerate(unknowns.bones)}
        self.bone_col = np.array([bcol.get(i, -1) for i in range(len(self.bones))], dtype=np.int64)
        t0 = b0 + len(unknowns.bones)
        tcol = {c: t0 + i for i, c in enumerate(unknowns.offset_cameras)}
        self.tau_col = np.array([tcol.get(c, -1) for c in range(prob.cameras)], dtype=np.int64)
        self.w_key = len(self.groups) * self.N
        self._ordering.push_back(self.w_key)
        self.prior_info = 1.0 / unknowns.sd**2

    # -- the cost -----------------------------------------------------------------------------

    def _kernel_skeleton(self, scales: np.ndarray) -> KernelArgs:
        if len(scales) == 0:  # no length groups (free points)
            return self.sk_args
        factor = np.where(self.point_group >= 0, scales[np.maximum(self.point_group, 0)], 1.0)
        args = self.sk_args
        return args[:6] + (self.base_offset * factor[:, None],) + args[7:]  # pt_offset scaled

    def _markers(self, Q: np.ndarray, scales: np.ndarray):
        """The markers' positions (N, M, 3) and their Jacobians in the poses (N, M, 3, P) and the
        length groups (N, M, 3, G) of the body scaled by ``scales``, at poses ``Q``."""
        args = self._kernel_skeleton(scales)
        return for_items(kinematics.fk_body_jacobian_batch, len(Q))(Q, *args[:8], self.pt_col, self.G)

    def normals(self, X: JointState, stretch=1.0) -> JointNormals:
        scales, bone_len, tau = self.unknowns.split(X.W)
        shift, frac = shift_and_fraction(tau)
        bl = self.bone_len.copy()
        bl[self.bone_col >= 0] = bone_len
        pos, dpos, dlen = self._markers(X.Q, scales)
        Ha, Hb, Hab, ga, gb, HaW, HbW, HWW, gW, uv, s, w, cost = for_items(kernels.window_normals, len(X.Q))(
            X.Q, self.meas, self.valid, self.intr, self.Rc, self.tc, self.sigma_cm, self.prob.options.robust,
            RA * stretch, RB * stretch, RC * stretch, shift, frac, self.tau_col, pos, dpos, dlen, self.marker_wdep,
            self.sk_args[8], self.bones, bl, self.bone_sigma, self.bone_col)
        H, g, HW = Ha.copy(), ga.copy(), HaW.copy()
        H[1:] += Hb[:-1]
        g[1:] += gb[:-1]
        HW[1:] += HbW[:-1]
        return JointNormals(H, Hab, HW, HWW.sum(0), g, gW.sum(0), uv, s, w, cost)

    def cost(self, X: JointState, data_cost) -> float:
        pw = (X.W - self.unknowns.mean) / self.unknowns.sd
        return super().cost(X.Q, data_cost) + 0.5 * float(pw @ pw)

    # -- the Gauss-Newton system ----------------------------------------------------------------

    def _system(self, X: JointState, nrm: JointNormals, lam: float, prior: bool = True):
        """The frames' and W's blocks of the damped system over the new state, in absolute form
        (:class:`graph.solve.fte.TrajectoryCost`): ``G x' = gvec`` with ``gvec = G_data x - g + ...``."""
        Q, W = X
        w = 1.0 / PRIOR_SIGMA**2
        Gd = nrm.H + (w + lam) * np.eye(self.P)
        gv = (np.einsum("npq,nq->np", nrm.H, Q) - nrm.g + w * self.Q0 + lam * Q
              + np.einsum("npg,g->np", nrm.HW, W))
        gv[:-1] += np.einsum("npq,nq->np", nrm.Hx[:-1], Q[1:])
        gv[1:] += np.einsum("nqp,nq->np", nrm.Hx[:-1], Q[:-1])
        GW = nrm.HWW + np.diag(self.prior_info + lam)
        gW = (nrm.HWW @ W - nrm.gW + np.einsum("npg,np->g", nrm.HW, Q) + self.prior_info * self.unknowns.mean
              + lam * W)
        return Gd, gv, GW, gW

    def _chains(self, Gd: np.ndarray, nrm: JointNormals) -> tuple[list, list]:
        """Each group's chain blocks (:func:`graph.solve.marginals.chain_band`: the per-frame ``Gd``
        (N, P, P), the motion prior of its order, the neighbouring frames' coupling ``Hx``) and its
        coupling to W (N, d, G): what the step solves and the marginals invert."""
        w2 = 1.0 / self.sigma3**2
        bands, Bs = [], []
        for order, idx in zip(self.orders, self.groups):
            a, b = idx[0], idx[-1] + 1
            band = chain_band(np.ascontiguousarray(Gd[:, a:b, a:b]), w2[a:b], STENCILS[int(order)])
            band[:-1, 1] += nrm.Hx[:-1, a:b, a:b]
            bands.append(band)
            Bs.append(np.ascontiguousarray(nrm.HW[:, a:b]))
        return bands, Bs

    def step(self, X: JointState, nrm: JointNormals, lam: float) -> JointState:
        """The damped Gauss-Newton step: each group's chain (with the neighbouring frames' coupling
        ``Hx``) eliminated in time order by the compiled block Cholesky
        (:func:`graph.solve.marginals.solve_band`), W's system reduced by every chain and solved, then
        each chain's back substitution: the elimination GTSAM makes of :meth:`joint_graph` (tests)."""
        Gd, gv, GW, gW = self._system(X, nrm, lam)
        bands, Bs = self._chains(Gd, nrm)
        rs = [np.ascontiguousarray(gv[:, idx[0]:idx[-1] + 1]) for idx in self.groups]
        try:
            xs, W = solve_band(bands, Bs, rs, GW, gW)
        except np.linalg.LinAlgError as e:
            raise IndefiniteSystem(f"the smoother's system is not positive definite: {e}") from None
        Q = np.empty_like(X.Q)
        for idx, x in zip(self.groups, xs):
            Q[:, idx[0]:idx[-1] + 1] = x
        sk = self.prob.skeleton
        return JointState(np.clip(Q, sk.lower, sk.upper), np.clip(W, self.unknowns.lower, self.unknowns.upper))

    def joint_graph(self, X: JointState, nrm: JointNormals, lam: float) -> gtsam.GaussianFactorGraph:
        """The same damped system as GTSAM's graph (the reference :meth:`step` is tested against)."""
        Gd, gv, GW, gW = self._system(X, nrm, lam)
        graph = gtsam.GaussianFactorGraph()
        for f in self._motion:
            graph.push_back(f)
        kw, G = self.w_key, self.G
        coupled = bool(np.any(nrm.Hx))
        zGG, zG = np.zeros((G, G)), np.zeros(G)
        for gi, idx in enumerate(self.groups):
            a, b = idx[0], idx[-1] + 1
            d = b - a
            zdd, zdG, zd = np.zeros((d, d)), np.zeros((d, G)), np.zeros(d)
            Gg, gg, HWg, Hxg = Gd[:, a:b, a:b], gv[:, a:b], nrm.HW[:, a:b], nrm.Hx[:, a:b, a:b]
            for n in range(self.N):
                k = self.key(n, gi)
                if coupled and n + 1 < self.N:
                    graph.add(gtsam.HessianFactor(k, self.key(n + 1, gi), kw, Gg[n], Hxg[n], HWg[n], gg[n],
                                                  zdd, zdG, zd, zGG, zG, 0.0))
                else:
                    graph.add(gtsam.HessianFactor(k, kw, Gg[n], HWg[n], gg[n], zGG, zG, 0.0))
        graph.add(gtsam.HessianFactor(kw, GW, gW, 0.0))
        return graph

    @staticmethod
    def change(X: JointState, Xn: JointState) -> float:
        return float(max(np.max(np.abs(Xn.Q - X.Q)), np.max(np.abs(Xn.W - X.W), initial=0.0)))

    def poses(self, X: JointState) -> np.ndarray:
        return X.Q

    # -- uncertainty ----------------------------------------------------------------------------

    def joint_marginals(self, nrm: JointNormals):
        """Marginal covariances of every pose (N, P, P), between each pose and W (N, P, G), and of
        W (G, G), at the optimum (undamped; module docstring). For free points without bones, one
        chain per marker: each marker's marginals use W's information with every other marker's
        chain eliminated (:func:`graph.solve.marginals.information_taken`)."""
        G = self.G
        DW = nrm.HWW + np.diag(self.prior_info)
        bands, Bs = self._chains(nrm.H + np.eye(self.P)[None] / PRIOR_SIGMA**2, nrm)
        Sigma = np.zeros((self.N, self.P, self.P))
        cross = np.zeros((self.N, self.P, G))
        if len(self.groups) == 1:
            Sigma, cross, SW, self.ridge = ridged_marginals(bands[0], Bs[0], DW)
            return Sigma, cross, SW
        # what each chain takes off W's information when eliminated
        taken = [information_taken(band, B) for band, B in zip(bands, Bs)]
        total = sum(taken)
        SW = np.zeros((G, G))
        for idx, band, B, t in zip(self.groups, bands, Bs, taken):
            a, b = idx[0], idx[-1] + 1
            S, X, SW, ridge = ridged_marginals(band, B, DW - (total - t))
            self.ridge = max(self.ridge, ridge)
            Sigma[:, a:b, a:b] = S
            cross[:, a:b] = X
        return Sigma, cross, SW

    def estimate(self, X: JointState, normals: JointNormals, uncertainty: bool) -> Estimate:
        """Markers of the estimated body and, with ``uncertainty``, their sd (module docstring); the
        report's ``body_lengths`` and ``time_offsets_frames`` with their sds from the marginals of W."""
        scales, bone_len, tau = self.unknowns.split(X.W)
        pos, dpos, dlen = self._markers(X.Q, scales)
        if not uncertainty:
            return Estimate(pos, np.full(pos.shape, np.nan), None, self._report(X, None))
        Sigma, cross, SW = self.joint_marginals(normals)
        # Var p = Jq S Jq^T + Jq X Jl^T + Jl X^T Jq^T + Jl SW Jl^T (the length columns of W move markers)
        JqS = np.matmul(dpos, Sigma[:, None])
        var = np.einsum("nmip,nmip->nmi", JqS, dpos)
        JqX = np.matmul(dpos, cross[:, None])  # (N, M, 3, G)
        var += 2.0 * np.einsum("nmig,nmig->nmi", JqX, dlen)
        var += np.einsum("nmig,gh,nmih->nmi", dlen, SW, dlen)
        std = np.sqrt(np.maximum(var, 0.0))
        params_std = np.sqrt(np.maximum(np.diagonal(Sigma, axis1=-2, axis2=-1), 0.0))
        return Estimate(pos, std, params_std, self._report(X, SW))

    def _report(self, X: JointState, SW: np.ndarray | None) -> dict:
        u = self.unknowns
        sk = self.prob.skeleton
        scales, bone_len, tau = u.split(X.W)
        sd = np.sqrt(np.maximum(np.diag(SW), 0.0)) if SW is not None else np.full(self.G, np.nan)
        out: dict = {"warnings": []}
        if u.groups or sk.kind != "points" and self.prob.options.body == "given":
            model = sk.model_lengths
            lengths = {}
            for g, name in enumerate(sk.length_groups):
                L = float(model[g] * scales[g])
                col = u.groups.index(g) if g in u.groups else -1
                lengths[name] = {"length_m": L, "std_m": float(L * sd[col]) if col >= 0 else 0.0,
                                 "model_m": float(model[g])}
            out["body_lengths"] = lengths
        if u.bones:
            out["body_lengths"] = {
                f"{sk.bones[b][0]}-{sk.bones[b][1]}": {"length_m": float(bone_len[i]),
                                                       "std_m": float(bone_len[i] * sd[len(u.groups) + i]),
                                                       "model_m": float(np.exp(u.mean[len(u.groups) + i]))}
                for i, b in enumerate(u.bones)}
        t0 = len(u.groups) + len(u.bones)
        tau_sd = np.zeros(len(tau))
        names = self.prob.calibration.names
        lost = [names[c] for c in u.untimed]
        for i, c in enumerate(u.offset_cameras):
            tau_sd[c] = sd[t0 + i]
            if not (sd[t0 + i] < IDENTIFIED_SHRINK * u.sd[t0 + i]):
                lost.append(names[c])
        if u.offset_cameras or u.untimed or np.any(tau != 0):
            out["time_offsets_frames"] = [float(t) for t in tau]
            out["time_offsets_std_frames"] = [float(t) for t in tau_sd]
        if lost:
            out["offsets_not_identified"] = lost
            out["warnings"].append(f"the motion does not tell the time offsets of {', '.join(lost)} (the animal "
                                   "moves too little, or those cameras see too little of it): they stay near "
                                   "their start; give them with time_offsets if they are known")
        return out


# -- the method ---------------------------------------------------------------------------------

def shares_unknowns(prob: Problem) -> bool:
    """Whether the solve has shared unknowns, or a body or clocks other than the model's: a body
    to estimate (a kinematic skeleton's lengths, or a points skeleton's bones), a given body,
    offsets to estimate, or offsets given that are not all zero."""
    o, sk = prob.options, prob.skeleton
    body = (o.body == "given" or o.body == "estimate" and (
        bool(sk.bones) if sk.kind == "points" else bool(sk.length_groups)))
    return (body or o.sync == "estimate"
            or (o.time_offsets is not None and any(float(t) != 0.0 for t in o.time_offsets)))


def given_offsets(prob: Problem) -> np.ndarray:
    """The options' time offsets (C,), relative to camera 1; zeros when none are given."""
    t = prob.options.time_offsets
    if t is None:
        return np.zeros(prob.cameras)
    if len(t) != prob.cameras:
        raise InputError(f"time_offsets: {len(t)} given for {prob.cameras} cameras (one per camera, in frames)")
    offsets = np.asarray(t, dtype=float)
    return offsets - offsets[0]


def body_scale_from_points(prob: Problem, X: np.ndarray) -> float:
    """The animal's overall size against the model's from the triangulated points ``X``, the noise's
    bias on each bone's length taken out (:func:`graph.solve.initial.body_scale`: the median over the
    bones of the length whose noisy distance has the observed median, over the model's), within
    :data:`SCALE_RANGE`; 1 when no bone is seen. The plain median of the distances put a cheetah of
    the model's size at 1.16x where each point was 80-100 mm off."""
    return body_scale(prob.skeleton, X, SCALE_RANGE)


def shared_unknowns(prob: Problem, X: np.ndarray, tau0: np.ndarray, bone_len: np.ndarray | None,
                    timed: np.ndarray | None = None) -> tuple[SharedUnknowns, np.ndarray, np.ndarray | None]:
    """The layout of W for the options, its start, and the bones' fixed lengths when given. With
    ``sync="estimate"`` the offsets of the cameras ``timed`` (C,) marks are unknowns; the others stay."""
    o, sk = prob.options, prob.skeleton
    G_all = len(sk.length_groups)
    scales = np.ones(G_all)
    groups: list[int] = []
    bones: list[int] = []
    mean, sd, lo, hi, start = [], [], [], [], []
    if o.body == "given":
        given = dict(o.body_lengths or {})
        if sk.kind == "points":
            names = [f"{a}-{b}" for a, b in sk.bones]
            bone_len = np.array([given.pop(n, np.nan) for n in names]) if bone_len is not None else bone_len
            if bone_len is not None:
                bone_len = np.where(np.isfinite(bone_len), bone_len, 0.0)
        else:
            scales = sk.scales_for(given)
            for name in sk.length_groups:
                given.pop(name, None)
        if given:
            raise InputError(f"body_lengths: not a length of the {sk.name} skeleton: {', '.join(sorted(given))}")
    elif o.body == "estimate":
        if sk.kind == "points":
            seen = bone_len if bone_len is not None else np.zeros(0)
            bones = [i for i, L in enumerate(seen) if L > 0]
            for i in bones:
                mean.append(np.log(seen[i]))
                sd.append(BONE_PRIOR_SD)
                lo.append(np.log(seen[i]) - 3 * BONE_PRIOR_SD)
                hi.append(np.log(seen[i]) + 3 * BONE_PRIOR_SD)
                start.append(np.log(seen[i]))
        else:
            groups = list(range(G_all))
            s0 = np.log(body_scale_from_points(prob, X))
            for _ in groups:
                mean.append(0.0)
                sd.append(LENGTH_PRIOR_SD)
                lo.append(np.log(SCALE_RANGE[0]))
                hi.append(np.log(SCALE_RANGE[1]))
                start.append(s0)
    cams: list[int] = []
    if o.sync == "estimate":
        cams = [c for c in range(1, prob.cameras) if timed is None or timed[c]]
        for c in cams:
            mean.append(tau0[c])
            sd.append(OFFSET_PRIOR_SD)
            lo.append(tau0[c] - OFFSET_RANGE)
            hi.append(tau0[c] + OFFSET_RANGE)
            start.append(tau0[c])
    arr = lambda v: np.asarray(v, dtype=float)  # noqa: E731
    u = SharedUnknowns(groups=groups, bones=bones, offset_cameras=cams, mean=arr(mean), sd=arr(sd), lower=arr(lo),
                       upper=arr(hi), scales=scales, tau=tau0.copy(),
                       untimed=[c for c in range(1, prob.cameras) if o.sync == "estimate" and c not in cams])
    return u, arr(start), bone_len


def solve_fte_joint(prob: Problem, progress: ProgressCallback | None = None) -> Result:
    """``--method fte`` (the registry's): :func:`graph.solve.fte.solve_fte` when the body is the model's
    and the clocks are in sync, else the joint solve of this module: the whole-frame offsets
    (:mod:`graph.solve.sync`), the triangulation on the reference clock, a start of the body's size and
    the poses, then one optimisation of the trajectory with W."""
    if not shares_unknowns(prob):
        return solve_fte(prob, progress)
    o = prob.options
    t0 = time.perf_counter()
    if progress:
        progress(Progress(stage="initialise", fraction=0.0))
    tau0 = given_offsets(prob)
    timed = None
    if o.sync == "estimate":
        coarse = coarse_offsets(prob.calibration, prob.meas, prob.valid, o.fps)
        tau0, timed = coarse.frames, coarse.decided
    meas_ref, valid_ref = on_reference_clock(prob.meas, prob.valid, tau0)
    X, _, _ = robust_points(prob.calibration, meas_ref, valid_ref, prob.sigma_px)
    bl = bone_lengths(prob, X) if prob.skeleton.kind == "points" else None
    unknowns, W0, bl = shared_unknowns(prob, X, tau0, bl, timed)
    scales0, _, _ = unknowns.split(W0)
    start = replace(prob, skeleton=prob.skeleton.scaled(scales0) if prob.skeleton.kind != "points" else prob.skeleton,
                    meas=meas_ref, valid=valid_ref)
    tp = JointTrajectoryProblem(prob, initial_poses(start, X), unknowns, bl)  # Q0: the anchor's target
    return solve_from(tp, JointState(tp.Q0.copy(), W0), t0, progress)
