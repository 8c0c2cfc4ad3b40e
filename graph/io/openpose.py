"""2D keypoints from OpenPose's JSON output (``--write_json``, what Pose2Sim reads): a folder of one
JSON file a frame, one folder a camera, as one :class:`Keypoints`.

Layout. Each file ``<name>_<frame number>_keypoints.json`` holds ``{"people": [{"pose_keypoints_2d":
[x0, y0, c0, x1, y1, c1, ...]}, ...]}``: K keypoints a person, ``c`` OpenPose's confidence in [0, 1]
(0 and x = y = 0 where the keypoint was not found). The frame is the number in the name (the last
run of digits), counted from the folder's smallest; a number without a file is a frame without
detections.

Names. A file names no keypoints; the model does: ``model`` one of :data:`MODELS` (``BODY_25``,
OpenPose's default, ``BODY_25B``, ``COCO``), else ``kp0 .. kp<K-1>`` (BODY_25 and BODY_25B both
have 25, in different orders, so the count cannot tell them apart).

People. OpenPose gives no identities across frames. With one person a frame there is nothing to
choose; with several, each frame's most confident person (the largest sum of confidences) is taken,
with a warning that identities across frames are not tracked.

Bounded: at most ``limits.max_frames`` files and frame numbers spanning no more, each file at most
:data:`MAX_FILE_BYTES`, at most :data:`MAX_PEOPLE` people and ``limits.max_bodyparts`` keypoints.
"""

from __future__ import annotations

import json
import re
import warnings
from pathlib import Path

import numpy as np

from graph.errors import InputError, TooLargeInput
from graph.io.keypoint_types import MAX_SLOTS, Keypoints, ReadLimits, Tracks

MODELS: dict[str, tuple[str, ...]] = {
    "BODY_25": ("Nose", "Neck", "RShoulder", "RElbow", "RWrist", "LShoulder", "LElbow", "LWrist", "MidHip", "RHip",
                "RKnee", "RAnkle", "LHip", "LKnee", "LAnkle", "REye", "LEye", "REar", "LEar", "LBigToe", "LSmallToe",
                "LHeel", "RBigToe", "RSmallToe", "RHeel"),
    "BODY_25B": ("Nose", "LEye", "REye", "LEar", "REar", "LShoulder", "RShoulder", "LElbow", "RElbow", "LWrist",
                 "RWrist", "LHip", "RHip", "LKnee", "RKnee", "LAnkle", "RAnkle", "UpperNeck", "HeadTop", "LBigToe",
                 "LSmallToe", "LHeel", "RBigToe", "RSmallToe", "RHeel"),
    "COCO": ("Nose", "Neck", "RShoulder", "RElbow", "RWrist", "LShoulder", "LElbow", "LWrist", "RHip", "RKnee",
             "RAnkle", "LHip", "LKnee", "LAnkle", "REye", "LEye", "REar", "LEar"),
}
MAX_FILE_BYTES = 10 << 20
MAX_PEOPLE = 1000
MAX_KEYPOINTS = 10_000  # without a bodyparts limit
_NUMBER = re.compile(r"(\d+)(?!.*\d)")


def is_openpose_folder(path: Path) -> bool:
    """Whether ``path`` is a folder holding OpenPose JSON files (``*.json``)."""
    return path.is_dir() and any(p.suffix == ".json" for p in path.iterdir())


def read_openpose(folder: str | Path, limits: ReadLimits, model: str | None = None) -> Keypoints:
    """One camera's OpenPose JSON folder as :class:`Keypoints`: each frame's most confident person
    (see the module docstring)."""
    folder, names, frames, first, people = _read_folder(folder, limits, model)
    K = len(names)
    xy = np.full((frames, K, 2), np.nan)
    likelihood = np.zeros((frames, K))
    crowded = 0
    for t, arr in people:
        if not arr:
            continue
        best = max(range(len(arr)), key=lambda i: float(np.nansum(arr[i][:, 2])))
        crowded += len(arr) > 1
        _put(arr[best], xy[t], likelihood[t])
    if crowded:
        warnings.warn(f"{folder.name}: {crowded} of {frames} frames hold several people; each frame's most confident "
                      "is taken, and identities across frames are not tracked", stacklevel=4)
    return Keypoints(bodyparts=names, xy=xy, likelihood=likelihood, scorer="openpose", source=str(folder))


