"""A ticket's evidence (:data:`service.tickets.EVIDENCE_KEYS`) and its CMMS export
(``GET /api/v1/tickets/{id}/cmms``, :func:`service.cmms.to_cmms_notification`): a SAP
PM M2 notification and a Maximo work order.  Fields the plant file's CMMS settings do
not set are absent."""

from __future__ import annotations

from pydantic import Field

from service.api.schemas.base import OpenSchema, Schema


class TicketEpisodePublic(Schema):
    """A stick-jump episode of the evidence (:data:`service.tickets.EPISODE_KEYS`)."""

    start: float
    """The valve holds from here, UNIX s."""
    jump: float
    """It slips, UNIX s."""
    end: float
    """PV has settled, UNIX s."""
    op_travel: float
    """OP travel during the hold, % of span."""
    pv_jump: float
    """PV jump at the slip, % of span."""


class TicketEvidencePublic(OpenSchema):
    """The analysis that opened or last confirmed the ticket, and the valve's size.

    Evidence stored before a field existed reads as null for it (``[]`` for
    ``episodes``, 0 for ``episodes_found``)."""

    loop_id: str | None = None
    valve_asset: str | None = None
    run_id: int | None = None
    """The analysis run (``GET /api/v1/runs/{id}``)."""
    window_start: float | None = None
    """Its window, UNIX s."""
    window_end: float | None = None
    confidence: float | None = None
    """Of the stiction verdict, 0..1."""
    S: float | None = None
    """Stiction, % of valve span: the valve's size combined over ``size_windows``
    windows."""
    J: float | None = None
    """Slip jump, % of valve span."""
    period_s: float | None = None
    """Oscillation period, s (null: no sustained cycle)."""
    amplitude_op: float | None = None
    """Oscillation amplitude (half peak-to-peak) of OP, % of span."""
    amplitude_pv: float | None = None
    """The same of PV."""
    pattern: str | None = None
    """How the sticky valve shows: ``limit_cycle``, ``irregular_cycle``, ``stick_jump`` or
    ``stuck`` (:data:`analytics.diagnosis.PATTERNS`)."""
    op_travel: float | None = None
    """OP travel over the window, % of span."""
    episode_stick_band: float | None = None
    """The stick band read off the episodes, % of span."""
    episode_S: float | None = None
    """S from OP's travel between its turns and the slips
    (:mod:`analytics.stiction.episode_size`)."""
    size_check: str | None = None
    """Whether ``episode_S`` agrees with the window's Hammerstein S."""
    episodes: list[TicketEpisodePublic] = Field(default_factory=list)
    """The latest stick-jump episodes (at most
    :data:`service.tickets.MAX_TICKET_EPISODES`)."""
    S_interval: list[float] | None = None
    """``[low, high]``, the 95 % interval of S."""
    J_interval: list[float] | None = None
    """``[low, high]``, the 95 % interval of J."""
    size_windows: int | None = None
    """Windows that do not overlap combined into S and J."""
    episodes_found: int = 0
    """Episodes the analysis found (``episodes`` keeps the latest)."""
    fs: float | None = None
    """He's static friction, % of span."""
    fd: float | None = None
    """He's dynamic friction, % of span."""
    confirmations: int | None = None
    """Analysis runs on windows that do not overlap that found stiction when the evidence
    was stored: the plant's ``confirmations_needed`` at the time."""
    plots: dict[str, str] | None = None
    """The loop's plots by kind (trend, signature, spectrum): API paths."""


class SapPmItem(Schema):
    """The notification item: damage and object part codes."""

    D_CODEGRP: str | None = None
    """Damage code group."""
    D_CODE: str | None = None
    """Damage code."""
    DL_CODEGRP: str | None = None
    """Object part code group."""
    DL_CODE: str | None = None
    """Object part code."""


class SapPmCause(Schema):
    """The notification's cause codes."""

    CAUSE_CODEGRP: str | None = None
    CAUSE_CODE: str | None = None


class SapPmNotification(Schema):
    """Header of ``BAPI_ALM_NOTIF_CREATE`` (NOTIFHEADER), with the long text lines."""

    NOTIF_TYPE: str
    """``M2``: malfunction report."""
    SHORT_TEXT: str
    """The ticket's title (at most 40 characters)."""
    FUNCT_LOC: str | None
    """Functional location: the loop's location."""
    EQUIPMENT: str
    """The valve asset."""
    PRIORITY: str
    """"1" (highest) to "4"."""
    STRMLFNDATE: str
    """Malfunction start date, YYYYMMDD (UTC)."""
    STRMLFNTIME: str
    """Malfunction start time, HHMMSS (UTC)."""
    BREAKDOWN: str
    """Empty: the valve still works."""
    LONG_TEXT: list[str]
    """Lines of the long text (at most 132 characters each, the LONGTEXTS table)."""
    PLANPLANT: str | None = None
    """Maintenance planning plant (IWERK), from the plant file."""
    WORK_CNTR: str | None = None
    """Main work centre (ARBPL), from the plant file."""
    CODE_GROUP: str | None = None
    """Coding code group (QMGRP), from the plant file."""
    CODING: str | None = None
    """Coding code (QMCOD), from the plant file."""
    ITEM: SapPmItem | None = None
    CAUSE: SapPmCause | None = None


class MaximoWorkOrder(Schema):
    """The ``mxwo`` object structure of the Maximo REST API."""

    description: str
    """The short text."""
    description_longdescription: str
    """The long text (with the malfunction start: a work order has no field for it)."""
    assetnum: str
    """The valve asset."""
    location: str | None
    """The loop's location."""
    wopriority: int
    """1 = highest (Maximo's scale is site-defined: map it there if it differs)."""
    worktype: str
    """``CM``: corrective."""
    status: str
    """``WAPPR``."""
    reportdate: str
    """When the ticket was created, ISO 8601."""
    externalrefid: str
    """``loopwatch-ticket-{id}``."""
    sourcesysid: str
    """``LOOPWATCH``."""
    siteid: str | None = None
    """From the plant file."""
    orgid: str | None = None
    """From the plant file."""


class CmmsExport(Schema):
    """The ticket as a SAP PM notification and as a Maximo work order."""

    sap_pm: SapPmNotification
    maximo: MaximoWorkOrder
