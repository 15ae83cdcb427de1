"""The per-loop pipeline: one window in, one :class:`LoopDiagnosis` out.

Steps, each feeding the next:

1. Data quality (:func:`analytics.quality.assess_quality`).  An unusable
   window stops here with the verdict ``undecided`` and the reasons.
2. Oscillation (:func:`analytics.oscillation.detect_loop_oscillation`) on OP
   and/or PV.  A loop without a regular oscillation is still examined when
   its spectrum shows a weaker cycle (:data:`IRREGULAR_MIN_PROMINENCE`):
   noise makes a sticky valve slip at random moments.  Only a stiction
   finding counts there; otherwise, and for a loop with no cycle at all, the
   verdict is ``no_stiction`` with a note that a valve sticking without
   causing a cycle is not visible in routine data.
3. The stiction battery (:mod:`analytics.stiction.battery`) on the window,
   with the process type given by the user (otherwise inferred, see
   :func:`_infer_process_type`), plus the Hammerstein
   identification (:func:`analytics.quantification.quantify_stiction`) as
   one more method: whether a stiction model explains the data better than
   a healthy valve (:func:`hammerstein_evidence`).  Quantised or compressed
   data blind the nonlinearity tests (Thornhill, Choudhury & Shah 2004), so
   on such data their evidence is set aside with that reason.  The evidence
   is combined by :func:`analytics.stiction.battery.combine`.
4. For a stiction verdict: the size (S, J, fs, fd) from the Hammerstein
   fit and the apparent stiction of the valve signature
   (:func:`analytics.stiction.signature.fit_signature_ellipse`).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from analytics.errors import DataError
from analytics.oscillation import LoopOscillation, detect_loop_oscillation
from analytics.quality import QualityReport, assess_quality
from analytics.quantification import (
    MIN_FIT_R2,
    MIN_R2_GAIN,
    StictionEstimate,
    quantify_stiction,
)
from analytics.stiction.battery import DEFAULT_DETECTORS, BatteryConfig, StictionVerdict, combine
from analytics.stiction.evidence import (
    NO_STICTION,
    STICTION,
    UNDECIDED,
    LoopWindow,
    MethodEvidence,
    ProcessType,
    margin_confidence,
)
from analytics.stiction.signature import EllipseFit, fit_signature_ellipse

__all__ = ["NONLINEARITY_METHODS", "LoopDiagnosis", "diagnose_loop"]

FloatArray = NDArray[np.float64]

NONLINEARITY_METHODS = ("bicoherence", "surrogate")
"""Methods that quantisation and historian compression make unreliable."""

NO_OSCILLATION_CONFIDENCE = 0.6
"""Confidence of ``no_stiction`` for a loop that does not oscillate: a valve can
stick without causing a cycle (e.g. with P-only control), so it is not 1."""

NO_CYCLE_NOTE = (
    "the loop does not oscillate; a valve that sticks without causing a limit cycle "
    "cannot be seen in this window"
)

IRREGULAR_MIN_PROMINENCE = 1.8
"""Spectral prominence (peak over its octave neighbours, see
:mod:`analytics.oscillation`) from which a loop without a *regular* oscillation
is still examined for an irregular stick-slip cycle.  Noise makes a sticky
valve slip at random moments, so its cycle is real but too irregular for
Thornhill's r > 1.  Over 8 h of the synthetic library in hour windows, every
irregular window a sticky valve was found in stood 1.83-4.6 above its
neighbours; noise-driven healthy loops mostly 1.0-1.7, but up to 2.6, and the
battery found stiction in 7 of their 131 windows (3 of them below 1.8).  The
ticket rule's confirmations on separate windows (service) keep the rest from
maintenance."""


@dataclass(frozen=True)
class LoopDiagnosis:
    """Everything the pipeline found in one window of one loop.

    Attributes
    ----------
    samples, ts : int, float
        Window length and sampling interval (s).
    quality : QualityReport
    oscillation : LoopOscillation or None
        None when the data were unusable.
    process_type : str or None
        The process type used ("self-regulating", "integrating" or None).
    process_type_source : {"given", "inferred", "assumed", "unknown"}
        Where it came from: the caller, the Hammerstein identification (an
        integrating model fits clearly), the default assumption
        (self-regulating, the common case) or nowhere (no analysis ran).
    stiction : StictionVerdict
        Verdict, confidence and the evidence of every method.
    quantification : StictionEstimate or None
        Hammerstein estimate of S, J (% of OP span), fs, fd with fit quality;
        None unless the verdict is stiction.
    ellipse : EllipseFit or None
        Apparent stiction from the valve signature (Choudhury et al. 2008).
    """

    samples: int
    ts: float
    quality: QualityReport
    oscillation: LoopOscillation | None
    process_type: ProcessType | None
    process_type_source: str
    cycle_period_s: float | None
    stiction: StictionVerdict
    quantification: StictionEstimate | None
    ellipse: EllipseFit | None

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-ready form (the ``loopwatch analyze --json`` contract)."""
        osc = self.oscillation
        return {
            "samples": self.samples,
            "ts": self.ts,
            "process_type": self.process_type,
            "process_type_source": self.process_type_source,
            "quality": {
                "usable": self.quality.usable,
                "issues": [
                    {"code": i.code, "signal": i.signal, "severity": i.severity,
                     "message": i.message, "value": i.value}
                    for i in self.quality.issues
                ],
            },
            "oscillation": {
                "detected": bool(osc and osc.detected),
                "period_s": osc.period_s if osc else None,
                "regularity": osc.regularity if osc else None,
                "amplitude_op": osc.amplitude_op if osc else None,
                "amplitude_pv": osc.amplitude_pv if osc else None,
                "analysed_period_s": self.cycle_period_s,
                "oscillations": [
                    {"signal": signal, "period_s": o.period_s, "amplitude": o.amplitude,
                     "regularity": o.regularity, "presence": o.presence,
                     "present_from_s": o.present_from_s, "present_to_s": o.present_to_s,
                     "method": o.method}
                    for signal, report in (("op", osc.op if osc else None),
                                           ("pv", osc.pv if osc else None))
                    if report is not None
                    for o in report.oscillations
                ],
            },
            "stiction": {
                "verdict": self.stiction.verdict,
                "confidence": self.stiction.confidence,
                "score": self.stiction.score,
                "reason": self.stiction.reason,
                "methods": {
                    name: {
                        "decision": e.decision,
                        "index": e.index,
                        "confidence": e.confidence,
                        "note": e.note,
                        "details": dict(e.details),
                    }
                    for name, e in self.stiction.methods.items()
                },
            },
            "quantification": None if self.quantification is None
            else self.quantification.to_dict(),
            "apparent_stiction": None if self.ellipse is None else {
                "apparent_stiction": self.ellipse.apparent_stiction,
                "width_ratio": self.ellipse.width_ratio,
                "op_amplitude": self.ellipse.op_amplitude,
                "residual": self.ellipse.residual,
            },
        }


