"""Tables of the store (SQLAlchemy 2 declarative models).

Times are UNIX seconds (float, UTC) throughout: sample stamps come from
historians and connectors in many formats, and one numeric time axis keeps
the ring buffers, windows and SQL range queries simple and exact.
"""

from __future__ import annotations

from typing import Any, ClassVar

from sqlalchemy import (
    JSON,
    Boolean,
    Float,
    ForeignKey,
    Index,
    Integer,
    String,
    Text,
    UniqueConstraint,
    text,
)
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column, relationship, validates


class Base(DeclarativeBase):
    """Declarative base of all loopwatch tables."""

    type_annotation_map: ClassVar[dict[Any, Any]] = {dict[str, Any]: JSON}


class Unit(Base):
    """A process unit (loops that interact)."""

    __tablename__ = "units"
    id: Mapped[str] = mapped_column(String(64), primary_key=True)
    name: Mapped[str] = mapped_column(String(200), default="")


class Loop(Base):
    """A control loop; ``config`` is its validated plant-file entry.

    ``origin`` is ``plant_file`` or ``api`` (added by ``PUT /api/v1/loops/{id}``):
    the store is the source of truth for the ``api`` loops, loaded at start.
    """

    __tablename__ = "loops"
    id: Mapped[str] = mapped_column(String(64), primary_key=True)
    name: Mapped[str] = mapped_column(String(200), default="")
    unit_id: Mapped[str | None] = mapped_column(ForeignKey("units.id"), index=True)
    config: Mapped[dict[str, Any]]
    origin: Mapped[str] = mapped_column(String(16), default="api", server_default="api")
    created_at: Mapped[float] = mapped_column(Float)
    updated_at: Mapped[float] = mapped_column(Float)
    tags: Mapped[list[Tag]] = relationship(back_populates="loop", cascade="all, delete-orphan")


class Tag(Base):
    """A measured signal of a loop (OP, PV, SP, MV or the controller's mode)."""

    __tablename__ = "tags"
    name: Mapped[str] = mapped_column(String(200), primary_key=True)
    loop_id: Mapped[str] = mapped_column(ForeignKey("loops.id", ondelete="CASCADE"), index=True)
    signal: Mapped[str] = mapped_column(String(8))
    loop: Mapped[Loop] = relationship(back_populates="tags")


class Sample(Base):
    """One value of one tag; the primary key makes every ingest idempotent.

    ``tag`` names a row of ``tags`` but has no foreign key (migration 0002):
    checking one on every row halved the PostgreSQL insert rate, and ingest
    already refuses samples of unknown tags.  Samples of a tag removed from
    the plant stay until the retention purge.
    """

    __tablename__ = "samples"
    __table_args__ = (Index("ix_samples_time", "time"),)
    tag: Mapped[str] = mapped_column(String(200), primary_key=True)
    time: Mapped[float] = mapped_column(Float, primary_key=True)
    value: Mapped[float | None] = mapped_column(Float)
    good: Mapped[bool] = mapped_column(Boolean, default=True)


class AnalysisRun(Base):
    """One run of the diagnosis pipeline on one loop window."""

    __tablename__ = "analysis_runs"
    __table_args__ = (
        Index("ix_analysis_runs_loop_started", "loop_id", "started_at"),
        Index("ix_analysis_runs_round_end", "round_end"),
        Index("ix_analysis_runs_ok_loop_started", "loop_id", "started_at", "id",
              postgresql_where=text("status = 'ok'"), sqlite_where=text("status = 'ok'")),
        UniqueConstraint("loop_id", "round_end", name="uq_analysis_runs_loop_round"),
    )
    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    loop_id: Mapped[str] = mapped_column(ForeignKey("loops.id", ondelete="CASCADE"))
    started_at: Mapped[float] = mapped_column(Float)
    finished_at: Mapped[float | None] = mapped_column(Float)
    window_start: Mapped[float | None] = mapped_column(Float)
    window_end: Mapped[float | None] = mapped_column(Float)
    status: Mapped[str] = mapped_column(String(16))  # ok | failed | timeout | no_data
    usable: Mapped[bool | None] = mapped_column(Boolean)
    oscillating: Mapped[bool | None] = mapped_column(Boolean)
    period_s: Mapped[float | None] = mapped_column(Float)
    verdict: Mapped[str | None] = mapped_column(String(16))
    confidence: Mapped[float | None] = mapped_column(Float)
    S: Mapped[float | None] = mapped_column(Float)
    J: Mapped[float | None] = mapped_column(Float)
    health: Mapped[float | None] = mapped_column(Float)
    result: Mapped[dict[str, Any] | None] = mapped_column(JSON)
    kpis: Mapped[dict[str, Any] | None] = mapped_column(JSON)
    """``result["kpis"]`` on its own, set with ``result`` (:meth:`_keep_kpis`): the KPI
    history and the ranking read it without the whole diagnosis (migration 0007)."""
    error: Mapped[str | None] = mapped_column(Text)
    round_end: Mapped[float | None] = mapped_column(Float)
    """End of the scheduled round's window; None for an analysis run on demand.  At most
    one run per loop and round (the constraint that keeps a failover from running twice)."""
    scheduled_by: Mapped[str | None] = mapped_column(String(200))
    """The scheduler process (host:pid:nonce) that stored the run."""

    @validates("result")
    def _keep_kpis(self, _key: str, result: dict[str, Any] | None) -> dict[str, Any] | None:
        self.kpis = None if result is None else result.get("kpis")
        return result

    @property
    def unread_when_new(self) -> bool:
        """A new run that is not ``ok`` changes neither the loop list nor the bad-actor
        ranking, which read the ``ok`` runs only (:meth:`service.store.db.Store.version`):
        a round of 2,000 loops without data must not make them be read again 2,000 times."""
        return self.status != "ok"


