"""Marginal covariances of every frame of a trajectory chain, in one compiled pass; and the
chain's linear solves (:func:`solve_band`) by the same block Cholesky elimination.

The FTE information matrix (undamped, at the optimum) of one parameter group is block-banded:

    Lambda = blockdiag(G_n) + sum_j D_j^T W D_j,    D_j q = q_{j+3} - 3 q_{j+2} + 3 q_{j+1} - q_j

with ``G_n`` (d, d) frame n's measurement and anchor information and ``W = diag(1/sigma_3^2)`` the
constant-acceleration factors' weight. The marginal covariance of frame n is the (n, n) block of
``Lambda^-1``. It is what GTSAM's Bayes tree of this chain gives (``marginalCovariance`` per frame),
computed the same way but without a call per frame:

* **Forward elimination** in time order, as a block Cholesky factorisation (the Bayes net of the
  chain): eliminating ``q_n`` leaves the conditional ``p(q_n | s_n)``, ``s_n = (q_{n+1}, q_{n+2},
  q_{n+3})``, with information ``[[D_n, U_n], [U_n^T, W_n^T W_n]]``, ``W_n = chol(D_n)^-1 U_n``, and
  takes ``W_n^T W_n`` off the band. After frame N-4 the band holds ``M_{N-3}``, the marginal
  information of the last three frames.
* **Backward marginalisation**, in information form: the joint information of ``(q_n, s_n)`` is the
  conditional's plus ``M_{n+1}`` on ``s_n``; the Schur complement that removes ``q_{n+3}`` is
  ``M_n``, the marginal information of ``(q_n, q_{n+1}, q_{n+2})``, and the one that also removes
  ``q_{n+1}, q_{n+2}`` is the marginal information of ``q_n``, whose inverse is ``Sigma_n``.

The stiff motion model makes neighbouring frames almost perfectly correlated, and the order of the
arithmetic decides whether the result survives it. Every Schur complement here is taken as a Gram
product ``J_aa - W^T W`` with ``W = chol(J_bb)^-1 J_ba`` (what GTSAM's Cholesky elimination does);
the textbook ``J_aa - J_ab J_bb^-1 J_ba`` with a general solve, and the covariance form of the
recursion (``Sigma_n = D_n^-1 + B_n Sigma_s B_n^T``, the Takahashi / RTS recursion), both lose
about a digit every few frames and are useless after a few dozen.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

D3 = np.array([-1.0, 3.0, -3.0, 1.0])  # coefficients of q_j .. q_{j+3} in the third difference


@njit(cache=True)
def _lower_solve(L, B):
    """``L^-1 B`` for lower-triangular ``L`` (forward substitution, a row of X at a time: the inner
    loop runs along B's rows, contiguous; each entry sums its terms in the textbook's order)."""
    n, k = B.shape
    X = np.empty((n, k))
    for i in range(n):
        for c in range(k):
            X[i, c] = B[i, c]
        for j in range(i):
            lij = L[i, j]
            for c in range(k):
                X[i, c] -= lij * X[j, c]
        inv = L[i, i]
        for c in range(k):
            X[i, c] /= inv
    return X


@njit(cache=True)
def _upper_solve(R, B):
    """``R^-1 B`` for upper-triangular ``R`` (back substitution, a row of X at a time)."""
    n, k = B.shape
    X = np.empty((n, k))
    for i in range(n - 1, -1, -1):
        for c in range(k):
            X[i, c] = B[i, c]
        for j in range(i + 1, n):
            r = R[i, j]
            for c in range(k):
                X[i, c] -= r * X[j, c]
        for c in range(k):
            X[i, c] /= R[i, i]
    return X


@njit(cache=True)
def _schur(J, keep):
    """Information of the first ``keep`` rows/columns of ``J`` with the rest marginalised out:
    ``J_aa - W^T W`` with ``W = chol(J_bb)^-1 J_ba`` (a Gram product: it stays symmetric and
    positive where the textbook ``J_ab J_bb^-1 J_ba`` drifts)."""
    C = np.linalg.cholesky(np.ascontiguousarray(J[keep:, keep:]))
    W = _lower_solve(C, np.ascontiguousarray(J[keep:, :keep]))
    return J[:keep, :keep] - W.T @ W


@njit(cache=True)
def chain_band(G, w2, stencil=D3):
    """The information of a chain as its blocks ``band[n, k]`` = (n, n + k), k = 0..3 (N, 4, d, d):
    per-frame information ``G`` (N, d, d) and the weights ``w2`` (d,) of the differences whose
    coefficients on frames j .. j+k are ``stencil`` (k + 1 <= 4; default the third difference's)."""
    N, d = G.shape[0], G.shape[1]
    k = stencil.shape[0] - 1
    band = np.zeros((N, 4, d, d))
    for n in range(N):
        band[n, 0] += G[n]
    for j in range(N - k):
        for a in range(k + 1):
            for b in range(a, k + 1):
                for i in range(d):
                    band[j + a, b - a, i, i] += stencil[a] * stencil[b] * w2[i]
    return band


def chain_marginals(G, w2, stencil=D3) -> tuple[np.ndarray, float]:
    """Marginal covariances (N, d, d) of a chain with per-frame information ``G`` (N, d, d) and
    difference weights ``w2`` (d,) (``1/sigma_3^2``) on ``stencil`` (:func:`chain_band`); see the
    module docstring (a lower order leaves the band's outer blocks zero). With the ridge
    :func:`ridged_marginals` needed."""
    N, d = G.shape[0], G.shape[1]
    out, _, _, ridge = ridged_marginals(chain_band(G, w2, stencil), np.zeros((N, d, 0)), np.zeros((0, 0)))
    return out, ridge


RIDGES = (1e-12, 1e-9, 1e-6)  # ridges tried, relative to the largest diagonal information


def ridged_marginals(band, B, Dw) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """:func:`banded_marginals`, and where its Cholesky factors meet a pivot that is not positive
    (information numerically singular: a point two views from one centre see, whose depth only
    the weak anchor fixes, at 1e-17 of the largest information), again with a ridge
    ``r max_i Lambda_ii`` on every diagonal, ``r`` the first of :data:`RIDGES` that factors.
    Returns ``(Sigma_n, Sigma_nW, Sigma_W, r)``, ``r`` 0 when none was needed, infinite (and the
    covariances NaN) when none would do. A ridge adds information: the sds it gives are a lower
    bound along the direction nothing fixed."""
    try:
        return (*banded_marginals(band, B, Dw), 0.0)
    except np.linalg.LinAlgError:
        pass
    d, G = band.shape[2], Dw.shape[0]
    scale = max(np.abs(np.diagonal(band[:, 0], axis1=1, axis2=2)).max(initial=0.0),
                np.abs(np.diag(Dw)).max(initial=0.0))
    for r in RIDGES:
        ridged = band.copy()
        ridged[:, 0] += r * scale * np.eye(d)
        try:
            return (*banded_marginals(ridged, B, Dw + r * scale * np.eye(G)), r)
        except np.linalg.LinAlgError:
            continue
    N = band.shape[0]
    return np.full((N, d, d), np.nan), np.full((N, d, G), np.nan), np.full((G, G), np.nan), math.inf


def information_taken(band, B):
    """What eliminating every frame of a chain takes off the shared unknowns' information:
    ``B^T A^-1 B`` for the chain's information ``A`` (``band``) and its coupling ``B`` (N, d, G) to
    ``W``, :func:`chain_forward`'s ``sum_n W_ng^T W_ng`` (``band`` is not overwritten)."""
    N = band.shape[0]
    return chain_forward(band.copy(), B, np.zeros((N, 0)), N)[3]


@njit(cache=True)
def banded_marginals(band, B, Dw):
    """Marginal covariances of a chain of frames and of unknowns ``W`` that every frame shares
    (the arrow-head: body lengths, time offsets). ``band`` (N, 4, d, d) holds the frames'
    information blocks (n, n + k), k = 0..3, ``B`` (N, d, G) each frame's coupling to ``W`` and
    ``Dw`` (G, G) ``W``'s own. Returns ``Sigma_n`` (N, d, d), the covariances ``Sigma_nW`` (N, d, G)
    between each frame and ``W``, and ``Sigma_W`` (G, G), each marginal over everything else: the
    recursion of the module docstring for the chain, eliminated in time order with ``W`` last
    (linear in N), and ``W``'s part by the block inverse of the arrow-head (below). With G = 0 it
    is the plain chain."""
    N, d = band.shape[0], band.shape[2]
    G = B.shape[2]
    out = np.zeros((N, d, d))
    cross = np.zeros((N, d, G))
    if N <= 4:  # too short for the recursion: invert the whole (small) matrix
        T = N * d + G
        full = np.zeros((T, T))
        for n in range(N):
            for k in range(4):
                if n + k < N:
                    full[n * d:(n + 1) * d, (n + k) * d:(n + k + 1) * d] = band[n, k]
                    if k > 0:
                        full[(n + k) * d:(n + k + 1) * d, n * d:(n + 1) * d] = band[n, k].T
            full[n * d:(n + 1) * d, N * d:] = B[n]
            full[N * d:, n * d:(n + 1) * d] = B[n].T
        full[N * d:, N * d:] = Dw
        inv = np.linalg.inv(full)
        for n in range(N):
            out[n] = inv[n * d:(n + 1) * d, n * d:(n + 1) * d]
            cross[n] = inv[n * d:(n + 1) * d, N * d:]
        return out, cross, np.ascontiguousarray(inv[N * d:, N * d:])

    band = band.copy()  # chain_forward overwrites it: the frames' D_n stay on its diagonal
    Cs, Ws, _, taken, _, B = chain_forward(band, B, np.zeros((N, 0)), N - 3)
    Ds = band[:N - 3, 0]
    M = _tail_information(band, B, Dw - taken)
    if G == 0:
        return _backward(Ds, Cs, Ws, M), cross, np.zeros((0, 0))
    # W by the block inverse of the arrow-head [[A, B], [B^T, Dw]] (A the chain's information):
    #   Sigma_W = (Dw - B^T A^-1 B)^-1,  Sigma_nW = -X_n Sigma_W,  Sigma_n = (A^-1)_nn + X_n Sigma_W X_n^T
    # with X = A^-1 B. M, the information of the last three frames and W once the others are
    # eliminated, gives Sigma_W (the Schur complement was accumulated as a Gram product) and the last
    # frames' X; a back substitution through the factor gives the others, X_n = C_n^-T (Y_n -
    # sum_k V_nk^T X_{n+k}) with W_n = C_n^-1 [V_n1 V_n2 V_n3 Y_n]. The chain's own marginals are the
    # recursion without W (separators of three frames, not three frames and W: (3d)^2 d a frame
    # instead of (3d + G)^2 d), and every term added to them is positive semi-definite.
    t = 3 * d
    Minv = np.linalg.inv(M)
    Sigma_W = np.ascontiguousarray(0.5 * (Minv[t:, t:] + Minv[t:, t:].T))
    X = np.empty((N, d, G))
    last = np.linalg.solve(np.ascontiguousarray(M[:t, :t]), np.ascontiguousarray(M[:t, t:]))
    for i in range(3):
        X[N - 3 + i] = last[i * d:(i + 1) * d]
    for n in range(N - 4, -1, -1):
        rhs = np.ascontiguousarray(Ws[n][:, t:])
        for k in range(3):
            rhs = rhs - np.ascontiguousarray(Ws[n][:, k * d:(k + 1) * d]) @ X[n + k + 1]
        X[n] = _upper_solve(Cs[n].T.copy(), rhs)
    chain = _backward(Ds, Cs, np.ascontiguousarray(Ws[:, :, :t]), np.ascontiguousarray(M[:t, :t]))
    for n in range(N):
        XS = X[n] @ Sigma_W
        cross[n] = -XS
        out[n] = chain[n] + XS @ X[n].T
    return out, cross, Sigma_W


@njit(cache=True)
def _tail_information(band, B, Dw):
    """``M``, the information (3d + G square) of a chain's last three frames and the shared unknowns
    ``W`` once the frames before them are eliminated: their blocks of ``band`` and ``B`` as
    :func:`chain_forward` left them (stopped three frames before the end) and ``W``'s own ``Dw``
    less what those frames took."""
    N, d = band.shape[0], band.shape[2]
    G = B.shape[2]
    m = 3 * d + G
    M = np.zeros((m, m))
    for i in range(3):
        for j in range(i, 3):
            blk = band[N - 3 + i, j - i]
            M[i * d:(i + 1) * d, j * d:(j + 1) * d] = blk
            if j != i:
                M[j * d:(j + 1) * d, i * d:(i + 1) * d] = blk.T
        M[i * d:(i + 1) * d, 3 * d:] = B[N - 3 + i]
        M[3 * d:, i * d:(i + 1) * d] = B[N - 3 + i].T
    M[3 * d:, 3 * d:] = Dw
    return M


@njit(cache=True)
def _backward(Ds, Cs, Ws, M):
    """Marginal covariances (N, d, d) of every frame of a chain: the backward marginalisation of
    the module docstring from the forward pass's ``D_n``, their Cholesky factors ``C_n``, ``W_n``
    (N-3, d, 3d) and ``M`` (the last three frames' information, 3d square)."""
    N = Ds.shape[0] + 3
    d = Ds.shape[1]
    m = 3 * d
    out = np.zeros((N, d, d))
    Minv = np.linalg.inv(M)
    for i in range(3):
        out[N - 3 + i] = Minv[i * d:(i + 1) * d, i * d:(i + 1) * d]
    # backward: M_n from the conditional of q_n and M_{n+1}; the joint information of (q_n, s_n)
    # is [[D_n, U_n], [U_n^T, W_n^T W_n + M_{n+1}]], with U_n = chol(D_n) W_n; q_{n+3} is moved
    # last and marginalised out, leaving (q_n, q_{n+1}, q_{n+2})
    J = np.zeros((m + d, m + d))
    for n in range(N - 4, -1, -1):
        W = Ws[n]
        J[:d, :d] = Ds[n]
        Un = Cs[n] @ W
        J[:d, d:] = Un
        J[d:, :d] = Un.T
        J[d:, d:] = W.T @ W + M
        M = _schur(J, m)  # q_{n+3}, last already, marginalised out: (q_n, q_{n+1}, q_{n+2})
        M = 0.5 * (M + M.T)
        S = np.linalg.inv(_schur(M, d))
        out[n] = 0.5 * (S + S.T)
    return out


@njit(cache=True)
def chain_forward(band, B, r, stop):
    """The forward half of a solve with a chain's information (``band`` (N, 4, d, d) as in
    :func:`banded_marginals`, coupled by ``B`` (N, d, G) to unknowns W shared by every frame) and
    right-hand side ``r`` (N, d; (N, 0) for the factorisation alone, ``y`` then zero): the block
    Cholesky factorisation in time order of frames ``0 .. stop - 1`` (``stop = N``: every frame, the
    chain's last ones too), and the forward substitution with it. Frame n's factor is
    ``C_n = chol(D_n)`` with ``D_n`` its block once the frames before it are eliminated,
    ``W_n = C_n^-1 [band[n, 1..3], B_n]`` its coupling to the next
    three frames and W, and ``y_n = C_n^-1 r_n``; later blocks lose ``W_ni^T W_nj``, later
    couplings ``W_ni^T W_ng`` and right-hand sides ``W_ni^T y_n``. Returns ``C`` (stop, d, d), ``W``
    (stop, d, 3d + G), ``y`` (stop, d), what those frames take off W's information and right-hand
    side, ``sum_n W_ng^T W_ng`` (G, G) and ``sum_n W_ng^T y_n`` (G,), and the coupling ``B`` as
    the elimination left it. ``band`` is overwritten (not copied: 10 MB at 500 frames of 25
    parameters): the frames not eliminated hold their remaining information, and each eliminated
    frame its ``D_n`` on the diagonal. ``B`` and ``r`` are not overwritten."""
    N, d = band.shape[0], band.shape[2]
    G = B.shape[2]
    B = B.copy()
    r = r.copy()
    solving = r.shape[1] == d  # else (N, 0): the factorisation alone (the marginals')
    m = 3 * d + G
    Cs = np.empty((stop, d, d))
    Ws = np.empty((stop, d, m))  # every row written whole below
    ys = np.zeros((stop, d))
    taken = np.zeros((G, G))
    taken_r = np.zeros(G)
    Wb = np.empty((3, d, d))
    U = np.empty((d, m))
    for n in range(stop):
        k_max = min(3, N - 1 - n)
        for k in range(k_max):
            U[:, k * d:(k + 1) * d] = band[n, k + 1]
        U[:, k_max * d:3 * d] = 0.0  # the last frames couple to fewer than three after them
        U[:, 3 * d:] = B[n]
        C = np.linalg.cholesky(band[n, 0])
        W = _lower_solve(C, U)
        if solving:
            y = _lower_solve(C, np.ascontiguousarray(r[n]).reshape(d, 1))[:, 0]
            ys[n] = y
        for i in range(k_max):
            Wb[i] = W[:, i * d:(i + 1) * d]
        Wg = np.ascontiguousarray(W[:, 3 * d:])
        for i in range(1, k_max + 1):
            for j in range(i, k_max + 1):
                band[n + i, j - i] -= Wb[i - 1].T @ Wb[j - 1]
            B[n + i] -= Wb[i - 1].T @ Wg
            if solving:
                r[n + i] -= Wb[i - 1].T @ ys[n]
        taken += Wg.T @ Wg
        if solving:
            taken_r += Wg.T @ ys[n]
        Cs[n] = C
        Ws[n] = W
    return Cs, Ws, ys, taken, taken_r, B


@njit(cache=True)
def chain_backward(Cs, Ws, ys, xW):
    """The back substitution of a solve factored by :func:`chain_forward`, given the shared
    unknowns' solution ``xW`` (G,): ``x_n = C_n^-T (y_n - sum_k W_nk x_{n+k} - W_ng xW)``, last
    frame first. Returns x (N, d)."""
    N, d = ys.shape
    x = np.empty((N, d))
    for n in range(N - 1, -1, -1):
        k_max = min(3, N - 1 - n)
        rhs = ys[n] - np.ascontiguousarray(Ws[n][:, 3 * d:]) @ xW
        for k in range(k_max):
            rhs -= np.ascontiguousarray(Ws[n][:, k * d:(k + 1) * d]) @ x[n + k + 1]
        x[n] = _upper_solve(Cs[n].T.copy(), rhs.reshape(d, 1))[:, 0]
    return x


def solve_band(bands, Bs, rs, Dw, rW):
    """``x_c`` (N, d_c) of every chain c and ``xW`` (G,) solving the arrow-head system of chains that
    share only the unknowns W: chain c's information ``A_c`` (``bands[c]``), its coupling ``Bs[c]``
    (N, d_c, G) to W and right-hand side ``rs[c]`` (N, d_c); W's own information ``Dw`` (G, G) and
    right-hand side ``rW`` (G,). Each chain by :func:`chain_forward`, W's system reduced by all of
    them, ``(Dw - sum_c taken_c) xW = rW - sum_c taken_r_c``, solved densely, then each chain by
    :func:`chain_backward`. One chain with G = 0 is a plain chain solve.
    ``numpy.linalg.LinAlgError`` where a pivot block is not positive definite. The bands are
    overwritten."""
    factors = [chain_forward(band, B, r, band.shape[0]) for band, B, r in zip(bands, Bs, rs)]
    if len(rW):
        xW = np.linalg.solve(Dw - sum(f[3] for f in factors), rW - sum(f[4] for f in factors))
    else:
        xW = np.zeros(0)
    return [chain_backward(f[0], f[1], f[2], xW) for f in factors], xW
