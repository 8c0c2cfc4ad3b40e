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
