"""Model check: what a loop simulation gets wrong, the cause, the extended model and the gain.

:func:`check_model` compares a loop model with measured data in two ways
that do not depend on the phase of a free-running limit cycle:

1. **Replay.**  The measured OP drives valve and process; the simulated PV
   is compared with the measured PV on blocks held out from any fitting
   (:class:`analytics.model_check.effects.ReplayData`), by two-fold
   cross-validation over alternate blocks: fitted on the even blocks and
   scored on the odd ones, then the other way round, so that every scored
   sample is held out once (a setpoint change or a slip in one half cannot
   hide from the score).  The score is the normalised mean squared error
   ``NMSE = sum (PV - PV_sim)^2 / sum (PV - mean PV)^2``.
2. **Closed loop.**  Controller, valve and process are simulated with the
   measured setpoint (and measurement noise of the measured size); period
   and amplitude of the PV oscillation are compared with the measured ones
   (:func:`analytics.oscillation.detect_loop_oscillation`, amplitudes as
   ``sqrt(2)`` times the RMS of the band-passed PV).

Every effect of :data:`analytics.model_check.effects.EFFECTS` is then fitted
and scored in the same way.  An effect explains the mismatch when it removes
at least ``min_gain`` of the base model's held-out error; the cause is the
simplest explaining effect whose held-out error is within
``simpler_tolerance`` of the best one, and ``none`` when no effect explains
anything.  Evidence beyond the scores (issue 21):

* a PV on a lattice coarse enough that its values repeat is quantised
  whatever a fit says (:func:`relevant_lattice`): the quantiser then needs
  only to improve the held-out error at all;
* effects that imitate each other in part (dead time and lag; gain,
  characteristic and stiction in a band) are fitted together when they are
  the two best, and the one the data need is named (:func:`_nested_verdict`);
* the confidence is the probability, from the held-out errors, that the
  cause explains the mismatch and beats the runner-up (:func:`_better`, a
  Diebold-Mariano test [4]), at most the share of the held-out PV variance
  the final model explains;
* a second effect is fitted on top of the first and named by the same rule
  against the first alone (:func:`_second_effect`).

The causes are then refitted on all scored data.  The findings state, in
sentences, how far the model is off, where (valve position, direction of
travel, time) and why, and for an uncertain cause the runner-up and the data
that would decide.

References
----------
.. [1] Thesis section 3.4.6 (three reasons why model and experiment
   disagree), section 5.5.3 and Fig. 5.14 (stiction in part of the travel,
   stiction in one direction).
.. [2] Ljung (1999), *System Identification*, 2nd ed., sec. 16.4-16.6: model
   validation by simulation and cross-validation; prefer the simpler model
   among those that validate equally well.
.. [3] Thornhill, Huang & Zhang (2003), J. Process Control 13:91-100: the
   oscillation period and amplitude compared here.
.. [4] Diebold & Mariano (1995), "Comparing predictive accuracy", J. Business
   & Economic Statistics 13:253-263: the test of equal accuracy of two
   predictions of the same data, here with batch means of the loss
   differential for its autocorrelation.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike
from scipy.stats import t as student_t

from analytics.errors import DataError, ModelSpecError
from analytics.model_check.effects import (
    EFFECTS,
    Candidate,
    Prediction,
    ReplayData,
    describe_parameters,
    fit_effect,
    pv_grid,
)
from analytics.model_check.identify import identify_controller, identify_model
from analytics.model_check.model import LoopModel, Quantiser, friction_of
from analytics.oscillation import bandpass, detect_loop_oscillation
from analytics.signals import autocorrelation
from analytics.types import BoolArray, FloatArray

__all__ = [
    "MIN_SAMPLES",
    "Cause",
    "CycleComparison",
    "Gain",
    "ModelCheck",
    "Overlay",
    "ScoredCandidate",
    "check_model",
    "noise_std",
    "relevant_lattice",
    "valve_synchronisation",
]


MIN_SAMPLES = 300
"""Fewest samples a check accepts (eight blocks of a few dozen samples each)."""

ADEQUATE_NOISE_RATIO, ADEQUATE_NMSE = 3.0, 0.01
"""A base model that no effect improves is called adequate when its held-out NMSE is at
most this multiple of the noise NMSE plus this margin."""

REPLAY_LIMIT = 1e6
"""Largest PV response to the measured OP a model may give, in units of the measured PV."""

TIME_SCALE_LIMIT = 1e6
"""Largest time constant or dead time of a model checked, in record lengths."""

BATCHES = 24
"""Batches of consecutive held-out samples in the comparison of two models' errors
(:func:`_better`)."""

EXPLAINED_FOR_CONFIDENCE = 0.5
"""Share of the held-out PV variance below which the findings say that no cause can be
named with confidence and what data would decide (the confidence of every verdict is at
most the share the final model explains)."""

CONFIDENT = 0.9
"""Confidence below which the findings name the runner-up and the data that would decide."""

DECIDING = {
    "gain_mismatch": "OP steps of known size (the PV's whole change per % of OP)",
    "deadtime_mismatch": "sharp OP steps held for several dead times (when PV starts to move)",
    "time_constant_mismatch": "OP steps held until PV settles (the shape of its rise)",
    "valve_characteristic": "equal OP steps at several valve positions (the gain at each)",
    "measurement_quantization": "PV recorded at a finer resolution",
    "external_disturbance": "a longer record, or the load measured",
    "asymmetric_stiction": "slow OP ramps up and down over the same range (the band each way)",
    "position_dependent_stiction": "small OP reversals at several valve positions (the band at "
    "each)",
}
"""What data show each effect apart from the others (said when a cause is uncertain)."""

DYNAMICS = ("deadtime_mismatch", "time_constant_mismatch")
"""Two effects that imitate each other in part (:func:`_joint_dynamics`)."""

POSITIONAL = ("gain_mismatch", "valve_characteristic", "position_dependent_stiction")
"""Effects that change how far PV moves per OP move, any two of which imitate each other
in part: a gain everywhere, a gain changing with valve position (the characteristic), a
stick band changing with position (stiction in a band of travel), told apart by fitting
two together (:func:`_joint_both_orders`)."""

OUTPUT_EFFECTS = ("external_disturbance", "measurement_quantization")
"""Effects on the measured PV rather than in the loop, in the order they act."""

LATTICE_REPEATS = 0.25
"""Share of consecutive PV samples that repeat exactly, on a PV on a lattice, from which
the lattice is taken to matter (quantisation is then evident from the data)."""


@dataclass(frozen=True)
class CycleComparison:
    """PV oscillation of the data and of a closed-loop simulation of a model.

    Attributes
    ----------
    period_measured, period_simulated : float or None
        Oscillation period, s (None: no oscillation detected).
    amplitude_measured, amplitude_simulated : float
        ``sqrt(2)`` times the RMS of PV band-passed around the period (the
        measured period, or the simulated one when the data do not oscillate).
    """

    period_measured: float | None
    period_simulated: float | None
    amplitude_measured: float | None
    amplitude_simulated: float | None

    @property
    def period_error(self) -> float | None:
        """``(simulated - measured) / measured``; None unless both oscillate."""
        if self.period_measured is None or self.period_simulated is None:
            return None
        return (self.period_simulated - self.period_measured) / self.period_measured

    @property
    def amplitude_error(self) -> float | None:
        """``(simulated - measured) / measured`` amplitude; None if there is nothing to compare."""
        if not self.amplitude_measured or self.amplitude_simulated is None:
            return None
        return (self.amplitude_simulated - self.amplitude_measured) / self.amplitude_measured

    def to_dict(self) -> dict[str, float | None]:
        """JSON form with the relative errors."""
        return {
            "period_measured_s": self.period_measured,
            "period_simulated_s": self.period_simulated,
            "amplitude_measured": self.amplitude_measured,
            "amplitude_simulated": self.amplitude_simulated,
            "period_error": self.period_error,
            "amplitude_error": self.amplitude_error,
        }


@dataclass(frozen=True)
class ScoredCandidate:
    """One effect tried: its fitted parameters and scores.

    Attributes
    ----------
    effect : str
    parameters : dict
        Fitted on the even blocks (the cause named by the check is refitted on
        all scored data, see :attr:`Cause.parameters`).
    nmse_fit, nmse_test : float
        NMSE of the replay on the blocks each half was fitted on and on the
        blocks it was not (two-fold cross-validation).
    improvement : float
        ``1 - SSE_test / SSE_test(base)``: the fraction of the base model's
        held-out error the extension removes (negative: it adds error).
    note : str
        Why the effect could not be fitted, if so.
    model : LoopModel
        The extended model fitted on the even blocks.
    """

    effect: str
    parameters: dict[str, float]
    nmse_fit: float
    nmse_test: float
    improvement: float
    note: str
    model: LoopModel = field(repr=False)

    def to_dict(self) -> dict[str, Any]:
        """JSON form."""
        return {
            "effect": self.effect,
            "parameters": self.parameters,
            "nmse_fit": self.nmse_fit,
            "nmse_test": self.nmse_test,
            "improvement": self.improvement,
            "note": self.note,
        }


@dataclass(frozen=True)
class Cause:
    """An effect named as a cause of the mismatch, its parameters fitted on all scored data.

    ``confidence`` is the probability, from the held-out errors, that the
    effect removes at least ``min_gain`` of the error left before it was
    added, times the probability that it predicts the held-out data better
    than ``runner_up`` (:func:`_better`).  For ``none`` it is the probability
    that the effect closest to explaining the data (the runner-up) does not
    remove ``min_gain``.  Neither exceeds the share of the held-out PV
    variance that the final model explains.

    Attributes
    ----------
    effect : str
        A name of :data:`EFFECTS`, or ``"none"``.
    confidence : float
    parameters : dict
    runner_up : str or None
        The effect that predicted the held-out data next best (for ``none``:
        the one closest to explaining it); None if there is none.
    nmse_before, nmse_after : float
        Held-out NMSE of the model before and after this effect was added
        (the second of two causes is added to the model with the first).
    """

    effect: str
    confidence: float
    parameters: dict[str, float]
    runner_up: str | None = None
    nmse_before: float = math.nan
    nmse_after: float = math.nan

    def to_dict(self) -> dict[str, Any]:
        """JSON form."""
        return {
            "effect": self.effect,
            "confidence": self.confidence,
            "parameters": self.parameters,
            "runner_up": self.runner_up,
            "nmse_before": self.nmse_before,
            "nmse_after": self.nmse_after,
        }


@dataclass(frozen=True)
class Gain:
    """How much better the extended model is than the base model."""

    nmse_before: float
    nmse_after: float
    before: CycleComparison
    after: CycleComparison

    def to_dict(self) -> dict[str, Any]:
        """JSON form: held-out NMSE, period and amplitude errors before and after."""
        return {
            "nmse_before": self.nmse_before,
            "nmse_after": self.nmse_after,
            "period_error_before": self.before.period_error,
            "period_error_after": self.after.period_error,
            "amplitude_error_before": self.before.amplitude_error,
            "amplitude_error_after": self.after.amplitude_error,
        }


@dataclass(frozen=True)
class Overlay:
    """Measured versus simulated PV (replay of the measured OP) for plotting.

    Each scored sample is predicted by the model fitted on the other half of
    the data (cross-validation); ``scored`` is False for the warm-up.
    """

    t: FloatArray
    pv: FloatArray
    pv_base: FloatArray
    pv_extended: FloatArray
    scored: BoolArray

    def to_dict(self) -> dict[str, list[float] | list[bool]]:
        """JSON form (lists)."""
        return {
            "t": self.t.tolist(),
            "pv": self.pv.tolist(),
            "pv_base": self.pv_base.tolist(),
            "pv_extended": self.pv_extended.tolist(),
            "scored": self.scored.tolist(),
        }


@dataclass(frozen=True)
class ModelCheck:
    """Result of :func:`check_model`.

    Attributes
    ----------
    model_source : {"given", "identified"}
    base_model, extended_model : LoopModel
    nmse_base_fit, nmse_base_test : float
        Replay NMSE of the base model, with its operating point fitted on the
        same blocks and scored on the other ones (cross-validated).
    noise_nmse : float
        NMSE that white measurement noise alone would cause (estimated from
        the second differences of PV): the floor a perfect model reaches.
    controller_nmse : float or None
        NMSE of the model's controller replayed on measured SP and PV, against
        the measured OP (None when it could not be computed).
    cycle_base : CycleComparison
        Measured against closed-loop simulated oscillation, base model.
    findings : tuple of str
        What the simulation gets wrong, where and how much, and why.
    cause : Cause
        The (first) cause.
    causes : tuple of Cause
        Every cause named, in the order they were added to the model: the
        cause, and a second effect when one explains part of what the first
        leaves (at most two).
    candidates : tuple of ScoredCandidate
        Every effect tried, in :data:`EFFECTS` order.
    gain : Gain
    overlay : Overlay
    notes : tuple of str
        How the base model was obtained, and caveats.
    """

    model_source: Literal["given", "identified"]
    base_model: LoopModel
    extended_model: LoopModel
    nmse_base_fit: float
    nmse_base_test: float
    noise_nmse: float
    controller_nmse: float | None
    cycle_base: CycleComparison
    findings: tuple[str, ...]
    cause: Cause
    causes: tuple[Cause, ...]
    candidates: tuple[ScoredCandidate, ...]
    gain: Gain
    overlay: Overlay = field(repr=False)
    notes: tuple[str, ...] = ()

    def to_dict(self, *, overlay: bool = False) -> dict[str, Any]:
        """JSON form: ``baseline``, ``findings``, ``cause``, ``causes``, ``candidates``,
        ``extended_model``, ``gain`` (and ``overlay`` when asked)."""
        out: dict[str, Any] = {
            "model_source": self.model_source,
            "base_model": self.base_model.to_dict(),
            "baseline": {
                "nmse": self.nmse_base_test,
                "nmse_fit": self.nmse_base_fit,
                "noise_nmse": self.noise_nmse,
                "controller_nmse": self.controller_nmse,
                **self.cycle_base.to_dict(),
            },
            "findings": list(self.findings),
            "cause": self.cause.to_dict(),
            "causes": [c.to_dict() for c in self.causes],
            "candidates": [c.to_dict() for c in self.candidates],
            "extended_model": self.extended_model.to_dict(),
            "gain": self.gain.to_dict(),
            "notes": list(self.notes),
        }
        if overlay:
            out["overlay"] = self.overlay.to_dict()
        return _finite_or_none(out)


# ----------------------------------------------------------------------------
# helpers


def _finite_or_none(value: Any) -> Any:
    """``value`` with every NaN or infinite float (nested in dicts and lists) as None,
    so that it is valid JSON."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: _finite_or_none(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_finite_or_none(v) for v in value]
    return value


