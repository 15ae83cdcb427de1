"""The samples of a loop's tags over a time range, downsampled for drawing: the answer of
``GET /loops/{id}/data`` and the trend plot's data."""

from __future__ import annotations

from itertools import pairwise

import numpy as np
from fastapi import HTTPException
from sqlalchemy import select
from sqlalchemy.orm import Session

from service.api.schemas.loops import LoopDataPublic, SeriesPublic
from service.store.models import Sample, Tag

__all__ = ["read_loop_data"]


def _downsample(t: np.ndarray, v: np.ndarray, max_points: int) -> tuple[np.ndarray, np.ndarray]:
    """Keep the min and max of equal buckets so oscillations survive downsampling."""
    if t.size <= max_points:
        return t, v
    buckets = max_points // 2
    edges = np.linspace(0, t.size, buckets + 1).astype(int)
    keep: list[int] = []
    for lo, hi in pairwise(edges):
        segment = v[lo:hi]
        finite = np.isfinite(segment)
        if not finite.any():
            keep.append(lo)
            continue
        idx = np.flatnonzero(finite)
        a = lo + idx[np.argmin(segment[finite])]
        b = lo + idx[np.argmax(segment[finite])]
        keep.extend(sorted({int(a), int(b)}))
    index = np.asarray(keep)
    return t[index], v[index]


def read_loop_data(session: Session, loop_id: str, now: float, start: float | None,
                   end: float | None, max_points: int) -> LoopDataPublic:
    """Samples of the loop's tags between start and end (UNIX s; default: the hour before
    ``now``), each tag at most ``max_points``; 422 unless end is after start."""
    end = now if end is None else end
    start = end - 3600.0 if start is None else start
    if not end > start:
        raise HTTPException(422, "end must be after start")
    series = []
    for tag in session.scalars(select(Tag).where(Tag.loop_id == loop_id).order_by(Tag.signal)):
        rows = session.execute(
            select(Sample.time, Sample.value, Sample.good)
            .where(Sample.tag == tag.name, Sample.time >= start, Sample.time <= end)
            .order_by(Sample.time)
        ).all()
        t = np.array([r[0] for r in rows], dtype=float)
        v = np.array([r[1] if r[2] and r[1] is not None else np.nan for r in rows], dtype=float)
        t, v = _downsample(t, v, max_points)
        series.append(SeriesPublic(
            tag=tag.name, signal=tag.signal, t=t.tolist(),
            value=[None if not np.isfinite(x) else float(x) for x in v],
        ))
    return LoopDataPublic(loop_id=loop_id, start=start, end=end, series=series)
