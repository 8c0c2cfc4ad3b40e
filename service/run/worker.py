"""Running one job: read its files, call :func:`graph.api.solve`, write the result files.

The same :func:`solve_job` runs under both backends:

* embedded: :func:`run_embedded` is the body of a child process of the server; it reports progress
  into the job table itself and moves its result files in place inside the transaction that marks
  the job succeeded (:meth:`service.store.Store.finish`).
* rq: :func:`run_rq_job` runs in an RQ work horse on any machine. It reads the input files from
  Redis (one zip archive per job), reports progress in the RQ job's ``meta`` and puts the result
  files back in Redis; the server stores them in the data dir and the job table, then deletes them
  from Redis (RQ expires results: it is not the record).

The job's files (inputs, manifest, results, their archives) are laid out by :mod:`service.store.jobfiles`.
The stages a job reports are :data:`service.api.models.STAGES`.

Errors: :class:`graph.errors.InputError` and other exceptions of the solve fail the job at once with
a one-line message (trying again would fail again); only a run that dies (killed, machine lost) is
tried again.
"""

from __future__ import annotations

import dataclasses
import json
import os
import re
import shutil
import socket
import sys
import tempfile
import time
import traceback
from pathlib import Path
from typing import TYPE_CHECKING, Callable

import numpy as np

from service.errors import DISK_FULL, EXIT_DISK_FULL, storage_full, strip_paths
from service.store import READING, RENDERING, WRITING, ErrorKind, StoreFull, jobfiles
from service.store.jobfiles import (
    ERROR_LOG,
    INPUT,
    RESULT,
    RESULT_FILES,
    STAGED,
    VIDEOS_DIR,
    get_archive,
    input_key,
    input_videos,
    inside,
    install_result,
    pack_files,
    put_archive,
    read_manifest,
    result_key,
    result_tmp,
    unpack_files,
    video_result_name,
)

if TYPE_CHECKING:
    from service.run.shared_windows import SharedWindows

SOLVER_THREADS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS")


def prepare_solver_environment() -> None:
    """Settings for a process that forks solves; call it before the solver is imported.

    One thread per solve (a machine runs one solve per core), and numba's ``workqueue`` threading
    layer: GNU OpenMP, numba's default here, aborts a process forked after it ran a parallel kernel.
    """
    for var in SOLVER_THREADS:
        os.environ.setdefault(var, "1")
    if os.environ.get("NUMBA_THREADING_LAYER") not in ("tbb", "workqueue"):
        os.environ["NUMBA_THREADING_LAYER"] = "workqueue"
    numba = sys.modules.get("numba")
    if numba is not None:
        numba.config.THREADING_LAYER = os.environ["NUMBA_THREADING_LAYER"]


# imported by every process that forks solves (missing ones are skipped); the package first: it sets numba's
# optimisation level before numba is imported
SOLVER_MODULES = ("graph", "gtsam", "numba", "graph.types", "graph.api", "graph.io.calibration",
                  "graph.io.keypoints", "graph.skeleton", "graph.solve.problem", "graph.solve.kernels",
                  "graph.solve.triangulate", "graph.solve.tri", "graph.solve.fte", "graph.solve.sync",
                  "graph.solve.joint", "graph.solve.online", "graph.io.results", "graph.viewer.payload")


def preload_modules(warm: bool) -> list[str]:
    """What a process that forks solves imports first: this module, the solver and, if ``warm``,
    :mod:`service.run.warmup` (importing it compiles the solver's kernels)."""
    return ["service.run.worker", *SOLVER_MODULES, *(["service.run.warmup"] if warm else [])]


def configure_forkserver(warm: bool) -> None:
    """Solve processes and upload readers fork from one forkserver with the library imported (and,
    if ``warm``, its kernels compiled). Call before the first fork."""
    import multiprocessing

    prepare_solver_environment()  # the forkserver inherits it
    multiprocessing.get_context("forkserver").set_forkserver_preload(preload_modules(warm))


def noop() -> None:
    """A process that does nothing: starting one starts (and warms) the forkserver."""


class JobCancelled(Exception):
    """The run no longer owns its job (cancelled, or given up for lost and run elsewhere)."""


# -- inputs ------------------------------------------------------------------------------------

