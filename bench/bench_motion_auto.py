"""What ``motion_scale="auto"`` costs: an ``fte`` of 500 frames, fixed against fitted smoothing, in process.

    .venv/bin/python bench/bench_motion_auto.py [--frames 500] [--repeats 5] [--skeleton cheetah points]

One simulated run on the AcinoSet rig in the target protocol (bench/harness.py: 120 fps, 5 px noise,
10 % outliers of sigma 100 px), solved by ``fte`` with the fixed default (``motion_scale=1``) and
with ``motion_scale="auto"``, alternately (so that the machine's load falls on both alike), after
an untimed warm-up of each. For every solve the wall time and where it went: the fits
(:func:`graph.solve.fte.fit_motion`, and how many evaluations of the evidence), the optimisations
(:func:`graph.solve.fte.optimise`), the result with its uncertainty; and the 3D error against the truth.
Prints medians and the ratio auto / fixed; writes bench/results/motion_auto_cost.json.
"""

from __future__ import annotations

import argparse
import statistics
import time

import harness as h

import graph.solve.fte as fte
import graph.solve.smoothing as smoothing

TIMED = {"fit_motion": (fte, "fit_motion"), "optimise": (fte, "optimise"),
         "result": (fte, "trajectory_result")}


def instrument() -> dict:
    """Wrap the stages so that each solve's time per stage, and the evidence evaluations, are counted."""
    spent: dict = {}

    def wrap(module, attr, key):
        inner = getattr(module, attr)

        def timed(*args, **kwargs):
            t0 = time.perf_counter()
            try:
                return inner(*args, **kwargs)
            finally:
                spent[key] = spent.get(key, 0.0) + time.perf_counter() - t0
                spent[key + "_calls"] = spent.get(key + "_calls", 0) + 1
        setattr(module, attr, timed)

    for key, (module, attr) in TIMED.items():
        wrap(module, attr, key)
    wrap(smoothing.ChainEvidence, "__call__", "evidence")
    return spent


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, default=500)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--skeleton", nargs="+", default=["cheetah", "points"])
    args = ap.parse_args()
    cal = h.rig()
    info = h.machine()
    print(f"# motion_scale auto cost: {args.frames} frames, {args.repeats} repeats; {info['cpu']}, "
          f"{info['cores']} cores, load {info['load_average'][0]:.1f}", flush=True)
    h.warm_up_ours(cal)
    run = h.simulate(cal, args.frames, seed=args.seed)
    spent = instrument()
    out = {}
    for skeleton in args.skeleton:
        settings = {"fixed": {"motion_scale": 1.0}, "auto": {"motion_scale": "auto"}}
        for extra in settings.values():  # warm-up
            h.solve_ours(run, cal, "fte", skeleton=skeleton, **extra)
        runs = {name: [] for name in settings}
        for _ in range(args.repeats):
            for name, extra in settings.items():
                spent.clear()
                t0 = time.perf_counter()
                r = h.solve_ours(run, cal, "fte", skeleton=skeleton, **extra)
                wall = time.perf_counter() - t0
                runs[name].append({"seconds": wall, **{k: v for k, v in spent.items()},
                                   "iterations": r.report.iterations, "motion_scales": r.report.motion_scales,
                                   **h.error_mm(r.positions, run)})
        med = {name: {k: statistics.median(x[k] for x in rs) for k in rs[0]
                      if isinstance(rs[0][k], (int, float)) and k != "motion_scales"}
               for name, rs in runs.items()}
        ratio = med["auto"]["seconds"] / med["fixed"]["seconds"]
        out[skeleton] = {"runs": runs, "median": med, "ratio_auto_over_fixed": ratio}
        for name, m in med.items():
            print(f"  {skeleton:8s} {name:5s} median {m['seconds']:.3f} s: fits {m.get('fit_motion', 0):.3f} s "
                  f"({m.get('fit_motion_calls', 0):.0f} fits, {m.get('evidence_calls', 0):.0f} evaluations), "
                  f"optimise {m.get('optimise', 0):.3f} s ({m.get('optimise_calls', 0):.0f} calls, "
                  f"{m['iterations']:.0f} iterations), result {m.get('result', 0):.3f} s; "
                  f"3D error {m['mean_mm']:.2f} mm", flush=True)
        print(f"  {skeleton:8s} auto / fixed: {ratio:.2f}x", flush=True)
    path = h.save("motion_auto_cost", {"machine": info, "args": vars(args), "results": out})
    print(f"\nwrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