def _series(name: str, values: ArrayLike, n: int | None = None) -> FloatArray:
    out = np.ascontiguousarray(values, dtype=np.float64)
    if out.ndim != 1:
        raise DataError(f"{name} must be one-dimensional, got shape {out.shape}")
    if n is not None and out.size != n:
        raise DataError(f"{name} has {out.size} samples, OP has {n}")
    bad = np.flatnonzero(~np.isfinite(out))
    if bad.size:
        raise DataError(
            f"{name} holds {bad.size} missing or non-finite value(s), first at sample {bad[0]}; "
            "fill or cut them before a model check"
        )
    return out


def noise_std(pv: FloatArray) -> float:
    """Standard deviation of white measurement noise in ``pv``, from its second differences.

    For white noise of variance ``s^2`` the second difference has variance
    ``6 s^2``; a smooth signal barely contributes, and the median absolute
    deviation ignores the few large steps of a slipping valve.

    Examples
    --------
    >>> rng = np.random.default_rng(1)
    >>> pv = np.sin(np.arange(5000) / 50.0) + rng.normal(0.0, 0.1, 5000)
    >>> round(noise_std(pv), 2)
    0.1
    """
    second = np.diff(pv, 2)
    mad = float(np.median(np.abs(second - np.median(second))))
    return 1.4826 * mad / math.sqrt(6.0)


