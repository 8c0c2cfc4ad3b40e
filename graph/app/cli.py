"""The ``acinoset`` command line: one-line errors and lazily loaded subcommands.

The library's own subcommands are :data:`COMMANDS` (``python -m graph.app.cli`` runs them); the
``acinoset`` script adds the service's (``service/cli.py``), which knows both layers. Only the
module of the subcommand given is imported, so ``acinoset --help`` and ``--version`` load no solver.

Subcommand contract. A module named by a :class:`Command` defines::

    def register(subparsers: argparse._SubParsersAction) -> None:
        p = subparsers.add_parser("name", description="...")   # the one-line help is the Command's
        p.add_argument(...)
        p.set_defaults(func=run)       # run(args: argparse.Namespace) -> int (exit status)

A module that does not exist is skipped; an ImportError raised *inside* an existing module is a
real error and propagates. Parsers made by ``add_parser`` share this module's one-line error
handling. Exit statuses: 0 success, 2 bad input (one line on stderr:
``acinoset: error: <file>: <problem>``), anything else from the subcommand itself. A
:class:`graph.errors.InputError` raised by ``func`` is printed the same way.
"""

from __future__ import annotations

import argparse
import importlib
import json
import os
import shutil
import sys
import warnings
from collections import namedtuple
from pathlib import Path
from typing import TYPE_CHECKING, NamedTuple

from graph import __version__
from graph.errors import InputError, WorkerLost

if TYPE_CHECKING:
    from graph.types import Body, SolveReport

PROG = "acinoset"


class Command(namedtuple("Command", "name module help")):
    """A subcommand: its ``name``, the ``module`` whose ``register`` adds it, and its one-line
    ``help``. (A named tuple, not a dataclass: ``dataclasses`` imports ``inspect``, 10 ms of every
    ``acinoset`` command's start, ``--version`` included.)"""

    __slots__ = ()


COMMANDS: tuple[Command, ...] = (
    Command("solve", "graph.app.cli", "3D trajectories from DeepLabCut files of calibrated cameras"),
    Command("simulate", "graph.simulate",
            "simulate a cheetah run on a rig and write DeepLabCut CSVs, calibration and truth"),
    Command("demo", "graph.app.demo", "simulate a cheetah run on the AcinoSet rig and solve it with every method"),
    Command("plot", "graph.viewer.cli", "draw a solved run: PNG figures and an HTML playback file"),
    Command("anipose", "graph.anipose.cli",
            "solve an Anipose project's trials unchanged (config.toml, pose-2d, calibration) into pose-3d"),
    Command("export", "graph.export.cli", "write a solved run in a format other tools read (listed by its -h)"),
    Command("video", "graph.video.cli", "draw a solved run over each camera's video, with a 3D view (H.264 MP4)"),
    Command("calibrate", "graph.calibrate.cli", "calibrate cameras from board views, or refine a rig from keypoints"),
    Command("evaluate", "graph.app.evaluate", "score a 3D method on a recording: leave one camera out"),
    Command("resident", "graph.app.resident.status",
            "the warm background process that serves 'acinoset solve': status, stop"),
)


class UsageError(Exception):
    """A command-line mistake; printed as one line, exit status 2."""


class OneLineParser(argparse.ArgumentParser):
    """argparse that reports mistakes as one line (the caller prints it) instead of usage + exit."""

    def error(self, message: str):  # noqa: D401 - argparse API
        raise UsageError(" ".join(message.split()))


class _Subparsers:
    """What a module's ``register`` is given: ``add_parser`` with the help line of its :class:`Command`."""

    def __init__(self, action, helps: dict[str, str]):
        self._action = action
        self._helps = helps

    def add_parser(self, name: str, **kwargs):
        kwargs.setdefault("help", self._helps.get(name))
        return self._action.add_parser(name, **kwargs)


def build_parser(commands: tuple[Command, ...] = COMMANDS, only: str | None = None) -> argparse.ArgumentParser:
    """The parser of ``commands``. With ``only``, just that subcommand's module is imported (the
    others are listed with their help line); without, every module is."""
    parser = OneLineParser(prog=PROG, description="Markerless 3D animal pose from calibrated cameras "
                           "and DeepLabCut keypoints.")
    parser.add_argument("--version", action="version", version=f"{PROG} {__version__}")
    action = parser.add_subparsers(dest="command", metavar="COMMAND")
    action.required = True
    sub = _Subparsers(action, {c.name: c.help for c in commands})
    loaded: set[str] = set()
    for c in commands:  # the modules first (one may add several commands), then the rest listed
        if (only is None or c.name == only) and c.module not in loaded:
            loaded.add(c.module)
            module = _optional_module(c.module)
            if module is not None and hasattr(module, "register"):
                module.register(sub)
    for c in commands:
        if c.name not in action.choices:
            action.add_parser(c.name, help=c.help, add_help=False)  # listed; its module is not loaded
    return parser


