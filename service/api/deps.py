"""Shared state and dependencies of the API routes."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from typing import Annotated

from fastapi import Depends, HTTPException, Request, Security
from fastapi.security import APIKeyHeader
from sqlalchemy.orm import Session

from service.auth import PERMISSIONS, Permission, authenticate
from service.runtime import AppState
from service.store.models import ApiKey

__all__ = ["AppState", "Principal", "SessionDep", "StateDep", "require"]


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


def require(permission: Permission) -> Callable[..., ApiKey]:
    """A dependency that admits keys whose role grants ``permission``.

    Missing or unknown key: 401; a valid key without the permission: 403.
    """

    def check(session: SessionDep, key: Annotated[str | None, Security(_key_header)]) -> ApiKey:
        if not key:
            raise HTTPException(401, "Missing API key (header X-API-Key)")
        row = authenticate(session, key)
        if row is None:
            raise HTTPException(401, "Invalid or revoked API key")
        if permission not in PERMISSIONS[row.role]:  # type: ignore[index]
            raise HTTPException(403, f"Role {row.role!r} may not {permission}")
        return row

    return check


Principal = ApiKey
