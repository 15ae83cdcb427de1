"""Model check of a loop on its current window: ``POST /api/v1/loops/{id}/model-check``.

Runs :func:`analytics.model_check.check_model` (issue 8) on the loop's
latest window (``LOOPWATCH_WINDOW_S``; from the store on an API replica), in % of
span as the analysis sees it, with the base model of the request body or,
without one, a model identified from the window.  The answer is the JSON of
``loopwatch model-check --json`` plus the measured-versus-simulated PV
overlay for the dashboard, stamped with the window's times.
"""

from __future__ import annotations

import dataclasses
from typing import Annotated, Any

import numpy as np
from fastapi import APIRouter, Body, HTTPException
from numpy.typing import NDArray
from pydantic import BaseModel, Field

from analytics.errors import AnalyticsError
from analytics.model_check import MIN_SAMPLES, LoopModel, check_model
from service.analysis import to_percent_of_span
from service.api.deps import (
    ERROR_RESPONSES,
    Analyst,
    SessionDep,
    StateDep,
    error_responses,
)
from service.api.schemas.model_check import ModelCheckPublic
from service.config import LoopConfig
from service.store.models import Loop

router = APIRouter(prefix="/api/v1", tags=["model check"],
                   responses={**ERROR_RESPONSES, **error_responses(404)})

EXAMPLE_MODEL = {
    "dt": 1.0, "op_bias": 50.0,
    "process": {"type": "fopdt", "K": 1.2, "tau": 20.0, "theta": 4.0},
    "controller": {"type": "PI", "Kc": 0.8, "Ti": 20.0},
    "valve": {"model": "he", "fs": 3.0, "fd": 1.0},
}


class ModelCheckRequest(BaseModel):
    """What to check: the base model, or nothing to identify one from the window."""

    model: dict[str, Any] | None = Field(
        default=None,
        description="Base model JSON of issue 8 (as for `loopwatch model-check --model`), "
                    "in % of span; absent or null: identified from the window first.",
        examples=[EXAMPLE_MODEL],
    )


def _longest_complete_stretch(signals: list[NDArray[np.float64]]) -> tuple[int, int]:
    """``(start, stop)`` of the longest run of samples where every signal is finite."""
    complete = np.logical_and.reduce([np.isfinite(x) for x in signals])
    edges = np.flatnonzero(np.diff(np.concatenate([[0], complete.astype(np.int8), [0]])))
    if edges.size == 0:
        return 0, 0
    starts, stops = edges[::2], edges[1::2]
    longest = int(np.argmax(stops - starts))
    return int(starts[longest]), int(stops[longest])


def _check(op: NDArray[np.float64], pv: NDArray[np.float64], t: NDArray[np.float64],
           ts: float, sp: NDArray[np.float64] | None, model: LoopModel | None
           ) -> dict[str, Any]:
    """The model check and its overlay as JSON (run in the analysis process), the overlay
    stamped with the samples' times ``t``."""
    check = check_model(op, pv, ts, sp=sp, model=model)
    stamped = dataclasses.replace(check, overlay=dataclasses.replace(check.overlay, t=t))
    return stamped.to_dict(overlay=True)


@router.post("/loops/{loop_id}/model-check", response_model=ModelCheckPublic,
             response_model_exclude_unset=True)
def loop_model_check(
    loop_id: str,
    session: SessionDep,
    state: StateDep,
    _: Analyst,
    request: Annotated[ModelCheckRequest | None, Body()] = None,
) -> dict[str, Any]:
    """What the simulation of the loop gets wrong, the cause, the extended model, the gain.

    A plain ``def`` (FastAPI's thread pool) waiting for the check in the analysis
    process (:meth:`service.runtime.AppState.analyse`).  The model is checked on
    the longest stretch of the current window where OP, PV (and SP, when the
    loop has one) are all present.  404 for an
    unknown loop or one without samples in its window; 422 with the reason
    for an invalid model, a loop without OP or PV, or too little complete data.
    """
    loop = session.get(Loop, loop_id)
    if loop is None:
        raise HTTPException(404, "Loop not found")
    spec = request.model if request is not None else None
    try:
        model = None if spec is None else LoopModel.from_dict(spec)
    except AnalyticsError as exc:
        raise HTTPException(422, f"Invalid base model: {exc}") from None
    now, window_s = state.clock(), state.settings.window_s
    config = LoopConfig.model_validate(loop.config)
    window = state.buffers_for(session, [config], window_s, now).window(loop_id, window_s, now)
    ranges = loop.config.get("ranges") or {}
    if "pv" in ranges:
        ranges = {"sp": ranges["pv"], **ranges}  # the set point is in PV units
    scaled = {name: to_percent_of_span(x, tuple(ranges[name]) if name in ranges else None)
              for name, x in window.signals.items()}
    op, pv, sp = scaled.get("op"), scaled.get("pv"), scaled.get("sp")
    if op is None or pv is None:
        raise HTTPException(422, f"A model check needs OP and PV; loop {loop_id} has no "
                                 f"{'OP' if op is None else 'PV'} tag")
    if not (np.isfinite(op).any() and np.isfinite(pv).any()):
        raise HTTPException(404, f"Loop {loop_id} has no OP and PV samples in its window")
    signals = [x for x in (op, pv, sp) if x is not None]
    start, stop = _longest_complete_stretch(signals)
    if stop - start < MIN_SAMPLES:
        names = "OP, PV and SP" if sp is not None else "OP and PV"
        raise HTTPException(
            422, f"A model check needs at least {MIN_SAMPLES} consecutive samples with "
                 f"{names} present; the current window of loop {loop_id} "
                 f"({window.t.size} samples at {window.ts:g} s) has {stop - start}")
    part = slice(start, stop)
    try:
        out = state.analyse(_check, op[part], pv[part], window.t[part], window.ts,
                            None if sp is None else sp[part], model)
    except AnalyticsError as exc:
        raise HTTPException(422, f"Model check not possible: {exc}") from None
    return {"loop_id": loop_id, "window_start": float(window.t[start]),
            "window_end": float(window.t[stop - 1]), "ts": window.ts, "samples": stop - start,
            **out}
