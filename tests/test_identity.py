"""Several animals at once: each camera's 2D slots assigned to 3D individuals by geometry and motion,
however the 2D tracker swapped them, and ``acinoset solve`` on multi-animal DeepLabCut files (written
by pandas as DeepLabCut writes them), SLEAP files with several tracks (written by sleap-io) and
OpenPose folders of several people."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from group_files import write_dlc_multi

from graph.errors import InputError
from graph.io.calibration import write_anipose_toml
from graph.io.keypoint_types import Tracks
from graph.io.results import read_anipose_csv, read_individuals, read_result
from graph.metrics import group_error
from graph.simulate import ring_rig
from graph.simulate_group import simulate_group
from graph.solve.identity import assign, count_individuals
from graph.solve.triangulate import robust_points

RIG = ring_rig(4)


def triangulated(keypoints: list, threshold: float = 0.5) -> np.ndarray:
    """(N, M, 3) robust triangulation of one individual's detections per camera."""
    meas = np.stack([k.xy for k in keypoints], axis=1)
    valid = np.stack([k.likelihood >= threshold for k in keypoints], axis=1)
    return robust_points(RIG, meas, valid)[0]


@pytest.mark.parametrize("animals,seed", [(2, 0), (2, 1), (3, 0), (3, 2)])
def test_swapped_2d_identities_do_not_swap_the_3d_animals(animals, seed):
    run = simulate_group(RIG, animals=animals, frames=1500, seed=seed)
    true_swaps = [int((np.diff(o, axis=0) != 0).any(axis=1).sum()) for o in run.owner]
    assert min(true_swaps) >= 15  # the tracker swapped in every camera
    ids = assign(run.tracks, RIG)
    assert ids.found and len(ids.names) == animals
    assert ids.names == [f"animal{k + 1}" for k in range(animals)]  # the names the 2D slots carried most
    ours = group_error(np.stack([triangulated(k) for k in ids.keypoints]), run.positions, run.markers)
    assert ours.switches == 0 and sorted(ours.match) == list(range(animals))
    oracle = group_error(np.stack([triangulated([t.slot(a) for t in run.true_tracks()]) for a in range(animals)]),
                         run.positions, run.markers)
    for i, e in enumerate(ours.errors):  # against the oracle's error of the same animal
        o = oracle.errors[oracle.match.index(ours.match[i])]
        assert e.mean_mm <= 1.05 * o.mean_mm + 0.1 and e.coverage >= 0.97 * o.coverage
    as_given = group_error(np.stack([triangulated([t.slot(k) for t in run.tracks]) for k in range(animals)]),
                           run.positions, run.markers)
    assert as_given.switches_per_10k > 300 and min(e.mean_mm for e in as_given.errors) > 10 * max(
        e.mean_mm for e in ours.errors)
    # every true 2D swap seen is corrected once; a swap next to a missing detection may count twice
    for c in range(len(RIG)):
        assert 0.9 * true_swaps[c] <= ids.switches[c] <= 1.4 * true_swaps[c] + 2


def _with_ghosts(run, seed: int) -> list[Tracks]:
    """A third slot in every camera holding, in 5 % of frames, a confident ghost: another animal's
    detections thrown 300 px (a reflection, a bystander)."""
    rng = np.random.default_rng(seed)
    out = []
    for t in run.tracks:
        N, _, M, _ = t.xy.shape
        xy = np.concatenate([t.xy, np.full((N, 1, M, 2), np.nan)], axis=1)
        lik = np.concatenate([t.likelihood, np.zeros((N, 1, M))], axis=1)
        hit = rng.random(N) < 0.05
        xy[hit, -1] = (t.xy[:, 0] + rng.normal(0, 300, (N, 1, 2)))[hit]
        lik[hit, -1] = 0.9
        out.append(Tracks(bodyparts=t.bodyparts, names=[*t.names, "ghost"], xy=xy, likelihood=lik))
    return out


def _one_gone(run, first: int, last: int) -> list[Tracks]:
    """Animal 0 out of every camera's view for frames ``first .. last - 1`` (its truth NaN there)."""
    out = []
    rows = np.arange(first, last)
    for c, t in enumerate(run.tracks):
        xy, lik = t.xy.copy(), t.likelihood.copy()
        k = np.argmax(run.owner[c, rows] == 0, axis=1)  # the slot holding animal 0 in each frame
        xy[rows, k], lik[rows, k] = np.nan, 0.0
        out.append(Tracks(bodyparts=t.bodyparts, names=list(t.names), xy=xy, likelihood=lik))
    run.positions[first:last, 0] = np.nan
    return out


