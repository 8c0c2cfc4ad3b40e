"""How many steps the stretched stage of the graduated robust loss takes: accuracy and time.

    python bench/bench_graduated.py [--steps 1 3] [--seeds 2]

``fte`` (graph.solve.fte.optimise) first minimises the robust loss with its knots stretched by 4, so that
detections far from a rough start are not rejected before the pose comes to them, then the loss
itself. This bench solves the same simulated runs with each value of ``graph.solve.fte.STRETCHED_STEPS``
(the stretched stage's step budget) and compares the mean 3D error against the truth, the number
of Gauss-Newton steps taken (accepted or not) and the wall time of the solve:

* the paper table's conditions (noise 0, 2, 5, 10 px x outliers 0, 10, 20 %, 200 frames, the
  AcinoSet rig), with the body estimated (the default) and with the model's body;
* bench_body_sync.py's conditions on both of its rigs (300 frames, 5 px, 10 % outliers), with the
  default and with the body and the clocks estimated;
* realistic outliers (simulate's own, not confident ones) with the cheetah, free points and ekf.

Writes bench/results/graduated.json.
"""

from __future__ import annotations

import argparse
import sys
import time
import warnings

import bench_body_sync as bbs
import harness as h
import numpy as np

from graph.api import SolveOptions, solve
from graph.simulate import simulate_run
from graph.solve import fte, joint


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--steps", type=int, nargs="+", default=[1, 3])
    ap.add_argument("--seeds", type=int, default=2)
    args = ap.parse_args()
    warnings.filterwarnings("ignore")
    info = h.machine()
    print(f"# stretched-stage steps {args.steps}; {info['cpu']}, {info['cores']} cores, "
          f"load {info['load_average'][0]:.1f}", flush=True)
    cal6 = h.rig()
    h.warm_up_ours(cal6)
    taken: list[int] = []
    for cls in (fte.TrajectoryProblem, joint.JointTrajectoryProblem):  # count the steps, accepted or not
        def counted(self, X, nrm, lam, _step=cls.step):
            taken.append(1)
            return _step(self, X, nrm, lam)
        cls.step = counted
    default = fte.STRETCHED_STEPS
    rows = []

    def case(name: str, run, cal, **opts) -> None:
        row = {"case": name}
        for k in args.steps:
            fte.STRETCHED_STEPS = k
            taken.clear()
            t0 = time.perf_counter()
            res = solve(run.keypoints, cal, SolveOptions(fps=run.fps, **opts))
            seconds = time.perf_counter() - t0
            err = float(np.nanmean(np.linalg.norm(res.positions - run.positions, axis=-1)) * 1000)
            row[str(k)] = {"mean_mm": err, "steps": len(taken), "seconds": seconds}
        fte.STRETCHED_STEPS = default
        rows.append(row)
        print(" ", name, " ".join(f"[{k}] {row[str(k)]['mean_mm']:.3f} mm {row[str(k)]['steps']} steps "
                                  f"{row[str(k)]['seconds']:.2f} s" for k in args.steps), flush=True)

    for seed in range(args.seeds):
        for noise in (0, 2, 5, 10):
            for outliers in (0.0, 0.1, 0.2):
                run = h.simulate(cal6, frames=200, seed=seed, noise=noise, outliers=outliers)
                case(f"paper {noise} px {outliers:.0%} seed {seed}", run, cal6)
                case(f"paper {noise} px {outliers:.0%} seed {seed}, model body", run, cal6, body="model")
    for rig_name, (make, fps) in bbs.RIGS.items():
        cal = make()
        for seed in range(args.seeds):
            for cname, kw in bbs.conditions(seed, len(cal)).items():
                run = simulate_run(cal, frames=300, fps=fps, noise=5.0, outliers=0.1, seed=seed,
                                   confident_outliers=1.0, **kw)
                case(f"{rig_name}: {cname} seed {seed}", run, cal)
                case(f"{rig_name}: {cname} seed {seed}, body and clocks", run, cal, body="estimate",
                     sync="estimate")
    for seed in range(args.seeds):
        run = h.simulate(cal6, frames=300, seed=seed, realistic=True)
        case(f"realistic seed {seed}", run, cal6)
        case(f"realistic seed {seed}, points", run, cal6, skeleton="points")
        case(f"realistic seed {seed}, ekf", run, cal6, method="ekf")

    summary = {}
    base = str(max(args.steps))
    for k in map(str, args.steps):
        err = np.array([r[k]["mean_mm"] for r in rows])
        rel = np.array([r[k]["mean_mm"] / r[base]["mean_mm"] - 1 for r in rows if r[base]["mean_mm"] > 0])
        summary[k] = {"mean_mm": float(err.mean()), "steps": float(np.mean([r[k]["steps"] for r in rows])),
                      "median_s": float(np.median([r[k]["seconds"] for r in rows])),
                      "error_change_vs_" + base: {"mean": float(rel.mean()), "worst": float(rel.max()),
                                                 "best": float(rel.min())}}
        print(f"steps {k}: mean error {summary[k]['mean_mm']:.4f} mm, {summary[k]['steps']:.2f} steps a solve, "
              f"median {summary[k]['median_s']:.3f} s; error against {base}: mean {rel.mean():+.2%}, "
              f"worst {rel.max():+.2%}, best {rel.min():+.2%}", flush=True)
    path = h.save("graduated", {"machine": info, "args": vars(args), "cases": rows, "summary": summary})
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
