"""Batches: an Anipose project uploaded in one request, each of its trials a job.

``POST /v1/batches`` takes the project as a zip archive (``config.toml`` at its top, or in its one
top folder, with the sessions, ``pose-2d/*.h5`` and ``calibration/calibration.toml`` as Anipose
lays them out). The server reads it as ``acinoset anipose`` does (:func:`graph.anipose.load_project`)
and submits every trial through :meth:`service.jobs.JobService.submit`, so each trial is validated,
stored and queued like any job: its keypoint files (rewritten as DeepLabCut CSVs where a camera has
an ``offset`` or more frames than the shortest), its calibration (the trial's cameras, in their
order, as Anipose TOML) and the project's options (an ``options`` JSON object overrides them).

A batch is a small JSON file, ``<data dir>/batches/<id>.json``: owner, project name, the trials with
their job ids (or why one was refused), and the keys the project set that have no equivalent. Its
status is computed from its jobs when asked: ``running`` while any is queued or running, then
``succeeded`` (all), ``failed`` (none) or ``partial``.
"""

from __future__ import annotations

import io
import json
import shutil
import time
import uuid
import zipfile
from pathlib import Path, PurePosixPath

from graph.errors import InputError
from service import jobfiles
from service.errors import JobError, NotFound, TooLarge, TooMany, Unprocessable
from service.jobs import JobService, Upload
from service.store import User

BATCH_ID = jobfiles.JOB_ID  # 32 hex digits
ACTIVE = ("queued", "running")


