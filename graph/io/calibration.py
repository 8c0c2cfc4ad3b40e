"""Camera calibration files: read and write AcinoSet scene JSON and Anipose ``calibration.toml``.

Both describe the same thing, a rig of cameras in one world frame with ``X_c = R X_w + t``:

* AcinoSet scene JSON (``scene_sba.json``), OpenCV fisheye cameras only::

      {"camera_resolution": [W, H],
       "cameras": [{"k": 3x3, "d": 4x1, "r": 3x3, "t": 3x1}, ...]}

* Anipose / aniposelib ``calibration.toml`` (``CameraGroup.dump``): one table per camera,
  ``[cam_0]``, ``[cam_1]``, ... with ``name``, ``size = [W, H]``, ``matrix`` (3x3), ``distortions``
  (4 fisheye coefficients, or 1..5 pinhole ones k1, k2, p1, p2, k3), ``rotation`` (a Rodrigues
  vector ``r``: ``R = exp([r]_x)``, rotation by ``|r|`` about ``r/|r|``), ``translation`` (3) and
  the keys that mark the camera's model (``fisheye = true`` for fisheye cameras, none for pinhole
  ones: :attr:`graph.camera.CameraModel.anipose_keys`); plus a ``[metadata]`` table. Cameras are taken in the
  numeric order of their ``cam_N`` keys (aniposelib itself sorts the keys as text, which puts
  ``cam_10`` before ``cam_2``; with fewer than 11 cameras both orders agree).

Units are those of the file (AcinoSet: metres). Everything read is validated: a bad file raises
:class:`graph.errors.InputError` with one line naming the file.
"""

from __future__ import annotations

import json
import math
import re
import tomllib
from dataclasses import replace
from importlib import resources
from pathlib import Path

import numpy as np

from graph.camera import CALIBRATION_UNITS, CAMERA_MODELS, FISHEYE, Calibration, Camera, CameraModel, camera_model
from graph.errors import NESTED_TOO_DEEPLY, InputError
from graph.io.cameras import float_array, image_size, intrinsic_matrix, rotation_matrix, vector3

_CAM_KEY = re.compile(r"^cam_(\d+)$")

SCENE_JSON_MODEL = FISHEYE  # the one camera model AcinoSet's scene JSON holds (it has no key naming one)


def default_rig_path() -> Path:
    """The packaged real AcinoSet 2019 rig: six 2704x1520 GoPro cameras, fisheye, metres."""
    return Path(str(resources.files("graph.data").joinpath("acinoset_2019_rig.json")))


# --------------------------------------------------------------------------------------- reading


def load_calibration(path: str | Path) -> Calibration:
    """Read an AcinoSet scene JSON or an Anipose ``calibration.toml``, chosen by content.

    Text that parses as JSON is AcinoSet JSON; anything else is tried as Anipose TOML.
    """
    path = Path(path)
    text = _read_text(path)
    if not text.strip():
        raise InputError("calibration file is empty", path)
    start = text.lstrip()[:1]
    if start in ("{", "["):  # JSON, or a TOML file that starts with a [table]
        parsed, is_json = None, False
        try:
            parsed, is_json = json.loads(text), True
        except json.JSONDecodeError as e:
            if start == "{":
                raise InputError(f"not valid JSON (line {e.lineno}: {e.msg})", path) from None
        except RecursionError:
            raise InputError(NESTED_TOO_DEEPLY, path) from None
        except ValueError:  # Python's limit on an integer's digits (4300)
            raise InputError("not a calibration file: a number with thousands of digits", path) from None
        if is_json:
            try:
                return _from_acinoset(parsed, path)
            except RecursionError:
                raise InputError(NESTED_TOO_DEEPLY, path) from None
    try:
        doc = tomllib.loads(text)
    except RecursionError:
        raise InputError(NESTED_TOO_DEEPLY, path) from None
    except tomllib.TOMLDecodeError as e:
        kind = "JSON or TOML" if path.suffix.lower() not in (".toml", ".json") else path.suffix[1:].upper()
        raise InputError(f"not a calibration file: not valid {kind} ({e})", path) from None
    except ValueError:  # Python's limit on an integer's digits (4300)
        raise InputError("not a calibration file: a number with thousands of digits", path) from None
    return _from_anipose(doc, path)


