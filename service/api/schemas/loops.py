"""The loops in lists, in the bad-actor ranking and their samples: the response models
that routes, the ranking (:mod:`service.ranking`) and the report share."""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel, ConfigDict, Field

from service.bad_actors import LoopScore


class LoopPublic(BaseModel):
    """A loop in lists: identity and its latest state."""

    id: str
    name: str
    unit: str | None
    valve_asset: str | None
    importance: str
    health: float | None
    oscillating: bool | None
    period_s: float | None
    verdict: str | None
    confidence: float | None
    S: float | None
    J: float | None
    analysed_at: float | None
    active_alarms: int


class BadActorPublic(LoopScore, LoopPublic):
    """A loop in the bad-actor ranking: its latest state and its KPI-based score over the
    period (:mod:`service.bad_actors`)."""

    model_config = ConfigDict(frozen=False)
    kpis: dict[str, Any] | None = Field(
        default=None, description="the KPIs of the loop's latest analysis run (as "
        "GET /loops/{id}/kpis gives them)")


class SeriesPublic(BaseModel):
    """One tag's samples over a time range (downsampled to at most max_points)."""

    tag: str
    signal: str
    t: list[float]
    value: list[float | None]


class LoopDataPublic(BaseModel):
    """Samples of every tag of a loop."""

    loop_id: str
    start: float
    end: float
    series: list[SeriesPublic]
