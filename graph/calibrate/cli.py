"""``acinoset calibrate intrinsics|extrinsics|refine``: the command line of :mod:`graph.calibrate`.

::

    acinoset calibrate intrinsics SOURCE --board SPEC [--model fisheye|pinhole] --out CAMERA.json [--report R.json]
    acinoset calibrate extrinsics SOURCE1 SOURCE2 ... --board SPEC [--intrinsics CAM1.json ...]
            [--model fisheye|pinhole] --out calibration.toml [--scene scene.json]
            [--origin camera1|board:FRAME] [--report R.json] [--figures DIR]
    acinoset calibrate refine CALIBRATION KEYPOINTS1 KEYPOINTS2 ... --out calibration.toml [--report R.json]

A SOURCE is a video (``--every N``), a folder of images or a detections JSON, in camera order.
"""

from __future__ import annotations

import argparse
import json
import sys
import warnings
from pathlib import Path

import numpy as np

from graph.calibrate.model import LENSES, lens_with_intrinsics
from graph.camera import CAMERA_MODELS, FISHEYE
from graph.errors import InputError


def register(sub) -> None:
    p = sub.add_parser("calibrate", description="Calibrate cameras from views of a board (a checkerboard or a "
                       "ChArUco board), or refine a rig from an animal's keypoints.")
    cmds = p.add_subparsers(dest="calibrate_command", metavar="STEP")
    board_help = ("checkerboard:COLSxROWS:SQUARE_M (inner corners, square side in metres) or "
                  "charuco:SQUARESXxSQUARESY:SQUARE_M:MARKER_M:DICT")

    def sources(q, many: bool):
        q.add_argument("sources", nargs="+" if many else None, metavar="SOURCE" if not many else "SOURCES",
                       help="a video, a folder of images or a detections JSON" + (", one per camera in order"
                                                                                 if many else ""))
        q.add_argument("--board", required=True, metavar="SPEC", help=board_help)
        q.add_argument("--model", choices=list(CAMERA_MODELS), default=FISHEYE,
                       help="camera model (default fisheye: OpenCV's 4 coefficients)")
        q.add_argument("--lens", choices=list(LENSES), default="full",
                       help="what of the lens is fitted: full (default), every coefficient of the model; k1, "
                       "Anipose's: one focal length, the principal point at the image's centre and radial k1 "
                       "alone")
        q.add_argument("--every", type=int, default=1, metavar="N", help="use every N-th frame of a video")
        q.add_argument("--no-cache", action="store_true", help="detect again even when a cache matches")
        q.add_argument("--report", metavar="R.json", help="write the quality report here")

    q = cmds.add_parser("intrinsics", help="one camera's intrinsics", description="One camera's intrinsics "
                        "from its board views; writes AcinoSet's camera JSON (camera_resolution, k, d).")
    sources(q, many=False)
    q.add_argument("--out", required=True, metavar="CAMERA.json")
    q.set_defaults(func=run_intrinsics)

    for step, helptext in (("extrinsics", "a rig from board views the cameras share"),
                           ("rig", "the same: a whole rig from each camera's board footage, in one command")):
        q = cmds.add_parser(step, help=helptext,
                            description="The rig from board views seen by several cameras at the same frames (matched "
                            "by the last number in each view's name, a video's by frame index): each camera's "
                            "intrinsics from its own views unless given, then one bundle adjustment of camera and "
                            "board poses.")
        _rig_options(q, sources)
    _register_refine(cmds)


