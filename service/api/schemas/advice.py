"""Tuning advice (``GET /api/v1/loops/{id}/advice``): :meth:`analytics.tuning.TuningAdvice.to_dict`
with the measured cycle for a sticky valve, :func:`analytics.tuning.detune` for a loop that
cycles with a healthy valve."""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import Field

from analytics.tuning import Action, Control, Outcome, ProcessType
from service.api.schemas.base import Schema


class TuningPublic(Schema):
    """A P or PI tuning (:class:`analytics.tuning.Tuning`)."""

    Kc: float
    """Controller gain (%/% of span)."""
    Ti: float | None
    """Integral time, s; null for P control."""


class OscillationEffectPublic(Schema):
    """An oscillation as predicted (describing function) or simulated
    (:class:`analytics.tuning.OscillationEffect`)."""

    oscillating: bool
    """A stable limit cycle is predicted, or the simulation cycles."""
    period_s: float | None
    """Period of that cycle, s."""
    amplitudes: list[float | None]
    """OP amplitude per loop, % of travel (null where a loop's OP does not cycle or,
    predicted, where the valve is healthy)."""
    travel_rate: float | None
    """Valve travel per second of the sticky loops, ``sum 4 A_k / T`` (% per s): 0 without
    a cycle, null (infinite) if the loop is unstable."""
    note: str
    """"unstable", "diverges", or the simulation's note."""


class RecommendationPublic(Schema):
    """A retune with its predicted and its simulated effect
    (:class:`analytics.tuning.Recommendation`)."""

    tunings: list[TuningPublic]
    """New tuning of every loop (unchanged loops repeat their current one)."""
    source: str
    """Where the candidate comes from: a Table 5.11 action, the safe-tuning map, or the
    section 5.6 search."""
    predicted: OscillationEffectPublic
    """Describing-function prediction."""
    simulated: OscillationEffectPublic
    """Verification by simulation."""
    outcome: Outcome
    """Judged on the simulation against the current tuning's: "removed" if it no longer
    cycles, "reduced" if its valve travel rate falls enough."""
    max_sensitivity: float | None
    """``Ms`` of the retuned loop (single loop only; null when unstable)."""
    travel_rate_with_noise: float | None = None
    """Valve travel of the sticky loops (% per s) in a simulation with the measured PV
    noise; null when the noise was not known (analyses stored before it was kept)."""
    load_error_ratio: float | None = None
    """The error a load step at a valve leaves, against the current tuning's (integrated
    error ``Ti / |Kc|`` under PI, the offset under P; the largest over the loops)."""


class FirstOrderProcessPublic(Schema):
    """The first-order process of chapter 5: ``K e^-theta s / (tau s + 1)`` or
    ``K e^-theta s / s``."""

    kind: ProcessType
    """Self-regulating or integrating."""
    K: float
    """Process gain (%/% of span; per s for an integrating process)."""
    tau: float | None
    """Time constant, s; null for an integrating process."""
    theta: float
    """Dead time, s (the sample-and-hold delay included)."""


class TuningRulePublic(Schema):
    """One row of thesis Table 5.11: what stiction does and which retune helps."""

    dynamics: str
    """The row's dynamics, e.g. "SR & PI, dead time"."""
    deadband_oscillation: str
    """Whether a deadband makes the loop cycle ("no", "yes", "maybe, if ...")."""
    stiction_oscillation: str
    """Whether stiction makes the loop cycle ("no", "yes", "maybe, if ...")."""
    actions: list[Action]
    """Recommended changes in the table's order."""
    new_oscillation: list[str]
    """Expected result of each action: "no" (removed) or "reduced"."""


