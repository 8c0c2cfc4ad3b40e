"""The first minute: from a fresh clone, the README's install command and then ``acinoset demo``.

    python bench/bench_first_minute.py [--repeats 3] [--keep]

Each repeat, in a new temporary folder:

1. ``git clone`` of this checkout's committed HEAD (no numba cache: the clone has no ``__pycache__``);
2. the README's install, timed: ``python3 -m venv .venv && .venv/bin/pip install -e .``, with
   ``--no-cache-dir`` so that pip downloads every wheel again (no cache from an earlier install);
3. ``.venv/bin/acinoset demo --out demo-out`` from a shell, timed with its peak memory by GNU time
   (every kernel compiled: the clone's cache is empty), and the demo's own "kernels ready in" line.

The issue's target: install and demo together within 60 s. Writes bench/results/first_minute.json.
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import harness as h

ROOT = Path(__file__).resolve().parents[1]


def one(work: Path) -> dict:
    clone = work / "acinoset"
    subprocess.run(["git", "clone", "-q", str(ROOT), str(clone)], check=True)
    env = {k: v for k, v in os.environ.items() if k not in ("VIRTUAL_ENV", "PYTHONPATH", "NUMBA_CACHE_DIR")}
    env["PIP_NO_CACHE_DIR"] = "1"
    t0 = time.perf_counter()
    done = subprocess.run("python3 -m venv .venv && .venv/bin/pip install -q -e .", shell=True, cwd=clone, env=env,
                          capture_output=True, text=True)
    install = time.perf_counter() - t0
    if done.returncode != 0:
        raise SystemExit(f"install failed: {done.stderr.strip()[-600:]}")
    env.pop("PIP_NO_CACHE_DIR")
    env["ACINOSET_RESIDENT"] = "0"
    with tempfile.TemporaryDirectory() as tmp:
        log = Path(tmp) / "out"
        cmd = ["bash", "-c", f"cd {clone} && .venv/bin/acinoset demo --out demo-out > {log} 2>&1"]
        demo = h.time_command(cmd, env)
        text = log.read_text(errors="replace")
    if demo["exit"] != 0:
        raise SystemExit(f"demo failed: {text[-600:]}")
    m = re.search(r"kernels ready in ([0-9.]+) s", text)
    return {"install_s": install, "demo_s": demo["wall_s"], "total_s": install + demo["wall_s"],
            "demo_peak_rss_mib": demo["peak_rss_mib"], "kernels_s": float(m.group(1)) if m else None,
            "load": demo["load"], "table": [line for line in text.splitlines() if line[:4] in ("tri ", "ekf ", "fte ")]}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--keep", action="store_true", help="keep the clones")
    args = ap.parse_args()
    info = h.machine()
    head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True).stdout
    print(f"# the first minute at {head.strip()}: {info['cpu']}, {info['cores']} cores, "
          f"load {info['load_average'][0]:.1f}", flush=True)
    runs = []
    for i in range(args.repeats):
        work = Path(tempfile.mkdtemp(prefix="acinoset-first-"))
        try:
            r = one(work)
        finally:
            if not args.keep:
                shutil.rmtree(work, ignore_errors=True)
        runs.append(r)
        print(f"run {i + 1}: install {r['install_s']:.1f} s + demo {r['demo_s']:.1f} s (kernels "
              f"{r['kernels_s']} s, peak {r['demo_peak_rss_mib']:.0f} MiB) = {r['total_s']:.1f} s, "
              f"load {r['load']:.1f}", flush=True)
    med = {k: statistics.median(r[k] for r in runs) for k in ("install_s", "demo_s", "total_s", "kernels_s")}
    print(f"median: install {med['install_s']:.1f} s, demo {med['demo_s']:.1f} s (kernels {med['kernels_s']:.1f} s), "
          f"total {med['total_s']:.1f} s against the 60 s target")
    h.save("first_minute", {"machine": info, "commit": head.strip(), "runs": runs, "median": med, "target_s": 60.0})
    return 0


if __name__ == "__main__":
    sys.exit(main())