def _read_text(path: Path) -> str:
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise InputError("no such file", path) from None
    except IsADirectoryError:
        raise InputError("is a directory, not a calibration file", path) from None
    except OSError as e:
        raise InputError(f"cannot read: {e.strerror}", path) from None
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError:
        raise InputError("not a calibration file (binary, not UTF-8 text)", path) from None


def _from_acinoset(doc, path: Path) -> Calibration:
    if not isinstance(doc, dict) or "cameras" not in doc:
        raise InputError('not an AcinoSet scene file: no "cameras" list', path)
    cams = doc["cameras"]
    if not isinstance(cams, list) or not cams:
        raise InputError('"cameras" must be a non-empty list', path)
    size = (0, 0)
    if "camera_resolution" in doc:
        size = image_size(doc["camera_resolution"], "camera_resolution", path)
    spec = camera_model(SCENE_JSON_MODEL)
    cameras = []
    for i, c in enumerate(cams):
        where = f"camera {i + 1}"
        if not isinstance(c, dict):
            raise InputError(f"{where}: expected an object with k, d, r, t", path)
        for key, what in (("k", "camera matrix"), ("d", "distortion"), ("r", "rotation"), ("t", "translation")):
            if key not in c:
                raise InputError(f'{where}: missing "{key}" ({what})', path)
        K = intrinsic_matrix(c["k"], f"{where} k", path)
        d = float_array(c["d"], f"{where} d", path).ravel()
        if d.size != spec.n_coefficients:
            raise InputError(f"{where} d: {spec.name} distortion needs {spec.n_coefficients} coefficients, "
                             f"got {d.size}", path)
        R = rotation_matrix(c["r"], f"{where} r", path)
        t = vector3(c["t"], f"{where} t", path)
        cameras.append(Camera(K=K, dist=d, R=R, t=t, model=spec.name, size=size, name=f"cam{i + 1}"))
    meta = {k: v for k, v in doc.items() if k not in ("cameras", "camera_resolution")
            and isinstance(v, (str, int, float, bool))}
    return Calibration(cameras=cameras, source=str(path), metadata=meta)


def _from_anipose(doc: dict, path: Path) -> Calibration:
    keys = [(int(m.group(1)), k) for k in doc if (m := _CAM_KEY.match(k))]
    if not keys:
        raise InputError("not a calibration file: no [cam_0] ... tables (Anipose) and not JSON (AcinoSet)", path)
    cameras = []
    for _, key in sorted(keys):
        c = doc[key]
        where = f"[{key}]"
        if not isinstance(c, dict):
            raise InputError(f"{where} must be a table", path)
        for field, what in (("matrix", "camera matrix"), ("distortions", "distortion"),
                            ("rotation", "Rodrigues rotation"), ("translation", "translation"),
                            ("size", "image size")):
            if field not in c:
                raise InputError(f"{where}: missing {field} ({what})", path)
        spec = _anipose_model(c, where, path)
        K = intrinsic_matrix(c["matrix"], f"{where} matrix", path)
        d = float_array(c["distortions"], f"{where} distortions", path).ravel()
        problem = spec.coefficient_problem(d.size)
        if problem:
            raise InputError(f"{where} distortions: {problem}", path)
        rvec = vector3(c["rotation"], f"{where} rotation", path)
        t = vector3(c["translation"], f"{where} translation", path)
        name = c.get("name", key)
        if not isinstance(name, (str, int)):
            raise InputError(f"{where} name: must be a string", path)
        cameras.append(Camera(K=K, dist=d, R=rodrigues_to_matrix(rvec), t=t,
                              model=spec.name,
                              size=image_size(c["size"], f"{where} size", path), name=str(name)))
    meta = doc.get("metadata", {})
    return Calibration(cameras=cameras, source=str(path), metadata=dict(meta) if isinstance(meta, dict) else {})


