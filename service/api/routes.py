"""The REST API, version 1. Thin: each route checks who calls and hands over to :mod:`service.core.jobs`."""

from __future__ import annotations

import re
import shutil
import time
from datetime import datetime, timezone
from typing import Annotated, Literal

from fastapi import APIRouter, Depends, File, Form, HTTPException, Query, Request, Response, Security, UploadFile
from fastapi.responses import FileResponse, JSONResponse, PlainTextResponse
from pydantic import BeforeValidator

import graph
from graph.errors import InputError
from graph.skeleton import available_skeletons, load_skeleton
from graph.types import Method
from service.api import media, metrics
from service.api.auth import current_user
from service.api.deps import (
    AUTH_ERRORS,
    BAD_REQUEST,
    BEARER,
    SERVER_ERROR,
    UPLOAD_ERRORS,
    CurrentUser,
    JobBackend,
    Jobs,
    JobTable,
    Responses,
    ServerSettings,
    error_doc,
)
from service.api.models import (
    BatchOut,
    Disk,
    FormatOut,
    Health,
    JobList,
    JobOut,
    JobStatus,
    Limits,
    Me,
    ResultFormat,
    SkeletonOut,
    VideoList,
    VideoOut,
    batch_out,
    download_formats,
    formats_help,
    job_out,
)
from service.core.batches import BatchService
from service.core.calibrations import calibration_upload
from service.core.jobs import Upload
from service.store.jobfiles import DOWNLOADS, JOB_ID, download_name

IsoTime = Annotated[datetime, BeforeValidator(lambda v: _iso_only(v))]

NOT_FOUND: Responses = {404: error_doc("No such job, or it belongs to another user")}

router = APIRouter(responses={**AUTH_ERRORS, **BAD_REQUEST, **SERVER_ERROR}, dependencies=[Security(BEARER)])
public = APIRouter(responses=SERVER_ERROR)


@router.post(
    "/v1/jobs", status_code=202, response_model=JobOut, tags=["jobs"], summary="Submit a job",
    responses={**UPLOAD_ERRORS,
               413: error_doc("Upload, frame count, bodyparts, camera count or the caller's storage over this "
                              "server's limits"),
               403: error_doc("video_paths on a server without a video root, or outside it"),
               422: error_doc("A file the readers refuse (the detail names it), bad options, or videos that do not "
                              "match the keypoint files"),
               429: error_doc("The caller already has the most queued and running jobs allowed"),
               404: error_doc("calibration_id names no succeeded calibration of the caller"),
               409: error_doc("calibration_id names a calibration that has not succeeded (yet)")})
