"""One long job over the embedded backend's slots (a real server): the slot no other job takes goes to a
helper process that solves the run's windows, the answer is the library's, byte for byte, whoever solved
which window; a helper killed mid-run costs time, not the answer; a job submitted meanwhile takes the
helper's slot; a cancelled job leaves no helper behind. And the folder the processes meet in, on its own."""

from __future__ import annotations

import os
import signal
import time
from datetime import datetime

import pytest
from servers import Server, add_user, library_csv, make_run, submit, wait_dead, wait_finished, wait_for

FRAMES = 4000
CORE = 400


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    return make_run(tmp_path_factory.mktemp("embedded_windows_run"), frames=FRAMES, cameras=4, seed=7)


@pytest.fixture(scope="module")
def library(run, tmp_path_factory):
    return library_csv(run, CORE, tmp_path_factory.mktemp("embedded_windows_library"))


@pytest.fixture
def server(tmp_path):
    token = add_user(tmp_path / "data", "alice")
    srv = Server(tmp_path / "data", tmp_path / "server.log", workers=2).start()
    yield srv, token
    srv.stop()


def _helpers(data, job: str) -> list[int]:
    """The pids of the job's helper processes, as their heartbeats on the run's board name them."""
    pids = []
    for p in (data / "jobs" / job).glob("result.*.tmp/staged/board/alive/helper-*"):
        try:
            pids.append(int(p.read_text()))
        except (OSError, ValueError):  # gone, or being written
            continue
    return pids


def _claimed_by(data, job: str, pid: int) -> list[int]:
    """The windows the helper ``pid`` has claimed on the run's board."""
    got = []
    for p in (data / "jobs" / job).glob("result.*.tmp/staged/board/claims/*"):
        try:
            if p.read_text().startswith(f"helper-{pid}@"):
                got.append(int(p.name))
        except (OSError, ValueError):
            continue
    return got


def _wait_helper(data, job: str, timeout: float = 120) -> int:
    deadline = time.time() + timeout
    while time.time() < deadline:
        pids = _helpers(data, job)
        if pids:
            return pids[0]
        time.sleep(0.05)
    raise AssertionError(f"no helper process for job {job} after {timeout} s")


def _submit(c, run) -> str:
    r = submit(c, run, {"method": "fte", "window_frames": CORE})
    assert r.status_code == 202, r.text
    return r.json()["id"]


def test_a_long_job_is_shared_with_a_helper_and_gives_the_librarys_answer(server, run, library):
    srv, token = server
    with srv.client(token) as c:
        done = wait_finished(c, _submit(c, run), timeout=600)
        assert done["status"] == "succeeded", done
        report = c.get(done["links"]["result"]["report"]).json()
        csv = c.get(done["links"]["result"]["csv"]).content
    solved_by = report["windows"]["solved_by"]
    assert len(solved_by) == 2 and sum(solved_by.values()) == FRAMES // CORE, solved_by
    assert csv == library


def test_a_helper_killed_mid_run_costs_time_not_the_answer(server, run, library):
    srv, token = server
    with srv.client(token) as c:
        job = _submit(c, run)
        helper = _wait_helper(srv.data_dir, job)
        deadline = time.time() + 120
        while not _claimed_by(srv.data_dir, job, helper):  # killed holding a window
            assert time.time() < deadline, "the helper claimed no window"
            time.sleep(0.02)
        os.kill(helper, signal.SIGKILL)
        done = wait_finished(c, job, timeout=600)
        assert done["status"] == "succeeded", done
        report = c.get(done["links"]["result"]["report"]).json()
        csv = c.get(done["links"]["result"]["csv"]).content
    assert sum(report["windows"]["solved_by"].values()) == FRAMES // CORE
    assert csv == library  # its window solved by the job's process instead
    assert _helpers(srv.data_dir, job) == []


def test_a_job_submitted_meanwhile_takes_the_helpers_slot(server, run):
    srv, token = server
    with srv.client(token) as c:
        long_job = _submit(c, run)
        helper = _wait_helper(srv.data_dir, long_job)
        r = submit(c, run, {"method": "tri"})
        assert r.status_code == 202, r.text
        short = wait_finished(c, r.json()["id"], timeout=300)
        assert short["status"] == "succeeded", short
        assert wait_dead(helper, timeout=5), "the helper did not leave its slot"
        long_done = wait_finished(c, long_job, timeout=600)
        assert long_done["status"] == "succeeded", long_done
    # the short job finished while the long one still ran: it had the helper's slot, not the long job's end
    finished = [datetime.fromisoformat(j["timings"]["finished_at"]) for j in (short, long_done)]
    assert finished[0] < finished[1]


