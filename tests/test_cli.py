"""The ``acinoset`` command line, run as a user runs it: a separate process, real files.

Every bad input must end with exit status 2 and exactly one stderr line
``acinoset: error: <file>: <problem>``, never a traceback.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from graph.camera import Calibration
from graph.io.calibration import default_rig_path, load_calibration, write_anipose_toml
from graph.io.keypoints import Keypoints, read_keypoints, write_dlc_csv
from graph.io.results import read_anipose_csv, read_result

ROOT = Path(__file__).resolve().parents[1]
MARKERS = ["nose", "l_eye", "r_eye", "neck_base", "spine"]
FRAMES = 40
FPS = 90.0


def run_cli(*args: str | Path, cwd: Path | None = None) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    return subprocess.run([sys.executable, "-m", "graph.app.cli", *map(str, args)], capture_output=True, text=True,
                          env=env, cwd=cwd, timeout=300)


def assert_user_error(proc: subprocess.CompletedProcess, filename: str, *fragments: str) -> str:
    lines = proc.stderr.splitlines()
    assert proc.returncode == 2, proc.stderr
    assert "Traceback" not in proc.stderr
    assert len(lines) == 1, proc.stderr
    assert lines[0].startswith(f"acinoset: error: {filename}: "), lines[0]
    for f in fragments:
        assert f in lines[0], lines[0]
    return lines[0]


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory) -> Path:
    """Three cameras of the AcinoSet rig watching five points move on smooth paths, 1 px noise,
    written as a user brings them: DeepLabCut CSVs and an Anipose calibration.toml."""
    out = tmp_path_factory.mktemp("run")
    rig = load_calibration(default_rig_path())
    cal = Calibration(rig.cameras[:3])
    write_anipose_toml(out / "calibration.toml", cal)
    t = np.arange(FRAMES) / FPS
    rng = np.random.default_rng(11)
    base = np.array([0.0, 5.0, 0.5]) + rng.normal(0, 0.15, (len(MARKERS), 3))
    truth = base[None] + np.stack([np.sin(2 * t), 0.5 * np.cos(3 * t), 0.1 * np.sin(5 * t)], -1)[:, None]
    np.save(out / "truth.npy", truth)
    for c, cam in enumerate(cal.cameras):
        uv = cam.project(truth) + rng.normal(0, 1.0, (FRAMES, len(MARKERS), 2))
        lik = rng.uniform(0.8, 1.0, (FRAMES, len(MARKERS)))
        uv[5, 2] = np.nan  # one detection missing
        lik[5, 2] = 0.0
        write_dlc_csv(out / f"cam{c + 1}.csv", Keypoints(bodyparts=MARKERS, xy=uv, likelihood=lik,
                                                        scorer="DLC_resnet50_testJan1shuffle1_1000"))
    return out


def cams(run_dir: Path) -> list[Path]:
    return [run_dir / f"cam{i}.csv" for i in (1, 2, 3)]


def solve_args(run_dir: Path, tmp_path: Path, files=None, calibration=None) -> list:
    return ["solve", *(files or cams(run_dir)), "--calibration", calibration or run_dir / "calibration.toml",
            "--method", "tri", "--skeleton", "points", "--fps", FPS, "--out", tmp_path / "out.csv"]


# ------------------------------------------------------------------------------- bad inputs


def test_missing_keypoint_file(run_dir, tmp_path):
    files = cams(run_dir)
    files[1] = tmp_path / "cam2_missing.csv"
    assert_user_error(run_cli(*solve_args(run_dir, tmp_path, files)), "cam2_missing.csv", "no such file")


def test_missing_calibration_file(run_dir, tmp_path):
    proc = run_cli(*solve_args(run_dir, tmp_path, calibration=tmp_path / "nocal.toml"))
    assert_user_error(proc, "nocal.toml", "no such file")


@pytest.mark.parametrize("name,content,fragment", [
    ("truncated.csv", None, "truncated"),
    ("nonsense.csv", "hello,world\n1,2,3\n", "not a DeepLabCut CSV"),
    ("empty.csv", "", "file is empty"),
    ("words.csv", "\x00\x01\x02 binary junk \xff", "not a DeepLabCut CSV"),
])
def test_bad_keypoint_files(run_dir, tmp_path, name, content, fragment):
    path = tmp_path / name
    if content is None:  # a real file cut off in the middle of a row
        text = (run_dir / "cam2.csv").read_text()
        path.write_text(text[: len(text) // 2])
    else:
        path.write_text(content)
    files = cams(run_dir)
    files[1] = path
    assert_user_error(run_cli(*solve_args(run_dir, tmp_path, files)), name, fragment)


def test_calibration_without_camera_matrix(run_dir, tmp_path):
    text = (run_dir / "calibration.toml").read_text()
    lines = [ln for ln in text.splitlines() if not ln.startswith("matrix")]
    bad = tmp_path / "no_matrix.toml"
    bad.write_text("\n".join(lines) + "\n")
    assert_user_error(run_cli(*solve_args(run_dir, tmp_path, calibration=bad)), "no_matrix.toml", "missing matrix")


def test_calibration_with_non_rotation(run_dir, tmp_path):
    doc = json.loads(default_rig_path().read_text())
    doc["cameras"] = doc["cameras"][:3]
    doc["cameras"][1]["r"] = [[1.0, 0.2, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
    bad = tmp_path / "sheared.json"
    bad.write_text(json.dumps(doc))
    assert_user_error(run_cli(*solve_args(run_dir, tmp_path, calibration=bad)), "sheared.json",
                      "camera 2 r: not a rotation matrix")


def test_camera_count_mismatch(run_dir, tmp_path):
    proc = run_cli(*solve_args(run_dir, tmp_path, calibration=default_rig_path()))
    assert_user_error(proc, "acinoset_2019_rig.json", "has 6 cameras but 3 keypoint files")


def test_frame_count_mismatch(run_dir, tmp_path):
    kp = read_keypoints(run_dir / "cam3.csv")
    short = tmp_path / "cam3_short.csv"
    write_dlc_csv(short, Keypoints(kp.bodyparts, kp.xy[:-5], kp.likelihood[:-5], kp.scorer))
    files = cams(run_dir)
    files[2] = short
    assert_user_error(run_cli(*solve_args(run_dir, tmp_path, files)), "cam3_short.csv",
                      f"has {FRAMES - 5} frames but cam1.csv has {FRAMES}")


def test_usage_errors_are_one_line(run_dir, tmp_path):
    for args, fragment in [(["solve", *cams(run_dir)], "required: --calibration, --out"),
                           (solve_args(run_dir, tmp_path)[:-2] + ["--method", "magic", "--out", "x.csv"],
                            "invalid choice: 'magic'"),
                           (solve_args(run_dir, tmp_path) + ["--fps", "-3"], "fps must be between"),
                           (solve_args(run_dir, tmp_path) + ["--measurement-std", "loud"],
                            "--measurement-std takes a number of pixels or 'auto'"),
                           (solve_args(run_dir, tmp_path) + ["--measurement-std", "0"],
                            "--measurement-std must be positive"),
                           (["frobnicate"], "invalid choice: 'frobnicate'"),
                           ([], "required: COMMAND")]:
        proc = run_cli(*args)
        lines = proc.stderr.splitlines()
        assert proc.returncode == 2 and len(lines) == 1 and "Traceback" not in proc.stderr, proc.stderr
        assert lines[0].startswith("acinoset: error: ") and fragment in lines[0], lines[0]


def test_output_folder_must_exist(run_dir, tmp_path):
    args = solve_args(run_dir, tmp_path)
    args[-1] = tmp_path / "no" / "such" / "dir" / "out.csv"
    assert_user_error(run_cli(*args), "out.csv", "output folder does not exist")


def test_help_and_version(tmp_path):
    proc = run_cli("--help")
    assert proc.returncode == 0 and "solve" in proc.stdout
    proc = run_cli("solve", "--help")
    assert proc.returncode == 0 and "--calibration" in proc.stdout and "--reprojections" in proc.stdout
    proc = run_cli("--version")
    assert proc.returncode == 0 and proc.stdout.startswith("acinoset ")


def test_registered_subcommands_follow_the_contract():
    """Every registered subcommand sets ``func``; modules that do not exist are skipped."""
    import argparse

    from graph.app.cli import _optional_module, build_parser

    def leaves(parser, path=()):
        """Every runnable command: a parser without subcommands of its own."""
        subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
        if not subs:
            yield path, parser
        for action in subs:
            for name, p in action.choices.items():
                yield from leaves(p, path + (name,))

    parser = build_parser()
    found = dict(leaves(parser))
    assert ("solve",) in found
    for path, p in found.items():
        assert callable(p.get_default("func")), " ".join(path)
    assert _optional_module("graph.no_such_module") is None
    assert _optional_module("no_such_package.cli") is None


# --------------------------------------------------------------------------------- full solves


@pytest.mark.parametrize("method", ["tri", "fte"])
def test_solve_writes_every_output(run_dir, tmp_path, method):
    out, h5, report, reproj = tmp_path / "run.csv", tmp_path / "run.h5", tmp_path / "report.json", tmp_path / "reproj"
    proc = run_cli("solve", *cams(run_dir), "--calibration", run_dir / "calibration.toml", "--method", method,
                   "--skeleton", "points", "--fps", FPS, "--out", out, "--h5", h5, "--report", report,
                   "--reprojections", reproj)
    assert proc.returncode == 0, proc.stderr
    assert "Traceback" not in proc.stderr and "\r" not in proc.stderr  # no progress bar when not a terminal
    truth = np.load(run_dir / "truth.npy")

    table = read_anipose_csv(out)
    assert table.markers == MARKERS and table.positions.shape == truth.shape
    err = np.linalg.norm(table.positions - truth, axis=-1)
    assert np.nanmedian(err) < 0.02, np.nanmedian(err)  # metres; 1 px noise at ~5 m
    assert np.isfinite(table.error).mean() > 0.9 and np.nanmax(table.ncams) == 3

    result = read_result(h5)
    assert result.method == method and result.camera_names == ["cam1", "cam2", "cam3"]
    np.testing.assert_array_equal(result.positions, table.positions)

    rep = json.loads(report.read_text())
    assert rep["method"] == method and rep["frames"] == FRAMES and rep["cameras"] == 3
    assert set(rep["seconds"]) >= {"total", "init", "solve"} and rep["seconds"]["total"] > 0
    assert rep["reprojection_rmse_px"] < 5

    files = sorted(p.name for p in reproj.iterdir())
    assert files == ["cam1_reprojected.csv", "cam2_reprojected.csv", "cam3_reprojected.csv"]
    kp = read_keypoints(reproj / "cam2_reprojected.csv")
    np.testing.assert_allclose(kp.xy, result.reprojections[1], equal_nan=True)


def test_progress_bar_on_a_terminal(run_dir, tmp_path):
    """With stderr on a terminal the solve draws a one-line bar that ends at 100%."""
    import pty

    leader, follower = pty.openpty()
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    proc = subprocess.Popen([sys.executable, "-m", "graph.app.cli", *map(str, solve_args(run_dir, tmp_path))],
                            stdout=subprocess.PIPE, stderr=follower, env=env)
    os.close(follower)
    chunks = []
    while True:
        try:
            data = os.read(leader, 4096)
        except OSError:  # the child closed the terminal
            break
        if not data:
            break
        chunks.append(data)
    proc.wait(timeout=300)
    os.close(leader)
    shown = b"".join(chunks).decode(errors="replace")
    assert proc.returncode == 0, shown
    assert "\r[" in shown and "100%" in shown, shown


def test_solve_reads_dlc_h5_files(run_dir, tmp_path):
    """The H5 files DeepLabCut's analyze_videos writes give the same answer as its CSVs."""
    pd = pytest.importorskip("pandas")
    pytest.importorskip("tables")
    h5s = []
    for src in cams(run_dir):
        kp = read_keypoints(src)
        cols = pd.MultiIndex.from_product([[kp.scorer], kp.bodyparts, ["x", "y", "likelihood"]],
                                          names=["scorer", "bodyparts", "coords"])
        data = np.concatenate([kp.xy, kp.likelihood[..., None]], -1).reshape(kp.frames, -1)
        dst = tmp_path / f"{src.stem}DLC_resnet50.h5"
        pd.DataFrame(data, columns=cols, index=range(kp.frames)).to_hdf(dst, key="df_with_missing",
                                                                        format="table", mode="w")
        h5s.append(dst)
    from_csv, from_h5 = tmp_path / "csv.csv", tmp_path / "h5.csv"
    args = ["--calibration", run_dir / "calibration.toml", "--method", "tri", "--skeleton", "points", "--fps", FPS]
    assert run_cli("solve", *cams(run_dir), *args, "--out", from_csv).returncode == 0
    proc = run_cli("solve", *h5s, *args, "--out", from_h5)
    assert proc.returncode == 0, proc.stderr
    assert from_csv.read_text() == from_h5.read_text()


