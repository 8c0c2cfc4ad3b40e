"""SLEAP analysis HDF5 files: the real export of SLEAP's minimal multi-camera session, the other axis
orders SLEAP and sleap-io write, several tracks, and one-line refusals for bad files."""

from __future__ import annotations

import json
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

SESSION = SLEAP_MINIMAL
CAMERAS = ("back", "mid", "side", "top")
NODES = ["Nose", "Ear_R", "Ear_L", "TTI", "TailTip", "Head", "Trunk", "Tail_0", "Tail_1", "Tail_2",
         "Shoulder_left", "Shoulder_right", "Haunch_left", "Haunch_right", "Neck"]
pytestmark = needs(SESSION)


def analysis(camera: str) -> Path:
    return SESSION / camera / f"minimal_{camera}_proofread.analysis.h5"


def _raw(camera: str) -> tuple[np.ndarray, np.ndarray]:
    """tracks (T, 2, M, N) and point_scores (T, M, N) as the file stores them (SLEAP's default order)."""
    with h5py.File(analysis(camera), "r") as f:
        return f["tracks"][()], f["point_scores"][()]


def _write(path: Path, tracks: np.ndarray, scores: np.ndarray, *, names=NODES, track_names=(b"track_0",),
           dims: tuple[str, ...] | None = None, transpose: bool | None = None, attrs: dict | None = None) -> Path:
    with h5py.File(path, "w") as f:
        t = f.create_dataset("tracks", data=tracks)
        s = f.create_dataset("point_scores", data=scores)
        if dims is not None:
            t.attrs["dims"] = json.dumps(dims)
            s.attrs["dims"] = json.dumps([d for d in dims if d != "xy"])
        if transpose is not None:
            f.attrs["transpose"] = transpose
        f["node_names"] = np.array([n.encode() if isinstance(n, str) else n for n in names])
        f["track_names"] = np.array(list(track_names), dtype="S16")
        f["track_occupancy"] = np.ones((tracks.shape[-1] if dims is None else 1, 1), dtype=np.uint8)
        for k, v in (attrs or {}).items():
            f.attrs[k] = v
    return path


def test_the_sessions_analysis_files_read_as_keypoints():
    for camera in CAMERAS:
        kp = read_keypoints(analysis(camera))
        tracks, scores = _raw(camera)
        assert kp.bodyparts == NODES and kp.frames == 120 and kp.xy.shape == (120, 15, 2)
        # point m of frame n is tracks[0, :, m, n]
        np.testing.assert_array_equal(kp.xy, tracks[0].transpose(2, 1, 0))
        seen = np.isfinite(kp.xy).all(-1)
        np.testing.assert_allclose(kp.likelihood[seen], np.clip(scores[0].T[seen], 0, 1))
        assert (kp.likelihood[~seen] == 0).all() and kp.likelihood.max() <= 1.0
        assert kp.scorer == "sleap" and kp.fps is None  # SLEAP's export records no frame rate
    assert np.isnan(read_keypoints(analysis("back")).xy).any(axis=-1).mean() == pytest.approx(0.2178, abs=1e-3)


def test_other_axis_orders_read_the_same(tmp_path):
    tracks, scores = _raw("side")
    want = read_keypoints(analysis("side"))
    standard = _write(tmp_path / "standard.h5", tracks.transpose(3, 0, 2, 1), scores.transpose(2, 0, 1),
                      dims=("frame", "track", "node", "xy"))  # sleap-io's preset "standard"
    plain = _write(tmp_path / "plain.h5", tracks.transpose(3, 2, 1, 0), scores.transpose(2, 1, 0),
                   transpose=False)  # SLEAP's export with transpose=False: (frame, node, xy, track)
    for path in (standard, plain):
        got = read_keypoints(path)
        np.testing.assert_array_equal(got.xy, want.xy)
        np.testing.assert_array_equal(got.likelihood, want.likelihood)


