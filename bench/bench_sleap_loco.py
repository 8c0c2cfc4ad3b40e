"""Leave one camera out on real data from another lab: acinoset against aniposelib on SLEAP's minimal session.

    .venv/bin/python bench/bench_sleap_loco.py [--data DIR] [--repeats 1] [--out sleap_loco]

The data (:data:`harness.SLEAP_MINIMAL`, see its SOURCE.md): one mouse, four cameras (back, mid,
side, top; 1280x1024), SLEAP's proofread predictions per camera as analysis HDF5 files
(``<cam>/minimal_<cam>_proofread.analysis.h5``, read by :mod:`graph.io.sleap`), 120 frames of 15
nodes, 30 frames per second, and the Anipose calibration in millimetres. Its entry for ``side`` is a
copy of ``top``'s: side's detections sit about 90 px from where the rig puts them, and side and top
are one camera to a triangulation (no baseline between them).

There is no 3D truth: every method is scored by :func:`graph.metrics.leave_one_camera_out`
(reconstruct from the other three cameras, predict the fourth's detections), every point used
(no likelihood threshold for either method, every detection judged: ``--confidence 0``), median
and 90th percentile pixel error per held-out camera and pooled, and for acinoset ``in 90 %``: the
share of the judged detections inside the 90 % prediction ellipse of its own uncertainty.

What runs, on the same inputs:

* acinoset ``fte --skeleton points`` at 30 fps, every other option at its default (motion scale
  fitted, 5 px detection noise); and ``tri``;
* aniposelib ``CameraGroup.triangulate_optim`` with every option at its default and no score
  threshold (the same detections), the calibration as shipped (millimetres); and plain
  ``triangulate`` (DLT from all views).

The camera that disagrees (:mod:`graph.solve.disagreement`) is measured on all four cameras: each
camera's held-out error against the others' robust triangulation, as a solve warns of it.

``--leave-out`` measures instead what leaving such a camera out of a solve would gain, where the truth is
known: the simulated AcinoSet rig (200 frames, 5 px, 10 % outliers, seeds 0-2), the second camera of a
set given the third's calibration entry (as side was given top's), solved with it kept, left out, and
on the clean rig; 3D error median and p90 in mm (``sleap_leave_out.json``).

Prints Markdown tables and writes bench/results/sleap_loco.json (``--out``).
"""

from __future__ import annotations

import argparse
import statistics
import warnings
from pathlib import Path

import harness as h
import numpy as np

from graph.api import SolveOptions
from graph.io.calibration import load_calibration
from graph.io.keypoints import read_keypoints
from graph.metrics import leave_one_camera_out, loco_difference
from graph.solve import disagreement, problem

DATA = h.SLEAP_MINIMAL
CAMERAS = ("back", "mid", "side", "top")
FPS = 30.0


def files(data: Path) -> list[Path]:
    return [data / c / f"minimal_{c}_proofread.analysis.h5" for c in CAMERAS]


def aniposelib_reconstruct(data: Path, optim: bool):
    """aniposelib on the kept cameras, every detection given (calibration units: mm)."""
    from aniposelib.cameras import CameraGroup

    full = CameraGroup.load(str(data / "calibration.toml"))

    def reconstruct(keypoints, calibration):
        cg = full.subset_cameras_names(calibration.names)
        pts = np.stack([k.xy for k in keypoints]).copy()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            if optim:
                X = cg.triangulate_optim(pts)
            else:
                C, N, M, _ = pts.shape
                X = cg.triangulate(pts.reshape(C, N * M, 2), progress=False).reshape(N, M, 3)
        return list(keypoints[0].bodyparts), np.asarray(X)

    return reconstruct


