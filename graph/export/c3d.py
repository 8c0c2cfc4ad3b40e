"""C3D (``.c3d``), the biomechanics archive format, written with ezc3d (a maintained C++ reader and
writer with Python bindings; ``pip install 'acinoset[export]'``).

* ``POINT:LABELS`` the markers, ``POINT:RATE`` the frame rate, ``POINT:UNITS`` ``mm`` (the
  convention of Vicon, Qualisys and OpenSim's C3D reader) or ``m``, real-valued (float) storage.
* Each point's 4th word holds, as the format defines it, the cameras that saw it (a bit per camera,
  the first 7 cameras only: the format has 7 bits) and its residual: C3D's residual is a length, the
  mean distance of the reconstructed point from the cameras' rays. Ours is the reprojection error
  carried to the marker (:func:`graph.export.base.error_as_length`), stored in steps of
  ``|POINT:SCALE|`` = ``residual_step``. The format gives it one byte (255 steps), so by default the
  step is the smallest of 1, 2 or 5 times a power of ten that holds the run's largest residual
  (a fly under 2e4 px lenses: 5e-5 mm; a cheetah at 10 m: 0.1 mm); a given step clips larger
  residuals to 255 steps. Residual -1 marks a frame with no estimate, which
  readers return as NaN. Without the calibration in the result file the residual is 0 (C3D:
  valid, residual unknown) and a warning says so.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from graph.export.base import ExportInput, Format, error_as_length, require

UNITS_SCALE = {"mm": 1000.0, "m": 1.0}
RESIDUAL_STEPS = 255  # the residual is one byte of the 4th word


def write(path: str | Path, run: ExportInput, units: str = "mm", residual_step: float | None = None) -> None:
    """``residual_step`` in ``units`` (default 0.1 mm, or 0.0001 m)."""
    ezc3d = require("ezc3d", "ezc3d")
    if units not in UNITS_SCALE:
        raise ValueError(f"C3D units must be one of {', '.join(UNITS_SCALE)}, not {units!r}")
    scale = UNITS_SCALE[units]
    if residual_step is not None and not residual_step > 0:
        raise ValueError(f"residual_step must be positive, not {residual_step}")
    res = run.result
    X = np.asarray(res.positions, dtype=np.float64) * scale  # (N, M, 3)
    n, m = X.shape[:2]
    has = np.isfinite(X).all(axis=-1)  # (N, M)

    err = error_as_length(run)
    if err is None:
        warnings.warn(f"{run.source or 'result'}: holds no calibration, so the C3D residuals are 0 "
                      "(unknown); give the calibration to export them", UserWarning, stacklevel=2)
        residual = np.zeros((n, m))
    else:
        residual = np.nan_to_num(err * scale, nan=0.0)
    step = residual_step or _step_for(float(residual[has].max(initial=0.0)), default=1e-4 * scale)
    residual = np.clip(residual, 0.0, RESIDUAL_STEPS * step)
    residual = np.where(has, residual, -1.0)

    used = np.isfinite(np.asarray(res.residuals, dtype=np.float64)) & ~np.asarray(res.outlier, dtype=bool)
    masks = np.zeros((7, m, n), dtype=bool)
    for c in range(min(7, used.shape[0])):
        masks[c] = used[c].T & has.T

    c = ezc3d.c3d()
    point = c["parameters"]["POINT"]
    point["RATE"]["value"] = [float(res.fps)]
    point["LABELS"]["value"] = tuple(res.markers)
    point["DESCRIPTIONS"]["value"] = tuple(f"{res.skeleton} marker {name}" for name in res.markers)
    point["UNITS"]["value"] = [units]
    point["SCALE"]["value"] = [-float(step)]  # negative: real-valued storage, |SCALE| the residual step
    points = np.ones((4, m, n))
    points[:3] = np.where(np.asarray(has)[..., None], X, np.nan).transpose(2, 1, 0)
    c["data"]["points"] = points
    c["data"]["meta_points"]["residuals"] = residual.T[None]
    c["data"]["meta_points"]["camera_masks"] = masks
    c.write(str(path))


def _step_for(largest: float, default: float) -> float:
    """The smallest 1, 2 or 5 x 10^k with ``255 * step >= largest`` (``default`` when ``largest`` is 0)."""
    if not largest > 0:
        return default
    need = largest / RESIDUAL_STEPS
    k = np.floor(np.log10(need))
    return float(next(f * 10.0 ** k for f in (1.0, 2.0, 5.0, 10.0) if f * 10.0 ** k >= need))


FORMAT = Format("c3d", ".c3d", "application/octet-stream", "C3D", "biomechanics point data, mm, with residuals",
                write, needs=("ezc3d",))
