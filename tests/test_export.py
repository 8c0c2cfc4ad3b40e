"""Exports read back by the field's own readers: NWB by pynwb + ndx-pose, C3D by ezc3d, TRC by pandas as
OpenSim lays the format out, EKS's CSV by pandas; and movement reading our Anipose 3D CSV.

The run is a real one: the tethered fly of the EKS repository (3 cameras, Anipose calibration in mm),
triangulated by ``tri`` with every bodypart a point.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from shared_data import EKS_FLY

from graph.errors import InputError
from graph.export import export, load_input
from graph.export.base import axes_matrix, error_as_length

FPS = 300.0
TOL = 1e-6  # metres


def _shared_data() -> Path:
    if not EKS_FLY.is_dir():
        pytest.skip("the shared eks_fly data is not here")
    return EKS_FLY


@pytest.fixture(scope="module")
def fly(tmp_path_factory) -> Path:
    """The fly's result H5 (with its calibration), as ``acinoset solve --h5`` writes it."""
    from graph import api
    from graph.io import results
    from graph.io.calibration import load_calibration
    from graph.io.keypoints import read_keypoints

    data = _shared_data()
    cal = load_calibration(data / "calibration.toml")
    kps = [read_keypoints(data / f"cam{c}.rng1.csv") for c in "ABC"]
    opts = api.SolveOptions(method="tri", skeleton="points", fps=FPS, bone_lengths=[("L1A", "L1B"), ("R1A", "R1B")])
    with pytest.warns(UserWarning, match="millimetres"):
        result = api.solve(kps, cal, opts)
    result.positions[7, 3] = np.nan  # a marker without an estimate in one frame, as real runs have
    result.std[7, 3] = np.nan
    path = tmp_path_factory.mktemp("fly") / "fly.h5"
    results.write_h5(path, result, calibration=cal)
    return path


def test_an_export_reads_only_the_arrays_it_writes(fly):
    """The exporters read four of a result's per-frame arrays (an hour's reprojections alone are 0.8
    GB): those are the file's, the other required ones are NaN of their shape and take no memory."""
    from graph.export.base import EXPORTED
    from graph.io.results import read_result

    whole, run = read_result(fly), load_input(fly).result
    for name in EXPORTED:
        np.testing.assert_array_equal(getattr(run, name), getattr(whole, name))
    skipped = run.reprojections
    assert skipped.shape == whole.reprojections.shape and np.isnan(skipped).all()
    assert skipped.strides == (0,) * skipped.ndim and not skipped.flags.writeable  # one value, viewed
    assert run.ncams.dtype == whole.ncams.dtype and not run.ncams.any()
    assert run.likelihood is None and whole.likelihood is not None  # an optional one is left out


def test_a_result_whose_positions_are_not_frames_of_markers_is_refused_in_one_line(fly, tmp_path):
    """A forged result file (positions of the wrong shape) is named and refused, not a ValueError from
    an exporter unpacking a shape."""
    import shutil

    import h5py

    forged = tmp_path / "forged.h5"
    shutil.copy(fly, forged)
    with h5py.File(forged, "r+") as f:
        del f["positions"]
        f["positions"] = np.zeros(3)
    with pytest.raises(InputError, match=r"forged\.h5: damaged acinoset result file \(its positions have shape "
                                         r"\(3,\), not \(frames, 12 markers, 3\)\)"):
        load_input(forged)


def test_the_h5_keeps_the_calibration_in_metres(fly):
    from graph.io.calibration import load_calibration

    run = load_input(fly)
    given = load_calibration(_shared_data() / "calibration.toml")
    assert run.calibration.names == given.names == ["Cam-A", "Cam-B", "Cam-C"]
    for a, b in zip(run.calibration.cameras, given.cameras):
        np.testing.assert_array_equal(a.K, b.K)
        np.testing.assert_array_equal(a.R, b.R)
        np.testing.assert_allclose(a.t, b.t / 1000.0, rtol=1e-15)
        np.testing.assert_array_equal(a.dist, b.dist)
        assert a.model == b.model == "pinhole"