def _optional_module(name: str):
    """Import ``name``; None if it (or its package) does not exist. Errors inside it propagate."""
    try:
        return importlib.import_module(name)
    except ModuleNotFoundError as e:
        if e.name is not None and (name == e.name or name.startswith(e.name + ".")):
            return None
        raise


def _command_named(argv: list[str]) -> str:
    """The subcommand ``argv`` names: its first word that is not an option ("" if none)."""
    return next((a for a in argv if not a.startswith("-")), "")


def main(argv: list[str] | None = None, commands: tuple[Command, ...] = COMMANDS) -> int:
    """Run the command line ``argv`` (default: this process's own, ``sys.argv[1:]``) with the
    ``commands`` table (:class:`Command`, or plain ``(name, module, help)`` triples); the exit status."""
    command_line = argv is None
    argv = sys.argv[1:] if argv is None else list(argv)
    commands = tuple(Command(*c) for c in commands)
    if _command_named(argv) == "solve":  # handed to a warm resident process when one is up
        try:
            from graph.app.resident import client

            return client.solve(argv, commands, lambda: _run(argv, commands), exit_when_served=command_line,
                                  entry="graph.app.cli:main")
        except KeyboardInterrupt:  # in the hand-over's first milliseconds (importing, finding the resident)
            return _interrupted()
    return _run(argv, commands)


def _run(argv: list[str], commands: tuple[Command, ...]) -> int:
    try:
        parser = build_parser(commands, only=_command_named(argv))
        args = parser.parse_args(argv)
        func = getattr(args, "func", None)
        if func is None:  # a command group given without one of its subcommands
            raise UsageError(f"'{args.command}' needs a subcommand (see {PROG} {args.command} --help)")
        with warnings.catch_warnings():
            warnings.showwarning = _show_warning
            return int(func(args) or 0)
    except UsageError as e:
        return _fail(str(e))
    except (InputError, WorkerLost) as e:
        return _fail(str(e))
    except OSError as e:  # an output path that cannot be written, a disk that is full, ...
        where = f"{Path(e.filename).name}: " if e.filename else ""
        return _fail(f"{where}{e.strerror or e}")
    except KeyboardInterrupt:
        return _interrupted()
    except SystemError as e:
        if _caused_by_ctrl_c(e):
            return _interrupted()
        raise


def _caused_by_ctrl_c(e: BaseException) -> bool:
    """A Ctrl-C inside a compiled kernel's call reaches us as numba's dispatcher reports it: a
    ``SystemError`` ('returned a result with an exception set') caused by (a chain ending in) it."""
    while e.__cause__ is not None:
        e = e.__cause__
    return isinstance(e, KeyboardInterrupt)


def _interrupted() -> int:
    """Ctrl-C: one line and the shell's status for SIGINT, 130 (no traceback)."""
    print(f"{PROG}: interrupted", file=sys.stderr)
    return 130


def _show_warning(message, category, filename, lineno, file=None, line=None) -> None:
    """Warnings meant for the user (``UserWarning``) as one line; numerical noise from inside
    the solvers (``RuntimeWarning`` and the like) is not shown."""
    if issubclass(category, UserWarning):
        print(f"{PROG}: warning: {' '.join(str(message).split())}", file=sys.stderr)


def _fail(message: str) -> int:
    print(f"{PROG}: error: {' '.join(message.split())}", file=sys.stderr)
    return 2


# ------------------------------------------------------------------------------------------ solve


def register(sub) -> None:
    """``acinoset solve``."""
    p = sub.add_parser("solve", description="Estimate 3D trajectories from one keypoint file per camera (DeepLabCut "
                       "CSV/H5, SLEAP analysis HDF5), given in the calibration's camera order.")
    p.add_argument("keypoints", nargs="+", metavar="CAM.csv", help=KEYPOINTS_HELP)
    p.add_argument("--calibration", required=True, metavar="FILE",
                   help="Anipose calibration.toml or AcinoSet scene JSON")
    add_solve_options(p)
    p.add_argument("--out", required=True, metavar="OUT.csv", help="3D result in Anipose's CSV layout")
    p.add_argument("--units", choices=["m", "cm", "mm", "auto"], default="m",
                   help="the CSV's units (default m); auto: the calibration's own (--calibration-units), as "
                        "'anipose triangulate' writes a project calibrated in millimetres; the H5 is in metres")
    p.add_argument("--h5", default=None, metavar="OUT.h5",
                   help="also write everything as HDF5 (several individuals: one file, an individuals axis)")
    p.add_argument("--report", default=None, metavar="REPORT.json", help="also write the solver report")
    p.add_argument("--reprojections", default=None, metavar="DIR",
                   help="also write the estimate reprojected into each camera as DeepLabCut CSVs")
    p.add_argument("--jobs", type=_positive_int, default=1, metavar="N",
                   help="a long run solved in windows by fte: N windows at a time in worker processes, each with its "
                        "share of the cores (default 1; the same answer; about 0.5 GB more memory a worker; ekf's "
                        "windows are one stream, solved in turn)")
    p.add_argument("--resume", action="store_true",
                   help="go on with a long run that stopped (killed, out of time) from its last finished window, "
                        "with the same files and options: a run solved in windows keeps OUT.csv.partial/ until done")
    p.set_defaults(func=run_solve)


