"""Links to a job's videos that a browser's ``<video>`` element can follow.

A media element cannot send the ``Authorization`` header, and the token must not travel in URLs
(they end up in logs and histories). So an authorised call (``GET /v1/jobs/{id}/videos``) hands out
links carrying ``access=<expires>.<key>.<signature>``: ``key`` is the key id of the token that
asked (its public part, never the secret) and the signature an HMAC-SHA256, under a key this server
process draws at start, of the job id, that key id and the expiry time. A link opens that job's
videos only, and only while the token it was made for is live and its user may still see the job:
revoking the token (``acinoset users token``) or removing the user closes its links at once.
Otherwise a link lasts until it expires (:data:`LIFETIME`) or the server restarts.
"""

from __future__ import annotations

import hashlib
import hmac
import re
import secrets
import time

LIFETIME = 6 * 3600.0  # seconds a link stays valid
_KEY = secrets.token_bytes(32)
_KEY_ID = re.compile(r"[0-9a-f]{1,32}")


def _mac(job_id: str, key_id: str, expires: int) -> str:
    return hmac.new(_KEY, f"{job_id}:{key_id}:{expires}".encode(), hashlib.sha256).hexdigest()


def sign(job_id: str, key_id: str, now: float | None = None) -> str:
    """The ``access`` value for ``job_id``'s videos on behalf of the token ``key_id``, valid for
    :data:`LIFETIME` seconds."""
    expires = int((time.time() if now is None else now) + LIFETIME)
    return f"{expires}.{key_id}.{_mac(job_id, key_id, expires)}"


def expiry(access: str) -> int:
    """The expiry time (Unix seconds) of an ``access`` value made by :func:`sign`."""
    return int(access.split(".", 1)[0])


def signer(job_id: str, access: str, now: float | None = None) -> str | None:
    """The key id of the token ``access`` was signed for, if it was signed here for ``job_id`` and has
    not expired; else None. Whether that token is still live is the caller's to check."""
    expires, _, rest = access.partition(".")
    key_id, _, mac = rest.partition(".")
    if not expires.isdigit() or len(expires) > 12 or not _KEY_ID.fullmatch(key_id):
        return None
    if int(expires) < (time.time() if now is None else now):
        return None
    return key_id if hmac.compare_digest(mac, _mac(job_id, key_id, int(expires))) else None
