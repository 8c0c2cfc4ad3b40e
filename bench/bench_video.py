"""``acinoset video`` from a shell: six 2704x1520 cameras of 150 frames, time and peak memory.

What is measured (``python bench/bench_video.py``):

1. The input, made once and kept in ``--work``: ``acinoset simulate --frames 150 --fps 120 --videos``
   on the real AcinoSet 2019 rig (six 2704x1520 fisheye GoPros): each camera's footage of the
   simulated cheetah, H.264 at a GoPro's bitrate (60 Mbit/s at 120 fps), and its DeepLabCut CSVs;
   then ``acinoset solve ... --method fte --h5 result.h5``.
2. Speed: ``acinoset video result.h5 --videos cam1.mp4 ... cam6.mp4 --out DIR`` run by the shell,
   ``--repeats`` times, and once more with ``--combined``: wall seconds, the CPU seconds of the
   command and every process it started (``RUSAGE_CHILDREN``), camera-frames per second
   (6 x 150 / wall). Target: at most 18 s (50 camera-frames/s).
3. Memory: the peak resident memory of the command and all its processes together (its Python
   process and the ffmpeg decoders and encoders), sampled from ``/proc`` every 20 ms. Target: under
   1.5 GB for a 20 000-frame video. Streaming keeps memory flat in the number of frames; this is
   shown, not assumed, by running the same command on the same footage looped ``--long-loops``
   times (``ffmpeg -stream_loop N -c copy``: every frame decoded and encoded as in a real long
   video) with the result repeated to match, and comparing the peak with the 150-frame one; and by
   a 20 000-frame result and 20 000-frame videos rendered over their first ``--tail-frames``
   frames (``--frames 0:K``), which holds everything a 20 000-frame job holds but the hours of CPU.

Results go to ``bench/results/video.json``; the machine is shared (its load average is recorded).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shlex
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from harness import RESULTS_DIR, machine  # noqa: E402

CAMERAS = 6
ACINOSET = str(ROOT / ".venv" / "bin" / "acinoset")


def tree_rss(pid: int) -> int:
    """Resident bytes of ``pid`` and all its descendants (from /proc)."""
    children: dict[int, list[int]] = {}
    rss: dict[int, int] = {}
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/stat") as f:
                parts = f.read().rsplit(")", 1)[1].split()
            p = int(entry)
            children.setdefault(int(parts[1]), []).append(p)
            rss[p] = int(parts[21]) * os.sysconf("SC_PAGE_SIZE")
        except (OSError, IndexError, ValueError):
            continue
    total, todo = 0, [pid]
    while todo:
        p = todo.pop()
        total += rss.get(p, 0)
        todo.extend(children.get(p, []))
    return total


def run_measured(command: str, cwd: Path) -> dict:
    """Run ``command`` in a shell; wall and CPU seconds, peak memory of its process tree, and the
    trace of memory over time."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    proc = subprocess.Popen(command, shell=True, cwd=cwd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    trace: list[tuple[float, int]] = []
    stop = threading.Event()

    def sample():
        while not stop.is_set():
            trace.append((time.perf_counter() - t0, tree_rss(proc.pid)))
            stop.wait(0.02)

    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    out, err = proc.communicate()
    wall = time.perf_counter() - t0
    stop.set()
    sampler.join()
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if proc.returncode != 0:
        raise SystemExit(f"failed ({proc.returncode}): {command}\n{err}")
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return {"command": command, "wall_s": wall, "cpu_s": cpu, "peak_rss_mb": max(r for _, r in trace) / 2**20,
            "stdout": out.strip(), "rss_trace_mb": [(round(t, 2), round(r / 2**20, 1)) for t, r in trace[::10]]}


def shell(command: str, cwd: Path) -> None:
    print(f"$ {command}", flush=True)
    subprocess.run(command, shell=True, cwd=cwd, check=True)


def make_input(work: Path, frames: int) -> Path:
    inp = work / "input"
    if not (inp / f"cam{CAMERAS}.mp4").exists():
        shell(f"{ACINOSET} simulate --frames {frames} --fps 120 --videos --out input", work)
    if not (work / "result.h5").exists():
        csvs = " ".join(f"input/cam{c + 1}.csv" for c in range(CAMERAS))
        shell(f"{ACINOSET} solve {csvs} --calibration input/calibration.toml --method fte --fps 120 "
              f"--h5 result.h5 --out result.csv", work)
    return inp