def test_nwb_round_trips_through_pynwb_and_ndx_pose(fly, tmp_path):
    pynwb = pytest.importorskip("pynwb")
    pytest.importorskip("ndx_pose")
    run = load_input(fly)
    res = run.result
    out = export(fly, "nwb", tmp_path / "fly.nwb")
    with pynwb.NWBHDF5IO(str(out), "r", load_namespaces=True) as io:
        nwb = io.read()
        behavior = nwb.processing["behavior"]
        pose = behavior["PoseEstimation"]
        assert sorted(pose.pose_estimation_series) == sorted(res.markers)  # a group: read back by name
        assert pose.source_software == "acinoset"
        assert list(pose.skeleton.nodes[:]) == res.markers
        edges = [(res.markers[a], res.markers[b]) for a, b in pose.skeleton.edges[:]]
        assert edges == res.bones
        assert behavior["Skeletons"].skeletons[res.skeleton] is pose.skeleton
        for j, name in enumerate(res.markers):
            s = pose.pose_estimation_series[name]
            data = s.data[:]
            assert data.shape == (len(res.positions), 3)
            np.testing.assert_allclose(data, res.positions[:, j], atol=TOL, rtol=0)
            assert np.isnan(data).sum() == np.isnan(res.positions[:, j]).sum()
            assert s.unit == "meters" and s.rate == FPS and s.starting_time == 0.0
            assert "calibration" in s.reference_frame
            assert s.confidence is None  # the sd is not a confidence
            sd = behavior["PoseEstimationSD"].time_series[name]
            np.testing.assert_allclose(sd.data[:], res.std[:, j], atol=1e-12, rtol=0)
            assert sd.unit == "meters" and sd.rate == FPS
        assert list(nwb.devices) == ["Cam-A", "Cam-B", "Cam-C"]
        for cam, name in zip(run.calibration.cameras, run.calibration.names):
            d = nwb.devices[name]
            assert type(d).__name__ == "CalibratedCamera"
            np.testing.assert_allclose(d.intrinsic_matrix[:], cam.K, rtol=1e-6)
            np.testing.assert_allclose(d.rotation_matrix[:], cam.R, atol=1e-7)
            np.testing.assert_allclose(d.translation_vector[:], cam.t, atol=1e-7)
            np.testing.assert_allclose(d.distortion_coefficients[:], cam.dist, rtol=1e-6)
    assert list(pynwb.validate(path=str(out))) == []  # the NWB schema and ndx-pose's, checked by pynwb


def test_movement_loads_our_nwb(fly, tmp_path):
    """A second reader of the NWB file: movement's NWB loader (3D, no confidence: NaN)."""
    pytest.importorskip("movement")
    pytest.importorskip("ndx_pose")
    from movement.io import load_poses

    res = load_input(fly).result
    ds = load_poses.from_nwb_file(export(fly, "nwb", tmp_path / "fly.nwb"))
    assert list(ds.keypoints.values) == res.markers and ds.attrs["fps"] == FPS
    got = ds.position.transpose("time", "keypoints", "space", "individuals").values[..., 0]
    np.testing.assert_allclose(got, res.positions, atol=TOL, rtol=0)
    assert np.isnan(ds.confidence.values).all()


def _read_trc(path: Path):
    """A TRC as OpenSim documents it, parsed with pandas: lines 2-3 the key/value header, line 4 the
    marker names (each followed by two empty cells), line 5 X1 Y1 Z1 ..., data from line 6 on."""
    import pandas as pd

    lines = Path(path).read_text().split("\n")
    assert lines[0].split("\t")[:3] == ["PathFileType", "4", "(X/Y/Z)"]
    meta = dict(zip(lines[1].split("\t"), lines[2].split("\t")))
    names = [c for c in lines[3].split("\t")[2:] if c]
    table = pd.read_csv(path, sep="\t", skiprows=5, header=None, skip_blank_lines=True)
    return meta, names, lines[4].split("\t"), table


@pytest.mark.parametrize("axes", [None, "opensim"])
def test_trc_read_back_as_opensim_lays_it_out(fly, tmp_path, axes):
    res = load_input(fly).result
    out = export(fly, "trc", tmp_path / "fly.trc", axes=axes)
    meta, names, xyz, table = _read_trc(out)
    n, m = res.positions.shape[:2]
    assert names == res.markers
    assert xyz[2:] == [f"{a}{j + 1}" for j in range(m) for a in "XYZ"]
    assert meta["NumFrames"] == meta["OrigNumFrames"] == str(n) and int(meta["NumMarkers"]) == m
    assert float(meta["DataRate"]) == float(meta["CameraRate"]) == FPS and meta["Units"] == "m"
    assert table.shape == (n, 2 + 3 * m)
    np.testing.assert_array_equal(table[0], np.arange(1, n + 1))
    np.testing.assert_allclose(table[1], np.arange(n) / FPS, atol=1e-12)
    got = table.iloc[:, 2:].to_numpy().reshape(n, m, 3)
    want = res.positions
    if axes == "opensim":  # y-up: (x, y, z) -> (x, z, -y)
        want = np.stack([want[..., 0], want[..., 2], -want[..., 1]], -1)
    np.testing.assert_allclose(got, want, atol=TOL, rtol=0)
    assert np.isnan(got[7, 3]).all()


