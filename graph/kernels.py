"""Compiled hot loops (numba): forward kinematics, projection, robust residuals and Jacobians.

One call computes, for every frame at once, the whitened and robustly weighted reprojection
residuals of all cameras and markers and their Jacobian with respect to that frame's pose
parameters. The solvers hand each frame's block to GTSAM as one linear factor: Python-level
per-measurement factors are two orders of magnitude too slow.

Rotation conventions (passive), ``c = cos a, s = sin a``::

    rot_x = [[1,0,0],[0,c,s],[0,-s,c]]   rot_y = [[c,0,-s],[0,1,0],[s,0,c]]   rot_z = [[c,s,0],[-s,c,0],[0,0,1]]

Camera intrinsics come packed as ``[model, fx, fy, cx, cy, d0..d4]`` (model 0 fisheye, 1 pinhole),
see :meth:`graph.camera.Camera.packed`; the maths is documented in :mod:`graph.camera`.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def _rot(axis, a):
    c, s = np.cos(a), np.sin(a)
    R = np.zeros((3, 3))
    if axis == 0:
        R[0, 0] = 1.0
        R[1, 1] = c; R[1, 2] = s
        R[2, 1] = -s; R[2, 2] = c
    elif axis == 1:
        R[0, 0] = c; R[0, 2] = -s
        R[1, 1] = 1.0
        R[2, 0] = s; R[2, 2] = c
    else:
        R[0, 0] = c; R[0, 1] = s
        R[1, 0] = -s; R[1, 1] = c
        R[2, 2] = 1.0
    return R


@njit(cache=True)
def _drot(axis, a):
    """d rot_axis(a) / d a."""
    c, s = np.cos(a), np.sin(a)
    D = np.zeros((3, 3))
    if axis == 0:
        D[1, 1] = -s; D[1, 2] = c
        D[2, 1] = -c; D[2, 2] = -s
    elif axis == 1:
        D[0, 0] = -s; D[0, 2] = -c
        D[2, 0] = c; D[2, 2] = -s
    else:
        D[0, 0] = -s; D[0, 1] = c
        D[1, 0] = -c; D[1, 1] = -s
    return D


@njit(cache=True)
def fk_jacobian(q, seg_parent, seg_axis, seg_param, pt_base, pt_seg, pt_root, pt_offset, marker_point):
    """Marker positions (M, 3) and their Jacobian d p / d q (M, 3, P) for one pose ``q`` (P,).

    ``d RI_k / d q_j = d Rloc_k / d q_j RI_parent + Rloc_k d RI_parent / d q_j``;
    ``d p / d q_j = d p_base / d q_j + (d RI_seg / d q_j)^T offset``.
    """
    P = q.shape[0]
    S = seg_parent.shape[0]
    K = pt_base.shape[0]
    RI = np.zeros((S, 3, 3))
    dRI = np.zeros((S, P, 3, 3))
    for k in range(S):
        # local rotation and its derivative for each of its (up to 3) axes
        Rloc = np.eye(3)
        n_ax = 0
        for j in range(3):
            if seg_axis[k, j] >= 0:
                n_ax += 1
        facs = np.zeros((3, 3, 3))
        dfacs = np.zeros((3, 3, 3))
        for j in range(n_ax):
            facs[j] = _rot(seg_axis[k, j], q[seg_param[k, j]])
            dfacs[j] = _drot(seg_axis[k, j], q[seg_param[k, j]])
            Rloc = Rloc @ facs[j]
        par = seg_parent[k]
        if par < 0:
            RI[k] = Rloc
        else:
            RI[k] = Rloc @ RI[par]
            for p in range(P):
                any_nz = False
                for a in range(3):
                    for b in range(3):
                        if dRI[par, p, a, b] != 0.0:
                            any_nz = True
                if any_nz:
                    dRI[k, p] = Rloc @ dRI[par, p]
        for j in range(n_ax):
            D = np.eye(3)
            for i in range(n_ax):
                D = D @ (dfacs[i] if i == j else facs[i])
            if par >= 0:
                D = D @ RI[par]
            dRI[k, seg_param[k, j]] += D
    pos = np.zeros((K, 3))
    dpos = np.zeros((K, 3, P))
    for k in range(K):
        b = pt_base[k]
        if b < 0:
            for c in range(3):
                pos[k, c] = q[pt_root[k, c]]
                dpos[k, c, pt_root[k, c]] = 1.0
        else:
            s = pt_seg[k]
            off = pt_offset[k]
            for c in range(3):
                acc = pos[b, c]
                for r in range(3):
                    acc += RI[s, r, c] * off[r]
                pos[k, c] = acc
            for p in range(P):
                for c in range(3):
                    acc = dpos[b, c, p]
                    for r in range(3):
                        acc += dRI[s, p, r, c] * off[r]
                    dpos[k, c, p] = acc
    M = marker_point.shape[0]
    out = np.zeros((M, 3))
    dout = np.zeros((M, 3, P))
    for m in range(M):
        out[m] = pos[marker_point[m]]
        dout[m] = dpos[marker_point[m]]
    return out, dout


@njit(cache=True)
def fk_batch(Q, seg_parent, seg_axis, seg_param, pt_base, pt_seg, pt_root, pt_offset, marker_point):
    """Marker positions (N, M, 3) for poses (N, P)."""
    N = Q.shape[0]
    M = marker_point.shape[0]
    out = np.empty((N, M, 3))
    for n in range(N):
        p, _ = fk_jacobian(Q[n], seg_parent, seg_axis, seg_param, pt_base, pt_seg, pt_root, pt_offset,
                           marker_point)
        out[n] = p
    return out


@njit(cache=True)
def project_point(intr, R, t, X):
    """Pixel (2,) of world point X in one camera, d uv / d X (2, 3), and whether it is in front."""
    xc = R[0, 0] * X[0] + R[0, 1] * X[1] + R[0, 2] * X[2] + t[0]
    yc = R[1, 0] * X[0] + R[1, 1] * X[1] + R[1, 2] * X[2] + t[1]
    zc = R[2, 0] * X[0] + R[2, 1] * X[1] + R[2, 2] * X[2] + t[2]
    uv = np.zeros(2)
    J = np.zeros((2, 3))
    if zc <= 1e-9:
        uv[:] = np.nan
        return uv, J, False
    x = xc / zc
    y = yc / zc
    fx, fy, cx, cy = intr[1], intr[2], intr[3], intr[4]
    d0, d1, d2, d3, d4 = intr[5], intr[6], intr[7], intr[8], intr[9]
    r2 = x * x + y * y
    if intr[0] == 0.0:
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
    else:
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
    return uv, J, True


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


@njit(cache=True)
def frame_block(q, meas, valid, intr, Rc, tc, sigma, robust, ra, rb, rc,
                seg_parent, seg_axis, seg_param, pt_base, pt_seg, pt_root, pt_offset, marker_point,
                bones, bone_len, bone_sigma, J, r, uv_out, s_out, w_out):
    """Fill one frame's whitened, robustly weighted residual r (2CM + B,) and Jacobian J (2CM + B, P).

    Row pair (c, m): ``sqrt(w) (uv_cm(q) - z_cm) / sigma`` with w the IRLS weight of
    ``s = |uv - z| / sigma``; rows of invalid detections are zero. Bone rows (points skeleton):
    ``(|p_a - p_b| - L) / sigma_L``. Returns the frame's robust cost sum(rho) + sum(bone^2)/2.
    """
    C = meas.shape[0]
    M = meas.shape[1]
    pos, dpos = fk_jacobian(q, seg_parent, seg_axis, seg_param, pt_base, pt_seg, pt_root, pt_offset,
                            marker_point)
    P = q.shape[0]
    cost = 0.0
    for c in range(C):
        for m in range(M):
            row = 2 * (c * M + m)
            uv, Jx, ok = project_point(intr[c], Rc[c], tc[c], pos[m])
            uv_out[c, m, 0] = uv[0]
            uv_out[c, m, 1] = uv[1]
            s_out[c, m] = np.nan
            w_out[c, m] = 0.0
            for p in range(P):
                J[row, p] = 0.0
                J[row + 1, p] = 0.0
            r[row] = 0.0
            r[row + 1] = 0.0
            if not valid[c, m]:
                continue
            if not ok:
                # a detection of a point behind the camera: counts as a rejected outlier
                rho, _ = redescending(1e9, ra, rb, rc)
                cost += rho if robust else 0.0
                continue
            ex = (uv[0] - meas[c, m, 0]) / sigma
            ey = (uv[1] - meas[c, m, 1]) / sigma
            s = np.sqrt(ex * ex + ey * ey)
            if robust:
                rho, w = redescending(s, ra, rb, rc)
            else:
                rho, w = 0.5 * s * s, 1.0
            cost += rho
            s_out[c, m] = s
            w_out[c, m] = w
            if w <= 0.0:
                continue
            sw = np.sqrt(w) / sigma
            r[row] = sw * (uv[0] - meas[c, m, 0])
            r[row + 1] = sw * (uv[1] - meas[c, m, 1])
            for p in range(P):
                g0 = 0.0
                g1 = 0.0
                for k in range(3):
                    g0 += Jx[0, k] * dpos[m, k, p]
                    g1 += Jx[1, k] * dpos[m, k, p]
                J[row, p] = sw * g0
                J[row + 1, p] = sw * g1
    base = 2 * C * M
    for i in range(bones.shape[0]):
        a = bones[i, 0]
        b = bones[i, 1]
        row = base + i
        for p in range(P):
            J[row, p] = 0.0
        r[row] = 0.0
        if not (bone_len[i] > 0):
            continue
        d = pos[a] - pos[b]
        L = np.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])
        if L < 1e-12:
            continue
        r[row] = (L - bone_len[i]) / bone_sigma[i]
        cost += 0.5 * r[row] * r[row]
        for p in range(P):
            g = 0.0
            for k in range(3):
                g += d[k] / L * (dpos[a, k, p] - dpos[b, k, p])
            J[row, p] = g / bone_sigma[i]
    return cost


@njit(cache=True)
def all_frames(Q, meas, valid, intr, Rc, tc, sigma, robust, ra, rb, rc,
               seg_parent, seg_axis, seg_param, pt_base, pt_seg, pt_root, pt_offset, marker_point,
               bones, bone_len, bone_sigma):
    """:func:`frame_block` for every frame: J (N, R, P), r (N, R), uv (N, C, M, 2), s, w (N, C, M), cost (N,).

    ``meas`` (N, C, M, 2) and ``valid`` (N, C, M).
    """
    N, P = Q.shape
    C = meas.shape[1]
    M = meas.shape[2]
    R = 2 * C * M + bones.shape[0]
    J = np.zeros((N, R, P))
    r = np.zeros((N, R))
    uv = np.zeros((N, C, M, 2))
    s = np.zeros((N, C, M))
    w = np.zeros((N, C, M))
    cost = np.zeros(N)
    for n in range(N):
        cost[n] = frame_block(Q[n], meas[n], valid[n], intr, Rc, tc, sigma, robust, ra, rb, rc,
                              seg_parent, seg_axis, seg_param, pt_base, pt_seg, pt_root, pt_offset,
                              marker_point, bones, bone_len, bone_sigma, J[n], r[n], uv[n], s[n], w[n])
    return J, r, uv, s, w, cost
