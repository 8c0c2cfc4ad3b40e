"""Reading an uploaded Anipose project: in a process of its own, under limits, kept to its archive.

Everything in a batch's archive was written by the caller, so the API process parses none of it.
:func:`read_batch` unpacks the archive, reads the project as ``acinoset anipose`` does but kept to
the archive (:func:`graph.anipose.load_project` with ``within``: a path its config names outside the
archive is refused, naming the key) and prepares each trial's files for a job. It runs in a spawned
process (:func:`run_limited`) whose address space (``RLIMIT_AS``) and CPU time (``RLIMIT_CPU``) are
capped and which is killed at a wall-clock limit, so a project that would take the server's memory,
a core or its time takes the helper's instead, and the API answers on meanwhile.

The archive is checked before anything is written: no names out of it or symbolic links, no file
and folder of one name, names of at most :data:`MAX_NAME_BYTES` bytes, paths of at most
:data:`MAX_PATH_CHARS` characters and :data:`MAX_PATH_PARTS` levels, at most :data:`MAX_ENTRIES`
entries and :data:`MAX_FOLDERS` folders, and at most the upload limit unpacked. A damaged entry
(bad CRC, truncated stream) or one compressed in a way this server cannot unpack is a 422.

What it hands back is plain data: the trials (their files inside the staging folder) or why each
was refused, and notes whose text names no path of the server (:func:`_public`).
"""

from __future__ import annotations

import json
import math
import multiprocessing
import signal
import stat
import zipfile
from pathlib import Path, PurePosixPath
from typing import Any, Callable

from service.errors import DISK_FULL, JobError, NoSpace, TooLarge, TooMany, Unprocessable, storage_full

MAX_ENTRIES = 10_000  # entries of the archive
MAX_FOLDERS = 10_000  # folders it unpacks to
MAX_NAME_BYTES = 255  # one file or folder name (the file system's limit)
MAX_PATH_CHARS = 1024  # one entry's path
MAX_PATH_PARTS = 32  # folders deep
BUILT_IN_SKELETONS = (None, "cheetah", "points")  # an options' skeleton that names no file
MAX_ANSWER_BYTES = 64 * 2**20  # of the reader's answer (JSON)
ERRORS: dict[str, type[JobError]] = {e.__name__: e for e in (Unprocessable, TooLarge, TooMany, NoSpace)}


# -- the archive ---------------------------------------------------------------------------------------

def unpack(archive: Path, dest: Path, max_bytes: int, filename: str | None = None) -> Path:
    """The archive's files under ``dest`` (see the module's docstring for what is refused); returns
    the folder holding ``config.toml`` (the archive's top, or its one top folder)."""
    try:
        z = zipfile.ZipFile(archive)
    except (zipfile.BadZipFile, EOFError, ValueError, NotImplementedError, OSError) as e:
        if isinstance(e, OSError) and storage_full(e):
            raise NoSpace(DISK_FULL) from None
        raise Unprocessable(f"project: {filename or 'the upload'} is not a zip archive") from None
    with z:
        infos = z.infolist()
        if len(infos) > MAX_ENTRIES:
            raise Unprocessable(f"project: the archive has {len(infos)} entries; this server unpacks at most "
                                f"{MAX_ENTRIES}")
        files: dict[tuple[str, ...], zipfile.ZipInfo] = {}
        folders: set[tuple[str, ...]] = set()
        for info in infos:
            parts = _entry_parts(info)
            if info.is_dir():
                folders.update(parts[:k] for k in range(1, len(parts) + 1))
            else:
                files[parts] = info
                folders.update(parts[:k] for k in range(1, len(parts)))
        clash = sorted(set(files) & folders)
        if clash:
            raise Unprocessable(f"project: the archive holds both a file and a folder named {'/'.join(clash[0])!r}")
        if len(folders) > MAX_FOLDERS:
            raise Unprocessable(f"project: the archive unpacks to {len(folders)} folders; this server takes at most "
                                f"{MAX_FOLDERS}")
        if sum(i.file_size for i in files.values()) > max_bytes:
            raise TooLarge(f"project archive unpacks to more than this server's upload limit of {max_bytes} bytes")
        for parts, info in files.items():
            target = dest.joinpath(*parts)
            try:
                target.parent.mkdir(parents=True, exist_ok=True)
                with z.open(info) as src, open(target, "wb") as out:
                    while chunk := src.read(1 << 20):  # never more than file_size: zipfile stops there
                        out.write(chunk)
            except NotImplementedError:
                raise Unprocessable(f"project: {info.filename!r} in the archive is compressed with a method this "
                                    "server cannot unpack (use deflate)") from None
            except RuntimeError:  # zipfile: encrypted, password required
                raise Unprocessable(f"project: {info.filename!r} in the archive is encrypted") from None
            except OSError as e:
                if storage_full(e):
                    raise NoSpace(DISK_FULL) from None
                raise Unprocessable(f"project: {info.filename!r} in the archive cannot be unpacked here "
                                    f"({e.strerror or type(e).__name__})") from None
            except Exception as e:  # BadZipFile (bad CRC), zlib.error, EOFError, lzma and bz2 errors
                raise Unprocessable(f"project: {info.filename!r} in the archive is damaged "
                                    f"({type(e).__name__}{': ' + str(e) if str(e) else ''})") from None
    tops = [parts for parts in files if parts[-1] == "config.toml"]
    top = min(tops, key=len, default=None)
    if top is None or len(top) > 2:
        raise Unprocessable("project: no config.toml at the archive's top or in its one top folder")
    return dest.joinpath(*top[:-1]) if len(top) == 2 else dest


