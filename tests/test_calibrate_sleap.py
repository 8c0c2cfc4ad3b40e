"""A whole rig from real ChArUco images: SLEAP's minimal session (four cameras, about 21 images each,
named ``<camera>-<time stamp>-<index>.jpg``, so frames match across cameras by their last number).
Its shipped calibration has side's entry copied from top's; the rig calibrated here from the images
must make side agree with the others on the mouse's keypoints."""

from __future__ import annotations

import numpy as np
import pytest
from shared_data import SLEAP_MINIMAL, needs

from graph.calibrate import calibrate_extrinsics, parse_board
from graph.calibrate.detect import detect_views
from graph.calibrate.views import frame_key
from graph.io.calibration import load_calibration
from graph.io.keypoints import read_keypoints
from graph.metrics import leave_one_camera_out
from graph.types import SolveOptions

SESSION = SLEAP_MINIMAL
CAMERAS = ("back", "mid", "side", "top")
BOARD = "charuco:8x11:0.024:0.01875:DICT_4X4_1000"  # the session's board.toml, in metres
pytestmark = needs(SESSION)


def test_frames_match_by_the_last_number_in_their_names():
    assert frame_key("back-02242022135219-3.jpg") == frame_key("side-02242022135220-3.jpg") == "3"
    assert frame_key("610.png") == frame_key("610") == frame_key("img_0610.png") == "610"
    assert frame_key("left.png") == "left"


@pytest.fixture(scope="module")
def views():
    board = parse_board(BOARD)
    # cache=False: nothing is written beside the shared data
    return [detect_views(SESSION / c / "calibration_images", board, cache=False, name=c) for c in CAMERAS]


@pytest.fixture(scope="module")
def rig(views):
    return calibrate_extrinsics(views, parse_board(BOARD), model="pinhole")


def apart_from_anipose(calibration) -> list[tuple[float, float]]:
    """For each pair of back, mid and top (the cameras Anipose's file has entries of its own for): our
    baseline over Anipose's, and the angle (degrees) between the two rigs' relative rotations."""
    import itertools

    from graph.calibrate.poses import rotation_angle

    anipose = load_calibration(SESSION / "calibration.toml")
    o, a = dict(zip(calibration.names, calibration.cameras)), dict(zip(anipose.names, anipose.cameras))
    out = []
    for p, q in itertools.combinations(("back", "mid", "top"), 2):
        ratio = np.linalg.norm(o[p].center - o[q].center) * 1000.0 / np.linalg.norm(a[p].center - a[q].center)
        turn = rotation_angle((o[q].R @ o[p].R.T) @ (a[q].R @ a[p].R.T).T)
        out.append((float(ratio), float(np.degrees(turn))))
    return out


def test_the_images_calibrate_every_camera(rig):
    assert len(rig.frames_used) >= 15
    assert all(c.rms_px < 0.6 for c in rig.cameras), [round(c.rms_px, 3) for c in rig.cameras]
    ours, anipose = rig.calibration, load_calibration(SESSION / "calibration.toml")
    by_name = dict(zip(anipose.names, anipose.cameras))
    # back to top as Anipose has it (its entries for back, mid and top are its own), within 5 %
    b_ours = np.linalg.norm(ours.cameras[0].center - ours.cameras[3].center) * 1000.0
    b_anipose = np.linalg.norm(by_name["back"].center - by_name["top"].center)
    assert abs(b_ours / b_anipose - 1) < 0.05, (b_ours, b_anipose)


def test_with_the_rig_from_the_images_side_agrees_with_the_others(rig):
    """Leave one camera out on the mouse (every point, tri): side 97 px with the shipped file's copied
    entry, about 13 px with the rig the images give (the others 6-13 px)."""
    kps = [read_keypoints(SESSION / c / f"minimal_{c}_proofread.slp") for c in CAMERAS]
    opts = SolveOptions(method="tri", skeleton="points", fps=30.0, likelihood_threshold=0.0)
    ours = leave_one_camera_out(kps, rig.calibration, opts, confidence=0.0)
    shipped = leave_one_camera_out(kps, load_calibration(SESSION / "calibration.toml"), opts, confidence=0.0)
    side_ours, side_shipped = ours.cameras[2].median_px, shipped.cameras[2].median_px
    assert side_shipped > 80 and side_ours < 20, (side_ours, side_shipped)
    assert ours.median_px < 0.6 * shipped.median_px, (ours.median_px, shipped.median_px)