class BatchService:
    def __init__(self, jobs: JobService):
        self.jobs = jobs
        self.dir = jobs.settings.data_dir / "batches"

    # -- submit ------------------------------------------------------------------------------

    def submit(self, user: User, archive: Upload, options_text: str | None = None) -> dict:
        """Unpack the project, submit one job per trial, record the batch; returns the batch record."""
        from graph.anipose import load_project

        try:
            overrides = json.loads(options_text) if options_text and options_text.strip() else {}
        except json.JSONDecodeError as e:
            raise Unprocessable(f"options: not valid JSON ({e.msg})")
        if not isinstance(overrides, dict):
            raise Unprocessable("options: must be a JSON object")
        batch_id = uuid.uuid4().hex
        staging = self.dir / f".upload-{batch_id}"
        try:
            root = self._unpack(archive, staging / "project")
            try:
                project = load_project(root)
            except InputError as e:
                raise Unprocessable(f"project: {e}")
            if not project.trials:
                raise Unprocessable("project: no trials found (pose-2d/*.h5 named by cam_regex, "
                                    "with a calibration folder in or above the session)")
            n_active = self.jobs.store.count_active(user.id)
            limit = self.jobs.settings.max_active_jobs_per_user
            if n_active + len(project.trials) > limit:
                raise TooMany(f"the project has {len(project.trials)} trials and you have {n_active} queued or "
                              f"running jobs; this server allows {limit} per user")
            trials = [self._submit_trial(user, project, t, overrides, staging / "trials" / str(i))
                      for i, t in enumerate(project.trials)]
        finally:
            shutil.rmtree(staging, ignore_errors=True)
        ignored = project.ignored + (["[triangulation] axes, reference_point (a job's CSV is in the "
                                      "calibration's frame)"] if project.frame else [])
        record = {"id": batch_id, "owner_id": user.id, "owner": user.name, "created_at": time.time(),
                  "project": root.name, "trials": trials, "ignored": ignored, "notes": project.notes}
        self.dir.mkdir(parents=True, exist_ok=True)
        tmp = self.dir / f".{batch_id}.json.tmp"
        tmp.write_text(json.dumps(record, indent=1), encoding="utf-8")
        tmp.replace(self.dir / f"{batch_id}.json")
        return record

    def _unpack(self, archive: Upload, dest: Path) -> Path:
        """The archive's files under ``dest`` (paths checked to stay inside it; the total unpacked
        size held to the upload limit); returns the folder holding config.toml."""
        limit = self.jobs.settings.max_upload_bytes
        data = archive.file.read(limit + 1)
        if len(data) > limit:
            raise TooLarge(f"project archive over this server's upload limit of {limit} bytes")
        try:
            z = zipfile.ZipFile(io.BytesIO(data))
        except zipfile.BadZipFile:
            raise Unprocessable(f"project: {archive.filename or 'the upload'} is not a zip archive")
        with z:
            infos = [i for i in z.infolist() if not i.is_dir()]
            if sum(i.file_size for i in infos) > limit:
                raise TooLarge(f"project archive unpacks to more than this server's upload limit of {limit} bytes")
            for info in infos:
                try:
                    target = jobfiles.inside(dest, info.filename)
                except ValueError:
                    raise Unprocessable(f"project: the archive holds a path outside it: {info.filename!r}")
                target.parent.mkdir(parents=True, exist_ok=True)
                with z.open(info) as src, open(target, "wb") as out:
                    shutil.copyfileobj(src, out, 1 << 20)
        tops = [PurePosixPath(i.filename).parts for i in infos if PurePosixPath(i.filename).name == "config.toml"]
        top = min(tops, key=len, default=None)
        if top is None or len(top) > 2:
            raise Unprocessable("project: no config.toml at the archive's top or in its one top folder")
        return dest.joinpath(*top[:-1]) if len(top) == 2 else dest

    def _submit_trial(self, user: User, project, trial, overrides: dict, tmp: Path) -> dict:
        """One trial as a job: ``{"trial", "job_id"}``, or ``{"trial", "error"}`` if it was refused."""
        from graph.anipose.batch import trial_options
        from graph.camera import Calibration
        from graph.io.calibration import load_calibration, write_anipose_toml
        from graph.io.keypoints import read_keypoints, write_dlc_csv
        from graph.types import jsonable

        tmp.mkdir(parents=True)
        opened = []
        try:
            options = jsonable(trial_options(project, trial).to_dict())
            options.update(overrides)
            skeleton = None
            if options.get("skeleton") not in (None, "cheetah", "points"):
                skeleton = Path(options.pop("skeleton"))
                if not skeleton.is_file() or project.root not in skeleton.parents:
                    raise Unprocessable(f"skeleton {skeleton.name}: not a file of the project")
            rig = load_calibration(trial.calibration)
            by_name = dict(zip(rig.names, rig.cameras))
            missing = [c for c in trial.cameras if c not in by_name]
            if missing:
                raise Unprocessable(f"{trial.calibration.name}: has no camera named {', '.join(missing)}")
            cal = tmp / "calibration.toml"
            write_anipose_toml(cal, Calibration([by_name[c] for c in trial.cameras], metadata=rig.metadata))
            files = list(trial.pose_files)
            keypoints = [read_keypoints(p) for p in files]
            n = min(k.frames for k in keypoints)
            for i, (cam, k) in enumerate(zip(trial.cameras, keypoints)):
                dx, dy = project.offsets.get(cam, (0.0, 0.0))
                if dx or dy or k.frames != n:  # as acinoset anipose solves it: shifted, truncated
                    k.xy, k.likelihood = k.xy[:n] + [dx, dy], k.likelihood[:n]
                    files[i] = tmp / f"{files[i].stem}.csv"
                    write_dlc_csv(files[i], k)
            uploads = [Upload(p.name, open(p, "rb")) for p in files]
            opened += [u.file for u in uploads]
            cal_up = Upload(cal.name, open(cal, "rb"))
            opened.append(cal_up.file)
            sk_up = None
            if skeleton is not None:
                sk_up = Upload(skeleton.name, open(skeleton, "rb"))
                opened.append(sk_up.file)
            job = self.jobs.submit(user, uploads, cal_up, json.dumps(options), sk_up)
            return {"trial": trial.label, "job_id": job.id}
        except (JobError, InputError) as e:
            return {"trial": trial.label, "error": getattr(e, "detail", None) or str(e)}
        finally:
            for f in opened:
                f.close()

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
        status = ("running" if active else "succeeded" if ok == len(trials)
                  else "failed" if ok == 0 else "partial")
        return {**{k: v for k, v in record.items() if k != "owner_id"}, "status": status, "counts": counts,
                "trials": trials}
