"""Who is calling: the ``Authorization: Bearer TOKEN`` header, checked against the user table.

Use as a FastAPI dependency: ``user: User = Depends(current_user)``. No header, or a token that is
unknown or revoked, is 401 with a JSON ``detail``. Tokens are made with ``acinoset users add``.
"""

from __future__ import annotations

import math
import threading
import time
from collections import OrderedDict, deque

from fastapi import HTTPException, Request

from service.store import Store, User

_CHALLENGE = {"WWW-Authenticate": "Bearer"}
WINDOW_SECONDS = 60.0
MAX_ADDRESSES = 10_000  # addresses remembered; the oldest are forgotten first


class TokenFailures:
    """Invalid tokens per client address over the last minute. Tokens are 256-bit, so guessing is
    hopeless, but an address that keeps sending wrong ones is refused (429, Retry-After) until its
    minute has passed: every call from it, with a valid token too (a lab behind one address waits a
    minute, the guesser gets nowhere). Memory is bounded: at most :data:`MAX_ADDRESSES` addresses of
    at most ``limit`` times each."""

    def __init__(self, limit: int):
        self.limit = limit
        self._seen: OrderedDict[str, deque[float]] = OrderedDict()
        self._lock = threading.Lock()

    def _recent(self, address: str, now: float) -> deque[float] | None:
        times = self._seen.get(address)
        while times and now - times[0] > WINDOW_SECONDS:
            times.popleft()
        return times

    def retry_after(self, address: str) -> int | None:
        """Seconds until ``address`` may call again, or None when it may now."""
        now = time.monotonic()
        with self._lock:
            times = self._recent(address, now)
            if times is None or len(times) < self.limit:
                return None
            return max(1, math.ceil(WINDOW_SECONDS - (now - times[0])))

    def failed(self, address: str) -> None:
        now = time.monotonic()
        with self._lock:
            times = self._recent(address, now)
            if times is None:
                times = self._seen[address] = deque(maxlen=self.limit)
                while len(self._seen) > MAX_ADDRESSES:
                    self._seen.popitem(last=False)
            self._seen.move_to_end(address)
            times.append(now)


def bearer_token(header: str | None) -> str | None:
    """The token of an ``Authorization: Bearer TOKEN`` header's value, or None."""
    scheme, _, token = (header or "").partition(" ")
    if scheme.lower() != "bearer" or not token.strip():
        return None
    return token.strip()


def authorized_user(store: Store, header: str | None) -> User:
    """The user of the ``Authorization`` header's value; 401 if none, or an unknown or revoked token."""
    token = bearer_token(header)
    if token is None:
        raise HTTPException(401, "missing token: send 'Authorization: Bearer TOKEN' "
                                 "(an admin makes one with 'acinoset users add NAME')", headers=_CHALLENGE)
    user = store.authenticate(token)
    if user is None:
        raise HTTPException(401, "invalid or revoked token", headers=_CHALLENGE)
    return user


def current_user(request: Request) -> User:
    """The caller (:func:`authorized_user`), unless its address sent too many invalid tokens lately
    (:class:`TokenFailures`, on the app's state: 429)."""
    failures: TokenFailures | None = getattr(request.app.state, "token_failures", None)
    address = request.client.host if request.client else ""
    if failures is not None:
        wait = failures.retry_after(address)
        if wait is not None:
            raise HTTPException(429, f"too many invalid tokens from this address; try again in {wait} s",
                                headers={"Retry-After": str(wait)})
    try:
        return authorized_user(request.app.state.store, request.headers.get("authorization"))
    except HTTPException as e:
        if failures is not None and e.status_code == 401 and bearer_token(request.headers.get("authorization")):
            failures.failed(address)
        raise

