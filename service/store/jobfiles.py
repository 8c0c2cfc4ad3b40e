"""A job's files: where its inputs and results lie in the data dir, and how they travel to an RQ worker.

A job's directory, ``<data dir>/jobs/<id>`` (:func:`job_dir`; ids match :data:`JOB_ID`)::

    input/                             the upload, as stored by the API (below)
    result/                            :data:`RESULT_FILES`, one per download format, once succeeded;
                                       with several individuals, report.json holds who is who and
                                       individuals/01/ ... (:func:`individual_folder`) each one's RESULT_FILES;
                                       videos/camera01.mp4 ..., 3d.mp4, combined.mp4 when the job had videos
                                       (:func:`video_result_name`);
                                       :data:`EXPORT_FILES` made from result.h5 when first downloaded
    result.<run token>.tmp/            a run's results being written (:func:`result_tmp`), then
                                       moved to result/ when the run is recorded (:func:`install_result`)
    error.log                          tracebacks of failed runs (embedded)

An upload is stored in ``<data dir>/jobs/.upload-<id>`` (:func:`staging_dir`) while it is read,
and becomes the job's directory only once it is accepted. Input layout, named by :data:`MANIFEST`::

    manifest.json                      {"keypoints": [...], "calibration": ..., "skeleton": ..., "options": {...}}
    keypoints/01/<uploaded name>.csv   one directory per camera, in the calibration's order (:func:`keypoints_dir`)
    videos/01/<uploaded name>.mp4      optional: each camera's footage (:func:`video_dir`); or the manifest's
                                       "video_paths" name files on shared storage under the admin's video root
    calibration/<uploaded name>.toml
    skeleton/<uploaded name>.toml      optional

Both sides use it: the API stores uploads in this layout and serves results from it, the workers read
and write it (for RQ, as zip archives in Redis under :func:`input_key` and :func:`result_key`,
each a list of chunks: :func:`put_archive`, :func:`get_archive`).
"""

from __future__ import annotations

import json
import os
import re
import shutil
import uuid
from contextlib import contextmanager
from pathlib import Path, PurePosixPath
from typing import Iterator

from graph.export import REGISTRY

JOB_ID = re.compile(r"^[0-9a-f]{32}$")  # what :func:`new_job_id` makes
INPUT = "input"
RESULT = "result"
ERROR_LOG = "error.log"
_STAGING = ".upload-"
MANIFEST = "manifest.json"
CALIBRATION_DIR = "calibration"
SKELETON_DIR = "skeleton"
CALIBRATION_KIND = "calibration"  # a manifest's and a job's options' "kind" for a calibration job (else a solve)
RESULT_FILES: dict[str, tuple[str, str]] = {  # download format: (file in the job's result dir, media type)
    "csv": ("result.csv", "text/csv"),
    "h5": ("result.h5", "application/x-hdf5"),
    "json": ("result.json", "application/json"),
    "report": ("report.json", "application/json"),
}
RESULT_NAMES: tuple[str, ...] = tuple(file for file, _ in RESULT_FILES.values())
# the export formats (graph.export.REGISTRY), written from result.h5 when first asked for, then kept beside it
EXPORT_FILES: dict[str, tuple[str, str]] = {name: (RESULT + f.extension, f.media_type) for name, f in REGISTRY.items()}
DOWNLOADS: dict[str, tuple[str, str]] = {**RESULT_FILES, **EXPORT_FILES}
_SUFFIXES = [file.removeprefix(RESULT + ".") for file, _ in DOWNLOADS.values()]  # of the downloaded files' names
if len(DOWNLOADS) < len(RESULT_FILES) + len(EXPORT_FILES) or len(set(_SUFFIXES)) < len(_SUFFIXES):
    raise RuntimeError(f"an export format takes the name or the file of one of a job's own results: formats "
                       f"{[*RESULT_FILES]} + {[*EXPORT_FILES]}, files {[file for file, _ in DOWNLOADS.values()]}")
# what a calibration job writes in its result dir (service.core.calibrations): file name -> media type
CALIBRATION_FILES: dict[str, str] = {
    "calibration.toml": "application/toml", "scene.json": "application/json", "report.json": "application/json",
    "rig.png": "image/png", "residuals.png": "image/png", "coverage.png": "image/png"}
# every file a run may hand back (a worker packs those it wrote; the server unpacks only these)
OUTPUT_NAMES: tuple[str, ...] = tuple(dict.fromkeys([*RESULT_NAMES, *CALIBRATION_FILES]))

