"""Compiled hot loops (numba): projection, robust residuals and Jacobians, triangulation.

Forward kinematics lives beside the skeleton, in :mod:`graph.kinematics`.

One call computes, for every frame at once, the whitened and robustly weighted reprojection
residuals of all cameras and markers and their Jacobian with respect to that frame's pose
parameters. The solvers hand each frame's block to GTSAM as one linear factor: Python-level
per-measurement factors are two orders of magnitude too slow.

Rotation conventions (passive), ``c = cos a, s = sin a``::

    rot_x = [[1,0,0],[0,c,s],[0,-s,c]]   rot_y = [[c,0,-s],[0,1,0],[s,0,c]]   rot_z = [[c,s,0],[-s,c,0],[0,0,1]]

Camera intrinsics come packed as ``[code, fx, fy, cx, cy, d0..d4]``, ``code`` the camera model's
(:attr:`graph.camera.CameraModel.code`: 0 fisheye, 1 pinhole), see :meth:`graph.camera.Camera.packed`;
:func:`project_point` has one branch per code and the maths is documented in :mod:`graph.camera`.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from graph.camera import FISHEYE, PINHOLE, camera_model
from graph.compiled import loop_kernel
from graph.kinematics import fk_jacobian

# the camera models' codes in packed intrinsics (compile-time constants of the kernels)
FISHEYE_CODE = float(camera_model(FISHEYE).code)
PINHOLE_CODE = float(camera_model(PINHOLE).code)


@njit(cache=True)
def project_point(intr, R, t, X, uv, J):
    """Write the pixel ``uv`` (2,) of world point X in one camera and ``J = d uv / d X`` (2, 3);
    return whether the point is in front of the camera (uv is NaN otherwise)."""
    xc = R[0, 0] * X[0] + R[0, 1] * X[1] + R[0, 2] * X[2] + t[0]
    yc = R[1, 0] * X[0] + R[1, 1] * X[1] + R[1, 2] * X[2] + t[1]
    zc = R[2, 0] * X[0] + R[2, 1] * X[1] + R[2, 2] * X[2] + t[2]
    if zc <= 1e-9:
        uv[0] = np.nan
        uv[1] = np.nan
        J[:, :] = 0.0
        return False
    x = xc / zc
    y = yc / zc
    fx, fy, cx, cy = intr[1], intr[2], intr[3], intr[4]
    d0, d1, d2, d3, d4 = intr[5], intr[6], intr[7], intr[8], intr[9]
    r2 = x * x + y * y
    if intr[0] == FISHEYE_CODE:
        r = np.sqrt(r2)
        th = np.arctan(r)
        th2 = th * th
        thd = th * (1 + th2 * (d0 + th2 * (d1 + th2 * (d2 + th2 * d3))))
        if r < 1e-12:
            s = 1.0
            dsr = 0.0
        else:
            s = thd / r
            dthd = 1 + th2 * (3 * d0 + th2 * (5 * d1 + th2 * (7 * d2 + th2 * 9 * d3)))
            dsr = (dthd / (1 + r2) * r - thd) / (r2 * r)
        xd, yd = s * x, s * y
        a00 = s + x * x * dsr
        a01 = x * y * dsr
        a10 = a01
        a11 = s + y * y * dsr
    else:  # PINHOLE_CODE
        k1, k2, p1, p2, k3 = d0, d1, d2, d3, d4
        rad = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xd = x * rad + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        yd = y * rad + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        dr = k1 + r2 * (2 * k2 + 3 * k3 * r2)
        a00 = rad + 2 * x * x * dr + 2 * p1 * y + 6 * p2 * x
        a01 = 2 * x * y * dr + 2 * p1 * x + 2 * p2 * y
        a10 = a01
        a11 = rad + 2 * y * y * dr + 6 * p1 * y + 2 * p2 * x
    uv[0] = fx * xd + cx
    uv[1] = fy * yd + cy
    # d(x, y)/d(xc, yc, zc) = [[1/z, 0, -x/z], [0, 1/z, -y/z]]
    iz = 1.0 / zc
    for c in range(3):
        dxn = (R[0, c] - x * R[2, c]) * iz
        dyn = (R[1, c] - y * R[2, c]) * iz
        J[0, c] = fx * (a00 * dxn + a01 * dyn)
        J[1, c] = fy * (a10 * dxn + a11 * dyn)
    return True


@njit(cache=True)
def redescending(s, a, b, c):
    """The AcinoSet redescending cost rho(s) and IRLS weight w(s) = rho'(s)/s on s = |r|/sigma >= 0.

    rho = s^2/2 (s < a); a s - a^2/2 (a <= s < b);
    a b - a^2/2 + a (c-b)/2 (1 - ((c-s)/(c-b))^2) (b <= s < c); a b - a^2/2 + a (c-b)/2 (s >= c).
    With a, b, c = 3, 10, 20 the flat part is 40.5. rho is C^1; the original blends the pieces
    with sigmoids for IPOPT, which Gauss-Newton with these weights does not need.
    """
    if s < a:
        return 0.5 * s * s, 1.0
    if s < b:
        return a * s - 0.5 * a * a, a / s
    if s < c:
        u = (c - s) / (c - b)
        return a * b - 0.5 * a * a + 0.5 * a * (c - b) * (1 - u * u), a * (c - s) / ((c - b) * s)
    return a * b - 0.5 * a * a + 0.5 * a * (c - b), 0.0


@njit(cache=True, inline="always")
def _detection_cost(uv, z, front, sigma, robust, ra, rb, rc):
    """One detection ``z`` of the projection ``uv``: the whitened residual ``e = (uv - z) / sigma``,
    ``s = |e|``, its cost ``rho(s)`` and IRLS weight ``w(s)`` (:func:`redescending`; plain least
    squares, ``s^2/2`` and 1, without ``robust``). A point behind the camera (not ``front``) costs
    what a fully rejected outlier does, with s NaN and w 0."""
    if not front:
        rho = redescending(1e9, ra, rb, rc)[0] if robust else 0.0
        return 0.0, 0.0, np.nan, rho, 0.0
    ex = (uv[0] - z[0]) / sigma
    ey = (uv[1] - z[1]) / sigma
    s = np.sqrt(ex * ex + ey * ey)
    if robust:
        rho, w = redescending(s, ra, rb, rc)
    else:
        rho, w = 0.5 * s * s, 1.0
    return ex, ey, s, rho, w


@njit(cache=True, inline="always")
def _add_information(K, Jx, a):
    """``K += a Jx^T Jx`` (upper triangle; :func:`_symmetrise` mirrors it) for ``Jx`` (2, 3)."""
    for i in range(3):
        for j in range(i, 3):
            K[i, j] += a * (Jx[0, i] * Jx[0, j] + Jx[1, i] * Jx[1, j])


@njit(cache=True, inline="always")
def _add_gradient(k, Jx, ex, ey, b):
    """``k += b Jx^T e`` for ``Jx`` (2, 3) and ``e = (ex, ey)``."""
    for i in range(3):
        k[i] += b * (Jx[0, i] * ex + Jx[1, i] * ey)


@njit(cache=True, inline="always")
def _symmetrise(K):
    K[1, 0] = K[0, 1]
    K[2, 0] = K[0, 2]
    K[2, 1] = K[1, 2]


@njit(cache=True)
def frame_normal(q, meas, valid, intr, Rc, tc, sigma, robust, ra, rb, rc,
                 seg_parent, seg_axis, seg_param, pt_base, pt_seg, pt_root, pt_offset, marker_point, marker_dep,
                 bones, bone_len, bone_sigma, H, g, uv_out, s_out, w_out):
    """One frame's Gauss-Newton normal equations of the robust reprojection cost.

    For each valid detection (c, m) with whitened residual ``e = (uv_cm(q) - z_cm) / sigma_cm``
    (``sigma`` (C, M): the detection noise of each camera and marker), ``s = |e|`` and IRLS weight
    ``w(s)`` (:func:`redescending`)::

        H += w J^T J,   g += w J^T e,   cost += rho(s),   J = d e / d q = (1/sigma_cm) d uv/dX dp_m/dq

    only over the parameters that move marker m (``marker_dep``). The cameras' terms are summed in
    3D first, per marker (``Jx = d uv / dX``)::

        K_m = sum_c w Jx^T Jx / sigma_cm^2 (3, 3),   k_m = sum_c w Jx^T e / sigma_cm (3,)
        H += (dp_m/dq)^T K_m (dp_m/dq),   g += (dp_m/dq)^T k_m

    so the parameters' products are formed once per marker, not once per camera. Bone rows
    (points skeleton): ``e = (|p_a - p_b| - L) / sigma_L`` with weight 1. ``H`` (P, P) and ``g``
    (P,) are overwritten. Returns the frame's cost.
    """
    C = meas.shape[0]
    M = meas.shape[1]
    pos, dpos = fk_jacobian(q, seg_parent, seg_axis, seg_param, pt_base, pt_seg, pt_root, pt_offset,
                            marker_point, marker_dep)
    H[:, :] = 0.0
    g[:] = 0.0
    uv = np.zeros(2)
    Jx = np.zeros((2, 3))
    K = np.zeros((3, 3))
    k = np.zeros(3)
    scratch = np.empty((marker_dep.shape[1], 3))
    cost = 0.0
    for m in range(M):
        K[:, :] = 0.0
        k[:] = 0.0
        seen = False
        for c in range(C):
            ok = project_point(intr[c], Rc[c], tc[c], pos[m], uv, Jx)
            uv_out[c, m, 0] = uv[0]
            uv_out[c, m, 1] = uv[1]
            s_out[c, m] = np.nan
            w_out[c, m] = 0.0
            if not valid[c, m]:
                continue
            sg = sigma[c, m]
            ex, ey, s, rho, w = _detection_cost(uv, meas[c, m], ok, sg, robust, ra, rb, rc)
            cost += rho
            s_out[c, m] = s
            w_out[c, m] = w
            if w <= 0.0:
                continue
            _add_information(K, Jx, w / (sg * sg))
            _add_gradient(k, Jx, ex, ey, w / sg)
            seen = True
        if seen:
            _symmetrise(K)
            _project_gradient(k, dpos[m], marker_dep[m], g)
            _project_information(K, dpos[m], dpos[m], marker_dep[m], marker_dep[m], True, H, scratch)
    return cost + _bone_rows(pos, dpos, bones, bone_len, bone_sigma, H, g)


@njit(cache=True)
def _project_gradient(k, J, dep, g):
    """``g[dep] += J[:, dep]^T k`` for a marker's 3D gradient ``k`` (3,) and Jacobian ``J`` (3, P)
    over its parameters ``dep`` (padded with -1). Called, not inlined, like
    :func:`_project_information`: inlined at their 15 call sites in :func:`window_normals`'s
    parallel loop they took its compilation to 31 s; called, the first run's kernels compile in
    73-75 s instead of 87-95 s (the warm-up, this 2-core machine), and solves take as long."""
    for d in range(dep.shape[0]):
        p = dep[d]
        if p < 0:
            break
        g[p] += k[0] * J[0, p] + k[1] * J[1, p] + k[2] * J[2, p]


@njit(cache=True)
def _project_information(K, Ja, Jb, dep_a, dep_b, same, H, t):
    """``H[dep_a, dep_b] += Ja[:, dep_a]^T K Jb[:, dep_b]`` for a marker's 3D information ``K``
    (3, 3) and Jacobians ``Ja``, ``Jb`` (3, P) over the parameters ``dep_a``, ``dep_b`` (padded with
    -1); ``t`` is scratch of at least (len(dep_b), 3). With ``same`` (``Ja`` is ``Jb`` and ``dep_a``
    is ``dep_b``) only the upper triangle is formed, and mirrored."""
    nb = 0
    for d in range(dep_b.shape[0]):
        p = dep_b[d]
        if p < 0:
            break
        for i in range(3):
            t[d, i] = K[i, 0] * Jb[0, p] + K[i, 1] * Jb[1, p] + K[i, 2] * Jb[2, p]
        nb += 1
    for i in range(dep_a.shape[0]):
        pi = dep_a[i]
        if pi < 0:
            break
        for j in range(i if same else 0, nb):
            pj = dep_b[j]
            h = Ja[0, pi] * t[j, 0] + Ja[1, pi] * t[j, 1] + Ja[2, pi] * t[j, 2]
            H[pi, pj] += h
            if same and j != i:
                H[pj, pi] += h


@njit(cache=True)
def _bone_rows(pos, dpos, bones, bone_len, bone_sigma, H, g):
    """The bone rows of a points skeleton added to one frame's ``H``, ``g``; returns their cost."""
    P = dpos.shape[2]
    cost = 0.0
    for i in range(bones.shape[0]):
        if not (bone_len[i] > 0):
            continue
        a = bones[i, 0]
        b = bones[i, 1]
        dx = pos[a, 0] - pos[b, 0]
        dy = pos[a, 1] - pos[b, 1]
        dz = pos[a, 2] - pos[b, 2]
        L = np.sqrt(dx * dx + dy * dy + dz * dz)
        if L < 1e-12:
            continue
        e = (L - bone_len[i]) / bone_sigma[i]
        cost += 0.5 * e * e
        jb = np.zeros(P)
        for p in range(P):
            jb[p] = (dx * (dpos[a, 0, p] - dpos[b, 0, p]) + dy * (dpos[a, 1, p] - dpos[b, 1, p])
                     + dz * (dpos[a, 2, p] - dpos[b, 2, p])) / (L * bone_sigma[i])
        for p in range(P):
            if jb[p] == 0.0:
                continue
            g[p] += jb[p] * e
            for p2 in range(P):
                H[p, p2] += jb[p] * jb[p2]
    return cost


