"""What the API's routes share (:mod:`service.api.routes`, :mod:`service.api.calibration_routes`): who calls,
what the app made at start-up (the job service, the job table, the settings, the backend: see
:func:`service.app.create_app`), the bearer scheme, and the error answers the spec lists.

Each dependency is an ``Annotated`` type for a route's parameter, e.g. ``user: CurrentUser``.
"""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import Depends, Request
from fastapi.security import HTTPBearer

from service.api.auth import current_user
from service.api.models import ErrorBody
from service.backends.base import Backend
from service.core.jobs import JobService
from service.settings import Settings
from service.store import Store, User

# the spec's error answers of a route, as FastAPI's ``responses=`` takes them
Responses = dict[int | str, dict[str, Any]]


def error_doc(description: str) -> dict[str, Any]:
    """The spec's entry for an error answer (``responses={404: error_doc("No such job")}``): its
    body is :class:`service.api.models.ErrorBody`, ``{"detail": "..."}``."""
    return {"model": ErrorBody, "description": description}


AUTH_ERRORS: Responses = {401: error_doc("No token, or an unknown or revoked one"),
                          429: error_doc("Too many invalid tokens from the caller's address in the last minute "
                                         "(ACINOSET_MAX_TOKEN_FAILURES_PER_MINUTE); try again after Retry-After "
                                         "seconds")}
BAD_REQUEST: Responses = {422: error_doc("A request parameter or field is missing or malformed")}
SERVER_ERROR: Responses = {500: error_doc("A fault of the server (logged there)")}
# what every upload route may answer while it receives the body (service.core.uploads)
UPLOAD_ERRORS: Responses = {400: error_doc("The body is not valid multipart/form-data"),
                            408: error_doc("The upload stalled or took too long (ACINOSET_UPLOAD_IDLE_TIMEOUT_SECONDS, "
                                           "ACINOSET_UPLOAD_TIMEOUT_SECONDS)"),
                            503: error_doc("Too many uploads arriving at once; try again after Retry-After seconds"),
                            507: error_doc("The server's disk or its storage for jobs is full")}

# Declares the bearer scheme of every /v1 call in the spec; the check itself is service.api.auth's
# (current_user), which answers 401 with the same challenge whether or not a token was sent.
BEARER = HTTPBearer(auto_error=False, scheme_name="bearer",
                    description="`Authorization: Bearer TOKEN`; an admin makes tokens with `acinoset users add NAME`")


async def caller(request: Request) -> User:
    """:func:`service.api.auth.current_user` on the event loop: one indexed read and a hash, well under a
    millisecond, where a thread-pool hop costs a GIL hand-off (several ms while uploads are parsed)."""
    return current_user(request)


async def job_service(request: Request) -> JobService:
    return request.app.state.jobs


async def job_table(request: Request) -> Store:
    return request.app.state.store


async def server_settings(request: Request) -> Settings:
    return request.app.state.settings


async def job_backend(request: Request) -> Backend:
    return request.app.state.backend


CurrentUser = Annotated[User, Depends(caller)]
Jobs = Annotated[JobService, Depends(job_service)]
JobTable = Annotated[Store, Depends(job_table)]
ServerSettings = Annotated[Settings, Depends(server_settings)]
JobBackend = Annotated[Backend, Depends(job_backend)]