KEYPOINTS_HELP = ("DeepLabCut CSV or H5, SLEAP .slp or analysis HDF5 (.analysis.h5), or an OpenPose JSON folder, "
                  "one per camera in the calibration's order; an ensemble of pose models as CAM_a.csv+CAM_b.csv "
                  "(one observation, its members' spread weighing the cameras)")


def read_cameras(paths: list[str], individual: str | None = None, openpose_model: str | None = None) -> list:
    """One :class:`~graph.io.keypoints.Keypoints` per camera argument: a file (or an OpenPose JSON
    folder), or an ensemble's files joined by ``+`` (combined by :func:`graph.solve.ensemble.combine`;
    a file whose own name has a ``+`` is read as one file)."""
    from graph.io.keypoints import read_keypoints

    def read(p: str):
        return read_keypoints(p, individual=individual, openpose_model=openpose_model)

    out = []
    for arg in paths:
        if _is_ensemble(arg):
            from graph.solve.ensemble import combine

            out.append(combine([read(p) for p in arg.split("+") if p]))
        else:
            out.append(read(arg))
    return out


def add_solve_options(p) -> None:
    """The options of a solve (``--method`` .. ``--time-offsets``), for ``solve`` and the commands
    that solve as it does; :func:`solve_options` reads them back."""
    from graph.camera import CALIBRATION_UNITS
    from graph.types import METHODS, WINDOW_FRAMES, WINDOWED_ABOVE, SolveOptions

    defaults = SolveOptions()
    p.add_argument("--method", choices=METHODS, default=defaults.method)
    p.add_argument("--fps", type=float, default=None,
                   help="the cameras' frame rate, frames per second; required unless the keypoint files record "
                        "it (SLEAP's analysis files may, DeepLabCut's never do)")
    p.add_argument("--skeleton", default=defaults.skeleton, metavar="cheetah|points|PATH",
                   help="skeleton: the AcinoSet cheetah, free points, or a skeleton TOML file")
    p.add_argument("--likelihood-threshold", type=float, default=defaults.likelihood_threshold, metavar="P",
                   help=f"ignore detections below this likelihood (default {defaults.likelihood_threshold:g})")
    p.add_argument("--min-views", type=int, default=defaults.min_views, metavar="K",
                   help="leave a marker's position NaN in frames fewer than K cameras see confidently (default "
                        f"{defaults.min_views}: fte and ekf answer every frame, from the motion model where fewer "
                        "than two cameras see it, flagged by ncams and a larger sd; 2: only triangulated positions)")
    p.add_argument("--swap-rate", type=_swap_rate, default=defaults.swap_rate, metavar="auto|P",
                   help="fte: the share of left/right pairs (l_eye/r_eye, Ear_L/Ear_R, LShoulder/RShoulder) the 2D "
                        "tracker swapped in a camera and frame; each pair is taken as labelled or swapped, whichever "
                        "the other cameras agree with, against these odds (default auto: estimated from the data; "
                        "0: every pair as labelled)")
    p.add_argument("--window-frames", type=int, default=None, metavar="N",
                   help="fte and ekf: solve a long run in windows keeping N frames each, in memory that does not "
                        f"grow with the run (default: windows of {WINDOW_FRAMES} frames for runs over "
                        f"{WINDOWED_ABOVE}; 0: the whole run at once)")
    p.add_argument("--measurement-std", default=str(defaults.measurement_std_px), metavar="PX|auto",
                   help=f"detection noise in pixels per coordinate (default {defaults.measurement_std_px:g}, the "
                        "paper's), or 'auto' to measure it from the data; the 3D uncertainties scale with it")
    p.add_argument("--motion-scale", default=None, metavar="S|auto|FILE",
                   help="multiplies the motion model's process noise (larger follows the data more), 'auto' to "
                        "fit it to the data (per marker for free points), or the report JSON or result H5 of a "
                        "run that fitted it, to use its scales (and their orders) without fitting again; default: "
                        "auto for fte on free points, else 1")
    p.add_argument("--motion-order", default=None, choices=["1", "2", "3", "auto"],
                   help="the motion prior's order: on the k-th differences of each coordinate, 3 (constant "
                        "acceleration, the default), 2, 1 (what aniposelib smooths), or 'auto' to choose it per "
                        "marker from the data (fte, with the motion scale fitted)")
    p.add_argument("--individual", default=None, metavar="NAME",
                   help="multi-animal files: solve this individual alone, trusting the 2D tracker's identities (a "
                        "SLEAP file's track name)")
    p.add_argument("--individuals", default=None, type=_positive_int, metavar="N",
                   help="multi-animal files: how many individuals (default: found); each camera's detections are "
                        "assigned to them by 3D geometry and motion, and each is solved and written as "
                        "OUT.<name>.csv")
    p.add_argument("--openpose-model", default=None, choices=["BODY_25", "BODY_25B", "COCO"],
                   help="OpenPose JSON folders: the model that wrote them, which names the keypoints (default: "
                        "kp0, kp1, ...; BODY_25 and BODY_25B both have 25 keypoints, in other orders)")
    p.add_argument("--calibration-units", choices=list(CALIBRATION_UNITS), default="auto",
                   help="units of the calibration's translations (default: auto, which recognises millimetres)")
    p.add_argument("--no-uncertainty", dest="uncertainty", action="store_false",
                   help="skip the per-marker standard deviations (fte: about a third faster)")
    p.add_argument("--bones", default=None, metavar="A-B,C-D",
                   help="points skeleton: soft bone-length terms between these bodypart pairs")
    p.add_argument("--body", default=defaults.body, metavar="model|estimate|FILE",
                   help="the animal's proportions: the skeleton's (model), estimated with the trajectory "
                        "(estimate), or a body estimated earlier: a report JSON or an H5 of this animal")
    p.add_argument("--sync", choices=["given", "estimate"], default=defaults.sync,
                   help="the cameras' clocks: as given (in sync, or --time-offsets) or estimated with the trajectory")
    p.add_argument("--time-offsets", default=None, metavar="T1,T2,...",
                   help="each camera's time offset in frames (camera frame n is at n + T), camera 1 the reference")


