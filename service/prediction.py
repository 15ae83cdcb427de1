"""Limit-cycle prediction of a model given as JSON, shared by the CLI and the API.

The model holds ``dt`` (the controllers' sampling period, s; its hold counts
as ``dt/2`` of dead time), ``process`` (one transfer function or
``{"matrix": n x n}``), ``controllers`` and ``valves`` (one per loop), and
optionally anything else :class:`analytics.simulation.ClosedLoopModel` reads.
The describing-function prediction (:func:`analytics.limit_cycle.predict_model`)
is checked against a simulation of the same model
(:func:`analytics.limit_cycle.compare`); errors name the place in the model.
"""

from __future__ import annotations

import math
from typing import Any

from analytics.errors import AnalyticsError
from analytics.limit_cycle import LimitCycleReport, compare, predict_model
from analytics.lti import TransferFunction
from analytics.simulation import ClosedLoopModel, PIDController
from analytics.tuning import excited_model
from analytics.valves import valve_from_dict

__all__ = ["ModelError", "check_matrix", "check_model", "predict_spec"]


class ModelError(ValueError):
    """The model cannot be predicted; the message names the place and the reason."""


#: Simulated periods of the slowest predicted cycle when the model gives no duration
#: (a cycle can take tens of periods to build up from a setpoint step).
PERIODS_SIMULATED = 200
#: Shortest simulation without a duration in the model, s.
MIN_DURATION = 2000.0
#: Longest simulation without a duration in the model, samples.
MAX_SAMPLES = 2_000_000


def _located(where: str, build: Any, spec: Any) -> Any:
    """``build(spec)``, with ``where`` in front of any error message."""
    try:
        return build(spec)
    except AnalyticsError as exc:
        raise ModelError(f"{where}: {exc}") from None


def _per_loop(spec: dict[str, Any], key: str, n: int) -> list[Any]:
    items = spec.get(key)
    if not isinstance(items, list) or len(items) != n:
        got = "nothing" if items is None else repr(items)
        raise ModelError(f"'{key}' must be a list with one entry per loop ({n}), got {got}")
    return items


def check_matrix(matrix: Any, where: str = "process.matrix") -> int:
    """Validate an n x n process matrix (entries as in the model file) and return n.

    Row ``i`` holds the transfer functions from every valve to the PV of loop
    ``i``; null is no coupling, but never on the diagonal.

    Raises
    ------
    ModelError
        Naming the place, e.g. ``process.matrix[2][1]: missing key 'tau' for
        model type 'fopdt'``, or a non-square matrix.
    """
    if not isinstance(matrix, list) or not matrix or not all(isinstance(r, list) for r in matrix):
        raise ModelError(f"{where} must be a list of rows (lists)")
    n = len(matrix)
    for i, row in enumerate(matrix):
        if len(row) != n:
            raise ModelError(
                f"{where} must be square ({n} x {n}, one row and column per "
                f"loop): row {i + 1} has {len(row)} entries"
            )
        for j, entry in enumerate(row):
            place = f"{where}[{i + 1}][{j + 1}]"
            if entry is None:
                if i == j:
                    raise ModelError(f"{place} is null: loop {i + 1} has no effect on its PV")
                continue
            if not isinstance(entry, dict):
                raise ModelError(f"{place} must be a transfer function object or null")
            _located(place, TransferFunction.from_dict, entry)
    return n


def check_model(spec: Any) -> None:
    """Validate the keys ``predict`` needs, naming the place of every error.

    Raises
    ------
    ModelError
        E.g. ``process.matrix[2][1]: missing key 'tau' for model type 'fopdt'``,
        a non-square matrix, a missing diagonal entry, a missing controller
        parameter.
    """
    if not isinstance(spec, dict):
        raise ModelError("a model must be a JSON object")
    for key in ("dt", "process", "controllers", "valves"):
        if key not in spec:
            raise ModelError(f"the model lacks the required key '{key}'")
    process = spec["process"]
    if isinstance(process, dict) and "matrix" in process:
        n = check_matrix(process["matrix"])
    elif isinstance(process, dict):
        n = 1
        _located("process", TransferFunction.from_dict, process)
    else:
        raise ModelError("process must be a transfer function object or {'matrix': [...]}")
    for i, controller in enumerate(_per_loop(spec, "controllers", n)):
        _located(f"controllers[{i + 1}]", PIDController.from_dict, controller)
    for i, valve in enumerate(_per_loop(spec, "valves", n)):
        _located(f"valves[{i + 1}]", valve_from_dict, valve)


def predict_spec(
    spec: Any,
    *,
    source: str = "model",
    omega_range: tuple[float, float] | None = None,
    duration: float | None = None,
) -> tuple[ClosedLoopModel, LimitCycleReport]:
    """The model ``spec``, predicted and simulated (see the module notes).

    Without a duration the simulation runs for :data:`PERIODS_SIMULATED`
    periods of the slowest predicted cycle (at least :data:`MIN_DURATION`).

    Raises
    ------
    ModelError
        A bad model (prefixed with ``source``), or a loop unstable without
        stiction.
    """
    try:
        check_model(spec)
    except ModelError as exc:
        raise ModelError(f"{source}: {exc}") from None
    model: ClosedLoopModel = _located(source, ClosedLoopModel.from_dict, spec)
    if duration is not None and not (math.isfinite(duration) and duration > 0):
        raise ModelError(f"--duration must be > 0 s, got {duration}")
    try:
        prediction = predict_model(model, omega_range=omega_range)
    except AnalyticsError as exc:
        raise ModelError(f"{source}: {exc}") from None
    if not prediction.linear_stable:
        raise ModelError(
            f"{source}: unstable without stiction, so no limit cycle: {prediction.note}"
        )
    if duration is None and "duration" not in spec:
        slowest = max((c.period_s for c in prediction.limit_cycles), default=0.0)
        duration = min(max(MIN_DURATION, PERIODS_SIMULATED * slowest), MAX_SAMPLES * model.dt)
    excited = excited_model(model, duration=duration or model.duration)
    return model, compare(excited, prediction=prediction)


