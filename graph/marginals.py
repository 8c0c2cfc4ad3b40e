"""Marginal covariances of every frame of a trajectory chain, in one compiled pass.

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

import numpy as np
from numba import njit

D3 = np.array([-1.0, 3.0, -3.0, 1.0])  # coefficients of q_j .. q_{j+3} in the third difference


@njit(cache=True)
def _lower_solve(L, B):
    """``L^-1 B`` for lower-triangular ``L`` (forward substitution, column by column of B)."""
    n, k = B.shape
    X = np.empty((n, k))
    for c in range(k):
        for i in range(n):
            acc = B[i, c]
            for j in range(i):
                acc -= L[i, j] * X[j, c]
            X[i, c] = acc / L[i, i]
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
def chain_marginals(G, w2):
    """Marginal covariances (N, d, d) of a chain with per-frame information ``G`` (N, d, d) and
    third-difference weights ``w2`` (d,) (``1/sigma_3^2``); see the module docstring."""
    N, d = G.shape[0], G.shape[1]
    out = np.zeros((N, d, d))
    # band[n, k]: the block (n, n + k) of the information matrix, k = 0..3
    band = np.zeros((N, 4, d, d))
    for n in range(N):
        band[n, 0] += G[n]
    for j in range(N - 3):
        for a in range(4):
            for b in range(a, 4):
                for i in range(d):
                    band[j + a, b - a, i, i] += D3[a] * D3[b] * w2[i]
    if N <= 4:  # too short for the recursion: invert the whole (small) matrix
        full = np.zeros((N * d, N * d))
        for n in range(N):
            for k in range(4):
                if n + k < N:
                    full[n * d:(n + 1) * d, (n + k) * d:(n + k + 1) * d] = band[n, k]
                    if k > 0:
                        full[(n + k) * d:(n + k + 1) * d, n * d:(n + 1) * d] = band[n, k].T
        inv = np.linalg.inv(full)
        for n in range(N):
            out[n] = inv[n * d:(n + 1) * d, n * d:(n + 1) * d]
        return out

    # forward elimination of frames 0 .. N-4, as a block Cholesky factorisation: with
    # C = chol(D_n) and W = C^-1 U_n, the band loses W^T W
    m = 3 * d
    Ds = np.empty((N - 3, d, d))
    Ws = np.empty((N - 3, d, m))
    U = np.empty((d, m))
    Wb = np.empty((3, d, d))  # W's blocks, contiguous for the matrix products
    for n in range(N - 3):
        for k in range(3):
            U[:, k * d:(k + 1) * d] = band[n, k + 1]
        W = _lower_solve(np.linalg.cholesky(band[n, 0]), U)
        for i in range(3):
            Wb[i] = W[:, i * d:(i + 1) * d]
        for i in range(1, 4):
            for j in range(i, 4):
                band[n + i, j - i] -= Wb[i - 1].T @ Wb[j - 1]
        Ds[n] = band[n, 0]
        Ws[n] = W

    # marginal information of the last three frames, and their covariances
    M = np.zeros((m, m))
    for i in range(3):
        for j in range(i, 3):
            blk = band[N - 3 + i, j - i]
            M[i * d:(i + 1) * d, j * d:(j + 1) * d] = blk
            if j != i:
                M[j * d:(j + 1) * d, i * d:(i + 1) * d] = blk.T
    Minv = np.linalg.inv(M)
    for i in range(3):
        out[N - 3 + i] = Minv[i * d:(i + 1) * d, i * d:(i + 1) * d]

    # backward: M_n from the conditional of q_n and M_{n+1}; the joint information of (q_n, s_n)
    # is [[D_n, U_n], [U_n^T, W_n^T W_n + M_{n+1}]], with U_n = chol(D_n) W_n
    J = np.zeros((m + d, m + d))
    for n in range(N - 4, -1, -1):
        W = Ws[n]
        J[:d, :d] = Ds[n]
        Un = np.linalg.cholesky(Ds[n]) @ W
        J[:d, d:] = Un
        J[d:, :d] = Un.T
        J[d:, d:] = W.T @ W + M
        M = _schur(J, m)  # q_{n+3} marginalised out: (q_n, q_{n+1}, q_{n+2})
        M = 0.5 * (M + M.T)
        # q_n's marginal information: q_{n+1}, q_{n+2} out; reordered so that they come last
        S = np.linalg.inv(_schur(M, d))
        out[n] = 0.5 * (S + S.T)
    return out
