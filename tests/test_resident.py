"""The warm resident process behind ``acinoset solve`` (graph.app.resident), with real processes.

Each test module's resident lives in its own runtime directory (``XDG_RUNTIME_DIR``) with the switch
turned on only for these tests' commands (conftest.py turns it off for the suite); every resident
started here is stopped at teardown.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest

from graph.app.processes import pid_alive
from graph.app.resident import client, protocol, status
from graph.camera import Calibration
from graph.io.calibration import default_rig_path, load_calibration, write_anipose_toml
from graph.io.keypoints import write_dlc_csv
from graph.simulate import simulate_run

ROOT = Path(__file__).resolve().parents[1]
MARKERS = ["nose", "l_eye", "r_eye", "neck_base", "spine"]
FRAMES = 60
FPS = 90.0
WARM_UP_S = 240  # a resident's warm-up: seconds here once the kernels are cached, a minute or two before


def acinoset(env: dict, *args, cwd: Path | None = None, **kw) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "graph.app.cli", *map(str, args)], capture_output=True, text=True,
                          env=env, cwd=cwd, timeout=300, **kw)


def wait_for(condition, timeout: float, what: str, every: float = 0.05):
    """``condition()``'s first true value, asked every ``every`` seconds (0: without a pause)."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        value = condition()
        if value:
            return value
        time.sleep(every)
    raise AssertionError(f"timed out after {timeout:g} s waiting for {what}")


def ready(env: dict) -> list[status.Resident]:
    return [r for r in status.residents(env) if r.ready and r.current]


def served_lines(env: dict) -> list[str]:
    place = protocol.place_of(env)
    return [line for line in place.log.read_text().splitlines() if " served child " in line]


def settled_served_lines(env: dict) -> list[str]:
    """The log's served lines once the resident serves nothing: each child it has is the spare
    (still in the resident's own folder; a served child works in its client's), and each child it
    reaped is logged (its count in the lock file, written before the log line, is reached)."""
    def settled() -> list[str] | None:
        r = ready(env)[0]
        home = os.readlink(f"/proc/{r.pid}/cwd")
        for c in resident_children(r.pid):
            try:
                if os.readlink(f"/proc/{c}/cwd") != home:
                    return None
            except OSError:  # a zombie, not reaped yet
                return None
        lines = served_lines(env)
        return lines if len(lines) >= r.served else None
    return wait_for(settled, 60, "the resident to serve nothing")


def served_since(env: dict, before: int, count: int = 1) -> list[str]:
    """The log's served lines once ``count`` more than ``before`` are there: the child tells its
    client the end itself, and the resident logs it when it reaps the child, a moment later."""
    wait_for(lambda: len(served_lines(env)) >= before + count, 10, "the resident to log the served solve")
    return served_lines(env)


def write_run(out: Path, frames: int) -> Path:
    """Five markers of a simulated cheetah run seen by three cameras of the AcinoSet rig, written as
    a user brings them: DeepLabCut CSVs and an Anipose calibration.toml."""
    cal = Calibration(load_calibration(default_rig_path()).cameras[:3])
    run = simulate_run(cal, frames=frames, fps=FPS, noise=1.0, outliers=0.0, bodyparts=MARKERS, seed=5)
    write_anipose_toml(out / "calibration.toml", cal)
    for c, kp in enumerate(run.keypoints):
        write_dlc_csv(out / f"cam{c + 1}.csv", kp)
    return out


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory) -> Path:
    return write_run(tmp_path_factory.mktemp("run"), FRAMES)


def solve_args(run_dir: Path, out: Path) -> list:
    """Relative input paths (the resident's child must work in the client's directory)."""
    return ["solve", "cam1.csv", "cam2.csv", "cam3.csv", "--calibration", "calibration.toml", "--method", "fte",
            "--skeleton", "points", "--fps", FPS, "--out", out / "run.csv", "--h5", out / "run.h5",
            "--report", out / "report.json"]


def make_env(runtime: Path, **extra: str) -> dict:
    return {**os.environ, "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""),
            "XDG_RUNTIME_DIR": str(runtime), "ACINOSET_RESIDENT": "1", "ACINOSET_RESIDENT_IDLE": "120", **extra}


def stop_all(env: dict) -> None:
    proc = acinoset(env, "resident", "stop")
    assert proc.returncode == 0, proc.stderr
    assert not status.residents(env)


