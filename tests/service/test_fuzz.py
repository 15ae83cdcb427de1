"""Bad input: every malformed request gets a 4xx that says what was wrong, never a 5xx,
and nothing already stored is lost or changed.

Two kinds of generated input:

* schemathesis reads our own OpenAPI schema and sends what it allows and what
  it does not (positive and negative cases) to every operation, checking
  that each answer is one the schema describes (status code, content type,
  headers, body), and, with more cases, to the ingest, loop configuration
  and model-check operations;
* hypothesis strategies aimed at the parsers behind them: near-valid loop
  configurations (a valid one with one part broken), ingest items of
  configured tags with any time stamp and value, and any text as CSV, both
  for the historian upload and for :func:`service.loop_csv.read_loop_csv`.

Before and after, the test snapshots every stored sample and every loop's
configuration; the store must hold the same (plus what a 2xx answer says it
stored).
"""

from __future__ import annotations

import csv
import io
import json
import math
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any
from urllib.parse import quote

import pytest
import schemathesis
from fastapi.testclient import TestClient
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st
from hypothesis.errors import Unsatisfiable
from schemathesis import GenerationMode
from schemathesis.checks import not_a_server_error
from schemathesis.core.failures import FailureGroup
from schemathesis.specs.openapi.checks import (
    content_type_conformance,
    response_headers_conformance,
    response_schema_conformance,
    status_code_conformance,
)
from sqlalchemy import select

from service.config import Settings
from service.loop_csv import LoopCsvError, read_loop_csv
from service.server import Service, build_service
from service.store.models import Loop, Sample
from tests.service.test_api import ADMIN, T0, plant, simulated_batch

EXAMPLES = 60
"""Generated cases per operation and mode (CI time on 2 cores: about a minute in all)."""

FUZZ = settings(max_examples=EXAMPLES, deadline=None, database=None,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.filter_too_much])

VALID_LOOP = {"name": "Fuzzed", "unit": "u1", "ts": 1.0, "tags": {"op": "NEW.OP", "pv": "NEW.PV"},
              "ranges": {"op": [0, 100], "pv": [0, 40]}, "process_type": "self-regulating",
              "controller": {"type": "PI", "Kc": 0.5, "Ti": 8.0}, "valve_asset": "FV-9",
              "importance": "high"}


class Snapshot:
    """The stored samples and loop configurations, to compare after the fuzzing."""

    def __init__(self, svc: Service) -> None:
        self.svc = svc
        self.samples, self.loops = self._read()
        self.changed_loops: set[str] = set()

    def _read(self) -> tuple[dict[tuple[str, float], tuple[float | None, bool]],
                             dict[str, Any]]:
        with self.svc.state.store.session() as session:
            samples = {(tag, t): (v, good) for tag, t, v, good in session.execute(
                select(Sample.tag, Sample.time, Sample.value, Sample.good))}
            loops = {loop.id: loop.config for loop in session.scalars(select(Loop))}
        return samples, loops

    def assert_running_plant_is_stored(self) -> None:
        """The loops the service runs with are the loops in the store."""
        running = {loop.id: loop.model_dump(mode="json")
                   for loop in self.svc.state.registry.plant.loops}
        assert running == self._read()[1], "the running plant and the stored loops differ"

    def assert_kept(self) -> None:
        """Every sample and every loop not replaced by a 2xx PUT is as it was, and the
        running service's plant is the stored one."""
        self.assert_running_plant_is_stored()
        samples, loops = self._read()
        lost = {k: v for k, v in self.samples.items() if samples.get(k) != v}
        assert not lost, f"{len(lost)} stored samples lost or changed, e.g. {next(iter(lost))}"
        for loop_id, config in self.loops.items():
            if loop_id not in self.changed_loops:
                assert loops[loop_id] == config, loop_id
        books = self.svc.state.accounting()
        assert books.balanced, books


def assert_clear_answer(response: Any, what: str) -> None:
    """No 5xx; a 4xx carries a ``detail`` that says what was wrong."""
    assert response.status_code < 500, f"{what}: {response.status_code} {response.text[:500]}"
    if response.status_code >= 400:
        detail = response.json()["detail"]
        messages = ([e["msg"] for e in detail] if isinstance(detail, list) else [detail])
        assert messages and all(isinstance(m, str) and m for m in messages), (what, detail)


@pytest.fixture
def service(store) -> Iterator[Service]:
    """The two-loop plant with 200 s of samples stored; rate limits out of the way."""
    svc = build_service(
        Settings(database_url=store.url, api_key=ADMIN, window_s=3600, buffer_horizon_s=7200,
                 rate_limit_burst=100_000, rate_limit_per_s=10_000.0),
        plant(), executor=ThreadPoolExecutor(1), clock=lambda: T0)
    svc.state.ingest(simulated_batch(200))
    yield svc
    svc.executor.shutdown()
    svc.state.store.close()


