"""API keys and roles.

A key is shown once, when it is created; the store keeps only its SHA-256
hash and an 8-character prefix to tell keys apart in lists.  Roles grant
permissions:

==========  ====  ======  =======  ======  =====
role        read  alarms  tickets  ingest  admin
==========  ====  ======  =======  ======  =====
viewer       x
operator     x      x
maintenance  x              x
historian                           x
admin        x      x       x       x       x
==========  ====  ======  =======  ======  =====

Requests are authenticated by :class:`KeyVerifier`, which asks the store on
every request (a revoked key is refused at once).  While the store cannot be
reached it still admits the keys it confirmed within ``grace_s``, so that a
historian's batches reach the ingest spool during a database outage; other
keys get :class:`~service.spool.StoreUnavailableError` (HTTP 503).  A key
revoked by another API replica just before an outage may thus be admitted
for up to ``grace_s`` more.  Keys and their hashes are never logged.
"""

from __future__ import annotations

import hashlib
import hmac
import secrets
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal, cast

from sqlalchemy import select
from sqlalchemy.orm import Session

from service.spool import StoreUnavailableError, is_store_outage
from service.store.db import Store
from service.store.models import ApiKey

__all__ = [
    "PERMISSIONS",
    "ROLES",
    "AuthError",
    "KeyVerifier",
    "Permission",
    "Principal",
    "Role",
    "authenticate",
    "create_key",
    "ensure_bootstrap_key",
    "hash_key",
    "list_keys",
    "revoke_key",
]

Role = Literal["viewer", "operator", "maintenance", "historian", "admin"]
Permission = Literal["read", "alarms", "tickets", "ingest", "admin"]
ROLES: tuple[Role, ...] = ("viewer", "operator", "maintenance", "historian", "admin")
PERMISSIONS: dict[Role, frozenset[Permission]] = {
    "viewer": frozenset({"read"}),
    "operator": frozenset({"read", "alarms"}),
    "maintenance": frozenset({"read", "tickets"}),
    "historian": frozenset({"ingest"}),
    "admin": frozenset({"read", "alarms", "tickets", "ingest", "admin"}),
}


class AuthError(ValueError):
    """A key operation was refused (unknown role, unknown key)."""


def hash_key(key: str) -> str:
    """SHA-256 hex digest of a key (keys are random, so no salt is needed)."""
    return hashlib.sha256(key.encode()).hexdigest()


def _insert(session: Session, key: str, name: str, role: Role, now: float) -> ApiKey:
    row = ApiKey(name=name, role=role, key_hash=hash_key(key), prefix=key[:8], created_at=now)
    session.add(row)
    session.flush()
    return row


def create_key(session: Session, name: str, role: str, now: float) -> tuple[str, ApiKey]:
    """A new random key for ``role``: the plain key (shown once) and its row."""
    if role not in ROLES:
        raise AuthError(f"unknown role {role!r}; roles are {', '.join(ROLES)}")
    key = "lw_" + secrets.token_urlsafe(30)
    return key, _insert(session, key, name, role, now)


def ensure_bootstrap_key(session: Session, key: str, now: float) -> None:
    """Store the bootstrap admin key (from the settings) unless it is already there."""
    if session.scalar(select(ApiKey).where(ApiKey.key_hash == hash_key(key))) is None:
        _insert(session, key, "bootstrap", "admin", now)


def authenticate(session: Session, key: str) -> ApiKey | None:
    """The active key row matching ``key``, or None."""
    digest = hash_key(key)
    row = session.scalar(select(ApiKey).where(ApiKey.key_hash == digest))
    if row is None or row.revoked_at is not None:
        return None
    return row if hmac.compare_digest(row.key_hash, digest) else None


def list_keys(session: Session) -> list[ApiKey]:
    """All keys, newest first (hashes are never returned by the API)."""
    return list(session.scalars(select(ApiKey).order_by(ApiKey.id.desc())))


def revoke_key(session: Session, key_id: int, now: float) -> ApiKey:
    """Revoke key ``key_id``; revoking twice keeps the first time."""
    row = session.get(ApiKey, key_id)
    if row is None:
        raise AuthError(f"no API key with id {key_id}")
    if row.revoked_at is None:
        row.revoked_at = now
    return row


@dataclass(frozen=True)
class Principal:
    """The holder of an authenticated key: what routes know about the caller."""

    id: int
    name: str
    role: str

    @property
    def permissions(self) -> frozenset[Permission]:
        """What the key's role may do."""
        return PERMISSIONS.get(cast(Role, self.role), frozenset())


class KeyVerifier:
    """Authenticates keys against the store, riding out short store outages.

    Parameters
    ----------
    store : Store
        Where the keys are.
    grace_s : float
        While the store is unreachable, a key confirmed by the store within
        the last ``grace_s`` seconds is still admitted (0: none is).
    clock : callable
        Monotonic seconds (injectable for tests).
    """

    def __init__(self, store: Store, *, grace_s: float,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.store = store
        self.grace_s = grace_s
        self.clock = clock
        self._confirmed: dict[str, tuple[Principal, float]] = {}  # digest -> (who, when)
        self._lock = threading.Lock()

    def verify(self, key: str) -> Principal | None:
        """The principal of an active ``key``, or None if it is unknown or revoked.

        Raises
        ------
        StoreUnavailableError
            The store cannot be reached and ``key`` was not confirmed within
            ``grace_s``.
        """
        digest = hash_key(key)
        try:
            with self.store.session() as session:
                row = authenticate(session, key)
                principal = None if row is None else Principal(row.id, row.name, row.role)
        except Exception as exc:
            if not is_store_outage(exc):
                raise
            return self._during_outage(digest)
        with self._lock:
            if principal is None:
                self._confirmed.pop(digest, None)
            else:
                self._confirmed[digest] = (principal, self.clock())
        return principal

    def _during_outage(self, digest: str) -> Principal:
        with self._lock:
            known = self._confirmed.get(digest)
        if known is not None and self.clock() - known[1] <= self.grace_s:
            return known[0]
        raise StoreUnavailableError(
            "The store is unreachable, so the API key cannot be checked; try again later"
        )