@pytest.fixture(scope="module")
def env(tmp_path_factory):
    """The environment of a client with the resident on, in a runtime directory of this module."""
    runtime = tmp_path_factory.mktemp("rt")
    e = make_env(runtime)
    yield e
    stop_all(e)


@pytest.fixture(scope="module")
def warm(env, run_dir, tmp_path_factory):
    """A resident started by a first solve (which ran in its own process), warm and listening;
    that first solve's output folder."""
    assert not status.residents(env)
    out = tmp_path_factory.mktemp("first")
    proc = acinoset(env, *solve_args(run_dir, out), cwd=run_dir)
    assert proc.returncode == 0, proc.stderr
    found = wait_for(lambda: ready(env), WARM_UP_S, "the resident to be warm")
    assert len(found) == 1 and found[0].served == 0  # the first solve was not served: it started it
    return out


def same_outputs(a: Path, b: Path) -> None:
    """The CSV to the byte; every H5 dataset exactly; the report but for its timings."""
    assert (a / "run.csv").read_bytes() == (b / "run.csv").read_bytes()
    with h5py.File(a / "run.h5", "r") as fa, h5py.File(b / "run.h5", "r") as fb:
        names = []
        fa.visit(lambda n: names.append(n) if isinstance(fa[n], h5py.Dataset) else None)
        assert names and sorted(names) == sorted(n for n in _datasets(fb))
        for n in names:
            x, y = fa[n][()], fb[n][()]
            assert x.dtype == y.dtype and np.array_equal(x, y, equal_nan=x.dtype.kind == "f"), n
    ra, rb = (json.loads((d / "report.json").read_text()) for d in (a, b))
    ra.pop("seconds"), rb.pop("seconds")
    assert ra == rb


def _datasets(f) -> list[str]:
    names = []
    f.visit(lambda n: names.append(n) if isinstance(f[n], h5py.Dataset) else None)
    return names


def test_a_second_solve_is_served_and_equals_an_in_process_one(env, warm, run_dir, tmp_path):
    here, served = tmp_path / "here", tmp_path / "served"
    here.mkdir()
    served.mkdir()
    alone = acinoset(dict(env, ACINOSET_RESIDENT="0"), *solve_args(run_dir, here), cwd=run_dir)
    assert alone.returncode == 0, alone.stderr
    before = len(served_lines(env))
    proc = acinoset(env, *solve_args(run_dir, served), cwd=run_dir)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.startswith("fte: 60 frames, 3 cameras, 5 markers")
    assert proc.stdout.split(" s -> ")[0].rsplit(",", 1)[0] == alone.stdout.split(" s -> ")[0].rsplit(",", 1)[0]
    assert proc.stderr == alone.stderr  # the same warnings, on the client's stderr
    lines = served_since(env, before)
    assert len(lines) == before + 1 and lines[-1].endswith(" s") and "exit 0" in lines[-1]
    wait_for(lambda: status.residents(env)[0].served == before + 1, 10, "the resident's count")
    same_outputs(here, served)
    same_outputs(warm, served)


def resident_children(pid: int) -> list[int]:
    listed = Path(f"/proc/{pid}/task/{pid}/children")
    if not listed.exists():
        pytest.skip("this kernel does not list a process's children")
    return [int(c) for c in listed.read_text().split()]


def gone(pid: int) -> bool:
    """Exited (a zombie counts: here PID 1 may not reap a dead resident's orphans)."""
    return not pid_alive(pid)


def test_the_next_solve_runs_in_a_child_forked_ahead(env, warm, run_dir, tmp_path):
    """Between solves the resident keeps one child forked ahead; the next solve runs in it (its pid
    is the one the log names), and a new one is forked once that solve has ended."""
    pid = status.residents(env)[0].pid
    spare = wait_for(lambda: resident_children(pid), 30, "a child forked ahead")
    assert len(spare) == 1
    before = len(served_lines(env))
    proc = acinoset(env, *solve_args(run_dir, tmp_path), cwd=run_dir)
    assert proc.returncode == 0, proc.stderr
    lines = served_since(env, before)
    assert f" served child {spare[0]}: exit 0" in lines[-1]
    after = wait_for(lambda: resident_children(pid), 30, "the next child forked ahead")
    assert len(after) == 1 and after != spare
    same_outputs(warm, tmp_path)


