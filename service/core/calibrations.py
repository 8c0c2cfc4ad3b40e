"""Calibration jobs: a rig from board detections, solved on the server by :mod:`graph.calibrate`.

A calibration is a job of its own kind: its row in the job table has ``options.kind`` set to
:data:`service.store.jobfiles.CALIBRATION_KIND`, so it is queued, run, cancelled, counted against the
owner's quota and recovered after a crash by the same backends as a solve. Its manifest names the
kind too, and :func:`service.run.worker.solve_job` hands such a job to
:func:`service.run.calibration_run.run_calibration`.

Input layout (under the job's ``input/``)::

    manifest.json        {"kind": "calibration", "detections": [...], "intrinsics": [...], "options": {...}}
    detections/01/<uploaded name>.json    AcinoSet detections JSON, one directory per camera, in order
    intrinsics/01/<uploaded name>.json    optional: AcinoSet camera JSON per camera

A refinement (:meth:`CalibrationService.submit_refine`) takes the rig and the keypoints of one of the
caller's solve jobs instead, copied into its own input (the solve job's layout:
:func:`service.store.jobfiles.keypoints_dir` per camera, the calibration in ``calibration/``), and
its manifest names them under ``"refine"``: ``{"kind": "calibration", "refine": {"job": ID,
"keypoints": [...], "calibration": ..., "individual": ...}, "options": {...}}``. It writes the refined
``calibration.toml`` and the report of ``acinoset calibrate refine``.

Outputs (its ``result/``): :data:`service.store.jobfiles.CALIBRATION_FILES`, the files ``acinoset
calibrate extrinsics`` writes with ``--out --scene --report --figures``.

A solve job may name a succeeded calibration of its owner by id instead of uploading a calibration
file (:func:`calibration_upload`): the calibration's ``calibration.toml`` is stored with the job as
if it had been uploaded, so the job keeps its inputs even if the calibration is deleted later.
"""

from __future__ import annotations

import contextlib
import json
import shutil
from pathlib import Path
from typing import Callable, Iterator

from graph.calibrate.model import LENSES, lens_with_intrinsics
from graph.camera import CAMERA_MODELS
from graph.errors import InputError
from service.core.jobs import JobService, Upload, parse_label, safe_name, stream_size
from service.errors import DISK_FULL, NoSpace, NotFound, NotReady, TooLarge, Unprocessable, storage_full
from service.store import Job, QuotaExceeded, StoreFull, User, jobfiles
from service.store.jobfiles import CALIBRATION_FILES, CALIBRATION_KIND

DETECTIONS_DIR = "detections"
VIDEOS_DIR = "videos"
INTRINSICS_DIR = "intrinsics"
MODELS = tuple(CAMERA_MODELS)  # the camera models a calibration may fit
OPTION_NAMES = ("model", "lens", "origin", "every", "label")
REFINE_OPTION_NAMES = ("likelihood", "refine_intrinsics", "focal_sd", "k1_sd", "pose_sd", "label")


def options_object(text: str | None, known: tuple[str, ...], example: str) -> dict:
    """The ``options`` form field as a JSON object of ``known`` names (empty: ``{}``); refusals are one
    line, ``example`` shown for a value that is not an object."""
    try:
        data = json.loads(text) if text and text.strip() else {}
    except (json.JSONDecodeError, RecursionError):
        raise Unprocessable("options: not a valid JSON object") from None
    if not isinstance(data, dict):
        raise Unprocessable(f"options: must be a JSON object such as {example}")
    unknown = sorted(set(data) - set(known))
    if unknown:
        raise Unprocessable(f"options: unknown option {repr(unknown[0]):.80}; known: {', '.join(known)}")
    return data


