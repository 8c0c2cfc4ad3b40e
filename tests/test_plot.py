"""Pictures of a solved run: the JSON payload, the PNG figures and the offline HTML playback.

The run is a cheetah galloping through the real AcinoSet 2019 rig: poses by forward kinematics of
the packaged cheetah skeleton, projected into the six cameras, noisy detections with outliers and
a camera dropout, solved by robust triangulation through :func:`graph.api.solve`.
"""

from __future__ import annotations

import json
import math
import re

import numpy as np
import pytest

from graph.api import Result, SolveOptions, SolveReport, solve
from graph.io.calibration import default_rig_path, load_calibration
from graph.io.keypoints import Keypoints
from graph.skeleton import load_skeleton
from graph.viewer import cli as plot_cli
from graph.viewer import figures, payload, playback

FPS = 120.0


def gallop_params(n: int, skeleton) -> np.ndarray:
    """Pose parameters (n, 25) of a cheetah running along +x through the middle of the rig."""
    t = np.arange(n) / FPS
    w = 2 * np.pi * 2.5  # stride frequency, Hz
    q = np.zeros((n, skeleton.n_params))
    ix = {name: i for i, name in enumerate(skeleton.param_names)}
    q[:, ix["x_0"]] = 0.8 + 4.0 * t
    q[:, ix["y_0"]] = 6.6 + 0.05 * np.sin(w * t / 2)
    q[:, ix["z_0"]] = 0.35 + 0.03 * np.sin(w * t)
    q[:, ix["theta_0"]] = 0.1 * np.sin(w * t)
    q[:, ix["theta_2"]] = 0.15 * np.sin(w * t + 0.5)
    q[:, ix["theta_3"]] = 0.2 * np.sin(w * t + 1.0)
    q[:, ix["theta_4"]] = -0.2 + 0.15 * np.sin(w * t)
    q[:, ix["psi_5"]] = 0.3 * np.sin(w * t / 2)
    for k, phase in ((6, 0.0), (8, 0.6), (10, np.pi), (12, np.pi + 0.6)):
        q[:, ix[f"theta_{k}"]] = 0.6 * np.sin(w * t + phase)
    for k, phase in ((7, 0.0), (9, 0.6)):
        q[:, ix[f"theta_{k}"]] = -0.8 - 0.5 * np.sin(w * t + phase + 1.2)
    for k, phase in ((11, np.pi), (13, np.pi + 0.6)):
        q[:, ix[f"theta_{k}"]] = 0.8 + 0.5 * np.sin(w * t + phase + 1.2)
    return skeleton.clip(q)


