"""A rig refined from a mouse's keypoints on real data (SLEAP's minimal session): acinoset against aniposelib.

    .venv/bin/python bench/bench_refine_sleap.py [--data DIR] [--likelihood 0.01] [--repeats 3] [--out refine_sleap]

The data (:data:`harness.SLEAP_MINIMAL`, its SOURCE.md): one mouse seen by four cameras (back, mid,
side, top), SLEAP's proofread predictions (``<cam>/minimal_<cam>_proofread.slp``: 120 frames, 15
bodyparts) and the Anipose calibration shipped with them (calibration.toml, millimetres). That
calibration's "side" entry is a copy of "top"'s, so side's detections sit ~96 px from where the rig
puts them: a refinement has a broken camera to mend, not only small errors to polish.

The detections used are those with a SLEAP point score of at least ``--likelihood`` (default 0.01:
the scores of these files are low, median ~0.4, so the 0.9 of a DeepLabCut run would leave almost
nothing). The 120 frames are split as acinoset splits them internally
(:func:`graph.calibrate.refine.split_blocks`: ten blocks of 12 frames, the 1st, 3rd, ... "fit", the
others "held").

What runs, and which frames each saw:

* acinoset ``calibrate refine CALIBRATION back.slp mid.slp side.slp top.slp --likelihood L --out ...
  --report ...`` from a shell (the whole command: reading, the adjustment, its own held-out check,
  writing), timed with wall time and peak RSS, the median of ``--repeats``. It is given all 120
  frames: it adjusts on the fit frames, checks the result on the held frames, and - when the check
  accepts the new rig - adjusts once more on all 120 frames, from the accepted rig. So the rig it
  writes has seen the held frames too: its "held" score below is not a held-out score in the strict
  sense (its own report's check, on the rig before the last adjustment, is; it is saved in the JSON).
* aniposelib ``CameraGroup.load(calibration.toml)`` then ``bundle_adjust_iter(p2ds,
  only_extrinsics=True)`` with every other option at its default, given the fit frames only (NaN
  where below the threshold), in this process; its time is the call's alone (the library already
  imported, no peak RSS). It samples points at random (``np.random``), so the global generator is
  seeded (0) before each call. Its rig is written with its own ``dump`` and read back with
  :func:`graph.io.calibration.load_calibration`. Should the call raise, its error is recorded as
  its result.
* the shipped calibration, unchanged.

The score: leave one camera out - each camera's detections (above the threshold) predicted by the
robust triangulation of the other cameras (:func:`graph.calibrate.refine.leave_one_out`), the
median px per camera and their mean; on the held frames and on all frames. Beside it, how far each
rig turned mid and top relative to back from the shipped rig's (whose back, mid and top entries are
Anipose's own board calibration, and agree within about 1 degree with ours from the session's
images): the keypoints can be fitted better by turning cameras than the rig could have turned (the
mouse is seen through a curved acrylic wall), so a lower error is not by itself a better rig.

Prints Markdown tables and writes bench/results/refine_sleap.json (``--out``).
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
import statistics
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from harness import SLEAP_MINIMAL, machine, save, time_command  # noqa: E402

CAMERAS = ("back", "mid", "side", "top")
EXE = str(Path(sys.executable).with_name("acinoset"))
SEED = 0


def keypoint_path(data: Path, cam: str) -> Path:
    return data / cam / f"minimal_{cam}_proofread.slp"


def main() -> int:
    from graph.calibrate.poses import rotation_angle
    from graph.calibrate.refine import _measurements, leave_one_out, split_blocks
    from graph.camera import Calibration
    from graph.io.calibration import load_calibration
    from graph.io.keypoints import read_keypoints

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", type=Path, default=SLEAP_MINIMAL)
    ap.add_argument("--likelihood", type=float, default=0.01)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", default="refine_sleap")
    args = ap.parse_args()
    calib_path = args.data / "calibration.toml"
    rig = load_calibration(calib_path)
    kps = [read_keypoints(keypoint_path(args.data, c)) for c in CAMERAS]
    meas, valid = _measurements(rig, kps, args.likelihood)  # (N, C, M, 2), (N, C, M)
    N = len(meas)
    fit, held = split_blocks(N)
    every = np.ones(N, bool)
    doc: dict = {
        "machine": machine(), "data": str(args.data), "likelihood": args.likelihood, "repeats": args.repeats,
        "frames": N, "bodyparts": int(meas.shape[2]),
        "fit_frames": np.flatnonzero(fit).tolist(), "held_frames": np.flatnonzero(held).tolist(),
        "detections_kept_per_camera": dict(zip(CAMERAS, valid.sum(axis=(0, 2)).tolist())),
        "score": "leave one camera out, median px per camera (graph.calibrate.refine.leave_one_out)",
        "rigs": {}}

    def turned(cal: Calibration, i: int) -> float:
        """Camera i's rotation relative to back, against the shipped rig's, in degrees."""
        rel = cal.cameras[i].R @ cal.cameras[0].R.T
        rel0 = rig.cameras[i].R @ rig.cameras[0].R.T
        return float(np.degrees(rotation_angle(rel @ rel0.T)))

    def score(name: str, cal: Calibration | None, frames_seen: str, seconds: float | None = None,
              peak_rss_mib: float | None = None, **extra) -> None:
        entry: dict = {"frames_seen": frames_seen, "seconds": seconds, "peak_rss_mib": peak_rss_mib}
        if cal is not None:
            entry["turned_deg"] = {c: turned(cal, i) for i, c in enumerate(CAMERAS) if c in ("mid", "top")}
            for label, rows in (("held", held), ("all", every)):
                per_cam = leave_one_out(cal, meas[rows], valid[rows])
                entry[label] = {"cameras": dict(zip(CAMERAS, per_cam)), "mean_px": float(np.nanmean(per_cam))}
        doc["rigs"][name] = {**entry, **extra}

    score("as shipped", rig, "none")

    # acinoset: the whole command, all frames given
    with tempfile.TemporaryDirectory() as tmp:
        out, report = Path(tmp) / "refined.toml", Path(tmp) / "report.json"
        cmd = [EXE, "calibrate", "refine", str(calib_path), *(str(keypoint_path(args.data, c)) for c in CAMERAS),
               "--likelihood", str(args.likelihood), "--out", str(out), "--report", str(report)]
        runs = [time_command(cmd, dict(os.environ)) for _ in range(args.repeats)]
        seen = (f"all {N} (adjusted on the {int(fit.sum())} fit frames, checked on the {int(held.sum())} held "
                f"frames, then - if accepted - adjusted again on all {N})")
        if any(r["exit"] != 0 for r in runs):
            failed = next(r for r in runs if r["exit"] != 0)
            print(failed["stderr_tail"], file=sys.stderr)
            score("acinoset calibrate refine", None, seen, error=f"exit {failed['exit']}: {failed['stderr_tail']}")
        else:
            rep = json.loads(report.read_text())
            score("acinoset calibrate refine", load_calibration(out), seen,
                  statistics.median(r["wall_s"] for r in runs), max(r["peak_rss_mib"] for r in runs),
                  wall_s=[r["wall_s"] for r in runs], cpu_s=[r["cpu_s"] for r in runs],
                  accepted=rep["accepted"], own_check=rep["leave_one_out_px"], changes=rep["cameras"],
                  notes=rep["notes"], stderr_tail=runs[-1]["stderr_tail"], load=runs[-1]["load"])

    # aniposelib: fit frames only
    from aniposelib.cameras import CameraGroup

    xy = np.where(valid[fit][..., None], meas[fit], np.nan)  # (n, C, M, 2)
    p2ds = xy.transpose(1, 0, 2, 3).reshape(len(CAMERAS), -1, 2)  # (C, n*M, 2)
    name = "aniposelib bundle_adjust_iter"
    seen = f"the {int(fit.sum())} fit frames"
    times, errors, params, printed, caught = [], [], [], "", []
    failure = None
    group = None
    for _ in range(args.repeats):
        group = CameraGroup.load(str(calib_path))
        np.random.seed(SEED)
        buf = io.StringIO()
        with warnings.catch_warnings(record=True) as w, contextlib.redirect_stdout(buf):
            warnings.simplefilter("always")
            t0 = time.perf_counter()
            try:
                errors.append(float(group.bundle_adjust_iter(p2ds, only_extrinsics=True)))
            except Exception as exc:  # recorded as the result, not a failure of the bench
                failure = f"{type(exc).__name__}: {exc}"
            times.append(time.perf_counter() - t0)
        printed = buf.getvalue()
        caught = sorted({f"{x.category.__name__}: {x.message}" for x in w})
        if failure is not None:
            break
        params.append(np.concatenate([np.ravel(c.get_params()) for c in group.cameras]))
    extra = {"wall_s": times, "stdout_tail": printed.strip()[-1500:], "warnings": caught}
    if failure is not None:
        score(name, None, seen, error=failure, **extra)
    else:
        assert group is not None
        same = all(np.allclose(p, params[0]) for p in params)
        with tempfile.TemporaryDirectory() as tmp:
            group.dump(str(Path(tmp) / "aniposelib.toml"))
            score(name, load_calibration(Path(tmp) / "aniposelib.toml"), seen, statistics.median(times),
                  reported_error_px=errors, repeats_agree=same, seed=SEED, **extra)

    print(f"\n{N} frames, {meas.shape[2]} bodyparts, detections with score >= {args.likelihood}; "
          f"fit frames {int(fit.sum())}, held frames {int(held.sum())} (graph.calibrate.refine.split_blocks).")
    print("Leave one camera out, median px per camera.\n")
    for label, title in (("held", f"the {int(held.sum())} held frames"), ("all", f"all {N} frames")):
        print(f"Scored on {title}:\n")
        print("| rig | " + " | ".join(CAMERAS) + " | mean | mid, top turned (deg) | seconds | peak MiB |\n"
              "|---|---|---|---|---|---|---|---|---|")
        for rname, r in doc["rigs"].items():
            secs = "" if r["seconds"] is None else f"{r['seconds']:.2f}"
            peak = "" if r["peak_rss_mib"] is None else f"{r['peak_rss_mib']:.0f}"
            if label in r:
                cells = " | ".join(f"{r[label]['cameras'][c]:.2f}" for c in CAMERAS)
                mean = f"{r[label]['mean_px']:.2f}"
            else:
                cells, mean = " | ".join("error" for _ in CAMERAS), "error"
            turn = ", ".join(f"{v:.1f}" for v in r.get("turned_deg", {}).values())
            print(f"| {rname} | {cells} | {mean} | {turn} | {secs} | {peak} |")
        print()
    print("Frames each rig saw:")
    for rname, r in doc["rigs"].items():
        print(f"- {rname}: {r['frames_seen']}" + (f" - ERROR {r['error']}" if "error" in r else ""))
    print(save(args.out, doc))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
