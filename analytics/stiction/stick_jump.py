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
   so a hold's own noise does not split it.  Holds at least ``min_hold``
   samples long whose ends sit within the band of each other (flat: not a
   piece of a ramp or of a slow swing) count, and consecutive ones at one
   level make a *stuck period*: the valve stood still through it.
3. Each stuck period followed within a short transition by the next is an
   *episode candidate*: OP travelled ``op_travel`` during the period, PV
   then moved ``pv_jump`` between the two levels, and OP moved
   ``op_during_jump`` during the jump.
4. A candidate is a *stick-jump episode* when PV's jump is clear (at least
   ``min_jump_bands`` bands) and fast (the transition is shorter than a
   quarter of the hold, and half the jump beyond the band is made within an
   eighth of it: the process could have followed OP within the hold, yet did
   not), followed by a hold at least a quarter as long (the valve sticks
   again) -- or, when the next hold comes later, a slip into a moving valve:
   on a stiction cycle the valve moves on with OP after slipping until OP
   turns (Kano's model), and PV answers the slip as a process answers a
   step, fast first and then slower (a healthy valve behind a dead time
   leaves a hold slowly, then faster: a ramp response), by at least
   ``follow_jump_bands`` bands within an eighth of the hold -- not caused by
   OP (OP moved the jump's way less during the jump than during the hold,
   unless the valve moves on with it, and in a ramp through the hold, not in
   a kick),
   from a hold off the reference (the set point during the hold or just
   after the jump, else the median PV: the error is why the controller
   pushed) towards it, and in the direction in which OP had been pushing the
   valve (the sign of the process gain, read from the controller, see
   :func:`loop_gain_sign`). Any other clear jump after a hold is a
   *contrary* one: a load disturbance moves PV away from the reference
   whatever OP did.

:class:`StickJumpDetector` decides from the episodes,
:class:`StuckSectionsDetector` from OP reversals made while PV held.

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
from numba import njit
from numpy.typing import NDArray

from analytics.signals import shared
from analytics.stiction.evidence import (
    INTEGRATING,
    NO_STICTION,
    STICTION,
    LoopWindow,
    MethodEvidence,
    ProcessType,
    margin_confidence,
)
from analytics.types import FloatArray

__all__ = [
    "MIN_TRAVEL",
    "EpisodeAnalysis",
    "StickEpisode",
    "StickJumpDetector",
    "StuckSectionsDetector",
    "analyse_window",
    "find_stick_episodes",
    "loop_gain_sign",
    "moving_average",
    "op_travel",
    "robust_noise",
    "travel_increments",
    "valve_travel",
]


MIN_TRAVEL = 2.0
"""OP travel beyond noise (OP units, % of span) below which a window shows too
little valve movement to judge: a stick band of 0.5-1 % needs a few reversals
or a long ramp to show."""

SMOOTHING_SCALES = (3, 12)
"""Smoothing widths (samples) at which :func:`analyse_window` looks for episodes.
Three samples keep fast slips sharp; twelve halve the noise band, so that a
small stick band on a noisy flow (a jump of one to two bands at three
samples) still shows in holds hundreds of samples long.  Chosen on the
synthetic libraries, ``plant_dev`` and the ISDB: a third, coarser scale (40
or 48) added no sticky window that was not found already, and the ladder
(3, 10, 30) found episodes in two healthy look-alikes (a slow sine and
historian compression)."""

MIN_HOLD = 8
"""Shortest hold (samples) at the finest smoothing; proportionally longer at
coarser ones, so a hold spans several smoothing widths."""


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
        OP travel while PV held (stuck periods: flat holds ``min_hold`` long
        at one level, :func:`find_stick_episodes`).
    hold_reversal : float
        The largest OP reversal made within one stuck period (OP went one
        way and back while PV held: the shorter leg around its largest turn,
        :func:`_reversal`).
    op_range : float
        Range of the smoothed OP over the window.
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
    hold_reversal: float
    op_range: float
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

    Within :func:`analytics.signals.shared_results` it is computed once
    (:func:`~analytics.signals.shared`): a diagnosis asks for the noise of the
    same OP and PV several times (the OP travel, the episodes at each
    smoothing, the episode sizes, the PV noise reported), under a millisecond
    each on 10,000 samples.
    """
    return shared(_robust_noise, np.asarray(x, dtype=np.float64))


def _robust_noise(x: FloatArray) -> float:
    """:func:`robust_noise`, computed."""
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


def moving_average(x: FloatArray, width: int) -> FloatArray:
    """Centred moving average of ``width`` samples, the ends padded with the edge values."""
    if width <= 1:
        return x.astype(np.float64, copy=True)
    padded = np.pad(x, (width // 2, width - 1 - width // 2), mode="edge")
    csum = np.concatenate(([0.0], np.cumsum(padded)))
    return np.asarray((csum[width:] - csum[:-width]) / width, dtype=np.float64)


@njit(cache=True)
def travel_increments(op: FloatArray, deadband: float) -> FloatArray:
    """OP moves beyond noise, sample by sample: what a positioner would travel.

    A backlash of half width ``deadband`` follows OP (the output moves only
    when OP leaves the band around it); element ``k`` is how far it moved at
    sample ``k``.  Noise within the band adds nothing, so a noisy but steady
    OP has (almost) no travel.
    """
    moves = np.zeros(op.size)
    position = op[0]
    for k in range(1, op.size):
        value = op[k]
        if value > position + deadband:
            moves[k] = value - deadband - position
            position = value - deadband
        elif value < position - deadband:
            moves[k] = position - (value + deadband)
            position = value + deadband
    return moves


def valve_travel(op: FloatArray, deadband: float) -> float:
    """Total OP travel beyond noise (:func:`travel_increments`)."""
    return float(travel_increments(op, deadband).sum())


def op_travel(op: FloatArray, *, smoothing: int = 3, noise_sigmas: float = 3.0) -> float:
    """OP travel beyond noise over a window: :func:`valve_travel` of OP smoothed
    over ``smoothing`` samples, with a backlash of ``noise_sigmas`` OP noise
    standard deviations (:func:`robust_noise`)."""
    return valve_travel(moving_average(op, smoothing), noise_sigmas * robust_noise(op))


def loop_gain_sign(op: FloatArray, pv: FloatArray, sp: FloatArray | None) -> int:
    """Sign of the process gain, read from the controller itself.

    A PI controller in velocity form moves OP by
    ``dOP_k = Kc (e_k - e_{k-1}) + Kc ts / Ti e_k`` with the error
    ``e = SP - PV`` (Astrom & Hagglund 2006, sec. 3.5); a least-squares fit of
    ``dOP`` on ``de``, ``e`` and a constant (the set point's offset when it is
    not given: the window's median PV stands for it) gives the controller's
    signs, whatever the valve does.  A stable loop has controller and process
    gains of one sign (reverse action for a positive process gain), so the
    sign of the better determined term (the larger |t|: the proportional one
    for P-only control) is the process gain's.  0 when neither term is
    significant (|t| < 3).
    """
    ref = np.median(pv) if sp is None else sp
    err = ref - pv
    dop = np.diff(op)
    regressors = np.column_stack((np.diff(err), err[1:], np.ones(dop.size)))
    coef, *_ = np.linalg.lstsq(regressors, dop, rcond=None)
    residual = dop - regressors @ coef
    dof = max(dop.size - 3, 1)
    variance = float(residual @ residual) / dof
    try:
        cov = variance * np.linalg.inv(regressors.T @ regressors)
    except np.linalg.LinAlgError:
        return 0
    with np.errstate(divide="ignore", invalid="ignore"):
        t_stat = coef[:2] / np.sqrt(np.maximum(np.diag(cov)[:2], 0.0))
    t_stat = np.nan_to_num(t_stat)
    k = int(np.argmax(np.abs(t_stat)))  # the better determined of the two terms
    if abs(t_stat[k]) < 3.0:
        return 0
    return 1 if coef[k] > 0 else -1


@njit(cache=True)
def _hold_kernel(y: FloatArray, band: float) -> tuple[NDArray[np.int64], NDArray[np.int64],
                                                      FloatArray]:
    """Starts, ends and median levels of the holds of :func:`_flat_holds` before the
    length and flatness tests, compiled."""
    starts = np.empty(y.size, dtype=np.int64)
    ends = np.empty(y.size, dtype=np.int64)
    levels = np.empty(y.size)
    count = 0
    start = 0
    lo = hi = y[0]
    for k in range(1, y.size + 1):
        if k < y.size:
            new_lo, new_hi = min(lo, y[k]), max(hi, y[k])
            if new_hi - new_lo <= 2.0 * band:
                lo, hi = new_lo, new_hi
                continue
        level = np.median(y[start:k])
        if count > 0 and abs(level - levels[count - 1]) < band:
            ends[count - 1] = k
            levels[count - 1] = np.median(y[starts[count - 1]:k])
        else:
            starts[count], ends[count], levels[count] = start, k, level
            count += 1
        if k < y.size:
            start = k
            lo = hi = y[k]
    return starts[:count], ends[:count], levels[:count]


@njit(cache=True)
def _is_flat(y: FloatArray, band: float) -> bool:
    """True if the last third of ``y`` sits within ``band`` of its first third: a
    hold, not a piece of a ramp or of a slow swing cut by the band."""
    third = max(y.size // 3, 1)
    return bool(abs(np.median(y[y.size - third:]) - np.median(y[:third])) <= band)


@njit(cache=True)
def _flat_kernel(y: FloatArray, starts: NDArray[np.int64], ends: NDArray[np.int64],
                 band: float, min_hold: int) -> NDArray[np.bool_]:
    """Which holds of :func:`_flat_holds` are ``min_hold`` long and flat, compiled."""
    keep = np.empty(starts.size, dtype=np.bool_)
    for h in range(starts.size):
        keep[h] = ends[h] - starts[h] >= min_hold and _is_flat(y[starts[h]:ends[h]], band)
    return keep


def _flat_holds(y: FloatArray, band: float, min_hold: int) -> list[tuple[int, int, float]]:
    """Runs of ``y`` inside a band of half width ``band`` (cut greedily, a new run
    wherever the band would widen past ``2 band``), merged when their median
    levels differ by less than the band, that last ``min_hold`` samples and are
    flat (:func:`_is_flat`): ``(start, end, level)`` per hold."""
    y = np.ascontiguousarray(y, dtype=np.float64)
    starts, ends, levels = _hold_kernel(y, band)
    keep = _flat_kernel(y, starts, ends, band, min_hold)
    return list(zip(starts[keep].tolist(), ends[keep].tolist(), levels[keep].tolist(),
                    strict=True))


KICK_SAMPLES = 3
"""Span (samples) over which an OP step counts as a kick rather than a ramp: a
set-point step under proportional action or an operator's move is one or two
samples, spread over three by the smoothing."""


def _stuck_periods(
    flat: list[tuple[int, int, float]], band: float, max_gap_fraction: float
) -> list[tuple[int, int, float]]:
    """Consecutive flat holds at one level (within two bands of the first), with
    short gaps between them, joined into one period in which the valve stood
    still: ``(start, end, level of the last hold)``.  Noise that drifts a hold
    across its band edge splits it; the valve did not move for that."""
    periods: list[tuple[int, int, float, float]] = []  # start, end, first and last level
    for s, e, level in flat:
        if periods:
            ps, pe, first, _ = periods[-1]
            if abs(level - first) < 2.0 * band and s - pe <= max_gap_fraction * (pe - ps):
                periods[-1] = (ps, e, first, level)
                continue
        periods.append((s, e, level, level))
    return [(s, e, last) for s, e, _, last in periods]


def find_stick_episodes(
    op: FloatArray,
    proxy: FloatArray,
    *,
    gain_sign: int,
    smoothing: int = 3,
    band_sigmas: float = 3.0,
    min_hold: int = MIN_HOLD,
    min_jump_bands: float = 2.0,
    max_transition_fraction: float = 0.25,
    travel_sigmas: float = 3.0,
    min_hold_travel_sigmas: float = 10.0,
    max_jump_op_share: float = 0.5,
    min_sharp_share: float = 0.5,
    min_range_share: float = 0.1,
    follow_jump_bands: float = 4.0,
    max_follow_ratio: float = 0.8,
    reference: FloatArray | None = None,
    level_error: FloatArray | None = None,
) -> EpisodeAnalysis:
    """Holds of the valve proxy with OP travel, and the jumps that end them.

    Parameters
    ----------
    op, proxy : ndarray
        OP and the valve proxy (PV, or its slope for an integrating process).
    gain_sign : int
        Sign of the process gain (:func:`loop_gain_sign`); with 0 no
        direction test is made.
    smoothing, band_sigmas, min_hold, min_jump_bands, max_transition_fraction
        See the module docstring, steps 1-4.
    travel_sigmas : float
        OP noise standard deviations below which an OP move is noise (the
        backlash of :func:`travel_increments`).
    min_hold_travel_sigmas : float
        Smallest net OP travel during an episode's hold, in OP noise
        standard deviations: a ramp the controller made, not jitter.
    max_jump_op_share : float
        Largest OP move during the jump in the direction that makes it, as a
        share of the hold's travel: a PV jump that OP made at the same time is
        the process following OP.  Not applied to a slip into a moving valve,
        which moves on with OP by definition.
    min_sharp_share : float
        Share of the jump beyond the band PV must make within an eighth of the
        hold's length (at least 3 samples) after the hold ends.
    min_range_share : float
        Smallest hold travel as a share of OP's range over the window: in
        closed loop the controller must push through the whole stick band, so
        a stick band is a sizeable part of OP's excursions, whereas a healthy
        valve's resolution steps (0.1-0.2 %) are a small part.
    follow_jump_bands : float
        Smallest slip (bands) within an eighth of the hold when the valve moves
        on after it (no hold follows at once): twice ``min_jump_bands``, since
        without the next hold the slip alone must stand out of the noise.
    max_follow_ratio : float
        Largest PV move in the next eighth of the hold after such a slip, as a
        share of the slip: a slip decelerates (a process's step response), a
        delayed answer to an OP ramp accelerates.
    reference : ndarray, optional
        What a stick-jump heads for (the set point); the proxy's median if
        None.
    level_error : ndarray, optional
        For an integrating process (the proxy is PV's slope): the level's
        error, set point (else the median PV) minus PV.  A slip turns the slope
        back towards its median (the valve returns to the balance of in- and
        outflow) or the way that closes the level's error (the controller's
        integral action pushed it off the balance); a load turns the slope
        away from the balance while the level sits at its set point.
    """
    pv_noise = robust_noise(proxy)
    op_noise = robust_noise(op)
    y = moving_average(proxy, smoothing)
    u = moving_average(op, smoothing)
    span = float(np.ptp(y))
    band = max(band_sigmas * pv_noise / np.sqrt(smoothing), 1e-9 * max(span, 1.0))
    median_level = float(np.median(y))  # the reference when none is given
    if level_error is not None:
        error = moving_average(level_error, smoothing)
        error_band = band_sigmas * robust_noise(level_error) / np.sqrt(smoothing)
    moves = travel_increments(u, travel_sigmas * op_noise)
    periods = _stuck_periods(_flat_holds(y, band, min_hold), band, max_transition_fraction)
    hold_travel = sum(float(moves[s:e].sum()) for s, e, _ in periods)
    reversal = max((_reversal(u[s:e], moves[s:e]) for s, e, _ in periods), default=0.0)
    min_travel = max(min_hold_travel_sigmas * op_noise, min_range_share * float(np.ptp(u)))
    episodes: list[StickEpisode] = []
    contrary: list[StickEpisode] = []
    for (s, e, level), (s_after, e_after, level_after) in pairwise(periods):
        length = e - s
        step = max(3, length // 8)
        # A slip is sharp: PV leaves the hold by a clear jump within an eighth of
        # the hold (a slow swing through its peak, cut into holds by the band,
        # leaves it by about one band in that time).
        slip = float(y[min(e - 1 + step, y.size - 1)] - y[e - 1])
        settled = (s_after - e <= max_transition_fraction * length
                   # a hold cut by the window's end may be short
                   and (e_after >= y.size or e_after - s_after >= max_transition_fraction * length))
        if settled:
            # The valve stuck again at once: PV settles at its new level.
            pv_jump = level_after - level
            jump_end = s_after
        else:
            # The valve slipped and moved on with OP until OP turned (Kano's model:
            # the valve follows OP once moving); PV answers the slip as the process
            # does a step, fast first, then slower, and ends the way it jumped.
            later = y[min(e - 1 + 2 * step, y.size - 1)] - y[min(e - 1 + step, y.size - 1)]
            if (abs(slip) < follow_jump_bands * band
                    or later * np.sign(slip) > max_follow_ratio * abs(slip)
                    or np.sign(level_after - level) != np.sign(slip)):
                continue
            pv_jump = slip
            jump_end = -1  # where PV has made half its slip (below)
        # Most of the jump happens within an eighth of the hold (a ramp cut into
        # pieces by the band changes level just as much, slowly); counted from
        # the band's edge, where a ramp's piece ends as well.
        reach = min(e + step, y.size - 1)
        beyond = band + min_sharp_share * max(abs(pv_jump) - band, 0.0)
        risen = np.flatnonzero(np.abs(y[e:reach + 1] - level) >= beyond)
        if (abs(pv_jump) < min_jump_bands * band or risen.size == 0
                or np.sign(pv_jump) != np.sign(slip)):
            continue
        if jump_end < 0:
            jump_end = e + int(risen[0])
        # OP's move over the jump starts twice the jump's rise time before PV left
        # the hold: the process answers a kick of OP only after its delay and lag.
        lead = max(s, e - 1 - max(2, 2 * int(risen[0])))
        op_travel = float(u[lead] - u[s])
        op_during_jump = float(u[min(jump_end + min(2, e_after - s_after - 1), u.size - 1)]
                               - u[lead])
        # OP moving with the jump (the way that makes it) caused it; OP moving
        # against it is the controller answering the jump (proportional action).
        pushing = abs(op_during_jump) if gain_sign == 0 else max(
            0.0, op_during_jump * gain_sign * float(np.sign(pv_jump)))
        # The controller's push is a ramp through the hold; a kick of OP (a set
        # point step under proportional action) with PV answering after its dead
        # time is the process following OP.
        kick = float(np.max(np.abs(u[s + KICK_SAMPLES:lead + 1] - u[s:lead + 1 - KICK_SAMPLES]),
                            initial=0.0))
        if (abs(op_travel) < min_travel
                or (settled and pushing > max_jump_op_share * abs(op_travel))
                or kick > max_jump_op_share * abs(op_travel)):
            continue
        # The controller pushed because PV held off its reference, and the slip
        # moved PV towards it (a load moves PV away from where it held).  The
        # reference during the hold, or just after the jump: operators often
        # move the set point to where a sticky valve's flow ended up.
        offsets = (
            (median_level if reference is None else float(np.median(reference[part]))) - level
            for part in (slice(s, e), slice(s_after, s_after + min_hold)))
        toward = any(abs(offset) >= band and np.sign(pv_jump) == np.sign(offset)
                     for offset in offsets)
        if level_error is not None and not toward:
            # or the slope turned to close the level's error, over the hold or as
            # the valve slipped
            errors = (float(np.median(error[s:e])), float(np.median(error[e - step:e])))
            toward = any(abs(offset) >= error_band and np.sign(pv_jump) == np.sign(offset)
                         for offset in errors)
        direction = np.sign(pv_jump) * np.sign(op_travel)
        consistent = toward and (gain_sign == 0 or direction == gain_sign)
        episode = StickEpisode(s, jump_end, e, op_travel, float(pv_jump), op_during_jump,
                               bool(consistent))
        (episodes if consistent else contrary).append(episode)
    return EpisodeAnalysis(
        tuple(episodes), tuple(contrary), float(moves.sum()), hold_travel, reversal,
        float(np.ptp(u)), pv_noise, op_noise, band, gain_sign, span,
    )


@njit(cache=True)
def _reversal(u: FloatArray, moves: FloatArray) -> float:
    """The largest OP reversal within one hold: how far OP went one way and came
    back, the shorter of the two legs around its largest turning point (0 for a
    one-way ramp).  Measured on the backlash-filtered OP (``moves``, from
    :func:`travel_increments`), so noise adds nothing; a zig-zag of small moves
    is as large as its largest leg, not the sum of its legs.  Compiled: it runs
    once per hold."""
    n = u.size
    if n < 3:
        return 0.0
    # The filtered position moves up only where OP rose (OP stays within the
    # backlash of it), so the signs of OP's differences give the moves' signs.
    position = np.empty(n)
    position[0] = 0.0
    for k in range(1, n):
        position[k] = position[k - 1] + moves[k] * np.sign(u[k] - u[k - 1])
    lowest_after = np.empty(n)
    highest_after = np.empty(n)
    lowest_after[n - 1] = highest_after[n - 1] = position[n - 1]
    for k in range(n - 2, -1, -1):
        lowest_after[k] = min(lowest_after[k + 1], position[k])
        highest_after[k] = max(highest_after[k + 1], position[k])
    largest = 0.0
    lowest_before = highest_before = position[0]
    for k in range(n):
        lowest_before = min(lowest_before, position[k])
        highest_before = max(highest_before, position[k])
        peak = min(position[k] - lowest_before, position[k] - lowest_after[k])
        trough = min(highest_before - position[k], highest_after[k] - position[k])
        largest = max(largest, peak, trough)
    return float(largest)


def valve_proxy(pv: FloatArray, ts: float, process_type: ProcessType | None,
                smoothing: int = 20) -> FloatArray:
    """The signal that follows the valve position: PV, or for an integrating
    process the slope of PV (a moving average of ``smoothing`` differences: a
    difference amplifies the level's noise, and holds last hundreds of
    samples)."""
    if process_type == INTEGRATING:
        slope = np.diff(pv, prepend=pv[0]) / ts
        return moving_average(slope, smoothing)
    return pv


def analyse_window(window: LoopWindow) -> EpisodeAnalysis | None:
    """The stick-jump episodes of ``window`` (None without OP and PV).

    The reference a jump must head for is the set point when given, else the
    proxy's median; for an integrating process, whose proxy is a slope, a jump
    may also turn the slope the way that closes the level's error (set point,
    else the median PV, minus PV).
    The episodes are looked for at every smoothing of :data:`SMOOTHING_SCALES`;
    the scale whose episodes outnumber the contrary jumps most is reported
    (the band, hence the significance of a jump, follows the noise left at
    each scale).
    """
    if window.op is None or window.pv is None:
        return None
    proxy = valve_proxy(window.pv, window.ts, window.process_type)
    sign = loop_gain_sign(window.op, window.pv, window.sp)
    integrating = window.process_type == INTEGRATING
    set_point = np.median(window.pv) if window.sp is None else window.sp
    analyses = [
        find_stick_episodes(window.op, proxy, gain_sign=sign, smoothing=smoothing,
                            min_hold=MIN_HOLD * smoothing // SMOOTHING_SCALES[0],
                            reference=None if integrating else window.sp,
                            level_error=set_point - window.pv if integrating else None)
        for smoothing in SMOOTHING_SCALES
    ]
    return max(analyses, key=lambda a: len(a.episodes) - len(a.contrary))


@dataclass(frozen=True, kw_only=True)
class StickJumpDetector:
    """Stiction from stick-jump episodes (Kano et al. 2004; module docstring).

    Works on transient windows as well as on cycles: it needs holds, not a
    period. Stiction when at least ``min_episodes`` episodes (or one strong
    one) go the way OP pushed and at most ``max_contrary_share`` of the
    clear jumps go against it; no stiction when the jumps go either way
    (``min_random_share``), or when OP travelled at least ``min_travel`` (OP
    units, % of span) with fewer episodes than needed, none strong, and PV
    following OP through most of it (the share of travel made during holds
    below ``max_hold_share``); undecided otherwise.

    Attributes
    ----------
    min_episodes : int
        Consistent episodes needed to vote stiction.
    strong_range_share : float
        One episode is enough when OP travelled this share of its range over
        the window while PV held: the controller pushed the valve through a
        quarter of its whole excursion, and nothing moved.
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
        Number of episodes that gives confidence 0.63.
    """

    name: ClassVar[str] = "stick_jump"
    min_episodes: int = 2
    strong_range_share: float = 0.25
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
        strong = any(abs(e.op_travel) >= self.strong_range_share * analysis.op_range
                     for e in analysis.episodes)
        if (n >= self.min_episodes or strong) and share <= self.max_contrary_share:
            travel = np.median([abs(e.op_travel) for e in analysis.episodes])
            return MethodEvidence(
                self.name, STICTION, float(n),
                margin_confidence(n, 0.0, self.confidence_scale),
                f"{n} stick-jump episodes: PV held while OP travelled about {travel:.3g} % "
                f"of span, then jumped the way OP pushed ({n_contrary} contrary)", details,
            )
        if n + n_contrary >= self.min_episodes + 1 and share >= self.min_random_share:
            return MethodEvidence(
                self.name, NO_STICTION, share,
                margin_confidence(share, self.max_contrary_share, 0.25),
                f"{n_contrary} of {n + n_contrary} jumps after a hold went against OP: PV "
                "jumps either way, as disturbances make it, not the valve", details,
            )
        if (n < self.min_episodes and not strong
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
    """Stiction from an OP reversal that PV did not follow (Kano et al. 2004).

    Kano et al.'s sticking sections -- OP moves, the valve does not -- taken
    where they are least ambiguous: within one stuck period (PV flat at one
    level, see :func:`find_stick_episodes`) OP went one way and came back.
    A healthy valve turns every OP reversal into a PV reversal unless a load
    happens to mirror it; a valve with a stick band wider than the reversal
    holds through it.  A one-way OP ramp with PV flat is not used: a loop
    rejecting a slow load looks just like it.

    * Undecided when OP travelled less than ``min_travel`` (too little
      movement to expose a stick band) or PV never left its noise band by
      ``min_response_bands`` (the process shows no response to the valve).
    * Stiction when the reversal reaches ``min_reversal_share`` of OP's range
      over the window (and 10 OP noise standard deviations); otherwise
      undecided: the test is one sided.

    Attributes
    ----------
    min_reversal_share : float
        Smallest reversal, as a share of OP's range.  Healthy plant_dev
        windows reach 0.26, the sticky valve's windows with a reversal
        0.61-0.80; checked leave-one-tag-out in ``benchmarks/detection.py``.
    min_travel : float
        OP travel beyond noise (OP units, % of span) needed to judge.
    min_response_bands : float
        Range of the smoothed PV, in hold bands, that shows the process
        responds.
    """

    name: ClassVar[str] = "stuck_sections"
    min_reversal_share: float = 0.4
    min_travel: float = MIN_TRAVEL
    min_response_bands: float = 3.0

    def decide(self, analysis: EpisodeAnalysis) -> MethodEvidence:
        """The evidence of an :class:`EpisodeAnalysis`."""
        share = analysis.hold_reversal / analysis.op_range if analysis.op_range > 0 else 0.0
        details = {"hold_reversal": analysis.hold_reversal, "hold_travel": analysis.hold_travel,
                   "op_travel": analysis.op_travel_total}
        if analysis.op_travel_total < self.min_travel:
            return MethodEvidence.undecided(
                self.name, f"OP travelled {analysis.op_travel_total:.3g}, less than "
                f"{self.min_travel:g}: not enough valve movement to judge", share, details)
        if analysis.proxy_span < self.min_response_bands * 2.0 * analysis.band:
            return MethodEvidence.undecided(
                self.name, "PV never left its noise band: the process shows no response "
                "to judge the valve by", share, details)
        note = (f"PV held while OP went {analysis.hold_reversal:.3g} % of span one way and "
                f"back ({share:.0%} of its range)")
        if share >= self.min_reversal_share and analysis.hold_reversal >= 10 * analysis.op_noise:
            return MethodEvidence(self.name, STICTION, share,
                                  margin_confidence(share, self.min_reversal_share - 0.1, 0.2),
                                  note, details)
        return MethodEvidence.undecided(
            self.name, f"{note}: below {self.min_reversal_share:.0%}, which says nothing "
            "either way", share, details)

    def detect(self, window: LoopWindow) -> MethodEvidence:
        analysis = analyse_window(window)
        if analysis is None:
            return MethodEvidence.undecided(self.name, "needs both OP and PV")
        return self.decide(analysis)
