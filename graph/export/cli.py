"""``acinoset export RESULT.h5 --format nwb|trc|c3d|csv-var --out FILE``."""

from __future__ import annotations

import argparse

FORMAT_HELP = ("nwb: NWB with ndx-pose (needs acinoset[export]); trc: OpenSim TRC; c3d: C3D (needs "
               "acinoset[export]); csv-var: EKS's 3D CSV with posterior variances")


def register(sub) -> None:
    from graph.export import FORMATS  # light: no optional library is imported here

    p = sub.add_parser("export", description="Write a solved run (the H5 of acinoset solve --h5, or of a "
                       "job) in a format other tools read. " + FORMAT_HELP)
    p.add_argument("result", metavar="RESULT.h5", help="result file written by acinoset solve --h5")
    p.add_argument("--format", required=True, choices=FORMATS)
    p.add_argument("--out", required=True, metavar="FILE")
    p.add_argument("--calibration", default=None, metavar="FILE",
                   help="the rig solved with, if the result file does not hold it (older files)")
    p.add_argument("--axes", default=None, metavar="opensim|x,z,-y",
                   help="trc: output axes as signed world axes; 'opensim' turns a z-up world y-up")
    p.add_argument("--units", default=None, choices=["m", "mm"],
                   help="trc (default m) and c3d (default mm): length unit of the file")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from graph.app.cli import UsageError
    from graph.export import export

    options = {}
    if args.axes is not None:
        if args.format != "trc":
            raise UsageError("--axes applies to --format trc only")
        options["axes"] = args.axes
    if args.units is not None:
        if args.format not in ("trc", "c3d"):
            raise UsageError("--units applies to --format trc and c3d only")
        options["units"] = args.units
    try:
        out = export(args.result, args.format, args.out, calibration=args.calibration, **options)
    except ValueError as e:
        if type(e) is not ValueError:
            raise
        raise UsageError(str(e)) from None
    print(f"{args.format}: {args.result} -> {out}")
    return 0