@pytest.mark.parametrize("case,seed", [("five animals", 0), ("five animals", 1), ("ghosts", 0), ("ghosts", 1),
                                       ("one out of view 200 frames", 3)])
def test_harder_groups(case, seed):
    """More animals, ghost detections that no other camera confirms, an animal that leaves every view
    and comes back: no 3D switch, the count found, every animal about as well as the swap-free cases."""
    animals = 5 if case == "five animals" else 2 if case == "ghosts" else 3
    run = simulate_group(RIG, animals=animals, frames=1000, seed=seed)
    tracks = (_with_ghosts(run, seed) if case == "ghosts" else _one_gone(run, 300, 500) if case.startswith("one")
              else run.tracks)
    ids = assign(tracks, RIG)
    assert len(ids.names) == animals
    g = group_error(np.stack([triangulated(k) for k in ids.keypoints]), run.positions, run.markers)
    assert g.switches == 0 and sorted(g.match) == list(range(animals))
    assert max(e.mean_mm for e in g.errors) < 10


def test_people_in_no_order_are_tracked_as_well():
    """OpenPose gives no identities: the slots are shuffled in every frame and the answer is the same."""
    run = simulate_group(RIG, animals=3, frames=800, seed=4)
    rng = np.random.default_rng(0)
    shuffled = []
    for t in run.true_tracks():
        order = np.argsort(rng.random(t.xy.shape[:2]), axis=1)
        rows = np.arange(t.frames)[:, None]
        shuffled.append(Tracks(bodyparts=t.bodyparts, names=["person1", "person2", "person3"], xy=t.xy[rows, order],
                               likelihood=t.likelihood[rows, order], identified=False))
    ids = assign(shuffled, RIG)
    assert ids.names == ["individual1", "individual2", "individual3"] and ids.switches == [0, 0, 0, 0]
    ours = group_error(np.stack([triangulated(k) for k in ids.keypoints]), run.positions, run.markers)
    assert ours.switches == 0 and max(e.mean_mm for e in ours.errors) < 10


def test_the_count_is_found_or_given():
    run = simulate_group(RIG, animals=3, frames=300, seed=5)
    assert count_individuals(run.tracks, 0.5) == 3
    two = assign(run.tracks, RIG, individuals=2)
    assert not two.found and len(two.names) == 2
    four = assign(run.tracks, RIG, individuals=4)
    assert len(four.names) == 4 and any("never seen" in n for n in four.notes)


# ------------------------------------------------------------------------------------ the command line


def run_cli(*args, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "graph.app.cli", *map(str, args)], capture_output=True, text=True,
                          timeout=600, cwd=cwd)


@pytest.fixture(scope="module")
def pair(tmp_path_factory):
    folder = tmp_path_factory.mktemp("pair")
    run = simulate_group(RIG, animals=2, frames=400, seed=6)
    write_anipose_toml(folder / "calibration.toml", RIG)
    names = ["dam", "../../cub"]  # a name from an upload must not leave the output folder
    files = [write_dlc_multi(folder / f"cam{c + 1}.csv", t, names) for c, t in enumerate(run.tracks)]
    return folder, run, files


def test_solve_writes_each_individual_and_the_identities(pair):
    folder, run, files = pair
    out = folder / "out"
    out.mkdir()
    p = run_cli("solve", *files, "--calibration", folder / "calibration.toml", "--fps", "60", "--skeleton", "points",
                "--out", out / "run.csv", "--report", out / "run.json", "--h5", out / "run.h5", cwd=folder)
    assert p.returncode == 0, p.stderr
    assert "Traceback" not in p.stderr
    assert sorted(x.name for x in out.iterdir()) == ["run.cub.csv", "run.dam.csv", "run.h5", "run.json"]
    assert "2 individuals (found: ../../cub, dam)" in p.stdout
    est = np.stack([read_anipose_csv(out / f"run.{n}.csv").positions for n in ("cub", "dam")])
    # the H5 has an individuals axis: the names, then every array stacked along it
    import h5py

    assert read_individuals(out / "run.h5") == ["../../cub", "dam"]
    with h5py.File(out / "run.h5", "r") as f:
        assert f["positions"].shape == (2, 400, len(run.markers), 3)
        assert f["reprojections"].shape[:2] == (2, 4)
        np.testing.assert_allclose(f["positions"][()], est, rtol=0, atol=1e-9)  # the CSVs are in metres
        assert json.loads(f.attrs["identity"])["individuals"] == ["../../cub", "dam"]
    assert read_result(out / "run.h5", individual="dam").report.frames == 400
    with pytest.raises(InputError, match=r"run\.h5: holds 2 individuals \(\.\./\.\./cub, dam\): name one"):
        read_result(out / "run.h5")
    with pytest.raises(InputError, match="holds no individual 'calf'"):
        read_result(out / "run.h5", individual="calf")
    g = group_error(est, run.positions, run.markers)
    assert g.switches == 0 and max(e.mean_mm for e in g.errors) < 8
    report = json.loads((out / "run.json").read_text())
    assert report["identity"]["individuals"] == ["../../cub", "dam"] and report["identity"]["count"] == "found"
    assert set(report["identity"]["switches_corrected"]) == {"cam1", "cam2", "cam3", "cam4"}
    assert min(report["identity"]["switches_corrected"].values()) >= 1
    assert set(report["individuals"]) == {"../../cub", "dam"}
    assert all(r["method"] == "fte" and r["frames"] == 400 for r in report["individuals"].values())


