"""A long run solved in overlapping windows, in memory that does not grow with the run
(``--method fte`` or ``ekf`` above :data:`graph.types.WINDOWED_ABOVE` frames, or ``window_frames`` given).

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

   ``ekf`` is windowed the same way, its margin ``P`` its lag's frames more (:func:`margin_frames`),
   but one window after another: each later window's stream (:func:`graph.solve.online.solve_ekf`)
   starts from the poses the window before gave its first frames (inside that one's core), with the
   held values, and the core is kept: its first frame is ``P`` frames into the stream and its last
   ``P`` frames before the window's end, beyond the stream's lag, so the core follows the whole
   stream given the same held values (within 0.1 mm on the test's walking cheetah). Started afresh
   instead, a window that began where one camera alone saw the animal started with no depth and kept
   that for its whole core (bench/probe_ekf_windows.py: 8-15x the whole stream's error). What every frame
   shares is settled by ``fte`` on the best-seen stretch for both methods (the whole-run ``ekf``
   settles it on its first seconds instead).

3. **One result.** The cores' positions, sds, reprojections, residuals, rejections and poses are
   put end to end and the report is made over the whole run (:func:`graph.solve.result.build_result`),
   with the settled values, the windows' seconds and iterations summed, and ``windows``:
   ``{count, core_frames, margin_frames, settled_on, held}``.

Memory: one window's normal equations, marginals and kernels' scratch at a time. Held in memory
(:func:`solve_in_windows`), the run's inputs and outputs come on top (about 12 KB a frame for six
cameras and 20 markers, against the whole solve's 170 KB); streamed (:func:`solve_streamed` of a run
staged on disk, :class:`Staged`: ``acinoset solve`` and the service's long jobs), no array of the
run's is held: 597, 631 and 637 MiB for 1, 10 and 60 minutes at 120 fps (bench/RESULTS.md, section 21;
what still grows is small: the frames no camera pair saw, a few warnings a window).
"""

from __future__ import annotations

import itertools
import re
import time
import warnings
from collections import deque
from collections.abc import Callable, Iterator
from concurrent.futures.process import BrokenProcessPool
from dataclasses import replace
from pathlib import Path
from typing import NamedTuple, Protocol

import numpy as np

from graph.camera import Calibration
from graph.errors import InputError, WorkerLost
from graph.io.staged import StagedRun
from graph.solve import problem
from graph.solve.joint import solve_fte_joint
from graph.solve.problem import Problem, frames_of
from graph.solve.result import build_result
from graph.types import (
    FRAME_AXIS,
    WINDOW_FRAMES,
    WINDOWED_ABOVE,
    WINDOWED_METHODS,
    Progress,
    ProgressCallback,
    Result,
    SolveOptions,
    SolveReport,
    jsonable,
)

MARGIN_FRAMES = 200  # frames solved on each side of a core and thrown away (ekf: and its lag, margin_frames)
SETTLE_FRAMES = 2000  # the stretch the shared unknowns are settled on


def one_stream(options: SolveOptions) -> bool:
    """Whether a run's windows are one stream, solved in turn, each from the one before (``ekf``),
    rather than each on its own, anywhere (``fte``: in worker processes, or by other workers)."""
    return options.method == "ekf"


def margin_frames(options: SolveOptions) -> int:
    """Frames solved each side of a window's core: :data:`MARGIN_FRAMES`; for ``ekf``, its lag's
    frames more (the core's last frame is final only ``lag_seconds`` into the stream after it)."""
    if one_stream(options):
        return MARGIN_FRAMES + int(np.ceil(options.lag_seconds * options.fps))
    return MARGIN_FRAMES


def solve_windowed(prob: Problem, progress: ProgressCallback | None = None) -> Result:
    """``--method fte`` and ``ekf``: the whole run at once (:func:`graph.solve.joint.solve_fte_joint`,
    :func:`graph.solve.online.solve_ekf`) when it is short or ``window_frames`` is 0, else in windows
    (module docstring)."""
    core = prob.options.window_frames
    if core is None:
        core = WINDOW_FRAMES if prob.frames > WINDOWED_ABOVE else 0
    if core == 0 or prob.frames <= core:
        return solve_whole(prob, progress)
    return solve_in_windows(prob, core, progress=progress)


