"""Who is calling: the ``Authorization: Bearer TOKEN`` header, checked against the user table.

Use as a FastAPI dependency: ``user: User = Depends(current_user)``. No header, or a token that is
unknown or revoked, is 401 with a JSON ``detail``. Tokens are made with ``acinoset users add``.
"""

from __future__ import annotations

from fastapi import HTTPException, Request

from service.store import Store, User

_CHALLENGE = {"WWW-Authenticate": "Bearer"}


def bearer_token(request: Request) -> str | None:
    header = request.headers.get("authorization")
    if not header:
        return None
    scheme, _, token = header.partition(" ")
    if scheme.lower() != "bearer" or not token.strip():
        return None
    return token.strip()


def current_user(request: Request) -> User:
    token = bearer_token(request)
    if token is None:
        raise HTTPException(401, "missing token: send 'Authorization: Bearer TOKEN' "
                                 "(an admin makes one with 'acinoset users add NAME')", headers=_CHALLENGE)
    store: Store = request.app.state.store
    user = store.authenticate(token)
    if user is None:
        raise HTTPException(401, "invalid or revoked token", headers=_CHALLENGE)
    return user

