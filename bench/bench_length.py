"""Does the solve time grow faster than the run? ``acinoset solve`` from a shell on runs of 150 to 2,400 frames.

    .venv/bin/python bench/bench_length.py [--quick] [--repeats 3] [--seeds 0,1,2] [--no-resident] [--out length]

The runs: a slow cheetah (``simulate_run(..., speed=1.0)``: 1 m/s along the simulator's figure of eight,
instead of its default 4 m/s) on the AcinoSet 2019 six-camera rig, 120 fps, the harness's target noise
protocol (:data:`harness.TARGET`: 5 px noise, 10 % outliers of sigma 100 px, every outlier with a high
likelihood), seeds 0, 1, 2 (``--seeds``), 150, 600, 1,200 and 2,400 frames (``--quick``: 150 and 1,200).
Each run is written as a user brings it (:func:`graph.simulate.write_run`: ``cam1.csv`` ... ``cam6.csv``,
DeepLabCut CSV, and ``calibration.toml``) and solved by

    acinoset solve cam1.csv ... cam6.csv --calibration calibration.toml --fps 120 --method fte \\
        --skeleton cheetah --out run.csv --report report.json

every other option at its default (the body estimated, the uncertainties computed). Timed, per run:

* the whole command as a new process (``subprocess``, ``ACINOSET_RESIDENT=0``: solved in the process
  itself), wall seconds around it (``time.perf_counter``), its CPU seconds (user + system) and its peak
  resident memory (GNU ``/usr/bin/time -f %M``: the command's own), ``--repeats`` times
  (default 3), after one untimed warm-up command (the shortest run, seed 0) that leaves numba's kernels
  compiled and cached. The repeats are the outer loop (every length and seed once, then again): the
  machine is shared, and a burst of another process's load then falls on all of them alike;
* from the report: the solve's own seconds (``seconds.total``, :func:`graph.api.solve` alone: no
  interpreter start, imports or file reading and writing) and the optimiser's iterations;
* the 3D error of the written ``run.csv`` against the simulated truth (:func:`graph.metrics.position_error`:
  mean and median mm);
* unless ``--no-resident``: the same commands handed to a warm resident process (graph.app.resident;
  ``ACINOSET_RESIDENT=1`` in a private runtime directory of this run, started by one solve, waited for
  until ready, stopped at the end; each timed command checked to have been served by it, and its CSV
  compared with the new process's). Its peak memory is the resident's child's, not measured here.

Per (length, seed) the median over the repeats; per length the median over the seeds. The ratios
1,200 / 150 frames of (a) the whole command's wall time, (b) the solve's own seconds and (c) the
iterations, each the ratio of the two medians over the seeds. The target: 1,200 frames in at most 10x the
time of 150 frames (8x the frames), judged for (a) and (b).

Prints Markdown tables and writes bench/results/length.json (``--out``).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
import warnings
from pathlib import Path

import harness as h
import numpy as np

from graph.io.results import read_anipose_csv
from graph.metrics import position_error
from graph.simulate import simulate_run, write_run

ACINOSET = str(Path(sys.executable).with_name("acinoset"))
SPEED = 1.0  # m/s: a slow run
TARGET_RATIO = 10.0  # 1,200 frames in at most 10x the time of 150
BASE, LONG = 150, 1200


def simulate(cal, frames: int, seed: int):
    """A slow run in the harness's target protocol (harness.simulate has no speed)."""
    t = h.TARGET
    return simulate_run(cal, frames=frames, fps=t["fps"], noise=t["noise"], outliers=t["outliers"],
                        outlier_std=t["outlier_std"], seed=seed, confident_outliers=1.0, speed=SPEED)


def run_command(cmd: list[str], env: dict) -> dict:
    """:func:`harness.time_command`, stopping the bench at a command that fails."""
    c = h.time_command(cmd, env)
    if c["exit"] != 0:
        raise SystemExit(f"{' '.join(cmd[:3])}...: exit {c['exit']}: {c['stderr_tail'][-600:]}")
    return {k: c[k] for k in ("wall_s", "cpu_s", "peak_rss_mib", "load")}


