"""A warm resident process that serves ``acinoset solve`` from a shell, as a build daemon serves builds.

Why. A new Python process pays about a second before it solves anything: importing numba and
gtsam, and numba's first load of its cached kernels in that process. The solve of a 150-frame run
takes a fifth of that. A process that has paid it once, and forks a child per solve (as the job
service's workers do), starts each solve at once.

Lifecycle.

* ``acinoset solve`` (the *client*) looks for the resident of its *key* and hands the solve over.
* If there is none, it solves in its own process as before, then starts one: ``python -c`` this
  module's :func:`serve`, detached (a new session, stdin/stdout/stderr on /dev/null, every other
  inherited file closed), so that a shell pipeline or a CI job never waits for it.
* The resident imports the solver, runs tiny solves (:func:`graph.app.warmup.warm_up`, and one tiny
  ``acinoset solve`` from files to files) so that its kernels and the command's readers and
  writers are loaded, then listens. It exits after ``ACINOSET_RESIDENT_IDLE`` seconds without a solve (default
  600), on SIGTERM (``acinoset resident stop``; a solve being served finishes first), or when the
  installed code changes. ``ACINOSET_RESIDENT=0`` turns it off: every solve runs in its own process.

Where. ``$XDG_RUNTIME_DIR/acinoset``, else ``$XDG_CACHE_HOME/acinoset/resident`` (``~/.cache``): a
directory of mode 0700 owned by the user (anything else and the client solves in its own process).
Per key: ``KEY.sock`` (the socket), ``KEY.lock`` (held with ``flock`` for the resident's whole life,
so two clients starting at once start one resident; it holds the resident's pid and counts as
JSON) and ``KEY.log`` (one line per solve served).

The key. A hash of the package version, the Python executable (path, size, mtime), every file of
the ``graph`` package (path, size, mtime), the mtime of each ``site-packages`` directory on
``sys.path`` (an install or upgrade changes it) and the environment variables that change what is
imported or compiled (:data:`KEY_ENV_PREFIXES`: ``NUMBA_*``, thread counts, ``PYTHON*``,
``ACINOSET_*`` ...). An edited or upgraded install has a new key: its first solve starts a new
resident and the old one idles out (it also checks its own key each minute and leaves when it changed).

Protocol: one Unix stream connection per solve.

1. client -> resident: an 8-byte big-endian length and a JSON object ``{argv, cwd, env, umask,
   entry, commands}`` (``entry``: the command line's ``main`` as ``module:function``, one of
   :data:`ENTRIES`; ``commands``: the :class:`graph.app.cli.Command` table it is called with).
2. The resident hands the connection to a child: the one it forked ahead while no solve ran (it
   waits on a socket pair for the connection; a fork of the resident takes 5-7 ms), or, when
   solves overlap, one forked on the spot. The child reads the request, enters ``cwd``, takes
   ``env`` and ``umask``, and answers ``pid N\\n`` (``fail\\n`` if any of that failed).
3. client -> child: ``go\\n`` with the client's file descriptors 0, 1, 2 attached (``SCM_RIGHTS``;
   sent only now, so that none waits in a hung resident's queue holding the client's pipes open);
   the child makes them its own 0, 1, 2 and answers ``run\\n``: from then on the solve is the
   child's. A child that gets no ``go`` (the client gave up waiting) exits having done nothing, and
   a client that gets no ``run`` solves in its own process.
4. The child runs ``entry(argv, commands)``, exactly what the client would have run, sends
   ``exit S\\n`` with its status and exits with it (the client need not wait for the teardown of a
   large process: 5-10 ms). The resident reaps it and sends the same line, or ``signal N\\n`` if it
   was killed before it could; the client takes the first line and exits the same way
   (re-raising the signal on itself).

Ctrl-C and SIGTERM/SIGHUP/SIGQUIT sent to the client are forwarded to the child's pid (held until
the child has said ``run``, and held blocked in the child from then until its solve's own handlers
are in place: one that comes at once ends the solve as 'interrupted', never lost); Ctrl-Z
(SIGTSTP) stops the child with the client, and SIGCONT resumes both. A client that dies without a
word (SIGKILL, a crashed shell) ends its child too: the child watches its connection and, when the
client's end closes before the solve has, kills itself as the client was killed. Anything that
fails before ``run`` makes the client solve in its own process: a resident never makes a solve fail.
The client's side imports nothing heavy (no numpy, numba or gtsam).
"""

