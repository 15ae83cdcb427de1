"""The response models of ``service.api.schemas`` document the answers without changing them.

FastAPI validates a route's answer against its ``response_model`` and serializes what
the model has: a key the model lacked would be dropped silently.  Each answer of the
demo plant (advice of both kinds, loop and unit diagnosis, model check, CMMS export,
configuration) and of a unit with a process matrix (prediction) is compared with the
JSON of the dict its route builds, as the API sent it before the models.  And every 2xx
answer of ``/openapi.json`` has a named schema or is a file, and the parts of the stored
loop diagnosis (data issues, oscillations, episodes, method evidence, the stiction
estimate, the ellipse, the valve's size windows) have a model that names each of their
keys.
"""

import itertools
import json
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np
import pytest
from fastapi.encoders import jsonable_encoder
from fastapi.testclient import TestClient
from pydantic import BaseModel
from sqlalchemy import select

from analytics.diagnosis import diagnose_loop
from analytics.model_check.cases import hidden_effect_case
from analytics.model_check.effects import EFFECTS
from service.api.app import openapi_with_json_errors
from service.api.routes import advice, loops, model_check, tickets, unit_diagnosis, unit_prediction
from service.api.schemas.base import Schema
from service.api.schemas.diagnosis import (
    ApparentStictionPublic,
    EpisodePublic,
    LoopDiagnosisPublic,
    ManualPublic,
    MethodEvidencePublic,
    ProcessEstimatePublic,
    QualityIssuePublic,
    QuantificationPublic,
    SignalOscillationPublic,
    SizeWindowPublic,
)
from service.api.schemas.model_check import LoopModelPublic
from service.api.schemas.units import (
    GroupMemberPublic,
    LoopEvidencePublic,
    RankedSignalPublic,
    ShapeDecompositionPublic,
)
from service.config import PlantConfig, Settings
from service.server import build_service
from service.store.models import AnalysisRun, Ticket
from service.stored import ManualStretch
from service.tickets import TicketEpisode, TicketEvidence
from tests.service.api.stored import store_run
from tests.service.api.test_advice import HEADERS, demo
from tests.service.api.test_unit_prediction import plant_data
from tests.service.test_api import ADMIN, T0

__all__ = ["demo"]  # the fixture, imported


def assert_unchanged(client: TestClient, method: str, url: str,
                     route: Callable[..., Any], *args: Any, **kwargs: Any) -> dict[str, Any]:
    """The API's answer to ``method url`` is the JSON of what ``route(*args, **kwargs)``
    builds (called with a session and the state, as FastAPI calls it)."""
    answer = client.request(method, url, headers=HEADERS)
    assert answer.status_code == 200, answer.text
    state = client.app.state.loopwatch  # type: ignore[attr-defined]
    with state.store.session() as session:
        built = route(*args, session=session, state=state, _=None, **kwargs)
    assert answer.json() == jsonable_encoder(built)
    body: dict[str, Any] = answer.json()
    return body


@pytest.mark.parametrize(("loop_id", "kind"), [("FIC-101", "stiction"), ("FIC-102", "detuning")])
def test_the_advice_is_unchanged(demo, loop_id, kind) -> None:
    client, _ = demo
    body = assert_unchanged(client, "GET", f"/api/v1/loops/{loop_id}/advice", advice.loop_advice,
                            loop_id)
    assert body["kind"] == kind


def test_the_unit_diagnosis_is_unchanged(demo) -> None:
    client, _ = demo
    for unit in client.get("/api/v1/units", headers=HEADERS).json()["data"]:
        body = assert_unchanged(client, "GET", f"/api/v1/units/{unit['id']}/diagnosis",
                                unit_diagnosis.unit_diagnosis, unit["id"])
        assert body["source"] == "scheduler"


def test_the_model_check_is_unchanged(demo) -> None:
    client, _ = demo
    assert_unchanged(client, "POST", "/api/v1/loops/FIC-101/model-check",
                     model_check.loop_model_check, "FIC-101")


def test_the_cmms_export_and_the_configuration_are_unchanged(demo) -> None:
    client, _ = demo
    state = client.app.state.loopwatch
    with state.store.session() as session:
        ticket_ids = list(session.scalars(select(Ticket.id)))
    assert ticket_ids
    for ticket_id in ticket_ids:
        assert_unchanged(client, "GET", f"/api/v1/tickets/{ticket_id}/cmms", tickets.cmms,
                         ticket_id)
    for loop in client.get("/api/v1/loops", headers=HEADERS).json()["data"]:
        answer = client.get(f"/api/v1/loops/{loop['id']}/config", headers=HEADERS)
        with state.store.session() as session:
            assert answer.json() == loops.get_loop_config(loop["id"], session, None)


