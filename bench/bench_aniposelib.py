"""acinoset against aniposelib on the same simulated runs: time and 3D error.

    python bench/bench_aniposelib.py [--frames 500] [--seeds 3] [--repeats 1] [--realistic]

Each seed is one simulated run (6 cameras, 120 fps, 5 px noise, 10 % outliers of sigma 100 px;
see bench/harness.py). On it, after one untimed warm-up of every method:

* acinoset ``tri``, ``ekf``, ``fte`` (cheetah skeleton; also without the marginal covariances,
  ``uncertainty=False``, which aniposelib does not compute either) and ``fte`` on free points with
  soft bone lengths (``points+bones``: the same model class as aniposelib's optimiser);
* aniposelib ``triangulate`` (Anipose's default, ``optim = false``) and ``triangulate_optim`` with
  every cheetah bone as a limb-length constraint and Anipose's default scales, after Anipose's
  default score threshold (0.8). The ``CameraGroup`` is loaded from the Anipose TOML acinoset
  writes for the rig (fisheye cameras); its projections agree with ours to 1e-10 px.

Prints a Markdown table and writes bench/results/aniposelib.json.
"""

from __future__ import annotations

import argparse
import statistics
import warnings

import harness as h
import numpy as np

from graph.api import SolveOptions, solve


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, default=500)
    ap.add_argument("--seeds", type=int, default=3, help="simulated runs (seeds 0..S-1)")
    ap.add_argument("--repeats", type=int, default=1, help="timed solves per run and method")
    ap.add_argument("--realistic", action="store_true", help="most outliers get a low likelihood")
    args = ap.parse_args()
    warnings.filterwarnings("ignore")  # aniposelib's numba object-mode notices

    cal = h.rig()
    cg = h.anipose_group(cal)
    info = h.machine()
    print(f"# acinoset vs aniposelib: {args.frames} frames, {args.seeds} runs x {args.repeats} timed solves; "
          f"{info['cpu']}, {info['cores']} cores, load {info['load_average'][0]:.1f}")

    def ours(method, skeleton="cheetah", bones=False, uncertainty=True):
        def run_fn(run):
            opts = SolveOptions(method=method, fps=run.fps, skeleton=skeleton, uncertainty=uncertainty,
                                bone_lengths=list(run.bones) if bones else None)
            return solve(run.keypoints, cal, opts).positions
        return run_fn

    methods = {
        "acinoset tri": ours("tri"),
        "acinoset ekf": ours("ekf"),
        "acinoset fte": ours("fte"),
        "acinoset fte, no uncertainty": ours("fte", uncertainty=False),
        "acinoset fte points+bones": ours("fte", "points", bones=True),
        "aniposelib triangulate": lambda run: h.anipose_triangulate(cg, h.anipose_points(run)),
        "aniposelib triangulate_optim": lambda run: h.anipose_triangulate_optim(
            cg, h.anipose_points(run), h.bone_constraints(run)),
    }
    # warm-up: one-time compiles (numba, jax) on a small run, untimed
    small = h.simulate(cal, 40, seed=99, realistic=args.realistic)
    for fn in methods.values():
        fn(small)

    per = {name: {"wall": [], "cpu": [], "errors": []} for name in methods}
    for seed in range(args.seeds):
        run = h.simulate(cal, args.frames, seed=seed, realistic=args.realistic)
        for name, fn in methods.items():
            pos, t = h.timed(lambda: fn(run), repeats=args.repeats, warmup=False)
            per[name]["wall"] += t.wall
            per[name]["cpu"] += t.cpu
            per[name]["errors"].append(h.error_mm(pos, run))
            print(f"  seed {seed} {name:<30} {t.median:8.2f} s  mean {per[name]['errors'][-1]['mean_mm']:7.1f} mm",
                  flush=True)

    summary = {}
    for name, d in per.items():
        summary[name] = {
            "median_s": statistics.median(d["wall"]), "cpu_median_s": statistics.median(d["cpu"]),
            "wall_s": d["wall"], "cpu_s": d["cpu"],
            "mean_mm": float(np.mean([e["mean_mm"] for e in d["errors"]])),
            "median_mm": float(np.mean([e["median_mm"] for e in d["errors"]])),
            "p90_mm": float(np.mean([e["p90_mm"] for e in d["errors"]])),
            "max_mm": float(np.max([e["max_mm"] for e in d["errors"]])),
            "per_run": d["errors"]}
    ref = summary["aniposelib triangulate_optim"]
    rows = []
    for name, s in summary.items():
        rows.append([name, s["mean_mm"], s["median_mm"], s["p90_mm"], s["median_s"], s["cpu_median_s"],
                     ref["median_s"] / s["median_s"], s["mean_mm"] / ref["mean_mm"]])
    print()
    print(h.markdown_table(["method", "3D mean mm", "3D median mm", "p90 mm", "wall s (median)", "CPU s (median)",
                            "speed-up vs triangulate_optim", "error / triangulate_optim"], rows))
    path = h.save("aniposelib" + ("_realistic" if args.realistic else ""),
                  {"machine": info, "args": vars(args), "protocol": h.TARGET, "anipose": h.ANIPOSE_DEFAULTS,
                   "results": summary})
    print(f"\nwrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
