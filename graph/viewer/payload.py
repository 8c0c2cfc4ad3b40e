"""The JSON payload the web job page and the HTML playback draw from: one definition for both.

:func:`result_payload` turns a :class:`~graph.types.Result` into the view's data (positions rounded
to 10 micrometres of the run's units at an animal's size, pixels to 0.01 px; its arrays NumPy's) and
:func:`payload_json` writes it as JSON; the REST service returns it as ``GET
/v1/jobs/{id}/result?format=json`` and :mod:`graph.viewer.playback` inlines it. The summaries it holds
(:func:`error_table`, :func:`frame_error`) are the ones the figures draw.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import orjson

from graph.errors import InputError
from graph.types import Result, jsonable, together

PAYLOAD_VERSION = 1

# Decimal places kept in the payload: 10 micrometres, 0.01 px, 0.001 likelihood, 1e-5 rad.
_POS_DECIMALS = 5
_PX_DECIMALS = 2
_SCORE_DECIMALS = 3
_PARAM_DECIMALS = 5


# ----------------------------------------------------------------------------------- summaries


@dataclass
class ErrorTable:
    """Reprojection error per camera and marker over the whole run (C, M).

    ``median``: median over frames of the pixel residual of the detections the solver used
    (observed, above the likelihood threshold, not rejected), NaN where there were none.
    ``observations``: detections above the likelihood threshold. ``outliers``: those the robust loss
    rejected.
    """

    median: np.ndarray
    observations: np.ndarray
    outliers: np.ndarray


def error_table(result: Result) -> ErrorTable:
    r = np.asarray(result.residuals, dtype=np.float64)
    out = np.asarray(result.outlier, dtype=bool) & np.isfinite(r)
    used = np.where(out, np.nan, r)
    has = np.isfinite(used).any(axis=1)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN cells: NaN, as documented
        med = np.nanmedian(used, axis=1)
    med[~has] = np.nan
    return ErrorTable(median=med, observations=np.isfinite(r).sum(axis=1).astype(int),
                      outliers=out.sum(axis=1).astype(int))


def frame_error(result: Result) -> np.ndarray:
    """Per-frame reprojection RMSE (N,) over the detections used, NaN where none:
    ``sqrt(mean_{c,m} r_cnm^2)``."""
    r = np.where(np.asarray(result.outlier, dtype=bool), np.nan, np.asarray(result.residuals, float))
    cnt = np.isfinite(r).sum(axis=(0, 2))
    ss = np.nansum(r ** 2, axis=(0, 2))
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(cnt > 0, np.sqrt(ss / np.maximum(cnt, 1)), np.nan)


def frame_ranges(frames) -> list[tuple[int, int]]:
    """Sorted frame numbers as inclusive runs: ``[1, 2, 3, 7] -> [(1, 3), (7, 7)]``."""
    fs = sorted({int(f) for f in frames})
    runs: list[tuple[int, int]] = []
    for f in fs:
        if runs and f == runs[-1][1] + 1:
            runs[-1] = (runs[-1][0], f)
        else:
            runs.append((f, f))
    return runs


def ranges_text(frames, limit: int = 8) -> str:
    runs = frame_ranges(frames)
    parts = [f"{a}" if a == b else f"{a}-{b}" for a, b in runs[:limit]]
    if len(runs) > limit:
        parts.append(f"and {len(runs) - limit} more")
    return ", ".join(parts)


def camera_centers(result: Result, calibration=None) -> np.ndarray | None:
    """World positions of the cameras (C, 3): from the result, else from ``calibration``."""
    cc = getattr(result, "camera_centers", None)
    if cc is not None:
        cc = np.asarray(cc, dtype=np.float64).reshape(-1, 3)
        if cc.shape[0] == len(result.camera_names):
            return cc
    if calibration is not None:
        if len(calibration) != len(result.camera_names):
            raise InputError(f"the calibration has {len(calibration)} cameras but the result has "
                             f"{len(result.camera_names)}", getattr(calibration, "source", None) or None)
        return np.stack([c.center for c in calibration.cameras])
    return None


def _camera_directions(result: Result, calibration=None) -> np.ndarray | None:
    """Unit optical axes in the world frame (C, 3), ``R^T [0, 0, 1]``, when a calibration is given."""
    if calibration is None or len(calibration) != len(result.camera_names):
        return None
    return np.stack([c.R[2] for c in calibration.cameras])


def is_length_param(name: str) -> bool:
    """Positions in metres: a kinematic skeleton's ``x_*``, ``y_*``, ``z_*`` (the root) and a points
    skeleton's ``<marker>_x``, ``_y``, ``_z``; the rest are angles."""
    return name.split("_", 1)[0] in ("x", "y", "z") or name.rsplit("_", 1)[-1] in ("x", "y", "z")


