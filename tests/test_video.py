"""Labelled videos (graph.video, ``acinoset video``, ``simulate --videos``), checked by pixels and
decoded with OpenCV and with the bundled ffmpeg. Small frames and few of them, so it stays fast."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from graph.io.calibration import default_rig_path, load_calibration, write_acinoset_json
from graph.io.results import write_h5
from graph.simulate import simulate_run, write_run
from graph.types import Result, SolveOptions, SolveReport
from graph.video import FrameWriter, YuvFrame, ffmpeg_exe, probe, render_videos, scaled_rig, write_simulated_videos
from graph.video.draw import LEFT, CameraOverlay, Style, bone_color, draw_camera_frame, yuv

ROOT = Path(__file__).resolve().parents[1]
FRAMES = 10
FPS = 30.0
SCALE = 0.125  # the AcinoSet rig's 2704x1520 cameras filmed at 338x190


def run_cli(*args) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    return subprocess.run([sys.executable, "-m", "graph.app.cli", *map(str, args)], capture_output=True, text=True,
                          env=env, timeout=300)


def truth_result(run, no_estimate: dict[int, list[int]] | None = None, offsets=None) -> Result:
    """A result whose estimate is the simulated truth (so drawings can be checked against the
    noiseless projections): camera c's frames ``no_estimate[c]`` have none."""
    reproj = run.projections.copy()
    for c, frames in (no_estimate or {}).items():
        reproj[c, frames] = np.nan
    N, M = run.positions.shape[:2]
    C = len(run.keypoints)
    report = SolveReport(method="fte", skeleton="cheetah", frames=N, cameras=C, markers=M,
                         time_offsets_frames=offsets)
    return Result(method="fte", skeleton="cheetah", markers=list(run.markers), positions=run.positions,
                  std=np.zeros_like(run.positions), reprojections=reproj, residuals=np.zeros((C, N, M)),
                  ncams=np.full((N, M), C), score=np.ones((N, M)), outlier=run.outlier,
                  camera_names=list(run.calibration.names), fps=run.fps, report=report,
                  options=SolveOptions(fps=run.fps), bones=list(run.bones),
                  camera_centers=np.stack([c.center for c in run.calibration.cameras]),
                  detections=np.stack([k.xy for k in run.keypoints]),
                  likelihood=np.stack([k.likelihood for k in run.keypoints]))


@pytest.fixture(scope="module")
def filmed(tmp_path_factory):
    """A simulated run on the AcinoSet rig at an eighth of its resolution, filmed by every camera."""
    out = tmp_path_factory.mktemp("filmed")
    rig = scaled_rig(load_calibration(default_rig_path()), SCALE)
    run = simulate_run(rig, frames=FRAMES, fps=FPS, seed=3)
    write_run(run, out)
    videos = write_simulated_videos(run, out)
    return run, videos, out


