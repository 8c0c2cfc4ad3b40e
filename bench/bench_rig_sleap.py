"""A whole rig from real ChArUco images in one command, against the rig Anipose made from them.

    .venv/bin/python bench/bench_rig_sleap.py [--data DIR] [--repeats 3] [--out rig_sleap]

The data (:data:`harness.SLEAP_MINIMAL`, its SOURCE.md): four cameras (back, mid, side, top;
1280x1024), about 21 ChArUco images each (8x11 squares of 24 mm, 18.75 mm markers, DICT_4X4_1000),
and the session's Anipose ``calibration.toml`` (millimetres; its entry for side is a copy of top's).

What runs, from a shell, each ``--repeats`` times (the median kept):
``acinoset calibrate rig <four image folders> --board ... --model pinhole --names ...`` with the
intrinsics held at each camera's own calibration, and with ``--refine-intrinsics``. The images are
linked into a scratch folder first, so the detections' cache lands there, not beside the data; the
first repeat of each detects (cold), the others read the cache.

Scored against Anipose's calibration (there is no truth): the baselines between back, mid and top
(Anipose's own entries) as a ratio, and the angle between the relative rotations; the board RMS per
camera (the rig's own fit); and on the mouse (SLEAP's proofread ``.slp``, every point, ``tri``),
leave one camera out, our rig against Anipose's on back, mid and top (side has no entry of its own
there) and our rig's side.

Prints Markdown tables and writes bench/results/rig_sleap.json (``--out``).
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import statistics
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from harness import SLEAP_MINIMAL, save, time_command  # noqa: E402

CAMERAS = ("back", "mid", "side", "top")
OWN = ("back", "mid", "top")  # the cameras Anipose's file has its own entries for
BOARD = "charuco:8x11:0.024:0.01875:DICT_4X4_1000"
EXE = str(Path(sys.executable).with_name("acinoset"))


def linked_images(data: Path, scratch: Path) -> list[Path]:
    """Each camera's calibration images linked into ``scratch/<camera>`` (the cache goes there)."""
    folders = []
    for cam in CAMERAS:
        folder = scratch / cam
        folder.mkdir(parents=True)
        for image in sorted((data / cam / "calibration_images").glob("*.jpg")):
            (folder / image.name).symlink_to(image)
        folders.append(folder)
    return folders


def compare(ours_path: Path, data: Path) -> dict:
    from graph.calibrate.poses import rotation_angle
    from graph.camera import Calibration
    from graph.io.calibration import load_calibration
    from graph.io.keypoints import read_keypoints
    from graph.metrics import leave_one_camera_out
    from graph.types import SolveOptions

    ours, anipose = load_calibration(ours_path), load_calibration(data / "calibration.toml")
    o, a = dict(zip(ours.names, ours.cameras)), dict(zip(anipose.names, anipose.cameras))
    pairs = {}
    for p, q in itertools.combinations(OWN, 2):
        b_ours = float(np.linalg.norm(o[p].center - o[q].center)) * 1000.0  # ours in metres, Anipose's in mm
        b_anipose = float(np.linalg.norm(a[p].center - a[q].center))
        turn = rotation_angle((o[q].R @ o[p].R.T) @ (a[q].R @ a[p].R.T).T)
        pairs[f"{p}-{q}"] = {"baseline_mm": b_ours, "anipose_mm": b_anipose, "ratio": b_ours / b_anipose,
                             "rotation_deg": float(np.degrees(turn))}
    kps = {c: read_keypoints(data / c / f"minimal_{c}_proofread.slp") for c in CAMERAS}
    opts = SolveOptions(method="tri", skeleton="points", fps=30.0, likelihood_threshold=0.0)
    loco = {}
    for name, cal, cams in (("ours", ours, CAMERAS), ("ours, back/mid/top", ours, OWN),
                            ("Anipose, back/mid/top", anipose, OWN)):
        d = dict(zip(cal.names, cal.cameras))
        sub = Calibration(cameras=[d[c] for c in cams], metadata=cal.metadata)
        r = leave_one_camera_out([kps[c] for c in cams], sub, opts, confidence=0.0)
        loco[name] = {"cameras": {c: r.cameras[k].median_px for k, c in enumerate(cams)}, "median_px": r.median_px}
    return {"pairs": pairs, "loco": loco}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", type=Path, default=SLEAP_MINIMAL)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", default="rig_sleap")
    args = ap.parse_args()
    env = dict(os.environ)
    doc: dict = {"variants": {}}
    with tempfile.TemporaryDirectory() as tmp:
        for variant, extra in (("intrinsics held", []), ("--refine-intrinsics", ["--refine-intrinsics"]),
                               ("--lens k1 (Anipose's lens)", ["--lens", "k1"]),
                               ("--lens k1 --refine-intrinsics", ["--lens", "k1", "--refine-intrinsics"])):
            scratch = Path(tmp) / "".join(ch if ch.isalnum() else "_" for ch in variant)
            folders = linked_images(args.data, scratch / "images")
            out, report = scratch / "calibration.toml", scratch / "report.json"
            runs = []
            for _ in range(args.repeats):
                runs.append(time_command([EXE, "calibrate", "rig", *map(str, folders), "--board", BOARD,
                                          "--model", "pinhole", "--names", ",".join(CAMERAS), *extra,
                                          "--out", str(out), "--report", str(report)], env))
                if runs[-1]["exit"] != 0:
                    print(runs[-1]["stderr_tail"], file=sys.stderr)
                    return 1
            rep = json.loads(report.read_text())
            doc["variants"][variant] = {
                "cold_s": runs[0]["wall_s"], "warm_s": statistics.median(r["wall_s"] for r in runs[1:] or runs),
                "peak_rss_mib": max(r["peak_rss_mib"] for r in runs), "load": runs[-1]["load"],
                "rms_px": {c["name"]: c["rms_px"] for c in rep["cameras"]}, **compare(out, args.data)}
    for variant, v in doc["variants"].items():
        print(f"\n### {variant}: cold {v['cold_s']:.2f} s, warm {v['warm_s']:.2f} s, peak {v['peak_rss_mib']:.0f} MiB")
        print("board RMS px: " + ", ".join(f"{c} {r:.3f}" for c, r in v["rms_px"].items()))
        print("\n| pair | ours mm | Anipose mm | ratio | rotation apart (deg) |\n|---|---|---|---|---|")
        for pair, p in v["pairs"].items():
            print(f"| {pair} | {p['baseline_mm']:.1f} | {p['anipose_mm']:.1f} | {p['ratio']:.4f} | "
                  f"{p['rotation_deg']:.2f} |")
        print("\n| leave one camera out (tri) | " + " | ".join(CAMERAS) + " | pooled |\n|---|---|---|---|---|---|")
        for name, r in v["loco"].items():
            cells = [f"{r['cameras'][c]:.1f}" if c in r["cameras"] else "" for c in CAMERAS]
            print(f"| {name} | " + " | ".join(cells) + f" | {r['median_px']:.1f} |")
    print(save(args.out, doc))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