def test_the_loop_diagnosis_of_health_is_the_stored_one(demo) -> None:
    client, _ = demo
    state = client.app.state.loopwatch
    for loop in client.get("/api/v1/loops", headers=HEADERS).json()["data"]:
        body = client.get(f"/api/v1/loops/{loop['id']}/health", headers=HEADERS).json()
        if body["latest"] is None:
            continue
        with state.store.session() as session:
            stored = session.get(AnalysisRun, body["latest"]["id"])
            assert stored is not None
            assert body["diagnosis"] == stored.result



def _documented(model: type[BaseModel], part: dict[str, Any]) -> None:
    """Every key of ``part`` is a field of ``model``, in the model's order (the answer's
    key order is the model's: a field declared out of order reorders the JSON)."""
    fields = list(model.model_fields)
    assert [key for key in part if key not in fields] == [], model.__name__
    assert list(part) == [f for f in fields if f in part], model.__name__


def test_the_stored_diagnosis_parts_are_documented_field_by_field(demo) -> None:
    client, _ = demo
    seen = set()
    for loop in client.get("/api/v1/loops", headers=HEADERS).json()["data"]:
        diagnosis = client.get(f"/api/v1/loops/{loop['id']}/health",
                               headers=HEADERS).json()["diagnosis"]
        if diagnosis is None:
            continue
        if diagnosis.get("quantification") is not None:
            _documented(QuantificationPublic, diagnosis["quantification"])
            _documented(ProcessEstimatePublic, diagnosis["quantification"]["process"])
            seen.add("quantification")
        if diagnosis.get("apparent_stiction") is not None:
            _documented(ApparentStictionPublic, diagnosis["apparent_stiction"])
            seen.add("apparent_stiction")
        for window in (diagnosis.get("valve") or {}).get("size_windows") or ():
            _documented(SizeWindowPublic, window)
            seen.add("size_windows")
        if diagnosis.get("manual") is not None:
            _documented(ManualPublic, diagnosis["manual"])
        for issue in diagnosis["quality"]["issues"]:
            _documented(QualityIssuePublic, issue)
            seen.add("issues")
        for oscillation in diagnosis["oscillation"]["oscillations"]:
            _documented(SignalOscillationPublic, oscillation)
            seen.add("oscillations")
        for episode in diagnosis["stiction"]["episodes"]:
            _documented(EpisodePublic, episode)
            seen.add("episodes")
        for evidence in diagnosis["stiction"]["methods"].values():
            _documented(MethodEvidencePublic, evidence)
            seen.add("methods")
    assert seen >= {"quantification", "apparent_stiction", "size_windows", "oscillations",
                    "methods"}



def test_the_unit_diagnosis_groups_are_documented_field_by_field(demo) -> None:
    client, _ = demo
    seen = set()
    for unit in client.get("/api/v1/units", headers=HEADERS).json()["data"]:
        body = client.get(f"/api/v1/units/{unit['id']}/diagnosis", headers=HEADERS).json()
        for group in body["groups"]:
            for member in group["members"]:
                _documented(GroupMemberPublic, member)
                seen.add("members")
            for ranked in group["ranking"]:
                _documented(RankedSignalPublic, ranked)
                seen.add("ranking")
            for evidence in group["evidence"]:
                _documented(LoopEvidencePublic, evidence)
                seen.add("evidence")
            if group["shape_decomposition"] is not None:
                _documented(ShapeDecompositionPublic, group["shape_decomposition"])
                seen.add("shape_decomposition")
    assert seen >= {"members", "ranking", "evidence"}

def test_data_issues_and_the_manual_stretch_pass_through_their_models_unchanged() -> None:
    """What the demo plant's answers lack: a window with data issues, and a run judged on
    a stretch in auto, read as the health route answers (unset fields left out)."""
    rng = np.random.default_rng(3)
    pv = rng.normal(50.0, 1.0, 400)
    pv[100:140] = np.nan
    diagnosis = diagnose_loop(ts=1.0, op=np.round(rng.normal(40.0, 2.0, 400)), pv=pv).to_dict()
    diagnosis["manual"] = ManualStretch(0.25, 1.0e9, 1.0e9 + 299.0, 300, "in manual").to_dict()
    assert diagnosis["quality"]["issues"]
    for issue in diagnosis["quality"]["issues"]:
        _documented(QualityIssuePublic, issue)
    _documented(ManualPublic, diagnosis["manual"])
    answer = LoopDiagnosisPublic.model_validate(diagnosis).model_dump(mode="json",
                                                                       exclude_unset=True)
    assert json.dumps(answer) == json.dumps(jsonable_encoder(diagnosis))

