"""The REST API's data as pydantic models: what clients send and get back (``openapi.yaml``).

Separate from the job table (:mod:`service.store`): a :class:`JobOut` is built from a stored row.
"""

from __future__ import annotations

import time
from datetime import datetime, timezone
from typing import TYPE_CHECKING, Any, Literal, cast
from urllib.parse import quote

from pydantic import BaseModel, Field

from graph.export import REGISTRY, available
from graph.types import STAGES as SOLVER_STAGES
from service.errors import strip_paths, without_paths
from service.store import COMPILING, DONE, READING, RENDERING, STARTING, WRITING, ErrorKind, Job, JobStatus
from service.store.jobfiles import (
    DOWNLOADS,
    EXPORT_FILES,
    GROUP_FORMATS,
    RESULT_FILES,
    download_name,
    individual_names,
)

if TYPE_CHECKING:
    ResultFormat = str
else:  # the download formats, a Literal made from the registry at import
    ResultFormat = Literal[tuple(DOWNLOADS)]

# a job's own result files as the API and the job page name them: format -> (label, what the file holds);
# the export formats say it themselves (graph.export.Format's label and help)
RESULT_LABELS: dict[str, tuple[str, str]] = {
    "csv": ("CSV", "Anipose 3D table: x, y, z, error, cameras and score per marker and frame"),
    "h5": ("HDF5", "everything: positions, uncertainty, reprojections, residuals, pose parameters"),
    "json": ("JSON", "what the job page draws (positions and their sd), for your own plots"),
    "report": ("Report", "the solver's report (JSON)"),
}
DOWNLOAD_LABELS: dict[str, tuple[str, str]] = {
    name: RESULT_LABELS[name] if name in RESULT_FILES else (REGISTRY[name].label, REGISTRY[name].help)
    for name in DOWNLOADS}


def offered_formats() -> list[str]:
    """The download formats this server can give: its own files, and the exports whose libraries
    are installed here."""
    return [f for f in DOWNLOADS if f in RESULT_FILES or available(f)]


def formats_help() -> str:
    """Every download format with its label and what its file holds, for the API's documentation of
    ``?format=``."""
    extra = [name for name in EXPORT_FILES if REGISTRY[name].needs]
    return ("; ".join(f"{name}: {label}, {what}" for name, (label, what) in DOWNLOAD_LABELS.items()) +
            f". {', '.join(EXPORT_FILES)} are made on the first download" +
            (f" ({', '.join(extra)} where the server has acinoset[export])" if extra else "") +
            "; GET /v1/formats lists them and which this server gives")


# What a job's progress can say it is doing, in order: the service's own stages around the solver's
# (each method reports only some of those); the solver's "done" comes before the results are written.
STAGES: tuple[str, ...] = (COMPILING, STARTING, READING, *(s for s in SOLVER_STAGES if s != DONE), WRITING, RENDERING,
                           DONE)


class ErrorBody(BaseModel):
    """Every error answer: one line saying what is wrong."""

    detail: str = Field(examples=["cam3.csv: no 'likelihood' column for bodypart nose"])


class Progress(BaseModel):
    stage: str | None = Field(None, description="what the job is doing, one of: " + ", ".join(STAGES))
    fraction: float | None = Field(None, description="share of the whole solve done, 0 to 1")
    iteration: int | None = Field(None, description="optimiser iteration")
    cost: float | None = Field(None, description="optimiser cost at that iteration")
    detail: str | None = Field(None, description="where the stage is, in words (a long run: its windows done "
                                                 "and the time left)", examples=["window 12 of 36, 40 s left"])


class Timings(BaseModel):
    created_at: datetime
    started_at: datetime | None = Field(None, description="start of the latest attempt")
    finished_at: datetime | None = None
    queued_seconds: float | None = Field(None, description="from submission to the start of the latest attempt")
    run_seconds: float | None = Field(None, description="of the latest attempt, so far or in all")


class InputFile(BaseModel):
    name: str = Field(description="the file name as uploaded")
    bytes: int
    frames: int | None = None
    bodyparts: int | None = None


class Inputs(BaseModel):
    cameras: int
    frames: int = Field(description="frames in the longest keypoint file")
    bodyparts: list[str]
    keypoints: list[InputFile] = Field(description="one per camera, in the calibration's order")
    calibration: InputFile
    calibration_id: str | None = Field(None, description="the calibration made on this server that the job "
                                                         "was given (GET /v1/calibrations/{id}), if one was")
    skeleton: InputFile | None = None
    videos: list[InputFile] | None = Field(None, description="each camera's video, when the job was given them")
    individuals: int = Field(1, description="the most individuals one keypoint file holds (several: each camera's "
                                            "detections are assigned to individuals and each is solved)")


