"""``acinoset demo``: simulate a run on the AcinoSet rig, solve it with every method, compare.

The run follows the paper's synthetic protocol on the real 2019 six-camera rig (defaults: 120 fps,
200 frames, 5 px noise, 10 % outliers of sigma 100 px, a share of them confident) and is solved
with ``tri``, ``ekf`` and ``fte``. Each is judged against the truth with :mod:`graph.metrics`.

Written to ``--out``::

    input/            the simulated run as a user would bring it (acinoset simulate's files)
    summary.csv       one row per method: 3D error, reprojection error, NRMSE, PCK, seconds
    summary.json      the same with per-marker errors and the simulation settings
    comparison.png    3D error against the truth over time and per marker, every method
    <method>/         result.csv (Anipose 3D layout), result.h5, report.json, the figures of
                      graph.viewer.figures and playback.html

With ``--videos`` (the ``video`` extra) the run is also filmed (``input/cam1.mp4`` ..., at the rig's
2704x1520, about a minute a camera on two cores) and ``fte/videos/`` gets the labelled videos of the
fte estimate over that footage, its 3D view and the combined grid (:mod:`graph.video`).
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import json
import math
import multiprocessing
import os
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

from graph.api import solve
from graph.app.warmup import warm_up
from graph.errors import InputError
from graph.io import results as result_files
from graph.io.calibration import default_rig_path, load_calibration
from graph.metrics import evaluate
from graph.simulate import simulate_run, write_run
from graph.types import Method, SolveOptions
from graph.viewer.figures import FIGURES

DEMO_METHODS: tuple[Method, ...] = ("tri", "ekf", "fte")


def run_demo(out: str | Path, frames: int = 200, fps: float = 120.0, noise: float = 5.0, outliers: float = 0.1,
             outlier_std: float = 100.0, seed: int = 0, figures: bool = True, videos: bool = False,
             log=print) -> list:
    """Simulate, solve with each method, evaluate and write everything; return the evaluations.

    ``figures=False`` skips the per-method figures and playback files (the comparison is drawn);
    ``videos=True`` films the run and draws the fte estimate over it (module docstring).
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    log("compiling the solver's kernels (once: later runs load them from the cache) ...")
    log(f"kernels ready in {warm_up():.1f} s; the seconds below are the solves alone")
    rig_path = default_rig_path()
    calibration = load_calibration(rig_path)
    run = simulate_run(calibration, frames=frames, fps=fps, noise=noise, outliers=outliers,
                       outlier_std=outlier_std, seed=seed)
    write_run(run, out / "input", rig_path=rig_path)
    log(f"simulated {run.frames} frames at {fps:g} fps on the AcinoSet 2019 rig ({len(calibration)} cameras, "
        f"{len(run.markers)} markers): noise {noise:g} px, {int(run.outlier.sum())} outliers "
        f"(sigma {outlier_std:g} px), seed {seed}")

    evaluations, results, drawn = [], [], []
    with _drawing_pool(figures) as pool:
        for method in DEMO_METHODS:
            result = solve(run.keypoints, calibration, SolveOptions(method=method, fps=fps))
            ev = evaluate(result, run)
            evaluations.append(ev)
            results.append(result)
            d = out / method
            d.mkdir(exist_ok=True)
            result_files.write_anipose_csv(d / "result.csv", result)
            result_files.write_h5(d / "result.h5", result)
            (d / "report.json").write_text(json.dumps(result.report.to_dict(), indent=2) + "\n", encoding="utf-8")
            if pool is not None:  # the heaviest figure on its own: the two processes share the work evenly
                drawn.append(pool.submit(_draw, result, d, calibration, ("coordinates",)))
                drawn.append(pool.submit(_draw, result, d, calibration, tuple(f for f in FIGURES if f != "coordinates"),
                                         playback=True))
        for done in drawn:
            done.result()

    log("")
    for line in format_table(evaluations):
        log(line)
    _write_summary(out, evaluations, run)
    plot_comparison(out / "comparison.png", evaluations, run)
    if videos:
        _videos(run, results[DEMO_METHODS.index("fte")], out, log)
    log(f"\nwrote {out}/summary.csv, summary.json, comparison.png, input/ and one folder per method")
    return evaluations