def valve_synchronisation(model: LoopModel, op: FloatArray) -> int:
    """First sample from which the replayed valve position no longer depends on where
    the valve stood at the start.

    The valve is replayed from rest at the first OP sample and two stick bands
    either side of it; a sticky valve keeps the memory of its start until OP
    has pushed it through its band.

    Examples
    --------
    >>> from analytics.model_check.model import LoopModel
    >>> model = LoopModel.from_dict({"dt": 1, "process": {"type": "fopdt", "K": 1, "tau": 5},
    ...     "controller": {"Kc": 1, "Ti": 5}, "valve": {"model": "he", "fs": 2, "fd": 1}})
    >>> valve_synchronisation(model, np.array([50.0, 50.5, 49.5, 60.0, 61.0, 40.0]))
    3
    """
    table = model.valve.friction_table()
    reach = 2.0 * float(np.max(table)) + 1e-9
    runs = [
        model.replay(op, initial_position=float(op[0]) + shift)[0] for shift in (-reach, 0.0, reach)
    ]
    differ = np.flatnonzero((runs[0] != runs[1]) | (runs[1] != runs[2]))
    return int(differ[-1]) + 1 if differ.size else 0


HORIZONS = (20, 40, 80, 160, 320, 640, None)
"""Prediction horizons (samples; None: free run) tried for an integrating process."""


def _valve_starts(
    model: LoopModel, op: FloatArray, *, convention: bool
) -> list[tuple[float, FloatArray]]:
    """Where the replayed valve may start.

    With ``convention`` (a given model, whose loop starts at rest at
    ``op_bias``) and OP starting within reach of ``op_bias``: there.
    Otherwise the start is unknown: at rest at the first OP sample, or
    arriving there from below or from above (stepped through its stick band).
    """
    reach = 2.0 * float(np.max(model.valve.friction_table()))
    first = float(op[0])
    if convention and abs(first - model.op_bias) <= reach:
        return [(model.op_bias, np.empty(0))]
    starts = [(first, np.empty(0))]
    if reach > 0:
        ramp = np.array([3.0, 2.0, 1.0]) * reach
        starts += [(first - 4 * reach, first - ramp), (first + 4 * reach, first + ramp)]
    return starts


def _replay_data(
    base: LoopModel,
    op: FloatArray,
    pv: FloatArray,
    ts: float,
    warm_up: int,
    folds: int,
    convention: bool,
) -> tuple[ReplayData, ReplayData]:
    """The two halves of the cross-validation (odd blocks held out, even blocks held out).

    Nuisance choices are those with which the base model predicts the scored
    data best: where the valve starts (:func:`_valve_starts`) and, for an
    integrating process, the prediction horizon (how fast level errors build up).
    """
    integrating = base.process.integrating
    block = (op.size - warm_up) // max(2 * folds, 1)
    horizons = [h for h in HORIZONS if h is None or h <= block] if integrating else [None]
    options = [
        ReplayData(op, pv, ts, warm_up=warm_up, folds=folds, horizon=h, ramp=integrating,
                   valve_start=start, held_out="none")
        for start in _valve_starts(base, op, convention=convention)
        for h in horizons
    ]
    best = min(options, key=lambda data: data.fit_error(base))
    return best.holding_out("odd"), best.holding_out("even")


@dataclass(frozen=True)
class _CrossValidated:
    """A model's predictions from the two halves: each scores the blocks it was not fitted on."""

    halves: tuple[ReplayData, ReplayData]
    predictions: tuple[Prediction, ...]

    @property
    def sse_test(self) -> float:
        """Squared error of every scored sample, predicted by the fit that did not see it."""
        return sum(p.sse_test for p in self.predictions)

    @property
    def nmse_test(self) -> float:
        """:attr:`sse_test` over the held-out variance of PV."""
        return self.sse_test / sum(h.sst_test for h in self.halves)

    @property
    def nmse_fit(self) -> float:
        """The same on the blocks each fit saw."""
        return sum(p.sse_fit for p in self.predictions) / sum(h.sst_fit for h in self.halves)

    def held_out_pv(self) -> FloatArray:
        """Every sample predicted by the fit that did not see it."""
        first, second = self.predictions
        return np.asarray(np.where(self.halves[1].test, second.pv, first.pv), dtype=np.float64)


def _amplitude(pv: FloatArray, period_samples: float) -> float:
    return float(math.sqrt(2.0) * np.std(bandpass(pv, period_samples)))


def _cycle(
    model: LoopModel,
    sp: FloatArray,
    pv_bias: float,
    noise: FloatArray,
    measured: float | None,
    measured_pv: FloatArray,
    warm_up: int,
) -> CycleComparison:
    """Closed-loop simulation of ``model`` (after its start-up ``warm_up``) against the
    measured oscillation (period ``measured``, None if there is none, and PV)."""
    ts = model.dt
    sim = model.simulate(sp, noise=noise, pv_bias=pv_bias)
    op_s, pv_s = sim.op[warm_up:], sim.pv[warm_up:]
    simulated = None
    if np.all(np.isfinite(pv_s)) and np.ptp(pv_s) > 0:
        simulated = detect_loop_oscillation(op_s, pv_s, ts).period_s
    reference = measured or simulated
    if reference is None:
        return CycleComparison(None, None, None, None)
    amp_m = _amplitude(measured_pv, (measured or reference) / ts)
    amp_s = _amplitude(pv_s, (simulated or reference) / ts) if np.all(np.isfinite(pv_s)) else None
    return CycleComparison(measured, simulated, amp_m, amp_s)


