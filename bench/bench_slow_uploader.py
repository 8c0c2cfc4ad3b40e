"""One slow uploader against everyone else's submissions, on a real server (uvicorn in a subprocess).

A client opens ``POST /v1/jobs`` with a valid multipart body and sends it a few hundred bytes at a
time; meanwhile another client submits the same small run normally, one after another. Reported:
the normal submissions' latencies while the slow one trickles, and what the slow one is answered.

    python bench/bench_slow_uploader.py [--out bench/results/slow_uploader.json] [--trickle-seconds 12]
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from servers import Server, add_user, make_run, multipart, slow_upload, submit  # noqa: E402

FAST = {"method": "tri", "skeleton": "points"}


def measure(run, env: dict, trickle: float, log: Path) -> dict:
    data = Path(tempfile.mkdtemp(prefix="slow-upload-"))
    token = add_user(data, "quick")
    srv = Server(data, log, workers=1, env={"ACINOSET_WARM_START": "0", **env}).start(ready=(200,))
    try:
        with srv.client(token) as c:
            for _ in range(3):  # the upload readers started, the paths warm
                assert submit(c, run, FAST).status_code == 202
            alone = []
            for _ in range(5):
                t = time.perf_counter()
                assert submit(c, run, FAST).status_code == 202
                alone.append(time.perf_counter() - t)
            slow: dict = {}
            th = threading.Thread(target=slow_upload, args=(srv.port, token, multipart(run, FAST), trickle, slow))
            th.start()
            time.sleep(0.5)
            during = []
            while th.is_alive() and len(during) < 50:
                t = time.perf_counter()
                r = submit(c, run, FAST)
                during.append(time.perf_counter() - t)
                assert r.status_code == 202, r.text
            th.join()
        return {"alone_s": alone, "during_s": during, "median_alone_s": statistics.median(alone),
                "median_during_s": statistics.median(during) if during else None,
                "max_during_s": max(during) if during else None, "slow_client": slow}
    finally:
        srv.stop()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--trickle-seconds", type=float, default=12.0)
    ap.add_argument("--label", default="current")
    args = ap.parse_args()
    work = Path(tempfile.mkdtemp(prefix="slow-run-"))
    run = make_run(work, frames=60, cameras=6, seed=1)
    out = {"label": args.label, "trickle_seconds": args.trickle_seconds,
           "result": measure(run, {}, args.trickle_seconds, work / "server.log")}
    print(json.dumps(out, indent=2))
    if args.out:
        args.out.write_text(json.dumps(out, indent=2) + "\n")


if __name__ == "__main__":
    main()
