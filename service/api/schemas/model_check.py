"""The model check of a loop (``POST /api/v1/loops/{id}/model-check``):
:meth:`analytics.model_check.ModelCheck.to_dict` with the overlay, stamped with the window.

NMSE is the normalised mean squared error of a replay of the measured OP,
``sum (PV - PV_sim)^2 / sum (PV - mean PV)^2``, scored by two-fold cross-validation.
Every number that is not finite is null.
"""

from __future__ import annotations

from typing import Literal

from service.api.schemas.base import Schema


class BaselinePublic(Schema):
    """How well the base model replays the window, and its closed-loop cycle against the
    measured one (:class:`analytics.model_check.CycleComparison`)."""

    nmse: float | None
    """Held-out NMSE of the base model."""
    nmse_fit: float | None
    """NMSE on the blocks its operating point was fitted on."""
    noise_nmse: float | None
    """NMSE that white measurement noise alone would cause: the floor a perfect model
    reaches."""
    controller_nmse: float | None
    """NMSE of the model's controller replayed on measured SP and PV, against the measured
    OP (null when it could not be computed)."""
    period_measured_s: float | None
    """Period of the measured PV oscillation, s (null: none detected)."""
    period_simulated_s: float | None
    """Period of the simulated PV oscillation, s (null: none)."""
    amplitude_measured: float | None
    """``sqrt(2)`` times the RMS of the measured PV band-passed around the period, % of
    span."""
    amplitude_simulated: float | None
    """The same of the simulated PV, % of span."""
    period_error: float | None
    """``(simulated - measured) / measured`` period; null unless both oscillate."""
    amplitude_error: float | None
    """``(simulated - measured) / measured`` amplitude; null if there is nothing to
    compare."""


class CausePublic(Schema):
    """An effect named as a cause of the mismatch, its parameters fitted on all scored data
    (:class:`analytics.model_check.Cause`)."""

    effect: str
    """A name of :data:`analytics.model_check.effects.EFFECTS`, or ``"none"``."""
    confidence: float | None
    """Probability, from the held-out errors, that the effect removes enough of the error
    and predicts better than the runner-up (for ``none``: that the runner-up does not)."""
    parameters: dict[str, float | None]
    """The effect's fitted parameters."""
    runner_up: str | None
    """The effect that predicted the held-out data next best."""
    nmse_before: float | None
    """Held-out NMSE of the model before this effect was added."""
    nmse_after: float | None
    """Held-out NMSE after it was added."""


class CandidatePublic(Schema):
    """One effect tried (:class:`analytics.model_check.ScoredCandidate`)."""

    effect: str
    parameters: dict[str, float | None]
    """Fitted on the even blocks."""
    nmse_fit: float | None
    """NMSE on the blocks each half was fitted on."""
    nmse_test: float | None
    """NMSE on the blocks it was not fitted on."""
    improvement: float | None
    """``1 - SSE_test / SSE_test(base)``: the fraction of the base model's held-out error
    the extension removes (negative: it adds error)."""
    note: str
    """Why the effect could not be fitted, if so."""


class GainPublic(Schema):
    """How much better the extended model is than the base model."""

    nmse_before: float | None
    nmse_after: float | None
    period_error_before: float | None
    period_error_after: float | None
    amplitude_error_before: float | None
    amplitude_error_after: float | None


class OverlayPublic(Schema):
    """Measured versus simulated PV (replay of the measured OP) for plotting; each scored
    sample predicted by the model fitted on the other half of the data."""

    t: list[float]
    """Sample times, UNIX s."""
    pv: list[float | None]
    """Measured PV, % of span."""
    pv_base: list[float | None]
    """PV of the base model, % of span."""
    pv_extended: list[float | None]
    """PV of the extended model, % of span."""
    scored: list[bool]
    """False for the warm-up."""


class ProcessPublic(Schema):
    """The first-order process (:func:`analytics.model_check.model.process_to_dict`)."""

    type: Literal["fopdt", "integrating"]
    """``fopdt``: ``K exp(-theta s) / (tau s + 1)``; ``integrating``:
    ``K exp(-theta s) / (s (tau s + 1))``."""
    K: float
    """Process gain: % of PV span per % of flow (per second for an integrating process)."""
    tau: float | None = None
    """Time constant (lag), s; absent for an integrating process without a lag."""
    theta: float
    """Dead time, s."""


