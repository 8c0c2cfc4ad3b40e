"""Reading an upload with the core's readers, in helper processes.

:func:`inspect_upload` reads a job's stored input files the way the solve will (keypoints,
calibration, skeleton) and describes them, or says in one line what is wrong;
:func:`inspect_calibration_upload` does the same for a calibration's detections JSON (or videos)
and intrinsics. It is CPU work that holds the GIL for tens of milliseconds per file (a detections
JSON of 60,000 views: seconds, and hundreds of MB of Python objects), so :class:`UploadReader`
runs it in a small pool of processes of its own: a burst of uploads does not stall the status
polls the API answers meanwhile, the memory a parse takes is the helper's and is given back when
it ends, and a file that makes a reader crash or blow up takes down a helper, not the server.
The helpers are spawned, not forked from the solves' forkserver: that one compiles the solver's
kernels before it forks anything (a minute and a half on a new install), and an upload must not
wait for it. A helper imports only the readers (about a second, once per helper).
"""

from __future__ import annotations

import multiprocessing
import threading
from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path

from service.errors import TooLarge, Unprocessable
from service.store.jobfiles import inside


def inspect_upload(input_dir: str, keypoints: list[str], calibration: str, skeleton_file: str | None,
                   skeleton: str, individual: str | None, max_frames: int, max_bodyparts: int,
                   videos: list[str] | None = None, individuals: int | None = None) -> dict:
    """Read the stored files (paths relative to ``input_dir``) and describe them for the job table.
    Each keypoint file's frames and columns are checked before its data are read
    (:class:`graph.io.keypoints.ReadLimits`). ``videos`` (absolute paths, one per camera) are probed:
    each must hold a video with one frame per keypoint row. Raises :class:`~service.errors.TooLarge` or
    :class:`~service.errors.Unprocessable`."""
    from graph.errors import NESTED_TOO_DEEPLY, InputError, TooLargeInput
    from graph.io.calibration import load_calibration
    from graph.io.keypoint_types import Tracks
    from graph.io.keypoints import ReadLimits, check_same_frames, read_recording, require_a_marker
    from graph.skeleton import load_skeleton

    base = Path(input_dir)
    kp_paths = [inside(base, rel) for rel in keypoints]
    cal_path = inside(base, calibration)
    sk_path = inside(base, skeleton_file) if skeleton_file else None
    try:
        limits = ReadLimits(max_frames=max_frames, max_bodyparts=max_bodyparts)
        cameras = read_recording(kp_paths, individual, individuals, limits)
        kps = [c.slot(0) if isinstance(c, Tracks) else c for c in cameras]
        check_same_frames(kps)
        cal = load_calibration(cal_path)
        if len(cal) != len(kps):
            raise Unprocessable(f"{cal_path.name}: the calibration has {len(cal)} cameras but {len(kps)} keypoint "
                               "files were uploaded (one per camera, in the calibration's order)")
        sk = load_skeleton(sk_path if sk_path is not None else skeleton, bodyparts=kps[0].bodyparts)
        if sk.kind != "points":
            require_a_marker(kps, sk.name, list(sk.markers))
        infos = check_videos(videos, max(k.frames for k in kps)) if videos else None
    except TooLargeInput as e:
        raise TooLarge(f"{e} on this server (ACINOSET_MAX_{e.limit.upper()})") from None
    except InputError as e:
        raise Unprocessable(str(e)) from None
    except RecursionError:
        raise Unprocessable(f"upload: {NESTED_TOO_DEEPLY}") from None
    except (OSError, ValueError, KeyError, IndexError, TypeError, UnicodeDecodeError, MemoryError) as e:
        # a reader tripped on something it did not foresee: still a bad file, still one line
        filename = getattr(e, "filename", None)
        where = Path(filename).name if filename else "upload"
        raise Unprocessable(f"{where}: cannot be read ({type(e).__name__}: {e})") from None
    return {
        "cameras": len(kps), "frames": max(k.frames for k in kps), "bodyparts": list(kps[0].bodyparts),
        "keypoints": [{"name": p.name, "bytes": p.stat().st_size, "frames": k.frames, "bodyparts": len(k.bodyparts)}
                      for p, k in zip(kp_paths, kps)],
        "calibration": {"name": cal_path.name, "bytes": cal_path.stat().st_size},
        "skeleton": {"name": sk_path.name, "bytes": sk_path.stat().st_size} if sk_path is not None else None,
        "videos": None if infos is None else [{"name": Path(i.path).name, "bytes": Path(i.path).stat().st_size,
                                               "frames": i.frames} for i in infos],
        "individuals": max((c.slots for c in cameras if isinstance(c, Tracks)), default=1),
        "recorded_fps": recorded_frame_rate([k.fps for k in kps], [i.fps for i in infos or []]),
    }