def decode_ffmpeg(path: Path, width: int, height: int) -> np.ndarray:
    """The luma plane of every frame of ``path``, decoded by the bundled ffmpeg."""
    raw = subprocess.run([ffmpeg_exe(), "-v", "error", "-i", str(path), "-f", "rawvideo", "-pix_fmt", "yuv420p", "-"],
                         capture_output=True, check=True).stdout
    return np.frombuffer(raw, np.uint8).reshape(-1, height * 3 // 2, width)[:, :height]


def stream_line(path: Path) -> str:
    """ffmpeg's description of the file's video stream."""
    err = subprocess.run([ffmpeg_exe(), "-hide_banner", "-i", str(path)], capture_output=True, text=True).stderr
    return next(line for line in err.splitlines() if "Video:" in line)


def decode_cv2(path: Path) -> list[np.ndarray]:
    cap = cv2.VideoCapture(str(path))
    frames = []
    while True:
        ok, img = cap.read()
        if not ok:
            break
        frames.append(img)
    cap.release()
    return frames


# ------------------------------------------------------------------------------- drawing, by pixels


def test_bone_is_drawn_where_the_reprojection_puts_it():
    W, H = 320, 240
    frame = YuvFrame(W, H)
    frame.y[:], frame.u[:], frame.v[:] = 16, 128, 128  # black
    a, b = np.array([40.3, 60.7]), np.array([270.2, 190.4])
    reproj = np.full((3, 2, 2), np.nan)
    reproj[1] = [a, b]
    overlay = CameraOverlay(name="cam", markers=["l_shoulder", "l_front_knee"], bones=[(0, 1)], reprojections=reproj,
                            detections=None, likelihood=None, outlier=np.zeros((3, 2), bool))
    assert draw_camera_frame(frame, overlay, 1, Style.for_width(W))
    bgr = frame.to_bgr()
    along = [a + s * (b - a) for s in np.linspace(0.1, 0.9, 30)]
    normal = np.array([-(b - a)[1], (b - a)[0]]) / np.linalg.norm(b - a)
    ly = yuv(LEFT)[0]
    for p in along:  # on the line: the bone's luma and (roughly) colour
        x, y = int(round(p[0])), int(round(p[1]))
        assert abs(int(frame.y[y, x]) - ly) <= 12, (p, frame.y[y, x], ly)
        assert np.abs(bgr[y, x].astype(int) - np.array(LEFT)).max() < 60, bgr[y, x]
    for p in along:  # 6 px to either side: untouched
        for q in (p + 6 * normal, p - 6 * normal):
            assert frame.y[int(round(q[1])), int(round(q[0]))] == 16
    # the joints are white dots exactly at the reprojections
    for p in (a, b):
        assert frame.y[int(round(p[1])), int(round(p[0]))] > 200


def test_frame_without_estimate_is_unchanged():
    rng = np.random.default_rng(0)
    frame = YuvFrame(64, 48, rng.integers(0, 256, 64 * 48 * 3 // 2, dtype=np.uint8))
    before = frame.data.copy()
    reproj = np.full((2, 2, 2), np.nan)
    reproj[0] = [[10, 10], [40, 30]]
    det = np.full((2, 2, 2), 20.0)  # detections in frame 1 too: still nothing is drawn there
    overlay = CameraOverlay(name="cam", markers=["a", "b"], bones=[(0, 1)], reprojections=reproj, detections=det,
                            likelihood=np.ones((2, 2)), outlier=np.ones((2, 2), bool))
    assert not draw_camera_frame(frame, overlay, 1)
    assert np.array_equal(frame.data, before)
    assert draw_camera_frame(frame, overlay, 0)
    assert not np.array_equal(frame.data, before)


# ------------------------------------------------------------------------------- the whole pass


def test_labelled_videos_decode_as_h264_with_the_input_frames(filmed, tmp_path):
    run, videos, _ = filmed
    result = truth_result(run, no_estimate={0: [4]})
    calls = []
    done = render_videos(result, videos, tmp_path, combined=True, progress=lambda *a: calls.append(a))
    assert calls[-1] == (7 * FRAMES, 7 * FRAMES) and len(calls) == 7 * FRAMES  # camera-frames and 3D frames
    assert not list(tmp_path.glob(".tiles-*"))  # the grid's temporary tiles are gone
    assert [p.name for p in done.cameras] == [f"cam{c + 1}_labeled.mp4" for c in range(6)]
    for path in done.paths:
        info = probe(path)
        assert info.fps == pytest.approx(FPS)
        assert info.frames == FRAMES
        line = stream_line(path)
        assert "h264" in line and "yuv420p" in line, line
        assert len(decode_cv2(path)) == FRAMES
        assert len(decode_ffmpeg(path, info.width, info.height)) == FRAMES
    cam = run.calibration.cameras[0]
    assert probe(done.cameras[0]).width == cam.size[0] and probe(done.cameras[0]).height == cam.size[1]

    # camera 1: frame 4 (no estimate) is the input frame again (up to the codec); frame 5 is drawn on
    W, H = cam.size
    src, out = decode_ffmpeg(videos[0], W, H).astype(int), decode_ffmpeg(done.cameras[0], W, H).astype(int)
    assert np.abs(out[4] - src[4]).mean() < 1.5
    assert np.abs(out[5] - src[5]).max() > 100
    # halfway along camera 1's longest bone, the labelled video has the bone's colour
    uv = run.projections[0, 5]
    a, b = max(run.bones, key=lambda ab: np.linalg.norm(uv[run.markers.index(ab[0])] - uv[run.markers.index(ab[1])]))
    mid = (uv[run.markers.index(a)] + uv[run.markers.index(b)]) / 2
    x, y = int(round(mid[0])), int(round(mid[1]))
    bgr = decode_cv2(done.cameras[0])[5]
    assert np.abs(bgr[y, x].astype(int) - np.array(bone_color(a, b))).max() < 70, (a, b, bgr[y, x])


def test_grid_matches_frames_by_the_cameras_offsets(tmp_path):
    """Camera 2 runs 2 frames late: the grid's frame n shows its frame n - 2 beside camera 1's n."""
    rig = scaled_rig(load_calibration(default_rig_path()), SCALE)
    run = simulate_run(rig, frames=FRAMES, fps=FPS, seed=3)
    W, H = rig.cameras[0].size
    videos = []
    for c in range(len(rig)):  # every frame a flat grey whose level says its number
        p = tmp_path / f"c{c}.mp4"
        with FrameWriter(p, W, H, FPS) as w:
            for m in range(FRAMES):
                f = YuvFrame(W, H)
                f.y[:], f.u[:], f.v[:] = 40 + 15 * m, 128, 128
                w.write(f)
        videos.append(p)
    offsets = [0.0, 2.2] + [0.0] * (len(rig) - 2)
    result = truth_result(run, no_estimate={c: list(range(FRAMES)) for c in range(len(rig))}, offsets=offsets)
    done = render_videos(result, videos, tmp_path / "out", combined=True)
    assert done.offsets_frames[:2] == [0, 2]
    info = probe(done.combined)
    grid = decode_ffmpeg(done.combined, info.width, info.height)
    assert len(grid) == FRAMES
    cols = 3  # 7 tiles
    tw, th = info.width // cols, info.height // 3

    def tile_level(n: int, k: int) -> float:
        r, c = divmod(k, cols)
        return float(np.median(grid[n, r * th + th // 4: r * th + 3 * th // 4, c * tw + tw // 4: c * tw + 3 * tw // 4]))

    for n in range(FRAMES):
        assert tile_level(n, 0) == pytest.approx(40 + 15 * n, abs=3)
        if n >= 2:
            assert tile_level(n, 1) == pytest.approx(40 + 15 * (n - 2), abs=3)
        else:
            assert tile_level(n, 1) < 25  # no such frame of camera 2: a blank tile

    # --frames 3:7 starts at frame 3 exactly (ffmpeg's accurate seek) and writes 4 frames
    part = render_videos(result, videos, tmp_path / "part", frames="3:7")
    levels = decode_ffmpeg(part.cameras[0], W, H)
    assert [int(np.median(f)) for f in levels] == pytest.approx([40 + 15 * m for m in range(3, 7)], abs=3)


def test_simulated_footage_shows_the_animal_where_the_cameras_project_it(filmed):
    run, videos, _ = filmed
    for c in (0, 2):
        frames = decode_cv2(videos[c])
        assert len(frames) == FRAMES
        n = FRAMES // 2
        p = run.projections[c, n, run.markers.index("spine")]
        x, y = int(round(p[0])), int(round(p[1]))
        b, g, r = frames[n][y, x].astype(int)
        assert r > g > b and r - b > 60, (c, frames[n][y, x])  # fur, not the blue sky or the grey-brown ground


# ------------------------------------------------------------------------------------------- CLI


def test_cli_writes_videos_and_names_bad_input_in_one_line(filmed, tmp_path):
    run, videos, _ = filmed
    h5 = tmp_path / "r.h5"
    write_h5(h5, truth_result(run))
    proc = run_cli("video", h5, "--videos", *videos, "--out", tmp_path / "v", "--frames", "2:7")
    assert proc.returncode == 0, proc.stderr
    assert "5 frames x 6 cameras" in proc.stdout
    assert probe(tmp_path / "v" / "cam1_labeled.mp4").frames == 5
    assert probe(tmp_path / "v" / "3d.mp4").frames == 5
    assert not (tmp_path / "v" / "combined.mp4").exists()

    def one_line(proc, *fragments):
        lines = proc.stderr.strip().splitlines()
        assert proc.returncode == 2 and len(lines) == 1 and "Traceback" not in proc.stderr, proc.stderr
        for f in fragments:
            assert f in lines[0], lines[0]

    one_line(run_cli("video", h5, "--videos", *videos[:5], "--out", tmp_path / "w"), "5 video(s)", "6 cameras")
    one_line(run_cli("video", h5, "--videos", *videos[:5], tmp_path / "nope.mp4", "--out", tmp_path / "w"),
             "nope.mp4: no such video file")
    short = tmp_path / "short.mp4"
    with FrameWriter(short, *run.calibration.cameras[0].size, FPS) as w:
        for _ in range(FRAMES - 3):
            w.write(np.zeros((run.calibration.cameras[0].size[1], run.calibration.cameras[0].size[0], 3), np.uint8))
    one_line(run_cli("video", h5, "--videos", short, *videos[1:], "--out", tmp_path / "w"),
             f"short.mp4: has {FRAMES - 3} frames but the result has {FRAMES}")
    one_line(run_cli("video", h5, "--videos", *videos, "--out", tmp_path / "w", "--frames", "8:3"), "--frames 8:3")


def test_simulate_videos_from_the_command_line(tmp_path):
    rig = tmp_path / "small.json"
    write_acinoset_json(rig, scaled_rig(load_calibration(default_rig_path()), SCALE))
    proc = run_cli("simulate", "--rig", rig, "--frames", "4", "--fps", "60", "--videos", "--out", tmp_path / "s")
    assert proc.returncode == 0, proc.stderr
    for c in range(6):
        info = probe(tmp_path / "s" / f"cam{c + 1}.mp4")
        assert (info.width, info.height, info.frames, info.fps) == (338, 190, 4, 60.0)
        assert re.search(r"h264.*yuv420p", stream_line(tmp_path / "s" / f"cam{c + 1}.mp4"))


def test_missing_extra_is_named_in_one_line(monkeypatch):
    from graph.errors import InputError

    monkeypatch.setitem(sys.modules, "imageio_ffmpeg", None)
    with pytest.raises(InputError, match=r"^videos need the 'video' extra: pip install 'acinoset\[video\]'$"):
        ffmpeg_exe()


def test_plot_frame_picker_draws_one_cameras_frame(filmed, tmp_path):
    run, videos, _ = filmed
    h5 = tmp_path / "r.h5"
    write_h5(h5, truth_result(run))
    proc = run_cli("plot", h5, "--out", tmp_path / "p", "--frame", "6", "--camera", "3", "--video", videos[2])
    assert proc.returncode == 0, proc.stderr
    png = tmp_path / "p" / "cam3_frame6.png"
    assert proc.stdout.strip().endswith("cam3_frame6.png")
    img = cv2.imread(str(png))
    assert img.shape[:2] == (190, 338)
    uv = run.projections[2, 6]
    a, b = max(run.bones, key=lambda ab: np.linalg.norm(uv[run.markers.index(ab[0])] - uv[run.markers.index(ab[1])]))
    mid = (uv[run.markers.index(a)] + uv[run.markers.index(b)]) / 2
    x, y = int(round(mid[0])), int(round(mid[1]))
    assert np.abs(img[y, x].astype(int) - np.array(bone_color(a, b))).max() < 60, (a, b, img[y, x])
    # the same frame of the footage, without the drawing, differs only near the animal
    plain = decode_cv2(videos[2])[6]
    assert np.abs(img.astype(int) - plain.astype(int)).max(axis=2)[:40, 200:].max() < 40

    bad = run_cli("plot", h5, "--out", tmp_path / "p", "--frame", "99", "--camera", "cam3", "--video", videos[2])
    assert bad.returncode == 2 and len(bad.stderr.strip().splitlines()) == 1 and "--frame 99" in bad.stderr



def test_several_individuals_each_in_its_own_colour(tmp_path):
    """Two animals solved together, their H5s given to `acinoset video`: each one's bones in its own
    colour where its reprojections are, in every camera; the 3D view holds both."""
    from group_files import write_dlc_multi

    from graph.io.calibration import write_anipose_toml
    from graph.io.results import read_results
    from graph.simulate import ring_rig
    from graph.simulate_group import simulate_group
    from graph.video.draw import marker_colors

    W, H, frames = 640, 360, 24
    rig = ring_rig(4, focal_px=470.0, size=(W, H))
    run = simulate_group(rig, animals=2, frames=frames, seed=21, swap_rate=0.0, missing_instances=0.0)
    write_anipose_toml(tmp_path / "calibration.toml", rig)
    cams = [write_dlc_multi(tmp_path / f"cam{c + 1}.csv", t, ["dam", "cub"]) for c, t in enumerate(run.tracks)]
    cli = [sys.executable, "-m", "graph.app.cli"]
    solved = subprocess.run([*cli, "solve", *map(str, cams), "--calibration", str(tmp_path / "calibration.toml"),
                             "--fps", "60", "--skeleton", "points", "--method", "tri",
                             "--bones", "nose-neck,neck-spine,spine-hip,hip-tail_base",
                             "--out", str(tmp_path / "run.csv"), "--h5", str(tmp_path / "run.h5")],
                            capture_output=True, text=True, timeout=300)
    assert solved.returncode == 0, solved.stderr
    videos = []
    for c in range(len(rig)):  # flat grey footage
        p = tmp_path / f"c{c}.mp4"
        with FrameWriter(p, W, H, 60.0) as w:
            for _ in range(frames):
                f = YuvFrame(W, H)
                f.y[:], f.u[:], f.v[:] = 90, 128, 128
                w.write(f)
        videos.append(p)
    done = subprocess.run([*cli, "video", str(tmp_path / "run.h5"), "--videos", *map(str, videos), "--out",
                           str(tmp_path / "out")],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    group = read_results(tmp_path / "run.h5")  # the individuals axis: cub, dam
    assert [name for name, _ in group] == ["cub", "dam"]
    tints = marker_colors(2)  # in the file's order
    raw = subprocess.run([ffmpeg_exe(), "-v", "error", "-i", str(tmp_path / "out" / "c0_labeled.mp4"), "-f",
                          "rawvideo", "-pix_fmt", "bgr24", "-"], capture_output=True, check=True).stdout
    bgr = np.frombuffer(raw, np.uint8).reshape(-1, H, W, 3)
    assert len(bgr) == frames
    n = frames // 2
    for k, (name, res) in enumerate(group):
        uv = res.reprojections[0, n]  # (M, 2) camera 1's frame n
        i, j = res.markers.index("spine"), res.markers.index("hip")
        mid = 0.5 * (uv[i] + uv[j])
        x, y = int(round(mid[0])), int(round(mid[1]))
        patch = bgr[n, y - 1:y + 2, x - 1:x + 2].reshape(-1, 3).astype(int)
        close = np.abs(patch - np.array(tints[k])).max(axis=1) < 70
        assert close.any(), (name, patch.tolist(), tints[k])
    assert (tmp_path / "out" / "3d.mp4").stat().st_size > 0
