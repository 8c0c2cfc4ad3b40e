"""Calibration files: the packaged AcinoSet rig, Anipose TOML as aniposelib writes and reads it,
round trips, and one-line errors for bad files."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from graph.camera import FISHEYE, PINHOLE, Calibration, Camera
from graph.errors import InputError
from graph.io.calibration import (
    default_rig_path,
    load_calibration,
    matrix_to_rodrigues,
    rodrigues_to_matrix,
    save_calibration,
    write_acinoset_json,
    write_anipose_toml,
)

RNG = np.random.default_rng(7)


def _points_in_front(calibration: Calibration, n: int = 50) -> np.ndarray:
    """World points the AcinoSet rig sees: a box around the middle of the cameras' field."""
    return np.array([0.0, 5.0, 0.5]) + RNG.uniform(-2.0, 2.0, size=(n, 3)) * [1.0, 1.0, 0.3]


def test_packaged_rig_is_the_acinoset_2019_rig():
    path = default_rig_path()
    assert path.is_file() and path.name == "acinoset_2019_rig.json"
    cal = load_calibration(path)
    raw = json.loads(path.read_text())
    assert len(cal) == 6
    for cam, c in zip(cal.cameras, raw["cameras"]):
        assert cam.model == FISHEYE and cam.size == (2704, 1520)
        np.testing.assert_array_equal(cam.K, c["k"])
        np.testing.assert_array_equal(cam.dist, np.ravel(c["d"]))
        np.testing.assert_allclose(cam.R, c["r"], atol=1e-12)
        np.testing.assert_array_equal(cam.t, np.ravel(c["t"]))
        # the values land in the right places: our projection equals OpenCV's fisheye model fed the raw file
        X = _points_in_front(cal)
        rvec = cv2.Rodrigues(np.array(c["r"]))[0]
        uv_cv, _ = cv2.fisheye.projectPoints(X.reshape(-1, 1, 3), rvec, np.array(c["t"], float),
                                             np.array(c["k"]), np.array(c["d"]))
        uv = cam.project(X)
        ok = np.isfinite(uv).all(-1)
        assert ok.sum() > 10
        np.testing.assert_allclose(uv[ok], uv_cv.reshape(-1, 2)[ok], atol=1e-6)
    assert cal.metadata["created_timestamp"] == raw["created_timestamp"]


def test_acinoset_json_round_trip(tmp_path):
    cal = load_calibration(default_rig_path())
    out = tmp_path / "scene_sba.json"
    write_acinoset_json(out, cal)
    doc = json.loads(out.read_text())
    assert doc["camera_resolution"] == [2704, 1520]
    assert np.shape(doc["cameras"][0]["d"]) == (4, 1) and np.shape(doc["cameras"][0]["t"]) == (3, 1)
    back = load_calibration(out)
    for a, b in zip(cal.cameras, back.cameras):
        for field in ("K", "dist", "R", "t"):
            np.testing.assert_array_equal(getattr(a, field), getattr(b, field))


def test_acinoset_json_refuses_pinhole_cameras(tmp_path):
    cam = Camera(K=np.diag([800.0, 800.0, 1.0]), dist=[0.1], R=np.eye(3), t=[0, 0, 1], model=PINHOLE, size=(640, 480))
    with pytest.raises(ValueError, match="fisheye"):
        write_acinoset_json(tmp_path / "x.json", Calibration([cam, cam]))


def test_rodrigues_matches_opencv():
    for _ in range(20):
        r = RNG.normal(size=3) * RNG.uniform(0, 3)
        np.testing.assert_allclose(rodrigues_to_matrix(r), cv2.Rodrigues(r)[0], atol=1e-12)
        np.testing.assert_allclose(rodrigues_to_matrix(matrix_to_rodrigues(rodrigues_to_matrix(r))),
                                   rodrigues_to_matrix(r), atol=1e-12)
    np.testing.assert_array_equal(rodrigues_to_matrix(np.zeros(3)), np.eye(3))


