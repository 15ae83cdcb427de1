"""The model check of a loop (``POST /api/v1/loops/{id}/model-check``):
:meth:`analytics.model_check.ModelCheck.to_dict` with the overlay, stamped with the window.

NMSE is the normalised mean squared error of a replay of the measured OP,
``sum (PV - PV_sim)^2 / sum (PV - mean PV)^2``, scored by two-fold cross-validation.
Every number that is not finite is null.
"""

from __future__ import annotations

from typing import Any, Literal

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
    base_model: dict[str, Any]
    """The base model in the model JSON of issue 8 (as the request's ``model``)."""
    baseline: BaselinePublic
    findings: list[str]
    """What the simulation gets wrong, where and how much, and why."""
    cause: CausePublic
    """The (first) cause."""
    causes: list[CausePublic]
    """Every cause named, in the order they were added to the model (at most two)."""
    candidates: list[CandidatePublic]
    """Every effect tried."""
    extended_model: dict[str, Any]
    """The base model with the causes, in the same model JSON."""
    gain: GainPublic
    notes: list[str]
    """How the base model was obtained, and caveats."""
    overlay: OverlayPublic