def leave_out_simulated() -> dict:
    """The named camera kept, left out, and the clean rig: 3D error (mm) on simulated runs."""
    import dataclasses

    from graph.api import solve
    from graph.camera import Calibration
    from graph.io.calibration import default_rig_path
    from graph.simulate import simulate_run

    rig = load_calibration(default_rig_path())
    out = {}
    for subset in ([0, 1, 2, 3, 4, 5], [0, 1, 2, 3], [1, 2, 3, 4]):
        for seed in (0, 1, 2):
            run = simulate_run(rig, frames=200, seed=seed)
            cams = [rig.cameras[i] for i in subset]
            kps = [run.keypoints[i] for i in subset]
            wrong = [cams[0], dataclasses.replace(cams[2], name=cams[1].name), *cams[2:]]
            for method in ("tri", "fte"):
                row = {}
                for tag, cal, k in (("kept", wrong, kps), ("left out", wrong[:1] + wrong[2:], kps[:1] + kps[2:]),
                                    ("clean", cams, kps)):
                    r = solve(k, Calibration(cameras=cal), SolveOptions(method=method, fps=run.fps))
                    e = np.linalg.norm(r.positions - run.positions, axis=-1) * 1000
                    row[tag] = [float(np.nanmedian(e)), float(np.nanpercentile(e, 90))]
                key = f"{len(subset)} cameras {subset}, seed {seed}, {method}"
                out[key] = row
                print(f"  {key}: " + ", ".join(f"{t} {a:.1f}/{b:.1f} mm" for t, (a, b) in row.items()), flush=True)
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", type=Path, default=DATA)
    ap.add_argument("--repeats", type=int, default=1, help="LOCO runs of each method")
    ap.add_argument("--skip-aniposelib", action="store_true")
    ap.add_argument("--out", default="sleap_loco", help="bench/results/OUT.json")
    ap.add_argument("--leave-out", action="store_true", help="measure leaving a faulty camera out, simulated")
    args = ap.parse_args()
    warnings.filterwarnings("ignore")
    if args.leave_out:
        path = h.save("sleap_leave_out", {"machine": h.machine(), "results": leave_out_simulated()})
        print(f"wrote {path}")
        return 0
    data = args.data
    cal = load_calibration(data / "calibration.toml")
    kps = [read_keypoints(p) for p in files(data)]
    info = h.machine()
    print(f"# SLEAP minimal session LOCO: {kps[0].frames} frames, {len(cal)} cameras, {len(kps[0].bodyparts)} "
          f"nodes; {info['cpu']}, {info['cores']} cores, load {info['load_average'][0]:.1f}", flush=True)

    every = dict(skeleton="points", fps=FPS, likelihood_threshold=0.0)
    ours = {"acinoset fte points": SolveOptions(method="fte", **every),
            "acinoset tri": SolveOptions(method="tri", **every)}
    methods = {name: (lambda o=o, name=name: leave_one_camera_out(kps, cal, o, method=name, confidence=0.0))
               for name, o in ours.items()}
    if not args.skip_aniposelib:
        for optim, name in ((True, "aniposelib triangulate_optim"), (False, "aniposelib triangulate")):
            rec = aniposelib_reconstruct(data, optim)
            methods[name] = (lambda rec=rec, name=name:
                             leave_one_camera_out(kps, cal, reconstruct=rec, method=name, confidence=0.0))
    for run in methods.values():  # warm-up: acinoset's kernels, aniposelib's compile
        run()

    prob = problem.build(kps, cal, ours["acinoset fte points"])
    agreements = disagreement.camera_agreement(prob.calibration, prob.meas, prob.valid, prob.sigma_px)
    named, said = disagreement.check(prob.calibration, prob.meas, prob.valid, prob.sigma_px)
    print("\ncamera agreement (each camera against the others' robust triangulation):")
    print(h.markdown_table(["camera", "held out px", "others agree px", "reference px", "judged", "named"],
                           [[a.camera, a.held_out_px, a.agreement_px, a.reference_px, a.count, a in named]
                            for a in agreements]))
    print(f"warning: {said}")

    summary, last = {}, {}
    for name, run in methods.items():
        scores = [run() for _ in range(args.repeats)]
        for r, s in enumerate(scores):
            print(f"  {name:<32} run {r + 1}: median {s.median_px:.3f} px  p90 {s.p90_px:.3f} px  "
                  f"coverage {s.coverage:.3f}  {s.seconds:.2f} s", flush=True)
        last[name] = scores[-1]
        summary[name] = {**scores[-1].to_dict(), "seconds_runs": [s.seconds for s in scores],
                         "median_s": statistics.median(s.seconds for s in scores)}

    share = lambda v: "-" if v is None else v  # noqa: E731
    print()
    print(h.markdown_table(
        ["method", "median px", "p90 px", "in 90 %", *[f"{n} held out: median px" for n in cal.names],
         "s (4 solves)"],
        [[name, s["median_px"], s["p90_px"], share(s.get("within_90")), *[c["median_px"] for c in s["cameras"]],
          s["median_s"]] for name, s in summary.items()]))
    print()
    print(h.markdown_table(
        ["method", *[f"{n}: p90 px" for n in cal.names], *[f"{n}: in 90 %" for n in cal.names]],
        [[name, *[c["p90_px"] for c in s["cameras"]], *[share(c.get("within_90")) for c in s["cameras"]]]
         for name, s in summary.items()]))
    versus = {}
    peer = "aniposelib triangulate_optim"
    if peer in last:
        for name in ours:
            versus[name] = {"against": peer, **loco_difference(last[peer], last[name]).to_dict()}
    path = h.save(args.out, {
        "machine": info, "args": {k: str(v) for k, v in vars(args).items()}, "fps": FPS,
        "agreement": [{"camera": a.camera, "held_out_px": a.held_out_px, "agreement_px": a.agreement_px,
                       "reference_px": a.reference_px, "count": a.count, "named": a in named} for a in agreements],
        "warning": said, "results": summary, "versus_aniposelib": versus})
    print(f"\nwrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
