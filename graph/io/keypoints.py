"""2D keypoints from DeepLabCut and SLEAP: one :class:`Keypoints` per camera.

Readers: DeepLabCut CSV (single-animal 3-row header, multi-animal 4-row header), DeepLabCut H5,
SLEAP's analysis HDF5 export (:mod:`graph.io.sleap`) and SLEAP's labels files, ``.slp``
(:mod:`graph.io.slp`, through sleap-io), chosen by the datasets a file holds; the first three read
with h5py only: the PyTables attributes in those files are pickles, and an uploaded file must
never execute code, so nothing here unpickles.

Layouts (what ``DataFrame.to_csv`` / ``to_hdf`` write for DeepLabCut's column MultiIndex):

* CSV, single animal::

      scorer,DLC_resnet50_...,DLC_resnet50_...,DLC_resnet50_...,...
      bodyparts,nose,nose,nose,...
      coords,x,y,likelihood,...
      0,812.3,433.9,0.998,...

  Multi-animal files add an ``individuals`` row after ``scorer``; the pseudo-individual
  ``single`` holds the unique bodyparts. Labelled-data files (``CollectedData_*.csv``) have a
  3-column row index (``labeled-data,video,img.png``: the header rows then start with two empty
  cells) and only ``x, y``: their likelihood is 1 where labelled.

* H5 written with ``format="table"`` (what ``deeplabcut.analyze_videos`` writes): a compound
  dataset ``/<key>/table`` with fields ``index`` and ``values_block_k`` (N, C_k); the column labels
  exist only in the table attribute ``values_block_k_kind``, a pickled list of label tuples.
  We read that pickle with :func:`_literal_unpickle`, which walks the opcodes with
  ``pickletools.genops`` (a parser that never executes anything) and builds lists, tuples, dicts,
  strings and numbers only: any opcode that would import or call something is refused.

* H5 written in the default "fixed" format: ``/<key>/block0_values`` (N, C) plus plain arrays
  ``axis0_level<i>`` (the level's labels) and ``axis0_label<i>`` (codes into it) for the column
  MultiIndex, and the same ``block<k>_items_*`` per block. No pickle is needed there.

Bounded memory: :class:`ReadLimits` (frames, bodyparts) are checked against what a file declares
before its data are read (an H5 dataset's shape, a CSV's header and running row count), and a CSV
is parsed a block of rows at a time, so a reader never holds more than about twice the largest
array the limits allow, whatever size the file claims.

Missing data: x, y may be NaN (DeepLabCut writes empty cells for them); a point with either
coordinate missing is missing (both NaN, likelihood 0). A NaN likelihood reads as 0. Likelihoods
are clipped to [0, 1]; infinite coordinates are an error.
"""

from __future__ import annotations

import csv
import pickletools
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import NamedTuple

import numpy as np

from graph.errors import InputError, TooLargeInput, unreadable
from graph.io.keypoint_types import EVERY, MAX_SLOTS, NO_LIMITS, Keypoints, ReadLimits, Tracks, as_tracks

CSV_BLOCK_ROWS = 4096  # rows parsed at a time
MAX_LABEL_BYTES = 4096  # one column label of an H5 file (a scorer's, a bodypart's name)

SINGLE = "single"  # DeepLabCut's pseudo-individual holding the unique bodyparts
_LEVELS_SINGLE = ("scorer", "bodyparts", "coords")
_LEVELS_MULTI = ("scorer", "individuals", "bodyparts", "coords")
_HDF5_MAGIC = b"\x89HDF\r\n\x1a\n"


# ------------------------------------------------------------------------------------- reading


def read_keypoints(path: str | Path, individual: str | None = None, limits: ReadLimits = NO_LIMITS,
                   openpose_model: str | None = None) -> Keypoints:
    """Read a DeepLabCut CSV or H5 file, a SLEAP analysis HDF5 or labels (.slp) file (chosen by
    content, not extension), or a folder of OpenPose JSON files (:mod:`graph.io.openpose`, its
    keypoints named by ``openpose_model``).

    ``individual`` picks one animal from a multi-animal file (a SLEAP track by its name); by default
    the first one (not counting ``single``), with a warning naming the others. Single-animal files ignore it.
    A file over ``limits`` raises :class:`~graph.errors.TooLargeInput` before its data are read.
    """
    out = _read(Path(path), individual, limits, openpose_model)
    assert isinstance(out, Keypoints)
    return out


def read_tracks(path: str | Path, limits: ReadLimits = NO_LIMITS, openpose_model: str | None = None) -> Tracks:
    """Every individual of one camera's file, as :class:`Tracks` (read as :func:`read_keypoints`
    reads one): DeepLabCut's individuals but ``single``, SLEAP's tracks (an untracked file: one slot),
    OpenPose's people (``identified`` False). A single-animal file gives one slot."""
    out = _read(Path(path), EVERY, limits, openpose_model)
    assert isinstance(out, Tracks)
    return out


