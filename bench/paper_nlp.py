"""The AcinoSet paper's Full Trajectory Estimation as a nonlinear program, solved by IPOPT.

Joska et al. (ICRA 2021) wrote FTE in Pyomo and solved it with IPOPT (MUMPS). This module writes
the same program directly for IPOPT through ``cyipopt`` (no Pyomo: from PyPI and Debian packages
alone Pyomo cannot reach IPOPT, see bench/bench_paper_ipopt.py), with exact first and second derivatives, as
Pyomo's AMPL interface would give them. It reuses acinoset's skeleton spec, camera calibration,
measurement std and robust loss, so that IPOPT and ``fte`` see the same cost.

Variables, for frames n = 0..N-1 and pose parameters p = 0..P-1 (P = 25 for the cheetah), h = 1/fps:

* the pose ``q[n]``, its rate ``qd[n]`` and acceleration ``qdd[n]``;
* the model slack ``w[n]`` (n = 0..N-2), the change of acceleration from one frame to the next;
* one measurement slack ``e[j]`` (2 pixels) per detection j = (n, c, m) above the likelihood threshold.

Equality constraints (the constant-acceleration model and the measurements)::

    q[n+1]   = q[n] + h qd[n] + h^2/2 qdd[n]
    qd[n+1]  = qd[n] + h qdd[n]
    qdd[n+1] = qdd[n] + w[n]
    pi_c(p_m(q[n])) - e[j] = z[j]          (fisheye projection of forward kinematics)

Variable bounds: the skeleton's joint limits on ``q``.

Cost, on the slacks::

    sum_j rho(|e[j]| / sigma)  +  motion(w)  [+  1/2 sum_n |(q[n] - q0[n]) / 10|^2]

``rho`` is :func:`graph.solve.robust.redescending` (a, b, c = 3, 10, 20; sigma = 5 px), as in ``fte``.
Two motion costs:

* ``cost="paper"``: the paper's ``1/2 sum_n sum_p (w[n,p] / sigma_p)^2`` with sigma_p the skeleton's
  process noise; no anchor term.
* ``cost="fte"`` (default): acinoset ``fte``'s cost, written in these variables. Under the
  constraints the third difference of q is ``h^2/2 (w[n] + w[n+1])``, so fte's motion term
  ``1/2 |third difference / (h^2 sigma_p)|^2`` is ``1/2 sum ((w[n,p] + w[n+1,p]) / (2 sigma_p))^2``, and
  fte's weak anchor to its start ``q0`` (sigma 10) is added. This cost does not see the alternating
  mode ``qdd[n] += (-1)^n d, w[n] -= 2 (-1)^n d`` (it leaves q unchanged), nor ``w[N-2]``; bounding
  ``w[0] = w[N-2] = 0`` removes both, so the feasible set maps one-to-one onto the trajectories
  q and IPOPT minimises exactly fte's function of q.

Derivatives: each frame's 2 C M projections as a function of its 25 parameters are built once,
symbolically, with CasADi (forward kinematics from the skeleton arrays, the OpenCV fisheye or
pinhole model of :mod:`graph.camera`), which gives their exact Jacobian and the exact Hessian of
``lambda . uv``; the rest of the program is linear or separable and written out by hand.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from graph.solve.fte import PRIOR_SIGMA
from graph.solve.robust import A as RA
from graph.solve.robust import B as RB
from graph.solve.robust import C as RC
from graph.solve.robust import redescending

# ------------------------------------------------------------------------- per-frame projections


def _rot(ca, axis: int, a):
    c, s = ca.cos(a), ca.sin(a)
    if axis == 0:
        rows = [[1, 0, 0], [0, c, s], [0, -s, c]]
    elif axis == 1:
        rows = [[c, 0, -s], [0, 1, 0], [s, 0, c]]
    else:
        rows = [[c, s, 0], [-s, c, 0], [0, 0, 1]]
    return ca.vertcat(*[ca.horzcat(*r) for r in rows])


def _project(ca, intr, R, t, X):
    """Pixel (2,) of world point X (3,) in one camera: :mod:`graph.camera`'s maths."""
    Xc = ca.mtimes(ca.DM(R), X) + ca.DM(t)
    x, y = Xc[0] / Xc[2], Xc[1] / Xc[2]
    fx, fy, cx, cy = (float(v) for v in intr[1:5])
    d = [float(v) for v in intr[5:10]]
    r2 = x * x + y * y
    if intr[0] == 0.0:  # fisheye
        r = ca.sqrt(r2)
        th = ca.atan(r)
        th2 = th * th
        thd = th * (1 + th2 * (d[0] + th2 * (d[1] + th2 * (d[2] + th2 * d[3]))))
        xd, yd = thd / r * x, thd / r * y
    else:  # pinhole, radial-tangential
        k1, k2, p1, p2, k3 = d
        rad = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xd = x * rad + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        yd = y * rad + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return ca.vertcat(fx * xd + cx, fy * yd + cy)


