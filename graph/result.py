"""Assemble a :class:`graph.api.Result` from a solver's arrays, with the diagnostics every method shares.

Reprojection RMSE is over the detections used (valid and not flagged as outliers):
``sqrt(mean |uv - z|^2)`` in pixels.
"""

from __future__ import annotations

import numpy as np

from graph.api import Result, SolveReport


def build_result(prob, method: str, *, positions, std, reprojections, s, outlier, seconds, iterations,
                 cost=float("nan"), params=None, params_std=None, causal_positions=None,
                 per_frame_ms=None, bounds_active=0) -> Result:
    """``s`` and ``outlier`` are (N, C, M); ``reprojections`` (C, N, M, 2)."""
    sk = prob.skeleton
    valid = prob.valid
    res_px = (s * prob.sigma_px).transpose(1, 0, 2)  # (C, N, M)
    res_px = np.where(valid.transpose(1, 0, 2), res_px, np.nan)
    out = (outlier & valid).transpose(1, 0, 2)
    used = np.isfinite(res_px) & ~out
    rmse = float(np.sqrt(np.mean(res_px[used] ** 2))) if used.any() else float("nan")
    ncams = valid.sum(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        score = np.where(ncams > 0, (prob.likelihood * valid).sum(axis=1) / np.maximum(ncams, 1), 0.0)
    um, uf = prob.unconstrained()
    rates = None
    if params is not None and params.shape[0] > 1:
        rates = np.gradient(params, prob.dt, axis=0)
    report = SolveReport(
        method=method, skeleton=sk.name, frames=prob.frames, cameras=prob.cameras, markers=len(sk.markers),
        seconds={"total": 0.0, **{k: float(v) for k, v in seconds.items()}},
        iterations=int(iterations), cost=float(cost), reprojection_rmse_px=rmse, per_frame_ms=per_frame_ms,
        outliers=int(out.sum()), observations=int(valid.sum()), unconstrained_markers=um,
        unconstrained_frames=uf, bounds_active=int(bounds_active), warnings=list(prob.warnings))
    return Result(
        method=method, skeleton=sk.name, markers=list(sk.markers), positions=positions, std=std,
        reprojections=reprojections, residuals=res_px, ncams=ncams, score=score, outlier=out,
        camera_names=prob.calibration.names, fps=prob.options.fps, report=report, options=prob.options,
        param_names=list(sk.param_names) if params is not None else [], params=params, rates=rates,
        params_std=params_std, causal_positions=causal_positions, bones=list(sk.bones),
        camera_centers=np.stack([c.center for c in prob.calibration.cameras]))