class SingleLoopAnalysisPublic(Schema):
    """The chapter 5 analysis of one loop at its current tuning
    (:class:`analytics.tuning.SingleLoopAnalysis`)."""

    process: FirstOrderProcessPublic
    control: Control
    """P or PI."""
    Kc: float
    """Controller gain (modulus)."""
    Ti: float | None
    """Integral time, s; null for P control."""
    omega_f: float | None
    """``w*`` (rad/s) of the point F (thesis Eqs. 5.16, 5.18)."""
    f_imag: float | None
    """Imaginary part of ``G Gc`` at ``w*``."""
    omega_h: float | None
    """``w**`` (rad/s) of the point H (thesis Eqs. 5.17, 5.19)."""
    h_real: float | None
    """Real part of ``G Gc`` at ``w**``."""
    low_frequency_real: float | None
    """``lim Re G Gc`` for ``w -> 0`` (null: minus infinity); ``d`` of Eq. 5.24 is its
    modulus."""
    band_edge_imag: float | None
    """``-pi S / (4 J)``, where ``-1/N`` starts (Table 5.1); null for a deadband or a valve
    without an (S, J) equivalent."""
    rule: TuningRulePublic
    """The row of Table 5.11."""
    thesis_oscillation: bool | None
    """Whether the chapter's conditions predict a stiction cycle; null where the chapter
    leaves it open ("maybe")."""
    thesis_linear_stable: bool
    """The chapter's test ``H_real > -1`` (section 5.3.2)."""
    linear_stable: bool
    """The Nyquist count of the loop with a healthy valve (rigorous)."""
    df_oscillation: bool
    """Whether the describing function predicts a stable limit cycle."""


class SafeTuningMapPublic(Schema):
    """Thesis Fig. 5.17 over a ``Kc x Ti`` grid (rows: ``Kc``)."""

    Kc: list[float]
    """Controller gains (moduli; the sign follows the controller action)."""
    Ti: list[float | None]
    """Integral times, s; ``[null]`` for P control."""
    linear_stable: list[list[bool]]
    """The loop is stable with a healthy valve (bottom of Fig. 5.17)."""
    limit_cycle_free: list[list[bool]]
    """``G Gc`` does not meet ``-1/N(A)``: no stiction limit cycle (top); false where the
    linear loop is unstable."""
    max_sensitivity: list[list[float | None]]
    """``Ms = max_w 1/|1 + G Gc|``; null where unstable."""
    omega: list[list[float | None]]
    """Frequency (rad/s) of the predicted stable cycle; null without one."""
    amplitude: list[list[float | None]]
    """OP amplitude (% of travel) of the predicted stable cycle; null without one."""


class MeasuredCyclePublic(Schema):
    """The loop's cycle as the diagnosis measured it."""

    period_s: float | None
    """Period, s."""
    amplitude: float | None
    """OP amplitude (first harmonic), % of span."""


class ModelErrorsPublic(Schema):
    """``(model - measured) / measured``, of the prediction and of the simulation; null
    where a side has no cycle."""

    predicted: float | None
    simulated: float | None


class CycleAgreementPublic(Schema):
    """The model's cycle at the current tuning against the measured one
    (:class:`analytics.tuning.CycleAgreement`): advice is only as good as its model."""

    measured: MeasuredCyclePublic
    period_error: ModelErrorsPublic
    amplitude_error: ModelErrorsPublic
    reproduces: bool
    """The simulated model cycles as the loop does (period and OP amplitude within the
    tolerances)."""
    agree: bool
    """The simulation reproduces the cycle and the describing function its period."""
    explanation: str
    """What agrees and what does not, in words."""


class FittedValvePublic(Schema):
    """One valve simulated in the loop model (:class:`analytics.cycle_fit.FittedValve`)."""

    valve_model: Literal["he", "kano", "choudhury"]
    """He's (fs = (S + J) / 2, fd = (S - J) / 2), Kano's or Choudhury's valve."""
    S: float
    """Stick band plus deadband, % of travel."""
    J: float
    """Slip jump, % of travel."""
    period_s: float | None
    """Period of its simulated cycle, s; null when the simulated loop comes to rest."""
    amplitude: float | None
    """OP amplitude of that cycle (first harmonic), % of span."""
    period_error: float | None
    """``(model - measured) / measured``; null without a cycle."""
    amplitude_error: float | None
    reproduces: bool
    """Period and OP amplitude within the tolerances."""


