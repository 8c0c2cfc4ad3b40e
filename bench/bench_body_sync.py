"""The animal's proportions and the cameras' clocks estimated with the trajectory, side by side.

For each condition (the rows) and rig, simulated runs in the paper's protocol (5 px noise, 10 %
confident outliers):

* exact: the model's proportions, cameras in sync;
* proportions: every length group drawn within +-15 % of the model's;
* juvenile: the whole animal 0.75-0.85x the model;
* offsets: every camera but the first off by up to +-1.5 frames;
* all: a juvenile with +-15 % proportions and offset cameras.

Columns: ``fte`` estimating both (``body="estimate", sync="estimate"``); the oracle, the same
solver given the true lengths and offsets; ``fte`` as it was (the model, in sync); ``ekf``
estimating both (over its first 2 s); aniposelib's ``triangulate_optim`` with every bone a limb
constraint at Anipose's default scales (it has no notion of time offsets or of a body model). Also:
the estimated lengths' largest error against the truth and the offsets' largest error, and the
time of 500 frames with both estimated against ``fte`` as it was.

``python bench/bench_body_sync.py [--frames 300] [--seeds 2]``; writes bench/results/body_sync.json.
"""

from __future__ import annotations

import argparse
import sys
import time
import warnings

import harness as h
import numpy as np

from graph.api import SolveOptions, solve
from graph.simulate import ring_rig, simulate_run

RIGS = {"AcinoSet 2019 rig, 6 cameras, 120 fps": (h.rig, 120.0), "ring of 4 cameras, 90 fps": (ring_rig, 90.0)}


def conditions(seed: int, cameras: int) -> dict[str, dict]:
    rng = np.random.default_rng([seed, 11])
    offsets = np.r_[0.0, rng.uniform(-1.5, 1.5, cameras - 1)]
    juvenile = float(rng.uniform(0.75, 0.85))
    return {"exact": {}, "proportions +-15 %": {"body_variation": 0.15}, "juvenile": {"body_scale": juvenile},
            "offsets +-1.5 frames": {"time_offsets": offsets},
            "all together": {"body_scale": juvenile, "body_variation": 0.15, "time_offsets": offsets}}