def _positive_int(text: str) -> int:
    """``--individuals``: a whole number of at least 1."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"takes a whole number, not {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, not {value}")
    return value


def _swap_rate(text: str) -> float | str:
    """``--swap-rate``: ``auto`` or a number (its range is the options' to check)."""
    if text.strip().lower() == "auto":
        return "auto"
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"takes a share such as 0.02, or 'auto', not {text!r}") from None


def _auto_option(text: str, option: str = "--measurement-std", unit: str = "a number of pixels"):
    """A positive number or ``auto`` (``--measurement-std``, ``--motion-scale``)."""
    if text.strip().lower() == "auto":
        return "auto"
    try:
        value = float(text)
    except ValueError:
        raise ValueError(f"{option} takes {unit} or 'auto', not {text!r}") from None
    if not value > 0:
        raise ValueError(f"{option} must be positive, not {text}")
    return value


def _body_option(text: str) -> tuple[Body, dict[str, float] | None]:
    """``--body``: ``model``, ``estimate``, or a file holding ``body_lengths`` (:func:`graph.io.results.read_body`)."""
    if text == "model":
        return "model", None
    if text == "estimate":
        return "estimate", None
    from graph.io.results import read_body

    return "given", read_body(text)


def _motion_options(scale: str | None, order: str | None):
    """``--motion-scale`` and ``--motion-order`` as SolveOptions values. A scale that is neither a
    number nor ``auto`` names an earlier run's report or result (:func:`graph.io.results.read_motion`): its
    scales per group, with the orders they were fitted for (an order given too must agree)."""
    given_order = None if order is None else ("auto" if order == "auto" else int(order))
    plain_order = 3 if given_order is None else given_order  # with a scale that is not a file's
    if scale is None:
        return None, plain_order
    if scale.strip().lower() == "auto" or _is_number(scale):
        return _auto_option(scale, "--motion-scale", "a positive number"), plain_order
    if not Path(scale).exists():
        raise ValueError(f"--motion-scale takes a positive number, 'auto', or the report JSON or result H5 of a run "
                         f"that fitted it; {scale!r} is none of these")
    from graph.io.results import given_motion

    return given_motion(scale, given_order)


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _offsets_option(text: str | None) -> list[float] | None:
    """``--time-offsets``: comma-separated frames, one per camera."""
    if text is None:
        return None
    try:
        return [float(v) for v in text.split(",")]
    except ValueError:
        raise ValueError(f"--time-offsets takes numbers of frames as 0,0.4,-1.2, not {text!r}") from None