def _controller_nmse(
    model: LoopModel, op: FloatArray, pv: FloatArray, sp: FloatArray
) -> float:
    """NMSE of the model's PI law replayed on measured SP and PV against measured OP."""
    c = model.controller
    e = sp - pv
    op_model = c.kp * e + c.ki * model.dt * np.cumsum(e)
    op_model += np.mean(op - op_model)  # the integrator's initial value
    op_model = np.clip(op_model, *c.op_limits)
    total = float(np.sum((op - op.mean()) ** 2))
    return float(np.sum((op - op_model) ** 2) / total) if total > 0 else math.nan


def relevant_lattice(pv: FloatArray) -> Quantiser | None:
    """The lattice the PV lies on if it is coarse enough to matter: quantisation seen in
    the data itself, whatever a fit says (None otherwise).

    The values lie on a lattice (:func:`analytics.model_check.effects.pv_grid`)
    and at least :data:`LATTICE_REPEATS` of consecutive samples repeat
    exactly.  A continuous signal never repeats; a signal rounded to a step
    ``q`` repeats about as often as its increments stay inside one cell, so
    that a fine historian rounding (``q`` well below the noise) does not
    count, while a step comparable with the noise, whose rounding error
    (variance ``q^2 / 12``) is then a visible part of the mismatch, does.

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> smooth = 50 + np.sin(np.arange(3000) / 40.0) + rng.normal(0, 0.05, 3000)
    >>> relevant_lattice(smooth) is None, relevant_lattice(np.round(smooth, 3)) is None
    (True, True)
    >>> round(relevant_lattice(np.round(smooth / 0.2) * 0.2).resolution, 3)
    0.2
    """
    if pv.size < 2 or np.mean(np.diff(pv) == 0.0) < LATTICE_REPEATS:
        return None
    return pv_grid(pv)


def _scored(
    effect: str, fits: list[Candidate], cv: _CrossValidated, reference_sse: float
) -> ScoredCandidate:
    """The score of an effect fitted on each half (``improvement`` against the held-out
    error ``reference_sse`` of the models the fits started from)."""
    return ScoredCandidate(
        effect=effect,
        parameters=fits[0].parameters,
        nmse_fit=cv.nmse_fit,
        nmse_test=cv.nmse_test,
        improvement=1.0 - cv.sse_test / reference_sse if reference_sse > 0 else 0.0,
        note=fits[0].note or fits[1].note,
        model=fits[0].model,
    )


def _try_effects(
    effects: tuple[str, ...],
    halves: tuple[ReplayData, ReplayData],
    models: tuple[LoopModel, ...],
    predictions: tuple[Prediction, ...],
    reference_sse: float,
    period_s: float | None,
) -> tuple[list[ScoredCandidate], dict[str, _CrossValidated], dict[str, list[Candidate]]]:
    """Fit every effect on each half, starting from that half's model and prediction, and
    score it on the blocks the half held out.

    Returns the scored candidates, their cross-validated predictions and the
    fits of each half.
    """
    scored: list[ScoredCandidate] = []
    cross_validated: dict[str, _CrossValidated] = {}
    fitted: dict[str, list[Candidate]] = {}
    for effect in effects:
        fits = fitted[effect] = [
            fit_effect(effect, h, m, p, period_s=period_s)
            for h, m, p in zip(halves, models, predictions, strict=True)
        ]
        cv = cross_validated[effect] = _CrossValidated(halves, tuple(c.prediction for c in fits))
        scored.append(_scored(effect, fits, cv, reference_sse))
    return scored, cross_validated, fitted


def _nesting(first: str, second: str) -> tuple[str, str]:
    """The order in which two effects are fitted together: the effects on the measured
    PV (:data:`OUTPUT_EFFECTS`) last, as they act last (and a friction search on a model
    that has them is slow)."""
    def rank(effect: str) -> int:
        return OUTPUT_EFFECTS.index(effect) + 1 if effect in OUTPUT_EFFECTS else 0

    return (first, second) if rank(first) <= rank(second) else (second, first)


def _fit_pair(
    inner: Candidate,
    outer: str,
    data: ReplayData,
    base: LoopModel,
    period_s: float | None,
) -> tuple[Candidate, Candidate]:
    """``outer`` fitted on top of the fitted ``inner`` effect: the inner fit as finally
    used and the combined candidate (effect and parameters of ``outer``, the model with
    both).

    A periodic load is fitted on top of the inner effect, then the inner effect is
    refitted with that load present (one step of alternating least squares: a friction
    or process fit made with the load unmodelled is biased by it), and the better fit
    of the two is kept.  The inner effect's fits are compared on the fitting blocks
    only.
    """
    pair = fit_effect(outer, data, inner.model, inner.prediction, period_s=period_s)
    if outer != "external_disturbance" or pair.model.load is None or inner.effect == outer:
        return inner, pair
    loaded = replace(base, load=pair.model.load)
    again = fit_effect(inner.effect, data, loaded, data.predict(loaded), period_s=period_s)
    if again.note or again.prediction.sse_fit >= pair.prediction.sse_fit:
        return inner, pair
    return again, replace(again, effect=outer, parameters=pair.parameters)


def _second_effect(
    chosen: str,
    effects: tuple[str, ...],
    halves: tuple[ReplayData, ReplayData],
    base: LoopModel,
    fitted: dict[str, list[Candidate]],
    first_cv: _CrossValidated,
    residuals: dict[str, FloatArray],
    residual: Callable[[_CrossValidated], FloatArray],
    min_gain: float,
    simpler_tolerance: float,
    evident: frozenset[str],
    period_s: float | None,
) -> tuple[_CrossValidated, tuple[str, str], float, str | None] | None:
    """A second effect besides ``chosen``: each other effect and ``chosen`` fitted together
    (in the order of :func:`_nesting` by :func:`_fit_pair`, from the inner one's fits on
    each half) and selected as :func:`_select` selects the first, against ``chosen`` alone.

    Returns the pair's cross-validated prediction, its (inner, outer) order, the
    confidence and the runner-up; None when no second effect explains enough.
    """
    scored: list[ScoredCandidate] = []
    cross_validated: dict[str, _CrossValidated] = {}
    orders: dict[str, tuple[str, str]] = {}
    for other in effects:
        if other == chosen or any(c.note for c in fitted[other]):
            continue
        inner, outer = orders[other] = _nesting(chosen, other)
        fits = [
            _fit_pair(start, outer, h, base, period_s)[1]
            for h, start in zip(halves, fitted[inner], strict=True)
        ]
        cv = cross_validated[other] = _CrossValidated(halves, tuple(c.prediction for c in fits))
        scored.append(_scored(other, fits, cv, first_cv.sse_test))
    second, confidence, runner_up = _select(
        scored, {e: residual(cv) for e, cv in cross_validated.items()}, residuals[chosen],
        min_gain, simpler_tolerance, evident,
    )
    if second is None:
        return None
    return cross_validated[second.effect], orders[second.effect], confidence, runner_up