def read_recording(paths: list, individual: str | None = None, individuals: int | None = None,
                   limits: ReadLimits = NO_LIMITS, openpose_model: str | None = None) -> list[Keypoints] | list[Tracks]:
    """One camera's detections per path, as a solve takes them: :class:`Keypoints` for one individual
    (``individual`` named, or every file holding one and no count ``individuals`` given), else
    :class:`Tracks` for :func:`graph.api.solve_group`. Each file is read once."""
    if individual is not None:
        return [read_keypoints(p, individual, limits, openpose_model) for p in paths]
    tracks = [read_tracks(p, limits, openpose_model) for p in paths]
    if individuals is None and all(t.slots == 1 for t in tracks):
        return [t.slot(0) for t in tracks]
    return tracks


def _read(path: Path, individual: str | None, limits: ReadLimits, openpose_model: str | None) -> Keypoints | Tracks:
    if path.is_dir():
        from graph.io import openpose

        if openpose.is_openpose_folder(path):
            if individual == EVERY:
                return openpose.read_openpose_people(path, limits, openpose_model)
            return openpose.read_openpose(path, limits, openpose_model)
    if _head(path).startswith(_HDF5_MAGIC):
        return _read_h5(path, individual, limits)
    return _read_csv(path, individual, limits)


def _read_csv(path: Path, individual: str | None, limits: ReadLimits) -> Keypoints | Tracks:
    """Stream the file: the header rows first (their width checked against ``limits`` before they
    are split), then the data a block of :data:`CSV_BLOCK_ROWS` rows at a time, the row count
    checked as it grows."""
    with _csv_text(path) as f:
        return _parse_csv(f, path, individual, limits)


@contextmanager
def _csv_text(path: Path):
    """The file open as UTF-8 text; one-line errors for a file that cannot be opened or is not text."""
    try:
        f = open(path, encoding="utf-8-sig", newline="")
    except OSError as e:
        raise unreadable(e, path, "a keypoint file") from None
    try:
        with f:
            yield f
    except UnicodeDecodeError:
        raise InputError("not a DeepLabCut CSV or H5 file (binary, not UTF-8 text)", path) from None


def _text_lines(f, path: Path, max_chars: int | None):
    """(line number, line without its end) of ``f``; a line longer than ``max_chars`` is refused
    unread beyond that."""
    number = 0
    while True:
        line = f.readline(max_chars + 1) if max_chars is not None else f.readline()
        if not line:
            return
        number += 1
        if max_chars is not None and len(line) > max_chars:
            raise TooLargeInput(f"line {number} is longer than {max_chars} characters (more columns than "
                                "the bodyparts limit allows)", path, "bodyparts")
        if "\x00" in line:
            raise InputError("not a DeepLabCut CSV or H5 file (binary data)", path)
        yield number, line.rstrip("\r\n")


def _parse_csv(f, path: Path, individual: str | None, limits: ReadLimits) -> Keypoints | Tracks:
    columns, blocks = _csv_blocks(f, path, limits)
    parts = list(blocks)
    values = parts[0] if len(parts) == 1 else np.concatenate(parts)
    del parts
    return _from_columns(columns, values, path, individual)


def read_blocks(path: str | Path, limits: ReadLimits = NO_LIMITS,
                openpose_model: str | None = None) -> Iterator[Tracks]:
    """Every individual of one camera's file (:func:`read_tracks`) a stretch of frames at a time: a
    DeepLabCut CSV :data:`CSV_BLOCK_ROWS` rows at a time (its header checked once, the same errors
    as a whole read), any other format whole, as one stretch."""
    path = Path(path)
    if path.is_dir() or _head(path).startswith(_HDF5_MAGIC):
        yield read_tracks(path, limits, openpose_model)
        return
    with _csv_text(path) as f:
        columns, blocks = _csv_blocks(f, path, limits)
        for values in blocks:
            out = _from_columns(columns, values, path, EVERY)
            assert isinstance(out, Tracks)
            yield out


def _head(path: Path) -> bytes:
    try:
        with open(path, "rb") as f:
            head = f.read(8)
    except OSError as e:
        raise unreadable(e, path, "a keypoint file") from None
    if not head:
        raise InputError("file is empty", path)
    return head


