"""Batches: an Anipose project uploaded in one request, each of its trials a job.

``POST /v1/batches`` takes the project as a zip archive (``config.toml`` at its top, or in its one
top folder, with the sessions, ``pose-2d/*.h5`` and ``calibration/calibration.toml`` as Anipose
lays them out). The archive is copied to the data dir as it is received, then unpacked and read as
``acinoset anipose`` reads a project (:func:`graph.anipose.load_project`), kept to the archive, in a
process of its own under time and memory limits (:mod:`service.run.batch_reader`); the API process
parses none of it. Every trial is submitted through :meth:`service.core.jobs.JobService.submit`, so each is validated,
stored and queued like any job: its keypoint files (rewritten as DeepLabCut CSVs where a camera has
an ``offset`` or more frames than the shortest), its calibration (the trial's cameras, in their
order, as Anipose TOML) and the project's options (an ``options`` JSON object overrides them).

A batch is a small JSON file, ``<data dir>/batches/<id>.json``: owner, project name, the trials with
their job ids (or why one was refused), and the keys the project set that have no equivalent. Its
status is computed from its jobs when asked: ``running`` while any is queued or running, then
``succeeded`` (all), ``failed`` (none) or ``partial``.
"""

from __future__ import annotations

import json
import shutil
import time
import uuid
from pathlib import Path

from graph.errors import NESTED_TOO_DEEPLY, InputError
from service.core.jobs import JobService, Upload
from service.errors import DISK_FULL, JobError, NoSpace, NotFound, TooLarge, TooMany, Unprocessable, storage_full
from service.store import User, jobfiles

BATCH_ID = jobfiles.JOB_ID  # 32 hex digits
ACTIVE = ("queued", "running")


