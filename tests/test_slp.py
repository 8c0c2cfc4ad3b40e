"""SLEAP's labels files (``.slp``) through sleap-io: the real session's four files read exactly as their
analysis exports, a two-animal file written by sleap-io, hand-placed points, and sizes refused before
sleap-io reads them."""

from __future__ import annotations

import shutil
import subprocess
import sys
import warnings
from pathlib import Path

import h5py
import numpy as np
import pytest
from shared_data import SLEAP_MINIMAL, needs

from graph.errors import InputError, TooLargeInput
from graph.io.keypoints import ReadLimits, read_keypoints

sio = pytest.importorskip("sleap_io")

SESSION = SLEAP_MINIMAL
CAMERAS = ("back", "mid", "side", "top")
pytestmark = needs(SESSION)


def slp(camera: str) -> Path:
    return SESSION / camera / f"minimal_{camera}_proofread.slp"


@pytest.mark.parametrize("camera", CAMERAS)
def test_the_sessions_slp_files_read_as_their_analysis_exports(camera):
    a = read_keypoints(slp(camera))
    b = read_keypoints(SESSION / camera / f"minimal_{camera}_proofread.analysis.h5")
    assert a.bodyparts == b.bodyparts and len(a.bodyparts) == 15 and a.frames == 120
    assert np.array_equal(np.isnan(a.xy), np.isnan(b.xy)) and np.nanmax(np.abs(a.xy - b.xy)) == 0.0
    assert np.array_equal(a.likelihood, b.likelihood)
    assert a.scorer == "sleap" and a.fps is None


def _two_animals(path: Path, frames: int = 6) -> tuple[Path, np.ndarray]:
    """A .slp as sleap-io writes it: two tracked mice, predicted points with scores, and in frame 2 a
    user instance (hand-placed: no score) corrected from mouse b's prediction."""
    skeleton = sio.Skeleton(["nose", "tail"])
    tracks = [sio.Track("mouse a"), sio.Track("mouse b")]
    video = sio.Video(filename="not-opened.mp4", open_backend=False)
    rng = np.random.default_rng(0)
    pts = rng.uniform(0, 500, (frames, 2, 2, 2))
    lfs = []
    for t in range(frames):
        inst = [sio.PredictedInstance.from_numpy(points_data=pts[t, i], point_scores=np.array([0.9, 1.4]),
                                                 score=1.0, skeleton=skeleton, track=tracks[i]) for i in range(2)]
        if t == 2:
            user = sio.Instance.from_numpy(pts[t, 1] + 3.0, skeleton=skeleton, track=tracks[1])
            user.from_predicted = inst[1]
            inst.append(user)
        lfs.append(sio.LabeledFrame(video=video, frame_idx=t, instances=inst))
    sio.save_slp(sio.Labels(labeled_frames=lfs, videos=[video], skeletons=[skeleton], tracks=tracks), str(path))
    return path, pts


def test_a_track_is_chosen_by_name_and_hand_placed_points_are_trusted(tmp_path):
    path, pts = _two_animals(tmp_path / "two.slp")
    with pytest.warns(UserWarning, match=r"two\.slp: 2 tracks \(mouse a, mouse b\); using 'mouse a'"):
        a = read_keypoints(path)
    np.testing.assert_allclose(a.xy, pts[:, 0])
    np.testing.assert_allclose(a.likelihood, np.tile([0.9, 1.0], (6, 1)))  # 1.4 clipped to 1
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        b = read_keypoints(path, individual="mouse b")
    np.testing.assert_allclose(b.xy[2], pts[2, 1] + 3.0)  # the user's correction, not the prediction
    assert (b.likelihood[2] == 1.0).all()
    np.testing.assert_allclose(b.xy[[0, 1, 3, 4, 5]], pts[[0, 1, 3, 4, 5], 1])
    with pytest.raises(InputError, match=r"^two\.slp: no track 'mouse c' \(the file has mouse a, mouse b\)$"):
        read_keypoints(path, individual="mouse c")


def test_sizes_are_checked_before_sleap_io_reads(tmp_path):
    """A frame index of 10^12 would make a dense array of 10^12 rows: refused from the table alone."""
    path = tmp_path / "far.slp"
    shutil.copy(slp("back"), path)
    with h5py.File(path, "r+") as f:
        frames = f["frames"][()]
        frames["frame_idx"][-1] = 10**12
        f["frames"][...] = frames
    with pytest.raises(TooLargeInput, match=r"^far\.slp: 1000000000001 frames; at most 100000 frames per file$"):
        read_keypoints(path, limits=ReadLimits(max_frames=100_000, max_bodyparts=1000))
    with pytest.raises(TooLargeInput, match=r"^back\.slp: 120 frames; at most 100 frames per file$"):
        shutil.copy(slp("back"), tmp_path / "back.slp")
        read_keypoints(tmp_path / "back.slp", limits=ReadLimits(max_frames=100))
    with pytest.raises(TooLargeInput, match=r"bodyparts"):
        read_keypoints(slp("back"), limits=ReadLimits(max_bodyparts=10))


def test_a_damaged_slp_is_refused_in_one_line(tmp_path):
    path = tmp_path / "damaged.slp"
    shutil.copy(slp("back"), path)
    with h5py.File(path, "r+") as f:
        del f["pred_points"]
    with pytest.raises(InputError) as e:
        read_keypoints(path)
    assert str(e.value).startswith("damaged.slp: ") and "\n" not in str(e.value)


def test_solve_takes_the_slp_files(tmp_path):
    """The whole command on the session's four .slp files, as a user runs it."""
    out = tmp_path / "run.csv"
    cmd = [sys.executable, "-m", "service", "solve", *[str(slp(c)) for c in CAMERAS],
           "--calibration", str(SESSION / "calibration.toml"), "--skeleton", "points", "--fps", "30",
           "--method", "tri", "--likelihood-threshold", "0", "--out", str(out)]
    p = subprocess.run(cmd, capture_output=True, text=True, timeout=600, env={"ACINOSET_RESIDENT": "0",
                                                                              **__import__("os").environ})
    assert p.returncode == 0, p.stderr
    header = out.read_text().splitlines()[0].split(",")
    assert "Nose_x" in header and "Neck_z" in header