@dataclass
class FrameModel:
    """CasADi functions of one frame's pose q (P,): projections uv (2CM,), their Jacobian (2CM, P),
    and the Hessian of ``lam . uv`` (P, P); ``uv`` is ordered (camera, marker, u/v)."""

    P: int
    C: int
    M: int
    uv: object
    jac: object
    hess: object
    jac_rows: np.ndarray  # structural nonzeros of the Jacobian
    jac_cols: np.ndarray
    hess_rows: np.ndarray  # structural nonzeros of the Hessian's lower triangle
    hess_cols: np.ndarray
    build_s: float = 0.0
    _maps: dict = field(default_factory=dict)

    def mapped(self, N: int, threads: int = 2):
        """The three functions over N frames at once (columns = frames)."""
        if N not in self._maps:
            self._maps[N] = tuple(f.map(N, "thread", threads) for f in (self.uv, self.jac, self.hess))
        return self._maps[N]


def frame_model(skeleton, calibration) -> FrameModel:
    """Build :class:`FrameModel` for a kinematic skeleton and a rig (once per skeleton and rig)."""
    import casadi as ca

    t0 = time.perf_counter()
    a = skeleton.arrays
    P = skeleton.n_params
    q = ca.SX.sym("q", P)
    RI = []
    for k in range(len(a.seg_parent)):
        Rloc = ca.SX.eye(3)
        for j in range(3):
            if a.seg_axis[k, j] >= 0:
                Rloc = ca.mtimes(Rloc, _rot(ca, int(a.seg_axis[k, j]), q[int(a.seg_param[k, j])]))
        par = a.seg_parent[k]
        RI.append(Rloc if par < 0 else ca.mtimes(Rloc, RI[par]))
    pts = []
    for k in range(len(a.pt_base)):
        if a.pt_base[k] < 0:
            pts.append(ca.vertcat(*[q[int(i)] for i in a.pt_root[k]]))
        else:
            pts.append(pts[a.pt_base[k]] + ca.mtimes(RI[a.pt_seg[k]].T, ca.DM(a.pt_offset[k])))
    markers = [pts[p] for p in a.marker_point]
    intr, Rc, tc = calibration.packed()
    uv = ca.vertcat(*[_project(ca, intr[c], Rc[c], tc[c], X) for c in range(len(intr)) for X in markers])
    lam = ca.SX.sym("lam", uv.shape[0])
    J = ca.jacobian(uv, q)
    H = ca.hessian(ca.dot(lam, uv), q)[0]
    Hl = ca.tril(H)
    f_uv = ca.Function("frame_uv", [q], [uv])
    f_jac = ca.Function("frame_jacobian", [q], [J])
    f_hess = ca.Function("frame_hessian", [q, lam], [Hl])
    jr, jc = J.sparsity().get_triplet()
    hr, hc = Hl.sparsity().get_triplet()
    return FrameModel(P=P, C=len(intr), M=len(markers), uv=f_uv, jac=f_jac, hess=f_hess,
                      jac_rows=np.asarray(jr), jac_cols=np.asarray(jc), hess_rows=np.asarray(hr),
                      hess_cols=np.asarray(hc), build_s=time.perf_counter() - t0)