# ----------------------------------------------------------------------------- schemathesis


OPERATIONS = [("POST", "/api/v1/ingest"), ("POST", "/api/v1/ingest/csv"),
              ("PUT", "/api/v1/loops/{loop_id}"), ("POST", "/api/v1/loops/{loop_id}/model-check")]


@pytest.mark.parametrize("mode", [GenerationMode.POSITIVE, GenerationMode.NEGATIVE])
@pytest.mark.parametrize(("method", "path"), OPERATIONS)
def test_schemathesis_finds_no_server_error(service, method, path, mode):
    schema = schemathesis.openapi.from_asgi("/openapi.json", service.app,
                                            headers={"X-API-Key": ADMIN})
    operation = schema[path][method]
    snapshot = Snapshot(service)

    @FUZZ
    @given(case=operation.as_strategy(generation_mode=mode))
    def check(case: Any) -> None:
        response = case.call(headers={"X-API-Key": ADMIN})
        assert_clear_answer(response, f"{method} {case.path} {case.path_parameters}")
        if method == "PUT" and response.status_code < 300:
            snapshot.changed_loops.add(response.json()["id"])

    check()
    snapshot.assert_kept()


CONFORMANCE = [not_a_server_error, status_code_conformance, content_type_conformance,
               response_headers_conformance, response_schema_conformance]
EVERY_OPERATION_EXAMPLES = 30
"""Cases per operation and mode over every operation (about 2,000 requests, 1-2 min)."""


def test_every_operation_answers_what_its_schema_says(tmp_path, capsys):
    """Every /api/v1 operation (and /metrics), positive and negative cases: no 5xx and
    every answer described by the schema.  SQLite only, to bound CI time; the key id 1
    (the admin key the fuzzing uses) is left alone."""
    svc = build_service(
        Settings(database_url=f"sqlite:///{tmp_path / 'fuzz.db'}", api_key=ADMIN,
                 window_s=3600, buffer_horizon_s=7200, rate_limit_burst=100_000,
                 rate_limit_per_s=10_000.0, auth_failure_burst=100_000),
        plant(), executor=ThreadPoolExecutor(1), clock=lambda: T0)
    svc.state.ingest(simulated_batch(200))
    schema = schemathesis.openapi.from_asgi("/openapi.json", svc.app,
                                            headers={"X-API-Key": ADMIN})
    sent: list[int] = []
    violations: dict[str, str] = {}
    for result in schema.get_all_operations():
        operation = result.ok()
        for mode in (GenerationMode.POSITIVE, GenerationMode.NEGATIVE):
            strategy = operation.as_strategy(generation_mode=mode).filter(
                lambda case: case.path_parameters is None
                or case.path_parameters.get("key_id") != 1)

            @settings(FUZZ, max_examples=EVERY_OPERATION_EXAMPLES)
            @given(case=strategy)
            def check(case: Any) -> None:
                response = case.call(headers={"X-API-Key": ADMIN})
                sent.append(response.status_code)
                try:
                    case.validate_response(response, checks=CONFORMANCE,
                                           headers={"X-API-Key": ADMIN})
                except FailureGroup as exc:
                    where = f"{case.method} {case.operation.path}"
                    violations.setdefault(where, f"{response.status_code}: {exc}"[:800])

            try:
                check()
            except Unsatisfiable:  # nothing to negate (an operation without parameters)
                assert mode is GenerationMode.NEGATIVE, operation.path
    server_errors = sum(status >= 500 for status in sent)
    with capsys.disabled():
        print(f"\nschemathesis over every operation: {len(sent)} requests, "
              f"{server_errors} 5xx, {len(violations)} operations with schema violations")
    assert not violations, "\n\n".join(f"{k}: {v}" for k, v in violations.items())
    assert server_errors == 0
    svc.executor.shutdown()
    svc.state.store.close()


# ----------------------------------------------------------------------------- loop configuration


json_values = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats(allow_nan=False, allow_infinity=False)
    | st.text(max_size=300),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner,
                                                                 max_size=4),
    max_leaves=10,
)
nasty_text = st.one_of(
    st.text(max_size=30), st.text(min_size=201, max_size=400),
    st.sampled_from(["", " ", "\x00", "FIC-1.PV", "a" * 65, "ü-ñ", "../etc", "NEW.PV"]),
)
LOOP_PATHS = [("name",), ("unit",), ("ts",), ("tags",), ("tags", "op"), ("tags", "pv"),
              ("ranges",), ("ranges", "op"), ("process_type",), ("controller",),
              ("controller", "Kc"), ("controller", "Ti"), ("controller", "type"),
              ("valve_asset",), ("importance",), ("location",), ("process_model",),
              ("surprise",)]


