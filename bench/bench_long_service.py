"""A long recording through the job service (issue 29): the 10-minute run of ``bench_long.py`` uploaded to
a real embedded server and solved there, beside the same run from a shell.

    .venv/bin/python bench/bench_long_service.py [--minutes 10] [--workers 1] [--seed 0] [--work DIR] [--out NAME]
    .venv/bin/python bench/bench_long_service.py --rq-workers 1,2 [--minutes 10] [--shared-data-dir]
    .venv/bin/python bench/bench_long_service.py --embedded-workers 1,2 [--minutes 10]

With ``--rq-workers``, the same job on the RQ backend instead, once per count of workers given: a
``redis-server`` of its own, the server with ``--backend rq`` and that many ``acinoset worker`` processes
(``python -m service worker``), all on this machine. A long job's windows are shared with the workers
that are idle (``service.run.shared_windows``): the ratio of the job's time with 2 workers to its time
with 1 is the issue's "through the service with 2 workers, <= 0.6x the time of 1". The memory sampled
is then the server's tree and every worker's tree, summed. ``--shared-data-dir``: the server shares its
data dir with the workers (``ACINOSET_SHARED_DATA_DIR``, each worker ``--data-dir``): the job's files go
by path, not through Redis. ``--embedded-workers``: the same on the embedded backend, a server with that
many ``--workers``; a long job's windows go to helper processes in the slots no other job takes.

The run: ``bench_long.make_run`` (the simulator's cheetah walking at 1 m/s on the AcinoSet 2019 rig,
120 fps, six DeepLabCut CSVs). The server: ``python -m service serve --backend embedded --workers N``
on a loopback port, its limits raised for the run as a lab would raise them (``ACINOSET_MAX_FRAMES``,
``ACINOSET_MAX_UPLOAD_BYTES``: the defaults take 50,000 frames a file and 512 MiB an upload). After one
small untimed job (the solver's warm-up), measured:

* the upload: ``POST /v1/jobs`` of the six CSVs and the calibration until its 202 (the server reads
  every file with the library's readers before it answers);
* the job: from the 202 until it succeeded (polled every 0.2 s), and the job's own ``run_seconds``;
* the server's memory: the resident memory of its whole process tree (the server, its solve and
  upload-reading processes), summed every 0.2 s, its peak while the job ran and over all;
* the downloaded CSV scored against the truth (``graph.metrics.position_error``).

Then the same run from a shell (``acinoset solve``, GNU time), as ``bench_long.py`` measures it.
Prints a Markdown table and writes bench/results/OUT.json (default ``long_service``).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import bench_long as bl
import harness as h
import httpx

PY = sys.executable
ROOT = Path(__file__).resolve().parents[1]
MIB = 1024 * 1024


def _env(frames: int) -> dict:
    return {**os.environ, "PYTHONUNBUFFERED": "1", "ACINOSET_MAX_FRAMES": str(frames + 1),
            "ACINOSET_MAX_UPLOAD_BYTES": str(4096 * MIB)}


def _spawn(args: list[str], log: Path, env: dict) -> subprocess.Popen:
    return subprocess.Popen(args, cwd=ROOT, stdout=open(log, "ab"), stderr=subprocess.STDOUT,
                            stdin=subprocess.DEVNULL, start_new_session=True, env=env)


def start_redis(work: Path) -> tuple[subprocess.Popen, str]:
    port = _free_port()
    (work / "redis").mkdir(parents=True, exist_ok=True)
    proc = _spawn(["redis-server", "--port", str(port), "--bind", "127.0.0.1", "--dir", str(work / "redis"),
                   "--save", "", "--appendonly", "no"], work / "redis.log", dict(os.environ))
    deadline = time.time() + 20
    import socket

    while time.time() < deadline:
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=1) as sock:
                sock.sendall(b"PING\r\n")
                if sock.recv(16).startswith(b"+PONG"):
                    return proc, f"redis://127.0.0.1:{port}/0"
        except OSError:
            time.sleep(0.05)
    raise RuntimeError((work / "redis.log").read_text()[-2000:])


def start_workers(redis_url: str, n: int, frames: int, work: Path,
                  data_dir: Path | None = None) -> list[subprocess.Popen]:
    """``data_dir``: the server's, which it shares with them."""
    where = ["--data-dir", str(data_dir)] if data_dir is not None else []
    return [_spawn([PY, "-m", "service", "worker", "--redis-url", redis_url, "--name", f"w{i + 1}",
                    "--log-level", "warning", *where], work / f"w{i + 1}.log", _env(frames)) for i in range(n)]