from __future__ import annotations

import errno
import fcntl
import hashlib
import json
import os
import signal
import socket
import struct
import sys
import time
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

_serving = False  # True in a resident's forked child: its solve runs there, not handed over again


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


# ------------------------------------------------------------------------------------ the key


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


def wanted(argv: list[str], env: dict[str, str]) -> bool:
    """Whether this command line may be served by a resident: ``solve`` (not its ``--help``), the
    switch not off, and numba's threading layer one that survives a fork."""
    if env.get(SWITCH, "1").strip().lower() in ("0", "off", "no", "false"):
        return False
    if env.get("NUMBA_THREADING_LAYER", "workqueue") not in ("workqueue", "tbb"):
        return False  # GNU OpenMP aborts a process forked after it ran: solve in process
    if any(a in ("-h", "--help") for a in argv):
        return False
    return hasattr(socket, "send_fds") and hasattr(os, "fork")


# --------------------------------------------------------------------------------- the client


ENTRIES = ("graph.app.cli:main",)  # the command lines a resident runs (named, so that it imports no CLI)


def _entry(name: str) -> Callable[..., int]:
    """The ``main`` an entry of :data:`ENTRIES` names (``module:function``), imported."""
    import importlib

    if name not in ENTRIES:
        raise ValueError(f"not a command line a resident runs: {name!r}")
    module, _, function = name.partition(":")
    return getattr(importlib.import_module(module), function)


def solve(argv: list[str], commands, run_here: Callable[[], int], exit_when_served: bool = False,
          entry: str = ENTRIES[0]) -> int:
    """Run ``acinoset solve`` (``argv``): handed over to a warm resident if one is up, which runs
    ``entry`` (``module:function`` of :data:`ENTRIES`) with ``argv`` and ``commands``, else
    ``run_here()`` in this process, after which a resident is started for the next ones.

    ``exit_when_served``: this process is the command itself (its own command line, not a caller's
    ``main([...])``), so once its solve was served it has nothing left to do: it flushes its
    streams and exits at once with the solve's status, without the interpreter's teardown (7-10 ms
    of a served solve's 0.3 s)."""
    env = dict(os.environ)
    if _serving or not wanted(argv, env):
        return run_here()
    try:
        place = place_of(env)
    except OSError:
        return run_here()
    status = _hand_over(place, argv, commands, env, entry)
    if status is not None:
        if exit_when_served:
            for stream in (sys.stdout, sys.stderr):
                try:
                    stream.flush()
                except (OSError, ValueError):
                    pass
            os._exit(status)
        return status
    try:
        return run_here()
    finally:
        start(place, env)


def _hand_over(place: Place, argv: list[str], commands, env: dict[str, str], entry: str) -> int | None:
    """Steps 1-4 of the protocol; None if the solve was not taken (nothing was run)."""
    try:
        signals = _Signals()  # from the start: a Ctrl-C before the child runs is not lost
    except ValueError:  # not the main thread: no handlers, no hand-over
        return None
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        sock.settimeout(CONNECT_TIMEOUT_S)
        sock.connect(str(place.socket))
        sock.settimeout(ANSWER_TIMEOUT_S)
        umask = os.umask(0o022)
        os.umask(umask)
        body = json.dumps({"argv": argv, "cwd": os.getcwd(), "env": env, "umask": umask, "entry": entry,
                           "commands": [[c.name, c.module, c.help] for c in commands]}).encode()
        sock.sendall(struct.pack(">Q", len(body)) + body)
        lines = _Lines(sock)
        answer = lines.next()
        pid = int(answer.split()[1]) if answer.startswith("pid ") else 0
        # the descriptors go only to a child that answered: none is left in flight in a hung
        # resident's queue, where it would hold the client's pipes open
        taken = pid > 0 and socket.send_fds(sock, [b"go\n"], [0, 1, 2]) > 0 and lines.next() == "run"
    except (OSError, ValueError):
        taken = False
    if not taken:  # no child runs the solve (one that answered exits having done nothing)
        sock.close()
        return signals.restore_before_solving()
    signals.forward_to(pid)
    # committed: the child runs the solve; wait for its end however long it takes
    try:
        sock.settimeout(None)
        end = lines.next()
    except OSError:
        end = ""
    finally:
        sock.close()
        signals.restore()
    word, _, value = end.partition(" ")
    if word == "exit":
        return int(value)
    if word == "signal":
        signum = int(value)
        signal.signal(signum, signal.SIG_DFL)
        os.kill(os.getpid(), signum)
        return 128 + signum
    # the resident itself was killed: its child's end is not known; wait for it, say so
    while _alive(pid):
        time.sleep(0.05)
    print("acinoset: error: the resident process serving this solve was stopped; run it again "
          f"(or with {SWITCH}=0)", file=sys.stderr)
    return 1