def load_inputs(input_dir: Path):
    """The job's detections (one per camera: :class:`~graph.io.keypoints.Keypoints`, or
    :class:`~graph.io.keypoint_types.Tracks` when they hold several individuals,
    :func:`graph.io.keypoints.read_recording`), calibration and solve options, read with the core's readers."""
    from graph.io.keypoint_types import Keypoints, Tracks
    from graph.io.keypoints import read_recording

    m = read_manifest(input_dir)
    opts = job_options(input_dir)
    cameras = read_recording([inside(input_dir, rel) for rel in m["keypoints"]], opts.individual, opts.individuals)
    for k, rel in zip(list[Keypoints | Tracks](cameras), m["keypoints"]):
        k.source = Path(rel).name  # what the results say they came from: the upload's name, no server path
    return cameras, job_calibration(input_dir), opts


def job_options(input_dir: Path):
    """The job's :class:`~graph.types.SolveOptions` (its skeleton file's path inside the job)."""
    from pydantic import TypeAdapter

    from graph.api import SolveOptions

    m = read_manifest(input_dir)
    options = dict(m["options"])
    if m.get("skeleton"):
        options["skeleton"] = str(inside(input_dir, m["skeleton"]))
    return TypeAdapter(SolveOptions).validate_python(options)


def job_calibration(input_dir: Path):
    """The job's calibration, named by the upload's name (no server path)."""
    from graph.io.calibration import load_calibration

    m = read_manifest(input_dir)
    calibration = load_calibration(inside(input_dir, m["calibration"]))
    return dataclasses.replace(calibration, source=Path(m["calibration"]).name)


def without_server_paths(result):
    """The result as its files are written for the user: the skeleton option by its file's name, and
    no server path in a warning (the report, the H5 and every export say only the uploads' names)."""
    result = dataclasses.replace(result, options=users_options(result.options))
    result.report.warnings = [strip_paths(w) for w in result.report.warnings]
    return result


def users_options(options):
    """``options`` as the user's files name them: the skeleton by its file's name, not its server path."""
    skeleton = options.skeleton
    return dataclasses.replace(options, skeleton=Path(skeleton).name) if "/" in skeleton else options


# -- outputs -----------------------------------------------------------------------------------

def write_results(result, out_dir: Path, calibration=None, individual: str | None = None) -> dict:
    """Write every result format into ``out_dir`` (the H5 with the calibration solved with, so the
    exports carry the rig, and the ``individual`` it is of, one of several); return the report as a dict."""
    from graph.io.results import write_anipose_csv, write_h5
    from graph.viewer.payload import payload_json, result_payload  # the job page: one definition for both sides

    out_dir.mkdir(parents=True, exist_ok=True)
    name = {fmt: file for fmt, (file, _) in RESULT_FILES.items()}
    write_anipose_csv(out_dir / name["csv"], result)
    write_h5(out_dir / name["h5"], result, calibration=calibration, individual=individual)
    report = result.report.to_dict()
    (out_dir / name["json"]).write_bytes(payload_json(result_payload(result)))
    (out_dir / name["report"]).write_text(json.dumps(report, indent=2))
    return report


# -- progress ----------------------------------------------------------------------------------

class ThrottledProgress:
    """The solve's progress callback: passes a report on to ``sink`` at most every ``interval``
    seconds (and always at a new stage). ``sink`` returns False when the run should stop."""

    def __init__(self, sink: Callable[[str, float, int, float | None, str | None], bool], interval: float):
        self.sink = sink
        self.interval = interval
        self._last = 0.0
        self._stage: str | None = None

    def __call__(self, p) -> None:
        now = time.monotonic()
        if p.stage == self._stage and now - self._last < self.interval:
            return
        self.report(p.stage, p.fraction, p.iteration, p.cost, p.detail)

    def throttled(self, stage: str, fraction: float) -> None:
        """:meth:`report`, at most every ``interval`` seconds."""
        if stage != self._stage or time.monotonic() - self._last >= self.interval:
            self.report(stage, fraction)

    def report(self, stage: str, fraction: float, iteration: int = 0, cost: float | None = None,
               detail: str | None = None) -> None:
        """``detail``: where the stage is, in words (a long run's windows done and the time left)."""
        self._last, self._stage = time.monotonic(), stage
        fraction = float(min(1.0, max(0.0, fraction))) if np.isfinite(fraction) else 0.0
        cost = float(cost) if cost is not None and np.isfinite(cost) else None
        if not self.sink(stage, fraction, int(iteration), cost, detail or None):
            raise JobCancelled()


