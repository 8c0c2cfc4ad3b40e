"""Solve a project's trials: in parallel processes, each reported as it goes, failures isolated,
and trials whose outputs are newer than every input (pose files, calibration, config) skipped.

A trial is solved exactly as ``acinoset solve`` would solve its files (the same reader, the same
:func:`graph.api.solve`, the same writers); its outputs are written under temporary names and
renamed into place, so a trial that fails or is interrupted leaves no output that a re-run would
take for done.
"""

from __future__ import annotations

import dataclasses
import multiprocessing
import os
import time
import traceback
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from dataclasses import dataclass
from pathlib import Path
from queue import Empty
from typing import Callable, Literal

from graph.anipose.project import Project, Trial
from graph.errors import InputError
from graph.solve.workers import share_cores
from graph.types import SolveOptions

Status = Literal["solved", "skipped", "failed"]
FALLBACK_FPS = 120.0


@dataclass
class TrialOutcome:
    """What became of one trial."""

    trial: Trial
    status: Status
    message: str = ""  # the failure, or a one-line summary
    seconds: float = 0.0


@dataclass
class TrialEvent:
    """A progress report of one trial: ``stage`` (queued, solving stages, solved, skipped, failed)."""

    trial: str
    stage: str
    fraction: float = 0.0
    message: str = ""


def up_to_date(trial: Trial, shared: list[Path]) -> bool:
    """Both outputs exist and are newer than every input (its own and ``shared``,
    :attr:`Project.inputs`)."""
    try:
        newest_in = max(p.stat().st_mtime_ns for p in trial.inputs(shared))
        oldest_out = min(p.stat().st_mtime_ns for p in (trial.csv, trial.h5))
    except FileNotFoundError:
        return False
    return oldest_out > newest_in


def trial_options(project: Project, trial: Trial) -> SolveOptions:
    """The project's options with this trial's frame rate (``[acinoset] fps``, else its video's)."""
    if trial.fps is not None:
        return dataclasses.replace(project.options, fps=trial.fps)
    return project.options