def _csv_blocks(f, path: Path, limits: ReadLimits) -> tuple[list[tuple], Iterator[np.ndarray]]:
    """A DeepLabCut CSV's columns (its header read and checked), and its data a block of
    :data:`CSV_BLOCK_ROWS` rows at a time as they are read (the row count checked as it grows; no
    row at all is an :class:`InputError` once the data are read)."""
    # a generous bound on a line's length where columns are bounded: 64 characters a cell
    max_chars = None if limits.max_columns is None else 64 * (limits.max_columns + 8) + 4096
    lines = _text_lines(f, path, max_chars)
    rows: list[list[str]] = []
    levels: list[str] = []
    for number, line in lines:
        if not rows and not line.strip():
            continue  # leading blank lines
        if limits.max_columns is not None:
            limits.check_columns(max(0, line.count(",") - 3), path)  # up to 3 index columns
        rows.append(_csv_row(line, path))
        levels.append(rows[-1][0].strip() if rows[-1] else "")
        if levels[0] != "scorer":
            raise InputError(f"not a DeepLabCut CSV: the first row must start with 'scorer', not "
                             f"{levels[0][:40]!r}", path)
        if levels[-1] == "coords" or len(rows) == 4:
            break
    if not rows:
        raise InputError("file is empty", path)
    if tuple(levels) not in (_LEVELS_SINGLE, _LEVELS_MULTI):
        raise InputError("not a DeepLabCut CSV: header rows must be scorer, bodyparts, coords "
                         "(or scorer, individuals, bodyparts, coords), found " + ", ".join(levels), path)
    header = rows
    width = len(header[0])
    for h in header[1:]:
        if len(h) != width:
            raise InputError(f"ragged header: row '{h[0]}' has {len(h)} cells, 'scorer' has {width}", path)
    coords_row = header[-1]
    n_index = 1
    while n_index < width and coords_row[n_index].strip() == "":
        n_index += 1
    if n_index >= width:
        raise InputError("not a DeepLabCut CSV: no data columns", path)
    limits.check_columns(width - n_index, path)
    columns = [tuple(h[j].strip() for h in header) for j in range(n_index, width)]
    return columns, _csv_data(lines, path, limits, n_index, width)


def _csv_data(lines, path: Path, limits: ReadLimits, n_index: int, width: int) -> Iterator[np.ndarray]:
    block: list[tuple[int, str | list[str]]] = []  # a row's data cells: as text, or split when quoted
    frames = 0
    blank_from: int | None = None  # first of a run of blank lines: fine at the end only
    for number, line in lines:
        if not line.strip():
            blank_from = blank_from or number
            continue
        if blank_from is not None:
            raise InputError(f"line {blank_from} has 1 cells, the header has {width} (truncated or ragged file)", path)
        if '"' in line:
            row = _csv_row(line, path)
            cells, data = len(row), row[n_index:]
        else:  # numbers need no quoting: the cells are the commas' count
            cells = line.count(",") + 1
            data = line.split(",", n_index)[-1]
        if cells != width:
            raise InputError(f"line {number} has {cells} cells, the header has {width} "
                             "(truncated or ragged file)", path)
        block.append((number, data))
        frames += 1
        limits.check_frames(frames, path, counting=True)
        if len(block) == CSV_BLOCK_ROWS:
            yield _csv_numbers(block, n_index, path)
            block = []
    if block:
        yield _csv_numbers(block, n_index, path)
    if frames == 0:
        raise InputError("no data rows after the header", path)


def _csv_numbers(block: list[tuple[int, str | list[str]]], n_index: int, path: Path) -> np.ndarray:
    """The data cells of a block of rows (each as its text, or its cells) as floats (empty: NaN);
    the first cell that is not a number is named by line and column.

    Fast path: rows of plain numbers, all non-empty, parsed at once by NumPy (``np.fromstring``, the
    same correctly rounded conversion as ``float``); anything else (an empty cell, a word, a row
    NumPy reads as another count of numbers) takes the cell-by-cell path."""
    width = len(block[0][1]) if isinstance(block[0][1], list) else block[0][1].count(",") + 1
    texts = [data for _, data in block if isinstance(data, str)]
    if len(texts) == len(block):
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # NumPy stops at a cell it cannot read, with a warning
            try:
                flat = np.fromstring(",".join(texts), dtype=np.float64, sep=",")
            except (ValueError, Warning):
                flat = None
        if flat is not None and flat.size == len(block) * width:
            return flat.reshape(len(block), width)
    rows = [(number, data.split(",") if isinstance(data, str) else data) for number, data in block]
    try:  # plain numbers and empty cells
        return np.array([[float(c or "nan") for c in row] for _, row in rows], dtype=np.float64)
    except ValueError:
        pass
    values = np.empty((len(rows), width))
    for i, (number, row) in enumerate(rows):
        for j, cell in enumerate(row):
            cell = cell.strip()
            try:
                values[i, j] = float(cell or "nan")
            except ValueError:
                raise InputError(f"line {number}, column {n_index + j + 1}: not a number: {cell[:40]!r}",
                                 path) from None
    return values


