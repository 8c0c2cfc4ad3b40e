"""A long run solved in overlapping windows, in memory that does not grow with the run
(``--method fte`` above :data:`graph.types.WINDOWED_ABOVE` frames, or ``window_frames`` given).

The whole-trajectory cost of :mod:`graph.solve.fte` couples frames only through the motion
prior's k-th differences (a band of k + 1 frames) and through what every frame shares: the
detection noise when measured, the motion scales when fitted, and, in :mod:`graph.solve.joint`,
the body's lengths and the cameras' clocks. So:

1. **What every frame shares, settled once.** The run's best-seen stretch of
   ``settle_frames`` frames (the one with the most confident detections among starts every
   quarter of it) is solved with the options as given. What it measured or estimated is then
   held for every window, as a user holds an earlier run's report for the next runs: the noise
   (``measurement_std_px``), the motion scales and orders (``motion_scale`` / ``motion_order``
   as the report's dicts), the body (``body="given"`` with its lengths) and the clocks
   (``sync="given"`` with its offsets).

2. **Windows with margins.** The frames are cut into cores of ``L`` frames; core
   ``[a, b)`` is solved as the frames ``[a - P, b + P)`` (clipped to the run) and only the core is
   kept. Given the held unknowns, the solve is a smoother on a chain: a frame ``d`` frames from a
   window's edge feels the missing data beyond it through the chain's correlation, which falls
   like ``rho^d`` with ``rho < 1`` set by how stiff the motion prior is against the data (a few
   frames to a few tens at the fitted scales). At ``P`` frames from the edge the core differs
   from the whole solve by ``rho^P`` of the edge's own change (bench/RESULTS.md, section 21:
   measured against the whole solve with the same held unknowns). The robust loss's weights are
   per detection, so they follow the same estimate in both.

3. **One result.** The cores' positions, sds, reprojections, residuals, rejections and poses are
   put end to end and the report is made over the whole run (:func:`graph.solve.result.build_result`),
   with the settled values, the windows' seconds and iterations summed, and ``windows``:
   ``{count, core_frames, margin_frames, settled_on, held}``.

Memory: one window's normal equations, marginals and kernels' scratch at a time, plus the
run's inputs and outputs (about 7 KB a frame for six cameras and 20 markers, against the whole
solve's 180 KB).
"""

from __future__ import annotations

import re
import time
import warnings
from dataclasses import replace
from typing import NamedTuple

import numpy as np

from graph.solve.joint import solve_fte_joint
from graph.solve.problem import Problem
from graph.solve.result import build_result
from graph.types import WINDOW_FRAMES, WINDOWED_ABOVE, Progress, ProgressCallback, Result, SolveOptions

MARGIN_FRAMES = 200  # frames solved on each side of a core and thrown away
SETTLE_FRAMES = 2000  # the stretch the shared unknowns are settled on


def solve_fte_windowed(prob: Problem, progress: ProgressCallback | None = None) -> Result:
    """``--method fte``: the whole trajectory (:func:`graph.solve.joint.solve_fte_joint`) when the
    run is short or ``window_frames`` is 0, else in windows (module docstring)."""
    core = prob.options.window_frames
    if core is None:
        core = WINDOW_FRAMES if prob.frames > WINDOWED_ABOVE else 0
    if core == 0 or prob.frames <= core:
        return solve_fte_joint(prob, progress)
    return solve_in_windows(prob, core, progress=progress)


def frames_of(prob: Problem, a: int, b: int, options: SolveOptions | None = None,
              sigma_px: float | None = None) -> Problem:
    """The frames ``[a, b)`` of ``prob`` as a problem of their own, with ``options`` (default the
    problem's) and detection noise ``sigma_px`` (default the problem's)."""
    return replace(prob, meas=prob.meas[a:b], likelihood=prob.likelihood[a:b], valid=prob.valid[a:b],
                   options=options or prob.options, sigma_px=prob.sigma_px if sigma_px is None else sigma_px,
                   warnings=[], window=(a, b))