class ValveFitPublic(Schema):
    """The estimate's valve checked in the loop model against the measured cycle, and the
    valve fitted to that cycle (:class:`analytics.cycle_fit.CycleFit`); the advice is
    computed on the chosen one."""

    measured: MeasuredCyclePublic
    cause: Literal["none", "valve_model", "valve_size", "process"]
    """What the check found wrong: nothing, the valve model (He, Kano, Choudhury), its
    size, or (no valve within the estimate's intervals reproduces the cycle) the process,
    whose dead time is then fitted."""
    estimated: FittedValvePublic
    """The estimate's valve."""
    chosen: FittedValvePublic
    """The valve the advice simulates."""
    reproduces: bool
    """The chosen valve reproduces the measured cycle."""
    tried: int
    """Valves simulated."""
    at_edge: bool
    """The chosen S or J lies on a bound of the estimate's intervals (the data allow no
    larger change: the process may be what is off)."""
    delay_s: list[float] | None
    """With cause "process": the identified dead time and the one the model keeps, s."""
    explanation: str
    """What was found, what was changed and the error that remains, in words."""


class StictionAdvice(Schema):
    """Retunes for a sticky valve (thesis chapter 5), checked in simulation and against the
    measured cycle."""

    loop_id: str
    run_id: int
    """The analysis run whose estimate the model uses."""
    kind: Literal["stiction"]
    loops: list[str]
    """Loop names of the model."""
    current: list[TuningPublic]
    """The tunings the advice starts from."""
    current_predicted: OscillationEffectPublic
    """The oscillation at the current tuning, predicted."""
    current_simulated: OscillationEffectPublic
    """The oscillation at the current tuning, simulated."""
    analysis: SingleLoopAnalysisPublic | None
    """The chapter 5 analysis (single first-order loops only)."""
    maps: dict[str, SafeTuningMapPublic]
    """Safe-tuning map of each sticky loop, by loop name (section 5.6 step 1)."""
    recommendations: list[RecommendationPublic]
    """Verified retunes, best first."""
    rejected: list[RecommendationPublic]
    """Candidates the simulation did not confirm."""
    notes: list[str]
    """Why an action was not offered, what the simulation adds."""
    current_travel_rate_with_noise: float | None = None
    """The current tuning's valve travel with the measured PV noise (% per s); null when
    the noise was not known."""
    max_load_error_ratio: float | None = None
    """The bound the search kept to on a retune's ``load_error_ratio`` (null: none)."""
    valve_fit: ValveFitPublic
    """The estimate's valve checked against the measured cycle and fitted to it."""
    measured_cycle: CycleAgreementPublic
    """Whether the model the advice is computed on (with the chosen valve) reproduces the
    measured cycle."""


class DetunedPrediction(Schema):
    """A detuned loop does not cycle."""

    oscillating: Literal[False]
    period_s: None


class DetuningPublic(Schema):
    """One detuning: ``Kc`` divided by the gain margin, ``Ti`` kept."""

    tunings: list[TuningPublic]
    source: str
    """How it was found: the ultimate point at the measured period."""
    gain_margin: float
    """Lower bound of the gain margin of the detuned loop."""
    predicted: DetunedPrediction


class DetuningAdvice(Schema):
    """Detuning of a loop that cycles with a healthy valve (:func:`analytics.tuning.detune`):
    its cycle is taken as its ultimate point."""

    loop_id: str
    run_id: int
    """The analysis run whose cycle is used."""
    kind: Literal["detuning"]
    current: list[TuningPublic]
    """The configured tuning."""
    ultimate_period_s: float
    """The measured period, s, taken as the ultimate period."""
    recommendations: list[DetuningPublic]
    """One per gain margin offered (2 and 3)."""
    notes: list[str]


LoopAdvice = Annotated[StictionAdvice | DetuningAdvice, Field(discriminator="kind")]
"""The advice for a loop, by ``kind``."""