class ResultSummary(BaseModel):
    """The headline numbers of a succeeded solve; the whole report is ``GET .../result?format=report``."""

    method: str | None = None
    skeleton: str | None = None
    frames: int | None = None
    cameras: int | None = None
    markers: int | None = None
    iterations: int | None = None
    cost: float | None = None
    reprojection_rmse_px: float | None = None
    observations: int | None = None
    outliers: int | None = None
    seconds: dict[str, float | None] = Field(default_factory=dict)
    motion_scales: dict[str, float] | None = Field(
        None, description="the smoothing fitted to the data (motion_scale \"auto\"), per group; give it back as "
                          "options.motion_scale, with motion_orders as options.motion_order, to solve other runs "
                          "with it")
    motion_orders: dict[str, int] | None = Field(None, description="the order each fitted scale is for")
    warnings: list[str] = Field(default_factory=list)
    formats: list[ResultFormat] = Field(default_factory=offered_formats)
    identity: dict[str, Any] | None = Field(
        None, description="several individuals: who is who (their names, in order; count found or given; the 2D "
                          "identity switches corrected per camera); the headline numbers above are the first's, and "
                          "each one's files are downloaded with &individual=NAME (links.individuals)")


class Links(BaseModel):
    self: str
    result: dict[str, str] | None = Field(None, description="download link per format, once succeeded (a job of "
                                                            "several individuals: its report and its page's view "
                                                            "of them all; each one's in individuals)")
    cancel: str | None = Field(None, description="DELETE this to cancel (active) or delete (finished) the job")
    videos: str | None = Field(None, description="the labelled videos, once succeeded, when the job had videos")
    individuals: dict[str, dict[str, str]] | None = Field(
        None, description="several individuals: each one's download link per format, once succeeded")


class JobOut(BaseModel):
    id: str
    owner: str
    label: str | None = Field(None, description="the user's name for the run (options.label at submission)")
    status: JobStatus
    has_warnings: bool = Field(False, description="succeeded, with warnings in its report (result.warnings): "
                                                  "check them before trusting the result")
    attempts: int = Field(description="runs started so far (a run interrupted by a crash is tried again)")
    max_attempts: int
    progress: Progress | None = None
    timings: Timings
    options: dict[str, Any]
    inputs: Inputs
    error: str | None = Field(None, description="why the job failed")
    error_kind: ErrorKind | None = Field(
        None, description="what failed: input (a file or option the solver refused: fix it and submit again), "
                          "limit (a limit of this server: time, memory), interrupted (its runs kept dying), "
                          "internal (a fault of the software: report the job id)")
    interruption: str | None = Field(None, description="the latest run that was interrupted, and why")
    worker: str | None = Field(None, description="host:pid (embedded) or worker name (rq) of the latest run")
    result: ResultSummary | None = None
    links: Links


class VideoOut(BaseModel):
    view: str = Field(description="a camera's number (from 1), 3d (the skeleton in 3D) or combined (all in a grid)")
    href: str = Field(description="the MP4 (H.264), with an access key a <video> element can use; it takes "
                                  "HTTP Range requests, so players can seek")


class VideoList(BaseModel):
    videos: list[VideoOut]
    expires_at: datetime = Field(description="when the links' access keys expire (or the server restarts)")


class JobList(BaseModel):
    jobs: list[JobOut]
    total: int = Field(description="jobs matching the filter, on all pages")
    next_cursor: str | None = Field(None, description="pass as ?cursor= for the next page")
    next: str | None = Field(None, description="the next page's URL")


class FormatOut(BaseModel):
    """A download format of a succeeded job's result: ``GET /v1/jobs/{id}/result?format=<name>``."""

    name: str = Field(examples=["nwb"])
    label: str = Field(description="a short name for it, as on a button", examples=["NWB"])
    description: str = Field(description="what the file holds")
    extension: str = Field(description="the downloaded file is named <job id><extension>", examples=[".var.csv"])
    media_type: str = Field(examples=["application/x-hdf5"])
    export: bool = Field(description="made from the job's result on its first download, as `acinoset export` "
                                     "writes it (else written by the solve)")
    offered: bool = Field(description="whether this server gives it (an export needs its libraries installed "
                                      "here); a succeeded job's links.result has a link for each one offered")