def parse_options(board_spec: str, text: str | None) -> tuple[dict, str | None]:
    """The board spec and the ``options`` JSON object (``model``: fisheye|pinhole, ``lens``: what of it is
    fitted, :data:`graph.calibrate.model.LENSES`, ``origin``: camera1|board:FRAME, ``every``: use every
    N-th frame of videos, ``label``) as the job's options, and its label. Refusals are one line."""
    from graph.calibrate import parse_board

    try:
        board = parse_board(board_spec)
    except InputError as e:
        raise Unprocessable(f"board: {e}") from None
    data = options_object(text, OPTION_NAMES, '{"model": "fisheye", "origin": "camera1"}')
    label = parse_label(data.get("label"))
    model = data.get("model", "fisheye")
    if model not in MODELS:
        raise Unprocessable(f"options: model must be one of {', '.join(MODELS)}, not {repr(model):.80}")
    lens = data.get("lens", "full")
    if lens not in LENSES:
        raise Unprocessable(f"options: lens must be one of {', '.join(LENSES)}, not {repr(lens):.80}")
    origin = data.get("origin", "camera1")
    if not isinstance(origin, str) or not (origin == "camera1" or (origin.startswith("board:") and origin[6:])):
        raise Unprocessable(f"options: origin must be camera1 or board:FRAME, not {repr(origin):.80}")
    every = data.get("every", 1)
    if not isinstance(every, int) or isinstance(every, bool) or every < 1:
        raise Unprocessable(f"options: every must be a whole number of frames, at least 1, not {repr(every):.80}")
    return {"kind": CALIBRATION_KIND, "board": board.spec, "model": model, "lens": lens, "origin": origin,
            "every": every}, label


def parse_refine_options(text: str | None) -> tuple[dict, str | None]:
    """The ``options`` JSON object of a refinement (``likelihood``, ``refine_intrinsics``: a list of
    :data:`graph.calibrate.refine.LENS`, ``focal_sd``, ``k1_sd``, ``pose_sd`` (degrees), ``label``) as
    the job's options, and
    its label; refusals are one line."""
    from graph.calibrate.refine import FOCAL_SD, K1_SD, LENS, POSE_SD_DEG

    data = options_object(text, REFINE_OPTION_NAMES, '{"refine_intrinsics": ["focal"]}')
    label = parse_label(data.get("label"))
    out: dict = {"kind": CALIBRATION_KIND, "refine": True}
    for name, default in (("likelihood", 0.9), ("focal_sd", FOCAL_SD), ("k1_sd", K1_SD)):
        v = data.get(name, default)
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not 0 < v <= 1:
            raise Unprocessable(f"options: {name} must be a number in (0, 1], not {repr(v):.80}")
        out[name] = float(v)
    lens = data.get("refine_intrinsics", [])
    if not isinstance(lens, list) or any(x not in LENS for x in lens):
        raise Unprocessable(f"options: refine_intrinsics must be a list of {', '.join(LENS)}, not {repr(lens):.80}")
    out["refine_intrinsics"] = list(dict.fromkeys(lens))
    pose_sd = data.get("pose_sd", POSE_SD_DEG)
    if isinstance(pose_sd, bool) or not isinstance(pose_sd, (int, float)) or not 0 <= pose_sd <= 180:
        raise Unprocessable(f"options: pose_sd must be a number of degrees in [0, 180], not {repr(pose_sd):.80}")
    out["pose_sd"] = float(pose_sd)
    return out, label


