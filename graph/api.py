"""The library's front door: :func:`solve`, and the registry of solvers it dispatches to;
:func:`solve_group` for several individuals.

The CLI and the REST service both call ``solve(keypoints, calibration, options, progress)`` and
read a :class:`~graph.types.Result` (``solve_group``: a :class:`GroupResult`); neither reaches into
the solvers. The types live in
:mod:`graph.types` and are re-exported here.
"""

from __future__ import annotations

import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Protocol

from graph.camera import Calibration
from graph.io.keypoint_types import Tracks
from graph.io.keypoints import Keypoints
from graph.io.staged import StagedRun
from graph.solve import disagreement, problem, windows
from graph.solve.problem import Problem
from graph.solve.tri import solve_tri
from graph.solve.windows import Core, solve_windowed
from graph.types import (
    METHODS,
    WINDOW_FRAMES,
    WINDOWED_METHODS,
    Method,
    Progress,
    ProgressCallback,
    Result,
    SolveOptions,
    SolveReport,
)

if TYPE_CHECKING:
    from graph.solve.identity import Identities

__all__ = ["solve", "prepare", "solve_prepared", "solve_streamed", "solve_group", "GroupResult", "SOLVERS", "Solver",
           "METHODS", "Method", "Progress", "ProgressCallback", "Result", "SolveOptions", "SolveReport"]


class Solver(Protocol):
    def __call__(self, prob: Problem, progress: ProgressCallback | None = None) -> Result: ...


# fte: graph.solve.fte.solve_fte, with the body and the clocks as unknowns where the options ask (graph.solve.joint);
# ekf: graph.solve.online.solve_ekf; for both, a long run in windows (graph.solve.windows)
SOLVERS: dict[str, Solver] = {"tri": solve_tri, "ekf": solve_windowed, "fte": solve_windowed}
assert tuple(SOLVERS) == METHODS, "graph.types.Method and SOLVERS must name the same methods"


def solve(keypoints: list[Keypoints], calibration: Calibration, options: SolveOptions | None = None,
          progress: ProgressCallback | None = None) -> Result:
    """Estimate 3D trajectories from one :class:`Keypoints` per camera, in the calibration's order.

    After the solve, a camera whose detections sit far from where the other cameras put them is
    named in the report's warnings (:mod:`graph.solve.disagreement`; checked only when the solve's
    own residuals hint at one). Raises :class:`graph.errors.InputError` when the inputs do not fit
    together. The same as :func:`solve_prepared` of :func:`prepare`.
    """
    t0 = time.perf_counter()
    return solve_prepared(prepare(keypoints, calibration, options), progress, t0)


def prepare(keypoints: list[Keypoints], calibration: Calibration, options: SolveOptions | None = None) -> Problem:
    """The inputs checked and stacked into one problem (:func:`graph.solve.problem.build`), for
    :func:`solve_prepared`. The problem holds its own copy of the detections: a caller that drops
    its keypoints before solving holds a long run's detections once, not twice."""
    return problem.build(keypoints, calibration, options or SolveOptions())


def solve_prepared(prob: Problem, progress: ProgressCallback | None = None, t0: float | None = None) -> Result:
    """:func:`solve` of a problem from :func:`prepare` (begun at ``t0``, default now)."""
    t0 = time.perf_counter() if t0 is None else t0
    result = SOLVERS[prob.options.method](prob, progress=progress)
    _name_a_disagreeing_camera(prob, result, result.report)
    result.report.seconds["total"] = time.perf_counter() - t0
    return result


def solve_streamed(run: StagedRun, calibration: Calibration, options: SolveOptions, write: Callable[[Core], None],
                   progress: ProgressCallback | None = None, resume: dict | None = None,
                   saved: Callable[[dict], None] | None = None, sample_file: str | Path | None = None,
                   jobs: int = 1, solver: "windows.WindowSolver | None" = None) -> SolveReport:
    """A long run staged on disk (:class:`graph.io.staged.StagedRun`) solved by ``fte`` or ``ekf`` in windows of
    ``options.window_frames`` kept frames (default :data:`graph.types.WINDOW_FRAMES`), each window's
    kept frames handed to ``write`` as it finishes (a :class:`graph.solve.windows.Core`: the run's
    frame it starts at and its :class:`Result`); the run's report. Memory: one window's, whatever the
    run's length (:func:`graph.solve.windows.solve_streamed`, which also says what ``resume``,
    ``saved`` and ``sample_file`` do: a run that goes on after it was stopped; ``jobs``: windows solved
    side by side in worker processes, the same answer; ``solver``: the windows solved by it, as the
    job service's workers do). The disagreeing-camera
    check of :func:`solve` is made on the settled stretch."""
    if options.method not in WINDOWED_METHODS:
        raise ValueError(f"a run is solved streamed by {' or '.join(WINDOWED_METHODS)}, not {options.method!r}")
    t0 = time.perf_counter()
    core = options.window_frames or WINDOW_FRAMES
    report, settled = windows.solve_streamed(windows.Staged(run, calibration, options), core, write, progress,
                                             resume, saved, sample_file, jobs, solver)
    _name_a_disagreeing_camera(settled.problem, settled.result, report)
    report.seconds["total"] = time.perf_counter() - t0
    return report


def _name_a_disagreeing_camera(prob: Problem, result: Result, report: SolveReport) -> None:
    """A camera whose detections sit far from where the others put them named in ``report``'s warnings
    (:mod:`graph.solve.disagreement`), checked only when ``result``'s residuals hint at one."""
    if disagreement.worth_checking(result.residuals, result.outlier):
        _, said = disagreement.check(prob.calibration, prob.meas, prob.valid, prob.sigma_px)
        if said:
            report.warnings.append(said)
            warnings.warn(said, stacklevel=3)


@dataclass
class GroupResult:
    """Several individuals solved: who is who (:class:`graph.solve.identity.Identities`) and each
    one's :class:`~graph.types.Result`, in the order of ``identities.names``."""

    identities: "Identities"
    results: list[Result]

    @property
    def names(self) -> list[str]:
        return list(self.identities.names)

    def report(self) -> dict:
        """The identities and each individual's report, as JSON values."""
        return {"identity": self.identities.to_dict(),
                "individuals": {n: r.report.to_dict() for n, r in zip(self.names, self.results)}}


def solve_group(tracks: list[Tracks], calibration: Calibration, options: SolveOptions | None = None,
                progress: ProgressCallback | None = None) -> GroupResult:
    """Several individuals from one :class:`~graph.io.keypoint_types.Tracks` per camera: each camera's
    detections assigned to ``options.individuals`` individuals (None: found) by geometry and motion
    (:func:`graph.solve.identity.assign`), then each solved by :func:`solve` with ``options``."""
    from graph.solve.identity import assign

    options = options or SolveOptions()
    ids = assign(tracks, calibration, options.individuals, options.likelihood_threshold)
    for note in ids.notes:
        warnings.warn(note, stacklevel=2)
    return GroupResult(identities=ids, results=[solve(k, calibration, options, progress) for k in ids.keypoints])