def _entry_parts(info: zipfile.ZipInfo) -> tuple[str, ...]:
    """An entry's path as folder and file names, or :class:`Unprocessable` saying why not."""
    name = info.filename
    p = PurePosixPath(name)
    if p.is_absolute() or ".." in p.parts or not p.parts:
        raise Unprocessable(f"project: the archive holds a path outside it: {name[:200]!r}")
    if stat.S_ISLNK(info.external_attr >> 16):
        raise Unprocessable(f"project: the archive holds a symbolic link: {name[:200]!r} (zip without --symlinks)")
    if len(name) > MAX_PATH_CHARS or len(p.parts) > MAX_PATH_PARTS:
        raise Unprocessable(f"project: the archive holds a path of {len(name)} characters, {len(p.parts)} levels "
                            f"deep; this server takes at most {MAX_PATH_CHARS} characters, {MAX_PATH_PARTS} levels")
    if any(len(part.encode("utf-8", "surrogateescape")) > MAX_NAME_BYTES for part in p.parts):
        raise Unprocessable(f"project: the archive holds a name longer than {MAX_NAME_BYTES} bytes: {name[:80]!r}...")
    return p.parts


# -- the project ---------------------------------------------------------------------------------------

def read_batch(archive: str, staging: str, overrides: dict, max_bytes: int, max_trials: int, max_frames: int,
               max_bodyparts: int, filename: str | None = None) -> dict:
    """Unpack ``archive`` into ``staging``/project, read the project kept to it, and prepare each
    trial's job files in ``staging``/trials/<i>: ``{"project", "count", "trials", "ignored",
    "notes"}``, each trial ``{"trial", "keypoints", "calibration", "options", "skeleton"}`` or
    ``{"trial", "error"}``. With more than ``max_trials`` trials none is prepared (``count`` says how
    many). Raises :class:`~service.errors.JobError`; no message names a path of the server."""
    from graph.anipose import load_project
    from graph.errors import InputError

    where = Path(staging)
    bound = where / "project"
    try:
        root = unpack(Path(archive), bound, max_bytes, filename)
        try:
            project = load_project(root, within=bound)
        except InputError as e:
            raise Unprocessable(f"project: {e}") from None
        skeleton = _given_skeleton(overrides, project.root, bound)
        out: dict[str, Any] = {
            "project": project.root.name, "count": len(project.trials), "trials": [],
            "ignored": project.ignored + (["[triangulation] axes, reference_point (a job's CSV is in the "
                                           "calibration's frame)"] if project.frame else []),
            "notes": project.notes}
        if len(project.trials) <= max_trials:
            out["trials"] = [_prepare_trial(project, t, overrides, skeleton, bound, where / "trials" / str(i),
                                            max_frames, max_bodyparts) for i, t in enumerate(project.trials)]
    except JobError as e:
        raise type(e)(_public(e.detail, where)) from None
    except RecursionError:
        from graph.errors import NESTED_TOO_DEEPLY

        raise Unprocessable(f"project: {NESTED_TOO_DEEPLY}") from None
    except MemoryError:
        raise
    except Exception as e:  # a reader tripped on something it did not foresee: still the project's
        raise Unprocessable(_public(f"project: cannot be read ({type(e).__name__}: {e})", where)) from None
    return _public(out, where)