# ------------------------------------------------------------------------------------ robust loss


def _rho_derivatives(s):
    """rho(s), w(s) = rho'(s)/s (:func:`graph.solve.robust.redescending`) and rho''(s) of the redescending
    loss, vectorised (s >= 0)."""
    a, b, c = RA, RB, RC
    rho, w = redescending(s, a, b, c)
    d2 = np.select([s < a, s < b, s < c], [np.ones_like(s), np.zeros_like(s), np.full_like(s, -a / (c - b))], 0.0)
    return rho, w, d2


# ------------------------------------------------------------------------------------------- NLP


class PaperNLP:
    """The program above for one :class:`graph.solve.problem.Problem`, as cyipopt's callbacks.

    ``x = [q (N P), qd (N P), qdd (N P), w ((N-1) P), e (2 V)]``, each block frame-major.
    """

    def __init__(self, prob, model: FrameModel, Q0: np.ndarray, cost: str = "fte"):
        if cost not in ("fte", "paper"):
            raise ValueError("cost must be 'fte' or 'paper'")
        sk = prob.skeleton
        self.prob, self.model, self.cost_kind = prob, model, cost
        N, P = Q0.shape
        C, M = prob.cameras, len(sk.markers)
        self.N, self.P, self.C, self.M = N, P, C, M
        self.h = prob.dt
        self.sigma = prob.sigma_px
        self.sigma_w = sk.process_noise * prob.options.motion_scale
        self.Q0 = Q0
        # detections: frame, flat index into the frame's uv vector
        n_j, c_j, m_j = np.nonzero(prob.valid)
        self.V = V = len(n_j)
        self.det_n = n_j
        self.det_r = (c_j * M + m_j) * 2
        self.z = prob.meas[n_j, c_j, m_j].reshape(-1)  # (2V,)
        NP = N * P
        self.o_q, self.o_v, self.o_a, self.o_w = 0, NP, 2 * NP, 3 * NP
        self.o_e = 3 * NP + (N - 1) * P
        self.n = self.o_e + 2 * V
        self.m_lin = 3 * (N - 1) * P
        self.m = self.m_lin + 2 * V
        self.uv_f, self.jac_f, self.hess_f = model.mapped(N)
        self._build_jacobian_structure()
        self._build_hessian_structure()
        self.eval_s = 0.0  # seconds spent in the callbacks
        self.evals = {"f": 0, "grad": 0, "g": 0, "jac": 0, "hess": 0}
        self.iterations = 0
        self._cache_x = None

    # --- structure ---------------------------------------------------------------------------

    def _iq(self, n, p):
        return self.o_q + n * self.P + p

    def _build_jacobian_structure(self):
        N, P, h = self.N, self.P, self.h
        n = np.repeat(np.arange(N - 1), P)
        p = np.tile(np.arange(P), N - 1)
        r_kin = n * P + p
        r_vel = (N - 1) * P + r_kin
        r_acc = 2 * (N - 1) * P + r_kin
        rows, cols, vals = [], [], []

        def add(r, c, v):
            rows.append(r)
            cols.append(c)
            vals.append(np.broadcast_to(np.asarray(v, dtype=float), r.shape))

        add(r_kin, self.o_q + (n + 1) * P + p, 1.0)
        add(r_kin, self.o_q + n * P + p, -1.0)
        add(r_kin, self.o_v + n * P + p, -h)
        add(r_kin, self.o_a + n * P + p, -0.5 * h * h)
        add(r_vel, self.o_v + (n + 1) * P + p, 1.0)
        add(r_vel, self.o_v + n * P + p, -1.0)
        add(r_vel, self.o_a + n * P + p, -h)
        add(r_acc, self.o_a + (n + 1) * P + p, 1.0)
        add(r_acc, self.o_a + n * P + p, -1.0)
        add(r_acc, self.o_w + n * P + p, -1.0)
        self.n_lin_jac = sum(len(r) for r in rows)
        # measurement rows: d uv / d q[n] over the structural nonzeros, and -1 on the slack
        jr, jc = self.model.jac_rows, self.model.jac_cols
        sel_r, sel_c, sel_det = [], [], []
        by_row = {}
        for r, c in zip(jr, jc):
            by_row.setdefault(int(r), []).append(int(c))
        for j in range(self.V):
            for k in range(2):
                cs = by_row.get(int(self.det_r[j] + k), [])
                sel_r += [self.det_r[j] + k] * len(cs)
                sel_c += cs
                sel_det += [j] * len(cs)
        sel_r, sel_c, sel_det = (np.array(sel_r, dtype=np.int64), np.array(sel_c, dtype=np.int64),
                                 np.array(sel_det, dtype=np.int64))
        k_of = sel_r - self.det_r[sel_det]
        meas_rows = self.m_lin + 2 * sel_det + k_of
        rows.append(meas_rows)
        cols.append(self.o_q + self.det_n[sel_det] * P + sel_c)
        vals.append(np.zeros(len(meas_rows)))
        # where each value comes from in the (N, 2CM, P) Jacobian array
        self._jac_src = (self.det_n[sel_det], sel_r, sel_c)
        er = self.m_lin + np.arange(2 * self.V)
        rows.append(er)
        cols.append(self.o_e + np.arange(2 * self.V))
        vals.append(np.full(2 * self.V, -1.0))
        self.jac_rows = np.concatenate(rows)
        self.jac_cols = np.concatenate(cols)
        self._jac_vals = np.concatenate(vals)
        self._jac_meas = slice(self.n_lin_jac, self.n_lin_jac + len(meas_rows))

    def _build_hessian_structure(self):
        N, P = self.N, self.P
        hr, hc = self.model.hess_rows, self.model.hess_cols
        diag = set(zip(hr.tolist(), hc.tolist()))
        extra = [(i, i) for i in range(P) if (i, i) not in diag]
        fr = np.concatenate([hr, np.array([e[0] for e in extra], dtype=np.int64)])
        fc = np.concatenate([hc, np.array([e[1] for e in extra], dtype=np.int64)])
        self._hq_r, self._hq_c = fr, fc  # per-frame lower-triangle entries (row >= col)
        self._hq_diag = np.flatnonzero(fr == fc)
        nq = len(fr)
        rows = [(np.arange(N)[:, None] * P + fr[None]).ravel()]
        cols = [(np.arange(N)[:, None] * P + fc[None]).ravel()]
        # motion on w
        Nw = N - 1
        wi = self.o_w + np.arange(Nw * P)
        rows.append(wi)
        cols.append(wi)
        if self.cost_kind == "fte":
            sub = self.o_w + np.arange((N - 3) * P)
            rows.append(sub + P)
            cols.append(sub)
        # slacks: (0,0), (1,0), (1,1) per detection
        e0 = self.o_e + 2 * np.arange(self.V)
        rows += [e0, e0 + 1, e0 + 1]
        cols += [e0, e0, e0 + 1]
        self.hess_rows = np.concatenate(rows)
        self.hess_cols = np.concatenate(cols)
        self._nq = nq
        # constant motion Hessian values
        s2 = np.tile(1.0 / self.sigma_w**2, Nw)
        if self.cost_kind == "paper":
            self._hw_diag, self._hw_sub = s2, None
        else:
            # 1/2 sum_{n=0}^{N-4} ((w_n + w_{n+1}) / (2 s))^2: w_n is in the terms n-1 and n
            cnt = np.zeros(Nw)
            cnt[: N - 3] += 1
            cnt[1: N - 2] += 1
            self._hw_diag = 0.25 * s2 * np.repeat(cnt, P)
            self._hw_sub = 0.25 * np.tile(1.0 / self.sigma_w**2, N - 3)

    # --- pieces ------------------------------------------------------------------------------

    def split(self, x):
        N, P = self.N, self.P
        q = x[self.o_q:self.o_v].reshape(N, P)
        v = x[self.o_v:self.o_a].reshape(N, P)
        a = x[self.o_a:self.o_w].reshape(N, P)
        w = x[self.o_w:self.o_e].reshape(N - 1, P)
        e = x[self.o_e:].reshape(self.V, 2)
        return q, v, a, w, e

    def bounds(self):
        sk = self.prob.skeleton
        lb = np.full(self.n, -np.inf)
        ub = np.full(self.n, np.inf)
        lb[: self.o_v] = np.tile(sk.lower, self.N)
        ub[: self.o_v] = np.tile(sk.upper, self.N)
        if self.cost_kind == "fte":
            for n in (0, self.N - 2):
                sl = slice(self.o_w + n * self.P, self.o_w + (n + 1) * self.P)
                lb[sl] = 0.0
                ub[sl] = 0.0
        big = 2e19  # IPOPT's infinity
        return np.nan_to_num(lb, neginf=-big), np.nan_to_num(ub, posinf=big)

    def start(self, Q0):
        """A feasible start from trajectories Q0: rates, accelerations and model slacks that
        reproduce Q0 exactly (with ``w[0] = 0``), measurement slacks = reprojection residuals."""
        N, P, h = self.N, self.P, self.h
        b = (Q0[2:] - 2 * Q0[1:-1] + Q0[:-2]) / h**2  # (N-2, P): qdd[n] + w[n]/2
        a = np.zeros((N, P))
        w = np.zeros((N - 1, P))
        a[0] = b[0]
        for n in range(N - 2):
            w[n] = 2 * (b[n] - a[n])
            a[n + 1] = a[n] + w[n]
        a[N - 1] = a[N - 2]
        v = np.zeros((N, P))
        v[0] = (Q0[1] - Q0[0]) / h - 0.5 * h * a[0]
        for n in range(N - 1):
            v[n + 1] = v[n] + h * a[n]
        uv = self._uv(Q0)
        e = (uv[self.det_n[:, None], self.det_r[:, None] + np.arange(2)[None]].reshape(-1) - self.z)
        return np.concatenate([Q0.ravel(), v.ravel(), a.ravel(), w.ravel(), e])

    def _uv(self, q):
        return self.uv_f(q.T).full().T  # (N, 2CM)

    def _motion(self, w):
        s = self.sigma_w
        if self.cost_kind == "paper":
            r = w / s
            return 0.5 * float(np.sum(r * r)), w / s**2
        L = self.N - 3  # third differences n = 0..N-4 use w[n] + w[n+1]; w[N-2] is in none
        r = (w[:L] + w[1:L + 1]) / (2 * s)  # (N-3, P): third differences over sigma_3
        g = np.zeros_like(w)
        g[:L] += r / (2 * s)
        g[1:L + 1] += r / (2 * s)
        return 0.5 * float(np.sum(r * r)), g

    def _data(self, e):
        s = np.sqrt(np.sum(e * e, axis=1)) / self.sigma
        rho, wgt, d2 = _rho_derivatives(s)
        return rho, wgt, d2, s

    # --- cyipopt callbacks -------------------------------------------------------------------

    def objective(self, x):
        t0 = time.perf_counter()
        q, _, _, w, e = self.split(x)
        rho, _, _, _ = self._data(e)
        f = float(rho.sum()) + self._motion(w)[0]
        if self.cost_kind == "fte":
            pr = (q - self.Q0) / PRIOR_SIGMA
            f += 0.5 * float(np.sum(pr * pr))
        self.evals["f"] += 1
        self.eval_s += time.perf_counter() - t0
        return f

    def gradient(self, x):
        t0 = time.perf_counter()
        q, _, _, w, e = self.split(x)
        g = np.zeros(self.n)
        _, wgt, _, _ = self._data(e)
        g[self.o_e:] = (wgt[:, None] * e / self.sigma**2).ravel()
        g[self.o_w:self.o_e] = self._motion(w)[1].ravel()
        if self.cost_kind == "fte":
            g[: self.o_v] = ((q - self.Q0) / PRIOR_SIGMA**2).ravel()
        self.evals["grad"] += 1
        self.eval_s += time.perf_counter() - t0
        return g

    def constraints(self, x):
        t0 = time.perf_counter()
        q, v, a, w, e = self.split(x)
        h = self.h
        kin = q[1:] - q[:-1] - h * v[:-1] - 0.5 * h * h * a[:-1]
        vel = v[1:] - v[:-1] - h * a[:-1]
        acc = a[1:] - a[:-1] - w
        uv = self._uv(q)
        meas = uv[self.det_n[:, None], self.det_r[:, None] + np.arange(2)[None]] - e
        self.evals["g"] += 1
        self.eval_s += time.perf_counter() - t0
        return np.concatenate([kin.ravel(), vel.ravel(), acc.ravel(), meas.ravel()])

    def jacobianstructure(self):
        return self.jac_rows, self.jac_cols

    def jacobian(self, x):
        t0 = time.perf_counter()
        q = x[: self.o_v].reshape(self.N, self.P)
        J = self.jac_f(q.T).full()  # (2CM, N P): frame n in columns n P .. n P + P - 1
        fn, r, c = self._jac_src
        vals = self._jac_vals.copy()
        vals[self._jac_meas] = J[r, fn * self.P + c]
        self.evals["jac"] += 1
        self.eval_s += time.perf_counter() - t0
        return vals

    def hessianstructure(self):
        return self.hess_rows, self.hess_cols

    def hessian(self, x, lagrange, obj_factor):
        t0 = time.perf_counter()
        N, P = self.N, self.P
        q, _, _, _, e = self.split(x)
        lam = np.zeros((N, 2 * self.C * self.M))
        lm = lagrange[self.m_lin:].reshape(self.V, 2)
        lam[self.det_n[:, None], self.det_r[:, None] + np.arange(2)[None]] = lm
        Hq = self.hess_f(q.T, lam.T).full()  # (P, N P)
        Hq = Hq.reshape(P, N, P).transpose(1, 0, 2)  # (N, P, P)
        hq = Hq[:, self._hq_r, self._hq_c]  # (N, nq)
        if self.cost_kind == "fte":
            hq[:, self._hq_diag] += obj_factor / PRIOR_SIGMA**2
        parts = [hq.ravel(), obj_factor * self._hw_diag]
        if self._hw_sub is not None:
            parts.append(obj_factor * self._hw_sub)
        # robust loss on each slack: w/sigma^2 I + (rho'' - w)/sigma^2 e_hat e_hat^T
        _, wgt, d2, s = self._data(e)
        nrm = np.maximum(s * self.sigma, 1e-300)
        eh = e / nrm[:, None]
        k = np.where(s < RA, 0.0, d2 - wgt)
        s2 = self.sigma**2
        h00 = (wgt + k * eh[:, 0] ** 2) / s2
        h10 = (k * eh[:, 0] * eh[:, 1]) / s2
        h11 = (wgt + k * eh[:, 1] ** 2) / s2
        parts += [obj_factor * h00, obj_factor * h10, obj_factor * h11]
        self.evals["hess"] += 1
        self.eval_s += time.perf_counter() - t0
        return np.concatenate(parts)

    def intermediate(self, alg_mod, iter_count, obj_value, inf_pr, inf_du, mu, d_norm, regularization_size,
                     alpha_du, alpha_pr, ls_trials):
        self.iterations = iter_count
        return True


