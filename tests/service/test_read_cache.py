"""Answers shared by requests until the store changes (issue 20's load: 20 dashboards
asking for the list and the ranking of 2,000 loops each second).

A real store (SQLite and PostgreSQL, ``tests/service/conftest.py``), the real
service and its routes; the clocks are the injectable ones, no timing.
"""

from concurrent.futures import ThreadPoolExecutor

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import update

from service.config import Settings
from service.read_cache import ReadCache
from service.server import build_service
from service.store.models import Alarm, AnalysisRun, Loop, Unit
from tests.service.test_api import ADMIN, T0, key
from tests.service.test_kpis import Clock, plant


def test_the_store_counts_the_commits_that_wrote_each_table(store):
    loops, units = store.version("loops"), store.version("units")
    with store.session() as session:
        session.add(Unit(id="u9", name="Unit 9"))
    assert (store.version("loops"), store.version("units")) == (loops, units + 1)
    with store.session() as session:
        session.add(Loop(id="L9", name="nine", unit_id="u9", config={}, created_at=T0,
                         updated_at=T0))
    assert store.version("loops") == loops + 1
    with pytest.raises(RuntimeError), store.session() as session:  # rolled back
        session.get(Loop, "L9").name = "renamed"
        session.flush()
        raise RuntimeError
    with store.session() as session:  # a read
        assert session.get(Loop, "L9").name == "nine"
    assert store.version("loops") == loops + 1
    with store.session() as session:  # a statement, not an object
        session.execute(update(Loop).where(Loop.id == "L9").values(name="renamed"))
    with store.session() as session:
        session.delete(session.get(Loop, "L9"))
    assert store.version("loops") == loops + 3
    assert store.version("loops", "units") == loops + units + 4
    runs = store.version("analysis_runs")
    with store.session() as session:  # a run without data: no shared view reads it
        session.add(Unit(id="u8", name="Unit 8"))
        session.add(Loop(id="L8", name="eight", config={}, created_at=T0, updated_at=T0))
        session.flush()
        session.add(AnalysisRun(loop_id="L8", started_at=T0, status="no_data"))
    assert store.version("analysis_runs") == runs
    with store.session() as session:  # touched, not changed
        session.get(Loop, "L8").name = "eight"
    assert store.version("loops") == loops + 4
    with store.session() as session:
        session.add(AnalysisRun(loop_id="L8", started_at=T0, status="ok"))
    assert store.version("analysis_runs") == runs + 1


def test_an_answer_is_shared_until_its_tables_are_written_or_it_is_too_old(store):
    now = [0.0]
    cache = ReadCache(store, ("loops",), max_age_s=2.0, clock=lambda: now[0])
    computed = []

    def compute() -> int:
        computed.append(1)
        return len(computed)

    assert [cache.get("k", compute) for _ in range(3)] == [1, 1, 1]
    assert cache.get("other", compute) == 2  # each key its own answer
    with store.session() as session:  # another table: still current
        session.add(Unit(id="u9", name="Unit 9"))
    assert cache.get("k", compute) == 1
    with store.session() as session:
        session.add(Loop(id="L9", name="nine", config={}, created_at=T0, updated_at=T0))
    assert cache.get("k", compute) == 3  # written: computed again, then shared
    assert cache.get("k", compute) == 3
    now[0] = 2.5
    assert cache.get("k", compute) == 4  # too old
    assert cache.get("k", compute, valid=lambda answer: answer != 4) == 5
    assert ReadCache(store, ("loops",), max_age_s=0).get("k", compute) == 6  # no sharing


def test_peek_takes_a_current_answer_only_and_an_answer_made_of_kept_ones_is_as_old(store):
    now = [0.0]
    cache = ReadCache(store, ("loops",), max_age_s=2.0, clock=lambda: now[0])
    assert cache.peek("rows") is None  # nothing kept: peek neither computes nor waits
    assert cache.get("rows", lambda: "rows of t=0") == "rows of t=0"
    assert cache.peek("rows") == "rows of t=0"
    assert cache.peek("rows", valid=lambda answer: answer.endswith("t=1")) is None
    now[0] = 1.5
    # a page computed at t=1.5 from the rows of t=0 is as old as they are
    page = cache.get("page", lambda: "page of " + cache.get("rows", lambda: "rows of t=1.5"))
    assert page == "page of rows of t=0"
    now[0] = 2.5
    assert (cache.peek("rows"), cache.peek("page")) == (None, None)
    assert cache.get("page", lambda: "page of " + cache.get("rows", lambda: "rows of t=2.5")) \
        == "page of rows of t=2.5"
    with store.session() as session:
        session.add(Loop(id="L9", name="nine", config={}, created_at=T0, updated_at=T0))
    assert cache.peek("page") is None  # written