@loop_kernel
def all_normals(Q, meas, valid, intr, Rc, tc, sigma, robust, ra, rb, rc,
                seg_parent, seg_axis, seg_param, pt_base, pt_seg, pt_root, pt_offset, marker_point, marker_dep,
                bones, bone_len, bone_sigma):
    """:func:`frame_normal` for every frame (a loop kernel: :mod:`graph.compiled`): H (N, P, P), g (N, P), reprojections
    uv (N, C, M, 2), normalised residuals s and weights w (N, C, M), cost (N,).
    ``meas`` (N, C, M, 2), ``valid`` (N, C, M)."""
    N, P = Q.shape
    C = meas.shape[1]
    M = meas.shape[2]
    H = np.zeros((N, P, P))
    g = np.zeros((N, P))
    uv = np.zeros((N, C, M, 2))
    s = np.zeros((N, C, M))
    w = np.zeros((N, C, M))
    cost = np.zeros(N)
    for n in prange(N):
        cost[n] = frame_normal(Q[n], meas[n], valid[n], intr, Rc, tc, sigma, robust, ra, rb, rc,
                               seg_parent, seg_axis, seg_param, pt_base, pt_seg, pt_root, pt_offset,
                               marker_point, marker_dep, bones, bone_len, bone_sigma, H[n], g[n], uv[n], s[n],
                               w[n])
    return H, g, uv, s, w, cost


