"""OpenPose JSON folders (one file a frame, one folder a camera, as OpenPose's --write_json and
Pose2Sim lay them out): read as the same detections a DeepLabCut file holds, several people a frame,
the model's names, and one-line refusals."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from graph.errors import InputError, TooLargeInput
from graph.io.calibration import default_rig_path, load_calibration, write_anipose_toml
from graph.io.keypoints import ReadLimits, read_keypoints, write_dlc_csv
from graph.io.openpose import MODELS
from graph.simulate import simulate_run


def write_folder(folder: Path, xy: np.ndarray, likelihood: np.ndarray, extra: dict[int, list] | None = None,
                 start: int = 0) -> Path:
    """OpenPose's files for one camera: ``xy`` (N, K, 2), missing keypoints as x = y = c = 0, and
    ``extra`` people (frame -> list of flat keypoint lists) beside the first."""
    folder.mkdir(parents=True)
    for t in range(xy.shape[0]):
        found = np.isfinite(xy[t]).all(axis=-1) & (likelihood[t] > 0)
        flat = np.where(found[:, None], np.column_stack([np.nan_to_num(xy[t]), likelihood[t]]), 0.0).ravel()
        people = [{"person_id": [-1], "pose_keypoints_2d": flat.tolist(), "face_keypoints_2d": []}]
        people += [{"person_id": [-1], "pose_keypoints_2d": p} for p in (extra or {}).get(t, [])]
        (folder / f"cam_{start + t:012d}_keypoints.json").write_text(json.dumps({"version": 1.3, "people": people}))
    return folder


@pytest.fixture(scope="module")
def run():
    return simulate_run(load_calibration(default_rig_path()), frames=30, seed=3)


def test_a_folder_reads_as_the_detections_it_holds(run, tmp_path):
    kp = run.keypoints[0]
    folder = write_folder(tmp_path / "cam1_json", kp.xy, kp.likelihood, start=100)
    got = read_keypoints(folder)
    assert got.bodyparts == [f"kp{i}" for i in range(len(kp.bodyparts))] and got.frames == 30
    seen = np.isfinite(kp.xy).all(axis=-1) & (kp.likelihood > 0)
    np.testing.assert_allclose(got.xy[seen], kp.xy[seen])
    np.testing.assert_allclose(got.likelihood[seen], kp.likelihood[seen])
    assert np.isnan(got.xy[~seen]).all() and (got.likelihood[~seen] == 0).all()


def test_several_people_take_the_most_confident_and_say_so(run, tmp_path):
    kp = run.keypoints[0]
    K = len(kp.bodyparts)
    ghost = np.column_stack([np.full(K, 5.0), np.full(K, 5.0), np.full(K, 0.2)]).ravel().tolist()
    folder = write_folder(tmp_path / "c", kp.xy, kp.likelihood, extra={3: [ghost], 7: [ghost, ghost]})
    with pytest.warns(UserWarning, match=r"c: 2 of 30 frames hold several people; each frame's most confident"):
        got = read_keypoints(folder)
    seen = np.isfinite(kp.xy[3]).all(axis=-1) & (kp.likelihood[3] > 0)
    np.testing.assert_allclose(got.xy[3][seen], kp.xy[3][seen])


def test_the_model_names_the_keypoints(tmp_path):
    xy = np.random.default_rng(0).uniform(0, 100, (4, 25, 2))
    folder = write_folder(tmp_path / "p", xy, np.full((4, 25), 0.7))
    assert read_keypoints(folder, openpose_model="BODY_25B").bodyparts == list(MODELS["BODY_25B"])
    assert read_keypoints(folder, openpose_model="BODY_25").bodyparts[:2] == ["Nose", "Neck"]
    with pytest.raises(InputError, match=r"^p: 25 keypoints a person, but OpenPose's COCO has 18$"):
        read_keypoints(folder, openpose_model="COCO")


def test_bad_folders_are_refused_in_one_line(tmp_path):
    xy = np.ones((3, 4, 2))
    folder = write_folder(tmp_path / "ok", xy, np.ones((3, 4)))
    with pytest.raises(TooLargeInput, match=r"^ok: more than 2 frames; at most 2 frames per file$"):
        read_keypoints(folder, limits=ReadLimits(max_frames=2))
    (folder / "cam_000000000009_keypoints.json").write_text("{not json")
    with pytest.raises(InputError, match=r"^ok: cam_000000000009_keypoints.json: not an OpenPose JSON file"):
        read_keypoints(folder)
    (folder / "cam_000000000009_keypoints.json").write_text(json.dumps({"people": [{"pose_keypoints_2d": [1, 2]}]}))
    with pytest.raises(InputError, match=r"pose_keypoints_2d is not a list of x, y, confidence numbers$"):
        read_keypoints(folder)
    (folder / "cam_000000000009_keypoints.json").write_text(json.dumps({"people": [{"pose_keypoints_2d": [1] * 9}]}))
    with pytest.raises(InputError, match=r"^ok: people with different numbers of keypoints \(3, 4\)$"):
        read_keypoints(folder)
    (folder / "cam_000000000009_keypoints.json").write_text(json.dumps({"people": [{"pose_keypoints_2d": [1] * 12}]}))
    with pytest.raises(TooLargeInput, match=r"^ok: 1000003 frames; at most 1000 frames per file$"):
        (folder / "cam_000001000002_keypoints.json").write_text(json.dumps({"people": []}))
        read_keypoints(folder, limits=ReadLimits(max_frames=1000))


def test_solve_takes_openpose_folders_and_gives_what_the_csvs_give(run, tmp_path):
    """The whole command: six OpenPose folders give the same 3D as the same detections in DeepLabCut CSVs."""
    cal = tmp_path / "calibration.toml"
    write_anipose_toml(cal, run.calibration)
    folders, csvs = [], []
    for c, kp in enumerate(run.keypoints):
        folders.append(write_folder(tmp_path / f"cam{c}_json", kp.xy, kp.likelihood))
        named = type(kp)(bodyparts=[f"kp{i}" for i in range(len(kp.bodyparts))], xy=kp.xy, likelihood=kp.likelihood)
        csvs.append(tmp_path / f"cam{c}.csv")
        write_dlc_csv(csvs[-1], named)
    outs = []
    for name, inputs in (("json", folders), ("csv", csvs)):
        out = tmp_path / f"{name}.csv"
        p = subprocess.run([sys.executable, "-m", "service", "solve", *map(str, inputs), "--calibration", str(cal),
                            "--skeleton", "points", "--fps", str(run.fps), "--method", "tri", "--out", str(out)],
                           capture_output=True, text=True, timeout=600)
        assert p.returncode == 0, p.stderr
        outs.append(np.genfromtxt(out, delimiter=",", skip_header=1))
    np.testing.assert_allclose(outs[0], outs[1], rtol=1e-9, atol=1e-9)
