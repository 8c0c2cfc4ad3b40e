"""Assemble a :class:`graph.types.Result` from a solver's arrays, with the diagnostics every method shares.

Reprojection RMSE is over the detections used (valid and not flagged as outliers):
``sqrt(mean |uv - z|^2)`` in pixels. The measured noise is :func:`graph.solve.noise.scatter_px` of the
residuals (for ``tri`` scaled for the three coordinates each point took); when it is far from the
sigma a smoother assumed, the report says so: the 3D standard deviations scale with that sigma.
"""

from __future__ import annotations

import warnings

import numpy as np

from graph.solve.noise import scatter_px, triangulation_dof
from graph.solve.problem import Problem
from graph.types import Result, SolveReport


def build_result(prob: Problem, method: str, *, positions, std, reprojections, s, outlier, seconds, iterations,
                 cost=float("nan"), sigma_px: float | None = None, params=None, params_std=None,
                 causal_positions=None, per_frame_ms=None, bounds_active=0, report: dict | None = None,
                 rates=None) -> Result:
    """``s`` and ``outlier`` are (N, C, M); ``reprojections`` (C, N, M, 2). ``sigma_px`` is the
    detection noise ``s`` is normalised by (default: the problem's); ``report`` more report fields
    (the body's lengths, the cameras' offsets) and their ``warnings``. ``rates`` (N, P): the
    parameters' rates, default their central differences."""
    sk = prob.skeleton
    valid = prob.valid
    sigma_px = prob.sigma_px if sigma_px is None else sigma_px
    rel_px = np.where(valid, s * sigma_px, np.nan).transpose(1, 0, 2)  # (C, N, M) in units of sigma_px
    res_px = rel_px if prob.noise_scale is None else rel_px * prob.noise_scale[:, None, :]  # pixels
    out = (outlier & valid).transpose(1, 0, 2)
    used = np.isfinite(res_px) & ~out
    rmse = float(np.sqrt(np.mean(res_px[used] ** 2))) if used.any() else float("nan")
    seen = valid.sum(axis=1)  # cameras that saw each marker
    ncams = prob.views()  # the same, cameras at one place counted once: 0 or 1 flags the motion model's answer
    with np.errstate(invalid="ignore", divide="ignore"):
        score = np.where(seen > 0, (prob.likelihood * valid).sum(axis=1) / np.maximum(seen, 1), 0.0)
    noise = measured_scatter(method, rel_px, seen)
    notes = list(prob.warnings)
    if prob.window is None:  # a window's inputs and answer are checked with the whole run's
        misfit = inputs_misfit(out, valid.transpose(1, 0, 2), prob.calibration.names)
        # when the inputs do not fit, the scatter is the misfit's, and more noise would only hide it
        mismatch = None
        if not misfit:
            held = held_out_check(prob, method, sigma_px, noise)
            mismatch = noise_mismatch(method, prob.options.measurement_std_px, sigma_px, noise, held)
        motion = implausible_motion(positions, prob.options.fps)
        for note in (misfit, mismatch, motion):
            if note:
                notes.append(note)
                warnings.warn(note, stacklevel=3)
    extra = dict(report or {})
    if prob.noise_scale is not None:
        extra["relative_noise"] = {name: float(np.median(prob.noise_scale[c]))
                                   for c, name in enumerate(prob.calibration.names)}
    for note in extra.pop("warnings", []):
        notes.append(note)
        warnings.warn(note, stacklevel=3)
    um, uf = prob.unconstrained()
    if rates is None and params is not None and params.shape[0] > 1:
        rates = np.gradient(params, prob.dt, axis=0)
    summary = SolveReport(
        method=method, skeleton=sk.name, frames=prob.frames, cameras=prob.cameras, markers=len(sk.markers),
        seconds={"total": 0.0, **{k: float(v) for k, v in seconds.items()}},
        iterations=int(iterations), cost=float(cost), reprojection_rmse_px=rmse, per_frame_ms=per_frame_ms,
        outliers=int(out.sum()), observations=int(valid.sum()), unconstrained_markers=um,
        unconstrained_frames=uf, bounds_active=int(bounds_active), sigma_px=float(sigma_px), noise_px=noise,
        warnings=notes, **extra)
    return Result(
        method=method, skeleton=sk.name, markers=list(sk.markers), positions=positions, std=std,
        reprojections=reprojections, residuals=res_px, ncams=ncams, score=score, outlier=out,
        camera_names=prob.calibration.names, fps=prob.options.fps, report=summary, options=prob.options,
        param_names=list(sk.param_names) if params is not None else [], params=params, rates=rates,
        params_std=params_std, causal_positions=causal_positions, bones=list(sk.bones),
        camera_centers=np.stack([c.center for c in prob.calibration.cameras]),
        detections=prob.meas.transpose(1, 0, 2, 3), likelihood=prob.likelihood.transpose(1, 0, 2))


