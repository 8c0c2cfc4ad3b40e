"""A long recording's detections kept on disk while it is solved a window at a time.

An hour at 120 fps is 432,000 frames: six cameras' detections of 20 markers are 1.2 GB as float64,
more than the rest of a windowed solve holds (:mod:`graph.solve.windows`). So each camera's file
is read once, in turn, a stretch of frames at a time as the reader gives them
(:func:`graph.io.keypoints.read_blocks`: a DeepLabCut CSV 4,096 rows at a time, any other format
whole), and its arrays appended to raw native float64 files in a scratch folder of the caller's:

* ``<c>.xy``: (N, M_c, 2) pixels, NaN where missing;
* ``<c>.likelihood``: (N, M_c), 0 where missing;
* ``<c>.spread``: (N, M_c), an ensemble's disagreement, where the camera has one.

:meth:`StagedRun.keypoints` reads frames ``[a, b)`` of every camera back (``np.fromfile`` at the
frames' offset: nothing stays mapped), so only a window's detections are in memory at a time. A
run whose files hold several individuals is not staged (:func:`stage` says so): several animals are
solved together (:func:`graph.api.solve_group`). :meth:`StagedRun.save` and :meth:`StagedRun.open`
keep the cameras' index beside the arrays, for a run that goes on after it was stopped.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from collections.abc import Callable, Iterable, Iterator
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from graph.errors import InputError
from graph.io.keypoint_types import Keypoints, Tracks

_F64 = np.dtype(np.float64)


@dataclass(frozen=True)
class StagedCamera:
    """One camera's file as staged: what its :class:`Keypoints` held besides the arrays."""

    index: int
    bodyparts: list[str]
    source: str
    scorer: str
    fps: float | None
    spread: bool


class StagedRun:
    """The detections of a run's cameras in ``folder`` (module docstring); cameras are added in the
    calibration's order, each with the first one's frame count."""

    def __init__(self, folder: str | Path):
        self.folder = Path(folder)
        self.cameras: list[StagedCamera] = []
        self.frames = 0

    def add(self, kp: Keypoints) -> None:
        """Write one camera's detections; :class:`InputError` when its frames are not the first's."""
        self.add_blocks([kp])

    def add_blocks(self, blocks: Iterable[Keypoints], index: int | None = None) -> None:
        """Write one camera's detections a stretch of frames at a time, in order (a reader's blocks:
        :func:`graph.io.keypoints.read_blocks`), as camera ``index`` (default: the next);
        :class:`InputError` when its frames are not the first's or a stretch's bodyparts are not the
        first stretch's."""
        c, frames, first = len(self.cameras) if index is None else index, 0, None
        for kp in blocks:
            if first is None:
                first = kp
                for name in ("xy", "likelihood", "spread"):
                    self._path(c, name).unlink(missing_ok=True)
            elif kp.bodyparts != first.bodyparts or (kp.spread_px is None) != (first.spread_px is None):
                raise InputError("its bodyparts change partway through the file", kp.source or None)
            arrays = {"xy": kp.xy, "likelihood": kp.likelihood}
            if kp.spread_px is not None:
                arrays["spread"] = kp.spread_px
            for name, a in arrays.items():
                with open(self._path(c, name), "ab") as f:
                    f.write(np.ascontiguousarray(a, dtype=_F64).tobytes())
            frames += kp.frames
        if first is None:
            raise InputError("no frames")
        if self.cameras:
            _same_frames(frames, first.source, self.frames, self.cameras[0].source)
        self.frames = frames
        self.cameras.append(StagedCamera(c, list(first.bodyparts), first.source, first.scorer, first.fps,
                                         first.spread_px is not None))

    def keypoints(self, a: int, b: int) -> list[Keypoints]:
        """Every camera's frames ``[a, b)`` (clipped to the run) as :class:`Keypoints`."""
        a, b = max(0, a), min(self.frames, b)
        n = max(0, b - a)
        out = []
        for cam in self.cameras:
            M = len(cam.bodyparts)
            xy = self._read(cam.index, "xy", a, n, M * 2).reshape(n, M, 2)
            lik = self._read(cam.index, "likelihood", a, n, M).reshape(n, M)
            spread = self._read(cam.index, "spread", a, n, M).reshape(n, M) if cam.spread else None
            out.append(Keypoints(bodyparts=list(cam.bodyparts), xy=xy, likelihood=lik, scorer=cam.scorer,
                                 source=cam.source, spread_px=spread, fps=cam.fps))
        return out

    @property
    def fps(self) -> list[float | None]:
        return [cam.fps for cam in self.cameras]

    def save(self) -> None:
        """The cameras' index (``cameras.json``) written beside their arrays, for :meth:`open`."""
        index = {"frames": self.frames, "cameras": [asdict(cam) for cam in self.cameras]}
        (self.folder / "cameras.json").write_text(json.dumps(index), encoding="utf-8")

    @classmethod
    def open(cls, folder: str | Path) -> StagedRun:
        """A run staged and saved (:meth:`save`) earlier, in ``folder``; :class:`InputError` when it is
        not there whole (each camera's arrays the size its index says)."""
        run = cls(folder)
        try:
            index = json.loads((run.folder / "cameras.json").read_text(encoding="utf-8"))
            run.frames = int(index["frames"])
            run.cameras = [StagedCamera(int(c["index"]), [str(b) for b in c["bodyparts"]], str(c["source"]),
                                        str(c["scorer"]), None if c["fps"] is None else float(c["fps"]),
                                        bool(c["spread"])) for c in index["cameras"]]
            for cam in run.cameras:
                run._check_whole(cam)
        except (OSError, ValueError, KeyError, TypeError) as e:
            raise InputError(f"no staged run to go on from ({e})", folder) from None
        return run

    @classmethod
    def gather(cls, folder: str | Path, count: int) -> StagedRun | None:
        """The run whose ``count`` cameras were staged in ``folder`` one by one (:func:`stage_camera`,
        each entry there); None when a file holds several individuals; :class:`InputError` when the
        cameras' frames differ (as :meth:`add_blocks` says it), ValueError when a camera's entry or
        arrays are not whole."""
        run = cls(folder)
        for c in range(count):
            try:
                entry = json.loads(run._path(c, "json").read_text(encoding="utf-8"))
                if "camera" not in entry:
                    return None
                cam, frames = StagedCamera(**entry["camera"]), int(entry["frames"])
            except (KeyError, TypeError, ValueError) as e:
                raise ValueError(f"camera {c + 1}'s entry is not a staged camera's ({e})") from None
            if run.cameras:
                _same_frames(frames, cam.source, run.frames, run.cameras[0].source)
            run.frames = frames
            run._check_whole(cam)
            run.cameras.append(cam)
        return run

    def unstaged(self, count: int) -> list[int]:
        """Which of ``count`` cameras staged one by one (:func:`stage_camera`) are not yet whole here."""
        return [c for c in range(count) if not self._path(c, "json").is_file()]

    def _check_whole(self, cam: StagedCamera) -> None:
        """ValueError when a camera's arrays are not the size its entry and the run's frames say."""
        M = len(cam.bodyparts)
        sizes = {"xy": 2 * M, "likelihood": M, **({"spread": M} if cam.spread else {})}
        for name, per_frame in sizes.items():
            if self._path(cam.index, name).stat().st_size != self.frames * per_frame * _F64.itemsize:
                raise ValueError(f"camera {cam.index + 1}'s {name} is not whole")

    def _path(self, camera: int, name: str) -> Path:
        return self.folder / f"{camera}.{name}"

    def _read(self, camera: int, name: str, a: int, n: int, per_frame: int) -> np.ndarray:
        return np.fromfile(self._path(camera, name), dtype=_F64, count=n * per_frame,
                           offset=a * per_frame * _F64.itemsize)


