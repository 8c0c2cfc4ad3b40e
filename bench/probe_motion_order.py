"""Probe: the order of the free points' motion prior on the fly (leave one camera out).

    python bench/probe_motion_order.py [--data DIR]

acinoset's smoother puts its prior on the third differences of each coordinate by default
(constant acceleration; graph.solve.fte, graph.solve.smoothing); aniposelib's ``triangulate_optim`` penalises
first differences. This probe solves the fly (bench_fly_loco.py) with the prior on the k-th
differences (``motion_order`` k = 1, 2, 3, and ``"auto"``), the scale fitted by the evidence as
``motion_scale="auto"`` does, at the library's stiffness bound and at 100x it, and scores each by
:func:`graph.metrics.leave_one_camera_out` on both members combined and on member 1. Then, on
simulated runs with a 3D truth (the cheetah solved as free points, the paper's protocol on the
AcinoSet rig: 200 frames, 2, 5 and 10 px, 10 % outliers, seeds 0 and 1), the mean 3D error of each
order. (Before ``motion_order`` existed it patched the library's internals; bench/RESULTS.md 12c
has that run, whose numbers the option reproduces.)
"""

from __future__ import annotations

import argparse
import sys
import warnings
from dataclasses import replace
from pathlib import Path

import numpy as np
from bench_fly_loco import DATA, FPS, member_files

from graph.io.calibration import load_calibration
from graph.io.keypoints import read_keypoints
from graph.metrics import leave_one_camera_out
from graph.solve import fte, smoothing
from graph.solve.ensemble import combine
from graph.types import SolveOptions

ORDERS = (3, 2, 1, "auto")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", type=Path, default=DATA)
    args = ap.parse_args()
    warnings.filterwarnings("ignore")
    cal = load_calibration(args.data / "calibration.toml")
    member1 = [read_keypoints(p) for p in member_files(args.data, 1)]
    ens = [combine([read_keypoints(p) for p in files]) for files in zip(*(member_files(args.data, m) for m in (1, 2)))]
    base = SolveOptions(method="fte", skeleton="points", fps=FPS, motion_scale="auto")
    bound = smoothing.MAX_STIFFNESS
    print("| order | stiffness bound | input | median px | p90 px |\n|---|---|---|---|---|")
    for k in ORDERS:
        base = replace(base, motion_order=k)
        for b in (bound, 100 * bound):
            smoothing.MAX_STIFFNESS = fte.MAX_STIFFNESS = b
            for name, inputs in (("ensemble", ens), ("member 1", member1)):
                r = leave_one_camera_out(inputs, cal, replace(base), method=f"order {k}", judge=member1)
                print(f"| {k} | {b:g} | {name} | {r.median_px:.3f} | {r.p90_px:.3f} |", flush=True)
    smoothing.MAX_STIFFNESS = fte.MAX_STIFFNESS = bound
    import harness as h

    from graph.api import solve

    rig = h.rig()
    runs = [h.simulate(rig, frames=200, seed=seed, noise=noise, outliers=0.1)
            for seed in (0, 1) for noise in (2.0, 5.0, 10.0)]
    print("\n| order | simulated cheetah as free points: mean 3D error per run (mm) | mean |\n|---|---|---|")
    for k in ORDERS:
        errs = []
        for run in runs:
            res = solve(run.keypoints, rig, SolveOptions(fps=run.fps, skeleton="points", motion_scale="auto",
                                                         motion_order=k))
            errs.append(float(np.nanmean(np.linalg.norm(res.positions - run.positions, axis=-1)) * 1000))
        print(f"| {k} | {', '.join(f'{e:.2f}' for e in errs)} | {np.mean(errs):.2f} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
