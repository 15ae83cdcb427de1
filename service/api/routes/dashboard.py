"""The dashboard: ``/`` serves the single page, ``/static/{name}`` its script and style.

Everything the page needs ships in ``service/static`` (no build step, no CDN),
so it works on a plant network without internet access.  The page talks to
the REST API with the key the user gives once; it keeps the key in the
browser tab's ``sessionStorage`` (gone when the tab closes) and accepts it
from a ``#key=...`` link as well: the fragment never reaches the server, so
the key stays out of access logs and proxies, and the page removes it from
the address bar at once.  ``GET /api/v1/me`` tells the page whose key it
holds, so it offers operator buttons only to roles that may use them.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

from fastapi import APIRouter, Depends, HTTPException
from fastapi.responses import FileResponse
from pydantic import BaseModel

from service.api.deps import ERROR_RESPONSES, Principal, require
from service.auth import PERMISSIONS

router = APIRouter(tags=["dashboard"])

STATIC_DIR = Path(__file__).resolve().parents[2] / "static"
MEDIA_TYPES = {".html": "text/html; charset=utf-8", ".js": "text/javascript; charset=utf-8",
               ".css": "text/css; charset=utf-8", ".svg": "image/svg+xml"}
STATIC_FILES = {p.name: p for p in sorted(STATIC_DIR.iterdir()) if p.suffix in MEDIA_TYPES}
"""The files served, fixed at start: a request can name nothing else."""
NO_CACHE = {"Cache-Control": "no-cache"}


class WhoAmI(BaseModel):
    """The key the request came with: its name, role and what the role may do."""

    name: str
    role: str
    permissions: list[str]


@router.get("/", include_in_schema=False)
def dashboard() -> FileResponse:
    """The dashboard page (it asks for an API key, then reads the API)."""
    return FileResponse(STATIC_FILES["index.html"], media_type=MEDIA_TYPES[".html"],
                        headers=NO_CACHE)


@router.get("/static/{name}", include_in_schema=False)
def static_file(name: str) -> FileResponse:
    """A script, style or icon of the dashboard."""
    path = STATIC_FILES.get(name)
    if path is None:
        raise HTTPException(404, "Static file not found")
    return FileResponse(path, media_type=MEDIA_TYPES[path.suffix], headers=NO_CACHE)


@router.get("/api/v1/me", response_model=WhoAmI, tags=["keys"], responses=ERROR_RESPONSES)
def who_am_i(key: Annotated[Principal, Depends(require("read"))]) -> WhoAmI:
    """The calling key's name, role and permissions (any role that may read)."""
    return WhoAmI(name=key.name, role=key.role,
                  permissions=sorted(PERMISSIONS[key.role]))  # type: ignore[index]