def download_formats() -> list[FormatOut]:
    """Every download format, in the order of :data:`service.store.jobfiles.DOWNLOADS`."""
    offered = set(offered_formats())
    return [FormatOut(name=name, label=label, description=what, extension=download_name("", name),
                      media_type=DOWNLOADS[name][1], export=name in EXPORT_FILES, offered=name in offered)
            for name, (label, what) in DOWNLOAD_LABELS.items()]


class SkeletonOut(BaseModel):
    name: str
    kind: str = Field(description="kinematic (a tree with pose parameters) or points (free 3D points)")
    markers: list[str] | None = Field(None, description="None for points: the keypoint files' bodyparts")
    parameters: int | None = None
    description: str = ""


class Limits(BaseModel):
    max_upload_bytes: int
    max_frames: int
    max_bodyparts: int
    max_cameras: int
    max_active_jobs: int


class Me(BaseModel):
    name: str
    admin: bool
    active_jobs: int
    jobs: dict[str, int]
    limits: Limits


class Disk(BaseModel):
    free_bytes: int = Field(description="free space on the data dir's disk")
    total_bytes: int
    min_free_bytes: int = Field(description="below this, submissions are refused (507) and health is degraded")


class Health(BaseModel):
    status: Literal["ok", "starting", "degraded"] = Field(
        description="ok: ready to take and run jobs; starting: up, its solver not ready yet (compiling); "
                    "degraded: it cannot run jobs or has no room for them (detail says why)")
    ready: bool = Field(description="a job submitted now would be stored and started without delay")
    version: str
    backend: str
    workers: int = Field(description="solves that can run at once (embedded) or connected workers (rq)")
    running: int
    queued: int
    oldest_queued_seconds: float | None = Field(None, description="how long the oldest queued job has waited")
    disk: Disk
    detail: str | None = None


def _ts(t: float | None) -> datetime | None:
    return None if t is None else datetime.fromtimestamp(t, tz=timezone.utc)


def _created(t: float) -> datetime:
    return datetime.fromtimestamp(t, tz=timezone.utc)


def summary_of(report: dict | None) -> ResultSummary | None:
    if not report:
        return None
    keys = ResultSummary.model_fields.keys() - {"formats"}
    summary = ResultSummary(**{k: report[k] for k in keys if report.get(k) is not None})
    summary.warnings = [strip_paths(w) for w in summary.warnings]
    return summary


def _timings(job: Job) -> Timings:
    now = time.time()
    queued = (job.started_at - job.created_at) if job.started_at else (
        (now - job.created_at) if job.status == "queued" else None)
    run = None
    if job.started_at:
        run = (job.finished_at or now) - job.started_at if job.status != "queued" else None
    return Timings(created_at=_created(job.created_at), started_at=_ts(job.started_at),
                   finished_at=_ts(job.finished_at),
                   queued_seconds=queued, run_seconds=run)


def _progress(job: Job) -> Progress | None:
    if job.stage is None and job.fraction is None:
        return None
    return Progress(stage=job.stage, fraction=job.fraction, iteration=job.iteration, cost=job.cost, detail=job.detail)


def job_out(job: Job, base: str = "/v1/jobs") -> JobOut:
    href = f"{base}/{job.id}"
    progress = _progress(job)
    result = summary_of(job.summary) if job.status == "succeeded" else None
    names = individual_names(job.summary) if job.status == "succeeded" else None
    return JobOut(
        id=job.id, owner=job.owner, label=job.label, status=job.status,
        has_warnings=bool(result is not None and result.warnings), attempts=job.attempts, max_attempts=job.max_attempts,
        progress=progress,
        timings=_timings(job),
        options=job.options, inputs=Inputs(**job.inputs), error=without_paths(job.error),
        error_kind=cast(ErrorKind | None, job.error_kind) if job.status == "failed" else None,
        interruption=without_paths(job.interruption),
        worker=job.worker, result=result,
        links=Links(self=href,
                    result={f: f"{href}/result?format={f}" for f in offered_formats()
                            if not names or f in GROUP_FORMATS}
                    if job.status == "succeeded" else None,
                    cancel=href,
                    videos=f"{href}/videos" if job.status == "succeeded" and (job.inputs or {}).get("videos")
                    else None,
                    individuals={n: {f: f"{href}/result?format={f}&individual={quote(n, safe='')}"
                                     for f in offered_formats()} for n in names} if names else None))


# -- batches ---------------------------------------------------------------------------------------

BatchStatus = Literal["running", "succeeded", "partial", "failed"]