def test_a_track_is_chosen_by_name_and_the_first_by_default(tmp_path):
    a, sa = _raw("mid")
    b, sb = _raw("top")
    path = _write(tmp_path / "two.h5", np.concatenate([a, b]), np.concatenate([sa, sb]),
                  track_names=(b"mouse_a", b"mouse_b"))
    with pytest.warns(UserWarning, match=r"two\.h5: 2 tracks \(mouse_a, mouse_b\); using 'mouse_a'"):
        first = read_keypoints(path)
    np.testing.assert_array_equal(first.xy, read_keypoints(analysis("mid")).xy)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        second = read_keypoints(path, individual="mouse_b")
    np.testing.assert_array_equal(second.xy, read_keypoints(analysis("top")).xy)
    with pytest.raises(InputError, match=r"^two\.h5: no track 'mouse_c' \(the file has mouse_a, mouse_b\)$"):
        read_keypoints(path, individual="mouse_c")


def test_hand_placed_points_without_a_score_are_trusted(tmp_path):
    tracks, scores = _raw("top")
    scores = scores.copy()
    scores[0, 3, :10] = np.nan  # a user instance's points carry no score
    kp = read_keypoints(_write(tmp_path / "user.h5", tracks, scores))
    assert (kp.likelihood[:10, 3] == 1.0).all()


def test_a_recorded_frame_rate_is_kept(tmp_path):
    tracks, scores = _raw("top")
    assert read_keypoints(_write(tmp_path / "a.h5", tracks, scores, attrs={"fps": 30.0})).fps == 30.0
    meta = json.dumps({"fps": 29.97, "grayscale": False})
    recorded = _write(tmp_path / "b.h5", tracks, scores, attrs={"video_backend_metadata": meta})
    assert read_keypoints(recorded).fps == 29.97
    assert read_keypoints(_write(tmp_path / "c.h5", tracks, scores, attrs={"fps": -1.0})).fps is None


def _bad(tmp_path: Path) -> dict[str, str]:
    tracks, scores = _raw("top")
    out = {}
    _write(tmp_path / "three_d.h5", tracks[0], scores)
    out["three_d.h5"] = "expected 4 axes"
    _write(tmp_path / "xyz.h5", np.concatenate([tracks, tracks[:, :1]], axis=1), scores)
    out["xyz.h5"] = "3 coordinates per point"
    _write(tmp_path / "names.h5", tracks, scores, names=NODES[:-1])
    out["names.h5"] = "14 node_names for 15 nodes"
    _write(tmp_path / "twice.h5", tracks, scores, names=NODES[:-1] + ["Nose"])
    out["twice.h5"] = "two nodes have the same name"
    _write(tmp_path / "scores.h5", tracks, scores[:, :, :-1])
    out["scores.h5"] = "point_scores have shape (1, 15, 119)"
    _write(tmp_path / "dims.h5", tracks, scores, dims=("track", "xy", "node", "time"))
    out["dims.h5"] = "dims attribute is not an order"
    _write(tmp_path / "words.h5", tracks.astype("S8"), scores)
    out["words.h5"] = "expected 4 axes of numbers"
    inf = tracks.copy()
    inf[0, 0, 0, 0] = np.inf
    _write(tmp_path / "inf.h5", inf, scores)
    out["inf.h5"] = "infinite pixel coordinates"
    _write(tmp_path / "empty.h5", tracks[:0], scores[:0], track_names=())
    out["empty.h5"] = "no tracks"
    with h5py.File(tmp_path / "wide_names.h5", "w") as f:  # names of a gigabyte each, declared, not written
        f.create_dataset("tracks", data=tracks)
        f.create_dataset("node_names", shape=(15,), dtype="S1000000000")
    out["wide_names.h5"] = "bytes each"
    return out


def test_bad_files_are_refused_in_one_line_naming_the_file(tmp_path):
    for name, words in _bad(tmp_path).items():
        with pytest.raises(InputError) as e:
            read_keypoints(tmp_path / name)
        assert str(e.value).startswith(f"{name}: ") and words in str(e.value) and "\n" not in str(e.value), (name, e)