def _fill_missing(x: FloatArray | None) -> FloatArray | None:
    """Linear interpolation over the (few, already reported) non-finite samples."""
    if x is None:
        return None
    ok = np.isfinite(x)
    if ok.all():
        return x
    k = np.arange(x.size)
    return np.interp(k, k[ok], x[ok])


HAMMERSTEIN_GAIN_SCALE = 0.05
"""R^2 gain over the stiction threshold that gives a Hammerstein vote confidence 0.63."""


def hammerstein_evidence(estimate: StictionEstimate) -> MethodEvidence:
    """The Hammerstein fit as a detection method: does a stiction model explain the data?

    The index is the output-error R^2 gained by putting the identified
    stiction model in front of the linear process instead of a healthy
    valve (Jelali 2008; thesis Appendix A).  A gain above the
    quantification's ``min_r2_gain`` votes stiction; a fit that explains the
    data well without needing stiction votes against; a poor fit (below
    ``MIN_FIT_R2``, even one that stiction improves) or an estimate that could
    not be made abstains.
    """
    name = "hammerstein"
    search = estimate.search
    if estimate.S is None or estimate.fit_r2 is None or search is None:
        return MethodEvidence.undecided(name, "; ".join(estimate.issues) or "no estimate")
    gain = estimate.fit_r2 - search.r2_ideal_valve
    threshold = MIN_R2_GAIN
    details = {"fit_r2": estimate.fit_r2, "fit_r2_healthy_valve": search.r2_ideal_valve,
               "S": estimate.S, "J": estimate.J if estimate.J is not None else float("nan")}
    if estimate.stiction_found and estimate.fit_r2 >= MIN_FIT_R2:
        return MethodEvidence(
            name, STICTION, gain, margin_confidence(gain, threshold, HAMMERSTEIN_GAIN_SCALE),
            f"a stiction model (S = {estimate.S:.2f}) raises the fit R2 from "
            f"{search.r2_ideal_valve:.2f} to {estimate.fit_r2:.2f}", details,
        )
    if estimate.fit_r2 < MIN_FIT_R2:
        return MethodEvidence.undecided(
            name, f"neither model fits the data (R2 {estimate.fit_r2:.2f})", gain, details
        )
    return MethodEvidence(
        name, NO_STICTION, gain,
        margin_confidence(min(gain, threshold), threshold, HAMMERSTEIN_GAIN_SCALE / 2),
        f"a healthy valve explains the data as well (R2 {search.r2_ideal_valve:.2f}; "
        f"stiction adds {gain:+.3f})", details,
    )