def solve_command(d: Path, run) -> list[str]:
    cams = [str(d / f"{name}.csv") for name in run.calibration.names]
    return [ACINOSET, "solve", *cams, "--calibration", str(d / "calibration.toml"), "--fps", str(run.fps),
            "--method", "fte", "--skeleton", "cheetah", "--out", str(d / "run.csv"),
            "--report", str(d / "report.json")]


def csv_error(d: Path, run) -> dict:
    """3D error of the command's run.csv against the truth, markers matched by name."""
    pts = read_anipose_csv(d / "run.csv")
    index = {m: k for k, m in enumerate(pts.markers)}
    est = np.full(run.positions.shape, np.nan)
    for k, m in enumerate(run.markers):
        if m in index:
            est[:, k] = pts.positions[:, index[m]]
    e = position_error(est, run.positions, run.markers)
    return {"mean_mm": e.mean_mm, "median_mm": e.median_mm, "p90_mm": e.p90_mm, "coverage": e.coverage}


def served(runtime: Path) -> int:
    """How many solves the residents of ``runtime`` have served (their logs)."""
    return sum(log.read_text().count(" served child ") for log in (runtime / "acinoset").glob("*.log"))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="150 and 1,200 frames only")
    ap.add_argument("--lengths", default=None, help="frames, comma-separated (default 150,600,1200,2400)")
    ap.add_argument("--seeds", default="0,1,2")
    ap.add_argument("--repeats", type=int, default=3, help="timed commands per (length, seed); their median")
    ap.add_argument("--no-resident", action="store_true", help="skip the commands served by a warm resident")
    ap.add_argument("--out", default="length", help="bench/results/OUT.json")
    args = ap.parse_args()
    warnings.filterwarnings("ignore")
    lengths = ([int(v) for v in args.lengths.split(",")] if args.lengths
               else [BASE, LONG] if args.quick else [BASE, 600, LONG, 2400])
    seeds = [int(v) for v in args.seeds.split(",")]
    info = h.machine()
    print(f"# solve time against length: {lengths} frames, seeds {seeds}, {args.repeats} repeats, speed {SPEED} m/s; "
          f"{info['cpu']}, {info['cores']} cores, load {info['load_average'][0]:.2f}", flush=True)
    cal = h.rig()
    med = statistics.median
    alone = {**os.environ, "ACINOSET_RESIDENT": "0"}
    keys = [(n, seed) for n in lengths for seed in seeds]
    per: dict[tuple[int, int], dict] = {k: {"commands": [], "resident_commands": []} for k in keys}
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        runs = {}
        for n, seed in keys:
            d = root / f"{n}_{seed}"
            run = simulate(cal, n, seed)
            write_run(run, d)
            runs[n, seed] = (d, run)
        d0, run0 = runs[keys[0]]
        t_warm = run_command(solve_command(d0, run0), alone)["wall_s"]  # untimed: kernels compiled or loaded
        print(f"  warm-up command: {t_warm:.2f} s", flush=True)

        def timed_command(key, env) -> dict:
            d, run = runs[key]
            c = run_command(solve_command(d, run), env)
            report = json.loads((d / "report.json").read_text())
            return {**c, "solve_s": report["seconds"]["total"], "seconds": report["seconds"],
                    "iterations": report["iterations"], "warnings": report.get("warnings", [])}

        # the repeats outermost: a burst of load from another process spreads over every length and seed
        for rep in range(args.repeats):
            for key in keys:
                c = timed_command(key, alone)
                d, run = runs[key]
                if rep == 0:
                    per[key]["error"] = csv_error(d, run)
                    (d / "run.csv").replace(d / "alone.csv")  # the new process's CSV, for the others to match
                else:
                    c["csv_same_as_first"] = (d / "run.csv").read_bytes() == (d / "alone.csv").read_bytes()
                per[key]["commands"].append(c)
                print(f"  repeat {rep + 1}, {key[0]:>5} frames, seed {key[1]}: command {c['wall_s']:.2f} s "
                      f"(cpu {c['cpu_s']:.2f} s, peak {c['peak_rss_mib']:.0f} MiB), solve {c['solve_s']:.2f} s, "
                      f"{c['iterations']} iterations, load {c['load']:.2f}", flush=True)

        resident_note = "skipped (--no-resident)"
        if not args.no_resident:
            runtime = root / "runtime"
            runtime.mkdir(mode=0o700)
            warm = {**os.environ, "ACINOSET_RESIDENT": "1", "XDG_RUNTIME_DIR": str(runtime)}
            try:
                t_start = run_command(solve_command(d0, run0), warm)["wall_s"]  # its own process; starts the resident
                t0 = time.perf_counter()
                while "ready" not in subprocess.run([ACINOSET, "resident", "status"], capture_output=True,
                                                    text=True, env=warm).stdout:
                    if time.perf_counter() - t0 > 600:
                        raise SystemExit("the resident did not get warm in 10 minutes")
                    time.sleep(0.2)
                print(f"  resident: started by a {t_start:.2f} s solve, ready {time.perf_counter() - t0:.1f} s later",
                      flush=True)
                for rep in range(args.repeats):
                    for key in keys:
                        before = served(runtime)
                        c = timed_command(key, warm)
                        t0 = time.perf_counter()  # the resident logs a solve when it reaps the child, just after
                        while served(runtime) != before + 1 and time.perf_counter() - t0 < 5:
                            time.sleep(0.01)
                        if served(runtime) != before + 1:
                            raise SystemExit("a solve meant for the resident was not served by it")
                        d, _ = runs[key]
                        c["csv_same_as_first"] = (d / "run.csv").read_bytes() == (d / "alone.csv").read_bytes()
                        del c["peak_rss_mib"], c["cpu_s"]  # the client's, not the solve's
                        per[key]["resident_commands"].append(c)
                        print(f"  repeat {rep + 1}, {key[0]:>5} frames, seed {key[1]}: served by the resident "
                              f"{c['wall_s']:.2f} s, its solve {c['solve_s']:.2f} s, CSV as in its own process: "
                              f"{c['csv_same_as_first']}, load {c['load']:.2f}", flush=True)
                resident_note = "measured"
            finally:
                subprocess.run([ACINOSET, "resident", "stop"], capture_output=True, env=warm)

    def median_of(key, field: str, which: str = "commands") -> float:
        """The median over the repeats of one (length, seed)."""
        return med(c[field] for c in per[key][which])

    def phase(key, name: str, which: str = "commands") -> float:
        return med(c["seconds"].get(name, float("nan")) for c in per[key][which])

    def over_seeds(n: int, get) -> float:
        """The median over the seeds of ``get((n, seed))``."""
        return med(get((n, s)) for s in seeds)

    summary = {}
    for n in lengths:
        row = {"frames": n,
               "wall_s": over_seeds(n, lambda k: median_of(k, "wall_s")),
               "cpu_s": over_seeds(n, lambda k: median_of(k, "cpu_s")),
               "peak_rss_mib": over_seeds(n, lambda k: median_of(k, "peak_rss_mib")),
               "solve_s": over_seeds(n, lambda k: median_of(k, "solve_s")),
               "iterations": over_seeds(n, lambda k: median_of(k, "iterations")),
               "init_s": over_seeds(n, lambda k: phase(k, "init")),
               "optimise_s": over_seeds(n, lambda k: phase(k, "solve")),
               "uncertainty_s": over_seeds(n, lambda k: phase(k, "uncertainty")),
               "error_mean_mm": over_seeds(n, lambda k: per[k]["error"]["mean_mm"]),
               "error_median_mm": over_seeds(n, lambda k: per[k]["error"]["median_mm"]),
               "coverage": over_seeds(n, lambda k: per[k]["error"]["coverage"]),
               "csv_repeatable": all(c.get("csv_same_as_first", True) for s in seeds
                                     for c in per[n, s]["commands"] + per[n, s]["resident_commands"])}
        if not args.no_resident:
            row["resident_wall_s"] = over_seeds(n, lambda k: median_of(k, "wall_s", "resident_commands"))
            row["resident_solve_s"] = over_seeds(n, lambda k: median_of(k, "solve_s", "resident_commands"))
        row["solve_ms_per_frame"] = 1000 * row["solve_s"] / n
        summary[n] = row

    print()
    resident = not args.no_resident
    print(h.markdown_table(
        ["frames", "command s", "command cpu s", "peak MiB", "solve s", "solve ms/frame", "init s", "optimise s",
         "uncertainty s", "iterations", "error mean mm", "error median mm", "coverage",
         *(["resident command s", "resident solve s"] if resident else [])],
        [[n, r["wall_s"], r["cpu_s"], r["peak_rss_mib"], r["solve_s"], r["solve_ms_per_frame"], r["init_s"],
          r["optimise_s"], r["uncertainty_s"], f"{r['iterations']:g}", r["error_mean_mm"], r["error_median_mm"],
          r["coverage"], *([r["resident_wall_s"], r["resident_solve_s"]] if resident else [])]
         for n, r in summary.items()]))
    print("\nper seed (median over the repeats):")
    print(h.markdown_table(
        ["frames", "seed", "command s", "solve s", "iterations", "error mean mm", "error median mm",
         *(["resident command s", "resident solve s"] if resident else [])],
        [[n, s, median_of((n, s), "wall_s"), median_of((n, s), "solve_s"), f"{median_of((n, s), 'iterations'):g}",
          per[n, s]["error"]["mean_mm"], per[n, s]["error"]["median_mm"],
          *([median_of((n, s), "wall_s", "resident_commands"), median_of((n, s), "solve_s", "resident_commands")]
            if resident else [])] for n, s in keys]))

    ratios, verdict = {}, {}
    if BASE in summary:
        base = summary[BASE]
        print()
        measures = [("wall_s", "(a) whole command, wall"), ("solve_s", "(b) solve seconds (report)"),
                    ("iterations", "(c) iterations"), ("cpu_s", "whole command, cpu")]
        if resident:
            measures += [("resident_wall_s", "command served by the resident, wall"),
                         ("resident_solve_s", "solve seconds in the resident")]
        others = [n for n in lengths if n != BASE]
        rows = []
        for name, label in measures:
            ratios[name] = {n: summary[n][name] / base[name] for n in others}
            rows.append([label, *[ratios[name][n] for n in others]])
        rows.append(["frames", *[n / BASE for n in others]])
        print(h.markdown_table([f"ratio to {BASE} frames", *[f"{n} / {BASE}" for n in others]], rows))
        if LONG in summary:
            print()
            for name, label in measures[:2] + (measures[4:6] if resident else []):
                r = ratios[name][LONG]
                verdict[name] = {"ratio": r, "target": TARGET_RATIO, "met": bool(r <= TARGET_RATIO)}
                print(f"target, {label}: {LONG} frames in {r:.2f}x the time of {BASE} "
                      f"(at most {TARGET_RATIO:g}x): {'met' if r <= TARGET_RATIO else 'NOT met'}")
    after = os.getloadavg()
    print(f"load average at the end: {after[0]:.2f} {after[1]:.2f} {after[2]:.2f}")
    path = h.save(args.out, {
        "machine": info, "load_average_end": list(after), "args": vars(args), "lengths": lengths, "seeds": seeds,
        "speed_m_s": SPEED, "protocol": {**h.TARGET, "confident_outliers": 1.0, "method": "fte", "skeleton": "cheetah"},
        "warm_up_s": t_warm, "resident": resident_note,
        "runs": {str(n): {str(s): per[n, s] for s in seeds} for n in lengths},
        "summary": {str(n): v for n, v in summary.items()},
        "ratios_to_150": {k: {str(n): v for n, v in r.items()} for k, r in ratios.items()},
        "target_1200_over_150": verdict})
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