def _csv_row(line: str, path: Path) -> list[str]:
    try:
        return next(csv.reader([line]), [])
    except csv.Error as e:
        raise InputError(f"not a valid CSV file ({e})", path) from None


def _read_h5(path: Path, individual: str | None, limits: ReadLimits) -> Keypoints | Tracks:
    import h5py

    try:
        f = h5py.File(path, "r")
    except OSError as e:
        raise InputError(f"not a readable HDF5 file ({' '.join(str(e).split())[:120]})", path) from None
    try:
        with f:
            from graph.io import sleap

            if sleap.is_analysis(f):
                return sleap.read_analysis(f, path, individual, limits)
            from graph.io import slp

            if slp.is_slp(f):
                slp.check_slp(f, path, limits)
                return slp.read_slp(path, individual, limits)
            group = _dlc_group(f, path)
            kind = _text(group.attrs.get("pandas_type", b""))
            if kind == "frame_table":
                columns, values = _h5_table(group, path, limits)
            elif kind == "frame":
                columns, values = _h5_fixed(group, path, limits)
            else:
                raise InputError(f"not a DeepLabCut H5 file: group '{group.name}' is not a pandas "
                                 f"DataFrame (pandas_type {kind!r})", path)
    except InputError:
        raise
    except (OSError, KeyError, RuntimeError, ValueError, TypeError) as e:  # h5py's words for a damaged file
        raise InputError(f"damaged HDF5 file ({' '.join(str(e).strip(chr(39)).split())[:120]})", path) from None
    if values.ndim != 2 or values.shape[1] != len(columns):
        raise InputError(f"H5 data have shape {values.shape} for {len(columns)} column labels", path)
    if values.shape[0] == 0:
        raise InputError("no data rows", path)
    return _from_columns(columns, values, path, individual)


def _dlc_group(f, path: Path):
    """The DataFrame's group: ``df_with_missing`` (analyze_videos), ``keypoints`` (labelled data),
    or the only top-level group that pandas wrote."""
    import h5py

    for key in ("df_with_missing", "keypoints"):
        if isinstance(f.get(key), h5py.Group):
            return f[key]
    groups = [g for g in f.values() if isinstance(g, h5py.Group) and "pandas_type" in g.attrs]
    if len(groups) == 1:
        return groups[0]
    if not groups:
        raise InputError("not a DeepLabCut H5 file: no pandas DataFrame in it", path)
    raise InputError("H5 file holds several DataFrames (" + ", ".join(g.name for g in groups)
                     + "); expected one", path)


def _h5_table(group, path: Path, limits: ReadLimits) -> tuple[list[tuple], np.ndarray]:
    """``format="table"``: values from ``table['values_block_k']``, labels from the
    ``values_block_k_kind`` attribute (a pickled list of label tuples, read as literals only)."""
    if "table" not in group:
        raise InputError(f"H5 group '{group.name}' has no 'table' dataset", path)
    table = group["table"]
    names = table.dtype.names or ()
    blocks = [n for n in names if n.startswith("values_block_")]
    if not blocks:
        raise InputError("H5 table has no values_block columns", path)
    if table.ndim != 1:
        raise InputError(f"H5 table has shape {table.shape}, expected one row per frame", path)
    limits.check_frames(table.shape[0], path)
    limits.check_columns(sum(int(np.prod(table.dtype[b].shape)) for b in blocks), path)
    for b in blocks:  # the element size too: a 3 KB file of 50,000 unwritten rows of S20000 is a gigabyte read
        base = table.dtype[b].base
        if base.kind not in "fiub" or base.itemsize > 8:
            raise InputError(f"H5 table's {b} holds {base} values, not numbers", path)
    data = table.fields(blocks)[()] if len(blocks) > 1 else {blocks[0]: table.fields(blocks[0])[()]}
    columns: list[tuple] = []
    parts = []
    for b in blocks:
        raw = table.attrs.get(f"{b}_kind")
        if raw is None:
            raise InputError(f"H5 table has no column labels for {b}", path)
        labels = _literal_unpickle(_attr_bytes(raw), path, f"{b}_kind")
        if not isinstance(labels, list) or not all(
                isinstance(t, tuple) and all(isinstance(x, (str, bytes, int, float)) for x in t) for t in labels):
            raise InputError(f"H5 column labels of {b} are not a MultiIndex", path)
        block = np.asarray(data[b], dtype=np.float64)
        block = block.reshape(block.shape[0], -1)
        if block.shape[1] != len(labels):
            raise InputError(f"H5 {b} has {block.shape[1]} columns but {len(labels)} labels", path)
        columns += [tuple(str(x) for x in t) for t in labels]
        parts.append(block)
    return columns, np.concatenate(parts, axis=1)