@st.composite
def broken_loop(draw: st.DrawFn) -> tuple[str, dict[str, Any]]:
    """A valid loop configuration with one or two parts deleted or replaced."""
    config: dict[str, Any] = {k: (dict(v) if isinstance(v, dict) else v)
                              for k, v in VALID_LOOP.items()}
    for _ in range(draw(st.integers(1, 2))):
        path = draw(st.sampled_from(LOOP_PATHS))
        parent = config
        for part in path[:-1]:
            if not isinstance(parent.get(part), dict):
                parent[part] = {}
            parent = parent[part]
        if draw(st.booleans()):
            parent.pop(path[-1], None)
        else:
            parent[path[-1]] = draw(json_values | nasty_text)
    loop_id = draw(st.sampled_from(["NEW-1", "NEW-2"]) | nasty_text.filter(
        lambda s: s.strip("./") and "/" not in s and "?" not in s and "#" not in s))
    return loop_id, config


def test_broken_loop_configurations_get_422_with_the_field(service):
    client = TestClient(service.app)
    snapshot = Snapshot(service)

    @FUZZ
    @given(broken_loop())
    @example(("NEW-1", {**VALID_LOOP, "tags": {"pv": "x" * 300}}))  # PostgreSQL: varchar(200)
    @example(("NEW-2", {**VALID_LOOP, "name": "a\x00b"}))  # PostgreSQL: no NUL in text
    def check(case: tuple[str, dict[str, Any]]) -> None:
        loop_id, config = case
        response = client.put(f"/api/v1/loops/{quote(loop_id, safe='')}", json=config,
                              headers={"X-API-Key": ADMIN})
        assert_clear_answer(response, f"PUT {loop_id!r} {config!r}")
        snapshot.assert_running_plant_is_stored()
        if response.status_code == 200:
            snapshot.changed_loops.add(loop_id)
            stored = client.get(f"/api/v1/loops/{loop_id}/config",
                                headers={"X-API-Key": ADMIN}).json()
            assert stored["id"] == loop_id and stored["ts"] == config["ts"]

    check()
    snapshot.assert_kept()


# ----------------------------------------------------------------------------- ingest


timestamps = st.one_of(
    st.floats(), st.floats(min_value=T0 - 300, max_value=T0 + 600),
    st.sampled_from([T0 - 150, T0 - 150.0001, -1.0, 0.0, 1e300]),
    st.text(max_size=40),
    st.datetimes().map(lambda d: d.isoformat()),
    st.builds(lambda d, h: f"{d.isoformat()}{'+' if h >= 0 else '-'}{abs(h):02d}:00",
              st.datetimes(), st.integers(-23, 23)),
)
items = st.fixed_dictionaries(
    {"timestamp": timestamps, "value": st.none() | st.floats()},
    optional={"good": st.booleans()},
)
known_tags = st.sampled_from(["FIC-1.OP", "FIC-1.PV", "FIC-1.SP", "FIC-2.PV", "NOPE"])


def test_ingest_of_configured_tags_with_any_time_and_value_never_fails(service):
    client = TestClient(service.app)
    snapshot = Snapshot(service)
    historian = {"X-API-Key": ADMIN}

    @FUZZ
    @given(st.lists(st.fixed_dictionaries({"tag": known_tags,
                                           "items": st.lists(items, max_size=6)}), max_size=4))
    def check(batch: list[dict[str, Any]]) -> None:
        before = service.state.accounting()
        # Python's JSON (not the client's) also writes NaN and Infinity, as some historians do
        response = client.post("/api/v1/ingest", content=json.dumps(batch),
                               headers={**historian, "Content-Type": "application/json"})
        assert_clear_answer(response, f"ingest {batch!r}")
        if response.status_code in (200, 207):
            report = response.json()
            assert report["received"] == sum(len(e["items"]) for e in batch)
            assert report["received"] == (report["stored"] + report["already_stored"]
                                          + sum(report["refused"].values()))
            assert service.state.accounting().stored - before.stored == report["stored"]

    check()
    snapshot.assert_kept()