def test_the_rig_is_drawn_upright():
    """With camera 1 as the world frame (z its optical axis), the picture's up is the cameras' mean image
    up: on the AcinoSet rig (six GoPros, world z up) within 3 degrees of the true vertical."""
    from dataclasses import replace
    from types import SimpleNamespace

    from graph.calibrate.report import viewing_frame
    from graph.camera import Calibration
    from graph.io.calibration import default_rig_path

    cal = load_calibration(default_rig_path())
    c0 = cal.cameras[0]  # x_1 = R_0 x + t_0, so camera i sees x_i = R_i R_0^T (x_1 - t_0) + t_i
    cams = [replace(c, R=c.R @ c0.R.T, t=c.t - c.R @ c0.R.T @ c0.t) for c in cal.cameras]
    V = viewing_frame(SimpleNamespace(origin="camera1", calibration=Calibration(cameras=cams)))
    assert np.degrees(np.arccos(V[2] @ (c0.R @ [0.0, 0.0, 1.0]))) < 3.0
    assert np.allclose(V @ V.T, np.eye(3)) and np.isclose(np.linalg.det(V), 1.0)


def test_given_anipose_intrinsics_the_rig_is_anipose_rig(views):
    """Given Anipose's own intrinsics (one focal length, the principal point at the centre, k1 alone;
    side's are top's, its entry a copy), the rig from the images is Anipose's within 0.3 degree and
    1 %: the rotations 0.45-1.1 degree apart with our own intrinsics are the lens model's, not the
    extrinsic step's. Before, the command ended in an IndexError: side's views, misfitted by top's lens,
    were still being dropped in the last round, after its solve."""
    from dataclasses import replace

    anipose = dict(zip(*(lambda c: (c.names, c.cameras))(load_calibration(SESSION / "calibration.toml"))))
    given = [replace(anipose["top" if c == "side" else c], R=np.eye(3), t=np.zeros(3)) for c in CAMERAS]
    rig = calibrate_extrinsics(views, parse_board(BOARD), given, model="pinhole")
    for ratio, turn in apart_from_anipose(rig.calibration):
        assert abs(ratio - 1) < 0.01 and turn < 0.3, (ratio, turn)


def test_anipose_lens_gives_anipose_rig(views):
    """``--lens k1 --refine-intrinsics``: each camera calibrated with Anipose's lens (one focal length,
    the principal point at the image's centre, radial k1 alone) gives the rig Anipose's calibration
    gives, rotations within 0.2 degree (0.06-0.12 measured) and baselines within 1.5 % (0.989-1.000);
    with the whole lens they are 0.65-1.12 degree apart (0.45-1.12 with the intrinsics held, our
    default). Side, which k1 alone fits worst, is at 0.87 px RMS on its boards (0.46 with the whole
    lens refined)."""
    rig = calibrate_extrinsics(views, parse_board(BOARD), model="pinhole", refine_intrinsics=True, lens="k1")
    for ratio, turn in apart_from_anipose(rig.calibration):
        assert abs(ratio - 1) < 0.015 and turn < 0.2, (ratio, turn)
    for cam in rig.calibration.cameras:
        w, h = cam.size
        assert np.isclose(cam.K[0, 0], cam.K[1, 1], rtol=1e-5), cam.K
        assert np.allclose(cam.K[:2, 2], [(w - 1) / 2, (h - 1) / 2], atol=1e-3), cam.K
        assert np.allclose(cam.dist[1:], 0.0, atol=1e-5) and cam.dist[0] < -0.2, cam.dist
    assert all(c.rms_px < 1.0 for c in rig.cameras), [round(c.rms_px, 3) for c in rig.cameras]


