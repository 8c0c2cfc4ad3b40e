"""The job service under load, as a lab would load it: many jobs at once, people polling.

    python bench/bench_service.py [--jobs 50] [--frames 150] [--backend embedded|rq|both] [--repeats 1]

For each backend it starts the real thing in subprocesses on loopback ports: ``python -m service
serve`` (embedded: 2 solve processes; rq: with Debian's ``redis-server`` and two ``python -m
service worker`` processes), adds a user, and then:

1. uploads six 500-frame DeepLabCut CSVs plus the calibration, ``--uploads`` times, one at a time
   on an idle server, and times each ``POST /v1/jobs`` until its 202 (the upload, the validation
   of every file with the library's readers, and the storing);
2. submits ``--jobs`` jobs of ``--frames`` frames from 6 cameras all at once (8 client threads),
   with the default solve (``fte`` on the cheetah skeleton);
3. meanwhile another process polls ``GET /v1/jobs/{id}`` of random jobs from 2 threads (each every
   ~20 ms; the ids from the job list every second, as the web page's list does) and keeps the
   latencies of the polls made while two solves were running (``/healthz`` before each poll): for
   the whole run, while the uploads arrive, and after;
4. waits for every job and checks that none is lost (every id succeeded, its CSV downloads) and
   none duplicated (the list has exactly the submitted ids, every job ran once: ``attempts == 1``).

Prints a Markdown table and writes bench/results/service.json.
"""

from __future__ import annotations

import argparse
import json
import os
import random
import shutil
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import httpx

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import harness  # noqa: E402

