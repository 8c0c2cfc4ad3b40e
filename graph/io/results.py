"""Result files: Anipose 3D CSV, a complete HDF5 archive, and reprojections as DeepLabCut CSVs.

* :func:`write_anipose_csv` writes the table ``anipose triangulate`` writes (``to_csv(index=False)``):
  for each marker ``<m>_x, <m>_y, <m>_z, <m>_error, <m>_ncams, <m>_score``, then ``M_00 .. M_22``
  and ``center_0 .. center_2`` (the frame Anipose rotated into: here identity and zero, the
  positions are in the calibration's world frame), then ``fnum``. Empty cells where there is no
  estimate. ``error`` is the mean reprojection error in pixels over the cameras whose detection
  was used, ``ncams`` those cameras' count, ``score`` their mean likelihood.
* :func:`write_h5` / :func:`read_result`: everything in a :class:`graph.api.Result`, as plain
  HDF5 datasets (no pickles): arrays under their field names, names as UTF-8 string datasets,
  options and report as JSON attributes; optionally the calibration solved with, in metres
  (:func:`read_calibration`), so exports can carry the rig. :func:`write_group_h5`: several
  individuals in one such file, every array on a leading individuals axis (:func:`read_results`).
* :func:`write_reprojections_dlc`: the estimate drawn into each camera, one DeepLabCut CSV per
  camera (likelihood 1 where there is an estimate), to overlay on the videos with DLC's tools.
"""

from __future__ import annotations

import csv
import dataclasses
import json
import math
import os
import re
from collections.abc import Collection
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from graph import __version__
from graph.camera import DISTORTION_SLOTS, Calibration, Camera
from graph.errors import InputError, unreadable
from graph.io.calibration import in_metres
from graph.io.keypoints import Keypoints, spreadsheet_safe, write_dlc_csv
from graph.types import FRAME_AXIS, Result, SolveOptions, SolveReport, jsonable

RESULT_FORMAT = "acinoset.result"
RESULT_FORMAT_VERSION = 1
_AXES = ("x", "y", "z")
_MARKER_FIELDS = ("x", "y", "z", "error", "ncams", "score")

# Arrays of a Result written as datasets of the same name; the optional ones may be None.
_ARRAYS = ("positions", "std", "reprojections", "residuals", "ncams", "score", "outlier")
_OPTIONAL_ARRAYS = ("params", "rates", "params_std", "causal_positions", "camera_centers", "detections",
                    "likelihood")


# ------------------------------------------------------------------------------ Anipose 3D CSV


@dataclass
class Points3D:
    """An Anipose 3D table: N frames, M markers."""

    markers: list[str]
    positions: np.ndarray  # (N, M, 3)
    error: np.ndarray  # (N, M) pixels
    ncams: np.ndarray  # (N, M)
    score: np.ndarray  # (N, M)
    fnum: np.ndarray  # (N,)
    M: np.ndarray  # (3, 3) rotation Anipose applied (identity for acinoset output)
    center: np.ndarray  # (3,)


CSV_BLOCK_ROWS = 4096


def write_anipose_csv(path: str | Path, result: Result,
                      frame: tuple[np.ndarray, np.ndarray] | None = None, metres_per_unit: float = 1.0) -> None:
    """Anipose's ``pose-3d`` CSV (column order as ``anipose triangulate``), floats as ``repr``
    (:class:`AniposeCsv`, all of ``result`` at once)."""
    with AniposeCsv(path, result.markers, frame, metres_per_unit) as out:
        out.write(result)


