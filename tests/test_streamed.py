"""A long run solved streamed (``acinoset solve`` over :data:`graph.types.WINDOWED_ABOVE` frames, or
with ``--window-frames``): each camera's file staged on disk, a window read at a time, its frames
written as it finishes. The answer is the one the run held whole in memory gets from the same windows,
to the bit; the staged copy is gone afterwards."""

import json
import os
import signal
import subprocess
import sys
import time
import warnings
from pathlib import Path

import h5py
import numpy as np
import pytest
from group_files import write_dlc_multi
from servers import children

from graph.api import solve
from graph.errors import InputError
from graph.io.calibration import load_calibration
from graph.io.keypoints import read_blocks, read_keypoints
from graph.io.results import H5Stream, read_result, write_anipose_csv, write_h5
from graph.io.staged import StagedRun, stage, stage_camera
from graph.simulate import ring_rig, simulate_run, write_run
from graph.simulate_group import simulate_group
from graph.solve import problem, windows
from graph.types import FRAME_AXIS, SolveOptions

FRAMES = 3000
CORE = 500


@pytest.fixture(scope="module")
def long_run(rig, tmp_path_factory):
    """A cheetah walking its figure of eight for 25 s at 120 fps (seed 7 turns a full circle across
    the seam at frame 500), written as a user brings it."""
    run = simulate_run(rig, frames=FRAMES, fps=120, seed=7, speed=1.0)
    d = tmp_path_factory.mktemp("long")
    write_run(run, d)
    return run, d


def _cams(rig, d) -> list[str]:
    return [str(d / f"{n}.csv") for n in rig.names]


@pytest.fixture(scope="module")
def in_memory(rig, long_run):
    """The same files read whole and solved in the same windows by :func:`graph.api.solve`."""
    _, d = long_run
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return solve([read_keypoints(p) for p in _cams(rig, d)], load_calibration(d / "calibration.toml"),
                     SolveOptions(fps=120, window_frames=CORE))


def test_the_command_streams_the_same_answer_as_the_run_in_memory(rig, long_run, in_memory, tmp_path):
    _, d = long_run
    out = tmp_path / "run.csv"
    cmd = [sys.executable, "-m", "graph.app.cli", "solve", *_cams(rig, d), "--calibration", str(d / "calibration.toml"),
           "--fps", "120", "--window-frames", str(CORE), "--out", str(out), "--h5", str(tmp_path / "run.h5"),
           "--report", str(tmp_path / "report.json")]
    done = subprocess.run(cmd, capture_output=True, text=True, env={**os.environ, "ACINOSET_RESIDENT": "0"})
    assert done.returncode == 0, done.stderr
    assert f"{FRAMES} frames" in done.stdout

    write_anipose_csv(tmp_path / "memory.csv", in_memory)
    assert out.read_bytes() == (tmp_path / "memory.csv").read_bytes()

    streamed = read_result(tmp_path / "run.h5")
    for name in FRAME_AXIS:
        a, b = getattr(in_memory, name), getattr(streamed, name)
        assert (a is None) == (b is None), name
        if a is not None:
            assert a.shape == b.shape and np.array_equal(a, b, equal_nan=True), name
    with h5py.File(tmp_path / "run.h5") as f:
        assert f["positions"].chunks[0] <= 1024  # written a stretch of frames at a time

    report = json.loads((tmp_path / "report.json").read_text())
    whole = in_memory.report.to_dict()
    assert set(report) == set(whole)
    for key in whole:  # the RMSE's squares summed a window at a time: to the last digit or so
        if isinstance(whole[key], float):
            assert report[key] == pytest.approx(whole[key], rel=1e-12), key
        elif key != "seconds":
            assert report[key] == whole[key], key
    assert report["windows"]["count"] == FRAMES // CORE
    assert not list(tmp_path.glob(".acinoset-staged-*")), "the staged copy was left behind"