def test_an_input_error_is_one_line_and_exit_2_through_the_resident(env, warm, run_dir, tmp_path):
    before = len(served_lines(env))
    proc = acinoset(env, "solve", "cam1.csv", "cam2.csv", "cam3.csv", "--calibration", "missing.toml",
                    "--out", tmp_path / "run.csv", cwd=run_dir)
    assert proc.returncode == 2
    assert proc.stderr.splitlines() == ["acinoset: error: missing.toml: no such file"]
    lines = served_since(env, before)
    assert len(lines) == before + 1 and "exit 2" in lines[-1]


def test_concurrent_clients_each_get_a_child(env, warm, run_dir, tmp_path):
    before = len(served_lines(env))
    outs = [tmp_path / f"p{i}" for i in range(2)]
    procs = []
    for out in outs:
        out.mkdir()
        procs.append(subprocess.Popen([sys.executable, "-m", "graph.app.cli", *map(str, solve_args(run_dir, out))],
                                      env=env, cwd=run_dir, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True))
    for p in procs:
        stdout, stderr = p.communicate(timeout=300)
        assert p.returncode == 0, stderr
    lines = served_since(env, before, 2)
    assert len(lines) == before + 2
    assert len({line.split(" served child ")[1].split(":")[0] for line in lines[-2:]}) == 2  # two children
    same_outputs(outs[0], outs[1])
    same_outputs(warm, outs[0])


def test_ctrl_c_reaches_the_served_solve(env, warm, run_dir, tmp_path):
    """SIGINT to the client is forwarded to its child in the resident: 'interrupted', exit 130."""
    before = len(served_lines(env))
    proc, child = start_long_solve(env, tmp_path)
    proc.send_signal(signal.SIGINT)
    stdout, stderr = proc.communicate(timeout=120)
    if proc.returncode == 0:  # the solve ended before the signal reached it: nothing to check
        pytest.skip("the solve finished before the signal")
    assert proc.returncode == 130, stderr
    assert stderr.splitlines()[-1] == "acinoset: interrupted"
    wait_for(lambda: gone(child), 30, "the child to end")
    assert "exit 130" in served_since(env, before)[-1]


def test_a_ctrl_c_as_the_child_takes_the_solve_is_never_lost(env, warm, run_dir, tmp_path):
    """Ctrl-C to the client the moment the resident's child has its request, on a busy machine: the
    client holds it until the child says 'run', then forwards it at once. Every round ends
    'interrupted' (130), or finished (0, its output written) if the small solve won. Before the
    child held the signals across 'run', a Ctrl-C there was lost: read as a request not taken (no
    answer, exit 1; 3 of 16 rounds here), or it ended the child outside its solve (exit 0, nothing
    written)."""
    busy = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(2)]
    ends = []
    try:
        for i in range(16):
            folder = tmp_path / f"round{i}"
            folder.mkdir()
            for name in ("cam1.csv", "cam2.csv", "cam3.csv", "calibration.toml"):
                (folder / name).symlink_to(run_dir / name)
            proc, _ = start_served_solve(env, folder, every=0)
            proc.send_signal(signal.SIGINT)
            _, stderr = proc.communicate(timeout=120)
            ended = stderr.splitlines()[-1] if proc.returncode else f"wrote run.csv: {(folder / 'run.csv').exists()}"
            ends.append((proc.returncode, ended))
    finally:
        for p in busy:
            p.kill()
            p.wait()
    assert set(ends) <= {(130, "acinoset: interrupted"), (0, "wrote run.csv: True")}, ends
    assert (130, "acinoset: interrupted") in ends


def start_long_solve(env: dict, folder: Path, **popen) -> tuple[subprocess.Popen, int]:
    """A served solve of some seconds (20000 frames), begun: the client process and the resident's
    child that took it (it has entered the client's folder). ``popen``: more of Popen's arguments."""
    big = write_run(folder, 20000)
    return start_served_solve(env, big, **popen)


def start_served_solve(env: dict, folder: Path, every: float = 0.05, **popen) -> tuple[subprocess.Popen, int]:
    """The solve of the run in ``folder``, begun: the client process and the resident's child that
    took it, once it has entered the client's folder (it then answers 'pid', then 'run'), looked for
    every ``every`` seconds (0: seen within microseconds)."""
    pid = status.residents(env)[0].pid
    proc = subprocess.Popen([sys.executable, "-m", "graph.app.cli", *map(str, solve_args(folder, folder))], env=env,
                            cwd=folder, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, **popen)

    def serving() -> list[int]:
        found = []
        for c in resident_children(pid):
            try:
                if os.readlink(f"/proc/{c}/cwd") == str(folder):
                    found.append(c)
            except OSError:  # gone meanwhile
                pass
        return found

    try:
        return proc, wait_for(serving, 60, "the resident's child serving this solve", every)[0]
    except BaseException:
        proc.kill()
        raise