class UnitAnalysisRun(Base):
    """One multi-loop diagnosis of a unit (thesis chapter 2) on its loops' windows.

    The scheduler stores one after each round's loop analyses for every unit
    with two or more complete windows; the ticket rule reads the latest
    ``ok`` one (:func:`service.tickets.update_ticket_from_analysis`).
    """

    __tablename__ = "unit_analysis_runs"
    __table_args__ = (
        Index("ix_unit_analysis_runs_unit_started", "unit_id", "started_at"),
        UniqueConstraint("unit_id", "round_end", name="uq_unit_analysis_runs_unit_round"),
    )
    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    unit_id: Mapped[str] = mapped_column(ForeignKey("units.id", ondelete="CASCADE"))
    started_at: Mapped[float] = mapped_column(Float)
    finished_at: Mapped[float | None] = mapped_column(Float)
    window_start: Mapped[float] = mapped_column(Float)
    window_end: Mapped[float] = mapped_column(Float)
    status: Mapped[str] = mapped_column(String(16))  # ok | failed | timeout
    loops: Mapped[list[str]] = mapped_column(JSON)
    """The loops diagnosed (those with a complete window)."""
    incomplete_loops: Mapped[list[str]] = mapped_column(JSON)
    """The unit's other loops: no complete OP and PV window."""
    sticky_loops: Mapped[list[str]] = mapped_column(JSON)
    """Loops whose valves the diagnosis names sticky."""
    cleared_loops: Mapped[list[str]] = mapped_column(JSON)
    """Loops of a diagnosed oscillation whose own valve the diagnosis clears
    (:meth:`analytics.plantwide.UnitDiagnosis.valve_decisions`)."""
    result: Mapped[dict[str, Any] | None] = mapped_column(JSON)
    error: Mapped[str | None] = mapped_column(Text)
    round_end: Mapped[float | None] = mapped_column(Float)
    """As in ``analysis_runs``: at most one diagnosis per unit and scheduled round."""
    scheduled_by: Mapped[str | None] = mapped_column(String(200))


class Alarm(Base):
    """An operator alarm of one loop and kind, with its ISA-18.2 state."""

    __tablename__ = "alarms"
    __table_args__ = (UniqueConstraint("loop_id", "kind"),)
    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    loop_id: Mapped[str] = mapped_column(ForeignKey("loops.id", ondelete="CASCADE"), index=True)
    kind: Mapped[str] = mapped_column(String(32))  # oscillation | data_quality
    priority: Mapped[str] = mapped_column(String(16))
    state: Mapped[str] = mapped_column(String(16), index=True)
    condition_active: Mapped[bool] = mapped_column(Boolean)
    shelved_until: Mapped[float | None] = mapped_column(Float)
    message: Mapped[str] = mapped_column(Text, default="")
    raised_at: Mapped[float] = mapped_column(Float)
    updated_at: Mapped[float] = mapped_column(Float)
    events: Mapped[list[AlarmEvent]] = relationship(
        back_populates="alarm", cascade="all, delete-orphan", order_by="AlarmEvent.id"
    )


class AlarmEvent(Base):
    """One transition of an alarm: who, when, from and to which state."""

    __tablename__ = "alarm_events"
    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    alarm_id: Mapped[int] = mapped_column(
        ForeignKey("alarms.id", ondelete="CASCADE"), index=True
    )
    at: Mapped[float] = mapped_column(Float)
    event: Mapped[str] = mapped_column(String(32))
    from_state: Mapped[str] = mapped_column(String(16))
    to_state: Mapped[str] = mapped_column(String(16))
    actor: Mapped[str] = mapped_column(String(100))
    note: Mapped[str] = mapped_column(Text, default="")
    alarm: Mapped[Alarm] = relationship(back_populates="events")


