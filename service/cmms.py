"""A ticket in the formats of the maintenance systems: a SAP PM notification and a Maximo
work order (:func:`to_cmms_notification`), with the plant file's CMMS settings."""

from __future__ import annotations

import textwrap
from datetime import UTC, datetime
from typing import Any

from service.config import CmmsConfig
from service.store.models import Ticket

__all__ = ["LONG_TEXT_LINE_CHARS", "SHORT_TEXT_CHARS", "short_text", "to_cmms_notification"]

SHORT_TEXT_CHARS = 40
"""SAP PM notification short text (QMTXT) length."""
LONG_TEXT_LINE_CHARS = 132
"""SAP long-text line (TLINE) length."""


def short_text(text: str) -> str:
    """``text`` cut to the SAP PM short text's :data:`SHORT_TEXT_CHARS`, with "..."."""
    return text if len(text) <= SHORT_TEXT_CHARS else text[: SHORT_TEXT_CHARS - 3] + "..."


def to_cmms_notification(ticket: Ticket, cmms: CmmsConfig | None = None) -> dict[str, Any]:
    """The ticket as a SAP PM M2 notification and as a Maximo work order.

    ``sap_pm``: the header fields of ``BAPI_ALM_NOTIF_CREATE`` (NOTIFHEADER)
    with notification type ``M2`` (malfunction report): ``FUNCT_LOC`` the
    loop's location, ``EQUIPMENT`` the valve asset, ``PRIORITY`` "1".."4",
    ``SHORT_TEXT`` (at most 40 characters), ``STRMLFNDATE``/``STRMLFNTIME``
    the malfunction start (YYYYMMDD/HHMMSS in UTC), ``BREAKDOWN`` empty (the
    valve still works); ``LONG_TEXT`` the lines of the long text (at most 132
    characters each, the LONGTEXTS table).

    ``maximo``: the ``mxwo`` object structure of the Maximo REST API:
    ``description`` (the short text), ``description_longdescription``,
    ``assetnum``, ``location``, ``wopriority`` (1 = highest; Maximo's scale is
    site-defined, map it there if it differs), ``worktype`` "CM"
    (corrective), ``status`` "WAPPR", ``reportdate`` (ISO 8601), and
    ``externalrefid``/``sourcesysid`` identifying the ticket here.  A work
    order has no malfunction-start field: the long text carries it.

    ``cmms`` (the plant file's settings of the ticket's loop,
    :meth:`service.config.PlantConfig.cmms_of`) adds what is set of:
    ``PLANPLANT``, ``WORK_CNTR`` and the coding ``CODE_GROUP``/``CODING`` to the
    SAP header, the damage (``D_CODEGRP``/``D_CODE``) and object part
    (``DL_CODEGRP``/``DL_CODE``) codes as ``ITEM``, the cause codes
    (``CAUSE_CODEGRP``/``CAUSE_CODE``) as ``CAUSE``; ``siteid`` and ``orgid`` to
    the Maximo work order.
    """
    start = datetime.fromtimestamp(ticket.malfunction_start, UTC)
    reported = datetime.fromtimestamp(ticket.created_at, UTC)
    long_text = (
        f"Malfunction start: {start.isoformat(timespec='seconds')}\n{ticket.description}"
    )
    lines = [
        line
        for paragraph in long_text.split("\n")
        for line in textwrap.wrap(paragraph, LONG_TEXT_LINE_CHARS)
    ]
    notification: dict[str, Any] = {
        "sap_pm": {
            "NOTIF_TYPE": "M2",
            "SHORT_TEXT": short_text(ticket.title),
            "FUNCT_LOC": ticket.location,
            "EQUIPMENT": ticket.valve_asset,
            "PRIORITY": str(ticket.priority),
            "STRMLFNDATE": start.strftime("%Y%m%d"),
            "STRMLFNTIME": start.strftime("%H%M%S"),
            "BREAKDOWN": "",
            "LONG_TEXT": lines,
        },
        "maximo": {
            "description": short_text(ticket.title),
            "description_longdescription": long_text,
            "assetnum": ticket.valve_asset,
            "location": ticket.location,
            "wopriority": ticket.priority,
            "worktype": "CM",
            "status": "WAPPR",
            "reportdate": reported.isoformat(timespec="seconds"),
            "externalrefid": f"loopwatch-ticket-{ticket.id}",
            "sourcesysid": "LOOPWATCH",
        },
    }
    if cmms is not None:
        _add_settings(notification, cmms)
    return notification


SAP_HEADER_FIELDS = {"planning_plant": "PLANPLANT", "work_center": "WORK_CNTR",
                     "code_group": "CODE_GROUP", "coding": "CODING"}
SAP_ITEM_FIELDS = {"damage_code_group": "D_CODEGRP", "damage_code": "D_CODE",
                   "object_part_code_group": "DL_CODEGRP", "object_part_code": "DL_CODE"}
SAP_CAUSE_FIELDS = {"cause_code_group": "CAUSE_CODEGRP", "cause_code": "CAUSE_CODE"}
"""Plant-file SAP PM settings -> BAPI_ALM_NOTIF_CREATE fields (header, item, cause)."""


def _add_settings(notification: dict[str, Any], cmms: CmmsConfig) -> None:
    """Add the fields ``cmms`` sets to ``notification``."""
    sap = cmms.sap_pm.model_dump(exclude_none=True)
    header = {SAP_HEADER_FIELDS[k]: v for k, v in sap.items() if k in SAP_HEADER_FIELDS}
    item = {SAP_ITEM_FIELDS[k]: v for k, v in sap.items() if k in SAP_ITEM_FIELDS}
    cause = {SAP_CAUSE_FIELDS[k]: v for k, v in sap.items() if k in SAP_CAUSE_FIELDS}
    notification["sap_pm"] |= header | ({"ITEM": item} if item else {}) | (
        {"CAUSE": cause} if cause else {})
    notification["maximo"] |= cmms.maximo.model_dump(exclude_none=True)