def state(pid: int) -> str:
    """The process's state letter (R, S, T stopped, Z ...); "" when gone."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return ""


def test_a_killed_client_ends_its_served_solve(env, warm, run_dir, tmp_path):
    """SIGKILL cannot be forwarded: the child sees its client's end of the connection close and
    kills itself, rather than solving on unseen."""
    before = len(served_lines(env))
    proc, child = start_long_solve(env, tmp_path)
    proc.kill()
    proc.communicate(timeout=30)
    wait_for(lambda: gone(child), 30, "the child to end with its client")
    assert "signal 9" in served_since(env, before)[-1]


def test_ctrl_z_stops_and_resumes_the_served_solve(env, warm, run_dir, tmp_path):
    """SIGTSTP stops the client and its child; SIGCONT resumes both; the solve then ends as usual.
    (The client leads a process group of its own, whose parent, this test, is in its session: a
    shell's job, not an orphaned group, whatever the test runner's own group is.)"""
    before = len(served_lines(env))
    proc, child = start_long_solve(env, tmp_path, process_group=0)
    # the child has the client's terminal (its stdout) once the hand-over is done
    wait_for(lambda: os.readlink(f"/proc/{child}/fd/1") == os.readlink(f"/proc/{proc.pid}/fd/1"), 30,
             "the child to hold the client's stdout")
    proc.send_signal(signal.SIGTSTP)
    wait_for(lambda: state(child) == "T" and state(proc.pid) == "T", 30, "the client and its child to stop")
    time.sleep(0.3)
    assert state(child) == "T"  # still stopped
    proc.send_signal(signal.SIGCONT)
    wait_for(lambda: state(child) not in ("T", "t"), 30, "the child to resume")
    stdout, stderr = proc.communicate(timeout=300)
    assert proc.returncode == 0, stderr
    assert stdout.startswith("fte: 20000 frames")
    assert "exit 0" in served_since(env, before)[-1]


def test_ctrl_z_in_an_orphaned_process_group_stops_nothing(env, warm, run_dir, tmp_path):
    """With no shell to resume it (a session of its own: an orphaned process group), the kernel
    discards SIGTSTP's stop; the served solve is not left stopped either, and ends as usual."""
    before = len(served_lines(env))
    proc, child = start_long_solve(env, tmp_path, start_new_session=True)
    proc.send_signal(signal.SIGTSTP)
    time.sleep(0.5)
    if proc.poll() is None:
        assert state(proc.pid) not in ("T", "t")
        wait_for(lambda: state(child) not in ("T", "t"), 10, "the child to go on")
    stdout, stderr = proc.communicate(timeout=300)
    assert proc.returncode == 0, stderr
    assert "exit 0" in served_since(env, before)[-1]


def test_the_off_switch(env, warm, run_dir, tmp_path):
    before = len(settled_served_lines(env))
    proc = acinoset(dict(env, ACINOSET_RESIDENT="0"), *solve_args(run_dir, tmp_path), cwd=run_dir)
    assert proc.returncode == 0, proc.stderr
    assert len(served_lines(env)) == before


def test_a_changed_key_starts_a_new_resident(env, warm, run_dir, tmp_path):
    """An environment variable that may change what is imported or compiled (here an ACINOSET_ one)
    makes a new key: that solve runs in its own process and starts a second resident."""
    other = dict(env, ACINOSET_KEY_PROBE="1")
    assert protocol.key_of(other) != protocol.key_of(env)
    before = len(settled_served_lines(env))
    proc = acinoset(other, *solve_args(run_dir, tmp_path), cwd=run_dir)
    assert proc.returncode == 0, proc.stderr
    assert len(served_lines(env)) == before  # not served by the first one
    new = wait_for(lambda: ready(other), WARM_UP_S, "a second resident")
    assert len(status.residents(env)) == 2 and new[0].key != ready(env)[0].key
    proc = acinoset(other, "resident", "status")
    assert proc.returncode == 0 and len(proc.stdout.splitlines()) == 2
    assert sum("(this install)" in line for line in proc.stdout.splitlines()) == 1


