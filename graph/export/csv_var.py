"""The 3D CSV of the Ensemble Kalman Smoother (EKS, paninski-lab/eks), with posterior variances.

EKS's multi-camera smoother writes its 3D latents as a pandas frame with DeepLabCut's three-level
column index (``scorer / bodyparts / coords``) and the frame index as the first column
(``DataFrame.to_csv``)::

    scorer,    S,   S,   S,   S,             S,             S,             S, ...
    bodyparts, m1,  m1,  m1,  m1,            m1,            m1,            m2, ...
    coords,    x,   y,   z,   x_posterior_var, y_posterior_var, z_posterior_var, x, ...
    0,         ...

Here ``x, y, z`` are the estimate in the calibration's world frame (metres) and
``<a>_posterior_var`` the marginal posterior variance of that coordinate (m^2): ``std**2`` of the
result, whose ``std`` is the square root of the diagonal of each marker's 3x3 posterior covariance,
as EKS takes the diagonal of its smoothed covariance. Empty cells where there is no estimate
(pandas writes NaN so). ``pandas.read_csv(path, header=[0, 1, 2], index_col=0)`` reads it back.
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from graph.export.base import ExportInput, Format

COORDS = ("x", "y", "z", "x_posterior_var", "y_posterior_var", "z_posterior_var")


def write(path: str | Path, run: ExportInput, scorer: str | None = None) -> None:
    res = run.result
    scorer = scorer or f"acinoset_{res.method}"
    X = np.asarray(res.positions, dtype=np.float64)
    var = np.asarray(res.std, dtype=np.float64) ** 2
    var = np.where(np.isfinite(X), var, np.nan)
    n, m = X.shape[:2]
    values = np.concatenate([X, var], axis=-1).reshape(n, 6 * m)
    with open(path, "w", newline="", encoding="utf-8") as f:
        w = csv.writer(f, lineterminator="\n")
        w.writerow(["scorer"] + [scorer] * (6 * m))
        w.writerow(["bodyparts"] + [name for name in res.markers for _ in COORDS])
        w.writerow(["coords"] + list(COORDS) * m)
        for i in range(n):
            w.writerow([str(i)] + ["" if not np.isfinite(v) else repr(float(v)) for v in values[i]])


FORMAT = Format("csv-var", ".var.csv", "text/csv", "EKS CSV", "EKS's 3D layout: x, y, z and their posterior variances",
                write)
