"""An hour of recording at bounded memory (issue 29): ``acinoset solve`` from a shell on runs of 1, 10 and 60 minutes.

    .venv/bin/python bench/bench_long.py [--minutes 1,10] [--quick] [--work DIR] [--keep] [--seed 0]
                                         [--aniposelib-minutes 1,10] [--aniposelib-seconds 400]
                                         [--block-frames 7200] [--no-aniposelib] [--jobs N] [--out long]

The runs: the simulator's cheetah walking slowly (``simulate_run(rig, frames=N, seed=0, speed=1.0)``:
1 m/s along its figure of eight) on the AcinoSet 2019 six-camera rig at 120 fps, with the simulator's
default detections (5 px noise, 10 % outliers of sigma 100 px, 30 % of the outliers with a high
likelihood and the rest with a low one); 1, 10 and 60 minutes: 7,200, 72,000 and 432,000 frames
(``--minutes``; default 1 and 10, ``--quick`` the same; the 60 minutes are opt-in: about 10 minutes
of solving and 6.7 GB of disk). Each run is written as a user brings it (:func:`graph.simulate.write_run`:
``cam1.csv`` ... ``cam6.csv`` DeepLabCut CSVs, ``calibration.toml``, ``truth.npz``) into a scratch
folder (``--work``, default a new folder under the system's temporary directory), one run at a time,
deleted once measured unless ``--keep``. The free disk is checked first against about 15.5 KB a frame
(inputs, truth and the written CSV) and the bench says how much it needs.

Solved, after one untimed warm-up command on a 150-frame run (numba's kernels loaded or compiled
into its cache), by the whole command as a new process

    ACINOSET_RESIDENT=0 /usr/bin/time acinoset solve cam1.csv ... cam6.csv --calibration calibration.toml \\
        --fps 120 --out run.csv --report report.json

every option at its default (``fte``, the cheetah skeleton, the body estimated, the uncertainties
computed; a run over :data:`graph.types.WINDOWED_ABOVE` frames solved in windows of
:data:`graph.types.WINDOW_FRAMES` kept frames, :mod:`graph.solve.windows`). Per run: the wall seconds
around the command (``time.perf_counter``), its CPU seconds and peak resident memory (GNU time's
``%M``: the command's own, MiB), its exit status (a failed command is recorded with its last stderr
line, not raised), and from its report the solve's ``seconds``, ``iterations`` and ``windows``.

The accuracy: the command's ``run.csv`` read back (pandas, the marker columns; checked on the first
run to equal :func:`graph.io.results.read_anipose_csv` to the bit) and scored against the simulated
truth over every marker and frame (:func:`graph.metrics.position_error`: mean, median, p90, max mm,
coverage), and the mean per minute of the run (does it drift?). The issue's target is "accuracy
equal to the one-minute solve's per-frame error", read here as mean and median within 5 % of the
1-minute run's (a different trajectory and different draws, so not to the digit).

On the 1-minute run also the whole run at once (``--window-frames 0``), its time and memory, and
the per-frame difference between the windowed and the whole positions (largest and median over
every marker and frame, and the largest within 20 frames of a window's seam and away from them).
The windows hold what the best-seen 2,000 frames settled (the body's lengths, noise, motion scales),
the whole solve estimates them from every frame, so the difference is not only the seams': the
largest relative difference between the two reports' body lengths is printed beside it.

aniposelib (0.8.0, in its own process under ``/usr/bin/time``: ``bench_long.py --aniposelib-only``),
on the 1- and 10-minute runs (``--aniposelib-minutes``), on the same detections read from the same
CSVs: points below Anipose's default score threshold (0.8) set to NaN as ``anipose triangulate``
does, the ``CameraGroup`` loaded from the run's ``calibration.toml``; after an untimed warm-up call
on 100 frames (numba's and jax's compiles), timed: ``triangulate`` (plain DLT, ``optim = false``) on
every frame, and ``triangulate_optim`` with every cheetah bone a limb constraint and Anipose's
default scales (:func:`harness.anipose_triangulate_optim`, as bench/bench_aniposelib.py). Its
optimiser (scipy's sparse least squares) holds about 0.45 MB a frame and took 184 s for 7,200 frames
here (3.4 GB peak; 48 s for 1,000, 73 s for 4,000), so 72,000 frames at once would need some 30 GB
(this machine has 23) and in one-minute pieces about 30 minutes. No other bench runs aniposelib on
a long run, so here it is run as a user cuts a long recording into trials: on consecutive blocks of
``--block-frames`` (default 7,200, a minute: the 1-minute run is one block, the whole run) from the
start of the run, each its own call, for as long as the next block is expected to end within
``--aniposelib-seconds`` (default 400 s of optimiser: two blocks of the 10-minute run) of the
first's start. Only what ran is reported: the frames it covered, its seconds, and its error over
those frames beside acinoset's over the same frames. The process's wall and peak memory include its
imports, reading the CSVs, the warm-up and ``triangulate`` (all frames).

Targets (the issue), printed beside the numbers: 60 minutes in at most 10 minutes of wall time and
2 GB of peak resident memory; 10 minutes in at most 100 s and 1 GB (GB read as GiB: 2,048 and 1,024 MiB).

``--jobs N``: each run also solved with ``--jobs N`` (windows in N worker processes) and, for a
like-for-like figure, once more in one process, both under a sampler that sums the resident memory
of the command's whole process tree every 0.1 s (GNU time counts the command's own process only);
whether the two CSVs are the same bytes.

Prints progress lines to stderr, Markdown tables to stdout, and writes bench/results/long.json (``--out``).
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import shutil
import sys
import tempfile
import time
import traceback
import warnings
from pathlib import Path

import harness as h
import numpy as np

from graph.io.results import read_anipose_csv
from graph.metrics import position_error
from graph.simulate import load_truth, simulate_run, write_run

ACINOSET = str(Path(sys.executable).with_name("acinoset"))
FPS = 120.0
SPEED = 1.0  # m/s: a slow walk
WARM_FRAMES = 150
# on disk: six DeepLabCut CSVs, truth.csv/.npz, run.csv (measured 10.2 KB + ~2 KB), and while it runs the
# command's staged inputs in run.csv.partial/ (6 cameras x 20 markers x 3 float64: 2.9 KB)
BYTES_PER_FRAME = 15_500
TARGETS = {10: {"wall_s": 100.0, "peak_rss_mib": 1024.0}, 60: {"wall_s": 600.0, "peak_rss_mib": 2048.0}}
ACCURACY_TOLERANCE = 1.05  # "equal to the one-minute solve's": mean and median within 5 %
SEAM_NEAR = 20  # frames either side of a window seam
ANIPOSE_WARM_FRAMES = 100


def log(msg: str) -> None:
    print(f"[{time.strftime('%H:%M:%S')}] {msg}", file=sys.stderr, flush=True)


def last_line(text: str) -> str:
    lines = [ln for ln in text.strip().splitlines() if ln.strip()]
    return lines[-1][:500] if lines else ""


def command(cmd: list[str], env: dict) -> dict:
    """:func:`harness.time_command`, a failure recorded (exit status, last stderr line), never raised."""
    try:
        c = h.time_command(cmd, env)
    except Exception as exc:  # /usr/bin/time missing, its usage file unreadable, ...
        return {"exit": None, "wall_s": float("nan"), "cpu_s": float("nan"), "peak_rss_mib": float("nan"),
                "error": f"{type(exc).__name__}: {exc}", "stderr_last": f"{type(exc).__name__}: {exc}"}
    tail = c.pop("stderr_tail")
    c["stderr_last"] = last_line(tail)
    if c["exit"] != 0:
        c["stderr_tail"] = tail
    return c


def _tree(pid: int) -> list[int]:
    """``pid`` and every process below it (/proc's children lists)."""
    out, todo = [], [pid]
    while todo:
        p = todo.pop()
        out.append(p)
        for task in Path(f"/proc/{p}/task").glob("*"):
            try:
                todo += [int(c) for c in (task / "children").read_text().split()]
            except OSError:
                pass
    return out


def _rss_kib(pid: int) -> int:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
    except OSError:
        pass
    return 0


def tree_command(cmd: list[str], env: dict, every: float = 0.1) -> dict:
    """The command's wall seconds and the peak of its whole process tree's resident memory (the sum of
    VmRSS over it and its workers, sampled every ``every`` s; GNU time sees only the command's own)."""
    import subprocess

    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    peak = 0
    while proc.poll() is None:
        peak = max(peak, sum(_rss_kib(p) for p in _tree(proc.pid)))
        time.sleep(every)
    err = proc.stderr.read() if proc.stderr else ""
    return {"exit": proc.returncode, "wall_s": time.perf_counter() - t0, "tree_peak_rss_mib": peak / 1024,
            "stderr_last": last_line(err)}


def solve_command(d: Path, out: str = "run", extra: tuple[str, ...] = (), method: str = "fte") -> list[str]:
    cams = [str(d / f"cam{k}.csv") for k in range(1, 7)]
    return [ACINOSET, "solve", *cams, "--calibration", str(d / "calibration.toml"), "--fps", f"{FPS:g}",
            "--method", method, "--out", str(d / f"{out}.csv"), "--report", str(d / f"{out}.json"), *extra]


def make_run(cal, frames: int, seed: int, d: Path) -> float:
    """Simulate and write a run into ``d``; the seconds it took. Nothing of it is kept in memory."""
    t0 = time.perf_counter()
    run = simulate_run(cal, frames=frames, seed=seed, speed=SPEED)
    write_run(run, d)
    del run
    return time.perf_counter() - t0


def read_positions(path: Path, markers: list[str]) -> np.ndarray:
    """The command's CSV as (N, M, 3) metres in ``markers``' order (NaN for a marker it lacks), by pandas
    (:func:`graph.io.results.read_anipose_csv` holds every cell as a Python string: gigabytes at an hour)."""
    import pandas as pd

    with open(path, encoding="utf-8-sig") as f:
        header = [c.strip() for c in f.readline().rstrip("\r\n").split(",")]
    have = set(header)
    cols = [f"{m}_{a}" for m in markers for a in "xyz" if f"{m}_x" in have]
    frame = pd.read_csv(path, usecols=cols, dtype=np.float64, float_precision="round_trip", engine="c",
                        skipinitialspace=True)
    frame.columns = [c.strip() for c in frame.columns]
    out = np.full((len(frame), len(markers), 3), np.nan)
    for k, m in enumerate(markers):
        if f"{m}_x" in have:
            out[:, k] = frame[[f"{m}_x", f"{m}_y", f"{m}_z"]].to_numpy()
    return out


def reader_check(path: Path, markers: list[str], est: np.ndarray) -> bool:
    """Does :func:`read_positions` give what the project's reader gives, to the bit?"""
    pts = read_anipose_csv(path)
    index = {m: k for k, m in enumerate(pts.markers)}
    ref = np.full(est.shape, np.nan)
    for k, m in enumerate(markers):
        if m in index:
            ref[:, k] = pts.positions[:, index[m]]
    return bool(np.array_equal(ref, est, equal_nan=True))


def score(est: np.ndarray, truth: np.ndarray, markers: list[str]) -> dict:
    e = position_error(est, truth, markers)
    return {"mean_mm": e.mean_mm, "median_mm": e.median_mm, "p90_mm": e.p90_mm, "max_mm": e.max_mm,
            "coverage": e.coverage}


def per_minute_mean(est: np.ndarray, truth: np.ndarray) -> list[float]:
    """Mean 3D error (mm) over each minute of the run (the last one possibly shorter)."""
    e = np.linalg.norm(est - truth, axis=-1) * 1000.0
    step = int(60 * FPS)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return [float(np.nanmean(e[a:a + step])) for a in range(0, len(e), step)]


def report_fields(path: Path) -> dict:
    try:
        rep = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        return {"report_error": f"{type(exc).__name__}: {exc}"}
    return {"seconds": rep.get("seconds"), "iterations": rep.get("iterations"), "windows": rep.get("windows"),
            "body_lengths": rep.get("body_lengths"), "warnings": rep.get("warnings", [])}


def length_difference(a: dict | None, b: dict | None) -> float:
    """Largest relative difference between two reports' body lengths."""
    if not a or not b:
        return float("nan")
    out = [abs(a[k]["length_m"] / b[k]["length_m"] - 1.0) for k in a if k in b and b[k].get("length_m")]
    return max(out) if out else float("nan")


def seams_of(frames: int, windows: dict | None) -> list[int]:
    if not windows:
        return []
    return list(range(int(windows["core_frames"]), frames, int(windows["core_frames"])))


def compare(windowed: np.ndarray, whole: np.ndarray, seams: list[int]) -> dict:
    """Per-frame, per-marker distance (mm) between two solves of one run."""
    d = np.linalg.norm(windowed - whole, axis=-1) * 1000.0  # (N, M)
    per_frame = np.nanmax(d, axis=1)
    near = np.zeros(len(per_frame), bool)
    for s in seams:
        near[max(0, s - SEAM_NEAR):s + SEAM_NEAR] = True
    nan = float("nan")
    return {"max_mm": float(np.nanmax(d)), "median_mm": float(np.nanmedian(d)), "mean_mm": float(np.nanmean(d)),
            "p99_mm": float(np.nanpercentile(d, 99)),
            "max_near_seams_mm": float(per_frame[near].max()) if near.any() else nan,
            "max_away_from_seams_mm": float(per_frame[~near].max()) if (~near).any() else nan,
            "worst_frame": int(np.nanargmax(per_frame)), "seams": seams}


# ------------------------------------------------------------------------------ aniposelib, own process


def aniposelib_only(d: Path, result: Path, block: int, budget: float) -> int:
    """In a process of its own: aniposelib on the run in ``d``; positions and seconds into ``result`` (.npz)."""
    warnings.filterwarnings("ignore")  # aniposelib's numba object-mode notices
    t_start = time.perf_counter()
    from aniposelib.cameras import CameraGroup

    from graph.io.keypoints import read_keypoints
    from graph.skeleton import load_skeleton

    t0 = time.perf_counter()
    kps = [read_keypoints(d / f"cam{k}.csv") for k in range(1, 7)]
    markers = list(kps[0].bodyparts)
    pts = np.stack([k.xy for k in kps]).astype(np.float64)
    lik = np.stack([k.likelihood for k in kps])
    del kps
    pts[lik < h.ANIPOSE_DEFAULTS["score_threshold"]] = np.nan
    del lik
    idx = {m: i for i, m in enumerate(markers)}
    cons = [[idx[a], idx[b]] for a, b in load_skeleton("cheetah").bones if a in idx and b in idx]
    cg = CameraGroup.load(str(d / "calibration.toml"))
    read_s = time.perf_counter() - t0
    C, N, M, _ = pts.shape
    print(f"aniposelib: {N} frames read in {read_s:.1f} s", file=sys.stderr, flush=True)

    t0 = time.perf_counter()
    h.anipose_triangulate_optim(cg, pts[:, :ANIPOSE_WARM_FRAMES], cons)  # untimed: numba, jax compiles
    warm_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    tri = h.anipose_triangulate(cg, pts)
    tri_s = time.perf_counter() - t0
    print(f"aniposelib: warm-up {warm_s:.1f} s, triangulate {tri_s:.1f} s", file=sys.stderr, flush=True)

    optim = np.full((N, M, 3), np.nan)
    blocks = []
    spent = 0.0
    for a in range(0, N, block):
        b = min(N, a + block)
        if blocks:
            per_frame = spent / sum(q - p for p, q, _ in blocks)
            if spent + per_frame * (b - a) > budget:
                break
        t0 = time.perf_counter()
        optim[a:b] = h.anipose_triangulate_optim(cg, pts[:, a:b], cons)
        dt = time.perf_counter() - t0
        spent += dt
        blocks.append((a, b, dt))
        print(f"aniposelib: triangulate_optim frames {a}-{b - 1}: {dt:.1f} s (load {os.getloadavg()[0]:.2f})",
              file=sys.stderr, flush=True)
    np.savez(result, optim=optim, tri=tri, markers=np.array(markers), blocks=np.array(blocks, dtype=np.float64),
             read_s=read_s, warm_s=warm_s, tri_s=tri_s, process_s=time.perf_counter() - t_start)
    return 0


def run_aniposelib(d: Path, block: int, budget: float, env: dict) -> tuple[dict, dict | None]:
    """``--aniposelib-only`` as a new process under ``/usr/bin/time``: its command record and what it wrote."""
    result = d / "aniposelib.npz"
    cmd = [sys.executable, str(Path(__file__).resolve()), "--aniposelib-only", str(d), "--result", str(result),
           "--block-frames", str(block), "--aniposelib-seconds", str(budget)]
    c = command(cmd, env)
    if c["exit"] != 0 or not result.exists():
        return c, None
    with np.load(result, allow_pickle=False) as z:
        got = {k: z[k] for k in z.files}
    return c, got


# ------------------------------------------------------------------------------------------ main


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--minutes", default=None, help="run lengths in minutes at 120 fps, comma-separated "
                                                    "(default 1,10; 60 is opt-in: ~10 min and ~6.7 GB of disk)")
    ap.add_argument("--quick", action="store_true", help="1 and 10 minutes only")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--work", default=None, help="scratch folder (default: a new one under the temporary directory)")
    ap.add_argument("--keep", action="store_true", help="keep the scratch folders")
    ap.add_argument("--no-aniposelib", action="store_true", help="skip aniposelib")
    ap.add_argument("--aniposelib-minutes", default="1,10", help="the runs aniposelib is given")
    ap.add_argument("--aniposelib-seconds", type=float, default=400.0,
                    help="aniposelib's optimiser: blocks while the next is expected to end within this")
    ap.add_argument("--block-frames", type=int, default=7200, help="aniposelib's optimiser: frames a call")
    ap.add_argument("--jobs", type=int, default=1,
                    help="also solve each run with --jobs N (its process tree's peak memory sampled)")
    ap.add_argument("--method", default="fte", choices=("fte", "ekf"), help="the method solved with (default fte)")
    ap.add_argument("--out", default="long", help="bench/results/OUT.json")
    ap.add_argument("--aniposelib-only", default=None, metavar="DIR", help=argparse.SUPPRESS)
    ap.add_argument("--result", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.aniposelib_only:
        return aniposelib_only(Path(args.aniposelib_only), Path(args.result), args.block_frames,
                               args.aniposelib_seconds)
    warnings.filterwarnings("ignore")

    minutes = sorted({float(v) for v in (args.minutes or "1,10").split(",")})  # 0.1: a short check
    if args.quick:
        minutes = [m for m in minutes if m in (1, 10)] or [1, 10]
    anipose_minutes = set() if args.no_aniposelib else {float(v) for v in args.aniposelib_minutes.split(",") if v}
    frames_of = {m: int(round(m * 60 * FPS)) for m in minutes}
    info = h.machine()
    counts = ", ".join(f"{n:,}" for n in frames_of.values())
    print(f"# long runs: {', '.join(f'{m:g}' for m in minutes)} minutes at {FPS:g} fps ({counts} frames), "
          f"seed {args.seed}, speed {SPEED} m/s; {info['cpu']}, {info['cores']} cores, {info['memory']}, "
          f"load {info['load_average'][0]:.2f}", flush=True)

    made_root = args.work is None
    root = Path(tempfile.mkdtemp(prefix="bench_long_")) if made_root else Path(args.work).expanduser().resolve()
    root.mkdir(parents=True, exist_ok=True)
    need = (sum if args.keep else max)(frames_of.values()) * BYTES_PER_FRAME + WARM_FRAMES * BYTES_PER_FRAME
    free = shutil.disk_usage(root).free
    log(f"scratch folder {root}: needs about {need / 1e9:.1f} GB of disk "
        f"({'every run kept' if args.keep else 'one run at a time'}), {free / 1e9:.1f} GB free")
    if free < need * 1.1:
        print(f"not enough disk in {root}: about {need / 1e9:.1f} GB needed, {free / 1e9:.1f} GB free "
              "(--work elsewhere, or fewer --minutes)", file=sys.stderr)
        if made_root:
            shutil.rmtree(root, ignore_errors=True)
        return 2

    cal = h.rig()
    alone = {**os.environ, "ACINOSET_RESIDENT": "0"}
    solve_cmd = functools.partial(solve_command, method=args.method)
    runs: dict[int, dict] = {}
    comparison: dict = {}
    anipose: dict[int, dict] = {}
    made: list[Path] = []
    t_bench = time.perf_counter()
    try:
        warm = root / "warm"
        made.append(warm)
        make_run(cal, WARM_FRAMES, 99, warm)
        c = command(solve_cmd(warm), alone)  # untimed: numba's kernels from its cache (or compiled into it)
        log(f"warm-up command ({WARM_FRAMES} frames): exit {c['exit']}, {c['wall_s']:.1f} s")
        warm_up = c
        if not args.keep:
            shutil.rmtree(warm, ignore_errors=True)

        for m in minutes:
            n = frames_of[m]
            d = root / f"run_{m:g}min"
            made.append(d)
            log(f"{m:g} min: simulating and writing {n:,} frames into {d}")
            entry: dict = {"minutes": m, "frames": n}
            try:
                entry["simulate_write_s"] = make_run(cal, n, args.seed, d)
            except Exception as exc:
                entry["simulate_error"] = f"{type(exc).__name__}: {exc}"
                entry["traceback"] = traceback.format_exc()[-3000:]
                log(f"{m:g} min: the simulation failed: {entry['simulate_error']}")
                runs[m] = entry
                continue
            entry["input_bytes"] = sum(p.stat().st_size for p in d.iterdir())
            log(f"{m:g} min: written in {entry['simulate_write_s']:.1f} s ({entry['input_bytes'] / 1e6:.0f} MB); "
                f"solving (load {os.getloadavg()[0]:.2f})")
            c = command(solve_cmd(d), alone)
            c.update(report_fields(d / "run.json") if c["exit"] == 0 else {})
            entry["command"] = c
            log(f"{m:g} min: exit {c['exit']}, {c['wall_s']:.1f} s (cpu {c['cpu_s']:.1f} s), peak "
                f"{c['peak_rss_mib']:.0f} MiB, windows {(c.get('windows') or {}).get('count', '-')}, "
                f"iterations {c.get('iterations', '-')}; {c['stderr_last']}")
            if args.jobs > 1 and c["exit"] == 0:  # the windows in worker processes, beside
                tree = tree_command(solve_cmd(d, "jobs", ("--jobs", str(args.jobs))), alone)
                alone_tree = tree_command(solve_cmd(d, "alone"), alone)
                tree["same_csv"] = (d / "jobs.csv").read_bytes() == (d / "run.csv").read_bytes()
                entry["jobs"] = {"jobs": args.jobs, "with_jobs": tree, "one_process": alone_tree}
                log(f"{m:g} min --jobs {args.jobs}: {tree['wall_s']:.1f} s, tree peak {tree['tree_peak_rss_mib']:.0f} "
                    f"MiB (one process, sampled alike: {alone_tree['wall_s']:.1f} s, "
                    f"{alone_tree['tree_peak_rss_mib']:.0f} MiB); the same CSV: {tree['same_csv']}")
            markers, truth = load_truth(d / "truth.npz")
            est = None
            if c["exit"] == 0:
                try:
                    est = read_positions(d / "run.csv", markers)
                    entry["output_bytes"] = (d / "run.csv").stat().st_size
                    if m == minutes[0]:
                        entry["reader_same_as_read_anipose_csv"] = reader_check(d / "run.csv", markers, est)
                    entry["error"] = score(est, truth, markers)
                    entry["per_minute_mean_mm"] = per_minute_mean(est, truth)
                    log(f"{m:g} min: error mean {entry['error']['mean_mm']:.2f} mm, median "
                        f"{entry['error']['median_mm']:.2f} mm")
                except Exception as exc:
                    entry["score_error"] = f"{type(exc).__name__}: {exc}"
                    log(f"{m:g} min: scoring failed: {entry['score_error']}")

            if m == 1:  # the whole run at once, beside the windows
                log(f"{m:g} min: the whole run at once (--window-frames 0)")
                w = command(solve_cmd(d, "whole", ("--window-frames", "0")), alone)
                w.update(report_fields(d / "whole.json") if w["exit"] == 0 else {})
                log(f"{m:g} min whole: exit {w['exit']}, {w['wall_s']:.1f} s, peak {w['peak_rss_mib']:.0f} MiB, "
                    f"iterations {w.get('iterations', '-')}")
                comparison = {"whole_command": w}
                if w["exit"] == 0:
                    whole = read_positions(d / "whole.csv", markers)
                    comparison["whole_error"] = score(whole, truth, markers)
                    if est is not None:
                        comparison["difference"] = compare(est, whole, seams_of(n, c.get("windows")))
                        comparison["body_length_max_rel_diff"] = length_difference(
                            c.get("body_lengths"), w.get("body_lengths"))

            if m in anipose_minutes:
                log(f"{m:g} min: aniposelib in its own process (blocks of {args.block_frames} frames, "
                    f"{args.aniposelib_seconds:g} s of optimiser)")
                ac, got = run_aniposelib(d, args.block_frames, args.aniposelib_seconds, alone)
                a_entry: dict = {"command": ac}
                if got is not None:
                    blocks = got["blocks"].reshape(-1, 3)
                    covered = int(blocks[:, 1].max()) if len(blocks) else 0
                    optim_s = float(blocks[:, 2].sum())
                    a_entry.update(read_s=float(got["read_s"]), warm_s=float(got["warm_s"]),
                                   triangulate_s=float(got["tri_s"]), optimise_s=optim_s, frames_optimised=covered,
                                   blocks=[[int(a), int(b), float(s)] for a, b, s in blocks],
                                   block_frames=args.block_frames)
                    a_markers = [str(v) for v in got["markers"]]
                    order = [a_markers.index(mk) for mk in markers]
                    tri, opt = got["tri"][:, order], got["optim"][:, order]
                    a_entry["triangulate_error"] = score(tri, truth, markers)
                    if covered:
                        a_entry["optim_error"] = score(opt[:covered], truth[:covered], markers)
                        if est is not None:
                            a_entry["ours_same_frames_error"] = score(est[:covered], truth[:covered], markers)
                    log(f"{m:g} min aniposelib: exit {ac['exit']}, {ac['wall_s']:.1f} s, peak "
                        f"{ac['peak_rss_mib']:.0f} MiB; triangulate {a_entry['triangulate_s']:.1f} s, "
                        f"triangulate_optim {covered:,} of {n:,} frames in {optim_s:.1f} s")
                else:
                    log(f"{m:g} min aniposelib: failed, exit {ac['exit']}: {ac['stderr_last']}")
                anipose[m] = a_entry
            runs[m] = entry
            del truth, est
            if not args.keep:
                shutil.rmtree(d, ignore_errors=True)
    finally:
        if not args.keep:
            for d in made:
                shutil.rmtree(d, ignore_errors=True)
            if made_root:
                shutil.rmtree(root, ignore_errors=True)
        else:
            log(f"kept {root}")

    nan = float("nan")
    base = runs.get(1, {}).get("error")

    def ok(flag: bool) -> str:
        return "met" if flag else "NOT met"

    print("\n## acinoset solve from a shell (windowed by default)\n")
    rows, verdict = [], {}
    for m, e in runs.items():
        c = e.get("command", {})
        er = e.get("error", {})
        win = c.get("windows") or {}
        t = TARGETS.get(m)
        wall_t = f"<= {t['wall_s']:g}: {ok(c.get('wall_s', nan) <= t['wall_s'])}" if t else "-"
        rss_t = f"<= {t['peak_rss_mib']:g}: {ok(c.get('peak_rss_mib', nan) <= t['peak_rss_mib'])}" if t else "-"
        if t:
            verdict[m] = {"wall_s": {"value": c.get("wall_s"), "target": t["wall_s"],
                                     "met": bool(c.get("wall_s", nan) <= t["wall_s"])},
                          "peak_rss_mib": {"value": c.get("peak_rss_mib"), "target": t["peak_rss_mib"],
                                           "met": bool(c.get("peak_rss_mib", nan) <= t["peak_rss_mib"])}}
        rows.append([f"{m:g}", f"{e['frames']:,}", c.get("exit", "-"), c.get("wall_s", nan), wall_t,
                     c.get("cpu_s", nan), c.get("peak_rss_mib", nan), rss_t, (c.get("seconds") or {}).get("total", nan),
                     c.get("iterations", "-"), f"{win['count']} x {win['core_frames']}" if win else "-",
                     er.get("mean_mm", nan), er.get("median_mm", nan), er.get("p90_mm", nan), er.get("max_mm", nan),
                     er.get("coverage", nan)])
    print(h.markdown_table(["minutes", "frames", "exit", "wall s", "target wall s", "cpu s", "peak MiB",
                            "target peak MiB", "solve s (report)", "iterations", "windows x kept frames",
                            "error mean mm", "error median mm", "p90 mm", "max mm", "coverage"], rows))
    for m, e in runs.items():
        c = e.get("command", {})
        if c.get("exit") != 0:
            print(f"\n{m:g} min failed: exit {c.get('exit')}: {c.get('stderr_last') or e.get('simulate_error')}")
    print("\nwhere the time goes (seconds; the command's wall minus the report's total is the interpreter, "
          "imports, reading the CSVs and writing the outputs):\n")
    phase_names = sorted({k for e in runs.values() for k in ((e.get("command") or {}).get("seconds") or {})})
    print(h.markdown_table(["minutes", "wall s", *phase_names, "wall - total"],
                           [[f"{m:g}", c["wall_s"], *[c["seconds"].get(k, nan) for k in phase_names],
                             c["wall_s"] - c["seconds"].get("total", nan)]
                            for m, e in runs.items() if (c := e.get("command") or {}).get("seconds")]))

    accuracy = {}
    if base:
        print("\n## accuracy against the 1-minute solve's (target: equal, read as within "
              f"{100 * (ACCURACY_TOLERANCE - 1):.0f} %)\n")
        rows = []
        for m, e in runs.items():
            er = e.get("error")
            if not er:
                continue
            pm = e.get("per_minute_mean_mm", [])
            rm, rd = er["mean_mm"] / base["mean_mm"], er["median_mm"] / base["median_mm"]
            accuracy[m] = {"mean_ratio": rm, "median_ratio": rd,
                           "met": bool(rm <= ACCURACY_TOLERANCE and rd <= ACCURACY_TOLERANCE)}
            rows.append([f"{m:g}", er["mean_mm"], rm, er["median_mm"], rd, min(pm) if pm else nan,
                         max(pm) if pm else nan, ok(accuracy[m]["met"]) if m != 1 else "(the reference)"])
        print(h.markdown_table(["minutes", "mean mm", "mean / 1 min", "median mm", "median / 1 min",
                                "per-minute mean: lowest mm", "highest mm", "target"], rows))

    if comparison:
        w = comparison["whole_command"]
        c1 = runs[1].get("command", {})
        print("\n## 1 minute: windows against the whole run at once (--window-frames 0)\n")
        print(h.markdown_table(
            ["solve", "exit", "wall s", "cpu s", "peak MiB", "solve s (report)", "iterations", "error mean mm",
             "error median mm"],
            [["windowed (default)", c1.get("exit", "-"), c1.get("wall_s", nan), c1.get("cpu_s", nan),
              c1.get("peak_rss_mib", nan), (c1.get("seconds") or {}).get("total", nan), c1.get("iterations", "-"),
              runs[1].get("error", {}).get("mean_mm", nan), runs[1].get("error", {}).get("median_mm", nan)],
             ["whole", w.get("exit", "-"), w.get("wall_s", nan), w.get("cpu_s", nan), w.get("peak_rss_mib", nan),
              (w.get("seconds") or {}).get("total", nan), w.get("iterations", "-"),
              comparison.get("whole_error", {}).get("mean_mm", nan),
              comparison.get("whole_error", {}).get("median_mm", nan)]]))
        if w.get("exit") != 0:
            print(f"\nthe whole solve failed: exit {w.get('exit')}: {w.get('stderr_last')}")
        if "difference" in comparison:
            df = comparison["difference"]
            print(f"\nwindowed - whole, per marker and frame (mm): largest {df['max_mm']:.3f} (frame "
                  f"{df['worst_frame']}), p99 {df['p99_mm']:.3f}, median {df['median_mm']:.3f}; largest within "
                  f"{SEAM_NEAR} frames of a seam (frames {', '.join(map(str, df['seams']))}) "
                  f"{df['max_near_seams_mm']:.3f}, away from them {df['max_away_from_seams_mm']:.3f}. Not only the "
                  "seams: the windows hold the body, noise and motion scales settled on the best-seen stretch, the "
                  "whole solve estimates them from every frame (body lengths differ by up to "
                  f"{100 * comparison['body_length_max_rel_diff']:.2f} %).")

    if anipose:
        print("\n## aniposelib, its own process (blocks of "
              f"{args.block_frames:,} frames for triangulate_optim, while within {args.aniposelib_seconds:g} s)\n")
        rows = []
        for m, a in anipose.items():
            ac = a["command"]
            n = frames_of[m]
            if "triangulate_s" not in a:
                rows.append([f"{m:g}", "failed", f"exit {ac.get('exit')}: {ac.get('stderr_last')}", *["-"] * 8])
                continue
            rows.append([f"{m:g}", "triangulate", f"{n:,}", a["triangulate_s"], 1000 * a["triangulate_s"] / n,
                         a["triangulate_error"]["mean_mm"], a["triangulate_error"]["median_mm"], "-", "-",
                         ac["wall_s"], ac["peak_rss_mib"]])
            cov = a["frames_optimised"]
            if cov:
                ours = a.get("ours_same_frames_error", {})
                k = len(a["blocks"])
                rows.append([f"{m:g}", f"triangulate_optim ({k} block{'s' if k > 1 else ''})",
                             f"{cov:,} of {n:,}", a["optimise_s"], 1000 * a["optimise_s"] / cov,
                             a["optim_error"]["mean_mm"], a["optim_error"]["median_mm"], ours.get("mean_mm", nan),
                             ours.get("median_mm", nan), ac["wall_s"], ac["peak_rss_mib"]])
        print(h.markdown_table(["minutes", "method", "frames", "call s", "s per 1,000 frames", "error mean mm",
                                "error median mm", "acinoset mean mm, same frames", "acinoset median mm",
                                "process wall s", "process peak MiB"], rows))
        print("\n(the process's wall and peak include its imports, reading the CSVs, an untimed warm-up call on "
              f"{ANIPOSE_WARM_FRAMES} frames, triangulate and every triangulate_optim block)")

    after = os.getloadavg()
    print(f"\nbench wall {time.perf_counter() - t_bench:.0f} s; load average at the end: "
          f"{after[0]:.2f} {after[1]:.2f} {after[2]:.2f}")
    def by_label(d: dict) -> dict:
        return {f"{k:g}": v for k, v in d.items()}

    path = h.save(args.out, {
        "machine": info, "load_average_end": list(after), "args": vars(args), "minutes": minutes,
        "frames": by_label(frames_of), "speed_m_s": SPEED, "fps": FPS,
        "protocol": {"simulator": "simulate_run defaults (5 px noise, 10 % outliers of 100 px, 30 % confident)",
                     "solve": f"acinoset solve --method {args.method}, every other option at its default",
                     "aniposelib": h.ANIPOSE_DEFAULTS},
        "warm_up": warm_up, "runs": by_label(runs), "windowed_vs_whole_1min": comparison,
        "aniposelib": by_label(anipose), "targets": by_label(TARGETS), "target_verdict": by_label(verdict),
        "accuracy_vs_1min": by_label(accuracy), "accuracy_tolerance": ACCURACY_TOLERANCE})
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