def read_openpose_people(folder: str | Path, limits: ReadLimits, model: str | None = None) -> Tracks:
    """One camera's OpenPose JSON folder as :class:`Tracks`: every person of each frame, in the file's
    order, in as many slots as the most crowded frame has people (``identified`` False: OpenPose
    gives no identities across frames)."""
    folder, names, frames, first, people = _read_folder(folder, limits, model)
    slots = max(len(arr) for _, arr in people)
    if slots > MAX_SLOTS:
        raise InputError(f"{slots} people in a frame; at most {MAX_SLOTS} are solved at once", folder)
    K = len(names)
    xy = np.full((frames, slots, K, 2), np.nan)
    likelihood = np.zeros((frames, slots, K))
    for t, arr in people:
        for j, a in enumerate(arr):
            _put(a, xy[t, j], likelihood[t, j])
    return Tracks(bodyparts=names, names=[f"person{j + 1}" for j in range(slots)], xy=xy, likelihood=likelihood,
                  identified=False, scorer="openpose", source=str(folder))


def _put(a: np.ndarray, xy: np.ndarray, likelihood: np.ndarray) -> None:
    """One person's (K, 3) rows into ``xy`` (K, 2) and ``likelihood`` (K,): found keypoints only."""
    found = a[:, 2] > 0
    xy[found] = a[found, :2]
    likelihood[found] = np.clip(a[found, 2], 0.0, 1.0)


def _read_folder(given: str | Path, limits: ReadLimits,
                 model: str | None) -> tuple[Path, list[str], int, int, list[tuple[int, list[np.ndarray]]]]:
    """The folder, its keypoint names, frame count, first frame number and ``(frame, [person (K, 3)])``."""
    folder = Path(given)
    if model is not None and model not in MODELS:
        raise InputError(f"unknown OpenPose model {model!r} (known: {', '.join(MODELS)})", folder)
    cap = limits.max_frames
    files: list[tuple[int, Path]] = []
    for p in folder.iterdir():
        if p.suffix != ".json":
            continue
        if cap is not None and len(files) >= cap:
            limits.check_frames(len(files) + 1, folder, counting=True)
        m = _NUMBER.search(p.stem)
        if m is None:
            raise InputError(f"{p.name}: no frame number in the file name", folder)
        files.append((int(m.group(1)), p))
    if not files:
        raise InputError("no OpenPose JSON files (*.json) in the folder", folder)
    files.sort()
    first = files[0][0]
    frames = files[-1][0] - first + 1
    limits.check_frames(frames, folder)
    if len({n for n, _ in files}) != len(files):
        raise InputError("two files have the same frame number", folder)
    raw = [(n - first, _people(p)) for n, p in files]
    counts = {len(person) // 3 for _, ps in raw for person in ps}
    if not counts:
        raise InputError("no person is detected in any frame", folder)
    if len(counts) > 1:
        raise InputError(f"people with different numbers of keypoints ({', '.join(map(str, sorted(counts)))})",
                         folder)
    (K,) = counts
    limits.check_columns(3 * K, folder)
    if K > MAX_KEYPOINTS:
        raise TooLargeInput(f"{K} keypoints a person; at most {MAX_KEYPOINTS}", folder, "bodyparts")
    names = list(MODELS[model]) if model else [f"kp{i}" for i in range(K)]
    if len(names) != K:
        raise InputError(f"{K} keypoints a person, but OpenPose's {model} has {len(names)}", folder)
    people = []
    for t, ps in raw:
        arr = [np.asarray(p, dtype=np.float64).reshape(K, 3) for p in ps]
        if any(not np.isfinite(a).all() for a in arr):
            raise InputError(f"frame {t + first}: a keypoint is not a finite number", folder)
        people.append((t, arr))
    return folder, names, frames, first, people


def _people(path: Path) -> list[list[float]]:
    """The ``pose_keypoints_2d`` list of every person in one frame's file."""
    try:
        size = path.stat().st_size
        if size > MAX_FILE_BYTES:
            raise TooLargeInput(f"{path.name} is {size} bytes; at most {MAX_FILE_BYTES} a frame", path.parent, "bytes")
        doc = json.loads(path.read_bytes())
    except (OSError, ValueError, RecursionError) as e:
        raise InputError(f"{path.name}: not an OpenPose JSON file ({type(e).__name__})", path.parent) from None
    people = doc.get("people") if isinstance(doc, dict) else None
    if not isinstance(people, list):
        raise InputError(f"{path.name}: no 'people' list", path.parent)
    if len(people) > MAX_PEOPLE:
        raise InputError(f"{path.name}: {len(people)} people; at most {MAX_PEOPLE}", path.parent)
    out = []
    for person in people:
        values = person.get("pose_keypoints_2d") if isinstance(person, dict) else None
        if (not isinstance(values, list) or len(values) % 3
                or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in values)):
            raise InputError(f"{path.name}: a person's pose_keypoints_2d is not a list of x, y, confidence numbers",
                             path.parent)
        if values:
            out.append(values)
    return out