RESTART_COST = 2.0  # in huber^2: a few markers beyond the Huber corner
RESTART_GAIN = 0.5
RESTART_EVERY = 5  # frames between restart checks: a wrong branch is left within 5 frames, at a fifth of the cost


@njit(cache=True, inline="always")
def _ik_frame(q, Xn, q0n, qprev, anchor_w, smooth_w, lower, upper, huber, iterations, H, g,
              seg_parent, seg_axis, seg_param, pt_base, pt_seg, pt_root, pt_offset, marker_point, marker_dep):
    """One frame of :func:`inverse_kinematics` from ``q`` (changed in place); ``qprev`` of length 0
    leaves the pull to the previous frame out. Returns the data cost at the end,
    ``sum_m huber(|p_m(q) - X_m|) + sum_i (anchor_w_i (q_i - q0_i))^2 / 2`` (Huber's
    ``d^2/2`` up to ``h``, ``h d - h^2/2`` beyond)."""
    P = q.shape[0]
    M = marker_point.shape[0]
    D = marker_dep.shape[1]
    smooth = qprev.shape[0] == P
    cost = 0.0
    settled = False
    for it in range(iterations + 1):
        pos, dpos = fk_jacobian(q, seg_parent, seg_axis, seg_param, pt_base, pt_seg, pt_root, pt_offset,
                                marker_point, marker_dep)
        H[:, :] = 0.0
        g[:] = 0.0
        cost = 0.0
        for m in range(M):
            if not (np.isfinite(Xn[m, 0]) and np.isfinite(Xn[m, 1]) and np.isfinite(Xn[m, 2])):
                continue
            e0 = pos[m, 0] - Xn[m, 0]
            e1 = pos[m, 1] - Xn[m, 1]
            e2 = pos[m, 2] - Xn[m, 2]
            d = np.sqrt(e0 * e0 + e1 * e1 + e2 * e2)
            w = 1.0 if d <= huber else huber / d
            cost += 0.5 * d * d if d <= huber else huber * d - 0.5 * huber * huber
            for a in range(D):
                pa = marker_dep[m, a]
                if pa < 0:
                    break
                g[pa] += w * (dpos[m, 0, pa] * e0 + dpos[m, 1, pa] * e1 + dpos[m, 2, pa] * e2)
                for b in range(a, D):
                    pb = marker_dep[m, b]
                    if pb < 0:
                        break
                    h = w * (dpos[m, 0, pa] * dpos[m, 0, pb] + dpos[m, 1, pa] * dpos[m, 1, pb]
                             + dpos[m, 2, pa] * dpos[m, 2, pb])
                    H[pa, pb] += h
                    if pb != pa:
                        H[pb, pa] += h
        for i in range(P):
            cost += 0.5 * (anchor_w[i] * (q[i] - q0n[i])) ** 2
        if settled or it == iterations:  # the cost at the final pose
            break
        for i in range(P):
            H[i, i] += anchor_w[i] ** 2 + 1e-3
            g[i] += anchor_w[i] ** 2 * (q[i] - q0n[i])
            if smooth:
                H[i, i] += smooth_w[i] ** 2
                g[i] += smooth_w[i] ** 2 * (q[i] - qprev[i])
        step = np.linalg.solve(H, g)
        biggest = 0.0
        for i in range(P):
            q[i] = min(max(q[i] - step[i], lower[i]), upper[i])
            biggest = max(biggest, abs(step[i]))
        settled = biggest < 1e-5  # one more pass, for the cost only
    return cost