PY = sys.executable


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def start(args: list[str], log: Path) -> subprocess.Popen:
    return subprocess.Popen(args, cwd=ROOT, stdout=open(log, "ab"), stderr=subprocess.STDOUT,
                            stdin=subprocess.DEVNULL, start_new_session=True,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"})


def stop(p: subprocess.Popen) -> None:
    if p.poll() is None:
        p.send_signal(signal.SIGTERM)
        try:
            p.wait(timeout=30)
        except subprocess.TimeoutExpired:
            pass
    try:
        os.killpg(p.pid, signal.SIGKILL)
    except ProcessLookupError:
        pass


def write_run(out: Path, frames: int, seed: int):
    from graph.simulate import simulate_run
    from graph.simulate import write_run as write

    cal = harness.rig()
    write(simulate_run(cal, frames=frames, seed=seed), out)
    return sorted(out.glob("cam*.csv")), out / "calibration.toml"


def upload(client: httpx.Client, cams: list[Path], calibration: Path, options: dict) -> tuple[float, httpx.Response]:
    files = [("keypoints", (p.name, p.read_bytes(), "text/csv")) for p in cams]
    files.append(("calibration", (calibration.name, calibration.read_bytes(), "application/toml")))
    t0 = time.perf_counter()
    r = client.post("/v1/jobs", files=files, data={"options": json.dumps(options)})
    return time.perf_counter() - t0, r


def percentile(xs: list[float], q: float) -> float:
    xs = sorted(xs)
    if not xs:
        return float("nan")
    k = min(len(xs) - 1, max(0, int(round(q / 100 * (len(xs) - 1)))))
    return xs[k]


def poller(base: str, token: str, out_path: str, stop_path: str, threads: int = 2) -> None:
    """A separate process polling like a user's client: ``GET /v1/jobs/{id}`` of a random job of the
    caller, every ~20 ms per thread; learns the ids from the job list every second. Writes
    (time, seconds, solves running) per poll to ``out_path``."""
    headers = {"Authorization": f"Bearer {token}"}
    ids: list[str] = []
    records: list[tuple[float, float, int]] = []
    lock = threading.Lock()
    stop = Path(stop_path)
    Path(out_path + ".ready").touch()

    def refresh():
        with httpx.Client(base_url=base, headers=headers, timeout=30) as c:
            while not stop.exists():
                got = [j["id"] for j in c.get("/v1/jobs", params={"limit": 500}).json()["jobs"]]
                with lock:
                    ids[:] = got
                time.sleep(1.0)

    def poll():
        with httpx.Client(base_url=base, headers=headers, timeout=30) as c:
            while not stop.exists():
                with lock:
                    pick = random.choice(ids) if ids else None
                if pick is None:
                    time.sleep(0.01)
                    continue
                running = c.get("/healthz").json()["running"]
                t0 = time.perf_counter()
                r = c.get(f"/v1/jobs/{pick}")
                dt = time.perf_counter() - t0
                if r.status_code == 200:
                    with lock:
                        records.append((time.time(), dt, running))
                time.sleep(0.02)

    ts = [threading.Thread(target=refresh, daemon=True)] + [threading.Thread(target=poll, daemon=True)
                                                             for _ in range(threads)]
    for t in ts:
        t.start()
    for t in ts:
        t.join()
    Path(out_path).write_text(json.dumps(records))


def poll_stats(records: list, t_from: float, t_to: float) -> dict:
    xs = [dt for t, dt, running in records if t_from <= t <= t_to and running >= 2]
    return {"n": len(xs), "p50": 1000 * percentile(xs, 50), "p99": 1000 * percentile(xs, 99),
            "max": 1000 * max(xs) if xs else float("nan")}


def run_backend(backend: str, work: Path, n_jobs: int, run150, run500, n_uploads: int) -> dict:
    from service.store import Store

    work.mkdir(parents=True, exist_ok=True)
    data = work / f"data-{backend}"
    store = Store(data / "acinoset.db")
    _, token = store.add_user("bench")
    store.close()
    procs: list[subprocess.Popen] = []
    port = free_port()
    args = [PY, "-m", "service", "serve", "--port", str(port), "--data-dir", str(data), "--backend", backend,
            "--workers", "2", "--log-level", "warning"]
    if backend == "rq":
        rport = free_port()
        (work / "redis").mkdir(exist_ok=True)
        procs.append(start(["redis-server", "--port", str(rport), "--bind", "127.0.0.1", "--dir", str(work / "redis"),
                            "--appendonly", "yes", "--save", ""], work / "redis.log"))
        url = f"redis://127.0.0.1:{rport}/0"
        time.sleep(0.5)
        args += ["--redis-url", url]
    server = start(args, work / f"server-{backend}.log")
    procs.append(server)
    base = f"http://127.0.0.1:{port}"
    deadline = time.time() + 120
    while True:
        try:
            if httpx.get(base + "/healthz").status_code in (200, 503):
                break
        except httpx.HTTPError:
            pass
        if time.time() > deadline or server.poll() is not None:
            raise RuntimeError((work / f"server-{backend}.log").read_text())
        time.sleep(0.1)
    if backend == "rq":
        for i in (1, 2):
            procs.append(start([PY, "-m", "service", "worker", "--redis-url", url, "--name", f"bench-w{i}",
                                "--log-level", "warning"], work / f"worker{i}.log"))
    headers = {"Authorization": f"Bearer {token}"}
    out: dict = {"backend": backend, "jobs": n_jobs}
    if backend == "rq":  # workers register once warmed up
        while httpx.get(base + "/healthz").json()["workers"] < 2:
            time.sleep(0.2)
    try:
        with httpx.Client(base_url=base, headers=headers, timeout=120) as c:
            # the solver warms up once per server (embedded) or worker (rq): wait for it, as users would
            dt, r = upload(c, *run150, {"method": "tri", "skeleton": "points"})
            while c.get(f"/v1/jobs/{r.json()['id']}").json()["status"] != "succeeded":
                time.sleep(0.2)
            c.delete(f"/v1/jobs/{r.json()['id']}")
            # 1. uploads of six 500-frame CSVs on an idle server (then cancelled: not part of the load)
            cams500, cal500 = run500
            times = []
            for _ in range(n_uploads):
                dt, r = upload(c, cams500, cal500, {"method": "tri", "skeleton": "points"})
                assert r.status_code == 202, r.text
                times.append(dt)
                c.delete(f"/v1/jobs/{r.json()['id']}")
            for j in c.get("/v1/jobs", params={"limit": 500}).json()["jobs"]:
                c.delete(f"/v1/jobs/{j['id']}")  # cancelled -> deleted
            out["upload_6x500_s"] = {"median": statistics.median(times), "max": max(times), "n": len(times),
                                     "bytes": sum(p.stat().st_size for p in cams500) + cal500.stat().st_size}
            # 2. + 3. n jobs at once, polled (from another process) while they run
            import multiprocessing

            cams150, cal150 = run150
            ids: list[str] = []
            submit_times: list[float] = []
            lock = threading.Lock()

            def submit_one(_):
                with httpx.Client(base_url=base, headers=headers, timeout=300) as cc:
                    dt, r = upload(cc, cams150, cal150, {"fps": 120})
                with lock:
                    submit_times.append(dt)
                    if r.status_code == 202:
                        ids.append(r.json()["id"])
                    else:
                        out.setdefault("submit_errors", []).append(f"{r.status_code} {r.text[:200]}")

            polls_path, stop_path = work / f"polls-{backend}.json", work / f"stop-{backend}"
            poll_proc = multiprocessing.get_context("spawn").Process(
                target=poller, args=(base, token, str(polls_path), str(stop_path)))
            poll_proc.start()
            while not Path(str(polls_path) + ".ready").exists():
                time.sleep(0.05)
            t0 = time.perf_counter()
            t_start = time.time()
            with ThreadPoolExecutor(8) as ex:
                list(ex.map(submit_one, range(n_jobs)))
            t_submitted = time.perf_counter() - t0
            t_burst_end = time.time()
            # 4. all of them, exactly once
            while c.get("/v1/jobs", params={"status": ["queued", "running"], "limit": 1}).json()["total"]:
                time.sleep(0.5)
            listed = c.get("/v1/jobs", params={"limit": 500}).json()
            wall = time.perf_counter() - t0
            stop_path.touch()
            poll_proc.join(60)
            records = json.loads(polls_path.read_text())
            jobs = {j["id"]: j for j in listed["jobs"]}
            succeeded = [j for j in jobs.values() if j["status"] == "succeeded"]
            downloads = sum(c.get(f"/v1/jobs/{i}/result").status_code == 200 for i in ids)
            run_s = [j["timings"]["run_seconds"] for j in succeeded]
            out.update({
                "submitted": len(ids), "submit_wall_s": t_submitted,
                "submit_s": {"median": statistics.median(submit_times), "max": max(submit_times)},
                "succeeded": len(succeeded), "failed": sum(j["status"] == "failed" for j in jobs.values()),
                "lost": len(set(ids) - set(jobs)), "unknown_in_list": len(set(jobs) - set(ids)),
                "listed_total": listed["total"], "ran_more_than_once": sum(j["attempts"] != 1 for j in succeeded),
                "results_downloaded": downloads, "wall_s": wall, "jobs_per_min": 60 * len(succeeded) / wall,
                "run_s": {"median": statistics.median(run_s), "max": max(run_s)},
                "poll_ms_while_2_solves": poll_stats(records, t_start, time.time()),
                "poll_ms_while_2_solves_after_submitting": poll_stats(records, t_burst_end, time.time()),
                "poll_ms_while_2_solves_while_submitting": poll_stats(records, t_start, t_burst_end),
            })
    finally:
        for p in reversed(procs):
            stop(p)
    return out


def table(results: list[dict]) -> str:
    rows = [
        ("uploads of six 500-frame CSVs + calibration (MB)", lambda r: f"{r['upload_6x500_s']['bytes'] / 1e6:.1f}"),
        ("upload to 202, median / max (s)",
         lambda r: f"{r['upload_6x500_s']['median']:.2f} / {r['upload_6x500_s']['max']:.2f}"),
        ("jobs submitted at once / succeeded", lambda r: f"{r['submitted']} / {r['succeeded']}"),
        ("lost / duplicated / ran twice",
         lambda r: f"{r['lost']} / {r['unknown_in_list']} / {r['ran_more_than_once']}"),
        ("results downloaded", lambda r: str(r["results_downloaded"])),
        ("all submitted in (s)", lambda r: f"{r['submit_wall_s']:.1f}"),
        ("all done in (s); jobs/min", lambda r: f"{r['wall_s']:.1f}; {r['jobs_per_min']:.1f}"),
        ("run time per job, median / max (s)", lambda r: f"{r['run_s']['median']:.2f} / {r['run_s']['max']:.2f}"),
        ("status polls while 2 solves run: n", lambda r: str(r["poll_ms_while_2_solves"]["n"])),
        ("  p50 / p99 / max (ms), whole run",
         lambda r: "{p50:.1f} / {p99:.1f} / {max:.1f}".format(**r["poll_ms_while_2_solves"])),
        ("  p50 / p99 / max (ms), while the uploads arrive",
         lambda r: "{p50:.1f} / {p99:.1f} / {max:.1f}".format(**r["poll_ms_while_2_solves_while_submitting"])),
        ("  p50 / p99 / max (ms), after the uploads",
         lambda r: "{p50:.1f} / {p99:.1f} / {max:.1f}".format(**r["poll_ms_while_2_solves_after_submitting"])),
    ]
    lines = ["| | " + " | ".join(r["backend"] for r in results) + " |", "|---|" + "---|" * len(results)]
    for name, f in rows:
        lines.append(f"| {name} | " + " | ".join(f(r) for r in results) + " |")
    return "\n".join(lines)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--jobs", type=int, default=50)
    ap.add_argument("--frames", type=int, default=150)
    ap.add_argument("--uploads", type=int, default=5)
    ap.add_argument("--backend", choices=["embedded", "rq", "both"], default="both")
    ap.add_argument("--repeats", type=int, default=1, help="runs per backend (the machine is shared: spread)")
    args = ap.parse_args()
    work = Path(tempfile.mkdtemp(prefix="acinoset-bench-service-"))
    try:
        run150 = write_run(work / "run150", args.frames, seed=1)
        run500 = write_run(work / "run500", 500, seed=2)
        backends = ["embedded", "rq"] if args.backend == "both" else [args.backend]
        if "rq" in backends and shutil.which("redis-server") is None:
            print("no redis-server: skipping the rq backend", file=sys.stderr)
            backends.remove("rq")
        results = []
        for i in range(args.repeats):
            for b in backends:
                r = run_backend(b, work / f"run{i}", args.jobs, run150, run500, args.uploads)
                if args.repeats > 1:
                    r["backend"] = f"{b} #{i + 1}"
                results.append(r)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    print(table(results))
    path = harness.save("service", {"machine": harness.machine(), "args": vars(args), "results": results})
    print(f"\nwrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