def animal_size(result: Result) -> float:
    """The animal's size (m): the median over frames of the largest extent of its markers (a fly's
    is a fraction of a millimetre, a cheetah's a metre or two); the pictures scale with it."""
    pos = np.asarray(result.positions)
    ext = []
    for P in pos[:: max(1, len(pos) // 50)]:
        P = P[np.isfinite(P).all(axis=1)]
        if len(P) >= 2:
            ext.append(float(np.ptp(P, axis=0).max()))
    size = float(np.median(ext)) if ext else 0.0
    return size if size > 0 else 1.0


def _position_decimals(result: Result) -> int:
    """Decimals of metres that keep 1e-4 of the animal's size: 5 (10 um) for a cheetah, 8 for a fly."""
    return int(np.clip(4 - np.floor(np.log10(animal_size(result))), _POS_DECIMALS, 10))


# ------------------------------------------------------------------------------------ payload


def _payload_array(a, decimals: int | None = None) -> np.ndarray | None:
    """An array as the payload keeps it: rounded to ``decimals``, C-ordered and native, for
    :func:`payload_json` (NaN and infinities written as ``null``)."""
    if a is None:
        return None
    a = np.asarray(a)
    if a.dtype == bool:
        return np.ascontiguousarray(a)
    if np.issubdtype(a.dtype, np.integer):
        return np.ascontiguousarray(a, dtype=np.int64)
    a = np.ascontiguousarray(a, dtype=np.float64)
    return np.round(a, decimals) if decimals is not None else a


def payload_json(payload: dict) -> bytes:
    """A payload (:func:`result_payload`, :func:`group_payload`) as compact JSON: its arrays as nested
    lists, NaN and infinities as ``null`` (orjson writes the arrays straight from memory: 18,000 frames
    of six cameras and 20 markers in 0.1 s, where building Python lists for :mod:`json` took 2 s)."""
    return orjson.dumps(payload, option=orjson.OPT_SERIALIZE_NUMPY)


def assumed_noise_px(result: Result) -> float:
    """The detection noise the solve assumed (px): the report's, which is the measured one when the
    option was ``"auto"``; the option itself for results written before the report had it."""
    sigma = getattr(result.report, "sigma_px", float("nan"))
    if not (isinstance(sigma, (int, float)) and np.isfinite(sigma) and sigma > 0):
        opt = getattr(result.options, "measurement_std_px", 5.0)
        sigma = float(opt) if isinstance(opt, (int, float)) and opt > 0 else 5.0
    return float(sigma)


def result_payload(result: Result, calibration=None) -> dict:
    """Everything the result view draws: names, numbers and NumPy arrays, written by
    :func:`payload_json` (NaN -> ``null``). Shapes: N frames,
    M markers, C cameras, P pose parameters.

    ``markers`` and ``cameras`` are names; ``bones`` pairs of marker names. ``positions``, ``std``
    (N, M, 3) metres; ``ncams`` (N, M) cameras that saw each marker; ``score`` (N, M) mean
    likelihood; ``reprojection_error_px`` (N, M) the mean over the cameras whose detection was used;
    ``residuals`` (C, N, M) px per camera; ``outliers`` a list of ``[camera, frame, marker]`` index
    triples; ``error_table`` {median, observations, outliers} (C, M); ``frame_error`` (N,) px;
    ``camera_centers`` (C, 3) or null; ``params``, ``params_std`` (N, P) or null, with
    ``param_units`` "m" or "rad"; ``report`` the solver's report; ``options`` the options the run
    was solved with.
    """
    N, M = result.positions.shape[:2]
    bones = [[a, b] for a, b in result.bones if a in result.markers and b in result.markers]
    table = error_table(result)
    out = np.argwhere(np.asarray(result.outlier, dtype=bool) & np.isfinite(result.residuals))
    report = result.report.to_dict()
    options = result.options.to_dict()
    cc = camera_centers(result, calibration)
    cd = _camera_directions(result, calibration)
    params = result.params
    pos_dec = _position_decimals(result)
    return {
        "version": PAYLOAD_VERSION,
        "method": result.method,
        "skeleton": result.skeleton,
        "fps": float(result.fps),
        "frames": int(N),
        "markers": list(result.markers),
        "bones": bones,
        "cameras": list(result.camera_names),
        "camera_centers": _payload_array(cc, pos_dec),
        "camera_directions": _payload_array(cd, 4),
        "positions": _payload_array(result.positions, pos_dec),
        "std": _payload_array(result.std, pos_dec),
        "ncams": _payload_array(np.asarray(result.ncams).astype(np.int64)),
        "score": _payload_array(result.score, _SCORE_DECIMALS),
        "reprojection_error_px": _payload_array(result.error, _PX_DECIMALS),
        "residuals": _payload_array(result.residuals, _PX_DECIMALS),
        "outliers": _payload_array(out),
        "error_table": {"median": _payload_array(table.median, _PX_DECIMALS),
                        "observations": _payload_array(table.observations),
                        "outliers": _payload_array(table.outliers)},
        "frame_error": _payload_array(frame_error(result), _PX_DECIMALS),
        "param_names": list(result.param_names or []),
        "param_units": ["m" if is_length_param(p) else "rad" for p in (result.param_names or [])],
        "params": _payload_array(params, max(pos_dec, _PARAM_DECIMALS)) if params is not None else None,
        "params_std": (_payload_array(result.params_std, max(pos_dec, _PARAM_DECIMALS))
                       if result.params_std is not None else None),
        "report": jsonable(report),
        "options": jsonable(options),
    }


def group_payload(group: Sequence[tuple[str, Result]], calibration=None) -> dict:
    """:func:`result_payload` of several individuals :func:`together`, with ``individuals``: each one's
    ``name`` and ``markers`` ``[first, count]`` (the page draws each in a colour of its own)."""
    payload = result_payload(together(group), calibration)
    first, out = 0, []
    for name, r in group:
        out.append({"name": name, "markers": [first, len(r.markers)]})
        first += len(r.markers)
    payload["individuals"] = out
    return payload


# ------------------------------------------------------------------------------------ figures
