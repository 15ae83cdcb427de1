"""PI Web API answers on POST /api/v1/ingest, as PI sends them.

The bodies follow the PI Web API reference: ``GET streamsets/recorded``
answers ``{"Links": {}, "Items": [{"WebId", "Name", "Path", "Links",
"Items": [timed values], "UnitsAbbreviation"}]}``; a timed value has
``Timestamp`` (ISO 8601, UTC, up to 7 decimals), ``Value``,
``UnitsAbbreviation``, ``Good``, ``Questionable``, ``Substituted`` and
``Annotated``; a digital state stands in ``Value`` as ``{"Name", "Value",
"IsSystem"}`` (system states such as "Bad Input" on any point).
"""

import json
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import select

from service.config import ConfigError, PlantConfig, Settings, parse_plant_config
from service.ingest import IngestError, parse_batch
from service.server import build_service
from service.store.models import Sample
from tests.service.test_api import ADMIN, T0, plant

PATH = "\\\\PISRV01\\FIC-1.PV"  # a PI point's path: \\server\point
ATTRIBUTE = "\\\\AFSRV\\Plant\\Unit 1\\FV-1|Output"  # an AF attribute's path


def timed(timestamp: str, value: Any, *, good: bool = True, questionable: bool = False,
          substituted: bool = False) -> dict[str, Any]:
    """A timed value with every field PI Web API writes."""
    return {"Timestamp": timestamp, "Value": value, "UnitsAbbreviation": "m3/h", "Good": good,
            "Questionable": questionable, "Substituted": substituted, "Annotated": False}


def stream(name: str, path: str, *values: dict[str, Any]) -> dict[str, Any]:
    """A stream of a ``streamsets/recorded`` answer."""
    return {"WebId": "F1DPDqD5loBNH0erqeqJodtALAAwAAAAUElTUlYwMVxGSUMtMS5QVg",
            "Name": name, "Path": path,
            "Links": {"Source": "https://pisrv01/piwebapi/points/F1DP"},
            "Items": list(values), "UnitsAbbreviation": "m3/h"}


def recorded(*streams: dict[str, Any]) -> dict[str, Any]:
    """A ``GET streamsets/recorded`` answer."""
    return {"Links": {}, "Items": list(streams)}


T = "2023-11-14T22:13:1{}Z"  # T0 - 10 + 0..9 s (T0 is 2023-11-14T22:13:20Z)
BAD_INPUT = {"Name": "Bad Input", "Value": 307, "IsSystem": True}
OPEN = {"Name": "Open", "Value": 1, "IsSystem": False}


def pi_plant() -> PlantConfig:
    """The test plant with FIC-1's PV known by its PI path and FIC-1's OP by an AF attribute."""
    return PlantConfig.model_validate({**plant().model_dump(), "pi_points": {
        PATH: "FIC-1.PV", ATTRIBUTE: "FIC-1.OP"}})


@pytest.fixture
def client(store):
    settings = Settings(database_url=store.url, api_key=ADMIN, window_s=3600,
                        buffer_horizon_s=7200)
    svc = build_service(settings, pi_plant(), executor=ThreadPoolExecutor(1),
                        clock=lambda: T0 + 10)
    yield TestClient(svc.app)
    svc.executor.shutdown()
    svc.state.store.close()


def stored(client: TestClient, tag: str) -> list[tuple[float, float | None, bool]]:
    with client.app.state.loopwatch.store.session() as session:  # type: ignore[attr-defined]
        return [tuple(row) for row in session.execute(
            select(Sample.time, Sample.value, Sample.good).where(Sample.tag == tag)
            .order_by(Sample.time))]