def _videos(run, result, out: Path, log) -> None:
    """Film the run into ``input/`` and draw the fte estimate over it into ``fte/videos/``."""
    import sys

    from graph.progress import FrameProgress
    from graph.video import render_videos, write_simulated_videos

    log(f"filming the run: {len(run.keypoints)} cameras x {run.frames} frames ...")
    bar = FrameProgress(sys.stderr, label="camera-frames filmed") if sys.stderr.isatty() else None
    try:
        footage = write_simulated_videos(run, out / "input", progress=bar, seed=run.seed)
    finally:
        if bar is not None:
            bar.close()
    bar = FrameProgress(sys.stderr) if sys.stderr.isatty() else None
    try:
        done = render_videos(result, footage, out / "fte" / "videos", combined=True, progress=bar)
    finally:
        if bar is not None:
            bar.close()
    log(f"labelled videos of the fte estimate in {done.seconds:.1f} s -> {out / 'fte' / 'videos'}")


@contextlib.contextmanager
def _drawing_pool(figures: bool):
    """Processes that draw each method's figures while the next method is solved (None without
    ``figures``): two, started from a server that imported the figures' modules once. matplotlib
    draws on one core; the three methods' figures take about 10 s on one, 5 s on two."""
    if not figures:
        yield None
        return
    ctx = multiprocessing.get_context("forkserver")
    ctx.set_forkserver_preload(["graph.viewer.figures", "graph.viewer.playback", "matplotlib.figure",
                               "matplotlib.backends.backend_agg"])
    with ProcessPoolExecutor(max_workers=max(1, min(2, os.cpu_count() or 1)), mp_context=ctx) as pool:
        yield pool


def _draw(result, folder: Path, calibration, figures: tuple[str, ...], playback: bool = False) -> None:
    """The ``figures`` named (:mod:`graph.viewer.figures`) and with ``playback`` the playback file
    (:mod:`graph.viewer.playback`)."""
    from graph.viewer.figures import write_figures
    from graph.viewer.playback import HTML_NAME, write_playback_html

    write_figures(result, folder, calibration, only=figures)
    if playback:
        write_playback_html(result, folder / HTML_NAME, calibration)


def format_table(evaluations) -> list[str]:
    """The printed table: one line per method."""
    head = (f"{'method':<7}{'3D mean mm':>11}{'median mm':>11}{'p90 mm':>9}{'reproj px':>11}"
            f"{'vs truth px':>13}{'PCK':>7}{'seconds':>9}")
    lines = [head, "-" * len(head)]
    for ev in evaluations:
        r = ev.row()
        lines.append(f"{r['method']:<7}{r['mean_mm']:>11.1f}{r['median_mm']:>11.1f}{r['p90_mm']:>9.1f}"
                     f"{r['reproj_rmse_px']:>11.2f}{r['reproj_rmse_truth_px']:>13.2f}{r['pck']:>7.3f}"
                     f"{r['seconds']:>9.2f}")
    lines.append("3D error against the simulated truth; reproj: RMSE to the inlier detections (5 px noise "
                 "alone gives ~7.1); vs truth: RMSE to the noiseless projections; PCK: within the "
                 "nose-to-eye length.")
    return lines


def _write_summary(out: Path, evaluations, run) -> None:
    rows = [ev.row() for ev in evaluations]
    with open(out / "summary.csv", "w", newline="", encoding="utf-8") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]), lineterminator="\n")
        w.writeheader()
        for r in rows:
            w.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in r.items()})
    doc = {
        "simulation": {"frames": run.frames, "fps": run.fps, "seed": run.seed, "cameras": len(run.keypoints),
                       "markers": run.markers, "noise_px": run.observation.noise_px,
                       "outlier_rate": run.observation.outlier_rate,
                       "outlier_std_px": run.observation.outlier_std_px,
                       "confident_outliers": run.observation.confident_outliers},
        "methods": [{**ev.row(), "position": ev.position.to_dict(),
                     "pck_per_marker": ev.pck.per_marker,
                     "reprojection_per_camera_px": ev.reprojection_detections.per_camera_rmse_px}
                    for ev in evaluations],
    }
    (out / "summary.json").write_text(json.dumps(_finite(doc), indent=2) + "\n", encoding="utf-8")