def test_intrinsics_refined_in_the_rig_keep_every_camera():
    """``--refine-intrinsics`` on the same images: the other cameras then fit so well (0.2 px) that
    side's views (0.47 px: a softer camera), judged against all cameras' at once, were every one an
    outlier and were dropped in one round, and the command ended in GTSAM's IndexError (its pose was
    in no factor). Views are judged among their own camera's: side keeps its views, and every camera
    fits within 0.5 px."""
    board = parse_board(BOARD)
    views = [detect_views(SESSION / c / "calibration_images", board, cache=False, name=c) for c in CAMERAS]
    rig = calibrate_extrinsics(views, board, model="pinhole", refine_intrinsics=True)
    by_name = {c.name: c for c in rig.cameras}
    assert by_name["side"].views_used >= 20, by_name["side"].views_dropped
    assert all(c.rms_px <= 0.5 for c in rig.cameras), [round(c.rms_px, 3) for c in rig.cameras]
    # the baseline back to top moves towards Anipose's (140.8 mm): 138.4 mm refined, 136.3 mm held
    ours, anipose = rig.calibration, load_calibration(SESSION / "calibration.toml")
    b_anipose = np.linalg.norm(dict(zip(anipose.names, anipose.cameras))["back"].center
                               - dict(zip(anipose.names, anipose.cameras))["top"].center)
    b_ours = np.linalg.norm(ours.cameras[0].center - ours.cameras[3].center) * 1000.0
    assert abs(b_ours / b_anipose - 1) < 0.025, (b_ours, b_anipose)


def test_refine_mends_the_copied_camera_from_the_mouse(tmp_path):
    """``calibrate refine`` with the shipped file, whose side entry is top's: side's detections sit
    about 96 px from the others' points, beyond what an adjustment can bring back (they were all
    trimmed and side stayed where it was, while mid turned 13 degrees). Side is posed again from the
    other cameras' points and on the held-out frames every camera predicts the mouse better than
    before: side within 20 px, no camera worse. The keypoints would then turn mid and top more than
    ten degrees (the mouse is seen through a curved acrylic wall): they are held and reported."""
    import json

    from test_cli import run_cli

    slp = [SESSION / c / f"minimal_{c}_proofread.slp" for c in CAMERAS]
    p = run_cli("calibrate", "refine", SESSION / "calibration.toml", *slp, "--likelihood", "0.01",
                "--out", tmp_path / "new.toml", "--report", tmp_path / "r.json")
    assert p.returncode == 0, p.stderr
    rep = json.loads((tmp_path / "r.json").read_text())
    assert rep["accepted"] and rep["leave_one_out_px"]["held_out_frames"] == 60
    assert [c["re_posed"] for c in rep["cameras"]] == [False, False, True, False]
    assert rep["cameras"][1]["held"] and rep["cameras"][3]["held"]
    assert any(n.startswith("held where they were: mid") for n in rep["notes"]), rep["notes"]
    old, new = rep["leave_one_out_px"]["old"], rep["leave_one_out_px"]["new"]
    assert old[2] > 80 and new[2] < 20, (old, new)
    assert all(n <= o for n, o in zip(new, old)), (old, new)
    assert rep["cameras"][0]["position_change_mm"] < 1e-9  # back holds the world frame
    assert "side was off" in p.stdout + "".join(rep["notes"])
    assert len(load_calibration(tmp_path / "new.toml")) == 4


def test_refine_leaves_the_rig_of_the_images_where_it_is(rig):
    """Refined from the mouse, the rig the board images give (every camera within 0.5 px on its
    boards) would turn 20-40 degrees, further the longer the solve runs: moves the keypoints' own
    errors ask for, not the rig's. Every camera is held and the rig comes back unchanged."""
    from graph.calibrate.refine import refine_rig

    kps = [read_keypoints(SESSION / c / f"minimal_{c}_proofread.slp") for c in CAMERAS]
    r = refine_rig(rig.calibration, kps, 0.01)
    assert [c["held"] for c in r.changes] == [False, True, True, True]
    assert all(c["rotation_change_deg"] < 1e-9 for c in r.changes)
    assert not r.accepted
