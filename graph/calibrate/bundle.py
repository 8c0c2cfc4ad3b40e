"""Bundle adjustment of cameras and board views on GTSAM.

Unknowns (each a GTSAM key):

* ``c_i``: camera i's pose ``wTc = (R_c, t_c)`` (camera to world), a Pose3; some are held fixed
  (camera 1 fixes the gauge; the board fixes the scale);
* ``b_j``: board view j's pose ``wTb = (R_b, t_b)``, a Pose3;
* ``k_i``: camera i's intrinsics ``theta`` (:mod:`graph.calibrate.model`), when refined, with an
  optional Gaussian prior ``|L (theta - theta0)|^2``.

A camera's pose may have a Gaussian prior too, ``|Log(R_0^T R_c)|^2 / s_r^2 + |t_c - t_0|^2 / s_t^2``
(:attr:`Settings.pose_priors`), whose Jacobian by ``(w_c, v_c)`` is taken as ``[[I / s_r, 0], [0,
R_c / s_t]]`` (exact in the position; in the rotation to first order in the angle from ``R_0``).

A corner ``p`` (board frame) seen at ``z`` by camera i in view j predicts::

    X_c = R_c^T (R_b p + t_b - t_c),    z_hat = pi(theta_i, X_c),    e = z_hat - z

Poses are perturbed on the right, as GTSAM's Pose3 (rotation first): ``R <- R Exp(w)``,
``t <- t + R v``. To first order::

    d X_c / d (w_c, v_c) = [ [X_c]_x ,  -I ]
    d X_c / d (w_b, v_b) = [ -R_c^T R_b [p]_x ,  R_c^T R_b ]

The loss is Huber's on each corner's residual length ``s = |e|`` (pixels)::

    rho(s) = s^2 / 2             for s <= k
           = k s - k^2 / 2       otherwise,        weight w = min(1, k / s)

with ``k`` = :data:`HUBER_SIGMAS` times the detection noise ``sigma`` measured from the residuals
(:func:`noise_sigma`) at the start of each round of the caller's outlier loop: a corner more than
3 sd from its prediction pulls with a constant force. Each
Levenberg-Marquardt step linearises every corner at once in numpy (rows scaled by ``sqrt(w)``),
forms the normal equations with Marquardt's damping ``lambda diag(J^T W J)`` and solves them by the
Schur complement of the boards' blocks (:func:`_step`): every board (or point) is a 6x6 (3x3) block
that only cameras share, so the system reduces to the cameras' and intrinsics' few dozen unknowns.
Building one GTSAM factor per view and per key for every damping trial cost 70 ms a step on 1500
points (``calibrate refine`` on the fly, 100 steps a round); this is 11 ms. Uncertainty: the
cameras' and intrinsics' covariance by the same Schur complement (:func:`camera_covariance`), scaled
by the measured noise ``sigma^2``; it equals GTSAM's marginals of the final linear system (one
``JacobianFactor`` per view over its 1-3 keys, :func:`linearize`, :func:`covariances`) where GTSAM
takes them, and also holds where the stiff rows of a held lens make GTSAM refuse the system.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import gtsam
import numpy as np
from scipy import sparse

from graph.calibrate.model import MAX_INTRINSICS, N_INTRINSICS, project

FIXED_DISTANCE_SD = 1e-6  # per px of residual: holds a distance to a micrometre
HUBER_SIGMAS = 3.03  # a 2D Gaussian residual is longer than 3.03 sigma with probability 1 %


def skew(v: np.ndarray) -> np.ndarray:
    """``[v]_x`` (..., 3, 3) with ``[v]_x u = v x u``."""
    S = np.zeros(v.shape[:-1] + (3, 3))
    S[..., 0, 1], S[..., 0, 2] = -v[..., 2], v[..., 1]
    S[..., 1, 0], S[..., 1, 2] = v[..., 2], -v[..., 0]
    S[..., 2, 0], S[..., 2, 1] = -v[..., 1], v[..., 0]
    return S


def exp_so3(w: np.ndarray) -> np.ndarray:
    """Rodrigues' formula, batched: ``Exp(w)`` (..., 3, 3)."""
    th = np.linalg.norm(w, axis=-1)[..., None, None]
    K = skew(w)
    small = th < 1e-10
    th_s = np.where(small, 1.0, th)
    A = np.where(small, 1.0, np.sin(th_s) / th_s)
    B = np.where(small, 0.5, (1 - np.cos(th_s)) / th_s ** 2)
    return np.eye(3) + A * K + B * (K @ K)


