"""Result files: Anipose 3D CSV (as ``anipose triangulate`` writes it), the HDF5 archive round
trip, and reprojections as DeepLabCut CSVs."""

from __future__ import annotations

import json

import h5py
import numpy as np
import pytest

from graph.api import Result, SolveOptions, SolveReport
from graph.errors import InputError
from graph.io.calibration import default_rig_path, load_calibration
from graph.io.keypoints import read_keypoints
from graph.io.results import read_anipose_csv, read_result, write_anipose_csv, write_h5, write_reprojections_dlc

MARKERS = ["nose", "l_eye", "r_eye", "neck_base", "spine"]


def _result(n: int = 20, method: str = "fte", causal: bool = False, seed: int = 0) -> Result:
    """A result with the shapes and gaps a solve produces: points near the rig's common view,
    their true reprojections, residuals with holes, outliers."""
    rng = np.random.default_rng(seed)
    cal = load_calibration(default_rig_path())
    m, c = len(MARKERS), len(cal)
    positions = np.array([0.0, 5.0, 0.5]) + rng.normal(0, 0.5, (n, m, 3))
    positions[3, 2] = np.nan  # no estimate
    reproj = cal.project(positions)
    residuals = np.abs(rng.normal(0, 3, (c, n, m)))
    residuals[:, 3, 2] = np.nan
    residuals[0, ::4] = np.nan  # camera 1 missed some frames
    outlier = rng.random((c, n, m)) < 0.05
    ncams = np.isfinite(residuals).sum(0)
    score = np.where(ncams > 0, rng.uniform(0.5, 1, (n, m)), np.nan)
    P = 25
    report = SolveReport(method=method, skeleton="cheetah", frames=n, cameras=c, markers=m,
                         seconds={"total": 1.5, "init": 0.25, "solve": 1.25}, iterations=12, cost=float("nan"),
                         reprojection_rmse_px=2.25, per_frame_ms={"mean": 4.0, "p95": 6.5} if method == "ekf" else None,
                         outliers=int(outlier.sum()), observations=int(ncams.sum()),
                         unconstrained_markers=["spine"], unconstrained_frames=[3], bounds_active=2,
                         warnings=["bodypart 'lure' is not a marker: ignored"])
    options = SolveOptions(method=method, fps=90.0, skeleton="cheetah", likelihood_threshold=0.3,
                           bone_lengths=[("nose", "l_eye"), ("l_eye", "r_eye")])
    return Result(method=method, skeleton="cheetah", markers=list(MARKERS), positions=positions,
                  std=np.abs(rng.normal(0, 0.01, (n, m, 3))), reprojections=reproj, residuals=residuals,
                  ncams=ncams, score=score, outlier=outlier, camera_names=cal.names, fps=90.0, report=report,
                  options=options, param_names=[f"q{i}" for i in range(P)], params=rng.normal(size=(n, P)),
                  rates=rng.normal(size=(n, P)), params_std=np.abs(rng.normal(size=(n, P))),
                  causal_positions=positions + 0.01 if causal else None,
                  bones=[("nose", "l_eye"), ("nose", "r_eye"), ("neck_base", "spine")])


# ------------------------------------------------------------------------------ Anipose CSV


def test_anipose_csv_matches_anipose_triangulate_output(tmp_path):
    """Byte for byte the table ``anipose triangulate`` builds and saves with ``to_csv(index=False)``."""
    pd = pytest.importorskip("pandas")
    res = _result()
    ours = tmp_path / "ours.csv"
    write_anipose_csv(ours, res)

    n = res.positions.shape[0]
    has = np.isfinite(res.positions).all(-1)
    errors = np.where(has, res.error, np.nan)
    num_cams = np.where(has, res.ncams.astype(float), np.nan)
    scores = np.where(has, res.score, np.nan)
    M, center = np.identity(3), np.zeros(3)
    dout = pd.DataFrame()  # anipose/triangulate.py, from here on
    for bp_num, bp in enumerate(res.markers):
        for ax_num, axis in enumerate(["x", "y", "z"]):
            dout[bp + "_" + axis] = res.positions[:, bp_num, ax_num]
        dout[bp + "_error"] = errors[:, bp_num]
        dout[bp + "_ncams"] = num_cams[:, bp_num]
        dout[bp + "_score"] = scores[:, bp_num]
    for i in range(3):
        for j in range(3):
            dout["M_{}{}".format(i, j)] = M[i, j]
    for i in range(3):
        dout["center_{}".format(i)] = center[i]
    dout["fnum"] = np.arange(n)
    theirs = tmp_path / "anipose.csv"
    dout.to_csv(theirs, index=False)
    assert ours.read_text() == theirs.read_text()