def _rig_options(q, sources) -> None:
    sources(q, many=True)
    q.add_argument("--names", metavar="A,B,...", help="the cameras' names in calibration.toml, in order "
                   "(default cam1, cam2, ...)")
    q.add_argument("--intrinsics", nargs="+", metavar="CAM.json",
                   help="each camera's intrinsics (AcinoSet camera JSON); calibrated from the views if not given")
    q.add_argument("--refine-intrinsics", action="store_true",
                   help="refine the intrinsics too, under the prior their own calibration gives them")
    q.add_argument("--out", required=True, metavar="calibration.toml", help="Anipose calibration.toml")
    q.add_argument("--scene", metavar="scene.json", help="also write AcinoSet's scene JSON (fisheye only)")
    q.add_argument("--origin", default="camera1", metavar="camera1|board:FRAME",
                   help="the world frame: camera 1 (default) or the board of view FRAME (origin at its first "
                   "corner, z up)")
    q.add_argument("--figures", metavar="DIR", help="write PNG figures here (rig, residuals, coverage)")
    q.set_defaults(func=run_extrinsics)


def _register_refine(cmds) -> None:
    q = cmds.add_parser("refine", help="refine a rig's extrinsics from an animal's keypoints",
                        description="Refine the cameras' poses (and optionally focal lengths and k1) from "
                        "confident keypoints, jointly with their 3D positions; a camera that is far off is "
                        "first posed again from the others' points; keeps the old rig when "
                        "leave-one-camera-out reprojection on held-out frames says the new one is not better.")
    q.add_argument("calibration", metavar="CALIBRATION", help="calibration.toml or AcinoSet scene JSON")
    q.add_argument("keypoints", nargs="+", metavar="KEYPOINTS",
                   help="keypoints, one file per camera (DeepLabCut CSV or H5, SLEAP .slp or analysis H5, ...)")
    q.add_argument("--out", required=True, metavar="calibration.toml")
    q.add_argument("--report", metavar="R.json")
    q.add_argument("--likelihood", type=float, default=0.9, help="keypoints at least this confident (default 0.9)")
    q.add_argument("--refine-intrinsics", default="", metavar="focal,k1",
                   help="also refine each camera's focal length (one scale for fx and fy) and/or first "
                   "distortion coefficient, under a prior centred on the calibration's values")
    q.add_argument("--focal-sd", type=float, default=0.02,
                   help="the focal prior's sd, relative (default 0.02: two board calibrations of one camera "
                   "differ by up to 2 %%)")
    q.add_argument("--k1-sd", type=float, default=0.02, help="the k1 prior's sd (default 0.02)")
    q.add_argument("--hold", metavar="CAMERA",
                   help="the camera whose pose, with its distance to the next, keeps the old rig's world frame and "
                   "scale (default: the first camera not posed again)")
    q.add_argument("--pose-sd", type=float, default=1.0, metavar="DEG",
                   help="the poses' prior sd in degrees (the position's: that angle at the camera's distance to the "
                   "animal); a camera the keypoints would move beyond 3 sd is held and reported (default 1; 0: no "
                   "prior, nothing held)")
    q.add_argument("--individual", help="multi-animal DeepLabCut: the individual to use")
    q.set_defaults(func=run_refine)


def _progress_bar():
    """A callback ``(stage, fraction)`` drawing the library's progress bar on a terminal (else None)."""
    if not sys.stderr.isatty():
        return None, None
    from graph.progress import ProgressBar
    from graph.types import Progress

    bar = ProgressBar(sys.stderr)
    return (lambda stage, fraction: bar(Progress(stage, fraction))), bar


def _load_sources(paths: list[str], board, every: int, cache: bool, names: list[str] | None = None) -> list:
    from graph.calibrate.detect import detect_views

    report, bar = _progress_bar()
    out = []
    try:
        for k, src in enumerate(paths):
            name = names[k] if names else f"cam{k + 1}" if len(paths) > 1 else Path(src).stem
            step = (lambda done, total, k=k, src=src: report(f"detect {Path(src).name}", (k + done / max(total, 1))
                                                             / len(paths))) if report else None
            out.append(detect_views(src, board, every=every, cache=cache, progress=step, name=name))
    finally:
        if bar:
            bar.close()
    return out


def _write_json(path: str, doc: dict) -> None:
    Path(path).write_text(json.dumps(doc, indent=2, default=_jsonable) + "\n", encoding="utf-8")