def test_ekf_streams_the_same_answer_as_its_windows_in_memory(rig, long_run, tmp_path):
    """``acinoset solve --method ekf`` on a long run streams it in windows, as fte: the CSV is the
    in-memory windowed ekf's byte for byte, and the report says ekf and its windows."""
    _, d = long_run
    out = tmp_path / "ekf.csv"
    cmd = [sys.executable, "-m", "graph.app.cli", "solve", *_cams(rig, d), "--calibration", str(d / "calibration.toml"),
           "--fps", "120", "--method", "ekf", "--window-frames", str(CORE), "--out", str(out),
           "--report", str(tmp_path / "report.json")]
    done = subprocess.run(cmd, capture_output=True, text=True, env={**os.environ, "ACINOSET_RESIDENT": "0"})
    assert done.returncode == 0, done.stderr
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        memory = solve([read_keypoints(p) for p in _cams(rig, d)], load_calibration(d / "calibration.toml"),
                       SolveOptions(fps=120, method="ekf", window_frames=CORE))
    write_anipose_csv(tmp_path / "memory.csv", memory)
    assert out.read_bytes() == (tmp_path / "memory.csv").read_bytes()
    report = json.loads((tmp_path / "report.json").read_text())
    assert report["method"] == "ekf" == memory.report.method and report["windows"]["count"] == FRAMES // CORE


@pytest.mark.parametrize("step", [3, 7])
def test_an_overview_written_as_the_windows_finish_is_every_kth_frame_of_the_whole(in_memory, step, tmp_path):
    """The job page's view of a long run is kept as the windows finish (stretches of uneven lengths,
    whose first kept frame moves): it is ``read_result(whole, step=k)`` array for array."""
    write_h5(tmp_path / "whole.h5", in_memory)
    stream = H5Stream(tmp_path / "view.h5", FRAMES, step=step)
    cuts = [0, 1, 499, 500, 1234, 2999, FRAMES]
    for a, b in zip(cuts, cuts[1:]):
        stream.write(in_memory.frames(a, b))
    stream.close(in_memory.report, in_memory.options)
    every, kept = read_result(tmp_path / "whole.h5", step=step), read_result(tmp_path / "view.h5")
    assert kept.positions.shape[0] == -(-FRAMES // step)
    for name in FRAME_AXIS:
        a, b = getattr(every, name), getattr(kept, name)
        assert (a is None) == (b is None), name
        if a is not None:
            assert a.shape == b.shape and np.array_equal(a, b, equal_nan=True), name
    assert kept.report.to_dict() == every.report.to_dict()


def test_angles_stay_on_one_turn_across_the_seams(in_memory):
    """Each window starts its yaw from the heading, within (-pi, pi]: without carrying the previous
    core's turn, the stitched angles jumped by 2 pi at a seam (and their rates by 2 pi fps)."""
    angles = problem.skeleton_of([], SolveOptions()).angle_params
    step = np.abs(np.diff(in_memory.params[:, angles], axis=0))
    assert step.max() < 1.0, f"a step of {step.max():.2f} rad at frame {np.unravel_index(step.argmax(), step.shape)[0]}"
    assert np.abs(in_memory.rates[:, angles]).max() < 120.0


def test_a_staged_run_reads_back_the_frames_asked_for(rig, long_run, tmp_path):
    run, _ = long_run
    staged = StagedRun(tmp_path)
    for kp in run.keypoints:
        staged.add(kp)
    got = staged.keypoints(1234, 1300)
    for kp, k in zip(got, run.keypoints):
        assert np.array_equal(kp.xy, k.xy[1234:1300], equal_nan=True)
        assert np.array_equal(kp.likelihood, k.likelihood[1234:1300])
        assert kp.bodyparts == k.bodyparts
    assert staged.keypoints(FRAMES - 10, FRAMES + 50)[0].frames == 10
    source = windows.Staged(staged, rig, SolveOptions(fps=120))
    whole = problem.build(run.keypoints, rig, SolveOptions(fps=120))
    assert np.array_equal(source.seen(), whole.valid.sum(axis=(1, 2)))


def test_cameras_staged_one_by_one_are_the_run_staged_in_turn(rig, long_run, tmp_path):
    """Workers that share a data dir stage a run's cameras between them, each camera once, and put
    them together: the same arrays and index as one process staging them in turn; a camera with
    other frames is named as one process names it; a file of several animals stages no run."""
    _, d = long_run
    paths = _cams(rig, d)
    whole = stage(paths, tmp_path / "whole", read_blocks, lambda frames: True)
    assert whole is not None
    folder = tmp_path / "together"
    with pytest.raises(FileNotFoundError):  # a folder removed (its job ended) is not made again
        stage_camera(paths[0], folder, 0, read_blocks)
    folder.mkdir()
    assert StagedRun(folder).unstaged(len(paths)) == list(range(len(paths)))
    for c in reversed(range(len(paths))):  # in any order, one twice (a camera taken over)
        stage_camera(paths[c], folder, c, read_blocks)
    stage_camera(paths[2], folder, 2, read_blocks)
    assert StagedRun(folder).unstaged(len(paths)) == [] and not list(folder.glob(".*"))
    together = StagedRun.gather(folder, len(paths))
    assert together is not None and together.frames == whole.frames == FRAMES
    assert together.cameras == whole.cameras
    for a, b in zip(together.keypoints(0, FRAMES), whole.keypoints(0, FRAMES)):
        assert np.array_equal(a.xy, b.xy, equal_nan=True) and np.array_equal(a.likelihood, b.likelihood)

    short = tmp_path / "short.csv"
    short.write_text("".join(Path(paths[1]).read_text().splitlines(keepends=True)[:-5]))
    stage_camera(str(short), folder, 1, read_blocks)
    with pytest.raises(InputError, match=r"has 2995 frames but .*\.csv has 3000; all cameras must have the same"):
        StagedRun.gather(folder, len(paths))

    stage_camera(paths[1], folder, 1, read_blocks)
    cut = folder / "3.xy"  # a camera's arrays cut short
    cut.write_bytes(cut.read_bytes()[:-16])
    with pytest.raises(ValueError, match="camera 4's xy is not whole"):
        StagedRun.gather(folder, len(paths))
    (folder / "3.json").write_text('{"frames": 3000, "camera": {"index": 3}}')  # an entry not ours
    with pytest.raises(ValueError, match="camera 4's entry is not a staged camera's"):
        StagedRun.gather(folder, len(paths))

    pack = simulate_group(ring_rig(3), animals=2, frames=20, seed=1)
    stage_camera(str(write_dlc_multi(tmp_path / "pack.csv", pack.tracks[0], ["a", "b"])), folder, 1, read_blocks)
    assert StagedRun.gather(folder, len(paths)) is None  # several animals: solved together, not staged


def _solve(rig, d, out, *extra, wait=True, stderr=False):
    cmd = [sys.executable, "-m", "graph.app.cli", "solve", *_cams(rig, d), "--calibration", str(d / "calibration.toml"),
           "--fps", "120", "--window-frames", str(CORE), "--out", str(out), "--h5", str(out.with_suffix(".h5")),
           "--report", str(out.with_suffix(".json")), *extra]
    env = {**os.environ, "ACINOSET_RESIDENT": "0"}
    if wait:
        return subprocess.run(cmd, capture_output=True, text=True, env=env)
    return subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE if stderr else subprocess.DEVNULL,
                            env=env, text=True)