def inspect_calibration_upload(input_dir: str, views: list[str], intrinsics: list[str], board: str,
                               videos: bool = False) -> list[dict]:
    """Read a calibration's stored files (paths relative to ``input_dir``) the way its run will:
    each of ``views`` a detections JSON read against ``board`` (a board spec), or with ``videos`` a
    video whose first frame OpenCV can read; each of ``intrinsics`` an AcinoSet camera JSON.
    Returns the description of each view file for the job table; raises
    :class:`~service.errors.Unprocessable` in one line naming the file."""
    from graph.calibrate import parse_board, read_detections
    from graph.errors import NESTED_TOO_DEEPLY, InputError
    from graph.io.cameras import load_camera_json

    base = Path(input_dir)
    grid = parse_board(board)
    described = []
    try:
        for path in (inside(base, rel) for rel in views):
            if videos:
                described.append({"name": path.name, "bytes": path.stat().st_size, **video_facts(path)})
            else:
                found = read_detections(path, grid)
                described.append({"name": path.name, "bytes": path.stat().st_size, "views": len(found.frames),
                                  "resolution": list(found.image_size)})
        for rel in intrinsics:
            load_camera_json(str(inside(base, rel)))
    except InputError as e:
        raise Unprocessable(str(e)) from None
    except RecursionError:
        raise Unprocessable(f"upload: {NESTED_TOO_DEEPLY}") from None
    except (OSError, ValueError, KeyError, IndexError, TypeError, UnicodeDecodeError, MemoryError) as e:
        filename = getattr(e, "filename", None)
        where = Path(filename).name if filename else "upload"
        raise Unprocessable(f"{where}: cannot be read ({type(e).__name__}: {e})") from None
    return described


def video_facts(path: Path) -> dict:
    """Frames and size of a video, from its first frame; :class:`Unprocessable` if OpenCV cannot read it."""
    import cv2

    cap = cv2.VideoCapture(str(path))
    try:
        ok, frame = cap.read() if cap.isOpened() else (False, None)
        if not ok or frame is None:
            raise Unprocessable(f"{path.name}: not a video OpenCV can read")
        return {"frames": int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) or None,
                "resolution": [int(frame.shape[1]), int(frame.shape[0])]}
    finally:
        cap.release()


def recorded_frame_rate(keypoints: list[float | None], videos: list[float]) -> float | None:
    """The frame rate the upload records: the keypoint files' (SLEAP's may record one, DeepLabCut's
    never do), else the videos'; None when neither does, or when those that do disagree."""
    for rates in (keypoints, videos):
        rates = [float(r) for r in rates if r is not None and r > 0]
        if rates and max(rates) - min(rates) <= 1e-3 * max(rates):
            return rates[0]
    return None


def check_videos(videos: list[str], frames: int) -> list:
    """Probe each video (:func:`graph.video.probe`): a video with ``frames`` frames, one per keypoint row."""
    from graph.errors import InputError
    from graph.video import probe

    infos = [probe(v) for v in videos]
    for i in infos:
        if i.frames != frames:
            raise InputError(f"has {i.frames} frames but the keypoint files have {frames} rows (one video per "
                             "camera, the footage the keypoints came from)", i.path)
    return infos


def _helper_init(niceness: int) -> None:
    from service.run.worker import server_child

    server_child(niceness)


class UploadReader:
    """:func:`inspect_upload` (and :func:`inspect_calibration_upload`; any work: :meth:`run`, as a
    job's exports in a pool of their own) in ``processes`` helper processes (0: in the calling thread), run at
    a lower priority than the API (``niceness``) so that a burst of uploads waits for the CPU
    rather than the status polls.

    A helper dies with the thread that started it (``PR_SET_PDEATHSIG`` names a thread, not a
    process), and the process pool starts helpers from the thread that hands it work. So work is
    handed over from one thread of this reader's own, alive until :meth:`close`: handed over from
    the API's threads, whose pool retires a thread idle for 10 s, the helpers were killed after a
    quiet spell and the next upload was refused as 'crashed a reader process'."""

    def __init__(self, processes: int = 2, niceness: int = 0):
        self.processes = processes
        self.niceness = niceness
        self._pool: ProcessPoolExecutor | None = None
        self._lock = threading.Lock()
        self._handover = ThreadPoolExecutor(1, thread_name_prefix="acinoset-upload-readers")

    def _executor(self) -> ProcessPoolExecutor:
        with self._lock:
            if self._pool is None:
                self._pool = ProcessPoolExecutor(self.processes, mp_context=multiprocessing.get_context("spawn"),
                                                 initializer=_helper_init, initargs=(self.niceness,),
                                                 max_tasks_per_child=500)
            return self._pool

    def inspect(self, **kwargs) -> dict:
        """:func:`inspect_upload` of a job's files."""
        return self._run(inspect_upload, Path(kwargs["keypoints"][0]).name, **kwargs)

    def inspect_calibration(self, **kwargs) -> list[dict]:
        """:func:`inspect_calibration_upload` of a calibration's files."""
        return self._run(inspect_calibration_upload, Path(kwargs["views"][0]).name, **kwargs)

    def run(self, work, **kwargs):
        """``work(**kwargs)`` in a helper process (in the calling thread with no processes): the
        readers, and a job's exports (an hour's result is gigabytes to read, kept out of the process
        that serves everyone). BrokenProcessPool when it crashed its process (the next call starts
        a new pool)."""
        if self.processes <= 0:
            return work(**kwargs)
        pool = self._executor()
        try:
            return self._handover.submit(lambda: pool.submit(work, **kwargs)).result().result()
        except BrokenProcessPool:
            with self._lock:
                if self._pool is pool:
                    self._pool = None
            pool.shutdown(wait=False, cancel_futures=True)
            raise

    def _run(self, read, first: str, **kwargs):
        try:
            return self.run(read, **kwargs)
        except BrokenProcessPool:
            raise Unprocessable(f"{first} ...: reading the upload crashed a reader process (a malformed or "
                               "oversized file?)") from None

    def close(self) -> None:
        with self._lock:
            pool, self._pool = self._pool, None
        if pool is not None:
            pool.shutdown(wait=True, cancel_futures=True)
        self._handover.shutdown(wait=False)
