"""How solve time grows with the run: ``fte`` at 100, 500 and 2000 frames; ``ekf`` per frame.

    python bench/bench_scaling.py [--frames 100 500 2000] [--repeats 3]

One simulated run per length (target protocol, bench/harness.py), solved ``repeats`` times after
one untimed warm-up on a short run (the one-time compile). Reports the median wall time, the time
per frame, a least-squares line ``t = a + b N`` through the medians with its worst relative
deviation (how linear the growth is), and for ``ekf`` the per-frame update time the solver itself
measures (median and 95th percentile over frames, after its batch start) next to wall time / N.

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
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()

    cal = h.rig()
    info = h.machine()
    print(f"# scaling: frames {args.frames}, {args.repeats} timed solves each; {info['cpu']}, "
          f"{info['cores']} cores, load {info['load_average'][0]:.1f}")
    h.warm_up_ours(cal)

    out = {"machine": info, "args": vars(args), "protocol": h.TARGET, "fte": {}, "ekf": {}}
    for n in args.frames:
        run = h.simulate(cal, n, seed=args.seed)
        for method in ("fte", "ekf"):
            results = []

            def go():
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

    ns = np.array(args.frames, dtype=float)
    tf = np.array([out["fte"][n]["median_s"] for n in args.frames])
    A = np.stack([np.ones_like(ns), ns], axis=1)
    (a, b), *_ = np.linalg.lstsq(A, tf, rcond=None)
    dev = float(np.max(np.abs(A @ [a, b] - tf) / tf))
    out["fte_line"] = {"intercept_s": float(a), "s_per_frame": float(b), "max_relative_deviation": dev}
    rows = [[n, out["fte"][n]["median_s"], out["fte"][n]["per_frame_ms"], out["fte"][n]["iterations"],
             out["fte"][n]["mean_mm"], out["ekf"][n]["median_s"], out["ekf"][n]["per_frame_ms"],
             out["ekf"][n]["update_ms_median"], out["ekf"][n]["update_ms_p95"], out["ekf"][n]["mean_mm"]]
            for n in args.frames]
    print()
    print(h.markdown_table(["frames", "fte s", "fte ms/frame", "fte iterations", "fte mean mm", "ekf s",
                            "ekf wall ms/frame", "ekf update ms median", "ekf update ms p95", "ekf mean mm"],
                           rows))
    print(f"\nfte: t = {a:.3f} s + {1000 * b:.3f} ms x N; worst relative deviation from the line {dev:.0%}")
    path = h.save("scaling", out)
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
