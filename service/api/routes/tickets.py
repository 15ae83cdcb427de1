"""Valve-repair tickets: list, detail with history, CMMS export, state changes."""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, HTTPException, Query
from pydantic import BaseModel, Field

from service.api.deps import (
    ERROR_RESPONSES,
    Maintenance,
    Offset,
    Reader,
    SessionDep,
    StateDep,
    error_responses,
    row_id,
)
from service.api.schemas.tickets import CmmsExport
from service.cmms import to_cmms_notification
from service.logs import audit
from service.store.models import Ticket
from service.tickets import (
    TICKET_STATES,
    TicketEvidence,
    TicketNotFoundError,
    TicketState,
    change_ticket_state,
    get_ticket,
    list_tickets,
    ticket_payload,
    ticket_to_dict,
)

router = APIRouter(prefix="/api/v1/tickets", tags=["tickets"],
                   responses={**ERROR_RESPONSES, **error_responses(404, 409)})
TicketId = Annotated[int, row_id("the ticket's id")]


class TicketEventPublic(BaseModel):
    """One change of a ticket."""

    at: float
    from_state: str | None
    to_state: str
    actor: str
    note: str


class TicketPublic(BaseModel):
    """A ticket with its evidence."""

    id: int
    valve_asset: str
    loop_id: str
    state: str
    priority: int
    title: str
    description: str
    location: str | None
    malfunction_start: float
    evidence: TicketEvidence
    created_at: float
    updated_at: float


class TicketDetail(TicketPublic):
    """A ticket with its history."""

    events: list[TicketEventPublic]


class TicketsPublic(BaseModel):
    """A page of tickets."""

    data: list[TicketPublic]
    count: int


class TicketUpdate(BaseModel):
    """A state change (maintenance)."""

    state: TicketState
    note: str = Field(default="", max_length=2000)


def _detail(ticket: Ticket) -> TicketDetail:
    return TicketDetail(
        **ticket_to_dict(ticket),
        events=[TicketEventPublic.model_validate(e, from_attributes=True) for e in ticket.events],
    )


def _get(session: SessionDep, ticket_id: int) -> Ticket:
    try:
        return get_ticket(session, ticket_id)
    except TicketNotFoundError:
        raise HTTPException(404, "Ticket not found") from None


@router.get("", response_model=TicketsPublic)
def list_all(
    session: SessionDep,
    _: Reader,
    state: Annotated[str | None, Query(description=f"one of {', '.join(TICKET_STATES)}")] = None,
    loop_id: str | None = None,
    valve_asset: str | None = None,
    offset: Offset = 0,
    limit: Annotated[int, Query(ge=1, le=1000)] = 100,
) -> TicketsPublic:
    """Tickets, most urgent and newest first."""
    if state is not None and state not in TICKET_STATES:
        raise HTTPException(422, f"state must be one of {', '.join(TICKET_STATES)}")
    tickets, count = list_tickets(session, state=state, loop_id=loop_id,
                                  valve_asset=valve_asset, limit=limit, offset=offset)
    return TicketsPublic(data=[TicketPublic(**ticket_to_dict(t)) for t in tickets], count=count)


@router.get("/{ticket_id}", response_model=TicketDetail)
def detail(ticket_id: TicketId, session: SessionDep, _: Reader) -> TicketDetail:
    """One ticket with its evidence and history."""
    return _detail(_get(session, ticket_id))


@router.get("/{ticket_id}/cmms", response_model=CmmsExport, response_model_exclude_unset=True)
def cmms(ticket_id: TicketId, session: SessionDep, state: StateDep,
         _: Reader) -> dict[str, Any]:
    """The ticket as a SAP PM M2 notification and a Maximo work order, with the CMMS fields
    the plant file sets for its loop (or unit, or the plant)."""
    ticket = _get(session, ticket_id)
    return to_cmms_notification(ticket, state.registry.plant.cmms_of(ticket.loop_id))


@router.patch("/{ticket_id}", response_model=TicketDetail)
def update(ticket_id: TicketId, body: TicketUpdate, session: SessionDep, state: StateDep,
           key: Maintenance) -> TicketDetail:
    """Move the ticket along open -> acknowledged -> scheduled -> done (or cancelled)."""
    _get(session, ticket_id)
    actor = key.actor
    ticket = change_ticket_state(session, ticket_id, body.state, actor=actor, now=state.clock(),
                                 note=body.note)
    audit(actor, "ticket state change", f"ticket {ticket.id} ({ticket.valve_asset})",
          to_state=body.state, note=body.note)
    if state.outbox is not None:
        state.outbox.add(session, "ticket.changed",
                         ticket_payload(ticket, state.registry.plant.cmms_of(ticket.loop_id)),
                         state.clock())
    return _detail(ticket)
