"""Fixtures shared by the tests: the AcinoSet rig and a simulated run on it.

Putting this file in ``tests/`` also puts that folder on ``sys.path``, so the service and page
tests import their real servers from ``servers.py``.
"""

from __future__ import annotations

import os

import pytest

# Every ``acinoset solve`` the tests start runs in its own process: no warm resident process is left
# behind or serves a test (tests/test_resident.py turns it on for its own, in a private directory).
os.environ["ACINOSET_RESIDENT"] = "0"

from graph.io.calibration import default_rig_path, load_calibration
from graph.simulate import simulate_run


@pytest.fixture(scope="module")
def rig():
    """The AcinoSet rig's calibration, loaded once per test module."""
    return load_calibration(default_rig_path())


@pytest.fixture(scope="module")
def run(rig, request):
    """A simulated run on the rig, once per test module, made with that module's ``SIMULATION``:
    the keyword arguments of :func:`graph.simulate.simulate_run` (each module sets its own frames,
    noise and seed)."""
    return simulate_run(rig, **request.module.SIMULATION)


def pytest_assertrepr_compare(op, left, right):
    """Two long texts or byte strings that differ (a CSV compared byte for byte): where they first
    differ, in three lines, instead of pytest's diff of the whole, which took over twenty minutes on a
    CSV of a few megabytes and held the suite."""
    if op != "==" or not isinstance(left, (bytes, str)) or type(left) is not type(right):
        return None
    if max(len(left), len(right)) < 10_000:
        return None
    n = next((i for i, (a, b) in enumerate(zip(left, right)) if a != b), min(len(left), len(right)))
    newline = b"\n" if isinstance(left, bytes) else "\n"
    return [f"{len(left)} and {len(right)} long; they first differ at offset {n}, line {left[:n].count(newline) + 1}:",
            f"  {left[max(0, n - 60):n + 60]!r}", f"  {right[max(0, n - 60):n + 60]!r}"]