MISFIT_REJECTED = 0.25  # a camera with this share of its detections rejected does not fit the others


def inputs_misfit(outlier: np.ndarray, valid: np.ndarray, names: list[str]) -> str | None:
    """A one-line warning when some cameras' detections do not fit the rest: ``outlier`` and
    ``valid`` (C, N, M). The robust loss rejects a detection beyond 10 sigma of the estimate; DLC's
    confident mistakes make that a few per cent of a camera's detections (2-3 % on simulated runs
    with 10 % outliers, none on the real fly recording), while keypoint files given in the wrong
    camera order, or a calibration of another rig, leave 45-100 % of the affected cameras'
    detections rejected. A camera at :data:`MISFIT_REJECTED` or more is named."""
    used = valid.sum(axis=(1, 2))
    rate = outlier.sum(axis=(1, 2)) / np.maximum(used, 1)
    bad = [c for c in range(len(rate)) if used[c] > 0 and rate[c] >= MISFIT_REJECTED]
    if not bad:
        return None
    which = ", ".join(f"{names[c] if c < len(names) else c + 1} ({rate[c]:.0%})" for c in bad)
    total = int(outlier.sum())
    return (f"the inputs do not fit together: {total} of {int(used.sum())} detections were rejected, most of "
            f"them in {which}; likely causes: keypoint files not in the calibration's camera order, a "
            f"calibration of another rig or session, or cameras out of sync")


MAX_BODY_LENGTHS_PER_S = 100.0  # faster than any animal's markers move (95th percentile of speeds)
LOW_FPS = 15.0  # below the frame rates pose is filmed at
STEP_SPAN = 5
MIN_STEP_AT_LOW_FPS = 0.02  # a moving animal filmed this slowly moves more than this share of its size a frame


def implausible_motion(positions: np.ndarray, fps: float) -> str | None:
    """A one-line warning when the motion in ``positions`` (N, M, 3) is implausible at ``fps``: a
    frame rate given wrong, which scales every speed and the motion model with it.

    The animal's size ``L`` is the median over frames of twice the largest distance of a marker from
    the markers' centroid; speeds are ``|X_{n+1} - X_n| fps``. Two checks, in body lengths:

    * too fast: the 95th percentile of the speeds over :data:`MAX_BODY_LENGTHS_PER_S` (a galloping
      cheetah's markers reach 15-30 L/s): the rate given is higher than the camera's;
    * too little motion a frame for a slow rate: ``fps`` under :data:`LOW_FPS` while the median
      marker moves less than :data:`MIN_STEP_AT_LOW_FPS` of ``L`` a frame, as in a video of a
      hundred frames a second or more (``--fps 3`` typed for 300). The step is taken over
      :data:`STEP_SPAN` frames, ``|X_{n+k} - X_n| / k``, so that a triangulation's jitter does not
      pass for motion."""
    X = np.asarray(positions, dtype=np.float64)
    if X.ndim != 3 or X.shape[0] < 3 or X.shape[1] < 2:
        return None
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # frames with no estimate: NaN
        centre = np.nanmean(X, axis=1, keepdims=True)
        size = 2.0 * float(np.nanmedian(np.nanmax(np.linalg.norm(X - centre, axis=-1), axis=1)))
        step = np.linalg.norm(np.diff(X, axis=0), axis=-1)
        k = min(STEP_SPAN, X.shape[0] - 1)
        span = np.linalg.norm(X[k:] - X[:-k], axis=-1) / k
    step, span = step[np.isfinite(step)], span[np.isfinite(span)]
    if not (np.isfinite(size) and size > 0) or step.size < 10 or span.size < 10:
        return None
    fast = float(np.percentile(step, 95)) * fps / size
    if fast > MAX_BODY_LENGTHS_PER_S:
        return (f"the markers move at {fast:.0f} body lengths a second at {fps:g} fps (95th percentile), faster "
                f"than animals move: is the frame rate lower than {fps:g}?")
    moved = float(np.median(span)) / size
    if fps < LOW_FPS and moved < MIN_STEP_AT_LOW_FPS:
        return (f"at {fps:g} fps the markers move only {moved:.1%} of the animal's size a frame, as in a video "
                f"of a hundred frames a second or more: is the frame rate higher than {fps:g}? (ignore this "
                f"for a still animal)")
    return None