def test_declared_sizes_are_checked_before_reading(tmp_path):
    with h5py.File(tmp_path / "long.h5", "w") as f:  # 15 nodes x 10 million frames declared, 8 KB on disk
        f.create_dataset("tracks", shape=(1, 2, 15, 10_000_000), dtype="f8", chunks=(1, 2, 15, 100_000),
                         compression="gzip")
        f["node_names"] = np.array([n.encode() for n in NODES])
    with pytest.raises(TooLargeInput, match=r"^long\.h5: 10000000 frames; at most 50000"):
        read_keypoints(tmp_path / "long.h5", limits=ReadLimits(max_frames=50_000, max_bodyparts=100))
    with pytest.raises(TooLargeInput, match="bodyparts"):
        read_keypoints(analysis("top"), limits=ReadLimits(max_bodyparts=10))


# --------------------------------------------------------------------------- the command line

def _cli(*args) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "graph.app.cli", *map(str, args)], capture_output=True, text=True,
                          timeout=600)


def test_solve_and_evaluate_take_the_files_and_need_a_frame_rate(tmp_path):
    files = [analysis(c) for c in CAMERAS]
    common = ["--calibration", SESSION / "calibration.toml", "--method", "tri", "--skeleton", "points",
              "--likelihood-threshold", "0"]
    missing = _cli("solve", *files, *common, "--out", tmp_path / "a.csv")
    assert missing.returncode == 2 and "--fps is required: the keypoint files record no frame rate" in missing.stderr
    assert not (tmp_path / "a.csv").exists()
    solved = _cli("solve", *files, *common, "--fps", "30", "--out", tmp_path / "a.csv")
    assert solved.returncode == 0, solved.stderr
    assert "tri: 120 frames, 4 cameras, 15 markers, 30 fps (--fps)" in solved.stdout
    assert "camera side disagrees with the others" in solved.stderr
    # a file recording its frame rate needs no --fps, and the command says where the rate came from
    recorded = []
    for c in CAMERAS:
        tracks, scores = _raw(c)
        recorded.append(_write(tmp_path / f"{c}.analysis.h5", tracks, scores, attrs={"fps": 30.0}))
    own = _cli("solve", *recorded, *common, "--out", tmp_path / "b.csv")
    assert own.returncode == 0 and "30 fps (recorded in the keypoint files)" in own.stdout, own.stderr
    loco = _cli("evaluate", "loco", *files, *common, "--fps", "30", "--confidence", "0")
    assert loco.returncode == 0, loco.stderr
    assert "leave one camera out, tri at 30 fps (--fps)" in loco.stdout
    side = next(line for line in loco.stdout.splitlines() if line.strip().startswith("side"))
    assert float(side.split()[1]) > 80  # side's held-out median: its calibration entry is top's
    assert _cli("evaluate", "loco", *files, *common).returncode == 2


def test_mutated_analysis_files_are_read_or_refused_in_one_line_within_the_memory_cap(tmp_path):
    from test_keypoint_memory import _read_capped

    rng = np.random.default_rng(11)
    source = analysis("top").read_bytes()
    paths = []
    for k in range(60):
        data = bytearray(source)
        if k % 3 == 0:  # flip bytes
            for at in rng.integers(0, len(data), rng.integers(1, 40)):
                data[at] = rng.integers(256)
        elif k % 3 == 1:  # delete a run
            a = int(rng.integers(0, len(data)))
            del data[a: a + int(rng.integers(1, 400))]
        else:  # cut short
            del data[int(rng.integers(1, len(data))):]
        paths.append(tmp_path / f"mutant{k:02d}.analysis.h5")
        paths[-1].write_bytes(bytes(data))
    got = _read_capped(paths)
    assert not {k: v for k, v in got.items() if v[0] == "crashed"}
    assert all("\n" not in v[2] and v[2].startswith(k) for k, v in got.items() if v[0] == "refused")
    kinds = [v[0] for v in got.values()]
    assert kinds.count("refused") > 30, kinds  # HDF5's structure seldom survives a mutation: most are refused