def frame_rate(given: float | None, keypoints: list) -> tuple[float, str]:
    """The frame rate to solve at and where it came from: ``--fps`` when given (a warning when the
    keypoint files record another), else the one the files record (:attr:`Keypoints.fps`; every file
    that records one must agree). Neither: a :class:`UsageError`, for a frame rate assumed silently
    sets the motion model's scale wrong (on the fly's 300 fps recording, the 120 that was the default
    left the fitted smoothing at its bound)."""
    recorded = sorted({float(k.fps) for k in keypoints if getattr(k, "fps", None) is not None})
    if given is not None:
        if recorded and any(abs(r - given) > 1e-3 * given for r in recorded):
            warnings.warn(f"--fps {given:g} given, the keypoint files record {', '.join(f'{r:g}' for r in recorded)} "
                          "fps: solving at the --fps given", stacklevel=2)
        return float(given), "--fps"
    if not recorded:
        raise UsageError("--fps is required: the keypoint files record no frame rate (DeepLabCut's never do)")
    if len(recorded) > 1:
        raise UsageError(f"the keypoint files record different frame rates ({', '.join(f'{r:g}' for r in recorded)} "
                         "fps); give the cameras' with --fps")
    return recorded[0], "recorded in the keypoint files"


def solve_options(args: argparse.Namespace, fps: float | None = None):
    """The :class:`~graph.types.SolveOptions` of :func:`add_solve_options`'s arguments, at frame rate
    ``fps`` (default ``--fps``; a command that reads the keypoint files first settles it with
    :func:`frame_rate`); a :class:`UsageError` for a malformed one."""
    from graph.types import SolveOptions

    try:
        bones = None
        if args.bones:
            bones = [tuple(pair.split("-", 1)) for pair in args.bones.split(",") if pair.strip()]
            if any(len(b) != 2 or not all(b) for b in bones):
                raise ValueError("--bones takes pairs of bodyparts as A-B,C-D")
        std_px = _auto_option(args.measurement_std)
        motion, order = _motion_options(args.motion_scale, args.motion_order)
        body, lengths = _body_option(args.body)
        offsets = _offsets_option(args.time_offsets)
        rate = fps if fps is not None else args.fps
        if rate is None:  # checked here; settled by frame_rate() once the keypoint files are read
            rate = SolveOptions.fps
        options = SolveOptions(body=body, body_lengths=lengths, sync=args.sync, time_offsets=offsets,
                               method=args.method, fps=rate, skeleton=args.skeleton, measurement_std_px=std_px,
                               motion_scale=motion,
                               motion_order=order,
                               likelihood_threshold=args.likelihood_threshold, individual=args.individual,
                               individuals=args.individuals,
                               min_views=args.min_views, window_frames=args.window_frames, swap_rate=args.swap_rate,
                               calibration_units=args.calibration_units, bone_lengths=bones,
                               uncertainty=args.uncertainty)
    except ValueError as e:
        raise UsageError(str(e)) from None
    return options


def run_solve(args: argparse.Namespace) -> int:
    from graph.io.calibration import load_calibration
    from graph.io.keypoints import check_same_frames

    options = solve_options(args)
    for out in (args.out, args.h5, args.report):
        if out is not None and not Path(out).parent.is_dir():
            raise InputError("the output folder does not exist", out)

    calibration = load_calibration(args.calibration)
    if len(args.keypoints) != len(calibration):
        raise InputError(f"has {len(calibration)} cameras but {len(args.keypoints)} keypoint files "
                         "were given (one per camera, in the calibration's order)", args.calibration)
    from graph.io.keypoints import Keypoints

    if _streamable(args, options) and _solve_streamed(args, options, calibration):
        return 0
    if args.resume:
        raise UsageError("--resume goes on with a long run solved in windows (fte, one individual, no ensemble, no "
                         "--reprojections), and this one is not")
    cameras = read_inputs(args.keypoints, args.individual, args.individuals, args.openpose_model)
    if all(isinstance(c, Keypoints) for c in cameras):
        check_same_frames(cameras)
        fps, fps_from = frame_rate(args.fps, cameras)
        from graph import api

        prob = api.prepare(cameras, calibration, solve_options(args, fps))
        del cameras  # the problem holds the detections now: a long run's are not held twice
        result = _with_progress(lambda bar: api.solve_prepared(prob, progress=bar))
        written = write_outputs(args, result, calibration, Path(args.out))
        print(_summary(result.report, options, fps, fps_from) + f" -> {', '.join(map(str, written))}")
        return 0

    tracks = cameras
    check_same_frames(tracks)
    fps, fps_from = frame_rate(args.fps, tracks)
    options = solve_options(args, fps)
    solved = _solve_group(tracks, calibration, options)
    ids = solved.identities
    if len(ids.names) == 1:
        result = solved.results[0]
        written = write_outputs(args, result, calibration, Path(args.out), identity=ids.to_dict())
        print(_summary(result.report, options, fps, fps_from) + f" -> {', '.join(map(str, written))}")
        return 0
    switches = ", ".join(f"{cam} {n}" for cam, n in zip(ids.cameras, ids.switches))
    print(f"{len(ids.names)} individuals ({'found' if ids.found else 'given'}: {', '.join(ids.names)}); 2D identity "
          f"switches corrected per camera: {switches}")
    for name, result in zip(ids.names, solved.results):
        written = write_outputs(args, result, calibration, individual_path(Path(args.out), name), report=False,
                                individual=name)
        summary = _summary(result.report, options, fps, fps_from)
        print(f"{name}: {summary} -> {', '.join(map(str, written))}")
    if args.h5:
        from graph.io.results import write_group_h5

        write_group_h5(args.h5, list(zip(ids.names, solved.results)), calibration=calibration,
                       identity=ids.to_dict())
        print(f"{len(ids.names)} individuals (an individuals axis) -> {args.h5}")
    if args.report:
        _write_report(args.report, solved.report())
        print(f"report -> {args.report}")
    return 0


