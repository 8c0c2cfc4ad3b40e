"""Where a long run's windows start, against ``ekf``'s answer: the drop-out runs of ``bench_dropout.py``
solved by ``ekf`` in windows of several sizes (so that windows start inside the stretch four cameras
are blind, or where camera 3 is alone), beside the whole stream (``window_frames=0``) and ``fte``.

    .venv/bin/python bench/probe_ekf_windows.py [--seeds 0,1,2] [--window-frames 2000,1700,1300] [--out NAME]

Per seed and solve: the mean 3D error (mm) per stretch (``bench_dropout.score``) and the windows'
first frames; the ratio of each windowed ekf to the whole ekf and to fte. Writes
bench/results/NAME.json (default ``ekf_windows``).
"""

from __future__ import annotations

import argparse
import sys
import time
import warnings

import bench_dropout as bd
import harness as h

from graph.api import solve
from graph.types import SolveOptions


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", default="0,1,2")
    ap.add_argument("--window-frames", default="2000,1700,1300")
    ap.add_argument("--frames", type=int, default=7200)
    ap.add_argument("--out", default="ekf_windows")
    args = ap.parse_args()
    seeds = [int(s) for s in args.seeds.split(",")]
    sizes = [int(s) for s in args.window_frames.split(",")]
    cal = h.rig()
    h.warm_up_ours(cal)
    rows, out = [], {"seeds": seeds, "window_frames": sizes, "frames": args.frames, "runs": {}}
    for seed in seeds:
        parts = bd.stretches(args.frames, quick=False)
        run = bd.with_dropouts(bd.simulate(cal, args.frames, seed), parts)
        solves = {"fte": SolveOptions(fps=run.fps, skeleton="cheetah"),
                  "ekf whole": SolveOptions(fps=run.fps, skeleton="cheetah", method="ekf", window_frames=0)}
        for n in sizes:
            solves[f"ekf windows of {n}"] = SolveOptions(fps=run.fps, skeleton="cheetah", method="ekf", window_frames=n)
        scores = {}
        for name, opts in solves.items():
            t0 = time.perf_counter()
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                r = solve(run.keypoints, run.calibration, opts)
            s = bd.score(r.positions, r.std, run.positions, run.markers, parts)
            scores[name] = {"seconds": time.perf_counter() - t0, "scores": s}
            print(f"seed {seed} {name}: {time.perf_counter() - t0:.1f} s, "
                  + ", ".join(f"{k.split(' ')[0]} {v['mean_mm']:.2f}" for k, v in s.items()), flush=True)
        out["runs"][str(seed)] = scores
        mean = {name: {k: v["scores"][k]["mean_mm"] for k in parts} for name, v in scores.items()}
        for name in mean:
            if name.startswith("ekf windows"):
                rows.append([seed, name, *[round(mean[name][k] / mean["ekf whole"][k], 3) for k in parts],
                             round(mean[name]["all"] / mean["fte"]["all"], 3)])
    print(h.markdown_table(["seed", "solve", *[f"/ ekf whole: {k}" for k in parts], "/ fte: all"], rows))
    print(f"wrote {h.save(args.out, out)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
