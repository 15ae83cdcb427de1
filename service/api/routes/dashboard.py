"""The dashboard: ``/`` serves the single page, ``/static/{name}`` its script and style;
``/docs`` and ``/redoc`` the API documentation (Swagger UI and ReDoc).

Everything the pages need ships in ``service/static`` (no build step, no CDN;
the documentation viewers are vendored in ``service/static/vendor``), so they
work on a plant network without internet access and under the
Content-Security-Policy of :mod:`service.security`.  The page talks to
the REST API with the key the user gives once; it keeps the key in the
browser tab's ``sessionStorage`` (gone when the tab closes) and accepts it
from a ``#key=...`` link as well: the fragment never reaches the server, so
the key stays out of access logs and proxies, and the page removes it from
the address bar at once.  ``GET /api/v1/me`` tells the page whose key it
holds, so it offers operator buttons only to roles that may use them.
"""

from __future__ import annotations

import secrets
from pathlib import Path
from typing import Annotated

from fastapi import APIRouter, Depends, HTTPException
from fastapi.responses import FileResponse, HTMLResponse
from pydantic import BaseModel

from service.api.deps import ERROR_RESPONSES, Principal, require
from service.auth import PERMISSIONS
from service.security import CONTENT_SECURITY_POLICY

router = APIRouter(tags=["dashboard"])

STATIC_DIR = Path(__file__).resolve().parents[2] / "static"
MEDIA_TYPES = {".html": "text/html; charset=utf-8", ".js": "text/javascript; charset=utf-8",
               ".css": "text/css; charset=utf-8", ".svg": "image/svg+xml"}
STATIC_FILES = {p.relative_to(STATIC_DIR).as_posix(): p for p in sorted(STATIC_DIR.rglob("*"))
                if p.suffix in MEDIA_TYPES and p.is_file()}
"""The files served, by their path under ``static``, fixed at start: a request can name
nothing else."""
NO_CACHE = {"Cache-Control": "no-cache"}
REDOC_STYLE_HASHES = (
    "sha256-47DEQpj8HBSa+/TImW+5JCeuQeRkm5NMpJWZG3hSuFU=",  # the element, still empty
    "sha256-QMIg+bpjm3JdElJ388KYke01izlUW0UoNOeKjpMxdgc=",  # its scrollbar styles
)
"""The ``<style>`` element the vendored ReDoc 2.5.4 adds as it loads, before any option
can give it a nonce (a new version with other styles fails ``test_api_docs_...``)."""


class WhoAmI(BaseModel):
    """The key the request came with: its name, role and what the role may do."""

    name: str
    role: str
    permissions: list[str]


def _page(name: str) -> FileResponse:
    """The HTML page ``name`` of ``static``."""
    return FileResponse(STATIC_FILES[name], media_type=MEDIA_TYPES[".html"], headers=NO_CACHE)


@router.get("/", include_in_schema=False)
def dashboard() -> FileResponse:
    """The dashboard page (it asks for an API key, then reads the API)."""
    return _page("index.html")


@router.get("/docs", include_in_schema=False)
def swagger_ui() -> FileResponse:
    """The API documentation with Swagger UI (it asks for a key to read the schema)."""
    return _page("docs.html")


@router.get("/redoc", include_in_schema=False)
def redoc() -> HTMLResponse:
    """The API documentation with ReDoc (it asks for a key to read the schema).

    ReDoc writes its styles into ``<style>`` elements: the page's policy is
    :data:`~service.security.CONTENT_SECURITY_POLICY` with those elements allowed
    by a nonce of this response (ReDoc's ``nonce`` option, as it renders) and by
    :data:`REDOC_STYLE_HASHES` (the one it adds as it loads), not by
    ``'unsafe-inline'``; scripts stay same-origin only.
    """
    nonce = secrets.token_urlsafe(18)
    page = STATIC_FILES["redoc.html"].read_text().replace("{{style_nonce}}", nonce)
    allowed = " ".join(f"'{source}'" for source in (f"nonce-{nonce}", *REDOC_STYLE_HASHES))
    policy = CONTENT_SECURITY_POLICY.replace("style-src 'self'", f"style-src 'self' {allowed}")
    return HTMLResponse(page, headers={**NO_CACHE, "Content-Security-Policy": policy})


@router.get("/static/{name:path}", include_in_schema=False)
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