def submit_job(
    user: CurrentUser, jobs: Jobs, response: Response,
    keypoints: Annotated[list[UploadFile], File(
        description="DeepLabCut keypoints (.csv or .h5), one file per camera, repeated, in the calibration's order",
        json_schema_extra={"minItems": 1})],
    # the optional fields' ignores: the spec declares a file (or string), not a nullable one,
    # and FastAPI passes None when the field is absent
    calibration: Annotated[UploadFile, File(
        description="AcinoSet scene JSON or Anipose calibration TOML (or give calibration_id)")] = None,  # type: ignore[assignment]
    calibration_id: Annotated[str, Form(
        description="instead of a calibration file: the id of one of the caller's succeeded calibrations "
                    "(POST /v1/calibrations)")] = None,  # type: ignore[assignment]
    options: Annotated[str, Form(
        description='JSON object of solve options, e.g. {"method": "fte", "fps": 120, "skeleton": "cheetah", '
                    '"likelihood_threshold": 0.5, "measurement_std_px": 5}; fps (the cameras\' frame rate) is '
                    'required unless the keypoint files or the videos record one (SLEAP analysis files may, '
                    'DeepLabCut files never do); measurement_std_px "auto" measures '
                    'the detection noise from the data, motion_scale "auto" fits the smoothing to it (the default '
                    'for fte on free points; 1 otherwise), motion_order 1, 2, 3 (the default) or "auto" the order '
                    'of the motion prior (an earlier report\'s motion_scales and motion_orders given back reuse its '
                    'fitted smoothing); body "estimate" (the default), "model" or "given" with '
                    'body_lengths {group: metres}; sync "given" (the default, with time_offsets in frames per '
                    'camera) or "estimate"; see GET /v1/skeletons')] = "{}",
    # a file or nothing: declared as a file only (a form field "null" is no file, and is refused)
    skeleton: Annotated[UploadFile, File(
        description="optional skeleton spec (.toml) to use instead of a named skeleton")] = None,  # type: ignore[assignment]
    videos: Annotated[list[UploadFile], File(
        description="optional: each camera's video, repeated, in the keypoint files' order (the footage the "
                    "keypoints came from, one frame per row); the job then also renders the labelled videos")] = None,  # type: ignore[assignment]
    video_paths: Annotated[list[str], Form(
        description="optional, instead of videos: each camera's video as a path on the server's shared storage, "
                    "repeated, under the folder its admin allows (ACINOSET_VIDEO_ROOT; absolute or relative to it)")
    ] = None,  # type: ignore[assignment]
) -> JobOut:
    """Validate the files with the library's readers, store them and queue the solve. Answers 202 with
    the job; poll its ``links.self`` until ``status`` is ``succeeded`` or ``failed``."""
    given = Upload(calibration.filename, calibration.file) if calibration is not None else None
    with calibration_upload(jobs, user, given, calibration_id) as cal:
        job = jobs.submit(user, [Upload(f.filename, f.file) for f in keypoints], cal,
                          options, Upload(skeleton.filename, skeleton.file) if skeleton is not None else None,
                          videos=[Upload(f.filename, f.file) for f in videos or []] or None,
                          video_paths=video_paths or None, calibration_id=calibration_id)
    out = job_out(job)
    response.headers["Location"] = out.links.self
    return out


@router.get("/v1/jobs", response_model=JobList, tags=["jobs"], summary="List jobs",
            responses={403: error_doc("A non-admin asked for another user's jobs"), 422: error_doc("Bad filter")})
def list_jobs(
    user: CurrentUser, jobs: Jobs, request: Request,
    status: Annotated[list[JobStatus] | None,
                      Query(description="only jobs in these states (repeat for several)")] = None,
    limit: Annotated[int, Query(ge=1, description="jobs per page (at most 500)")] = 50,
    cursor: Annotated[str | None,
                      Query(pattern=r"^[0-9]{1,18}$", description="next_cursor of the previous page")] = None,
    owner: Annotated[str | None, Query(description="admins: only this user's jobs")] = None,
    label: Annotated[str | None,
                     Query(max_length=200, description="only jobs whose label contains this (any case)")] = None,
    method: Annotated[Method | None, Query(description="only jobs solved with this method")] = None,
    since: Annotated[IsoTime | None, Query(description="only jobs submitted at or after this time (ISO 8601)")] = None,
    warnings: Annotated[bool | None, Query(
        description="true: only jobs that succeeded with warnings; false: only those that succeeded without")] = None,
) -> JobList:
    """The caller's jobs, newest first (an admin's call lists everyone's)."""
    rows, total, next_cursor = jobs.list(user, list(status) if status else None, limit, cursor, owner, label=label,
                                         method=method, since=_epoch(since), warnings=warnings)
    nxt = None
    if next_cursor is not None:
        nxt = f"{request.url.path}?{request.url.include_query_params(cursor=next_cursor).query}"
    return JobList(jobs=[job_out(j) for j in rows], total=total, next_cursor=next_cursor, next=nxt)


def _iso_only(value):
    """A time as ISO 8601 text only: pydantic would also take a bare number as seconds since 1970."""
    if isinstance(value, str) and re.fullmatch(r"\s*[-+]?[0-9.eE+-]+\s*", value):
        raise ValueError("give a date and time in ISO 8601, such as 2026-12-01T20:00:00Z")
    return value


def _epoch(t: datetime | None) -> float | None:
    """Seconds since the epoch; a time without a zone is UTC."""
    if t is None:
        return None
    return (t if t.tzinfo else t.replace(tzinfo=timezone.utc)).timestamp()


@router.get("/v1/jobs/{job_id}", response_model=JobOut, tags=["jobs"], summary="A job's status",
            responses=NOT_FOUND)