class CalibrationService:
    """Submit, find and serve calibration jobs, through the :class:`service.core.jobs.JobService` of solves."""

    def __init__(self, jobs: JobService):
        self.jobs = jobs

    def submit(self, user: User, detections: list[Upload], intrinsics: list[Upload], board_spec: str,
               options_text: str | None, videos: list[Upload] | None = None) -> Job:
        """Check the uploads (every detections file read against the board, every video opened),
        store them, queue the job. ``detections`` or ``videos``, one per camera, not both."""
        s = self.jobs.settings
        videos = videos or []
        if detections and videos:
            raise Unprocessable("upload detections or videos (one per camera), not both")
        kind = "videos" if videos else "detections"
        detections = detections or videos
        if len(detections) < 2:
            raise Unprocessable(f"{kind}: {len(detections)} file(s); a rig needs at least two cameras, one "
                                "detections JSON or video each, in camera order")
        if len(detections) > s.max_cameras:
            raise TooLarge(f"{len(detections)} {kind} files; this server takes at most {s.max_cameras} "
                           "cameras per job (ACINOSET_MAX_CAMERAS)")
        if intrinsics and len(intrinsics) != len(detections):
            raise Unprocessable(f"intrinsics: {len(intrinsics)} files for {len(detections)} cameras; upload one "
                                "per camera, in the same order, or none")
        options, label = parse_options(board_spec, options_text)
        if intrinsics and (why := lens_with_intrinsics(options["lens"])):
            raise Unprocessable(f"options: {why}")
        self.jobs.check_quota(user)
        self.jobs.check_storage(user, sum(stream_size(u.file) for u in [*detections, *intrinsics]))
        return self._queue(user, lambda: self._store_upload(detections, intrinsics, options, videos=bool(videos)),
                           options, label)

    def _queue(self, user: User, stage: Callable[[], tuple[str, dict]], options: dict, label: str | None) -> Job:
        """Stage the job's input (``stage`` returns its id and the inputs' description), add its row and
        queue it; a refusal on the way removes the files."""
        s = self.jobs.settings
        try:
            job_id, inputs = stage()
            try:
                job = self.jobs.store.insert_job(job_id, user.id, self.jobs.backend.name, options, inputs,
                                                 s.max_attempts, max_active=s.max_active_jobs_per_user, label=label)
            except BaseException:
                jobfiles.remove(s.jobs_dir, job_id)
                raise
        except QuotaExceeded:
            self.jobs.check_quota(user)
            raise
        except (OSError, StoreFull) as e:
            if storage_full(e):
                raise NoSpace(DISK_FULL) from None
            raise
        self.jobs.backend.submit(job.id)
        return job

    def _store_upload(self, detections: list[Upload], intrinsics: list[Upload], options: dict,
                      videos: bool = False) -> tuple[str, dict]:
        """Write the files into a new job directory, streamed, and read them in the upload readers'
        processes (:func:`service.core.uploads.inspect_calibration_upload`), not in the API's."""
        s = self.jobs.settings
        with jobfiles.staged_input(s.jobs_dir) as (job_id, input_dir):
            det_paths = [_save(u, input_dir / (VIDEOS_DIR if videos else DETECTIONS_DIR) / f"{i + 1:02d}",
                               f"camera{i + 1}.mp4" if videos else f"camera{i + 1}.json", videos)
                         for i, u in enumerate(detections)]
            cam_paths = [_save(u, input_dir / INTRINSICS_DIR / f"{i + 1:02d}", f"camera{i + 1}.json")
                         for i, u in enumerate(intrinsics)]
            rel = lambda p: p.relative_to(input_dir).as_posix()  # noqa: E731
            described = self.jobs.reader.inspect_calibration(
                input_dir=str(input_dir), views=[rel(p) for p in det_paths], intrinsics=[rel(p) for p in cam_paths],
                board=options["board"], videos=videos)
            inputs = {"cameras": len(det_paths), "videos" if videos else "detections": described,
                      "intrinsics": [{"name": p.name, "bytes": p.stat().st_size} for p in cam_paths]}
            manifest = {"kind": CALIBRATION_KIND, "videos" if videos else "detections": [rel(p) for p in det_paths],
                        "intrinsics": [rel(p) for p in cam_paths], "options": options}
            jobfiles.write_manifest(input_dir, manifest)
        return job_id, inputs

    def submit_refine(self, user: User, job_id: str, options_text: str | None) -> Job:
        """Queue the refinement of the rig of the caller's solve job ``job_id`` from its keypoints (see
        the module): its files copied into the new job, so it keeps them if the solve job is deleted."""
        s = self.jobs.settings
        source = self.jobs.visible(user, job_id)
        if source.owner_id != user.id:  # admins too refine only their own jobs' rigs
            raise NotFound(f"no job {job_id}")
        if source.options.get("individuals"):
            raise Unprocessable(f"job {job_id} tracks several animals; a rig is refined from a single animal's "
                                "keypoints (a job with one individual)")
        options, label = parse_refine_options(options_text)
        src_dir = jobfiles.job_dir(s.jobs_dir, source.id) / jobfiles.INPUT
        try:
            src = jobfiles.read_manifest(src_dir)
            files = [jobfiles.inside(src_dir, rel) for rel in [*src["keypoints"], src["calibration"]]]
        except (OSError, KeyError, ValueError):
            raise Unprocessable(f"job {job_id}: its input files are gone") from None
        self.jobs.check_quota(user)
        self.jobs.check_storage(user, sum(p.stat().st_size for p in files))
        individual = source.options.get("individual")
        return self._queue(user, lambda: self._copy_inputs(src_dir, src, job_id, individual, options), options, label)

    def _copy_inputs(self, src_dir: Path, src: dict, job_id: str, individual: str | None,
                     options: dict) -> tuple[str, dict]:
        with jobfiles.staged_input(self.jobs.settings.jobs_dir) as (new_id, input_dir):
            rels = []
            for rel in [*src["keypoints"], src["calibration"]]:
                dest = jobfiles.inside(input_dir, rel)
                dest.parent.mkdir(parents=True, exist_ok=True)
                shutil.copyfile(jobfiles.inside(src_dir, rel), dest)
                rels.append(rel)
            manifest = {"kind": CALIBRATION_KIND, "options": options,
                        "refine": {"job": job_id, "keypoints": rels[:-1], "calibration": rels[-1],
                                   "individual": individual}}
            jobfiles.write_manifest(input_dir, manifest)
            inputs = {"cameras": len(rels) - 1, "refined_from": job_id,
                      "keypoints": [{"name": Path(r).name, "bytes": (input_dir / r).stat().st_size} for r in rels[:-1]]}
        return new_id, inputs

    def visible(self, user: User, calibration_id: str) -> Job:
        """The calibration if the caller may see it (its owner, or an admin); 404 otherwise."""
        return self.jobs.visible(user, calibration_id, CALIBRATION_KIND)

    def file(self, user: User, calibration_id: str, name: str) -> Path:
        """One output file (a name of :data:`CALIBRATION_FILES`) of a succeeded calibration."""
        job = self.visible(user, calibration_id)
        if job.status != "succeeded":
            why = f": {job.error}" if job.status == "failed" and job.error else ""
            raise NotReady(f"calibration {calibration_id} is {job.status}{why}; its files are ready when it succeeded")
        path = jobfiles.job_dir(self.jobs.settings.jobs_dir, job.id) / jobfiles.RESULT / name
        if name not in CALIBRATION_FILES or not path.is_file():
            raise NotFound(f"calibration {calibration_id} has no {name}")
        return path

    def owned_calibration_file(self, user: User, calibration_id: str) -> Path:
        """The ``calibration.toml`` of the caller's own succeeded calibration, for a solve job (admins
        too may use only their own)."""
        job = self.visible(user, calibration_id)
        if job.owner_id != user.id:
            raise NotFound(f"no calibration {calibration_id}")
        return self.file(user, calibration_id, "calibration.toml")