@njit(cache=True, nogil=True)
def inverse_kinematics(Q0, X, anchor_w, smooth_w, lower, upper, huber, iterations,
                       seg_parent, seg_axis, seg_param, pt_base, pt_seg, pt_root, pt_offset, marker_point,
                       marker_dep):
    """Per-frame pose from 3D points: minimise, frame by frame,

        sum_m huber(|p_m(q) - X_m|) + sum_i (anchor_w_i (q_i - q0_i))^2 / 2
                                    + sum_i (smooth_w_i (q_i - q_{n-1,i}))^2 / 2

    by damped Gauss-Newton with IRLS Huber weights, clipped to the bounds. Frame n starts from the
    solution of frame n-1 for the parameters without an anchor, and from ``Q0[n]`` for the others.
    The weak pull towards the previous frame's solution keeps the pose on one branch where the
    points do not decide (a tail pointing straight down has two equivalent (psi, theta); a frame
    of outliers could turn an unbounded yaw by a full turn). ``X`` (N, M, 3) may hold NaN.

    Restart: that pull also keeps a wrong branch once a frame of outliers has put a chain on it (a
    tail folded back, its tip 0.2-0.3 m from well triangulated points for a hundred frames and
    more). So when a frame's data cost (the sum without the pull) stays above
    ``RESTART_COST huber^2``, the frame is solved again from ``Q0[n]`` without the pull, and that
    pose is kept when its data cost is under ``RESTART_GAIN`` times the first one's: clearly
    better, never a swap between equivalent branches. Every ``RESTART_EVERY``-th frame is checked:
    frames with a few outliers are common and their restarts futile (checked every frame, the
    restarts tripled the time of the whole start), while a wrong branch lasts far longer.
    """
    N, P = Q0.shape
    Q = Q0.copy()
    H = np.zeros((P, P))
    g = np.zeros(P)
    none = np.zeros(0)
    for n in range(N):
        q = Q0[n].copy()
        if n > 0:
            for i in range(P):
                if anchor_w[i] == 0.0:
                    q[i] = Q[n - 1, i]
        cost = _ik_frame(q, X[n], Q0[n], Q[n - 1] if n > 0 else none, anchor_w, smooth_w, lower, upper, huber,
                         iterations, H, g, seg_parent, seg_axis, seg_param, pt_base, pt_seg, pt_root, pt_offset,
                         marker_point, marker_dep)
        if n > 0 and n % RESTART_EVERY == 0 and cost > RESTART_COST * huber * huber:
            q2 = Q0[n].copy()
            cost2 = _ik_frame(q2, X[n], Q0[n], none, anchor_w, smooth_w, lower, upper, huber, iterations, H, g,
                              seg_parent, seg_axis, seg_param, pt_base, pt_seg, pt_root, pt_offset, marker_point,
                              marker_dep)
            if cost2 < RESTART_GAIN * cost:
                q = q2
        Q[n] = q
    return Q


