"""Shared pieces of the benchmarks: the machine, timing, the simulated data and aniposelib.

Every benchmark solves simulated runs on the real AcinoSet 2019 six-camera rig and judges the
answers against the simulated truth (:mod:`graph.metrics`). Times are wall-clock seconds around
the solve call (``time.perf_counter``), with the process CPU time beside them: the machine is
shared, so a median over repeats is reported, after one untimed warm-up call that pays the one-time
compile (numba for acinoset, jax for aniposelib's ``triangulate``).

The target configuration (the paper's protocol): 120 fps, 5 px noise, 10 % outliers with
sigma 100 px. In the paper's protocol an outlier is indistinguishable by its likelihood, so here
every outlier keeps a high likelihood (``confident_outliers=1``): no method can drop them by the
likelihood threshold. ``--realistic`` runs the simulator's default instead (30 % confident, the
rest with a low likelihood that the threshold removes).

The benchmarks on real recordings read them in place from the shared data folder (:data:`SHARED_DATA`:
``$ACINOSET_SHARED_DATA`` when set, otherwise the first ``shared/data`` beside the project root or
beside one of its ancestors); nothing of it is copied into the project.
"""

from __future__ import annotations

import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from graph.api import SolveOptions, solve  # noqa: E402
from graph.io.calibration import default_rig_path, load_calibration, write_anipose_toml  # noqa: E402
from graph.metrics import position_error  # noqa: E402
from graph.simulate import simulate_run  # noqa: E402

RESULTS_DIR = Path(__file__).resolve().parent / "results"


def _shared_data() -> Path:
    given = os.environ.get("ACINOSET_SHARED_DATA")
    if given:
        return Path(given).expanduser().resolve()
    found = (base / "shared" / "data" for base in ROOT.parents)
    return next((p for p in found if p.is_dir()), ROOT.parent / "shared" / "data")


SHARED_DATA = _shared_data()
ACINOSET_CALIB = SHARED_DATA / "acinoset_calib"  # AcinoSet's public board detections and calibrations
EKS_FLY = SHARED_DATA / "eks_fly"  # the EKS repository's tethered fly: 3 cameras, Anipose calibration in mm
SLEAP_MINIMAL = SHARED_DATA / "sleap_minimal"  # SLEAP's minimal multi-camera session: one mouse, 4 cameras
ACINOSET_RIG = SHARED_DATA / "acinoset_2019_rig.json"  # AcinoSet's 2019 six-camera rig

TARGET = {"fps": 120.0, "noise": 5.0, "outliers": 0.1, "outlier_std": 100.0}

# Anipose's own defaults for `anipose triangulate` (anipose.py DEFAULT_CONFIG['triangulation'])
ANIPOSE_DEFAULTS = {"score_threshold": 0.8, "scale_smooth": 2, "scale_length": 2, "scale_length_weak": 1,
                    "reproj_error_threshold": 5, "n_deriv_smooth": 3}


def machine() -> dict:
    """What ran the benchmark: CPU, cores, memory, load, versions."""
    cpu = platform.processor() or ""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    mem = ""
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemTotal"):
                mem = f"{int(line.split()[1]) / 2**20:.0f} GiB"
    except OSError:
        pass
    from importlib import metadata

    versions = {}
    for dist in ("numpy", "scipy", "gtsam", "numba", "aniposelib", "jax", "opencv-python-headless"):
        try:
            versions[dist] = metadata.version(dist)
        except metadata.PackageNotFoundError:
            versions[dist] = "absent"
    commit = ""
    try:
        commit = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"], capture_output=True,
                                text=True, timeout=10).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        pass
    return {"date": datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC"), "cpu": cpu,
            "cores": os.cpu_count(), "memory": mem, "load_average": list(os.getloadavg()),
            "python": platform.python_version(), "versions": versions, "commit": commit}


@dataclass
class Timing:
    """Wall and CPU seconds of repeated calls (after a warm-up)."""

    wall: list[float] = field(default_factory=list)
    cpu: list[float] = field(default_factory=list)

    @property
    def median(self) -> float:
        return statistics.median(self.wall) if self.wall else float("nan")

    @property
    def best(self) -> float:
        return min(self.wall) if self.wall else float("nan")

    @property
    def cpu_median(self) -> float:
        return statistics.median(self.cpu) if self.cpu else float("nan")

    def to_dict(self) -> dict:
        return {"wall_s": self.wall, "cpu_s": self.cpu, "median_s": self.median, "best_s": self.best,
                "cpu_median_s": self.cpu_median}


def timed(fn, repeats: int, warmup: bool = True):
    """Call ``fn()`` once untimed (if ``warmup``), then ``repeats`` times; return (last value, Timing)."""
    if warmup:
        fn()
    t = Timing()
    value = None
    for _ in range(repeats):
        w0, c0 = time.perf_counter(), time.process_time()
        value = fn()
        t.wall.append(time.perf_counter() - w0)
        t.cpu.append(time.process_time() - c0)
    return value, t


def rig():
    return load_calibration(default_rig_path())


def simulate(calibration, frames: int, seed: int, noise: float = TARGET["noise"],
             outliers: float = TARGET["outliers"], outlier_std: float = TARGET["outlier_std"],
             realistic: bool = False, fps: float = TARGET["fps"]):
    """A run in the benchmark's protocol (see the module docstring)."""
    kw = {} if realistic else {"confident_outliers": 1.0}
    return simulate_run(calibration, frames=frames, fps=fps, noise=noise, outliers=outliers,
                        outlier_std=outlier_std, seed=seed, **kw)