def _aniposelib_group():
    cameras = pytest.importorskip("aniposelib.cameras")
    rig = load_calibration(default_rig_path())
    group = []
    for i, c in enumerate(rig.cameras[:3]):
        group.append(cameras.FisheyeCamera(matrix=c.K, dist=c.dist, size=c.size, rvec=matrix_to_rodrigues(c.R),
                                           tvec=c.t, name=f"fish{i}"))
    # pinhole cameras with full and with short distortion vectors (aniposelib accepts 1..5)
    K = np.array([[1100.0, 0.0, 640.0], [0.0, 1105.0, 500.0], [0.0, 0.0, 1.0]])
    group.append(cameras.Camera(matrix=K, dist=[-0.2, 0.05, 0.001, -0.002, 0.01], size=(1280, 1024),
                                rvec=[0.1, -0.3, 0.05], tvec=[0.5, 0.2, 6.0], name="pin-full"))
    group.append(cameras.Camera(matrix=K, dist=[-0.15], size=(1280, 1024),
                                rvec=[-0.2, 0.25, 0.0], tvec=[-0.5, 0.1, 5.5], name="pin-k1"))
    cg = cameras.CameraGroup(group, metadata={"adjusted": False, "error": 0.42})
    return cameras, cg


def _padded(cg):
    """The same group with every distortion vector padded to 5: OpenCV's projectPoints (which
    aniposelib calls) takes 4, 5, 8, 12 or 14 coefficients, not 1."""
    cg = cg.copy()
    for cam in cg.cameras:
        d = cam.get_distortions()
        if d.size < 4:
            cam.set_distortions(np.pad(d, (0, 5 - d.size)))
    return cg


def test_reads_anipose_toml_written_by_aniposelib(tmp_path):
    cameras, cg = _aniposelib_group()
    path = tmp_path / "calibration.toml"
    cg.dump(str(path))
    cal = load_calibration(path)
    assert cal.names == ["fish0", "fish1", "fish2", "pin-full", "pin-k1"]
    assert [c.model for c in cal.cameras] == [FISHEYE] * 3 + [PINHOLE] * 2
    np.testing.assert_array_equal(cal.cameras[4].dist, [-0.15, 0, 0, 0, 0])
    assert cal.metadata == {"adjusted": False, "error": 0.42}
    assert cal.cameras[3].size == (1280, 1024)
    # same pixels as aniposelib's own projection
    X = _points_in_front(cal, 40)
    X[:, 1] = RNG.uniform(-1, 1, 40)  # in front of the pinhole cameras too
    X[:, 2] = RNG.uniform(-1, 1, 40)
    X_fish = _points_in_front(cal, 40)
    ours = cal.project(X)
    theirs = _padded(cg).project(X)
    for c in (3, 4):
        np.testing.assert_allclose(ours[c], theirs[c], atol=1e-6)
    ours_f, theirs_f = cal.project(X_fish), _padded(cg).project(X_fish)
    for c in (0, 1, 2):
        ok = np.isfinite(ours_f[c]).all(-1)
        np.testing.assert_allclose(ours_f[c][ok], theirs_f[c][ok], atol=1e-6)


def test_written_anipose_toml_loads_in_aniposelib(tmp_path):
    cameras, cg = _aniposelib_group()
    src = tmp_path / "src.toml"
    cg.dump(str(src))
    cal = load_calibration(src)
    out = tmp_path / "calibration.toml"
    write_anipose_toml(out, cal)
    back = cameras.CameraGroup.load(str(out))
    assert back.get_names() == cal.names
    assert [type(c).__name__ for c in back.cameras] == ["FisheyeCamera"] * 3 + ["Camera"] * 2
    assert back.metadata == {"adjusted": False, "error": 0.42}
    for a, b in zip(cg.cameras, back.cameras):
        np.testing.assert_array_equal(a.get_camera_matrix(), b.get_camera_matrix())
        np.testing.assert_allclose(a.get_rotation(), b.get_rotation(), atol=1e-12)
        np.testing.assert_array_equal(a.get_translation(), b.get_translation())
        assert list(a.get_size()) == list(b.get_size())
    X = np.column_stack([RNG.uniform(-1, 1, 30), RNG.uniform(-1, 1, 30), RNG.uniform(-1, 1, 30)])
    np.testing.assert_allclose(back.project(X)[3:], _padded(cg).project(X)[3:], atol=1e-9)
    # and our own reader gets back exactly what it wrote
    again = load_calibration(out)
    for a, b in zip(cal.cameras, again.cameras):
        np.testing.assert_array_equal(a.K, b.K)
        np.testing.assert_array_equal(a.dist, b.dist)
        np.testing.assert_allclose(a.R, b.R, atol=1e-14)
        assert a.model == b.model and a.size == b.size and a.name == b.name