def stage(paths: list[str], folder: str | Path, read: Callable[[str], Iterable[Tracks]],
          long_enough: Callable[[int], bool]) -> StagedRun | None:
    """The cameras' files ``paths``, each read by ``read`` a stretch of frames at a time (one file,
    one stretch, at a time: :func:`graph.io.keypoints.read_blocks`), staged in ``folder`` when the run
    is ``long_enough`` (judged on the first file's frame count) and every file holds one individual;
    None otherwise (read the files as a solve in memory takes them)."""
    Path(folder).mkdir(parents=True, exist_ok=True)
    run = StagedRun(folder)
    for path in paths:
        try:
            run.add_blocks(_one_individual(read(path)))
        except _SeveralIndividuals:
            return None
        if len(run.cameras) == 1 and not long_enough(run.frames):
            return None
    return run


def stage_camera(path: str, folder: str | Path, index: int, read: Callable[[str], Iterable[Tracks]]) -> None:
    """Camera ``index``'s file ``path`` staged in ``folder`` (which must exist) on its own, for
    processes that stage a run's cameras between them (:meth:`StagedRun.gather` puts them together):
    its arrays written in a folder of this call's own, then renamed into ``folder``, then its entry
    ``<index>.json`` (its frame count and :class:`StagedCamera`, or that the file holds several
    individuals), by a rename too: an entry there means the camera is whole, and two processes that
    stage the same camera never write into one file."""
    folder = Path(folder)
    if not folder.is_dir():
        raise FileNotFoundError(f"no folder to stage into: {folder}")
    own = Path(tempfile.mkdtemp(prefix=f".{index}-", dir=folder))
    try:
        run = StagedRun(own)
        try:
            run.add_blocks(_one_individual(read(path)), index=index)
            entry: dict = {"frames": run.frames, "camera": asdict(run.cameras[0])}
        except _SeveralIndividuals:
            entry = {"several_individuals": True}
        for name in ("xy", "likelihood", "spread"):
            if run._path(index, name).exists():
                os.replace(run._path(index, name), folder / run._path(index, name).name)
        run._path(index, "json").write_text(json.dumps(entry), encoding="utf-8")
        os.replace(run._path(index, "json"), folder / run._path(index, "json").name)
    finally:
        shutil.rmtree(own, ignore_errors=True)


def _same_frames(frames: int, source: str, first_frames: int, first_source: str) -> None:
    """:class:`InputError` naming ``source`` when its ``frames`` are not the first camera's."""
    if frames != first_frames:
        name = Path(first_source).name or "camera 1"
        raise InputError(f"has {frames} frames but {name} has {first_frames}; all cameras must have the same "
                         "frames", source or None)


class _SeveralIndividuals(Exception):
    pass


def _one_individual(blocks: Iterable[Tracks]) -> Iterator[Keypoints]:
    for tracks in blocks:
        if tracks.slots != 1:
            raise _SeveralIndividuals
        yield tracks.slot(0)