@njit(cache=True, inline="always")
def _solve3(H, g):
    """Solve the 3x3 system H x = g by Cramer's rule (H symmetric positive definite here)."""
    a, b, c = H[0, 0], H[0, 1], H[0, 2]
    d, e, f = H[1, 0], H[1, 1], H[1, 2]
    gg, h, i = H[2, 0], H[2, 1], H[2, 2]
    A = e * i - f * h
    B = -(d * i - f * gg)
    C = d * h - e * gg
    det = a * A + b * B + c * C
    x = np.empty(3)
    if det == 0.0:
        x[:] = np.nan
        return x
    inv = 1.0 / det
    x[0] = (A * g[0] + (c * h - b * i) * g[1] + (b * f - c * e) * g[2]) * inv
    x[1] = (B * g[0] + (a * i - c * gg) * g[1] + (c * d - a * f) * g[2]) * inv
    x[2] = (C * g[0] + (b * gg - a * h) * g[1] + (a * e - b * d) * g[2]) * inv
    return x


@njit(cache=True)
def _dlt(norm, ok, Pm, use):
    """Least-squares point from the views in ``use``: rows ``x P_3 - P_1``, ``y P_3 - P_2``."""
    H = np.zeros((3, 3))
    g = np.zeros(3)
    row = np.empty(4)
    for c in range(norm.shape[0]):
        if not use[c]:
            continue
        for r in range(2):
            for j in range(4):
                row[j] = norm[c, r] * Pm[c, 2, j] - Pm[c, r, j]
            for i in range(3):
                g[i] -= row[i] * row[3]
                for j in range(3):
                    H[i, j] += row[i] * row[j]
    for i in range(3):
        H[i, i] += 1e-12
    return _solve3(H, g)


@njit(cache=True)
def _cauchy_cost(X, z, ok, intr, Rc, tc, sigma, uv, J):
    cost = 0.0
    for c in range(z.shape[0]):
        if not ok[c]:
            continue
        front = project_point(intr[c], Rc[c], tc[c], X, uv, J)
        if not front:
            cost += np.log1p(1e12)
            continue
        s2 = ((uv[0] - z[c, 0]) ** 2 + (uv[1] - z[c, 1]) ** 2) / (sigma * sigma)
        cost += np.log1p(s2)
    return cost