def _windows_done(state: Path) -> int:
    try:
        return json.loads(state.read_text())["windows"]["done"]
    except (OSError, ValueError):
        return 0


@pytest.mark.parametrize("method", ["fte", "ekf"])
def test_a_killed_run_goes_on_from_its_last_window(rig, long_run, tmp_path, method):
    """Killed (SIGKILL) after its first windows, ``--resume`` goes on from the last one finished and
    writes what the run that was never stopped writes: the CSV byte for byte, the H5's arrays and the
    report; the partial folder is gone after. ekf's windows, one stream, go on from the poses the
    last one left."""
    _, d = long_run
    whole = _solve(rig, d, tmp_path / "whole.csv", "--method", method)
    assert whole.returncode == 0, whole.stderr

    out = tmp_path / "run.csv"
    state = tmp_path / "run.csv.partial" / "state.json"
    proc = _solve(rig, d, out, "--method", method, wait=False)
    deadline = time.monotonic() + 120
    while _windows_done(state) < 1 and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.02)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    done = _windows_done(state)
    assert 1 <= done < FRAMES // CORE, f"killed after {done} windows"
    assert out.stat().st_size < (tmp_path / "whole.csv").stat().st_size

    again = _solve(rig, d, out, "--method", method, "--resume")
    assert again.returncode == 0, again.stderr
    assert out.read_bytes() == (tmp_path / "whole.csv").read_bytes()
    a, b = read_result(tmp_path / "whole.h5"), read_result(out.with_suffix(".h5"))
    for name in FRAME_AXIS:
        if getattr(a, name) is not None:
            assert np.array_equal(getattr(a, name), getattr(b, name), equal_nan=True), name
    ra, rb = (json.loads(p.with_suffix(".json").read_text()) for p in (tmp_path / "whole.csv", out))
    timed = ("seconds", "per_frame_ms")  # what the clock says, not the answer
    assert {k: v for k, v in ra.items() if k not in timed} == {k: v for k, v in rb.items() if k not in timed}
    assert (ra["per_frame_ms"] is None) == (rb["per_frame_ms"] is None) == (method == "fte")
    assert not state.parent.exists()


