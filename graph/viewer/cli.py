"""``acinoset plot``: the figures and the playback file of a solved run, or one camera's frame with the
estimate drawn on it."""

from __future__ import annotations

import argparse
from pathlib import Path

from graph.errors import InputError
from graph.io.calibration import load_calibration
from graph.io.results import read_results, safe_name
from graph.types import Result
from graph.viewer.figures import write_figures
from graph.viewer.playback import HTML_NAME, write_playback_html


def register(subparsers) -> None:
    """Add ``acinoset plot RESULT.h5 --out DIR``."""
    p = subparsers.add_parser(
        "plot",
        description="Write PNG figures (skeleton with cameras, reprojection error per marker and "
                    "camera, coordinates and pose parameters over time with uncertainty, flagged "
                    f"frames) and {HTML_NAME}, a self-contained 3D playback that opens offline.")
    p.add_argument("result", type=Path, nargs="+", metavar="RESULT.h5",
                   help="RESULT.h5 written by `acinoset solve --h5`; several individuals solved together (its "
                        "individuals axis, or one file each): the figures of each in a folder of its name, one "
                        "playback of all")
    p.add_argument("--out", type=Path, required=True, help="folder to write the pictures into")
    p.add_argument("--calibration", type=Path, default=None,
                   help="calibration file, to draw the cameras when the result file holds no camera positions")
    p.add_argument("--snapshots", type=int, default=5, help="frames drawn in skeleton.png (default 5)")
    p.add_argument("--no-html", action="store_true", help=f"PNG figures only, no {HTML_NAME}")
    pick = p.add_argument_group("frame picker", "one camera's video frame with the estimate drawn on it, as a PNG "
                                "(instead of the figures; needs the 'video' extra)")
    pick.add_argument("--frame", type=int, default=None, metavar="N", help="the frame (counting from 0)")
    pick.add_argument("--camera", default=None, metavar="K", help="the camera: its number (from 1) or its name")
    pick.add_argument("--video", type=Path, default=None, metavar="CAM.mp4", help="that camera's video")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    for path in args.result:
        if not Path(path).is_file():
            raise InputError("no such file", path)
    if args.snapshots < 1:
        raise InputError("--snapshots must be at least 1")
    if Path(args.out).exists() and not Path(args.out).is_dir():
        raise InputError("--out must be a folder, and this is a file", args.out)

    group = [named for path in args.result for named in read_results(path)]
    picking = args.frame is not None or args.camera is not None or args.video is not None
    if picking and len(group) > 1:
        raise InputError("the frame picker draws one result: give one RESULT.h5 of one individual")
    calibration = None
    if args.calibration is not None:
        calibration = load_calibration(args.calibration)
    if len(group) == 1:
        result = group[0][1]
        if picking:
            print(_pick_frame(result, args))
            return 0
        written = write_figures(result, args.out, calibration, snapshots=args.snapshots)
        if not args.no_html:
            written.append(write_playback_html(result, Path(args.out) / HTML_NAME, calibration))
    else:
        written = []
        for name, result in group:
            written += write_figures(result, Path(args.out) / safe_name(name, "individual"), calibration,
                                     snapshots=args.snapshots)
        if not args.no_html:
            written.append(write_playback_html(group, Path(args.out) / HTML_NAME, calibration))
    for p in written:
        print(p)
    return 0


def _pick_frame(result: Result, args: argparse.Namespace) -> Path:
    """``--frame N --camera K --video CAM.mp4``: ``<camera>_frame<N>.png`` in ``--out``."""
    if args.frame is None or args.camera is None or args.video is None:
        raise InputError("the frame picker needs all of --frame N, --camera K and --video CAM.mp4")
    names = list(result.camera_names)
    if args.camera in names:
        camera = names.index(args.camera)
    else:
        try:
            camera = int(args.camera) - 1
        except ValueError:
            raise InputError(f"--camera {args.camera}: not a camera number or one of {', '.join(names)}") from None
    if not Path(args.video).is_file():
        raise InputError("no such video file", args.video)
    from graph.video import camera_frame_png

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    name = names[camera] if 0 <= camera < len(names) else f"camera{camera + 1}"
    return camera_frame_png(result, camera, args.video, args.frame, out / f"{name}_frame{args.frame}.png")
