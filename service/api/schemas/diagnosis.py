"""A loop's diagnosis as the latest analysis run stored it (``diagnosis`` of
``GET /api/v1/loops/{id}/health``): :meth:`analytics.diagnosis.LoopDiagnosis.to_dict`
plus what the service adds (health, first sample, KPIs, the valve's final verdict, the
stretch judged when the loop was in manual).

The models keep keys they do not name: stored diagnoses were written by other
versions of the analysis.  They describe the JSON as stored and fill in nothing (the
health answer leaves out what a run did not store), so their defaults are None; the
service's own reading (:class:`service.stored.StoredDiagnosis`) fills the defaults of
``LoopDiagnosis.from_dict(..., lenient=True)`` to compute with (``detected`` False,
no oscillations), which an answer must not invent for an old run.
"""

from __future__ import annotations

from typing import Any

from service.api.schemas.base import OpenSchema


class HarrisPublic(OpenSchema):
    """The minimum-variance benchmark of the window (:class:`analytics.kpi.HarrisIndex`;
    Desborough and Harris 1992)."""

    ratio: float | None = None
    """Harris index: minimum variance / mean square error, 1 at minimum-variance control,
    towards 0 worse."""
    normalised: float | None = None
    """Desborough-Harris normalised index, 1 - ratio."""
    mv_variance: float | None = None
    """Estimated minimum achievable variance, (% of span)^2."""
    mse: float | None = None
    """Mean square of SP - PV, (% of span)^2."""
    dead_time: int | None = None
    """The dead time used, samples (the zero-order hold's included)."""


class KpisPublic(OpenSchema):
    """The loop's KPIs over one window (:meth:`analytics.kpi.LoopKpis.to_dict`); the
    fields not named here (error statistics, valve travel, reversals, saturation,
    set-point responses, service factor, oscillation index, notes) are described there."""

    harris: HarrisPublic | None = None
    """Null when the dead time is unknown (``dead_time_note`` says why) or the window
    too short."""
    dead_time_source: str | None = None
    """Where the Harris index's dead time came from: ``configured`` (the loop's process
    model), ``identified`` (from the window's set-point steps or the operator's OP moves
    in manual: :func:`analytics.kpi.identify_dead_time`; never from the loop under
    feedback alone, where the delay cannot be identified) or ``unknown``."""
    dead_time_note: str | None = None
    """The same in words, to show beside the index: ``configured``, ``identified from
    set-point steps``, ``identified from the operator's OP moves in manual``, or
    ``unknown: ...`` with the reason."""
    dead_time_samples: int | None = None
    """The dead time d in samples (the hold's counted); null when unknown."""
    dead_time_s: float | None = None
    """The same in seconds, (d - 1) ts."""


class QualityIssuePublic(OpenSchema):
    """One problem found in the window's data (:class:`analytics.quality.QualityIssue`)."""

    code: str | None = None
    """Machine-readable kind, e.g. ``too_few_samples``, ``gaps``, ``quantisation``."""
    signal: str | None = None
    """The signal it concerns (``op``, ``pv``, ``sp``, ``t``); null for the window."""
    severity: str | None = None
    """``fatal`` (the window cannot be analysed), ``warning`` or ``info``."""
    message: str | None = None
    """The problem in one sentence."""
    value: float | None = None
    """The number behind it (the measured figure)."""


class QualityPublic(OpenSchema):
    """Whether the window's data could be analysed."""

    usable: bool | None = None
    pv_noise: float | None = None
    """PV's noise standard deviation (PV units, from its first differences) of a window
    with a sticky valve; null otherwise."""
    issues: list[QualityIssuePublic] | None = None
    """Each problem found: ``code``, ``signal``, ``severity``, ``message``, ``value``."""


class SignalOscillationPublic(OpenSchema):
    """One oscillation of OP or PV (:class:`analytics.oscillation.Oscillation`)."""

    signal: str | None = None
    """``op`` or ``pv``."""
    period_s: float | None = None
    """Period, s (from the ACF zero crossings of the band-passed signal)."""
    amplitude: float | None = None
    """Half peak-to-peak of the band-passed component, % of span (median over the
    complete cycles)."""
    regularity: float | None = None
    """Thornhill's regularity r (above 1: regular)."""
    presence: float | None = None
    """Share of the window in which the oscillation is present."""
    present_from_s: float | None = None
    """Start of that stretch, s from the window's first sample; null when not measured."""
    present_to_s: float | None = None
    """Its end, s from the window's first sample."""
    method: str | None = None
    """``acf_regularity`` (the whole window) or ``segment_acf_regularity`` (only segments
    of it)."""


