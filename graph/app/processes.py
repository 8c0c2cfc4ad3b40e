"""Whether a process runs, by its pid: the check the resident's client, the embedded backend's shared
windows and the tests' servers make."""

from __future__ import annotations

import os
from pathlib import Path


def pid_alive(pid: int) -> bool:
    """Whether process ``pid`` runs on this machine: it exists (another user's counts) and is neither a
    zombie, exited or killed and not yet reaped (where PID 1 reaps no orphans, as in some containers,
    one stays a zombie for good), nor dead on its way out (state X). Without ``/proc``, existing is
    running."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's: it exists
        pass
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] not in ("Z", "X")
    except (OSError, IndexError):
        return True