def test_a_cancelled_job_leaves_no_helper(server, run):
    srv, token = server
    with srv.client(token) as c:
        job = _submit(c, run)
        helper = _wait_helper(srv.data_dir, job)
        assert c.delete(f"/v1/jobs/{job}").status_code == 200
        wait_for(c, job, lambda j: j["status"] == "cancelled", 60, "cancelled")
    assert wait_dead(helper, timeout=10)
    deadline = time.time() + 10  # the scheduler removes what the killed run wrote when it reaps it
    while list((srv.data_dir / "jobs" / job).glob("result.*.tmp")) and time.time() < deadline:
        time.sleep(0.1)
    assert not list((srv.data_dir / "jobs" / job).glob("result.*.tmp")), "the run's folder was left behind"


def test_the_board_claims_once_and_knows_who_is_gone(tmp_path):
    """The folder board on its own: a window is claimed once (a second claimant is refused), taken over
    by the parent, a heartbeat of a process that ended is not alive, and a board whose folder went is
    stopped and asks for no helper."""
    import shutil
    import subprocess
    import sys

    from service.run.folder_windows import FolderBoard

    board = FolderBoard(tmp_path / "board")
    board.want(1)
    assert board.wanted() == 1 and board.parent_running()
    board.publish({"spans": [[0, 10], [10, 20]]}, 2, "me")
    assert board.claim(0, "helper-1@here") and not board.claim(0, "me")
    assert board.owner(0) == "helper-1@here"
    board.take_over(0, "me")
    assert board.owner(0) == "me" and not board.all_claimed(2)
    assert board.claim(1, "me") and board.all_claimed(2) and board.wanted() == 0

    gone = subprocess.Popen([sys.executable, "-c", "pass"])
    gone.wait()
    (board.folder / "alive" / "helper-2@here").write_text(str(gone.pid))
    assert not board.alive("helper-2@here")
    board.beat("helper-3@here")
    assert board.alive("helper-3@here")
    board.leave("helper-3@here")
    assert not board.alive("helper-3@here")

    board.stop()
    assert board.stopped() and board.wanted() == 0
    board.clear(2)
    assert board.plan() is None and board.owner(0) is None
    shutil.rmtree(board.folder)
    assert board.stopped() and board.wanted() == 0
    board.beat("helper-3@here")  # a helper's heartbeat after its run ended does not make the folder again
    assert not board.folder.exists()


def test_cameras_staged_together_on_the_board_survive_a_helper_that_died_and_a_run_that_ended(tmp_path, run):
    """The cameras staged by the parent and its helpers between them, on the folder board: a camera
    claimed by a helper whose process ended is taken over by the parent (one taker) and the run comes
    out whole; a helper that comes after the run's board went stages nothing."""
    import shutil
    import subprocess
    import sys

    from graph.io.keypoints import read_blocks
    from graph.io.staged import StagedRun
    from service.run.folder_windows import FolderBoard
    from service.run.shared_windows import PARENT, stage_together

    scratch = tmp_path / "staged"
    board = FolderBoard(scratch / "board")
    assert board.together(before_staging=True) and board.staging_together()
    board.want(1)
    gone = subprocess.Popen([sys.executable, "-c", "pass"])
    gone.wait()
    assert board.claim_camera(1, "helper-1@here") == 1 and board.claim_camera(1, PARENT) == 0
    (board.folder / "alive" / "helper-1@here").write_text(str(gone.pid))  # its helper died
    paths = [str(p) for p in run.cams]
    got = stage_together(board, PARENT, paths, scratch, read_blocks)
    assert isinstance(got, StagedRun) and len(got.cameras) == len(paths) and got.frames == run.frames
    assert board.camera_owner(1) == PARENT  # taken over
    assert not board.take_over_camera(1, "helper-1@here", "helper-2@here")  # only from the claimant it names

    shutil.rmtree(board.folder)  # the run ended
    late = tmp_path / "late"
    late.mkdir()
    assert board.claim_camera(0, "helper-3@here") == -1
    assert stage_together(board, "helper-3@here", paths, late, read_blocks) is None
    assert list(late.iterdir()) == []
