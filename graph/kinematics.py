"""Forward kinematics of a skeleton (numba): marker positions and their Jacobians.

A skeleton is a tree of segments; segment ``k`` turns by ``RI_k = R_axes(q) RI_parent`` (only the
segment's listed axes) and a marker is ``p = p_parent_point + RI_k^T offset``
(:class:`graph.skeleton.Skeleton` packs the arrays these kernels take).

Rotation conventions (passive), ``c = cos a, s = sin a``::

    rot_x = [[1,0,0],[0,c,s],[0,-s,c]]   rot_y = [[c,0,-s],[0,1,0],[s,0,c]]   rot_z = [[c,s,0],[-s,c,0],[0,0,1]]
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from graph.compiled import loop_kernel


@njit(cache=True)
def _rot(axis, a):
    c, s = np.cos(a), np.sin(a)
    R = np.zeros((3, 3))
    if axis == 0:
        R[0, 0] = 1.0
        R[1, 1] = c
        R[1, 2] = s
        R[2, 1] = -s
        R[2, 2] = c
    elif axis == 1:
        R[0, 0] = c
        R[0, 2] = -s
        R[1, 1] = 1.0
        R[2, 0] = s
        R[2, 2] = c
    else:
        R[0, 0] = c
        R[0, 1] = s
        R[1, 0] = -s
        R[1, 1] = c
        R[2, 2] = 1.0
    return R


@njit(cache=True)
def _drot(axis, a):
    """d rot_axis(a) / d a."""
    c, s = np.cos(a), np.sin(a)
    D = np.zeros((3, 3))
    if axis == 0:
        D[1, 1] = -s
        D[1, 2] = c
        D[2, 1] = -c
        D[2, 2] = -s
    elif axis == 1:
        D[0, 0] = -s
        D[0, 2] = -c
        D[2, 0] = c
        D[2, 2] = -s
    else:
        D[0, 0] = -s
        D[0, 1] = c
        D[1, 0] = -c
        D[1, 1] = -s
    return D


@njit(cache=True, inline="always")
def _mul3(A, B, out):
    for i in range(3):
        for j in range(3):
            out[i, j] = A[i, 0] * B[0, j] + A[i, 1] * B[1, j] + A[i, 2] * B[2, j]


@njit(cache=True)
def _segment_rotations(q, seg_parent, seg_axis, seg_param):
    """Every segment's rotation ``RI_k`` (S, 3, 3), its derivatives ``d RI_k / d q_j`` (S, P, 3, 3)
    and which of them are not zero (S, P): ``d RI_k / d q_j = d Rloc_k / d q_j RI_parent`` for the
    segment's own parameters and ``Rloc_k d RI_parent / d q_j`` for its ancestors'."""
    P = q.shape[0]
    S = seg_parent.shape[0]
    RI = np.zeros((S, 3, 3))
    dRI = np.zeros((S, P, 3, 3))
    has = np.zeros((S, P), dtype=np.bool_)
    facs = np.zeros((3, 3, 3))
    dfacs = np.zeros((3, 3, 3))
    Rloc = np.zeros((3, 3))
    T1 = np.zeros((3, 3))
    T2 = np.zeros((3, 3))
    for k in range(S):
        n_ax = 0
        for j in range(3):
            if seg_axis[k, j] >= 0:
                facs[n_ax] = _rot(seg_axis[k, j], q[seg_param[k, j]])
                dfacs[n_ax] = _drot(seg_axis[k, j], q[seg_param[k, j]])
                n_ax += 1
        # Rloc = facs[0] facs[1] ...
        Rloc[:] = 0.0
        for i in range(3):
            Rloc[i, i] = 1.0
        for j in range(n_ax):
            _mul3(Rloc, facs[j], T1)
            Rloc[:] = T1
        par = seg_parent[k]
        if par < 0:
            RI[k] = Rloc
        else:
            _mul3(Rloc, RI[par], RI[k])
            for p in range(P):
                if has[par, p]:
                    _mul3(Rloc, dRI[par, p], dRI[k, p])
                    has[k, p] = True
        for j in range(n_ax):
            T1[:] = 0.0
            for i in range(3):
                T1[i, i] = 1.0
            for i in range(n_ax):
                _mul3(T1, dfacs[i] if i == j else facs[i], T2)
                T1[:] = T2
            if par >= 0:
                _mul3(T1, RI[par], T2)
                T1[:] = T2
            p = seg_param[k, j]
            for a in range(3):
                for b in range(3):
                    dRI[k, p, a, b] += T1[a, b]
            has[k, p] = True
    return RI, dRI, has


@njit(cache=True)
def fk_jacobian(q, seg_parent, seg_axis, seg_param, pt_base, pt_seg, pt_root, pt_offset, marker_point,
                marker_dep):
    """Marker positions (M, 3) and their Jacobian d p / d q (M, 3, P) for one pose ``q`` (P,):
    ``d p / d q_j = d p_base / d q_j + (d RI_seg / d q_j)^T offset`` (:func:`_segment_rotations`).
    """
    pos, dpos, _ = fk_body_jacobian(q, seg_parent, seg_axis, seg_param, pt_base, pt_seg, pt_root, pt_offset,
                                    marker_point, np.full(pt_base.shape[0], -1, dtype=np.int64), 0)
    return pos, dpos


@njit(cache=True)
def fk_body_jacobian(q, seg_parent, seg_axis, seg_param, pt_base, pt_seg, pt_root, pt_offset, marker_point,
                     pt_group, G):
    """:func:`fk_jacobian`, and the Jacobian ``d p / d l`` (M, 3, G) with respect to the log scale
    ``l_g`` of each length group (offset ``exp(l_g) u_k``, so ``d offset_k / d l_g = offset_k`` for
    the points of group g): ``d p_k / d l_g = d p_base / d l_g + [group(k) = g] RI_seg^T offset_k``.
    ``pt_group`` (K,) is each point's group (-1: none)."""
    P = q.shape[0]
    K = pt_base.shape[0]
    RI, dRI, has = _segment_rotations(q, seg_parent, seg_axis, seg_param)
    pos = np.zeros((K, 3))
    dpos = np.zeros((K, 3, P))
    dlen = np.zeros((K, 3, G))
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
                arm = RI[s, 0, c] * off[0] + RI[s, 1, c] * off[1] + RI[s, 2, c] * off[2]
                pos[k, c] = pos[b, c] + arm
                for gi in range(G):
                    dlen[k, c, gi] = dlen[b, c, gi]
                if pt_group[k] >= 0 and pt_group[k] < G:
                    dlen[k, c, pt_group[k]] += arm
            for p in range(P):
                for c in range(3):
                    dpos[k, c, p] = dpos[b, c, p]
                if has[s, p]:
                    for c in range(3):
                        dpos[k, c, p] += dRI[s, p, 0, c] * off[0] + dRI[s, p, 1, c] * off[1] + dRI[s, p, 2, c] * off[2]
    M = marker_point.shape[0]
    out = np.zeros((M, 3))
    dout = np.zeros((M, 3, P))
    dl = np.zeros((M, 3, G))
    for m in range(M):
        out[m] = pos[marker_point[m]]
        dout[m] = dpos[marker_point[m]]
        dl[m] = dlen[marker_point[m]]
    return out, dout, dl