def test_axes_are_rotations_only():
    np.testing.assert_array_equal(axes_matrix("opensim"), [[1, 0, 0], [0, 0, 1], [0, -1, 0]])
    np.testing.assert_array_equal(axes_matrix(None), np.eye(3))
    for bad in ("x,y,-z", "x,x,z", "x,y", "a,b,c"):
        with pytest.raises(ValueError):
            axes_matrix(bad)


def test_c3d_round_trips_through_ezc3d(fly, tmp_path):
    ezc3d = pytest.importorskip("ezc3d")
    run = load_input(fly)
    res = run.result
    out = export(fly, "c3d", tmp_path / "fly.c3d")
    c = ezc3d.c3d(str(out))
    point = c["parameters"]["POINT"]
    n, m = res.positions.shape[:2]
    assert list(point["LABELS"]["value"]) == res.markers
    assert point["RATE"]["value"][0] == FPS
    assert point["UNITS"]["value"] == ["mm"]
    assert c["header"]["points"]["last_frame"] - c["header"]["points"]["first_frame"] + 1 == n
    xyz = c["data"]["points"][:3].transpose(2, 1, 0) / 1000.0  # (N, M, 3) metres
    np.testing.assert_allclose(xyz, res.positions, atol=TOL, rtol=0)
    assert np.isnan(xyz[7, 3]).all()
    residual = c["data"]["meta_points"]["residuals"][0].T  # (N, M), mm
    step = -point["SCALE"]["value"][0]
    want = np.clip(error_as_length(run) * 1000.0, 0, 255 * step)
    assert residual[7, 3] == -1.0
    has = np.isfinite(res.positions).all(-1) & np.isfinite(want)
    assert np.all(residual[has] >= 0)
    np.testing.assert_allclose(residual[has], want[has], atol=step * 1.001)  # stored in steps of |SCALE|
    assert residual[has].max() > 0  # the residual is really there


def test_csv_var_is_eks_layout(fly, tmp_path):
    pd = pytest.importorskip("pandas")
    res = load_input(fly).result
    out = export(fly, "csv-var", tmp_path / "fly_var.csv")
    df = pd.read_csv(out, header=[0, 1, 2], index_col=0)
    assert df.columns.names == ["scorer", "bodyparts", "coords"]
    assert list(df.columns.get_level_values(1).unique()) == res.markers
    n = len(res.positions)
    assert len(df) == n and list(df.index) == list(range(n))
    for j, name in enumerate(res.markers):
        for a, axis in enumerate("xyz"):
            col = df[("acinoset_tri", name, axis)].to_numpy()
            np.testing.assert_allclose(col, res.positions[:, j, a], atol=TOL, rtol=0)
            var = df[("acinoset_tri", name, f"{axis}_posterior_var")].to_numpy()
            np.testing.assert_allclose(var, res.std[:, j, a] ** 2, rtol=1e-12)
    # the bytes EKS's own writer gives: its index (scorer, bodyparts, coords) and DataFrame.to_csv
    labels = ["x", "y", "z", "x_posterior_var", "y_posterior_var", "z_posterior_var"]
    index = pd.MultiIndex.from_product([["acinoset_tri"], res.markers, labels],
                                       names=["scorer", "bodyparts", "coords"])
    values = np.concatenate([res.positions, res.std ** 2], -1).reshape(n, -1)
    theirs = tmp_path / "pandas.csv"
    pd.DataFrame(values, columns=index).to_csv(theirs)
    assert out.read_text() == theirs.read_text()


def test_movement_loads_our_anipose_csv(fly, tmp_path):
    pytest.importorskip("movement")
    from movement.io import load_poses

    from graph.io.results import write_anipose_csv

    res = load_input(fly).result
    path = tmp_path / "fly.csv"
    write_anipose_csv(path, res)
    ds = load_poses.from_anipose_file(path, fps=FPS)
    pos = ds.position  # (time, space, keypoints, individuals)
    assert list(ds.keypoints.values) == res.markers
    assert pos.sizes["time"] == len(res.positions) and ds.attrs["fps"] == FPS
    got = pos.transpose("time", "keypoints", "space", "individuals").values[..., 0]
    np.testing.assert_allclose(got, res.positions, atol=1e-12, rtol=0)


