"""A camera that disagrees with the others is named after a solve: on SLEAP's minimal session, whose
calibration entry for 'side' is a copy of 'top''s, and never on a clean simulation of the real rig."""

from __future__ import annotations

import dataclasses
import re
import warnings

import numpy as np
import pytest
from shared_data import SLEAP_MINIMAL

from graph.api import SolveOptions, solve
from graph.camera import Calibration
from graph.io.calibration import default_rig_path, load_calibration
from graph.io.keypoints import read_keypoints
from graph.simulate import simulate_run
from graph.solve import disagreement, problem

SESSION = SLEAP_MINIMAL
CAMERAS = ("back", "mid", "side", "top")
NAMED = re.compile(r"camera (\w+) disagrees with the others: its detections sit (\d+) px")


def _said(result) -> list[str]:
    return [w for w in result.report.warnings if "disagree" in w]


@pytest.fixture(scope="module")
def session():
    if not SESSION.is_dir():
        pytest.skip("the SLEAP session is not on this machine")
    kps = [read_keypoints(SESSION / c / f"minimal_{c}_proofread.analysis.h5") for c in CAMERAS]
    return kps, load_calibration(SESSION / "calibration.toml")


@pytest.mark.parametrize("method", ["tri", "ekf", "fte"])
def test_the_session_names_side_and_how_far_off_it_is(session, method):
    kps, cal = session
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        result = solve(kps, cal, SolveOptions(method=method, skeleton="points", fps=30.0, likelihood_threshold=0.0))
    said = _said(result)
    assert len(said) == 1, result.report.warnings
    camera, px = NAMED.match(said[0]).groups()
    assert camera == "side" and 80 <= int(px) <= 110, said[0]  # SOURCE.md: about 92 px
    assert said[0] in [str(w.message) for w in caught]  # warned too, as the command line shows it


def test_the_check_alone_on_the_session(session):
    kps, cal = session
    prob = problem.build(kps, cal, SolveOptions(skeleton="points", fps=30.0, likelihood_threshold=0.0))
    agreements = disagreement.camera_agreement(prob.calibration, prob.meas, prob.valid, prob.sigma_px)
    by = {a.camera: a for a in agreements}
    assert [a.camera for a in agreements if a.disagrees] == ["side"]
    assert by["side"].held_out_px > 5 * max(by[c].held_out_px for c in ("back", "top"))
    # three cameras cannot tell: with mid left out, nothing is named (a pair agrees about anything)
    keep = [0, 2, 3]
    sub = Calibration(cameras=[prob.calibration.cameras[i] for i in keep])
    assert disagreement.camera_agreement(sub, prob.meas[:, keep], prob.valid[:, keep]) == []
    assert not disagreement.worth_checking(np.zeros((3, 4, 5)), np.ones((3, 4, 5), dtype=bool))


def test_two_views_from_one_place_count_as_one(session):
    """Back, side and top, side's entry top's: where back misses a node only two rays from one centre
    see it. Triangulated, that put the point at the centre, and the marginals' Cholesky then met a
    pivot that was not positive (numpy's LinAlgError, a traceback from ``solve``). Now the two cameras
    are named as one place, count as one view, and those frames are answered by the motion model."""
    kps, cal = session
    keep = [0, 2, 3]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        result = solve([kps[i] for i in keep], Calibration(cameras=[cal.cameras[i] for i in keep]),
                       SolveOptions(skeleton="points", fps=30.0, likelihood_threshold=0.0))
    assert [w for w in result.report.warnings if w.startswith("cameras side and top are at one place")]
    seen = np.stack([k.likelihood > 0 for k in kps])  # (4, N, M)
    two_places = seen[0] & (seen[2] | seen[3])
    one_place = ~seen[0] & seen[2] & seen[3]
    answered = np.isfinite(result.positions).all(axis=-1)
    assert one_place.sum() > 100 and answered[two_places].all()
    # a marker seen from two places in some frames is carried by the motion model between them, with a wider sd
    carried = one_place & two_places.any(axis=0)[None]
    sd = np.linalg.norm(result.std, axis=-1)
    assert answered[carried].all() and np.median(sd[carried]) > 1.1 * np.median(sd[two_places])
    assert (result.ncams[one_place] == 1).all()  # flagged as the motion model's answer, though two cameras saw it
    # one never seen from two places has no estimate, as a marker no camera pair sees
    never = ~two_places.any(axis=0)
    assert not answered[:, never].any()


def test_a_clean_simulation_of_the_rig_names_no_camera():
    rig = load_calibration(default_rig_path())
    for seed in (0, 1):
        run = simulate_run(rig, frames=200, seed=seed)
        prob = problem.build(run.keypoints, rig, SolveOptions(fps=run.fps))
        agreements = disagreement.camera_agreement(prob.calibration, prob.meas, prob.valid, prob.sigma_px)
        assert len(agreements) == 6 and not any(a.disagrees for a in agreements), agreements
        assert max(a.held_out_px / a.reference_px for a in agreements) < 2.0
        for method in ("tri", "fte"):
            result = solve(run.keypoints, rig, SolveOptions(method=method, fps=run.fps))
            assert not _said(result), result.report.warnings


def test_a_copied_calibration_entry_on_the_simulated_rig_is_named():
    """The session's fault made on the simulated rig: camera 3's entry replaced by camera 4's."""
    rig = load_calibration(default_rig_path())
    run = simulate_run(rig, frames=200, seed=0)
    cams = list(rig.cameras)
    wrong = Calibration(cameras=cams[:2] + [dataclasses.replace(cams[3], name=cams[2].name)] + cams[3:],
                        source=rig.source)
    result = solve(run.keypoints, wrong, SolveOptions(method="tri", fps=run.fps))
    said = _said(result)
    assert len(said) == 1 and NAMED.match(said[0]).group(1) == cams[2].name, result.report.warnings
