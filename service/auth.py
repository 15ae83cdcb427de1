"""API keys and roles.

A key is shown once, when it is created.  The store keeps a key id that is
not secret (it names the key in lists and logs), a random salt per key and
``SHA-256(salt || SHA-256(key))``: a stolen table neither shows the keys nor
lets one hash be tried against all rows at once.  A generated key carries its
id (``lw_<key id>_<secret>``), so it is checked against one row; a key chosen
by the operator (the bootstrap ``LOOPWATCH_API_KEY``, and keys stored before
migration 0004) has an ``ext-`` id and is checked against those rows, which
are few.  Roles grant permissions:

==========  ====  ======  =======  ======  =====
role        read  alarms  tickets  ingest  admin
==========  ====  ======  =======  ======  =====
viewer       x
operator     x      x
maintenance  x              x
historian                           x
admin        x      x       x       x       x
==========  ====  ======  =======  ======  =====

Requests are authenticated by :class:`KeyVerifier`.  A key the store
confirmed within ``cache_s`` (``LOOPWATCH_AUTH_CACHE_S``) is admitted without
asking it again (:meth:`KeyVerifier.cached`: twenty dashboards polling each
second asked the store eighty times a second, each from a worker thread).  A
key revoked through this process is refused by it at once
(:meth:`KeyVerifier.revoked`); one revoked by another API replica, or in the
database, is refused by this process at most ``cache_s`` later.  While the
store cannot be reached it still admits the keys it confirmed within
``grace_s``, so that a historian's batches reach the ingest spool during a
database outage; other keys get :class:`~service.spool.StoreUnavailableError`
(HTTP 503).  A key revoked by another API replica just before an outage may
thus be admitted for up to ``grace_s`` more.  Keys and their hashes are never
logged.
"""

from __future__ import annotations

import hashlib
import hmac
import re
import secrets
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal, cast

from sqlalchemy import func, select
from sqlalchemy.orm import Session

from service.spool import StoreUnavailableError, is_store_outage
from service.store.db import Store
from service.store.models import ApiKey

