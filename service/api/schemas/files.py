"""OpenAPI content of the answers that are files: text (CSV, SVG) or binary (PDF, PNG)."""

from __future__ import annotations

from typing import Any

TEXT: dict[str, Any] = {"schema": {"type": "string"}}
"""A text file of the media type it is filed under."""

BINARY: dict[str, Any] = {"schema": {"type": "string", "format": "binary"}}
"""A binary file of the media type it is filed under."""