def _finite(x):
    if isinstance(x, dict):
        return {k: _finite(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_finite(v) for v in x]
    if isinstance(x, (float, np.floating)):
        return None if not math.isfinite(float(x)) else float(x)
    return x


def plot_comparison(path: Path, evaluations, run) -> Path:
    """Left: mean 3D error over the markers, per frame, each method. Right: mean per marker."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(13, 4.5), gridspec_kw={"width_ratios": [1.4, 1]})
    t = np.arange(run.frames) / run.fps
    y = np.arange(len(run.markers))
    h = 0.8 / max(len(evaluations), 1)
    for i, ev in enumerate(evaluations):
        with np.errstate(invalid="ignore"):
            per_frame = np.nanmean(ev.position.per_frame, axis=1) * 1000
        a.plot(t, per_frame, lw=1.2, label=f"{ev.method}: mean {ev.position.mean_mm:.1f} mm")
        vals = [ev.position.per_marker_mean_mm[m] for m in run.markers]
        b.barh(y + (i - (len(evaluations) - 1) / 2) * h, vals, height=h, label=ev.method)
    a.set_xlabel("time (s)")
    a.set_ylabel("mean 3D error over markers (mm)")
    a.set_yscale("log")
    a.grid(alpha=0.3, which="both")
    a.legend(fontsize=8)
    a.set_title(f"{run.frames} frames, {len(run.keypoints)} cameras, noise {run.observation.noise_px:g} px, "
                f"{run.observation.outlier_rate:.0%} outliers", fontsize=9)
    b.set_yticks(y, run.markers, fontsize=7)
    b.invert_yaxis()
    b.set_xlabel("mean 3D error (mm)")
    b.set_xscale("log")
    b.grid(alpha=0.3, axis="x", which="both")
    b.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


# -------------------------------------------------------------------------------------------- CLI


def register(subparsers) -> None:
    """``acinoset demo``."""
    p = subparsers.add_parser(
        "demo",
        description="Simulate a cheetah run on the real AcinoSet 2019 six-camera rig (the paper's protocol: "
                    "Gaussian pixel noise and outliers), solve it with tri, ekf and fte, print a comparison "
                    "against the truth and write the results, figures and the simulated inputs.")
    p.add_argument("--out", default="demo-out", help="output folder (default demo-out)")
    p.add_argument("--frames", type=int, default=200, help="frames to simulate (default 200)")
    p.add_argument("--fps", type=float, default=120.0, help="frame rate (default 120)")
    p.add_argument("--noise", type=float, default=5.0, help="pixel noise sigma (default 5)")
    p.add_argument("--outliers", type=float, default=0.1, help="outlier probability (default 0.1)")
    p.add_argument("--outlier-std", type=float, default=100.0, help="outlier sigma in px (default 100)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--no-figures", action="store_true",
                   help="skip each method's figures and playback file (comparison.png is still drawn)")
    p.add_argument("--videos", action="store_true",
                   help="also film the run (input/cam1.mp4 ...) and draw the fte estimate over it (fte/videos/); "
                        "about a minute a camera; needs the 'video' extra")
    p.set_defaults(func=_cli)


def _cli(args: argparse.Namespace) -> int:
    if args.frames < 10:
        raise InputError(f"--frames must be at least 10, not {args.frames}")
    if not args.fps > 0:
        raise InputError(f"--fps must be positive, not {args.fps}")
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise InputError("exists and is not a folder", out)
    if args.videos:
        from graph.video import ffmpeg_exe

        ffmpeg_exe()  # the one-line message naming the extra, before any work
    try:
        run_demo(out, frames=args.frames, fps=args.fps, noise=args.noise, outliers=args.outliers,
                 outlier_std=args.outlier_std, seed=args.seed, figures=not args.no_figures, videos=args.videos)
    except ValueError as e:
        if isinstance(e, InputError):
            raise
        raise InputError(str(e)) from None
    return 0
