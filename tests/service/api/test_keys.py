"""``/api/v1/keys`` and the key check every route makes: 401 for a missing, unknown or
revoked key, 403 for a role without the permission, with their exact ``detail``."""

from tests.service.test_api import ADMIN, key

HEADERS = {"X-API-Key": ADMIN}


def test_missing_wrong_and_insufficient_keys(client):
    assert client.get("/healthz").status_code == 200
    assert client.get("/api/v1/loops").json() == {
        "detail": "Missing API key (header X-API-Key)"}
    wrong = client.get("/api/v1/loops", headers={"X-API-Key": "nope"})
    assert (wrong.status_code, wrong.json()) == (401, {"detail": "Invalid or revoked API key"})
    viewer, historian = key(client, "viewer"), key(client, "historian")
    assert client.get("/api/v1/loops", headers=viewer).status_code == 200
    assert client.get("/api/v1/loops", headers=historian).json() == {
        "detail": "Role 'historian' may not read"}
    assert client.post("/api/v1/ingest", json=[], headers=viewer).status_code == 403
    refused = client.post("/api/v1/keys", json={"name": "x", "role": "admin"}, headers=viewer)
    assert (refused.status_code, refused.json()) == (403, {
        "detail": "Role 'viewer' may not admin"})


def test_keys_are_shown_once_and_revocation_locks_out(client):
    viewer = key(client, "viewer")
    listed = client.get("/api/v1/keys", headers=HEADERS).json()
    assert listed["count"] == 2
    assert all("key" not in k and "key_hash" not in k for k in listed["data"])
    victim = next(k for k in listed["data"] if k["role"] == "viewer")
    assert viewer["X-API-Key"].startswith(f"lw_{victim['key_id']}_")
    revoked = client.delete(f"/api/v1/keys/{victim['id']}", headers=HEADERS)
    assert (revoked.status_code, revoked.json()["revoked_at"] is not None) == (200, True)
    assert client.get("/api/v1/loops", headers=viewer).json() == {
        "detail": "Invalid or revoked API key"}
    unknown = client.delete("/api/v1/keys/999", headers=HEADERS)
    assert (unknown.status_code, unknown.json()) == (404, {"detail": "API key not found"})


def test_the_last_admin_key_cannot_be_revoked_and_a_role_must_be_known(client):
    admin = next(k for k in client.get("/api/v1/keys", headers=HEADERS).json()["data"]
                 if k["role"] == "admin")
    last = client.delete(f"/api/v1/keys/{admin['id']}", headers=HEADERS)
    assert (last.status_code, last.json()) == (409, {
        "detail": f"Key {admin['id']} is the last active admin key; create another admin "
                  "key before revoking it"})
    assert client.get("/api/v1/me", headers=HEADERS).status_code == 200
    unknown = client.post("/api/v1/keys", json={"name": "x", "role": "root"}, headers=HEADERS)
    assert unknown.status_code == 422
    assert unknown.json()["detail"][0]["loc"] == ["body", "role"]
