"""What a user waits for: the whole ``acinoset solve`` process from a shell, against aniposelib.

    python bench/bench_cold_start.py [--frames 150] [--repeats 5] [--compile] [--install regular]

A simulated 150-frame run on the AcinoSet rig (6 cameras, 120 fps, 5 px noise, 10 % outliers;
bench/harness.py), written as a user brings it (``cam1.csv`` ... and ``calibration.toml``). Timed:

* ``acinoset --version`` and ``acinoset solve --help`` (the parser alone);
* ``acinoset solve ... --out run.csv --h5 run.h5`` as a new process, after one earlier run has
  filled numba's cache (every default: ``fte``, the cheetah, the body estimated), the median of
  ``--repeats``; the solve's own ``seconds.total`` from its report beside it. Twice: solved in the
  process itself (``ACINOSET_RESIDENT=0``), and handed to the warm resident process that an earlier
  ``acinoset solve`` started (graph.app.resident; in a private runtime directory of this run, stopped at
  the end; every timed run checked to have been served, and its CSV to equal the in-process one);
* aniposelib's ``triangulate_optim`` call alone on the same detections, in this process (its
  import, the camera group and the threshold not counted), with every bone a limb constraint;
* with ``--compile``, the first ``acinoset solve`` after an install: a new ``NUMBA_CACHE_DIR`` so
  that every kernel compiles, as on a fresh machine.

The package's modules are byte-compiled first, as ``pip install`` leaves them (an environment with
``PYTHONDONTWRITEBYTECODE`` set would otherwise compile every module from source in every process).

``--install regular`` times the ``acinoset`` of a user's install instead of this editable one: a
temporary virtual environment with the project installed by pip, not editable, and this
environment's dependencies on its path. An editable install puts setuptools' import finder in every
process's start (``site`` imports it, with ``pathlib``, ``re`` and ``urllib.parse``: 18 ms of a
30 ms interpreter start here); an install from PyPI or ``pip install .`` has none. Its kernels
compile once in that environment before the timed runs (the bench says so).

Writes bench/results/cold_start.json.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
import warnings
from pathlib import Path

import harness as h

from graph.io.calibration import write_anipose_toml
from graph.io.keypoints import write_dlc_csv

ACINOSET = str(Path(sys.executable).with_name("acinoset"))


def regular_install(dest: Path) -> str:
    """The project installed at ``dest`` as ``pip install .`` leaves it (no editable finder), in a
    virtual environment that sees this one's dependencies; returns its ``acinoset``."""
    import sysconfig

    root = Path(__file__).resolve().parents[1]
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(dest)], check=True)
    python = dest / "bin" / "python"
    site = Path(subprocess.run([str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                               capture_output=True, text=True, check=True).stdout.strip())
    # this venv's packages, after its own
    (site / "dependencies.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    with tempfile.TemporaryDirectory() as build:  # a copy: pip's build must not write into the checkout
        src = Path(build) / "src"
        shutil.copytree(root, src,
                        ignore=shutil.ignore_patterns(".venv", ".git", "__pycache__", "results", "*.egg-info"))
        subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--no-deps",
                        "--target", str(site), str(src)], check=True)
    script = dest / "bin" / "acinoset"  # pip's console script, run by the new environment's python
    made = (site / "bin" / "acinoset").read_text().split("\n", 1)[1]
    script.write_text(f"#!{python}\n{made}")
    script.chmod(0o755)
    import compileall

    for package in ("graph", "service"):
        compileall.compile_dir(site / package, quiet=1)
    return str(script)


def wall(cmd: list[str], env: dict | None = None) -> tuple[float, subprocess.CompletedProcess]:
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env)
    t = time.perf_counter() - t0
    if proc.returncode != 0:
        raise SystemExit(f"{' '.join(cmd[:3])}...: exit {proc.returncode}: {proc.stderr.strip()[-400:]}")
    return t, proc