def _joint_dynamics(
    halves: tuple[ReplayData, ReplayData],
    base: LoopModel,
    fitted: dict[str, list[Candidate]],
    period_s: float | None,
) -> list[Candidate]:
    """Dead time and time constant fitted together on each half: the dead time over the
    whole samples between the base's and the single fit's (two either side), the time
    constant fitted at each.

    A longer dead time and an added lag both delay the response to an OP
    move, but differently: a dead time shifts the whole response (a phase lag
    growing with frequency, the gain unchanged), a lag rounds its start (phase
    lag and attenuation).  Either single fit imitates the other in part, most
    of all on an integrating process, where a lag ``tau`` delays the ramp's
    asymptote by ``tau``; the joint fit sees the response's shape.
    """
    joint: list[Candidate] = []
    for h, delay_fit in zip(halves, fitted["deadtime_mismatch"], strict=True):
        d0 = base.process.delay_samples(h.ts)
        d1 = delay_fit.model.process.delay_samples(h.ts)
        best: Candidate | None = None
        for d in range(max(0, min(d0, d1) - 2), max(d0, d1) + 3):
            delayed = replace(base, process=replace(base.process, theta=d * h.ts))
            fit = fit_effect("time_constant_mismatch", h, delayed, h.predict(delayed),
                             period_s=period_s)
            if best is None or fit.prediction.sse_fit < best.prediction.sse_fit:
                best = fit
        assert best is not None
        joint.append(best)
    return joint


def _joint_both_orders(
    first: str,
    second: str,
    halves: tuple[ReplayData, ReplayData],
    fitted: dict[str, list[Candidate]],
    period_s: float | None,
) -> list[Candidate]:
    """Two effects fitted together on each half: each on top of the other's fit, the
    order with the smaller error on the fitting blocks kept (two starts of alternating
    least squares)."""
    joint: list[Candidate] = []
    for i, h in enumerate(halves):
        fits = [
            fit_effect(outer, h, fitted[inner][i].model, fitted[inner][i].prediction,
                       period_s=period_s)
            for inner, outer in ((first, second), (second, first))
        ]
        joint.append(min(fits, key=lambda c: c.prediction.sse_fit))
    return joint


def _nested_verdict(
    first: str,
    second: str,
    both: FloatArray,
    residuals: dict[str, FloatArray],
    min_gain: float,
) -> tuple[str, float, str]:
    """Which of two effects that imitate each other the data need, from the held-out
    residuals ``both`` of the model with the two.

    An effect is needed when the joint model beats the other effect alone by
    ``min_gain`` (:func:`_better`): the nested-model comparison of Ljung (1999,
    sec. 16.4), prefer the smaller model among those that validate equally well.
    The confidence of an effect is the probability that it is needed and the
    other is not.  ``first`` (the better one alone) is kept unless ``second``
    is more likely than not the one needed; when both are needed neither is
    confident, and the second cause of the check adds the other.  Returns the
    effect, its confidence and the other effect.
    """
    need_first = _better(residuals[second], both, min_gain)
    need_second = _better(residuals[first], both, min_gain)
    if need_second * (1.0 - need_first) > 0.5:
        return second, need_second * (1.0 - need_first), first
    return first, need_first * (1.0 - need_second), second


def _undecided_sentence(cause: Cause) -> str:
    """The runner-up of an uncertain cause, and the data that would tell the two apart."""
    assert cause.runner_up is not None
    return (
        f"{cause.runner_up} explains the held-out data almost as well as {cause.effect} "
        f"(confidence {cause.confidence:.2f}); to decide, {DECIDING[cause.effect]} would show "
        f"{cause.effect}, {DECIDING[cause.runner_up]} {cause.runner_up}."
    )


