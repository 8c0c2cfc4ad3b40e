"""An Anipose project read as Anipose reads it: ``config.toml``, sessions, trials, calibrations.

What ``anipose triangulate`` does, and so what this does (lambdaloop/anipose, ``anipose.py``
``load_config``, ``common.py`` ``process_all`` / ``find_calibration_folder`` / ``get_cam_name`` /
``get_video_name``, ``triangulate.py`` ``process_session``):

* ``config.toml`` at the project's top, with Anipose's defaults for missing keys. ``path`` (if it
  exists on this machine) is the project folder, else the config's folder.
* Sessions by ``nesting``: 0 the project folder itself; k the folders k levels down (sorted);
  -1 every folder at every level.
* A session's calibration: from the session folder up ``nesting`` levels, the first folder holding
  a ``[pipeline] calibration_videos`` folder (default ``calibration``); the file is
  ``<that>/<calibration_results>/calibration.toml``.
* Its 2D poses: ``<session>/<pose_2d>/*.h5`` (``pose-2d``; ``pose-2d-filtered`` when ``[filter]
  enabled``, as after ``anipose filter``). A file's camera is the first group of
  ``re.search(cam_regex, stem)``; its trial the stem with ``cam_regex`` removed
  (``re.sub``, stripped). Cameras in sorted order, taken from the calibration by name. The pattern
  runs on RE2 (time linear in the name's length, whatever the pattern: no backreferences or
  lookarounds).
* ``[cameras.<name>] offset = [dx, dy]`` is added to that camera's 2D points (a cropped video).
* Frames: the fewest of the trial's cameras (Anipose truncates to them).
* Output: ``<session>/<pose_3d>/<trial>.csv`` (``pose-3d``) in Anipose's 3D layout, and ours, the
  result H5, beside it as ``<trial>.h5``.

Options (:func:`solve_options`): ``[triangulation] score_threshold`` is the likelihood threshold
(Anipose's default 0.8); ``optim = true`` (Anipose's smoothing with limb constraints) is ``fte``,
``false`` (plain triangulation) is ``tri``; every bodypart is a free point (``points``) and
``constraints`` (and ``constraints_weak``) are its bones, soft length terms. Our own options go in
an ``[acinoset]`` table: ``method``, ``skeleton`` (a name or a TOML file relative to the project),
``body`` (model, estimate or a file), ``sync``, ``fps`` (else each trial's video frame rate when its
``videos-raw`` file is readable, else 120), and any other :class:`SolveOptions` field;
``motion_scale`` may name an earlier solve's report or result, whose fitted smoothing every trial
is then solved with (:func:`graph.io.results.given_motion`). Files named there are relative to the project
and count as every trial's inputs: a trial is solved again when one of them changes. Keys of
Anipose's 3D step that have no equivalent here are listed in :attr:`Project.ignored`.
``axes`` with ``reference_point`` turn the CSVs into Anipose's frame (:mod:`graph.anipose.frame`);
the H5 stays in the calibration's.

A project from elsewhere (an upload) is read with ``within``, the folder it must keep to: every path
its config names (``[pipeline]`` folders, ``video_extension``, the ``[acinoset]`` files) must resolve
inside it after symlinks, or :class:`InputError` names the key; a ``path`` out of it is not
followed; the session walk follows no symlink; ``config.toml`` is at most :data:`MAX_CONFIG_BYTES`.
Any walk visits at most :data:`MAX_FOLDERS` folders, :data:`MAX_DEPTH` levels deep.
"""

from __future__ import annotations

import dataclasses
import os
import re
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import re2

from graph.errors import NESTED_TOO_DEEPLY, InputError
from graph.types import SolveOptions

CONFIG = "config.toml"
CALIBRATION_FILE = "calibration.toml"
PIPELINE_DEFAULTS = {"pose_2d": "pose-2d", "pose_2d_filter": "pose-2d-filtered", "pose_3d": "pose-3d",
                     "calibration_videos": "calibration", "calibration_results": "calibration",
                     "videos_raw": "videos-raw"}