def run_project(project: Project, jobs: int = 1, force: bool = False,
                report: Callable[[TrialEvent], None] | None = None) -> list[TrialOutcome]:
    """Solve every trial not up to date (all with ``force``), ``jobs`` at a time in processes (1: in
    this process). ``report`` gets a :class:`TrialEvent` as each trial moves on."""
    report = report or (lambda event: None)
    outcomes: dict[int, TrialOutcome] = {}
    todo = []
    for i, trial in enumerate(project.trials):
        if not force and up_to_date(trial, project.inputs):
            outcomes[i] = TrialOutcome(trial, "skipped", "outputs newer than its inputs")
            report(TrialEvent(trial.label, "skipped", 1.0, outcomes[i].message))
        else:
            todo.append(i)
    args = {i: (project.trials[i], trial_options(project, project.trials[i]), project.offsets, project.config,
                project.frame) for i in todo}
    if jobs <= 1 or len(todo) <= 1:
        for i in todo:
            outcomes[i] = _finish(project.trials[i], solve_trial(*args[i], progress=report), report)
    else:
        ctx = multiprocessing.get_context("forkserver")
        ctx.set_forkserver_preload(["graph.api", "graph.io.results"])
        workers = min(jobs, len(todo))
        threads = max(1, (os.cpu_count() or 1) // workers)
        with multiprocessing.Manager() as manager:
            queue = manager.Queue()
            with ProcessPoolExecutor(max_workers=workers, mp_context=ctx, initializer=share_cores,
                                     initargs=(threads,)) as pool:
                futures = {pool.submit(_solve_in_worker, *args[i], queue): i for i in todo}
                pending = set(futures)
                while pending:
                    done, pending = wait(pending, timeout=0.2, return_when=FIRST_COMPLETED)
                    _drain(queue, report)
                    for fut in done:
                        i = futures[fut]
                        try:
                            outcome = fut.result()
                        except Exception as e:  # the worker process itself died
                            outcome = TrialOutcome(project.trials[i], "failed", f"worker died: {e}")
                        outcomes[i] = _finish(project.trials[i], outcome, report)
                _drain(queue, report)
    return [outcomes[i] for i in range(len(project.trials))]


def _finish(trial: Trial, outcome: TrialOutcome, report) -> TrialOutcome:
    outcome.trial = trial
    report(TrialEvent(trial.label, outcome.status, 1.0, outcome.message))
    return outcome


def _drain(queue, report) -> None:
    while True:
        try:
            report(queue.get_nowait())
        except Empty:
            return


def _solve_in_worker(trial: Trial, options: SolveOptions, offsets, config: Path, frame, queue) -> TrialOutcome:
    return solve_trial(trial, options, offsets, config, frame, progress=queue.put)


def solve_trial(trial: Trial, options: SolveOptions, offsets: dict[str, tuple[float, float]], config: Path,
                frame: tuple[list, str] | None = None,
                progress: Callable[[TrialEvent], None] | None = None) -> TrialOutcome:
    """Solve one trial and write its CSV (in Anipose's frame of ``frame`` = (axes, reference_point),
    if given) and H5; never raises (a failure is the outcome)."""
    import warnings

    t0 = time.perf_counter()
    emit = progress or (lambda event: None)
    emit(TrialEvent(trial.label, "started"))
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            result, calibration = _solve(trial, options, offsets, emit)
        from graph.io import results

        trial.csv.parent.mkdir(parents=True, exist_ok=True)
        tmp_csv, tmp_h5 = (p.with_name(f".{p.name}.partial") for p in (trial.csv, trial.h5))
        # the CSV in the calibration's units, as anipose triangulate writes it (a project calibrated in
        # millimetres gets millimetres); the H5 keeps metres, as every acinoset result file does
        from graph.camera import CALIBRATION_UNITS
        from graph.io.calibration import resolve_units

        per_unit = CALIBRATION_UNITS[resolve_units(calibration, result.options.calibration_units)[0]]
        csv_frame = None
        if frame is not None:
            from graph.anipose.frame import anipose_frame

            csv_frame = anipose_frame(result.positions / per_unit, result.markers, *frame)
        results.write_anipose_csv(tmp_csv, result, frame=csv_frame, metres_per_unit=per_unit)
        results.write_h5(tmp_h5, result, calibration=calibration)
        os.replace(tmp_h5, trial.h5)
        os.replace(tmp_csv, trial.csv)  # the CSV last: it is what Anipose's tools look for
        rep = result.report
        notes = sorted({" ".join(str(w.message).split()) for w in caught if issubclass(w.category, UserWarning)})
        msg = (f"{rep.method}, {rep.frames} frames, {rep.cameras} cameras, reprojection RMSE "
               f"{rep.reprojection_rmse_px:.2f} px, {rep.seconds.get('total', 0.0):.1f} s"
               + "".join(f"; {n}" for n in notes))
        return TrialOutcome(trial, "solved", msg, time.perf_counter() - t0)
    except InputError as e:
        return TrialOutcome(trial, "failed", str(e), time.perf_counter() - t0)
    except Exception as e:  # one trial's bug must not stop the others; say where it was
        where = traceback.extract_tb(e.__traceback__)[-1]
        return TrialOutcome(trial, "failed", f"{type(e).__name__}: {e} ({Path(where.filename).name}:{where.lineno})",
                            time.perf_counter() - t0)


def _solve(trial: Trial, options: SolveOptions, offsets, emit):
    import warnings

    from graph import api
    from graph.camera import Calibration
    from graph.io.calibration import load_calibration
    from graph.io.keypoints import read_keypoints

    keypoints = [read_keypoints(p, individual=options.individual) for p in trial.pose_files]
    n = min(k.frames for k in keypoints)
    for cam, k in zip(trial.cameras, keypoints):
        if k.frames != n:  # Anipose truncates to the shortest camera
            warnings.warn(f"camera {cam} has {k.frames} frames, the shortest {n}: the last "
                          f"{k.frames - n} left out, as Anipose does", UserWarning, stacklevel=2)
            k.xy, k.likelihood = k.xy[:n], k.likelihood[:n]
        dx, dy = offsets.get(cam, (0.0, 0.0))
        if dx or dy:
            k.xy = k.xy + [dx, dy]
    rig = load_calibration(trial.calibration)
    by_name = {name: c for name, c in zip(rig.names, rig.cameras)}
    missing = [c for c in trial.cameras if c not in by_name]
    if missing:
        raise InputError(f"has no camera named {', '.join(missing)} (it has {', '.join(rig.names)})",
                         trial.calibration)
    calibration = Calibration(cameras=[by_name[c] for c in trial.cameras], source=rig.source, metadata=rig.metadata)
    last = [0.0, ""]

    def progress(p) -> None:
        if p.stage != last[1] or p.fraction - last[0] >= 0.1 or p.fraction >= 1.0:
            last[:] = [p.fraction, p.stage]
            emit(TrialEvent(trial.label, str(p.stage), float(p.fraction)))

    return api.solve(keypoints, calibration, options, progress=progress), calibration