def _h5_fixed(group, path: Path, limits: ReadLimits) -> tuple[list[tuple], np.ndarray]:
    """Default "fixed" format: plain arrays for the column MultiIndex of the frame and each block."""
    axis0 = _fixed_index(group, "axis0", path, limits)
    nblocks = int(group.attrs.get("nblocks", 0))
    if nblocks < 1:
        raise InputError("H5 DataFrame has no data blocks", path)
    position = {label: j for j, label in enumerate(axis0)}
    values = None
    for k in range(nblocks):
        if f"block{k}_values" not in group:
            raise InputError(f"H5 DataFrame has no block{k}_values", path)
        dataset = group[f"block{k}_values"]
        if not hasattr(dataset, "shape") or dataset.ndim != 2:
            raise InputError(f"H5 block{k}_values is not a table of numbers", path)
        limits.check_frames(dataset.shape[0], path)
        limits.check_columns(dataset.shape[1], path)
        if dataset.dtype.kind not in "fiub":
            raise InputError(f"H5 block{k}_values are not numbers", path)
        items = _fixed_index(group, f"block{k}_items", path, limits)
        block = dataset[()]
        block = np.asarray(block, dtype=np.float64).reshape(block.shape[0], -1)
        if values is None:
            values = np.full((block.shape[0], len(axis0)), np.nan)
        if block.shape != (values.shape[0], len(items)):
            raise InputError(f"H5 block{k}_values has shape {block.shape}, expected "
                             f"({values.shape[0]}, {len(items)})", path)
        for j, label in enumerate(items):
            if label not in position:
                raise InputError(f"H5 block{k} column {label} is not among the frame's columns", path)
            values[:, position[label]] = block[:, j]
    assert values is not None  # nblocks >= 1
    return axis0, values


def _fixed_index(group, prefix: str, path: Path, limits: ReadLimits) -> list[tuple]:
    """A pandas MultiIndex stored as ``<prefix>_level<i>`` (labels) + ``<prefix>_label<i>`` (codes)."""
    nlevels = int(group.attrs.get(f"{prefix}_nlevels", 0))
    if _text(group.attrs.get(f"{prefix}_variety", b"")) != "multi" or nlevels not in (3, 4):
        raise InputError("H5 columns are not a DeepLabCut MultiIndex (scorer, bodyparts, coords)", path)
    level_values = []
    for i in range(nlevels):
        try:
            level_set, code_set = group[f"{prefix}_level{i}"], group[f"{prefix}_label{i}"]
        except KeyError:
            raise InputError(f"H5 file lacks {prefix}_level{i}/{prefix}_label{i}", path) from None
        for d in (level_set, code_set):
            if not hasattr(d, "shape") or d.ndim != 1:
                raise InputError(f"H5 {d.name} is not a list of column labels", path)
            limits.check_columns(d.shape[0], path)
        if code_set.dtype.kind not in "iu" or code_set.dtype.itemsize > 8:
            raise InputError(f"H5 {code_set.name} codes are {code_set.dtype}, not integers", path)
        levels = _labels(level_set, path)
        codes = np.asarray(code_set[()], dtype=np.int64)
        if codes.size and (codes.min() < -1 or codes.max() >= len(levels)):
            raise InputError(f"H5 {prefix}_label{i} codes out of range", path)
        level_values.append(["" if c < 0 else levels[c] for c in codes])
    n = len(level_values[0])
    if any(len(v) != n for v in level_values):
        raise InputError(f"H5 {prefix} levels differ in length", path)
    return [tuple(v[j] for v in level_values) for j in range(n)]


def _labels(dataset, path: Path) -> list[str]:
    """A level's labels, each at most :data:`MAX_LABEL_BYTES`, checked before they are read: from the
    element size of fixed-length strings, one at a time for variable-length ones."""
    kind, size = dataset.dtype.kind, dataset.dtype.itemsize
    if kind in "SU" and size > MAX_LABEL_BYTES * (4 if kind == "U" else 1):
        raise InputError(f"H5 {dataset.name} labels are {size} bytes each; at most {MAX_LABEL_BYTES}", path)
    if kind == "O":
        out = []
        for i in range(dataset.shape[0]):
            text = _text(dataset[i])
            if len(text) > MAX_LABEL_BYTES:
                raise InputError(f"H5 {dataset.name} label {i} is {len(text)} characters; at most {MAX_LABEL_BYTES}",
                                 path)
            out.append(text)
        return out
    if kind not in "SUiuf" or size > MAX_LABEL_BYTES * 4:
        raise InputError(f"H5 {dataset.name} labels are {dataset.dtype}, not names", path)
    return [_text(x) for x in dataset[()]]