def test_a_hung_resident_leaves_the_solve_to_the_client(env, warm, run_dir, tmp_path):
    """A resident that accepts but does not answer (stopped here with SIGSTOP): after the
    hand-over's timeout the client solves in its own process; the resident, continued, runs nothing."""
    pid = ready(env)[0].pid
    before = len(settled_served_lines(env))
    os.kill(pid, signal.SIGSTOP)
    try:
        t0 = time.monotonic()
        proc = acinoset(env, *solve_args(run_dir, tmp_path), cwd=run_dir)
        waited = time.monotonic() - t0
    finally:
        os.kill(pid, signal.SIGCONT)
    assert proc.returncode == 0, proc.stderr
    assert waited >= protocol.ANSWER_TIMEOUT_S and proc.stdout.startswith("fte: 60 frames")
    same_outputs(warm, tmp_path)
    log = protocol.place_of(env).log
    wait_for(lambda: "ran no solve" in log.read_text(), 30, "the resident to drop the request")
    assert len(served_lines(env)) == before


def test_a_killed_resident_is_replaced(env, warm, run_dir, tmp_path):
    """SIGKILL leaves its socket file behind: the next solve runs in its own process and starts a new one."""
    place = protocol.place_of(env)
    old = ready(env)[0].pid
    os.kill(old, signal.SIGKILL)
    wait_for(lambda: not any(r.current for r in status.residents(env)), 30, "its lock to be free")
    assert place.socket.exists()
    proc = acinoset(env, *solve_args(run_dir, tmp_path), cwd=run_dir)
    assert proc.returncode == 0, proc.stderr
    new = wait_for(lambda: ready(env), WARM_UP_S, "a new resident")
    assert new[0].pid != old


def test_resident_stop(env, warm, run_dir, tmp_path):
    place = protocol.place_of(env)
    pid = status.residents(env)[0].pid
    spare = wait_for(lambda: resident_children(pid), 30, "a child forked ahead")
    proc = acinoset(env, "resident", "stop")
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.startswith("stopped pid ")
    assert not status.residents(env) and not place.socket.exists()
    assert "exit: stopped (SIGTERM)" in place.log.read_text()
    wait_for(lambda: all(gone(c) for c in spare), 10, "the child forked ahead to end with the resident")
    proc = acinoset(env, "resident", "status")
    assert proc.returncode == 0 and proc.stdout.startswith("no resident process")
    # with none up, a solve runs in its own process (and starts one again)
    proc = acinoset(env, *solve_args(run_dir, tmp_path), cwd=run_dir)
    assert proc.returncode == 0, proc.stderr
    wait_for(lambda: ready(env), WARM_UP_S, "a new resident")


def test_a_resident_exits_when_idle(run_dir, tmp_path_factory, tmp_path):
    e = make_env(tmp_path_factory.mktemp("idle"), ACINOSET_RESIDENT_IDLE="1")
    try:
        proc = acinoset(e, *solve_args(run_dir, tmp_path), cwd=run_dir)
        assert proc.returncode == 0, proc.stderr
        place = protocol.place_of(e)
        wait_for(lambda: place.log.exists() and "listening" in place.log.read_text(), WARM_UP_S, "warm")
        wait_for(lambda: not status.residents(e), 30, "the idle exit")
        assert "exit: idle for 1 s" in place.log.read_text() and not place.socket.exists()
    finally:
        stop_all(e)


def test_two_clients_at_once_start_one_resident(run_dir, tmp_path_factory, tmp_path):
    e = make_env(tmp_path_factory.mktemp("two"))
    try:
        procs = []
        for i in range(2):
            (tmp_path / f"p{i}").mkdir()
            procs.append(subprocess.Popen([sys.executable, "-m", "graph.app.cli",
                                           *map(str, solve_args(run_dir, tmp_path / f"p{i}"))],
                                          env=e, cwd=run_dir, stdout=subprocess.PIPE, stderr=subprocess.PIPE))
        for p in procs:
            p.communicate(timeout=300)
            assert p.returncode == 0
        wait_for(lambda: ready(e), WARM_UP_S, "warm")
        time.sleep(0.5)
        assert len(status.residents(e)) == 1
    finally:
        stop_all(e)