def test_anipose_csv_round_trip(tmp_path):
    res = _result()
    path = tmp_path / "run.csv"
    write_anipose_csv(path, res)
    header = path.read_text().splitlines()[0].split(",")
    assert header[:6] == ["nose_x", "nose_y", "nose_z", "nose_error", "nose_ncams", "nose_score"]
    assert header[-1] == "fnum" and "M_22" in header and "center_2" in header
    table = read_anipose_csv(path)
    assert table.markers == MARKERS
    np.testing.assert_array_equal(table.positions, res.positions)
    has = np.isfinite(res.positions).all(-1)
    np.testing.assert_array_equal(table.error, np.where(has, res.error, np.nan))
    np.testing.assert_array_equal(table.ncams, np.where(has, res.ncams, np.nan))
    np.testing.assert_array_equal(table.score, np.where(has, res.score, np.nan))
    np.testing.assert_array_equal(table.fnum, np.arange(20))
    np.testing.assert_array_equal(table.M, np.eye(3))
    assert np.isnan(table.positions[3, 2]).all() and np.isnan(table.error[3, 2])


def test_read_anipose_csv_without_frame_columns(tmp_path):
    """Older / trimmed tables: only the marker columns."""
    path = tmp_path / "old.csv"
    path.write_text("tail_tip_x,tail_tip_y,tail_tip_z,tail_tip_error\n1.0,2.0,3.0,0.5\n,,,\n")
    t = read_anipose_csv(path)
    assert t.markers == ["tail_tip"]
    np.testing.assert_array_equal(t.positions[0, 0], [1, 2, 3])
    assert np.isnan(t.positions[1]).all() and np.isnan(t.ncams).all()
    np.testing.assert_array_equal(t.fnum, [0, 1])


@pytest.mark.parametrize("content,expected", [
    ("", "file is empty"),
    ("a,b,c\n1,2,3\n", "not an Anipose 3D CSV: no <marker>_x, _y, _z columns"),
    ("n_x,n_y,n_z\n1,2\n", "line 2 has 2 cells"),
    ("n_x,n_y,n_z\n1,2,zz\n", "line 2, column n_z: not a number"),
])
def test_bad_anipose_csv(tmp_path, content, expected):
    path = tmp_path / "bad.csv"
    path.write_text(content)
    with pytest.raises(InputError, match=f"^bad\\.csv: {expected}"):
        read_anipose_csv(path)


# ------------------------------------------------------------------------------------ HDF5


def _assert_same(a: Result, b: Result) -> None:
    for name in ("positions", "std", "reprojections", "residuals", "ncams", "score", "outlier",
                 "params", "rates", "params_std", "causal_positions"):
        x, y = getattr(a, name), getattr(b, name)
        if x is None:
            assert y is None, name
            continue
        assert np.asarray(y).dtype == np.asarray(x).dtype, name
        np.testing.assert_array_equal(y, x, err_msg=name)
    for name in ("method", "skeleton", "markers", "camera_names", "param_names", "bones", "fps"):
        assert getattr(a, name) == getattr(b, name), name
    assert a.options == b.options
    assert json.dumps(a.report.to_dict()) == json.dumps(b.report.to_dict())