VIDEOS_DIR = "videos"  # input: each camera's footage; result: the labelled videos
VIDEO_VIEWS = ("3d", "combined")  # the labelled videos beside the cameras' (named by camera number, from 1)
_VIDEO_RESULT = re.compile(r"^videos/(camera[0-9]{2}|3d|combined)\.mp4$")
INDIVIDUALS_DIR = "individuals"  # result: one folder per individual of a job with several
_INDIVIDUAL_RESULT = re.compile(rf"^{INDIVIDUALS_DIR}/[0-9]{{2}}/({'|'.join(map(re.escape, RESULT_NAMES))})$")


# a job of several individuals' own files: them all drawn, who is who, them all on an individuals axis
GROUP_FORMATS = ("json", "report", "h5")


def individual_names(summary: dict | None) -> list[str] | None:
    """The individuals of a job that solved several (its report's ``identity``), in the order of their
    folders (:func:`individual_folder`); None for a job of one."""
    names = ((summary or {}).get("identity") or {}).get("individuals")
    return [str(n) for n in names] if isinstance(names, list) and len(names) > 1 else None


def individual_folder(k: int) -> str:
    """The result folder of a job's ``k``-th individual (0-based; at most 99): ``individuals/01``, ..."""
    if not 0 <= k < 99:
        raise ValueError(f"individual {k}: a job holds at most 99")
    return f"{INDIVIDUALS_DIR}/{k + 1:02d}"


def video_dir(input_dir: Path, camera: int) -> Path:
    """The directory of camera ``camera``'s uploaded video (0-based, in the calibration's order)."""
    return input_dir / VIDEOS_DIR / f"{camera + 1:02d}"


def video_result_name(view: str) -> str:
    """The result file of a labelled video: ``view`` is a camera's number (``"1"``...) or one of
    :data:`VIDEO_VIEWS`; ValueError for anything else."""
    if view in VIDEO_VIEWS:
        return f"{VIDEOS_DIR}/{view}.mp4"
    if view.isdigit() and 1 <= int(view) <= 99:
        return f"{VIDEOS_DIR}/camera{int(view):02d}.mp4"
    raise ValueError(f"no video {view!r}: name a camera's number (1, 2, ...), 3d or combined")


def is_result_name(rel: str) -> bool:
    """Whether ``rel`` is a file a run may put in a job's result dir (:data:`OUTPUT_NAMES`, the videos,
    an individual's results)."""
    return rel in OUTPUT_NAMES or bool(_VIDEO_RESULT.match(rel)) or bool(_INDIVIDUAL_RESULT.match(rel))


def new_job_id() -> str:
    return uuid.uuid4().hex


def job_dir(jobs_dir: Path, job_id: str) -> Path:
    return Path(jobs_dir) / job_id


def staging_dir(jobs_dir: Path, job_id: str) -> Path:
    """Where an upload is stored and read before it becomes ``job_dir(jobs_dir, job_id)``."""
    return Path(jobs_dir) / f"{_STAGING}{job_id}"


@contextmanager
def staged_input(jobs_dir: Path) -> Iterator[tuple[str, Path]]:
    """A new job id and its staging input dir (``<staging>/input``), for an upload to be written and
    read into. On leaving the block the staging dir becomes the job's dir; on an error (a refusal
    included) it is removed with everything in it, and the error goes on."""
    job_id = new_job_id()
    staging = staging_dir(jobs_dir, job_id)
    try:
        yield job_id, staging / INPUT
        staging.replace(job_dir(jobs_dir, job_id))
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise


def keypoints_dir(input_dir: Path, camera: int) -> Path:
    """The directory of the keypoint file of camera ``camera`` (0-based, in the calibration's order)."""
    return input_dir / "keypoints" / f"{camera + 1:02d}"


def result_tmp(job_dir: Path, token: str) -> Path:
    """Where the run ``token`` writes (embedded) or unpacks (rq) its result files."""
    return job_dir / f"{RESULT}.{token}.tmp"


STAGED = "staged"  # the folder of a long run's staged detections, in the run's result folder
WINDOWS_BOARD = "board"  # in it, on the embedded backend: where its windows are shared (service.run.folder_windows)


def windows_board(job_dir: Path, token: str) -> Path:
    """Where the embedded run ``token`` shares a long run's windows with helper processes."""
    return result_tmp(job_dir, token) / STAGED / WINDOWS_BOARD


def install_result(job_dir: Path, tmp: Path) -> None:
    """Make ``tmp`` the job's result directory, replacing an older one (called inside the
    transaction that records the run's success)."""
    final = job_dir / RESULT
    if final.exists():
        shutil.rmtree(final)
    os.replace(tmp, final)