def _given_skeleton(overrides: dict, root: Path, bound: Path) -> Path | None:
    """The skeleton file the ``options`` field names (relative to the project), kept to the archive."""
    from graph.anipose.project import resolves_inside

    name = overrides.get("skeleton")
    if name in BUILT_IN_SKELETONS:
        return None
    if not isinstance(name, str):
        raise Unprocessable("options: skeleton must be a skeleton's name or a .toml file of the project")
    path = root / name
    if not resolves_inside(path, bound):
        raise Unprocessable("options: skeleton names a file outside the project (an uploaded project reads only "
                            "its own files)")
    return path


def _prepare_trial(project, trial, overrides: dict, skeleton: Path | None, bound: Path, tmp: Path, max_frames: int,
                   max_bodyparts: int) -> dict:
    """One trial's job files (its cameras' calibration, its keypoints shifted and truncated as
    ``acinoset anipose`` solves them) and options, or ``{"trial", "error"}``."""
    from graph.anipose.batch import trial_options
    from graph.anipose.project import resolves_inside
    from graph.camera import Calibration
    from graph.errors import InputError, TooLargeInput
    from graph.io.calibration import load_calibration, write_anipose_toml
    from graph.io.keypoints import ReadLimits, read_keypoints, write_dlc_csv
    from graph.types import jsonable

    try:
        tmp.mkdir(parents=True)
        options = jsonable(trial_options(project, trial).to_dict())
        options.update(overrides)
        sk_file = skeleton
        if skeleton is not None:
            options.pop("skeleton")
        elif options.get("skeleton") not in BUILT_IN_SKELETONS:
            sk_file = Path(options.pop("skeleton"))  # the config's, resolved inside the archive by load_project
        if sk_file is not None and not (sk_file.is_file() and resolves_inside(sk_file, bound)):
            raise Unprocessable(f"skeleton {sk_file.name}: not a file of the project")
        rig = load_calibration(trial.calibration)
        by_name = dict(zip(rig.names, rig.cameras))
        missing = [c for c in trial.cameras if c not in by_name]
        if missing:
            raise Unprocessable(f"{trial.calibration.name}: has no camera named {', '.join(missing)}")
        cal = tmp / "calibration.toml"
        write_anipose_toml(cal, Calibration([by_name[c] for c in trial.cameras], metadata=rig.metadata))
        files = list(trial.pose_files)
        limits = ReadLimits(max_frames=max_frames, max_bodyparts=max_bodyparts)
        keypoints = [read_keypoints(p, limits=limits) for p in files]
        n = min(k.frames for k in keypoints)
        for i, (cam, k) in enumerate(zip(trial.cameras, keypoints)):
            dx, dy = project.offsets.get(cam, (0.0, 0.0))
            if dx or dy or k.frames != n:  # as acinoset anipose solves it: shifted, truncated
                k.xy, k.likelihood = k.xy[:n] + [dx, dy], k.likelihood[:n]
                files[i] = tmp / f"{files[i].stem}.csv"
                write_dlc_csv(files[i], k)
        return {"trial": trial.label, "keypoints": [str(p) for p in files], "calibration": str(cal),
                "options": options, "skeleton": None if sk_file is None else str(sk_file)}
    except TooLargeInput as e:
        return {"trial": trial.label, "error": f"{e} on this server (ACINOSET_MAX_{e.limit.upper()})"}
    except (JobError, InputError) as e:
        return {"trial": trial.label, "error": getattr(e, "detail", None) or str(e)}
    except MemoryError:
        return {"trial": trial.label, "error": "its files need more memory to read than this server allows "
                                               "(ACINOSET_BATCH_READ_MEMORY_BYTES)"}
    except Exception as e:  # one trial's odd file: that trial's refusal
        if isinstance(e, OSError) and storage_full(e):
            raise NoSpace(DISK_FULL) from None
        return {"trial": trial.label, "error": f"cannot be read ({type(e).__name__}: {e})"}