class OscillationPublic(OpenSchema):
    """The loop's oscillation (:class:`analytics.oscillation.LoopOscillation`)."""

    detected: bool | None = None
    period_s: float | None = None
    """Period, s."""
    regularity: float | None = None
    """Thornhill's regularity r (above 1: a regular oscillation)."""
    amplitude_op: float | None = None
    """OP amplitude, % of span."""
    amplitude_pv: float | None = None
    """PV amplitude, % of span."""
    analysed_period_s: float | None = None
    """The period the cycle shapes were analysed at, s."""
    envelope_variation: float | None = None
    """How steady the oscillation's amplitude is: near 0 for a limit cycle or a periodic
    forcing, about 0.52 for a loop cycling by its own tuning (noise-driven resonance);
    null without an oscillation or with fewer than eight periods."""
    oscillations: list[SignalOscillationPublic] | None = None
    """Every oscillation of OP and PV: ``signal``, ``period_s``, ``amplitude``,
    ``regularity``, ``presence`` and its span ``present_from_s``..``present_to_s``,
    ``method``."""


class EpisodeSizePublic(OpenSchema):
    """The valve's bands read off its stick-jump episodes
    (:class:`analytics.stiction.episode_size.EpisodeSize`)."""

    S: float | None = None
    """Median OP travel from OP's turn to the slip over the episodes after a reversal,
    % of span; null without a reversal."""
    S_range: list[float] | None = None
    """The smallest and largest of those travels."""
    reversals: int = 0
    """Episodes after an OP reversal."""
    same_direction_band: float | None = None
    """Median OP travel between slips without a reversal (between J and S)."""
    same_direction: int = 0
    """Episodes without a reversal."""
    agrees_with_hammerstein: bool | None = None
    """Whether S lies within the Hammerstein interval widened by the episodes' error;
    null without a Hammerstein estimate."""
    note: str | None = None
    """The comparison in one sentence."""


class EpisodePublic(OpenSchema):
    """One stick-jump episode (:class:`analytics.stiction.stick_jump.StickEpisode`)."""

    start_s: float | None = None
    """Start of the hold, s from the window's first sample."""
    jump_s: float | None = None
    """The slip, s from the window's first sample."""
    end_s: float | None = None
    """End of the episode, s from the window's first sample."""
    op_travel: float | None = None
    """Net OP change during the hold, % of span: the band the controller pushed through."""
    pv_jump: float | None = None
    """Change of the valve proxy from the hold's level to the next (PV units; per second
    for an integrating process)."""
    op_during_jump: float | None = None
    """Net OP change during the jump itself."""


class MethodEvidencePublic(OpenSchema):
    """One detection method's evidence (:class:`analytics.stiction.evidence.MethodEvidence`)."""

    decision: str | None = None
    """``stiction``, ``no_stiction`` or ``undecided``, with the method's published
    thresholds."""
    index: float | None = None
    """The method's index (e.g. the area ratio, NGI); null when it could not be computed."""
    confidence: float | None = None
    """0 to 1: how clearly the index lies on its side of the thresholds."""
    note: str | None = None
    """What the index means here, or why the method is undecided."""
    details: dict[str, Any] | None = None
    """Further numbers of the method (secondary indices, fit errors)."""