def test_a_missing_library_names_the_extra(fly, tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "ezc3d", None)  # as if not installed
    with pytest.raises(InputError, match=r"acinoset\[export\]"):
        export(fly, "c3d", tmp_path / "x.c3d")


def test_export_command(fly, tmp_path):
    exe = Path(sys.executable).with_name("acinoset")
    ok = subprocess.run([str(exe), "export", str(fly), "--format", "trc", "--axes", "opensim",
                         "--out", str(tmp_path / "a.trc")], capture_output=True, text=True)
    assert ok.returncode == 0, ok.stderr
    assert (tmp_path / "a.trc").read_text().startswith("PathFileType\t4")
    for args, fragment in ((["--format", "c3d", "--axes", "opensim"], "--axes applies to --format trc"),
                           (["--format", "xls"], "invalid choice"),
                           (["--format", "csv-var", "--units", "mm"], "--units applies to --format trc and c3d only"),
                           (["--format", "trc", "--axes", "x,y,-z"], "not a rotation")):
        bad = subprocess.run([str(exe), "export", str(fly), "--out", str(tmp_path / "b"), *args],
                             capture_output=True, text=True)
        assert bad.returncode == 2 and fragment in bad.stderr and len(bad.stderr.strip().splitlines()) == 1
    missing = subprocess.run([str(exe), "export", str(tmp_path / "none.h5"), "--format", "nwb", "--out",
                              str(tmp_path / "c.nwb")], capture_output=True, text=True)
    assert missing.returncode == 2 and "none.h5: no such file" in missing.stderr


def test_each_format_is_declared_once_by_its_module():
    """The registry, the default extensions, the command's help and which formats take --axes and
    --units all come from the modules' own Format."""
    import importlib

    from graph.export import EXTENSIONS, FORMATS, REGISTRY, Format, c3d, trc
    from graph.export.cli import format_help

    assert FORMATS[:4] == ("nwb", "trc", "c3d", "csv-var") and FORMATS == tuple(REGISTRY)
    assert EXTENSIONS["csv-var"] == ".var.csv" and EXTENSIONS["nwb"] == ".nwb"
    assert REGISTRY["nwb"].needs == ("pynwb", "ndx_pose") and REGISTRY["c3d"].needs == ("ezc3d",)
    assert trc.FORMAT.options == {"axes": None, "units": "m"}  # read from write's signature
    assert c3d.FORMAT.options == {"units": "mm", "residual_step": None}
    for name, f in REGISTRY.items():  # each declared by the module graph.export.<name> and read from there
        assert importlib.import_module(f"graph.export.{name.replace('-', '_')}").FORMAT is f
        assert EXTENSIONS[name] == f.extension
        assert f"{name}: {f.label}, {f.help}" + (" (needs acinoset[export])" if f.needs else "") in format_help()
    with pytest.raises(ValueError, match="start with a dot"):
        Format("markers", "json", "application/json", "Markers", "x, y, z per marker", trc.write)


def test_a_result_file_without_its_calibration(fly, tmp_path):
    """Older result files hold no calibration: C3D residuals are 0 with a warning, NWB has plain
    devices; given the calibration file, both are as with it stored."""
    ezc3d = pytest.importorskip("ezc3d")
    pynwb = pytest.importorskip("pynwb")
    from graph.io.results import read_result, write_h5

    old = tmp_path / "old.h5"
    write_h5(old, read_result(fly))
    assert load_input(old).calibration is None
    with pytest.warns(UserWarning, match="holds no calibration"):
        export(old, "c3d", tmp_path / "old.c3d")
    has = np.isfinite(read_result(fly).positions).all(-1).T
    residual = ezc3d.c3d(str(tmp_path / "old.c3d"))["data"]["meta_points"]["residuals"][0]
    assert (residual[has] == 0).all() and (residual[~has] == -1).all()
    export(old, "nwb", tmp_path / "old.nwb")
    with pynwb.NWBHDF5IO(str(tmp_path / "old.nwb"), "r", load_namespaces=True) as io:
        assert {type(d).__name__ for d in io.read().devices.values()} == {"Device"}
    given = export(old, "c3d", tmp_path / "given.c3d", calibration=_shared_data() / "calibration.toml")
    stored = export(fly, "c3d", tmp_path / "stored.c3d")
    np.testing.assert_array_equal(ezc3d.c3d(str(given))["data"]["meta_points"]["residuals"],
                                  ezc3d.c3d(str(stored))["data"]["meta_points"]["residuals"])
