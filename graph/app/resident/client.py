"""The client's side of the resident: ``acinoset solve`` hands its solve to a warm resident, or solves
in its own process and starts one (:mod:`graph.app.resident` describes the protocol). It imports
nothing heavy (no numpy, numba or gtsam)."""

from __future__ import annotations

import fcntl
import json
import os
import signal
import socket
import struct
import sys
import time
from collections.abc import Callable

from graph.app.processes import pid_alive
from graph.app.resident import protocol
from graph.app.resident.protocol import (
    ANSWER_TIMEOUT_S,
    CONNECT_TIMEOUT_S,
    ENTRIES,
    FORWARDED,
    JOB_CONTROL,
    SWITCH,
    Lines,
    Place,
    place_of,
)


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
    if protocol.serving or not wanted(argv, env):
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


# what of the client's environment a solve reads (its options, numba's and the BLAS' threads, the
# locale, the terminal's width for the progress bar, temporary and cache folders, the path to ffmpeg)
SOLVE_ENV_PREFIXES = ("ACINOSET_", "NUMBA_", "OMP_", "OPENBLAS_", "MKL_", "XDG_", "LC_", "PYTHON")
SOLVE_ENV_NAMES = frozenset({"HOME", "PATH", "LANG", "LANGUAGE", "TMPDIR", "TEMP", "TMP", "TERM", "COLUMNS", "LINES",
                             "NO_COLOR", "TZ", "USER", "LOGNAME", "MPLBACKEND", "MPLCONFIGDIR"})


def solve_env(env: dict[str, str]) -> dict[str, str]:
    """The part of the client's environment the resident's child runs the solve in: what a solve
    reads, not the rest (a shell's tokens and keys stay in the client)."""
    return {k: v for k, v in env.items() if k in SOLVE_ENV_NAMES or k.startswith(SOLVE_ENV_PREFIXES)}


def trusted_peer(sock: socket.socket, place: Place) -> bool:
    """Whether the process listening at the other end of ``sock`` is this user's resident of
    ``place``: its uid is ours and its pid is the one the resident wrote in the lock it holds
    (``SO_PEERCRED``: the kernel's word, not the peer's). A socket path in a shared runtime folder
    could be bound by another user's process; a solve's argv, folder, environment and terminal
    must not go to it."""
    try:
        creds = sock.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED, struct.calcsize("3i"))
    except (OSError, AttributeError):  # no SO_PEERCRED on this system: no way to know, so no
        return False
    pid, uid, _ = struct.unpack("3i", creds)
    if uid != os.getuid() or not protocol.lock_held(place.lock):
        return False
    try:
        info = json.loads(place.lock.read_text(encoding="utf-8") or "{}")
    except (OSError, ValueError):
        return False
    return isinstance(info, dict) and info.get("pid") == pid


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
        if not trusted_peer(sock, place):  # nothing is sent to a listener that is not our resident
            raise OSError("the process listening on the resident's socket is not its resident")
        sock.settimeout(ANSWER_TIMEOUT_S)
        umask = os.umask(0o022)
        os.umask(umask)
        body = json.dumps({"argv": argv, "cwd": os.getcwd(), "env": solve_env(env), "umask": umask, "entry": entry,
                           "commands": [[c.name, c.module, c.help] for c in commands]}).encode()
        sock.sendall(struct.pack(">Q", len(body)) + body)
        lines = Lines(sock)
        answer = lines.next()
        pid = int(answer.split()[1]) if answer.startswith("pid ") else 0
        if pid > 0:
            signals.stops_with(pid)
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
    while pid_alive(pid):
        time.sleep(0.05)
    print("acinoset: error: the resident process serving this solve was stopped; run it again "
          f"(or with {SWITCH}=0)", file=sys.stderr)
    return 1


class _Signals:
    """The client's handlers of :data:`FORWARDED` while it hands a solve over: signals that come
    before the child runs are kept, and sent to it once it does (:meth:`forward_to`). Job control
    (Ctrl-Z, and the shell's SIGCONT) reaches the child from the moment it answers with its pid
    (:meth:`stops_with`): a Ctrl-Z in the hand-over stops the child with the client, so neither
    runs on while the shell holds the job stopped."""

    def __init__(self) -> None:
        self.pid = 0  # the child running the solve: every forwarded signal goes to it
        self.child = 0  # the child that answered: it stops and resumes with this process
        self.pending: list[int] = []
        self.previous = {s: signal.signal(s, self._handle) for s in FORWARDED + JOB_CONTROL}

    def _handle(self, signum: int, _frame) -> None:
        if signum == signal.SIGTSTP:  # Ctrl-Z: the child stops with us; we stop as we would have
            self._stop_together()
        elif signum == signal.SIGCONT:
            if self.child:
                forward_signal(self.child, signal.SIGCONT)
        elif self.pid:
            forward_signal(self.pid, signum)
        else:
            self.pending.append(signum)

    def _stop_together(self) -> None:
        """Stop the child (SIGSTOP: in the resident's session, its own SIGTSTP would be discarded),
        then this process as SIGTSTP's default would. In an orphaned process group (no shell to
        resume it) the kernel discards that: then the child goes on too. Whether this process
        stopped shows as a SIGCONT pending once it runs again (held blocked meanwhile); its handler
        resumes the child."""
        if self.child:
            forward_signal(self.child, signal.SIGSTOP)
        signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGCONT})
        try:
            signal.signal(signal.SIGTSTP, signal.SIG_DFL)
            os.kill(os.getpid(), signal.SIGTSTP)  # stopped here until a SIGCONT, unless discarded
            signal.signal(signal.SIGTSTP, self._handle)
            stopped = signal.SIGCONT in signal.sigpending()
        finally:
            signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGCONT})
        if not stopped and self.child:
            forward_signal(self.child, signal.SIGCONT)

    def stops_with(self, pid: int) -> None:
        self.child = pid

    def forward_to(self, pid: int) -> None:
        self.pid = self.child = pid
        for signum in self.pending:
            forward_signal(pid, signum)
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


def forward_signal(pid: int, signum: int) -> None:
    try:
        os.kill(pid, signum)
    except OSError:
        pass


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

        code = "import sys; from graph.app.resident.server import serve; serve(int(sys.argv[1]), sys.argv[2])"
        subprocess.Popen([sys.executable, "-c", code, str(fd), place.key], stdin=subprocess.DEVNULL,
                         stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, close_fds=True, pass_fds=(fd,),
                         start_new_session=True, cwd=str(place.dir), env=env)
        return True
    except OSError:
        return False
    finally:
        os.close(fd)  # the resident's copy keeps the lock