def _attr_bytes(value) -> bytes:
    if isinstance(value, (bytes, np.bytes_)):
        return bytes(value)
    if isinstance(value, np.void):
        return value.tobytes()
    if isinstance(value, np.ndarray):
        return value.tobytes()
    if isinstance(value, str):
        return value.encode("latin-1")
    return bytes(value)


def _text(value) -> str:
    if isinstance(value, (bytes, np.bytes_)):
        return bytes(value).decode("utf-8", errors="replace")
    return str(value)


# Opcodes that only build literals. Everything else (GLOBAL, STACK_GLOBAL, REDUCE, BUILD, INST,
# OBJ, NEWOBJ, EXT*, PERSID, ...) imports or calls something and is refused.
_PUSH_ARG = {"UNICODE", "BINUNICODE", "SHORT_BINUNICODE", "BINUNICODE8", "STRING", "BINSTRING",
             "SHORT_BINSTRING", "BINBYTES", "SHORT_BINBYTES", "BINBYTES8", "INT", "BININT", "BININT1",
             "BININT2", "LONG", "LONG1", "LONG4", "FLOAT", "BINFLOAT"}


class _RefusedPickle(Exception):
    pass


def _literal_unpickle(data: bytes, path: Path, what: str):
    """Rebuild a pickle made only of literals (str, bytes, numbers, bool, None, list, tuple, dict).

    Walks ``pickletools.genops(data)``, which decodes opcodes without running any, and emulates
    the unpickler's stack for the literal opcodes. Nothing is imported or called: a pickle that
    needs a class or function raises :class:`InputError`.
    """
    stack: list = []
    marks: list[int] = []
    memo: dict = {}

    def pop_mark() -> list:
        k = marks.pop()
        items = stack[k:]
        del stack[k:]
        return items

    try:
        for op, arg, _pos in pickletools.genops(data):
            name = op.name
            if name in ("PROTO", "FRAME"):
                continue
            if name == "STOP":
                break
            if name in _PUSH_ARG:
                stack.append(arg)
            elif name == "NONE":
                stack.append(None)
            elif name in ("NEWTRUE", "NEWFALSE"):
                stack.append(name == "NEWTRUE")
            elif name == "MARK":
                marks.append(len(stack))
            elif name == "EMPTY_LIST":
                stack.append([])
            elif name == "LIST":
                stack.append(pop_mark())
            elif name == "EMPTY_TUPLE":
                stack.append(())
            elif name == "TUPLE":
                stack.append(tuple(pop_mark()))
            elif name in ("TUPLE1", "TUPLE2", "TUPLE3"):
                n = int(name[-1])
                top = tuple(stack[-n:])
                del stack[-n:]
                stack.append(top)
            elif name == "EMPTY_DICT":
                stack.append({})
            elif name == "DICT":
                items = pop_mark()
                stack.append(dict(zip(items[::2], items[1::2])))
            elif name == "APPEND":
                value = stack.pop()
                stack[-1].append(value)
            elif name == "APPENDS":
                items = pop_mark()
                stack[-1].extend(items)
            elif name == "SETITEM":
                value = stack.pop()
                key = stack.pop()
                stack[-1][key] = value
            elif name == "SETITEMS":
                items = pop_mark()
                stack[-1].update(zip(items[::2], items[1::2]))
            elif name in ("PUT", "BINPUT", "LONG_BINPUT"):
                memo[arg] = stack[-1]
            elif name == "MEMOIZE":
                memo[len(memo)] = stack[-1]
            elif name in ("GET", "BINGET", "LONG_BINGET"):
                stack.append(memo[arg])
            elif name == "POP":
                stack.pop()
            elif name == "POP_MARK":
                pop_mark()
            elif name == "DUP":
                stack.append(stack[-1])
            else:
                raise _RefusedPickle(name)
    except _RefusedPickle as e:
        raise InputError(f"H5 attribute {what} is a pickle that would run code ({e}); refusing to read it",
                         path) from None
    except Exception as e:  # malformed pickle bytes: genops raises ValueError and friends
        raise InputError(f"H5 attribute {what} is not a readable pickle ({type(e).__name__})", path) from None
    if len(stack) != 1:
        raise InputError(f"H5 attribute {what} is not a readable pickle", path)
    return stack[0]


# ------------------------------------------------------------------------- columns to Keypoints