class ControllerPublic(Schema):
    """The PI controller ``OP = Kc (e + (1 / Ti) integral(e))``, ``e = SP - PV``
    (:func:`analytics.model_check.model.controller_to_dict`)."""

    type: Literal["PI"]
    Kc: float
    """Controller gain (negative: direct acting)."""
    Ti: float | None = None
    """Integral time, s; absent for P-only control."""
    op_limits: list[float] | None = None
    """``[low, high]`` of OP, %; absent for ``[0, 100]``."""


class FrictionPublic(Schema):
    """Friction parameters of the base valve's model: ``fs``, ``fd`` (He) or ``S``, ``J``
    (Choudhury, Kano), % of valve travel."""

    fs: float | None = None
    fd: float | None = None
    S: float | None = None
    J: float | None = None


class _Band(Schema):
    low: float
    high: float


class StictionZonePublic(FrictionPublic, _Band):
    """Friction inside the band of travel ``low <= MV <= high``, in both directions.

    (Fields come base by base from the last base: the band, then the friction, as
    :meth:`analytics.model_check.model.Valve.to_dict` writes them.)"""


class CharacteristicPublic(Schema):
    """The installed flow characteristic ``flow(MV) = (100 / c) (exp(c (MV - op_bias) / 100)
    - 1)``: gain 1 at ``op_bias``, changing by ``e^c`` over the whole travel."""

    type: Literal["exponential"]
    curvature: float
    """``c`` (0: linear)."""


class _FrictionModel(Schema):
    model: str
    """The base friction model: ``he``, ``choudhury`` or ``kano`` (a healthy valve is
    ``he`` with ``fs = fd = 0``)."""


class ModelValvePublic(FrictionPublic, _FrictionModel):
    """The valve (:meth:`analytics.model_check.model.Valve.to_dict`): the base friction
    model and its parameters, with direction- or position-dependent friction and a
    characteristic when the check found them (fields in that order, as for
    :class:`StictionZonePublic`)."""

    opening: FrictionPublic | None = None
    """Friction while the valve opens, when it differs from closing."""
    closing: FrictionPublic | None = None
    """Friction while the valve closes."""
    zone: StictionZonePublic | None = None
    characteristic: CharacteristicPublic | None = None


class LoadPublic(Schema):
    """An unmeasured periodic load ``amplitude sin(2 pi t / period + phase)`` on PV."""

    kind: Literal["sine"]
    amplitude: float
    """% of PV span."""
    period: float
    """s."""
    phase: float
    """rad."""


class MeasurementPublic(Schema):
    """The PV transmitter: quantised to ``resolution`` from ``origin``, with white noise."""

    resolution: float
    """% of PV span."""
    origin: float
    noise: float
    """Standard deviation of white measurement noise, % of PV span."""


class LoopModelPublic(Schema):
    """A loop model in the model JSON of issue 8 (the request's ``model``;
    :meth:`analytics.model_check.model.LoopModel.to_dict`), in % of span."""

    dt: float
    """Sampling interval of the simulation, s."""
    process: ProcessPublic
    controller: ControllerPublic
    valve: ModelValvePublic
    op_bias: float
    """OP at the operating point (valve at rest, process at zero deviation), %."""
    pv_bias: float | None = None
    """PV at rest with MV at ``op_bias``, %; absent: estimated from the data."""
    load: LoadPublic | None = None
    measurement: MeasurementPublic | None = None


class ModelCheckPublic(Schema):
    """What the simulation of the loop gets wrong, the cause, the extended model and the
    gain, on the longest complete stretch of the loop's current window."""

    loop_id: str
    window_start: float
    """First sample checked, UNIX s."""
    window_end: float
    """Last sample checked, UNIX s."""
    ts: float
    """Sampling interval, s."""
    samples: int
    """Samples checked."""
    model_source: Literal["given", "identified"]
    """The request's model, or one identified from the window."""
    base_model: LoopModelPublic
    """The base model."""
    baseline: BaselinePublic
    findings: list[str]
    """What the simulation gets wrong, where and how much, and why."""
    cause: CausePublic
    """The (first) cause."""
    causes: list[CausePublic]
    """Every cause named, in the order they were added to the model (at most two)."""
    candidates: list[CandidatePublic]
    """Every effect tried."""
    extended_model: LoopModelPublic
    """The base model with the causes."""
    gain: GainPublic
    notes: list[str]
    """How the base model was obtained, and caveats."""
    overlay: OverlayPublic
