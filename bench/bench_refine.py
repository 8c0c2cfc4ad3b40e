"""A rig refined from an animal's keypoints, scored on frames it did not see: acinoset against aniposelib.

    .venv/bin/python bench/bench_refine.py [--data DIR] [--frames 250] [--repeats 3] [--out refine]

The data (:data:`harness.EKS_FLY`, its SOURCE.md): a fly seen by three near-telecentric cameras
(a rig in millimetres), DeepLabCut's predictions of 12 keypoints, 500 frames, ensemble member 1.
The first ``--frames`` frames are given to each refinement; the frames after them, which neither
saw, score every rig.

What runs, on the same confident keypoints (likelihood at least 0.9):

* acinoset ``calibrate refine CALIBRATION camA camB camC --out ... --report ...`` from a shell
  (the whole command: reading, the adjustment, its own held-out check, writing), the median of
  ``--repeats``;
* aniposelib ``CameraGroup.bundle_adjust_iter`` with ``only_extrinsics=True`` and every other option
  at its default, on the same detections (NaN where not confident), in this process (its time is the
  call's alone, the library already imported).

The score: leave one camera out on the later frames - each camera's confident detections predicted
by the robust triangulation of the others (:func:`graph.calibrate.refine.leave_one_out`), the
median px per camera and their mean; the same for the rig as shipped.

Prints a Markdown table and writes bench/results/refine.json (``--out``).
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from harness import EKS_FLY, save, time_command  # noqa: E402

CAMERAS = ("A", "B", "C")
EXE = str(Path(sys.executable).with_name("acinoset"))
MIN_LIKELIHOOD = 0.9


def first_frames(source: Path, frames: int, out: Path) -> Path:
    """The DeepLabCut CSV ``source`` cut to its first ``frames`` frames (three header rows)."""
    lines = source.read_text().splitlines()
    out.write_text("\n".join(lines[:3 + frames]) + "\n")
    return out


def main() -> int:
    from graph.calibrate.refine import _measurements, leave_one_out
    from graph.camera import Calibration
    from graph.io.calibration import load_calibration
    from graph.io.keypoints import read_keypoints

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", type=Path, default=EKS_FLY)
    ap.add_argument("--frames", type=int, default=250)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", default="refine")
    args = ap.parse_args()
    rig = load_calibration(args.data / "calibration.toml")
    kps = [read_keypoints(args.data / f"cam{c}.rng1.csv") for c in CAMERAS]
    meas, valid = _measurements(rig, kps, MIN_LIKELIHOOD)  # (N, C, M, 2), (N, C, M)
    later = slice(args.frames, None)
    doc: dict = {"frames_given": args.frames, "frames_scored": int(len(meas) - args.frames), "rigs": {}}

    def score(name: str, cal: Calibration, seconds: float | None = None, **extra) -> None:
        per_cam = leave_one_out(cal, meas[later], valid[later])
        doc["rigs"][name] = {"cameras": dict(zip(CAMERAS, per_cam)), "mean_px": float(np.nanmean(per_cam)),
                             "seconds": seconds, **extra}

    score("as shipped", rig)
    with tempfile.TemporaryDirectory() as tmp:
        paths = [first_frames(args.data / f"cam{c}.rng1.csv", args.frames, Path(tmp) / f"cam{c}.csv")
                 for c in CAMERAS]
        out, report = Path(tmp) / "refined.toml", Path(tmp) / "report.json"
        runs = [time_command([EXE, "calibrate", "refine", str(args.data / "calibration.toml"), *map(str, paths),
                              "--out", str(out), "--report", str(report)], dict(os.environ))
                for _ in range(args.repeats)]
        if any(r["exit"] != 0 for r in runs):
            print(runs[-1]["stderr_tail"], file=sys.stderr)
            return 1
        import json

        rep = json.loads(report.read_text())
        score("acinoset calibrate refine", load_calibration(out), statistics.median(r["wall_s"] for r in runs),
              peak_rss_mib=max(r["peak_rss_mib"] for r in runs), accepted=rep["accepted"],
              own_check=rep["leave_one_out_px"], changes=rep["cameras"], load=runs[-1]["load"])

    from aniposelib.cameras import CameraGroup

    group = CameraGroup.load(str(args.data / "calibration.toml"))
    given = slice(0, args.frames)
    xy = np.where(valid[given][..., None], meas[given], np.nan)  # (N, C, M, 2)
    p2ds = xy.transpose(1, 0, 2, 3).reshape(len(CAMERAS), -1, 2)  # (C, N*M, 2)
    t0 = time.perf_counter()
    error = group.bundle_adjust_iter(p2ds, only_extrinsics=True, verbose=False)
    seconds = time.perf_counter() - t0
    with tempfile.TemporaryDirectory() as tmp:
        group.dump(str(Path(tmp) / "aniposelib.toml"))
        score("aniposelib bundle_adjust_iter", load_calibration(Path(tmp) / "aniposelib.toml"), seconds,
              reported_error=float(error))
    print(f"\nRefined on frames 0-{args.frames - 1}, scored on {doc['frames_scored']} later frames "
          "(leave one camera out, median px):\n")
    print("| rig | " + " | ".join(f"cam {c}" for c in CAMERAS) + " | mean | seconds |\n|---|---|---|---|---|---|")
    for name, r in doc["rigs"].items():
        secs = "" if r["seconds"] is None else f"{r['seconds']:.2f}"
        cells = " | ".join(f"{r['cameras'][c]:.3f}" for c in CAMERAS)
        print(f"| {name} | {cells} | {r['mean_px']:.3f} | {secs} |")
    print(save(args.out, doc))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