def solve_whole(prob: Problem, progress: ProgressCallback | None = None) -> Result:
    """``prob`` solved at once by its method, ``fte`` or ``ekf`` (a window is solved so too)."""
    if prob.options.method == "ekf":
        from graph.solve.online import solve_ekf

        return solve_ekf(prob, progress)
    if prob.options.method not in WINDOWED_METHODS:
        raise ValueError(f"a run is solved in windows by {' or '.join(WINDOWED_METHODS)}, not {prob.options.method!r}")
    return solve_fte_joint(prob, progress)


class Frames(Protocol):
    """Where a windowed solve takes a run's frames from: a :class:`Problem` in memory
    (:class:`InMemory`), or a run staged on disk (:class:`Staged`)."""

    @property
    def frames(self) -> int: ...

    @property
    def options(self) -> SolveOptions: ...

    def seen(self) -> np.ndarray:
        """The confident detections in each frame (N,)."""
        ...

    def stretch(self, a: int, b: int, options: SolveOptions) -> Problem:
        """Frames ``[a, b)`` solved with ``options`` as given: the stretch the shared unknowns are settled on."""
        ...

    def window(self, a: int, b: int, options: SolveOptions, sigma_px: float) -> Problem:
        """Frames ``[a, b)`` with the held ``options`` and noise ``sigma_px``: one window."""
        ...


class InMemory:
    """The frames of a :class:`Problem` built whole (:func:`frames_of`)."""

    def __init__(self, prob: Problem):
        self.prob = prob

    @property
    def frames(self) -> int:
        return self.prob.frames

    @property
    def options(self) -> SolveOptions:
        return self.prob.options

    def seen(self) -> np.ndarray:
        return self.prob.valid.sum(axis=(1, 2))

    def stretch(self, a: int, b: int, options: SolveOptions) -> Problem:
        return frames_of(self.prob, a, b, options)

    def window(self, a: int, b: int, options: SolveOptions, sigma_px: float) -> Problem:
        return frames_of(self.prob, a, b, options, sigma_px)


class Staged:
    """The frames of a run staged on disk (:class:`graph.io.staged.StagedRun`), read a window at a
    time. The settled stretch is built and checked as a run of its own (:func:`graph.solve.problem.build`:
    the noise measured on it, when ``"auto"``, and an ensemble's relative noise), and every window
    takes its skeleton, rig and noise (:func:`graph.solve.problem.window_of`)."""

    BLOCK = 8192  # frames read at a time to count the confident detections

    def __init__(self, run: StagedRun, calibration: Calibration, options: SolveOptions):
        self.run, self.calibration, self.options = run, calibration, options
        self.skeleton = problem.skeleton_of([cam.bodyparts for cam in run.cameras], options)
        self._template: Problem | None = None

    @property
    def frames(self) -> int:
        return self.run.frames

    def seen(self) -> np.ndarray:
        t = self.options.likelihood_threshold
        return np.concatenate([problem.confident(self.run.keypoints(a, a + self.BLOCK), self.skeleton, t)
                               for a in range(0, self.frames, self.BLOCK)])

    def stretch(self, a: int, b: int, options: SolveOptions) -> Problem:
        prob = replace(problem.build(self.run.keypoints(a, b), self.calibration, options), window=(a, b))
        self._template = prob
        return prob

    def window(self, a: int, b: int, options: SolveOptions, sigma_px: float) -> Problem:
        if self._template is None:
            raise RuntimeError("a staged run's windows come after its settled stretch (settle)")
        template = replace(self._template, options=options, sigma_px=sigma_px)
        return problem.window_of(template, self.run.keypoints(a, b), (a, b))


