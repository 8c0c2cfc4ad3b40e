"""The FastAPI application: :func:`create_app` wires settings, the job table, a backend and the routes.

One server process owns a data dir at a time (an exclusive lock on ``<data dir>/server.lock``,
released by the kernel however the process ends): that is what lets a restarted server treat every
run still marked ``running`` as interrupted.
"""

from __future__ import annotations

import fcntl
import logging
import os
from contextlib import asynccontextmanager
from pathlib import Path

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException

import graph
from service.api.auth import TokenFailures
from service.api.headers import SecurityHeaders
from service.api.limits import UploadGuard
from service.backends import make_backend
from service.core.jobs import JobService
from service.core.uploads import UploadReader
from service.errors import (
    DISK_FULL,
    Forbidden,
    JobError,
    NoSpace,
    NotFound,
    NotReady,
    TooLarge,
    TooMany,
    Unprocessable,
    storage_full,
)
from service.run.worker import configure_forkserver
from service.settings import Settings
from service.store import Store, jobfiles

log = logging.getLogger("acinoset.service")

DESCRIPTION = """\
3D animal pose from DeepLabCut keypoints and a camera calibration, as a shared lab service.

Submit one keypoint file per camera and the calibration (`POST /v1/jobs`), poll the job
(`GET /v1/jobs/{id}`) and download the result (`GET /v1/jobs/{id}/result?format=csv|h5|json`).
Every call under `/v1` needs `Authorization: Bearer TOKEN` (an admin makes tokens with
`acinoset users add NAME`). Every error answer is JSON: `{"detail": "one line"}`.
"""


# How the API answers each refusal of the job service (:class:`service.errors.JobError`)
JOB_ERROR_STATUS: dict[type[JobError], int] = {NotFound: 404, Forbidden: 403, NotReady: 409, Unprocessable: 422,
                                               TooLarge: 413, TooMany: 429, NoSpace: 507}


class DataDirInUse(RuntimeError):
    pass


class DataDirLock:
    """An exclusive, non-blocking ``flock`` on ``<data dir>/server.lock``."""

    def __init__(self, data_dir: Path):
        self.path = data_dir / "server.lock"
        self._fd: int | None = None

    def acquire(self) -> None:
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o600)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            raise DataDirInUse(f"another acinoset server is using {self.path.parent}") from None
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()}\n".encode())
        self._fd = fd

    def release(self) -> None:
        if self._fd is not None:
            fcntl.flock(self._fd, fcntl.LOCK_UN)
            os.close(self._fd)
            self._fd = None


def allowed_methods(app: FastAPI, scope) -> list[str]:
    """Every method some route of ``app`` answers on the path of ``scope`` (the ``Allow`` of a 405)."""
    from starlette.routing import Match

    methods: set[str] = set()

    def walk(routes) -> None:
        for route in routes:
            inner = getattr(route, "original_router", None)  # an included router (ours have no prefix)
            if inner is not None:
                walk(inner.routes)
            elif route.matches(scope)[0] != Match.NONE:
                methods.update(getattr(route, "methods", None) or ())

    walk(app.router.routes)
    return sorted(methods)


def create_app(settings: Settings | None = None) -> FastAPI:
    """The application. The data dir is locked, and the backend started, when the app starts up."""
    settings = settings or Settings()

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        settings.make_private()
        lock = DataDirLock(settings.data_dir)
        lock.acquire()
        try:
            store = Store(settings.db_path)
            jobfiles.tidy(settings.jobs_dir, store.all_job_ids())
            configure_forkserver(warm=settings.warm_start and settings.backend == "embedded")
            backend = make_backend(settings, store)
            reader = UploadReader(settings.upload_readers, settings.upload_niceness)
            # exports in a process of their own: one that dies (an hour's result, memory) takes no upload along
            exporter = UploadReader(min(1, settings.upload_readers), settings.upload_niceness)
            app.state.store = store
            app.state.token_failures = TokenFailures(settings.max_token_failures_per_minute)
            app.state.backend = backend
            app.state.jobs = JobService(settings, store, backend, reader, exporter)
            backend.start()
            try:
                yield
            finally:
                backend.stop()
                reader.close()
                exporter.close()
        finally:
            lock.release()

    # no CDN-served API explorer on the origin where the token lives: /docs is a page of our own (service.api.web)
    app = FastAPI(title="acinoset", version=graph.__version__, description=DESCRIPTION, lifespan=lifespan,
                  docs_url=None, redoc_url=None)
    app.state.settings = settings
    app.add_middleware(UploadGuard, settings=settings, error_status=JOB_ERROR_STATUS)
    app.add_middleware(UploadGuard, settings=settings, error_status=JOB_ERROR_STATUS, path="/v1/batches")
    app.add_middleware(UploadGuard, settings=settings, error_status=JOB_ERROR_STATUS, path="/v1/calibrations")
    app.add_middleware(SecurityHeaders)  # outermost: on every answer, the guard's refusals included

    @app.exception_handler(StarletteHTTPException)
    async def http_error(request: Request, exc: StarletteHTTPException):
        detail = exc.detail if isinstance(exc.detail, str) else str(exc.detail)
        headers = dict(getattr(exc, "headers", None) or {})
        if exc.status_code == 405:  # Starlette names the methods of the first route on the path only
            headers["Allow"] = ", ".join(allowed_methods(request.app, request.scope))
        return JSONResponse({"detail": detail}, status_code=exc.status_code, headers=headers or None)

    @app.exception_handler(JobError)
    async def job_error(request: Request, exc: JobError):
        return JSONResponse({"detail": exc.detail}, status_code=JOB_ERROR_STATUS.get(type(exc), 400))

    @app.exception_handler(RequestValidationError)
    async def validation_error(request: Request, exc: RequestValidationError):
        parts = []
        for err in exc.errors():
            loc = [str(x) for x in err.get("loc", ()) if x not in ("body", "query", "path", "header")]
            parts.append(f"{'.'.join(loc) + ': ' if loc else ''}{err.get('msg', 'invalid')}")
        return JSONResponse({"detail": "; ".join(parts) or "invalid request"}, status_code=422)

    @app.exception_handler(Exception)
    async def internal_error(request: Request, exc: Exception):
        if storage_full(exc):  # any write the routes make (a cancel, a token) on a full disk
            log.error("%s %s: %s", request.method, request.url.path, exc)
            return JSONResponse({"detail": DISK_FULL}, status_code=507)
        log.exception("unhandled error on %s %s", request.method, request.url.path)
        return JSONResponse({"detail": f"internal error ({type(exc).__name__}); the server log has the details"},
                            status_code=500)

    from service.api import calibration_routes, routes

    app.include_router(routes.router)
    app.include_router(calibration_routes.router)
    app.include_router(routes.public)
    _include_web(app)
    return app


def _include_web(app: FastAPI) -> None:
    """The web pages (``service/api/web.py``), when that module exists; not part of the REST contract."""
    import importlib

    try:
        web = importlib.import_module("service.api.web")
    except ModuleNotFoundError as e:
        if e.name != "service.api.web":
            raise
        return
    app.include_router(web.router, include_in_schema=False)