_TOML_KINDS = {bool: "true or false", str: "a string", int: "an integer", float: "a number"}


def _anipose_model(table: dict, where: str, path: Path) -> CameraModel:
    """The camera model an Anipose camera table marks: of the models whose every marking key
    (:attr:`graph.camera.CameraModel.anipose_keys`) the table has, the one with the most (a table
    with none is a pinhole, as in aniposelib)."""
    for m in CAMERA_MODELS.values():
        for key, value in m.anipose_keys:
            if key in table and type(table[key]) is not type(value):
                raise InputError(f"{where} {key}: must be {_TOML_KINDS.get(type(value), type(value).__name__)}", path)
    found = [m for m in CAMERA_MODELS.values() if all(key in table and table[key] == value
                                                      for key, value in m.anipose_keys)]
    most = max((len(m.anipose_keys) for m in found), default=0)
    best = [m for m in found if len(m.anipose_keys) == most]
    if len(best) != 1:
        raise InputError(f"{where}: marks " + (" and ".join(m.name for m in best) + " cameras at once" if best
                                               else "no camera model"), path)
    return best[0]


# ----------------------------------------------------------------------------------- rotations


def rodrigues_to_matrix(rvec: np.ndarray) -> np.ndarray:
    """Rodrigues vector to rotation matrix (as ``cv2.Rodrigues``), with ``theta = |r|, k = r/theta``::

        R = cos(theta) I + sin(theta) [k]_x + (1 - cos(theta)) k k^T
    """
    r = np.asarray(rvec, dtype=np.float64).reshape(3)
    theta = float(np.linalg.norm(r))
    if theta < 1e-15:
        return np.eye(3)
    k = r / theta
    kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return math.cos(theta) * np.eye(3) + math.sin(theta) * kx + (1.0 - math.cos(theta)) * np.outer(k, k)


def matrix_to_rodrigues(R: np.ndarray) -> np.ndarray:
    """Rotation matrix to Rodrigues vector, the inverse of :func:`rodrigues_to_matrix` (``cv2.Rodrigues``)."""
    import cv2

    rvec, _ = cv2.Rodrigues(np.asarray(R, dtype=np.float64).reshape(3, 3))
    return rvec.ravel()


# --------------------------------------------------------------------------------------- writing


def save_calibration(path: str | Path, calibration: Calibration) -> None:
    """Write ``.json`` as AcinoSet scene JSON, anything else as Anipose TOML."""
    if Path(path).suffix.lower() == ".json":
        write_acinoset_json(path, calibration)
    else:
        write_anipose_toml(path, calibration)


def write_acinoset_json(path: str | Path, calibration: Calibration) -> None:
    """AcinoSet scene JSON. The format holds fisheye cameras (:data:`SCENE_JSON_MODEL`) of one resolution only."""
    cams = calibration.cameras
    if any(c.model != SCENE_JSON_MODEL for c in cams):
        raise ValueError(f"AcinoSet scene JSON holds {SCENE_JSON_MODEL} cameras only; write Anipose TOML instead")
    sizes = {tuple(c.size) for c in cams}
    if len(sizes) > 1:
        raise ValueError(f"AcinoSet scene JSON has one camera_resolution, the cameras have {sorted(sizes)}")
    doc: dict = {k: v for k, v in calibration.metadata.items() if isinstance(v, (str, int, float, bool))}
    doc["camera_resolution"] = list(sizes.pop()) if sizes else [0, 0]
    doc["cameras"] = [{"k": c.K.tolist(), "d": c.dist.reshape(-1, 1).tolist(),
                       "r": c.R.tolist(), "t": c.t.reshape(3, 1).tolist()} for c in cams]
    Path(path).write_text(json.dumps(doc, indent=2) + "\n", encoding="utf-8")