def _from_columns(columns: list[tuple], values: np.ndarray, path: Path,
                  individual: str | None) -> Keypoints | Tracks:
    """Turn DeepLabCut columns ``(scorer, [individual,] bodypart, coord)`` and values (N, C)
    into :class:`Keypoints` for one individual, or (``individual`` :data:`EVERY`) :class:`Tracks`
    of every individual but ``single``."""
    if not columns:
        raise InputError("no data columns", path)
    nlev = len(columns[0])
    if nlev not in (3, 4) or any(len(c) != nlev for c in columns):
        raise InputError("columns are not DeepLabCut's (scorer, bodyparts, coords) "
                         "or (scorer, individuals, bodyparts, coords)", path)
    scorers = list(dict.fromkeys(c[0] for c in columns))
    if len(scorers) > 1:
        raise InputError("several scorers in one file (" + ", ".join(scorers[:4]) + ")", path)
    if nlev == 3:
        one = _individual(columns, values, path, scorers[0])
        return as_tracks(one) if individual == EVERY else one
    names = list(dict.fromkeys(c[1] for c in columns))
    animals = [n for n in names if n != SINGLE] or names

    def pick(name: str) -> Keypoints:
        keep = [j for j, c in enumerate(columns) if c[1] == name]
        return _individual([(c[0], c[2], c[3]) for c in (columns[j] for j in keep)], values[:, keep], path, scorers[0])

    if individual == EVERY:
        if len(animals) > MAX_SLOTS:
            raise InputError(f"{len(animals)} individuals; at most {MAX_SLOTS} are solved at once", path)
        each = [pick(a) for a in animals]
        if any(k.bodyparts != each[0].bodyparts for k in each):
            raise InputError(f"the individuals have different bodyparts ({', '.join(animals[:4])})", path)
        return Tracks(bodyparts=each[0].bodyparts, names=animals, xy=np.stack([k.xy for k in each], axis=1),
                      likelihood=np.stack([k.likelihood for k in each], axis=1), scorer=scorers[0], source=str(path))
    if individual is None:
        chosen = animals[0]
        if len(animals) > 1:
            warnings.warn(f"{path.name}: {len(animals)} individuals ({', '.join(animals)}); "
                          f"using '{chosen}' (choose another with --individual)", stacklevel=4)
    elif individual in names:
        chosen = individual
    else:
        raise InputError(f"no individual '{individual}' (the file has {', '.join(names)})", path)
    return pick(chosen)


def _individual(columns: list[tuple], values: np.ndarray, path: Path, scorer: str) -> Keypoints:
    """One individual's columns ``(scorer, bodypart, coord)`` and values as :class:`Keypoints`."""
    bodyparts = list(dict.fromkeys(c[1] for c in columns))
    where: dict[tuple[str, str], int] = {}
    for j, (_, bp, coord) in enumerate(columns):
        if coord not in ("x", "y", "likelihood"):
            raise InputError(f"bodypart '{bp}': unknown coordinate '{coord}' (expected x, y, likelihood)", path)
        if (bp, coord) in where:
            raise InputError(f"bodypart '{bp}' has two '{coord}' columns", path)
        where[(bp, coord)] = j
    n = values.shape[0]
    xy = np.empty((n, len(bodyparts), 2))
    lik = np.empty((n, len(bodyparts)))
    for m, bp in enumerate(bodyparts):
        for a, coord in enumerate(("x", "y")):
            if (bp, coord) not in where:
                raise InputError(f"bodypart '{bp}' has no '{coord}' column", path)
            xy[:, m, a] = values[:, where[(bp, coord)]]
        lik[:, m] = values[:, where[(bp, "likelihood")]] if (bp, "likelihood") in where else 1.0
    if np.isinf(xy).any():
        raise InputError("infinite pixel coordinates", path)
    missing = ~np.isfinite(xy).all(axis=-1)
    xy[missing] = np.nan
    lik = np.clip(np.nan_to_num(lik, nan=0.0, posinf=1.0, neginf=0.0), 0.0, 1.0)
    lik[missing] = 0.0
    return Keypoints(bodyparts=bodyparts, xy=xy, likelihood=lik, scorer=scorer, source=str(path))


# ------------------------------------------------------------------------------------- writing


_FORMULA_START = ("=", "+", "-", "@", "\t", "\r")


def spreadsheet_safe(text: str) -> str:
    """A name as a CSV cell no spreadsheet runs as a formula: one that starts with ``= + - @``, a tab
    or a carriage return gets a leading ``'`` (a bodypart named ``=HYPERLINK(...)`` in an upload
    would otherwise run when the result CSV is opened in a spreadsheet)."""
    return "'" + text if text.startswith(_FORMULA_START) else text