@pytest.mark.parametrize("method,causal", [("fte", False), ("ekf", True), ("tri", False)])
def test_h5_round_trip(tmp_path, method, causal):
    res = _result(method=method, causal=causal)
    if method == "tri":
        res.params = res.rates = res.params_std = None
        res.param_names = []
    path = tmp_path / "run.h5"
    write_h5(path, res)
    back = read_result(path)
    _assert_same(res, back)
    assert np.isnan(back.report.cost) and back.report.seconds == {"total": 1.5, "init": 0.25, "solve": 1.25}
    assert back.options.bone_lengths == [("nose", "l_eye"), ("l_eye", "r_eye")]
    with h5py.File(path) as f:  # readable without acinoset: plain datasets and JSON attributes
        assert f.attrs["format"] == "acinoset.result"
        assert json.loads(f.attrs["report"])["method"] == method
        assert f["positions"].shape == res.positions.shape
        assert [s.decode() for s in f["markers"][()]] == MARKERS


def test_h5_keeps_camera_centers_when_the_result_has_them(tmp_path):
    res = _result()
    if not hasattr(res, "camera_centers"):
        pytest.skip("Result has no camera_centers field")
    res.camera_centers = np.stack([c.center for c in load_calibration(default_rig_path()).cameras])
    write_h5(tmp_path / "r.h5", res)
    np.testing.assert_array_equal(read_result(tmp_path / "r.h5").camera_centers, res.camera_centers)


def test_read_result_rejects_other_files(tmp_path):
    other = tmp_path / "other.h5"
    with h5py.File(other, "w") as f:
        f["x"] = np.zeros(2)
    with pytest.raises(InputError, match=r"^other\.h5: not an acinoset result file"):
        read_result(other)
    text = tmp_path / "run.csv"
    text.write_text("a,b\n")
    with pytest.raises(InputError, match=r"^run\.csv: not an HDF5 file$"):
        read_result(text)
    with pytest.raises(InputError, match=r"^nope\.h5: no such file$"):
        read_result(tmp_path / "nope.h5")
    damaged = tmp_path / "damaged.h5"
    write_h5(damaged, _result())
    with h5py.File(damaged, "r+") as f:
        del f["positions"]
    with pytest.raises(InputError, match=r"^damaged\.h5: result file lacks the dataset 'positions'$"):
        read_result(damaged)


# ------------------------------------------------------------------------- reprojections


def test_reprojections_as_dlc_csv(tmp_path):
    res = _result()
    paths = write_reprojections_dlc(tmp_path / "reproj", res)
    assert [p.name for p in paths] == [f"{n}.csv" for n in res.camera_names]
    for c, p in enumerate(paths):
        kp = read_keypoints(p)
        assert kp.bodyparts == MARKERS and kp.scorer == "acinoset_fte"
        seen = np.isfinite(res.reprojections[c]).all(-1)
        np.testing.assert_array_equal(kp.xy[seen], res.reprojections[c][seen])
        np.testing.assert_array_equal(kp.likelihood, seen.astype(float))
        assert not seen[3, 2]
    named = write_reprojections_dlc(tmp_path / "named", res, stems=[f"cam{i}_reproj" for i in range(6)])
    assert named[0].name == "cam0_reproj.csv"
    with pytest.raises(ValueError):
        write_reprojections_dlc(tmp_path / "x", res, stems=["only_one"])


def test_marker_names_written_to_csv_never_start_a_spreadsheet_formula(tmp_path):
    """Issue item 11: a bodypart named '=HYPERLINK(...)' (an upload chooses the names under the points
    skeleton) ran as a formula when a result CSV was opened in a spreadsheet."""
    import csv
    import dataclasses

    res = _result()
    evil = ['=HYPERLINK("http://evil.example","x")', "+1+cmd|' /C calc'!A0", "-2+3", "@SUM(A1:A2)", "\tx"]
    res = dataclasses.replace(res, markers=evil + list(res.markers[len(evil):]))
    write_anipose_csv(tmp_path / "run.csv", res)
    paths = write_reprojections_dlc(tmp_path / "reproj", res)
    for path in [tmp_path / "run.csv", *paths]:
        with open(path, newline="") as f:
            rows = list(csv.reader(f))
            for row in rows[:1] if path.name == "run.csv" else rows[:3]:  # the header rows: names
                for cell in row:
                    assert not cell.startswith(("=", "+", "-", "@", "\t", "\r")), (path.name, cell)
    assert "'=HYPERLINK" in (tmp_path / "run.csv").read_text().splitlines()[0]
    assert read_keypoints(paths[0]).bodyparts[:2] == ["'" + evil[0], "'" + evil[1]]
