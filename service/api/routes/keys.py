"""API keys (admin): create (the key is shown once), list, revoke."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, HTTPException
from pydantic import BaseModel, Field

from service.api.deps import (
    ERROR_RESPONSES,
    Admin,
    SessionDep,
    StateDep,
    error_responses,
    row_id,
)
from service.auth import AuthError, KeyConflictError, Role, create_key, list_keys, revoke_key
from service.logs import audit
from service.store.models import ApiKey

router = APIRouter(prefix="/api/v1/keys", tags=["keys"], responses=ERROR_RESPONSES)


class KeyCreate(BaseModel):
    """A new key's name and role."""

    name: str = Field(min_length=1, max_length=100)
    role: Role


class KeyPublic(BaseModel):
    """A key as listed: never the key itself, only its id (not secret)."""

    id: int
    name: str
    role: str
    key_id: str = Field(description="names the key; a generated key starts "
                                    "lw_<key_id>_, the bootstrap key's id starts ext-")
    created_at: float
    revoked_at: float | None


class KeyCreated(KeyPublic):
    """The response to creating a key: the only time the key is shown."""

    key: str


class KeysPublic(BaseModel):
    """All keys."""

    data: list[KeyPublic]
    count: int


def _public(row: ApiKey) -> KeyPublic:
    return KeyPublic.model_validate(row, from_attributes=True)


@router.post("", response_model=KeyCreated, status_code=201)
def create(body: KeyCreate, session: SessionDep, state: StateDep, admin: Admin) -> KeyCreated:
    """Create a key; store the returned ``key`` now, it cannot be shown again."""
    key, row = create_key(session, body.name, body.role, state.clock())
    session.flush()
    audit(admin.actor, "created API key", f"{row.key_id} ({row.name})",
          role=row.role)
    return KeyCreated(**_public(row).model_dump(), key=key)


@router.get("", response_model=KeysPublic)
def list_all(session: SessionDep, _: Admin) -> KeysPublic:
    """All keys, newest first."""
    rows = list_keys(session)
    return KeysPublic(data=[_public(r) for r in rows], count=len(rows))


@router.delete("/{key_id}", response_model=KeyPublic, responses=error_responses(404, 409))
def revoke(key_id: Annotated[int, row_id("the key's row id (`id`)")], session: SessionDep,
           state: StateDep, admin: Admin) -> KeyPublic:
    """Revoke a key; requests with it get 401 from now on.  409 for the last active
    admin key (create another one first)."""
    try:
        row = revoke_key(session, key_id, state.clock())
    except KeyConflictError as exc:
        raise HTTPException(409, str(exc)) from None
    except AuthError:
        raise HTTPException(404, "API key not found") from None
    state.keys.revoked(row.id)
    audit(admin.actor, "revoked API key", f"{row.key_id} ({row.name})",
          role=row.role)
    return _public(row)
