"""What the API does with jobs: submit (validate, store, queue), find, list, cancel, delete.

The routes (:mod:`service.api.routes`) stay thin and call these. Every refusal is a
:class:`service.errors.JobError` with a one-line message; the app answers each kind with its HTTP
status (:data:`service.app.JOB_ERROR_STATUS`).

Uploads never choose a path: each file lands in the job's own directory under a name made only of
``[A-Za-z0-9._-]`` (directories stripped), one directory per camera; user options name a shipped
skeleton or the uploaded skeleton file, never a path on the server. Files are read with the core's
readers (CSV, h5py without pickles, JSON, TOML): nothing uploaded is executed.
"""

from __future__ import annotations

import builtins
import dataclasses
import json
import os
import re
import shutil
import threading
import uuid
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path, PurePosixPath
from typing import BinaryIO

from graph.errors import NESTED_TOO_DEEPLY
from service.backends.base import Backend
from service.core.uploads import UploadReader
from service.errors import (
    DISK_FULL,
    Forbidden,
    NoSpace,
    NotFound,
    NotReady,
    TooLarge,
    TooMany,
    Unprocessable,
    storage_full,
)
from service.settings import Settings
from service.store import STATUSES, Job, QuotaExceeded, Store, StoreFull, User, jobfiles
from service.store.jobfiles import (
    CALIBRATION_DIR,
    INPUT,
    JOB_ID,
    SKELETON_DIR,
    individual_names,
    keypoints_dir,
    result_path,
    video_dir,
)

KEYPOINT_SUFFIXES = (".csv", ".h5", ".hdf5", ".slp")
CURSOR = re.compile(r"^[0-9]{1,18}$")
CALIBRATION_SUFFIXES = (".json", ".toml")
VIDEO_SUFFIXES = (".mp4", ".avi", ".mov", ".mkv", ".m4v", ".webm")
HDF5_SIGNATURE = b"\x89HDF\r\n\x1a\n"


@dataclasses.dataclass
class Upload:
    """One uploaded file: the name the client gave and a readable binary stream."""

    filename: str | None
    file: BinaryIO


def safe_name(filename: str | None, default: str) -> str:
    """The last path component of ``filename`` with every character outside ``[A-Za-z0-9._-]``
    replaced, no leading dots, at most 100 characters; ``default`` if nothing is left."""
    base = PurePosixPath((filename or "").replace("\\", "/")).name
    base = re.sub(r"[^A-Za-z0-9._-]+", "_", base).lstrip(".-_")
    if len(base) > 100:
        stem, dot, suffix = base.rpartition(".")
        base = (stem[: 100 - len(suffix) - 1] + "." + suffix) if dot and len(suffix) < 10 else base[:100]
    return base or default


LABEL_MAX = 200


def parse_label(value) -> str | None:
    """A job's label: text of at most :data:`LABEL_MAX` characters, no control characters; None if empty."""
    if value is None:
        return None
    if not isinstance(value, str):
        raise Unprocessable("options: label must be text, e.g. \"label\": \"cheetah 3, run 2\"")
    value = " ".join(value.split())
    if len(value) > LABEL_MAX or any(ord(c) < 0x20 or 0x7F <= ord(c) < 0xA0 for c in value):
        raise Unprocessable(f"options: label must be at most {LABEL_MAX} printable characters")
    return value or None


def stream_size(f: BinaryIO) -> int:
    """Bytes from the stream's position to its end (the upload is spooled: seekable)."""
    here = f.tell()
    end = f.seek(0, os.SEEK_END)
    f.seek(here)
    return end - here


def _gib(n: float) -> str:
    return f"{n / 2**30:.2f} GiB" if n >= 2**30 else f"{n / 2**20:.1f} MiB"


def _with_suffix(name: str, head: bytes, allowed: tuple[str, ...], sniff) -> str:
    if Path(name).suffix.lower() in allowed:
        return name
    return name + sniff(head)


def _keypoint_suffix(head: bytes) -> str:
    return ".h5" if head.startswith(HDF5_SIGNATURE) else ".csv"


def _calibration_suffix(head: bytes) -> str:
    return ".json" if head.lstrip()[:1] == b"{" else ".toml"


