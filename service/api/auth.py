"""Who is calling: the ``Authorization: Bearer TOKEN`` header, checked against the user table.

Use as a FastAPI dependency: ``user: User = Depends(current_user)``. No header, or a token that is
unknown or revoked, is 401 with a JSON ``detail``. Tokens are made with ``acinoset users add``.
"""

from __future__ import annotations

from fastapi import HTTPException, Request

from service.store import Store, User

_CHALLENGE = {"WWW-Authenticate": "Bearer"}


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
    return authorized_user(request.app.state.store, request.headers.get("authorization"))