async def get_job(job_id: str, user: CurrentUser, jobs: Jobs) -> JobOut:
    """Status, progress (stage, iteration, cost, fraction), timings, the error when failed and a
    summary of the result when succeeded."""
    # on the event loop: the poll everyone makes is one indexed read, and answering it without a
    # thread-pool hop keeps it quick while uploads arrive
    return job_out(jobs.visible(user, job_id))


def _file_schema(media_type: str) -> dict:
    if media_type == "application/json":
        return {"type": "object"}
    return {"type": "string"} if media_type.startswith("text/") else {"type": "string", "format": "binary"}


@router.get(
    "/v1/jobs/{job_id}/result", tags=["jobs"], summary="Download the result",
    response_class=FileResponse,
    responses={200: {"description": "The result file", "content": {
                   media_type: {"schema": _file_schema(media_type)} for _, media_type in DOWNLOADS.values()}},
               **NOT_FOUND, 409: error_doc("The job has not succeeded (yet)")})
def get_result(job_id: str, user: CurrentUser, jobs: Jobs,
               format: Annotated[ResultFormat, Query(description=formats_help())] = "csv",
               individual: Annotated[str | None, Query(
                   max_length=200, description="a job that solved several individuals: whose result (one of "
                                               "result.identity.individuals); the report alone is the job's")] = None,
               ) -> FileResponse:
    path = jobs.result_file(user, job_id, format, individual)
    return FileResponse(path, media_type=DOWNLOADS[format][1], filename=download_name(job_id, format, individual))


@router.get("/v1/jobs/{job_id}/videos", response_model=VideoList, tags=["videos"], summary="A job's labelled videos",
            responses={**NOT_FOUND, 409: error_doc("The job has not succeeded (yet)")})
def list_videos(job_id: str, user: CurrentUser, jobs: Jobs) -> VideoList:
    """Links to the job's labelled videos (none when it was submitted without videos): each camera's
    footage with the estimate drawn on it, the 3D view and the grid of all, at the footage's rate."""
    job = jobs.visible(user, job_id)
    if job.status != "succeeded":
        jobs.video_file(job, "1")  # says why (409)
    access = media.sign(job.id, user.token_key)
    expires = datetime.fromtimestamp(media.expiry(access), timezone.utc)
    return VideoList(videos=[VideoOut(view=v, href=f"/v1/jobs/{job.id}/videos/{v}?access={access}")
                             for v in jobs.video_views(job)], expires_at=expires)


@router.get(
    "/v1/jobs/{job_id}/videos/{view}", tags=["videos"], summary="Download or stream a labelled video",
    response_class=FileResponse,
    responses={200: {"description": "H.264 in MP4", "content": {"video/mp4": {"schema": {"type": "string",
                                                                                           "format": "binary"}}}},
               206: {"description": "The byte range asked for (Range: bytes=A-B)",
                     "content": {"video/mp4": {"schema": {"type": "string", "format": "binary"}}}},
               400: error_doc("A malformed Range header"),
               401: error_doc("No token, or the link's token was revoked or its user removed"),
               **NOT_FOUND, 409: error_doc("The job has not succeeded (yet)"),
               416: error_doc("A Range beyond the end of the file")})
def get_video(job_id: str, view: str, request: Request, jobs: Jobs,
              access: Annotated[str | None, Query(max_length=200, description="the access key of a link of GET "
                                                  "/v1/jobs/{id}/videos (instead of the Authorization header)")] = None
              ) -> FileResponse:
    """A camera's number (from 1), ``3d`` or ``combined``. Answers Range requests (206), so a
    player can seek without downloading the whole file."""
    key_id = media.signer(job_id, access) if access is not None and JOB_ID.match(job_id) else None
    holder = jobs.store.token_holder(key_id) if key_id else None
    if key_id and holder is None:
        raise HTTPException(401, "the token this video link was made for was revoked or its user removed: "
                                 "list the job's videos again for new links", headers={"WWW-Authenticate": "Bearer"})
    job = jobs.visible(holder or current_user(request), job_id)
    path = jobs.video_file(job, view)
    _check_range(request.headers.get("range"), path.stat().st_size)
    return FileResponse(path, media_type="video/mp4", filename=f"{job.id}.{path.stem}.mp4",
                        content_disposition_type="inline", headers={"Cache-Control": "private, max-age=3600"})