SCORE_THRESHOLD = 0.8  # Anipose's default
DEFAULT_NESTING = 1
MAX_CONFIG_BYTES = 2**20  # of a config read ``within`` a folder (Anipose's are a few kB)
MAX_FOLDERS = 100_000  # folders the session walk visits at most
MAX_DEPTH = 64  # levels it descends at most (nesting -1)
# keys of Anipose's 3D step with no equivalent here (what replaces them, for the message)
IGNORED = {
    "triangulation": {"ransac": "the robust loss", "scale_smooth": "the motion model",
                      "scale_length": "the bone terms' own weight", "scale_length_weak": "the bone terms' own weight",
                      "reproj_error_threshold": "the robust loss", "n_deriv_smooth": "the motion model",
                      "optim_chunking": "solving whole trials", "optim_chunking_size": "solving whole trials",
                      "cam_align": "axes and reference_point"},
    "filter": {"type": "the robust loss", "medfilt": "the robust loss", "offset_threshold": "the robust loss",
               "score_threshold": "score_threshold of [triangulation]", "spline": "the motion model",
               "n_back": "the robust loss", "multiprocessing": "trial processes"},
    "filter3d": {"enabled": "the motion model", "medfilt": "the motion model", "offset_threshold": "the motion model"},
}
OUR_KEYS = ("method", "skeleton", "body", "sync", "fps")


@dataclass
class Trial:
    """One trial: a camera's DLC H5 per camera, the session's calibration, and where results go."""

    session: str  # the session folder, relative to the project ("." for nesting 0)
    name: str
    cameras: list[str]  # sorted, as Anipose orders them
    pose_files: list[Path]  # one per camera, in ``cameras``' order
    calibration: Path
    csv: Path
    h5: Path
    fps: float | None = None  # from the trial's videos, when readable

    @property
    def label(self) -> str:
        return self.name if self.session == "." else f"{self.session}/{self.name}"

    def inputs(self, shared: list[Path]) -> list[Path]:
        """The files its results depend on: its own and ``shared`` (:attr:`Project.inputs`)."""
        return [*self.pose_files, self.calibration, *shared]


@dataclass
class Project:
    """An Anipose project: its trials and the options they are solved with."""

    root: Path
    config: Path
    options: SolveOptions
    offsets: dict[str, tuple[float, float]]
    trials: list[Trial]
    # [triangulation] axes and reference_point: the CSVs' frame (graph.anipose.frame), or None
    frame: tuple[list, str] | None = None
    ignored: list[str] = field(default_factory=list)  # "[section] key (what stands in)"
    notes: list[str] = field(default_factory=list)  # sessions without a calibration, ...
    option_files: list[Path] = field(default_factory=list)  # skeleton, body, motion files of [acinoset]

    @property
    def inputs(self) -> list[Path]:
        """The files every trial's results depend on: ``config.toml`` and :attr:`option_files`."""
        return [self.config, *self.option_files]


