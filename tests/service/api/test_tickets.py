"""``/api/v1/tickets``: the list's filter, one ticket, its CMMS export and its state
changes, with their refusals' status codes and exact ``detail``."""

import pytest

from tests.service.test_api import ADMIN, T0, key
from tests.service.test_tickets import add_run, analyse

HEADERS = {"X-API-Key": ADMIN}


@pytest.fixture
def ticket_id(service):
    """An open ticket of FV-1 (FIC-1), opened by one confirming run."""
    with service.state.store.session() as session:
        run = add_run(session, at=T0, loop_id="FIC-1")
        return analyse(session, run, loop_id="FIC-1", valve_asset="FV-1", needed=1).id


def test_the_list_filters_by_state_and_refuses_an_unknown_one(client, ticket_id):
    listed = client.get("/api/v1/tickets", headers=HEADERS, params={"state": "open"})
    assert [t["id"] for t in listed.json()["data"]] == [ticket_id]
    assert client.get("/api/v1/tickets", headers=HEADERS,
                      params={"state": "done"}).json()["count"] == 0
    refused = client.get("/api/v1/tickets", headers=HEADERS, params={"state": "closed"})
    assert (refused.status_code, refused.json()) == (422, {
        "detail": "state must be one of open, acknowledged, scheduled, done, cancelled"})


@pytest.mark.parametrize(("method", "suffix", "body"), [
    ("get", "", None), ("get", "/cmms", None), ("patch", "", {"state": "acknowledged"}),
])
def test_an_unknown_ticket_is_404(client, ticket_id, method, suffix, body):
    answer = client.request(method, f"/api/v1/tickets/{ticket_id + 1}{suffix}", json=body,
                            headers=HEADERS)
    assert (answer.status_code, answer.json()) == (404, {"detail": "Ticket not found"})


def test_a_state_change_must_be_allowed_known_and_made_by_maintenance(client, ticket_id):
    url = f"/api/v1/tickets/{ticket_id}"
    maintenance = key(client, "maintenance")
    skipped = client.patch(url, json={"state": "done"}, headers=maintenance)
    assert (skipped.status_code, skipped.json()) == (409, {
        "detail": f"ticket {ticket_id} (valve FV-1): cannot move a ticket that is open to "
                  "done (possible: acknowledged, cancelled)"})
    unknown = client.patch(url, json={"state": "closed"}, headers=maintenance)
    assert unknown.status_code == 422
    assert unknown.json()["detail"][0]["loc"] == ["body", "state"]
    refused = client.patch(url, json={"state": "acknowledged"}, headers=key(client, "operator"))
    assert (refused.status_code, refused.json()) == (403, {
        "detail": "Role 'operator' may not tickets"})
    moved = client.patch(url, json={"state": "acknowledged", "note": "seen"},
                         headers=maintenance)
    assert (moved.status_code, moved.json()["state"]) == (200, "acknowledged")
    assert moved.json()["events"][-1]["note"] == "seen"


def test_the_cmms_export_of_a_ticket(client, ticket_id):
    answer = client.get(f"/api/v1/tickets/{ticket_id}/cmms", headers=key(client, "viewer"))
    assert answer.status_code == 200, answer.text
    assert answer.json()["sap_pm"]["NOTIF_TYPE"] == "M2"