def keep_results(tmp: Path) -> None:
    """Leave in ``tmp`` only what a result archive may carry (:func:`unpack_files` with
    :func:`is_result_name`): regular files with a result's name. Links and other names are removed (a
    worker on a shared data dir writes the folder itself; the API serves what is installed)."""
    for root, dirs, files in os.walk(tmp, followlinks=False):
        for name in files + [d for d in dirs if os.path.islink(os.path.join(root, d))]:
            path = Path(root) / name
            rel = path.relative_to(tmp).as_posix()
            if path.is_symlink() or not path.is_file() or not is_result_name(rel):
                path.unlink()


def result_path(job_dir: Path, fmt: str, individual: int | None = None) -> Path:
    """The result file of download format ``fmt``: the job's, or its ``individual``-th individual's (0-based)."""
    folder = job_dir / RESULT if individual is None else job_dir / RESULT / individual_folder(individual)
    return folder / DOWNLOADS[fmt][0]


def download_name(job_id: str, fmt: str, individual: str | None = None) -> str:
    """The file name a download of format ``fmt`` is offered under: ``<id>.csv``, ``<id>.report.json``;
    an individual's ``<id>.<name>.csv`` (the name made safe for a file name)."""
    from graph.io.results import safe_name

    middle = "" if individual is None else f"{safe_name(individual, 'individual')}."
    return f"{job_id}.{middle}{DOWNLOADS[fmt][0].removeprefix(RESULT + '.')}"


def disk_bytes(path: Path) -> int:
    """The bytes of the files under ``path`` (0 if it does not exist)."""
    total = 0
    try:
        entries = list(os.scandir(path))
    except OSError:
        return 0
    for e in entries:
        try:
            if e.is_dir(follow_symlinks=False):
                total += disk_bytes(Path(e.path))
            elif e.is_file(follow_symlinks=False):
                total += e.stat(follow_symlinks=False).st_size
        except OSError:
            pass
    return total


def remove(jobs_dir: Path, job_id: str) -> None:
    """A job's directory and everything in it."""
    shutil.rmtree(job_dir(jobs_dir, job_id), ignore_errors=True)


def tidy(jobs_dir: Path, known: set[str]) -> None:
    """Remove what a crash can leave in the jobs dir: half-stored uploads, half-written results and
    directories of jobs that never made it into the table (ids not in ``known``)."""
    for p in Path(jobs_dir).iterdir():
        if p.name.startswith(_STAGING) or (p.is_dir() and p.name not in known and JOB_ID.match(p.name)):
            shutil.rmtree(p, ignore_errors=True)
        elif p.is_dir():
            for tmp in p.glob(f"{RESULT}.*.tmp"):
                shutil.rmtree(tmp, ignore_errors=True)


def write_manifest(input_dir: Path, manifest: dict) -> None:
    (input_dir / MANIFEST).write_text(json.dumps(manifest, indent=2))


def read_manifest(input_dir: Path) -> dict:
    return json.loads((input_dir / MANIFEST).read_text())


def inside(base: Path, rel: str) -> Path:
    """``base / rel`` where ``rel`` is a relative POSIX path that stays inside ``base``."""
    p = PurePosixPath(rel)
    if p.is_absolute() or ".." in p.parts or not p.parts:
        raise ValueError(f"bad path in job manifest: {rel!r}")
    return base.joinpath(*p.parts)


def input_videos(input_dir: Path) -> list[Path]:
    """The job's videos, one per camera (none when it was given none): uploaded ones in
    ``input_dir``, or the files on shared storage its manifest names."""
    m = read_manifest(input_dir)
    if m.get("videos"):
        return [inside(input_dir, rel) for rel in m["videos"]]
    return [Path(p) for p in m.get("video_paths") or []]


def input_key(token: str) -> str:
    """Redis key of the input files of the RQ job ``token``."""
    return f"acinoset:input:{token}"


def result_key(token: str) -> str:
    """Redis key of the result files of the RQ job ``token``."""
    return f"acinoset:result:{token}"


def windows_key(token: str) -> str:
    """The prefix of the Redis keys of the windows the RQ job ``token`` shares with helpers
    (:mod:`service.run.redis_windows`)."""
    return f"acinoset:windows:{token}"


def helpers_prefix(token: str) -> str:
    """What the id of every RQ job helping the RQ job ``token`` with its windows starts with."""
    return f"{token}-helper-"


ARCHIVE_CHUNK_BYTES = 1_000_000  # one Redis value: under the smallest proto-max-bulk-len Redis takes (1 MB)
PARTIAL = ":partial"  # an archive being written lies under its key plus this, then is renamed


