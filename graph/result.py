"""Assemble a :class:`graph.types.Result` from a solver's arrays, with the diagnostics every method shares.

Reprojection RMSE is over the detections used (valid and not flagged as outliers):
``sqrt(mean |uv - z|^2)`` in pixels. The measured noise is :func:`graph.noise.scatter_px` of the
residuals (for ``tri`` scaled for the three coordinates each point took); when it is far from the
sigma a smoother assumed, the report says so: the 3D standard deviations scale with that sigma.
"""

from __future__ import annotations

import warnings

import numpy as np

from graph.noise import scatter_px, triangulation_dof
from graph.problem import Problem
from graph.types import Result, SolveReport


def build_result(prob: Problem, method: str, *, positions, std, reprojections, s, outlier, seconds, iterations,
                 cost=float("nan"), sigma_px: float | None = None, params=None, params_std=None,
                 causal_positions=None, per_frame_ms=None, bounds_active=0, report: dict | None = None) -> Result:
    """``s`` and ``outlier`` are (N, C, M); ``reprojections`` (C, N, M, 2). ``sigma_px`` is the
    detection noise ``s`` is normalised by (default: the problem's); ``report`` more report fields
    (the body's lengths, the cameras' offsets) and their ``warnings``."""
    sk = prob.skeleton
    valid = prob.valid
    sigma_px = prob.sigma_px if sigma_px is None else sigma_px
    rel_px = np.where(valid, s * sigma_px, np.nan).transpose(1, 0, 2)  # (C, N, M) in units of sigma_px
    res_px = rel_px if prob.noise_scale is None else rel_px * prob.noise_scale[:, None, :]  # pixels
    out = (outlier & valid).transpose(1, 0, 2)
    used = np.isfinite(res_px) & ~out
    rmse = float(np.sqrt(np.mean(res_px[used] ** 2))) if used.any() else float("nan")
    ncams = valid.sum(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        score = np.where(ncams > 0, (prob.likelihood * valid).sum(axis=1) / np.maximum(ncams, 1), 0.0)
    noise = measured_scatter(method, rel_px, ncams)
    notes = list(prob.warnings)
    mismatch = noise_mismatch(method, prob.options.measurement_std_px, sigma_px, noise)
    if mismatch:
        notes.append(mismatch)
        warnings.warn(mismatch, stacklevel=3)
    extra = dict(report or {})
    if prob.noise_scale is not None:
        extra["relative_noise"] = {name: float(np.median(prob.noise_scale[c]))
                                   for c, name in enumerate(prob.calibration.names)}
    for note in extra.pop("warnings", []):
        notes.append(note)
        warnings.warn(note, stacklevel=3)
    um, uf = prob.unconstrained()
    rates = None
    if params is not None and params.shape[0] > 1:
        rates = np.gradient(params, prob.dt, axis=0)
    report = SolveReport(
        method=method, skeleton=sk.name, frames=prob.frames, cameras=prob.cameras, markers=len(sk.markers),
        seconds={"total": 0.0, **{k: float(v) for k, v in seconds.items()}},
        iterations=int(iterations), cost=float(cost), reprojection_rmse_px=rmse, per_frame_ms=per_frame_ms,
        outliers=int(out.sum()), observations=int(valid.sum()), unconstrained_markers=um,
        unconstrained_frames=uf, bounds_active=int(bounds_active), sigma_px=float(sigma_px), noise_px=noise,
        warnings=notes, **extra)
    return Result(
        method=method, skeleton=sk.name, markers=list(sk.markers), positions=positions, std=std,
        reprojections=reprojections, residuals=res_px, ncams=ncams, score=score, outlier=out,
        camera_names=prob.calibration.names, fps=prob.options.fps, report=report, options=prob.options,
        param_names=list(sk.param_names) if params is not None else [], params=params, rates=rates,
        params_std=params_std, causal_positions=causal_positions, bones=list(sk.bones),
        camera_centers=np.stack([c.center for c in prob.calibration.cameras]))


NOISE_MISMATCH = 1.5  # measured / assumed noise beyond this factor (either way) gets a warning


def measured_scatter(method: str, res_px: np.ndarray, ncams: np.ndarray) -> float:
    """The detections' noise (px) measured from the residuals ``res_px`` (C, N, M) of the estimate."""
    dof = triangulation_dof(ncams)[None] if method == "tri" else 1.0
    return scatter_px(res_px, dof)


def noise_mismatch(method: str, option, sigma_px: float, noise_px: float) -> str | None:
    """A one-line warning when a smoother was given a detection noise far from the measured one."""
    if method == "tri" or option == "auto" or not (np.isfinite(noise_px) and noise_px > 0):
        return None
    ratio = noise_px / sigma_px
    if 1.0 / NOISE_MISMATCH <= ratio <= NOISE_MISMATCH:
        return None
    how = f"{ratio:.2g}x too small" if ratio > 1 else f"{1 / ratio:.2g}x too large"
    px = f"{noise_px:.1f}" if noise_px >= 1 else f"{noise_px:.2g}"
    return (f"the detections scatter {px} px about the estimate, not the {sigma_px:g} px assumed: the 3D "
            f"standard deviations are about {how}; set the detection noise to {px} px or 'auto'")
