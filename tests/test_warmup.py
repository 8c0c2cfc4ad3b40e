"""The warm-up: from a cold cache a child compiles the marginals' kernels while the parent compiles the rest."""

from __future__ import annotations

import subprocess
import sys

import pytest

from graph.app import warmup


def test_the_child_runs_its_methods_and_exits_cleanly():
    """``python -m graph.app.warmup marginals`` (what the parent starts) and a method's run exit 0,
    also on a method it does not know (a warm-up never fails)."""
    for args in (["marginals"], ["ekf/cheetah"], ["nonsense/points"]):
        done = subprocess.run([sys.executable, "-m", "graph.app.warmup", *args], capture_output=True, text=True,
                              timeout=600)
        assert done.returncode == 0, done.stderr[-2000:]


def test_a_warm_cache_is_seen_and_no_child_is_started(monkeypatch):
    warmup.warm_up()  # whatever the cache held, it holds every kernel now
    assert warmup.kernels_cached()
    started = []
    monkeypatch.setattr(warmup, "_start_child", lambda: started.append(1))
    assert warmup.warm_up() < 30.0 and started == []


@pytest.mark.slow  # a cold compile: 20 s here
def test_from_an_empty_cache_every_kernel_is_cached(tmp_path):
    """From an empty numba cache (its own folder) the warm-up, child and parent together, leaves
    every kernel cached: a second process's warm-up then compiles nothing (0.4 s here, against 20 s
    for the first), nor do solves of 200 frames with every method and skeleton after it."""
    import os

    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "cache")}
    code = "from graph.app.warmup import kernels_cached, warm_up; c = kernels_cached(); s = warm_up(); print(c, s)"
    first = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=900, env=env)
    assert first.returncode == 0, first.stderr[-2000:]
    cached, seconds = first.stdout.split()
    assert cached == "False"
    again = subprocess.run([sys.executable, "-c", code + "\n" + SOLVES_COMPILE], capture_output=True, text=True,
                           timeout=900, env=env)
    assert again.returncode == 0, again.stderr[-2000:]
    cached_again, seconds_again, *compiled = again.stdout.split()
    assert cached_again == "True" and float(seconds_again) < 5.0 < float(seconds), (seconds, seconds_again)
    assert compiled == [], compiled  # numba compiled these kernels for the solves, after the warm-up


# solves of 200 frames with every method and skeleton; prints each kernel numba compiles meanwhile
SOLVES_COMPILE = """
from numba.core import event
from graph.api import solve
from graph.io.calibration import default_rig_path, load_calibration
from graph.simulate import simulate_run
from graph.types import SolveOptions

class Compiled(event.Listener):
    def on_start(self, ev):
        print(ev.data["dispatcher"].py_func.__qualname__)
    def on_end(self, ev):
        pass

cal = load_calibration(default_rig_path())
run = simulate_run(cal, frames=200, seed=0)
with event.install_listener("numba:compile", Compiled()):
    for method in ("tri", "ekf", "fte"):
        for skeleton in ("cheetah", "points"):
            solve(run.keypoints, cal, SolveOptions(method=method, skeleton=skeleton, fps=120))
"""
