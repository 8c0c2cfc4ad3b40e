"""How much the detections scatter: a robust estimate of the pixel noise from 2D residuals.

Every method weighs a detection by the measurement noise sigma (pixels, per image coordinate), and
the 3D uncertainties scale with it, so a sigma that is wrong for the data gives standard deviations
that are wrong by the same factor. DeepLabCut's noise depends on the resolution, the lens and the
network, so :func:`scatter_px` measures it from the residuals ``r = pi(X) - z`` of a fit.

Model: an inlier's residual is ``r ~ N(0, sigma^2 I_2)``, so ``|r|^2 / sigma^2 ~ chi^2_2`` and
``|r|`` is Rayleigh distributed with median ``sigma sqrt(2 ln 2)``; an outlier lands anywhere.
The estimate is an iterated truncated mean: start from the Rayleigh median (robust to fewer than
half outliers), then keep the residuals within ``k sigma`` and solve

    E[ |r|^2  |  |r| < k sigma ] = 2 sigma^2 g(k),   g(k) = 1 - (k^2/2) e^{-k^2/2} / (1 - e^{-k^2/2})

for sigma, until it settles (k = 3: g = 0.9495, 98.9 % of the inliers kept).

A fitted model pulls the residuals in: with n coordinates and p fitted parameters,
``E|r|^2 = 2 sigma^2 (n - p) / n``. ``dof`` scales each residual by ``sqrt(n / (n - p))`` before
the estimate (triangulation: ``n = 2 v`` for v views of a point and ``p = 3``).
"""

from __future__ import annotations

import math

import numpy as np

K_SIGMA = 3.0
RAYLEIGH_MEDIAN = math.sqrt(2.0 * math.log(2.0))  # median |r| / sigma for a 2D Gaussian residual


def _truncation(k: float) -> float:
    """``g(k)``: the mean of ``|r|^2 / (2 sigma^2)`` over the residuals within ``k sigma``."""
    e = math.exp(-0.5 * k * k)
    return 1.0 - 0.5 * k * k * e / (1.0 - e)


def scatter_px(residuals: np.ndarray, dof: np.ndarray | float = 1.0, k: float = K_SIGMA,
               iterations: int = 30) -> float:
    """Robust per-coordinate noise sigma (px) from residual lengths ``|r|`` (any shape; NaN left
    out), each first multiplied by ``dof`` (``sqrt(n / (n - p))``, broadcast). NaN when fewer than
    ten residuals are finite."""
    r = np.asarray(residuals, dtype=np.float64) * dof
    r = r[np.isfinite(r)].ravel()
    if r.size < 10:
        return float("nan")
    r2 = r * r
    sigma = float(np.median(r)) / RAYLEIGH_MEDIAN
    g = _truncation(k)
    for _ in range(iterations):
        if not sigma > 0:
            return 0.0
        inside = r2 < (k * sigma) ** 2
        if inside.sum() < 10:
            break
        new = math.sqrt(float(r2[inside].mean()) / (2.0 * g))
        if abs(new - sigma) <= 1e-4 * sigma:
            sigma = new
            break
        sigma = new
    return sigma


def triangulation_dof(views: np.ndarray) -> np.ndarray:
    """``sqrt(n / (n - p))`` for points triangulated from ``views`` cameras (``n = 2 v``, ``p = 3``);
    NaN for fewer than two views (no redundancy to measure)."""
    n = 2.0 * np.asarray(views, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(n > 3.0, np.sqrt(n / np.maximum(n - 3.0, 1e-12)), np.nan)