def delete_finished(store: Store, jobs_dir: Path, job_id: str) -> bool:
    """Delete a finished job's row and then its files; False when it is gone (or not finished).
    The API's DELETE and ``acinoset jobs prune`` both delete this way.

    On a full disk the job table cannot record the deletion (SQLite's log must grow): the job's
    files go first, which frees the room, and the row after them. A finished job never runs
    again, so its files are not needed any more. :class:`NoSpace` if even that cannot be written."""
    try:
        deleted = store.delete(job_id)
    except Exception as e:
        if not storage_full(e):
            raise
        jobfiles.remove(jobs_dir, job_id)
        try:
            deleted = store.delete(job_id)
        except Exception as again:
            if storage_full(again):
                raise NoSpace(f"{DISK_FULL} (job {job_id}: its files were removed, its record stays until there "
                              "is room)") from None
            raise
    if deleted:
        jobfiles.remove(jobs_dir, job_id)
    return deleted


class JobService:
    # Uploads stored and read at once (the reading runs in :class:`UploadReader`'s processes).
    VALIDATING_AT_ONCE = 2

    def __init__(self, settings: Settings, store: Store, backend: Backend, reader: UploadReader | None = None,
                 exporter: UploadReader | None = None):
        """``reader``: the processes that read uploads; ``exporter``: those that write a job's exports."""
        self.settings = settings
        self.store = store
        self.backend = backend
        self.reader = reader or UploadReader(0)
        self.exporter = exporter or UploadReader(0)
        self._validating = threading.BoundedSemaphore(self.VALIDATING_AT_ONCE)

    # -- submit ------------------------------------------------------------------------------

    def parse_options(self, text: str | None, skeleton_file: str | None) -> tuple[dict, str | None]:
        """The ``options`` form field: a JSON object of :class:`graph.api.SolveOptions` fields, and
        the job's ``label`` (the user's name for the run, not an option of the solve). Without ``fps``
        the options come back without it: the upload's files settle it (:meth:`_store_upload`)."""
        from pydantic import TypeAdapter, ValidationError

        from graph.api import SolveOptions
        from graph.skeleton import available_skeletons

        try:
            data = json.loads(text) if text and text.strip() else {}
        except json.JSONDecodeError as e:
            raise Unprocessable(f"options: not valid JSON ({e.msg} at line {e.lineno} column {e.colno})")
        except RecursionError:
            raise Unprocessable(f"options: {NESTED_TOO_DEEPLY}") from None
        except ValueError:  # Python's limit on an integer's digits (4300)
            raise Unprocessable("options: a number with thousands of digits") from None
        if not isinstance(data, dict):
            raise Unprocessable("options: must be a JSON object such as {\"method\": \"fte\", \"fps\": 120}")
        label = parse_label(data.pop("label", None))
        known = [f.name for f in dataclasses.fields(SolveOptions)]
        unknown = sorted(set(data) - set(known))
        if unknown:
            raise Unprocessable(f"options: unknown option {unknown[0]!r}; known: {', '.join(known)}")
        if skeleton_file is not None:
            data["skeleton"] = skeleton_file
        else:
            name = data.get("skeleton", SolveOptions.skeleton)
            names = available_skeletons()
            if name not in names:
                raise Unprocessable(f"options: unknown skeleton {name!r}; use one of {', '.join(names)} "
                                     "or upload a skeleton .toml file as 'skeleton'")
        try:
            opts = TypeAdapter(SolveOptions).validate_python(data)
        except ValidationError as e:
            err = e.errors()[0]
            where = str(err["loc"][0]) if err["loc"] else ""  # the field, not the union member tried
            msg = err["msg"].removeprefix("Value error, ")
            if where == "measurement_std_px":
                msg = "must be a positive number of pixels or 'auto'"
            elif where == "motion_scale":
                msg = "must be a positive number, 'auto', or {group: positive number} as a report's motion_scales"
            elif where == "motion_order":
                msg = "must be 1, 2, 3, 'auto', or {group: 1, 2 or 3} as a report's motion_orders"
            elif where == "swap_rate":
                msg = "must be 'auto' or a share from 0 to below 0.5"
            raise Unprocessable(f"options: {where + ': ' if where else ''}{msg}")
        except (TypeError, ValueError) as e:
            raise Unprocessable(f"options: {e}")
        out = json.loads(json.dumps(opts.to_dict()))
        if "fps" not in data:
            del out["fps"]
        return out, label

    def _save(self, upload: Upload, dest_dir: Path, default: str, allowed: tuple[str, ...], sniff) -> Path:
        head = upload.file.read(16)
        name = _with_suffix(safe_name(upload.filename, default), head, allowed, sniff)
        dest_dir.mkdir(parents=True, exist_ok=True)
        path = dest_dir / name
        with open(path, "wb") as f:
            f.write(head)
            shutil.copyfileobj(upload.file, f, 1 << 20)
        return path

    def video_path(self, given: str) -> Path:
        """A video on shared storage, named by the path ``given`` (absolute, or relative to the
        admin's ``video_root``): the real file after symlinks and ``..`` are resolved, which must lie
        under the root. :class:`Forbidden` when the server has no root or the file is outside it."""
        root = self.settings.video_root
        if root is None:
            raise Forbidden("video_paths: this server takes no paths on its storage (its admin has not set "
                            "ACINOSET_VIDEO_ROOT); upload the videos as 'videos' instead")
        if not given or "\x00" in given:
            raise Unprocessable("video_paths: an empty path")
        real = (root / given).resolve()  # an absolute ``given`` replaces the root
        if not real.is_relative_to(root):
            raise Forbidden(f"video_paths: {given!r} is outside the folder this server's videos may come from")
        if not real.is_file():
            raise Unprocessable(f"video_paths: {given!r}: no such file")
        return real

    def submit(self, user: User, keypoints: list[Upload], calibration: Upload, options_text: str | None,
               skeleton: Upload | None = None, videos: list[Upload] | None = None,
               video_paths: list[str] | None = None, calibration_id: str | None = None) -> Job:
        """Validate the upload with the core's readers, store it, queue the job. ``videos`` (uploads)
        or ``video_paths`` (on shared storage, :meth:`video_path`): each camera's footage, one per
        keypoint file, for the labelled videos. ``calibration_id``: the calibration job whose
        ``calibration.toml`` ``calibration`` is, recorded with the inputs."""
        s = self.settings
        if not keypoints:
            raise Unprocessable("keypoints: upload one keypoint file per camera")
        if len(keypoints) > s.max_cameras:
            raise TooLarge(f"{len(keypoints)} keypoint files; this server takes at most "
                           f"{s.max_cameras} cameras per job (ACINOSET_MAX_CAMERAS)")
        if videos and video_paths:
            raise Unprocessable("give the videos either as uploads ('videos') or as paths ('video_paths'), not both")
        given = len(videos or video_paths or [])
        if given and given != len(keypoints):
            raise Unprocessable(f"{given} videos for {len(keypoints)} keypoint files: give one video per camera, "
                                "in the keypoint files' order")
        shared = [self.video_path(p) for p in video_paths] if video_paths else None
        self.check_quota(user)
        skeleton_name = safe_name(skeleton.filename, "skeleton.toml") if skeleton is not None else None
        options, label = self.parse_options(options_text, skeleton_name)
        upload_bytes = sum(stream_size(u.file) for u in [*keypoints, calibration, *([skeleton] if skeleton else []),
                                                   *(videos or [])])
        self.check_storage(user, upload_bytes)

        try:
            with self._validating:
                job_id, inputs = self._store_upload(keypoints, calibration, skeleton, options, videos or None, shared)
            if calibration_id is not None:
                inputs["calibration_id"] = calibration_id
            try:
                job = self.store.insert_job(job_id, user.id, self.backend.name, options, inputs, s.max_attempts,
                                            max_active=s.max_active_jobs_per_user, label=label)
            except BaseException:
                jobfiles.remove(s.jobs_dir, job_id)
                raise
        except QuotaExceeded:
            self.check_quota(user)
            raise
        except (OSError, StoreFull) as e:
            if storage_full(e):
                raise NoSpace(DISK_FULL) from None
            raise
        self.backend.submit(job.id)
        return job

    def _store_upload(self, keypoints: list[Upload], calibration: Upload, skeleton: Upload | None,
                      options: dict, videos: list[Upload] | None = None,
                      video_paths: list[Path] | None = None) -> tuple[str, dict]:
        """Write the files into a new job directory and read them with the core's readers.
        Returns the job id and the description of the inputs; refusals remove everything."""
        s = self.settings
        with jobfiles.staged_input(s.jobs_dir) as (job_id, input_dir):
            kp_paths = [self._save(u, keypoints_dir(input_dir, i), f"camera{i + 1}.csv",
                                   KEYPOINT_SUFFIXES, _keypoint_suffix) for i, u in enumerate(keypoints)]
            cal_path = self._save(calibration, input_dir / CALIBRATION_DIR, "calibration.toml",
                                  CALIBRATION_SUFFIXES, _calibration_suffix)
            sk_path = (self._save(skeleton, input_dir / SKELETON_DIR, "skeleton.toml", (".toml",), lambda h: ".toml")
                       if skeleton is not None else None)
            video_files = ([self._save(u, video_dir(input_dir, i), f"camera{i + 1}.mp4", VIDEO_SUFFIXES,
                                       lambda h: ".mp4") for i, u in enumerate(videos)] if videos else None)
            rel = lambda p: p.relative_to(input_dir).as_posix()  # noqa: E731
            manifest = {"keypoints": [rel(p) for p in kp_paths], "calibration": rel(cal_path),
                        "skeleton": rel(sk_path) if sk_path is not None else None, "options": options}
            if video_files:
                manifest["videos"] = [rel(p) for p in video_files]
            if video_paths:
                manifest["video_paths"] = [str(p) for p in video_paths]
            inputs = self.reader.inspect(
                input_dir=str(input_dir), keypoints=manifest["keypoints"], calibration=manifest["calibration"],
                skeleton_file=manifest["skeleton"], skeleton=options["skeleton"],
                individual=options.get("individual"), individuals=options.get("individuals"), max_frames=s.max_frames,
                max_bodyparts=s.max_bodyparts,
                videos=[str(p) for p in (video_files or video_paths or [])] or None)
            recorded = inputs.pop("recorded_fps", None)
            if "fps" not in options:  # as the command line's --fps: required unless the files record it
                if recorded is None:
                    raise Unprocessable("options: fps is required: the cameras' frame rate, frames per second (the "
                                        "keypoint files record none, DeepLabCut's never do, and no video gave one)")
                options["fps"] = recorded
            manifest["frames"] = inputs.get("frames")  # as read here: a worker's hint before it stages the files
            jobfiles.write_manifest(input_dir, manifest)
        return job_id, inputs

    def storage_used(self, user: User | None = None) -> int:
        """Bytes of the job files of ``user`` (everyone's: None)."""
        if user is None:
            return jobfiles.disk_bytes(self.settings.jobs_dir)
        return sum(jobfiles.disk_bytes(jobfiles.job_dir(self.settings.jobs_dir, j))
                   for j in self.store.job_ids_of(user.id))

    def check_storage(self, user: User, upload_bytes: int) -> None:
        """Room for ``upload_bytes`` more: :class:`NoSpace` (507) if the disk would keep less than
        ``min_free_bytes`` free or everyone's jobs would pass ``max_storage_bytes``; :class:`TooLarge`
        (413) if the user's jobs would pass ``max_storage_bytes_per_user``."""
        s = self.settings
        free = shutil.disk_usage(s.jobs_dir).free
        if free - upload_bytes < s.min_free_bytes:
            raise NoSpace(f"the server's disk is nearly full ({_gib(free)} free, {_gib(s.min_free_bytes)} kept free: "
                          "ACINOSET_MIN_FREE_BYTES); delete finished jobs to make room, or ask the admin")
        if s.max_storage_bytes:
            total = self.storage_used()
            if total + upload_bytes > s.max_storage_bytes:
                raise NoSpace(f"the server's storage for jobs is full ({_gib(total)} of {_gib(s.max_storage_bytes)}: "
                              "ACINOSET_MAX_STORAGE_BYTES); delete finished jobs to make room, or ask the admin")
        if s.max_storage_bytes_per_user:
            mine = self.storage_used(user)
            if mine + upload_bytes > s.max_storage_bytes_per_user:
                raise TooLarge(f"your jobs use {_gib(mine)} of your {_gib(s.max_storage_bytes_per_user)} "
                               f"(ACINOSET_MAX_STORAGE_BYTES_PER_USER) and this upload is {_gib(upload_bytes)}; "
                               "delete finished jobs to make room")

    def check_quota(self, user: User) -> None:
        """:class:`TooMany` if the user already has the most queued and running jobs allowed."""
        n = self.store.count_active(user.id)
        if n >= self.settings.max_active_jobs_per_user:
            raise TooMany(f"you have {n} queued or running jobs, the most this server allows per user "
                          "(ACINOSET_MAX_ACTIVE_JOBS_PER_USER); wait for some to finish or cancel some")

    # -- read --------------------------------------------------------------------------------

    def visible(self, user: User, job_id: str, kind: str | None = None) -> Job:
        """The job of ``kind`` (None: a solve; see :mod:`service.core.calibrations`) if the caller may see it
        (its owner, or an admin); 404 otherwise, whether or not it exists."""
        job = self.store.job(job_id) if JOB_ID.match(job_id) else None
        if job is None or job.options.get("kind") != kind or (job.owner_id != user.id and not user.is_admin):
            raise NotFound(f"no {kind or 'job'} {job_id}")
        return job

    def list(self, user: User, statuses: list[str] | None, limit: int, cursor: str | None,
             owner: str | None, label: str | None = None, method: str | None = None, since: float | None = None,
             warnings: bool | None = None, kind: str | None = None) -> tuple[list[Job], int, str | None]:
        if statuses:
            bad = [st for st in statuses if st not in STATUSES]
            if bad:
                raise Unprocessable(f"status: {bad[0]!r} is not one of {', '.join(STATUSES)}")
        before = None
        if cursor:
            if not CURSOR.match(cursor):  # a job's seq: at most 18 digits fit SQLite's INTEGER
                raise Unprocessable("cursor: pass the next_cursor of the previous page")
            before = int(cursor)
        owner_id: int | None = user.id
        if user.is_admin:
            owner_id = None
            if owner:
                u = self.store.user(owner)
                if u is None:
                    return [], 0, None
                owner_id = u.id
        elif owner and owner != user.name:
            raise Forbidden("only admins can list other users' jobs")
        limit = max(1, min(limit, self.settings.page_size_max))
        jobs, total = self.store.jobs(owner_id, statuses, limit + 1, before, label=label, method=method, since=since,
                                      warnings=warnings, kind=kind)
        more = len(jobs) > limit
        jobs = jobs[:limit]
        return jobs, total, (str(jobs[-1].seq) if more and jobs else None)

    def result_file(self, user: User, job_id: str, fmt: str, individual: str | None = None) -> Path:
        """The job's result file of download format ``fmt`` (:data:`service.store.jobfiles.DOWNLOADS`);
        of a job that solved several individuals, ``individual``'s (its report and its view of them all,
        :data:`~service.store.jobfiles.GROUP_FORMATS`: the job's, without one)."""
        job = self.visible(user, job_id)
        if job.status != "succeeded":
            why = f": {job.error}" if job.status == "failed" and job.error else ""
            raise NotReady(f"job {job_id} is {job.status}{why}; its result is ready when it succeeded")
        k = self._individual(job, fmt, individual)
        job_dir = jobfiles.job_dir(self.settings.jobs_dir, job.id)
        path = result_path(job_dir, fmt, k)
        if fmt in jobfiles.EXPORT_FILES and not path.is_file():
            try:  # in a helper process: reading an hour's result takes gigabytes
                self.exporter.run(export_result, job_dir=job_dir, fmt=fmt, individual=k)
            except BrokenProcessPool:
                raise RuntimeError(f"writing job {job_id}'s {fmt} crashed its process (out of memory?)") from None
        if not path.is_file():
            raise NotFound(f"job {job_id} has no {jobfiles.DOWNLOADS[fmt][0]} (its result files were removed)")
        return path

    @staticmethod
    def _individual(job: Job, fmt: str, individual: str | None) -> int | None:
        """The index of ``individual`` among the job's (None: the job's own files)."""
        names = individual_names(job.summary)
        if names is None:
            if individual is not None:
                raise Unprocessable(f"individual: job {job.id} solved one individual; download its result without "
                                    "individual")
            return None
        if individual is None:
            if fmt in jobfiles.GROUP_FORMATS:
                return None
            shown = ", ".join(names[:8]) + (", ..." if len(names) > 8 else "")
            raise Unprocessable(f"individual: job {job.id} solved {len(names)} individuals ({shown}); give "
                                "individual=NAME for one's result")
        if individual not in names:
            raise NotFound(f"job {job.id} has no individual {individual[:60]!r}")
        return names.index(individual)

    # -- videos ------------------------------------------------------------------------------

    def _succeeded(self, job: Job) -> Path:
        if job.status != "succeeded":
            why = f": {job.error}" if job.status == "failed" and job.error else ""
            raise NotReady(f"job {job.id} is {job.status}{why}; its videos are ready when it succeeded")
        return jobfiles.job_dir(self.settings.jobs_dir, job.id)

    def video_views(self, job: Job) -> builtins.list[str]:  # builtins: this class has a method named list
        """The labelled videos a succeeded job with videos has: its cameras' numbers, 3d, combined
        (none when they could not be rendered: its report's warnings say why)."""
        if job.status != "succeeded" or not (job.inputs or {}).get("videos"):
            return []
        views = [str(c + 1) for c in range(len(job.inputs["videos"]))] + list(jobfiles.VIDEO_VIEWS)
        result = jobfiles.job_dir(self.settings.jobs_dir, job.id) / jobfiles.RESULT
        return [v for v in views if (result / jobfiles.video_result_name(v)).is_file()]

    def video_file(self, job: Job, view: str) -> Path:
        """The labelled video ``view`` (a camera's number, ``3d`` or ``combined``) of ``job``."""
        folder = self._succeeded(job)
        views = self.video_views(job)
        if view not in views:
            why = (f": it has {', '.join(views)}" if views else " (its videos could not be rendered: see its "
                   "report's warnings)" if (job.inputs or {}).get("videos") else " (it was submitted without videos)")
            raise NotFound(f"job {job.id} has no video {view!r}{why}")
        path = folder / jobfiles.RESULT / jobfiles.video_result_name(view)
        if not path.is_file():
            raise NotFound(f"job {job.id} has no video {view!r} (its result files were removed)")
        return path

    def frame_png(self, user: User, job_id: str, camera: int, frame: int) -> bytes:
        """Camera ``camera``'s (from 1) frame ``frame`` of the job's own video with the estimate
        drawn on it (:func:`graph.video.camera_frame_png`), as PNG bytes."""
        import tempfile

        from graph.errors import InputError
        from graph.io.results import read_result
        from graph.video import camera_frame_png

        job = self.visible(user, job_id)
        folder = self._succeeded(job)
        videos = jobfiles.input_videos(folder / INPUT)
        if not videos:
            raise NotFound(f"job {job.id} was submitted without videos: it has no frames to draw on")
        if not 1 <= camera <= len(videos):
            raise Unprocessable(f"camera: the job has cameras 1 to {len(videos)}, not {camera}")
        frames = int(job.inputs.get("frames") or 0)
        if not 0 <= frame < frames:
            raise Unprocessable(f"n: the job has frames 0 to {frames - 1}, not {frame}")
        try:
            result = read_result(result_path(folder, "h5"))
            with tempfile.TemporaryDirectory(prefix=".frame-", dir=folder) as tmp:
                png = camera_frame_png(result, camera - 1, videos[camera - 1], frame, Path(tmp) / "frame.png")
                return png.read_bytes()
        except InputError as e:
            raise Unprocessable(str(e)) from None

    # -- cancel, delete ----------------------------------------------------------------------

    def cancel_or_delete(self, user: User, job_id: str, kind: str | None = None) -> Job | None:
        """Cancel an active job (its run stops) and return it; delete a finished one and its files (None)."""
        job = self.visible(user, job_id, kind)
        if job.active:
            before = self.store.cancel(job.id)
            if before is not None:
                self.backend.cancel(job.id, before.run_token)
            now = self.store.job(job.id)
            assert now is not None
            return now
        delete_finished(self.store, self.settings.jobs_dir, job.id)
        return None


def export_result(job_dir: Path, fmt: str, individual: int | None = None) -> None:
    """Write the export ``fmt`` of a succeeded job (or of its ``individual``-th individual) from its
    result.h5 and its uploaded calibration (:func:`graph.export.export`), under a temporary name first,
    so concurrent downloads of the same format each see a whole file."""
    from graph.export import available, export

    if not available(fmt):
        raise Unprocessable(f"this server cannot write {fmt}: it needs acinoset[export] installed")
    h5 = result_path(job_dir, "h5", individual)
    if not h5.is_file():
        return
    from graph.io.calibration import load_calibration

    input_dir = job_dir / INPUT
    path = jobfiles.inside(input_dir, jobfiles.read_manifest(input_dir)["calibration"])
    calibration = dataclasses.replace(load_calibration(path), source=path.name)  # no server path in the file
    target = result_path(job_dir, fmt, individual)
    tmp_dir = target.parent / f".export-{uuid.uuid4().hex}"  # the file keeps its name (TRC writes it inside)
    tmp_dir.mkdir()
    try:
        os.replace(export(h5, fmt, tmp_dir / target.name, calibration=calibration), target)
    finally:
        shutil.rmtree(tmp_dir, ignore_errors=True)