_RANGE = re.compile(r"^bytes=\s*(\d*)\s*-\s*(\d*)\s*(,\s*(\d*)\s*-\s*(\d*)\s*)*$")


def _check_range(header: str | None, size: int) -> None:
    """A ``Range`` header the file can answer, or the refusal as the API's other errors are, JSON
    ``{"detail": ...}`` (the file response itself would answer plain text): 400 for a malformed one,
    416 (with ``Content-Range: bytes */size``) for one that starts past the end."""
    if header is None:
        return
    if len(header) > 1000 or not _RANGE.match(header):
        raise HTTPException(400, f"Range: expected bytes=START-END, got {header[:60]!r}")
    starts = [int(a) for a, b in re.findall(r"(\d*)\s*-\s*(\d*)", header.split("=", 1)[1]) if a]
    if any(s >= size for s in starts):
        raise HTTPException(416, f"Range: starts past the end of the file ({size} bytes)",
                            headers={"Content-Range": f"bytes */{size}"})


@router.get(
    "/v1/jobs/{job_id}/frame", tags=["videos"], summary="One camera's frame with the estimate drawn on it",
    response_class=Response,
    responses={200: {"description": "PNG",
                     "content": {"image/png": {"schema": {"type": "string", "format": "binary"}}}},
               **NOT_FOUND, 409: error_doc("The job has not succeeded (yet)"),
               422: error_doc("No such camera or frame")})
def get_frame(job_id: str, user: CurrentUser, jobs: Jobs,
              camera: Annotated[int, Query(ge=1, le=999, description="the camera, from 1, in the job's order")] = 1,
              n: Annotated[int, Query(ge=0, description="the frame, from 0")] = 0) -> Response:
    """Frame ``n`` of camera ``camera``'s own video with the detections and the reprojected
    skeleton drawn on it (the frame picker); for jobs submitted with videos."""
    return Response(jobs.frame_png(user, job_id, camera, n), media_type="image/png",
                    headers={"Cache-Control": "private, max-age=3600"})


@router.delete(
    "/v1/jobs/{job_id}", tags=["jobs"], summary="Cancel or delete a job",
    response_model=JobOut,
    responses={200: {"description": "The job was queued or running: it is cancelled and its solve stopped"},
               204: {"description": "The job had finished: it is deleted with its files"}, **NOT_FOUND})
def delete_job(job_id: str, user: CurrentUser, jobs: Jobs):
    job = jobs.cancel_or_delete(user, job_id)
    if job is None:
        return Response(status_code=204)
    return job_out(job)


async def _batches(request: Request) -> BatchService:
    return BatchService(request.app.state.jobs)


Batches = Annotated[BatchService, Depends(_batches)]


@router.post(
    "/v1/batches", status_code=202, response_model=BatchOut, tags=["batches"],
    summary="Submit an Anipose project: a job per trial",
    responses={**UPLOAD_ERRORS,
               413: error_doc("The archive is over this server's upload limit"),
               422: error_doc("Not a zip, no config.toml, no trials, or bad options"),
               429: error_doc("More trials than the caller may still queue")})
def submit_batch(
    user: CurrentUser, batches: Batches, response: Response,
    project: Annotated[UploadFile, File(description="zip archive of an Anipose project: config.toml at its top "
                                                    "(or in its one top folder), sessions, pose-2d/*.h5, "
                                                    "calibration/")],
    options: Annotated[str, Form(description="JSON object of solve options overriding the project's "
                                             "(config.toml [triangulation] and [acinoset])")] = "{}",
) -> BatchOut:
    """Read the project as ``acinoset anipose`` does and queue every trial as a job. A trial whose
    files the readers refuse is listed with its error; the others are queued."""
    record = batches.submit(user, Upload(project.filename, project.file), options)
    out = batch_out(batches.status(record))
    response.headers["Location"] = out.links["self"]
    return out


@router.get("/v1/batches/{batch_id}", response_model=BatchOut, tags=["batches"], summary="A batch's status",
            responses=NOT_FOUND)
