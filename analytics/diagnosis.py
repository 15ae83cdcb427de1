"""The per-loop pipeline: one window in, one :class:`LoopDiagnosis` out.

Steps, each feeding the next:

1. Data quality (:func:`analytics.quality.assess_quality`).  An unusable
   window stops here with the verdict ``undecided`` and the reasons.
2. Oscillation (:func:`analytics.oscillation.detect_loop_oscillation`) on OP
   and/or PV.  A loop without a regular oscillation is still examined for a
   cycle when its spectrum shows a weaker one
   (:data:`IRREGULAR_MIN_PROMINENCE`): noise makes a sticky valve slip at
   random moments.
   Every usable window in which the controller moved the valve is examined:
   a window whose OP travel beyond noise is below
   :data:`analytics.stiction.stick_jump.MIN_TRAVEL` is ``undecided`` ("not
   enough valve movement to judge"), with or without a cycle; one with
   enough travel goes on (without OP, a cycle of PV alone).  A frozen PV
   while OP travels :data:`STUCK_MIN_TRAVEL` is the valve (or its positioner
   or transmitter) stuck, not unusable data.
3. The stiction battery (:mod:`analytics.stiction.battery`).  With a cycle:
   the cycle methods, the transient methods of
   :mod:`analytics.stiction.stick_jump` and the Hammerstein identification
   (:func:`analytics.quantification.quantify_stiction`) as one more method
   (:func:`hammerstein_evidence`), with the process type given by the user
   (otherwise inferred, see :func:`_infer_process_type`).  Quantised or
   compressed data blind the nonlinearity tests (Thornhill, Choudhury &
   Shah 2004), so on such data their evidence is set aside with that
   reason.  Without a cycle, or when an irregular cycle does not show
   stiction: the transient methods alone (stick-jump episodes and stuck
   sections, Kano et al. 2004), which need holds, not a period; when the
   process type is only assumed, PV's slope is read as well and taken when
   it shows stiction (a sticky level valve holds the slope).  The verdict
   names the pattern: ``limit_cycle``, ``irregular_cycle``, ``stick_jump``
   or ``stuck`` (:data:`PATTERNS`), with the episodes as evidence.
4. For a stiction verdict: the size (S, J, fs, fd) from the Hammerstein
   fit (with a process gain known from elsewhere, fitted again with it:
   :func:`analytics.quantification.quantify_with_gain`) and the apparent
   stiction of the valve signature
   (:func:`analytics.stiction.signature.fit_signature_ellipse`) on a
   cycle, and the stick band read off the episodes
   (:func:`episode_stick_band`) beside them.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from analytics.errors import DataError
from analytics.oscillation import (
    LoopOscillation,
    Oscillation,
    OscillationReport,
    detect_loop_oscillation,
    envelope_variation,
)
from analytics.quality import QualityIssue, QualityReport, assess_quality
from analytics.quantification import (
    MIN_FIT_R2,
    MIN_R2_GAIN,
    StictionEstimate,
    quantify_stiction,
    quantify_with_gain,
)
from analytics.replay import ModelTrace, model_trace
from analytics.serial import Reader
from analytics.signals import shared_results
from analytics.stiction.battery import (
    DEFAULT_DETECTORS,
    TRANSIENT_DETECTORS,
    BatteryConfig,
    StictionVerdict,
    TransientDetector,
    combine,
)
from analytics.stiction.episode_size import EpisodeSize, SizeComparison, compare_sizes, episode_size
from analytics.stiction.evidence import (
    INTEGRATING,
    NO_STICTION,
    STICTION,
    UNDECIDED,
    LoopWindow,
    MethodEvidence,
    ProcessType,
    margin_confidence,
)
from analytics.stiction.signature import EllipseFit, fit_signature_ellipse
from analytics.stiction.stick_jump import (
    MIN_TRAVEL,
    EpisodeAnalysis,
    StickEpisode,
    analyse_window,
    op_travel,
    robust_noise,
)
from analytics.types import FloatArray

__all__ = [
    "NONLINEARITY_METHODS",
    "PATTERNS",
    "LoopDiagnosis",
    "diagnose_loop",
    "episode_stick_band",
    "transient_verdict",
]


NONLINEARITY_METHODS = ("bicoherence", "surrogate")
"""Methods that quantisation and historian compression make unreliable."""

PATTERNS = ("limit_cycle", "irregular_cycle", "stick_jump", "stuck")
"""How a sticky valve shows in the window: a regular stiction cycle, an
irregular stick-slip cycle, holds and jumps without a sustained cycle, or a
valve that did not move at all while OP travelled far."""

STUCK_MIN_TRAVEL = 10.0
"""OP travel beyond noise (OP units, % of span) with a frozen PV that makes the
window a ``stuck`` finding (valve, positioner or transmitter failed) rather
than unusable data: no controller drives a healthy valve 10 % without the
process answering."""

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
        Apparent stiction from the OP-PV valve signature (Choudhury et al. 2008),
        with the ellipse's geometry, which the signature plot draws.
    pattern : str or None
        How the sticky valve shows (one of :data:`PATTERNS`); None unless
        the verdict is stiction.
    episodes : tuple of StickEpisode
        The stick-jump episodes found (evidence to mark on the trend).
    op_travel : float or None
        OP travel beyond noise over the window (OP units); None if not
        measured (no OP, or unusable data).
    episode_stick_band : float or None
        Stick band read off the episodes (:func:`episode_stick_band`).
    episode_size : EpisodeSize or None
        ``S`` from OP's travel between its turns and the slips
        (:func:`analytics.stiction.episode_size.episode_size`); None unless the
        verdict is stiction with episodes.
    size_comparison : SizeComparison or None
        Whether that ``S`` agrees with the Hammerstein estimate's; None unless both
        exist.
    model_trace : ModelTrace or None
        The estimate's valve and process replayed on the window, its last periods
        (:func:`analytics.replay.model_trace`), which the signature plot draws; None
        without an estimate and a period, or with gaps in OP or PV.
    envelope_variation : float or None
        How steady the detected oscillation's amplitude is
        (:func:`analytics.oscillation.envelope_variation` of OP, else PV):
        near 0 for a limit cycle or a periodic forcing, about 0.52 for a
        lightly damped loop driven by noise (an over-tuned loop); None
        without an oscillation or with fewer than eight periods.
    pv_noise : float or None
        PV's noise standard deviation from its first differences
        (:func:`~analytics.stiction.stick_jump.robust_noise`), with which the tuning
        advice checks its retunes (:func:`analytics.tuning.advise`); None unless the
        verdict is stiction.
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
    pattern: str | None = None
    episodes: tuple[StickEpisode, ...] = ()
    op_travel: float | None = None
    episode_stick_band: float | None = None
    envelope_variation: float | None = None
    episode_size: EpisodeSize | None = None
    size_comparison: SizeComparison | None = None
    model_trace: ModelTrace | None = None
    pv_noise: float | None = None

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
                "pv_noise": self.pv_noise,
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
                "envelope_variation": self.envelope_variation,
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
                "pattern": self.pattern,
                "op_travel": self.op_travel,
                "episode_stick_band": self.episode_stick_band,
                "episode_size": None if self.episode_size is None else {
                    **self.episode_size.to_dict(),
                    "agrees_with_hammerstein": None if self.size_comparison is None
                    else self.size_comparison.agree,
                    "note": None if self.size_comparison is None else self.size_comparison.note,
                },
                "episodes": [
                    {"start_s": e.start * self.ts, "jump_s": e.jump_at * self.ts,
                     "end_s": e.end * self.ts, "op_travel": e.op_travel,
                     "pv_jump": e.pv_jump, "op_during_jump": e.op_during_jump}
                    for e in self.episodes
                ],
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
            "apparent_stiction": None if self.ellipse is None else self.ellipse.to_dict(),
            "model_trace": None if self.model_trace is None else self.model_trace.to_dict(),
        }

    @classmethod
    def from_dict(cls, d: Mapping[str, Any], *, lenient: bool = False) -> LoopDiagnosis:
        """The diagnosis of :meth:`to_dict`'s form (a stored or an ``analyze --json`` one):
        ``to_dict(from_dict(d)) == d``.

        What :meth:`to_dict` does not keep is left empty: of the oscillation the
        per-signal method results (empty), ``periods_consistent`` (None), each
        oscillation's ``power_fraction`` (NaN; its frequency is ``1 / period_s``), and a
        signal's report only where it lists an oscillation; of the quantification see
        :meth:`StictionEstimate.from_dict`.  The oscillation is None where the data were
        unusable; the episodes listed are the consistent ones (``consistent`` True), their
        times in samples ``round(t_s / ts)``.

        ``lenient`` reads a diagnosis stored by an older version (or a partial one). Every
        version stored ``samples`` and ``ts`` (the episodes need ``ts``); later ones added
        ``oscillations``, ``envelope_variation``, the pattern, ``op_travel``, the episodes
        and their band (26 Nov 2026), the ellipse's geometry (26 Nov), ``episode_size`` (1
        Dec), ``model_trace`` and ``quality.pv_noise`` (2 Dec; these two read None where
        missing, strict or not). A missing field reads None, except ``quality.usable``,
        ``oscillation.detected``, ``stiction_found`` and ``trustworthy`` (False),
        ``stiction.confidence`` (0), ``process_type_source`` ("unknown"), the texts (empty)
        and the lists and ``methods`` (empty); the oscillation is read also for unusable
        data (not detected); an ``apparent_stiction`` stored before its geometry
        (``centre``, ``semi_axes``, ``angle``) reads None, and a quantification without its
        ``process`` has no ``model``.

        Raises
        ------
        DataError
            A field is missing or of the wrong kind; the message names it and where
            (``loop diagnosis.stiction.methods.hammerstein``).
        """
        read = Reader(d, "loop diagnosis", lenient=lenient)
        samples, ts = read("samples"), read("ts")
        quality = read.part("quality")
        report = QualityReport(
            quality("usable", False),
            tuple(QualityIssue(i("code", ""), i("signal"), i("severity", ""), i("message", ""),
                               i("value"))
                  for i in quality.items("issues")),
            ts, samples)
        osc, stiction = read.part("oscillation"), read.part("stiction")
        methods = stiction.part("methods")
        size = stiction("episode_size")
        agrees = None if size is None else stiction.part("episode_size")("agrees_with_hammerstein")
        quantification = read("quantification")
        return cls(
            samples=samples, ts=ts, quality=report,
            oscillation=_oscillation_from_dict(osc) if report.usable or lenient else None,
            process_type=read("process_type"),
            process_type_source=read("process_type_source", "unknown"),
            cycle_period_s=osc("analysed_period_s"),
            stiction=StictionVerdict(
                stiction("verdict"), stiction("confidence", 0.0), stiction("score"),
                {name: MethodEvidence(name, e("decision"), e("index"), e("confidence"),
                                      e("note"), dict(e("details", {})))
                 for name in methods.d for e in (methods.part(name),)},
                stiction("reason", "")),
            quantification=None if quantification is None else StictionEstimate.from_dict(
                quantification, f"{read.where}.quantification", lenient=lenient),
            ellipse=_ellipse_from_dict(read),
            pattern=stiction("pattern"),
            episodes=tuple(
                StickEpisode(round(e("start_s") / ts), round(e("end_s") / ts),
                             round(e("jump_s") / ts), e("op_travel"), e("pv_jump"),
                             e("op_during_jump"), True)
                for e in stiction.items("episodes")),
            op_travel=stiction("op_travel"), episode_stick_band=stiction("episode_stick_band"),
            envelope_variation=osc("envelope_variation"),
            episode_size=None if size is None else EpisodeSize.from_dict(
                size, f"{stiction.where}.episode_size"),
            size_comparison=None if agrees is None else SizeComparison(
                agrees, stiction.part("episode_size")("note")),
            model_trace=None if read.get("model_trace") is None else ModelTrace.from_dict(
                read("model_trace"), f"{read.where}.model_trace"),
            pv_noise=quality.get("pv_noise"),
        )


def _oscillation_from_dict(read: Reader) -> LoopOscillation:
    """The oscillation of :meth:`LoopDiagnosis.to_dict`'s form (see
    :meth:`LoopDiagnosis.from_dict` for what it does not keep)."""
    found: dict[str, list[Oscillation]] = {"op": [], "pv": []}
    for o in read.items("oscillations"):
        signal = o("signal")
        if signal not in found:
            raise DataError(f"{o.where}.signal: expected 'op' or 'pv', got {signal!r}")
        found[signal].append(Oscillation(
            o("period_s"), 1.0 / o("period_s"), o("regularity"), o("amplitude"), math.nan,
            o("presence"), o("present_from_s"), o("present_to_s"), o("method")))
    op, pv = (OscillationReport(True, tuple(found[s])) if found[s] else None
              for s in ("op", "pv"))
    return LoopOscillation(read("detected", False), read("period_s"), read("regularity"),
                           read("amplitude_op"), read("amplitude_pv"), None, op, pv)


def _ellipse_from_dict(read: Reader) -> EllipseFit | None:
    """The ``apparent_stiction`` of a diagnosis's JSON form back; None where it is (and,
    leniently, where it was stored without its geometry)."""
    stored = read("apparent_stiction")
    if stored is None or (read.lenient and "centre" not in stored):
        return None
    try:
        return EllipseFit.from_dict(Reader(stored, f"{read.where}.apparent_stiction").d)
    except KeyError as missing:
        raise DataError(f"{read.where}.apparent_stiction: the field {missing.args[0]!r} "
                        "is missing") from missing


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
            f"a stiction model (S = {estimate.S:.2f} % of OP span) raises the fit R2 from "
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


def transient_verdict(
    analysis: EpisodeAnalysis,
    battery: BatteryConfig | None = None,
    detectors: Sequence[TransientDetector] = TRANSIENT_DETECTORS,
) -> StictionVerdict:
    """The verdict of the transient methods alone (no cycle to judge by).

    Only they can apply, so one deciding method is enough; a stiction
    verdict's reason says what the episodes show.
    """
    evidence = [d.decide(analysis) for d in detectors]
    config = battery or BatteryConfig()
    verdict = combine(evidence, BatteryConfig(config.weights, config.threshold, 1))
    if verdict.verdict == STICTION:
        seen = []
        if analysis.episodes:
            seen.append(f"{len(analysis.episodes)} episode(s) of PV holding while OP pushed, "
                        "then jumping")
        stuck = verdict.methods.get("stuck_sections")
        if stuck is not None and stuck.decision == STICTION:
            seen.append(f"PV held through an OP reversal of {analysis.hold_reversal:.3g}")
        reason = (f"stick-jump without a sustained cycle: {'; '.join(seen)}; "
                  f"{verdict.reason}")
        return StictionVerdict(STICTION, verdict.confidence, verdict.score,
                               verdict.methods, reason)
    return verdict


CYCLE_SLIP_BANDS = 5.0
"""Smallest PV jump (in hold bands) of a stick-jump episode on a regular cycle.
A smooth swing through its peak is cut by the band into holds whose levels
differ by two to three bands, which look like small slips; a valve's slip is
a fast move well beyond that (4-28 bands on the sticky valves of the synthetic
library and the ISDB, 2.0-4.4 on the external sines of the library)."""


def cycle_slips(analysis: EpisodeAnalysis) -> EpisodeAnalysis:
    """``analysis`` with only the episodes whose jump reaches
    :data:`CYCLE_SLIP_BANDS`: what counts as a slip on a regular cycle."""
    return dataclasses.replace(analysis, episodes=tuple(
        e for e in analysis.episodes if abs(e.pv_jump) >= CYCLE_SLIP_BANDS * analysis.band))


def episode_stick_band(episodes: tuple[StickEpisode, ...]) -> float | None:
    """Stick band from the episodes: the median OP travel while the valve held.

    Each hold ends when OP has pushed through the stick band (Kano et al.
    2004: S is the OP change over a sticking section).  After a reversal the
    travel is the whole band S; in the same direction only ``S - J`` (Kano's
    model), so the median lies between the two and reads low when the
    valve slips often in one direction.  None without episodes.
    """
    if not episodes:
        return None
    return float(np.median([abs(e.op_travel) for e in episodes]))


def _stuck_verdict(quality: QualityReport, op: FloatArray | None) -> tuple[
        StictionVerdict, float] | None:
    """A frozen PV while OP travelled far: the valve (or its positioner or the
    transmitter) is stuck.  None unless PV's flat line is the only fatal issue
    and OP travelled :data:`STUCK_MIN_TRAVEL`."""
    fatal = {(i.code, i.signal) for i in quality.issues if i.severity == "fatal"}
    if op is None or not fatal or not fatal <= {("flatline", "pv"), ("constant", "pv")}:
        return None
    travel = op_travel(op[np.isfinite(op)])
    if travel < STUCK_MIN_TRAVEL:
        return None
    reason = (f"stuck: OP travelled {travel:.3g} while PV stayed frozen; the valve, its "
              "positioner or the transmitter does not respond")
    return StictionVerdict(STICTION, 1.0 - float(np.exp(-travel / STUCK_MIN_TRAVEL)), 1.0, {},
                           reason), travel


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


def _envelope_variation(oscillation: LoopOscillation, x: FloatArray | None, ts: float
                        ) -> float | None:
    """:func:`~analytics.oscillation.envelope_variation` of the detected oscillation in
    ``x``; None without one or with fewer than eight periods."""
    if not oscillation.detected or oscillation.period_s is None or x is None:
        return None
    try:
        return envelope_variation(x, oscillation.period_s / ts)
    except DataError:
        return None


def _set_aside(evidence: MethodEvidence, why: str) -> MethodEvidence:
    return MethodEvidence.undecided(evidence.method, why, evidence.index, evidence.details)


@shared_results()  # the methods share their filtered signals and noise levels
def diagnose_loop(
    *,
    ts: float,
    op: ArrayLike | None = None,
    pv: ArrayLike | None = None,
    sp: ArrayLike | None = None,
    mv: ArrayLike | None = None,
    t: ArrayLike | None = None,
    process_type: ProcessType | None = None,
    process_gain: float | None = None,
    sizing_pv: ArrayLike | None = None,
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
    process_gain : float, optional
        The process gain from MV to PV known from elsewhere (a step test, the
        plant's process model), as :func:`analytics.quantification.quantify_stiction`
        takes it; needs ``process_type``.  The verdict is reached with the gain
        fitted; a sticky valve is then sized with this gain
        (:func:`analytics.quantification.quantify_with_gain`): a limit cycle
        pins the PV step ``K J`` of a slip better than J.
    sizing_pv : array_like, optional
        PV less the known effect of the process's other inputs (the other
        valves of a unit, through its process matrix), as long as PV: with
        ``process_gain``, a sticky valve is sized on it (fitted anew with the
        gain fitted, then with the given one), so that the gain is that of
        the valve alone.
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
    if process_gain is not None and process_type is None:
        raise DataError("a process_gain needs the process_type it is the gain of")
    sizing = None if sizing_pv is None else _fill_missing(np.asarray(sizing_pv, dtype=np.float64))
    if sizing is not None and (pv is None or sizing.shape != np.shape(pv)
                               or not np.isfinite(sizing).any()):
        raise DataError("sizing_pv must be as long as pv and hold finite samples")
    signals = {name: np.asarray(x, dtype=np.float64) for name, x in given.items()}
    source = "given" if process_type is not None else "unknown"
    quality = assess_quality(t, signals, ts, ranges=ranges)
    samples = quality.samples
    if not quality.usable:
        stuck = _stuck_verdict(quality, signals.get("op"))
        if stuck is not None:
            return LoopDiagnosis(samples, ts, quality, None, process_type, source, None,
                                 stuck[0], None, None, "stuck", (), stuck[1])
        verdict = StictionVerdict(
            UNDECIDED, 0.0, 0.0, {}, "data unusable: " + "; ".join(quality.reasons())
        )
        return LoopDiagnosis(samples, ts, quality, None, process_type, source, None, verdict,
                             None, None)

    clean = {name: _fill_missing(x) for name, x in signals.items()}
    op_clean, pv_clean = clean.get("op"), clean.get("pv")
    oscillation = detect_loop_oscillation(op_clean, pv_clean, ts)
    period_s = oscillation.period_s if oscillation.detected else _irregular_cycle(oscillation)
    travel = None
    if op_clean is not None:
        travel = op_travel(op_clean)
    # Even a regular cycle needs the valve to travel: a micro-cycle of a tenth of
    # a percent of OP exposes no stick band worth a repair (healthy plant_dev
    # flows show them).  Without OP, a regular cycle of PV can still be judged.
    if (travel is not None and travel < MIN_TRAVEL) or (travel is None and period_s is None):
        cycle = ("no cycle" if period_s is None
                 else "a cycle" if oscillation.detected else "no regular cycle")
        seen = "no OP" if travel is None else f"OP travelled {travel:.3g}"
        verdict = StictionVerdict(
            UNDECIDED, 0.0, 0.0, {},
            f"not enough valve movement to judge: {cycle} and {seen} (at least "
            f"{MIN_TRAVEL:g} needed)",
        )
        return LoopDiagnosis(samples, ts, quality, oscillation, process_type, source, None,
                             verdict, None, None, None, (), travel)

    estimate = None
    if quantify and period_s is not None and op_clean is not None and pv_clean is not None:
        estimate = quantify_stiction(
            op_clean, pv_clean, ts, process_type=process_type, period_s=period_s
        )
    if process_type is None:
        process_type, source = _infer_process_type(estimate)
    window = LoopWindow(
        ts=ts, op=op_clean, pv=pv_clean, sp=clean.get("sp"), mv=clean.get("mv"),
        process_type=process_type, period_s=period_s,
    )
    # Historian compression and a coarse transmitter hold PV and let it jump by
    # themselves: holds and jumps then say nothing about the valve.
    archived = sorted(quality.codes("pv") & {"quantisation", "compression"})
    analysis = None if archived else analyse_window(window)
    transient = [] if analysis is None else [d.decide(analysis) for d in TRANSIENT_DETECTORS]
    pattern = None
    if period_s is not None:
        # On a cycle the transient methods add the evidence of its holds, not of
        # their absence (a stiction cycle's noisy holds split); on a regular
        # cycle only clear slips count (:func:`cycle_slips`).
        evidence = [d.detect(window) for d in DEFAULT_DETECTORS]
        if oscillation.detected and analysis is not None:
            analysis = cycle_slips(analysis)  # the episodes reported are those that count
            transient = [d.decide(analysis) for d in TRANSIENT_DETECTORS]
        evidence += [
            e if e.decision != NO_STICTION
            else _set_aside(e, "set aside: on a cycle only holds count, not their absence")
            for e in transient
        ]
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
        if oscillation.detected:
            pattern = "limit_cycle"
        elif verdict.verdict == STICTION:
            pattern = "irregular_cycle"
            verdict = StictionVerdict(
                STICTION, verdict.confidence, verdict.score, verdict.methods,
                f"irregular stick-slip cycle of about {period_s:.0f} s (no regular "
                f"oscillation); {verdict.reason}",
            )
    if pattern is None and analysis is not None:
        # No cycle, or an irregular one that did not show stiction: judge the holds.
        verdict = transient_verdict(analysis, battery)
        pattern = "stick_jump"
        period_s = None
        if source == "assumed" and verdict.verdict != STICTION:
            # The process type is a guess: a sticky valve on a level holds PV's
            # slope, not PV.  Read the slope too; it is taken only if its
            # stick-jump episodes find stiction (a held slope alone is no slip:
            # a healthy flow's smoothed slope held through an OP reversal in a
            # part of a plant_dev window).  Without the type given it finds 18 of
            # the 20 sticky valves of the transient library, none of its 21
            # healthy look-alikes.
            slope = analyse_window(dataclasses.replace(window, process_type=INTEGRATING))
            slope_verdict = None if slope is None else transient_verdict(slope, battery)
            if slope is not None and slope_verdict is not None \
                    and slope_verdict.verdict == STICTION \
                    and slope_verdict.methods["stick_jump"].decision == STICTION:
                analysis, process_type, source = slope, INTEGRATING, "inferred"
                verdict = StictionVerdict(
                    STICTION, slope_verdict.confidence, slope_verdict.score,
                    slope_verdict.methods,
                    "read as an integrating process (PV's slope holds and jumps, as a "
                    f"level's does behind a sticky valve): {slope_verdict.reason}")
    elif pattern is None:
        why = (f"PV shows {' and '.join(archived)}, which holds it and lets it jump like a "
               "sticky valve" if archived else "stick-jump episodes need both OP and PV")
        verdict = StictionVerdict(UNDECIDED, 0.0, 0.0, {},
                                  f"no cycle, and the holds cannot be judged: {why}")

    ellipse = None
    episodes = () if analysis is None else analysis.episodes
    if verdict.verdict == STICTION and period_s is not None and op_clean is not None \
            and pv_clean is not None:
        try:
            ellipse = fit_signature_ellipse(op_clean, pv_clean, period_s / ts)
        except DataError:
            ellipse = None  # too few cycles for a signature; the verdict stands
    if verdict.verdict != STICTION:
        estimate = None  # sizes are reported for sticky valves only
        pattern = None
    elif estimate is not None and process_gain is not None and process_type is not None \
            and op_clean is not None and pv_clean is not None:
        sized_on, fitted = pv_clean, estimate
        if sizing is not None:  # without an estimate on it, the valve is sized as found
            sized_on = sizing
            fitted = quantify_stiction(op_clean, sizing, ts, process_type=process_type,
                                       period_s=estimate.period_s)
        if fitted.S is not None:
            estimate = quantify_with_gain(fitted, op_clean, sized_on, ts,
                                          process_type=process_type, process_gain=process_gain)
    sized = None
    compared = None
    if verdict.verdict == STICTION and op_clean is not None:
        sized = episode_size(op_clean, episodes)
        if sized is not None and estimate is not None and estimate.S is not None:
            compared = compare_sizes(sized, estimate.S, estimate.S_interval)
    return LoopDiagnosis(
        samples, ts, quality, oscillation, process_type, source, period_s, verdict, estimate,
        ellipse, pattern, episodes, travel,
        episode_stick_band(episodes) if verdict.verdict == STICTION else None,
        _envelope_variation(oscillation, op_clean if op_clean is not None else pv_clean, ts),
        sized, compared,
        None if estimate is None or "op" not in signals or "pv" not in signals
        else model_trace(signals["op"], signals["pv"], ts, estimate, period_s),
        None if verdict.verdict != STICTION or pv_clean is None else robust_noise(pv_clean),
    )
