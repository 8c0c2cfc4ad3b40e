"""acinoset ``fte`` against the AcinoSet paper's own solver (its FTE program solved by IPOPT), same runs.

    python bench/bench_paper_ipopt.py [--frames 100] [--seeds 3] [--repeats 1] [--name paper_ipopt]

The paper (Joska et al., ICRA 2021) wrote Full Trajectory Estimation in Pyomo and solved it with
IPOPT and MUMPS. ``bench/paper_nlp.py`` writes that program (pose, rate and acceleration per frame
as variables, the constant-acceleration model and the measurements as equality constraints, joint
limits as variable bounds, model and measurement slacks in the cost) and hands it to IPOPT through
cyipopt with exact first and second derivatives. It is the paper's formulation solved by IPOPT
without Pyomo's modelling layer: Pyomo reaches IPOPT either through an ``ipopt`` executable (no
PyPI or Debian package ships one) or through pynumero's AMPL Solver Library extension, which
``pyomo build-extensions`` builds by cloning the ASL sources at build time and which no package
ships either. Derivatives of the projections come from CasADi (symbolic, exact), the rest by hand.

Each seed is one simulated run (the AcinoSet 2019 rig, 6 cameras, 120 fps, 5 px noise, 10 %
confident outliers of sigma 100 px; bench/harness.py). After one untimed warm-up of every method
(numba's compile for acinoset; the CasADi functions and IPOPT's first call for the peer), on each run:

* acinoset ``fte`` with its default options (covariances included) and with ``uncertainty=False``;
* IPOPT on the paper's program with acinoset ``fte``'s cost written in its variables
  (``cost="fte"``: the same function of the trajectory, so both must reach the same optimum);
* IPOPT on the paper's program with the paper's own motion cost (``cost="paper"``: the squared
  change of acceleration per frame, no anchor term): the paper's objective, a different one.

IPOPT starts from fte's own start (robust triangulation and inverse kinematics, inside the timed
call for both) and runs with its defaults (MUMPS, tol 1e-8, exact Hessian). Every answer is judged
against the simulated truth (3D error) and scored with ONE cost function, fte's
(:func:`paper_nlp.common_cost`). Prints Markdown tables and writes bench/results/paper_ipopt.json (``--name``).

Extra dependencies (PyPI; IPOPT 3.14 and MUMPS come inside the ``cyipopt-wheels`` wheel, no system
package is needed)::

    pip install -e '.[peers]'      # cyipopt-wheels, casadi
"""

from __future__ import annotations

import argparse
import statistics
from importlib import metadata

import harness as h
import numpy as np
import paper_nlp as pn

from graph.api import SolveOptions, solve
from graph.solve import problem as gp
from graph.solve.initial import initial_poses
from graph.solve.triangulate import robust_points

METHODS = ["acinoset fte", "acinoset fte, no uncertainty", "IPOPT, paper program, fte cost",
           "IPOPT, paper program, paper cost"]


