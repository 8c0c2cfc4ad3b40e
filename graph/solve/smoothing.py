"""How smooth: the motion model's scale fitted to the data by the marginal likelihood
(``motion_scale="auto"``).

The smoother's prior on a group of parameters x (one free point's x, y, z over N frames, or a whole
kinematic pose) is the constant-acceleration model of :mod:`graph.solve.fte`: the third differences
``D3 x_i`` of each parameter i are independent ``N(0, (s sigma_i)^2)`` with ``sigma_i = h^2 w_i``
(``w_i`` the skeleton's process noise, h the frame interval) and s the scale to fit. As a precision::

    A(s) = sum_i c_i D3^T D3 (on parameter i),   c_i = 1 / (s sigma_i)^2

an improper prior (flat along the quadratics, which the third difference does not see), normalised
by its pseudo-determinant ``pdet A(s) = prod_i c_i^(N-3) pdet(D3^T D3)^d``. The detections enter
through the robust cost f(x), which about a trajectory x* near the data is the Gauss-Newton quadratic
``f(x) ~ f* + g^T (x - x*) + 1/2 (x - x*)^T H (x - x*)`` (H block-diagonal in frames, the
IRLS-weighted information of :func:`graph.solve.kernels.all_normals`); the smoother's weak anchor
``|x - x0|^2 / (2 sigma_p^2)`` counts with the data (it does not depend on s). With that quadratic
the evidence ``p(z | s) = int exp(-f(x) - |x - x0|^2 / (2 sigma_p^2)) p(x | s) dx`` is Gaussian
(Laplace's approximation)::

    K(s) = H + I / sigma_p^2 + A(s),   x_s = K^{-1} (H x* - g + x0 / sigma_p^2)
    Phi(s) = g^T (x_s - x*) + 1/2 (x_s - x*)^T H (x_s - x*) + 1/2 x_s^T A(s) x_s + |x_s - x0|^2 / (2 sigma_p^2)
    log p(z | s) = -Phi(s) - 1/2 log det K(s) + (N - 3)/2 sum_i log c_i + const

the quantity EKS maximises for its smoothing parameter, here in closed form. K is banded (bandwidth
4 frames), so each evaluation is a banded Cholesky factorisation (LAPACK ``pbtrf``), linear in
frames. The scale maximising it is bracketed by a walk of decades from the current scale and refined
by parabolic interpolation on log s (:func:`best_scales`). Groups whose chains are independent
(free points without bones: one chain per marker) get one scale each; a kinematic skeleton (or free
points joined by bones) one scale.

The fit is local: it is made at the smoother's optimum, the smoother solved again with the scales
found and the fit repeated (:func:`graph.solve.fte.refit_motion`), since H and the robust weights depend
on the trajectory. The same banded band form solves the smoother's own steps for free points
without bones (:func:`solve_chains`).

**The order** (``motion_order``): the prior may be on the k-th differences instead, k = 1 (a random
walk of positions, what aniposelib's ``triangulate_optim`` penalises), 2 or 3; ``Dk`` then replaces
``D3`` above and N - k replaces N - 3. With ``motion_order="auto"`` each group's order is chosen by
the fractional Bayes factor (:meth:`ChainEvidence.across_orders`): the evidence as above is defined
only up to a constant of the order, which a fraction of the data's own evidence cancels.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, NamedTuple

import numpy as np
from scipy.linalg import cho_solve_banded, cholesky_banded

if TYPE_CHECKING:
    from threadpoolctl import ThreadpoolController

SCALE_RANGE = (1e-6, 1e6)  # the motion scales searched (relative to the skeleton's process noise)
_FIRST_STEP = 2.0  # the bracketing walk's first factor either side of the start; each further step doubles
_PARABOLA_STEPS = 8  # at most this many parabolic refinements
_X_TOL = 0.02  # ... ending when the vertex moves less than this in log s (2 % in s)
_D3 = np.array([-1.0, 3.0, -3.0, 1.0])  # the third difference's stencil on frames n .. n+3


ORDERS = (1, 2, 3)  # the difference orders the motion prior may take
STENCILS = {1: np.array([-1.0, 1.0]), 2: np.array([1.0, -2.0, 1.0]), 3: _D3}  # on frames n .. n+k


def difference_gram(N: int, order: int = 3) -> np.ndarray:
    """The lower diagonals of ``Dk^T Dk`` (N x N) for the k-th difference operator ``Dk``
    ((N-k) x N, k = ``order``): row L (0..3) holds ``(Dk^T Dk)[n + L, n]`` for n < N - L (zero-padded;
    rows past k are zero)."""
    st = STENCILS[order]
    T = np.zeros((4, N))
    for a in range(order + 1):  # window j contributes st[a] st[a+L] to (j + a + L, j + a)
        for L in range(order + 1 - a):
            n = np.arange(max(N - order, 0)) + a  # n = j + a for windows j = 0 .. N-k-1
            np.add.at(T[L], n, st[a] * st[a + L])
    return T


def data_band(H: np.ndarray, w: float) -> np.ndarray:
    """``blockdiag(H) + w I`` of G independent chains, ``H`` (G, N, d, d), in LAPACK's lower band
    form (4d, G N d) over the variables ``(g N + n) d + i`` (chain by chain, frame by frame): row k
    holds the entries (j + k, j). The band is 4d deep so that :func:`motion_band` fits in it."""
    G, N, d = H.shape[:3]
    ab = np.zeros((4 * d, G * N * d))
    for k in range(d):
        for b in range(d - k):
            ab[k, b::d] = H[:, :, b + k, b].ravel()
    ab[0] += w
    return ab


def motion_band(c: np.ndarray, N: int, orders: np.ndarray | None = None) -> np.ndarray:
    """``sum_i c_gi Dk^T Dk`` (on parameter i of chain g, k its order, default 3) of G chains of N
    frames, ``c`` (G, d), in the band form of :func:`data_band`: parameter i of frame n couples only
    with itself in frames n + 1 .. n + k, at band rows d .. kd."""
    G, d = c.shape
    orders = np.full(G, 3) if orders is None else np.asarray(orders)
    ab = np.zeros((4 * d, G * N * d))
    for k in np.unique(orders):
        T = difference_gram(N, int(k))
        sel = np.flatnonzero(orders == k)
        for L in range(int(k) + 1):
            row = ab[L * d].reshape(G, N * d)  # a view: chain g's columns
            for i in range(d):
                row[np.ix_(sel, np.arange(i, (N - L) * d, d))] = c[sel, i, None] * T[L, : N - L]
    return ab


def solve_chains(ab: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """``K^-1 rhs`` for K in the band form of :func:`data_band` (symmetric positive definite), by
    LAPACK's banded Cholesky (``pbtrf``, ``pbtrs``): linear in frames. Raises
    ``numpy.linalg.LinAlgError`` where K is not numerically positive definite."""
    with one_blas_thread():
        return cho_solve_banded((cholesky_banded(ab, lower=True), True), rhs)


# the process's threadpoolctl controller, found once (finding the libraries takes ~6 ms)
_BLAS: list[ThreadpoolController] = []


def one_blas_thread():
    """A context in which BLAS and LAPACK run on one thread: the banded factorisations here are
    small, and OpenBLAS's threads on a busy machine made one of 1500 x 100 take 1.5 s instead of
    5 ms."""
    if not _BLAS:
        from threadpoolctl import ThreadpoolController

        _BLAS.append(ThreadpoolController())
    return _BLAS[0].limit(limits=1, user_api="blas")


class ChainEvidence:
    """The log evidence of G independent chains of d parameters over N frames, each as a function of
    its own scale, all in one banded factorisation (the chains one after another: K is then block
    diagonal, and so is its Cholesky factor, whose log-determinant splits by chain).

    ``H`` (G, N, d, d) and ``g`` (G, N, d): the data's Gauss-Newton information and gradient at
    ``x`` (G, N, d), a trajectory near the data; ``x0`` (G, N, d) the anchor's target, ``w`` its
    precision; ``sigma`` (G, d) the k-th difference sd of each parameter at scale 1; ``orders`` (G,)
    each chain's k (default 3: the module docstring's D3 is then Dk, and N - 3 is N - k)."""

    def __init__(self, H: np.ndarray, g: np.ndarray, x: np.ndarray, x0: np.ndarray, w: float, sigma: np.ndarray,
                 orders: np.ndarray | None = None):
        G, N, d = x.shape
        self.G, self.N, self.d, self.w = G, N, d, w
        self.H, self.g, self.x, self.x0 = H, g, x, x0
        self.sigma = np.asarray(sigma, dtype=np.float64).reshape(G, d)
        self.orders = np.full(G, 3) if orders is None else np.asarray(orders, dtype=np.int64)
        self.base = data_band(H, w)
        self.rhs = (np.einsum("gnij,gnj->gni", H, x) - g + w * x0).ravel()

    def _c(self, s) -> np.ndarray:
        return 1.0 / (np.asarray(s, dtype=np.float64).reshape(self.G, 1) * self.sigma) ** 2  # (G, d)

    def __call__(self, s: np.ndarray) -> np.ndarray:
        """``log p(z | s_g)`` of every chain g (G,) up to a constant of its order (module docstring)."""
        G, N, d = self.G, self.N, self.d
        c = self._c(s)
        ab = self.base + motion_band(c, N, self.orders)
        try:
            chol = cholesky_banded(ab, lower=True)
        except np.linalg.LinAlgError:
            return np.full(G, -math.inf)
        xs = cho_solve_banded((chol, True), self.rhs).reshape(G, N, d)
        dx = xs - self.x
        motion = np.empty(G)
        for k in np.unique(self.orders):
            sel = self.orders == k
            dk = np.diff(xs[sel], int(k), axis=1)
            motion[sel] = np.einsum("gi,gni->g", c[sel], dk * dk)
        phi = (np.einsum("gni,gni->g", self.g, dx) + 0.5 * np.einsum("gni,gnij,gnj->g", dx, self.H, dx)
               + 0.5 * motion + 0.5 * self.w * np.sum((xs - self.x0) ** 2, axis=(1, 2)))
        logdet_K = 2.0 * np.log(chol[0]).reshape(G, N * d).sum(axis=1)
        log_pdet = np.maximum(N - self.orders, 0) * np.log(c).sum(axis=1)  # log pdet A(s) but for a constant
        return -phi - 0.5 * logdet_K + 0.5 * log_pdet

    def across_orders(self, s: np.ndarray, frames: float = 3.0) -> np.ndarray:
        """The log evidence (G,) comparable between orders: O'Hagan's fractional Bayes factor. The
        k-th difference prior is flat along the polynomials of degree below k, so its evidence holds
        only up to a constant of the order (the width given those polynomials, arbitrary). Dividing
        by the evidence of a fraction ``b = frames / N`` of the data's information (``b H``,
        ``b g``: as much as ``frames`` frames hold, enough to pin those polynomials) cancels it:
        ``log p(z | s) - log p_b(z | s)``, each by ``__call__``. A proper prior (the anchor's
        precision on the polynomials) was tried instead: its verdict moved with the anchor's width,
        and it chose the second order on the simulated cheetah, 3-6 % more 3D error than the
        third (bench/RESULTS.md, section 12d)."""
        b = frames / self.N
        part = ChainEvidence(self.H * b, self.g * b, self.x, self.x0, self.w, self.sigma, self.orders)
        return self(s) - part(s)


class GroupEvidence:
    """:class:`ChainEvidence` of one chain: ``H`` (N, d, d), ``g``, ``x``, ``x0`` (N, d),
    ``sigma`` (d,); called with a scalar scale."""

    def __init__(self, H, g, x, x0, w, sigma, order: int = 3):
        self.chain = ChainEvidence(H[None], g[None], x[None], x0[None], w, np.asarray(sigma)[None], np.array([order]))

    def __call__(self, s: float) -> float:
        return float(self.chain(np.array([s]))[0])


def best_scales(evidence, lo: np.ndarray, hi: float = SCALE_RANGE[1], start: np.ndarray | None = None) -> np.ndarray:
    """For G chains, the scale s_g in [lo_g, hi] maximising ``evidence(s)[g]`` (``evidence`` takes
    and gives (G,)), every chain at once, on x = log s:

    * **bracket**: from ``start`` (default 1; a previous fit's scales make this short), walk uphill,
      first by a factor ``_FIRST_STEP`` and each step twice as far (in log s) as the one before,
      until the middle of three points is the best, ``f(a) <= f(b) >= f(c)`` (points clipped to
      the bounds);
    * **refine**: successive parabolic interpolation: the vertex of the parabola through ``a < b < c``,
      ``x* = b - 1/2 [(b-a)^2 (f_b - f_c) - (b-c)^2 (f_b - f_a)] / [(b-a)(f_b - f_c) - (b-c)(f_b - f_a)]``,
      is evaluated and the three best points around the maximum kept, until the vertex moves less
      than ``_X_TOL``. The log evidence is smooth in log s and near-quadratic about its maximum, so
      this takes a few evaluations where golden-section search took ten.

    A chain whose best point is a bound keeps the bound."""
    lo = np.asarray(lo, dtype=np.float64)
    a_lo, a_hi = np.log(lo), math.log(hi)
    h = math.log(_FIRST_STEP)

    def f(x):
        v = np.asarray(evidence(np.exp(x)), dtype=np.float64)
        return np.where(np.isfinite(v), v, -np.inf)

    xb = np.clip(np.zeros(len(lo)) if start is None else np.log(np.asarray(start, dtype=np.float64)), a_lo, a_hi)
    xa, xc = np.maximum(xb - h, a_lo), np.minimum(xb + h, a_hi)
    fb, fa, fc = f(xb), f(xa), f(xc)
    for _ in range(int(math.ceil(math.log2((a_hi - a_lo.min()) / h))) + 2):  # bracket: walk uphill
        up = (fc > fb) & (xc > xb)
        down = ~up & (fa > fb) & (xa < xb)
        if not (up | down).any():
            break
        new_x = np.where(up, np.minimum(xc + 2 * (xc - xb), a_hi),
                         np.where(down, np.maximum(xa - 2 * (xb - xa), a_lo), xb))
        fn = f(new_x)
        xa, xb, xc, fa, fb, fc = (np.where(up, xb, np.where(down, new_x, xa)), np.where(up, xc, np.where(down, xa, xb)),
                                  np.where(up, new_x, np.where(down, xb, xc)), np.where(up, fb, np.where(down, fn, fa)),
                                  np.where(up, fc, np.where(down, fa, fb)), np.where(up, fn, np.where(down, fb, fc)))
    active = (xa < xb) & (xb < xc) & np.isfinite(fa) & np.isfinite(fb) & np.isfinite(fc)
    for _ in range(_PARABOLA_STEPS):  # refine
        if not active.any():
            break
        p, q = (xb - xa) * (fb - fc), (xb - xc) * (fb - fa)
        den = p - q
        x = xb - 0.5 * ((xb - xa) * p - (xb - xc) * q) / np.where(den != 0, den, 1.0)
        # a vertex within _X_TOL of b: converged. Safeguard: a degenerate parabola, or a vertex outside
        # the bracket, takes the middle of the larger side
        bad = (den == 0) | ~(x > xa) | ~(x < xc)
        active &= bad | (np.abs(x - xb) >= _X_TOL)
        if not active.any():
            break
        mid = np.where(xb - xa > xc - xb, 0.5 * (xa + xb), 0.5 * (xb + xc))
        x = np.where(active, np.where(bad, mid, x), xb)
        fx = f(x)
        better, left = active & (fx > fb), x < xb
        worse = active & ~better
        xa, xc, fa, fc = (np.where(better & ~left, xb, np.where(worse & left, x, xa)),
                          np.where(better & left, xb, np.where(worse & ~left, x, xc)),
                          np.where(better & ~left, fb, np.where(worse & left, fx, fa)),
                          np.where(better & left, fb, np.where(worse & ~left, fx, fc)))
        xb, fb = np.where(better, x, xb), np.where(better, fx, fb)
    return np.exp(xb)


def best_scale(evidence, lo: float = SCALE_RANGE[0], hi: float = SCALE_RANGE[1]) -> float:
    """:func:`best_scales` of one chain whose ``evidence(s)`` takes and gives scalars."""
    return float(best_scales(lambda s: np.array([evidence(float(s[0]))]), np.array([lo]), hi)[0])


class MotionFit(NamedTuple):
    """What :func:`fit_motion_scales` chose for each of G groups."""

    scales: np.ndarray  # (G,) the motion scale of each group
    orders: np.ndarray  # (G,) the difference order of each group's prior
    # order -> (G,) the log evidence at its best scale (across_orders), when the orders were compared
    evidence: dict[int, np.ndarray] | None = None


def fit_motion_scales(H: np.ndarray, g: np.ndarray, Q: np.ndarray, Q0: np.ndarray, prior_sigma: float,
                      sigma3: np.ndarray, groups: list[np.ndarray], start: np.ndarray | None = None,
                      max_stiffness: float | None = None, orders: np.ndarray | None = None,
                      candidates: tuple[int, ...] | None = None) -> MotionFit:
    """The scale of each group in ``groups`` (index arrays into the P parameters, all of one size)
    maximising its evidence, given the data's ``H`` (N, P, P), ``g`` (N, P) at the trajectory ``Q``
    (N, P), the anchor ``Q0`` (N, P) of sd ``prior_sigma`` and the difference sds ``sigma3``
    (P,) at scale 1; the search starts from ``start`` (G,) (a previous fit's scales; default 1) and
    stops at ``max_stiffness`` (:func:`stiffest_scale`; default ``MAX_STIFFNESS``).
    Cross-group blocks of H are left out (groups are independent chains).

    Each group's prior is on the differences of its order in ``orders`` (G,) (default 3). With
    ``candidates`` (orders, e.g. :data:`ORDERS`) the order is chosen too: for each candidate k every
    group's scale is fitted with the k-th difference, and each group takes the order of largest
    :meth:`ChainEvidence.across_orders` at its best scale (the same quadratic model of the data at
    ``Q`` for every order; the optimum moves little between orders, and the caller solves again)."""
    idx = np.stack(groups)  # (G, d)
    Hg = np.ascontiguousarray(np.stack([H[:, i][:, :, i] for i in idx]))  # (G, N, d, d)
    w = 1.0 / prior_sigma**2
    chains = (Hg, np.stack([g[:, i] for i in idx]), np.stack([Q[:, i] for i in idx]), np.stack([Q0[:, i] for i in idx]),
              w, sigma3[idx])
    lo = np.array([stiffest_scale(Hg[k], sigma3[i], w, max_stiffness) for k, i in enumerate(idx)])
    G = len(idx)
    with one_blas_thread():
        if not candidates:
            orders = np.full(G, 3) if orders is None else np.asarray(orders)
            return MotionFit(best_scales(ChainEvidence(*chains, orders), lo, start=start), orders)
        fits, evidence = {}, {}
        for k in candidates:
            ev = ChainEvidence(*chains, np.full(G, k))
            fits[k] = best_scales(ev, lo, start=start if orders is not None and np.all(orders == k) else None)
            evidence[k] = ev.across_orders(fits[k])
    table = np.stack([evidence[k] for k in candidates])  # (K, G)
    best = np.asarray(candidates)[np.argmax(table, axis=0)]
    scales = np.array([fits[k][gi] for gi, k in enumerate(best)])
    return MotionFit(scales, best, evidence)


MAX_STIFFNESS = 1e7  # the motion's precision at most this many times the data's (per frame and parameter)
# ... for ekf's stream, which GTSAM's iSAM2 eliminates with all markers of a frame in one key: its
# Cholesky of a clique fails when two consecutive diagonal entries of the factor differ by 2^12
# (information by 2^24, 1.7e7), and a stiff chain's pivots run from the motion's precision down to
# the data's, spread further by the data's anisotropy (30x between a marker's axes on the fly).
# Measured: the fly's stream failed at 1e7, not at 1e6. (fte's kinematic skeletons stay at
# MAX_STIFFNESS: their fits on the simulated cheetah stop short of it, and a bound taken over
# parameters of mixed units, angles and metres, is crude: 1e6 bound them at 10 px noise.)
GTSAM_MAX_STIFFNESS = 1e6


def stiffest_scale(H: np.ndarray, sigma: np.ndarray, w: float = 0.0, max_stiffness: float | None = None) -> float:
    """The smallest scale searched for a group with data information ``H`` (N, d, d), the anchor's
    precision ``w`` and third-difference sds ``sigma`` (d,) at scale 1: the one whose motion
    precision ``c = 1 / (s sigma)^2`` is ``MAX_STIFFNESS`` times the median per-frame information
    ``h`` of the parameters (the diagonal of H, plus w). Smoother than that, the trajectory is a
    parabola for all the data can tell, and solving for it loses the digits that tell the parabola
    from the motion: the chain's information ``K = H + w I + c D3^T D3`` has its largest eigenvalue
    near ``64 c`` and its smallest near the data's (the parabolas, which D3 does not see), a
    condition number of about ``64 MAX_STIFFNESS`` (1e9-1e10 measured, at 500 frames): about six of
    double precision's sixteen digits are left to the solve (:func:`solve_chains`). A marker no
    camera pair sees has only the anchor's ``w`` and gets the same bound relative to it.
    ``max_stiffness`` (default ``MAX_STIFFNESS``) replaces the 1e7: ``GTSAM_MAX_STIFFNESS`` for
    ekf's stream, where GTSAM's dense Cholesky of a clique stops at a 2^24 spread of pivots."""
    max_stiffness = MAX_STIFFNESS if max_stiffness is None else max_stiffness
    diag = np.diagonal(H, axis1=1, axis2=2)
    info = (float(np.median(diag[diag > 0])) if np.any(diag > 0) else 0.0) + w
    if not info > 0:
        return SCALE_RANGE[0]
    return float(np.clip(1.0 / (float(np.min(sigma)) * np.sqrt(max_stiffness * info)), *SCALE_RANGE))
