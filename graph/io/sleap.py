"""2D keypoints from SLEAP's analysis HDF5 export (``*.analysis.h5``): one :class:`Keypoints` per file.

:func:`graph.io.keypoints.read_keypoints` hands an HDF5 file here when it holds SLEAP's datasets
(:func:`is_analysis`); everything is read with h5py, nothing unpickled.

Layout. Dense arrays over ``T`` tracks (individuals), ``M`` nodes (bodyparts) and ``N`` frames:

* ``tracks`` (float): the points; ``point_scores`` (float): each point's score;
* ``node_names`` (M,), ``track_names`` (T,) byte strings (``track_names`` empty: one untracked animal);
* ``instance_scores``, ``tracking_scores``, ``track_occupancy``, ``edge_names``, ``video_path``, ...:
  not needed here.

The axes' order: ``tracks.attrs["dims"]`` names them (a JSON list, written by sleap-io); without it
the file attribute ``transpose`` tells (SLEAP's default, true or absent: ``tracks`` is
(track, xy, node, frame), as MATLAB reads it; false: (frame, node, xy, track)). ``point_scores``
has the same axes less ``xy``, in the same order (or its own ``dims``).

Values. A point is missing where either coordinate is NaN (likelihood 0). SLEAP's scores are a
network's confidence map peaks, not probabilities (above 1 at times): clipped to [0, 1] they stand
for DeepLabCut's likelihood. A point present with a NaN score was placed by hand (a user
instance has no score) and gets likelihood 1.

Bounded memory: the shapes, element sizes and :class:`~graph.io.keypoints.ReadLimits` are checked
before anything is read, and only the chosen track's slice of ``tracks`` and ``point_scores`` is.

Frame rate: SLEAP's export records none; a file whose attributes (``fps``, or ``fps`` in the
``video_backend_metadata`` JSON) give a positive one has it in :attr:`Keypoints.fps`.
"""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np

from graph.errors import InputError
from graph.io.keypoint_types import EVERY, MAX_SLOTS, Keypoints, ReadLimits, Tracks

AXES = ("track", "xy", "node", "frame")
MATLAB_ORDER = ("track", "xy", "node", "frame")  # SLEAP's default export (transposed for MATLAB)
PLAIN_ORDER = ("frame", "node", "xy", "track")  # SLEAP's export with transpose=False
MAX_NAME_BYTES = 4096  # a node's or track's name
MAX_TRACKS = 100_000
MAX_ATTRIBUTE_BYTES = 1 << 20


def is_analysis(f) -> bool:
    """Whether the open h5py file ``f`` is a SLEAP analysis file: ``tracks`` and ``node_names`` datasets."""
    import h5py

    return all(f.get(k, getclass=True) is h5py.Dataset for k in ("tracks", "node_names"))


def read_analysis(f, path: Path, individual: str | None, limits: ReadLimits) -> Keypoints | Tracks:
    """The chosen track of the open SLEAP analysis file ``f`` (:func:`is_analysis`) as :class:`Keypoints`.

    ``individual`` names a track; by default the first, with a warning naming the others;
    :data:`~graph.io.keypoint_types.EVERY`: all of them (at most ``MAX_SLOTS``) as :class:`Tracks`."""
    tracks = f["tracks"]
    order = _axes(f, tracks, path)
    if tracks.ndim != 4 or tracks.dtype.kind not in "fiu":
        raise InputError(f"SLEAP tracks have shape {tracks.shape} of {tracks.dtype}, expected 4 axes of numbers "
                         f"({', '.join(order)})", path)
    size = dict(zip(order, tracks.shape))
    if size["xy"] != 2:
        raise InputError(f"SLEAP tracks have {size['xy']} coordinates per point, expected 2 (x, y)", path)
    limits.check_frames(size["frame"], path)
    limits.check_columns(3 * size["node"], path)
    if size["frame"] == 0 or size["node"] == 0:
        raise InputError(f"no points: SLEAP tracks have shape {tracks.shape}", path)
    if size["track"] == 0:
        raise InputError("no tracks: the SLEAP file holds no animal", path)
    if size["track"] > MAX_TRACKS:
        raise InputError(f"{size['track']} tracks; at most {MAX_TRACKS}", path)
    nodes = _names(f["node_names"], path, "node_names")
    if len(nodes) != size["node"]:
        raise InputError(f"{len(nodes)} node_names for {size['node']} nodes in tracks", path)
    if len(set(nodes)) != len(nodes):
        raise InputError("two nodes have the same name in node_names", path)
    names = _names(f["track_names"], path, "track_names") if "track_names" in f else []
    if names and len(names) != size["track"]:
        raise InputError(f"{len(names)} track_names for {size['track']} tracks", path)
    if individual == EVERY:
        if size["track"] > MAX_SLOTS:
            raise InputError(f"{size['track']} tracks; at most {MAX_SLOTS} are solved at once", path)
        chosen = list(range(size["track"]))
    else:
        chosen = [_choose(names, size["track"], individual, path)]
    points = [_points(f, tracks, order, size, k, path) for k in chosen]
    if individual != EVERY:
        xy, likelihood = points[0]
        return Keypoints(bodyparts=nodes, xy=xy, likelihood=likelihood, scorer="sleap", source=str(path),
                         fps=_frame_rate(f))
    return Tracks(bodyparts=nodes, names=names or [f"track_{k}" for k in chosen],
                  xy=np.stack([p[0] for p in points], axis=1), likelihood=np.stack([p[1] for p in points], axis=1),
                  scorer="sleap", source=str(path), fps=_frame_rate(f))


