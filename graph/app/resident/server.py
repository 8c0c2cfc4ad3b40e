"""The resident itself: warm up, listen, fork a child per solve, run the command line in it with the
client's descriptors, environment and folder, and report its end (:mod:`graph.app.resident`)."""

from __future__ import annotations

import json
import os
import signal
import socket
import struct
import sys
import time
from pathlib import Path

from graph import __version__
from graph.app.resident import protocol
from graph.app.resident.protocol import (
    ANSWER_TIMEOUT_S,
    ENTRIES,
    FORWARDED,
    KEY_CHECK_S,
    NOT_TAKEN,
    Place,
    entry_function,
    idle_seconds,
    key_of,
    lock_held,
    read_exactly,
    runtime_dir,
)


def serve(lock_fd: int, key: str) -> None:
    """The resident's body (run by :func:`start`): warm up, then serve until idle, stopped or stale."""
    env = dict(os.environ)  # the starting client's: the key is computed on it
    place = Place(runtime_dir(env), key)
    if key_of(env) != key:  # this Python imports other code than the client did
        return
    log = open(place.log, "w", buffering=1, encoding="utf-8")
    idle = idle_seconds(env)
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

    for module in ("graph.app.cli", "graph.api", "graph.io.results", "graph.solve.kernels", "graph.kinematics",
                   "graph.io.calibration", "graph.io.keypoints",
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
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        place.socket.unlink()  # a killed resident's
    except FileNotFoundError:
        pass
    sock.bind(str(place.socket))
    os.chmod(place.socket, 0o600)
    sock.listen(64)
    listener: socket.socket | None = sock  # None once it stops listening
    ino = place.socket.stat().st_ino
    info["ready"] = True
    _write_info(lock_fd, info)
    say(f"warm in {time.perf_counter() - t0:.1f} s; listening on {place.socket} (idle exit after {idle:g} s)")

    wake_r, wake_w = os.pipe()
    os.set_blocking(wake_r, False)
    os.set_blocking(wake_w, False)
    signal.set_wakeup_fd(wake_w)
    held = (sock.fileno(), wake_r, wake_w, lock_fd)  # the resident's own: a child closes them
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
    import tempfile

    from graph.io.calibration import default_rig_path, load_calibration, write_anipose_toml
    from graph.io.keypoints import write_dlc_csv
    from graph.simulate import simulate_run

    protocol.serving = True  # this process's own solve: not handed over
    try:
        with tempfile.TemporaryDirectory(dir=where) as tmp:
            d = Path(tmp)
            cal = load_calibration(default_rig_path())
            run = simulate_run(cal, frames=12, seed=0)
            write_anipose_toml(d / "calibration.toml", cal)
            cams = [str(d / f"{name}.csv") for name in cal.names]
            for path, kp in zip(cams, run.keypoints):
                write_dlc_csv(path, kp)
            entry_function(ENTRIES[0])(["solve", *cams, "--calibration", str(d / "calibration.toml"),
                                        "--fps", str(run.fps), "--out", str(d / "run.csv"), "--h5", str(d / "run.h5"),
                                        "--report", str(d / "report.json")])
    except Exception:  # noqa: BLE001 - a colder first solve, nothing worse
        pass
    finally:
        protocol.serving = False


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
    protocol.serving = True
    signal.set_wakeup_fd(-1)
    for s in (signal.SIGTERM, signal.SIGCHLD, signal.SIGHUP):
        signal.signal(s, signal.SIG_DFL)
    signal.signal(signal.SIGINT, signal.default_int_handler)
    for fd in close:
        os.close(fd)


def _read_request(conn: socket.socket) -> dict:
    """Read the request; take its cwd, environment and umask."""
    (n,) = struct.unpack(">Q", read_exactly(conn, 8))
    request = json.loads(read_exactly(conn, n))
    os.chdir(request["cwd"])
    os.environ.clear()
    os.environ.update(request["env"])
    os.umask(int(request["umask"]))
    return request


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
        main = entry_function(request.get("entry", ENTRIES[0]))
        argv = list(request["argv"])
        sys.argv = ["acinoset", *argv]
        code = main(argv, tuple(tuple(c) for c in request["commands"]))
    except SystemExit as e:
        if e.code is None:
            code = 0
        elif isinstance(e.code, int):
            code = e.code
        else:
            print(e.code, file=sys.stderr)
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
        if lock == place.lock or recent or lock_held(lock) is not False:
            continue
        for suffix in (".lock", ".sock", ".log"):
            try:
                lock.with_suffix(suffix).unlink()
            except OSError:
                pass
