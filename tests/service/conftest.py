"""Fixtures of the service tests: simulated runs, written once per test run, and clients of the
users ``alice`` and ``bob`` of the module's ``server`` (:func:`servers.server_with_users`)."""

from __future__ import annotations

import pytest
from servers import Run, make_run


@pytest.fixture(scope="session")
def small_run(tmp_path_factory) -> Run:
    """6 cameras, 60 frames: a solve well under a second."""
    return make_run(tmp_path_factory.mktemp("small_run"), frames=60, cameras=6, seed=1)


@pytest.fixture(scope="session")
def long_run(tmp_path_factory) -> Run:
    """3 cameras, 4000 frames: an fte/cheetah solve of some seconds (6.4 s from a shell here), to stop
    or kill while it runs (800 frames, once enough, now end in under 2 s)."""
    return make_run(tmp_path_factory.mktemp("long_run"), frames=4000, cameras=3, seed=2)


@pytest.fixture
def alice(server):
    with server.client(server.tokens["alice"]) as c:
        yield c


@pytest.fixture
def bob(server):
    with server.client(server.tokens["bob"]) as c:
        yield c