def test_rig_written_as_toml_projects_identically(tmp_path):
    rig = load_calibration(default_rig_path())
    save_calibration(tmp_path / "calibration.toml", rig)
    save_calibration(tmp_path / "scene.json", rig)
    X = _points_in_front(rig)
    ref = rig.project(X)
    for name in ("calibration.toml", "scene.json"):
        np.testing.assert_allclose(load_calibration(tmp_path / name).project(X), ref, atol=1e-9, equal_nan=True)


def test_cameras_follow_numeric_cam_order(tmp_path):
    rig = load_calibration(default_rig_path())
    cams = [Camera(K=c.K, dist=c.dist, R=c.R, t=c.t, size=c.size, name=f"c{i}")
            for i, c in enumerate(rig.cameras * 2)]  # 12 cameras: cam_10, cam_11 sort after cam_9
    path = tmp_path / "calibration.toml"
    write_anipose_toml(path, Calibration(cams))
    assert load_calibration(path).names == [f"c{i}" for i in range(12)]


def test_unusual_metadata_and_names_survive(tmp_path):
    rig = load_calibration(default_rig_path())
    cams = [Camera(K=c.K, dist=c.dist, R=c.R, t=c.t, size=c.size, name=n)
            for c, n in zip(rig.cameras[:2], ['left "A"', "rechts\\Ä"])]
    meta = {"note": "line1\nline2", "weird key": [1, 2.5, True], "nested": {"a": 1}}
    path = tmp_path / "calibration.toml"
    write_anipose_toml(path, Calibration(cams, metadata=meta))
    back = load_calibration(path)
    assert back.names == ['left "A"', "rechts\\Ä"]
    assert back.metadata == meta


def _rig_json() -> dict:
    return json.loads(default_rig_path().read_text())


def _toml_text(**overrides) -> str:
    fields = {"name": '"A"', "size": "[640, 480]",
              "matrix": "[[800.0, 0.0, 320.0], [0.0, 800.0, 240.0], [0.0, 0.0, 1.0]]",
              "distortions": "[0.1, 0.0, 0.0, 0.0, 0.0]", "rotation": "[0.0, 0.0, 0.0]",
              "translation": "[0.0, 0.0, 0.0]"}
    fields.update(overrides)
    body = "\n".join(f"{k} = {v}" for k, v in fields.items() if v is not None)
    return f"[cam_0]\n{body}\n\n[cam_1]\n{body}\n\n[metadata]\n"


def _json_with(change) -> str:
    doc = _rig_json()
    change(doc)
    return json.dumps(doc)


