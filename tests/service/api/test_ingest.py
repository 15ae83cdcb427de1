"""``/api/v1/ingest`` and ``/api/v1/ingest/csv``: 200 when every item is taken, 207 with
the per-tag report, 422 for a batch or CSV that cannot be read, with its exact ``detail``."""

from tests.service.test_api import T0, key, simulated_batch


def test_ingest_is_idempotent_and_reports_refusals(client):
    historian = key(client, "historian")
    batch = simulated_batch(200)
    first = client.post("/api/v1/ingest", json=batch, headers=historian)
    assert first.status_code == 200, first.text
    assert first.json()["stored"] == 6 * 200
    again = client.post("/api/v1/ingest", json=batch, headers=historian)
    assert again.status_code == 200
    assert again.json()["stored"] == 0 and again.json()["already_stored"] == 6 * 200
    mixed = [{"tag": "NOPE", "items": [{"timestamp": T0, "value": 1.0}]},
             {"tag": "FIC-1.OP", "items": [{"timestamp": T0 + 1, "value": 50.0}]}]
    partial = client.post("/api/v1/ingest", json=mixed, headers=historian)
    assert partial.status_code == 207
    assert partial.json()["refused"] == {"unknown_tag": 1}
    assert partial.json()["stored"] == 1
    # QA: a value sent as text ("NaN") is refused alone, with its tag and time stamp
    text = [{"tag": "FIC-1.OP", "items": [{"timestamp": T0 + 2, "value": 51.0},
                                          {"timestamp": T0 + 3, "value": "NaN"}]}]
    partial = client.post("/api/v1/ingest", json=text, headers=historian)
    assert partial.status_code == 207, partial.text
    answer = partial.json()
    assert (answer["stored"], answer["refused"]) == (1, {"bad_value": 1})
    assert answer["tags"][0]["tag"] == "FIC-1.OP"
    assert answer["tags"][0]["refused_items"] == [{"timestamp": T0 + 3, "reason": "bad_value"}]
    bad = client.post("/api/v1/ingest", json=[{"items": []}], headers=historian)
    assert bad.status_code == 422


def test_a_body_that_is_not_a_batch_is_422_saying_why(client):
    historian = key(client, "historian")
    answer = client.post("/api/v1/ingest", content=b"{", headers=historian)
    assert (answer.status_code, answer.json()) == (422, {
        "detail": "invalid batch: not JSON: Expecting property name enclosed in double "
                  "quotes: line 1 column 2 (char 1)"})
    refused = client.post("/api/v1/ingest", json=[], headers=key(client, "viewer"))
    assert (refused.status_code, refused.json()) == (403, {
        "detail": "Role 'viewer' may not ingest"})


def test_a_csv_upload_is_stored_or_refused_with_row_and_column(client):
    historian = key(client, "historian")
    stored = client.post("/api/v1/ingest/csv", headers=historian,
                         content=f"time,FIC-1.OP\n{T0},50\n{T0 + 1},51\n".encode())
    assert (stored.status_code, stored.json()["stored"]) == (200, 2)
    binary = client.post("/api/v1/ingest/csv", content=b"\xff\xfe", headers=historian)
    assert (binary.status_code, binary.json()) == (422, {
        "detail": "CSV is not UTF-8 text: invalid start byte at byte 0"})
    no_time = client.post("/api/v1/ingest/csv", content=b"a,b\n", headers=historian)
    assert (no_time.status_code, no_time.json()) == (422, {
        "detail": "CSV row 1, column 1: 'a' is not a time column; the wide format starts "
                  "with time/t/t_s/timestamp, the long format has a tag column"})