def test_a_tickets_evidence_is_documented_field_by_field(demo) -> None:
    """The stored evidence of each demo ticket, key by key and in order, is what the
    ticket routes answer (its episodes included), and nothing is added to it."""
    client, _ = demo
    state = client.app.state.loopwatch
    with state.store.session() as session:
        stored = {t.id: t.evidence for t in session.scalars(select(Ticket))}
    assert stored
    for ticket_id, evidence in stored.items():
        _documented(TicketEvidence, evidence)
        for episode in evidence["episodes"]:
            _documented(TicketEpisode, episode)
        answer = client.get(f"/api/v1/tickets/{ticket_id}", headers=HEADERS).json()
        assert json.dumps(answer["evidence"]) == json.dumps(jsonable_encoder(evidence))


def _documented_tree(model: type[Schema], part: dict[str, Any]) -> None:
    """:func:`_documented` for ``part`` and, field by field, its nested objects."""
    _documented(model, part)
    for key, value in part.items():
        nested = _schema_of(model.model_fields[key].annotation)
        if isinstance(value, dict) and nested is not None:
            _documented_tree(nested, value)


def _schema_of(annotation: Any) -> type[Schema] | None:
    """The response model in ``annotation`` (``Model`` or ``Model | None``), if any."""
    options = getattr(annotation, "__args__", (annotation,))
    return next((o for o in options if isinstance(o, type) and issubclass(o, Schema)), None)


def test_every_loop_model_the_check_writes_is_documented_field_by_field() -> None:
    """The model check's base and extended models: the true models of the hidden-effect
    cases carry each extension (direction and zone friction, characteristic, load,
    quantiser), on self-regulating and integrating processes."""
    seen = set()
    for effect, seed in itertools.product(["none", *EFFECTS], (0, 1)):
        case = hidden_effect_case(effect, seed, samples=600)
        for model in (case.base_model, case.true_model):
            if model is None:
                continue
            spec = model.to_dict()
            _documented_tree(LoopModelPublic, spec)
            answer = LoopModelPublic.model_validate(spec).model_dump(exclude_unset=True)
            assert json.dumps(answer) == json.dumps(spec)
            seen |= {*spec, *spec["valve"], spec["process"]["type"]}
    assert seen >= {"load", "measurement", "opening", "closing", "zone", "characteristic",
                    "fs", "S", "fopdt", "integrating"}


@pytest.fixture
def unit_client(tmp_path) -> Iterator[TestClient]:
    """The units of :func:`tests.service.api.test_unit_prediction.plant_data` on SQLite."""
    settings = Settings(database_url=f"sqlite:///{tmp_path / 'p.db'}", api_key=ADMIN)
    svc = build_service(settings, PlantConfig.model_validate(plant_data()),
                        executor=ThreadPoolExecutor(1), clock=lambda: T0)
    yield TestClient(svc.app)
    svc.executor.shutdown()
    svc.state.store.close()


def test_the_prediction_is_unchanged(unit_client) -> None:
    store_run(unit_client, "TIC-3", "no_stiction")
    none = assert_unchanged(unit_client, "GET", "/api/v1/units/u3/prediction",
                            unit_prediction.unit_prediction, "u3")
    assert none["limit_cycles"] == [] and "linear_stable" not in none
    store_run(unit_client, "TIC-1", "stiction", {"S": 4.0, "J": 2.0, "fs": 3.0, "fd": 1.0})
    store_run(unit_client, "FIC-2", "undecided", {"fs": 3.0, "fd": 1.0})
    body = assert_unchanged(unit_client, "GET", "/api/v1/units/u1/prediction",
                            unit_prediction.unit_prediction, "u1")
    assert body["limit_cycles"] and body["comparison"] is not None


def test_every_answer_of_the_api_has_a_named_schema_or_is_a_file(unit_client) -> None:
    schema = openapi_with_json_errors(unit_client.app)  # type: ignore[arg-type]
    unnamed = []
    for path, operations in schema["paths"].items():
        for method, operation in operations.items():
            for status, response in operation["responses"].items():
                if not status.startswith("2"):
                    continue
                for media_type, content in response.get("content", {}).items():
                    body = content.get("schema", {})
                    named = "$ref" in body or (media_type == "application/json" and all(
                        "$ref" in option for option in body.get("oneOf", [None])))
                    if not (named or body.get("type") == "string"):
                        unnamed.append(f"{method.upper()} {path} {status} {media_type}")
    assert unnamed == []