class StictionPublic(OpenSchema):
    """The loop's own stiction verdict and the evidence of every method."""

    verdict: str | None = None
    """``stiction``, ``no_stiction`` or ``undecided``."""
    confidence: float | None = None
    """0 to 1."""
    score: float | None = None
    """The weighted vote of the methods."""
    reason: str | None = None
    """The verdict in one sentence."""
    pattern: str | None = None
    """How the sticky valve shows: ``limit_cycle``, ``irregular_cycle``, ``stick_jump``
    or ``stuck``; null unless the verdict is stiction."""
    op_travel: float | None = None
    """OP travel beyond noise over the window, % of span."""
    episode_stick_band: float | None = None
    """Stick band read off the stick-jump episodes, % of span."""
    episode_size: EpisodeSizePublic | None = None
    """S read off the episodes (OP's travel from its turns to the slips) and whether it
    agrees with the Hammerstein estimate; null unless the verdict is stiction with
    episodes."""
    episodes: list[EpisodePublic] | None = None
    """The stick-jump episodes, s from the window's first sample: ``start_s``,
    ``jump_s``, ``end_s``, ``op_travel``, ``pv_jump``, ``op_during_jump``."""
    methods: dict[str, MethodEvidencePublic] | None = None
    """Each method's ``decision``, ``index``, ``confidence``, ``note`` and ``details``."""


class ProcessEstimatePublic(OpenSchema):
    """The linear part the stiction estimate identified, from MV (% of travel) to PV
    (:class:`analytics.lti.FirstOrderProcess`)."""

    K: float | None = None
    """Process gain (for an integrating process, of PV's rate of change, 1/s)."""
    tau: float | None = None
    """Lag, s (0 when no lag was found)."""
    theta: float | None = None
    """Dead time, s (the MV delay less the one sample of the hold)."""
    integrating: bool | None = None


class QuantificationPublic(OpenSchema):
    """The Hammerstein estimate of the valve's stiction
    (:meth:`analytics.quantification.StictionEstimate.to_dict`, plus the service's
    ``gain_source``).  Fields in the order ``to_dict`` writes them: the answer keeps it."""

    S: float | None = None
    """Stick band plus deadband, % of OP span."""
    J: float | None = None
    """Slip jump, % of OP span."""
    fs: float | None = None
    """Static friction band in He's parametrisation, S = fs + fd."""
    fd: float | None = None
    """Dynamic friction band in He's parametrisation, J = fs - fd."""
    fit_r2: float | None = None
    """Output-error R^2 of the simulated PV over the scored window."""
    stiction_found: bool | None = None
    """The best model has a stick band that matters (large enough a share of the OP
    travel, explaining clearly more than a healthy valve)."""
    trustworthy: bool | None = None
    """An estimate exists and none of ``issues`` applies."""
    issues: list[str] | None = None
    """Why the estimate is not to be trusted (too few cycles, a poor fit, S at the search
    bound, J undetermined, ...)."""
    S_interval: list[float] | None = None
    """Interval of S at ``interval_level`` (likelihood ratio, widened by the model
    error)."""
    J_interval: list[float] | None = None
    """Interval of J, as for S."""
    interval_level: float | None = None
    """Nominal level of the intervals."""
    gain_given: bool | None = None
    """J was sized with a process gain the configuration gives, not a fitted one."""
    J_product_only: bool | None = None
    """The window pins only the product K J (``KJ``), not J."""
    KJ: float | None = None
    """Process gain times J: the PV step of one slip."""
    valve_model: str | None = None
    """The valve model the search chose."""
    process: ProcessEstimatePublic | None = None
    gain_source: str | None = None
    """Where a given process gain came from, in words (the service adds it; absent when
    no gain was given)."""


class ApparentStictionPublic(OpenSchema):
    """The ellipse fitted to the band-passed OP-PV signature
    (:meth:`analytics.stiction.signature.EllipseFit.to_dict`; Choudhury et al. 2008)."""

    apparent_stiction: float | None = None
    """Width of the ellipse along the OP axis through its centre, OP units."""
    width_ratio: float | None = None
    """Apparent stiction over OP's peak-to-peak."""
    op_amplitude: float | None = None
    """Amplitude of the filtered OP."""
    residual: float | None = None
    """Relative RMS radial distance of the points from the ellipse (0: a perfect one)."""
    centre: list[float] | None = None
    """Centre (OP, PV) in signal units; null for runs stored before the geometry."""
    semi_axes: list[float] | None = None
    """Semi-major and semi-minor axes in the plot's units."""
    angle: float | None = None
    """Angle of the major axis from the OP axis, radians."""