__all__ = [
    "PERMISSIONS",
    "ROLES",
    "RUN_KEY_NAME",
    "AuthError",
    "KeyConflictError",
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
    "salted_hash",
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


class KeyConflictError(AuthError):
    """A key operation that would lock every administrator out."""


EXTERNAL_ID_PREFIX = "ext-"
"""Key ids of keys that do not carry their id (bootstrap keys, keys from before 0004)."""

_GENERATED = re.compile(r"lw_([0-9a-f]{12})_[A-Za-z0-9_-]{40}")


def hash_key(key: str) -> str:
    """SHA-256 hex digest of a key: the salted hash's input, and the in-memory cache key
    of :class:`KeyVerifier` (never stored)."""
    return hashlib.sha256(key.encode()).hexdigest()


def salted_hash(key_digest: str, salt: str) -> str:
    """What the store keeps of a key: ``SHA-256(salt || SHA-256(key))``, hex (both
    arguments hex, ``key_digest`` from :func:`hash_key`)."""
    return hashlib.sha256(bytes.fromhex(salt) + bytes.fromhex(key_digest)).hexdigest()


def _insert(session: Session, key: str, key_id: str, name: str, role: Role,
            now: float) -> ApiKey:
    salt = secrets.token_hex(16)
    row = ApiKey(name=name, role=role, key_id=key_id, salt=salt,
                 key_hash=salted_hash(hash_key(key), salt), created_at=now)
    session.add(row)
    session.flush()
    return row


def _candidates(session: Session, key: str) -> list[ApiKey]:
    """The rows ``key`` may be: the one its id names, else the rows without one."""
    generated = _GENERATED.fullmatch(key)
    if generated is not None:
        row = session.scalar(select(ApiKey).where(ApiKey.key_id == generated[1]))
        if row is not None:
            return [row]
    return list(session.scalars(
        select(ApiKey).where(ApiKey.key_id.startswith(EXTERNAL_ID_PREFIX))))


def _matching(session: Session, key: str) -> ApiKey | None:
    digest = hash_key(key)
    for row in _candidates(session, key):
        if hmac.compare_digest(row.key_hash, salted_hash(digest, row.salt)):
            return row
    return None


def create_key(session: Session, name: str, role: str, now: float) -> tuple[str, ApiKey]:
    """A new random key for ``role``: the plain key (shown once) and its row."""
    if role not in ROLES:
        raise AuthError(f"unknown role {role!r}; roles are {', '.join(ROLES)}")
    key_id = secrets.token_hex(6)
    key = f"lw_{key_id}_{secrets.token_urlsafe(30)}"
    return key, _insert(session, key, key_id, name, role, now)


RUN_KEY_NAME = "bootstrap, this run only"
"""Name of an admin key generated for one run (no ``LOOPWATCH_API_KEY`` set)."""


def ensure_bootstrap_key(session: Session, key: str, now: float, *,
                         generated: bool = False) -> None:
    """Store the bootstrap admin key unless it is already there.

    A key from the settings is named ``bootstrap``.  A key ``generated`` for
    this run (:meth:`service.config.Settings.bootstrap_key`) is named
    :data:`RUN_KEY_NAME`, and revokes the keys generated for earlier runs:
    nobody can use them again (their run printed them, and is over), so they
    must not pile up as active admin keys, one per start.
    """
    if _matching(session, key) is not None:
        return
    new = _insert(session, key, EXTERNAL_ID_PREFIX + secrets.token_hex(6),
                  RUN_KEY_NAME if generated else "bootstrap", "admin", now)
    if generated:
        for row in session.scalars(select(ApiKey).where(
                ApiKey.name == RUN_KEY_NAME, ApiKey.revoked_at.is_(None), ApiKey.id != new.id)):
            row.revoked_at = now


def authenticate(session: Session, key: str) -> ApiKey | None:
    """The active key row matching ``key``, or None."""
    row = _matching(session, key)
    return None if row is None or row.revoked_at is not None else row


def list_keys(session: Session) -> list[ApiKey]:
    """All keys, newest first (hashes are never returned by the API)."""
    return list(session.scalars(select(ApiKey).order_by(ApiKey.id.desc())))


def revoke_key(session: Session, key_id: int, now: float) -> ApiKey:
    """Revoke key ``key_id``; revoking twice keeps the first time.

    Raises
    ------
    AuthError
        No key has that id.
    KeyConflictError
        It is the last active admin key: nobody could manage keys afterwards.
    """
    row = session.get(ApiKey, key_id)
    if row is None:
        raise AuthError(f"no API key with id {key_id}")
    if row.revoked_at is None and row.role == "admin":
        admins = session.scalar(select(func.count()).where(
            ApiKey.role == "admin", ApiKey.revoked_at.is_(None)))
        if admins == 1:
            raise KeyConflictError(f"Key {key_id} is the last active admin key; create "
                                   "another admin key before revoking it")
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

    @property
    def actor(self) -> str:
        """Who acted, as histories and audit records name the key: ``name (role)``."""
        return f"{self.name} ({self.role})"


class KeyVerifier:
    """Authenticates keys against the store, riding out short store outages.

    Parameters
    ----------
    store : Store
        Where the keys are.
    grace_s : float
        While the store is unreachable, a key confirmed by the store within
        the last ``grace_s`` seconds is still admitted (0: none is).
    cache_s : float
        A key confirmed by the store within the last ``cache_s`` seconds is
        admitted by :meth:`cached` without asking the store (0: never).
    clock : callable
        Monotonic seconds (injectable for tests).
    """

    def __init__(self, store: Store, *, grace_s: float, cache_s: float = 0.0,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.store = store
        self.grace_s = grace_s
        self.cache_s = cache_s
        self.clock = clock
        self._confirmed: dict[str, tuple[Principal, float]] = {}  # digest -> (who, when)
        self._revoked: set[int] = set()  # row ids of keys revoked through this process
        self._lock = threading.Lock()

    def _known(self, digest: str, within_s: float) -> Principal | None:
        with self._lock:
            known = self._confirmed.get(digest)
            if known is None or known[0].id in self._revoked:
                return None
        return known[0] if self.clock() - known[1] <= within_s else None

    def cached(self, key: str) -> Principal | None:
        """The principal of ``key`` if the store confirmed it within ``cache_s`` and it
        was not revoked through this process since; else None (ask :meth:`verify`).
        Does no I/O: safe on the event loop."""
        return self._known(hash_key(key), self.cache_s) if self.cache_s > 0 else None

    def revoked(self, key_id: int) -> None:
        """Key row ``key_id`` was revoked: no longer admitted from memory."""
        with self._lock:
            self._revoked.add(key_id)

    def verify(self, key: str) -> Principal | None:
        """The principal of an active ``key``, or None if it is unknown or revoked.

        Raises
        ------
        StoreUnavailableError
            The store cannot be reached and ``key`` was not confirmed within
            ``grace_s``.
        """
        digest = hash_key(key)
        asked = self.clock()  # the confirmation dates from before the store was read
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
                self._confirmed[digest] = (principal, asked)
        return principal

    def _during_outage(self, digest: str) -> Principal:
        known = self._known(digest, self.grace_s)
        if known is not None:
            return known
        raise StoreUnavailableError(
            "The store is unreachable, so the API key cannot be checked; try again later"
        )