def versions() -> dict:
    out = {}
    for dist in ("cyipopt-wheels", "casadi", "pyomo"):
        try:
            out[dist] = metadata.version(dist)
        except metadata.PackageNotFoundError:
            out[dist] = "absent"
    import cyipopt

    out["ipopt"] = ".".join(str(v) for v in cyipopt.IPOPT_VERSION)
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--seeds", type=int, default=3, help="simulated runs (seeds 0..S-1)")
    ap.add_argument("--repeats", type=int, default=1, help="timed solves per run and method")
    ap.add_argument("--name", default="paper_ipopt", help="results file bench/results/NAME.json")
    args = ap.parse_args()

    cal = h.rig()
    info = h.machine()
    vers = versions()
    print(f"# acinoset fte vs the paper's program in IPOPT {vers['ipopt']}: {args.frames} frames, {args.seeds} runs x "
          f"{args.repeats} timed solves; {info['cpu']}, {info['cores']} cores, load {info['load_average'][0]:.1f}")

    models: dict = {}

    def model_for(prob):
        if "m" not in models:
            models["m"] = pn.frame_model(prob.skeleton, prob.calibration)
        return models["m"]

    def fte(uncertainty):
        def run_fn(run):
            r = solve(run.keypoints, cal, SolveOptions(method="fte", fps=run.fps, uncertainty=uncertainty))
            return {"Q": r.params, "positions": r.positions, "iterations": r.report.iterations,
                    "own_cost": r.report.cost, "seconds": dict(r.report.seconds)}
        return run_fn

    def ipopt(cost):
        def run_fn(run):
            prob = gp.build(run.keypoints, cal, SolveOptions(method="fte", fps=run.fps))
            s = pn.solve_paper(prob, model_for(prob), cost=cost)
            return {"Q": s.Q, "positions": s.positions, "iterations": s.iterations, "own_cost": s.objective,
                    "seconds": s.seconds, "status": s.status, "status_msg": s.status_msg, "evals": s.evals,
                    "size": s.size}
        return run_fn

    fns = dict(zip(METHODS, [fte(True), fte(False), ipopt("fte"), ipopt("paper")]))
    small = h.simulate(cal, 40, seed=99)
    for fn in fns.values():
        fn(small)
    model_s = models["m"].build_s

    per = {name: {"wall": [], "cpu": [], "iterations": [], "errors": [], "runs": []} for name in fns}
    for seed in range(args.seeds):
        run = h.simulate(cal, args.frames, seed=seed)
        prob = gp.build(run.keypoints, cal, SolveOptions(method="fte", fps=run.fps))
        X, _, _ = robust_points(prob.calibration, prob.meas, prob.valid, prob.sigma_px)
        Q0 = initial_poses(prob, X)  # fte's start, the anchor of its cost
        answers = {}
        for name, fn in fns.items():
            out, t = h.timed(lambda: fn(run), repeats=args.repeats, warmup=False)
            answers[name] = out
            err = h.error_mm(out["positions"], run)
            cc = pn.common_cost(prob, Q0, out["Q"])
            d = per[name]
            d["wall"] += t.wall
            d["cpu"] += t.cpu
            d["iterations"].append(out["iterations"])
            d["errors"].append(err)
            d["runs"].append({"seed": seed, "wall_s": t.wall, "cpu_s": t.cpu, "iterations": out["iterations"],
                              "common_cost": cc, "own_cost": out["own_cost"], "error": err,
                              **{k: out[k] for k in ("seconds", "status", "status_msg", "evals", "size") if k in out}})
            print(f"  seed {seed} {name:<34} {t.median:7.2f} s  {out['iterations']:3d} it  "
                  f"cost {cc['total']:.6f}  mean {err['mean_mm']:5.2f} mm", flush=True)
        ref = answers["acinoset fte"]
        for name in METHODS[2:]:
            a = answers[name]
            dq = np.abs(a["Q"] - ref["Q"])
            dp = np.linalg.norm(a["positions"] - ref["positions"], axis=-1) * 1000
            per[name]["runs"][-1]["vs_fte"] = {"max_abs_dq": float(dq.max()), "mean_marker_mm": float(np.nanmean(dp)),
                                               "max_marker_mm": float(np.nanmax(dp))}

    summary = {}
    for name, d in per.items():
        summary[name] = {
            "median_s": statistics.median(d["wall"]), "cpu_median_s": statistics.median(d["cpu"]),
            "iterations_median": statistics.median(d["iterations"]),
            "mean_mm": float(np.mean([e["mean_mm"] for e in d["errors"]])),
            "median_mm": float(np.mean([e["median_mm"] for e in d["errors"]])),
            "p90_mm": float(np.mean([e["p90_mm"] for e in d["errors"]])),
            "wall_s": d["wall"], "cpu_s": d["cpu"], "per_run": d["runs"]}
    ref = summary["acinoset fte"]
    rows = [[name, s["median_s"], s["cpu_median_s"], s["iterations_median"], s["mean_mm"], s["median_mm"],
             s["median_s"] / ref["median_s"]] for name, s in summary.items()]
    print()
    print(h.markdown_table(["method", "wall s (median)", "CPU s (median)", "iterations (median)", "3D mean mm",
                            "3D median mm", "wall / fte"], rows))
    rows = []
    for seed in range(args.seeds):
        c_fte = summary["acinoset fte"]["per_run"][seed]["common_cost"]["total"]
        row = [seed, f"{c_fte:.4f}"]
        for name in METHODS[2:]:
            r = summary[name]["per_run"][seed]
            c = r["common_cost"]["total"]
            row += [f"{c:.4f} ({c - c_fte:+.2g})", f"{r['vs_fte']['max_marker_mm']:.2g}"]
        rows.append(row)
    print()
    print(h.markdown_table(["seed", "fte cost of fte's answer", "... of IPOPT fte-cost answer (minus fte's)",
                            "max marker distance to fte mm", "... of IPOPT paper-cost answer (minus fte's)",
                            "max marker distance to fte mm"], rows))
    path = h.save(args.name, {"machine": info, "peer_versions": vers, "args": vars(args), "protocol": h.TARGET,
                            "casadi_model_build_s": model_s, "ipopt_options": pn.DEFAULT_IPOPT,
                            "results": summary})
    print(f"\nwrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
