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