def test_measured_detection_noise(run_dir, tmp_path):
    """``--measurement-std auto`` measures the 1 px noise of these files; the paper's fixed 5 px gets
    one warning line saying how far off the uncertainties then are."""
    h5, report = tmp_path / "run.h5", tmp_path / "report.json"
    base = ["solve", *cams(run_dir), "--calibration", run_dir / "calibration.toml", "--method", "fte",
            "--skeleton", "points", "--fps", FPS, "--out", tmp_path / "run.csv"]
    proc = run_cli(*base, "--measurement-std", "auto", "--h5", h5, "--report", report)
    assert proc.returncode == 0, proc.stderr
    assert "detection noise" in proc.stdout and "(measured)" in proc.stdout
    rep = json.loads(report.read_text())
    assert 0.8 < rep["sigma_px"] < 1.25 and 0.8 < rep["noise_px"] < 1.25, rep
    result = read_result(h5)
    assert result.options.measurement_std_px == "auto" and result.report.sigma_px == pytest.approx(rep["sigma_px"])
    assert "standard deviations are about" not in proc.stderr

    fixed = run_cli(*base)
    assert fixed.returncode == 0, fixed.stderr
    warned = [line for line in fixed.stderr.splitlines() if "standard deviations are about" in line]
    assert len(warned) == 1 and warned[0].startswith("acinoset: warning: ") and "too large" in warned[0], fixed.stderr


