"""Refuse an upload before reading it: an ASGI middleware in front of ``POST /v1/jobs``.

FastAPI reads a whole multipart body before any dependency runs. This guard answers first, from the
headers alone, when the caller has no valid token (401), already has the most active jobs allowed
(429), has no room left for the body it announces (413 over the user's storage quota, 507 when
the server's disk or storage is full) or announces a body over ``max_upload_bytes`` (413); it counts the bytes of a body sent
without a length, stopping at the limit (413); and it lets only a few submissions in at a time.
"""

from __future__ import annotations

import asyncio
import json

from fastapi import HTTPException
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from service.auth import authorized_user
from service.errors import JobError, NoSpace, TooLarge, TooMany
from service.settings import Settings


class UploadGuard:
    # Submissions received at once; later ones wait (unread) for a turn, at most TURN_WAIT seconds.
    # Receiving and storing an upload is CPU work in this process: a burst of them queues here, and
    # the status polls and downloads sharing the process keep answering quickly. The bounded wait
    # keeps a few slow uploaders from holding up everyone else's submissions. One at a time: with two,
    # status polls inside a burst of 50 uploads had p99 up to 43 ms, with one 8-15 ms, the 50 in about
    # 1 s more (bench/RESULTS-service.md).
    RECEIVING_AT_ONCE = 1
    TURN_WAIT = 2.0

    def __init__(self, app: ASGIApp, settings: Settings, error_status: dict[type[JobError], int],
                 path: str = "/v1/jobs"):
        self.app = app
        self.settings = settings
        self.error_status = error_status  # the app's answer to each refusal
        self.path = path
        self._turns: asyncio.Semaphore | None = None

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or scope["method"] != "POST" or scope["path"].rstrip("/") != self.path:
            await self.app(scope, receive, send)
            return
        headers = {k.decode("latin-1").lower(): v.decode("latin-1") for k, v in scope["headers"]}
        refusal = self._refuse(scope, headers)
        if refusal is not None:
            status, detail, extra = refusal
            await _answer(send, status, detail, extra)
            return
        limit = self.settings.max_upload_bytes
        seen = 0

        async def counted() -> Message:
            nonlocal seen
            message = await receive()
            if message["type"] == "http.request":
                seen += len(message.get("body", b""))
                if seen > limit:
                    raise TooLarge(_too_large(limit))
            return message

        if self._turns is None:
            self._turns = asyncio.Semaphore(self.RECEIVING_AT_ONCE)
        try:
            await asyncio.wait_for(self._turns.acquire(), self.TURN_WAIT)
            turn = True
        except asyncio.TimeoutError:
            turn = False
        try:
            await self.app(scope, counted, send)
        finally:
            if turn:
                self._turns.release()

    def _refuse(self, scope: Scope, headers: dict[str, str]) -> tuple[int, str, dict] | None:
        jobs = getattr(getattr(scope.get("app"), "state", None), "jobs", None)  # the JobService, once started
        length = headers.get("content-length")
        announced = int(length) if length is not None and length.isdigit() else None
        if jobs is not None:
            try:
                user = authorized_user(jobs.store, headers.get("authorization"))
                jobs.check_quota(user)
                jobs.check_storage(user, announced or 0)
            except HTTPException as e:
                return e.status_code, e.detail, dict(e.headers or {})
            except (TooMany, TooLarge, NoSpace) as e:
                return self.error_status[type(e)], e.detail, {"connection": "close"}
        if announced is not None and announced > self.settings.max_upload_bytes:
            return self.error_status[TooLarge], _too_large(self.settings.max_upload_bytes), {"connection": "close"}
        return None


def _too_large(limit: int) -> str:
    return (f"upload larger than this server's limit of {limit / 2**20:.1f} MiB per job "
            "(ACINOSET_MAX_UPLOAD_BYTES)")


async def _answer(send: Send, status: int, detail: str, extra: dict[str, str]) -> None:
    body = json.dumps({"detail": detail}).encode()
    headers = [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode())]
    headers += [(k.lower().encode(), v.encode()) for k, v in extra.items()]
    await send({"type": "http.response.start", "status": status, "headers": headers})
    await send({"type": "http.response.body", "body": body})