def simulated_keypoints(n: int = 60, seed: int = 1):
    """DeepLabCut-like detections of the gallop in every camera of the real rig."""
    rng = np.random.default_rng(seed)
    calib = load_calibration(default_rig_path())
    sk = load_skeleton("cheetah")
    q = gallop_params(n, sk)
    X = sk.positions(q)  # (n, M, 3)
    uv = calib.project(X)  # (C, n, M, 2)
    kps = []
    for c, cam in enumerate(calib.cameras):
        xy = uv[c] + rng.normal(0, 2.0, uv[c].shape)
        lik = rng.uniform(0.7, 1.0, xy.shape[:2])
        wild = rng.random(xy.shape[:2]) < 0.03  # confident mistakes
        xy[wild] += rng.normal(0, 120.0, (wild.sum(), 2))
        w, h = cam.size
        off = ~((xy[..., 0] >= 0) & (xy[..., 0] < w) & (xy[..., 1] >= 0) & (xy[..., 1] < h))
        xy[off] = np.nan
        lik[off] = 0.0
        if c == 3:  # a whole-camera dropout in the middle of the run
            xy[n // 3: n // 3 + 8] = np.nan
            lik[n // 3: n // 3 + 8] = 0.0
        kps.append(Keypoints(bodyparts=list(sk.markers), xy=xy, likelihood=lik))
    return kps, calib, sk, q, X


@pytest.fixture(scope="module")
def solved():
    """A real triangulation result, and its calibration."""
    kps, calib, sk, q, X = simulated_keypoints()
    result = solve(kps, calib, SolveOptions(method="tri", fps=FPS, skeleton="cheetah"))
    return result, calib


@pytest.fixture(scope="module")
def kinematic():
    return kinematic_result()


def kinematic_result() -> Result:
    """A constructed result with pose parameters (as the kinematic smoother returns), one marker
    never seen by two cameras and a frame with no marker seen twice."""
    kps, calib, sk, q, X = simulated_keypoints(n=48, seed=2)
    tri = solve(kps, calib, SolveOptions(method="tri", fps=FPS, skeleton="cheetah"))
    N, M = X.shape[:2]
    ncams = tri.ncams.copy()
    ncams[:, sk.markers.index("tail2")] = np.minimum(ncams[:, sk.markers.index("tail2")], 1)
    ncams[30] = np.minimum(ncams[30], 1)
    std = np.full((N, M, 3), 0.004)
    std[30] = 0.05
    report = SolveReport(method="fte", skeleton="cheetah", frames=N, cameras=len(calib), markers=M,
                         reprojection_rmse_px=2.3, outliers=int(tri.outlier.sum()),
                         observations=int(np.isfinite(tri.residuals).sum()),
                         unconstrained_markers=["tail2"], unconstrained_frames=[30])
    pstd = np.full_like(q, 0.01)
    pstd[30] = 0.08
    return Result(method="fte", skeleton="cheetah", markers=list(sk.markers), positions=X, std=std,
                  reprojections=calib.project(X), residuals=tri.residuals, ncams=ncams, score=tri.score,
                  outlier=tri.outlier, camera_names=calib.names, fps=FPS, report=report,
                  options=SolveOptions(method="fte", fps=FPS), param_names=list(sk.param_names),
                  params=q, params_std=pstd, bones=list(sk.bones),
                  camera_centers=np.stack([c.center for c in calib.cameras]))


def test_payload_is_strict_json_with_the_result_numbers(solved):
    result, calib = solved
    p = payload.result_payload(result, calib)
    text = payload.payload_json(p).decode("utf-8")

    def not_json(token: str):
        raise AssertionError(f"{token} is not JSON")

    back = json.loads(text, parse_constant=not_json)  # NaN or Infinity in the text fails
    N, M = result.positions.shape[:2]
    C = len(result.camera_names)
    np.testing.assert_allclose(np.array(back["reprojection_error_px"], dtype=float), result.error, atol=0.006)
    assert back["frames"] == N and back["markers"] == result.markers
    assert np.array(back["positions"], dtype=float).shape == (N, M, 3)
    assert np.array(back["residuals"], dtype=float).shape == (C, N, M)
    # NaN became null and numbers survive to the payload's rounding.
    pos = np.array(back["positions"], dtype=float)
    assert np.array_equal(np.isnan(pos), np.isnan(result.positions))
    np.testing.assert_allclose(pos, result.positions, atol=1e-5, equal_nan=True)
    # Bones are pairs of marker names, drawn from the skeleton's tree.
    assert {tuple(b) for b in back["bones"]} == set(map(tuple, result.bones)) and len(back["bones"]) == 21
    assert back["cameras"] == calib.names
    # Camera centres come from the calibration: -R^T t.
    np.testing.assert_allclose(back["camera_centers"], [c.center for c in calib.cameras], atol=1e-5)
    # Every rejected detection is listed once, as [camera, frame, marker].
    assert len(back["outliers"]) == int((result.outlier & np.isfinite(result.residuals)).sum()) > 0
    c, n, m = back["outliers"][0]
    assert result.outlier[c, n, m]
    med = np.array(back["error_table"]["median"], dtype=float)
    assert med.shape == (C, M) and np.nanmax(med) < 20  # inlier medians of 2 px noise
    assert back["report"]["method"] == "tri" and back["options"]["fps"] == FPS


def test_payload_without_camera_positions_says_so(solved):
    result, _ = solved
    bare = Result(**{**result.__dict__, "camera_centers": None})
    assert payload.result_payload(bare)["camera_centers"] is None


def test_camera_count_mismatch_is_a_one_line_input_error(solved):
    from graph.errors import InputError
    from graph.io.calibration import Calibration

    result, calib = solved
    bare = Result(**{**result.__dict__, "camera_centers": None})
    with pytest.raises(InputError, match="calibration has 2 cameras but the result has 6"):
        payload.result_payload(bare, Calibration(cameras=calib.cameras[:2]))


def test_error_table_median_and_counts():
    """Median over frames of the residuals the solver used; rejected ones are only counted."""
    r = np.array([[[1.0, np.nan], [3.0, np.nan], [100.0, np.nan]]])  # (C=1, N=3, M=2)
    out = np.array([[[False, False], [False, False], [True, False]]])
    res = Result(method="tri", skeleton="points", markers=["a", "b"], positions=np.zeros((3, 2, 3)),
                 std=np.zeros((3, 2, 3)), reprojections=np.zeros((1, 3, 2, 2)), residuals=r,
                 ncams=np.ones((3, 2)), score=np.ones((3, 2)), outlier=out, camera_names=["c"], fps=1.0,
                 report=SolveReport("tri", "points", 3, 1, 2), options=SolveOptions(method="tri"))
    t = payload.error_table(res)
    assert t.median[0, 0] == 2.0 and math.isnan(t.median[0, 1])
    assert t.observations.tolist() == [[3, 0]] and t.outliers.tolist() == [[1, 0]]
    np.testing.assert_allclose(payload.frame_error(res), [1.0, 3.0, np.nan])


def test_frame_ranges():
    assert payload.frame_ranges([7, 1, 2, 3, 3]) == [(1, 3), (7, 7)]
    assert payload.frame_ranges([]) == []


def _png_size(path):
    head = path.read_bytes()[:24]
    assert head[:8] == b"\x89PNG\r\n\x1a\n", f"{path.name} is not a PNG"
    return int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")


def _ink(path) -> float:
    """Fraction of pixels that are not background white."""
    from matplotlib.image import imread

    img = imread(path)[..., :3]
    return float((img.min(axis=2) < 0.9).mean())


def test_figures_of_a_kinematic_result(kinematic, tmp_path):
    written = figures.write_figures(kinematic, tmp_path)
    names = sorted(p.name for p in written)
    assert names == ["coordinates.png", "flags.png", "parameters.png", "reprojection_error.png", "skeleton.png"]
    for p in written:
        w, h = _png_size(p)
        assert w >= 500 and h >= 300
        assert _ink(p) > 0.02, f"{p.name} is blank"


def test_figures_of_a_triangulation_have_no_parameter_figure(solved, tmp_path):
    result, calib = solved
    written = figures.write_figures(result, tmp_path, calib)
    assert "parameters.png" not in {p.name for p in written}
    assert (tmp_path / "skeleton.png").is_file() and (tmp_path / "flags.png").is_file()


def test_playback_html_is_self_contained(kinematic, tmp_path):
    path = playback.write_playback_html(kinematic, tmp_path / "playback.html")
    text = path.read_text(encoding="utf-8")
    # No file or address outside the page is referenced: scripts and styles are inline.
    assert not re.search(r"<script[^>]+src=", text)
    assert not re.search(r"<link[^>]+stylesheet", text)
    assert len(text) > 3_000_000  # plotly.js itself is inside
    payload = re.search(r'<script type="application/json" id="payload">(.*?)</script>', text, re.S).group(1)
    data = json.loads(payload.replace("<\\/", "</"))
    assert data["frames"] == kinematic.positions.shape[0]
    assert data["param_names"][:3] == ["x_0", "y_0", "z_0"] and data["param_units"][3] == "rad"


def test_plot_command_on_a_result_file(solved, tmp_path, capsys):
    """`acinoset plot RESULT.h5 --out DIR` on a file written by the result writer."""
    import argparse

    from graph.io.results import write_h5

    result, calib = solved
    h5 = tmp_path / "run.h5"
    write_h5(h5, result)
    parser = argparse.ArgumentParser(prog="acinoset")
    plot_cli.register(parser.add_subparsers(dest="command"))
    args = parser.parse_args(["plot", str(h5), "--out", str(tmp_path / "pics")])
    assert args.func(args) == 0
    printed = capsys.readouterr().out.split()
    assert {p.rsplit("/", 1)[-1] for p in printed} == {
        "skeleton.png", "reprojection_error.png", "coordinates.png", "flags.png", "playback.html"}
    html_text = (tmp_path / "pics" / "playback.html").read_text(encoding="utf-8")
    assert '"camera_centers":[[' in html_text or result.camera_centers is None


def test_plot_command_names_a_missing_file(tmp_path):
    import argparse

    from graph.errors import InputError

    parser = argparse.ArgumentParser(prog="acinoset")
    plot_cli.register(parser.add_subparsers(dest="command"))
    args = parser.parse_args(["plot", str(tmp_path / "nope.h5"), "--out", str(tmp_path)])
    with pytest.raises(InputError, match=r"^nope\.h5: no such file$"):
        args.func(args)