def _streamable(args: argparse.Namespace, options) -> bool:
    """Whether a long run may be solved streamed (:func:`_solve_streamed`): ``fte`` or ``ekf`` in
    windows, one individual, no ensemble, no reprojections asked for (they are written from the whole run)."""
    from graph.types import WINDOWED_METHODS

    return (options.method in WINDOWED_METHODS and options.window_frames != 0 and args.individual is None
            and args.individuals is None and not args.reprojections
            and not any(map(_is_ensemble, args.keypoints)))


# what a run solved streamed keeps in OUT.csv.partial/ until it is done
PARTIAL_ENTRIES = {"staged", "state.json", "state.json.part", "noise_sample.f64"}


def _solve_streamed(args: argparse.Namespace, options, calibration) -> bool:
    """A run over :data:`graph.types.WINDOWED_ABOVE` frames (or ``--window-frames``) solved in windows
    in memory that does not grow with it: each camera's file read in turn and staged in
    ``OUT.csv.partial/`` (:mod:`graph.io.staged`), each window read from there, and its kept frames
    written to the CSV (and the H5) as it finishes (:func:`graph.api.solve_streamed`), with where
    the run stands (``state.json``), so that ``--resume`` goes on from the last window finished.
    The folder is removed when the run is done. False when the run is not that long or a file holds
    several individuals: solve it in memory."""
    from graph.io.keypoints import read_blocks
    from graph.io.staged import StagedRun, stage
    from graph.types import WINDOWED_ABOVE

    out = Path(args.out)
    work = out.with_name(out.name + ".partial")
    state = None
    if args.resume:
        state = _stopped_run(work)
    elif work.exists():  # a stopped run's, started again: removed if it holds only what a run leaves
        if not work.is_dir() or not {p.name for p in work.iterdir()} <= PARTIAL_ENTRIES:
            raise InputError("is in the way of the run's working folder (it is not one a stopped run left: "
                             "move it, or give another --out)", work)
        shutil.rmtree(work)
    try:
        if state is not None:
            run = StagedRun.open(work / "staged")
        else:
            (work / "staged").mkdir(parents=True)
            above = options.window_frames or WINDOWED_ABOVE
            got = stage(args.keypoints, work / "staged",
                        lambda p: read_blocks(p, openpose_model=args.openpose_model), lambda frames: frames > above)
            if got is None:
                shutil.rmtree(work)
                return False
            run = got
            run.save()
        fps, fps_from = frame_rate(args.fps, run.cameras)
        options = solve_options(args, fps)
        inputs = _fingerprint(args, options, run.frames)
        if state is not None and state["inputs"] != inputs:
            raise InputError("the keypoint files, the calibration or the options are not the ones of the run that "
                             "stopped (run again without --resume)", work)
        report = _stream(args, options, calibration, run, work, inputs, state)
    except BaseException as e:
        if not (work / "state.json").exists():
            shutil.rmtree(work, ignore_errors=True)  # stopped before its first window: nothing to go on from
        elif not isinstance(e, (InputError, UsageError)):  # stopped (Ctrl-C, a worker lost, a full disk)
            try:
                done = _stopped_run(work)["windows"]["done"]
                print(f"{PROG}: stopped after {done} windows: acinoset solve ... --resume goes on from there",
                      file=sys.stderr)
            except InputError:
                pass
        raise
    shutil.rmtree(work)
    written: list = [_csv_label(out, report.unit)]
    if args.h5:
        written.append(args.h5)
    if args.report:
        _write_report(args.report, report.report.to_dict())
        written.append(args.report)
    print(_summary(report.report, options, fps, fps_from) + f" -> {', '.join(map(str, written))}")
    return True