def start_server(data: Path, workers: int, frames: int, log: Path, redis_url: str | None = None,
                 shared: bool = False) -> tuple[subprocess.Popen, str, str]:
    """The server: embedded with ``workers`` solve processes, or on the RQ backend of ``redis_url``
    (``shared``: its data dir shared with the workers)."""
    from service.store import Store

    store = Store(data / "acinoset.db")
    _, token = store.add_user("bench")
    store.close()
    port = _free_port()
    backend = ["--backend", "rq", "--redis-url", redis_url] if redis_url else ["--backend", "embedded", "--workers",
                                                                             str(workers)]
    proc = _spawn([PY, "-m", "service", "serve", "--port", str(port), "--data-dir", str(data), *backend,
                   "--log-level", "warning"], log, {**_env(frames), "ACINOSET_SHARED_DATA_DIR": "1" if shared else "0"})
    base = f"http://127.0.0.1:{port}"
    deadline = time.time() + 120
    while True:
        try:
            if httpx.get(base + "/healthz").status_code == 200:
                return proc, base, token
        except httpx.HTTPError:
            pass
        if time.time() > deadline or proc.poll() is not None:
            raise RuntimeError(log.read_text()[-2000:])
        time.sleep(0.2)


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class TreeSampler(threading.Thread):
    """The summed resident memory of the process trees of ``pids``, every ``every`` s, until stopped."""

    def __init__(self, *pids: int, every: float = 0.2):
        super().__init__(daemon=True)
        self.pids, self.every, self.samples = pids, every, []
        self.halt = threading.Event()

    def run(self) -> None:
        while not self.halt.is_set():
            self.samples.append((time.perf_counter(),
                                 sum(bl._rss_kib(p) for pid in self.pids for p in bl._tree(pid)) / 1024))
            time.sleep(self.every)

    def peak(self, t0: float = float("-inf"), t1: float = float("inf")) -> float:
        return max((m for t, m in self.samples if t0 <= t <= t1), default=float("nan"))


def submit(c: httpx.Client, d: Path, options: dict) -> tuple[float, httpx.Response]:
    files = [("keypoints", (p.name, p.read_bytes(), "text/csv")) for p in sorted(d.glob("cam*.csv"))]
    files.append(("calibration", ("calibration.toml", (d / "calibration.toml").read_bytes(), "application/toml")))
    t0 = time.perf_counter()
    r = c.post("/v1/jobs", files=files, data={"options": json.dumps(options)})
    return time.perf_counter() - t0, r