def test_the_client_imports_nothing_heavy(tmp_path):
    """Deciding, computing the key and trying the socket load neither numpy nor the solver."""
    code = (
        "import os, sys\n"
        "from graph.app.resident import client, protocol\n"
        "from graph.app.cli import COMMANDS\n"
        "env = dict(os.environ)\n"
        "assert client.wanted(['solve', 'a.csv'], env)\n"
        "place = protocol.place_of(env)\n"
        "assert client._hand_over(place, ['solve', 'a.csv'], COMMANDS, env, protocol.ENTRIES[0]) is None\n"
        "print([m for m in ('numpy', 'numba', 'gtsam', 'scipy', 'h5py', 'cv2', 'graph.api') if m in sys.modules])\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=make_env(tmp_path))
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == "[]"


def test_the_directory_must_be_private(tmp_path):
    (tmp_path / "acinoset").mkdir(mode=0o755)
    os.chmod(tmp_path / "acinoset", 0o755)
    with pytest.raises(OSError):
        protocol.runtime_dir({"XDG_RUNTIME_DIR": str(tmp_path)})
    assert not client.wanted(["solve", "--help"], {}) and not client.wanted(["solve"], {"ACINOSET_RESIDENT": "0"})
    assert not client.wanted(["solve"], {"NUMBA_THREADING_LAYER": "omp"}) and client.wanted(["solve"], {})


def test_a_resident_runs_only_the_command_lines_it_knows():
    """The request names the command line to run as module:function; only those of ENTRIES are
    imported (a request is the user's own, but a resident runs nothing it was not made for)."""
    assert protocol.entry_function("graph.app.cli:main").__module__ == "graph.app.cli"
    for name in ("os:system", "graph.app.cli:_run", "graph.app.cli"):
        with pytest.raises(ValueError):
            protocol.entry_function(name)


def test_a_listener_that_is_not_the_resident_gets_nothing(run_dir, tmp_path):
    """Another process listening at the resident's socket path (possible in a shared runtime folder):
    the client sent it the solve's argv, folder, whole environment and its terminal (security issue
    25). It checks the listener's credentials first (SO_PEERCRED: this uid and the pid in the lock the
    resident holds); here the lock is held and names another pid, the listener gets no byte, and the
    solve runs in the client's own process."""
    import fcntl
    import socket
    import threading

    env = make_env(tmp_path / "rt")
    place = protocol.place_of(env)
    place.dir.mkdir(parents=True, exist_ok=True)
    lock = os.open(place.lock, os.O_RDWR | os.O_CREAT, 0o600)
    fcntl.flock(lock, fcntl.LOCK_EX)  # held, as a live resident holds it, naming a pid not the listener's
    os.write(lock, json.dumps({"pid": 1, "key": place.key, "ready": True}).encode())
    listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    listener.bind(str(place.socket))
    listener.listen(4)
    received: list[bytes] = []

    def serve():
        listener.settimeout(60)
        try:
            conn, _ = listener.accept()
        except OSError:
            return
        conn.settimeout(5)
        try:
            while chunk := conn.recv(65536):
                received.append(chunk)
        except OSError:
            pass
        conn.close()

    thread = threading.Thread(target=serve, daemon=True)
    thread.start()
    try:
        out = tmp_path / "out"
        out.mkdir()
        proc = acinoset(env, *solve_args(run_dir, out), cwd=run_dir)
        assert proc.returncode == 0, proc.stderr
        assert (out / "run.csv").is_file()
        thread.join(10)
        assert b"".join(received) == b"", b"".join(received)[:200]
    finally:
        listener.close()
        os.close(lock)


def test_only_what_a_solve_reads_of_the_environment_is_sent():
    env = {"ACINOSET_RESIDENT_IDLE": "60", "NUMBA_NUM_THREADS": "2", "OMP_NUM_THREADS": "1", "HOME": "/home/a",
           "PATH": "/usr/bin", "LC_ALL": "C.UTF-8", "COLUMNS": "120", "PYTHONPATH": "/src",
           "AWS_SECRET_ACCESS_KEY": "k", "GITHUB_TOKEN": "t", "SSH_AUTH_SOCK": "/tmp/ssh", "OTHER": "x"}
    sent = client.solve_env(env)
    assert set(sent) == {"ACINOSET_RESIDENT_IDLE", "NUMBA_NUM_THREADS", "OMP_NUM_THREADS", "HOME", "PATH", "LC_ALL",
                         "COLUMNS", "PYTHONPATH"}
    assert all(sent[k] == env[k] for k in sent)
