"""``/api/v1/alarms``: the list's filter, one alarm, and the operator's and admin's actions,
with their refusals' status codes and exact ``detail``."""

import pytest

from service.alarms import update_alarms_from_analysis
from tests.service.test_api import ADMIN, T0, key

HEADERS = {"X-API-Key": ADMIN}


@pytest.fixture
def alarm_id(service):
    """An unacknowledged oscillation alarm of FIC-1."""
    with service.state.store.session() as session:
        (alarm,) = update_alarms_from_analysis(session, "FIC-1", oscillating=True, usable=True,
                                               importance="high", message="period 48 s",
                                               now=T0)
        return alarm.id


def test_the_list_filters_by_state_and_refuses_an_unknown_one(client, alarm_id):
    listed = client.get("/api/v1/alarms", headers=HEADERS, params={"state": "unacknowledged"})
    assert [a["id"] for a in listed.json()["data"]] == [alarm_id]
    assert client.get("/api/v1/alarms", headers=HEADERS,
                      params={"state": "normal"}).json()["count"] == 0
    refused = client.get("/api/v1/alarms", headers=HEADERS, params={"state": "open"})
    assert (refused.status_code, refused.json()) == (422, {
        "detail": "state must be one of normal, unacknowledged, acknowledged, rtn_unack, "
                  "shelved, out_of_service"})


@pytest.mark.parametrize(("method", "suffix", "body"), [
    ("get", "", None), ("post", "/acknowledge", None), ("post", "/shelve", {"duration_s": 60}),
    ("post", "/unshelve", None), ("post", "/out-of-service", None),
    ("post", "/in-service", None),
])
def test_an_unknown_alarm_is_404(client, alarm_id, method, suffix, body):
    answer = client.request(method, f"/api/v1/alarms/{alarm_id + 1}{suffix}", json=body,
                            headers=HEADERS)
    assert (answer.status_code, answer.json()) == (404, {"detail": "Alarm not found"})


def test_an_alarm_id_must_be_a_positive_integer(client):
    answer = client.get("/api/v1/alarms/0", headers=HEADERS)
    assert answer.status_code == 422
    assert answer.json()["detail"][0]["loc"] == ["path", "alarm_id"]


def test_actions_the_state_does_not_allow_are_409(client, alarm_id):
    operator = key(client, "operator")
    url = f"/api/v1/alarms/{alarm_id}"
    acked = client.post(f"{url}/acknowledge", headers=operator)
    assert (acked.status_code, acked.json()["state"]) == (200, "acknowledged")
    prefix = f"alarm {alarm_id} (FIC-1 oscillation): cannot "
    for suffix, headers, message in (
            ("/acknowledge", operator, "acknowledge an alarm that is acknowledged (possible "
                                       "when unacknowledged or rtn_unack)"),
            ("/unshelve", operator, "unshelve an alarm that is acknowledged (possible when "
                                    "shelved)"),
            ("/in-service", HEADERS, "return to service an alarm that is acknowledged "
                                     "(possible when out_of_service)")):
        answer = client.post(url + suffix, headers=headers)
        assert (answer.status_code, answer.json()) == (409, {"detail": prefix + message})
    assert client.get(url, headers=HEADERS).json()["state"] == "acknowledged"


def test_who_may_act_and_how_long_a_shelve_may_be(client, alarm_id):
    url = f"/api/v1/alarms/{alarm_id}"
    viewer, operator = key(client, "viewer"), key(client, "operator")
    refused = client.post(f"{url}/acknowledge", headers=viewer)
    assert (refused.status_code, refused.json()) == (403, {
        "detail": "Role 'viewer' may not alarms"})
    refused = client.post(f"{url}/out-of-service", headers=operator)
    assert (refused.status_code, refused.json()) == (403, {
        "detail": "Role 'operator' may not admin"})
    for duration in (0, 24 * 3600 + 1):
        answer = client.post(f"{url}/shelve", json={"duration_s": duration}, headers=operator)
        assert answer.status_code == 422
        assert answer.json()["detail"][0]["loc"] == ["body", "duration_s"]
    shelved = client.post(f"{url}/shelve", json={"duration_s": 60, "note": "trip"},
                          headers=operator)
    assert (shelved.status_code, shelved.json()["state"]) == (200, "shelved")
    assert shelved.json()["shelved_until"] == T0 + 60
    out = client.post(f"{url}/out-of-service", headers=HEADERS)
    assert (out.status_code, out.json()["state"]) == (200, "out_of_service")