csv_cells = st.one_of(
    st.sampled_from(["", "1.5", "nan", "NA", "true", "bad", "FIC-1.PV", "FIC-2.PV", "NOPE",
                     str(T0 - 30), "2023-11-14T22:13:00Z", "1e999", "-inf", "\"", "x,y"]),
    st.text(max_size=12),
)
csv_headers = st.lists(st.sampled_from(["time", "timestamp", "tag", "value", "good",
                                        "FIC-1.PV", "FIC-2.PV", "NOPE", "", "Time"]),
                       min_size=1, max_size=5)


@st.composite
def csv_texts(draw: st.DrawFn) -> str:
    """Table-shaped CSV text (rows may be ragged), or any text at all."""
    if draw(st.booleans()):
        return draw(st.text(max_size=200))
    header = draw(csv_headers)
    rows = draw(st.lists(st.lists(csv_cells, min_size=len(header) - 1,
                                  max_size=len(header) + 1), max_size=6))
    out = io.StringIO()
    writer = csv.writer(out)
    writer.writerow(header)
    writer.writerows(rows)
    return out.getvalue()


def test_csv_uploads_of_any_shape_get_a_clear_answer(service):
    client = TestClient(service.app)
    snapshot = Snapshot(service)

    @FUZZ
    @given(st.one_of(csv_texts().map(str.encode), st.binary(max_size=100)))
    @example(b"\n")  # an empty first line: found by this test (IndexError, a 500)
    def check(body: bytes) -> None:
        response = client.post("/api/v1/ingest/csv", content=body,
                               headers={"X-API-Key": ADMIN, "Content-Type": "text/csv"})
        assert_clear_answer(response, f"CSV {body!r}")

    check()
    snapshot.assert_kept()


# ----------------------------------------------------------------------------- loop CSV files


def test_read_loop_csv_answers_any_text_with_data_or_an_error_naming_the_file(tmp_path):
    path = tmp_path / "loop.csv"

    @FUZZ
    @given(st.one_of(csv_texts(), st.text(max_size=300)), st.none() | st.floats())
    def check(text: str, ts: float | None) -> None:
        path.write_text(text, encoding="utf-8", errors="surrogatepass")
        try:
            data = read_loop_csv(path, ts=ts)
        except LoopCsvError as exc:
            assert str(path) in str(exc) or str(exc).startswith("--ts"), str(exc)
            return
        assert data.samples >= 2 and data.ts > 0 and math.isfinite(data.ts)
        assert data.op is not None or data.pv is not None

    check()


finite = st.floats(min_value=-1e12, max_value=1e12, allow_nan=False)


def test_read_loop_csv_gives_back_exactly_the_numbers_written(tmp_path: Path):
    """Round trip: a table written with Python's csv module is read back value for value."""
    path = tmp_path / "loop.csv"

    @FUZZ
    @given(st.lists(st.tuples(finite, finite | st.none()), min_size=2, max_size=50),
           st.floats(min_value=1e-3, max_value=1e4))
    def check(rows: list[tuple[float, float | None]], ts: float) -> None:
        with path.open("w", newline="") as handle:
            writer = csv.writer(handle)
            writer.writerow(["t_s", "OP", "PV"])
            writer.writerows((k * ts, op, "" if pv is None else pv)
                             for k, (op, pv) in enumerate(rows))
        data = read_loop_csv(path)
        assert data.op is not None and data.pv is not None
        assert data.op.tolist() == [op for op, _ in rows]
        assert [None if math.isnan(v) else v for v in data.pv.tolist()] == [pv for _, pv in rows]
        assert data.t.tolist() == [k * ts for k in range(len(rows))]

    check()


def test_a_value_the_store_refuses_leaves_the_running_plant_as_stored(service):
    # Found by the fuzzing above on PostgreSQL: a valve tag with a NUL character is kept in
    # the loop's JSON configuration, whose json column took it, until a later read of the
    # same request cast it; the refusal (422) came after the running plant had the loop.
    # Now it is refused before, on every store, saying where the NUL stands.
    client = TestClient(service.app)
    snapshot = Snapshot(service)
    for config, where in (({**VALID_LOOP, "valve_asset": "FV\x009"}, "valve_asset"),
                          ({**VALID_LOOP, "tags": {"op": "A.OP", "pv": "A\x00PV"}}, "tags.pv"),
                          ({**VALID_LOOP, "cmms": {"sap_pm": {"\x00": "x"}}},
                           "cmms.sap_pm.'\\x00'")):
        response = client.put("/api/v1/loops/NEW-3", json=config, headers={"X-API-Key": ADMIN})
        assert response.status_code == 422, response.text
        (error,) = response.json()["detail"]
        assert error["msg"].endswith(f"text cannot hold a NUL (0x00) character: at {where}")
        snapshot.assert_running_plant_is_stored()
