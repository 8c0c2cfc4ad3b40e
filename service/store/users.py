"""Users and their tokens.

Tokens: ``acn_<key id>_<secret>``. The table holds the key id and SHA-256 of the secret (the
secret is 256 random bits, so a plain hash suffices); a lookup finds the row by key id and compares
the hashes with :func:`hmac.compare_digest`, in constant time. A user has one live token: a new one
revokes the others. A removed user is kept (disabled, its tokens deleted) so its jobs keep an owner.
"""

from __future__ import annotations

import hashlib
import hmac
import re
import secrets
import sqlite3
import time

from service.store.database import Database
from service.store.errors import StoreRefused
from service.store.jobs import counts
from service.store.records import ACTIVE_IN, USER_COLUMNS, User, user_from_row

USER_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._@-]{0,63}$")
TOKEN_PREFIX = "acn"
_DUMMY_HASH = hashlib.sha256(b"no such key").hexdigest()


def hash_secret(secret: str) -> str:
    return hashlib.sha256(secret.encode("utf-8")).hexdigest()


def _new_token(db: sqlite3.Connection, user_id: int, now: float) -> str:
    key_id = secrets.token_hex(6)
    secret = secrets.token_urlsafe(32)
    db.execute("INSERT INTO tokens(key_id, user_id, secret_sha256, created_at) VALUES (?, ?, ?, ?)",
               (key_id, user_id, hash_secret(secret), now))
    return f"{TOKEN_PREFIX}_{key_id}_{secret}"


def _revoke(db: sqlite3.Connection, name: str) -> int:
    """Delete the tokens of the user ``name``; its id."""
    row = db.execute("SELECT id FROM users WHERE name = ?", (name,)).fetchone()
    if not row:
        raise StoreRefused(f"no user {name!r}")
    db.execute("DELETE FROM tokens WHERE user_id = ?", (row[0],))
    return row[0]


class UserStore(Database):
    """The users and tokens of the job table."""

    def add_user(self, name: str, admin: bool = False) -> tuple[User, str]:
        """A new user and its first token (the token is returned once and never stored)."""
        if not USER_NAME.match(name):
            raise StoreRefused(f"bad user name {name!r}: use 1-64 letters, digits, '.', '_', '-', '@'")
        now = time.time()
        with self.transaction() as db:
            if db.execute("SELECT 1 FROM users WHERE name = ?", (name,)).fetchone():
                raise StoreRefused(f"user {name!r} already exists (use 'acinoset users token {name}' for a new token)")
            uid = db.execute("INSERT INTO users(name, is_admin, created_at) VALUES (?, ?, ?)",
                             (name, int(admin), now)).lastrowid
            assert uid is not None
            token = _new_token(db, uid, now)
        return User(uid, name, admin, False, now), token

    def new_token(self, name: str, enable: bool = False) -> str:
        """Revoke a user's tokens and issue a new one. A removed user stays removed (:class:`StoreRefused`)
        unless ``enable``: a new token alone must not bring it back."""
        with self.transaction() as db:
            row = db.execute("SELECT disabled FROM users WHERE name = ?", (name,)).fetchone()
            if row and row[0] and not enable:
                raise StoreRefused(f"user {name!r} was removed; give --enable to let it sign in again with a new token")
            uid = _revoke(db, name)
            db.execute("UPDATE users SET disabled = 0 WHERE id = ?", (uid,))
            return _new_token(db, uid, time.time())

    def disable_user(self, name: str) -> int:
        """Revoke a user's tokens and cancel its queued and running jobs; returns how many were cancelled.
        Its jobs stay in the table (admins can still read and delete them)."""
        now = time.time()
        with self.transaction() as db:
            uid = _revoke(db, name)
            db.execute("UPDATE users SET disabled = 1 WHERE id = ?", (uid,))
            return db.execute(
                "UPDATE jobs SET status = 'cancelled', finished_at = ?, updated_at = ?, lease_until = NULL, "
                "detail = NULL, error = 'cancelled: the user was removed' "
                f"WHERE owner_id = ? AND status IN {ACTIVE_IN}",
                (now, now, uid)).rowcount

    def user(self, name: str) -> User | None:
        with self.reading() as db:
            row = db.execute(f"SELECT {USER_COLUMNS} FROM users WHERE name = ?", (name,)).fetchone()
        return user_from_row(row) if row else None

    def users(self) -> list[tuple[User, dict[str, int]]]:
        """Every user with its job counts by status (the states it has jobs in)."""
        with self.reading() as db:
            rows = db.execute(f"SELECT {USER_COLUMNS} FROM users ORDER BY name").fetchall()
            return [(user_from_row(r), counts(db, r[0])) for r in rows]

    def authenticate(self, token: str) -> User | None:
        """The user a token belongs to, or None. Constant time in the secret."""
        parts = token.split("_", 2)
        if len(parts) != 3 or parts[0] != TOKEN_PREFIX:
            key_id, secret = "", token
        else:
            key_id, secret = parts[1], parts[2]
        with self.reading() as db:
            row = db.execute(
                "SELECT t.secret_sha256, u.id, u.name, u.is_admin, u.disabled, u.created_at "
                "FROM tokens t JOIN users u ON u.id = t.user_id WHERE t.key_id = ?", (key_id,)).fetchone()
        expected = row[0] if row else _DUMMY_HASH
        ok = hmac.compare_digest(hash_secret(secret), expected)
        if not (ok and row) or row[4]:
            return None
        return user_from_row(row[1:], key_id)

    def token_holder(self, key_id: str) -> User | None:
        """The user of the live token whose key id is ``key_id`` (a media link names it), or None
        once that token was revoked or its user removed."""
        with self.reading() as db:
            row = db.execute(
                "SELECT u.id, u.name, u.is_admin, u.disabled, u.created_at "
                "FROM tokens t JOIN users u ON u.id = t.user_id WHERE t.key_id = ?", (key_id,)).fetchone()
        if not row or row[3]:
            return None
        return user_from_row(row, key_id)