def test_resume_without_a_stopped_run_or_with_other_options_is_one_line(rig, long_run, tmp_path):
    _, d = long_run
    out = tmp_path / "run.csv"
    nothing = _solve(rig, d, out, "--resume")
    assert nothing.returncode == 2 and "no stopped run to go on from" in nothing.stderr
    assert "Traceback" not in nothing.stderr and len(nothing.stderr.strip().splitlines()) == 1

    (tmp_path / "run.csv.partial" / "staged").mkdir(parents=True)
    proc = _solve(rig, d, out, wait=False)
    state = tmp_path / "run.csv.partial" / "state.json"
    deadline = time.monotonic() + 120
    while _windows_done(state) < 1 and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.02)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    other = _solve(rig, d, out, "--resume", "--likelihood-threshold", "0.6")
    assert other.returncode == 2 and "not the ones of the run that stopped" in other.stderr
    assert "Traceback" not in other.stderr

    doc = json.loads(state.read_text())
    doc["sums"]["valid"] = [1]  # damaged: one camera's count for six
    state.write_text(json.dumps(doc))
    damaged = _solve(rig, d, out, "--resume")
    assert damaged.returncode == 2 and "cannot go on from the stopped run" in damaged.stderr
    assert "Traceback" not in damaged.stderr and len(damaged.stderr.strip().splitlines()) == 1
    doc["csv"] = "x"  # a field of the wrong kind
    state.write_text(json.dumps(doc))
    wrong = _solve(rig, d, out, "--resume")
    assert wrong.returncode == 2 and "no stopped run to go on from" in wrong.stderr and "Traceback" not in wrong.stderr

    short = subprocess.run([sys.executable, "-m", "graph.app.cli", "solve", *_cams(rig, d), "--calibration",
                            str(d / "calibration.toml"), "--fps", "120", "--method", "tri", "--out",
                            str(tmp_path / "tri.csv"), "--resume"], capture_output=True, text=True)
    assert short.returncode == 2 and "--resume goes on with a long run" in short.stderr


def test_windows_in_two_worker_processes_give_the_same_answer(rig, long_run, in_memory, tmp_path):
    """``--jobs 2``: the windows solved side by side in worker processes, written in order: the same
    CSV, byte for byte, as the windows solved one after another in memory."""
    _, d = long_run
    out = tmp_path / "run.csv"
    done = _solve(rig, d, out, "--jobs", "2")
    assert done.returncode == 0, done.stderr
    write_anipose_csv(tmp_path / "memory.csv", in_memory)
    assert out.read_bytes() == (tmp_path / "memory.csv").read_bytes()
    b = read_result(out.with_suffix(".h5"))
    assert np.array_equal(in_memory.params, b.params) and np.array_equal(in_memory.std, b.std, equal_nan=True)


def test_a_folder_of_the_users_in_the_way_is_left_alone(rig, long_run, tmp_path):
    """``OUT.csv.partial`` that a run did not leave (here: a user's notes in it) is not removed: one line."""
    _, d = long_run
    mine = tmp_path / "run.csv.partial"
    mine.mkdir()
    (mine / "notes.txt").write_text("mine")
    done = _solve(rig, d, tmp_path / "run.csv")
    assert done.returncode == 2 and "is in the way" in done.stderr and "Traceback" not in done.stderr
    assert (mine / "notes.txt").read_text() == "mine"