class BatchTrial(BaseModel):
    trial: str = Field(description="session/trial, as acinoset anipose names it")
    job_id: str | None = Field(None, description="the trial's job (none if it was refused)")
    status: Literal["queued", "running", "succeeded", "failed", "cancelled", "refused", "deleted"]
    error: str | None = Field(None, description="why it was refused or failed")
    link: str | None = Field(None, description="the job")


class BatchOut(BaseModel):
    id: str
    owner: str
    created_at: datetime
    project: str = Field(description="the project folder's name")
    status: BatchStatus = Field(description="running while any job is queued or running; then succeeded (all), "
                                            "failed (none) or partial")
    counts: dict[str, int] = Field(description="trials per status")
    trials: list[BatchTrial]
    ignored: list[str] = Field(default_factory=list, description="config.toml keys with no equivalent here")
    notes: list[str] = Field(default_factory=list, description="what was skipped while reading the project")
    links: dict[str, str]


def batch_out(view: dict, base: str = "/v1") -> BatchOut:
    """A batch as the API shows it, from :meth:`service.core.batches.BatchService.status`."""
    trials = [BatchTrial(**t, link=f"{base}/jobs/{t['job_id']}" if t.get("job_id") else None)
              for t in view["trials"]]
    return BatchOut(id=view["id"], owner=view["owner"], created_at=_created(view["created_at"]),
                    project=view["project"],
                    status=view["status"], counts=view["counts"], trials=trials, ignored=view["ignored"],
                    notes=view["notes"], links={"self": f"{base}/batches/{view['id']}"})


# -- calibrations ----------------------------------------------------------------------------------

class CalibrationInput(BaseModel):
    name: str = Field(description="the file name as stored (the uploaded name, made safe)")
    bytes: int
    views: int | None = Field(None, description="board views in a detections file")
    frames: int | None = Field(None, description="frames of a video")
    resolution: list[int] | None = Field(None, description="[width, height] of the camera's images")


class CalibrationInputs(BaseModel):
    cameras: int
    detections: list[CalibrationInput] = Field(default_factory=list, description="one per camera, in camera order")
    videos: list[CalibrationInput] = Field(default_factory=list, description="one per camera, if videos were given")
    intrinsics: list[CalibrationInput] = Field(default_factory=list, description="camera JSON per camera, if given")
    refined_from: str | None = Field(None, description="a refinement: the solve job whose rig and keypoints it took")
    keypoints: list[CalibrationInput] = Field(default_factory=list, description="a refinement: the keypoint files, "
                                                                                "one per camera")


class CalibrationOut(BaseModel):
    id: str = Field(description="the calibration's id; a solve job may name it as calibration_id")
    owner: str
    label: str | None = None
    status: JobStatus
    attempts: int
    max_attempts: int
    progress: Progress | None = None
    timings: Timings
    options: dict[str, Any] = Field(description="board (its spec), model, lens, origin, every")
    inputs: CalibrationInputs
    error: str | None = Field(None, description="why it failed (e.g. the cameras share no board view)")
    error_kind: ErrorKind | None = None
    worker: str | None = None
    report: dict[str, Any] | None = Field(
        None, description="once succeeded: rms_px, per camera (name, rms_px, views_used, views_dropped, position "
                          "and rotation uncertainty), the overlap graph, baselines_m, warnings")
    links: dict[str, str] = Field(description="self, cancel, page (the web page), and once succeeded one link per "
                                              "output file")


def calibration_out(job: Job, base: str = "/v1/calibrations") -> CalibrationOut:
    """A calibration job as the API shows it (the same row as a solve, other inputs and outputs)."""
    href = f"{base}/{job.id}"
    links = {"self": href, "cancel": href, "page": f"/calibrations/{job.id}"}
    if job.status == "succeeded":
        links.update({name: f"{href}/{name}" for name in job.summary.get("files", [])} if job.summary else {})
    return CalibrationOut(
        id=job.id, owner=job.owner, label=job.label, status=job.status, attempts=job.attempts,
        max_attempts=job.max_attempts, progress=_progress(job), timings=_timings(job),
        options={k: v for k, v in job.options.items() if k != "kind"}, inputs=CalibrationInputs(**job.inputs),
        error=without_paths(job.error),
        error_kind=cast(ErrorKind | None, job.error_kind) if job.status == "failed" else None,
        worker=job.worker, report=job.summary if job.status == "succeeded" else None, links=links)


class CalibrationList(BaseModel):
    calibrations: list[CalibrationOut]
    total: int = Field(description="calibrations matching the filter, on all pages")
    next_cursor: str | None = Field(None, description="pass as ?cursor= for the next page")