class _Signals:
    """The client's handlers of :data:`FORWARDED` while it hands a solve over: signals that come
    before the child runs are kept, and sent to it once it does (:meth:`forward_to`)."""

    def __init__(self):
        self.pid = 0
        self.pending: list[int] = []
        self.previous = {s: signal.signal(s, self._handle) for s in FORWARDED + JOB_CONTROL}

    def _handle(self, signum: int, _frame) -> None:
        if signum == signal.SIGTSTP:  # Ctrl-Z: the child stops with us; we stop as we would have
            self._stop_together()
        elif signum == signal.SIGCONT:
            if self.pid:
                _forward(self.pid, signal.SIGCONT)
        elif self.pid:
            _forward(self.pid, signum)
        else:
            self.pending.append(signum)

    def _stop_together(self) -> None:
        """Stop the child (SIGSTOP: in the resident's session, its own SIGTSTP would be discarded),
        then this process as SIGTSTP's default would. In an orphaned process group (no shell to
        resume it) the kernel discards that: then the child goes on too. Whether this process
        stopped shows as a SIGCONT pending once it runs again (held blocked meanwhile); its handler
        resumes the child."""
        if self.pid:
            _forward(self.pid, signal.SIGSTOP)
        signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGCONT})
        try:
            signal.signal(signal.SIGTSTP, signal.SIG_DFL)
            os.kill(os.getpid(), signal.SIGTSTP)  # stopped here until a SIGCONT, unless discarded
            signal.signal(signal.SIGTSTP, self._handle)
            stopped = signal.SIGCONT in signal.sigpending()
        finally:
            signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGCONT})
        if not stopped and self.pid:
            _forward(self.pid, signal.SIGCONT)

    def forward_to(self, pid: int) -> None:
        self.pid = pid
        for signum in self.pending:
            _forward(pid, signum)
        self.pending.clear()

    def restore(self) -> None:
        for s, handler in self.previous.items():
            signal.signal(s, handler)

    def restore_before_solving(self) -> int | None:
        """The previous handlers back; None to solve in this process, or the exit status of a
        signal that came meanwhile (the solve is not started: Ctrl-C is 'interrupted', 130)."""
        self.restore()
        if not self.pending:
            return None
        signum = self.pending[0]
        if signum == signal.SIGINT:
            print("acinoset: interrupted", file=sys.stderr)
            return 130
        signal.signal(signum, signal.SIG_DFL)
        os.kill(os.getpid(), signum)
        return 128 + signum


def _forward(pid: int, signum: int) -> None:
    try:
        os.kill(pid, signum)
    except OSError:
        pass


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


class _Lines:
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


def start(place: Place, env: dict[str, str]) -> bool:
    """Start the resident of ``place`` with the environment ``env`` (the client's as it began: a
    solve changes its own, cv2 adds to ``LD_LIBRARY_PATH``) unless one is up or starting (its lock
    is held); never raises. The lock taken here is handed to the resident, which holds it for its
    whole life."""
    try:
        fd = os.open(place.lock, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o600)
    except OSError:
        return False
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        os.close(fd)
        return False
    try:
        import subprocess

        code = "import sys; from graph.app.resident import serve; serve(int(sys.argv[1]), sys.argv[2])"
        subprocess.Popen([sys.executable, "-c", code, str(fd), place.key], stdin=subprocess.DEVNULL,
                         stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, close_fds=True, pass_fds=(fd,),
                         start_new_session=True, cwd=str(place.dir), env=env)
        return True
    except OSError:
        return False
    finally:
        os.close(fd)  # the resident's copy keeps the lock