def test_evaluate_loco(run_dir, tmp_path):
    """``acinoset evaluate loco``: each camera predicted from the other two, a table and a JSON."""
    out = tmp_path / "loco.json"
    proc = run_cli("evaluate", "loco", *cams(run_dir), "--calibration", run_dir / "calibration.toml",
                   "--method", "tri", "--skeleton", "points", "--fps", FPS, "--json", out)
    assert proc.returncode == 0, proc.stderr
    assert "leave one camera out" in proc.stdout and "all" in proc.stdout
    assert "judged against: each held-out camera's detections in the files given" in proc.stdout, proc.stdout
    doc = json.loads(out.read_text())
    assert [c["camera"] for c in doc["cameras"]] == load_calibration(run_dir / "calibration.toml").names
    assert doc["options"]["method"] == "tri" and doc["confidence"] == 0.9
    assert 0.3 < doc["median_px"] < 5.0 and doc["p90_px"] > doc["median_px"] and doc["coverage"] > 0.9
    # an ensemble per camera: judged against its members' median, and the output says so
    second = []
    for c, path in enumerate(cams(run_dir)):
        k = read_keypoints(path)
        k.xy = k.xy + np.random.default_rng(c).normal(0, 0.5, k.xy.shape)
        write_dlc_csv(tmp_path / f"cam{c + 1}_b.csv", k)
        second.append(f"{path}+{tmp_path / f'cam{c + 1}_b.csv'}")
    ens = run_cli("evaluate", "loco", *second, "--calibration", run_dir / "calibration.toml", "--method", "tri",
                  "--skeleton", "points", "--fps", FPS)
    assert ens.returncode == 0, ens.stderr
    judged = [line.strip() for line in ens.stdout.splitlines() if line.strip().startswith("judged against:")]
    assert judged == ["judged against: each held-out camera's detections as given; an ensemble's are its members' "
                      "median position with their mean likelihood, not one member's"], ens.stdout
    two = run_cli("evaluate", "loco", *cams(run_dir)[:2], "--calibration", run_dir / "calibration.toml")
    assert_user_error(two, "calibration.toml", "3 cameras but 2 keypoint files")
    proc = run_cli("evaluate", "loco", *cams(run_dir), "--calibration", run_dir / "calibration.toml",
                   "--confidence", "1.5")
    assert proc.returncode == 2 and "--confidence" in proc.stderr and "Traceback" not in proc.stderr