def get_batch(batch_id: str, user: CurrentUser, batches: Batches) -> BatchOut:
    """Each trial's job and status, the counts per status and the batch's status."""
    return batch_out(batches.status(batches.visible(user, batch_id)))


@router.get("/v1/skeletons", response_model=list[SkeletonOut], tags=["reference"], summary="Skeletons")
def list_skeletons(user: CurrentUser) -> list[SkeletonOut]:
    """The skeletons a job's ``options.skeleton`` can name."""
    out = []
    for name in available_skeletons():
        if name == "points":
            out.append(SkeletonOut(name=name, kind="points", description="free 3D points, one per bodypart of "
                                   "the keypoint files (any animal); no kinematic model"))
            continue
        try:
            sk = load_skeleton(name)
        except InputError as e:
            out.append(SkeletonOut(name=name, kind="unknown", description=f"cannot be loaded: {e}"))
            continue
        out.append(SkeletonOut(name=name, kind=sk.kind, markers=list(sk.markers), parameters=sk.n_params,
                               description=sk.description))
    return out


@router.get("/v1/formats", response_model=list[FormatOut], tags=["reference"], summary="Result formats")
def list_formats(user: CurrentUser) -> list[FormatOut]:
    """Every format a succeeded job's result can be downloaded in (``GET /v1/jobs/{id}/result?format=``):
    its label, what the file holds, its file extension and media type, and whether this server gives it."""
    return download_formats()


@router.get("/v1/me", response_model=Me, tags=["reference"], summary="The caller")
def me(user: CurrentUser, store: JobTable, s: ServerSettings) -> Me:
    """Who the token belongs to, its job counts and this server's limits."""
    counts = store.job_counts(user.id)
    return Me(name=user.name, admin=user.is_admin, active_jobs=store.count_active(user.id), jobs=counts,
              limits=Limits(max_upload_bytes=s.max_upload_bytes, max_frames=s.max_frames, max_bodyparts=s.max_bodyparts,
                            max_cameras=s.max_cameras,
                            max_active_jobs=s.max_active_jobs_per_user))


@public.get("/healthz", response_model=Health, tags=["service"], summary="Health",
            responses={503: {"model": Health, "description": "Not ready: starting (the solver compiles), the "
                                                              "backend cannot run jobs, or the disk is nearly full"}})
def healthz(backend: JobBackend, store: JobTable, s: ServerSettings):
    h = backend.health()
    counts = store.status_counts()
    du = shutil.disk_usage(s.jobs_dir)
    oldest = store.oldest_queued_at()
    status: Literal["ok", "starting", "degraded"] = "ok"
    detail = h.get("detail")
    if not h["ok"]:
        status = "degraded"
    elif du.free <= s.min_free_bytes:
        status = "degraded"
        detail = (f"the disk is nearly full: {du.free / 2**20:.0f} MiB free, {s.min_free_bytes / 2**20:.0f} MiB "
                  "kept free (ACINOSET_MIN_FREE_BYTES); submissions are refused")
    elif not h.get("ready", True):
        status = "starting"
    body = Health(status=status, ready=status == "ok", version=graph.__version__, backend=backend.name,
                  workers=h["workers"], running=counts["running"], queued=counts["queued"],
                  oldest_queued_seconds=None if oldest is None else max(0.0, time.time() - oldest),
                  disk=Disk(free_bytes=du.free, total_bytes=du.total, min_free_bytes=s.min_free_bytes), detail=detail)
    if status != "ok":
        return JSONResponse(body.model_dump(), status_code=503)
    return body


@public.get("/metrics", response_class=Response, tags=["service"], summary="Prometheus metrics",
            responses={200: {"content": {metrics.CONTENT_TYPE: {"schema": {"type": "string"}}},
                             "description": "Prometheus text format"},
                       401: error_doc("The server requires a token for metrics (ACINOSET_METRICS_PUBLIC=false)")})
def get_metrics(request: Request, s: ServerSettings, store: JobTable, backend: JobBackend) -> PlainTextResponse:
    if not s.metrics_public:
        current_user(request)
    text = metrics.render(store, backend.name, backend.health())
    return PlainTextResponse(text, media_type=metrics.CONTENT_TYPE)