NOISE_MISMATCH = 1.5  # measured / assumed noise beyond this factor (either way) gets a warning


def measured_scatter(method: str, res_px: np.ndarray, ncams: np.ndarray) -> float:
    """The detections' noise (px) measured from the residuals ``res_px`` (C, N, M) of the estimate."""
    dof = triangulation_dof(ncams)[None] if method == "tri" else 1.0
    return scatter_px(res_px, dof)


def _px(value: float) -> str:
    return f"{value:.1f}" if value >= 1 else f"{value:.2g}"


def held_out_check(prob: Problem, method: str, sigma_px: float, noise_px: float) -> float | None:
    """The noise the cameras held out accept (:func:`graph.solve.disagreement.held_out_noise`), where
    :func:`noise_mismatch` would advise a smaller noise for ``tri`` (the check is triangulation's own
    prediction); None where it is not needed."""
    option = prob.options.measurement_std_px
    if option == "auto" or method != "tri" or not (np.isfinite(noise_px) and noise_px * NOISE_MISMATCH < sigma_px):
        return None
    from graph.solve.disagreement import held_out_noise

    return held_out_noise(prob.calibration, prob.meas, prob.valid, prob.sigma_px)


def noise_mismatch(method: str, option, sigma_px: float, noise_px: float, held_px: float | None = None) -> str | None:
    """A one-line warning when a solve was given a detection noise far from the measured one.

    The scatter ``noise_px`` sees only how the cameras agree with each other about the estimate they
    make together; an error a camera makes on its own (its calibration, its detector's bias) hides in
    it, so a noise smaller than the one assumed is advised only where a held-out check accepts it:
    ``held_px``, the noise at which 90 % of each camera's detections fall inside the 90 % ellipse of
    its prediction from the other cameras (:func:`graph.solve.disagreement.held_out_noise`). That is
    ``tri``'s own prediction (on the fly recording, tri's held-out ``in 90 %`` share at it was 0.90:
    bench/RESULTS.md), and too small for a smoother, whose ellipses are narrower (fte at the same
    2.0 px: 0.72; at the scatter's 1.4 px, 0.58; at 5 px, 0.95): a smoother is told the scatter and
    how to judge a smaller noise, not to take it. A larger noise is advised as measured (the 3D
    standard deviations grow with it)."""
    if option == "auto" or not (np.isfinite(noise_px) and noise_px > 0):
        return None
    ratio = noise_px / sigma_px
    if 1.0 / NOISE_MISMATCH <= ratio <= NOISE_MISMATCH:
        return None
    px = _px(noise_px)
    said = f"the detections scatter {px} px about the estimate, not the {sigma_px:g} px assumed"
    if ratio > 1:
        return (f"{said}: the 3D standard deviations are about {ratio:.2g}x too small (set the detection noise "
                f"to {px} px or 'auto')")
    if held_px is not None:
        if not (np.isfinite(held_px) and held_px * NOISE_MISMATCH < sigma_px):
            return None  # the cameras held out accept the noise assumed
        return (f"{said}, and the cameras held out (each predicted from the others) accept {_px(held_px)} px: "
                f"the 3D standard deviations are about {sigma_px / held_px:.2g}x too large (set the detection "
                f"noise to {_px(held_px)} px)")
    return (f"{said}: if the cameras agree with each other that well, the 3D standard deviations are about "
            f"{1 / ratio:.2g}x too large; but a scatter does not see a camera's own errors (its calibration, its "
            f"detector's bias), so judge a smaller noise before setting it: acinoset evaluate loco with it, its "
            f"'in 90 %' column near 0.9")