@loop_kernel
def triangulate_points(norm, z, ok, intr, Rc, tc, Pm, sigma, iterations):
    """Robust triangulation of K points seen by C cameras (see :mod:`graph.solve.triangulate`).

    ``norm`` (K, C, 2) undistorted normalised coordinates, ``z`` (K, C, 2) pixels, ``ok`` (K, C).
    Returns X (K, 3) (NaN with fewer than two views) and the Gauss-Newton information H (K, 3, 3).
    """
    K, C = ok.shape
    X = np.full((K, 3), np.nan)
    Hout = np.zeros((K, 3, 3))
    for k in prange(K):
        nv = 0
        for c in range(C):
            if ok[k, c]:
                nv += 1
        if nv < 2:
            continue
        use = ok[k].copy()
        uv = np.zeros(2)
        J = np.zeros((2, 3))
        x = _dlt(norm[k], ok[k], Pm, use)
        best = _cauchy_cost(x, z[k], ok[k], intr, Rc, tc, sigma, uv, J)
        # every view within ~3 sigma of the all-view point: no outlier to look for
        if nv >= 3 and best > nv * np.log1p(9.0):
            for a in range(C):
                if not ok[k, a]:
                    continue
                for b in range(a + 1, C):
                    if not ok[k, b]:
                        continue
                    use[:] = False
                    use[a] = True
                    use[b] = True
                    xp = _dlt(norm[k], ok[k], Pm, use)
                    cst = _cauchy_cost(xp, z[k], ok[k], intr, Rc, tc, sigma, uv, J)
                    if cst < best:
                        best = cst
                        x = xp
        H = np.zeros((3, 3))
        for it in range(iterations):
            H[:, :] = 0.0
            g = np.zeros(3)
            for c in range(C):
                if not ok[k, c]:
                    continue
                front = project_point(intr[c], Rc[c], tc[c], x, uv, J)
                if not front:
                    continue
                r0 = uv[0] - z[k, c, 0]
                r1 = uv[1] - z[k, c, 1]
                w = 1.0 / (1.0 + (r0 * r0 + r1 * r1) / (sigma * sigma))
                for i in range(3):
                    g[i] += w * (J[0, i] * r0 + J[1, i] * r1)
                    for j in range(3):
                        H[i, j] += w * (J[0, i] * J[0, j] + J[1, i] * J[1, j])
            for i in range(3):
                H[i, i] += 1e-9
            step = _solve3(H, g)
            x = x - step
            if np.max(np.abs(step)) < 1e-7:
                break
        X[k] = x
        Hout[k] = H
    return X, Hout


