"""``acinoset evaluate``: judge a 3D method on a recording of one's own rig, without 3D truth.

``acinoset evaluate loco CAM1.csv CAM2.csv CAM3.csv ... --calibration FILE [solve options] [--json OUT]``
reconstructs from every set of all cameras but one, projects into the camera left out and compares
with its confident detections (:func:`graph.metrics.leave_one_camera_out`): the median and 90th
percentile of that pixel error, per camera and over all, for the solve options given.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from graph.errors import InputError


def register(sub) -> None:
    """``acinoset evaluate`` and its subcommands."""
    from graph.cli import KEYPOINTS_HELP, add_solve_options
    from graph.metrics import LOCO_CONFIDENCE

    p = sub.add_parser("evaluate", description="Score a 3D method on a recording without 3D truth.")
    kinds = p.add_subparsers(dest="evaluation", metavar="EVALUATION")
    loco = kinds.add_parser("loco", help="leave one camera out: predict each camera's confident detections "
                            "from the others", description="For each camera: reconstruct from the other cameras "
                            "with the solve options given, project into it and compare with its detections of "
                            "likelihood at least --confidence. Needs three or more cameras.")
    loco.add_argument("keypoints", nargs="+", metavar="CAM.csv", help=KEYPOINTS_HELP)
    loco.add_argument("--calibration", required=True, metavar="FILE",
                      help="Anipose calibration.toml or AcinoSet scene JSON")
    add_solve_options(loco)
    loco.add_argument("--confidence", type=float, default=LOCO_CONFIDENCE, metavar="P",
                      help=f"judge the held-out detections of at least this likelihood (default {LOCO_CONFIDENCE:g})")
    loco.add_argument("--json", default=None, metavar="OUT.json", help="also write the scores as JSON")
    loco.set_defaults(func=run_loco)


def run_loco(args: argparse.Namespace) -> int:
    from graph.calibration import load_calibration
    from graph.cli import UsageError, read_cameras, solve_options
    from graph.metrics import leave_one_camera_out
    from graph.types import jsonable

    options = solve_options(args)
    if not 0.0 <= args.confidence <= 1.0:
        raise UsageError(f"--confidence must be in [0, 1], not {args.confidence:g}")
    if args.json is not None and not Path(args.json).parent.is_dir():
        raise InputError("the output folder does not exist", args.json)
    calibration = load_calibration(args.calibration)
    if len(args.keypoints) != len(calibration):
        raise InputError(f"has {len(calibration)} cameras but {len(args.keypoints)} keypoint files "
                         "were given (one per camera, in the calibration's order)", args.calibration)
    keypoints = read_cameras(args.keypoints, args.individual)
    say = (lambda text: print(f"  {text}", file=sys.stderr, flush=True)) if sys.stderr.isatty() else None
    score = leave_one_camera_out(keypoints, calibration, options, confidence=args.confidence, progress=say)
    for note in score.notes:
        print(f"acinoset: note: {note}", file=sys.stderr)
    print(f"leave one camera out, {score.method}, detections of likelihood >= {score.confidence:g}:")
    print(f"  {'camera':<16} {'median px':>10} {'p90 px':>10} {'judged':>8} {'coverage':>9} {'seconds':>8}")
    for c in score.cameras:
        print(f"  {c.camera:<16} {c.median_px:10.3f} {c.p90_px:10.3f} {c.count:8d} {c.coverage:9.3f} {c.seconds:8.2f}")
    print(f"  {'all':<16} {score.median_px:10.3f} {score.p90_px:10.3f} {score.count:8d} {score.coverage:9.3f} "
          f"{score.seconds:8.2f}")
    if args.json:
        doc = {"options": options.to_dict(), "keypoints": [str(p) for p in args.keypoints],
               "calibration": str(args.calibration), **score.to_dict()}
        Path(args.json).write_text(json.dumps(jsonable(doc), indent=2) + "\n", encoding="utf-8")
        print(f"  -> {args.json}")
    return 0
