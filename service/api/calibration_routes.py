"""The REST API of calibrations, version 1: submit board detections, poll, download the rig.

Thin like :mod:`service.api.routes` (whose router settings, caller and job service it shares, from
:mod:`service.api.deps`); the work is :mod:`service.core.calibrations`'."""

from __future__ import annotations

from typing import TYPE_CHECKING, Annotated, Literal

from fastapi import APIRouter, Depends, File, Form, Query, Response, Security, UploadFile
from fastapi.responses import FileResponse

from service.api.deps import (
    AUTH_ERRORS,
    BAD_REQUEST,
    BEARER,
    SERVER_ERROR,
    UPLOAD_ERRORS,
    CurrentUser,
    Jobs,
    Responses,
    error_doc,
)
from service.api.models import CalibrationList, CalibrationOut, calibration_out
from service.core.calibrations import CalibrationService
from service.core.jobs import Upload
from service.store import JobStatus
from service.store.jobfiles import CALIBRATION_FILES, CALIBRATION_KIND

router = APIRouter(responses={**AUTH_ERRORS, **BAD_REQUEST, **SERVER_ERROR}, dependencies=[Security(BEARER)],
                   tags=["calibrations"])
NOT_FOUND: Responses = {404: error_doc("No such calibration, or it belongs to another user")}
if TYPE_CHECKING:
    CalibrationFile = str
else:  # the files a calibration writes, a Literal made from jobfiles at import
    CalibrationFile = Literal[tuple(CALIBRATION_FILES)]


async def _calibrations(jobs: Jobs) -> CalibrationService:
    return CalibrationService(jobs)


Calibrations = Annotated[CalibrationService, Depends(_calibrations)]


@router.post(
    "/v1/calibrations", status_code=202, response_model=CalibrationOut, summary="Calibrate a rig",
    responses={**UPLOAD_ERRORS,
               413: error_doc("Upload or camera count over this server's limits, or the caller's storage full"),
               422: error_doc("A bad board spec, a detections or camera file the readers refuse, fewer than two "
                              "cameras, or bad options"),
               429: error_doc("The caller already has the most queued and running jobs allowed")})
def submit_calibration(
    user: CurrentUser, calibrations: Calibrations, response: Response,
    board: Annotated[str, Form(description="checkerboard:COLSxROWS:SQUARE_M (inner corners, square side in metres) "
                                           "or charuco:SQUARESXxSQUARESY:SQUARE_M:MARKER_M:DICT")],
    # the optional fields' ignores: the spec declares a file (or string), not a nullable one,
    # and FastAPI passes None when the field is absent
    detections: Annotated[list[UploadFile], File(
        description="board detections, AcinoSet's detections JSON (board_shape, board_square_len, "
                    "camera_resolution, points: {frame: corners}), one per camera, repeated, in camera order; views "
                    "are matched across cameras by frame name (or give videos)")] = None,  # type: ignore[assignment]
    videos: Annotated[list[UploadFile], File(
        description="instead of detections: a short video of the board per camera, in camera order, filmed at the "
                    "same instants (frames are matched by index); the board is found on the server in every "
                    "options.every-th frame")] = None,  # type: ignore[assignment]
    intrinsics: Annotated[list[UploadFile], File(
        description="optional: each camera's intrinsics (AcinoSet camera JSON: camera_resolution, k, d), in camera "
                    "order; calibrated from the views if not given")] = None,  # type: ignore[assignment]
    options: Annotated[str, Form(description='JSON object: {"model": "fisheye" (default) or "pinhole", "lens": '
                                             '"full" (default: every coefficient) or "k1" (Anipose\'s: one focal '
                                             'length, the principal point at the centre, radial k1 alone), "origin": '
                                             '"camera1" (default) or "board:FRAME", "every": N (videos: every N-th '
                                             'frame, default 1), "label": "..."}')] = "{}",
) -> CalibrationOut:
    """Check the files (each detections file is read against the board), store them and queue the
    calibration: one bundle adjustment of camera and board poses. Answers 202; poll ``links.self``
    until ``status`` is ``succeeded`` (then ``report`` and a link per output file) or ``failed``."""
    job = calibrations.submit(user, [Upload(f.filename, f.file) for f in detections or []],
                              [Upload(f.filename, f.file) for f in intrinsics or []], board, options,
                              [Upload(f.filename, f.file) for f in videos or []])
    out = calibration_out(job)
    response.headers["Location"] = out.links["self"]
    return out