class BatchService:
    def __init__(self, jobs: JobService):
        self.jobs = jobs
        self.dir = jobs.settings.data_dir / "batches"

    # -- submit ------------------------------------------------------------------------------

    def submit(self, user: User, archive: Upload, options_text: str | None = None) -> dict:
        """Receive the archive, read the project in a limited process of its own
        (:mod:`service.run.batch_reader`), submit one job per trial, record the batch; returns the batch record."""
        from service.run.batch_reader import read_batch, run_limited

        try:
            overrides = json.loads(options_text) if options_text and options_text.strip() else {}
        except json.JSONDecodeError as e:
            raise Unprocessable(f"options: not valid JSON ({e.msg})")
        except RecursionError:
            raise Unprocessable(f"options: {NESTED_TOO_DEEPLY}") from None
        if not isinstance(overrides, dict):
            raise Unprocessable("options: must be a JSON object")
        s = self.jobs.settings
        batch_id = uuid.uuid4().hex
        staging = self.dir / f".upload-{batch_id}"
        try:
            staging.mkdir(parents=True)
            received = self._receive(archive, staging / "project.zip")
            n_active = self.jobs.store.count_active(user.id)
            limit = s.max_active_jobs_per_user
            project = run_limited(
                read_batch, dict(archive=str(received), staging=str(staging), overrides=overrides,
                                 max_bytes=s.max_upload_bytes, max_trials=limit - n_active, max_frames=s.max_frames,
                                 max_bodyparts=s.max_bodyparts, filename=archive.filename),
                timeout=s.batch_read_timeout_seconds, memory_bytes=s.batch_read_memory_bytes,
                cpu_seconds=s.batch_read_cpu_seconds, niceness=s.upload_niceness)
            if not project["count"]:
                raise Unprocessable("project: no trials found (pose-2d/*.h5 named by cam_regex, "
                                    "with a calibration folder in or above the session)")
            if n_active + project["count"] > limit:
                raise TooMany(f"the project has {project['count']} trials and you have {n_active} queued or "
                              f"running jobs; this server allows {limit} per user")
            trials = [self._submit_trial(user, t, staging) for t in project["trials"]]
        except OSError as e:
            if storage_full(e):
                raise NoSpace(DISK_FULL) from None
            raise
        finally:
            shutil.rmtree(staging, ignore_errors=True)
        record = {"id": batch_id, "owner_id": user.id, "owner": user.name, "created_at": time.time(),
                  "project": project["project"], "trials": trials, "ignored": project["ignored"],
                  "notes": project["notes"]}
        self.dir.mkdir(parents=True, exist_ok=True)
        tmp = self.dir / f".{batch_id}.json.tmp"
        tmp.write_text(json.dumps(record, indent=1), encoding="utf-8")
        tmp.replace(self.dir / f"{batch_id}.json")
        return record

    def _receive(self, archive: Upload, dest: Path) -> Path:
        """The uploaded archive copied to ``dest`` a megabyte at a time (never whole in memory);
        :class:`TooLarge` past the upload limit."""
        limit = self.jobs.settings.max_upload_bytes
        seen = 0
        with open(dest, "wb") as out:
            while chunk := archive.file.read(1 << 20):
                seen += len(chunk)
                if seen > limit:
                    raise TooLarge(f"project archive over this server's upload limit of {limit} bytes")
                out.write(chunk)
        return dest

    def _submit_trial(self, user: User, trial: dict, staging: Path) -> dict:
        """One prepared trial (:func:`service.run.batch_reader.read_batch`) as a job: ``{"trial", "job_id"}``,
        or ``{"trial", "error"}`` if it was refused."""
        if "error" in trial:
            return {"trial": trial["trial"], "error": trial["error"]}
        opened = []
        try:
            paths = [self._staged(p, staging) for p in trial["keypoints"]]
            cal, sk = self._staged(trial["calibration"], staging), trial["skeleton"]
            uploads = []
            for p in paths:
                uploads.append(Upload(p.name, open(p, "rb")))
                opened.append(uploads[-1].file)
            cal_up = Upload(cal.name, open(cal, "rb"))
            opened.append(cal_up.file)
            sk_up = None
            if sk is not None:
                sk_path = self._staged(sk, staging)
                sk_up = Upload(sk_path.name, open(sk_path, "rb"))
                opened.append(sk_up.file)
            job = self.jobs.submit(user, uploads, cal_up, json.dumps(trial["options"]), sk_up)
            return {"trial": trial["trial"], "job_id": job.id}
        except (JobError, InputError) as e:
            return {"trial": trial["trial"], "error": getattr(e, "detail", None) or str(e)}
        finally:
            for f in opened:
                f.close()

    @staticmethod
    def _staged(path: str, staging: Path) -> Path:
        """A file the reader prepared: it must be a file inside the batch's staging folder."""
        p = Path(path)
        if not (p.resolve().is_relative_to(staging.resolve()) and p.is_file()):
            raise Unprocessable(f"{p.name}: not a file of the project")
        return p

    # -- read --------------------------------------------------------------------------------

    def visible(self, user: User, batch_id: str) -> dict:
        path = self.dir / f"{batch_id}.json"
        record = json.loads(path.read_text(encoding="utf-8")) if BATCH_ID.match(batch_id) and path.is_file() else None
        if record is None or (record["owner_id"] != user.id and not user.is_admin):
            raise NotFound(f"no batch {batch_id}")
        return record

    def status(self, record: dict) -> dict:
        """The record with each trial's job status and the batch's counts and status."""
        counts = {s: 0 for s in ("queued", "running", "succeeded", "failed", "cancelled", "refused")}
        trials = []
        for t in record["trials"]:
            job = self.jobs.store.job(t["job_id"]) if t.get("job_id") else None
            status = job.status if job is not None else ("refused" if t.get("error") else "deleted")
            counts[status] = counts.get(status, 0) + 1
            trials.append({**t, "status": status, "error": t.get("error") or (job.error if job else None)})
        active = sum(counts[s] for s in ACTIVE)
        ok = counts["succeeded"]
        overall = ("running" if active else "succeeded" if ok == len(trials)
                   else "failed" if ok == 0 else "partial")
        return {**{k: v for k, v in record.items() if k != "owner_id"}, "status": overall, "counts": counts,
                "trials": trials}