@njit(cache=True)
def fk_batch(Q, seg_parent, seg_axis, seg_param, pt_base, pt_seg, pt_root, pt_offset, marker_point, marker_dep):
    """Marker positions (N, M, 3) for poses (N, P)."""
    N = Q.shape[0]
    M = marker_point.shape[0]
    out = np.empty((N, M, 3))
    for n in range(N):
        p, _ = fk_jacobian(Q[n], seg_parent, seg_axis, seg_param, pt_base, pt_seg, pt_root, pt_offset,
                           marker_point, marker_dep)
        out[n] = p
    return out


@njit(cache=True)
def fk_jacobian_batch(Q, seg_parent, seg_axis, seg_param, pt_base, pt_seg, pt_root, pt_offset, marker_point,
                      marker_dep):
    """Marker positions (N, M, 3) and Jacobians (N, M, 3, P) for poses (N, P)."""
    N, P = Q.shape
    M = marker_point.shape[0]
    pos = np.empty((N, M, 3))
    dpos = np.empty((N, M, 3, P))
    for n in range(N):
        p, dp = fk_jacobian(Q[n], seg_parent, seg_axis, seg_param, pt_base, pt_seg, pt_root, pt_offset,
                            marker_point, marker_dep)
        pos[n] = p
        dpos[n] = dp
    return pos, dpos


@loop_kernel
def fk_body_jacobian_batch(Q, seg_parent, seg_axis, seg_param, pt_base, pt_seg, pt_root, pt_offset, marker_point,
                           pt_group, G):
    """:func:`fk_body_jacobian` for poses (N, P): positions (N, M, 3), ``d p / d q`` (N, M, 3, P)
    and ``d p / d l`` (N, M, 3, G)."""
    N, P = Q.shape
    M = marker_point.shape[0]
    pos = np.empty((N, M, 3))
    dpos = np.empty((N, M, 3, P))
    dlen = np.empty((N, M, 3, G))
    for n in prange(N):
        p, dp, dl = fk_body_jacobian(Q[n], seg_parent, seg_axis, seg_param, pt_base, pt_seg, pt_root, pt_offset,
                                     marker_point, pt_group, G)
        pos[n] = p
        dpos[n] = dp
        dlen[n] = dl
    return pos, dpos, dlen
