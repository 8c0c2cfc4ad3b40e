"""Real servers for the service and page tests: ``python -m service serve`` (and ``worker``, and
Debian's ``redis-server``) in subprocesses on free loopback ports, the ``acinoset`` commands run as
an admin runs them, simulated runs written as a user would bring them, and a small HTTP client."""

from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import httpx

from graph.app.processes import pid_alive

ROOT = Path(__file__).resolve().parents[1]
PY = sys.executable


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


_compiled = False


def compile_kernels(timeout: float = 1200) -> None:
    """Compile the solver's kernels into numba's on-disk cache once per test session, before the
    first server starts: a fresh checkout compiles for minutes, which no job's timeout should pay.
    Later processes (servers, workers, resident) load the cache in about a second."""
    global _compiled
    if _compiled:
        return
    subprocess.run([PY, "-c", "from graph.app.warmup import warm_up; warm_up()"], cwd=ROOT, check=True,
                   timeout=timeout, capture_output=True)
    _compiled = True


def acinoset(*args: str, timeout: float = 60) -> subprocess.CompletedProcess:
    """``acinoset ARGS...`` (the service's command line, as ``python -m service``), run from the checkout."""
    return subprocess.run([PY, "-m", "service", *args], cwd=ROOT, capture_output=True, text=True, timeout=timeout)


# -- simulated runs ------------------------------------------------------------------------------

@dataclass
class Run:
    dir: Path
    cams: list[Path]
    calibration: Path  # Anipose TOML
    scene: Path  # AcinoSet JSON
    fps: float
    frames: int


def library_csv(run: Run, window_frames: int, folder: Path) -> bytes:
    """The CSV the library writes for ``run`` solved in memory in windows of ``window_frames`` (``fte``,
    every other option at its default): what a long job's CSV must be, byte for byte."""
    import warnings

    from graph.api import solve
    from graph.io.calibration import load_calibration
    from graph.io.keypoints import read_keypoints
    from graph.io.results import write_anipose_csv
    from graph.types import SolveOptions

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        whole = solve([read_keypoints(p) for p in run.cams], load_calibration(run.calibration),
                      SolveOptions(fps=run.fps, window_frames=window_frames))
    write_anipose_csv(folder / "library.csv", whole)
    return (folder / "library.csv").read_bytes()


def make_run(out: Path, frames: int, cameras: int = 6, seed: int = 0) -> Run:
    """A simulated cheetah run on the AcinoSet rig (its first ``cameras`` cameras), written as
    DeepLabCut CSVs plus the calibration in both formats."""
    from graph.camera import Calibration
    from graph.io.calibration import default_rig_path, load_calibration, write_acinoset_json
    from graph.simulate import simulate_run, write_run

    cal = load_calibration(default_rig_path())
    if cameras < len(cal):
        cal = Calibration(cameras=cal.cameras[:cameras])
    run = simulate_run(cal, frames=frames, seed=seed)
    write_run(run, out)
    scene = out / "scene.json"
    write_acinoset_json(scene, cal)
    cams = [out / f"{name}.csv" for name in cal.names]
    return Run(out, cams, out / "calibration.toml", scene, run.fps, frames)


def make_filmed_run(out: Path, frames: int, cameras: int = 3, fps: float = 30.0) -> tuple[Run, list[Path]]:
    """A simulated run on the first ``cameras`` cameras of the AcinoSet rig, scaled down, with each
    camera's footage (``acinoset simulate --videos``' renderer)."""
    from graph.camera import Calibration
    from graph.io.calibration import default_rig_path, load_calibration
    from graph.simulate import simulate_run, write_run
    from graph.video import scaled_rig, write_simulated_videos

    rig = scaled_rig(load_calibration(default_rig_path()), 0.1)
    rig = Calibration(cameras=rig.cameras[:cameras])
    run = simulate_run(rig, frames=frames, fps=fps, seed=4)
    write_run(run, out)
    videos = write_simulated_videos(run, out)
    cams = [out / f"{n}.csv" for n in rig.names]
    return Run(out, cams, out / "calibration.toml", out / "scene.json", fps, frames), videos


def submit_with_videos(client: httpx.Client, run: Run, videos: list[Path] | None = None,
                       paths: list[str] | None = None) -> httpx.Response:
    """A job of ``run`` (``tri``) with its videos as uploads or as ``video_paths``."""
    import json

    files = [("keypoints", (p.name, p.read_bytes(), "text/csv")) for p in run.cams]
    files.append(("calibration", (run.calibration.name, run.calibration.read_bytes(), "application/octet-stream")))
    files += [("videos", (v.name, v.read_bytes(), "video/mp4")) for v in videos or []]
    data = {"options": json.dumps({"method": "tri", "fps": run.fps})}
    if paths:
        data["video_paths"] = paths
    return client.post("/v1/jobs", files=files, data=data)