class SizeWindowPublic(OpenSchema):
    """One window combined into the valve's size (:class:`service.stored.SizeWindow`)."""

    window_start: float | None = None
    """UNIX s."""
    window_end: float | None = None
    """UNIX s."""
    S: float | None = None
    """This window's S, % of valve span."""
    S_interval: list[float] | None = None
    J: float | None = None
    """This window's J, % of valve span."""
    J_interval: list[float] | None = None
    gain_given: bool | None = None
    """J sized with a process gain the configuration gives."""
    gain_source: str | None = None
    J_product_only: bool | None = None
    """J known only through the product K J."""
    fit_r2: float | None = None
    """Output-error R^2 of the window's fit (its weight in the combination)."""


class ManualPublic(OpenSchema):
    """The stretch in auto or cascade judged in a window with manual samples
    (:class:`service.stored.ManualStretch`)."""

    share: float | None = None
    """Share of the window's samples in manual, 0 to 1."""
    judged_from: float | None = None
    """Start of the stretch judged, UNIX s; null when no sample was judged."""
    judged_to: float | None = None
    """Its end, UNIX s."""
    judged_samples: int | None = None
    note: str | None = None
    """The stretch in words."""


class ValveVerdictPublic(OpenSchema):
    """The final verdict on the loop's valve, the one every page and rule reads
    (:func:`service.verdicts.valve_verdict`): the loop's own, or its unit's."""

    verdict: str | None = None
    confidence: float | None = None
    S: float | None = None
    """Stick band, % of valve span: combined over the windows of the valve's stiction
    streak (:func:`analytics.quantification.combine_windows`)."""
    J: float | None = None
    """Slip jump, % of valve span, combined as S is."""
    S_interval: list[float] | None = None
    """Interval of S (nominal 95 %; on the synthetic library it holds the true S in
    about 84 % of cases)."""
    J_interval: list[float] | None = None
    """Interval of J, as for S."""
    J_note: str | None = None
    """What J rests on: sized with a configured process gain, or known only through the
    product of the process gain and J in some windows; null otherwise."""
    size_windows: list[SizeWindowPublic] | None = None
    """The windows combined: each one's ``window_start``, ``window_end`` and sizes."""
    reason: str | None = None
    decided_by: str | None = None
    """``loop`` or ``unit``."""
    own_verdict: str | None = None
    """The loop's own verdict."""
    unit_id: str | None = None
    unit_run_id: int | None = None
    """The unit diagnosis run that decided."""
    sticky_valves: list[str] | None = None
    """The unit's sticky valves that make this loop cycle."""


class LoopDiagnosisPublic(OpenSchema):
    """Everything the analysis found in one window of one loop."""

    samples: int | None = None
    """Window length, samples."""
    ts: float | None = None
    """Sampling interval, s."""
    process_type: str | None = None
    """``self-regulating``, ``integrating`` or null."""
    process_type_source: str | None = None
    """``given``, ``inferred``, ``assumed`` or ``unknown``."""
    quality: QualityPublic | None = None
    oscillation: OscillationPublic | None = None
    stiction: StictionPublic | None = None
    quantification: QuantificationPublic | None = None
    """Hammerstein estimate of S, J (% of OP span), fs, fd with its fit and process;
    null unless the verdict is stiction."""
    apparent_stiction: ApparentStictionPublic | None = None
    """Apparent stiction from the valve signature's ellipse (Choudhury et al. 2008)."""
    model_trace: dict[str, Any] | None = None
    """The Hammerstein estimate replayed on the window, its last three periods (at most
    300 samples each, 4 decimals): ``op``, the model's ``mv`` and predicted ``pv`` (% of
    span), the replay's ``r2`` and ``label``; what the signature plot draws.  Null
    without an estimate, with gaps in OP or PV, and for runs stored before 2 Dec 2026."""
    health: float | None = None
    """Health score, 0 (worst) to 100."""
    first_sample_at: float | None = None
    """First sample judged, UNIX s."""
    kpis: KpisPublic | None = None
    """The loop's KPIs over the window."""
    valve: ValveVerdictPublic | None = None
    manual: ManualPublic | None = None
    """Present when the loop was in manual: its share of the window and the stretch in
    auto or cascade that was judged."""