class AniposeCsv:
    """Anipose's ``pose-3d`` CSV written a stretch of frames at a time (a long run's windows as they
    finish; :func:`write_anipose_csv` for a whole result).

    Positions in units of ``metres_per_unit`` metres (1: metres; 0.001: millimetres, as ``anipose
    triangulate`` writes a project calibrated in millimetres): ``X / metres_per_unit``.
    ``frame = (M, center)``: the positions written as ``M X - center`` (``center`` in the same units),
    with ``M`` and ``center`` in their columns, as Anipose writes a run it turned into the frame of
    ``[triangulation] axes`` (:func:`graph.anipose.frame.anipose_frame`). Without it, the
    calibration's frame (identity, 0). ``fnum`` counts the rows written."""

    def __init__(self, path: str | Path, markers: list[str], frame: tuple[np.ndarray, np.ndarray] | None = None,
                 metres_per_unit: float = 1.0, resume: tuple[int, int] | None = None):
        if not (np.isfinite(metres_per_unit) and metres_per_unit > 0):
            raise ValueError(f"metres_per_unit must be a positive number, not {metres_per_unit!r}")
        self.metres_per_unit, self.frame, self.rows = metres_per_unit, frame, 0
        self.M: np.ndarray = np.eye(3) if frame is None else np.asarray(frame[0], float)
        self.center: np.ndarray = np.zeros(3) if frame is None else np.asarray(frame[1], float)
        header = [spreadsheet_safe(f"{name}_{f}") for name in markers for f in _MARKER_FIELDS]
        header += [f"M_{i}{j}" for i in range(3) for j in range(3)] + [f"center_{i}" for i in range(3)] + ["fnum"]
        self.frame_const = ",".join([_cell(v) for v in self.M.ravel().tolist()] +
                                    [_cell(v) for v in self.center.tolist()])
        if resume is not None:  # a file written up to (bytes, rows), by :meth:`position`: on from there
            with open(path, "r+b") as f:
                f.truncate(resume[0])
            self.file = open(path, "a", newline="", encoding="utf-8")
            self.rows = resume[1]
            return
        self.file = open(path, "w", newline="", encoding="utf-8")
        csv.writer(self.file, lineterminator="\n").writerow(header)

    def write(self, result: Result) -> None:
        """The next rows: every frame of ``result``."""
        pos = np.asarray(result.positions, dtype=np.float64) / self.metres_per_unit
        if self.frame is not None:
            pos = pos @ self.M.T - self.center
        n, m = pos.shape[:2]
        has = np.isfinite(pos).all(axis=-1)
        error = np.where(has, result.error, np.nan)
        ncams = np.where(has, np.asarray(result.ncams, dtype=np.float64), np.nan)
        score = np.where(has, np.asarray(result.score, dtype=np.float64), np.nan)
        per_marker = np.concatenate([pos, error[..., None], ncams[..., None], score[..., None]], axis=-1)
        per_marker = np.where(np.isfinite(per_marker), per_marker, np.nan).reshape(n, 6 * m)
        for a in range(0, n, CSV_BLOCK_ROWS):  # a block's rows as Python floats at a time, not the run's
            first = self.rows + a
            self.file.writelines(f"{_cells(row)},{self.frame_const},{first + i}\n"
                                 for i, row in enumerate(per_marker[a:a + CSV_BLOCK_ROWS].tolist()))
        self.rows += n

    def position(self) -> tuple[int, int]:
        """The bytes and rows written so far, on disk (``resume`` goes on from them)."""
        self.file.flush()
        os.fsync(self.file.fileno())
        return os.fstat(self.file.fileno()).st_size, self.rows

    def close(self) -> None:
        self.file.close()

    def __enter__(self) -> AniposeCsv:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def read_anipose_csv(path: str | Path) -> Points3D:
    """Read an Anipose 3D CSV (ours or ``anipose triangulate``'s). Markers are the ``<m>_x``
    columns that have ``<m>_y`` and ``<m>_z``; absent error/ncams/score columns read as NaN."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError:
        raise InputError("not an Anipose CSV (binary, not UTF-8 text)", path) from None
    except OSError as e:
        raise unreadable(e, path, "an Anipose CSV") from None
    rows = [r for r in csv.reader(text.splitlines()) if r]  # blank lines only; ",,," is a row
    if not rows:
        raise InputError("file is empty", path)
    header = [h.strip() for h in rows[0]]
    col = {h: j for j, h in enumerate(header)}
    markers = [h[:-2] for h in header if h.endswith("_x") and f"{h[:-2]}_y" in col and f"{h[:-2]}_z" in col]
    if not markers:
        raise InputError("not an Anipose 3D CSV: no <marker>_x, _y, _z columns", path)
    body = rows[1:]
    values = np.full((len(body), len(header)), np.nan)
    for i, row in enumerate(body):
        if len(row) != len(header):
            raise InputError(f"line {i + 2} has {len(row)} cells, the header has {len(header)}", path)
        for j, cell in enumerate(row):
            cell = cell.strip()
            if cell:
                try:
                    values[i, j] = float(cell)
                except ValueError:
                    raise InputError(f"line {i + 2}, column {header[j]}: not a number: {cell[:40]!r}",
                                     path) from None

    def column(name: str) -> np.ndarray:
        return values[:, col[name]] if name in col else np.full(len(body), np.nan)

    positions = np.stack([np.stack([column(f"{mk}_{a}") for a in _AXES], -1) for mk in markers], 1)
    M = np.array([[column(f"M_{i}{j}")[0] if body and f"M_{i}{j}" in col else float(i == j)
                   for j in range(3)] for i in range(3)])
    center = np.array([column(f"center_{i}")[0] if body and f"center_{i}" in col else 0.0 for i in range(3)])
    fnum = column("fnum") if "fnum" in col else np.arange(len(body), dtype=np.float64)
    return Points3D(markers=markers, positions=positions.reshape(len(body), len(markers), 3),
                    error=np.stack([column(f"{mk}_error") for mk in markers], 1).reshape(len(body), -1),
                    ncams=np.stack([column(f"{mk}_ncams") for mk in markers], 1).reshape(len(body), -1),
                    score=np.stack([column(f"{mk}_score") for mk in markers], 1).reshape(len(body), -1),
                    fnum=fnum.astype(np.int64) if np.isfinite(fnum).all() else fnum, M=M, center=center)


def _cell(v: float) -> str:
    return repr(float(v)) if math.isfinite(v) else ""


def _cells(row: list[float]) -> str:
    """``,``-joined ``repr`` of finite floats, empty cells for NaN, as :func:`_cell` each: one
    ``repr`` of the whole list, which formats its floats the same way in one call (``nan`` is the
    only non-number; no number's ``repr`` contains it)."""
    return repr(row)[1:-1].replace(", ", ",").replace("nan", "")


# ------------------------------------------------------------------------------------ HDF5 archive


def write_h5(path: str | Path, result: Result, calibration: Calibration | None = None,
             individual: str | None = None) -> None:
    """Everything in ``result`` as plain HDF5 (readable from any language; no pickles); with
    ``calibration`` (the one solved with), also the rig in metres (:func:`read_calibration`); with
    ``individual``, whose result it is (one of several solved together: :func:`read_individual`)."""
    import h5py

    with h5py.File(path, "w") as f:
        if individual is not None:
            f.attrs["individual"] = individual
        _write_results(f, [result])
        _write_run(f, result.report, result.options, calibration)


def _write_run(f, report: SolveReport, options: SolveOptions, calibration: Calibration | None) -> None:
    """What one run's file holds besides its arrays: the body the solve used, the cameras' offsets
    and the rig in metres."""
    if report.body_lengths:
        # the body the solve used, one row per length group (or bone): also in the report attribute
        g = f.create_group("body_lengths")
        _strings(g, "names", list(report.body_lengths))
        for col in ("length_m", "std_m", "model_m"):
            g.create_dataset(col, data=np.array([float(v[col]) for v in report.body_lengths.values()]))
    if report.time_offsets_frames is not None:
        f.create_dataset("time_offsets_frames", data=np.asarray(report.time_offsets_frames, dtype=float))
        f.create_dataset("time_offsets_std_frames", data=np.asarray(report.time_offsets_std_frames, dtype=float))
    if calibration is not None:
        _write_calibration(f, in_metres(calibration, options.calibration_units)[0])


class H5Stream:
    """The file of :func:`write_h5` written a stretch of frames at a time, for a run of ``frames``
    frames whose windows finish one after another: each per-frame array a dataset of the run's
    length, chunked along its frame axis (:data:`graph.types.FRAME_AXIS`) and filled as the stretches
    come; the report (and the body, clocks and rig) written by :meth:`close`, after the last.
    ``step`` > 1: the run's frames ``0, step, 2 step, ...`` only (a long run's overview, as
    ``read_result(..., step=step)`` of the whole file reads it, without reading the whole)."""

    CHUNK_FRAMES = 1024

    def __init__(self, path: str | Path, frames: int, resume: int | None = None, step: int = 1):
        import h5py

        self.frames, self.step, self.seen = frames, max(1, int(step)), 0
        if resume:  # a file of which ``resume`` frames were written (:meth:`flush`): on from there
            self.file = h5py.File(path, "r+")
            self.seen = resume
        else:
            self.file = h5py.File(path, "w")

    @property
    def rows(self) -> int:
        """The file's frames written so far."""
        return -(-self.seen // self.step)

    def flush(self) -> int:
        """The run's frames written so far, on disk."""
        self.file.flush()
        return self.seen

    def write(self, result: Result) -> None:
        """The next frames: every frame of ``result`` (every ``step``-th of the run's)."""
        f, n = self.file, result.positions.shape[0]
        first, rows = (-self.seen) % self.step, self.rows  # the stretch's first frame kept, where it goes
        if self.seen == 0:
            _write_header(f, result)
            for name in _ARRAYS + _OPTIONAL_ARRAYS:
                a = getattr(result, name, None)
                if a is None:
                    continue
                a = np.asarray(a)
                axis = FRAME_AXIS.get(name)
                if axis is None:  # not per frame: once
                    _write_array(f, name, a)
                    continue
                length = -(-self.frames // self.step)
                shape = a.shape[:axis] + (length,) + a.shape[axis + 1:]
                chunks = a.shape[:axis] + (max(1, min(length, self.CHUNK_FRAMES)),) + a.shape[axis + 1:]
                _write_array(f, name, a, shape=shape, chunks=chunks)
        for name, axis in FRAME_AXIS.items():
            a = getattr(result, name, None)
            if a is not None and name in f:
                a = np.asarray(a)[(slice(None),) * axis + (slice(first, None, self.step),)]
                f[name][(slice(None),) * axis + (slice(rows, rows + a.shape[axis]),)] = (
                    a.astype(np.uint8) if a.dtype == bool else a)
        self.seen += n

    def close(self, report: SolveReport, options: SolveOptions, calibration: Calibration | None = None) -> None:
        """The run's ``report``, body, clocks and rig, and the file closed."""
        if self.seen != self.frames:
            self.file.close()
            raise ValueError(f"{self.seen} of {self.frames} frames were written")
        self.file.attrs["report"] = json.dumps(report.to_dict())
        _write_run(self.file, report, options, calibration)
        self.file.close()


def write_group_h5(path: str | Path, group: list[tuple[str, Result]], calibration: Calibration | None = None,
                   identity: dict | None = None) -> None:
    """Several individuals solved together (the same frames, markers and cameras) in one file with an
    individuals axis: the dataset ``individuals`` names them, every array of :func:`write_h5` gains a
    leading axis I (``positions`` (I, N, M, 3), ``reprojections`` (I, C, N, M, 2) ...; an optional
    array only where every individual has it), the ``report`` attribute is the JSON list of their
    reports (each with its body) and ``identity`` the identities' report. Read one with
    ``read_result(path, individual=NAME)``, all with :func:`read_results`."""
    import h5py

    names = [name for name, _ in group]
    if not names or len(set(names)) != len(names):
        raise ValueError(f"a group needs distinct names, not {names}")
    with h5py.File(path, "w") as f:
        _strings(f, "individuals", names)
        _write_results(f, [r for _, r in group])
        if identity is not None:
            f.attrs["identity"] = json.dumps(jsonable(identity))
        if calibration is not None:
            _write_calibration(f, in_metres(calibration, group[0][1].options.calibration_units)[0])


def _write_results(f, results: list[Result]) -> None:
    """The attributes, names and arrays of :func:`write_h5` for one result, or stacked on a leading
    individuals axis for several (:func:`write_group_h5`): they share method, skeleton, fps,
    options, markers, cameras and bones, the first one's written."""
    stacked = len(results) > 1 or "individuals" in f
    _write_header(f, results[0])
    reports = [r.report.to_dict() for r in results]
    f.attrs["report"] = json.dumps(reports if stacked else reports[0])
    for name in _ARRAYS + _OPTIONAL_ARRAYS:
        values = [getattr(r, name, None) for r in results]
        if any(v is None for v in values):
            continue
        _write_array(f, name, np.stack([np.asarray(v) for v in values]) if stacked else np.asarray(values[0]))


def _write_header(f, first: Result) -> None:
    """The attributes and names of a result file (all but the report), from its ``first`` result."""
    import h5py

    f.attrs["format"] = RESULT_FORMAT
    f.attrs["format_version"] = RESULT_FORMAT_VERSION
    f.attrs["version"] = __version__
    f.attrs["method"] = first.method
    f.attrs["skeleton"] = first.skeleton
    f.attrs["fps"] = float(first.fps)
    f.attrs["options"] = json.dumps(jsonable(first.options.to_dict()))
    _strings(f, "markers", first.markers)
    _strings(f, "camera_names", first.camera_names)
    _strings(f, "param_names", first.param_names)
    bones = np.array([[str(a), str(b)] for a, b in first.bones], dtype=object).reshape(-1, 2)
    f.create_dataset("bones", data=bones, dtype=h5py.string_dtype("utf-8"))


def _write_array(f, name: str, a: np.ndarray, shape: tuple | None = None, chunks: tuple | None = None) -> None:
    """Dataset ``name`` holding ``a`` (bool as uint8, with the attribute ``dtype = "bool"``); with
    ``shape`` (and ``chunks``), an empty one of that shape and ``a``'s type, filled later.

    gzip for the flags and counts only: measured on a 150-frame run, it took the float arrays
    (positions, residuals, detections ...) from 1.17 to 1.01 MB (shuffled) at 8x the write time (20
    ms against 2.5 ms), and the flags from 18 to 2 kB for nothing."""
    size = a.size if shape is None else int(np.prod(shape))
    kw = {"compression": "gzip", "compression_opts": 4} if size > 4096 and a.dtype.kind in "biu" else {}
    dtype = np.uint8 if a.dtype == bool else a.dtype
    if shape is None:
        f.create_dataset(name, data=a if a.dtype == dtype else a.astype(dtype), **kw)
    else:
        f.create_dataset(name, shape=shape, dtype=dtype, chunks=chunks, **kw)
    if a.dtype == bool:
        f[name].attrs["dtype"] = "bool"


def _write_calibration(f, calibration: Calibration) -> None:
    """Group ``calibration``: per camera (C) ``names``, ``models`` (fisheye|pinhole|...: the names of
    :data:`graph.camera.CAMERA_MODELS`), ``size`` (C, 2) px, ``K`` (C, 3, 3), ``R`` (C, 3, 3) and ``t``
    (C, 3) m with ``X_c = R X_w + t``, ``dist`` (C, :data:`graph.camera.DISTORTION_SLOTS`, 5 today): the
    model's coefficients then NaN (fisheye: k1..k4 then NaN; pinhole: k1, k2, p1, p2, k3)."""
    g = f.create_group("calibration")
    g.attrs["units"] = "m"
    g.attrs["source"] = calibration.source or ""
    cams = calibration.cameras
    _strings(g, "names", calibration.names)
    _strings(g, "models", [c.model for c in cams])
    g.create_dataset("size", data=np.array([c.size for c in cams], dtype=np.int64).reshape(-1, 2))
    for name in ("K", "R"):
        g.create_dataset(name, data=np.stack([getattr(c, name) for c in cams]))
    g.create_dataset("t", data=np.stack([c.t for c in cams]))
    g.create_dataset("dist", data=np.stack([np.pad(c.dist, (0, DISTORTION_SLOTS - c.dist.size), constant_values=np.nan)
                                            for c in cams]))


def read_individual(path: str | Path) -> str | None:
    """The individual a result file is of (several solved together), or None."""
    import h5py

    with h5py.File(path, "r") as f:
        return _attr(f, "individual")


def read_individuals(path: str | Path) -> list[str]:
    """The names along a group file's individuals axis (:func:`write_group_h5`); ``[]`` for a file
    of one result."""
    import h5py

    with h5py.File(path, "r") as f:
        return _read_strings(f, "individuals")


def read_results(path: str | Path) -> list[tuple[str, Result]]:
    """Every individual in a result file with its name: a group file's, or the one result of any
    other (named after its ``individual`` attribute, else the file's stem)."""
    _check_result_file(path)
    names = read_individuals(path)
    if names:
        return [(name, read_result(path, individual=name)) for name in names]
    return [(read_individual(path) or Path(path).stem, read_result(path))]


def _check_result_file(path: str | Path) -> None:
    import h5py

    path = Path(path)
    if not path.exists():
        raise InputError("no such file", path)
    try:
        f = h5py.File(path, "r")
    except OSError:
        raise InputError("not an HDF5 file", path) from None
    with f:
        if _attr(f, "format") != RESULT_FORMAT:
            raise InputError("not an acinoset result file (no format attribute 'acinoset.result')", path)


def read_calibration(path: str | Path) -> Calibration | None:
    """The rig (metres) a result file was solved with, or None if the file does not hold it."""
    import h5py

    with h5py.File(path, "r") as f:
        if "calibration" not in f:
            return None
        g = f["calibration"]
        names, models = _read_strings(g, "names"), _read_strings(g, "models")
        K, R, t, dist, size = (g[k][()] for k in ("K", "R", "t", "dist", "size"))
        cams = [Camera(K=K[i], dist=dist[i][np.isfinite(dist[i])], R=R[i], t=t[i], model=models[i],
                       size=tuple(size[i]), name=names[i]) for i in range(len(names))]
        return Calibration(cameras=cams, source=_attr(g, "source") or "", metadata={"units": "m"})


def read_result(path: str | Path, individual: str | None = None, step: int = 1,
                arrays: Collection[str] | None = None) -> Result:
    """Read a file written by :func:`write_h5` back into a :class:`Result`; of a group file
    (:func:`write_group_h5`), the ``individual`` named, which it must then be given. ``step`` > 1:
    every ``step``-th frame only (a long run's overview; the rates and sds as they were).
    ``arrays``: only these of the per-frame arrays are read (an export of an hour needs four of them:
    the cameras' reprojections alone are 0.8 GB); a required one not named is a read-only view of its
    shape filled with NaN (False, 0 for flags and counts) that takes no memory, an optional one is
    left out."""
    import h5py

    path = Path(path)
    _check_result_file(path)
    with h5py.File(path, "r") as f:
        names = _read_strings(f, "individuals")
        at: Any = ()
        if names:
            if individual is None:
                raise InputError(f"holds {len(names)} individuals ({', '.join(names)}): name one "
                                 "(--individual NAME)", path)
            if individual not in names:
                raise InputError(f"holds no individual '{individual}' (it holds {', '.join(names)})", path)
            at = names.index(individual)
            if "positions" in f and (f["positions"].ndim != 4 or f["positions"].shape[0] != len(names)):
                raise InputError(f"damaged acinoset result file (names {len(names)} individuals, its positions "
                                 f"have shape {f['positions'].shape})", path)
        elif individual is not None and _attr(f, "individual") not in (None, individual):
            raise InputError(f"is the result of '{_attr(f, 'individual')}', not '{individual}'", path)
        try:
            got: dict[str, Any] = {}
            for name in _ARRAYS + _OPTIONAL_ARRAYS:
                if name in f:
                    axis = FRAME_AXIS.get(name)
                    index: tuple = () if at == () else (at,)
                    if step > 1 and axis is not None:
                        index += (slice(None),) * axis + (slice(None, None, step),)
                    boolean = _attr(f[name], "dtype") == "bool"
                    if arrays is not None and name not in arrays:
                        if name in _ARRAYS:
                            shape = np.broadcast_to(np.uint8(0), f[name].shape)[index].shape  # nothing read
                            dtype = bool if boolean else f[name].dtype
                            fill = np.array(np.nan if np.issubdtype(dtype, np.floating) else 0, dtype=dtype)
                            got[name] = np.broadcast_to(fill, shape)
                        continue
                    a = f[name][index]
                    got[name] = a.astype(bool) if boolean else a
                elif name in _ARRAYS:
                    raise InputError(f"result file lacks the dataset '{name}'", path)
            bones = [(_text(a), _text(b)) for a, b in f["bones"][()]] if "bones" in f else []
            fields: dict[str, Any] = {
                "method": _attr(f, "method"),
                "skeleton": _attr(f, "skeleton"),
                "fps": float(f.attrs["fps"]),
                "markers": _read_strings(f, "markers"),
                "camera_names": _read_strings(f, "camera_names"),
                "param_names": _read_strings(f, "param_names"),
                "bones": bones,
                "options": _options(json.loads(_attr(f, "options") or "")),
                "report": _report(_pick(json.loads(_attr(f, "report") or ""), at)),
            }
            M = len(fields["markers"])
            for name in ("positions", "std"):  # what every reader of a result takes as (N, M, 3)
                if got[name].ndim != 3 or got[name].shape[1:] != (M, 3):
                    raise InputError(f"damaged acinoset result file (its {name} have shape {got[name].shape}, "
                                     f"not (frames, {M} markers, 3))", path)
        except (KeyError, ValueError, TypeError, IndexError) as e:
            if isinstance(e, InputError):
                raise
            raise InputError(f"damaged acinoset result file ({type(e).__name__}: {e})", path) from None
    known = {fld.name for fld in dataclasses.fields(Result)}
    return Result(**fields, **{k: v for k, v in got.items() if k in known})


def _pick(value, at):
    """A group file's attribute list at index ``at``; a single file's value as it is (``at`` is ())."""
    return value if at == () else value[at]


def _strings(f, name: str, values: list[str]) -> None:
    import h5py

    f.create_dataset(name, data=np.array([str(v) for v in values], dtype=object),
                     dtype=h5py.string_dtype("utf-8"))


def _read_strings(f, name: str) -> list[str]:
    return [_text(v) for v in f[name][()]] if name in f else []


def _text(v) -> str:
    return v.decode("utf-8") if isinstance(v, bytes) else str(v)


def _attr(obj, name: str) -> str | None:
    v = obj.attrs.get(name)
    return None if v is None else _text(v)


def _options(d: dict) -> SolveOptions:
    known = {fld.name for fld in dataclasses.fields(SolveOptions)}
    d = {k: v for k, v in d.items() if k in known}
    if d.get("bone_lengths") is not None:
        d["bone_lengths"] = [tuple(b) for b in d["bone_lengths"]]
    return SolveOptions(**d)


def _report(d: dict) -> SolveReport:
    """Inverse of ``SolveReport.to_dict``: JSON ``null`` back to NaN in the float fields."""
    known = {fld.name: fld for fld in dataclasses.fields(SolveReport)}
    d = {k: v for k, v in d.items() if k in known}
    for k in ("cost", "reprojection_rmse_px", "sigma_px", "noise_px"):
        if k in d and d[k] is None:
            d[k] = float("nan")
    for k in ("seconds", "per_frame_ms"):
        if isinstance(d.get(k), dict):
            d[k] = {a: float("nan") if b is None else b for a, b in d[k].items()}
    return SolveReport(**d)


# ------------------------------------------------------------------- reprojections for DeepLabCut


def write_reprojections_dlc(directory: str | Path, result: Result, stems: list[str] | None = None) -> list[Path]:
    """One DeepLabCut single-animal CSV per camera with the estimate reprojected into it.

    Files are ``<directory>/<stem>.csv`` with ``stems`` (default: the camera names); the scorer is
    ``acinoset_<method>``, likelihood 1 where the marker has an estimate, empty cells elsewhere.
    """
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    reproj = np.asarray(result.reprojections, dtype=np.float64)
    stems = list(stems) if stems is not None else [safe_name(c) for c in result.camera_names]
    if len(stems) != reproj.shape[0]:
        raise ValueError(f"{len(stems)} file names for {reproj.shape[0]} cameras")
    paths = []
    for c, stem in enumerate(stems):
        xy = reproj[c]
        seen = np.isfinite(xy).all(axis=-1)
        kp = Keypoints(bodyparts=list(result.markers), xy=np.where(seen[..., None], xy, np.nan),
                       likelihood=seen.astype(np.float64), scorer=f"acinoset_{result.method}")
        p = directory / f"{stem}.csv"
        write_dlc_csv(p, kp)
        paths.append(p)
    return paths


def safe_name(name: str, default: str = "camera") -> str:
    """A name (a camera's, an individual's) as part of a file name: letters, digits, ``_ . -`` (others
    ``_``), no leading dot, so a name from an upload cannot leave the output folder."""
    return re.sub(r"[^A-Za-z0-9._-]+", "_", str(name)).strip("._") or default


# ----------------------------------------------------------------------------------- a body, reused

def _earlier_report(path: str | Path, missing: str) -> dict | list:
    """The report of an earlier solve, from its report JSON or result H5 (or a JSON file of one's
    own); :class:`InputError` naming ``path`` (``missing``: what to say when there is no file)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(missing, path)
    if path.read_bytes()[:8] == b"\x89HDF\r\n\x1a\n":
        import h5py

        try:
            with h5py.File(path, "r") as f:
                return json.loads(_attr(f, "report") or "{}")
        except (OSError, ValueError):
            raise InputError("not a result file written by acinoset", path) from None
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, ValueError) as e:
        raise InputError(f"not JSON ({type(e).__name__})", path) from None


def read_body(path: str | Path) -> dict[str, float]:
    """The body lengths (m per length group or bone) of an earlier solve, to solve more runs of the
    same animal with (``body="given"``): its report JSON or result H5 (``body_lengths``: ``{name:
    {length_m, std_m, model_m}}``), or a JSON object ``{name: length_m}``."""
    data = _earlier_report(path, "no such body file (give model, estimate, or a report JSON or result H5 "
                                 "with body_lengths)")
    lengths = data.get("body_lengths", data) if isinstance(data, dict) else None
    if not isinstance(lengths, dict) or not lengths:
        raise InputError("holds no body_lengths (solve one run with --body estimate and give its report)", path)
    out = {}
    for name, v in lengths.items():
        L = v.get("length_m") if isinstance(v, dict) else v
        if not isinstance(L, (int, float)) or isinstance(L, bool) or not 0 < L < float("inf"):
            raise InputError(f"body length {name!r} is not a positive number of metres", path)
        out[str(name)] = float(L)
    return out


def read_motion(path: str | Path) -> tuple[dict[str, float], dict[str, int] | None]:
    """The smoothing an earlier solve fitted (``motion_scale="auto"``), to solve more runs of the
    same rig and animal with it, without fitting again: ``motion_scales`` ``{group: scale}`` of its
    report JSON or result H5, and ``motion_orders`` ``{group: k}``, the order each was fitted for
    (None in reports written before they were kept with the scales)."""
    data = _earlier_report(path, "no such file (give a number, auto, or the report JSON or result H5 of a "
                                 "solve with the motion scale fitted)")
    scales = data.get("motion_scales") if isinstance(data, dict) else None
    if not isinstance(data, dict) or not isinstance(scales, dict) or not scales:
        raise InputError("holds no motion_scales (solve one run with --motion-scale auto and give its report)", path)
    orders = data.get("motion_orders")
    for name, v in scales.items():
        if not isinstance(v, (int, float)) or isinstance(v, bool) or not 0 < v < float("inf"):
            raise InputError(f"motion scale {name!r} is not a positive number", path)
    if orders is not None and (not isinstance(orders, dict) or set(orders) != set(scales)
                               or any(k not in (1, 2, 3) or isinstance(k, bool) for k in orders.values())):
        raise InputError("motion_orders must give 1, 2 or 3 for each group of motion_scales", path)
    return ({str(k): float(v) for k, v in scales.items()},
            {str(k): int(v) for k, v in orders.items()} if orders is not None else None)


def given_motion(path: str | Path, order: int | str | None = None) -> tuple[dict[str, float], dict[str, int] | int]:
    """An earlier solve's fitted smoothing (:func:`read_motion`) as ``motion_scale`` and
    ``motion_order`` values: its scales with the orders they were fitted for. ``order``, when given,
    must be those orders; a file from before the orders were kept needs it (1, 2 or 3), since a
    scale means nothing with another order's prior. :class:`InputError` naming ``path`` otherwise."""
    scales, orders = read_motion(path)
    if orders is None:
        if order not in (1, 2, 3):
            raise InputError("it does not say which order its scales were fitted for: give that motion order "
                             "(1, 2 or 3) with it", path)
        return scales, order
    if order is not None and {order} != set(orders.values()):
        fitted = ", ".join(str(k) for k in sorted(set(orders.values())))
        raise InputError(f"its scales were fitted for motion order(s) {fitted}: give no motion order with it", path)
    return scales, orders