# ------------------------------------------------------------------------------- the resident


def serve(lock_fd: int, key: str) -> None:
    """The resident's body (run by :func:`start`): warm up, then serve until idle, stopped or stale."""
    env = dict(os.environ)  # the starting client's: the key is computed on it
    place = Place(runtime_dir(env), key)
    if key_of(env) != key:  # this Python imports other code than the client did
        return
    log = open(place.log, "w", buffering=1, encoding="utf-8")
    idle = _idle_seconds(env)
    info = {"pid": os.getpid(), "key": key, "version": __version__, "python": sys.executable,
            "started": time.time(), "idle_s": idle, "served": 0, "last": None, "ready": False}
    _write_info(lock_fd, info)
    _prune(place)
    _say(log, f"resident {os.getpid()} of acinoset {__version__} ({sys.executable}), key {key}: warming up")
    try:
        _serve(place, lock_fd, env, info, log)
    except BaseException:  # noqa: BLE001 - said in the log; clients solve in their own processes meanwhile
        import traceback

        _say(log, "failed:\n" + traceback.format_exc())
    log.close()


def _serve(place: Place, lock_fd: int, env: dict[str, str], info: dict, log) -> None:
    """Warm up, listen, fork a child per connection and report its end, until told to stop."""
    key, idle = place.key, info["idle_s"]

    def say(text: str) -> None:
        _say(log, text)

    os.environ.setdefault("NUMBA_THREADING_LAYER", "workqueue")  # survives a fork (wanted() refused omp)
    t0 = time.perf_counter()
    import importlib

    for module in ("graph.app.cli", "graph.api", "graph.io.results", "graph.solve.kernels", "graph.kinematics", "graph.io.calibration", "graph.io.keypoints",
                   "graph.solve.ensemble", "h5py"):
        try:
            importlib.import_module(module)
        except ImportError:
            pass
    from graph.app.warmup import warm_up

    warm_up()
    _warm_cli(place.dir)
    import gc

    gc.collect()
    gc.freeze()  # the children share these pages instead of touching them
    listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        place.socket.unlink()  # a killed resident's
    except FileNotFoundError:
        pass
    listener.bind(str(place.socket))
    os.chmod(place.socket, 0o600)
    listener.listen(64)
    ino = place.socket.stat().st_ino
    info["ready"] = True
    _write_info(lock_fd, info)
    say(f"warm in {time.perf_counter() - t0:.1f} s; listening on {place.socket} (idle exit after {idle:g} s)")

    wake_r, wake_w = os.pipe()
    os.set_blocking(wake_r, False)
    os.set_blocking(wake_w, False)
    signal.set_wakeup_fd(wake_w)
    held = (listener.fileno(), wake_r, wake_w, lock_fd)  # the resident's own: a child closes them
    stop = []
    signal.signal(signal.SIGCHLD, lambda *_: None)
    signal.signal(signal.SIGTERM, lambda *_: stop.append("stopped (SIGTERM)"))
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGHUP, signal.SIG_IGN)
    children: dict[int, tuple[socket.socket, float]] = {}
    spare: _Spare | None = None
    last = checked = time.monotonic()
    import select

    while True:
        now = time.monotonic()
        if not stop and not children and now - last >= idle:
            stop.append(f"idle for {idle:g} s")
        if not stop and now - checked >= KEY_CHECK_S:
            checked = now
            try:
                if key_of(env) != key:
                    stop.append("its code or Python changed")
            except OSError:
                stop.append("its code or Python changed")
        if stop and listener is not None:
            listener.close()
            listener = None
            _unlink_if(place.socket, ino)
            say(f"no longer listening: {stop[0]}")
        if stop and not children:
            break
        if spare is None and listener is not None and not children:
            # the next solve's process, forked while none runs rather than on the next solve's time
            # (a fork of this process takes 5-7 ms); solves that overlap get one forked on the spot
            spare = _Spare.fork(held, log)
        if children:
            timeout = KEY_CHECK_S  # a child's end wakes the loop (SIGCHLD)
        else:
            timeout = max(0.0, min(idle - (now - last), KEY_CHECK_S - (now - checked)))
        ready, _, _ = select.select([wake_r] + ([listener] if listener is not None else []), [], [], timeout)
        if wake_r in ready:
            try:
                while os.read(wake_r, 512):
                    pass
            except BlockingIOError:
                pass
        for pid, status in _reap():
            if spare is not None and pid == spare.pid:  # it died waiting: fork the next one below
                spare.close()
                spare = None
            if pid not in children:
                continue
            conn, began = children.pop(pid)
            last = time.monotonic()
            code = os.waitstatus_to_exitcode(status)
            if code == NOT_TAKEN:  # the client solved in its own process
                conn.close()
                say(f"child {pid} ran no solve")
                continue
            reply = f"exit {code}\n" if code >= 0 else f"signal {-code}\n"
            try:
                conn.sendall(reply.encode())
            except OSError:
                pass
            conn.close()
            info["served"] += 1
            info["last"] = time.time()
            _write_info(lock_fd, info)
            say(f"served child {pid}: {reply.strip()} after {last - began:.2f} s")
        if listener is not None and listener in ready:
            try:
                conn, _ = listener.accept()
            except OSError:
                continue
            pid = spare.take(conn) if spare is not None else 0
            spare = None
            if not pid:
                try:
                    pid = os.fork()
                except OSError as e:  # the client solves in its own process
                    conn.close()
                    say(f"cannot fork: {e}")
                    continue
                if pid == 0:
                    _child(conn, held, log)  # never returns
            children[pid] = (conn, time.monotonic())
            last = time.monotonic()
    if spare is not None:
        spare.close()  # it sees the end of its socket and exits
    say(f"exit: {stop[0]}; served {info['served']} solve(s)")