def test_evaluate_loco_versus(run_dir, tmp_path):
    """``--versus "OPTIONS"``: the recording scored again with those options changed, with the
    difference from the first and its interval; a value that names no solve option is one line."""
    out = tmp_path / "loco.json"
    base = ["evaluate", "loco", *cams(run_dir), "--calibration", run_dir / "calibration.toml", "--skeleton", "points",
            "--fps", FPS]
    proc = run_cli(*base, "--versus", "--motion-order 1", "--json", out)
    assert proc.returncode == 0, proc.stderr
    assert "versus --motion-order 1:" in proc.stdout and "minus the first: median" in proc.stdout, proc.stdout
    # the solves' warnings (1 px noise solved as 5 px) name the camera held out, once per solve
    held = [line for line in proc.stderr.splitlines() if " held out: the detections scatter" in line]
    assert len(held) == 6 and held[0].startswith("acinoset: warning: cam1 held out: "), proc.stderr
    doc = json.loads(out.read_text())
    (v,) = doc["versus"]
    assert doc["options"]["motion_order"] == 3 and v["options"]["motion_order"] == 1
    d = v["difference"]
    assert d["median_px"] == pytest.approx(v["median_px"] - doc["median_px"])
    assert d["p90_interval"][0] <= d["p90_px"] <= d["p90_interval"][1] and d["blocks"] * d["block_frames"] >= FRAMES
    for bad in ("--no-such-option 1", "fte"):
        proc = run_cli(*base, "--versus", bad)
        assert proc.returncode == 2 and "--versus" in proc.stderr and "Traceback" not in proc.stderr, proc.stderr
        assert len(proc.stderr.strip().splitlines()) == 1, proc.stderr