@loop_kernel
def window_normals(Q, meas, valid, intr, Rc, tc, sigma, robust, ra, rb, rc, shift, frac, tau_col, pos_all, dpos_all,
                   dlen_all, marker_wdep, marker_dep, bones, bone_len, bone_sigma, bone_col):
    """The robust reprojection cost's normal equations with unknowns shared by all frames: the
    body's length scales and the cameras' time offsets (``G`` of them, the vector ``W``).

    Camera c's frame ``m`` was taken at time ``m + tau_c`` frames on the trajectory's clock; with
    ``shift_c = -floor(tau_c)`` and ``f = frac_c = tau_c - floor(tau_c)`` it falls in window
    ``n = m - shift_c``, between frames n and n+1, where every marker is interpolated::

        p(n + f) = (1 - f) p(q_n) + f p(q_{n+1}),     d p / d tau_c = p(q_{n+1}) - p(q_n)

    (linear between the frames' own forward kinematics: the chord of a leg turning 0.07 rad a
    frame, a gallop at 120 fps, is within 0.3 mm of its arc; at ``f = 0`` it is frame n's pose).
    With ``Jx = d uv / d p`` / sigma_cm (``sigma`` (C, M) per camera and marker) the detection's
    whitened residual e has ``J_n = (1-f) Jx dp_n/dq`` and ``J_{n+1} = f Jx dp_{n+1}/dq``; it adds
    ``w J_n^T J_n`` to frame n's information, ``w J_{n+1}^T J_{n+1}`` to frame n+1's and
    ``w J_n^T J_{n+1}`` between them, and with
    ``J_W = [Jx ((1-f) dp_n/dl + f dp_{n+1}/dl), Jx (p_{n+1} - p_n)]`` (the length groups on the
    marker's chain, ``marker_wdep`` (M, D_W) padded with -1, :func:`fk_body_jacobian`; and the
    camera's offset column ``tau_col[c]``, -1 when given) the blocks to and of ``W``. Bone rows of a
    points skeleton are frame n's own, with the bone's log length ``bone_col[i] >= 0`` a column of
    ``W`` (``e = (|p_a - p_b| - bone_len_i) / sigma_i``).

    As in :func:`frame_normal`, the cameras are summed in 3D first, per window and marker, with
    ``K_c = w Jx^T Jx / sigma^2`` and ``k_c = w Jx^T e / sigma``::

        A_a = sum_c (1-f_c)^2 K_c,  A_b = sum_c f_c^2 K_c,  A_ab = sum_c (1-f_c) f_c K_c
        k_a = sum_c (1-f_c) k_c,    k_b = sum_c f_c k_c

    so that with ``J_n = [dp_n/dq, dp_n/dl]``: frame n's block is ``J_n^T A_a J_n``, frame n+1's
    ``J_{n+1}^T A_b J_{n+1}``, the cross ``J_n^T A_ab J_{n+1}`` (the length columns take their share
    of each), the gradients ``J_n^T k_a`` and ``J_{n+1}^T k_b``; an offset's column, one camera's
    own, is ``v_c = K_c (p_{n+1} - p_n)``: ``(1-f_c) J_n^T v_c``, ``f_c J_{n+1}^T v_c`` and
    ``(p_{n+1} - p_n)^T v_c``.

    ``pos_all, dpos_all, dlen_all`` are the markers' positions and Jacobians at ``Q``
    (:func:`graph.kinematics.fk_body_jacobian_batch`: each a loop kernel of :mod:`graph.compiled`,
    chosen by the caller).

    Returns, per window n: ``Ha, Hb, Hab`` (N, P, P): frame n's, frame n+1's and their cross
    information; ``ga, gb`` (N, P); ``HaW, HbW`` (N, P, G); ``HWW`` (N, G, G), ``gW`` (N, G); and per
    camera frame (the detections' own indexing) ``uv`` (N, C, M, 2), ``s`` and ``w`` (N, C, M); the
    cost (N,). A detection whose time falls outside the trajectory is not used (s NaN).
    """
    N, P = Q.shape
    C = meas.shape[1]
    M = meas.shape[2]
    D = marker_dep.shape[1]
    DW = marker_wdep.shape[1]
    G = dlen_all.shape[3]
    Ha = np.zeros((N, P, P))
    Hb = np.zeros((N, P, P))
    Hab = np.zeros((N, P, P))
    ga = np.zeros((N, P))
    gb = np.zeros((N, P))
    HaW = np.zeros((N, P, G))
    HbW = np.zeros((N, P, G))
    HWW = np.zeros((N, G, G))
    gW = np.zeros((N, G))
    uv_out = np.full((N, C, M, 2), np.nan)
    s_out = np.full((N, C, M), np.nan)
    w_out = np.zeros((N, C, M))
    cost = np.zeros(N)
    for n in prange(N):
        uv = np.zeros(2)
        Jx = np.zeros((2, 3))
        X = np.zeros(3)
        vel = np.zeros(3)
        v = np.zeros(3)
        Kc = np.zeros((3, 3))
        kc = np.zeros(3)
        Aa = np.zeros((3, 3))
        Ab = np.zeros((3, 3))
        Aab = np.zeros((3, 3))
        ka = np.zeros(3)
        kb = np.zeros(3)
        ua = np.zeros((G, 3))
        ub = np.zeros((G, 3))
        timed = np.empty(C, dtype=np.int64)
        scratch = np.empty((max(D, DW), 3))
        n1 = min(n + 1, N - 1)
        for mk in range(M):
            Aa[:, :] = 0.0
            Ab[:, :] = 0.0
            Aab[:, :] = 0.0
            ka[:] = 0.0
            kb[:] = 0.0
            nt = 0
            seen = False
            later = False
            for i in range(3):  # d p / d tau: the chord to the next frame (the last frame: from the one before)
                if n1 > n:
                    vel[i] = pos_all[n1, mk, i] - pos_all[n, mk, i]
                elif n > 0:
                    vel[i] = pos_all[n, mk, i] - pos_all[n - 1, mk, i]
                else:
                    vel[i] = 0.0
            for c in range(C):
                m_frame = n + shift[c]
                f = frac[c]
                if m_frame < 0 or m_frame >= N or (f > 0.0 and n + 1 >= N):
                    continue
                a = 1.0 - f
                for i in range(3):
                    X[i] = a * pos_all[n, mk, i] + f * pos_all[n1, mk, i]
                ok = project_point(intr[c], Rc[c], tc[c], X, uv, Jx)
                uv_out[m_frame, c, mk, 0] = uv[0]
                uv_out[m_frame, c, mk, 1] = uv[1]
                if not valid[m_frame, c, mk]:
                    continue
                sg = sigma[c, mk]
                ex, ey, s, rho, w = _detection_cost(uv, meas[m_frame, c, mk], ok, sg, robust, ra, rb, rc)
                cost[n] += rho
                s_out[m_frame, c, mk] = s
                w_out[m_frame, c, mk] = w
                if w <= 0.0:
                    continue
                Kc[:, :] = 0.0
                _add_information(Kc, Jx, w / (sg * sg))
                _symmetrise(Kc)
                kc[:] = 0.0
                _add_gradient(kc, Jx, ex, ey, w / sg)
                for i in range(3):
                    ka[i] += a * kc[i]
                    for j in range(3):
                        Aa[i, j] += a * a * Kc[i, j]
                if f > 0.0:
                    later = True
                    for i in range(3):
                        kb[i] += f * kc[i]
                        for j in range(3):
                            Ab[i, j] += f * f * Kc[i, j]
                            Aab[i, j] += a * f * Kc[i, j]
                seen = True
                tcol = tau_col[c]
                if tcol >= 0:  # the camera's own offset column
                    for i in range(3):
                        v[i] = Kc[i, 0] * vel[0] + Kc[i, 1] * vel[1] + Kc[i, 2] * vel[2]
                        ua[tcol, i] = a * v[i]
                        ub[tcol, i] = f * v[i]
                    HWW[n, tcol, tcol] += vel[0] * v[0] + vel[1] * v[1] + vel[2] * v[2]
                    gW[n, tcol] += vel[0] * kc[0] + vel[1] * kc[1] + vel[2] * kc[2]
                    timed[nt] = tcol
                    nt += 1
            if not seen:
                continue
            dep = marker_dep[mk]
            wdep = marker_wdep[mk]
            Jn = dpos_all[n, mk]
            Jn1 = dpos_all[n1, mk]
            Ln = dlen_all[n, mk]
            Ln1 = dlen_all[n1, mk]
            _project_gradient(ka, Jn, dep, ga[n])
            _project_information(Aa, Jn, Jn, dep, dep, True, Ha[n], scratch)
            _project_gradient(ka, Ln, wdep, gW[n])
            _project_information(Aa, Jn, Ln, dep, wdep, False, HaW[n], scratch)
            _project_information(Aa, Ln, Ln, wdep, wdep, True, HWW[n], scratch)
            if later:
                _project_gradient(kb, Jn1, dep, gb[n])
                _project_information(Ab, Jn1, Jn1, dep, dep, True, Hb[n], scratch)
                _project_information(Aab, Jn, Jn1, dep, dep, False, Hab[n], scratch)
                _project_gradient(kb, Ln1, wdep, gW[n])
                _project_information(Aab, Jn, Ln1, dep, wdep, False, HaW[n], scratch)
                _project_information(Aab, Jn1, Ln, dep, wdep, False, HbW[n], scratch)
                _project_information(Ab, Jn1, Ln1, dep, wdep, False, HbW[n], scratch)
                _project_information(Aab, Ln, Ln1, wdep, wdep, False, HWW[n], scratch)
                _project_information(Aab, Ln1, Ln, wdep, wdep, False, HWW[n], scratch)
                _project_information(Ab, Ln1, Ln1, wdep, wdep, True, HWW[n], scratch)
            for t in range(nt):  # the offsets' columns: with the poses and with the lengths
                col = timed[t]
                for d in range(dep.shape[0]):
                    p = dep[d]
                    if p < 0:
                        break
                    HaW[n, p, col] += Jn[0, p] * ua[col, 0] + Jn[1, p] * ua[col, 1] + Jn[2, p] * ua[col, 2]
                    if later:
                        HbW[n, p, col] += Jn1[0, p] * ub[col, 0] + Jn1[1, p] * ub[col, 1] + Jn1[2, p] * ub[col, 2]
                for d in range(wdep.shape[0]):
                    g = wdep[d]
                    if g < 0:
                        break
                    h = (Ln[0, g] * ua[col, 0] + Ln[1, g] * ua[col, 1] + Ln[2, g] * ua[col, 2]
                         + Ln1[0, g] * ub[col, 0] + Ln1[1, g] * ub[col, 1] + Ln1[2, g] * ub[col, 2])
                    HWW[n, g, col] += h
                    HWW[n, col, g] += h
        # bone-length rows at frame n's own pose
        if bones.shape[0] > 0:
            jb = np.zeros(P)
            for i in range(bones.shape[0]):
                if not (bone_len[i] > 0):
                    continue
                ia = bones[i, 0]
                ib = bones[i, 1]
                dx = pos_all[n, ia, 0] - pos_all[n, ib, 0]
                dy = pos_all[n, ia, 1] - pos_all[n, ib, 1]
                dz = pos_all[n, ia, 2] - pos_all[n, ib, 2]
                L = np.sqrt(dx * dx + dy * dy + dz * dz)
                if L < 1e-12:
                    continue
                e = (L - bone_len[i]) / bone_sigma[i]
                cost[n] += 0.5 * e * e
                for p in range(P):
                    jb[p] = (dx * (dpos_all[n, ia, 0, p] - dpos_all[n, ib, 0, p])
                             + dy * (dpos_all[n, ia, 1, p] - dpos_all[n, ib, 1, p])
                             + dz * (dpos_all[n, ia, 2, p] - dpos_all[n, ib, 2, p])) / (L * bone_sigma[i])
                col = bone_col[i]
                jl = -bone_len[i] / bone_sigma[i]  # d e / d log(bone_len)
                for p in range(P):
                    if jb[p] == 0.0:
                        continue
                    ga[n, p] += jb[p] * e
                    for p2 in range(P):
                        Ha[n, p, p2] += jb[p] * jb[p2]
                    if col >= 0:
                        HaW[n, p, col] += jb[p] * jl
                if col >= 0:
                    gW[n, col] += jl * e
                    HWW[n, col, col] += jl * jl
    return Ha, Hb, Hab, ga, gb, HaW, HbW, HWW, gW, uv_out, s_out, w_out, cost