class _Spare:
    """A child forked ahead of the next connection: it waits on a socket pair for the accepted
    connection (``SCM_RIGHTS``) and then serves it as a child forked on the spot would
    (:func:`_child`); the end of that socket, the resident gone or done, ends it."""

    def __init__(self, pid: int, sock: socket.socket):
        self.pid = pid
        self.sock = sock

    @classmethod
    def fork(cls, inherited: tuple[int, ...], log) -> "_Spare | None":
        try:
            ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_STREAM)
        except OSError:
            return None
        try:
            pid = os.fork()
        except OSError:
            ours.close()
            theirs.close()
            return None
        if pid == 0:
            try:
                ours.close()
                _detach(inherited)
                _, fds, _, _ = socket.recv_fds(theirs, 16, 1)
                theirs.close()
            except BaseException:  # noqa: BLE001 - a signal (the resident's group stopped): nothing begun
                os._exit(0)
            if len(fds) != 1:  # the resident closed its end: not needed
                os._exit(0)
            _child(socket.socket(fileno=fds[0]), (), log)  # never returns
        theirs.close()
        return cls(pid, ours)

    def take(self, conn: socket.socket) -> int:
        """Hand ``conn`` to this child; its pid, or 0 if it is gone (fork another)."""
        try:
            socket.send_fds(self.sock, [b"c"], [conn.fileno()])
        except OSError:
            return 0
        finally:
            self.sock.close()
        return self.pid

    def close(self) -> None:
        self.sock.close()


def _warm_cli(where: Path) -> None:
    """One real ``acinoset solve`` of a tiny simulated run, files in and out (in a temporary folder
    of ``where``), so that what the command does around the solve (its parser, the readers, the
    writers, HDF5) is loaded before the first fork too. Never raises."""
    global _serving
    import tempfile

    from graph.io.calibration import default_rig_path, load_calibration, write_anipose_toml
    from graph.io.keypoints import write_dlc_csv
    from graph.simulate import simulate_run

    _serving = True  # this process's own solve: not handed over
    try:
        with tempfile.TemporaryDirectory(dir=where) as tmp:
            d = Path(tmp)
            cal = load_calibration(default_rig_path())
            run = simulate_run(cal, frames=12, seed=0)
            write_anipose_toml(d / "calibration.toml", cal)
            cams = [str(d / f"{name}.csv") for name in cal.names]
            for path, kp in zip(cams, run.keypoints):
                write_dlc_csv(path, kp)
            _entry(ENTRIES[0])(["solve", *cams, "--calibration", str(d / "calibration.toml"), "--fps", str(run.fps),
                                "--out", str(d / "run.csv"), "--h5", str(d / "run.h5"),
                                "--report", str(d / "report.json")])
    except Exception:  # noqa: BLE001 - a colder first solve, nothing worse
        pass
    finally:
        _serving = False