def test_solve_motion_scale_auto(run_dir, tmp_path):
    """``--motion-scale auto``: the fitted scales are in the report and said on the summary line;
    a malformed value is one line."""
    report = tmp_path / "report.json"
    proc = run_cli(*solve_args(run_dir, tmp_path)[:-2], "--method", "fte", "--motion-scale", "auto",
                   "--out", tmp_path / "out.csv", "--report", report)
    assert proc.returncode == 0, proc.stderr
    assert "motion scales" in proc.stdout and "(fitted" in proc.stdout
    scales = json.loads(report.read_text())["motion_scales"]
    assert set(scales) == set(MARKERS) and all(v > 0 for v in scales.values())
    bad = run_cli(*solve_args(run_dir, tmp_path), "--motion-scale", "smooth")
    assert bad.returncode == 2 and "--motion-scale" in bad.stderr and len(bad.stderr.splitlines()) == 1


def test_solve_motion_order(run_dir, tmp_path):
    """``--motion-order auto`` (with the scale fitted, the points' default): each marker's order
    is in the report and counted on the summary line; 'auto' with a fixed scale, and an order
    that is not 1, 2, 3 or auto, are one line each."""
    report = tmp_path / "report.json"
    args = solve_args(run_dir, tmp_path)[:-2]
    proc = run_cli(*args, "--method", "fte", "--skeleton", "points", "--motion-order", "auto",
                   "--out", tmp_path / "out.csv", "--report", report)
    assert proc.returncode == 0, proc.stderr
    assert "motion order" in proc.stdout
    orders = json.loads(report.read_text())["motion_orders"]
    assert set(orders) == set(MARKERS) and set(orders.values()) <= {1, 2, 3}
    fixed = run_cli(*args, "--method", "fte", "--skeleton", "points", "--motion-scale", "1", "--motion-order", "auto",
                    "--out", tmp_path / "out2.csv")
    assert fixed.returncode == 2 and "motion_scale 'auto'" in fixed.stderr and len(fixed.stderr.splitlines()) == 1
    bad = run_cli(*args, "--motion-order", "4", "--out", tmp_path / "out3.csv")
    assert bad.returncode == 2 and "--motion-order" in bad.stderr and len(bad.stderr.splitlines()) == 1


