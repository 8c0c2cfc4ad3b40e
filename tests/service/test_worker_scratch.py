"""A work horse killed by SIGKILL leaves its temporary folder; the next job on the machine removes the
ones older than a job's timeout, and nothing else."""

from __future__ import annotations

import os
import time

from service.run.worker import sweep_stale_scratch


def test_stale_work_horse_folders_are_swept_and_nothing_else(tmp_path):
    old = time.time() - 7 * 3600
    names = {"acinoset-0123abcd-xyz": True, "acinoset-0123abcd-helper-q": True, "acinoset-window-k": True,
             "acinoset-test.abc": False, "other-0123abcd-x": False}
    for name in names:
        (tmp_path / name).mkdir()
        (tmp_path / name / "input.csv").write_text("x")
        os.utime(tmp_path / name, (old, old))
    (tmp_path / "acinoset-89abcdef-fresh").mkdir()  # a job's folder now in use
    (tmp_path / "acinoset-0123abcd-file").write_text("a file, not a folder")
    os.utime(tmp_path / "acinoset-0123abcd-file", (old, old))
    removed = sweep_stale_scratch(6 * 3600, str(tmp_path))
    assert sorted(removed) == sorted(n for n, gone in names.items() if gone)
    left = sorted(p.name for p in tmp_path.iterdir())
    assert left == sorted(["acinoset-89abcdef-fresh", "acinoset-0123abcd-file",
                           *(n for n, gone in names.items() if not gone)])


def test_a_workers_result_folder_keeps_only_regular_result_files(tmp_path):
    """A worker on the shared data dir writes its result folder itself; the collector installs only what a
    result archive may carry: a link to a server file named like a result, a linked folder, other names and
    a folder in a result's name go."""
    from service.store.jobfiles import keep_results

    tmp = tmp_path / "result.tok.tmp"
    (tmp / "videos").mkdir(parents=True)
    (tmp / "result.csv").write_text("a,b\n")
    (tmp / "videos" / "camera01.mp4").write_bytes(b"\0")
    (tmp / "report.json").symlink_to("/etc/passwd")
    (tmp / "individuals").symlink_to(tmp_path, target_is_directory=True)
    (tmp / "notes.txt").write_text("not a result")
    (tmp / "result.h5").mkdir()
    (tmp / "result.h5" / "x").write_text("inside a folder named like a result")
    keep_results(tmp)
    kept = sorted(p.relative_to(tmp).as_posix() for p in tmp.rglob("*") if p.is_file() or p.is_symlink())
    assert kept == ["result.csv", "videos/camera01.mp4"]
    assert (tmp_path / "result.tok.tmp").exists() and os.path.exists("/etc/passwd")


def test_a_job_id_from_redis_that_is_not_one_reaches_no_folder(tmp_path, monkeypatch):
    """Whoever writes to Redis names the job: on the shared data dir only an id of the server's form is
    looked up, under the worker's own data dir."""
    from service.run.worker import shared_job

    monkeypatch.setenv("ACINOSET_DATA_DIR", str(tmp_path))
    for hostile in ("../../etc", "/etc", "0" * 31 + "/", "a" * 32 + "/../x"):
        assert shared_job(hostile) == f"not a job id: {hostile!r}"
    said = shared_job("0" * 32)
    assert isinstance(said, str) and "does not see the server's data dir" in said and "\n" not in said