def _say(log, text: str) -> None:
    log.write(f"{time.strftime('%Y-%m-%dT%H:%M:%S')} {text}\n")


def _reap():
    while True:
        try:
            pid, status = os.waitpid(-1, os.WNOHANG)
        except ChildProcessError:
            return
        if pid == 0:
            return
        yield pid, status


def _child(conn: socket.socket, close: tuple[int, ...], log) -> None:
    """A forked child of the resident: steps 2-4 of the protocol; ends the process, whatever is
    raised (never back into the resident's loop, which it shares the code of)."""
    try:
        _serve_request(conn, close, log)
    finally:
        os._exit(1)


def _serve_request(conn: socket.socket, close: tuple[int, ...], log) -> None:
    """Steps 2-4 in a forked child, ending with ``os._exit``. A request it cannot take is one line
    in the resident's log (and the client solves in its own process)."""
    try:
        _detach(close)
        conn.settimeout(ANSWER_TIMEOUT_S)
        request = _read_request(conn)
        conn.sendall(f"pid {os.getpid()}\n".encode())
        if not _take_descriptors(conn):
            os._exit(NOT_TAKEN)
        # from 'run' the client forwards its signals here: held until the solve's own try below
        # (a Ctrl-C handled here, before it, would read as a request not taken: exit 75, no answer)
        signal.pthread_sigmask(signal.SIG_BLOCK, FORWARDED)
        conn.sendall(b"run\n")
    except BaseException as e:  # noqa: BLE001 - the client solves in its own process
        try:
            _say(log, f"child {os.getpid()} did not take its request: {type(e).__name__}: {e}")
            conn.sendall(b"fail\n")
        except BaseException:  # noqa: BLE001
            pass
        os._exit(NOT_TAKEN)
    watch = _ClientWatch(conn)  # its thread keeps the signals blocked: they reach the main thread
    try:
        signal.pthread_sigmask(signal.SIG_UNBLOCK, FORWARDED)  # one that came meanwhile lands here
        code = _run(request, log)
    except KeyboardInterrupt:  # forwarded the moment the client heard ``run``, before the solve began
        print("acinoset: interrupted", file=sys.stderr, flush=True)
        code = 130
    finally:
        signal.pthread_sigmask(signal.SIG_BLOCK, FORWARDED)  # a second Ctrl-C cannot cut the answer short
    code = code if code != NOT_TAKEN else 1
    watch.finished = True
    for fd in (0, 1, 2):  # flushed by _run: the client's pipes are not held open through the teardown
        try:
            os.close(fd)
        except OSError:
            pass
    try:  # the client hears the end now, not after this process's teardown and the resident's reaping
        conn.sendall(f"exit {code}\n".encode())
    except BaseException:  # noqa: BLE001 - the resident reports it when it reaps this process
        pass
    os._exit(code)


class _ClientWatch:
    """A served child's watch on its client: a thread waiting on the connection, on which the
    client sends nothing more once the solve runs. Its end (the client gone: SIGKILL, a crashed
    shell or CI runner) before the solve's own end kills this process with SIGKILL, as a solve in
    the client's own process would have died with it, instead of letting it run on unseen."""

    def __init__(self, conn: socket.socket):
        import threading

        self.finished = False
        self.conn = conn
        threading.Thread(target=self._wait, name="client-watch", daemon=True).start()

    def _wait(self) -> None:
        try:
            self.conn.settimeout(None)
            while self.conn.recv(64):
                pass
        except OSError:
            pass
        if not self.finished:
            os.kill(os.getpid(), signal.SIGKILL)


def _detach(close: tuple[int, ...]) -> None:
    """What a child forked from the resident does first: a process's own signal handling (SIGINT
    a KeyboardInterrupt), none of the resident's descriptors ``close`` held."""
    global _serving
    _serving = True
    signal.set_wakeup_fd(-1)
    for s in (signal.SIGTERM, signal.SIGCHLD, signal.SIGHUP):
        signal.signal(s, signal.SIG_DFL)
    signal.signal(signal.SIGINT, signal.default_int_handler)
    for fd in close:
        os.close(fd)