def test_solve_with_an_earlier_runs_smoothing(run_dir, tmp_path):
    """``--motion-scale REPORT`` (a report JSON or result H5 of a run that fitted the smoothing): its
    scales and orders, not fitted again; an order that disagrees, and a report without scales, are
    one line each."""
    args = [*solve_args(run_dir, tmp_path)[:-2], "--method", "fte", "--skeleton", "points"]
    report, h5 = tmp_path / "fitted.json", tmp_path / "fitted.h5"
    proc = run_cli(*args, "--motion-order", "1", "--out", tmp_path / "a.csv", "--report", report, "--h5", h5)
    assert proc.returncode == 0, proc.stderr
    fitted = json.loads(report.read_text())
    assert set(fitted["motion_orders"].values()) == {1}
    for source in (report, h5):
        again = tmp_path / f"again_{source.suffix[1:]}.json"
        proc = run_cli(*args, "--motion-scale", source, "--out", tmp_path / "b.csv", "--report", again, "--h5",
                       tmp_path / "b.h5")
        assert proc.returncode == 0, proc.stderr
        assert "(fitted" not in proc.stdout and json.loads(again.read_text())["motion_scales"] is None
        opts = read_result(tmp_path / "b.h5").options
        assert opts.motion_scale == fitted["motion_scales"] and opts.motion_order == fitted["motion_orders"]
    clash = run_cli(*args, "--motion-scale", report, "--motion-order", "3", "--out", tmp_path / "c.csv")
    assert_user_error(clash, "fitted.json", "fitted for motion order(s) 1: give no motion order with it")
    none = tmp_path / "none.json"
    none.write_text(json.dumps({"method": "fte"}))
    proc = run_cli(*args, "--motion-scale", none, "--out", tmp_path / "d.csv")
    assert_user_error(proc, "none.json", "holds no motion_scales")