def solve_job(input_dir: Path, out_dir: Path, progress: ThrottledProgress,
              solver: "SharedWindows | None" = None) -> dict:
    """Read the inputs, solve, write the results; return the solve report. A calibration job
    (its manifest's ``kind``) is run by :func:`service.run.calibration_run.run_calibration` instead.
    ``solver``: a long run's windows shared with other workers (:func:`solve_streamed_job`)."""
    from graph.api import solve

    if read_manifest(input_dir).get("kind") == jobfiles.CALIBRATION_KIND:
        from service.run.calibration_run import run_calibration

        return run_calibration(input_dir, out_dir, progress)

    progress.report(READING, 0.0)
    if not input_videos(input_dir):
        report = solve_streamed_job(input_dir, out_dir, progress, solver)
        if report is not None:
            return report
    cameras, calibration, options = load_inputs(input_dir)
    from graph.io.keypoint_types import Tracks

    if all(isinstance(c, Tracks) for c in cameras):
        return solve_group_job(cameras, calibration, options, out_dir, progress)
    result = without_server_paths(solve(cameras, calibration, options, progress=progress))
    progress.report(WRITING, 1.0, result.report.iterations, result.report.cost)
    report = write_results(result, out_dir, calibration)
    videos = input_videos(input_dir)
    if videos:
        from graph.errors import InputError

        try:
            render_labelled_videos(result, videos, out_dir, progress)
        except InputError as e:  # the solve stands: the job succeeds, with the reason it has no videos
            shutil.rmtree(out_dir / VIDEOS_DIR, ignore_errors=True)
            report["warnings"] = [*report.get("warnings", []),
                                  strip_paths(f"the labelled videos could not be rendered: {e}")]
            (out_dir / RESULT_FILES["report"][0]).write_text(json.dumps(report, indent=2))
    return report


PAGE_FRAMES = 20_000  # the job page's view of a long run: every k-th frame, at most this many


def stage_job(input_dir: Path, scratch: Path, long_enough: Callable[[int], bool], together=None):
    """The job's keypoint files staged in ``scratch`` (:func:`graph.io.staged.stage`), each camera
    named by its upload's name; None when ``long_enough`` says the run is not. ``together(paths,
    folder, read)``: the cameras staged with other workers instead
    (:func:`service.run.shared_windows.stage_together`)."""
    from graph.io.keypoints import read_blocks
    from graph.io.staged import stage

    m = read_manifest(input_dir)
    paths = [str(inside(input_dir, rel)) for rel in m["keypoints"]]
    if together is None:
        run = stage(paths, scratch, read_blocks, long_enough)
    else:
        run = together(paths, scratch, read_blocks)
        run = run if run is not None and long_enough(run.frames) else None
    if run is not None:
        run.cameras = [dataclasses.replace(cam, source=Path(rel).name) for cam, rel in zip(run.cameras, m["keypoints"])]
    return run


