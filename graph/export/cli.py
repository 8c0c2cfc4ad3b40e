"""``acinoset export RESULT.h5 --format FORMAT --out FILE``: the formats, their help and
which of them take ``--axes`` and ``--units`` come from :data:`graph.export.REGISTRY`."""

from __future__ import annotations

import argparse

# the command's options that are a format's write options: only formats whose write takes them accept them
FORMAT_OPTIONS = ("axes", "units")


def _and(names: list[str]) -> str:
    return " and ".join(names) if len(names) <= 2 else ", ".join(names[:-1]) + " and " + names[-1]


def _takers(option: str) -> list[str]:
    from graph.export import REGISTRY

    return [name for name, f in REGISTRY.items() if option in f.options]


def format_help() -> str:
    """One clause per format: ``nwb: NWB, Neurodata Without Borders ... (needs acinoset[export])``."""
    from graph.export import REGISTRY

    return "; ".join(f"{name}: {f.label}, {f.help}" + (" (needs acinoset[export])" if f.needs else "")
                     for name, f in REGISTRY.items())


def register(sub) -> None:
    from graph.export import FORMATS, REGISTRY  # light: no optional library is imported here

    units = [f"{name} (default {REGISTRY[name].options['units']})" for name in _takers("units")]
    p = sub.add_parser("export", description="Write a solved run (the H5 of acinoset solve --h5, or of a "
                       "job) in a format other tools read. " + format_help())
    p.add_argument("result", metavar="RESULT.h5", help="result file written by acinoset solve --h5")
    p.add_argument("--format", required=True, choices=FORMATS)
    p.add_argument("--out", required=True, metavar="FILE")
    p.add_argument("--calibration", default=None, metavar="FILE",
                   help="the rig solved with, if the result file does not hold it (older files)")
    p.add_argument("--individual", default=None, metavar="NAME",
                   help="a result of several individuals (its individuals axis): the one to write")
    p.add_argument("--axes", default=None, metavar="opensim|x,z,-y",
                   help=f"{_and(_takers('axes'))}: output axes as signed world axes; 'opensim' turns a z-up "
                        "world y-up")
    p.add_argument("--units", default=None, choices=["m", "mm"],
                   help=f"{_and(units)}: length unit of the file")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from graph.app.cli import UsageError
    from graph.export import REGISTRY, export

    options = {}
    for option in FORMAT_OPTIONS:
        value = getattr(args, option)
        if value is None:
            continue
        if option not in REGISTRY[args.format].options:
            raise UsageError(f"--{option} applies to --format {_and(_takers(option))} only")
        options[option] = value
    try:
        out = export(args.result, args.format, args.out, calibration=args.calibration, individual=args.individual,
                     **options)
    except ValueError as e:
        if type(e) is not ValueError:
            raise
        raise UsageError(str(e)) from None
    print(f"{args.format}: {args.result} -> {out}")
    return 0
