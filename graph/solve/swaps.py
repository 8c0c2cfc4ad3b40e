"""Left/right swaps: a 2D tracker that labels an animal's left limb as its right one, and the right
as the left, in one camera and frame.

A swapped pair is not an outlier of each marker alone: each detection sits on a real limb, often
within a few pixels of where the other marker projects, so the redescending loss keeps part of it,
and the pull of the kept part is toward the partner. On a rig whose triangulation is coarse (a ring
of wide fisheye cameras, 10 % of pairs swapped) that pulled the left and right markers together:
the body's shoulder and hip widths came out 10-12 % short, 7-9 standard deviations off, and the
trajectory 1.13x the error of the same solver given the true body (tests/test_swaps.py).

So each pair ``(l, r)`` of markers named by their side (:func:`graph.skeleton.left_right_pairs`) is,
in each camera and frame, one of two hypotheses: as given, or exchanged. With the current estimate's
reprojections ``u`` and the detections ``z`` (``sigma`` the slot's noise), the pair's robust cost is

    as given:   rho(|z_l - u_l| / sigma_l) + rho(|z_r - u_r| / sigma_r)
    exchanged:  rho(|z_l - u_r| / sigma_r) + rho(|z_r - u_l| / sigma_l)

(a term only where its detection is valid), ``rho`` the truncated quadratic ``min(s^2, a^2) / 2``,
the redescending loss (:mod:`graph.solve.robust`) held at its first knot ``a`` = 3 (:data:`FITS`):
beyond it the loss no longer takes a detection as Gaussian, and in a decision such a detection is an
outlier in either slot, of one cost, so that only detections that fit decide. With the loss itself
(its plateau 40.5) an outlier near the partner's projection, beside the partner's own detection,
made the exchange far cheaper without being a swap (the plateau saved, the partner's detection moved
a short limb away): on the paper's runs of 20 % outliers and no swaps, 2-4 % more 3D error.

With the tracker swapping a share ``p`` of pairs, a pair is taken as exchanged when that costs less
by more than the log prior odds ``ln((1 - p) / p)``: a max-mixture of the two hypotheses, decided
from the unchanged detections each time, so a decision can be taken back. Where the two limbs
project close together the costs are nearly equal and the detections stay as given.

``p`` is given (``swap_rate``) or estimated (``"auto"``) by expectation-maximisation of the mixture's
weight over the pairs both of whose detections are valid: each pair's posterior of being swapped,
``1 / (1 + exp(ln((1 - p) / p) - gain))`` with ``gain`` the cost the exchange saves, averaged, gives
the next ``p`` (:data:`RATE_RANGE` bounds it). On the simulated regime of 10 % swaps it finds
0.086-0.087 (seeds 0-3); on runs without swaps it ends at the lower bound, where a swap must save ln 999 = 6.9.
"""

from __future__ import annotations

import math

import numpy as np

from graph.solve.robust import A

FITS = 0.5 * A**2  # a detection's cost in a decision: at most that of one at the loss's first knot (3 sigma)
RATE_RANGE = (1e-3, 0.3)  # the swap rate estimated stays within these
EM_ROUNDS = 20  # expectation-maximisation steps of the rate (from 1 %)


def exchanged(uv: np.ndarray, meas: np.ndarray, valid: np.ndarray, sigma: np.ndarray, pairs: np.ndarray,
              rate: float | str = "auto") -> tuple[np.ndarray, float]:
    """Which pairs to take as swapped (N, C, K) bool, and the swap rate ``p`` used (``rate``, or
    estimated when ``"auto"``), from the reprojections ``uv`` (N, C, M, 2) of the current estimate, the
    detections ``meas`` (N, C, M, 2, finite where ``valid``), ``valid`` (N, C, M), each camera's and
    marker's noise ``sigma`` (C, M) and the pairs (K, 2) of marker indices."""
    i, j = pairs[:, 0], pairs[:, 1]
    zi, zj, ui, uj = meas[:, :, i], meas[:, :, j], uv[:, :, i], uv[:, :, j]
    si, sj = sigma[None, :, i], sigma[None, :, j]
    vi, vj = valid[:, :, i], valid[:, :, j]

    def rho(z, u, s, v):
        return np.where(v, np.minimum(0.5 * (np.linalg.norm(z - u, axis=-1) / s) ** 2, FITS), 0.0)

    with np.errstate(invalid="ignore", over="ignore"):
        ii, jj, ij, ji = rho(zi, ui, si, vi), rho(zj, uj, sj, vj), rho(zi, uj, sj, vi), rho(zj, ui, si, vj)
        gain = (ii + jj) - (ij + ji)  # NaN where a reprojection is not finite: never exchanged
    if rate == "auto":
        both = gain[vi & vj & ~np.isnan(gain)]
        p = 0.01
        for _ in range(EM_ROUNDS if both.size else 0):
            posterior = 1.0 / (1.0 + np.exp(np.clip(math.log((1 - p) / p) - both, -50.0, 50.0)))
            p = float(np.clip(posterior.mean(), *RATE_RANGE))
    else:
        p = float(rate)
    if p <= 0:
        return np.zeros(gain.shape, dtype=bool), 0.0
    with np.errstate(invalid="ignore"):
        return gain > math.log((1 - p) / p), p


def exchange(meas: np.ndarray, valid: np.ndarray, swap: np.ndarray, pairs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``meas`` (N, C, M, 2) and ``valid`` (N, C, M) with each pair's detections traded where ``swap``
    (N, C, K): new arrays, the inputs unchanged."""
    meas, valid = meas.copy(), valid.copy()
    for k, (i, j) in enumerate(pairs):
        at = swap[:, :, k]
        meas[at, i], meas[at, j] = meas[at, j], meas[at, i]
        valid[at, i], valid[at, j] = valid[at, j], valid[at, i]
    return meas, valid