def _public(value, staging: Path):
    """``value`` (a string, or lists and dicts of them) with the server's paths taken out of its
    text: the project's folder becomes relative, the staging folder ``<upload>``. The prepared
    files' own paths (``keypoints``, ``calibration``, ``skeleton``) are kept: the API opens them."""
    if isinstance(value, dict):
        return {k: v if k in ("keypoints", "calibration", "skeleton") else _public(v, staging)
                for k, v in value.items()}
    if isinstance(value, list):
        return [_public(v, staging) for v in value]
    if not isinstance(value, str):
        return value
    data_dir = staging.parent.parent
    for path, instead in ((staging / "project", "."), (staging, "<upload>"), (data_dir, "<data dir>")):
        value = value.replace(f"{path}/", "" if instead == "." else f"{instead}/").replace(str(path), instead)
    return value


# -- the process ---------------------------------------------------------------------------------------

def run_limited(target: Callable[..., Any], kwargs: dict, timeout: float, memory_bytes: int, cpu_seconds: float,
                niceness: int = 0) -> Any:
    """``target(**kwargs)`` in a spawned process with at most ``memory_bytes`` of address space and
    ``cpu_seconds`` of CPU time beyond its start-up, killed after ``timeout`` seconds: its value (which
    must be JSON: the answer is read as JSON, never unpickled), or the
    :class:`~service.errors.JobError` it raised, raised here. Past a limit:
    :class:`~service.errors.Unprocessable` naming it (the settings ``ACINOSET_BATCH_READ_*``)."""
    ctx = multiprocessing.get_context("spawn")
    receive, send = ctx.Pipe(duplex=False)
    p = ctx.Process(target=_limited_child, args=(send, target, kwargs, memory_bytes, cpu_seconds, niceness),
                    name="acinoset-batch-reader", daemon=True)
    p.start()
    send.close()
    answer: dict | None = None
    try:
        if receive.poll(timeout):
            try:
                answer = json.loads(receive.recv_bytes(MAX_ANSWER_BYTES))
            except (EOFError, OSError, ValueError):
                answer = None  # it died before answering (or said too much)
        else:
            answer = {"timeout": True}
    finally:
        if p.is_alive() and (answer is None or "timeout" in answer):
            p.kill()
        p.join(10)
        if p.is_alive():
            p.kill()
            p.join()
        code = p.exitcode
        receive.close()
        p.close()
    answer = answer if isinstance(answer, dict) else {}
    if "value" in answer:
        return answer["value"]
    if answer.get("error") in ERRORS:
        raise ERRORS[answer["error"]](str(answer.get("detail")))
    if "timeout" in answer:
        raise Unprocessable(f"reading the project took longer than {timeout:g} s, this server's limit "
                            "(ACINOSET_BATCH_READ_TIMEOUT_SECONDS)")
    if code == -signal.SIGXCPU:
        raise Unprocessable(f"reading the project used more than {cpu_seconds:g} s of CPU time, this server's "
                            "limit (ACINOSET_BATCH_READ_CPU_SECONDS)")
    if code == -signal.SIGKILL:
        raise Unprocessable("reading the project was killed (out of memory, or past its CPU time limit)")
    raise Unprocessable(f"reading the project crashed its reader process (exit status {code}): a malformed file?")


def _limited_child(conn, target: Callable[..., Any], kwargs: dict, memory_bytes: int, cpu_seconds: float,
                   niceness: int) -> None:
    import resource

    from service.run.worker import server_child

    server_child(niceness)
    use = resource.getrusage(resource.RUSAGE_SELF)
    soft = math.ceil(use.ru_utime + use.ru_stime + cpu_seconds)
    resource.setrlimit(resource.RLIMIT_CPU, (soft, soft + 2))  # SIGXCPU at soft, SIGKILL at hard
    resource.setrlimit(resource.RLIMIT_AS, (memory_bytes, memory_bytes))
    try:
        answer = json.dumps({"value": target(**kwargs)})
    except JobError as e:
        answer = json.dumps({"error": type(e).__name__ if type(e) in ERRORS.values() else "Unprocessable",
                             "detail": e.detail})
    except MemoryError:
        answer = json.dumps({"error": "Unprocessable", "detail": f"reading the project needs more than "
                             f"{memory_bytes / 2**20:.0f} MiB of memory, this server's limit "
                             "(ACINOSET_BATCH_READ_MEMORY_BYTES)"})
    except BaseException as e:
        answer = json.dumps({"error": "Unprocessable", "detail": f"project: cannot be read ({type(e).__name__})"})
    try:
        conn.send_bytes(answer.encode())
    finally:
        conn.close()