class Ticket(Base):
    """A valve-repair ticket; one open ticket per valve asset."""

    __tablename__ = "tickets"
    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    valve_asset: Mapped[str] = mapped_column(String(100), index=True)
    loop_id: Mapped[str] = mapped_column(ForeignKey("loops.id", ondelete="CASCADE"), index=True)
    state: Mapped[str] = mapped_column(String(16), index=True)
    priority: Mapped[int] = mapped_column(Integer)  # 1 (very high) .. 4 (low), SAP PM style
    title: Mapped[str] = mapped_column(String(200))
    description: Mapped[str] = mapped_column(Text)
    location: Mapped[str | None] = mapped_column(String(100))
    malfunction_start: Mapped[float] = mapped_column(Float)
    evidence: Mapped[dict[str, Any]]
    created_at: Mapped[float] = mapped_column(Float)
    updated_at: Mapped[float] = mapped_column(Float)
    events: Mapped[list[TicketEvent]] = relationship(
        back_populates="ticket", cascade="all, delete-orphan", order_by="TicketEvent.id"
    )


class TicketEvent(Base):
    """One change of a ticket: state transitions and evidence updates."""

    __tablename__ = "ticket_events"
    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    ticket_id: Mapped[int] = mapped_column(
        ForeignKey("tickets.id", ondelete="CASCADE"), index=True
    )
    at: Mapped[float] = mapped_column(Float)
    from_state: Mapped[str | None] = mapped_column(String(16))
    to_state: Mapped[str] = mapped_column(String(16))
    actor: Mapped[str] = mapped_column(String(100))
    note: Mapped[str] = mapped_column(Text, default="")
    ticket: Mapped[Ticket] = relationship(back_populates="events")


class ApiKey(Base):
    """An API key: a salted hash of it (service.auth) and an id that is not secret."""

    __tablename__ = "api_keys"
    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    name: Mapped[str] = mapped_column(String(100))
    role: Mapped[str] = mapped_column(String(16))
    key_id: Mapped[str] = mapped_column(String(16), unique=True)
    salt: Mapped[str] = mapped_column(String(32))
    key_hash: Mapped[str] = mapped_column(String(64))
    created_at: Mapped[float] = mapped_column(Float)
    revoked_at: Mapped[float | None] = mapped_column(Float)


class LeaderLease(Base):
    """Who holds a leadership (the active scheduler) and until when; see service.leader."""

    __tablename__ = "leader_leases"
    name: Mapped[str] = mapped_column(String(64), primary_key=True)
    holder: Mapped[str] = mapped_column(String(200))
    acquired_at: Mapped[float] = mapped_column(Float)
    expires_at: Mapped[float] = mapped_column(Float)


class IngestLog(Base):
    """One ingest transaction: when it was received and the time span of what it stored.

    Schedulers in other processes read the samples of the spans received since
    their last look (a historian backfill of old samples included).
    """

    __tablename__ = "ingest_log"
    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    received_at: Mapped[float] = mapped_column(Float, index=True)
    first_time: Mapped[float] = mapped_column(Float)
    last_time: Mapped[float] = mapped_column(Float)
    samples: Mapped[int] = mapped_column(Integer)


class Notification(Base):
    """One event to deliver on one channel (the notification outbox).

    Written in the transaction of the change it reports, so a change that is
    stored is delivered at least once, across restarts;
    :class:`service.notifications.OutboxDispatcher` delivers it.  ``event_id``
    is the ``webhook-id`` the receiver may drop repeats by.
    """

    __tablename__ = "notifications"
    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    event_id: Mapped[str] = mapped_column(String(40), unique=True)
    channel: Mapped[str] = mapped_column(String(16))
    event_type: Mapped[str] = mapped_column(String(40))
    payload: Mapped[dict[str, Any]]
    created_at: Mapped[float] = mapped_column(Float)
    state: Mapped[str] = mapped_column(String(16))  # pending, delivered, failed
    attempts: Mapped[int] = mapped_column(Integer, default=0)
    next_attempt_at: Mapped[float] = mapped_column(Float)
    last_error: Mapped[str | None] = mapped_column(Text)
    finished_at: Mapped[float | None] = mapped_column(Float)

    __table_args__ = (Index("ix_notifications_state_due", "state", "next_attempt_at"),)