def test_a_recorded_answer_is_stored_by_path_name_and_attribute(client) -> None:
    answer = recorded(
        stream("FIC-1.PV", PATH,
               timed(T.format(0), 12.5),
               timed(T.format("1.1234567"), 12.75, questionable=True),
               timed(T.format(2), BAD_INPUT, good=False),
               timed(T.format(3), 13, substituted=True),
               timed(T.format(4), 14.0, good=False)),
        stream("Output", ATTRIBUTE, timed(T.format(0), 40.0), timed(T.format(1), OPEN)),
        stream("FIC-2.SP", "\\\\PISRV01\\FIC-2.SP", timed(T.format(0), 50.0)),  # by its name
        stream("TIC-9.PV", "\\\\PISRV01\\TIC-9.PV", timed(T.format(0), 1.0)),  # not a loop's
    )
    response = client.post("/api/v1/ingest", json=answer, headers={"X-API-Key": ADMIN})
    assert response.status_code == 207, response.text
    report = response.json()
    assert [(t["tag"], t["stored"], t["bad"]) for t in report["tags"]] == [
        ("FIC-1.PV", 5, 2), ("FIC-1.OP", 2, 0), ("FIC-2.SP", 1, 0), ("TIC-9.PV", 0, 0)]
    assert report["refused"] == {"unknown_tag": 1}
    t0 = T0 - 10
    assert stored(client, "FIC-1.PV") == [
        (t0, 12.5, True),
        (pytest.approx(t0 + 1.123456), 12.75, True),  # questionable: the value PI shows
        (t0 + 2, None, False),  # a system digital state is a hole
        (t0 + 3, 13.0, True),  # substituted: the value PI shows
        (t0 + 4, None, False),  # Good: false
    ]
    assert stored(client, "FIC-1.OP") == [(t0, 40.0, True), (t0 + 1, 1.0, True)]  # state code


def test_the_items_list_alone_and_the_simple_shape_are_both_taken(client) -> None:
    admin = {"X-API-Key": ADMIN}
    bare = [stream("FIC-1.PV", PATH, timed(T.format(0), 1.0))]
    assert client.post("/api/v1/ingest", json=bare, headers=admin).json()["stored"] == 1
    simple = [{"tag": "FIC-1.PV", "items": [{"timestamp": T.format(1), "value": 2.0}]}]
    assert client.post("/api/v1/ingest", json=simple, headers=admin).json()["stored"] == 1
    assert [v for _, v, _ in stored(client, "FIC-1.PV")] == [1.0, 2.0]


@pytest.mark.parametrize(
    ("answer", "where"),
    [
        (recorded(stream("FIC-1.PV", PATH, timed(T.format(0), "12,5"))),
         "batch.Items[0].Items[0].Value"),
        (recorded(stream("FIC-1.PV", PATH, {"Value": 1.0, "Good": True})),
         "batch.Items[0].Items[0].Timestamp: Field required"),
        (recorded(stream("FIC-1.PV", PATH, timed(T.format(0), {"Name": "Open"}))),
         "batch.Items[0].Items[0].Value"),
        (recorded({"WebId": "F1DP", "Items": [timed(T.format(0), 1.0)]}),
         "batch.Items[0]: a stream needs a Name or a Path"),
        ({"Items": 5}, "expected a list of {tag, items} objects or a PI Web API answer"),
    ],
)
def test_an_answer_of_the_wrong_shape_is_refused_with_the_place(answer: Any, where: str) -> None:
    with pytest.raises(IngestError, match="invalid batch") as error:
        parse_batch(json.dumps(answer).encode(), max_samples=100, pi_points={})
    assert where in str(error.value)


def test_a_long_answer_is_refused_before_it_is_validated() -> None:
    answer = recorded(stream("FIC-1.PV", PATH, *[timed(T.format(0), "x")] * 11))
    with pytest.raises(IngestError, match="batch of 11 samples is longer than the limit of 10"):
        parse_batch(json.dumps(answer).encode(), max_samples=10)


def test_pi_points_must_name_a_loop_tag() -> None:
    data = {**plant().model_dump(), "pi_points": {PATH: "FIC-9.PV"}}
    with pytest.raises(ConfigError, match=r"pi_points\[.*FIC-1.PV'\]: 'FIC-9.PV' is not a tag"):
        parse_plant_config(data, "plant.yaml")