def _read_request(conn: socket.socket) -> dict:
    """Read the request; take its cwd, environment and umask."""
    (n,) = struct.unpack(">Q", _read_exactly(conn, 8))
    request = json.loads(_read_exactly(conn, n))
    os.chdir(request["cwd"])
    os.environ.clear()
    os.environ.update(request["env"])
    os.umask(int(request["umask"]))
    return request


def _read_exactly(conn: socket.socket, n: int) -> bytes:
    data = b""
    while len(data) < n:
        chunk = conn.recv(min(1 << 20, n - len(data)))
        if not chunk:
            raise ValueError("the request ended early")
        data += chunk
    return data


def _take_descriptors(conn: socket.socket) -> bool:
    """Receive ``go`` with the client's stdin, stdout and stderr and make them this process's 0, 1,
    2 (and ``sys.stdin/stdout/stderr``); False if the client sent no ``go`` (it gave up)."""
    data, fds, _, _ = socket.recv_fds(conn, 64, 3)
    try:
        if data != b"go\n":
            return False
        if len(fds) != 3:
            raise ValueError(f"'go' came with {len(fds)} descriptors, not 3")
        for fd, target in zip(fds, (0, 1, 2)):
            os.dup2(fd, target)
    finally:
        for fd in fds:
            if fd > 2:
                os.close(fd)
    _std_streams()
    return True


def _std_streams() -> None:
    """New ``sys.stdin/stdout/stderr`` on descriptors 0, 1, 2 (now the client's), buffered as
    Python buffers them in a process of its own: by line on a terminal (stderr always), not at
    all with ``PYTHONUNBUFFERED``."""
    import io

    for fd, name in ((0, "stdin"), (1, "stdout"), (2, "stderr")):
        old = getattr(sys, name)
        write = fd > 0
        raw = io.FileIO(fd, "w" if write else "r", closefd=False)
        unbuffered = write and bool(getattr(old, "write_through", False))  # PYTHONUNBUFFERED or -u
        buffered = raw if unbuffered else (io.BufferedWriter(raw) if write else io.BufferedReader(raw))
        stream = io.TextIOWrapper(buffered, encoding=getattr(old, "encoding", None) or "utf-8",
                                  errors="backslashreplace" if fd == 2 else (getattr(old, "errors", None) or "strict"),
                                  line_buffering=write and (fd == 2 or os.isatty(fd)), write_through=unbuffered)
        setattr(sys, name, stream)
        setattr(sys, f"__{name}__", stream)


def _run(request: dict, log) -> int:
    """``entry(argv, commands)`` with its exit status as a process of its own would have it (the
    solve is the child's from its first line: a Ctrl-C forwarded at once lands in here)."""
    try:
        log.close()
        main = _entry(request.get("entry", ENTRIES[0]))
        argv = list(request["argv"])
        sys.argv = ["acinoset", *argv]
        code = main(argv, tuple(tuple(c) for c in request["commands"]))
    except SystemExit as e:
        code = e.code
        if code is None:
            code = 0
        elif not isinstance(code, int):
            print(code, file=sys.stderr)
            code = 1
    except KeyboardInterrupt:  # a Ctrl-C forwarded before the command's own handler was in place
        print("acinoset: interrupted", file=sys.stderr)
        code = 130
    except BaseException:  # noqa: BLE001 - a traceback, as in a process of its own
        import traceback

        traceback.print_exc()
        code = 1
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):
            pass
    return int(code) & 0xFF


def _idle_seconds(env: dict[str, str]) -> float:
    try:
        value = float(env.get(IDLE, DEFAULT_IDLE_S))
    except ValueError:
        return DEFAULT_IDLE_S
    return value if value > 0 else DEFAULT_IDLE_S


def _write_info(fd: int, info: dict) -> None:
    """Overwrite the lock file's JSON in place, padded with spaces to the file's length: never
    truncated first, so that a reader (:func:`residents`) never finds it empty in between."""
    data = json.dumps(info).encode()
    os.pwrite(fd, data.ljust(os.fstat(fd).st_size), 0)