def _irregular_cycle(oscillation: LoopOscillation) -> float | None:
    """Period of the most prominent spectral candidate of OP or PV when no regular
    oscillation was found and it stands out by :data:`IRREGULAR_MIN_PROMINENCE`."""
    candidates = [
        (method.statistic, method.period_s)
        for report in (oscillation.op, oscillation.pv) if report is not None
        for method in (report.methods.get("spectral_peak"),)
        if method is not None and method.period_s is not None
    ]
    if not candidates:
        return None
    prominence, period = max(candidates)
    return period if prominence >= IRREGULAR_MIN_PROMINENCE else None


def _irregular_verdict(verdict: StictionVerdict, period_s: float) -> StictionVerdict:
    """Only a stiction finding stands for an irregular cycle; anything else is the
    no-oscillation verdict, with the evidence kept for inspection."""
    if verdict.verdict == STICTION:
        return StictionVerdict(
            STICTION, verdict.confidence, verdict.score, verdict.methods,
            f"irregular stick-slip cycle of about {period_s:.0f} s (no regular "
            f"oscillation); {verdict.reason}",
        )
    return StictionVerdict(NO_STICTION, NO_OSCILLATION_CONFIDENCE, verdict.score,
                           verdict.methods, NO_CYCLE_NOTE)


def _infer_process_type(estimate: StictionEstimate | None) -> tuple[ProcessType, str]:
    """Integrating if the Hammerstein identification chose an integrating model with a
    good fit; otherwise self-regulating, the common case (flow, pressure, temperature).

    On the synthetic library the identification never called a self-regulating
    loop integrating, but recognised few integrating ones, so "assumed
    self-regulating" is the honest default and the report says which it was.
    """
    model = None if estimate is None else estimate.model
    if (model is not None and model.integrating and estimate is not None
            and estimate.fit_r2 is not None and estimate.fit_r2 >= MIN_FIT_R2):
        return "integrating", "inferred"
    return "self-regulating", "assumed"


def _set_aside(evidence: MethodEvidence, why: str) -> MethodEvidence:
    return MethodEvidence.undecided(evidence.method, why, evidence.index, evidence.details)


