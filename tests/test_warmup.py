"""The warm-up: from a cold cache a child compiles ekf's kernels while the parent compiles the rest."""

from __future__ import annotations

import subprocess
import sys

import pytest

from graph.app import warmup


def test_the_child_runs_its_methods_and_exits_cleanly():
    """``python -m graph.app.warmup ekf/cheetah`` (what the parent starts) runs and exits 0, also on
    a method it does not know (a warm-up never fails)."""
    for args in (["ekf/cheetah"], ["nonsense/points"]):
        done = subprocess.run([sys.executable, "-m", "graph.app.warmup", *args], capture_output=True, text=True,
                              timeout=600)
        assert done.returncode == 0, done.stderr[-2000:]


def test_a_warm_cache_is_seen_and_no_child_is_started(monkeypatch):
    warmup.warm_up()  # whatever the cache held, it holds every kernel now
    assert warmup.kernels_cached()
    started = []
    monkeypatch.setattr(warmup, "_start_child", lambda: started.append(1))
    assert warmup.warm_up() < 30.0 and started == []


@pytest.mark.slow  # a cold compile: 45 s here
def test_from_an_empty_cache_every_kernel_is_cached(tmp_path):
    """From an empty numba cache (its own folder) the warm-up, child and parent together, leaves
    every kernel cached: a second process's warm-up then compiles nothing (0.6 s here, against 45 s
    for the first)."""
    import os

    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "cache")}
    code = "from graph.app.warmup import kernels_cached, warm_up; c = kernels_cached(); s = warm_up(); print(c, s)"
    first = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=900, env=env)
    assert first.returncode == 0, first.stderr[-2000:]
    cached, seconds = first.stdout.split()
    assert cached == "False"
    again = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=900, env=env)
    assert again.returncode == 0, again.stderr[-2000:]
    cached_again, seconds_again = again.stdout.split()
    assert cached_again == "True" and float(seconds_again) < 5.0 < float(seconds), (seconds, seconds_again)
