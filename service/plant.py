"""The plant as the service runs it: the configuration, kept in step with the store.

The plant file's loops are written to the store at every start; loops added
with ``PUT /api/v1/loops/{id}`` live in the store only (``origin`` "api"), so
the plant the service runs is the file's plus those (:func:`sync_plant`).  A
tag belongs to one loop: taking the tag of another loop is refused with
:class:`TagConflictError`.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Mapping
from types import MappingProxyType

from pydantic import ValidationError
from sqlalchemy import select
from sqlalchemy.orm import Session

from service.config import ConfigError, LoopConfig, PlantConfig, UnitConfig
from service.store.models import Loop, Tag, Unit

log = logging.getLogger(__name__)

__all__ = ["PlantRegistry", "TagConflictError", "sync_plant"]

PLANT_FILE, API = "plant_file", "api"
"""Where a loop was configured (``loops.origin``)."""


class TagConflictError(ValueError):
    """A loop names a tag that belongs to another loop (HTTP 409)."""


def _upsert_loop(session: Session, loop: LoopConfig, now: float, origin: str) -> None:
    row = session.get(Loop, loop.id)
    config = loop.model_dump(mode="json")
    if row is None:
        row = Loop(id=loop.id, name=loop.name, unit_id=loop.unit, config=config,
                   created_at=now, updated_at=now, origin=origin)
        session.add(row)
    else:
        row.name, row.unit_id, row.config, row.updated_at = loop.name, loop.unit, config, now
        row.origin = origin
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


def _claimed_tags(session: Session, loop: LoopConfig) -> None:
    """Refuse ``loop`` if one of its tags belongs to another loop in the store."""
    names = [tag for _, tag in loop.tags.items()]
    for name, owner in session.execute(
            select(Tag.name, Tag.loop_id).where(Tag.name.in_(names), Tag.loop_id != loop.id)):
        raise TagConflictError(f"Tag {name!r} belongs to loop {owner!r}")


def _stored_api_loop(row: Loop) -> LoopConfig | None:
    """A loop added through the API as stored; None, with a warning, when its configuration
    no longer validates (stored before a check was added, e.g. a process_model without K):
    the loop is then not run, as one that left the plant file, and the service starts."""
    try:
        return LoopConfig.model_validate(row.config)
    except ValidationError as exc:
        log.warning("loop %s, added through the API, is not run: its stored configuration no "
                    "longer validates (%s); send it again with PUT /api/v1/loops/%s",
                    row.id, "; ".join(f"{'.'.join(map(str, e['loc']))}: {e['msg']}"
                                      for e in exc.errors(include_url=False)), row.id)
        return None


def sync_plant(session: Session, plant: PlantConfig, now: float) -> PlantConfig:
    """Write the plant file's units, loops and tags to the store; the plant to run: the
    file's and the loops added through the API (the file wins for a loop in both).

    Loops that left the file are kept in the store (their history stays
    queryable) but not run.

    Raises
    ------
    ConfigError
        A loop of the file names a tag of a loop added through the API.
    """
    in_file = {loop.id for loop in plant.loops}
    added = [loop for row in session.scalars(select(Loop).where(Loop.origin == API)
                                            .order_by(Loop.id))
             if row.id not in in_file and (loop := _stored_api_loop(row)) is not None]
    owner = {tag: loop.id for loop in added for _, tag in loop.tags.items()}
    for loop in plant.loops:
        for _, tag in loop.tags.items():
            if tag in owner:
                raise ConfigError(
                    f"loops.{loop.id}: tag {tag!r} belongs to loop {owner[tag]!r}, added "
                    "through the API (PUT /api/v1/loops); rename the tag or give that loop "
                    "another one first")
    for unit in plant.units:
        _upsert_unit(session, unit)
    session.flush()
    for loop in plant.loops:
        _upsert_loop(session, loop, now, PLANT_FILE)
    known_units = {unit.id for unit in plant.units}
    extra_units = [UnitConfig(id=row.id, name=row.name) for row in session.scalars(
        select(Unit).where(Unit.id.in_({loop.unit for loop in added if loop.unit})))
        if row.id not in known_units]
    return PlantConfig(**{**dict(plant), "units": [*plant.units, *extra_units],
                          "loops": [*plant.loops, *added]})


class PlantRegistry:
    """The current plant configuration; loops can be added or changed at run time."""

    def __init__(self, plant: PlantConfig) -> None:
        self._plant = plant
        self._lock = threading.Lock()
        self._index: tuple[PlantConfig | None, Mapping[str, tuple[str, str]]] = (None, {})

    @property
    def plant(self) -> PlantConfig:
        """The configuration now."""
        return self._plant

    def upsert_loop(self, session: Session, loop: LoopConfig, now: float) -> bool:
        """Add or replace ``loop`` (stored as added through the API); True if it was new.
        The whole plant is validated again.

        Raises
        ------
        TagConflictError
            A tag of ``loop`` belongs to another loop.
        """
        with self._lock:
            _claimed_tags(session, loop)
            loops = [x for x in self._plant.loops if x.id != loop.id]
            created = len(loops) == len(self._plant.loops)
            plant = PlantConfig.model_validate(
                {**self._plant.model_dump(), "loops": [*(x.model_dump() for x in loops),
                                                      loop.model_dump()]}
            )
            _upsert_loop(session, loop, now, API)
            session.flush()  # a row the database refuses must not change the running plant
            self._plant = plant
            return created

    def tag_index(self) -> Mapping[str, tuple[str, str]]:
        """tag -> (loop id, signal) for every configured tag (read only).

        Built once per configuration, not for every ingest batch: 2,000 loops took
        a tenth of the ingest's time to index again each time."""
        plant, index = self._index
        if plant is not self._plant:
            plant = self._plant
            index = MappingProxyType({tag: (loop.id, signal) for loop in plant.loops
                                      for signal, tag in loop.tags.items()})
            self._index = (plant, index)
        return index
