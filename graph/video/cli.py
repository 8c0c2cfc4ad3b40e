"""``acinoset video RESULT.h5 [MORE.h5 ...] --videos CAM1.mp4 ... --out DIR [--frames A:B] [--combined]``:
several results are several individuals solved together, drawn in colours of their own."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from graph.errors import InputError
from graph.progress import FrameProgress

AXES = {"x": (1, 0, 0), "-x": (-1, 0, 0), "y": (0, 1, 0), "-y": (0, -1, 0), "z": (0, 0, 1), "-z": (0, 0, -1)}


def register(sub) -> None:
    p = sub.add_parser(
        "video",
        description="Draw a solved run over each camera's own video: the DeepLabCut detections (disc size by "
                    "likelihood, outliers crossed) and the estimate reprojected as the skeleton's bones. Also "
                    "writes 3d.mp4, a 3D view of the skeleton and the cameras, and with --combined one grid of "
                    "every view. H.264 MP4 (yuv420p) at the videos' size, rate and frame count; frames where a "
                    "camera has no estimate are left as they are. The cameras' time offsets of the solve are "
                    "honoured when the grid matches their frames.")
    p.add_argument("result", type=Path, nargs="+", metavar="RESULT.h5",
                   help="RESULT.h5 written by `acinoset solve --h5`; several individuals solved together (its "
                        "individuals axis, or one file each): drawn each in its own colour")
    p.add_argument("--videos", nargs="+", required=True, metavar="CAM.mp4",
                   help="one video per camera, in the result's camera order (the videos the keypoints came from)")
    p.add_argument("--out", type=Path, required=True, help="folder to write the videos into")
    p.add_argument("--frames", default=None, metavar="A:B", help="only frames A to B-1 (default: all)")
    p.add_argument("--combined", action="store_true", help="also write combined.mp4: every view in one grid")
    p.add_argument("--up", choices=list(AXES), default="z", help="the world's up axis for the 3D view (default z)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from graph.io.results import read_results
    from graph.video import render_videos

    for path in args.result:
        if not Path(path).is_file():
            raise InputError("no such file", path)
    for v in args.videos:
        if not Path(v).is_file():
            raise InputError("no such video file", v)
    if Path(args.out).exists() and not Path(args.out).is_dir():
        raise InputError("--out must be a folder, and this is a file", args.out)
    results = [named for path in args.result for named in read_results(path)]  # a group file: all in it
    bar = FrameProgress(sys.stderr) if sys.stderr.isatty() else None
    try:
        done = render_videos(results[0][1] if len(results) == 1 else results, args.videos, args.out,
                             frames=args.frames, combined=args.combined,
                             up=np.array(AXES[args.up], dtype=float), progress=bar)
    finally:
        if bar is not None:
            bar.close()
    shift = "" if not any(done.offsets_frames) else \
        f", cameras' offsets {', '.join(str(k) for k in done.offsets_frames)} frames"
    print(f"{done.frames} frames x {len(done.cameras)} cameras at {done.fps:g} fps in {done.seconds:.1f} s "
          f"({done.camera_frames_per_second:.0f} camera-frames/s{shift}) -> "
          f"{', '.join(str(p) for p in done.paths)}")
    return 0