def test_a_camera_file_is_staged_a_block_of_rows_at_a_time(rig, long_run, tmp_path, monkeypatch):
    """A DeepLabCut CSV staged as it is read, a block of rows at a time (here 256): the staged frames are
    the file's as one read gives them, and a file of several individuals is not staged."""
    from graph.io import keypoints
    from graph.io.staged import stage

    _, d = long_run
    monkeypatch.setattr(keypoints, "CSV_BLOCK_ROWS", 256)
    blocks = list(keypoints.read_blocks(_cams(rig, d)[0]))
    assert len(blocks) == -(-FRAMES // 256) and all(b.slots == 1 for b in blocks)
    staged = stage(_cams(rig, d), tmp_path / "staged", keypoints.read_blocks, lambda n: n > 1000)
    assert staged is not None and staged.frames == FRAMES
    for got, path in zip(staged.keypoints(0, FRAMES), _cams(rig, d)):
        whole = read_keypoints(path)
        assert np.array_equal(got.xy, whole.xy, equal_nan=True) and np.array_equal(got.likelihood, whole.likelihood)
    assert stage(_cams(rig, d), tmp_path / "short", keypoints.read_blocks, lambda n: n > FRAMES) is None


PEAK = ("import resource, subprocess, sys; done = subprocess.run(sys.argv[1:]); "
        "print(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss); sys.exit(done.returncode)")


@pytest.mark.slow
def test_the_memory_does_not_grow_with_the_run(rig, tmp_path):
    """The command's peak resident memory on 20,000 frames is within 60 MB of its peak on 5,000 (windows
    of 1,000): the run held whole would add some 12 KB a frame (180 MB), solved at once 170 KB."""
    peaks = {}
    for frames in (5000, 20000):
        d = tmp_path / str(frames)
        write_run(simulate_run(rig, frames=frames, fps=120, seed=1, speed=1.0), d)
        cmd = [sys.executable, "-c", PEAK, sys.executable, "-m", "graph.app.cli", "solve", *_cams(rig, d),
               "--calibration", str(d / "calibration.toml"), "--fps", "120", "--window-frames", "1000",
               "--out", str(d / "run.csv")]
        done = subprocess.run(cmd, capture_output=True, text=True, env={**os.environ, "ACINOSET_RESIDENT": "0"})
        assert done.returncode == 0, done.stderr
        peaks[frames] = int(done.stdout.strip().splitlines()[-1]) / 1024  # MiB
        for p in d.glob("cam*.csv"):
            p.unlink()
    print(f"peak MiB by frames: {peaks}")
    assert peaks[20000] - peaks[5000] < 60, peaks


def _workers(pid: int) -> list[int]:
    """The window workers below the command ``pid``: the children of its fork server."""
    found = []
    for child in children(pid):
        try:
            if "forkserver" in Path(f"/proc/{child}/cmdline").read_text():
                found += children(child)
        except OSError:
            pass
    return found


def test_a_worker_that_dies_is_one_line_and_the_run_goes_on(rig, long_run, in_memory, tmp_path):
    """``--jobs 2``, a window worker killed (as the kernel's OOM killer would): one line, no traceback;
    ``--resume`` finishes the run with the answer of one never stopped."""
    _, d = long_run
    out = tmp_path / "run.csv"
    state = tmp_path / "run.csv.partial" / "state.json"
    proc = _solve(rig, d, out, "--jobs", "2", wait=False, stderr=True)
    deadline = time.monotonic() + 120
    while (_windows_done(state) < 1 or not _workers(proc.pid)) and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.02)
    victims = _workers(proc.pid)
    assert victims, "no window worker found"
    os.kill(victims[0], signal.SIGKILL)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 2, err
    assert "worker process solving window" in err and "Traceback" not in err, err
    again = _solve(rig, d, out, "--resume")
    assert again.returncode == 0, again.stderr
    write_anipose_csv(tmp_path / "memory.csv", in_memory)
    assert out.read_bytes() == (tmp_path / "memory.csv").read_bytes()


def test_a_run_that_fails_before_its_first_window_leaves_no_folder(rig, long_run, tmp_path):
    """A camera file shorter than the others, found while staging: one line, and no OUT.csv.partial left
    (nothing to go on from)."""
    _, d = long_run
    cams = _cams(rig, d)
    short = tmp_path / Path(cams[1]).name
    short.write_text("".join(Path(cams[1]).read_text().splitlines(keepends=True)[:-100]))
    cmd = [sys.executable, "-m", "graph.app.cli", "solve", cams[0], str(short), *cams[2:], "--calibration",
           str(d / "calibration.toml"), "--fps", "120", "--window-frames", str(CORE), "--out", str(tmp_path / "r.csv")]
    done = subprocess.run(cmd, capture_output=True, text=True, env={**os.environ, "ACINOSET_RESIDENT": "0"})
    assert done.returncode == 2 and "all cameras must have the same frames" in done.stderr, done.stderr
    assert "Traceback" not in done.stderr and len(done.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "r.csv.partial").exists()