def served(runtime: Path) -> int:
    """How many solves the residents of ``runtime`` have served (their logs)."""
    return sum(log.read_text().count(" served child ") for log in (runtime / "acinoset").glob("*.log"))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, default=150)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--compile", action="store_true", help="also time a first run with an empty kernel cache")
    ap.add_argument("--install", choices=["editable", "regular"], default="editable",
                    help="whose acinoset: this editable install's, or a temporary regular install's")
    args = ap.parse_args()
    global ACINOSET
    warnings.filterwarnings("ignore")
    import compileall

    import graph
    import service

    for package in (graph, service):
        compileall.compile_dir(Path(package.__file__).parent, quiet=1)
    info = h.machine()
    print(f"# whole process: {args.frames} frames; {info['cpu']}, {info['cores']} cores, "
          f"load {info['load_average'][0]:.1f}", flush=True)
    cal = h.rig()
    run = h.simulate(cal, frames=args.frames, seed=0)
    out: dict = {"machine": info, "args": vars(args)}
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        if args.install == "regular":
            ACINOSET = regular_install(d / "venv")
            print(f"  a regular install at {d / 'venv'}; its kernels compile in the first run", flush=True)
        cams = []
        for name, kp in zip(cal.names, run.keypoints):
            write_dlc_csv(d / f"{name}.csv", kp)
            cams.append(str(d / f"{name}.csv"))
        write_anipose_toml(d / "calibration.toml", cal)
        solve = [ACINOSET, "solve", *cams, "--calibration", str(d / "calibration.toml"), "--fps", str(run.fps),
                 "--out", str(d / "run.csv"), "--h5", str(d / "run.h5"), "--report", str(d / "report.json")]

        if args.compile:
            cache = d / "numba-cache"
            env = {**os.environ, "NUMBA_CACHE_DIR": str(cache)}
            t, proc = wall(solve, env)
            said = [line for line in proc.stderr.splitlines() if "compiling" in line]
            out["first_run_s"] = t
            out["first_run_said"] = said
            print(f"  first run after install (empty kernel cache): {t:.1f} s; said: {said[:1]}", flush=True)
            shutil.rmtree(cache, ignore_errors=True)

        version = [wall([ACINOSET, "--version"])[0] for _ in range(args.repeats)]
        helps = [wall([ACINOSET, "solve", "--help"])[0] for _ in range(args.repeats)]
        alone = {**os.environ, "ACINOSET_RESIDENT": "0"}
        wall(solve, alone)  # fills the cache if it was empty
        runs, inner = [], []
        for _ in range(args.repeats):
            t, _ = wall(solve, alone)
            runs.append(t)
            inner.append(json.loads((d / "report.json").read_text())["seconds"]["total"])
        reference = (d / "run.csv").read_bytes()

        runtime = d / "runtime"
        runtime.mkdir(mode=0o700)
        warm = {**os.environ, "ACINOSET_RESIDENT": "1", "XDG_RUNTIME_DIR": str(runtime)}
        try:
            t_start, _ = wall(solve, warm)  # in its own process; starts the resident
            t0 = time.perf_counter()
            while "ready" not in wall([ACINOSET, "resident", "status"], warm)[1].stdout:
                if time.perf_counter() - t0 > 600:
                    raise SystemExit("the resident did not get warm in 10 minutes")
                time.sleep(0.2)
            warm_s = time.perf_counter() - t0
            resident, resident_inner = [], []
            for _ in range(args.repeats):
                before = served(runtime)
                t, _ = wall(solve, warm)
                t0 = time.perf_counter()  # the resident logs a solve when it reaps the child, just after
                while served(runtime) != before + 1 and time.perf_counter() - t0 < 5:
                    time.sleep(0.01)
                if served(runtime) != before + 1:
                    raise SystemExit("a solve meant for the resident was not served by it")
                if (d / "run.csv").read_bytes() != reference:
                    raise SystemExit("the resident's CSV differs from the in-process one")
                resident.append(t)
                resident_inner.append(json.loads((d / "report.json").read_text())["seconds"]["total"])
        finally:
            wall([ACINOSET, "resident", "stop"], warm)
        cg = h.anipose_group(cal)
        pts = h.anipose_points(run)
        cons = h.bone_constraints(run)
        anipose = []
        for _ in range(max(1, min(args.repeats, 3))):
            t0 = time.perf_counter()
            h.anipose_triangulate_optim(cg, pts, cons)
            anipose.append(time.perf_counter() - t0)
    med = statistics.median
    out.update({"version_s": version, "solve_help_s": helps, "solve_process_s": runs, "solve_in_process_s": inner,
                "resident_first_solve_s": t_start, "resident_warm_up_s": warm_s,
                "solve_process_resident_s": resident, "solve_in_resident_s": resident_inner,
                "aniposelib_triangulate_optim_s": anipose,
                "ratio_process": med(anipose) / med(runs), "ratio_process_resident": med(anipose) / med(resident),
                "ratio_in_process": med(anipose) / med(inner)})
    print(f"  acinoset --version       median {med(version):.3f} s (best {min(version):.3f})")
    print(f"  acinoset solve --help    median {med(helps):.3f} s (best {min(helps):.3f})")
    print(f"  acinoset solve (process) median {med(runs):.2f} s (best {min(runs):.2f}); its solve() {med(inner):.2f} s")
    print(f"  acinoset solve (served by the resident) median {med(resident):.3f} s (best {min(resident):.3f}); "
          f"its solve() {med(resident_inner):.3f} s; the run that started it {t_start:.2f} s, "
          f"warm {warm_s:.1f} s later")
    print(f"  aniposelib triangulate_optim alone: median {med(anipose):.2f} s")
    print(f"  ratio: {out['ratio_process']:.1f}x the whole process on its own, {out['ratio_process_resident']:.1f}x "
          f"the whole process served by the resident, {out['ratio_in_process']:.1f}x the solve in process")
    path = h.save("cold_start", out)
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
