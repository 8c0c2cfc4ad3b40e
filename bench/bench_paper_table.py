"""The AcinoSet paper's simulation table: 3D error of each method by noise and outlier rate.

    python bench/bench_paper_table.py [--frames 200] [--seeds 3] [--noise 0 2 5 10] [--outliers 0 0.1 0.2]
                                      [--methods tri ekf fte fte-auto] [--out paper_table]

For every noise level sigma_n (px) and outlier rate p_o (outlier sigma 100 px, every outlier with a
high likelihood: the paper's protocol, bench/harness.py) and every seed, one run on the AcinoSet
rig is simulated and solved with ``tri``, ``ekf`` and ``fte`` (cheetah skeleton; ``fte-auto`` is
``fte`` with ``motion_scale="auto"``, ``fte-auto-noise`` with ``measurement_std_px="auto"`` too;
``fte-points`` and ``fte-points-auto`` the same run as free points (no bones); the
seconds of every solve are kept). The cell is the
mean over seeds of the mean 3D error (mm) against the truth; the median error is kept in the JSON.

Prints Markdown and writes bench/results/paper_table.json.
"""

from __future__ import annotations

import argparse
import time

import harness as h
import numpy as np

METHODS = ("tri", "ekf", "fte")
VARIANTS = {"tri": ("tri", {}), "ekf": ("ekf", {}), "fte": ("fte", {}), "fte-auto": ("fte", {"motion_scale": "auto"}),
            "fte-auto-noise": ("fte", {"motion_scale": "auto", "measurement_std_px": "auto"}),
            "fte-points": ("fte", {"skeleton": "points"}),
            "fte-points-auto": ("fte", {"skeleton": "points", "motion_scale": "auto"})}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, default=200)
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--noise", type=float, nargs="+", default=[0.0, 2.0, 5.0, 10.0])
    ap.add_argument("--outliers", type=float, nargs="+", default=[0.0, 0.1, 0.2])
    ap.add_argument("--methods", nargs="+", default=list(METHODS), choices=list(VARIANTS))
    ap.add_argument("--out", default="paper_table", help="bench/results/OUT.json")
    args = ap.parse_args()
    methods = tuple(args.methods)

    cal = h.rig()
    info = h.machine()
    print(f"# paper table: {args.frames} frames, {args.seeds} seeds per cell; {info['cpu']}, {info['cores']} cores")
    h.warm_up_ours(cal)
    t0 = time.perf_counter()
    cells = {}
    for noise in args.noise:
        for p in args.outliers:
            errs = {m: [] for m in methods}
            secs = {m: [] for m in methods}
            for seed in range(args.seeds):
                run = h.simulate(cal, args.frames, seed=seed, noise=noise, outliers=p)
                for m in methods:
                    method, extra = VARIANTS[m]
                    t1 = time.perf_counter()
                    r = h.solve_ours(run, cal, method, **extra)
                    secs[m].append(time.perf_counter() - t1)
                    errs[m].append({**h.error_mm(r.positions, run), "motion_scales": r.report.motion_scales,
                                    "sigma_px": r.report.sigma_px})
            cells[f"{noise:g}px/{p:.0%}"] = {
                m: {"mean_mm": float(np.mean([e["mean_mm"] for e in errs[m]])),
                    "median_mm": float(np.mean([e["median_mm"] for e in errs[m]])),
                    "seconds": secs[m], "per_seed": errs[m]} for m in methods}
            c = cells[f"{noise:g}px/{p:.0%}"]
            print(f"  noise {noise:4g} px, outliers {p:4.0%}: " + ", ".join(
                f"{m} {c[m]['mean_mm']:.1f}" for m in methods) + " mm", flush=True)
    rows = []
    for noise in args.noise:
        for p in args.outliers:
            c = cells[f"{noise:g}px/{p:.0%}"]
            rows.append([f"{noise:g}", f"{p:.0%}"] + [c[m]["mean_mm"] for m in methods]
                        + [c[m]["median_mm"] for m in methods])
    print()
    print(h.markdown_table(["noise px", "outliers"] + [f"{m} mean mm" for m in methods]
                           + [f"{m} median mm" for m in methods], rows))
    path = h.save(args.out, {"machine": info, "args": vars(args), "cells": cells,
                                  "seconds": time.perf_counter() - t0})
    print(f"\nwrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
