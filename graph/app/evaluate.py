"""``acinoset evaluate``: judge a 3D method on a recording of one's own rig, without 3D truth.

``acinoset evaluate loco CAM1.csv CAM2.csv CAM3.csv ... --calibration FILE [solve options] [--json OUT]``
reconstructs from every set of all cameras but one, projects into the camera left out and compares
with its confident detections (:func:`graph.metrics.leave_one_camera_out`): the median and 90th
percentile of that pixel error, per camera and over all, for the solve options given. Each held-out
camera is judged against the detections it was given, and the output says so: an ensemble's
(``CAM_a.csv+CAM_b.csv``) are its members' median with their mean likelihood, so its scores are not
those of a comparison judged against one member's detections (``bench/bench_fly_loco.py`` judges
every row against member 1).

``--versus "OPTIONS"`` (repeatable) scores the same recording again with those solve options
changed (``--versus "--motion-order 1"``) and gives each one's difference from the first with its
95 % interval (:func:`graph.metrics.loco_difference`): whether a setting is better on this rig, or
within what the recording can tell apart.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from graph.errors import InputError


def register(sub) -> None:
    """``acinoset evaluate`` and its subcommands."""
    from graph.app.cli import KEYPOINTS_HELP, add_solve_options
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
    loco.add_argument("--versus", action="append", default=[], metavar='"OPTIONS"',
                      help='score again with these solve options changed (e.g. "--motion-order 1"; repeatable) '
                           "and give the difference from the first, with its 95%% interval")
    loco.add_argument("--json", default=None, metavar="OUT.json", help="also write the scores as JSON")
    loco.set_defaults(func=run_loco)


def _variant(args: argparse.Namespace, text: str, keypoints: list):
    """The solve options of ``args`` with those in ``text`` (a --versus value) changed, at the frame rate
    :func:`graph.app.cli.frame_rate` settles for them and ``keypoints``."""
    import copy
    import shlex

    from graph.app.cli import UsageError, add_solve_options, frame_rate, solve_options

    parser = argparse.ArgumentParser(prog=f"--versus {text!r}", add_help=False, exit_on_error=False)
    add_solve_options(parser)
    try:
        words = shlex.split(text)
        changed, rest = parser.parse_known_args(words, namespace=copy.copy(args))
    except (ValueError, argparse.ArgumentError) as e:
        raise UsageError(f"--versus {text!r}: {e}") from None
    if rest or not words:
        raise UsageError(f"--versus {text!r}: give solve options to change, such as \"--motion-order 1\""
                         + (f" ({' '.join(rest)} is not one)" if rest else ""))
    return solve_options(changed, frame_rate(changed.fps, keypoints)[0])


def _table(score) -> None:
    """The score per held-out camera and over all; what a reconstruction warned of, after it.
    ``in 90 %``: the share of the judged detections inside the 90 % prediction ellipse the
    reconstruction's own uncertainty gives (honest: about 0.9)."""
    share = lambda v: f"{v:9.3f}" if v is not None else f"{'-':>9}"  # noqa: E731
    print(f"  {'camera':<16} {'median px':>10} {'p90 px':>10} {'judged':>8} {'coverage':>9} {'in 90 %':>9} "
          f"{'seconds':>8}")
    for c in score.cameras:
        print(f"  {c.camera:<16} {c.median_px:10.3f} {c.p90_px:10.3f} {c.count:8d} {c.coverage:9.3f} "
              f"{share(c.within_90)} {c.seconds:8.2f}")
    print(f"  {'all':<16} {score.median_px:10.3f} {score.p90_px:10.3f} {score.count:8d} {score.coverage:9.3f} "
          f"{share(score.within_90)} {score.seconds:8.2f}", flush=True)
    for c in score.cameras:
        for w in c.warnings:
            print(f"acinoset: warning: {c.camera} held out: {w}", file=sys.stderr)


def _judged(keypoints: list) -> str:
    """What each held-out camera is scored against: the detections it was given. An ensemble's
    (``CAM_a.csv+CAM_b.csv``) are those :func:`graph.solve.ensemble.combine` makes of its members."""
    if any(k.spread_px is not None for k in keypoints):
        return ("judged against: each held-out camera's detections as given; an ensemble's are its members' "
                "median position with their mean likelihood, not one member's")
    return "judged against: each held-out camera's detections in the files given"


def run_loco(args: argparse.Namespace) -> int:
    from graph.app.cli import UsageError, frame_rate, read_cameras, solve_options
    from graph.io.calibration import load_calibration
    from graph.metrics import leave_one_camera_out, loco_difference
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
    keypoints = read_cameras(args.keypoints, args.individual, args.openpose_model)
    fps, fps_from = frame_rate(args.fps, keypoints)
    options = solve_options(args, fps)
    variants = [(text, _variant(args, text, keypoints)) for text in args.versus]
    say = (lambda text: print(f"  {text}", file=sys.stderr, flush=True)) if sys.stderr.isatty() else None
    score = leave_one_camera_out(keypoints, calibration, options, confidence=args.confidence, progress=say)
    for note in score.notes:
        print(f"acinoset: note: {note}", file=sys.stderr)
    print(f"leave one camera out, {score.method} at {fps:g} fps ({fps_from}), detections of likelihood >= "
          f"{score.confidence:g}:")
    print(f"  {_judged(keypoints)}")
    _table(score)
    versus = []
    for text, other in variants:
        if say:
            say(f"versus {text}")
        theirs = leave_one_camera_out(keypoints, calibration, other, confidence=args.confidence, progress=say)
        d = loco_difference(score, theirs)
        print(f"versus {text}:")
        _table(theirs)
        few = "; few blocks: the intervals are too narrow" if d.blocks < 30 else ""
        (m0, m1), (q0, q1) = d.median_interval, d.p90_interval
        print(f"  minus the first: median {d.median_px:+.3f} px [{m0:+.3f}, {m1:+.3f}], p90 {d.p90_px:+.3f} px "
              f"[{q0:+.3f}, {q1:+.3f}] (95 %, {d.blocks} blocks of {d.block_frames} frames{few})")
        versus.append({"versus": text, "options": other.to_dict(), **theirs.to_dict(), "difference": d.to_dict()})
    if args.json:
        doc = {"options": options.to_dict(), "keypoints": [str(p) for p in args.keypoints],
               "calibration": str(args.calibration), **score.to_dict(), "versus": versus}
        Path(args.json).write_text(json.dumps(jsonable(doc), indent=2) + "\n", encoding="utf-8")
        print(f"  -> {args.json}")
    return 0
