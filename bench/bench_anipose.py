"""A whole Anipose project through ``acinoset anipose`` against ``acinoset solve`` run per trial, and
against Anipose's own ``anipose triangulate`` on the same, unchanged project.

    python bench/bench_anipose.py [--sessions 2] [--trials 3] [--frames 500] [--jobs 2]

The project (:mod:`graph.anipose.simulate`): ``--sessions`` sessions of ``--trials`` trials, each a
simulated cheetah run (8 markers as free points, 5 px noise, 10 % outliers) on three cameras of the
real AcinoSet rig, DeepLabCut H5 per camera, ``optim = true`` with 4 limb ``constraints``, so ours
runs ``fte`` with those bones and Anipose runs ``triangulate_optim``.

Timed (wall clock, the whole command, as a user waits for it; after one untimed ``acinoset solve``
that loads the compiled kernels):

* ``acinoset solve`` once per trial, one after another (a shell loop over the trials);
* ``acinoset anipose --force`` with ``--jobs 1`` and ``--jobs N``;
* ``acinoset anipose`` again with everything up to date (the no-op re-run);
* ``anipose triangulate`` (the peer, if the ``anipose`` package is importable: ``pip install
  --no-deps anipose`` beside aniposelib, into a folder given by ``--anipose-path``) on a copy.

The 3D error of each tool's ``pose-3d`` CSVs against the simulated truth is reported too. Writes
bench/results/anipose.json (``--name``) and prints a Markdown table.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import harness as h  # noqa: E402

from graph.anipose import load_project  # noqa: E402
from graph.anipose.simulate import CONSTRAINTS, simulated_trials, write_project  # noqa: E402
from graph.io.results import read_anipose_csv  # noqa: E402

EXE = Path(sys.executable).with_name("acinoset")


def wall(cmd: list, cwd=None, env=None) -> float:
    t0 = time.perf_counter()
    proc = subprocess.run([str(c) for c in cmd], cwd=cwd, env=env, capture_output=True, text=True)
    seconds = time.perf_counter() - t0
    if proc.returncode != 0:
        raise SystemExit(f"{' '.join(map(str, cmd[:3]))} failed:\n{proc.stderr[-2000:]}")
    return seconds


def errors(root: Path, sessions: dict, frames: int, fps: float) -> dict:
    """Mean and median 3D error (mm) over every trial's pose-3d CSV against the truth."""
    per = []
    for session, trial, run in simulated_trials(sessions, frames, fps):
        est = read_anipose_csv(root / session / "pose-3d" / f"{trial}.csv")
        order = [est.markers.index(m) for m in run.markers]
        per.append(h.error_mm(est.positions[:, order], run))
    return {"mean_mm": float(np.mean([e["mean_mm"] for e in per])),
            "median_mm": float(np.mean([e["median_mm"] for e in per])),
            "coverage": float(np.mean([e["coverage"] for e in per])), "per_trial": per}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sessions", type=int, default=2)
    ap.add_argument("--trials", type=int, default=3, help="trials per session")
    ap.add_argument("--frames", type=int, default=500)
    ap.add_argument("--fps", type=float, default=120.0)
    ap.add_argument("--jobs", type=int, default=os.cpu_count() or 2)
    ap.add_argument("--anipose-path", default=None, help="a folder holding the anipose package (pip --target)")
    ap.add_argument("--name", default="anipose", help="results file: bench/results/NAME.json")
    args = ap.parse_args()

    sessions = {f"2026-12-{s + 1:02d}": [f"trial{s * args.trials + t + 1}" for t in range(args.trials)]
                for s in range(args.sessions)}
    tmp = Path(tempfile.mkdtemp(prefix="bench-anipose-"))
    root = write_project(tmp / "project", sessions=sessions, frames=args.frames, fps=args.fps)
    pristine = tmp / "pristine"
    shutil.copytree(root, pristine)
    trials = load_project(root).trials
    bones = ",".join(f"{a}-{b}" for a, b in CONSTRAINTS)
    info = h.machine()

    def solve_cmd(t, out: Path) -> list:
        return [EXE, "solve", *t.pose_files, "--calibration", t.calibration, "--method", "fte", "--skeleton",
                "points", "--bones", bones, "--likelihood-threshold", "0.5", "--fps", args.fps,
                "--out", out.with_suffix(".csv"), "--h5", out.with_suffix(".h5")]

    wall(solve_cmd(trials[0], tmp / "warmup"))  # untimed: loads (or compiles) the kernels
    times: dict[str, float] = {}
    solo = tmp / "solo"
    solo.mkdir()
    times["acinoset solve per trial"] = sum(wall(solve_cmd(t, solo / f"{t.session}_{t.name}")) for t in trials)
    times["acinoset anipose --jobs 1"] = wall([EXE, "anipose", root, "--force", "--jobs", "1"])
    times[f"acinoset anipose --jobs {args.jobs}"] = wall([EXE, "anipose", root, "--force", "--jobs", args.jobs])
    times["acinoset anipose (re-run, up to date)"] = wall([EXE, "anipose", root])
    accuracy = {"acinoset": errors(root, sessions, args.frames, args.fps)}

    peer = None
    env = dict(os.environ)
    if args.anipose_path:
        env["PYTHONPATH"] = os.pathsep.join(filter(None, [args.anipose_path, env.get("PYTHONPATH")]))
    has_anipose = subprocess.run([sys.executable, "-c", "import anipose.triangulate"], env=env,
                                 capture_output=True).returncode == 0
    if has_anipose:
        theirs = tmp / "anipose"
        shutil.copytree(pristine, theirs)
        times["anipose triangulate (optim, constraints)"] = wall(
            [sys.executable, "-m", "anipose.anipose", "triangulate"], cwd=theirs, env=env)
        accuracy["anipose"] = errors(theirs, sessions, args.frames, args.fps)
        import importlib.metadata as md

        peer = {"anipose": subprocess.run([sys.executable, "-c", "import importlib.metadata as m; "
                                           "print(m.version('anipose'))"], env=env, capture_output=True,
                                          text=True).stdout.strip(), "aniposelib": md.version("aniposelib")}
    info["load_average_after"] = list(os.getloadavg())
    n = len(trials)
    rows = [[name, f"{s:.1f}", f"{s / n:.2f}"] for name, s in times.items()]
    print(f"{n} trials x {args.frames} frames, 3 cameras, 8 markers; load average before "
          f"{info.get('load_average')}, after {info['load_average_after']}")
    print(h.markdown_table(["run", "wall s (whole project)", "s per trial"], rows))
    for tool, e in accuracy.items():
        print(f"{tool}: mean 3D error {e['mean_mm']:.1f} mm, median {e['median_mm']:.1f} mm, "
              f"coverage {e['coverage']:.3f}")
    path = h.save(args.name, {"machine": info, "args": vars(args), "trials": n, "times_s": times,
                              "accuracy": accuracy, "peer_versions": peer})
    print(f"-> {path}")
    shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
