"""Links to a job's videos that a browser's ``<video>`` element can follow.

A media element cannot send the ``Authorization`` header, and the token must not travel in URLs
(they end up in logs and histories). So an authorised call (``GET /v1/jobs/{id}/videos``) hands out
links carrying ``access=<expires>.<signature>``: an HMAC-SHA256, under a key this server process
draws at start, of the job id and the expiry time. A link opens that job's videos only, until it
expires (:data:`LIFETIME`) or the server restarts, whichever comes first.
"""

from __future__ import annotations

import hashlib
import hmac
import secrets
import time

LIFETIME = 6 * 3600.0  # seconds a link stays valid
_KEY = secrets.token_bytes(32)


def _mac(job_id: str, expires: int) -> str:
    return hmac.new(_KEY, f"{job_id}:{expires}".encode(), hashlib.sha256).hexdigest()


def sign(job_id: str, now: float | None = None) -> str:
    """The ``access`` value for ``job_id``'s videos, valid for :data:`LIFETIME` seconds."""
    expires = int((time.time() if now is None else now) + LIFETIME)
    return f"{expires}.{_mac(job_id, expires)}"


def valid(job_id: str, access: str, now: float | None = None) -> bool:
    """Whether ``access`` was signed here for ``job_id`` and has not expired."""
    expires, _, mac = access.partition(".")
    if not expires.isdigit() or len(expires) > 12:
        return False
    if int(expires) < (time.time() if now is None else now):
        return False
    return hmac.compare_digest(mac, _mac(job_id, int(expires)))
