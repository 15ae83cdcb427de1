"""The plant as the service runs it: the configuration, kept in step with the store."""

from __future__ import annotations

import threading

from sqlalchemy import select
from sqlalchemy.orm import Session

from service.config import LoopConfig, PlantConfig, UnitConfig
from service.store.models import Loop, Tag, Unit

__all__ = ["PlantRegistry", "sync_plant"]


def _upsert_loop(session: Session, loop: LoopConfig, now: float) -> None:
    row = session.get(Loop, loop.id)
    config = loop.model_dump(mode="json")
    if row is None:
        row = Loop(id=loop.id, name=loop.name, unit_id=loop.unit, config=config,
                   created_at=now, updated_at=now)
        session.add(row)
    else:
        row.name, row.unit_id, row.config, row.updated_at = loop.name, loop.unit, config, now
    wanted = dict(loop.tags.items())
    existing = {t.name: t for t in session.scalars(select(Tag).where(Tag.loop_id == loop.id))}
    for name, tag in existing.items():
        if name not in wanted.values():
            session.delete(tag)
    for signal, name in wanted.items():
        if name in existing:
            existing[name].signal = signal
        else:
            session.add(Tag(name=name, loop_id=loop.id, signal=signal))


def _upsert_unit(session: Session, unit: UnitConfig) -> None:
    row = session.get(Unit, unit.id)
    if row is None:
        session.add(Unit(id=unit.id, name=unit.name))
    else:
        row.name = unit.name


def sync_plant(session: Session, plant: PlantConfig, now: float) -> None:
    """Make the store's units, loops and tags match ``plant`` (loops not in it are kept:
    their history stays queryable)."""
    for unit in plant.units:
        _upsert_unit(session, unit)
    session.flush()
    for loop in plant.loops:
        _upsert_loop(session, loop, now)


class PlantRegistry:
    """The current plant configuration; loops can be added or changed at run time."""

    def __init__(self, plant: PlantConfig) -> None:
        self._plant = plant
        self._lock = threading.Lock()

    @property
    def plant(self) -> PlantConfig:
        """The configuration now."""
        return self._plant

    def upsert_loop(self, session: Session, loop: LoopConfig, now: float) -> bool:
        """Add or replace ``loop``; True if it was new.  The whole plant is validated again."""
        with self._lock:
            loops = [x for x in self._plant.loops if x.id != loop.id]
            created = len(loops) == len(self._plant.loops)
            plant = PlantConfig.model_validate(
                {**self._plant.model_dump(), "loops": [*(x.model_dump() for x in loops),
                                                      loop.model_dump()]}
            )
            _upsert_loop(session, loop, now)
            session.flush()  # a row the database refuses must not change the running plant
            self._plant = plant
            return created

    def tag_index(self) -> dict[str, tuple[str, str]]:
        """tag -> (loop id, signal) for every configured tag."""
        return {tag: (loop.id, signal) for loop in self._plant.loops
                for signal, tag in loop.tags.items()}
