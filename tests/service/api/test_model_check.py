"""``POST /api/v1/loops/{id}/model-check`` (service.api.routes.model_check).

A loop with a known hidden effect (analytics.model_check.cases) is ingested
into FIC-1 of the test plant; the route checks the loop's current window.
The route does not depend on the store beyond the loop's configuration, so
these tests run on SQLite only.
"""

from __future__ import annotations

from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest
from fastapi.testclient import TestClient

from analytics.model_check.cases import HiddenEffectCase, hidden_effect_case
from service.buffer import LoopBuffers
from service.config import Settings
from service.server import build_service
from tests.service.test_api import ADMIN, T0, key, plant

SAMPLES = 3000
"""Samples ingested: the last 3000 s of the 3600 s window (the first 600 s are empty)."""

URL = "/api/v1/loops/{}/model-check"
HEADERS = {"X-API-Key": ADMIN}


@pytest.fixture(scope="module")
def gain_case() -> HiddenEffectCase:
    return hidden_effect_case("gain_mismatch", 3, samples=SAMPLES)


def case_batch(case: HiddenEffectCase, loop_id: str = "FIC-1",
               pv_span: tuple[float, float] = (0.0, 100.0)) -> list[dict]:
    """The case's SP, OP and PV as an ingest batch ending at T0 (PV, SP in engineering
    units of ``pv_span``)."""
    t = T0 - case.op.size + 1 + np.arange(case.op.size)
    low, high = pv_span
    signals = {"OP": case.op, "PV": low + case.pv * (high - low) / 100.0,
               "SP": low + case.sp * (high - low) / 100.0}
    return [{"tag": f"{loop_id}.{name}",
             "items": [{"timestamp": float(a), "value": float(b)}
                       for a, b in zip(t, values, strict=True)]}
            for name, values in signals.items()]


@pytest.fixture
def client(tmp_path, gain_case) -> Iterator[TestClient]:
    """The two-loop test plant on SQLite, FIC-1 fed with the gain-mismatch case."""
    svc = build_service(
        Settings(database_url=f"sqlite:///{tmp_path / 'loopwatch.db'}", api_key=ADMIN,
                 window_s=3600, buffer_horizon_s=7200),
        plant(), executor=ThreadPoolExecutor(1), clock=lambda: T0)
    svc.state.ingest(case_batch(gain_case))
    yield TestClient(svc.app)
    svc.executor.shutdown()
    svc.state.store.close()


def test_given_model_is_checked_on_the_window(client, gain_case) -> None:
    response = client.post(URL.format("FIC-1"), json={"model": gain_case.base_model.to_dict()},
                           headers=HEADERS)
    assert response.status_code == 200, response.text
    out = response.json()
    assert out["loop_id"] == "FIC-1"
    assert out["samples"] == SAMPLES  # the complete stretch of the window
    assert out["window_end"] == T0 and out["window_start"] == T0 - SAMPLES + 1
    assert out["model_source"] == "given"
    assert out["cause"]["effect"] == "gain_mismatch"
    assert out["cause"]["parameters"]["K"] == pytest.approx(
        gain_case.true_model.process.K, rel=0.03)
    assert out["gain"]["nmse_after"] < out["gain"]["nmse_before"] == out["baseline"]["nmse"]
    assert out["causes"][0] == out["cause"] and out["cause"]["runner_up"] != "gain_mismatch"
    overlay = out["overlay"]
    assert overlay["t"][0] == out["window_start"] and overlay["t"][-1] == T0
    assert len(overlay["pv"]) == len(overlay["pv_base"]) == len(overlay["pv_extended"]) == SAMPLES
    np.testing.assert_allclose(overlay["pv"], gain_case.pv, atol=1e-9)


def test_engineering_units_are_converted_to_percent_of_span(tmp_path, gain_case) -> None:
    # PV configured over 0-40 (the model is in % of span, as the analysis sees the loop)
    config = plant().model_dump(mode="json")
    config["loops"][0]["ranges"]["pv"] = [0.0, 40.0]
    svc = build_service(
        Settings(database_url=f"sqlite:///{tmp_path / 'units.db'}", api_key=ADMIN,
                 window_s=3600, buffer_horizon_s=7200),
        type(plant()).model_validate(config), executor=ThreadPoolExecutor(1), clock=lambda: T0)
    try:
        svc.state.ingest(case_batch(gain_case, pv_span=(0.0, 40.0)))
        response = TestClient(svc.app).post(
            URL.format("FIC-1"), json={"model": gain_case.base_model.to_dict()}, headers=HEADERS)
        assert response.status_code == 200, response.text
        out = response.json()
        assert out["cause"]["effect"] == "gain_mismatch"
        np.testing.assert_allclose(out["overlay"]["pv"], gain_case.pv, atol=1e-6)
    finally:
        svc.executor.shutdown()
        svc.state.store.close()


