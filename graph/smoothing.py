"""How smooth: the motion model's scale fitted to the data by the marginal likelihood
(``motion_scale="auto"``).

The smoother's prior on a group of parameters x (one free point's x, y, z over N frames, or a whole
kinematic pose) is the constant-acceleration model of :mod:`graph.fte`: the third differences
``D3 x_i`` of each parameter i are independent ``N(0, (s sigma_i)^2)`` with ``sigma_i = h^2 w_i``
(``w_i`` the skeleton's process noise, h the frame interval) and s the scale to fit. As a precision::

    A(s) = sum_i c_i D3^T D3 (on parameter i),   c_i = 1 / (s sigma_i)^2

an improper prior (flat along the quadratics, which the third difference does not see), normalised
by its pseudo-determinant ``pdet A(s) = prod_i c_i^(N-3) pdet(D3^T D3)^d``. The detections enter
through the robust cost f(x), which about a trajectory x* near the data is the Gauss-Newton quadratic
``f(x) ~ f* + g^T (x - x*) + 1/2 (x - x*)^T H (x - x*)`` (H block-diagonal in frames, the
IRLS-weighted information of :func:`graph.kernels.all_normals`); the smoother's weak anchor
``|x - x0|^2 / (2 sigma_p^2)`` counts with the data (it does not depend on s). With that quadratic
the evidence ``p(z | s) = int exp(-f(x) - |x - x0|^2 / (2 sigma_p^2)) p(x | s) dx`` is Gaussian
(Laplace's approximation)::

    K(s) = H + I / sigma_p^2 + A(s),   x_s = K^{-1} (H x* - g + x0 / sigma_p^2)
    Phi(s) = g^T (x_s - x*) + 1/2 (x_s - x*)^T H (x_s - x*) + 1/2 x_s^T A(s) x_s + |x_s - x0|^2 / (2 sigma_p^2)
    log p(z | s) = -Phi(s) - 1/2 log det K(s) + (N - 3)/2 sum_i log c_i + const

the quantity EKS maximises for its smoothing parameter, here in closed form. K is banded (bandwidth
4 frames), so each evaluation is a banded Cholesky factorisation (LAPACK ``pbtrf``), linear in
frames. The scale maximising it is found on a grid of decades and refined by golden-section search on
log s. Groups whose chains are independent (free points without bones: one chain per marker) get
one scale each; a kinematic skeleton (or free points joined by bones) one scale.

The fit is local: the smoother is solved again with the scales found and the fit repeated
(:func:`graph.fte.solve_from`), since H and the robust weights depend on the trajectory.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.linalg import cho_solve_banded, cholesky_banded

SCALE_RANGE = (1e-6, 1e6)  # the motion scales searched (relative to the skeleton's process noise)
_GRID_STEP = 10.0  # the coarse grid's factor
_GOLDEN_STEPS = 10  # golden-section refinements within the best grid bracket (about 3 % in s)
_D3 = np.array([-1.0, 3.0, -3.0, 1.0])  # the third difference's stencil on frames n .. n+3


def third_difference_gram(N: int) -> np.ndarray:
    """The lower diagonals of ``D3^T D3`` (N x N): row L (0..3) holds ``(D3^T D3)[n + L, n]`` for
    n < N - L (zero-padded), with ``D3`` the (N-3) x N third-difference operator."""
    T = np.zeros((4, N))
    for a in range(4):  # window j contributes s[a] s[a+L] to (j + a + L, j + a)
        for L in range(4 - a):
            n = np.arange(max(N - 3, 0)) + a  # n = j + a for windows j = 0 .. N-4
            np.add.at(T[L], n, _D3[a] * _D3[a + L])
    return T


class ChainEvidence:
    """The log evidence of G independent chains of d parameters over N frames, each as a function of
    its own scale, all in one banded factorisation (the chains one after another: K is then block
    diagonal, and so is its Cholesky factor, whose log-determinant splits by chain).

    ``H`` (G, N, d, d) and ``g`` (G, N, d): the data's Gauss-Newton information and gradient at
    ``x`` (G, N, d), a trajectory near the data; ``x0`` (G, N, d) the anchor's target, ``w`` its
    precision; ``sigma`` (G, d) the third-difference sd of each parameter at scale 1."""

    def __init__(self, H: np.ndarray, g: np.ndarray, x: np.ndarray, x0: np.ndarray, w: float, sigma: np.ndarray):
        G, N, d = x.shape
        self.G, self.N, self.d, self.w = G, N, d, w
        self.H, self.g, self.x, self.x0 = H, g, x, x0
        self.sigma = np.asarray(sigma, dtype=np.float64).reshape(G, d)
        self.T = third_difference_gram(N)
        # the data's block diagonal in LAPACK lower band form over the variables (g N + n) d + i
        self.base = np.zeros((4 * d, G * N * d))
        for k in range(d):
            for b in range(d - k):
                self.base[k, b::d] = H[:, :, b + k, b].ravel()
        self.base[0] += w
        self.rhs = (np.einsum("gnij,gnj->gni", H, x) - g + w * x0).ravel()

    def __call__(self, s: np.ndarray) -> np.ndarray:
        """``log p(z | s_g)`` of every chain g (G,) up to a constant (module docstring)."""
        G, N, d = self.G, self.N, self.d
        c = 1.0 / (np.asarray(s, dtype=np.float64).reshape(G, 1) * self.sigma) ** 2  # (G, d)
        ab = self.base.copy()
        for L in range(4):
            row = ab[L * d].reshape(G, N * d)  # a view: chain g's columns
            for i in range(d):
                row[:, i::d][:, : N - L] += c[:, i, None] * self.T[L, : N - L]
        try:
            chol = cholesky_banded(ab, lower=True)
        except np.linalg.LinAlgError:
            return np.full(G, -math.inf)
        xs = cho_solve_banded((chol, True), self.rhs).reshape(G, N, d)
        dx = xs - self.x
        d3 = xs[:, 3:] - 3 * xs[:, 2:-1] + 3 * xs[:, 1:-2] - xs[:, :-3]
        phi = (np.einsum("gni,gni->g", self.g, dx) + 0.5 * np.einsum("gni,gnij,gnj->g", dx, self.H, dx)
               + 0.5 * np.einsum("gi,gni->g", c, d3 * d3) + 0.5 * self.w * np.sum((xs - self.x0) ** 2, axis=(1, 2)))
        logdet_K = 2.0 * np.log(chol[0]).reshape(G, N * d).sum(axis=1)
        log_pdet = max(N - 3, 0) * np.log(c).sum(axis=1)  # log pdet A(s) but for a constant
        return -phi - 0.5 * logdet_K + 0.5 * log_pdet


class GroupEvidence(ChainEvidence):
    """:class:`ChainEvidence` of one chain: ``H`` (N, d, d), ``g``, ``x``, ``x0`` (N, d),
    ``sigma`` (d,); called with a scalar scale."""

    def __init__(self, H, g, x, x0, w, sigma):
        super().__init__(H[None], g[None], x[None], x0[None], w, np.asarray(sigma)[None])

    def __call__(self, s: float) -> float:
        return float(super().__call__(np.array([s]))[0])


def best_scales(evidence, lo: np.ndarray, hi: float = SCALE_RANGE[1]) -> np.ndarray:
    """For G chains, the scale s_g in [lo_g, hi] maximising ``evidence(s)[g]`` (``evidence`` takes
    and gives (G,)): the best of a grid of factor 10, refined by golden-section search on log s
    between its neighbours, for every chain at once."""
    lo = np.asarray(lo, dtype=np.float64)
    grid = np.exp(np.arange(math.log(lo.min()), math.log(hi) + 1e-9, math.log(_GRID_STEP)))
    if len(grid) < 2:
        return lo.copy()
    values = np.stack([np.where(s >= lo * (1 - 1e-9), evidence(np.full(lo.shape, s)), -np.inf) for s in grid])
    k = np.argmax(values, axis=0)  # (G,)
    logs = np.log(grid)
    a = np.maximum(logs[np.maximum(k - 1, 0)], np.log(lo))
    b = logs[np.minimum(k + 1, len(grid) - 1)]
    r = (math.sqrt(5.0) - 1.0) / 2.0
    x1, x2 = b - r * (b - a), a + r * (b - a)
    f1, f2 = evidence(np.exp(x1)), evidence(np.exp(x2))
    for _ in range(_GOLDEN_STEPS):
        left = f1 >= f2  # the maximum is in [a, x2]
        a, b = np.where(left, a, x1), np.where(left, x2, b)
        nx1, nx2 = np.where(left, b - r * (b - a), x2), np.where(left, x1, a + r * (b - a))
        fnew = evidence(np.exp(np.where(left, nx1, nx2)))
        f1, f2 = np.where(left, fnew, f2), np.where(left, f1, fnew)
        x1, x2 = nx1, nx2
    cand_x = np.stack([logs[k], x1, x2])
    cand_f = np.stack([values[k, np.arange(len(k))], f1, f2])
    return np.exp(cand_x[np.argmax(cand_f, axis=0), np.arange(len(k))])


def best_scale(evidence, lo: float = SCALE_RANGE[0], hi: float = SCALE_RANGE[1]) -> float:
    """:func:`best_scales` of one chain whose ``evidence(s)`` takes and gives scalars."""
    return float(best_scales(lambda s: np.array([evidence(float(s[0]))]), np.array([lo]), hi)[0])


def fit_motion_scales(H: np.ndarray, g: np.ndarray, Q: np.ndarray, Q0: np.ndarray, prior_sigma: float,
                      sigma3: np.ndarray, groups: list[np.ndarray]) -> np.ndarray:
    """The scale of each group in ``groups`` (index arrays into the P parameters, all of one size)
    maximising its evidence, given the data's ``H`` (N, P, P), ``g`` (N, P) at the trajectory ``Q``
    (N, P), the anchor ``Q0`` (N, P) of sd ``prior_sigma`` and the third-difference sds ``sigma3``
    (P,) at scale 1. Cross-group blocks of H are left out (groups are independent chains)."""
    from threadpoolctl import threadpool_limits

    idx = np.stack(groups)  # (G, d)
    Hg = np.ascontiguousarray(np.stack([H[:, i][:, :, i] for i in idx]))  # (G, N, d, d)
    ev = ChainEvidence(Hg, np.stack([g[:, i] for i in idx]), np.stack([Q[:, i] for i in idx]),
                       np.stack([Q0[:, i] for i in idx]), 1.0 / prior_sigma**2, sigma3[idx])
    lo = np.array([stiffest_scale(Hg[k], sigma3[i]) for k, i in enumerate(idx)])
    # one BLAS thread: the banded factorisations are small, and OpenBLAS's threads on a busy machine
    # made one of 1500 x 100 take 1.5 s instead of 5 ms
    with threadpool_limits(limits=1, user_api="blas"):
        return best_scales(ev, lo)


MAX_STIFFNESS = 1e7  # the motion's precision at most this many times the data's (per frame and parameter)


def stiffest_scale(H: np.ndarray, sigma: np.ndarray) -> float:
    """The smallest scale searched for a group with data information ``H`` (N, d, d) and
    third-difference sds ``sigma`` (d,) at scale 1: the one whose motion precision ``1 / (s sigma)^2``
    is ``MAX_STIFFNESS`` times the median per-frame information of the parameters. Smoother than
    that, the trajectory is a parabola for all the data can tell, and the smoother's banded
    elimination loses the digits that tell the parabola from the motion."""
    diag = np.diagonal(H, axis1=1, axis2=2)
    info = float(np.median(diag[diag > 0])) if np.any(diag > 0) else 0.0
    if not info > 0:
        return SCALE_RANGE[0]
    return float(np.clip(1.0 / (float(np.min(sigma)) * np.sqrt(MAX_STIFFNESS * info)), *SCALE_RANGE))
