"""Leave one camera out on a real recording: acinoset against aniposelib and EKS on the fly data.

    .venv/bin/python bench/bench_fly_loco.py [--data DIR] [--repeats 3] [--eks-repeats 1]
                                            [--eks-python eks-venv/bin/python]

The data (:data:`harness.EKS_FLY`, see its SOURCE.md): a tethered fly, 3 cameras of 832x632 px,
500 frames, 12 leg keypoints, two DeepLabCut ensemble members per camera (``camX.rng1.csv``,
``camX.rng2.csv``), an Anipose calibration in millimetres with near-telecentric lenses. There is no
3D truth, so every method is scored by :func:`graph.metrics.leave_one_camera_out`: for each camera,
reconstruct from the other two and predict that camera's detections of likelihood >= 0.9 (of
member 1, the one every single-member method gets); median and 90th percentile pixel error pooled
over the three held-out cameras, and the coverage (share of those detections that got a position);
for acinoset, ``in 90 %``: the share of them inside the 90 % prediction ellipse of its own
uncertainty (:func:`graph.metrics.prediction_share`; about 0.9 when it is honest).

What runs, on the same data in one run:

* acinoset ``fte --skeleton points`` (free points, no bones), 300 frames per second assumed (SOURCE.md),
  with the fixed process noise (``motion_scale=1``) and every other option at its default, on
  member 1; then with ``motion_scale="auto"`` (the default for free points since 12a; and with
  ``measurement_std_px="auto"`` too); then given both members as one ensemble per camera
  (:func:`graph.solve.ensemble.combine`: their median, their spread weighing cameras and markers), with
  the same three settings; then with the motion prior's order chosen from the data
  (``motion_order="auto"``, member 1 and the ensemble) and with the first order given (the
  ensemble). The three reconstructions timed in process (wall clock around
  :func:`graph.api.solve`, compiled kernels loaded by an untimed warm-up);
* aniposelib ``CameraGroup.triangulate_optim`` on member 1 with every option at its default
  (smoothing ``scale_smooth=4``, ``n_deriv_smooth=1``, ``reproj_loss='soft_l1'``,
  ``reproj_error_threshold=15``) and detections below Anipose's score threshold (0.8) set to NaN, as
  ``anipose triangulate`` does; the calibration as shipped (millimetres). Timed after an untimed
  warm-up call that pays its numba compile. Again on the ensemble's combined detections (the
  members' median and mean likelihood, what acinoset's ensemble rows are given; aniposelib has no
  use for their spread), so that both peers are also compared on the same members;
* EKS (``ensemble-kalman-smoother``), ``ensemble_kalman_smoother_multicam`` on both members with
  aniposelib's camera group (its nonlinear path, smoothing fitted by maximum likelihood), every
  option at its default, run by ``bench/eks_multicam_run.py`` in EKS's own virtualenv (it pins
  jax<=0.4.36; see bench/bench_eks.py for the install). Its time is the smoother call in that
  process (jax compiles in every call, as a user sees it), not the process start.

Then each acinoset row against aniposelib given the same inputs (member 1, or the ensemble): the
paired difference of the pooled median and p90 and its 95 % moving-block bootstrap interval over
frames (:func:`graph.metrics.loco_difference`). The fly's 500 frames make about ten blocks, so those
intervals are if anything too narrow.

Prints Markdown tables and writes bench/results/fly_loco.json (``--out``; ``--eks-python ''``
leaves EKS out). Times are medians over repeats;
the machine is shared, so ratios matter more than seconds.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import tempfile
import time
import warnings
from dataclasses import replace
from pathlib import Path

import harness as h
import numpy as np

from graph.api import SolveOptions
from graph.io.calibration import load_calibration
from graph.io.keypoints import read_keypoints
from graph.metrics import leave_one_camera_out, loco_difference
from graph.solve.ensemble import combine

DATA = h.EKS_FLY
FPS = 300.0  # assumed (SOURCE.md)
LETTERS = "ABC"


def member_files(data: Path, member: int) -> list[Path]:
    return [data / f"cam{x}.rng{member}.csv" for x in LETTERS]


def aniposelib_reconstruct(data: Path, score_threshold: float):
    """``triangulate_optim`` at its defaults on the kept cameras (calibration units: mm)."""
    from aniposelib.cameras import CameraGroup

    full = CameraGroup.load(str(data / "calibration.toml"))

    def reconstruct(keypoints, calibration):
        cg = full.subset_cameras_names(calibration.names)
        pts = np.stack([k.xy for k in keypoints]).copy()
        pts[np.stack([k.likelihood for k in keypoints]) < score_threshold] = np.nan
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            X = cg.triangulate_optim(pts)
        return list(keypoints[0].bodyparts), np.asarray(X)

    return reconstruct


def eks_reconstruct(data: Path, eks_python: str, members: list[int], log: list):
    """EKS's multi-camera smoother on ``members`` of the kept cameras, in its own process."""
    here = Path(__file__).resolve().parent

    def reconstruct(keypoints, calibration):
        idx = [load_calibration(data / "calibration.toml").names.index(n) for n in calibration.names]
        with tempfile.TemporaryDirectory() as tmp:
            req = {"calibration": str(data / "calibration.toml"), "cameras": calibration.names,
                   "members": [[str(member_files(data, m)[i]) for i in idx] for m in members],
                   "out": str(Path(tmp) / "out.npz")}
            (Path(tmp) / "req.json").write_text(json.dumps(req))
            w0 = time.perf_counter()
            proc = subprocess.run([eks_python, str(here / "eks_multicam_run.py"), str(Path(tmp) / "req.json")],
                                  capture_output=True, text=True)
            wall = time.perf_counter() - w0
            if proc.returncode:
                raise RuntimeError(f"EKS failed: {proc.stderr[-2000:]}")
            out = np.load(req["out"])
            log.append({"cameras": calibration.names, "seconds": float(out["seconds"]), "process_s": wall,
                        "smooth_param": out["smooth_param"].tolist()})
            return [str(k) for k in out["keypoints"]], out["positions"]

    return reconstruct


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", type=Path, default=DATA)
    ap.add_argument("--repeats", type=int, default=3, help="LOCO runs of acinoset and aniposelib")
    ap.add_argument("--eks-repeats", type=int, default=1, help="LOCO runs of EKS")
    ap.add_argument("--eks-python", default="/work/venv-eks/bin/python", help="python of EKS's virtualenv ('' skips)")
    ap.add_argument("--skip-aniposelib", action="store_true")
    ap.add_argument("--out", default="fly_loco", help="bench/results/OUT.json")
    args = ap.parse_args()
    warnings.filterwarnings("ignore")
    data = args.data
    cal = load_calibration(data / "calibration.toml")
    kps = [read_keypoints(p) for p in member_files(data, 1)]
    info = h.machine()
    print(f"# fly LOCO: {kps[0].frames} frames, {len(cal)} cameras, {len(kps[0].bodyparts)} keypoints; "
          f"{info['cpu']}, {info['cores']} cores, load {info['load_average'][0]:.1f}", flush=True)

    ens = [combine([read_keypoints(p) for p in files]) for files in zip(*(member_files(data, m) for m in (1, 2)))]
    base = SolveOptions(method="fte", skeleton="points", fps=FPS, motion_scale=1.0)  # the fixed process noise
    ours = {  # name: (inputs, options); every one judged against member 1's confident detections
        "acinoset fte points": (kps, base),
        "acinoset fte points, motion auto": (kps, replace(base, motion_scale="auto")),
        "acinoset fte points, motion and noise auto": (kps, replace(base, motion_scale="auto",
                                                                    measurement_std_px="auto")),
        "acinoset fte points, ensemble": (ens, base),
        "acinoset fte points, ensemble, motion auto": (ens, replace(base, motion_scale="auto")),
        "acinoset fte points, ensemble, motion and noise auto": (ens, replace(base, motion_scale="auto",
                                                                              measurement_std_px="auto")),
        "acinoset fte points, motion auto, order auto": (kps, replace(base, motion_scale="auto", motion_order="auto")),
        "acinoset fte points, ensemble, motion auto, order auto": (ens, replace(base, motion_scale="auto",
                                                                                motion_order="auto")),
        "acinoset fte points, ensemble, motion auto, order 1": (ens, replace(base, motion_scale="auto",
                                                                              motion_order=1)),
    }
    methods = {name: (lambda i=i, o=o, name=name: leave_one_camera_out(i, cal, o, method=name, judge=kps))
               for name, (i, o) in ours.items()}
    eks_log: list = []
    if not args.skip_aniposelib:
        rec = aniposelib_reconstruct(data, h.ANIPOSE_DEFAULTS["score_threshold"])
        methods["aniposelib triangulate_optim"] = lambda: leave_one_camera_out(
            kps, cal, reconstruct=rec, method="aniposelib triangulate_optim")
        methods["aniposelib triangulate_optim, ensemble"] = lambda: leave_one_camera_out(
            ens, cal, reconstruct=rec, method="aniposelib triangulate_optim, ensemble", judge=kps)
    if args.eks_python:
        rec_eks = eks_reconstruct(data, args.eks_python, [1, 2], eks_log)
        methods["EKS multicam, 2 members"] = lambda: leave_one_camera_out(
            kps, cal, reconstruct=rec_eks, method="EKS multicam, 2 members")

    # warm-up: acinoset's kernels, aniposelib's numba compile (a short slice)
    short = [type(k)(bodyparts=k.bodyparts, xy=k.xy[:40], likelihood=k.likelihood[:40], source=k.source) for k in kps]
    for name, (_, o) in ours.items():
        leave_one_camera_out(short, cal, o)
    if not args.skip_aniposelib:
        leave_one_camera_out(short, cal, reconstruct=aniposelib_reconstruct(data, 0.8))

    summary = {}
    last_scores = {}
    for name, run in methods.items():
        repeats = args.eks_repeats if name.startswith("EKS") else args.repeats
        scores, seconds = [], []
        for r in range(repeats):
            eks_log.clear()
            s = run()
            scores.append(s)
            seconds.append(sum(e["seconds"] for e in eks_log) if name.startswith("EKS") else s.seconds)
            print(f"  {name:<40} run {r + 1}: median {s.median_px:.3f} px  p90 {s.p90_px:.3f} px  "
                  f"coverage {s.coverage:.3f}  {seconds[-1]:.2f} s", flush=True)
        last = scores[-1]
        last_scores[name] = last
        summary[name] = {**last.to_dict(), "seconds_runs": seconds, "median_s": statistics.median(seconds),
                         "median_px_runs": [s.median_px for s in scores], "p90_px_runs": [s.p90_px for s in scores]}
        if name.startswith("EKS"):
            summary[name]["eks_calls"] = list(eks_log)

    ref = summary.get("aniposelib triangulate_optim")
    rows = []
    for name, s in summary.items():
        rows.append([name, s["median_px"], s["p90_px"], s["coverage"],
                     "-" if s.get("within_90") is None else s["within_90"],
                     *[c["median_px"] for c in s["cameras"]], s["median_s"],
                     ref["median_s"] / s["median_s"] if ref else float("nan")])
    print()
    print(h.markdown_table(["method", "median px", "p90 px", "coverage", "in 90 %", *[f"median {n}" for n in cal.names],
                            "s (3 solves)", "speed-up vs aniposelib"], rows))
    # each acinoset row against aniposelib given the same inputs (one member, or the ensemble's
    # combined rows): the paired difference of the pooled median and p90, with 95 % block-bootstrap
    # intervals (graph.metrics.loco_difference)
    versus = {}
    for name in ours:
        peer = "aniposelib triangulate_optim" + (", ensemble" if ours[name][0] is ens else "")
        if peer in last_scores:
            d = loco_difference(last_scores[peer], last_scores[name])
            versus[name] = {"against": peer, **d.to_dict()}
    if versus:
        print()
        print(h.markdown_table(
            ["acinoset row", "against", "median diff px (95 %)", "p90 diff px (95 %)", "share p90 lower", "blocks"],
            [[name, v["against"],
              f"{v['median_px']:+.3f} [{v['median_interval'][0]:+.3f}, {v['median_interval'][1]:+.3f}]",
              f"{v['p90_px']:+.3f} [{v['p90_interval'][0]:+.3f}, {v['p90_interval'][1]:+.3f}]",
              f"{v['share_b_p90_lower']:.2f}", f"{v['blocks']} x {v['block_frames']} frames"]
             for name, v in versus.items()]))
    path = h.save(args.out, {"machine": info, "args": {k: str(v) for k, v in vars(args).items()}, "fps": FPS,
                               "anipose_score_threshold": h.ANIPOSE_DEFAULTS["score_threshold"],
                               "results": summary, "versus_aniposelib": versus})
    print(f"\nwrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