@contextlib.contextmanager
def calibration_upload(jobs: JobService, user: User, upload: Upload | None,
                       calibration_id: str | None) -> Iterator[Upload]:
    """A solve job's calibration: the uploaded file, or the ``calibration.toml`` of the caller's
    calibration ``calibration_id``; exactly one of them."""
    if (upload is None) == (calibration_id is None):
        raise Unprocessable("calibration: upload a calibration file or give calibration_id (one of them)")
    if upload is not None:
        yield upload
        return
    assert calibration_id is not None  # exactly one of them, checked above
    path = CalibrationService(jobs).owned_calibration_file(user, calibration_id)
    with open(path, "rb") as f:
        yield Upload("calibration.toml", f)


def _save(upload: Upload, dest_dir: Path, default: str, video: bool = False) -> Path:
    from graph.calibrate.detect import VIDEO_SUFFIXES

    name = safe_name(upload.filename, default)
    if video and Path(name).suffix.lower() not in VIDEO_SUFFIXES:
        raise Unprocessable(f"{name}: not a video file name (one of {', '.join(VIDEO_SUFFIXES)})")
    if not video and not name.lower().endswith(".json"):
        name += ".json"
    dest_dir.mkdir(parents=True, exist_ok=True)
    path = dest_dir / name
    with open(path, "wb") as f:
        shutil.copyfileobj(upload.file, f, 1 << 20)
    return path