@router.post(
    "/v1/jobs/{job_id}/refinement", status_code=202, response_model=CalibrationOut,
    summary="Refine a job's rig from its keypoints",
    responses={404: error_doc("No such job of the caller's"),
               413: error_doc("The caller's storage full"),
               422: error_doc("Bad options, or a job of several animals"),
               429: error_doc("The caller already has the most queued and running jobs allowed")})
def submit_refine(
    job_id: str, user: CurrentUser, calibrations: Calibrations, response: Response,
    options: Annotated[str, Form(description='JSON object: {"likelihood": 0.9 (keypoints at least this confident), '
                                             '"refine_intrinsics": [] or ["focal"] or ["focal", "k1"], "focal_sd": '
                                             '0.02, "k1_sd": 0.02, "pose_sd": 1 (degrees; a camera the keypoints '
                                             'would move beyond 3 sd is held), "label": "..."}')] = "{}",
) -> CalibrationOut:
    """Queue ``acinoset calibrate refine`` on the rig and keypoints of the caller's solve job
    ``job_id`` (copied into a new calibration): a camera far off posed again from the others, the
    poses (and optionally focal lengths and k1) adjusted, the new rig kept only when it predicts
    each camera from the others better on held-out frames. Poll ``links.self``; once succeeded,
    ``report`` has each camera's change and leave-one-camera-out error before and after, and
    ``calibration.toml`` is the rig to use (the old one when the check kept it)."""
    job = calibrations.submit_refine(user, job_id, options)
    out = calibration_out(job)
    response.headers["Location"] = out.links["self"]
    return out


@router.get("/v1/calibrations", response_model=CalibrationList, summary="List calibrations")
def list_calibrations(
    user: CurrentUser, calibrations: Calibrations,
    status: Annotated[list[JobStatus] | None, Query(description="only calibrations in these states")] = None,
    limit: Annotated[int, Query(ge=1, description="calibrations per page (at most 500)")] = 50,
    cursor: Annotated[str | None, Query(pattern=r"^[0-9]{1,18}$",
                                        description="next_cursor of the previous page")] = None,
) -> CalibrationList:
    """The caller's calibrations, newest first (an admin's call lists everyone's)."""
    rows, total, nxt = calibrations.jobs.list(user, list(status) if status else None, limit, cursor, None,
                                              kind=CALIBRATION_KIND)
    return CalibrationList(calibrations=[calibration_out(j) for j in rows], total=total, next_cursor=nxt)


@router.get("/v1/calibrations/{calibration_id}", response_model=CalibrationOut, summary="A calibration's status",
            responses=NOT_FOUND)
async def get_calibration(calibration_id: str, user: CurrentUser, calibrations: Calibrations) -> CalibrationOut:
    """Status and progress; once succeeded, the quality report (RMS, per camera views and
    uncertainty, baselines) and the links to its files."""
    return calibration_out(calibrations.visible(user, calibration_id))


@router.get(
    "/v1/calibrations/{calibration_id}/{file}", response_class=FileResponse, summary="Download a calibration file",
    responses={200: {"description": "The file", "content": {
                   "application/toml": {"schema": {"type": "string"}},
                   "application/json": {"schema": {"type": "object"}},
                   "image/png": {"schema": {"type": "string", "format": "binary"}}}},
               **NOT_FOUND, 409: error_doc("The calibration has not succeeded (yet)")})
def get_calibration_file(calibration_id: str, file: CalibrationFile, user: CurrentUser,
                         calibrations: Calibrations) -> FileResponse:
    """calibration.toml (Anipose), scene.json (AcinoSet's scene; fisheye rigs of one resolution only),
    report.json, and the figures rig.png, residuals.png and coverage.png."""
    path = calibrations.file(user, calibration_id, file)
    return FileResponse(path, media_type=CALIBRATION_FILES[file], filename=f"{calibration_id}.{file}")


@router.delete(
    "/v1/calibrations/{calibration_id}", response_model=CalibrationOut, summary="Cancel or delete a calibration",
    responses={200: {"description": "It was queued or running: it is cancelled"},
               204: {"description": "It had finished: it is deleted with its files"}, **NOT_FOUND})
def delete_calibration(calibration_id: str, user: CurrentUser, calibrations: Calibrations):
    job = calibrations.jobs.cancel_or_delete(user, calibration_id, CALIBRATION_KIND)
    if job is None:
        return Response(status_code=204)
    return calibration_out(job)