def test_without_a_model_one_is_identified(client) -> None:
    response = client.post(URL.format("FIC-1"), headers=HEADERS)
    assert response.status_code == 200, response.text
    out = response.json()
    assert out["model_source"] == "identified"
    assert any("identified" in note for note in out["notes"])
    assert out["cause"]["effect"] in {c["effect"] for c in out["candidates"]} | {"none"}
    assert out["findings"][0].startswith("Driven by the measured OP, the model misses")


@pytest.mark.parametrize(
    ("loop_id", "body", "status", "detail"),
    [
        ("NOPE", {}, 404, "Loop not found"),
        ("FIC-2", {}, 404, "Loop FIC-2 has no OP and PV samples in its window"),
        ("FIC-1", {"model": {"dt": 1}}, 422,
         "Invalid base model: the model lacks the key(s) 'process', 'controller'"),
        ("FIC-1", {"model": {"dt": 1, "process": {"type": "fopdt", "K": 1, "tau": 1e300},
                             "controller": {"Kc": 1}}}, 422,
         "Model check not possible: process tau = 1e+300 s is more than 1e+06 times the "
         "record (3000 s): the data cannot check such a model"),
    ],
)
def test_refusals_say_why(client, loop_id, body, status, detail) -> None:
    response = client.post(URL.format(loop_id), json=body, headers=HEADERS)
    assert (response.status_code, response.json()) == (status, {"detail": detail})


def test_keys_and_a_loop_without_a_pv_tag(client) -> None:
    anonymous = client.post(URL.format("FIC-1"))
    assert (anonymous.status_code, anonymous.json()) == (
        401, {"detail": "Missing API key (header X-API-Key)"})
    refused = client.post(URL.format("FIC-1"), headers=key(client, "historian"))
    assert (refused.status_code, refused.json()) == (
        403, {"detail": "Role 'historian' may not read"})
    body = {"ts": 1.0, "tags": {"op": "FIC-9.OP"}}
    assert client.put("/api/v1/loops/FIC-9", json=body, headers=HEADERS).status_code == 200
    answer = client.post(URL.format("FIC-9"), headers=HEADERS)
    assert (answer.status_code, answer.json()) == (
        422, {"detail": "A model check needs OP and PV; loop FIC-9 has no PV tag"})


def test_a_window_with_too_few_complete_samples_is_refused(tmp_path, gain_case) -> None:
    svc = build_service(
        Settings(database_url=f"sqlite:///{tmp_path / 'short.db'}", api_key=ADMIN,
                 window_s=3600, buffer_horizon_s=7200),
        plant(), executor=ThreadPoolExecutor(1), clock=lambda: T0)
    try:
        batch = case_batch(hidden_effect_case("none", 0, samples=1000))
        pv = next(entry for entry in batch if entry["tag"] == "FIC-1.PV")
        del pv["items"][700]  # a gap: complete stretches of 700 and 299 samples
        del pv["items"][:450]  # now 250 and 299
        svc.state.ingest(batch)
        response = TestClient(svc.app).post(URL.format("FIC-1"), headers=HEADERS)
        assert response.status_code == 422
        assert response.json()["detail"] == (
            "A model check needs at least 300 consecutive samples with OP, PV and SP present; "
            "the current window of loop FIC-1 (3600 samples at 1 s) has 299"
        )
    finally:
        svc.executor.shutdown()
        svc.state.store.close()


def test_an_api_replica_checks_the_same_window_from_the_store(client) -> None:
    """A replica of ``--role api`` keeps no rolling buffers: it reads the window from the
    store, and the check comes out the same."""
    buffered = client.post(URL.format("FIC-1"), headers=HEADERS)
    client.app.state.loopwatch.buffers = LoopBuffers(plant(), horizon_s=7200)
    assert not client.app.state.loopwatch.buffers.holds_samples("FIC-1")
    stored = client.post(URL.format("FIC-1"), headers=HEADERS)
    assert buffered.status_code == stored.status_code == 200, stored.text
    assert stored.json() == buffered.json()
