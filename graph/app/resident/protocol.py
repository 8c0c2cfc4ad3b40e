"""What the resident and its clients agree on: where a resident lives (its key and files), the
limits and signals of the hand-over, the command lines it may run, and the framing of its lines.

The lifecycle and the protocol are described in :mod:`graph.app.resident`.
"""

from __future__ import annotations

import errno
import fcntl
import hashlib
import os
import signal
import socket
import sys
from collections import namedtuple
from collections.abc import Callable
from pathlib import Path

from graph import __version__

SWITCH = "ACINOSET_RESIDENT"  # "0" (or off/no/false): every solve in its own process


IDLE = "ACINOSET_RESIDENT_IDLE"  # seconds without a solve before the resident exits


DEFAULT_IDLE_S = 600.0


KEY_ENV_PREFIXES = ("NUMBA_", "OMP_", "OPENBLAS_", "MKL_", "BLIS_", "GOTO", "VECLIB_", "KMP_", "NUMEXPR_",
                    "PYTHON", "LD_", "LC_", "LANG", "ACINOSET_")


CONNECT_TIMEOUT_S = 1.0


ANSWER_TIMEOUT_S = 5.0  # from the request to the child's ``pid`` line


KEY_CHECK_S = 60.0


FORWARDED = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP, signal.SIGQUIT)


JOB_CONTROL = (signal.SIGTSTP, signal.SIGCONT)  # Ctrl-Z and fg/bg: the child stops and resumes with the client


NOT_TAKEN = 75  # a child's exit status when it ran no solve (a solve's own 75 is reported as 1)


SOCKET_PATH_MAX = 100  # sun_path is 108 bytes on Linux, 104 on macOS


serving = False  # True in a resident's forked child: its solve runs there, not handed over again


class Place(namedtuple("Place", "dir key")):
    """Where the resident of one key lives: its directory (a Path) and key. (Named tuples here and
    in :class:`Resident`: the client imports no ``dataclasses``, 10 ms; see :class:`graph.app.cli.Command`.)"""

    __slots__ = ()

    @property
    def socket(self) -> Path:
        return self.dir / f"{self.key}.sock"

    @property
    def lock(self) -> Path:
        return self.dir / f"{self.key}.lock"

    @property
    def log(self) -> Path:
        return self.dir / f"{self.key}.log"


def runtime_dir(env: dict[str, str]) -> Path:
    """The private directory of this user's residents, made if missing; OSError if it is not
    owned by the user or others may enter it."""
    base = env.get("XDG_RUNTIME_DIR")
    if base:
        d = Path(base) / "acinoset"
    else:
        cache = env.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
        if not os.path.isabs(cache):  # no home directory: no resident
            raise OSError(errno.ENOENT, "no cache directory", cache)
        d = Path(cache) / "acinoset" / "resident"
    d.mkdir(mode=0o700, parents=True, exist_ok=True)
    st = d.stat()
    if st.st_uid != os.getuid() or st.st_mode & 0o077:
        raise OSError(errno.EPERM, "not a private directory", str(d))
    return d


def key_of(env: dict[str, str]) -> str:
    """The resident key of this install, Python and environment (see the module's docstring)."""
    import graph

    parts: list = [__version__, os.getuid()]
    exe = os.path.realpath(sys.executable)
    st = os.stat(exe)
    parts.append((sys.executable, exe, st.st_size, st.st_mtime_ns))
    root = os.path.dirname(os.path.abspath(graph.__file__))
    parts.append(root)
    skip = len(root) + 1  # a path under root, relative to it (os.path.relpath: 10x the cost)
    for dirpath, dirnames, filenames in os.walk(root):
        dirnames[:] = sorted(d for d in dirnames if d != "__pycache__")
        for name in sorted(filenames):
            if name.endswith((".pyc", ".nbi", ".nbc")):
                continue
            path = os.path.join(dirpath, name)
            st = os.stat(path)
            parts.append((path[skip:], st.st_size, st.st_mtime_ns))
    for entry in sys.path:
        if entry.endswith(("site-packages", "dist-packages")) and os.path.isdir(entry):
            parts.append((entry, os.stat(entry).st_mtime_ns))
    parts.append(sorted((k, v) for k, v in env.items()
                        if k.startswith(KEY_ENV_PREFIXES) and not k.startswith(SWITCH)))
    return hashlib.sha256(repr(parts).encode()).hexdigest()[:20]


def place_of(env: dict[str, str]) -> Place:
    place = Place(runtime_dir(env), key_of(env))
    if len(str(place.socket)) > SOCKET_PATH_MAX:
        raise OSError(errno.ENAMETOOLONG, "socket path too long", str(place.socket))
    return place


ENTRIES = ("graph.app.cli:main",)  # the command lines a resident runs (named, so that it imports no CLI)


def entry_function(name: str) -> Callable[..., int]:
    """The ``main`` an entry of :data:`ENTRIES` names (``module:function``), imported."""
    import importlib

    if name not in ENTRIES:
        raise ValueError(f"not a command line a resident runs: {name!r}")
    module, _, function = name.partition(":")
    return getattr(importlib.import_module(module), function)


class Lines:
    """Reads ``\\n``-terminated ASCII lines from a socket ("" at the end of the stream)."""

    def __init__(self, sock: socket.socket):
        self.sock = sock
        self.buf = b""

    def next(self) -> str:
        while b"\n" not in self.buf:
            data = self.sock.recv(4096)
            if not data:
                rest, self.buf = self.buf, b""
                return rest.decode("ascii", "replace")
            self.buf += data
        line, _, self.buf = self.buf.partition(b"\n")
        return line.decode("ascii", "replace")


def read_exactly(conn: socket.socket, n: int) -> bytes:
    data = b""
    while len(data) < n:
        chunk = conn.recv(min(1 << 20, n - len(data)))
        if not chunk:
            raise ValueError("the request ended early")
        data += chunk
    return data


def idle_seconds(env: dict[str, str]) -> float:
    try:
        value = float(env.get(IDLE, DEFAULT_IDLE_S))
    except ValueError:
        return DEFAULT_IDLE_S
    return value if value > 0 else DEFAULT_IDLE_S


def lock_held(lock: Path) -> bool | None:
    """Whether a resident holds ``lock`` (None if it cannot be opened)."""
    try:
        fd = os.open(lock, os.O_RDONLY | os.O_CLOEXEC)
    except OSError:
        return None
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except OSError:
        return True
    finally:
        os.close(fd)
    return False