class _Streamed(NamedTuple):
    report: "SolveReport"
    unit: str


def _stream(args: argparse.Namespace, options, calibration, run, work: Path, inputs: dict,
            state: dict | None) -> _Streamed:
    """:func:`graph.api.solve_streamed` of the staged ``run``, its windows written to the CSV and H5 as
    they finish and the run's state saved in ``work`` after each (``state``: a stopped run's, to go on from)."""
    from graph import api
    from graph.camera import CALIBRATION_UNITS
    from graph.io import results
    from graph.solve.problem import skeleton_of

    markers = skeleton_of([cam.bodyparts for cam in run.cameras], options).markers
    unit = csv_unit(args.units, calibration, options.calibration_units)
    csv = results.AniposeCsv(args.out, markers, metres_per_unit=CALIBRATION_UNITS[unit],
                             resume=None if state is None else tuple(state["csv"]))
    h5 = results.H5Stream(args.h5, run.frames, resume=None if state is None else state["h5"]) if args.h5 else None

    def write(core) -> None:
        csv.write(core.result)
        if h5 is not None:
            h5.write(core.result)

    def saved(solve_state: dict) -> None:
        doc = {"inputs": inputs, "csv": csv.position(), "h5": h5.flush() if h5 is not None else None, **solve_state}
        part = work / "state.json.part"
        part.write_text(json.dumps(doc), encoding="utf-8")
        os.replace(part, work / "state.json")

    try:
        report = _with_progress(lambda bar: api.solve_streamed(
            run, calibration, options, write, progress=bar, resume=state, saved=saved,
            sample_file=work / "noise_sample.f64", jobs=args.jobs))
    except BaseException:
        if h5 is not None:
            h5.file.close()
        raise
    finally:
        csv.close()
    if h5 is not None:
        h5.close(report, options, calibration)
    return _Streamed(report, unit)


def _stopped_run(work: Path) -> dict:
    """The state a stopped run saved in ``work`` (one line when there is none to go on from)."""
    try:
        state = json.loads((work / "state.json").read_text(encoding="utf-8"))
        if not isinstance(state, dict) or not {"inputs", "csv", "h5", "windows", "sums"} <= set(state):
            raise ValueError("not a run's state")
        csv, h5, windows = state["csv"], state["h5"], state["windows"]
        if not (isinstance(csv, list) and len(csv) == 2 and all(type(v) is int and v >= 0 for v in csv)
                and (h5 is None or (type(h5) is int and h5 >= 0)) and isinstance(windows, dict)
                and type(windows.get("done")) is int and isinstance(state["sums"], dict)):
            raise ValueError("a damaged state")
    except (OSError, ValueError) as e:
        raise InputError(f"no stopped run to go on from here ({type(e).__name__}: the run finished, was never "
                         "solved in windows, or stopped before its first window)", work) from None
    return state


def _fingerprint(args: argparse.Namespace, options, frames: int) -> dict:
    """What a stopped run must share with the one going on from it: the files (path, size, time
    modified), the options and the outputs asked for."""
    from graph.types import jsonable

    def stat(path: str) -> list:
        info = Path(path).stat()
        return [str(Path(path).resolve()), info.st_size, info.st_mtime_ns]

    return {"keypoints": [stat(p) for p in args.keypoints], "calibration": stat(args.calibration),
            "options": jsonable(options.to_dict()), "frames": frames, "units": args.units,
            "h5": None if args.h5 is None else str(Path(args.h5).resolve())}


def _is_ensemble(arg: str) -> bool:
    """Whether a camera argument is an ensemble's files joined by ``+`` (:func:`read_cameras`), not a
    file whose own name has one."""
    return "+" in arg and not Path(arg).exists()


def read_inputs(paths: list[str], individual: str | None, individuals: int | None,
                openpose_model: str | None) -> list:
    """Each camera's detections as a solve takes them: :class:`~graph.io.keypoints.Keypoints` for one
    individual (named, an ensemble's ``+``, or one slot in every file and no count given), else
    :class:`~graph.io.keypoint_types.Tracks` (:func:`graph.io.keypoints.read_recording`)."""
    if individual is not None or any(map(_is_ensemble, paths)):
        return read_cameras(paths, individual, openpose_model)
    from graph.io.keypoints import read_recording

    return read_recording(paths, individuals=individuals, openpose_model=openpose_model)


def individual_path(path: Path, name: str) -> Path:
    """``run.csv`` of individual ``name``: ``run.<name>.csv`` (:func:`safe_name`)."""
    return path.with_name(f"{path.stem}.{safe_name(name)}{path.suffix}")