def best_seen(seen: np.ndarray, length: int) -> int:
    """The start of the ``length`` frames with the most confident detections, ``seen`` (N,) a frame,
    among starts every quarter of ``length`` and the last one."""
    N = seen.shape[0]
    if length >= N:
        return 0
    counts = np.concatenate([[0], np.cumsum(seen)])
    starts = np.unique(np.r_[np.arange(0, N - length + 1, max(length // 4, 1)), N - length])
    total = counts[starts + length] - counts[starts]
    return int(starts[int(np.argmax(total))])


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
    if options.swap_rate == "auto" and rep.swap_rate is not None:
        change["swap_rate"] = float(rep.swap_rate)
    if options.sync == "estimate" and rep.time_offsets_frames is not None:
        change["sync"] = "given"
        change["time_offsets"] = [float(t) for t in rep.time_offsets_frames]
    return replace(options, window_frames=0, **change), change


class Settled(NamedTuple):
    """What every window holds (module docstring, step 1): the ``options`` to solve them with, the
    detection noise ``sigma_px``, the values held (``held``: the options changed) and the stretch
    ``[start, stop)`` they were settled on, with its ``problem`` and ``result``."""

    options: SolveOptions
    sigma_px: float
    held: dict
    start: int
    stop: int
    result: Result
    problem: Problem


def settle(source: Frames | Problem, frames: int) -> Settled:
    """Solve the best-seen ``frames`` of ``source`` (a :class:`Problem`'s options, or the options of
    the run it stages) with its options and hold what it measured or estimated (:func:`held_options`)."""
    src = InMemory(source) if isinstance(source, Problem) else source
    s0 = best_seen(src.seen(), frames)
    s1 = min(src.frames, s0 + frames)
    # an ekf's stream is a constant-acceleration filter: its smoothing is fitted for the third differences
    o = replace(src.options, window_frames=0)
    stretch = src.stretch(s0, s1, replace(o, motion_order=3) if o.method == "ekf" else o)
    o = stretch.options  # as the problem resolved them (the skeleton's default motion scale)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the settling stretch's own warnings: the whole run's are made after
        result = solve_fte_joint(stretch)
    held, values = held_options(o, result)
    return Settled(held, float(result.report.sigma_px), values, s0, s1, result, stretch)


# solves a run's windows elsewhere too (:class:`Windows`' ``solver``): given the run, the windows' frames
# ``[lo, hi)`` and what they hold (:class:`Settled`), each window's Result and confident detections
# (n, C, M) (:func:`solve_window`'s), in the spans' order
WindowSolver = Callable[["Frames", list[tuple[int, int]], Settled], Iterator[tuple[Result, np.ndarray]]]


class Core(NamedTuple):
    """One window's kept frames: the run's frames from ``at``, their :class:`Result` (its report the
    window's) and confident detections ``valid`` (n, C, M)."""

    at: int
    result: Result
    valid: np.ndarray


class Windows:
    """The windows of a run (module docstring), solved one at a time as they are iterated, each
    giving its :class:`Core`; what they add up to (iterations, cost, bounds, warnings) is kept here."""

    def __init__(self, source: Frames, core: int, margin: int | None = None, settle_frames: int = SETTLE_FRAMES,
                 progress: ProgressCallback | None = None, settled: Settled | None = None, jobs: int = 1,
                 solver: WindowSolver | None = None):
        margin = margin_frames(source.options) if margin is None else margin
        if margin < 1:
            raise ValueError(f"a window needs at least one frame of margin, not {margin}")
        self.source, self.core, self.margin, self.progress, self.jobs = source, core, margin, progress, jobs
        self.solver = solver
        if progress:
            progress(Progress(stage="initialise", fraction=0.0, detail="settling what every window shares"))
        self.settled = settled or settle(source, settle_frames)
        self.starts = list(range(0, source.frames, core))
        self.done = 0  # windows finished
        self.last: list[float] | None = None  # the last kept frame's angles
        self.iterations = self.settled.result.report.iterations
        self.cost = 0.0
        self.bounds_active = 0
        self.side_swaps = 0  # the windows' left/right swaps (their margins counted twice, as the cost)
        self.warnings: list[list[str]] = []
        self.per_frame: list[dict] = []  # ekf: each window's stream's time a frame (its report's per_frame_ms)
        self.start: list | None = None  # ekf: the next window's first poses, from this one's stream

    def state(self) -> dict:
        """Where the windows stand, as JSON values: the windows finished, the last kept frame's angles
        and what they added up to (:meth:`restore` goes on from there)."""
        return {"done": self.done, "last": self.last, "iterations": self.iterations, "cost": self.cost,
                "bounds_active": self.bounds_active, "side_swaps": self.side_swaps, "warnings": self.warnings,
                "per_frame": self.per_frame, "start": self.start, "held": jsonable(self.settled.held)}

    def restore(self, state: dict) -> None:
        """Go on from :meth:`state` of the same run: ValueError when the values the windows hold are not
        the ones held then."""
        if jsonable(self.settled.held) != state["held"]:
            raise ValueError("the values settled for every window came out other than when the run stopped")
        self.done, self.iterations = int(state["done"]), int(state["iterations"])
        self.last = None if state["last"] is None else [float(v) for v in state["last"]]
        self.cost, self.bounds_active = float(state["cost"]), int(state["bounds_active"])
        self.side_swaps = int(state.get("side_swaps", 0))
        self.warnings = [[str(w) for w in ws] for ws in state["warnings"]]
        self.per_frame = [{str(k): float(v) for k, v in d.items()} for d in state.get("per_frame", [])]
        self.start = state.get("start")

    def __iter__(self) -> Iterator[Core]:
        st, N, t0 = self.settled, self.source.frames, time.perf_counter()
        angles, first = st.problem.skeleton.angle_params, self.done
        for k, (r, valid) in zip(range(first, len(self.starts)), self._solved(first)):
            a = self.starts[k]
            b = min(N, a + self.core)
            lo = max(0, a - self.margin)
            if r.params is not None and angles.size:
                if self.last is not None:  # the same turn as the core before: an angle may end a window 2 pi apart
                    turns = np.round((np.asarray(self.last) - r.params[a - lo - 1, angles]) / (2 * np.pi))
                    r.params[:, angles] += 2 * np.pi * turns
                self.last = r.params[b - lo - 1, angles].tolist()
            self.iterations += r.report.iterations
            self.cost += r.report.cost  # the windows' costs (their margins counted twice)
            self.bounds_active += r.report.bounds_active
            self.side_swaps += r.report.side_swaps
            self.warnings.append(r.report.warnings)
            if r.report.per_frame_ms:
                self.per_frame.append(dict(r.report.per_frame_ms))
            core = Core(a, r.frames(a - lo, b - lo), valid[a - lo:b - lo])
            del r, valid  # one window at a time
            self.done = k + 1
            yield core
            del core
            if self.progress:
                left = (time.perf_counter() - t0) / (k + 1 - first) * (len(self.starts) - k - 1)
                self.progress(Progress(stage="optimise", fraction=0.05 + 0.9 * (k + 1) / len(self.starts),
                                       iteration=self.iterations,
                                       detail=f"window {k + 1} of {len(self.starts)}, {left:.0f} s left"))

    def _solved(self, first: int) -> Iterator[tuple[Result, np.ndarray]]:
        """Each window from the ``first`` solved (:func:`solve_window`), in order: by the ``solver``
        given (the job service's workers), here, or ``jobs`` at a time in worker processes
        (:func:`graph.solve.workers.window_pool`), at most ``jobs + 1`` in flight. A window's answer
        does not depend on where it was solved. ``ekf``'s windows are one stream: here, in turn, each
        starting from the poses the one before gave its first frames (``solver`` and ``jobs`` unused)."""
        st, N = self.settled, self.source.frames
        spans = [(max(0, a - self.margin), min(N, a + self.core + self.margin)) for a in self.starts[first:]]
        if one_stream(st.options):  # each window goes on from the one before, in turn
            from graph.solve.online import START_FRAMES

            for k, (lo, hi) in enumerate(spans):
                start = None if self.start is None else np.asarray(self.start, dtype=np.float64)
                r, valid = solve_window(self.source, lo, hi, st.options, st.sigma_px, start)
                if k + 1 < len(spans) and r.params is not None:
                    nxt = spans[k + 1][0] - lo  # inside this window's core (the margin is shorter than it)
                    self.start = r.params[nxt:nxt + START_FRAMES].tolist()
                yield r, valid
            return
        if self.solver is not None:
            yield from self.solver(self.source, spans, st)
            return
        if self.jobs <= 1 or len(spans) <= 1:
            for lo, hi in spans:
                yield solve_window(self.source, lo, hi, st.options, st.sigma_px)
            return
        from graph.solve.workers import window_pool

        with window_pool(self.source, self.jobs) as pool:
            flight: deque = deque()
            todo = iter(spans)
            try:
                for lo, hi in itertools.islice(todo, self.jobs + 1):
                    flight.append(pool.submit(solve_window, None, lo, hi, st.options, st.sigma_px))
                while flight:
                    done = flight.popleft().result()
                    for lo, hi in itertools.islice(todo, 1):
                        flight.append(pool.submit(solve_window, None, lo, hi, st.options, st.sigma_px))
                    yield done
            except BrokenProcessPool:
                raise WorkerLost(f"a worker process solving window {self.done + 1} of {len(self.starts)} died "
                                 "(killed, or out of memory): fewer jobs use less memory") from None

    def per_frame_ms(self) -> dict[str, float] | None:
        """ekf: the windows' times a frame put together: the median of their medians and p95s, the
        largest of their maxima."""
        if not self.per_frame:
            return None
        return {"median": float(np.median([d["median"] for d in self.per_frame])),
                "p95": float(np.median([d["p95"] for d in self.per_frame])),
                "max": float(max(d["max"] for d in self.per_frame))}

    def report(self, report: SolveReport) -> None:
        """What the windows share written into the run's ``report``: ``windows`` and the settled values."""
        st = self.settled
        report.windows = {"count": len(self.starts), "core_frames": self.core, "margin_frames": self.margin,
                          "settled_on": [st.start, st.stop], "held": st.held}
        report.side_swaps = self.side_swaps
        report.per_frame_ms = self.per_frame_ms()
        for name in ("motion_scales", "motion_orders", "body_lengths", "time_offsets_frames",
                     "time_offsets_std_frames", "offsets_not_identified", "swap_rate"):
            setattr(report, name, getattr(st.result.report, name))


def solve_window(source: Frames | None, lo: int, hi: int, options: SolveOptions,
                 sigma_px: float, start: np.ndarray | None = None) -> tuple[Result, np.ndarray]:
    """Frames ``[lo, hi)`` of ``source`` (None: a worker process's, :mod:`graph.solve.workers`) solved
    with the held ``options`` and noise: the window's :class:`Result` and confident detections (n, C, M).
    ``start``: ekf's poses of the first frames, from the window before (:class:`Windows`)."""
    if source is None:
        from graph.solve.workers import worker_source

        source = worker_source()
    prob = source.window(lo, hi, options, sigma_px)
    if start is not None:
        prob = replace(prob, start_poses=start)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # a window's warnings are gathered into the run's (grouped)
        return solve_whole(prob), prob.valid


def solve_in_windows(prob: Problem, core: int, margin: int | None = None, settle_frames: int = SETTLE_FRAMES,
                     progress: ProgressCallback | None = None, settled: Settled | None = None) -> Result:
    """``prob`` solved in windows of ``core`` kept frames and ``margin`` frames each side (default
    :func:`margin_frames`), with
    the shared unknowns settled on ``settle_frames`` frames (module docstring), or held as
    ``settled`` gives them; the cores put end to end into one :class:`Result`."""
    t0 = time.perf_counter()
    run = Windows(InMemory(prob), core, margin, settle_frames, progress, settled)
    cores = _Cores(prob.frames)
    for c in run:
        cores.keep(c.at, c.result)
    st = run.settled
    result = cores.result(prob, st.options, st.sigma_px, run, time.perf_counter() - t0)
    run.report(result.report)
    result.report.motion_only_frames = _motion_only(result)
    if progress:
        progress(Progress(stage="done", fraction=1.0, iteration=run.iterations))
    return result


def solve_streamed(source: Frames, core: int, write: Callable[[Core], None],
                   progress: ProgressCallback | None = None, resume: dict | None = None,
                   saved: Callable[[dict], None] | None = None, sample_file: str | Path | None = None,
                   jobs: int = 1, solver: WindowSolver | None = None) -> tuple[SolveReport, Settled]:
    """``source`` solved in windows of ``core`` kept frames (:class:`Windows`), each core handed to
    ``write`` as it finishes and then dropped; the run's report made from their sums
    (:class:`graph.solve.run_sums.RunSums`, its noise sample in ``sample_file`` when given), and what
    the windows held. Memory: one window, whatever the run's length.

    After each window ``saved`` (when given) gets the run's state as JSON values, and ``resume``
    (such a state) goes on from the window after it: the shared values are settled again (the same
    inputs settle to the same values, checked) and the windows done are not solved again. ``jobs``:
    windows solved at a time, in worker processes (the same answer; a staged ``source`` only);
    ``solver``: the windows solved by it instead (:data:`WindowSolver`)."""
    from graph.solve.run_sums import RunSums

    t0 = time.perf_counter()
    run = Windows(source, core, progress=progress, jobs=jobs, solver=solver)
    st = run.settled
    sums = RunSums(source.frames, st.problem.cameras, len(st.problem.markers), st.problem.noise_scale, sample_file,
                   resuming=resume is not None)
    if resume is not None:
        try:
            run.restore(resume["windows"])
            sums.restore(resume["sums"])
        except (KeyError, TypeError, ValueError, OSError) as e:
            raise InputError(f"cannot go on from the stopped run ({e}): run again from the start") from None
    for c in run:
        write(c)
        sums.add(c.at, c.result, c.valid)
        if saved is not None:
            saved({"windows": run.state(), "sums": sums.state()})
    stretch = replace(st.problem, options=st.options)
    report = sums.report(stretch, st.result, st.sigma_px, {"init": 0.0, "solve": time.perf_counter() - t0},
                         run.iterations, run.cost, run.bounds_active, grouped(run.warnings))
    run.report(report)
    if progress:
        progress(Progress(stage="done", fraction=1.0, iteration=run.iterations))
    return report, st


# the arrays of a Result kept from each window's core (the rest are made over the whole run)
# (the rates each window's own: at a seam, the central difference of the window that keeps the frame)
KEPT = ("positions", "std", "params", "rates", "params_std", "reprojections", "residuals", "outlier",
        "causal_positions")


class _Cores:
    """The windows' cores of a run of N frames, copied into arrays of the whole run as each window
    finishes (so one window's :class:`Result` is held at a time)."""

    def __init__(self, frames: int):
        self.frames = frames
        self.arrays: dict[str, np.ndarray | None] = {}

    def keep(self, at: int, r: Result) -> None:
        """Keep the core ``r`` as the run's frames from ``at``."""
        for name in KEPT:
            a, axis = getattr(r, name), FRAME_AXIS[name]
            if name not in self.arrays:
                shape = None if a is None else a.shape[:axis] + (self.frames,) + a.shape[axis + 1:]
                self.arrays[name] = None if shape is None else np.empty(shape, dtype=a.dtype)
            out = self.arrays[name]
            if out is not None:
                out[(slice(None),) * axis + (slice(at, at + a.shape[axis]),)] = a

    def result(self, prob: Problem, options: SolveOptions, sigma_px: float, run: Windows, solve_s: float) -> Result:
        """One :class:`Result` of the whole run, its report made over the whole
        (:func:`graph.solve.result.build_result`)."""
        whole = replace(prob, options=options, sigma_px=sigma_px)
        A = self.arrays
        residuals, outlier = A["residuals"], A["outlier"]  # (C, N, M)
        assert residuals is not None and outlier is not None
        residuals /= sigma_px * (whole.noise_scale[:, None, :] if whole.noise_scale is not None else 1.0)
        s = residuals.transpose(1, 0, 2)  # in place: the run's residuals in units of the noise
        return build_result(whole, options.method, positions=A["positions"], std=A["std"],
                            reprojections=A["reprojections"], s=s, outlier=outlier.transpose(1, 0, 2),
                            seconds={"init": 0.0, "solve": solve_s}, iterations=run.iterations, cost=run.cost,
                            sigma_px=sigma_px, params=A["params"], params_std=A["params_std"], rates=A["rates"],
                            causal_positions=A["causal_positions"], bounds_active=run.bounds_active,
                            report={"warnings": grouped(run.warnings)})


def grouped(said: list[list[str]]) -> list[str]:
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
    return {m: int(k) for m, k in zip(result.markers, motion_only(result)) if k}


def motion_only(result: Result) -> np.ndarray:
    """Per marker (M,), the frames of ``result`` answered from the motion model alone."""
    return ((result.ncams < 2) & np.isfinite(result.positions).all(axis=-1)).sum(axis=0)