def _points(f, tracks, order: tuple[str, ...], size: dict, k: int, path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Track ``k``'s pixels (frame, node, 2) and likelihoods (frame, node), missing points NaN with 0."""
    xy = _slice(tracks, order, k)  # (frame, node, xy)
    likelihood = _scores(f, order, size, k, path)
    if np.isinf(xy).any():
        raise InputError("infinite pixel coordinates", path)
    missing = ~np.isfinite(xy).all(axis=-1)
    xy[missing] = np.nan
    likelihood = np.clip(np.nan_to_num(likelihood, nan=1.0, posinf=1.0, neginf=0.0), 0.0, 1.0)
    likelihood[missing] = 0.0
    return xy, likelihood


def _axes(f, tracks, path: Path) -> tuple[str, ...]:
    """The order of the axes of ``tracks``: its ``dims`` attribute, else the file's ``transpose``."""
    dims = tracks.attrs.get("dims")
    if dims is not None:
        try:
            order = tuple(json.loads(_text(dims)))
        except (ValueError, TypeError):
            order = ()
        if sorted(order) != sorted(AXES):
            raise InputError(f"SLEAP tracks' dims attribute is not an order of {', '.join(AXES)}", path)
        return order
    transpose = f.attrs.get("transpose", True)
    return MATLAB_ORDER if bool(np.asarray(transpose).ravel()[0] if np.size(transpose) else True) else PLAIN_ORDER


def _slice(dataset, order: tuple[str, ...], k: int) -> np.ndarray:
    """Track ``k`` of a dataset whose axes are ``order`` (with or without ``xy``), read alone:
    (frame, node[, xy]) float64."""
    index = tuple(k if a == "track" else slice(None) for a in order)
    kept = [a for a in order if a != "track"]
    want = [a for a in ("frame", "node", "xy") if a in kept]
    return np.asarray(dataset[index], dtype=np.float64).transpose([kept.index(a) for a in want]).copy()


def _scores(f, order: tuple[str, ...], size: dict, k: int, path: Path) -> np.ndarray:
    """``point_scores`` of track ``k`` (frame, node); 1 where the file has none."""
    if "point_scores" not in f:
        return np.ones((size["frame"], size["node"]))
    scores = f["point_scores"]
    dims = scores.attrs.get("dims")
    try:
        own = tuple(json.loads(_text(dims))) if dims is not None else tuple(a for a in order if a != "xy")
    except (ValueError, TypeError):
        own = ()
    if sorted(own) != ["frame", "node", "track"]:
        raise InputError("SLEAP point_scores' dims attribute is not an order of frame, node, track", path)
    expected = tuple(size[a] for a in own)
    if scores.shape != expected or scores.dtype.kind not in "fiu":
        raise InputError(f"SLEAP point_scores have shape {scores.shape} of {scores.dtype}, expected {expected} "
                         f"numbers ({', '.join(own)})", path)
    return _slice(scores, own, k)


def _names(dataset, path: Path, what: str) -> list[str]:
    """A 1-D dataset of names (byte or text strings), its sizes checked before it is read."""
    import h5py

    if not isinstance(dataset, h5py.Dataset) or dataset.ndim != 1:
        raise InputError(f"SLEAP {what} is not a list of names", path)
    if dataset.shape[0] > MAX_TRACKS:
        raise InputError(f"SLEAP {what} has {dataset.shape[0]} names; at most {MAX_TRACKS}", path)
    kind = dataset.dtype.kind
    if kind in "SU" and dataset.dtype.itemsize > MAX_NAME_BYTES * (4 if kind == "U" else 1):
        raise InputError(f"SLEAP {what} are {dataset.dtype.itemsize} bytes each; at most {MAX_NAME_BYTES}", path)
    if kind not in "SUO":
        raise InputError(f"SLEAP {what} are {dataset.dtype}, not names", path)
    out = [_text(v) for v in dataset[()]]
    if any(len(v) > MAX_NAME_BYTES for v in out):
        raise InputError(f"a name in SLEAP {what} is longer than {MAX_NAME_BYTES} characters", path)
    return out


def _choose(names: list[str], count: int, individual: str | None, path: Path) -> int:
    """The index of the track to read: the one named ``individual``, else the first (with a warning
    naming the others when there are several)."""
    if individual is None:
        if count > 1:
            shown = ", ".join(names[:8]) + (", ..." if len(names) > 8 else "") if names else "unnamed"
            first = f"'{names[0]}'" if names else "the first"
            warnings.warn(f"{path.name}: {count} tracks ({shown}); using {first} (choose another with --individual)",
                          stacklevel=6)
        return 0
    if individual in names:
        return names.index(individual)
    shown = ", ".join(names[:8]) + (", ..." if len(names) > 8 else "") if names else "none is named"
    raise InputError(f"no track '{individual}' (the file has {shown})", path)


def _frame_rate(f) -> float | None:
    """A positive frame rate the file records (attribute ``fps``, or ``fps`` of the JSON attribute
    ``video_backend_metadata``), else None."""
    candidates = [f.attrs.get("fps")]
    meta = f.attrs.get("video_backend_metadata")
    if meta is not None and np.size(meta) == 1 and len(_text(meta)) <= MAX_ATTRIBUTE_BYTES:
        try:
            parsed = json.loads(_text(meta))
        except (ValueError, TypeError, RecursionError):
            parsed = None
        if isinstance(parsed, dict):
            candidates.append(parsed.get("fps"))
    for value in candidates:
        try:
            fps = float(np.asarray(value).ravel()[0]) if value is not None and np.size(value) == 1 else None
        except (TypeError, ValueError):
            fps = None
        if fps is not None and np.isfinite(fps) and fps > 0:
            return fps
    return None


def _text(value) -> str:
    if isinstance(value, np.ndarray) and value.size == 1:
        value = value.ravel()[0]
    if isinstance(value, (bytes, np.bytes_)):
        return bytes(value).decode("utf-8", errors="replace")
    return str(value)