def safe_name(name: str) -> str:
    """An individual's name as part of a file name (:func:`graph.io.results.safe_name`)."""
    from graph.io.results import safe_name as file_name_part

    return file_name_part(name, "individual")


def _solve_group(tracks: list, calibration, options):
    """Several individuals' solve (:func:`graph.api.solve_group`), with the progress bar and the compile
    note on a terminal."""
    from graph import api

    return _with_progress(lambda bar: api.solve_group(tracks, calibration, options, progress=bar))


def _with_progress(run):
    """``run(bar)`` with a progress bar on a terminal (None otherwise) and the compile note."""
    from graph.progress import ProgressBar, compile_notice

    bar = ProgressBar(sys.stderr) if sys.stderr.isatty() else None
    try:
        with compile_notice(lambda line: print(f"{PROG}: {line}", file=sys.stderr, flush=True)):
            return run(bar)
    finally:
        if bar is not None:
            bar.close()


def write_outputs(args: argparse.Namespace, result, calibration, out: Path, report: bool = True,
                  individual: str | None = None, identity: dict | None = None) -> list:
    """The CSV at ``out`` and what ``--h5``, ``--report`` (when ``report``) and ``--reprojections`` ask
    for; an ``individual``'s CSV and reprojections are named after it (the H5 of several is one file with
    an individuals axis: :func:`graph.io.results.write_group_h5`). The paths written."""
    from graph.camera import CALIBRATION_UNITS
    from graph.io import results

    unit = csv_unit(args.units, calibration, result.options.calibration_units)
    written: list = [_csv_label(out, unit)]
    results.write_anipose_csv(out, result, metres_per_unit=CALIBRATION_UNITS[unit])
    if args.h5 and individual is None:  # several individuals go in one file, after them all
        results.write_h5(args.h5, result, calibration=calibration)
        written.append(args.h5)
    if args.report and report:
        doc = result.report.to_dict()
        if identity is not None:
            doc["identity"] = identity
        _write_report(args.report, doc)
        written.append(args.report)
    if args.reprojections:
        stems = [f"{Path(p.split('+')[0] if not Path(p).exists() else p).stem}_reprojected" for p in args.keypoints]
        where = Path(args.reprojections) if individual is None else Path(args.reprojections) / safe_name(individual)
        results.write_reprojections_dlc(where, result, stems=stems)
        written.append(where)
    return written


def csv_unit(units: str, calibration, calibration_units: str) -> str:
    """``--units`` as the CSV's unit (``m``, ``cm`` or ``mm``: metres per unit in
    :data:`graph.camera.CALIBRATION_UNITS`): the calibration's own for ``auto`` (as the solve took
    them, given ``calibration_units``)."""
    from graph.io.calibration import resolve_units

    return resolve_units(calibration, calibration_units)[0] if units == "auto" else units


def _csv_label(out: Path, unit: str) -> str | Path:
    """The CSV as the summary line names it: with its unit when not metres."""
    return out if unit == "m" else f"{out} (in {unit})"


def _write_report(path: str, doc) -> None:
    """``--report``: the report as indented JSON."""
    Path(path).write_text(json.dumps(doc, indent=2) + "\n", encoding="utf-8")


def _summary(rep, options, fps: float, fps_from: str) -> str:
    """The one line a solve prints, of its report ``rep``."""
    rmse = "n/a" if rep.reprojection_rmse_px != rep.reprojection_rmse_px else f"{rep.reprojection_rmse_px:.2f} px"
    noise = f", detection noise {rep.sigma_px:.2f} px (measured)" if options.measurement_std_px == "auto" else ""
    if rep.motion_scales:
        v = sorted(rep.motion_scales.values())
        noise += (f", motion scale {v[0]:.3g} (fitted)" if len(v) == 1 else
                  f", motion scales {v[0]:.3g}-{v[-1]:.3g} (fitted, median {v[len(v) // 2]:.3g})")
    if rep.motion_orders and options.motion_order == "auto":
        counts = {k: list(rep.motion_orders.values()).count(k) for k in sorted(set(rep.motion_orders.values()))}
        noise += ", motion order " + ", ".join(f"{k} for {n}" for k, n in counts.items())
    return (f"{rep.method}: {rep.frames} frames, {rep.cameras} cameras, {rep.markers} markers, {fps:g} fps "
            f"({fps_from}), reprojection RMSE {rmse}{noise}, {rep.seconds.get('total', 0.0):.2f} s")


if __name__ == "__main__":  # ``python -m graph.app.cli``: the library's commands, from the module proper
    from graph.app.cli import main as library_main

    sys.exit(library_main())
