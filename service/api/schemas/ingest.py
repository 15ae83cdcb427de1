"""What an ingest call did (``POST /api/v1/ingest`` and ``/ingest/csv``,
:meth:`service.ingest.IngestReport.as_dict`)."""

from __future__ import annotations

from typing import Any

from pydantic import Field

from service.api.schemas.base import Schema


class TagIngest(Schema):
    """What happened to the items of one tag (:class:`service.ingest.TagReport`)."""

    tag: str
    received: int
    stored: int
    """Samples written."""
    already_stored: int
    """Items the store already held with the same value."""
    bad: int
    """Bad samples written (NaN, null or ``good: false``)."""
    out_of_order: int
    """Items that came after a later one of the same tag."""
    refused: dict[str, int]
    """Refused items by reason: ``unknown_tag``, ``bad_timestamp``, ``future_timestamp``,
    ``bad_value`` (a value sent as text), ``duplicate_in_batch``, ``conflict``."""
    first_timestamp: float | None
    """First of the tag's items in the store after the call, UNIX s; null if none is."""
    last_timestamp: float | None
    """Last of them, UNIX s."""
    refused_items: list[dict[str, Any]] = Field(default_factory=list)
    """The first 10 refused items: ``timestamp`` as sent and ``reason``."""


class IngestAnswer(Schema):
    """Totals over all tags, then the per-tag reports."""

    partial: bool
    """True when any item was refused (answered 207)."""
    received: int
    stored: int
    already_stored: int
    bad: int
    out_of_order: int
    refused: dict[str, int]
    """Refused items by reason, all tags (reasons with none left out)."""
    tags: list[TagIngest]
