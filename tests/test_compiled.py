"""The loop kernels: serial for small calls, a parallel twin for large ones, with the same answer."""

from __future__ import annotations

import numpy as np
import pytest

from graph import compiled
from graph.io.calibration import default_rig_path, load_calibration
from graph.simulate import simulate_run
from graph.solve import kernels
from graph.solve.triangulate import triangulate


@pytest.fixture
def two_threads(monkeypatch):
    monkeypatch.setattr(compiled, "_threads", 2)


def test_small_calls_and_one_thread_take_the_serial_kernel(monkeypatch, two_threads):
    kernel = kernels.triangulate_points
    assert compiled.for_items(kernel, compiled.PARALLEL_ITEMS - 1) is kernel
    twin = compiled.for_items(kernel, compiled.PARALLEL_ITEMS)
    assert twin is not kernel and twin.targetoptions.get("parallel") is True
    assert compiled.for_items(kernel, 10 * compiled.PARALLEL_ITEMS) is twin  # made once
    monkeypatch.setattr(compiled, "_threads", 1)
    assert compiled.for_items(kernel, 10 * compiled.PARALLEL_ITEMS) is kernel


def test_the_twin_has_a_cache_file_of_its_own(two_threads):
    twin = compiled.for_items(kernels.all_normals, compiled.PARALLEL_ITEMS)
    assert twin.py_func.__qualname__ == "all_normals_parallel"
    assert twin.py_func.__code__ is kernels.all_normals.py_func.__code__  # one source


def test_the_twin_triangulates_as_the_serial_kernel_does(monkeypatch):
    """The same points, bit for bit, whichever kernel a run of 2,000 frames takes."""
    cal = load_calibration(default_rig_path())
    run = simulate_run(cal, frames=compiled.PARALLEL_ITEMS, seed=3)
    meas = np.stack([k.xy for k in run.keypoints], axis=1)
    valid = np.stack([k.likelihood > 0.5 for k in run.keypoints], axis=1)
    monkeypatch.setattr(compiled, "_threads", 1)
    serial = triangulate(cal, meas, valid)[0]
    monkeypatch.setattr(compiled, "_threads", 2)
    parallel = triangulate(cal, meas, valid)[0]
    assert np.isfinite(serial).mean() > 0.9
    np.testing.assert_array_equal(parallel, serial)
