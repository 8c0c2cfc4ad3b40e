"""How solve time grows with the run: ``fte`` at 100, 500 and 2000 frames; ``ekf`` per frame.

    python bench/bench_scaling.py [--frames 100 500 2000] [--repeats 5]

One simulated run per length (target protocol, bench/harness.py), solved ``repeats`` times after
one untimed warm-up on a short run (the one-time compile). Reports the median wall time of ``fte``
(with and without the marginal covariances) and ``ekf``, the time per frame, a least-squares line
``t = a + b N`` through the best-of-repeats and through the CPU times of ``fte`` with its worst
relative deviation (how linear the growth is; the median is at the mercy of other load), and for
``ekf`` the per-frame update time the solver itself measures (median and 95th percentile over
frames, after its batch start) next to wall time / N.

Prints Markdown and writes bench/results/scaling.json.
"""

from __future__ import annotations

import argparse
import statistics

import harness as h
import numpy as np


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, nargs="+", default=[100, 500, 2000])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()

    cal = h.rig()
    info = h.machine()
    print(f"# scaling: frames {args.frames}, {args.repeats} timed solves each; {info['cpu']}, "
          f"{info['cores']} cores, load {info['load_average'][0]:.1f}")
    h.warm_up_ours(cal)

    out = {"machine": info, "args": vars(args), "protocol": h.TARGET, "fte": {}, "fte-traj": {}, "ekf": {}}
    for n in args.frames:
        run = h.simulate(cal, n, seed=args.seed)
        for method in ("fte", "fte-traj", "ekf"):
            results = []

            def go():
                if method == "fte-traj":
                    r = h.solve_ours(run, cal, "fte", uncertainty=False)
                else:
                    r = h.solve_ours(run, cal, method)
                results.append(r)
                return r

            res, t = h.timed(go, repeats=args.repeats, warmup=False)
            err = h.error_mm(res.positions, run)
            entry = {**t.to_dict(), "per_frame_ms": 1000 * t.median / n, "iterations": res.report.iterations,
                     "mean_mm": err["mean_mm"], "solver_seconds": [r.report.seconds for r in results]}
            if method == "ekf":
                pf = [r.report.per_frame_ms or {} for r in results]
                entry["update_ms_median"] = statistics.median(p.get("median", float("nan")) for p in pf)
                entry["update_ms_p95"] = statistics.median(p.get("p95", float("nan")) for p in pf)
            out[method][n] = entry
            print(f"  {method} {n:5d} frames: {t.median:7.3f} s median ({1000 * t.median / n:6.2f} ms/frame), "
                  f"{res.report.iterations} iterations, mean {err['mean_mm']:.1f} mm", flush=True)

    # the line through the best (least disturbed) wall time of each length, and through the CPU time
    ns = np.array(args.frames, dtype=float)
    A = np.stack([np.ones_like(ns), ns], axis=1)
    lines = {}
    for method in ("fte", "fte-traj"):
        for what, key in (("best wall", "best_s"), ("CPU", "cpu_median_s")):
            tf = np.array([out[method][n][key] for n in args.frames])
            (a, b), *_ = np.linalg.lstsq(A, tf, rcond=None)
            dev = float(np.max(np.abs(A @ [a, b] - tf) / tf))
            lines[f"{method} {what}"] = {"intercept_s": float(a), "ms_per_frame": 1000 * float(b),
                                         "max_relative_deviation": dev}
    out["lines"] = lines
    rows = []
    for n in args.frames:
        f, ft, e = out["fte"][n], out["fte-traj"][n], out["ekf"][n]
        rows.append([n, f["median_s"], f["best_s"], f["cpu_median_s"], ft["median_s"], ft["best_s"], f["per_frame_ms"],
                     f["iterations"], f["mean_mm"], e["median_s"], e["per_frame_ms"], e["update_ms_median"],
                     e["update_ms_p95"], e["mean_mm"]])
    print()
    print(h.markdown_table(["frames", "fte s median", "fte s best", "fte CPU s", "fte s (no uncertainty) median",
                            "fte s (no uncertainty) best", "fte ms/frame", "fte iterations", "fte mean mm", "ekf s",
                            "ekf wall ms/frame", "ekf update ms median", "ekf update ms p95", "ekf mean mm"],
                           rows))
    print()
    for name, ln in lines.items():
        print(f"{name}: t = {ln['intercept_s']:.3f} s + {ln['ms_per_frame']:.3f} ms x N; "
              f"worst relative deviation from the line {ln['max_relative_deviation']:.0%}")
    path = h.save("scaling", out)
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
