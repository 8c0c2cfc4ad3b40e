"""Does ``ekf``'s answer on long camera drop-outs depend on rounding? ``bench_dropout.py``'s runs (7,200
frames: four cameras blind for 1000-2999, camera 3 alone for 3000-3499), each solved by ``fte`` and by
``ekf`` as simulated and with draws of 0.001 px of Gaussian jitter added to every detection.

    .venv/bin/python bench/bench_ekf_jitter.py [--seeds 0,1,2] [--draws 3] [--window-frames N] [--out NAME]

``--window-frames``: ekf's windows (default: the solver's default; 0 the whole stream). Per seed and draw:
the mean 3D error (mm) over the run and per stretch (``bench_dropout.score``), and ekf's ratio to fte's
over the run. Writes bench/results/NAME.json (default ``ekf_jitter``).
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
import warnings

import bench_dropout as bd
import harness as h
import numpy as np

from graph.api import solve
from graph.types import SolveOptions

JITTER_PX = 0.001


def jittered(keypoints, draw: int):
    """The detections with draw ``draw`` of :data:`JITTER_PX` jitter (draw 0: as they are)."""
    if draw == 0:
        return keypoints
    rng = np.random.default_rng(1000 + draw)
    return [dataclasses.replace(k, xy=k.xy + rng.normal(0.0, JITTER_PX, k.xy.shape)) for k in keypoints]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", default="0,1,2")
    ap.add_argument("--draws", type=int, default=3, help="draws of jitter, the first the detections as they are")
    ap.add_argument("--window-frames", type=int, default=None)
    ap.add_argument("--frames", type=int, default=7200)
    ap.add_argument("--out", default="ekf_jitter")
    args = ap.parse_args()
    cal = h.rig()
    h.warm_up_ours(cal)
    rows, out = [], {"args": vars(args), "machine": h.machine(), "runs": {}}
    for seed in (int(s) for s in args.seeds.split(",")):
        parts = bd.stretches(args.frames, quick=False)
        run = bd.with_dropouts(bd.simulate(cal, args.frames, seed), parts)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            f = solve(run.keypoints, run.calibration, SolveOptions(fps=run.fps, skeleton="cheetah"))
        fte = bd.score(f.positions, f.std, run.positions, run.markers, parts)
        out["runs"][str(seed)] = {"fte": fte, "ekf": []}
        for draw in range(args.draws):
            t0 = time.perf_counter()
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                r = solve(jittered(run.keypoints, draw), run.calibration,
                          SolveOptions(fps=run.fps, skeleton="cheetah", method="ekf", window_frames=args.window_frames))
            s = bd.score(r.positions, r.std, run.positions, run.markers, parts)
            out["runs"][str(seed)]["ekf"].append({"draw": draw, "seconds": time.perf_counter() - t0, "scores": s})
            rows.append([seed, draw, *[round(v["mean_mm"], 1) for v in s.values()],
                         round(s["all"]["mean_mm"] / fte["all"]["mean_mm"], 2)])
            print(f"seed {seed} draw {draw}: {time.perf_counter() - t0:.1f} s, " +
                  ", ".join(f"{k.split(' ')[0]} {v['mean_mm']:.1f}" for k, v in s.items()) +
                  f" (fte all {fte['all']['mean_mm']:.1f})", flush=True)
    print(h.markdown_table(["seed", "draw", *[f"ekf {k} mm" for k in parts], "ekf / fte"], rows))
    print(f"wrote {h.save(args.out, out)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