def _unlink_if(path: Path, ino: int) -> None:
    """Remove our socket file, not one a newer resident of the same key has bound since."""
    try:
        if path.stat().st_ino == ino:
            path.unlink()
    except OSError:
        pass


def _prune(place: Place, older_than_s: float = 86400.0) -> None:
    """Remove the files of other keys' residents that are gone and were last used a day ago."""
    for lock in place.dir.glob("*.lock"):
        try:
            recent = time.time() - lock.stat().st_mtime < older_than_s
        except OSError:
            continue
        if lock == place.lock or recent or _held(lock) is not False:
            continue
        for suffix in (".lock", ".sock", ".log"):
            try:
                lock.with_suffix(suffix).unlink()
            except OSError:
                pass


def _held(lock: Path) -> bool | None:
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


# ------------------------------------------------------------------------ ``acinoset resident``


class Resident(namedtuple("Resident", "key pid ready served started last idle_s python current")):
    """A running resident, as its lock file describes it: ``key``, ``pid`` (int or None), ``ready``,
    ``served`` (solves), ``started`` and ``last`` (times or None), ``idle_s``, ``python`` and
    ``current`` (its key is this install's, Python's and environment's)."""

    __slots__ = ()


def residents(env: dict[str, str] | None = None) -> list[Resident]:
    """This user's running residents (their lock held), newest first."""
    env = dict(os.environ) if env is None else env
    d = runtime_dir(env)
    try:
        mine = key_of(env)
    except OSError:
        mine = ""
    out = []
    for lock in d.glob("*.lock"):
        if not _held(lock):
            continue
        try:
            info = json.loads(lock.read_text(encoding="utf-8") or "{}")
        except (OSError, ValueError):
            info = {}
        out.append(Resident(key=lock.stem, pid=info.get("pid"), ready=bool(info.get("ready")),
                            served=int(info.get("served") or 0), started=info.get("started"), last=info.get("last"),
                            idle_s=info.get("idle_s"), python=info.get("python"), current=lock.stem == mine))
    return sorted(out, key=lambda r: -(r.started or 0.0))


def stop(env: dict[str, str] | None = None, wait_s: float = 30.0) -> list[Resident]:
    """Ask every running resident to stop (SIGTERM: solves being served finish first) and wait up
    to ``wait_s`` for them to exit; return those asked."""
    env = dict(os.environ) if env is None else env
    asked = [r for r in residents(env) if r.pid]
    for r in asked:
        _forward(r.pid, signal.SIGTERM)
    d = runtime_dir(env)
    deadline = time.monotonic() + wait_s
    while time.monotonic() < deadline and any(_held(d / f"{r.key}.lock") for r in asked):
        time.sleep(0.05)
    return asked


def register(sub) -> None:
    """``acinoset resident status|stop``."""
    p = sub.add_parser("resident", description="The warm background process that serves 'acinoset solve': "
                       "started by a solve, it exits after " + f"{DEFAULT_IDLE_S / 60:g} minutes without one "
                       f"(${IDLE} seconds). {SWITCH}=0 turns it off.")
    rs = p.add_subparsers(dest="resident_command", required=True, metavar="{status,stop}")
    rs.add_parser("status", help="list this user's resident processes").set_defaults(func=run_status)
    rs.add_parser("stop", help="stop them (a solve being served finishes first)").set_defaults(func=run_stop)


def run_status(args) -> int:
    found = residents()
    if not found:
        off = not wanted(["solve"], dict(os.environ))
        print(f"no resident process ({f'off: {SWITCH}=0' if off else 'the next acinoset solve starts one'})")
        return 0
    now = time.time()
    for r in found:
        state = "ready" if r.ready else "warming up"
        up = f"up {now - r.started:.0f} s" if r.started else "starting"
        last = f", last solve {now - r.last:.0f} s ago" if r.last else ""
        which = "this install" if r.current else "another install, Python or environment"
        idle = f"{r.idle_s:g} s" if r.idle_s else "?"
        print(f"pid {r.pid}: {state}, {up}, served {r.served}{last}; idle exit after {idle}; key {r.key} ({which})")
    return 0


def run_stop(args) -> int:
    asked = stop()
    if not asked:
        print("no resident process")
    for r in asked:
        print(f"stopped pid {r.pid} (key {r.key})")
    return 0
