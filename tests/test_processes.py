"""Whether a process runs (graph.app.processes.pid_alive): a zombie, exited and not yet reaped, does not."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

from graph.app.processes import pid_alive


def test_a_zombie_is_not_running_and_a_live_process_is():
    child = subprocess.Popen([sys.executable, "-c", "pass"])
    stat = Path(f"/proc/{child.pid}/stat")
    deadline = time.time() + 30
    while stat.read_text().rsplit(")", 1)[1].split()[0] != "Z":  # exited, not reaped: Popen waits for us
        assert time.time() < deadline, "the child did not exit"
        time.sleep(0.01)
    assert not pid_alive(child.pid)
    child.wait()
    assert not pid_alive(child.pid)
    assert pid_alive(os.getpid())
    assert pid_alive(1)  # another user's, or ours: it exists