def retract(R: np.ndarray, t: np.ndarray, xi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(R Exp(w), t + R v)`` for ``xi = (w, v)`` (..., 6)."""
    return R @ exp_so3(xi[..., :3]), t + np.einsum("...ij,...j->...i", R, xi[..., 3:])


@dataclass
class Observations:
    """Corners seen: corner m belongs to view ``view[m]``; view v is camera ``cam[v]`` seeing board
    pose ``board[v]``; ``uv`` (M, 2) pixels, ``points`` (M, 3) in the board frame."""

    view: np.ndarray
    cam: np.ndarray
    board: np.ndarray
    uv: np.ndarray
    points: np.ndarray

    @property
    def n_views(self) -> int:
        return len(self.cam)

    def grouping(self) -> tuple[np.ndarray, np.ndarray]:
        """Corners sorted by view (``order``) and where each view's run starts (``bounds``, V+1)."""
        if getattr(self, "_grouping", None) is None:
            order = np.argsort(self.view, kind="stable")
            self._grouping = order, np.searchsorted(self.view[order], np.arange(self.n_views + 1))
        return self._grouping

    def keep_views(self, keep: np.ndarray) -> "Observations":
        """The views where ``keep`` (V,) is true, renumbered."""
        new = np.full(len(keep), -1)
        new[keep] = np.arange(int(keep.sum()))
        m = keep[self.view]
        return Observations(new[self.view[m]], self.cam[keep], self.board[keep], self.uv[m], self.points[m])


@dataclass
class Rig:
    """The state: camera poses (C, 3, 3), (C, 3); intrinsics per camera; board poses (B, 3, 3), (B, 3)."""

    models: list[str]
    intrinsics: list[np.ndarray]
    R_cam: np.ndarray
    t_cam: np.ndarray
    R_board: np.ndarray
    t_board: np.ndarray

    def copy(self) -> "Rig":
        return Rig(list(self.models), [th.copy() for th in self.intrinsics], self.R_cam.copy(),
                   self.t_cam.copy(), self.R_board.copy(), self.t_board.copy())


@dataclass
class Settings:
    """What is estimated. ``fixed_cams``: cameras whose pose is held; ``free_intrinsics``: cameras whose
    intrinsics are refined, each with a prior ``(theta0, L)`` or ``None`` (the board alone anchors
    them: intrinsic calibration); ``huber_px``: the Huber threshold (None: least squares).
    ``board_dof=3``: the "boards" are free 3D points (``R_b = I``, ``p = 0``; only ``v_b`` moves).
    ``fixed_distance=(i, j, d)``: the distance between cameras i (fixed) and j held at ``d`` by a stiff
    term ``((|C_j - C_i| - d) / FIXED_DISTANCE_SD)^2`` (the scale, when no board sets it)."""

    fixed_cams: frozenset = frozenset({0})
    free_intrinsics: dict = field(default_factory=dict)
    huber_px: float | None = None
    board_dof: int = 6
    fixed_distance: tuple[int, int, float] | None = None
    pose_priors: dict = field(default_factory=dict)  # camera i -> (R_0, t_0, s_r radians, s_t): see the module
    max_iterations: int = 100
    tolerance: float = 1e-9


@dataclass
class Solution:
    rig: Rig
    residuals: np.ndarray  # (M, 2) pixels
    weights: np.ndarray  # (M,) robust weights
    iterations: int
    cost: float
    seconds: float


def cam_key(i: int) -> int:
    return gtsam.symbol("c", i)


def board_key(j: int) -> int:
    return gtsam.symbol("b", j)


def intrinsics_key(i: int) -> int:
    return gtsam.symbol("k", i)


def residuals(rig: Rig, obs: Observations, jacobians: bool = True):
    """``e`` (M, 2) and, with ``jacobians``, ``d e / d xi_cam`` (M, 2, 6), ``d e / d xi_board``
    (M, 2, 6) and ``d e / d theta`` (a list per corner-camera model, (M, 2, P) zero-padded to
    :data:`~graph.calibrate.model.MAX_INTRINSICS`)."""
    c = obs.cam[obs.view]
    # per view: A = R_c^T R_b and a = R_c^T (t_b - t_c), so that X_c = A p + a
    Rc_v, tc_v = rig.R_cam[obs.cam], rig.t_cam[obs.cam]
    Rb_v, tb_v = rig.R_board[obs.board], rig.t_board[obs.board]
    A_v = np.matmul(Rc_v.transpose(0, 2, 1), Rb_v)
    a_v = np.matmul(Rc_v.transpose(0, 2, 1), (tb_v - tc_v)[:, :, None])[:, :, 0]
    A = A_v[obs.view]
    p = obs.points
    Xc = np.matmul(A, p[:, :, None])[:, :, 0] + a_v[obs.view]
    M = len(p)
    e = np.empty((M, 2))
    if jacobians:
        J_X = np.empty((M, 2, 3))
        J_k = np.zeros((M, 2, MAX_INTRINSICS))
    for i in np.unique(obs.cam):
        m = c == i
        model = rig.models[i]
        if jacobians:
            uv, jx, jt = project(rig.intrinsics[i], model, Xc[m])
            J_X[m] = jx
            J_k[m, :, : N_INTRINSICS[model]] = jt
        else:
            uv = project(rig.intrinsics[i], model, Xc[m], jacobians=False)
        e[m] = uv - obs.uv[m]
    if not jacobians:
        return e
    # rows j of J_X: j^T [X]_x = (j x X)^T;  j^T (-A [p]_x) = (p x (A^T j))^T
    J_cam = np.concatenate([np.cross(J_X, Xc[:, None, :]), -J_X], axis=2)
    B = np.matmul(J_X, A)
    J_board = np.concatenate([np.cross(p[:, None, :], B), B], axis=2)
    return e, J_cam, J_board, J_k


def _robust(e: np.ndarray, k: float | None) -> tuple[np.ndarray, np.ndarray]:
    """Huber weights (M,) and costs (M,) on residual lengths."""
    s = np.linalg.norm(e, axis=1)
    if k is None:
        return np.ones_like(s), 0.5 * s * s
    w = np.where(s <= k, 1.0, k / np.maximum(s, 1e-300))
    rho = np.where(s <= k, 0.5 * s * s, k * s - 0.5 * k * k)
    return w, rho


def _distance_term(rig: Rig, fixed: tuple[int, int, float]) -> tuple[float, np.ndarray]:
    """The fixed distance's (:attr:`Settings.fixed_distance`) whitened residual and its derivative by
    camera j's ``(w, v)`` (6,)."""
    i, j, d = fixed
    u = rig.t_cam[j] - rig.t_cam[i]
    L = float(np.linalg.norm(u))
    J = np.zeros(6)
    J[3:] = (u / L) @ rig.R_cam[j] / FIXED_DISTANCE_SD  # t_j <- t_j + R_j v
    return (L - d) / FIXED_DISTANCE_SD, J


def _pose_prior_term(rig: Rig, i: int, prior: tuple) -> tuple[np.ndarray, np.ndarray]:
    """Camera i's pose prior (:attr:`Settings.pose_priors`): whitened residual (6,) and its Jacobian
    by the pose's ``(w, v)`` (6, 6)."""
    R0, t0, s_r, s_t = prior
    phi = np.asarray(gtsam.Rot3.Logmap(gtsam.Rot3(R0.T @ rig.R_cam[i])))
    r = np.concatenate([phi / s_r, (rig.t_cam[i] - t0) / s_t])
    J = np.zeros((6, 6))
    J[:3, :3] = np.eye(3) / s_r
    J[3:, 3:] = rig.R_cam[i] / s_t
    return r, J


def _prior_cost(rig: Rig, settings: Settings) -> float:
    total = 0.0
    for i, prior in settings.pose_priors.items():
        r, _ = _pose_prior_term(rig, i, prior)
        total += 0.5 * float(r @ r)
    if settings.fixed_distance is not None:
        total += 0.5 * _distance_term(rig, settings.fixed_distance)[0] ** 2
    for i, prior in settings.free_intrinsics.items():
        if prior is not None:
            theta0, L = prior
            r = L @ (rig.intrinsics[i] - theta0)
            total += 0.5 * float(r @ r)
    return total


def total_cost(rig: Rig, obs: Observations, settings: Settings) -> float:
    e = residuals(rig, obs, jacobians=False)
    _, rho = _robust(e, settings.huber_px)
    if not np.all(np.isfinite(rho)):
        return math.inf
    return float(rho.sum()) + _prior_cost(rig, settings)


def linearize(rig: Rig, obs: Observations, settings: Settings):
    """The whitened linear system at ``rig`` as GTSAM sees it, for its marginals (:func:`covariances`):
    a list of JacobianFactors (one per view, plus the fixed distance and the intrinsics' priors),
    the residuals and the weights. The steps of :func:`solve` use :func:`normal_equations` instead."""
    e, Jc, Jb, Jk = residuals(rig, obs)
    w, _ = _robust(e, settings.huber_px)
    order, bounds = obs.grouping()
    sw = np.sqrt(w)[order, None]
    nb = settings.board_dof
    e_w = (e[order] * sw).reshape(-1)  # corners of view v are rows 2 bounds[v] .. 2 bounds[v+1]
    Jc = (Jc[order] * sw[..., None]).reshape(-1, 6)
    Jb = (Jb[order][:, :, 6 - nb:] * sw[..., None]).reshape(-1, nb)
    Jk = (Jk[order] * sw[..., None]).reshape(-1, MAX_INTRINSICS)
    factors = []
    cam_free = np.array([i not in settings.fixed_cams for i in range(len(rig.models))])
    k_free = np.array([i in settings.free_intrinsics for i in range(len(rig.models))])
    unit: dict[int, gtsam.noiseModel.Unit] = {}
    bkeys = [board_key(int(j)) for j in obs.board]
    ckeys = [cam_key(int(i)) for i in range(len(rig.models))]
    kkeys = [intrinsics_key(int(i)) for i in range(len(rig.models))]
    for v in range(obs.n_views):
        a, z = 2 * bounds[v], 2 * bounds[v + 1]
        if z == a:
            continue
        i = int(obs.cam[v])
        rows = z - a
        noise = unit.get(rows) or unit.setdefault(rows, gtsam.noiseModel.Unit.Create(rows))
        board, b = (bkeys[v], Jb[a:z]), -e_w[a:z]
        cam, lens = (ckeys[i], Jc[a:z]), (kkeys[i], Jk[a:z, :N_INTRINSICS[rig.models[i]]])
        if cam_free[i] and k_free[i]:
            factors.append(gtsam.JacobianFactor(*board, *cam, *lens, b, noise))
        elif cam_free[i]:
            factors.append(gtsam.JacobianFactor(*board, *cam, b, noise))
        elif k_free[i]:
            factors.append(gtsam.JacobianFactor(*board, *lens, b, noise))
        else:
            factors.append(gtsam.JacobianFactor(*board, b, noise))
    if settings.fixed_distance is not None:
        r, J = _distance_term(rig, settings.fixed_distance)
        key = cam_key(settings.fixed_distance[1])
        factors.append(gtsam.JacobianFactor(key, J[None, :], np.array([-r]), gtsam.noiseModel.Unit.Create(1)))
    for i, prior in settings.pose_priors.items():
        if cam_free[i]:
            r6, J6 = _pose_prior_term(rig, i, prior)
            factors.append(gtsam.JacobianFactor(cam_key(i), J6, -r6, gtsam.noiseModel.Unit.Create(6)))
    for i, prior in settings.free_intrinsics.items():
        if prior is not None:
            theta0, L = prior
            key = intrinsics_key(i)
            factors.append(gtsam.JacobianFactor(key, L, L @ (theta0 - rig.intrinsics[i]),
                                                gtsam.noiseModel.Unit.Create(len(theta0))))
    return factors, e, w


@dataclass
class NormalEquations:
    """The Gauss-Newton system of one linearisation, split for the Schur complement: camera-side
    unknowns (each free camera's pose, then each refined camera's intrinsics: ``D`` in all, at
    ``cam_slots`` and ``lens_slots``) against one block of ``nb`` per board (or point). ``H_cc`` (D, D), ``g_c`` (D,),
    ``W`` (B, D, nb), ``H_bb`` (B, nb, nb), ``g_b`` (B, nb): ``J^T W J`` and ``J^T W e`` of the
    whitened, robustly weighted residuals, the priors and the fixed distance included."""

    H_cc: np.ndarray
    g_c: np.ndarray
    W: np.ndarray
    H_bb: np.ndarray
    g_b: np.ndarray
    cam_slots: dict  # camera i -> (start, stop) of its pose's columns
    lens_slots: dict  # camera i -> (start, stop) of its intrinsics' columns


def normal_equations(rig: Rig, obs: Observations, settings: Settings) -> NormalEquations:
    """:class:`NormalEquations` at ``rig``: every corner's rows in numpy at once (no factor graph)."""
    e, Jc, Jb, Jk = residuals(rig, obs)
    w, _ = _robust(e, settings.huber_px)
    sw = np.sqrt(w)[:, None]
    nb = settings.board_dof
    C, B = len(rig.models), len(rig.R_board)
    corner_cam, corner_board = obs.cam[obs.view], obs.board[obs.view]
    cam_slots, lens_slots, D = {}, {}, 0
    for i in range(C):
        if i not in settings.fixed_cams:
            cam_slots[i] = (D, D + 6)
            D += 6
    for i in sorted(settings.free_intrinsics):
        lens_slots[i] = (D, D + N_INTRINSICS[rig.models[i]])
        D = lens_slots[i][1]
    M = len(e)
    Js = np.zeros((M, 2, D))  # the camera side's columns of every corner's two rows
    for i, (a, z) in cam_slots.items():
        m = corner_cam == i
        Js[m, :, a:z] = Jc[m]
    for i, (a, z) in lens_slots.items():
        m = corner_cam == i
        Js[m, :, a:z] = Jk[m, :, : z - a]
    Js *= sw[:, :, None]
    Jp = Jb[:, :, 6 - nb:] * sw[:, :, None]
    r = e * sw
    Js2, r2 = Js.reshape(2 * M, D), r.reshape(2 * M)
    H_cc = Js2.T @ Js2
    g_c = Js2.T @ r2
    JpT = Jp.transpose(0, 2, 1)
    # sums over each board's corners: a (B, M) indicator times the per-corner products, by BLAS
    G = sparse.csr_matrix((np.ones(M), (corner_board, np.arange(M))), shape=(B, M))
    H_bb = (G @ np.matmul(JpT, Jp).reshape(M, nb * nb)).reshape(B, nb, nb)
    g_b = G @ np.matmul(JpT, r[:, :, None]).reshape(M, nb)
    W = (G @ np.matmul(Js.transpose(0, 2, 1), Jp).reshape(M, D * nb)).reshape(B, D, nb)
    if settings.fixed_distance is not None:
        res, J = _distance_term(rig, settings.fixed_distance)
        a, z = cam_slots[settings.fixed_distance[1]]
        H_cc[a:z, a:z] += np.outer(J, J)
        g_c[a:z] += J * res
    for i, prior in settings.pose_priors.items():
        if i in cam_slots:
            res6, J6 = _pose_prior_term(rig, i, prior)
            a, z = cam_slots[i]
            H_cc[a:z, a:z] += J6.T @ J6
            g_c[a:z] += J6.T @ res6
    for i, prior in settings.free_intrinsics.items():
        if prior is not None:
            theta0, L = prior
            a, z = lens_slots[i]
            H_cc[a:z, a:z] += L.T @ L
            g_c[a:z] += L.T @ (L @ (rig.intrinsics[i] - theta0))
    return NormalEquations(H_cc, g_c, W, H_bb, g_b, cam_slots, lens_slots)


def _damped(H: np.ndarray, lam: float, floor_of: np.ndarray) -> np.ndarray:
    """``H + lam diag(max(diag H, floor))`` on the last two axes (Marquardt's damping)."""
    d = np.diagonal(H, axis1=-2, axis2=-1)
    return H + lam * np.maximum(d, floor_of)[..., None] * np.eye(H.shape[-1])


def _schur(A: np.ndarray, W: np.ndarray, Hinv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The camera side's reduced system ``S = A - sum_j W_j H_j^-1 W_j^T`` (D, D), each board's (or
    point's) block ``H_j`` eliminated, and ``W H^-1`` laid out (D, B nb) for the right-hand side."""
    D = W.shape[1]
    WH2 = np.matmul(W, Hinv).transpose(1, 0, 2).reshape(D, -1)
    return A - WH2 @ W.transpose(1, 0, 2).reshape(D, -1).T, WH2


def _step(eq: NormalEquations, lam: float) -> tuple[np.ndarray, np.ndarray, float] | None:
    """The damped step ``(d_c (D,), d_b (B, nb))`` by the Schur complement: each board's block
    eliminated, ``(A - sum_j W_j H_j^-1 W_j^T) d_c = -g_c + sum_j W_j H_j^-1 g_j``, then
    ``d_j = -H_j^-1 (g_j + W_j^T d_c)``, and the reduction of the cost the linear model predicts,
    ``-g.d - d^T H d / 2 = (lambda d^T D d - g.d) / 2`` (D the damping's diagonal); None where the
    damped system is not positive definite.
    Each key's damping has a floor of 1e-9 of its largest diagonal entry (a variable its
    down-weighted data barely see); a variable no data see stays where it is."""
    db = np.diagonal(eq.H_bb, axis1=1, axis2=2)
    seen_b = db.max(axis=1) > 0
    floor_b = 1e-9 * np.maximum(db.max(axis=1, keepdims=True), 1e-12)
    Hb = _damped(eq.H_bb, lam, floor_b)
    Hb[~seen_b] = np.eye(Hb.shape[-1])
    try:
        np.linalg.cholesky(Hb)  # positive definite, or damp more
    except np.linalg.LinAlgError:
        return None
    Hinv = np.linalg.inv(Hb)
    D = len(eq.g_c)
    dc = np.zeros(D)
    damp = lam * np.maximum(db, floor_b)
    damp[~seen_b] = 0.0
    damp_c = np.zeros(D)
    if D:
        dcd = np.diagonal(eq.H_cc)
        floor_c = np.zeros(D)
        for a, z in [*eq.cam_slots.values(), *eq.lens_slots.values()]:
            floor_c[a:z] = 1e-9 * max(float(dcd[a:z].max()), 1e-12)
        A = _damped(eq.H_cc, lam, floor_c)
        seen_c = dcd > 0
        damp_c = lam * np.maximum(dcd, floor_c) * seen_c
        S, WH2 = _schur(A, eq.W, Hinv)
        rhs = -eq.g_c + WH2 @ eq.g_b.reshape(-1)
        S[~seen_c, :], S[:, ~seen_c] = 0.0, 0.0
        S[~seen_c, ~seen_c] = 1.0
        rhs[~seen_c] = 0.0
        try:
            Lc = np.linalg.cholesky(0.5 * (S + S.T))
        except np.linalg.LinAlgError:
            return None
        dc = np.linalg.solve(Lc.T, np.linalg.solve(Lc, rhs))
    dbx = -np.matmul(Hinv, (eq.g_b + np.matmul(eq.W.transpose(0, 2, 1), dc))[:, :, None])[:, :, 0]
    dbx[~seen_b] = 0.0
    if not (np.all(np.isfinite(dc)) and np.all(np.isfinite(dbx))):
        return None
    gd = float(eq.g_c @ dc + np.sum(eq.g_b * dbx))
    predicted = 0.5 * (float(dc @ (damp_c * dc)) + float(np.sum(damp * dbx * dbx)) - gd)
    return dc, dbx, predicted


def _apply_step(rig: Rig, eq: NormalEquations, dc: np.ndarray, dbx: np.ndarray, settings: Settings) -> Rig:
    new = rig.copy()
    xb = np.zeros((len(rig.R_board), 6))
    xb[:, 6 - settings.board_dof:] = dbx
    new.R_board, new.t_board = retract(rig.R_board, rig.t_board, xb)
    for i, (a, z) in eq.cam_slots.items():
        new.R_cam[i], new.t_cam[i] = retract(rig.R_cam[i], rig.t_cam[i], dc[a:z])
    for i, (a, z) in eq.lens_slots.items():
        new.intrinsics[i] = rig.intrinsics[i] + dc[a:z]
    return new


def solve(rig: Rig, obs: Observations, settings: Settings) -> Solution:
    """Levenberg-Marquardt from ``rig`` (see the module for the model): each step solved by the
    Schur complement of the boards' (points') blocks in numpy (:func:`_step`); the final linear
    system kept as GTSAM factors for the marginals (:func:`covariances`)."""
    start = time.perf_counter()
    lam, grow = 1e-4, 2.0
    cost = total_cost(rig, obs, settings)
    it = 0
    for it in range(1, settings.max_iterations + 1):
        eq = normal_equations(rig, obs, settings)
        improved = False
        while lam < 1e12:
            step = _step(eq, lam)
            if step is None:  # not positive definite at this damping: damp more
                lam *= 10.0
                continue
            dc, dbx, predicted = step
            trial = _apply_step(rig, eq, dc, dbx, settings)
            new_cost = total_cost(trial, obs, settings)
            if new_cost < cost:
                improved = True
                break
            lam, grow = lam * grow, grow * 2.0
        if not improved:
            break
        # Nielsen's update: damp less the better the linear model predicted the decrease
        gain = (cost - new_cost) / max(predicted, 1e-300)
        lam, grow = max(lam * max(1.0 / 3.0, 1.0 - (2.0 * gain - 1.0) ** 3), 1e-12), 2.0
        rel = (cost - new_cost) / max(cost, 1e-300)
        rig, cost = trial, new_cost
        if rel < settings.tolerance:
            break
    e = residuals(rig, obs, jacobians=False)
    w, _ = _robust(e, settings.huber_px)
    return Solution(rig, e, w, it, cost, time.perf_counter() - start)


def noise_sigma(e: np.ndarray) -> float:
    """The noise per coordinate from residuals (M, 2): ``sqrt(mean |e|^2 / 2)``. Not the median's
    robust estimate: real views misfit in correlated ways (a lens model a little off at the edge, a
    board moving between two unsynchronised exposures), and a Huber threshold from the median
    (``median |e| / sqrt(2 ln 2)``) then treats a third of a good rig's corners as outliers, pulling
    the geometry (on AcinoSet's Ex1 pair: a 1.2 % shorter baseline). Gross errors are handled by
    dropping the views that stand out, and the next round's estimate is clean."""
    return float(np.sqrt((e * e).sum(axis=1).mean() / 2.0)) if len(e) else 1.0


def view_rms(e: np.ndarray, obs: Observations) -> np.ndarray:
    """RMS residual length (pixels) per view (V,)."""
    sq = np.bincount(obs.view, weights=(e * e).sum(axis=1), minlength=obs.n_views)
    n = np.bincount(obs.view, minlength=obs.n_views)
    return np.sqrt(sq / np.maximum(n, 1))


def camera_covariance(rig: Rig, obs: Observations, settings: Settings,
                      sigma: float) -> tuple[np.ndarray, NormalEquations]:
    """The covariance of the camera-side unknowns (:class:`NormalEquations`' columns), the points or
    boards marginalised: ``sigma^2 S^+``, ``S = H_cc - sum_j W_j H_j^-1 W_j^T`` the Schur complement
    of the undamped system at ``rig`` (a pseudo-inverse: a direction no data or prior sees has no
    finite variance, and GTSAM's marginals refuse such a system outright). The pseudo-inverse is
    taken of ``D^-1 S D^-1``, ``D = diag(S)^(1/2)``: a held lens's stiff rows (``1 / HELD^2``, some
    1e12 times the data's) otherwise swamp the poses' eigenvalues in rounding (sds of 0.01 mm where
    the poses are known to millimetres, and negative variances). With its equations, for the slots."""
    eq = normal_equations(rig, obs, settings)
    Hb = eq.H_bb.copy()
    unseen = np.diagonal(Hb, axis1=1, axis2=2).max(axis=1) <= 0
    Hb[unseen] = np.eye(Hb.shape[-1])
    Hinv = np.linalg.inv(Hb)
    S, _ = _schur(eq.H_cc, eq.W, Hinv)
    S = 0.5 * (S + S.T)
    d = np.sqrt(np.clip(np.diagonal(S), 1e-300, None))
    return sigma * sigma * np.linalg.pinv(S / np.outer(d, d)) / np.outer(d, d), eq


def covariances(rig: Rig, obs: Observations, settings: Settings, keys: list[int],
                sigma: float) -> dict[int, np.ndarray]:
    """Marginal covariances of ``keys`` from GTSAM's marginals of the linear system at ``rig``
    (:func:`linearize`), scaled by the detection noise ``sigma^2`` (the factors are whitened to 1 px):
    the check of :func:`camera_covariance`, which the calibrations use."""
    g = gtsam.GaussianFactorGraph()
    for f in linearize(rig, obs, settings)[0]:
        g.push_back(f)
    marginals = gtsam.Marginals(g, gtsam.VectorValues())
    return {k: marginals.marginalCovariance(k) * sigma * sigma for k in keys}
