"""Analysis runs written straight into the store, for the answers of the routes to
results the scheduler would need long simulated windows to produce."""

from __future__ import annotations

from typing import Any

from fastapi.testclient import TestClient

from service.store.models import AnalysisRun
from tests.service.test_api import T0


def store_run(client: TestClient, loop_id: str, verdict: str,
              estimate: dict[str, Any] | None = None, *,
              window: tuple[float, float] | None = None, **result: Any) -> int:
    """A finished analysis of ``loop_id`` with a stiction verdict and estimate (the
    result's ``quantification``), the other fields of its result, and the window it
    diagnosed (none unless given); its id."""
    state = client.app.state.loopwatch  # type: ignore[attr-defined]
    start, end = window if window is not None else (None, None)
    with state.store.session() as session:
        run = AnalysisRun(loop_id=loop_id, started_at=T0, finished_at=T0, status="ok",
                          verdict=verdict, window_start=start, window_end=end,
                          result={"quantification": estimate, **result})
        session.add(run)
        session.flush()
        return int(run.id)
