"""Refuse an upload before reading it, and receive it before parsing it: an ASGI middleware in
front of ``POST /v1/jobs``.

FastAPI reads a whole multipart body before any dependency runs. This guard answers first, from the
headers alone, when the caller has no valid token (401), already has the most active jobs allowed
(429), has no room left for the body it announces (413 over the user's storage quota, 507 when the
server's disk or storage is full), announces a body over ``max_upload_bytes`` (413), or when too
many uploads are arriving at once (503). It then receives the body into a spooled file, counting
its bytes (413 at the limit) and timing it (408 when it stalls or takes too long), and only then
lets it in to be parsed and stored, a few submissions at a time.
"""

from __future__ import annotations

import asyncio
import json
import tempfile
import time

from fastapi import HTTPException
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from service.api.auth import authorized_user
from service.errors import JobError, NoSpace, TooLarge, TooMany
from service.settings import Settings


class UploadGuard:
    # Submissions parsed and stored at once; later ones wait for a turn, at most TURN_WAIT seconds.
    # Parsing and storing an upload is CPU work in this process: a burst of them queues here, and
    # the status polls and downloads sharing the process keep answering quickly. One at a time: with
    # two, status polls inside a burst of 50 uploads had p99 up to 43 ms, with one 8-15 ms
    # (bench/RESULTS-service.md). The body is received (and spooled to disk) before the turn is
    # taken, so a slow client holds nobody's turn: while one trickled its upload for 12 s, every
    # other submission took 2.2 s (the whole TURN_WAIT), now 0.1 s (bench/bench_slow_uploader.py).
    RECEIVING_AT_ONCE = 1
    TURN_WAIT = 2.0
    SPOOL_IN_MEMORY = 4 * 2**20  # bytes of a body kept in memory; beyond, it goes to a file in the jobs dir
    CHUNK = 2**20  # bytes handed to the app per message when the body is replayed

    def __init__(self, app: ASGIApp, settings: Settings, error_status: dict[type[JobError], int],
                 path: str = "/v1/jobs"):
        self.app = app
        self.settings = settings
        self.error_status = error_status  # the app's answer to each refusal
        self.path = path
        self._turns: asyncio.Semaphore | None = None
        self._receiving = 0  # bodies being received now

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or scope["method"] != "POST" or scope["path"].rstrip("/") != self.path:
            await self.app(scope, receive, send)
            return
        headers = {k.decode("latin-1").lower(): v.decode("latin-1") for k, v in scope["headers"]}
        refusal = self._refuse(scope, headers)
        if refusal is None and self._receiving >= self.settings.max_receiving_uploads:
            refusal = (503, f"{self._receiving} uploads are arriving already, the most this server receives at "
                            "once (ACINOSET_MAX_RECEIVING_UPLOADS); try again in a few seconds",
                       {"retry-after": "5", "connection": "close"})
        if refusal is not None:
            status, detail, extra = refusal
            await _answer(send, status, detail, extra)
            return
        self._receiving += 1
        try:
            body = await self._receive_body(receive, send)
        finally:
            self._receiving -= 1
        if body is None:
            return  # answered (too large, stalled, too slow) or the client left
        with body:
            if self._turns is None:
                self._turns = asyncio.Semaphore(self.RECEIVING_AT_ONCE)
            try:
                await asyncio.wait_for(self._turns.acquire(), self.TURN_WAIT)
                turn = True
            except asyncio.TimeoutError:
                turn = False
            try:
                await self.app(scope, _replay(body, receive, self.CHUNK), send)
            finally:
                if turn:
                    self._turns.release()

    async def _receive_body(self, receive: Receive, send: Send):
        """The whole request body in a spooled file, or None once the client was answered: 413 past
        ``max_upload_bytes``, 408 when no byte came for ``upload_idle_timeout_seconds`` or the body
        took longer than ``upload_timeout_seconds``."""
        s = self.settings
        body = tempfile.SpooledTemporaryFile(self.SPOOL_IN_MEMORY, dir=str(s.jobs_dir))
        deadline = time.monotonic() + s.upload_timeout_seconds
        seen = 0
        try:
            while True:
                wait = min(s.upload_idle_timeout_seconds, deadline - time.monotonic())
                try:
                    message = await asyncio.wait_for(receive(), max(wait, 0.001))
                except asyncio.TimeoutError:
                    late = time.monotonic() >= deadline
                    why = (f"took longer than {s.upload_timeout_seconds:g} s (ACINOSET_UPLOAD_TIMEOUT_SECONDS)" if late
                           else f"sent nothing for {s.upload_idle_timeout_seconds:g} s "
                                "(ACINOSET_UPLOAD_IDLE_TIMEOUT_SECONDS)")
                    await _answer(send, 408, f"the upload {why}; send it again", {"connection": "close"})
                    body.close()
                    return None
                if message["type"] == "http.disconnect":
                    body.close()
                    return None
                chunk = message.get("body", b"")
                seen += len(chunk)
                if seen > s.max_upload_bytes:
                    await _answer(send, self.error_status[TooLarge], _too_large(s.max_upload_bytes),
                                  {"connection": "close"})
                    body.close()
                    return None
                body.write(chunk)
                if not message.get("more_body", False):
                    body.seek(0)
                    return body
        except BaseException:
            body.close()
            raise

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


def _replay(body, receive: Receive, chunk: int) -> Receive:
    """A ``receive`` that hands the app the stored body, then waits on the client (a disconnect)."""
    size = body.seek(0, 2)
    body.seek(0)
    done = False

    async def replayed() -> Message:
        nonlocal done
        if done:
            return await receive()
        data = body.read(chunk)
        more = body.tell() < size
        done = not more
        return {"type": "http.request", "body": data, "more_body": more}

    return replayed


async def _answer(send: Send, status: int, detail: str, extra: dict[str, str]) -> None:
    body = json.dumps({"detail": detail}).encode()
    headers = [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode())]
    headers += [(k.lower().encode(), v.encode()) for k, v in extra.items()]
    await send({"type": "http.response.start", "status": status, "headers": headers})
    await send({"type": "http.response.body", "body": body})
