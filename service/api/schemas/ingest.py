"""What an ingest call did (``POST /api/v1/ingest`` and ``/ingest/csv``,
:meth:`service.ingest.IngestReport.as_dict`)."""

from __future__ import annotations

from service.api.schemas.base import Schema
from service.ingest import TagReport


class TagIngest(TagReport, Schema):
    """What happened to the items of one tag (:class:`service.ingest.TagReport`)."""


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