def wait(c: httpx.Client, job_id: str, timeout: float = 3600, stages: list | None = None) -> dict:
    """The job once it ended; ``stages`` (when given) gets ``[seconds, status, stage, fraction]``
    each time the job's status or stage changes (polled every 0.2 s)."""
    t0 = time.perf_counter()
    deadline = time.time() + timeout
    last = None
    while time.time() < deadline:
        job = c.get(f"/v1/jobs/{job_id}").json()
        p = job.get("progress") or {}
        now = (job["status"], p.get("stage"))
        if stages is not None and now != last:
            stages.append([round(time.perf_counter() - t0, 1), *now, p.get("fraction")])
            last = now
        if job["status"] in ("succeeded", "failed", "cancelled"):
            return job
        time.sleep(0.2)
    raise TimeoutError(job_id)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--minutes", type=float, default=10.0)
    ap.add_argument("--workers", type=int, default=1)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--work", default=None)
    ap.add_argument("--out", default="long_service")
    ap.add_argument("--shared-data-dir", action="store_true",
                    help="RQ: the workers mount the server's data dir (files by path, not through Redis)")
    ap.add_argument("--rq-workers", default=None,
                    help="the RQ backend instead, once per count of workers given (comma-separated, e.g. 1,2)")
    ap.add_argument("--embedded-workers", default=None,
                    help="the embedded backend once per count of --workers given (comma-separated, e.g. 1,2)")
    args = ap.parse_args()
    if args.rq_workers:
        return main_counts(args, "rq", args.rq_workers)
    if args.embedded_workers:
        return main_counts(args, "embedded", args.embedded_workers)
    frames = int(round(args.minutes * 60 * bl.FPS))
    info = h.machine()
    work = Path(args.work or tempfile.mkdtemp(prefix="bench_long_service_"))
    work.mkdir(parents=True, exist_ok=True)
    run_dir, warm_dir, data = work / "run", work / "warm", work / "data"
    data.mkdir(exist_ok=True)
    cal = h.rig()
    bl.make_run(cal, bl.WARM_FRAMES, 99, warm_dir)
    bl.log(f"{args.minutes:g} min: simulating and writing {frames:,} frames")
    bl.make_run(cal, frames, args.seed, run_dir)
    out: dict = {"machine": info, "args": vars(args), "frames": frames}
    proc, base, token = start_server(data, args.workers, frames, work / "server.log")
    sampler = TreeSampler(proc.pid)
    sampler.start()
    try:
        out["service"] = timed_job(base, token, warm_dir, run_dir, sampler, work)
        out["service"].pop("csv_bytes", None)
        out["service"]["tree_peak_mib_all"] = sampler.peak()
    finally:
        sampler.halt.set()
        proc.terminate()
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
    bl.log("the same run from a shell")
    c = bl.command(bl.solve_command(run_dir), {**os.environ, "ACINOSET_RESIDENT": "0"})
    out["shell"] = c
    if c["exit"] == 0:
        markers, truth = bl.load_truth(run_dir / "truth.npz")
        out["shell"]["error"] = bl.score(bl.read_positions(run_dir / "run.csv", markers), truth, markers)
        out["same_csv"] = (run_dir / "run.csv").read_bytes() == (work / "service.csv").read_bytes()
    s = out.get("service", {})
    rows = [["service (embedded, 1 worker)", s.get("status"), s.get("upload_s"), s.get("job_s"), s.get("run_seconds"),
             s.get("tree_mib_idle"), s.get("tree_peak_mib_job"), s.get("tree_peak_mib_all"),
             (s.get("error") or {}).get("mean_mm")],
            ["acinoset solve from a shell", c["exit"], "-", c["wall_s"], "-", "-", c["peak_rss_mib"], "-",
             (c.get("error") or {}).get("mean_mm")]]
    print(h.markdown_table(["how", "status", "upload s", "job / command s", "job's run_seconds", "idle MiB",
                            "peak MiB while solving", "peak MiB overall", "error mean mm"], rows))
    print("\n(the service's memory: its whole process tree summed, the pages its processes share counted in each)")
    print(f"\nthe service's CSV and the command's: {'the same bytes' if out.get('same_csv') else 'different'}")
    print(f"wrote {h.save(args.out, out)}")
    if args.work is None:
        shutil.rmtree(work, ignore_errors=True)
    return 0