def load_project(folder: str | Path = ".", within: str | Path | None = None) -> Project:
    """Read ``folder/config.toml`` and find every trial, as ``anipose triangulate`` would.
    ``within``: the folder a project from elsewhere must keep to (see the module's docstring)."""
    folder = Path(folder).resolve()
    bound = None if within is None else Path(within).resolve()
    config_path = folder / CONFIG
    if not config_path.is_file() or (bound is not None and not resolves_inside(config_path, bound)):
        raise InputError(f"no {CONFIG} here: not an Anipose project folder", folder)
    if bound is not None and config_path.stat().st_size > MAX_CONFIG_BYTES:
        raise InputError(f"over {MAX_CONFIG_BYTES} bytes (an Anipose config is a few kB)", config_path)
    try:
        config = tomllib.loads(config_path.read_text(encoding="utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
        raise InputError(f"not valid TOML ({e})", config_path) from None
    except RecursionError:
        raise InputError(NESTED_TOO_DEEPLY, config_path) from None

    def keep(path: Path, key: str) -> Path:
        """``path``, which ``key`` named: inside ``within`` (after symlinks), or refused."""
        if bound is not None and not resolves_inside(path, bound):
            raise InputError(f"{key} names a path outside the project (an uploaded project reads only its own "
                             "files)", config_path)
        return path

    notes: list[str] = []
    root = folder
    if isinstance(config.get("path"), str) and bound is not None:  # the author's folder: used only if in the upload
        given = folder / config["path"]
        if resolves_inside(given, bound) and given.is_dir():
            root = given.resolve()
        else:  # whether or not it exists on this machine: the same note
            notes.append("path: not a folder of the upload; the upload's own folder is the project")
    elif isinstance(config.get("path"), str):
        given = Path(os.path.expanduser(config["path"]))
        if given.is_dir():
            root = given.resolve()
        elif given.resolve() != folder:
            notes.append(f"path = {config['path']!r} does not exist here; using {folder}")
    model_type = config.get("model_type", "deeplabcut")
    if model_type != "deeplabcut":
        raise InputError(f"model_type {model_type!r}: only DeepLabCut H5 poses are read", config_path)
    tri = _table(config, "triangulation", config_path)
    if "cam_regex" not in tri:
        raise InputError("[triangulation] has no cam_regex (how a pose file names its camera)", config_path)
    cam_regex = compile_pattern(tri["cam_regex"], "[triangulation] cam_regex", config_path)
    pipeline = {**PIPELINE_DEFAULTS, **_table(config, "pipeline", config_path)}
    for key in PIPELINE_DEFAULTS:
        if not (isinstance(pipeline[key], str) and pipeline[key] and "\x00" not in pipeline[key]):
            raise InputError(f"[pipeline] {key} must be a folder's name", config_path)
    nesting = config.get("nesting", DEFAULT_NESTING)
    if not isinstance(nesting, int) or isinstance(nesting, bool):
        raise InputError(f"nesting must be an integer, not {nesting!r}", config_path)
    extension = config.get("video_extension", "avi")
    if not isinstance(extension, str) or "\x00" in extension:
        raise InputError("video_extension must be a file extension such as 'avi'", config_path)
    filt = _table(config, "filter", config_path)
    pose_key = "pose_2d_filter" if filt.get("enabled", False) else "pose_2d"
    pose_dir = pipeline[pose_key]

    options, option_files = solve_options(config, root, config_path, within=bound)
    offsets = {}
    for name, cam in _table(config, "cameras", config_path).items():
        off = cam.get("offset", (0, 0)) if isinstance(cam, dict) else None
        try:
            if not (isinstance(off, (list, tuple)) and len(off) == 2
                    and all(isinstance(v, (int, float)) for v in off)):
                raise ValueError
            offsets[str(name)] = (float(off[0]), float(off[1]))
        except (ValueError, OverflowError):
            raise InputError(f"[cameras.{name}] offset must be [dx, dy] pixels", config_path) from None
    our_fps = "fps" in _table(config, "acinoset", config_path)

    trials: list[Trial] = []
    for session in sessions(root, nesting, follow_links=bound is None):
        cal_dir = find_calibration_folder(session, root, nesting, pipeline["calibration_videos"], within=bound)
        rel = os.path.relpath(session, root)
        poses = sorted(keep(p, f"[pipeline] {pose_key}")
                       for p in keep(session / pose_dir, f"[pipeline] {pose_key}").glob("*.h5"))
        if not poses:
            if pose_dir != pipeline["pose_2d"] and any(keep(session / pipeline["pose_2d"], "[pipeline] pose_2d")
                                                       .glob("*.h5")):
                notes.append(f"{rel}: [filter] enabled but no {pose_dir}/ (run anipose filter, or set "
                             "enabled = false: the robust loss stands in for it): skipped")
            continue
        if cal_dir is None:
            notes.append(f"{rel}: no '{pipeline['calibration_videos']}' folder in it or above it: skipped")
            continue
        by_trial: dict[str, dict[str, Path]] = {}
        for p in poses:
            match = cam_regex.search(p.stem)
            if not match or not match.groups() or match.groups()[0] is None:
                notes.append(f"{rel}/{pose_dir}/{p.name}: cam_regex finds no camera in its name: skipped")
                continue
            by_trial.setdefault(cam_regex.sub("", p.stem).strip(), {})[match.groups()[0].strip()] = p
        out_dir = keep(session / pipeline["pose_3d"], "[pipeline] pose_3d")
        calibration = keep(cal_dir / pipeline["calibration_results"] / CALIBRATION_FILE,
                           "[pipeline] calibration_results")
        for name in sorted(by_trial, key=_natural):
            files = by_trial[name]
            cams = sorted(files)
            video = session / pipeline["videos_raw"] / f"{files[cams[0]].stem}.{extension.lstrip('.')}"
            trials.append(Trial(session=rel, name=name, cameras=cams, pose_files=[files[c] for c in cams],
                                calibration=calibration, csv=out_dir / f"{name}.csv", h5=out_dir / f"{name}.h5",
                                fps=None if our_fps else _video_fps(keep(video, "[pipeline] videos_raw"))))
    frame = None
    if "axes" in tri and "reference_point" in tri:  # as Anipose: both, or the calibration's frame
        frame = (tri["axes"], str(tri["reference_point"]))
        if not isinstance(frame[0], list) or not all(isinstance(a, list) and len(a) == 3 for a in frame[0]):
            raise InputError('[triangulation] axes must be a list of ["x|y|z", bodypart, bodypart]', config_path)
    return Project(root=root, config=config_path, options=options, offsets=offsets, trials=trials,
                   frame=frame, ignored=ignored_keys(config), notes=notes, option_files=option_files)


def solve_options(config: dict, root: Path, config_path: Path,
                  within: Path | None = None) -> tuple[SolveOptions, list[Path]]:
    """The :class:`SolveOptions` a project's ``config.toml`` asks for (see the module's docstring),
    and the files its ``[acinoset]`` table names (a skeleton, body or motion file); with ``within``,
    each must resolve inside that folder."""
    tri = _table(config, "triangulation", config_path)
    ours = dict(_table(config, "acinoset", config_path))
    known = {f.name for f in dataclasses.fields(SolveOptions)}
    unknown = sorted(set(ours) - known)
    if unknown:
        raise InputError(f"[acinoset] has unknown keys {', '.join(unknown)} (known: {', '.join(OUR_KEYS)}, "
                         "or any solve option)", config_path)
    try:
        threshold = float(tri.get("score_threshold", SCORE_THRESHOLD))
    except (TypeError, ValueError, OverflowError):
        raise InputError("[triangulation] score_threshold must be a number from 0 to 1", config_path) from None
    bones = []
    for key in ("constraints", "constraints_weak"):
        pairs = tri.get(key, [])
        if not isinstance(pairs, list) or any(not isinstance(p, (list, str)) or len(p) != 2 for p in pairs):
            raise InputError(f"[triangulation] {key} must be pairs of bodyparts", config_path)
        bones += [tuple(map(str, pair)) for pair in pairs]
    kw: dict[str, Any] = {"method": "fte" if tri.get("optim", False) else "tri", "skeleton": "points",
          "likelihood_threshold": threshold, "bone_lengths": bones or None}
    kw.update(ours)
    files: list[Path] = []

    def project_file(name: str, key: str) -> Path:
        path = root / name if within is not None else Path(os.path.expanduser(name))
        if within is not None and not resolves_inside(path, within):
            raise InputError(f"[acinoset] {key} names a file outside the project (an uploaded project reads only "
                             "its own files)", config_path)
        files.append(path if path.is_absolute() else root / path)
        return files[-1]

    if not isinstance(kw["skeleton"], str):
        raise InputError("[acinoset] skeleton must be a skeleton's name or a .toml file of the project", config_path)
    if kw["skeleton"] not in ("cheetah", "points"):
        kw["skeleton"] = str(project_file(kw["skeleton"], "skeleton"))
    if isinstance(kw.get("body"), str) and kw["body"] not in ("model", "estimate", "given"):
        from graph.io.results import read_body

        kw["body"], kw["body_lengths"] = "given", read_body(project_file(kw["body"], "body"))
    if isinstance(kw.get("motion_scale"), str) and kw["motion_scale"].strip().lower() != "auto":
        from graph.io.results import given_motion

        kw["motion_scale"], kw["motion_order"] = given_motion(project_file(kw["motion_scale"], "motion_scale"),
                                                              kw.get("motion_order"))
    if kw["skeleton"] != "points":
        kw["bone_lengths"] = None  # bones between free points only
    try:
        return SolveOptions(**kw), files
    except (TypeError, ValueError, OverflowError) as e:
        raise InputError(f"[acinoset] / [triangulation]: {e}", config_path) from None


def ignored_keys(config: dict) -> list[str]:
    """The keys the user set that steer Anipose's 3D step and have no equivalent here."""
    out = []
    for section, keys in IGNORED.items():
        table = config.get(section, {})
        if not isinstance(table, dict):
            continue
        for key, instead in keys.items():
            if key in table and not (section == "filter3d" and key == "enabled" and not table[key]):
                out.append(f"[{section}] {key} ({instead} stands in)")
    return out


def sessions(root: Path, nesting: int, follow_links: bool = True) -> list[Path]:
    """Anipose's ``process_all``: the session folders for ``nesting``; through symlinked folders only
    with ``follow_links``. At most :data:`MAX_FOLDERS` folders, :data:`MAX_DEPTH` levels down, are
    visited (:class:`InputError` beyond: a symlink loop, or not a project)."""
    if nesting == 0:
        return [root]
    out: list[Path] = []
    visited = 0

    def walk(folder: Path, level: int) -> None:
        nonlocal visited
        if level > MAX_DEPTH:
            raise InputError(f"folders nested more than {MAX_DEPTH} levels deep under the project (nesting = "
                             f"{nesting}; a symbolic link to a folder above?)")
        subs = sorted(p for p in folder.iterdir()
                      if not p.name.startswith(".") and p.is_dir() and (follow_links or not p.is_symlink()))
        visited += len(subs)
        if visited > MAX_FOLDERS:
            raise InputError(f"more than {MAX_FOLDERS} folders under the project (nesting = {nesting}): not an "
                             "Anipose project's sessions")
        for sub in subs:
            if nesting < 0:
                out.append(sub)
                walk(sub, level + 1)
            elif level == nesting:
                out.append(sub)
            elif level < nesting:
                walk(sub, level + 1)

    walk(root, 1)
    return out


def find_calibration_folder(session: Path, root: Path, nesting: int, calibration_videos: str,
                            within: Path | None = None) -> Path | None:
    """Anipose's ``find_calibration_folder``: the session folder or one of its ``nesting`` parents
    (the nearest) that holds a ``calibration_videos`` folder. With nesting -1, up to the project.
    With ``within``, a ``calibration_videos`` that leads out of that folder is refused."""
    levels = nesting if nesting >= 0 else len(session.relative_to(root).parts)
    folder = session
    for _ in range(levels + 1):
        candidate = folder / calibration_videos
        if within is not None and not resolves_inside(candidate, within):
            raise InputError("[pipeline] calibration_videos names a path outside the project (an uploaded project "
                             "reads only its own files)")
        if candidate.is_dir():
            return folder
        folder = folder.parent
    return None


def compile_pattern(pattern: object, key: str, path: Path):
    """``pattern`` as an RE2 expression: matching takes time linear in the text, whatever the pattern
    (Python's ``re`` backtracks: ``_((a+)+)$`` on a 30-letter name took seconds). RE2 has no
    backreferences or lookarounds; such a pattern is an :class:`InputError` naming ``key``."""
    if not isinstance(pattern, str):
        raise InputError(f"{key} must be a string (a regular expression)", path)
    options = re2.Options()
    options.log_errors = False
    try:
        return re2.compile(pattern, options)
    except re2.error as e:
        why = e.args[0].decode(errors="replace") if e.args and isinstance(e.args[0], bytes) else str(e)
        raise InputError(f"{key} is not a regular expression this reader runs (RE2's syntax: no backreferences "
                         f"or lookarounds): {why[:200]}", path) from None


def resolves_inside(path: Path, folder: Path) -> bool:
    """Whether ``path`` resolves (after symlinks and ``..``) to ``folder`` or below it."""
    try:
        return path.resolve().is_relative_to(folder)
    except (OSError, RuntimeError, ValueError):  # a symlink loop, a name too long, a NUL byte
        return False


def _table(config: dict, name: str, path: Path) -> dict:
    t = config.get(name, {})
    if not isinstance(t, dict):
        raise InputError(f"[{name}] must be a table", path)
    return t


def _natural(text: str) -> list:
    """Anipose's ``natural_keys``: trial2 before trial10."""
    return [int(c) if c.isdigit() else c for c in re.split(r"(\d+)", text)]


def _video_fps(path: Path) -> float | None:
    """The frame rate of the video ``path`` when OpenCV can read it."""
    if not path.is_file():
        return None
    import cv2

    cap = cv2.VideoCapture(str(path))
    try:
        fps = float(cap.get(cv2.CAP_PROP_FPS))
    finally:
        cap.release()
    return fps if 0 < fps < 10000 else None
