"""2D keypoints from SLEAP's own files (``*.slp``, labels and predictions), read through sleap-io,
the field's library for them (the optional extra ``acinoset[sleap]``): one :class:`Keypoints` per file.

:func:`graph.io.keypoints.read_keypoints` hands an HDF5 file here when it holds a SLEAP labels file's
datasets (:func:`is_slp`); SLEAP's analysis export (``*.analysis.h5``) is :mod:`graph.io.sleap`'s.

What is read. A ``.slp`` holds, per labelled frame of each video, instances of a skeleton: predicted
ones (each point with a score) and user ones (placed or corrected by hand, no score). One file is one
camera, so it must hold one video. Per track (animal) and frame the user instance is preferred
over the prediction it was made from (sleap-io's ``Labels.numpy``), an untracked file (one animal,
no tracks) takes each frame's first instance. A point is missing where either coordinate is NaN
(likelihood 0); a score is clipped to [0, 1] and stands for DeepLabCut's likelihood; a hand-placed
point (no score) gets likelihood 1. The videos the file names are never opened.

Bounded before sleap-io reads anything: the file's frame, instance and point tables, checked with
h5py against :class:`~graph.io.keypoint_types.ReadLimits` (frames; bodyparts through the point
rows an instance may hold), and the largest frame index, so that neither the tables nor the dense
(frame, track, node) array built from them can exceed what the limits allow.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from graph.errors import InputError, TooLargeInput
from graph.io.keypoint_types import EVERY, MAX_SLOTS, Keypoints, ReadLimits, Tracks

TABLES = ("frames", "instances")
MAX_TRACKS = 1000  # animals in one file
MAX_INSTANCES_PER_FRAME = 1000
MAX_NODES = 10_000  # without a bodyparts limit
INSTALL = "reading SLEAP .slp files needs sleap-io: pip install 'acinoset[sleap]'"


def is_slp(f) -> bool:
    """Whether the open h5py file ``f`` is a SLEAP labels file: ``frames`` and ``instances`` tables and
    a ``metadata`` group."""
    import h5py

    return (all(f.get(k, getclass=True) is h5py.Dataset for k in TABLES)
            and f.get("metadata", getclass=True) is h5py.Group)


def check_slp(f, path: Path, limits: ReadLimits) -> None:
    """The sizes of the open labels file ``f`` against ``limits``, before sleap-io reads it: the rows of
    its tables and the largest frame index (the dense array has one row per frame up to it)."""
    frames, instances = f["frames"], f["instances"]
    for name in TABLES + ("points", "pred_points"):
        d = f.get(name)
        if d is not None and getattr(d, "ndim", 1) != 1:
            raise InputError(f"SLEAP's {name} table has shape {d.shape}, expected one axis", path)
    if frames.dtype.names is None or "frame_idx" not in frames.dtype.names:
        raise InputError("SLEAP's frames table has no frame_idx", path)
    max_frames = limits.max_frames
    if max_frames is not None:
        limits.check_frames(frames.shape[0], path)
        if instances.shape[0] > MAX_INSTANCES_PER_FRAME * max(max_frames, 1):
            raise InputError(f"{instances.shape[0]} instances; at most {MAX_INSTANCES_PER_FRAME} a frame", path)
    nodes = limits.max_bodyparts if limits.max_bodyparts is not None else MAX_NODES
    for name in ("points", "pred_points"):
        d = f.get(name)
        if d is not None and d.shape[0] > max(instances.shape[0], 1) * nodes:
            raise TooLargeInput(f"SLEAP's {name} table has {d.shape[0]} rows for {instances.shape[0]} instances "
                                f"(at most {nodes} bodyparts each)", path, "bodyparts")
    if frames.shape[0]:
        last = int(np.max(frames.fields("frame_idx")[()]))
        limits.check_frames(last + 1, path)


def read_slp(path: Path, individual: str | None, limits: ReadLimits) -> Keypoints | Tracks:
    """The chosen track of the SLEAP labels file at ``path`` (:func:`is_slp`) as :class:`Keypoints`.

    ``individual`` names a track; by default the first, with a warning naming the others;
    :data:`~graph.io.keypoint_types.EVERY`: every track (at most ``MAX_SLOTS``; an untracked file's
    instances, in each frame's order, not identified) as :class:`Tracks`."""
    try:
        import sleap_io
    except ImportError:
        raise InputError(INSTALL, path) from None
    try:
        labels = sleap_io.load_slp(str(path), open_videos=False)
    except Exception as e:  # noqa: BLE001  (an untrusted file: any failure of the parser is a refusal)
        raise InputError(f"not a SLEAP labels file sleap-io can read ({type(e).__name__}: {e})", path) from None
    if len(labels.videos) != 1:
        raise InputError(f"the SLEAP file holds {len(labels.videos)} videos; give one file per camera", path)
    if len(labels.skeletons) != 1:
        raise InputError(f"the SLEAP file holds {len(labels.skeletons)} skeletons, expected one", path)
    nodes = list(labels.skeletons[0].node_names)
    limits.check_columns(3 * len(nodes), path)
    if not nodes:
        raise InputError("the SLEAP skeleton has no nodes", path)
    if len(set(nodes)) != len(nodes):
        raise InputError("two nodes of the SLEAP skeleton have the same name", path)
    names = [t.name for t in labels.tracks]
    if len(names) > MAX_TRACKS:
        raise InputError(f"{len(names)} tracks; at most {MAX_TRACKS}", path)
    if not len(labels):
        raise InputError("the SLEAP file has no labelled frames", path)
    untracked = not names
    every = individual == EVERY
    if untracked and not every and any(len(lf.instances) > 1 for lf in labels):
        warnings.warn(f"{path.name}: several untracked instances in a frame; using each frame's first", stacklevel=6)
    if every and len(names) > MAX_SLOTS:
        raise InputError(f"{len(names)} tracks; at most {MAX_SLOTS} are solved at once", path)
    k = 0 if every else _choose(names, individual, path)
    try:
        arr = labels.numpy(video=0, untracked=untracked, return_confidence=True)  # (frame, track, node, 3)
    except Exception as e:  # noqa: BLE001
        raise InputError(f"SLEAP's points could not be arranged by frame ({type(e).__name__}: {e})", path) from None
    if arr.ndim != 4 or arr.shape[1] <= k or arr.shape[2] != len(nodes):
        raise InputError(f"SLEAP's points came out as {arr.shape}, not (frames, tracks, {len(nodes)}, 3)", path)
    limits.check_frames(arr.shape[0], path)
    if every and arr.shape[1] > MAX_SLOTS:
        raise InputError(f"{arr.shape[1]} instances in a frame; at most {MAX_SLOTS} are solved at once", path)
    part = arr if every else arr[:, k:k + 1]
    xy = np.asarray(part[..., :2], dtype=np.float64)
    score = np.asarray(part[..., 2], dtype=np.float64)
    if np.isinf(xy).any():
        raise InputError("infinite pixel coordinates", path)
    missing = ~np.isfinite(xy).all(axis=-1)
    xy[missing] = np.nan
    likelihood = np.clip(np.nan_to_num(score, nan=1.0, posinf=1.0, neginf=0.0), 0.0, 1.0)
    likelihood[missing] = 0.0
    if not every:
        return Keypoints(bodyparts=nodes, xy=xy[:, 0], likelihood=likelihood[:, 0], scorer="sleap", source=str(path))
    slots = names or [f"instance_{j}" for j in range(xy.shape[1])]
    return Tracks(bodyparts=nodes, names=slots, xy=xy, likelihood=likelihood, identified=not untracked or
                  xy.shape[1] == 1, scorer="sleap", source=str(path))


def _choose(names: list[str], individual: str | None, path: Path) -> int:
    """The track to read: the one named ``individual``, else the first (warning of the others)."""
    if individual is None:
        if len(names) > 1:
            shown = ", ".join(names[:8]) + (", ..." if len(names) > 8 else "")
            warnings.warn(f"{path.name}: {len(names)} tracks ({shown}); using '{names[0]}' (choose another with "
                          "--individual)", stacklevel=6)
        return 0
    if individual in names:
        return names.index(individual)
    shown = ", ".join(names[:8]) + (", ..." if len(names) > 8 else "") if names else "no tracks"
    raise InputError(f"no track '{individual}' (the file has {shown})", path)