def write_anipose_toml(path: str | Path, calibration: Calibration) -> None:
    """Anipose ``calibration.toml`` with the tables and keys ``aniposelib.CameraGroup.dump`` writes."""
    lines: list[str] = []
    for i, (c, name) in enumerate(zip(calibration.cameras, calibration.names)):
        lines.append(f"[cam_{i}]")
        lines.append(f"name = {_toml_value(name)}")
        lines.append(f"size = {_toml_value([int(c.size[0]), int(c.size[1])])}")
        lines.append(f"matrix = {_toml_value(c.K.tolist())}")
        lines.append(f"distortions = {_toml_value(c.dist.tolist())}")
        lines.append(f"rotation = {_toml_value(matrix_to_rodrigues(c.R).tolist())}")
        lines.append(f"translation = {_toml_value(c.t.tolist())}")
        lines.extend(f"{_toml_key(key)} = {_toml_value(value)}" for key, value in c.camera_model.anipose_keys)
        lines.append("")
    lines.append("[metadata]")
    for key, value in calibration.metadata.items():
        try:
            lines.append(f"{_toml_key(key)} = {_toml_value(value)}")
        except TypeError:
            continue  # not representable in TOML: left out
    Path(path).write_text("\n".join(lines) + "\n", encoding="utf-8")


def _toml_key(key) -> str:
    key = str(key)
    return key if re.fullmatch(r"[A-Za-z0-9_-]+", key) else _toml_value(key)


def _toml_value(v) -> str:
    """A TOML value: bool, int, float (``repr``, which TOML reads back exactly), string, array,
    inline table."""
    if isinstance(v, (bool, np.bool_)):
        return "true" if v else "false"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, (float, np.floating)):
        f = float(v)
        if math.isnan(f):
            return "nan"
        if math.isinf(f):
            return "inf" if f > 0 else "-inf"
        return repr(f)
    if isinstance(v, str):
        # JSON escapes control characters as TOML basic strings do; DEL must be escaped too
        return json.dumps(v, ensure_ascii=False).replace("\x7f", "\\u007f")
    if isinstance(v, (list, tuple, np.ndarray)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{_toml_key(k)} = {_toml_value(x)}" for k, x in v.items()) + "}"
    raise TypeError(f"cannot write {type(v).__name__} as TOML")


RIG_SIZE_MM_GUESS = 50.0  # a rig whose cameras sit this many units apart is not in metres


def resolve_units(calibration: Calibration, units: str) -> tuple[str, str | None]:
    """The units of the calibration's translations (a key of :data:`CALIBRATION_UNITS` other than
    ``auto``) and a note when guessed: with ``units="auto"`` a rig whose cameras are more than 50
    units from their centroid is taken to be in millimetres (and said so), otherwise metres."""
    if CALIBRATION_UNITS[units] != 0.0:
        return units, None
    centres = np.stack([c.center for c in calibration.cameras])
    spread = float(np.median(np.linalg.norm(centres - centres.mean(0), axis=1)))
    if spread > RIG_SIZE_MM_GUESS:
        return "mm", (f"{calibration.source or 'calibration'}: cameras are {spread:.0f} units from their centre; "
                      "taking the calibration to be in millimetres (set calibration units to override)")
    return "m", None


def in_metres(calibration: Calibration, units: str) -> tuple[Calibration, str | None]:
    """The calibration with translations in metres. Anipose calibrations are in the units of the
    calibration board, often millimetres; ``units="auto"`` guesses them (:func:`resolve_units`)."""
    units, note = resolve_units(calibration, units)
    scale = CALIBRATION_UNITS[units]
    if scale == 1.0:
        return calibration, note
    cams = [replace(c, t=c.t * scale) for c in calibration.cameras]
    return replace(calibration, cameras=cams), note