def test_one_individual_by_name_trusts_the_2d_identities(pair):
    folder, _, files = pair
    out = folder / "one"
    out.mkdir()
    p = run_cli("solve", *files, "--calibration", folder / "calibration.toml", "--fps", "60", "--skeleton", "points",
                "--method", "tri", "--individual", "dam", "--out", out / "run.csv", cwd=folder)
    assert p.returncode == 0, p.stderr
    assert sorted(x.name for x in out.iterdir()) == ["run.csv"]


def test_a_count_and_a_name_together_are_refused(pair):
    folder, _, files = pair
    p = run_cli("solve", *files, "--calibration", folder / "calibration.toml", "--fps", "60", "--individual", "dam",
                "--individuals", "2", "--out", folder / "x.csv", cwd=folder)
    assert p.returncode == 2 and p.stderr.count("\n") == 1 and "give one of them" in p.stderr


def test_sleap_files_with_two_tracks(tmp_path):
    """Two tracked mice per camera in .slp files that sleap-io writes; its tracks swap in each camera."""
    sio = pytest.importorskip("sleap_io")
    run = simulate_group(RIG, animals=2, frames=200, seed=7)
    skeleton = sio.Skeleton(list(run.markers))
    files = []
    for c, t in enumerate(run.tracks):
        tracks = [sio.Track(n) for n in ("mouse a", "mouse b")]
        video = sio.Video(filename=f"cam{c}.mp4", open_backend=False)
        frames = []
        for n in range(t.frames):
            inst = [sio.PredictedInstance.from_numpy(points_data=t.xy[n, k], point_scores=t.likelihood[n, k], score=1.0,
                                                     skeleton=skeleton, track=tracks[k])
                    for k in range(2) if np.isfinite(t.xy[n, k]).any()]
            frames.append(sio.LabeledFrame(video=video, frame_idx=n, instances=inst))
        path = tmp_path / f"cam{c + 1}.slp"
        sio.save_slp(sio.Labels(labeled_frames=frames, videos=[video], skeletons=[skeleton], tracks=tracks), str(path))
        files.append(path)
    write_anipose_toml(tmp_path / "calibration.toml", RIG)
    p = run_cli("solve", *files, "--calibration", tmp_path / "calibration.toml", "--fps", "60", "--skeleton", "points",
                "--method", "tri", "--out", tmp_path / "run.csv", cwd=tmp_path)
    assert p.returncode == 0, p.stderr
    est = np.stack([read_anipose_csv(tmp_path / f"run.mouse_{x}.csv").positions for x in "ab"])
    g = group_error(est, run.positions, run.markers)
    assert g.switches == 0 and max(e.median_mm for e in g.errors) < 8


def test_openpose_folders_of_two_people(tmp_path):
    """OpenPose's JSON files, two people a frame in no fixed order (as OpenPose writes them)."""
    run = simulate_group(RIG, animals=2, frames=150, seed=8)
    rng = np.random.default_rng(1)
    folders = []
    for c, t in enumerate(run.true_tracks()):
        folder = tmp_path / f"cam{c + 1}_json"
        folder.mkdir()
        for n in range(t.frames):
            people = []
            for k in rng.permutation(2):
                found = np.isfinite(t.xy[n, k]).all(-1)
                flat = np.where(found[:, None], np.column_stack([np.nan_to_num(t.xy[n, k]), t.likelihood[n, k]]), 0.0)
                if found.any():
                    people.append({"person_id": [-1], "pose_keypoints_2d": flat.ravel().tolist()})
            (folder / f"cam{c + 1}_{n:012d}_keypoints.json").write_text(json.dumps({"version": 1.3, "people": people}))
        folders.append(folder)
    write_anipose_toml(tmp_path / "calibration.toml", RIG)
    p = run_cli("solve", *folders, "--calibration", tmp_path / "calibration.toml", "--fps", "60", "--skeleton",
                "points", "--method", "tri", "--out", tmp_path / "run.csv", cwd=tmp_path)
    assert p.returncode == 0, p.stderr
    assert "2 individuals (found: individual1, individual2)" in p.stdout
    est = np.stack([read_anipose_csv(tmp_path / f"run.individual{i}.csv").positions for i in (1, 2)])
    g = group_error(est, run.positions, run.markers)
    assert g.switches == 0 and max(e.median_mm for e in g.errors) < 8