def looped(work: Path, inp: Path, loops: int, name: str) -> tuple[Path, list[Path]]:
    """The footage played ``loops`` times in a row (stream copy: no re-encoding) and the result
    repeated to match, under ``work/name``."""
    from graph.io.results import read_result, write_h5
    from graph.video import ffmpeg_exe

    d = work / name
    d.mkdir(exist_ok=True)
    videos = [d / f"cam{c + 1}.mp4" for c in range(CAMERAS)]
    for c, v in enumerate(videos):
        if not v.exists():
            subprocess.run([ffmpeg_exe(), "-v", "error", "-y", "-stream_loop", str(loops - 1), "-i",
                            str(inp / f"cam{c + 1}.mp4"), "-c", "copy", str(v)], check=True)
    h5 = d / "result.h5"
    if not h5.exists():
        r = read_result(work / "result.h5")
        for f in ("positions", "std", "ncams", "score", "params", "rates", "params_std"):
            a = getattr(r, f)
            if a is not None:
                setattr(r, f, np.concatenate([a] * loops, axis=0))
        for f in ("reprojections", "residuals", "outlier", "detections", "likelihood"):
            a = getattr(r, f)
            if a is not None:
                setattr(r, f, np.concatenate([a] * loops, axis=1))
        r.report.frames = r.positions.shape[0]
        write_h5(h5, r)
    return h5, videos


def video_command(h5: Path, videos: list[Path], out: Path, extra: str = "") -> str:
    return (f"{ACINOSET} video {shlex.quote(str(h5))} --videos {' '.join(shlex.quote(str(v)) for v in videos)} "
            f"--out {shlex.quote(str(out))} {extra}").strip()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--work", type=Path, default=Path("/tmp/acinoset-bench-video"))
    ap.add_argument("--frames", type=int, default=150)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--long-loops", type=int, default=20, help="the footage played this many times in a row")
    ap.add_argument("--tail-frames", type=int, default=600, help="frames rendered of the 20 000-frame input")
    ap.add_argument("--skip-long", action="store_true")
    args = ap.parse_args()
    work = args.work
    work.mkdir(parents=True, exist_ok=True)
    inp = make_input(work, args.frames)
    videos = [inp / f"cam{c + 1}.mp4" for c in range(CAMERAS)]
    h5 = work / "result.h5"
    camera_frames = CAMERAS * args.frames
    doc: dict = {"machine": machine(), "frames": args.frames, "cameras": CAMERAS, "size": [2704, 1520],
                 "input_bytes": sum(v.stat().st_size for v in videos)}

    runs = []
    for k in range(args.repeats):
        r = run_measured(video_command(h5, videos, work / "out"), work)
        r["camera_frames_per_s"] = camera_frames / r["wall_s"]
        runs.append(r)
        print(f"video: {r['wall_s']:.1f} s wall, {r['cpu_s']:.1f} s CPU, {r['camera_frames_per_s']:.0f} "
              f"camera-frames/s, peak {r['peak_rss_mb']:.0f} MB (load {os.getloadavg()[0]:.1f})", flush=True)
    doc["video"] = runs
    doc["video_median_s"] = float(np.median([r["wall_s"] for r in runs]))
    doc["video_best_s"] = float(np.min([r["wall_s"] for r in runs]))
    r = run_measured(video_command(h5, videos, work / "out_combined", "--combined"), work)
    r["camera_frames_per_s"] = camera_frames / r["wall_s"]
    doc["video_combined"] = r
    print(f"video --combined: {r['wall_s']:.1f} s wall, {r['cpu_s']:.1f} s CPU, peak {r['peak_rss_mb']:.0f} MB",
          flush=True)
    doc["output_bytes"] = {p.name: p.stat().st_size for p in sorted((work / "out_combined").iterdir())}

    if not args.skip_long:
        loops = args.long_loops
        lh5, lvideos = looped(work, inp, loops, f"loop{loops}")
        r = run_measured(video_command(lh5, lvideos, work / "out_long", "--combined"), work)
        r["frames"] = loops * args.frames
        r["camera_frames_per_s"] = CAMERAS * r["frames"] / r["wall_s"]
        doc["long"] = r
        print(f"long ({r['frames']} frames, --combined): {r['wall_s']:.1f} s, peak {r['peak_rss_mb']:.0f} MB",
              flush=True)
        big = int(np.ceil(20000 / args.frames))
        bh5, bvideos = looped(work, inp, big, f"loop{big}")
        r = run_measured(video_command(bh5, bvideos, work / "out_20000", f"--combined --frames 0:{args.tail_frames}"),
                         work)
        r["frames_in_videos"] = big * args.frames
        r["frames_rendered"] = args.tail_frames
        doc["long_20000"] = r
        print(f"{big * args.frames}-frame input, first {args.tail_frames} rendered: peak {r['peak_rss_mb']:.0f} MB",
              flush=True)

    RESULTS_DIR.mkdir(exist_ok=True)
    (RESULTS_DIR / "video.json").write_text(json.dumps(doc, indent=1) + "\n", encoding="utf-8")
    print(f"wrote {RESULTS_DIR / 'video.json'}")


if __name__ == "__main__":
    main()