def test_solve_an_ensemble_per_camera(run_dir, tmp_path):
    """``CAM_a.csv+CAM_b.csv``: an ensemble of two models per camera, combined; the report gives each
    camera's relative noise, and a missing member is named."""
    groups = []
    for i, path in enumerate(cams(run_dir), start=1):
        k = read_keypoints(path)
        second = tmp_path / f"cam{i}_b.csv"
        shaken = k.xy + np.random.default_rng(i).normal(0.0, 0.5 * i, k.xy.shape)
        write_dlc_csv(second, Keypoints(bodyparts=k.bodyparts, xy=shaken, likelihood=k.likelihood, scorer=k.scorer))
        groups.append(f"{path}+{second}")
    report = tmp_path / "report.json"
    proc = run_cli("solve", *groups, "--calibration", run_dir / "calibration.toml", "--skeleton", "points",
                   "--fps", FPS, "--out", tmp_path / "out.csv", "--report", report, "--reprojections", tmp_path / "rep")
    assert proc.returncode == 0, proc.stderr
    rel = json.loads(report.read_text())["relative_noise"]
    assert list(rel.values()) == sorted(rel.values())  # camera 3's second member was shaken most
    assert (tmp_path / "rep" / "cam1_reprojected.csv").exists()
    proc = run_cli("solve", f"{cams(run_dir)[0]}+{tmp_path / 'nope.csv'}", *cams(run_dir)[1:], "--calibration",
                   run_dir / "calibration.toml", "--out", tmp_path / "out.csv")
    assert_user_error(proc, "nope.csv")


def test_a_ctrl_c_numba_wrapped_reads_as_interrupted():
    """A Ctrl-C that lands inside a compiled kernel's first call (numba unpickling its constants)
    surfaces as numba's dispatcher reports it, seen on a served solve: SystemError ('returned a
    result with an exception set') caused by SystemError caused by the KeyboardInterrupt. The
    command reads that as Ctrl-C ('interrupted', 130), and any other SystemError as what it is."""
    from graph.app.cli import _caused_by_ctrl_c

    def raised(*chain: BaseException) -> BaseException:
        try:
            try:
                try:
                    raise chain[0]
                except BaseException as first:
                    raise chain[1] from first
            except BaseException as second:
                raise chain[2] from second
        except BaseException as last:
            return last

    numba = raised(KeyboardInterrupt(), SystemError("<function _numba_unpickle> returned a result with an "
                                                    "exception set"),
                   SystemError("CPUDispatcher(<function triangulate_points>) returned a result with an exception set"))
    assert isinstance(numba, SystemError) and _caused_by_ctrl_c(numba)
    other = raised(ValueError("bad"), SystemError("x"), SystemError("y"))
    assert not _caused_by_ctrl_c(other)
    assert not _caused_by_ctrl_c(SystemError("plain"))


def test_the_csv_in_the_calibrations_units(run_dir, tmp_path):
    """``--units auto`` writes the CSV in the calibration's units (a rig measured in millimetres gives
    millimetres, as ``anipose triangulate`` writes it), ``--units mm`` in millimetres from any rig; the
    H5 stays in metres."""
    import dataclasses

    rig = load_calibration(run_dir / "calibration.toml")
    in_mm = Calibration([dataclasses.replace(c, t=1000 * c.t) for c in rig.cameras])
    write_anipose_toml(tmp_path / "mm.toml", in_mm)
    common = ("--method", "tri", "--skeleton", "points", "--fps", FPS)
    metres = run_cli("solve", *cams(run_dir), "--calibration", run_dir / "calibration.toml", *common,
                     "--out", tmp_path / "m.csv")
    auto = run_cli("solve", *cams(run_dir), "--calibration", tmp_path / "mm.toml", *common, "--units", "auto",
                   "--out", tmp_path / "auto.csv", "--h5", tmp_path / "auto.h5")
    mm = run_cli("solve", *cams(run_dir), "--calibration", run_dir / "calibration.toml", *common, "--units", "mm",
                 "--out", tmp_path / "mm.csv")
    for p in (metres, auto, mm):
        assert p.returncode == 0, p.stderr
    assert "auto.csv (in mm)" in auto.stdout and "(in " not in metres.stdout
    m = read_anipose_csv(tmp_path / "m.csv").positions
    np.testing.assert_allclose(read_anipose_csv(tmp_path / "auto.csv").positions, 1000 * m, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(read_anipose_csv(tmp_path / "mm.csv").positions, 1000 * m, rtol=1e-9)
    np.testing.assert_allclose(read_result(tmp_path / "auto.h5").positions, m, rtol=1e-6, atol=1e-9)