def _jsonable(o):
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    raise TypeError(type(o).__name__)


def run_intrinsics(args: argparse.Namespace) -> int:
    from graph.calibrate import calibrate_intrinsics, parse_board

    board = parse_board(args.board)
    _warn_mm(board)
    (views,) = _load_sources([args.sources], board, args.every, not args.no_cache)
    result = calibrate_intrinsics(views, board, args.model, args.lens)
    doc = result.to_dict()
    camera = {k: doc[k] for k in ("camera_resolution", "k", "d", "model", "rms_px")}
    _write_json(args.out, camera)
    if args.report:
        _write_json(args.report, doc)
    print(f"intrinsics {views.name}: RMS {result.rms_px:.3f} px over {len(result.views_used)} views "
          f"({len(result.views_dropped)} dropped), coverage {result.coverage * 100:.0f} % -> {args.out}")
    for f, why in result.views_dropped.items():
        print(f"  dropped {f}: {why}")
    return 0


def _warn_mm(board) -> None:
    if board.looks_like_mm():
        warnings.warn(f"the board's square is {board.square:g} m: is it given in millimetres? "
                      "Board lengths are in metres")


def run_extrinsics(args: argparse.Namespace) -> int:
    from graph.calibrate import calibrate_extrinsics, parse_board
    from graph.io.calibration import write_acinoset_json, write_anipose_toml
    from graph.io.cameras import load_camera_json

    board = parse_board(args.board)
    intrinsics = None
    if args.intrinsics:
        if len(args.intrinsics) != len(args.sources):
            raise InputError(f"{len(args.intrinsics)} --intrinsics files for {len(args.sources)} sources")
        intrinsics = [load_camera_json(p) for p in args.intrinsics]
        if args.refine_intrinsics:
            raise InputError("--refine-intrinsics needs the intrinsics calibrated here (their uncertainty is "
                             "the prior): leave out --intrinsics")
        if why := lens_with_intrinsics(args.lens):
            raise InputError(f"--{why}")
    names = _camera_names(args.names, len(args.sources))
    views = _load_sources(args.sources, board, args.every, not args.no_cache, names)
    report, bar = _progress_bar()
    try:
        result = calibrate_extrinsics(views, board, intrinsics, model=args.model, origin=args.origin,
                                      refine_intrinsics=args.refine_intrinsics, progress=report, lens=args.lens)
    finally:
        if bar:
            bar.close()
    write_anipose_toml(args.out, result.calibration)
    written = [args.out]
    if args.scene:
        try:
            write_acinoset_json(args.scene, result.calibration)
        except ValueError as e:
            raise InputError(f"--scene: {e}", args.scene) from None
        written.append(args.scene)
    if args.report:
        _write_json(args.report, result.to_dict())
        written.append(args.report)
    if args.figures:
        from graph.calibrate.report import write_figures

        write_figures(result, args.figures, board)
        written.append(args.figures)
    dropped = sum(len(c.views_dropped) for c in result.cameras)
    print(f"extrinsics: {len(views)} cameras, {len(result.frames_used)} shared frames, RMS {result.rms_px:.3f} px "
          f"({dropped} views dropped), {result.seconds:.2f} s -> {', '.join(written)}")
    for c in result.cameras:
        print(f"  {c.name}: RMS {c.rms_px:.3f} px, {c.views_used} views, position sd "
              f"{max(c.position_std_mm):.2f} mm, rotation sd {max(c.rotation_std_deg):.3f} deg")
    return 0


def _camera_names(text: str | None, count: int) -> list[str] | None:
    """``--names A,B,...``: one distinct, non-empty name per source."""
    if text is None:
        return None
    names = [n.strip() for n in text.split(",")]
    if len(names) != count or not all(names) or len(set(names)) != count:
        raise InputError(f"--names: {count} distinct names, one per source, separated by commas (got {text!r})")
    return names


def run_refine(args: argparse.Namespace) -> int:
    from graph.calibrate.refine import run

    return run(args)