def solve_ours(run, calibration, method: str, skeleton: str = "cheetah", **options):
    return solve(run.keypoints, calibration, SolveOptions(method=method, fps=run.fps, skeleton=skeleton, **options))


def error_mm(positions: np.ndarray, run) -> dict:
    e = position_error(positions, run.positions, run.markers)
    return {"mean_mm": e.mean_mm, "median_mm": e.median_mm, "p90_mm": e.p90_mm, "max_mm": e.max_mm,
            "coverage": e.coverage}


def warm_up_ours(calibration) -> None:
    """Pay the one-time compile (numba kernels: loaded from cache or compiled) before timing."""
    small = simulate(calibration, frames=30, seed=99)
    for method in ("tri", "ekf", "fte"):
        solve_ours(small, calibration, method)


# ------------------------------------------------------------------------------------ aniposelib


def anipose_group(calibration):
    """aniposelib's ``CameraGroup`` for our calibration, through the Anipose TOML we write
    (fisheye cameras become ``FisheyeCamera``)."""
    from aniposelib.cameras import CameraGroup

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "calibration.toml"
        write_anipose_toml(path, calibration)
        return CameraGroup.load(str(path))


def anipose_points(run, score_threshold: float = ANIPOSE_DEFAULTS["score_threshold"]) -> np.ndarray:
    """(C, N, M, 2) detections with those below the score threshold set to NaN, as
    ``anipose triangulate`` does."""
    pts = np.stack([k.xy for k in run.keypoints]).copy()
    lik = np.stack([k.likelihood for k in run.keypoints])
    pts[lik < score_threshold] = np.nan
    return pts


def bone_constraints(run) -> list[list[int]]:
    idx = {m: i for i, m in enumerate(run.markers)}
    return [[idx[a], idx[b]] for a, b in run.bones]


def anipose_triangulate(cgroup, pts: np.ndarray) -> np.ndarray:
    """Plain multi-view triangulation (``anipose triangulate`` with ``optim = false``)."""
    C, N, M, _ = pts.shape
    return np.asarray(cgroup.triangulate(pts.reshape(C, N * M, 2), progress=False)).reshape(N, M, 3)


def anipose_triangulate_optim(cgroup, pts: np.ndarray, constraints: list[list[int]]) -> np.ndarray:
    """``triangulate_optim`` with limb-length constraints and Anipose's default scales."""
    d = ANIPOSE_DEFAULTS
    return np.asarray(cgroup.triangulate_optim(
        pts, constraints=constraints, constraints_weak=[], scale_smooth=d["scale_smooth"],
        scale_length=d["scale_length"], scale_length_weak=d["scale_length_weak"],
        reproj_error_threshold=d["reproj_error_threshold"], n_deriv_smooth=d["n_deriv_smooth"]))


# ------------------------------------------------------------------------------------ commands

GNU_TIME = "/usr/bin/time"


def time_command(cmd: list[str], env: dict) -> dict:
    """Run ``cmd`` under ``/usr/bin/time``: its exit status, wall seconds (around the whole), CPU seconds, peak RSS.

    The peak is GNU time's ``%M`` for the command, a child of ``time``: the ``ru_maxrss`` that ``os.wait4``
    gives for a child of this process counts this process's own resident memory too (a forked child's pages
    before its ``exec``), hundreds of MiB here after solves of its own.
    """
    with tempfile.TemporaryDirectory() as tmp:
        usage, err = Path(tmp) / "usage", Path(tmp) / "stderr"
        with open(err, "wb") as f:
            t0 = time.perf_counter()
            proc = subprocess.run([GNU_TIME, "-f", "%M %U %S", "-o", str(usage), *cmd], stdin=subprocess.DEVNULL,
                                  stdout=subprocess.DEVNULL, stderr=f, env=env)
            wall = time.perf_counter() - t0
        stderr = err.read_text(errors="replace")
        fields = usage.read_text().split()[-3:]  # a killed command's file starts with a line of its own
    peak_kib, user, system = int(fields[0]), float(fields[1]), float(fields[2])
    return {"exit": proc.returncode, "wall_s": wall, "cpu_s": user + system, "peak_rss_mib": peak_kib / 1024.0,
            "stderr_tail": stderr.strip()[-1500:], "load": os.getloadavg()[0]}


# ------------------------------------------------------------------------------------------ output


def save(name: str, doc: dict) -> Path:
    RESULTS_DIR.mkdir(exist_ok=True)
    path = RESULTS_DIR / f"{name}.json"
    path.write_text(json.dumps(_finite(doc), indent=2) + "\n", encoding="utf-8")
    return path


def _finite(x):
    if isinstance(x, dict):
        return {str(k): _finite(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_finite(v) for v in x]
    if isinstance(x, (float, np.floating)):
        return None if not np.isfinite(x) else round(float(x), 6)
    if isinstance(x, np.integer):
        return int(x)
    return x


def markdown_table(header: list[str], rows: list[list]) -> str:
    def cell(v):
        if isinstance(v, float):
            return "n/a" if not np.isfinite(v) else f"{v:.3g}" if abs(v) < 100 else f"{v:.0f}"
        return str(v)

    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(cell(v) for v in r) + " |" for r in rows]
    return "\n".join(lines)