BAD_FILES = {
    "empty.json": ("", "empty"),
    "blank.toml": ("\n  \n", "empty"),
    "nonsense.toml": ("hello world, this is no calibration\n", "not a calibration file"),
    "nonsense.json": ("{not json", "not valid JSON"),
    "list.json": ("[1, 2, 3]", "not an AcinoSet scene"),
    "nocams.json": ('{"camera_resolution": [10, 10], "cameras": []}', "non-empty"),
    "nocams.toml": ("[metadata]\nerror = 1.0\n", "no [cam_0]"),
    "binary.toml": (b"\x89PNG\r\n\x1a\n\x00\x00\xff\xfe", "binary"),
    "no_k.json": (_json_with(lambda d: d["cameras"][2].pop("k")), 'camera 3: missing "k"'),
    "k_2x3.json": (_json_with(lambda d: d["cameras"][0].update(k=[[1, 0, 1], [0, 1, 1]])), "3x3"),
    "k_negative.json": (_json_with(lambda d: d["cameras"][0]["k"][0].__setitem__(0, -5.0)),
                        "focal lengths must be positive"),
    "k_ragged.json": (_json_with(lambda d: d["cameras"][0].update(k=[[1, 0], [0, 1, 1], [0, 0, 1]])), "regular array"),
    "r_scaled.json": (_json_with(lambda d: d["cameras"][1].update(r=(np.array(d["cameras"][1]["r"]) * 1.01).tolist())),
                      "not a rotation"),
    "r_reflection.json": (_json_with(lambda d: d["cameras"][1].update(r=(-np.array(d["cameras"][1]["r"])).tolist())),
                          "not a rotation"),
    "r_random.json": (_json_with(lambda d: d["cameras"][0].update(r=[[1, 2, 3], [4, 5, 6], [7, 8, 9]])),
                      "not a rotation"),
    "t_nan.json": (_json_with(lambda d: d["cameras"][3].update(t=[[0.0], [float("nan")], [1.0]])), "NaN"),
    "t_short.json": (_json_with(lambda d: d["cameras"][3].update(t=[[0.0], [1.0]])), "expected 3 numbers"),
    "d_5.json": (_json_with(lambda d: d["cameras"][0].update(d=[[0.1]] * 5)), "4 coefficients"),
    "res_bad.json": (_json_with(lambda d: d.update(camera_resolution=[2704])), "camera_resolution"),
    "no_matrix.toml": (_toml_text(matrix=None), "missing matrix"),
    "matrix_text.toml": (_toml_text(matrix='"eye"'), "expected numbers"),
    "matrix_skew.toml": (_toml_text(matrix="[[800.0, 9.0, 320.0], [0.0, 800.0, 240.0], [0.0, 0.0, 1.0]]"), "skew"),
    "matrix_lastrow.toml": (_toml_text(matrix="[[800.0, 0.0, 320.0], [0.0, 800.0, 240.0], [0.0, 1.0, 1.0]]"),
                            "last row"),
    "rotation_2.toml": (_toml_text(rotation="[0.1, 0.2]"), "rotation: expected 3 numbers"),
    "translation_inf.toml": (_toml_text(translation="[0.0, inf, 1.0]"), "infinite"),
    "dist_8.toml": (_toml_text(distortions="[0.1, 0, 0, 0, 0, 0, 0, 0]"), "up to 5"),
    "fisheye_5.toml": (_toml_text(fisheye="true"), "fisheye needs 4"),
    "size_neg.toml": (_toml_text(size="[-640, 480]"), "width, height"),
    "broken.toml": ('[cam_0]\nname = "A\n', "not valid TOML"),
}


@pytest.mark.parametrize("name", sorted(BAD_FILES))
def test_bad_calibration_files_give_one_line_naming_the_file(tmp_path, name):
    content, expected = BAD_FILES[name]
    path = tmp_path / name
    if isinstance(content, bytes):
        path.write_bytes(content)
    else:
        path.write_text(content)
    with pytest.raises(InputError) as info:
        load_calibration(path)
    message = str(info.value)
    assert message.startswith(f"{name}: ")
    assert "\n" not in message
    assert expected in message


def test_missing_and_directory_calibration(tmp_path):
    with pytest.raises(InputError, match=r"^nope\.toml: no such file$"):
        load_calibration(tmp_path / "nope.toml")
    with pytest.raises(InputError, match="is a directory"):
        load_calibration(tmp_path)


def test_slightly_rounded_rotation_is_accepted_and_made_orthonormal(tmp_path):
    doc = _rig_json()
    for c in doc["cameras"]:
        c["r"] = np.round(np.array(c["r"]), 6).tolist()
    path = tmp_path / "rounded.json"
    path.write_text(json.dumps(doc))
    for cam in load_calibration(path).cameras:
        np.testing.assert_allclose(cam.R.T @ cam.R, np.eye(3), atol=1e-12)
        assert np.linalg.det(cam.R) == pytest.approx(1.0, abs=1e-12)


def test_dispatch_is_by_content_not_extension(tmp_path):
    path = tmp_path / "calib.txt"
    path.write_text(default_rig_path().read_text())
    assert len(load_calibration(path)) == 6
    path2 = tmp_path / "calib.json"
    path2.write_text(_toml_text())
    assert load_calibration(path2).names == ["A", "A"]


def test_written_files_are_valid_toml_for_tomllib(tmp_path):
    import tomllib

    write_anipose_toml(tmp_path / "c.toml", load_calibration(default_rig_path()))
    doc = tomllib.loads(Path(tmp_path / "c.toml").read_text())
    assert sorted(doc) == [f"cam_{i}" for i in range(6)] + ["metadata"]
    assert doc["cam_0"]["fisheye"] is True and len(doc["cam_0"]["distortions"]) == 4
