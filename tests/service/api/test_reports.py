"""``/api/v1/reports/bad-actors``: the file and its refusals (the report's contents:
``tests/service/test_kpis``)."""

from tests.service.test_api import key


def test_the_report_is_a_csv_file_by_default(client):
    answer = client.get("/api/v1/reports/bad-actors", headers=key(client, "viewer"))
    assert answer.status_code == 200
    assert answer.headers["content-type"] == "text/csv; charset=utf-8"
    assert answer.headers["content-disposition"] == 'attachment; filename="bad-actors-7d.csv"'
    assert answer.text.splitlines()[0].startswith("rank,loop,")


def test_refusals(client):
    viewer = key(client, "viewer")
    url = "/api/v1/reports/bad-actors"
    long = client.get(url, headers=viewer, params={"period": "93d"})
    assert (long.status_code, long.json()) == (422, {"detail": "period must be at most 92 days"})
    for params in ({"format": "xls"}, {"period": "7w"}, {"limit": 0}):
        answer = client.get(url, headers=viewer, params=params)
        assert answer.status_code == 422
        assert answer.json()["detail"][0]["loc"][-1] == next(iter(params)), params
    refused = client.get(url, headers=key(client, "historian"))
    assert (refused.status_code, refused.json()) == (403, {
        "detail": "Role 'historian' may not read"})
