"""Stick-jump episodes: stiction in routine data that does not cycle.

Between slips a sticky valve stands still while the controller's integral
action ramps OP; when OP has travelled the stick band the valve slips and
PV jumps (Kano et al. 2004, the "stuck sections" of their method; thesis
section 1.2.2, Fig. 1.6).  In routine plant data this shows up as holds and
jumps long before -- and often without -- a limit cycle: a set-point change
or a load starts the ramp, PV stays put, then jumps.  This module finds
those episodes in OP and the valve's proxy signal and decides from them.

The valve's proxy is PV for a self-regulating process (flow, pressure: PV
follows the valve position within the process's response time) and the
slope of PV for an integrating one (a level's rate of change follows the
outflow, hence the valve position).

Algorithm (:func:`find_stick_episodes`):

1. Noise of the proxy ``y`` and of OP from the median absolute first
   difference (robust to the jumps themselves); ``y`` and OP are smoothed
   by a centred moving average of ``smoothing`` samples.
2. ``y`` is cut into *holds*: runs in which it stays inside a band of
   ``band_sigmas`` noise standard deviations (of the smoothed signal).
   Neighbouring holds whose levels differ by less than the band are merged,
   so a hold's own noise does not split it.
3. Holds at least ``min_hold`` samples long whose ends sit within the band
   of each other (flat: not a piece of a ramp or a slow swing) count.  Each
   such hold followed within a short transition by the next is an *episode
   candidate*: OP travelled
   ``op_travel`` during the hold, PV then moved ``pv_jump`` between the two
   levels, and OP moved ``op_during_jump`` during the transition.
4. A candidate is a *stick-jump episode* when PV's jump is clear (at least
   ``min_jump_bands`` bands), fast (the transition is shorter than a
   quarter of the hold: the process could have followed OP within the hold,
   yet did not), not caused by OP (OP moved less during the jump than
   during the hold), from a hold off the reference (the set point, else
   the median PV: the error is why the controller pushed) towards it, and
   in the direction in which OP had been pushing the valve (the sign of the
   process gain, from the controller's integral action, see
   :func:`loop_gain_sign`).  Any other clear jump after a hold is a
   *contrary* one: a load disturbance moves PV away from the reference
   whatever OP did.

:class:`StickJumpDetector` votes stiction when the window holds
``min_episodes`` episodes and at most a third as many contrary ones; no
stiction when OP travelled enough to expose a stick band and PV followed
it without any episode.

References
----------
.. [1] M. Kano, H. Maruta, H. Kugemoto and K. Shimizu, "Practical model and
   detection algorithm for valve stiction", IFAC DYCOPS, Cambridge MA, 2004
   (sticking sections: OP changes while the valve position does not).
.. [2] Y. Yamashita, "An automatic method for detection of valve stiction in
   process control loops", Control Eng. Practice 14 (2006) 503-510
   (movement patterns of OP and the valve signal over episodes).
.. [3] M. Jelali and B. Huang (eds.), *Detection and Diagnosis of Stiction in
   Control Loops*, Springer 2010, ch. 2 (stick-slip without a limit cycle
   under slow integral action and set-point changes).
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import pairwise
from typing import ClassVar

import numpy as np
from numpy.typing import NDArray

from analytics.stiction.evidence import (
    INTEGRATING,
    NO_STICTION,
    STICTION,
    LoopWindow,
    MethodEvidence,
    ProcessType,
    margin_confidence,
)

__all__ = [
    "MIN_TRAVEL",
    "EpisodeAnalysis",
    "StickEpisode",
    "StickJumpDetector",
    "StuckSectionsDetector",
    "analyse_window",
    "find_stick_episodes",
    "loop_gain_sign",
    "op_travel",
    "robust_noise",
    "valve_travel",
]

FloatArray = NDArray[np.float64]

MIN_TRAVEL = 2.0
"""OP travel beyond noise (OP units, % of span) below which a window shows too
little valve movement to judge: a stick band of 0.5-1 % needs a few reversals
or a long ramp to show."""


@dataclass(frozen=True)
class StickEpisode:
    """One hold of the valve followed by a jump of PV.

    Attributes
    ----------
    start, end : int
        First sample of the hold and first sample after the jump (the next
        hold starts there).
    jump_at : int
        First sample after the hold: where the valve slipped.
    op_travel : float
        Net OP change during the hold (OP units): the stick band the
        controller had to push through.
    pv_jump : float
        Change of the valve proxy from the hold's level to the next (PV
        units; for an integrating process, PV units per second).
    op_during_jump : float
        Net OP change during the jump itself.
    consistent : bool
        True if PV jumped the way OP had been pushing (a stick-jump); False
        for a contrary jump (a load disturbance, not the valve).
    """

    start: int
    end: int
    jump_at: int
    op_travel: float
    pv_jump: float
    op_during_jump: float
    consistent: bool


@dataclass(frozen=True)
class EpisodeAnalysis:
    """What :func:`find_stick_episodes` found in one window.

    Attributes
    ----------
    episodes : tuple of StickEpisode
        Consistent stick-jump episodes, in time order.
    contrary : tuple of StickEpisode
        Clear jumps after a hold with OP travel that went against OP.
    op_travel_total : float
        OP travel beyond noise over the window (:func:`valve_travel`).
    hold_travel : float
        OP travel inside holds of PV long enough to count (``min_hold``).
    pv_noise, op_noise : float
        Noise standard deviations of the valve proxy and OP.
    band : float
        Half width of a hold's band (smoothed proxy units).
    gain_sign : int
        +1 if OP and PV move the same way, -1 if opposite, 0 if the
        controller's action could not be read from the data.
    proxy_span : float
        Range of the smoothed valve proxy over the window.
    """

    episodes: tuple[StickEpisode, ...]
    contrary: tuple[StickEpisode, ...]
    op_travel_total: float
    hold_travel: float
    pv_noise: float
    op_noise: float
    band: float
    gain_sign: int
    proxy_span: float

    @property
    def hold_share(self) -> float:
        """Share of the OP travel made while PV held (0 without travel)."""
        return self.hold_travel / self.op_travel_total if self.op_travel_total > 0 else 0.0


def robust_noise(x: FloatArray) -> float:
    """Noise standard deviation of ``x`` from its first differences.

    ``1.4826 MAD(diff x) / sqrt(2)``: the differences of white noise have
    twice its variance, and the median ignores the few large differences of
    steps and jumps.  Quantised or held signals (MAD 0) fall back to the
    standard deviation of the non-zero differences over ``sqrt(2)``, scaled
    by their share, so a lattice still has a noise floor.
    """
    d = np.diff(x)
    if d.size == 0:
        return 0.0
    mad = float(np.median(np.abs(d - np.median(d))))
    if mad > 0:
        return 1.4826 * mad / np.sqrt(2.0)
    moving = d[d != 0]
    if moving.size == 0:
        return 0.0
    return float(np.sqrt(np.mean(moving**2) * moving.size / d.size / 2.0))


def _moving_average(x: FloatArray, width: int) -> FloatArray:
    """Centred moving average of ``width`` samples, the ends padded with the edge values."""
    if width <= 1:
        return x.astype(np.float64, copy=True)
    padded = np.pad(x, (width // 2, width - 1 - width // 2), mode="edge")
    csum = np.concatenate(([0.0], np.cumsum(padded)))
    return np.asarray((csum[width:] - csum[:-width]) / width, dtype=np.float64)


def valve_travel(op: FloatArray, deadband: float) -> float:
    """OP travel beyond noise: the total of OP moves a positioner would make.

    A backlash of half width ``deadband`` follows OP (the output moves only
    when OP leaves the band around it) and its total variation is the
    travel; noise within the band adds nothing, so a noisy but steady OP
    has (almost) no travel.
    """
    position = float(op[0])
    travel = 0.0
    for value in op[1:]:
        if value > position + deadband:
            travel += value - deadband - position
            position = float(value) - deadband
        elif value < position - deadband:
            travel += position - (value + deadband)
            position = float(value) + deadband
    return travel


def op_travel(op: FloatArray, *, smoothing: int = 3, noise_sigmas: float = 3.0) -> float:
    """OP travel beyond noise over a window: :func:`valve_travel` of OP smoothed
    over ``smoothing`` samples, with a backlash of ``noise_sigmas`` OP noise
    standard deviations (:func:`robust_noise`)."""
    return valve_travel(_moving_average(op, smoothing), noise_sigmas * robust_noise(op))


def loop_gain_sign(op: FloatArray, pv: FloatArray, sp: FloatArray | None) -> int:
    """Sign of the process gain read from the controller's integral action.

    A stable loop's controller moves OP to cancel the error: with integral
    action ``dOP/dt`` follows ``g (SP - PV)`` where ``g`` is the sign of the
    process gain (reverse action for a positive gain).  The sign of the
    correlation between the error and the next OP move is ``g``; without a
    set point the window's median PV stands for it.  0 if the correlation
    is too weak to tell (below 2 standard errors).
    """
    ref = np.median(pv) if sp is None else sp
    err = (ref - pv)[:-1]
    dop = np.diff(op)
    err = err - err.mean()
    dop = dop - dop.mean()
    denom = float(np.sqrt(np.dot(err, err) * np.dot(dop, dop)))
    if denom == 0:
        return 0
    corr = float(np.dot(err, dop)) / denom
    if abs(corr) * np.sqrt(err.size) < 2.0:
        return 0
    return 1 if corr > 0 else -1


def _holds(y: FloatArray, band: float) -> list[tuple[int, int, float]]:
    """Runs of ``y`` inside a band of half width ``band``, merged when their
    levels differ by less than the band: ``(start, end, level)`` per hold."""
    runs: list[tuple[int, int]] = []
    start, lo, hi = 0, float(y[0]), float(y[0])
    for k in range(1, y.size):
        value = float(y[k])
        new_lo, new_hi = min(lo, value), max(hi, value)
        if new_hi - new_lo > 2.0 * band:
            runs.append((start, k))
            start, lo, hi = k, value, value
        else:
            lo, hi = new_lo, new_hi
    runs.append((start, y.size))
    merged: list[tuple[int, int, float]] = []
    for s, e in runs:
        level = float(np.median(y[s:e]))
        if merged and abs(level - merged[-1][2]) < band:
            ps, _, _ = merged[-1]
            merged[-1] = (ps, e, float(np.median(y[ps:e])))
        else:
            merged.append((s, e, level))
    return merged


def _is_flat(y: FloatArray, band: float) -> bool:
    """True if the last third of ``y`` sits within ``band`` of its first third: a
    hold, not a piece of a ramp or of a slow swing cut by the band."""
    third = max(y.size // 3, 1)
    return abs(float(np.median(y[-third:]) - np.median(y[:third]))) <= band


def find_stick_episodes(
    op: FloatArray,
    proxy: FloatArray,
    *,
    gain_sign: int,
    smoothing: int = 3,
    band_sigmas: float = 3.0,
    min_hold: int = 8,
    min_jump_bands: float = 2.0,
    max_transition_fraction: float = 0.25,
    travel_sigmas: float = 3.0,
    min_hold_travel_sigmas: float = 10.0,
    max_jump_op_share: float = 0.5,
    reference: FloatArray | None = None,
) -> EpisodeAnalysis:
    """Holds of the valve proxy with OP travel, and the jumps that end them.

    Parameters
    ----------
    op, proxy : ndarray
        OP and the valve proxy (PV, or its slope for an integrating process).
    gain_sign : int
        Sign of the process gain (:func:`loop_gain_sign`); with 0 every
        clear jump after a hold counts as consistent if it goes the way OP
        pushed under either sign, i.e. no direction test is made.
    smoothing, band_sigmas, min_hold, min_jump_bands, max_transition_fraction
        See the module docstring, steps 1-4.
    travel_sigmas : float
        OP noise standard deviations below which an OP move is noise (the
        backlash of :func:`valve_travel`).
    min_hold_travel_sigmas : float
        Smallest net OP travel during an episode's hold, in OP noise
        standard deviations: a ramp the controller made, not jitter.
    max_jump_op_share : float
        Largest OP move during the jump, as a share of the hold's travel: a
        PV jump that OP made at the same time is the process following OP.
    reference : ndarray, optional
        What a stick-jump heads for (the set point); the proxy's median if
        None.
    """
    pv_noise = robust_noise(proxy)
    op_noise = robust_noise(op)
    y = _moving_average(proxy, smoothing)
    u = _moving_average(op, smoothing)
    span = float(np.ptp(y))
    band = max(band_sigmas * pv_noise / np.sqrt(smoothing), 1e-9 * max(span, 1.0))
    op_deadband = travel_sigmas * op_noise
    holds = _holds(y, band)
    if reference is None:
        reference = np.full(y.size, float(np.median(y)))
    episodes: list[StickEpisode] = []
    contrary: list[StickEpisode] = []
    flat = [h for h in holds if h[1] - h[0] >= min_hold and _is_flat(y[h[0]:h[1]], band)]
    hold_travel = sum(valve_travel(u[s:e], op_deadband) for s, e, _ in flat)
    for (s, e, level), (s_after, e_after, level_after) in pairwise(flat):
        length = e - s
        transition = s_after - e
        if transition > max_transition_fraction * length:
            continue
        pv_jump = level_after - level
        if abs(pv_jump) < min_jump_bands * band:
            continue
        op_travel = float(u[e - 1] - u[s])
        op_during_jump = float(u[min(s_after + min(2, e_after - s_after - 1), u.size - 1)]
                               - u[e - 1])
        if (abs(op_travel) < max(min_hold_travel_sigmas * op_noise, 1e-12)
                or abs(op_during_jump) > max_jump_op_share * abs(op_travel)):
            continue
        # The controller pushed because PV held off its reference, and the slip
        # moved PV towards it (a load moves PV away from where it held).
        offset = float(np.median(reference[s:e])) - level
        toward = abs(offset) >= band and np.sign(pv_jump) == np.sign(offset)
        direction = np.sign(pv_jump) * np.sign(op_travel)
        consistent = toward and (gain_sign == 0 or direction == gain_sign)
        episode = StickEpisode(s, s_after, e, op_travel, float(pv_jump), op_during_jump,
                               bool(consistent))
        (episodes if consistent else contrary).append(episode)
    return EpisodeAnalysis(
        tuple(episodes), tuple(contrary), valve_travel(u, op_deadband), hold_travel,
        pv_noise, op_noise, band, gain_sign, span,
    )


def valve_proxy(pv: FloatArray, ts: float, process_type: ProcessType | None,
                smoothing: int = 5) -> FloatArray:
    """The signal that follows the valve position: PV, or for an integrating
    process the slope of PV (a moving average of ``smoothing`` differences)."""
    if process_type == INTEGRATING:
        slope = np.diff(pv, prepend=pv[0]) / ts
        return _moving_average(slope, smoothing)
    return pv


def analyse_window(window: LoopWindow) -> EpisodeAnalysis | None:
    """The stick-jump episodes of ``window`` (None without OP and PV).

    The reference a jump must head for is the set point when given (not for
    an integrating process, whose proxy is a slope), else the proxy's median.
    """
    if window.op is None or window.pv is None:
        return None
    proxy = valve_proxy(window.pv, window.ts, window.process_type)
    sign = loop_gain_sign(window.op, window.pv, window.sp)
    use_sp = window.sp is not None and window.process_type != INTEGRATING
    return find_stick_episodes(window.op, proxy, gain_sign=sign,
                               reference=window.sp if use_sp else None)


@dataclass(frozen=True, kw_only=True)
class StickJumpDetector:
    """Stiction from stick-jump episodes (Kano et al. 2004; module docstring).

    Works on transient windows as well as on cycles: it needs holds, not a
    period.  Stiction when at least ``min_episodes`` episodes go the way OP
    pushed and at most ``max_contrary_share`` of the clear jumps go against
    it; no stiction when the jumps go either way (``min_random_share``), or
    when OP travelled at least ``min_travel`` (OP units, % of span) with
    fewer episodes than needed and no more than contrary jumps and PV
    following OP through most of it (the share of travel made during holds
    below ``max_hold_share``); undecided otherwise.

    Attributes
    ----------
    min_episodes : int
        Consistent episodes needed to vote stiction.
    max_contrary_share : float
        Largest share of contrary jumps among all clear jumps.
    min_random_share : float
        Share of contrary jumps (among at least ``min_episodes + 1``) from
        which the jumps are taken for disturbances: they go either way, about
        half each, while a sticky valve's go the way OP pushed.
    min_travel : float
        OP travel beyond noise needed to vote no stiction.
    max_hold_share : float
        Largest share of OP travel during holds for a no-stiction vote: a
        valve that held through more has perhaps not slipped yet (a little
        below :class:`StuckSectionsDetector`'s ``stuck_share``).
    confidence_scale : float
        Episodes beyond ``min_episodes - 1`` that give confidence 0.63.
    """

    name: ClassVar[str] = "stick_jump"
    min_episodes: int = 2
    max_contrary_share: float = 0.25
    min_random_share: float = 0.4
    min_travel: float = MIN_TRAVEL
    max_hold_share: float = 0.8
    confidence_scale: float = 2.0

    def decide(self, analysis: EpisodeAnalysis) -> MethodEvidence:
        """The evidence of an :class:`EpisodeAnalysis`."""
        n, n_contrary = len(analysis.episodes), len(analysis.contrary)
        details = {"episodes": float(n), "contrary": float(n_contrary),
                   "op_travel": analysis.op_travel_total}
        share = n_contrary / (n + n_contrary) if n + n_contrary else 0.0
        if n >= self.min_episodes and share <= self.max_contrary_share:
            travel = np.median([abs(e.op_travel) for e in analysis.episodes])
            return MethodEvidence(
                self.name, STICTION, float(n),
                margin_confidence(n, self.min_episodes - 1, self.confidence_scale),
                f"{n} stick-jump episodes: PV held while OP travelled about {travel:.3g}, "
                f"then jumped the way OP pushed ({n_contrary} contrary)", details,
            )
        if n + n_contrary >= self.min_episodes + 1 and share >= self.min_random_share:
            return MethodEvidence(
                self.name, NO_STICTION, share,
                margin_confidence(share, self.max_contrary_share, 0.25),
                f"{n_contrary} of {n + n_contrary} jumps after a hold went against OP: PV "
                "jumps either way, as disturbances make it, not the valve", details,
            )
        if (n < self.min_episodes and n <= n_contrary
                and analysis.op_travel_total >= self.min_travel
                and analysis.hold_share < self.max_hold_share):
            return MethodEvidence(
                self.name, NO_STICTION, 0.0,
                margin_confidence(analysis.op_travel_total, self.min_travel, self.min_travel),
                f"OP travelled {analysis.op_travel_total:.3g} and PV followed it: {n} hold(s) "
                f"ended in a jump the way OP pushed, {n_contrary} the other way", details,
            )
        return MethodEvidence.undecided(
            self.name,
            f"{n} stick-jump episode(s) and {n_contrary} contrary jump(s) in "
            f"{analysis.op_travel_total:.3g} of OP travel: not enough to judge",
            float(n), details,
        )

    def detect(self, window: LoopWindow) -> MethodEvidence:
        analysis = analyse_window(window)
        if analysis is None:
            return MethodEvidence.undecided(self.name, "needs both OP and PV")
        return self.decide(analysis)


@dataclass(frozen=True, kw_only=True)
class StuckSectionsDetector:
    """Stiction from the share of OP travel made while PV held (Kano et al. 2004).

    Kano et al.'s sticking sections -- OP moves, the valve does not -- read
    over the whole window as Yamashita (2006) reads his movement patterns:
    the index is the OP travel inside holds of PV (flat stretches at least
    ``min_hold`` samples long, see :func:`find_stick_episodes`) over the OP
    travel in the window.  A healthy valve on a process that responds moves
    PV whenever OP travels, so most travel falls outside holds; a sticky
    valve holds PV through most of it, whether or not it slipped inside the
    window.

    * Undecided when OP travelled less than ``min_travel`` (too little
      movement to expose a stick band) or PV never left its noise band by
      ``min_response_bands`` (the process does not visibly respond to the
      valve at all: a held PV then says nothing about the valve).
    * Stiction from ``stuck_share``; otherwise undecided.  The test is one
      sided: in a stiction limit cycle PV moves during every slip and the
      noise splits its holds, so a low share is no evidence of health (the
      sticky ISDB loops give 0.07-0.6).

    Attributes
    ----------
    stuck_share : float
        Index threshold.  Chosen on the labelled plant windows (healthy
        loops reach 0.77 when a well-controlled flow holds its set point
        while OP compensates a load; the sticky flow valve stayed 0.73-0.98)
        and checked leave-one-tag-out in ``benchmarks/detection.py``.
    min_travel : float
        OP travel beyond noise (OP units, % of span) needed to judge.
    min_response_bands : float
        Range of the smoothed PV, in hold bands, that shows the process
        responds.
    """

    name: ClassVar[str] = "stuck_sections"
    stuck_share: float = 0.85
    min_travel: float = MIN_TRAVEL
    min_response_bands: float = 3.0

    def decide(self, analysis: EpisodeAnalysis) -> MethodEvidence:
        """The evidence of an :class:`EpisodeAnalysis`."""
        share = analysis.hold_share
        details = {"hold_travel": analysis.hold_travel, "op_travel": analysis.op_travel_total}
        if analysis.op_travel_total < self.min_travel:
            return MethodEvidence.undecided(
                self.name, f"OP travelled {analysis.op_travel_total:.3g}, less than "
                f"{self.min_travel:g}: not enough valve movement to judge", share, details)
        if analysis.proxy_span < self.min_response_bands * 2.0 * analysis.band:
            return MethodEvidence.undecided(
                self.name, "PV never left its noise band: the process shows no response "
                "to judge the valve by", share, details)
        note = (f"{share:.0%} of the OP travel ({analysis.op_travel_total:.3g}) was made "
                "while PV held")
        if share >= self.stuck_share:
            return MethodEvidence(self.name, STICTION, share,
                                  margin_confidence(share, self.stuck_share - 0.1, 0.1),
                                  note, details)
        return MethodEvidence.undecided(
            self.name, f"{note}: below {self.stuck_share:.0%}, which says nothing either way",
            share, details)

    def detect(self, window: LoopWindow) -> MethodEvidence:
        analysis = analyse_window(window)
        if analysis is None:
            return MethodEvidence.undecided(self.name, "needs both OP and PV")
        return self.decide(analysis)