# -- users ---------------------------------------------------------------------------------------

def add_user(data_dir: Path, name: str, admin: bool = False) -> str:
    """A user made the way ``acinoset users add`` does; returns its token."""
    from service.store import Store

    store = Store(Path(data_dir) / "acinoset.db")
    _, token = store.add_user(name, admin=admin)
    store.close()
    return token


def server_with_users(data_dir: Path, log: Path, users: tuple[str, ...] = ("alice", "bob"),
                      admins: tuple[str, ...] = ()) -> "Server":
    """An embedded server on ``data_dir``, started, with these users and admins; ``.tokens`` maps
    each name to its token (the service tests' ``alice`` and ``bob`` fixtures use them)."""
    tokens = {name: add_user(data_dir, name) for name in users}
    tokens.update({name: add_user(data_dir, name, admin=True) for name in admins})
    srv = Server(data_dir, log).start()
    srv.tokens = tokens
    return srv


# -- processes -----------------------------------------------------------------------------------

class Proc:
    """A subprocess in a process group of its own (so kill -9 reaches everything it started)."""

    def __init__(self, args: list[str], log: Path, env: dict | None = None):
        self.args = args
        self.log_path = log
        self.env = {**os.environ, "PYTHONUNBUFFERED": "1", **(env or {})}
        self.p: subprocess.Popen | None = None

    def start(self) -> "Proc":
        self._log = open(self.log_path, "ab")
        self.p = subprocess.Popen(self.args, cwd=ROOT, env=self.env, stdout=self._log, stderr=subprocess.STDOUT,
                                  stdin=subprocess.DEVNULL, start_new_session=True)
        return self

    @property
    def pid(self) -> int:
        assert self.p is not None
        return self.p.pid

    def alive(self) -> bool:
        return self.p is not None and self.p.poll() is None

    def kill9(self) -> None:
        """SIGKILL to the whole process group: the process and every child it forked."""
        if self.p is None:
            return
        self._kill_group()
        self.p.wait(timeout=30)

    def _kill_group(self) -> None:
        try:
            os.killpg(self.p.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass

    def stop(self, timeout: float = 30) -> int | None:
        if self.p is None or self.p.poll() is not None:
            return self.p.returncode if self.p else None
        self.p.send_signal(signal.SIGTERM)
        try:
            return self.p.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            self.kill9()
            return None
        finally:
            self._kill_group()  # nothing of its process group may outlive the test

    def log(self) -> str:
        return self.log_path.read_text(errors="replace") if self.log_path.exists() else ""


def wait_answering(url: str, proc: Proc, timeout: float = 60, ready: tuple[int, ...] = (200, 503)) -> None:
    """Until the server ``proc`` at ``url`` answers ``/healthz`` with a status in ``ready``; its log
    in the error when it exits or stays silent."""
    deadline = time.time() + timeout
    while time.time() < deadline:
        if not proc.alive():
            raise RuntimeError(f"server exited:\n{proc.log()}")
        try:
            if httpx.get(url + "/healthz", timeout=2).status_code in ready:
                return
        except httpx.HTTPError:
            pass
        time.sleep(0.1)
    raise RuntimeError(f"server did not answer in {timeout} s:\n{proc.log()}")


class Server(Proc):
    def __init__(self, data_dir: Path, log: Path, backend: str = "embedded", workers: int = 2,
                 redis_url: str | None = None, env: dict | None = None, port: int | None = None):
        self.port = port or free_port()
        self.data_dir = Path(data_dir)
        args = [PY, "-m", "service", "serve", "--port", str(self.port), "--data-dir", str(data_dir),
                "--backend", backend, "--workers", str(workers), "--log-level", "warning"]
        if redis_url:
            args += ["--redis-url", redis_url]
        super().__init__(args, log, env)

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def start(self, timeout: float = 60, ready: tuple[int, ...] = (200, 503)) -> "Server":
        """Start it and wait until ``/healthz`` answers with one of ``ready`` (503: up, its backend
        not yet able to run jobs)."""
        compile_kernels()
        super().start()
        wait_answering(self.url, self, timeout, ready)
        return self

    def client(self, token: str | None = None, timeout: float = 60) -> httpx.Client:
        headers = {"Authorization": f"Bearer {token}"} if token else {}
        return httpx.Client(base_url=self.url, headers=headers, timeout=timeout)


class Redis(Proc):
    def __init__(self, workdir: Path, log: Path, port: int | None = None, config: tuple[str, ...] = ()):
        """``config``: more of redis-server's options (``("--proto-max-bulk-len", "1mb")``)."""
        self.port = port or free_port()
        workdir.mkdir(parents=True, exist_ok=True)
        super().__init__(["redis-server", "--port", str(self.port), "--bind", "127.0.0.1", "--dir", str(workdir),
                          "--appendonly", "yes", "--appendfsync", "always", "--save", "", *config], log)

    @property
    def url(self) -> str:
        return f"redis://127.0.0.1:{self.port}/0"

    def start(self, timeout: float = 20) -> "Redis":
        super().start()
        deadline = time.time() + timeout
        while time.time() < deadline:
            try:
                with socket.create_connection(("127.0.0.1", self.port), timeout=1) as s:
                    s.sendall(b"PING\r\n")
                    if s.recv(16).startswith((b"+PONG", b"-NOAUTH")):  # up (with a password: asks for it)
                        return self
            except OSError:
                time.sleep(0.05)
        raise RuntimeError(f"redis-server did not start:\n{self.log()}")


def worker(redis_url: str, log: Path, name: str, env: dict | None = None, data_dir: Path | None = None) -> Proc:
    """``data_dir``: the server's, shared with the worker (ACINOSET_SHARED_DATA_DIR)."""
    where = ["--data-dir", str(data_dir)] if data_dir is not None else []
    return Proc([PY, "-m", "service", "worker", "--redis-url", redis_url, "--name", name, "--log-level", "warning",
                 *where], log, env)


def have_redis() -> bool:
    return shutil.which("redis-server") is not None


# fast failure detection for the tests: workers heartbeat every second, a run is lost after 6 s
ENV = {"ACINOSET_LEASE_SECONDS": "6", "ACINOSET_HEARTBEAT_SECONDS": "1"}


# the smallest largest value Redis takes (512 MB by default): any archive over 1 MB travels in chunks
SMALL_VALUES = ("--proto-max-bulk-len", "1mb")


class Pool:
    """A redis-server of the RQ tests' own (small values, ``ENV``'s quick failure detection) and the
    workers started over it, by name; ``stop`` ends the workers (their work horses killed) and Redis."""

    def __init__(self, base, redis_port=None):
        self.base = base
        self.redis = Redis(base / "redis", base / "redis.log", port=redis_port, config=SMALL_VALUES)
        self.workers = {}

    def start_redis(self):
        self.redis.start()

    def redis_back(self):
        """A new redis-server on the killed one's port and folder (its append-only file kept)."""
        self.redis = Redis(self.base / "redis", self.base / "redis2.log", port=self.redis.port, config=SMALL_VALUES)
        self.start_redis()

    def start_workers(self, names=("w1", "w2"), data_dir: Path | None = None):
        for n in names:
            self.workers[n] = worker(self.redis.url, self.base / f"{n}.log", n, ENV, data_dir).start()

    def wait_idle(self, timeout: float = 300):
        """Until every worker started is registered in Redis and idle (a worker registers once its
        warm-up is done; a long job invites helpers only for the workers idle when it starts)."""
        from redis import Redis as Client
        from rq import Worker

        conn = Client.from_url(self.redis.url)
        deadline = time.time() + timeout
        while time.time() < deadline:
            idle = {w.name for w in Worker.all(connection=conn) if w.get_state() == "idle"}
            if set(self.workers) <= idle:
                return
            time.sleep(0.2)
        raise AssertionError(f"workers {sorted(set(self.workers) - idle)} not idle after {timeout} s")

    def busy_worker(self, name):
        """(worker process, its work horse's pid) for the worker running a job."""
        proc = self.workers[name]
        deadline = time.time() + 30
        while time.time() < deadline:
            kids = children(proc.pid)
            if kids:
                return proc, kids[0]
            time.sleep(0.05)
        raise AssertionError(f"worker {name} has no work horse")

    def kill_worker(self, name):
        """kill -9 a worker and its work horse (RQ puts the horse in a process group of its own), as
        when the machine dies."""
        proc = self.workers[name]
        horses = children(proc.pid)
        proc.kill9()
        for pid in horses:
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass

    def stop(self):
        for name, w in self.workers.items():
            for pid in children(w.pid) if w.alive() else []:
                try:
                    os.kill(pid, signal.SIGKILL)
                except ProcessLookupError:
                    pass
            w.stop(10)
        self.redis.stop(10)


def rq_server(base, user: str, shared: bool = False) -> tuple[Pool, str, Server]:
    """Redis and a server on the RQ backend over it, no worker yet: the pool, a user's token, the server
    (``shared``: sharing its data dir, ``base / "data"``, with the workers)."""
    pool = Pool(base)
    pool.start_redis()
    token = add_user(base / "data", user)
    env = {**ENV, "ACINOSET_SHARED_DATA_DIR": "1"} if shared else ENV
    return pool, token, Server(base / "data", base / "server.log", backend="rq", redis_url=pool.redis.url,
                               env=env).start()


# -- the API -------------------------------------------------------------------------------------

def submit(client: httpx.Client, run: Run, options: dict | None = None, calibration: Path | None = None,
           cams: list[Path] | None = None) -> httpx.Response:
    import json

    files = [("keypoints", (p.name, p.read_bytes(), "text/csv")) for p in (cams or run.cams)]
    cal = calibration or run.calibration
    files.append(("calibration", (cal.name, cal.read_bytes(), "application/octet-stream")))
    return client.post("/v1/jobs", files=files, data={"options": json.dumps({"fps": run.fps, **(options or {})})})


def submit_ok(client: httpx.Client, run: Run, options: dict | None = None) -> str:
    r = submit(client, run, options)
    assert r.status_code == 202, r.text
    return r.json()["id"]


# -- a client that trickles its upload over a raw socket --------------------------------------------

BOUNDARY = "acinoset-slow-boundary"


def multipart(run: Run, options: dict, boundary: str = BOUNDARY) -> bytes:
    """The ``POST /v1/jobs`` body of ``run``'s keypoints and calibration with ``options``, as multipart form data."""
    import json

    parts = []
    for p in run.cams:
        parts.append(f'--{boundary}\r\nContent-Disposition: form-data; name="keypoints"; filename="{p.name}"\r\n'
                     f"Content-Type: text/csv\r\n\r\n".encode() + p.read_bytes() + b"\r\n")
    parts.append(f'--{boundary}\r\nContent-Disposition: form-data; name="calibration"; '
                 f'filename="calibration.toml"\r\nContent-Type: text/plain\r\n\r\n'.encode()
                 + run.calibration.read_bytes() + b"\r\n")
    parts.append(f'--{boundary}\r\nContent-Disposition: form-data; name="options"\r\n\r\n{json.dumps(options)}\r\n'
                 .encode())
    parts.append(f"--{boundary}--\r\n".encode())
    return b"".join(parts)


def slow_upload(port: int, token: str, body: bytes, seconds: float, result: dict) -> None:
    """Send ``body`` (:func:`multipart`) spread evenly over ``seconds``; record the answer's status line and when."""
    t0 = time.perf_counter()
    head = (f"POST /v1/jobs HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nAuthorization: Bearer {token}\r\n"
            f"Content-Type: multipart/form-data; boundary={BOUNDARY}\r\n"
            f"Content-Length: {len(body)}\r\n\r\n").encode()
    chunk = max(1, len(body) // max(1, int(seconds / 0.1)))
    try:
        with socket.create_connection(("127.0.0.1", port), timeout=seconds + 60) as s:
            s.sendall(head)
            for i in range(0, len(body), chunk):
                s.sendall(body[i:i + chunk])
                time.sleep(0.1)
            answer = s.recv(4096).decode(errors="replace")
        result["status"] = answer.split("\r\n", 1)[0]
    except OSError as e:
        result["status"] = f"{type(e).__name__}: {e}"
    result["seconds"] = time.perf_counter() - t0


def wait_for(client: httpx.Client, job_id: str, pred, timeout: float = 120, what: str = "") -> dict:
    deadline = time.time() + timeout
    job = None
    while time.time() < deadline:
        r = client.get(f"/v1/jobs/{job_id}")
        assert r.status_code == 200, r.text
        job = r.json()
        if pred(job):
            return job
        time.sleep(0.05)
    raise AssertionError(f"job {job_id} not {what or 'as expected'} after {timeout} s: {job}")


def wait_finished(client: httpx.Client, job_id: str, timeout: float = 180) -> dict:
    return wait_for(client, job_id, lambda j: j["status"] in ("succeeded", "failed", "cancelled"), timeout,
                    "finished")


def wait_solving(client: httpx.Client, job_id: str, timeout: float = 180) -> dict:
    """Until the job's run is inside the solver (past reading its files)."""
    return wait_for(client, job_id, lambda j: j["status"] == "running" and j["progress"] is not None
                    and j["progress"]["stage"] not in (None, "starting", "reading"), timeout, "solving")


def wait_dead(pid: int, timeout: float = 10) -> bool:
    deadline = time.time() + timeout
    while time.time() < deadline:
        if not pid_alive(pid):
            return True
        time.sleep(0.05)
    return False


def children(pid: int) -> list[int]:
    out = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == pid:
            out.append(int(stat.parent.name))
    return out