# --------------------------------------------------------------------------------------- solving


@dataclass
class PaperSolution:
    Q: np.ndarray  # (N, P) pose trajectories
    positions: np.ndarray  # (N, M, 3)
    iterations: int
    status: int
    status_msg: str
    objective: float  # the NLP's own objective at the answer
    seconds: dict
    evals: dict
    size: dict


DEFAULT_IPOPT = {"linear_solver": "mumps", "print_level": 0, "max_iter": 3000, "sb": "yes"}


def solve_paper(prob, model: FrameModel, cost: str = "fte", ipopt_options: dict | None = None,
                Q0: np.ndarray | None = None) -> PaperSolution:
    """Start as ``fte`` does (robust triangulation, then inverse kinematics: the same ``q0``),
    then solve the program with IPOPT."""
    import cyipopt

    from graph.solve.initial import initial_poses
    from graph.solve.triangulate import robust_points

    t0 = time.perf_counter()
    if Q0 is None:
        X, _, _ = robust_points(prob.calibration, prob.meas, prob.valid, prob.sigma_px)
        Q0 = initial_poses(prob, X)
    t_init = time.perf_counter() - t0
    nlp = PaperNLP(prob, model, Q0, cost=cost)
    lb, ub = nlp.bounds()
    x0 = nlp.start(Q0)
    x0 = np.clip(x0, lb, ub)
    cl = np.concatenate([np.zeros(nlp.m_lin), nlp.z])
    problem = cyipopt.Problem(n=nlp.n, m=nlp.m, problem_obj=nlp, lb=lb, ub=ub, cl=cl, cu=cl)
    for k, v in {**DEFAULT_IPOPT, **(ipopt_options or {})}.items():
        problem.add_option(k, v)
    t_setup = time.perf_counter() - t0 - t_init
    x, info = problem.solve(x0)
    t_total = time.perf_counter() - t0
    t_ipopt = t_total - t_init - t_setup
    Q = x[: nlp.o_v].reshape(nlp.N, nlp.P)
    pos = prob.skeleton.positions(Q)
    msg = info["status_msg"]
    return PaperSolution(
        Q=Q, positions=pos, iterations=int(nlp.iterations), status=int(info["status"]),
        status_msg=msg.decode() if isinstance(msg, bytes) else str(msg), objective=float(info["obj_val"]),
        seconds={"total": t_total, "init": t_init, "setup": t_setup, "ipopt": t_ipopt,
                 "callbacks": nlp.eval_s, "ipopt_internal": t_ipopt - nlp.eval_s},
        evals=dict(nlp.evals), size={"variables": nlp.n, "constraints": nlp.m, "detections": nlp.V,
                                     "jacobian_nonzeros": len(nlp.jac_rows), "hessian_nonzeros": len(nlp.hess_rows)})


def common_cost(prob, Q0: np.ndarray, Q: np.ndarray) -> dict:
    """acinoset ``fte``'s cost of trajectories Q (:meth:`graph.solve.fte.TrajectoryProblem.cost`: robust
    reprojection + third-difference motion + weak anchor to Q0), with its parts."""
    from graph.solve.fte import TrajectoryProblem

    tp = TrajectoryProblem(prob, Q0)
    *_, dc = tp.normals(np.ascontiguousarray(Q), 1.0)
    m = tp.motion_residual(Q)
    pr = (Q - Q0) / PRIOR_SIGMA
    return {"total": tp.cost(Q, dc), "data": float(dc.sum()), "motion": 0.5 * float(np.sum(m * m)),
            "anchor": 0.5 * float(np.sum(pr * pr))}
