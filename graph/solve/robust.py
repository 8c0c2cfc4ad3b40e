"""Robust losses on normalised residuals ``s = |r| / sigma`` (r a 2D reprojection residual in pixels).

* The AcinoSet redescending loss (Hampel's three-part form), a, b, c = 3, 10, 20::

      rho(s) = s^2/2                                       s < a
             = a s - a^2/2                                 a <= s < b
             = a b - a^2/2 + a (c-b)/2 (1 - ((c-s)/(c-b))^2)  b <= s < c
             = a b - a^2/2 + a (c-b)/2   (= 40.5)          s >= c

  IRLS weight ``w(s) = rho'(s)/s``: 1, a/s, a (c-s)/((c-b) s), 0. The compiled version used by the
  solvers is :func:`graph.solve.kernels.redescending`.
* Cauchy: ``rho(s) = log(1 + s^2)/2``, ``w(s) = 1/(1 + s^2)`` (triangulation refinement).

A detection is called an *outlier* when ``s >= OUTLIER_S`` (beyond b: the loss is redescending
there and the detection has lost most of its pull).
"""

from __future__ import annotations

import numpy as np

A, B, C = 3.0, 10.0, 20.0
OUTLIER_S = B


def redescending(s: np.ndarray, a: float = A, b: float = B, c: float = C) -> tuple[np.ndarray, np.ndarray]:
    """Vectorised redescending cost and IRLS weight of ``s >= 0``."""
    s = np.asarray(s, dtype=np.float64)
    u = (c - s) / (c - b)
    with np.errstate(divide="ignore", invalid="ignore"):
        rho = np.select([s < a, s < b, s < c],
                        [0.5 * s * s, a * s - 0.5 * a * a, a * b - 0.5 * a * a + 0.5 * a * (c - b) * (1 - u * u)],
                        a * b - 0.5 * a * a + 0.5 * a * (c - b))
        w = np.select([s < a, s < b, s < c], [np.ones_like(s), a / s, a * (c - s) / ((c - b) * s)], 0.0)
    return rho, w

