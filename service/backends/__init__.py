"""Where solves run: :mod:`.embedded` (child processes of the server) or :mod:`.rq` (RQ workers)."""

from __future__ import annotations

from service.backends.base import Backend
from service.settings import Settings
from service.store import Store


def make_backend(settings: Settings, store: Store) -> Backend:
    if settings.backend == "rq":
        from service.backends.rq import RQBackend

        return RQBackend(settings, store)
    from service.backends.embedded import EmbeddedBackend

    return EmbeddedBackend(settings, store)


__all__ = ["Backend", "make_backend"]