def solve_streamed_job(input_dir: Path, out_dir: Path, progress: ThrottledProgress,
                       solver: "SharedWindows | None" = None) -> dict | None:
    """A long run of one individual solved as ``acinoset solve`` solves it, streamed
    (:func:`graph.api.solve_streamed`: the inputs staged on disk a camera at a time, the CSV and H5
    written as the windows finish), in memory that does not grow with the run; the page's view
    (``result.json``) made of every k-th frame, at most :data:`PAGE_FRAMES` (``frame_step`` says k),
    kept as the windows finish (an overview H5 beside the staged inputs). ``solver``: the windows
    shared with other workers too (:class:`service.run.shared_windows.SharedWindows`). None when the
    job is not such a run (solve it in memory)."""
    from graph.api import solve_streamed
    from graph.io.results import AniposeCsv, H5Stream, read_result
    from graph.solve.windows import one_stream
    from graph.types import WINDOW_FRAMES, WINDOWED_ABOVE, WINDOWED_METHODS
    from graph.viewer.payload import payload_json, result_payload

    options = job_options(input_dir)
    if (options.method not in WINDOWED_METHODS or options.window_frames == 0 or options.individual
            or options.individuals):
        return None
    above = options.window_frames or WINDOWED_ABOVE
    if one_stream(options):
        solver = None  # ekf's windows: solved in turn by this process, none shared
    # staged inside the job's result folder: a run killed (cancelled, timed out) leaves nothing behind
    # that the job's own clean-up does not remove
    scratch = out_dir / STAGED
    windows = lambda frames: -(-frames // (options.window_frames or WINDOW_FRAMES))  # noqa: E731
    hint = read_manifest(input_dir).get("frames")
    try:
        scratch.mkdir(parents=True, exist_ok=True)  # before the helpers come: they stage into it, never make it
        if solver is not None and isinstance(hint, int) and hint > above:
            # the helpers stage the run while this process stages (with them, on a shared data dir) and settles it
            solver.invite(windows(hint), before_staging=True)
        run = stage_job(input_dir, scratch, lambda frames: frames > above,
                        solver.stage if solver is not None and solver.together else None)
        if run is None:
            return None
        if solver is not None:  # no hint: invited now (once)
            solver.invite(windows(run.frames))
            if not solver.together:
                run.save()  # for helpers that read this folder (the embedded backend's)
        calibration = job_calibration(input_dir)
        out_dir.mkdir(parents=True, exist_ok=True)
        name = {fmt: file for fmt, (file, _) in RESULT_FILES.items()}
        h5 = H5Stream(out_dir / name["h5"], run.frames)
        step = max(1, -(-run.frames // PAGE_FRAMES))
        # the page's view: every step-th frame, kept as the windows finish (reading them back out of
        # the whole H5 took 1.4-1.7 s at 72,000 frames)
        seen_path = scratch / "view.h5" if step > 1 else out_dir / name["h5"]
        streams = [h5] if step == 1 else [h5, H5Stream(seen_path, run.frames, step=step)]
        csv: list[AniposeCsv] = []

        def write(core) -> None:
            r = dataclasses.replace(core.result, options=users_options(core.result.options))
            if not csv:
                csv.append(AniposeCsv(out_dir / name["csv"], r.markers))
            csv[0].write(r)
            for stream in streams:
                stream.write(r)

        try:
            report = solve_streamed(run, calibration, options, write, progress=progress, solver=solver)
            if solver is not None and solver.solved and report.windows is not None:
                report.windows["solved_by"] = dict(solver.solved)  # the workers that solved windows, how many each
                if solver.staged:
                    report.windows["staged_by"] = dict(solver.staged)  # and staged the cameras
            report.warnings = [strip_paths(w) for w in report.warnings]
            for stream in streams:
                stream.close(report, options, calibration)
            progress.report(WRITING, 1.0, report.iterations, report.cost)
            seen = read_result(seen_path)
        except BaseException:
            for stream in streams:
                stream.file.close()
            raise
        finally:
            for f in csv:
                f.close()
    finally:
        if solver is not None:
            solver.close()  # the helpers invited stop (the windows' own end stops them too)
        for _ in range(3):  # a helper on its way out may have written in it meanwhile
            shutil.rmtree(scratch, ignore_errors=True)
            if not scratch.exists():
                break
            time.sleep(0.2)
    payload = result_payload(dataclasses.replace(seen, fps=seen.fps / step))
    payload["frame_step"] = step
    # the view's frames: the run's frames n * step (the report's frame numbers are the run's)
    payload["report"]["unconstrained_frames"] = [n // step for n in report.unconstrained_frames if n % step == 0]
    (out_dir / name["json"]).write_bytes(payload_json(payload))
    doc = report.to_dict()
    (out_dir / name["report"]).write_text(json.dumps(doc, indent=2))
    return doc


def solve_group_job(tracks: list, calibration, options, out_dir: Path, progress: "ThrottledProgress") -> dict:
    """Several individuals (:func:`graph.api.solve_group`): each one's result files in its folder
    (:func:`service.store.jobfiles.individual_folder`, in the order of the report's ``individuals``),
    the job's page view of them all (``result.json``, :func:`graph.viewer.payload.group_payload`), the
    H5 of them all on an individuals axis (``result.h5``, :func:`graph.io.results.write_group_h5`)
    and the job's report: the first individual's headline numbers, who is who (``identity``), each
    one's report (``individuals``) and every warning, each prefixed with its individual's name."""
    from graph.api import solve_group

    group = solve_group(tracks, calibration, options, progress=progress)
    results = [without_server_paths(r) for r in group.results]
    progress.report(WRITING, 1.0, results[0].report.iterations, results[0].report.cost)
    doc = group.report()
    if len(results) == 1:  # one found: the job's own files, as a job of one animal
        report = write_results(results[0], out_dir, calibration)
        report["identity"] = doc["identity"]
    else:
        for k, result in enumerate(results):
            write_results(result, out_dir / jobfiles.individual_folder(k), calibration, individual=group.names[k])
        from graph.io.results import write_group_h5
        from graph.viewer.payload import group_payload, payload_json  # the job page's view of them all

        named = list(zip(group.names, results))
        (out_dir / RESULT_FILES["json"][0]).write_bytes(payload_json(group_payload(named)))
        write_group_h5(out_dir / RESULT_FILES["h5"][0], named, calibration=calibration, identity=doc["identity"])
        report = {**doc["individuals"][group.names[0]], **doc}
        report["warnings"] = [f"{name}: {w}" for name, r in zip(group.names, results) for w in r.report.warnings]
    report["warnings"] = [*group.identities.notes, *report.get("warnings", [])]
    (out_dir / RESULT_FILES["report"][0]).write_text(json.dumps(report, indent=2))
    return report


def render_labelled_videos(result, videos: list[Path], out_dir: Path, progress: "ThrottledProgress") -> None:
    """Each camera's video with the result drawn on it, the 3D view and the grid of all
    (:func:`graph.video.render_videos`), as ``videos/camera01.mp4``, ..., ``3d.mp4`` and
    ``combined.mp4`` in ``out_dir`` (:func:`service.store.jobfiles.video_result_name`)."""
    from graph.video import render_videos

    folder = out_dir / VIDEOS_DIR
    progress.report(RENDERING, 0.0)
    done = render_videos(result, videos, folder, combined=True,
                         progress=lambda n, total: progress.throttled(RENDERING, n / max(total, 1)))
    for c, path in enumerate(done.cameras):
        os.replace(path, out_dir / video_result_name(str(c + 1)))
    progress.report(RENDERING, 1.0)


def one_line(e: BaseException) -> str:
    from graph.errors import InputError

    text = " ".join(str(e).split()) or type(e).__name__
    return text if isinstance(e, InputError) else f"{type(e).__name__}: {text}"


def error_kind(e: BaseException) -> ErrorKind:
    """``input`` when the solver refused the job's files or options (:class:`graph.errors.InputError`),
    ``limit`` when the run ran out of memory, ``internal`` for any other error (a fault of the software)."""
    from graph.errors import InputError

    if isinstance(e, InputError):
        return "input"
    return "limit" if isinstance(e, MemoryError) else "internal"


# -- embedded: one child process per job -------------------------------------------------------

def die_with_parent() -> None:
    """Ask Linux to SIGKILL this process when its parent dies (``PR_SET_PDEATHSIG``)."""
    try:
        import ctypes
        import signal

        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
        if os.getppid() == 1:  # the parent died before the request took effect
            os._exit(1)
    except (OSError, AttributeError):  # not Linux: fencing by run token still stops orphans writing
        pass


def die_with_server() -> None:
    """No process forked for the server (solves, upload readers) outlives it.

    Their parent is the forkserver, which exits when no process holds its "alive" pipe any more.
    Every process it forks gets a copy of that pipe: this one closes its copy, so the forkserver
    exits as soon as the server dies, and this process dies with the forkserver.
    """
    try:
        from multiprocessing import forkserver

        fd = getattr(forkserver._forkserver, "_forkserver_alive_fd", None)
        if fd is not None:
            os.close(fd)
            forkserver._forkserver._forkserver_alive_fd = None  # type: ignore[attr-defined]  # CPython's own
    except (ImportError, AttributeError, OSError):
        pass
    die_with_parent()


def server_child(niceness: int) -> None:
    """Set up a process the server forked: it dies with the server and yields the CPU to the API
    (``niceness`` added to its nice value; 0 leaves it alone)."""
    die_with_server()
    _yield_cpu(niceness)


def _yield_cpu(niceness: int) -> None:
    """Add ``niceness`` to this process's nice value (0 leaves it alone)."""
    if niceness:
        try:
            os.nice(niceness)
        except OSError:
            pass


def run_embedded(db_path: str, jobs_dir: str, job_id: str, token: str, progress_interval: float,
                 niceness: int, helpers: int = 0) -> None:
    """Body of the child process that runs one job for the embedded backend. ``helpers``: how many
    helper processes a long run's windows may have at most (:func:`help_embedded`)."""
    from service.store import Store

    server_child(niceness)
    store = Store(db_path)
    job_dir = jobfiles.job_dir(Path(jobs_dir), job_id)
    tmp = result_tmp(job_dir, token)

    def sink(stage, fraction, iteration, cost, detail) -> bool:
        return store.report_progress(job_id, token, stage, fraction, iteration, cost, detail)

    try:
        solver = _embedded_windows(job_dir, token, helpers) if helpers > 0 else None
        report = solve_job(job_dir / INPUT, tmp, ThrottledProgress(sink, progress_interval), solver)
        store.finish(job_id, token, "succeeded", summary=report, commit=lambda: install_result(job_dir, tmp))
    except JobCancelled:
        pass
    except Exception as e:  # noqa: BLE001 - any error of the solve fails the job with its message
        if storage_full(e):
            _fail_disk_full(store, job_id, token, tmp)
        else:
            _log_traceback(job_dir)
            store.finish(job_id, token, "failed", error=one_line(e), error_kind=error_kind(e))
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
        store.close()


def _embedded_windows(job_dir: Path, token: str, helpers: int) -> "SharedWindows":
    """A long run's windows shared with at most ``helpers`` helper processes, which the server starts
    in its free slots when the run asks (:mod:`service.run.folder_windows`)."""
    from service.run.folder_windows import FolderBoard
    from service.run.shared_windows import SharedWindows

    board = FolderBoard(jobfiles.windows_board(job_dir, token))

    def enqueue(n: int) -> list[str]:
        board.want(n)
        return []

    return SharedWindows(board, f"{socket.gethostname()}:{os.getpid()}", enqueue, lambda: helpers)


def help_embedded(db_path: str, jobs_dir: str, job_id: str, token: str, niceness: int, backend: str) -> None:
    """Body of a helper process of the embedded backend: it solves windows of the run ``token`` of job
    ``job_id`` (:func:`service.run.shared_windows.help_with_windows`), staging the run's cameras with
    it, until none is left or another job of the ``backend`` waits for a slot."""
    from graph.io.staged import StagedRun
    from service.run.folder_windows import FolderBoard
    from service.run.shared_windows import help_with_windows, stage_together, wait_for_plan
    from service.store import Store

    server_child(niceness)
    store = Store(db_path)
    job_dir = jobfiles.job_dir(Path(jobs_dir), job_id)
    board = FolderBoard(jobfiles.windows_board(job_dir, token))
    me = f"helper-{os.getpid()}@{socket.gethostname()}:{os.getpid()}"
    input_dir, scratch = job_dir / INPUT, board.folder.parent

    def stage():
        if board.staging_together():  # the cameras staged with the parent, in its folder
            return stage_job(input_dir, scratch, lambda frames: True,
                             lambda paths, folder, read: stage_together(board, me, paths, folder, read))
        return None if wait_for_plan(board) is None else StagedRun.open(scratch)  # as the parent staged them

    try:
        help_with_windows(board, me, stage, job_calibration(input_dir), job_options(input_dir),
                          lambda: store.oldest_queued_at(backend) is not None)
    except Exception:  # noqa: BLE001 - the parent solves what a helper did not
        if not board.stopped():  # not merely the run's end, which clears the board under it
            traceback.print_exc()
            raise SystemExit(1) from None  # the scheduler starts no other helper for this run
    finally:
        store.close()


def _fail_disk_full(store, job_id: str, token: str, tmp: Path) -> None:
    """The disk is full (a result file, the job table): fail the job now, naming the disk, not run
    again (it would only fill it again). Its partial results go first, to make room; the table's
    reserve, spent by the write that failed, is room for the record. If even that cannot be written,
    exit with :data:`~service.errors.EXIT_DISK_FULL`: the scheduler records it once it can."""
    shutil.rmtree(tmp, ignore_errors=True)
    print(f"job {job_id}: {DISK_FULL}", file=sys.stderr, flush=True)
    try:
        store.finish(job_id, token, "failed", error=DISK_FULL, error_kind="limit")
    except StoreFull:
        raise SystemExit(EXIT_DISK_FULL) from None


def _log_traceback(job_dir: Path) -> None:
    text = traceback.format_exc()
    try:
        with open(job_dir / ERROR_LOG, "a") as f:
            f.write(f"--- {time.strftime('%Y-%m-%d %H:%M:%S')} on {socket.gethostname()}:{os.getpid()}\n{text}")
    except OSError:
        pass
    print(text, file=sys.stderr, flush=True)


# -- rq: a work horse anywhere -----------------------------------------------------------------

def run_rq_job(job_id: str, progress_interval: float = 0.5, niceness: int = 0, helper_of: str | None = None,
               shared: bool = False) -> dict:
    """The RQ job function. Reads the input archive from Redis (:func:`input_key`), stores the result
    archive there (:func:`result_key`) and returns ``{"status": "succeeded", "report", "seconds",
    "worker"}`` or ``{"status": "failed", "error"}``; raises only if the process itself is in trouble.
    ``shared``: the server shares its data dir with the workers (:func:`shared_job`): the inputs are read
    where the API stored them and the results written beside them (``"files": "shared"``).
    A long run's windows are shared with the workers that are idle (:mod:`service.run.shared_windows`);
    ``helper_of``, the RQ token of such a job: this one helps it (``{"status": "helped", "windows"}``)."""
    from rq import get_current_job

    rq_job = get_current_job()
    die_with_parent()  # a worker that dies takes its work horse along: the job is retried, not orphaned
    _yield_cpu(niceness)
    worker = _this_worker()
    if rq_job is None:
        return {"status": "failed", "error": "not run by an RQ worker", "worker": worker}
    if rq_job.timeout:
        sweep_stale_scratch(float(rq_job.timeout))
    if helper_of is not None:
        return _help(rq_job, job_id, helper_of, worker, shared)
    rq_job.meta["host"] = f"{socket.gethostname()}:{os.getpid()}"
    rq_job.save_meta()

    def sink(stage, fraction, iteration, cost, detail) -> bool:
        rq_job.meta["progress"] = {"stage": stage, "fraction": fraction, "iteration": iteration, "cost": cost,
                                   "detail": detail}
        rq_job.save_meta()
        return True

    t0 = time.time()
    token = rq_job.id

    def solved(input_dir: Path, out_dir: Path) -> dict:
        """The job solved from ``input_dir`` into ``out_dir``: what the function returns, less how the
        files travel."""
        try:
            report = solve_job(input_dir, out_dir, ThrottledProgress(sink, progress_interval),
                               _shared_windows(rq_job, job_id, progress_interval, niceness, shared))
        except Exception as e:  # noqa: BLE001 - a failed solve is a result, not a retry
            traceback.print_exc()
            return {"status": "failed", "error": one_line(e), "error_kind": error_kind(e), "worker": worker}
        return {"status": "succeeded", "report": report, "seconds": time.time() - t0, "worker": worker}

    if shared:
        job = shared_job(job_id)
        if isinstance(job, str):
            return {"status": "failed", "error": job, "worker": worker}
        out_dir = jobfiles.result_tmp(job, token)
        shutil.rmtree(out_dir, ignore_errors=True)
        done = solved(job / INPUT, out_dir)
        if done["status"] == "succeeded":
            return {**done, "files": "shared"}
        shutil.rmtree(out_dir, ignore_errors=True)
        return done
    archive = get_archive(rq_job.connection, input_key(token))
    if archive is None:
        return {"status": "failed", "error": "the job's input files are no longer in Redis", "worker": worker}
    with tempfile.TemporaryDirectory(prefix=f"acinoset-{job_id[:8]}-") as tmp:
        input_dir, out_dir = Path(tmp) / INPUT, Path(tmp) / RESULT
        unpack_files(archive, input_dir)
        del archive
        done = solved(input_dir, out_dir)
        if done["status"] == "succeeded":
            put_archive(rq_job.connection, result_key(token), pack_files(out_dir, jobfiles.written_outputs(out_dir)))
        return done


SCRATCH = re.compile(r"^acinoset-([0-9a-f]{8}-|window-)")  # the work horses' temporary folders (their prefixes)


def sweep_stale_scratch(older_than_s: float, where: str | None = None) -> list[str]:
    """Remove the work horses' temporary folders (:data:`SCRATCH`) in ``where`` (the temporary
    directory) untouched for longer than ``older_than_s``, a job's timeout: a work horse killed by
    SIGKILL (a cancel, a lost worker) leaves its folder behind, and no job still running can own one
    that old. Returns the names removed."""
    base = Path(where or tempfile.gettempdir())
    removed: list[str] = []
    now = time.time()
    try:
        entries = list(os.scandir(base))
    except OSError:
        return removed
    for e in entries:
        try:
            if SCRATCH.match(e.name) and e.is_dir(follow_symlinks=False) and now - e.stat().st_mtime > older_than_s:
                shutil.rmtree(e.path, ignore_errors=True)
                removed.append(e.name)
        except OSError:
            continue
    return removed


def shared_job(job_id: str) -> Path | str:
    """The job's directory on the data dir this worker shares with the server (its ``--data-dir``, or
    ``ACINOSET_DATA_DIR``), or a one-line reason why this worker cannot reach it."""
    from service.settings import Settings

    if not jobfiles.JOB_ID.match(job_id):
        return f"not a job id: {job_id!r}"
    jobs = Settings().jobs_dir
    job = jobfiles.job_dir(jobs, job_id)
    if not (job / INPUT / jobfiles.MANIFEST).is_file():
        return (f"worker {_this_worker()} does not see the server's data dir (no job {job_id} under {jobs}): start it "
                "with --data-dir where it mounts the server's, or unset the server's ACINOSET_SHARED_DATA_DIR")
    return job


def _shared_windows(rq_job, job_id: str, progress_interval: float, niceness: int, shared: bool):
    """The windows of this RQ job's run shared with the workers of its queue that are idle: a helper
    is this function's RQ job again, given ``helper_of`` (the one function the workers run)."""
    from rq import Queue, Worker
    from rq.job import Job as RQJob
    from rq.serializers import JSONSerializer

    from service.run.redis_windows import RedisBoard
    from service.run.shared_windows import SharedWindows

    queue = Queue(rq_job.origin, connection=rq_job.connection, serializer=JSONSerializer)
    token = rq_job.id
    function = f"{run_rq_job.__module__}.{run_rq_job.__name__}"

    def idle() -> int:
        return sum(1 for w in Worker.all(queue=queue) if w.get_state() == "idle")

    def enqueue(n: int) -> list[str]:
        ids = [f"{jobfiles.helpers_prefix(token)}{time.time_ns()}-{i}" for i in range(n)]
        for jid in ids:
            queue.enqueue_call(function, args=(job_id, progress_interval, niceness),
                               kwargs={"helper_of": token, "shared": shared},
                               job_id=jid, timeout=rq_job.timeout, result_ttl=0, failure_ttl=600,
                               description=f"acinoset job {job_id}: a helper with its windows")
        return ids

    def drop(ids: list[str]) -> None:
        for jid in ids:
            try:
                helper = RQJob.fetch(jid, connection=rq_job.connection, serializer=JSONSerializer)
                if helper.get_status() in ("queued", "deferred", "scheduled"):
                    helper.delete()
            except Exception:  # noqa: BLE001 - gone already
                pass

    board = RedisBoard(rq_job.connection, token, _timeout(rq_job), shared=shared)
    return SharedWindows(board, _worker_name(rq_job), enqueue, idle, drop)


def _timeout(rq_job) -> int:
    """How long the job may run (s), and its keys in Redis outlive it at most: RQ's timeout, else an hour."""
    return int(rq_job.timeout or 3600)


def _this_worker() -> str:
    """This worker as a job's record names it: ``RQ_WORKER_ID``, else host:pid."""
    return os.environ.get("RQ_WORKER_ID") or f"{socket.gethostname()}:{os.getpid()}"


def _worker_name(rq_job) -> str:
    """The RQ worker running ``rq_job`` (unique among the queue's workers)."""
    return str(rq_job.worker_name or _this_worker())


def _others_waiting(rq_job, token: str):
    """Whether jobs other than this job's helpers wait in this RQ job's queue (a test to call)."""
    from rq import Queue
    from rq.serializers import JSONSerializer

    queue = Queue(rq_job.origin, connection=rq_job.connection, serializer=JSONSerializer)
    mine = jobfiles.helpers_prefix(token)
    return lambda: any(not jid.startswith(mine) for jid in queue.get_job_ids())


def _help(rq_job, job_id: str, token: str, worker: str, shared: bool) -> dict:
    """This RQ job (on ``worker``) helps the job whose token is ``token`` with its windows
    (:func:`service.run.shared_windows.help_with_windows`), from the job's input files in Redis, or
    on the shared data dir (``shared``)."""
    from service.run.redis_windows import RedisBoard
    from service.run.shared_windows import help_with_windows, stage_together

    redis, me = rq_job.connection, f"{rq_job.id}@{_worker_name(rq_job)}"
    board = RedisBoard(redis, token, _timeout(rq_job), shared=shared)
    where = shared_job(job_id) if shared else get_archive(redis, input_key(token))
    if where is None or isinstance(where, str):  # the files are gone, or not seen from here
        return {"status": "helped", "windows": 0, "worker": worker}
    with tempfile.TemporaryDirectory(prefix=f"acinoset-{job_id[:8]}-helper-") as tmp:
        scratch, together = Path(tmp) / STAGED, None
        if isinstance(where, Path):
            input_dir = where / INPUT
            if board.staging_together():  # the cameras staged with the parent, in its folder
                scratch = jobfiles.result_tmp(where, token) / STAGED

                def together(paths: list[str], folder: Path, read):
                    return stage_together(board, me, paths, folder, read)
        else:
            input_dir = Path(tmp) / INPUT
            unpack_files(where, input_dir)
            del where

        try:  # staged while the parent stages and settles the run
            stage = lambda: stage_job(input_dir, scratch, lambda frames: True, together)  # noqa: E731
            n = help_with_windows(board, me, stage, job_calibration(input_dir), job_options(input_dir),
                                  _others_waiting(rq_job, token))
        except Exception:  # noqa: BLE001 - the parent solves what a helper did not
            traceback.print_exc()
            return {"status": "failed", "error": "the helper stopped", "worker": worker}
    return {"status": "helped", "windows": n, "worker": worker}
