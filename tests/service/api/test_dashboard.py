"""The dashboard's pages and files (no key) and ``/api/v1/me``."""

import pytest

from tests.service.test_api import ADMIN, key


@pytest.mark.parametrize("path", ["/", "/docs", "/redoc"])
def test_the_pages_load_without_a_key(client, path):
    answer = client.get(path)
    assert answer.status_code == 200
    assert answer.headers["content-type"].startswith("text/html")


def test_an_unknown_static_file_is_404(client):
    answer = client.get("/static/nope.js")
    assert (answer.status_code, answer.json()) == (404, {"detail": "Static file not found"})


def test_me_names_the_calling_key(client):
    me = client.get("/api/v1/me", headers=key(client, "operator"))
    assert me.json() == {"name": "operator key", "role": "operator",
                         "permissions": ["alarms", "read"]}
    assert client.get("/api/v1/me", headers={"X-API-Key": ADMIN}).json()["role"] == "admin"
    assert client.get("/api/v1/me").json() == {"detail": "Missing API key (header X-API-Key)"}
    refused = client.get("/api/v1/me", headers=key(client, "historian"))
    assert (refused.status_code, refused.json()) == (403, {
        "detail": "Role 'historian' may not read"})