def test_an_answer_half_as_old_as_allowed_is_refreshed_once_with_its_parts(store):
    now = [0.0]
    cache = ReadCache(store, ("loops",), max_age_s=2.0, clock=lambda: now[0])

    def page() -> str:
        return f"page of {cache.get('rows', lambda: f'rows of t={now[0]}')}"

    assert cache.get("page", page) == "page of rows of t=0.0"
    now[0] = 0.5
    assert not cache.refresh_ahead("page")
    assert not cache.refresh_ahead("missing")
    now[0] = 1.5
    assert cache.refresh_ahead("page")
    assert not cache.refresh_ahead("page")  # claimed by the first caller
    assert cache.peek("page") == "page of rows of t=0.0"  # requests meanwhile take it
    cache.refresh("page", page)
    assert cache.peek("page") == "page of rows of t=1.5"
    now[0] = 2.2  # 0.7 s old: not due
    assert (cache.peek("page"), cache.refresh_ahead("page")) == ("page of rows of t=1.5", False)

    def broken() -> str:
        raise RuntimeError("store gone")

    now[0] = 2.8
    assert cache.refresh_ahead("page")
    cache.refresh("page", broken)  # logged; the kept answer stays until it expires
    assert cache.peek("page") == "page of rows of t=1.5"


@pytest.fixture
def clock():
    return Clock(T0)


@pytest.fixture
def service(store, clock):
    settings = Settings(database_url=store.url, api_key=ADMIN, window_s=3600,
                        buffer_horizon_s=7200, read_cache_s=60.0)
    svc = build_service(settings, plant(), executor=ThreadPoolExecutor(1), clock=clock)
    yield svc
    svc.executor.shutdown()
    svc.state.store.close()


def test_dashboards_share_the_ranking_and_see_every_write_at_once(service, clock):
    client = TestClient(service.app)
    viewer = key(client, "viewer")

    def ranking() -> dict:
        response = client.get("/api/v1/plant/bad-actors", headers=viewer)
        assert response.status_code == 200, response.text
        return response.json()

    def loops() -> dict:
        return {loop["id"]: loop for loop in
                client.get("/api/v1/loops", headers=viewer).json()["data"]}

    first = ranking()
    assert (first["until"], first["data"][0]["runs"]) == (T0, 0)
    clock.now = T0 + 30
    # nothing written: the ranking of 30 s ago is given again, and says so
    assert ranking() == first
    assert loops()["FIC-2"]["active_alarms"] == 0
    with service.state.store.session() as session:
        session.add(AnalysisRun(loop_id="FIC-2", started_at=T0 + 20, finished_at=T0 + 20,
                                status="ok", health=40.0, oscillating=True,
                                verdict="stiction", result={"kpis": {
                                    "oscillation_index": 0.8}}))
        session.add(Alarm(loop_id="FIC-2", kind="oscillation", priority="high",
                          state="unack_active", condition_active=True, raised_at=T0 + 20,
                          updated_at=T0 + 20))
    # a run and an alarm stored: both show in the next answers
    second = ranking()
    assert second["until"] == T0 + 30
    top = second["data"][0]
    assert (top["id"], top["runs"], top["bad_runs"], top["health"]) == ("FIC-2", 1, 1, 40.0)
    assert (loops()["FIC-2"]["active_alarms"], loops()["FIC-2"]["verdict"]) == (1, "stiction")
    assert [r["id"] for r in client.get("/api/v1/loops", headers=viewer,
                                        params={"state": "stiction"}).json()["data"]] == ["FIC-2"]
    # the clock moved on by more than LOOPWATCH_READ_CACHE_S: ranked again
    clock.now = T0 + 100
    assert ranking()["until"] == T0 + 100
    # a different period is its own ranking
    day = client.get("/api/v1/plant/bad-actors", headers=viewer, params={"period": "1d"})
    assert (day.json()["period"], day.json()["until"]) == ("1d", T0 + 100)


def test_shared_answers_carry_an_etag_and_answer_304_until_they_change(service):
    client = TestClient(service.app)
    viewer = key(client, "viewer")
    paths = ("/api/v1/loops", "/api/v1/plant/bad-actors", "/api/v1/alarms")
    etags = {}
    for path in paths:
        first = client.get(path, headers=viewer)
        assert first.status_code == 200, first.text
        etags[path] = first.headers["etag"]
        again = client.get(path, headers={**viewer, "If-None-Match": f'"x", {etags[path]}'})
        assert (again.status_code, again.content, again.headers["etag"]) == (
            304, b"", etags[path]), path
    with service.state.store.session() as session:
        session.add(Alarm(loop_id="FIC-2", kind="oscillation", priority="high",
                          state="unack_active", condition_active=True, raised_at=T0,
                          updated_at=T0))
    for path in paths:  # an alarm raised: every answer changed
        changed = client.get(path, headers={**viewer, "If-None-Match": etags[path]})
        assert changed.status_code == 200, path
        assert changed.headers["etag"] != etags[path]
        assert changed.json() == client.get(path, headers=viewer).json()
    assert client.get("/api/v1/alarms", headers=viewer).json()["count"] == 1
