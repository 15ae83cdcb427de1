"""A ticket's CMMS export (``GET /api/v1/tickets/{id}/cmms``,
:func:`service.cmms.to_cmms_notification`): a SAP PM M2 notification and a Maximo
work order.  Fields the plant file's CMMS settings do not set are absent."""

from __future__ import annotations

from service.api.schemas.base import Schema


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
