"""The peer: Anipose's ``label-2d-proj`` on the same footage and estimate as ``bench_video.py``.

``anipose label-2d-proj`` (anipose 1.1.24, the newest on PyPI) does, for each camera's video in turn:
project the 3D CSV into the camera (``anipose.project_2d.get_projected_points``, aniposelib's
camera model), write those points as a DeepLabCut H5, then ``anipose.label_videos.visualize_labels``:
decode with OpenCV, convert to RGB, draw the bones and points with OpenCV, and pipe RGB frames to
ffmpeg through scikit-video (``-vcodec h264 -qp 28 -pix_fmt yuv420p``, x264's default preset).

Two things stop it as published on this stack, and are bridged here without touching its code:
its H5 step calls ``DataFrame.to_hdf`` with the key as a positional argument, which pandas 3
refuses (so the points go to ``visualize_labels`` as the DataFrame it accepts); scikit-video
1.1.11 calls ``ndarray.tostring``, removed in numpy 2 (frames are handed to it as an ndarray view
that still has ``tostring``). scikit-video finds ffmpeg in a folder holding ``ffmpeg`` and
``ffprobe``: both are links to the binary of the imageio-ffmpeg wheel (the writer runs only ffmpeg).

Setup (a folder of its own, not the project's environment)::

    pip install --target /tmp/peer/lib --no-deps anipose==1.1.24 scikit-video==1.1.11

Run after ``bench_video.py`` made its input (it reuses ``--work``'s footage, ``result.csv`` and
calibration); ``--cameras cam1`` measures one camera (label-2d-proj renders them one after the
other, so six cost six times one). Writes ``bench/results/video_anipose.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))

from harness import RESULTS_DIR, machine  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--work", type=Path, default=Path("/tmp/acinoset-bench-video"))
    ap.add_argument("--peer-lib", type=Path, default=Path("/tmp/peer/lib"))
    ap.add_argument("--cameras", nargs="+", default=["cam1"])
    args = ap.parse_args()
    sys.path.insert(0, str(args.peer_lib))

    import imageio_ffmpeg
    import numpy as np
    import pandas as pd
    import skvideo

    bin_dir = args.work / "peer-ffmpeg"
    bin_dir.mkdir(exist_ok=True)
    for name in ("ffmpeg", "ffprobe"):
        if not (bin_dir / name).exists():
            os.symlink(imageio_ffmpeg.get_ffmpeg_exe(), bin_dir / name)
    skvideo.setFFmpegPath(str(bin_dir))
    import skvideo.io
    from anipose.anipose import DEFAULT_CONFIG
    from anipose.label_videos import visualize_labels
    from anipose.project_2d import get_projected_points
    from aniposelib.cameras import CameraGroup

    class Frame(np.ndarray):
        """An ndarray view with numpy 1's ``tostring`` (scikit-video 1.1.11 calls it)."""

        def tostring(self):
            return self.tobytes()

    write_frame = skvideo.io.FFmpegWriter.writeFrame
    skvideo.io.FFmpegWriter.writeFrame = lambda self, im: write_frame(self, np.asarray(im).view(Frame))

    from graph.io.results import read_result

    result = read_result(args.work / "result.h5")
    config = {**DEFAULT_CONFIG, "labeling": {"scheme": [list(b) for b in result.bones]},
              "triangulation": {**DEFAULT_CONFIG["triangulation"], "cam_regex": "-(cam[0-9])"}}
    cgroup = CameraGroup.load(str(args.work / "input" / "calibration.toml")).subset_cameras_names(args.cameras)
    out = args.work / "out_anipose"
    out.mkdir(exist_ok=True)
    before = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    bodyparts, proj, scores = get_projected_points(config, str(args.work / "result.csv"), cgroup,
                                                   {c: (0, 0) for c in args.cameras})
    for cix, cam in enumerate(args.cameras):
        pts = proj[cix].swapaxes(0, 1)
        cols = pd.MultiIndex.from_product([bodyparts, ["x", "y", "likelihood"]], names=["bodyparts", "coords"])
        table = pd.DataFrame(np.concatenate([pts, scores.T[..., None]], axis=2).reshape(pts.shape[0], -1),
                             columns=cols)
        visualize_labels(config, table, str(args.work / "input" / f"{cam}.mp4"), str(out / f"{cam}.mp4"))
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = sum((a.ru_utime - b.ru_utime) + (a.ru_stime - b.ru_stime) for a, b in zip(after, before))
    doc = {"machine": machine(), "peer": "anipose 1.1.24 label-2d-proj (get_projected_points + visualize_labels)",
           "cameras": args.cameras, "frames": int(proj.shape[2]), "wall_s": wall, "cpu_s": cpu,
           "peak_rss_mb_python": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
           "output_bytes": {p.name: p.stat().st_size for p in sorted(out.iterdir())}}
    print(f"anipose label-2d-proj, {len(args.cameras)} camera(s) x {doc['frames']} frames: {wall:.1f} s wall, "
          f"{cpu:.1f} s CPU")
    RESULTS_DIR.mkdir(exist_ok=True)
    (RESULTS_DIR / "video_anipose.json").write_text(json.dumps(doc, indent=1) + "\n", encoding="utf-8")


if __name__ == "__main__":
    main()