def put_archive(redis, key: str, archive: bytes, ttl: int | None = None) -> None:
    """Store ``archive`` under ``key`` as a Redis list of chunks of :data:`ARCHIVE_CHUNK_BYTES`.

    One Redis value holds at most ``proto-max-bulk-len`` bytes (512 MB by default, 1 MB at the
    least), and a job's footage or labelled videos can be larger: whole, such an archive could not be
    stored at all. The chunks go under ``key`` + :data:`PARTIAL` and the list is renamed to ``key``
    at the end, so that a reader finds the whole archive or none. ``ttl``: both expire after that many
    seconds (the partial one too, should the writer die)."""
    partial = key + PARTIAL
    view = memoryview(archive)
    step = ARCHIVE_CHUNK_BYTES
    chunks = [view[i:i + step] for i in range(0, len(view), step)] or [view]
    with redis.pipeline(transaction=False) as pipe:
        pipe.delete(partial)
        for i in range(0, len(chunks), 16):  # a few MB a command
            pipe.rpush(partial, *chunks[i:i + 16])
            if ttl is not None:
                pipe.expire(partial, ttl)
        pipe.rename(partial, key)  # the key keeps the partial one's expiry
        pipe.execute()


def get_archive(redis, key: str) -> bytes | None:
    """The archive :func:`put_archive` stored under ``key`` (a plain string value too, as earlier
    versions stored it); None if there is none."""
    kind = redis.type(key)
    if kind in (b"string", "string"):
        return redis.get(key)
    chunks = redis.lrange(key, 0, -1)
    return b"".join(chunks) if chunks else None


def written_outputs(out_dir: Path) -> list[str]:
    """The files of :data:`OUTPUT_NAMES` and the labelled videos that a run wrote into ``out_dir``,
    relative to it (what travels back from an RQ worker)."""
    out_dir = Path(out_dir)
    videos = sorted(f"{VIDEOS_DIR}/{p.name}" for p in (out_dir / VIDEOS_DIR).glob("*.mp4"))
    each = sorted(p.relative_to(out_dir).as_posix() for p in (out_dir / INDIVIDUALS_DIR).glob("*/*") if p.is_file())
    return [*(name for name in OUTPUT_NAMES if (out_dir / name).is_file()),
            *(v for v in [*videos, *each] if is_result_name(v))]


STORED_SUFFIXES = (".h5", ".mp4")  # packed as they are: compressed already, or float arrays deflate barely shrinks


def pack_files(base: Path, rels: list[str]) -> bytes:
    """Files under ``base`` as one zip archive (deflate, fast level; :data:`STORED_SUFFIXES` stored),
    names relative to ``base``. Deflate at its fast level takes float64 arrays to 96 % of their size
    at 46 MB/s here (80 MB of normal draws in 1.7 s): a long run's result H5, hundreds of MB, would
    cost seconds of the job for nothing."""
    import io
    import zipfile

    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_DEFLATED, compresslevel=1) as z:
        for rel in rels:  # one compress call per file (the GIL is released while it runs)
            kind = zipfile.ZIP_STORED if rel.endswith(STORED_SUFFIXES) else zipfile.ZIP_DEFLATED
            z.writestr(rel, inside(base, rel).read_bytes(), compress_type=kind)
    return buf.getvalue()


def unpack_files(archive: bytes, base: Path, allowed=None) -> list[str]:
    """Extract :func:`pack_files`' archive under ``base`` (names that would leave it are refused;
    with ``allowed``, a tuple of names or a test of a name, other names are skipped). Returns the
    names extracted."""
    import io
    import zipfile

    names = []
    with zipfile.ZipFile(io.BytesIO(archive)) as z:
        for info in z.infolist():
            ok = allowed is None or (allowed(info.filename) if callable(allowed) else info.filename in allowed)
            if info.is_dir() or not ok:
                continue
            p = inside(base, info.filename)
            p.parent.mkdir(parents=True, exist_ok=True)
            with z.open(info) as src, open(p, "wb") as dst:
                shutil.copyfileobj(src, dst, 1 << 20)
            names.append(info.filename)
    return names


def input_archive(input_dir: Path) -> bytes:
    """What an RQ worker needs to run a job: the manifest and the input files, zipped."""
    m = read_manifest(input_dir)
    rels = [MANIFEST, *m.get("keypoints", []), *([m["calibration"]] if m.get("calibration") else []),
            *([m["skeleton"]] if m.get("skeleton") else []), *m.get("detections", []), *m.get("videos", []),
            *m.get("intrinsics", [])]
    return pack_files(input_dir, rels)
