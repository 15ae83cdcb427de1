"""The limit cycles of a unit (``GET /api/v1/units/{id}/prediction``):
:meth:`analytics.limit_cycle.LimitCycleReport.to_dict` with where each valve comes from."""

from __future__ import annotations

from typing import Literal

from service.api.schemas.advice import CycleAgreementPublic, ValveFitPublic
from service.api.schemas.base import Schema


class ChoudhuryValve(Schema):
    """A sticky valve of the estimated stick band and slip jump (Choudhury model)."""

    model: Literal["choudhury"]
    S: float
    """Stick band plus deadband, % of valve span."""
    J: float
    """Slip jump, % of valve span."""


class HeValve(Schema):
    """A sticky valve of the estimated static and dynamic friction (He model)."""

    model: Literal["he"]
    fs: float
    """Static friction, % of valve span."""
    fd: float
    """Dynamic friction, % of valve span."""


class KanoValve(Schema):
    """A sticky valve of the estimated stick band and slip jump (Kano model)."""

    model: Literal["kano"]
    S: float
    """Stick band plus deadband, % of valve span."""
    J: float
    """Slip jump, % of valve span."""


class ValveSource(Schema):
    """Where a loop's valve in the model comes from."""

    loop: str
    run_id: int | None
    """The loop's latest analysis run; null if it was not analysed yet."""
    verdict: str | None
    """That run's stiction verdict."""
    valve: ChoudhuryValve | HeValve | KanoValve | None
    """The sticky valve of the run's stiction estimate (the estimate's valve model at the
    size combined over the valve's windows); null: a healthy valve."""
    cleared_by_unit_run: int | None = None
    """Present when the unit's diagnosis cleared the valve: that unit run."""


class LimitCyclePublic(Schema):
    """One solution of the harmonic balance (:class:`analytics.limit_cycle.LimitCycle`)."""

    omega: float
    """Frequency, rad/s."""
    period_s: float
    """Period ``2 pi / omega``, s."""
    amplitudes: list[float | None]
    """OP amplitude ``A`` of ``N(A)`` of each loop with a sticky valve, % of travel; null
    for healthy valves."""
    stable: bool
    """The cycle attracts: only stable cycles are observed in a plant."""
    residual: float
    """``|(I + P(jw) N(A)) x| / |x|`` at the solution, ``x`` the OP phasors."""
    op_amplitudes: list[float]
    """Predicted OP amplitude of every loop, healthy ones included, % of travel."""
    moving: list[bool]
    """Whether each valve moves (a sticky valve whose OP amplitude stays below its
    threshold stays stuck)."""
    at_band_edge: bool
    """The solution lies at the end ``A -> S/2`` of the ``-1/N`` curve, where the valve
    only just moves."""


class SimulatedCyclePublic(Schema):
    """The steady oscillation at the end of a closed-loop simulation
    (:class:`analytics.limit_cycle.SimulatedLimitCycle`)."""

    oscillating: bool
    """At least one loop's OP oscillates regularly with a steady amplitude."""
    period_s: float | None
    """Period, s: that of the sticky loop with the largest OP amplitude."""
    amplitudes: list[float | None]
    """Fundamental amplitude of each loop's OP at its own period, % of travel; null for a
    loop that does not oscillate."""
    half_ranges: list[float | None]
    """``(max - min) / 2`` of each OP in the window (null if it diverges)."""
    periods_s: list[float | None]
    """Period of each loop's OP, s."""
    window_s: list[float]
    """Time window analysed, s (start, end)."""
    note: str
    """"diverges", "growing", "decaying" or empty."""


class ComparisonPublic(Schema):
    """The describing-function prediction against the simulation."""

    agree: bool
    """Prediction and simulation agree on whether the loops oscillate, and (when the unit
    has a diagnosis) the model reproduces the measured cycle: period within 15 % in
    prediction and simulation, or no cycle where none was measured."""
    matched_omega: float | None
    """Frequency of the stable predicted cycle closest in period to the simulated one,
    rad/s."""
    period_error_pct: float | None
    """``100 (T_DF - T_sim) / T_sim``."""
    amplitude_error_pct: list[float | None]
    """Per loop with a sticky valve, ``100 (A_DF - A_sim) / A_sim``; null elsewhere."""
    measured_cycle: CycleAgreementPublic | None = None
    """The model's cycle against the one the unit's latest diagnosis measured in the first
    sticky loop (absent from ``loopwatch predict``, which has no measurement)."""


class UnitPrediction(Schema):
    """The unit's stiction limit cycles predicted by the describing function (thesis Eqs.
    3.11-3.14) beside the simulated cycle of the same model.  Without a sticky valve,
    ``limit_cycles`` is empty, ``simulated`` and ``comparison`` are null and ``note``
    says why."""

    unit_id: str
    loops: list[str]
    """The loops of the unit's process matrix, in its order."""
    dt: float
    """Sampling interval the model is predicted and simulated at, s."""
    valves: list[ValveSource]
    """Each loop's valve and where it comes from."""
    unknown: list[str]
    """What was assumed."""
    limit_cycles: list[LimitCyclePublic]
    """Every solution found, sorted by frequency; empty when the linear loops are
    unstable."""
    linear_stable: bool | None = None
    """The loops are stable with every valve healthy (absent without a sticky valve)."""
    omega_range: list[float] | None = None
    """Frequencies searched, rad/s (absent without a sticky valve)."""
    note: str
    """Why nothing was predicted, or how the describing function was obtained."""
    simulated: SimulatedCyclePublic | None
    comparison: ComparisonPublic | None
    valve_fit: ValveFitPublic | None = None
    """The first sticky valve's estimate simulated in the unit's model against the measured
    cycle, and fitted to it (:func:`analytics.cycle_fit.fit_valve_to_cycle`): the
    prediction uses the chosen valve.  Absent without a measured cycle."""
    describing_note: str | None = None
    """Present when the harmonic balance cannot give the measured period with any size of
    that valve, and why."""