def write_dlc_csv(path: str | Path, keypoints: Keypoints) -> None:
    """Write the single-animal DeepLabCut CSV layout, byte for byte what
    ``DataFrame.to_csv`` writes for DeepLabCut's (scorer, bodyparts, coords) columns: floats as
    ``repr``, empty cells for NaN, the frame number as the index."""
    n, m = keypoints.xy.shape[:2]
    with open(path, "w", newline="", encoding="utf-8") as f:
        w = csv.writer(f, lineterminator="\n")
        w.writerow(["scorer"] + [spreadsheet_safe(keypoints.scorer)] * (3 * m))
        w.writerow(["bodyparts"] + [spreadsheet_safe(bp) for bp in keypoints.bodyparts for _ in range(3)])
        w.writerow(["coords"] + ["x", "y", "likelihood"] * m)
        block = np.concatenate([keypoints.xy, keypoints.likelihood[..., None]], axis=-1).reshape(n, 3 * m)
        gaps = np.isnan(block).any(axis=1)
        for i, row in enumerate(block.tolist()):
            cells = [("" if v != v else repr(v)) for v in row] if gaps[i] else map(repr, row)
            f.write(f"{i},{','.join(cells)}\n")


# ------------------------------------------------------------------------- bodyparts to markers


class BodypartMatch(NamedTuple):
    """How one file's bodyparts map onto a skeleton's markers.

    ``index[k]`` is the bodypart column of marker ``k`` (-1: the file lacks it); ``unknown`` are
    bodyparts no marker uses (ignored), ``missing`` markers the file lacks (unobserved).
    """

    # the field's name shadows tuple.index, as NamedTuple allows: the public name, kept
    index: np.ndarray  # type: ignore[assignment]
    unknown: list[str]
    missing: list[str]


def _normal(name: str) -> str:
    return "_".join(name.strip().lower().replace("-", " ").split())


def match_bodyparts(keypoints: Keypoints, marker_names: list[str]) -> BodypartMatch:
    """Map bodyparts to markers by name: exact match first, then ignoring case, spaces and
    hyphens (``"Left Eye"`` = ``"left_eye"``). Pure: the caller decides what to warn about."""
    exact = {bp: j for j, bp in enumerate(keypoints.bodyparts)}
    loose: dict[str, int] = {}
    for j, bp in enumerate(keypoints.bodyparts):
        loose.setdefault(_normal(bp), j)
    index = np.full(len(marker_names), -1, dtype=np.int64)
    for k, name in enumerate(marker_names):
        index[k] = exact.get(name, loose.get(_normal(name), -1))
    used = set(index[index >= 0].tolist())
    unknown = [bp for j, bp in enumerate(keypoints.bodyparts) if j not in used]
    missing = [name for k, name in enumerate(marker_names) if index[k] < 0]
    return BodypartMatch(index=index, unknown=unknown, missing=missing)


def no_marker_matched(bodyparts: list[str], skeleton_name: str, markers: list[str]) -> InputError:
    """The refusal when no bodypart of the keypoint files is a marker of the skeleton, with the way out."""
    shown = lambda names: ", ".join(names[:6]) + (", ..." if len(names) > 6 else "")  # noqa: E731
    return InputError(f"no bodypart in the keypoint files ({shown(bodyparts)}) matches a marker of the "
                      f"{skeleton_name} skeleton ({shown(markers)}); for another animal use the points skeleton: "
                      '"skeleton": "points"')


def require_a_marker(keypoints: list[Keypoints], skeleton_name: str, markers: list[str]) -> None:
    """:func:`no_marker_matched` unless some file has a bodypart that is one of ``markers``."""
    if not any((match_bodyparts(kp, markers).index >= 0).any() for kp in keypoints):
        raise no_marker_matched(keypoints[0].bodyparts if keypoints else [], skeleton_name, markers)


def select_markers(keypoints: Keypoints, marker_names: list[str]) -> Keypoints:
    """The detections in marker order (N, len(marker_names)): missing markers NaN with likelihood 0."""
    match = match_bodyparts(keypoints, marker_names)
    n = keypoints.frames
    xy = np.full((n, len(marker_names), 2), np.nan)
    lik = np.zeros((n, len(marker_names)))
    have = match.index >= 0
    xy[:, have] = keypoints.xy[:, match.index[have]]
    lik[:, have] = keypoints.likelihood[:, match.index[have]]
    spread = None
    if keypoints.spread_px is not None:
        spread = np.full((n, len(marker_names)), np.nan)
        spread[:, have] = keypoints.spread_px[:, match.index[have]]
    return Keypoints(bodyparts=list(marker_names), xy=xy, likelihood=lik,
                     scorer=keypoints.scorer, source=keypoints.source, spread_px=spread, fps=keypoints.fps)


def check_same_frames(keypoints: list[Keypoints] | list[Tracks]) -> int:
    """The common frame count; :class:`InputError` naming the first file whose count differs."""
    if not keypoints:
        raise InputError("no keypoint files given")
    n = keypoints[0].frames
    for k in keypoints[1:]:
        if k.frames != n:
            first = Path(keypoints[0].source).name or "camera 1"
            raise InputError(f"has {k.frames} frames but {first} has {n}; all cameras must have "
                             "the same frames", k.source or None)
    return n