def timed_job(base: str, token: str, warm_dir: Path, run_dir: Path, sampler: TreeSampler, work: Path) -> dict:
    """One untimed warm-up job, then the run's job: its upload, its time, memory, windows and error."""
    with httpx.Client(base_url=base, headers={"Authorization": f"Bearer {token}"}, timeout=600) as c:
        _, r = submit(c, warm_dir, {"fps": bl.FPS})
        assert r.status_code == 202, r.text
        warm = wait(c, r.json()["id"])
        bl.log(f"warm-up job: {warm['status']}")
        time.sleep(3.0)  # idle, sampled
        t0 = time.perf_counter()
        up_s, r = submit(c, run_dir, {"fps": bl.FPS})
        assert r.status_code == 202, r.text
        t_up = time.perf_counter()
        stages: list = []
        job = wait(c, r.json()["id"], stages=stages)
        t1 = time.perf_counter()
        bl.log(f"job {job['status']}: upload {up_s:.1f} s, then {t1 - t_up:.1f} s; stages (s, status, stage, "
               f"fraction): {stages}")
        out = {"status": job["status"], "error": job.get("error"), "upload_s": up_s, "job_s": t1 - t_up,
               "stages": stages,
               "run_seconds": (job.get("timings") or {}).get("run_seconds"),
               "tree_peak_mib_job": sampler.peak(t_up, t1), "tree_mib_idle": sampler.peak(t0 - 2.0, t0)}
        if job["status"] == "succeeded":
            report = c.get(job["links"]["result"]["report"]).json()
            out["windows"] = report.get("windows")
            csv = work / "service.csv"
            csv.write_bytes(c.get(job["links"]["result"]["csv"]).content)
            markers, truth = bl.load_truth(run_dir / "truth.npz")
            out["error"] = bl.score(bl.read_positions(csv, markers), truth, markers)
            out["csv_bytes"] = csv.read_bytes()
    return out


def main_counts(args, backend: str, given: str) -> int:
    """The job on the ``backend`` with each count of workers ``given`` (``--rq-workers``,
    ``--embedded-workers``: module docstring)."""
    counts = [int(n) for n in given.split(",")]
    frames = int(round(args.minutes * 60 * bl.FPS))
    info = h.machine()
    work = Path(args.work or tempfile.mkdtemp(prefix=f"bench_long_service_{backend}_"))
    run_dir, warm_dir = work / "run", work / "warm"
    cal = h.rig()
    bl.make_run(cal, bl.WARM_FRAMES, 99, warm_dir)
    bl.log(f"{args.minutes:g} min: simulating and writing {frames:,} frames")
    bl.make_run(cal, frames, args.seed, run_dir)
    out: dict = {"machine": info, "args": vars(args), "frames": frames, backend: {}}
    csvs = {}
    for n in counts:
        here = work / f"{backend}{n}"
        (here / "data").mkdir(parents=True, exist_ok=True)
        if backend == "rq":
            redis, url = start_redis(here)
            server, base, token = start_server(here / "data", 0, frames, here / "server.log", redis_url=url,
                                               shared=args.shared_data_dir)
            workers = start_workers(url, n, frames, here, here / "data" if args.shared_data_dir else None)
            others = [redis]  # not sampled: the memory is the server's and the workers'
        else:
            server, base, token = start_server(here / "data", n, frames, here / "server.log")
            workers, others = [], []
        sampler = TreeSampler(server.pid, *(w.pid for w in workers))
        sampler.start()
        try:
            bl.log(f"{backend} backend, {n} worker(s)")
            r = timed_job(base, token, warm_dir, run_dir, sampler, here)
        finally:
            sampler.halt.set()
            for p in [server, *workers, *others]:
                p.terminate()
            for p in [server, *workers, *others]:
                try:
                    p.wait(timeout=30)
                except subprocess.TimeoutExpired:
                    p.kill()
        csvs[n] = r.pop("csv_bytes", None)
        out[backend][n] = r
    rows = []
    for n, r in out[backend].items():
        w = r.get("windows") or {}
        rows.append([n, r["status"], r["upload_s"], r["job_s"], r["job_s"] / out[backend][counts[0]]["job_s"],
                     r["tree_mib_idle"], r["tree_peak_mib_job"], (r.get("error") or {}).get("mean_mm"),
                     json.dumps(w.get("solved_by"))])
    print(h.markdown_table([f"{backend} workers", "status", "upload s", "job s", f"vs {counts[0]}", "idle MiB",
                            "peak MiB while solving", "error mean mm", "windows solved by"], rows))
    same = len({c for c in csvs.values() if c is not None}) == 1 and all(c is not None for c in csvs.values())
    out["same_csv"] = same
    print(f"\nthe CSVs of every count of workers: {'the same bytes' if same else 'different'}")
    print(f"wrote {h.save(args.out, out)}")
    if args.work is None:
        shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
