"""Shared state and dependencies of the API routes."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Annotated

from fastapi import Depends, HTTPException, Request, Security
from fastapi.security import APIKeyHeader
from sqlalchemy.orm import Session

from service.auth import Permission, Principal
from service.runtime import AppState
from service.security import retry_after

__all__ = ["AppState", "Principal", "RequireKey", "SessionDep", "StateDep", "require"]


def get_state(request: Request) -> AppState:
    """The application's :class:`AppState`."""
    state: AppState = request.app.state.loopwatch
    return state


StateDep = Annotated[AppState, Depends(get_state)]


def get_session(state: StateDep) -> Iterator[Session]:
    """One transaction per request: committed when the route returns normally."""
    with state.store.session() as session:
        yield session


SessionDep = Annotated[Session, Depends(get_session)]

_key_header = APIKeyHeader(name="X-API-Key", auto_error=False)


class RequireKey:
    """A dependency that admits active keys, counted against their rate limit.

    ``permission`` None admits any active key; otherwise the key's role must
    grant it.  Missing, unknown or revoked key: 401; over the key's rate
    limit: 429 with ``Retry-After``; a role without the permission: 403.
    The route-table test reads ``permission`` to check every route's access.
    """

    def __init__(self, permission: Permission | None) -> None:
        self.permission = permission

    def __call__(self, state: StateDep,
                 key: Annotated[str | None, Security(_key_header)]) -> Principal:
        if not key:
            raise HTTPException(401, "Missing API key (header X-API-Key)")
        principal = state.keys.verify(key)
        if principal is None:
            raise HTTPException(401, "Invalid or revoked API key")
        wait = state.limiter.acquire(principal.id)
        if wait > 0:
            raise HTTPException(
                429,
                f"Rate limit of {state.limiter.rate_per_s:g} requests/s (burst "
                f"{state.limiter.burst}) exceeded for key {principal.name!r}; retry later",
                headers={"Retry-After": retry_after(wait)},
            )
        if self.permission is not None and self.permission not in principal.permissions:
            raise HTTPException(403, f"Role {principal.role!r} may not {self.permission}")
        return principal


def require(permission: Permission | None) -> RequireKey:
    """The dependency admitting keys whose role grants ``permission`` (None: any key)."""
    return RequireKey(permission)