def best_seen(valid: np.ndarray, length: int) -> int:
    """The start of the ``length`` frames with the most confident detections in ``valid``
    (N, C, M), among starts every quarter of ``length`` and the last one."""
    N = valid.shape[0]
    if length >= N:
        return 0
    counts = np.concatenate([[0], np.cumsum(valid.sum(axis=(1, 2)))])
    starts = np.unique(np.r_[np.arange(0, N - length + 1, max(length // 4, 1)), N - length])
    seen = counts[starts + length] - counts[starts]
    return int(starts[int(np.argmax(seen))])


def held_options(options: SolveOptions, settled: Result) -> tuple[SolveOptions, dict]:
    """``options`` with what the solve ``settled`` measured or estimated held (module docstring,
    step 1), and those values as the report's ``windows.held``."""
    rep = settled.report
    change: dict = {}
    if options.measurement_std_px == "auto":
        change["measurement_std_px"] = float(rep.sigma_px)
    if options.motion_scale == "auto" and rep.motion_scales:
        change["motion_scale"] = dict(rep.motion_scales)
        if rep.motion_orders:
            change["motion_order"] = dict(rep.motion_orders)
    if options.body == "estimate" and rep.body_lengths:
        change["body"] = "given"
        change["body_lengths"] = {k: float(v["length_m"]) for k, v in rep.body_lengths.items()}
    if options.sync == "estimate" and rep.time_offsets_frames is not None:
        change["sync"] = "given"
        change["time_offsets"] = [float(t) for t in rep.time_offsets_frames]
    return replace(options, window_frames=0, **change), change


class Settled(NamedTuple):
    """What every window holds (module docstring, step 1): the ``options`` to solve them with, the
    detection noise ``sigma_px``, the values held (``held``: the options changed) and the stretch
    ``[start, stop)`` they were settled on, with its ``result``."""

    options: SolveOptions
    sigma_px: float
    held: dict
    start: int
    stop: int
    result: Result


def settle(prob: Problem, frames: int) -> Settled:
    """Solve the best-seen ``frames`` of ``prob`` with its options and hold what it measured or
    estimated (:func:`held_options`)."""
    o = replace(prob.options, window_frames=0)
    s0 = best_seen(prob.valid, frames)
    s1 = min(prob.frames, s0 + frames)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the settling stretch's own warnings: the whole run's are made after
        result = solve_fte_joint(frames_of(prob, s0, s1, o))
    held, values = held_options(o, result)
    return Settled(held, float(result.report.sigma_px), values, s0, s1, result)


def solve_in_windows(prob: Problem, core: int, margin: int = MARGIN_FRAMES, settle_frames: int = SETTLE_FRAMES,
                     progress: ProgressCallback | None = None, settled: Settled | None = None) -> Result:
    """``prob`` solved in windows of ``core`` kept frames and ``margin`` frames each side, with
    the shared unknowns settled on ``settle_frames`` frames (module docstring), or held as
    ``settled`` gives them."""
    t0 = time.perf_counter()
    N = prob.frames
    if progress:
        progress(Progress(stage="initialise", fraction=0.0, detail="settling what every window shares"))
    st = settled or settle(prob, settle_frames)
    starts = list(range(0, N, core))
    cores = _Cores(N)
    iterations = st.result.report.iterations
    t_windows = time.perf_counter()
    for k, a in enumerate(starts):
        b = min(N, a + core)
        lo, hi = max(0, a - margin), min(N, b + margin)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # a window's warnings are gathered into the run's (_grouped)
            r = solve_fte_joint(frames_of(prob, lo, hi, st.options, st.sigma_px))
        cores.keep(a, r, a - lo, b - lo)
        iterations += r.report.iterations
        del r  # one window's result at a time
        if progress:
            elapsed = time.perf_counter() - t_windows
            left = elapsed / (k + 1) * (len(starts) - k - 1)
            progress(Progress(stage="optimise", fraction=0.05 + 0.9 * (k + 1) / len(starts), iteration=iterations,
                              detail=f"window {k + 1} of {len(starts)}, {left:.0f} s left"))
    result = cores.result(prob, st.options, st.sigma_px, iterations, time.perf_counter() - t0)
    report = result.report
    report.windows = {"count": len(starts), "core_frames": core, "margin_frames": margin,
                      "settled_on": [st.start, st.stop], "held": st.held}
    for name in ("motion_scales", "motion_orders", "body_lengths", "time_offsets_frames", "time_offsets_std_frames",
                 "offsets_not_identified"):
        setattr(report, name, getattr(st.result.report, name))
    report.motion_only_frames = _motion_only(result)
    if progress:
        progress(Progress(stage="done", fraction=1.0, iteration=iterations))
    return result


# the arrays of a Result kept from each window's core, with their frame axis
FRAME_AXIS = {"positions": 0, "std": 0, "params": 0, "params_std": 0, "reprojections": 1, "residuals": 1, "outlier": 1}


class _Cores:
    """The windows' cores of a run of N frames, copied into arrays of the whole run as each window
    finishes (so one window's :class:`Result` is held at a time), with their costs and warnings."""

    def __init__(self, frames: int):
        self.frames = frames
        self.arrays: dict[str, np.ndarray | None] = {}
        self.cost = 0.0
        self.bounds_active = 0
        self.warnings: list[list[str]] = []

    def keep(self, at: int, r: Result, i: int, j: int) -> None:
        """Keep frames ``[i, j)`` of the window's result ``r`` as the run's frames from ``at``."""
        for name, axis in FRAME_AXIS.items():
            a = getattr(r, name)
            if at == 0:
                shape = list(a.shape) if a is not None else None
                if shape is not None:
                    shape[axis] = self.frames
                self.arrays[name] = np.empty(shape, dtype=a.dtype) if a is not None and shape else None
            out = self.arrays[name]
            if out is not None:
                index = [slice(None)] * out.ndim
                index[axis] = slice(at, at + j - i)
                src = [slice(None)] * out.ndim
                src[axis] = slice(i, j)
                out[tuple(index)] = a[tuple(src)]
        self.cost += r.report.cost  # the windows' costs (their margins counted twice)
        self.bounds_active += r.report.bounds_active
        self.warnings.append(r.report.warnings)

    def result(self, prob: Problem, options: SolveOptions, sigma_px: float, iterations: int,
               solve_s: float) -> Result:
        """One :class:`Result` of the whole run, its report made over the whole
        (:func:`graph.solve.result.build_result`)."""
        whole = replace(prob, options=options, sigma_px=sigma_px)
        A = self.arrays
        residuals, outlier = A["residuals"], A["outlier"]  # (C, N, M)
        assert residuals is not None and outlier is not None
        residuals /= sigma_px * (whole.noise_scale[:, None, :] if whole.noise_scale is not None else 1.0)
        s = residuals.transpose(1, 0, 2)  # in place: the run's residuals in units of the noise
        return build_result(whole, "fte", positions=A["positions"], std=A["std"], reprojections=A["reprojections"],
                            s=s, outlier=outlier.transpose(1, 0, 2), seconds={"init": 0.0, "solve": solve_s},
                            iterations=iterations, cost=self.cost, sigma_px=sigma_px, params=A["params"],
                            params_std=A["params_std"], bounds_active=self.bounds_active,
                            report={"warnings": _grouped(self.warnings)})


def _grouped(said: list[list[str]]) -> list[str]:
    """The windows' warnings, one of each kind (the same words, whatever numbers) with the number
    of windows that gave it: the first one's text, and ``(in n of K windows)``."""
    first: dict[str, str] = {}
    count: dict[str, int] = {}
    for texts in said:
        for kind, text in {re.sub(r"[0-9.]+", "#", t): t for t in texts}.items():
            first.setdefault(kind, text)
            count[kind] = count.get(kind, 0) + 1
    return [f"{text} (in {count[kind]} of {len(said)} windows)" for kind, text in first.items()]


def _motion_only(result: Result) -> dict[str, int]:
    """Per marker, the frames answered from the motion model alone (fewer than two cameras saw it)."""
    alone = (result.ncams < 2) & np.isfinite(result.positions).all(axis=-1)
    return {m: int(k) for m, k in zip(result.markers, alone.sum(axis=0)) if k}