def error_mm(result, run) -> float:
    return float(np.nanmean(np.linalg.norm(result.positions - run.positions, axis=-1)) * 1000)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--seeds", type=int, default=2)
    ap.add_argument("--timing-repeats", type=int, default=5, help="0: accuracy only")
    ap.add_argument("--no-aniposelib", action="store_true")
    ap.add_argument("--timing-only", action="store_true", help="only the 500-frame speed table")
    args = ap.parse_args()
    warnings.filterwarnings("ignore")
    info = h.machine()
    print(f"# body and clocks: {args.frames} frames, {args.seeds} runs per cell; {info['cpu']}, "
          f"{info['cores']} cores, load {info['load_average'][0]:.1f}", flush=True)
    h.warm_up_ours(h.rig())
    out: dict = {"machine": info, "args": vars(args), "rigs": {}}
    for rig_name, (make, fps) in () if args.timing_only else RIGS.items():
        cal = make()
        cg = None if args.no_aniposelib else h.anipose_group(cal)
        cells: dict[str, dict[str, list]] = {}
        for seed in range(args.seeds):
            for cond, kw in conditions(seed, len(cal)).items():
                run = simulate_run(cal, frames=args.frames, fps=fps, seed=seed, confident_outliers=1.0, **kw)
                truth_offsets = list(run.time_offsets)
                c = cells.setdefault(cond, {k: [] for k in (
                    "fte estimate", "oracle", "fte model, in sync", "ekf estimate", "aniposelib triangulate_optim",
                    "length error %", "offset error frames", "fte estimate s", "aniposelib s")})
                t0 = time.perf_counter()
                est = solve(run.keypoints, cal, SolveOptions(fps=fps, body="estimate", sync="estimate"))
                c["fte estimate s"].append(time.perf_counter() - t0)
                oracle = solve(run.keypoints, cal, SolveOptions(fps=fps, body="given", body_lengths=run.true_lengths,
                                                                time_offsets=truth_offsets))
                today = solve(run.keypoints, cal, SolveOptions(fps=fps, body="model"))
                ekf = solve(run.keypoints, cal, SolveOptions(method="ekf", fps=fps, body="estimate", sync="estimate"))
                c["fte estimate"].append(error_mm(est, run))
                c["oracle"].append(error_mm(oracle, run))
                c["fte model, in sync"].append(error_mm(today, run))
                c["ekf estimate"].append(error_mm(ekf, run))
                lengths = est.report.body_lengths
                c["length error %"].append(max(abs(lengths[g]["length_m"] / L - 1) * 100
                                               for g, L in run.true_lengths.items() if g != "eye"))
                c["offset error frames"].append(float(np.max(np.abs(np.subtract(est.report.time_offsets_frames,
                                                                                 truth_offsets)))))
                if cg is not None:
                    t0 = time.perf_counter()
                    pos = h.anipose_triangulate_optim(cg, h.anipose_points(run), h.bone_constraints(run))
                    c["aniposelib s"].append(time.perf_counter() - t0)
                    c["aniposelib triangulate_optim"].append(float(np.nanmean(np.linalg.norm(pos - run.positions,
                                                                                             axis=-1)) * 1000))
                print(f"  {rig_name[:12]:12s} seed {seed} {cond:22s} est {c['fte estimate'][-1]:6.1f} oracle "
                      f"{c['oracle'][-1]:6.1f} today {c['fte model, in sync'][-1]:6.1f} "
                      f"ekf {c['ekf estimate'][-1]:6.1f}"
                      + (f" anipose {c['aniposelib triangulate_optim'][-1]:6.1f}" if cg is not None else "")
                      + f"  lengths {c['length error %'][-1]:.1f} %  offsets {c['offset error frames'][-1]:.3f}",
                      flush=True)
        summary = {cond: {k: (float(np.mean(v)) if k not in ("length error %", "offset error frames") else
                              float(np.max(v))) if v else float("nan") for k, v in c.items()}
                   for cond, c in cells.items()}
        out["rigs"][rig_name] = {"cells": summary, "raw": cells}
        rows = [[cond, s["fte estimate"], s["oracle"], s["fte estimate"] / s["oracle"], s["fte model, in sync"],
                 s["ekf estimate"], s["aniposelib triangulate_optim"], s["length error %"], s["offset error frames"]]
                for cond, s in summary.items()]
        print(f"\n## {rig_name} (3D mean error, mm; lengths and offsets: the largest error over the runs)\n")
        print(h.markdown_table(["condition", "fte estimating", "oracle", "ratio", "fte model, in sync",
                                "ekf estimating", "aniposelib triangulate_optim", "lengths max err %",
                                "offsets max err (frames)"], rows), flush=True)

    # speed: 500 frames, both estimated, against fte as it was, in-process and medians of repeats
    cal = h.rig()
    run = simulate_run(cal, frames=500, seed=3, confident_outliers=1.0, body_variation=0.15,
                       time_offsets=conditions(3, len(cal))["offsets +-1.5 frames"]["time_offsets"])
    timing = {}
    cases = (("fte model, in sync", {"body": "model"}),
             ("fte estimating both", {"body": "estimate", "sync": "estimate"}),
             ("fte estimating the body", {"body": "estimate"}),
             ("fte estimating the clocks", {"body": "model", "sync": "estimate"}))
    for name, opts in cases if args.timing_repeats > 0 else ():
        _, t = h.timed(lambda: solve(run.keypoints, cal, SolveOptions(fps=120.0, **opts)), repeats=args.timing_repeats)
        timing[name] = t.to_dict()
        print(f"  500 frames {name:28s} median {t.median:.3f} s (best {t.best:.3f}, cpu {t.cpu_median:.3f})",
              flush=True)
    out["timing_500"] = timing
    path = h.save("body_sync_timing" if args.timing_only else "body_sync", out)
    print(f"\nwrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