@pytest.fixture(scope="module")
def solved_pair(pair):
    """The pair solved once by tri with --h5: the folder holding run.<name>.csv and run.h5 (both)."""
    folder, _, files = pair
    out = folder / "solved"
    out.mkdir()
    p = run_cli("solve", *files, "--calibration", folder / "calibration.toml", "--fps", "60", "--skeleton", "points",
                "--method", "tri", "--out", out / "run.csv", "--h5", out / "run.h5", cwd=folder)
    assert p.returncode == 0, p.stderr
    return out


def test_each_individual_exports_to_nwb_as_movement_reads_a_group(pair, solved_pair):
    """Each individual of the H5 exports to its own NWB, one subject (NWB holds one a file) identified
    by the name, so movement's loader names the individual and merging the files gives the group.
    Without a name the export is refused in one line."""
    pytest.importorskip("ndx_pose")
    load_poses = pytest.importorskip("movement.io.load_poses")
    import xarray as xr

    folder, run, files = pair
    out = solved_pair
    e = run_cli("export", out / "run.h5", "--format", "nwb", "--out", out / "x.nwb", cwd=folder)
    assert e.returncode != 0 and "holds 2 individuals" in e.stderr and e.stderr.count("\n") == 1, e.stderr
    sets = []
    for name in ("dam", "cub"):
        e = run_cli("export", out / "run.h5", "--individual", "dam" if name == "dam" else "../../cub",
                    "--format", "nwb", "--out", out / f"{name}.nwb", cwd=folder)
        assert e.returncode == 0, e.stderr
        sets.append(load_poses.from_nwb_file(out / f"{name}.nwb"))
    group = xr.merge(sets, join="outer", compat="no_conflicts")
    assert list(group.individuals.values) == sorted(["dam", "../../cub"])
    for name in ("dam", "cub"):
        table = read_anipose_csv(out / f"run.{name}.csv")
        csv = table.positions  # (N, M, 3)
        ind = "dam" if name == "dam" else "../../cub"
        got = group.position.sel(individuals=ind, keypoints=table.markers)
        got = got.transpose("time", "keypoints", "space").values
        np.testing.assert_allclose(got, csv, rtol=1e-9, atol=1e-12)


def test_plot_of_several_individuals(pair, solved_pair):
    """`acinoset plot` of the H5 of several individuals: each one's figures in a folder of its name,
    and one offline playback of them all (its payload naming each one's markers)."""
    import re

    folder, _, files = pair
    out = solved_pair
    p = run_cli("plot", out / "run.h5", "--out", out / "figs", "--snapshots", "1", cwd=folder)
    assert p.returncode == 0, p.stderr
    assert any((out / "figs" / "dam").glob("*.png")) and any((out / "figs" / "cub").glob("*.png"))
    page = (out / "figs" / "playback.html").read_text(encoding="utf-8")
    payload = json.loads(re.search(r'<script type="application/json" id="payload">(.*?)</script>', page, re.S)[1])
    assert [i["name"] for i in payload["individuals"]] == ["../../cub", "dam"]
    assert [i["markers"] for i in payload["individuals"]] == [[0, 12], [12, 12]]
    assert "../../cub, dam" in page.split("<title>")[1].split("</title>")[0]
    p = run_cli("plot", out / "run.h5", "--out", out / "x", "--frame", "1", "--camera", "1",
                "--video", out / "run.csv", cwd=folder)
    assert p.returncode == 2 and "give one RESULT.h5" in p.stderr and p.stderr.count("\n") == 1


def test_a_file_naming_individuals_its_arrays_do_not_hold_is_refused(solved_pair, tmp_path):
    """A result file whose ``individuals`` dataset names more individuals than its arrays hold (a
    one-animal file with the dataset added) is refused in one line, not read frame by frame as if
    each frame were an individual."""
    import h5py

    from graph.io.results import read_results, write_h5

    one = read_result(solved_pair / "run.h5", individual="dam")
    path = tmp_path / "forged.h5"
    write_h5(path, one)
    with h5py.File(path, "a") as f:
        f.create_dataset("individuals", data=np.array(["dam", "cub"], dtype=object), dtype=h5py.string_dtype("utf-8"))
    with pytest.raises(InputError, match=r"forged\.h5: damaged acinoset result file \(names 2 individuals"):
        read_results(path)