def diagnose_loop(
    *,
    ts: float,
    op: ArrayLike | None = None,
    pv: ArrayLike | None = None,
    sp: ArrayLike | None = None,
    mv: ArrayLike | None = None,
    t: ArrayLike | None = None,
    process_type: ProcessType | None = None,
    ranges: Mapping[str, tuple[float, float]] | None = None,
    battery: BatteryConfig | None = None,
    quantify: bool = True,
) -> LoopDiagnosis:
    """Diagnose one loop window (see the module docstring for the steps).

    Parameters
    ----------
    ts : float
        Sampling interval in seconds.
    op, pv, sp, mv : array_like, optional
        Signals; at least one of OP and PV.  OP in % of span gives S and J
        in % of span.
    t : array_like, optional
        Time stamps (s) for the quality screen; None for uniform sampling.
    process_type : {"self-regulating", "integrating"} or None
        None when unknown: then inferred from the Hammerstein identification
        or assumed self-regulating (``LoopDiagnosis.process_type_source``).
    ranges : mapping, optional
        Engineering ranges per signal for the saturation check.
    battery : BatteryConfig, optional
        How the evidence is combined.
    quantify : bool
        Whether to run the (slower) quantification when stiction is found.

    Raises
    ------
    DataError
        If neither OP nor PV is given or the signals differ in length.
    """
    given = {name: x for name, x in (("op", op), ("pv", pv), ("sp", sp), ("mv", mv))
             if x is not None}
    if "op" not in given and "pv" not in given:
        raise DataError("diagnose_loop needs at least one of op and pv")
    signals = {name: np.asarray(x, dtype=np.float64) for name, x in given.items()}
    source = "given" if process_type is not None else "unknown"
    quality = assess_quality(t, signals, ts, ranges=ranges)
    samples = quality.samples
    if not quality.usable:
        verdict = StictionVerdict(
            UNDECIDED, 0.0, 0.0, {}, "data unusable: " + "; ".join(quality.reasons())
        )
        return LoopDiagnosis(samples, ts, quality, None, process_type, source, None, verdict,
                             None, None)

    clean = {name: _fill_missing(x) for name, x in signals.items()}
    op_clean, pv_clean = clean.get("op"), clean.get("pv")
    oscillation = detect_loop_oscillation(op_clean, pv_clean, ts)
    period_s = oscillation.period_s if oscillation.detected else _irregular_cycle(oscillation)
    if period_s is None:
        verdict = StictionVerdict(NO_STICTION, NO_OSCILLATION_CONFIDENCE, 0.0, {}, NO_CYCLE_NOTE)
        return LoopDiagnosis(samples, ts, quality, oscillation, process_type, source, None,
                             verdict, None, None)

    estimate = None
    if quantify and op_clean is not None and pv_clean is not None:
        estimate = quantify_stiction(
            op_clean, pv_clean, ts, process_type=process_type, period_s=period_s
        )
    if process_type is None:
        process_type, source = _infer_process_type(estimate)
    window = LoopWindow(
        ts=ts, op=op_clean, pv=pv_clean, sp=clean.get("sp"), mv=clean.get("mv"),
        process_type=process_type, period_s=period_s,
    )
    evidence = [d.detect(window) for d in DEFAULT_DETECTORS]
    if estimate is not None:
        evidence.append(hammerstein_evidence(estimate))
    blinding = quality.codes() & {"quantisation", "compression"}
    if blinding:
        why = (f"set aside: {' and '.join(sorted(blinding))} in the data make "
               "nonlinearity tests unreliable")
        evidence = [
            _set_aside(e, why) if e.method in NONLINEARITY_METHODS and e.decision != UNDECIDED
            else e
            for e in evidence
        ]
    verdict = combine(evidence, battery)
    if not oscillation.detected:
        verdict = _irregular_verdict(verdict, period_s)

    ellipse = None
    if verdict.verdict == STICTION and op_clean is not None and pv_clean is not None:
        try:
            ellipse = fit_signature_ellipse(op_clean, pv_clean, period_s / ts)
        except DataError:
            ellipse = None  # too few cycles for a signature; the verdict stands
    else:
        estimate = None  # sizes are reported for sticky valves only
    return LoopDiagnosis(
        samples, ts, quality, oscillation, process_type, source, period_s, verdict, estimate,
        ellipse,
    )