def _better(first: FloatArray, second: FloatArray, margin: float = 0.0) -> float:
    """Probability that the held-out residuals ``second`` have a smaller mean square than
    ``1 - margin`` times those of ``first`` (residuals of the same samples, in time order).

    The Diebold-Mariano test of equal predictive accuracy [4]: the loss
    differential ``d_k = (1 - margin) first_k^2 - second_k^2`` is averaged over
    batches of consecutive samples (batch means, so that the correlation of
    neighbouring residuals does not make the spread look smaller than it is:
    at most :data:`BATCHES`, each at least five correlation times long
    (:func:`_correlation_time`) as far as four batches allow) and its mean over
    its standard error is referred to Student's t with one degree of freedom
    fewer than batches.

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> noise = rng.normal(0.0, 1.0, 2400)
    >>> round(_better(noise + 1.0, noise), 3), round(_better(noise, noise + 1.0), 3)
    (1.0, 0.0)
    >>> 0.05 < _better(noise, rng.normal(0.0, 1.0, 2400)) < 0.95  # equally good
    True
    """
    d = (1.0 - margin) * first**2 - second**2
    batches = max(min(BATCHES, d.size // math.ceil(5.0 * _correlation_time(d))), 4)
    means = np.array([chunk.mean() for chunk in np.array_split(d, batches) if chunk.size])
    mean = float(means.mean())
    spread = float(means.std(ddof=1)) / math.sqrt(means.size) if means.size > 1 else 0.0
    if spread == 0.0:
        return 0.5 if mean == 0.0 else float(mean > 0.0)
    return float(student_t.cdf(mean / spread, means.size - 1))


def _correlation_time(d: FloatArray) -> float:
    """Integrated correlation time of ``d`` in samples, ``1 + 2 sum rho_k``, summed over
    the lags before the autocorrelation ``rho_k`` first falls to zero (at least 1).

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> white = rng.normal(size=20000)
    >>> round(_correlation_time(white))
    1
    >>> ar = np.zeros(20000)
    >>> for k in range(1, ar.size):
    ...     ar[k] = 0.8 * ar[k - 1] + white[k]
    >>> 7 < _correlation_time(ar) < 11  # (1 + 0.8) / (1 - 0.8) = 9
    True
    """
    rho = autocorrelation(d, d.size // 4 - 1)
    if not rho[0] > 0:
        return 1.0
    stop = np.flatnonzero(rho <= 0.0)
    last = int(stop[0]) if stop.size else rho.size
    return max(1.0 + 2.0 * float(np.sum(rho[1:last])), 1.0)


def _select(
    scored: list[ScoredCandidate],
    residuals: dict[str, FloatArray],
    reference: FloatArray,
    min_gain: float,
    simpler_tolerance: float,
    evident: frozenset[str] = frozenset(),
) -> tuple[ScoredCandidate | None, float, str | None]:
    """The cause (None: the reference model is adequate), its confidence and the runner-up.

    An effect explains the data when it removes at least ``min_gain`` of the
    reference model's held-out error (an effect ``evident`` in the data
    itself, such as a PV on a lattice, when it removes any).  Of those, the
    simplest whose held-out error is within ``simpler_tolerance`` of the best
    is the cause.  Under a correct model an extension fitted to noise changes
    the held-out error by ``O(1 / N)`` only, so a few per cent is a safe
    threshold.  ``residuals`` are the held-out residuals of each effect,
    ``reference`` those of the model the effects extend; the confidence is
    that of :class:`Cause`, from :func:`_better`.
    """
    valid = [c for c in scored if not c.note]
    explaining = [
        c for c in valid
        if c.improvement >= min_gain or (c.effect in evident and c.improvement > 0.0)
    ]
    if not explaining:
        closest = max(valid, key=lambda c: c.improvement, default=None)
        if closest is None:
            return None, 1.0, None
        return None, 1.0 - _better(reference, residuals[closest.effect], min_gain), closest.effect
    best_error = min(c.nmse_test for c in explaining)
    chosen = next(c for c in explaining if c.nmse_test <= best_error * (1.0 + simpler_tolerance))
    runner_up = min(
        (c for c in valid if c.effect != chosen.effect), key=lambda c: c.nmse_test, default=None
    )
    margin = 0.0 if chosen.effect in evident else min_gain
    confidence = _better(reference, residuals[chosen.effect], margin)
    if runner_up is not None:
        confidence *= _better(residuals[runner_up.effect], residuals[chosen.effect])
    return chosen, confidence, None if runner_up is None else runner_up.effect


def _pct(x: float | None) -> str:
    return "-" if x is None else f"{100 * x:+.0f} %"


def _where(data: ReplayData, predicted: FloatArray, op: FloatArray) -> list[str]:
    """Sentences locating the base model's held-out error: by OP range, by direction of
    OP, in time (``data`` with every scored sample in ``data.fit``)."""
    out: list[str] = []
    scored = data.fit
    error = (data.pv - predicted)[scored]
    rms_all = float(np.sqrt(np.mean(error**2)))
    if rms_all == 0:
        return out
    cuts = np.quantile(op[scored], [0.0, 1 / 3, 2 / 3, 1.0])
    band = np.clip(np.searchsorted(cuts, op[scored], side="right") - 1, 0, 2)
    rms = [float(np.sqrt(np.mean(error[band == b] ** 2))) if np.any(band == b) else 0.0
           for b in range(3)]
    worst = int(np.argmax(rms))
    rest = [r for b, r in enumerate(rms) if b != worst]
    if rms[worst] > 1.3 * max(rest):
        out.append(
            f"The error is largest with OP between {cuts[worst]:.1f} and {cuts[worst + 1]:.1f} %: "
            f"RMS {rms[worst]:.3g} against {max(rest):.3g} in the rest of the travel."
        )
    slope = np.zeros(op.size)
    slope[5:-5] = op[10:] - op[:-10]  # OP over +-5 samples: rising pushes the valve open
    push = np.sign(slope)[scored]
    rising = float(np.sqrt(np.mean(error[push > 0] ** 2))) if np.any(push > 0) else 0.0
    falling = float(np.sqrt(np.mean(error[push < 0] ** 2))) if np.any(push < 0) else 0.0
    if max(rising, falling) > 1.3 * min(rising, falling) and min(rising, falling) > 0:
        which = "rises (the valve is pushed open)" if rising > falling else "falls (pushed shut)"
        out.append(
            f"The error is larger while OP {which}: RMS {max(rising, falling):.3g} "
            f"against {min(rising, falling):.3g}."
        )
    block_rms = [float(np.sqrt(np.mean((data.pv - predicted)[a:b] ** 2))) for a, b in data.blocks]
    a, b = data.blocks[int(np.argmax(block_rms))]
    if max(block_rms) > 1.3 * rms_all:
        out.append(
            f"The error is largest at t = {data.t[a]:.0f}-{data.t[b - 1]:.0f} s: "
            f"RMS {max(block_rms):.3g} against {rms_all:.3g} overall."
        )
    return out


def _cause_sentence(chosen: Candidate, base: LoopModel) -> str:
    p, b = chosen.parameters, base
    effect = chosen.effect
    if effect == "gain_mismatch":
        return (
            f"The process gain is {p['K']:.3g} instead of {b.process.K:.3g} "
            f"({p['ratio']:.2f} times the model's)."
        )
    if effect == "deadtime_mismatch":
        return f"The dead time is {p['theta']:.3g} s instead of {b.process.theta:.3g} s."
    if effect == "time_constant_mismatch":
        return f"The time constant is {p['tau']:.3g} s instead of {b.process.tau:.3g} s."
    if effect == "valve_characteristic":
        c = p["curvature"]
        kind = "equal-percentage-like" if c > 0 else "quick-opening-like"
        return (
            f"The installed valve characteristic is not linear ({kind}, curvature {c:.2f}): "
            f"the valve's gain changes by a factor {math.exp(abs(c) / 10):.2f} every 10 % of "
            f"travel, {'rising' if c > 0 else 'falling'} as it opens."
        )
    if effect == "measurement_quantization":
        return (
            f"The PV is recorded on a grid of {p['resolution']:.3g} (sensor resolution or "
            "historian rounding), which the model lacks."
        )
    if effect == "external_disturbance":
        return (
            f"An unmeasured periodic load of amplitude {p['amplitude']:.3g} and period "
            f"{p['period']:.4g} s acts on PV."
        )
    S0, j0 = friction_of(b.valve.base)
    base_text = f"S = {S0:.3g}, J = {S0 * j0:.3g}"
    if effect == "asymmetric_stiction":
        v = chosen.model.valve
        assert v.opening is not None and v.closing is not None
        return (
            f"The valve sticks differently opening (S = {v.opening.S:.3g}, J = {v.opening.J:.3g}) "
            f"and closing (S = {v.closing.S:.3g}, J = {v.closing.J:.3g}); the model has "
            f"{base_text} both ways."
        )
    zone = chosen.model.valve.zone
    assert zone is not None
    return (
        f"The valve sticks with S = {zone.valve.S:.3g}, J = {zone.valve.J:.3g} between "
        f"{zone.low:.1f} and {zone.high:.1f} % of travel, and with {base_text} elsewhere."
    )


def check_model(
    op: ArrayLike,
    pv: ArrayLike,
    ts: float,
    *,
    sp: ArrayLike | None = None,
    model: LoopModel | dict[str, Any] | None = None,
    effects: tuple[str, ...] = EFFECTS,
    folds: int = 4,
    min_gain: float = 0.05,
    simpler_tolerance: float = 0.02,
    seed: int = 0,
) -> ModelCheck:
    """Check a loop model against measured data, name the cause of the mismatch and extend it.

    Parameters
    ----------
    op, pv : array_like
        Measured controller output (% of span) and process variable.
    ts : float
        Sampling interval, s.
    sp : array_like, optional
        Measured setpoint; without it a constant setpoint is fitted with the
        controller law.
    model : LoopModel or dict, optional
        The base model (JSON form of :class:`LoopModel`); identified from the
        data when omitted (:func:`analytics.model_check.identify.identify_model`).
        A model with another ``dt`` is used at ``ts``.
    effects : tuple of str
        Effects tried (default: all of :data:`EFFECTS`).
    folds : int
        Pairs of fitting and held-out blocks.
    min_gain : float
        Fraction of the base model's held-out error an effect must remove to be named.
    simpler_tolerance : float
        An effect earlier in :data:`EFFECTS` is preferred when its held-out
        error is within this fraction of the best.
    seed : int
        Seed of the measurement noise in the closed-loop simulations.

    Returns
    -------
    ModelCheck

    Raises
    ------
    DataError
        Signals of different length, not 1-D, missing values, fewer than
        :data:`MIN_SAMPLES` samples, or OP that never moves.
    ModelSpecError
        An invalid model.

    Examples
    --------
    Data from a loop whose process gain is 1.5 times the model's:

    >>> from analytics.model_check.cases import hidden_effect_case
    >>> case = hidden_effect_case("gain_mismatch", seed=3, samples=3000)
    >>> result = check_model(case.op, case.pv, case.ts, sp=case.sp, model=case.base_model)
    >>> result.cause.effect
    'gain_mismatch'
    >>> result.gain.nmse_after < result.gain.nmse_before
    True
    """
    if not (isinstance(ts, int | float) and math.isfinite(ts) and ts > 0):
        raise DataError(f"sampling interval ts must be a positive number of seconds, got {ts!r}")
    op_a = _series("OP", op)
    n = op_a.size
    pv_a = _series("PV", pv, n)
    sp_a = None if sp is None else _series("SP", sp, n)
    if n < MIN_SAMPLES:
        raise DataError(f"a model check needs at least {MIN_SAMPLES} samples, got {n}")
    if not np.ptp(op_a) > 0:
        raise DataError("OP never moves: nothing drives the model")
    if not np.ptp(pv_a) > 0:
        raise DataError("PV never moves: there is nothing to compare the model with")
    unknown = [e for e in effects if e not in EFFECTS]
    if unknown:
        raise DataError(f"unknown effect(s) {unknown}; expected some of {EFFECTS}")

    notes: list[str] = []
    if model is None:
        base, controller_fit, identified = identify_model(op_a, pv_a, ts, sp_a)
        notes.extend(identified)
        source: Literal["given", "identified"] = "identified"
    else:
        base = model if isinstance(model, LoopModel) else LoopModel.from_dict(model)
        if not math.isclose(base.dt, ts, rel_tol=1e-6):
            notes.append(f"the model's dt = {base.dt:g} s differs from the data's {ts:g} s; "
                         f"the model is used at {ts:g} s")
            base = base.with_dt(ts)
        controller_fit = identify_controller(op_a, pv_a, ts, sp_a)
        source = "given"
    if sp_a is None:
        setpoint = controller_fit.setpoint if controller_fit.setpoint is not None else pv_a.mean()
        sp_a = np.full(n, setpoint)
        notes.append(f"no SP measured: a constant setpoint of {setpoint:.4g} is assumed")

    process = base.process
    for name, value in (("tau", process.tau), ("theta", process.theta)):
        if value > TIME_SCALE_LIMIT * n * ts:
            raise ModelSpecError(
                f"process {name} = {value:g} s is more than {TIME_SCALE_LIMIT:g} times the "
                f"record ({n * ts:g} s): the data cannot check such a model"
            )
    oscillation = detect_loop_oscillation(op_a, pv_a, ts)
    settle = min(process.delay_samples(ts), n) + math.ceil(min(3.0 * process.tau / ts, n))
    synchronised = valve_synchronisation(base, op_a)
    warm_up = min(n // 5, max(20, settle + 1, synchronised))
    if synchronised > n // 5:
        until = (f"until sample {synchronised}" if synchronised < n
                 else "throughout the window (OP never pushes it through its band)")
        scored_uncertain = (f"samples {n // 5} to {synchronised - 1}" if synchronised < n
                            else f"every sample from {n // 5} on")
        notes.append(
            f"the model valve's position depends on its unknown initial state {until}; at "
            f"most a fifth of the window is left unscored (the first {n // 5} samples), so "
            f"{scored_uncertain} are scored with that position uncertain"
        )
    reach = float(np.max(np.abs(base.replay(op_a)[1])))
    if not reach <= REPLAY_LIMIT * float(np.max(np.abs(pv_a)) + np.ptp(pv_a)):
        raise ModelSpecError(
            f"the base model's replay of the measured OP reaches {reach:.3g}, more than "
            f"{REPLAY_LIMIT:g} times the measured PV: check the model's gain against the data"
        )
    # Two-fold cross-validation: fit on the even blocks and score on the odd ones,
    # then the other way round, so that every scored sample is held out once.
    halves = _replay_data(base, op_a, pv_a, ts, warm_up, folds, convention=source == "given")
    base_cv = _CrossValidated(halves, tuple(h.predict(base) for h in halves))
    scored_samples = halves[0].fit | halves[0].test
    period = oscillation.period_s

    def residual(cv: _CrossValidated) -> FloatArray:
        return np.asarray((pv_a - cv.held_out_pv())[scored_samples], dtype=np.float64)

    sigma = noise_std(pv_a)
    noise = np.random.default_rng(seed).normal(0.0, sigma, n)
    pv_var = float(np.var(pv_a[warm_up:]))
    lattice = relevant_lattice(pv_a[warm_up:])
    # a PV on a lattice carries the rounding error, of variance q^2 / 12, on top of the noise
    rounding = 0.0 if lattice is None else lattice.resolution**2 / 12.0
    noise_nmse = (sigma**2 + rounding) / pv_var if pv_var > 0 else math.nan

    def evident_against(sse: float) -> frozenset[str]:
        # The quantiser removes at most the rounding error: a lattice is evident only if
        # that is ``min_gain`` of the error left (a noise-free PV written to 6 digits
        # repeats, yet its grid of 1e-4 explains nothing of an NMSE of 0.03).
        matters = lattice is not None and (
            rounding * np.count_nonzero(scored_samples) >= min_gain * sse)
        return frozenset({"measurement_quantization"} if matters else set())

    evident = evident_against(base_cv.sse_test)
    scored, cross_validated, fitted = _try_effects(
        effects, halves, (base, base), base_cv.predictions, base_cv.sse_test, period
    )
    residuals = {effect: residual(cv) for effect, cv in cross_validated.items()}
    chosen, confidence, runner_up = _select(
        scored, residuals, residual(base_cv), min_gain, simpler_tolerance, evident
    )
    # Effects that imitate each other in part: the joint fit says which the data need.
    if chosen is not None and runner_up is not None and (
        {chosen.effect, runner_up} == set(DYNAMICS)
        or {chosen.effect, runner_up} <= set(POSITIONAL)
    ):
        joint = (
            _joint_dynamics(halves, base, fitted, period)
            if chosen.effect in DYNAMICS
            else _joint_both_orders(chosen.effect, runner_up, halves, fitted, period)
        )
        both = residual(_CrossValidated(halves, tuple(c.prediction for c in joint)))
        effect, confidence, runner_up = _nested_verdict(
            chosen.effect, runner_up, both, residuals, min_gain
        )
        chosen = next(c for c in scored if c.effect == effect)
    whole = halves[0].holding_out("none")
    base_fit = whole.predict(base)
    named: list[tuple[Candidate, Cause]] = []
    extended, extended_cv, extended_fit = base, base_cv, base_fit
    if chosen is not None:  # the named cause, refitted on all scored data
        first = fitted[chosen.effect]
        final = fit_effect(
            chosen.effect, whole, base, base_fit, period_s=period,
            seeds=[c.search_point for c in first if c.search_point],
        )
        first_cv = cross_validated[chosen.effect]
        named.append((final, Cause(final.effect, confidence, final.parameters, runner_up,
                                   base_cv.nmse_test, first_cv.nmse_test)))
        extended, extended_cv, extended_fit = final.model, first_cv, final.prediction
        # A second effect: each other effect and the first together, scored the same way
        # against the first alone; only an effect evident in the data when the first leaves
        # no more than noise.
        evident = evident_against(first_cv.sse_test)
        others = (
            effects if first_cv.nmse_test > ADEQUATE_NOISE_RATIO * noise_nmse
            else tuple(e for e in effects if e in evident)
        )
        if set(others) - {chosen.effect}:
            second = _second_effect(
                chosen.effect, others, halves, base, fitted, first_cv, residuals, residual,
                min_gain, simpler_tolerance, evident, period,
            )
            if second is not None:
                pair_cv, (inner, outer), confidence2, runner_up2 = second
                inner_fit = final if inner == chosen.effect else fit_effect(
                    inner, whole, base, base_fit, period_s=period,
                    seeds=[c.search_point for c in fitted[inner] if c.search_point],
                )
                inner_fit, pair = _fit_pair(inner_fit, outer, whole, base, period)
                first_cause = named[0][1]
                if inner == chosen.effect:
                    named[0] = (inner_fit, replace(first_cause, parameters=inner_fit.parameters))
                    named.append((pair, Cause(outer, confidence2, pair.parameters, runner_up2,
                                              first_cv.nmse_test, pair_cv.nmse_test)))
                else:  # the first cause acts on the measured PV: fitted on top of the second
                    named[0] = (pair, replace(first_cause, parameters=pair.parameters))
                    named.append((inner_fit, Cause(inner, confidence2, inner_fit.parameters,
                                                   runner_up2, first_cv.nmse_test,
                                                   pair_cv.nmse_test)))
                extended, extended_cv, extended_fit = pair.model, pair_cv, pair.prediction
    # Confidence never exceeds the share of the held-out PV variance the (extended) model
    # explains: an effect fitted on top of a model that predicts little is little evidence.
    explained = max(1.0 - extended_cv.nmse_test, 0.0)
    named = [(fit, replace(cause, confidence=min(cause.confidence, explained)))
             for fit, cause in named]
    confidence = min(confidence, explained)

    def bias(prediction: Prediction) -> float:
        return float(sp_a[0]) if process.integrating else prediction.pv_bias

    cycle_base = _cycle(base, sp_a, bias(base_fit), noise, period, pv_a, warm_up)
    cycle_ext = (
        _cycle(extended, sp_a, bias(extended_fit), noise, period, pv_a, warm_up)
        if named else cycle_base
    )
    controller_nmse = _controller_nmse(base, op_a[warm_up:], pv_a[warm_up:], sp_a[warm_up:])

    findings = [
        f"Driven by the measured OP, the model misses the measured PV by NMSE "
        f"{base_cv.nmse_test:.3g} on held-out data (noise alone would give about "
        f"{noise_nmse:.2g})."
    ]
    findings.extend(_where(whole, base_cv.held_out_pv(), op_a))
    cb = cycle_base
    if cb.period_measured is not None:
        sim = (
            f"the closed-loop simulation gives {cb.period_simulated:.4g} s and "
            f"{cb.amplitude_simulated:.3g} (period {_pct(cb.period_error)}, amplitude "
            f"{_pct(cb.amplitude_error)})"
            if cb.period_simulated is not None
            else f"the closed-loop simulation does not oscillate (amplitude "
            f"{cb.amplitude_simulated or 0.0:.3g} at that period)"
        )
        findings.append(
            f"The measured loop oscillates with period {cb.period_measured:.4g} s and PV "
            f"amplitude {cb.amplitude_measured:.3g}; {sim}."
        )
    elif cb.period_simulated is not None:
        findings.append(
            f"The closed-loop simulation oscillates with period {cb.period_simulated:.4g} s "
            f"and amplitude {cb.amplitude_simulated:.3g}, but the measured loop does not."
        )
    if controller_nmse > 0.3:
        findings.append(
            f"The model's controller reproduces the measured OP only with NMSE "
            f"{controller_nmse:.2f}: the loop may be in cascade or manual, or tuned otherwise; "
            "the closed-loop comparison is then indicative only."
        )
    if not named:
        tried = ""
        if runner_up is not None:
            closest = next(c for c in scored if c.effect == runner_up)
            tried = f" (closest: {runner_up}, {100 * closest.improvement:+.1f} %)"
        verdict = (
            "the base model is adequate for these data"
            if base_cv.nmse_test <= ADEQUATE_NOISE_RATIO * noise_nmse + ADEQUATE_NMSE
            else f"its held-out NMSE {base_cv.nmse_test:.3g} is well above what noise explains, "
            "so the model is wrong in a way outside the catalogue (or in several at once)"
        )
        findings.append(
            f"No effect in the catalogue removes {100 * min_gain:.0f} % or more of the held-out "
            f"error{tried}: {verdict}."
        )
        causes = [Cause("none", confidence, {}, runner_up, base_cv.nmse_test, base_cv.nmse_test)]
    else:
        causes = [cause for _, cause in named]
        for fit, cause in named:
            findings.append(_cause_sentence(fit, base))
            if cause.runner_up is not None and cause.confidence < CONFIDENT:
                findings.append(_undecided_sentence(cause))
        cycle = [
            f"closed-loop {name} error {_pct(before)} -> {_pct(after)}"
            for name, before, after in (
                ("period", cycle_base.period_error, cycle_ext.period_error),
                ("amplitude", cycle_base.amplitude_error, cycle_ext.amplitude_error),
            )
            if before is not None or after is not None
        ]
        extensions = " and ".join(
            f"{cause.effect} ({describe_parameters(cause.parameters)})" for _, cause in named
        )
        each = (
            " (" + "; ".join(f"{c.effect}: {c.nmse_before:.3g} -> {c.nmse_after:.3g}"
                             for c in causes) + ")"
            if len(causes) > 1 else ""
        )
        findings.append(
            f"Extended with {extensions}, the held-out NMSE falls from {base_cv.nmse_test:.3g} to "
            f"{extended_cv.nmse_test:.3g}{each}" + "".join(f"; {text}" for text in cycle) + "."
        )
    if explained < EXPLAINED_FOR_CONFIDENCE:
        findings.append(
            f"The {'extended' if named else 'base'} model explains only {100 * explained:.0f} % "
            "of the held-out PV variance, so no cause is named with confidence: data with "
            "steps of OP large against the noise (an open-loop step test, or set-point steps), "
            "each held until PV settles, would identify the process first and then decide "
            "the cause."
        )
    return ModelCheck(
        model_source=source,
        base_model=base,
        extended_model=extended,
        nmse_base_fit=base_cv.nmse_fit,
        nmse_base_test=base_cv.nmse_test,
        noise_nmse=noise_nmse,
        controller_nmse=controller_nmse,
        cycle_base=cycle_base,
        findings=tuple(findings),
        cause=causes[0],
        causes=tuple(causes),
        candidates=tuple(scored),
        gain=Gain(base_cv.nmse_test, extended_cv.nmse_test, cycle_base, cycle_ext),
        overlay=Overlay(
            whole.t, pv_a, base_cv.held_out_pv(), extended_cv.held_out_pv(), whole.fit
        ),
        notes=tuple(
            notes + ([controller_fit.note] if controller_fit.note and source == "given" else [])
        ),
    )
