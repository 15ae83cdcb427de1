"""Which valves of a unit stick, from the unit's own model: the time-domain replay.

The harmonic-balance fingerprint (:mod:`analytics.plantwide.fingerprint`) reads a
cycle at its fundamental and third harmonic only; a sticky valve whose OP swings
far beyond its band has a describing function close to 1 and hides there.  In
the time domain it does not: between its slips it holds, and the PVs of the unit
carry every step.  :func:`replay_sticky_sets` fits, for every candidate set of
sticky valves,

1. each candidate valve's output as He's stiction model driven by its own measured
   OP (He et al. 2007; thesis Eq. 1.2 and Table 2.3, ``S = fs + fd``, ``J = fs -
   fd``, ERRATA item 6), a healthy valve passing its OP on unchanged.  Two
   families of replays are tried per valve (:class:`_Valve`): He's model running
   free from a few stick states (a valve that follows a wide OP swing in small
   slips, whose memory of its start is soon lost), and He's model whose band is
   a little narrower just before the turning points of its OP (a valve whose OP
   barely passes its band and slips once per swing; run free, such a replay is
   lost for good when ``fs`` is 2 % off, ``benchmarks/plantwide.py sync``).  The
   second family slips wherever its band says between the turns too: with two
   sticky valves, one valve's slips drive the other's OP through the process, and
   that valve slips while its OP still ramps, away from any turn of its own;
2. the valve outputs through the unit's sampled process matrix (exact zero-order
   hold, :func:`analytics.lti.discretise`) to every loop's PV, thesis Eq. 3.11 in
   the time domain, each matrix entry's gain free around the model's
   (:data:`GAIN_SIGMA`, so a matrix with gains 20 % off is absorbed) and each PV
   with an offset of its own;
3. the misfit: the squared residual of every PV in units of its noise variance
   (the sample-to-sample noise, :func:`analytics.stiction.stick_jump.robust_noise`)
   once the replay has settled.

Each set's members are chosen on their grids valve by valve (coordinate descent,
the others held); a valve of the second family then has its slip jump
fitted by least squares (its levels ``OP - fd`` must be exact: a level 0.1 % off
in valve 1 of the column moves PV 3 by 17 noise deviations) and its slips moved,
all together (:func:`_shift_slips`) and one by one (:func:`_refine_slips`), to
the instants the PVs show; then each member is chosen again with the others'
fitted replays held (:func:`_reselect`).  ``S`` of such a valve is the OP travel
between its slips that reverse (:func:`_slip_band`), which does not depend on the
gains.  A set of two or more valves is also grown from each set one valve smaller, the
added valve chosen with that set's replays held (:func:`_replace`), and a set whose
members another set replays better takes those replays (:func:`_borrow`).  The sets
are ranked by ``m ln(misfit / m) + VALVE_PENALTY * len(set)`` (``m`` PV samples) and
the best is named if it beats healthy valves and removes at least
:data:`MIN_MISFIT_DROP` of their misfit.  Figures: ``benchmarks/plantwide.py
replay`` (calibration seeds) and ``replay held-out``.

References
----------
.. [1] Q. P. He, J. Wang, M. Pottmann, S. J. Qin, "A curve fitting method for
   detecting valve stiction in oscillating control loops", Ind. Eng. Chem. Res.
   46 (2007) 4549-4560.
.. [2] Thesis chapter 3, Eq. 3.11 (the process side of the balance); Table 2.3.
"""

from __future__ import annotations

import itertools
import math
import weakref
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numba import njit
from numpy.typing import ArrayLike, NDArray
from scipy.signal import ss2tf

from analytics.errors import DataError, ModelSpecError
from analytics.limit_cycle import ProcessMatrix
from analytics.lti import DiscreteEntry, discretise
from analytics.stiction.stick_jump import moving_average, robust_noise
from analytics.types import FloatArray
from analytics.valves import he_update

__all__ = [
    "GAIN_SIGMA",
    "MIN_MISFIT_DROP",
    "VALVE_PENALTY",
    "ReplayFit",
    "ReplayLocalisation",
    "replay_sticky_sets",
]

GAIN_SIGMA = 0.3
"""Prior standard deviation of each process gain relative to the model's (ridge)."""

VALVE_PENALTY = 200.0
"""Score one more sticky valve must gain to be named (the score is ``m ln(misfit / m)``,
``m`` PV samples).  Chosen among 0-1,600 on the calibration columns (seeds 100-103,
every sticky set, gains exact and 20 % off, two external sines, ``benchmarks/plantwide.py
replay``): 50-800 named 27 of 28 sets right either way, 50 and less named a valve for a
sine at valve 1's input, 1,600 missed {1, 2, 3} three times in four; 200 is kept from
the earlier calibration (then 100-200 named 25 of 28)."""

FREE_BANDS = 10
"""Stick bands ``fs`` of the free-running replays, geometric over 0.3-30 % of the OP's
range: a valve that follows a wide OP swing in small slips."""

FREE_STARTS = 3
"""Stick states of the free-running replays (position at the start within ``fs`` of OP)."""

TURN_BANDS = tuple(np.geomspace(0.3, 0.9, 12))
"""Stick bands ``fs`` of the replays whose band narrows before turning points, share of
the OP's range, 30-90 % (the OP of a valve that slips once per swing turns just past its
band) in steps of :data:`TURN_TOLERANCE`, so that one of them is at most the tolerance
wider than any ``fs`` in the range and still slips where the valve's OP turns just past
its band."""

TURN_TOLERANCE = 0.1
"""How much narrower the band of those replays is just before a turning point of the OP."""

SLIP_ROUNDS = 3
"""Rounds of slip-jump fit and slip moves per valve."""

SLIP_SHIFT = 4
"""Most samples each slip of a replay is moved on its own to fit the PVs."""

GLOBAL_SHIFT = 3
"""Most samples all slips of a replay are moved together to fit the PVs."""

MAX_LAG = 10
"""Most samples before its OP's turning point at which a replay's band narrows (the slip
leads the turn by the loop's reaction)."""

TURN_HYSTERESIS = 0.3
"""Least swing of the (5-sample smoothed) OP between two turning points, share of its range."""

JUMP_RATIOS = (0.15, 0.3, 0.45, 0.6)
"""Ratios ``fd / fs`` tried per valve."""

MIN_MISFIT_DROP = 0.2
"""Least share of the healthy valves' misfit a named set must remove.  Right sets removed
54-85 % ({3} alone, gains 20 % off) to over 99 % on the calibration columns, the best set
for an external sine 0.04-0.5 %."""

FIT_SAMPLES = 3000
"""About this many samples of every PV enter the misfit (the window is strided)."""

SHORTLIST = 32
"""Grid replays whose misfit in single precision is among this many least are scored
exactly (:meth:`_Problem.best_grid_replay`)."""


@dataclass(frozen=True)
class ReplayFit:
    """One candidate set replayed through the unit's matrix.

    Attributes
    ----------
    loops : tuple of str
        The valves assumed sticky.
    misfit : float
        Squared PV residual in units of each PV's noise variance.
    score : float
        ``m ln(misfit / m) + VALVE_PENALTY * len(loops)`` over the ``m`` PV samples of
        the misfit; the lowest wins.
    S, J : tuple of float
        Fitted stick band and slip jump of each valve (``S = fs + fd``,
        ``J = fs - fd``, % of OP span).
    """

    loops: tuple[str, ...]
    misfit: float
    score: float
    S: tuple[float, ...]
    J: tuple[float, ...]


@dataclass(frozen=True)
class ReplayLocalisation:
    """Result of :func:`replay_sticky_sets`.

    Attributes
    ----------
    candidates : tuple of ReplayFit
        Every non-empty set of valves, best first.
    no_valve_misfit : float
        Misfit with every valve healthy.
    no_valve_score : float
        Its score (:func:`_score` with no valve).
    samples : int
        PV samples in the misfit (all loops together).
    """

    candidates: tuple[ReplayFit, ...]
    no_valve_misfit: float
    no_valve_score: float
    samples: int

    @property
    def sticky_valves(self) -> tuple[str, ...]:
        """The best-scoring set; empty when healthy valves score best or when it removes
        less than :data:`MIN_MISFIT_DROP` of their misfit (the model does not describe
        the cycle, or something outside the valves drives it)."""
        best = self.candidates[0] if self.candidates else None
        if best is None or best.score >= self.no_valve_score:
            return ()
        return best.loops if best.misfit <= (1 - MIN_MISFIT_DROP) * self.no_valve_misfit else ()

    @property
    def note(self) -> str:
        """The finding in words."""
        named = self.sticky_valves
        if named:
            fit = self.fit_of(named)
            assert fit is not None
            return (f"sticky: {', '.join(named)} (replay misfit {fit.misfit:.3g} against "
                    f"{self.no_valve_misfit:.3g} with healthy valves, over {self.samples} "
                    "PV samples)")
        best = self.candidates[0] if self.candidates else None
        tried = "" if best is None else (
            f"; the best, {', '.join(best.loops)}, leaves {best.misfit:.3g} against "
            f"{self.no_valve_misfit:.3g}")
        return ("no sticky set replayed through the unit model explains the PVs better than "
                f"healthy valves{tried}: the cycle comes from an external disturbance or a "
                "nonlinearity the model does not hold")

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-ready form."""
        return {
            "samples": self.samples,
            "no_valve_misfit": self.no_valve_misfit,
            "candidates": [{"loops": list(c.loops), "misfit": c.misfit, "score": c.score,
                            "S": list(c.S), "J": list(c.J)} for c in self.candidates],
            "sticky_valves": list(self.sticky_valves),
            "note": self.note,
        }

    @classmethod
    def of(cls, candidates: Sequence[ReplayFit], no_valve_misfit: float,
           samples: int) -> ReplayLocalisation:
        """The localisation of ``candidates`` (best first) against healthy valves'
        misfit, the healthy valves scored by :func:`_score`."""
        return cls(tuple(candidates), no_valve_misfit, _score(no_valve_misfit, samples, 0),
                   samples)

    def fit_of(self, loops: Sequence[str]) -> ReplayFit | None:
        """The fit of one candidate set (None for the empty set)."""
        wanted = set(loops)
        return next((c for c in self.candidates if set(c.loops) == wanted), None)


@njit(cache=True)
def _he_replays(op: FloatArray, fs: FloatArray, fd: FloatArray, start: FloatArray
                ) -> FloatArray:
    """He's valve driven by ``op``, one replay per row of parameters (``fs, fd`` and the
    position before the first sample)."""
    out = np.empty((fs.size, op.size))
    for p in range(fs.size):
        y = start[p]
        for k in range(op.size):
            y = he_update(fs[p], fd[p], y, op[k])
            out[p, k] = y
    return out


def _polynomials(entry: DiscreteEntry) -> tuple[FloatArray, FloatArray]:
    """``(b, a)`` in powers of ``z^-1`` of the sampled entry ``H(z)`` (see
    :meth:`analytics.lti.DiscreteEntry.frequency_response`), for :func:`scipy.signal.lfilter`."""
    m = entry.Ad.shape[0]
    num0, den = ss2tf(entry.Ad, entry.B0[:, None], entry.C[None, :], np.zeros((1, 1)))
    num1, _ = ss2tf(entry.Ad, entry.B1[:, None], entry.C[None, :], np.zeros((1, 1)))
    b = np.zeros(m + 2)
    b[:m + 1] += num0[0]
    b[1:m + 2] += num1[0] + entry.D * den
    return np.concatenate([np.zeros(entry.delay_samples), b]), np.asarray(den, dtype=float)


@njit(cache=True)
def _first_output(start: int, step: int, delay: int, count: int) -> tuple[int, int]:
    """The first of the ``count`` output samples ``start, start + step, ...`` at or after
    the dead time ``delay`` (the earlier ones stay zero): its index and sample."""
    q, pick = 0, start
    while q < count and pick < delay:
        q, pick = q + 1, pick + step
    return q, pick


@njit(cache=True)
def _low_order_coefficients(b: FloatArray, a: FloatArray
                            ) -> tuple[float, float, float, float, float]:
    """``b0, b1, a1, b2, a2`` of a filter of order at most 2 (zero beyond its order)."""
    order = b.size
    b1, a1 = (b[1], a[1]) if order > 1 else (0.0, 0.0)
    b2, a2 = (b[2], a[2]) if order > 2 else (0.0, 0.0)
    return b[0], b1, a1, b2, a2


@njit(cache=True)
def _direct_form(b: FloatArray, a: FloatArray, delay: int, u: FloatArray, centred: bool,
                 start: int, stop: int, step: int) -> FloatArray:
    """Each row of ``u`` (less its first sample if ``centred``) through ``z^-delay b(z) /
    a(z)`` (``b`` and ``a`` of one length, ``a[0] = 1``) from zero state, at the samples
    ``range(start, stop, step)``: the transposed direct form II of
    :func:`scipy.signal.lfilter`, operation for operation (the same bits), several rows at
    a time so that their recursions overlap (first and second order, the lags of a
    process matrix: :func:`_direct_form_low_order`, their states in registers)."""
    if b.size <= 3 and u.shape[0] == 1:
        return _direct_form_one_row(b, a, delay, u[0], centred, start, stop, step)
    if b.size <= 3:
        return _direct_form_low_order(b, a, delay, u, centred, start, stop, step)
    order, rows, width = b.size, u.shape[0], 8
    count = len(range(start, stop, step))
    out = np.zeros((rows, count))
    state, x, y = np.zeros((order, width)), np.empty(width), np.empty(width)
    origin = np.zeros(width)
    for first in range(0, rows, width):
        block = min(width, rows - first)
        state[:] = 0.0
        if centred:
            origin[:block] = u[first:first + block, 0]
        q, pick = _first_output(start, step, delay, count)
        for n in range(u.shape[1] - delay):
            for r in range(block):
                x[r] = u[first + r, n] - origin[r]
                y[r] = state[0, r] + b[0] * x[r]
            for j in range(1, order - 1):
                for r in range(block):
                    state[j - 1, r] = state[j, r] + x[r] * b[j] - y[r] * a[j]
            if order > 1:
                for r in range(block):
                    state[order - 2, r] = x[r] * b[order - 1] - y[r] * a[order - 1]
            if q < count and pick == n + delay:
                for r in range(block):
                    out[first + r, q] = y[r]
                q, pick = q + 1, pick + step
    return out


@njit(cache=True)
def _direct_form_low_order(b: FloatArray, a: FloatArray, delay: int, u: FloatArray,
                           centred: bool, start: int, stop: int, step: int) -> FloatArray:
    """:func:`_direct_form` of a filter of order at most 2 (``b`` of at most three
    coefficients), four rows at a time with the two states of each in local variables
    (rows beyond the last are zero, their outputs dropped)."""
    rows, order = u.shape[0], b.size
    count = len(range(start, stop, step))
    out = np.zeros((rows, count))
    b0, b1, a1, b2, a2 = _low_order_coefficients(b, a)
    q_first, pick_first = _first_output(start, step, delay, count)
    four = np.zeros((4, u.shape[1]))
    for first in range(0, rows, 4):
        block = min(4, rows - first)
        four[:block] = u[first:first + block]
        four[block:] = 0.0
        origin = four[:, 0].copy() if centred else np.zeros(4)
        o0, o1, o2, o3 = origin[0], origin[1], origin[2], origin[3]
        s00 = s01 = s02 = s03 = 0.0  # first state of each row
        s10 = s11 = s12 = s13 = 0.0  # second state
        q, pick = q_first, pick_first
        for n in range(u.shape[1] - delay):
            x0, x1 = four[0, n] - o0, four[1, n] - o1
            x2, x3 = four[2, n] - o2, four[3, n] - o3
            y0, y1 = s00 + b0 * x0, s01 + b0 * x1
            y2, y3 = s02 + b0 * x2, s03 + b0 * x3
            if order > 2:
                s00, s01 = s10 + x0 * b1 - y0 * a1, s11 + x1 * b1 - y1 * a1
                s02, s03 = s12 + x2 * b1 - y2 * a1, s13 + x3 * b1 - y3 * a1
                s10, s11 = x0 * b2 - y0 * a2, x1 * b2 - y1 * a2
                s12, s13 = x2 * b2 - y2 * a2, x3 * b2 - y3 * a2
            elif order > 1:
                s00, s01 = x0 * b1 - y0 * a1, x1 * b1 - y1 * a1
                s02, s03 = x2 * b1 - y2 * a1, x3 * b1 - y3 * a1
            if q < count and pick == n + delay:
                out[first, q] = y0
                if block > 1:
                    out[first + 1, q] = y1
                if block > 2:
                    out[first + 2, q] = y2
                if block > 3:
                    out[first + 3, q] = y3
                q, pick = q + 1, pick + step
    return out


@njit(cache=True)
def _direct_form_one_row(b: FloatArray, a: FloatArray, delay: int, x: FloatArray,
                         centred: bool, start: int, stop: int, step: int) -> FloatArray:
    """:func:`_direct_form_low_order` of one signal ``x`` (a replay's response is filtered
    alone): its two states in local variables, a third of the time of a block of four."""
    order = b.size
    count = len(range(start, stop, step))
    out = np.zeros((1, count))
    b0, b1, a1, b2, a2 = _low_order_coefficients(b, a)
    q, pick = _first_output(start, step, delay, count)
    origin = x[0] if centred else 0.0
    s0 = s1 = 0.0
    for n in range(x.size - delay):
        xn = x[n] - origin
        y = s0 + b0 * xn
        if order > 2:
            s0 = s1 + xn * b1 - y * a1
            s1 = xn * b2 - y * a2
        elif order > 1:
            s0 = xn * b1 - y * a1
        if q < count and pick == n + delay:
            out[0, q] = y
            q, pick = q + 1, pick + step
    return out


@dataclass(frozen=True)
class _Filter:
    """A sampled entry as :func:`scipy.signal.lfilter` polynomials (of one length, ``a[0] =
    1``) without the leading zeros of ``b`` (its dead time), which become a shift of the
    output: the filter's order, and its cost, is that of the lag alone."""

    b: FloatArray
    a: FloatArray
    delay: int

    @classmethod
    def of(cls, entry: DiscreteEntry) -> _Filter:
        b, a = _polynomials(entry)
        nonzero = np.flatnonzero(b)
        delay = int(nonzero[0]) if nonzero.size else 0
        b = np.trim_zeros(b[delay:], "b") if nonzero.size else b[:1]
        if a[0] != 1.0:  # normalised as lfilter does
            b, a = b / a[0], a / a[0]
        order = max(b.size, a.size)
        return cls(np.pad(b, (0, order - b.size)), np.pad(a, (0, order - a.size)), delay)

    def __call__(self, u: FloatArray, samples: slice, centred: bool = False) -> FloatArray:
        """``H(z) u`` of each row of ``u`` (less its first sample if ``centred``) from zero
        initial state, at ``samples``."""
        return np.asarray(_direct_form(self.b, self.a, self.delay, u, centred,
                                       *samples.indices(u.shape[1])))


@dataclass(frozen=True)
class _Row:
    """One PV's data for the ridge fits: weighted target and the healthy regressors."""

    target: FloatArray  # w (y - mean y) on the fit samples
    healthy: FloatArray  # (n, samples): w G_ik x_k
    present: tuple[bool, ...]


class _Problem:
    """The weighted least-squares problem of one unit: PV rows, filters, fit samples."""

    def __init__(self, ops: list[FloatArray], pvs: list[FloatArray],
                 process: ProcessMatrix, ts: float) -> None:
        n = len(ops)
        self.n, self.ops = n, ops
        entries = [[None if g is None else discretise(g, ts) for g in row] for row in process]
        self.filters: list[list[_Filter | None]] = [
            [None if e is None else _Filter.of(e) for e in row] for row in entries]
        settle = max(_settling_samples(e) for row in entries for e in row if e is not None)
        samples = pvs[0].size
        # each entry's step response over the window, for the slips moved one by one
        self.steps = [[None if f is None else f(np.ones((1, samples)), slice(None))[0]
                       for f in row] for row in self.filters]
        self.spans = [max(float(np.percentile(x, 99) - np.percentile(x, 1)), 1e-9) for x in ops]
        self.turns = [_turning_points(moving_average(x, 5), TURN_HYSTERESIS * span)
                      for x, span in zip(ops, self.spans, strict=True)]
        # the replays whose band narrows at turns know their level from the first one on
        self.settle = settle
        settle += max((int(t[0][0]) for t in self.turns if t[0].size), default=0)
        if samples - settle < 200:
            raise DataError(f"{samples} samples leave too few after the {settle} samples the "
                            "replay needs to settle")
        stride = max(1, (samples - settle) // FIT_SAMPLES)
        self.fit = slice(settle, samples, stride)
        self._signal_responses: dict[tuple[int, int, int],
                                     tuple[weakref.ref[FloatArray], FloatArray]] = {}
        self.weights = [1.0 / max(robust_noise(y), 1e-9 * max(np.ptp(y), 1.0)) for y in pvs]
        self.rows = []
        for i in range(n):
            healthy = np.zeros((n, self._fit_count(samples)))
            for k in range(n):
                if self.filters[i][k] is not None:
                    healthy[k] = self.response(i, k, ops[k][None, :])[0]
            y = pvs[i][self.fit]
            self.rows.append(_Row(self.weights[i] * (y - y.mean()), healthy,
                                  tuple(f is not None for f in self.filters[i])))

    def _fit_count(self, samples: int) -> int:
        return len(range(*self.fit.indices(samples)))

    def response(self, i: int, k: int, u: FloatArray) -> FloatArray:
        """``w_i G_ik u`` on the fit samples, centred, one row per row of ``u``."""
        filt = self.filters[i][k]
        assert filt is not None
        z = filt(u, self.fit, centred=True)
        return self.weights[i] * (z - z.mean(axis=1, keepdims=True))

    def signal_response(self, i: int, k: int, signal: FloatArray) -> FloatArray:
        """:meth:`response` of one signal, kept while the signal lives: the fits of the
        candidate sets filter the same replays again and again (two in three filterings
        of a column localisation repeat one already made).  The signal is known by
        identity and made read only, so that it cannot change behind its response."""
        key = (i, k, id(signal))
        kept = self._signal_responses.get(key)
        if kept is not None and kept[0]() is signal:
            return kept[1]
        signal.flags.writeable = False
        response = self.response(i, k, signal[None, :])[0]
        response.flags.writeable = False
        self._signal_responses[key] = (weakref.ref(signal), response)
        return response

    def row_misfits(self, i: int, regressors: FloatArray, valve: _Valve,
                    extra: FloatArray | None = None, picks: NDArray[np.int64] | None = None
                    ) -> FloatArray:
        """Ridge misfit of row ``i`` for every grid replay of ``valve`` (in single
        precision), or exactly for the grid replays ``picks``, the other valves' regressors
        held (``regressors``, and the columns ``extra`` with free coefficients: other
        valves' slip jumps)."""
        return self._candidate_misfits(i, valve, self._fixed_fit(i, regressors, valve, extra),
                                       picks)

    def _fixed_fit(self, i: int, regressors: FloatArray, valve: _Valve,
                   extra: FloatArray | None) -> tuple[FloatArray, FloatArray, float]:
        """The ridge fit of row ``i`` without ``valve`` (see :meth:`row_misfits`): its data
        columns with the residual on the data samples as the last column, the inverse of
        its Gram matrix and its misfit."""
        present = self.rows[i].present
        fixed = [k for k in range(self.n) if present[k] and k != valve.k]
        target = self.rows[i].target
        prior = 1.0 / GAIN_SIGMA
        free = np.zeros((0, target.size)) if extra is None else extra
        # fixed part: data columns plus one prior row per gain (target = prior for gain 1)
        a_data = np.vstack([regressors[fixed], free]).T
        a = np.vstack([a_data, np.hstack([prior * np.eye(len(fixed)),
                                          np.zeros((len(fixed), free.shape[0]))])])
        t = np.concatenate([target, prior * np.ones(len(fixed))])
        gram_inv = np.linalg.inv(a.T @ a)
        theta = gram_inv @ (a.T @ t)
        residual = t - a @ theta
        columns = np.column_stack([a_data, residual[:target.size]])
        return columns, gram_inv, float(residual @ residual)

    def _candidate_misfits(self, i: int, valve: _Valve,
                           fit: tuple[FloatArray, FloatArray, float],
                           picks: NDArray[np.int64] | None = None) -> FloatArray:
        """:meth:`row_misfits` from the fixed part's fit (:meth:`_fixed_fit`)."""
        columns, gram_inv, base = fit
        prior = 1.0 / GAIN_SIGMA
        responses, coarse, norms = valve.responses[i], valve.coarse[i], valve.norms[i]
        if responses is None or coarse is None or norms is None:
            return np.full(valve.size if picks is None else picks.size, base)
        # one pass over the candidates' responses for both products
        if picks is None:
            products = np.asarray(coarse @ columns.astype(np.float32), dtype=float)
        else:
            products, norms = responses[picks] @ columns, norms[picks]
        cross = products[:, :-1]  # (P, fixed)
        z_r = products[:, -1] + prior**2
        z_norm = norms + prior**2
        z_norm -= np.einsum("pf,fg,pg->p", cross, gram_inv, cross)
        # the candidate's own prior row: the fixed fit leaves its target, ``prior``, there
        return np.asarray(base + prior**2 - z_r**2 / np.maximum(z_norm, 1e-12))

    def best_grid_replay(self, valve: _Valve,
                         rows: Sequence[tuple[FloatArray, FloatArray | None]]) -> int:
        """The grid replay of ``valve`` with the least misfit summed over the PVs, the
        others held as ``rows`` gives them (each PV's regressors and extra columns, see
        :meth:`row_misfits`): the :data:`SHORTLIST` best in single precision (a pass over
        the grid's responses in half the memory), then the best of those exactly."""
        fits = [self._fixed_fit(i, regressors, valve, extra)
                for i, (regressors, extra) in enumerate(rows)]
        coarse = sum(self._candidate_misfits(i, valve, fit) for i, fit in enumerate(fits))
        picks = np.sort(np.argpartition(coarse, SHORTLIST)[:SHORTLIST]
                        if valve.size > SHORTLIST else np.arange(valve.size))
        exact = sum(self._candidate_misfits(i, valve, fit, picks) for i, fit in enumerate(fits))
        return int(picks[np.argmin(exact)])


def _settling_samples(entry: DiscreteEntry) -> int:
    """Samples until the slowest mode of a sampled entry has decayed to 0.1 %."""
    radius = float(np.max(np.abs(np.linalg.eigvals(entry.Ad)))) if entry.Ad.size else 0.0
    decay = 0 if radius < 1e-12 or radius >= 1.0 else math.ceil(math.log(1e-3) / math.log(radius))
    return decay + entry.delay_samples + 2


@njit(cache=True)
def _turn_replays(op: FloatArray, turns: NDArray[np.int64], directions: FloatArray,
                  lag: NDArray[np.int64], fs: FloatArray, fd: FloatArray) -> FloatArray:
    """He's valve (thesis Eq. 1.2: it slips to ``OP -/+ fd`` once OP has left it by more
    than ``fs``) whose band is :data:`TURN_TOLERANCE` narrower ``lag`` samples before each
    turning point of its OP, in the direction of the turn: in a limit cycle the
    controller reverses only once the valve has slipped, so a valve whose OP turns just
    past its band slipped there even if ``fs`` is a little too wide (run as He's model
    alone, such a replay is lost for good when ``fs`` is 1 % off); a slip while OP still
    ramps (another loop reversing it) is placed by the band alone.  The valve slips at
    the first such instant.  One replay per row of parameters."""
    out = np.empty((fs.size, op.size))
    for p in range(fs.size):
        first = max(turns[0] - lag[p], 0)
        out[p, :first] = op[first] - 2.0 * directions[0] * fs[p]
        y = op[first] - directions[0] * fd[p]
        out[p, first] = y
        k = first + 1
        for j in range(1, turns.size):
            narrowed = max(turns[j] - lag[p], 0)
            if narrowed < k:
                continue
            y = _he_run(op, out[p], y, fs[p], fd[p], k, narrowed)
            up = down = fs[p]
            if directions[j] > 0:
                up = (1.0 - TURN_TOLERANCE) * fs[p]
            else:
                down = (1.0 - TURN_TOLERANCE) * fs[p]
            if op[narrowed] - y > up:
                y = op[narrowed] - fd[p]
            elif y - op[narrowed] > down:
                y = op[narrowed] + fd[p]
            out[p, narrowed] = y
            k = narrowed + 1
        _he_run(op, out[p], y, fs[p], fd[p], k, op.size)
    return out


@njit(cache=True)
def _he_run(op: FloatArray, out: FloatArray, y: float, fs: float, fd: float, start: int,
            stop: int) -> float:
    """He's valve from position ``y`` driven by ``op[start:stop]``, written to
    ``out[start:stop]``; its last position."""
    for k in range(start, stop):
        y = he_update(fs, fd, y, op[k])
        out[k] = y
    return y


def _turning_points(x: FloatArray, hysteresis: float) -> tuple[NDArray[np.int64], FloatArray]:
    """Extremes of ``x`` between which it moves by more than ``hysteresis`` (the zig-zag
    of its swings): indices and +1 for a maximum, -1 for a minimum."""
    index, direction = [], []
    ext, heading = 0, 0
    for k in range(1, x.size):
        if heading == 0:
            if abs(x[k] - x[0]) > hysteresis:
                heading, ext = (1 if x[k] > x[0] else -1), k
        elif heading * (x[k] - x[ext]) > 0:
            ext = k
        elif heading * (x[ext] - x[k]) > hysteresis:
            index.append(ext)
            direction.append(float(heading))
            heading, ext = -heading, k
    return np.array(index, dtype=np.int64), np.array(direction)


class _Valve:
    """A candidate valve's grid of replays: He's model running free from its OP (a valve
    that follows a wide swing in small slips), and He's model whose band narrows before
    its OP's turning points (:func:`_turn_replays`: a valve that slips once per swing,
    its OP barely past the band); each replay's ``fs`` and ``fd`` and its response in
    every PV."""

    def __init__(self, problem: _Problem, k: int) -> None:
        self.k = k
        op, span = problem.ops[k], problem.spans[k]
        fs, ratio, share = (a.reshape(-1) for a in np.meshgrid(
            np.geomspace(0.003, 0.3, FREE_BANDS) * span, np.asarray(JUMP_RATIOS),
            np.linspace(-1.0, 1.0, FREE_STARTS), indexing="ij"))
        self.op, self.start, self.free = op, op[0] + share * fs, fs.size
        bands, jumps, self.lag = [fs], [fs * ratio], np.zeros(0, dtype=np.int64)
        self.turns, self.directions = problem.turns[k]
        if self.turns.size >= 4:
            lag, band, ratio = (a.reshape(-1) for a in np.meshgrid(
                np.arange(MAX_LAG + 1), np.asarray(TURN_BANDS) * span,
                np.asarray(JUMP_RATIOS), indexing="ij"))
            self.lag = lag
            bands.append(band)
            jumps.append(band * ratio)
        self.fs, self.fd = np.concatenate(bands), np.concatenate(jumps)
        self.size = self.fs.size
        # one family at a time, through every PV: only the responses are kept, not the grid
        rows = [i for i in range(problem.n) if problem.filters[i][k] is not None]
        parts: dict[int, list[FloatArray]] = {i: [] for i in rows}
        for family in self._families():
            replays = self._replays(family)
            for i in rows:
                parts[i].append(problem.response(i, k, replays))
        self.responses = [np.vstack(parts[i]) if i in parts else None for i in range(problem.n)]
        self.norms = [None if z is None else np.einsum("ps,ps->p", z, z) for z in self.responses]
        self.coarse = [None if z is None else z.astype(np.float32) for z in self.responses]
        # the grid replay chosen with the other valves' grid replays held (:func:`_descend`),
        # by those valves and their replays: the same choice recurs across candidate sets
        self.choices: dict[frozenset[tuple[int, int]], int] = {}

    def _families(self) -> list[slice]:
        return [slice(0, self.free)] + ([slice(self.free, self.size)] if self.lag.size else [])

    def _replays(self, rows: slice) -> FloatArray:
        """The replays of grid rows ``rows``, all of one family."""
        fs, fd = self.fs[rows], self.fd[rows]
        if rows.start < self.free:
            return _he_replays(self.op, fs, fd, self.start[rows])
        lag = self.lag[rows.start - self.free:rows.stop - self.free]
        return _turn_replays(self.op, self.turns, self.directions, lag, fs, fd)

    def replay(self, p: int) -> FloatArray:
        """Grid replay ``p``, computed again (the grid is not kept)."""
        return self._replays(slice(p, p + 1))[0]

    def slips_at_turns(self, p: int) -> bool:
        """Whether replay ``p`` is of the family whose band narrows before turning points
        (its slips are fitted one by one)."""
        return p >= self.free


def _row_fit(problem: _Problem, i: int, replays: Mapping[int, FloatArray],
             jumps: Mapping[int, FloatArray],
             held: Mapping[tuple[int, bool], FloatArray] | None = None
             ) -> tuple[float, FloatArray, FloatArray, FloatArray]:
    """Ridge fit of PV ``i``: each valve's response (its replay or its OP) with its gain
    drawn to the model's, and for each valve in ``jumps`` the response of its slip
    directions with a free coefficient (its slip jump ``fd`` times the gain, so that the
    jump is fitted as exactly as the levels need).  Returns the misfit, the gains of the
    valves (0 where the matrix has no entry), the residual and the jumps' coefficients.
    ``held`` gives responses already computed, by valve and whether of its jumps."""
    row = problem.rows[i]
    present = [k for k in range(problem.n) if row.present[k]]
    known = held or {}

    def column(k: int, signal: FloatArray, jump: bool) -> FloatArray:
        response = known.get((k, jump))
        return problem.signal_response(i, k, signal) if response is None else response

    columns = [column(k, replays[k], False) if k in replays else row.healthy[k]
               for k in present]
    extra = [column(k, jumps[k], True) for k in jumps if row.present[k]]
    # the normal equations of the data rows and one prior row per gain (target ``prior``
    # for the model's gain), as in :meth:`_Problem.row_misfits`: the prior rows keep them
    # well conditioned, and they cost a fifth of an orthogonal factorisation
    data = np.array(columns + extra)  # (columns, samples)
    prior_squared = np.zeros(data.shape[0])
    prior_squared[:len(present)] = GAIN_SIGMA**-2
    theta = np.linalg.solve(data @ data.T + np.diag(prior_squared),
                            data @ row.target + prior_squared)
    residual = row.target - theta @ data
    gain_misfit = float(np.sum(prior_squared * (1.0 - theta) ** 2))
    gains = np.zeros(problem.n)
    gains[present] = theta[:len(present)]
    return (float(residual @ residual) + gain_misfit, gains, residual,
            theta[len(present):])


def _slip_directions(u: FloatArray) -> FloatArray:
    """+1 after an upward slip of a replay, -1 after a downward one (0 before the first)."""
    steps = np.sign(np.diff(u, prepend=u[0]))
    index = np.where(steps != 0, np.arange(u.size), 0)
    return np.asarray(steps[np.maximum.accumulate(index)])


def _slips(base: FloatArray, jump: FloatArray) -> NDArray[np.int64]:
    """The samples where a replay (its levels before the jump, ``base``, and its slip
    directions) slips: two slips the same way change the level only."""
    return np.flatnonzero((np.diff(base) != 0) | (np.diff(jump) != 0)) + 1


def _set_misfit(problem: _Problem, replays: Mapping[int, FloatArray],
                jumps: Mapping[int, FloatArray] | None = None) -> float:
    return sum(_row_fit(problem, i, replays, jumps or {})[0] for i in range(problem.n))


def _descend(problem: _Problem, members: tuple[int, ...], valves: Mapping[int, _Valve],
             passes: int = 2) -> dict[int, int]:
    """Coordinate descent: each member's replay chosen over its grid, the others held."""
    chosen: dict[int, int] = {}
    for _ in range(passes):
        for k in members:
            valve = valves[k]
            held = frozenset((other, p) for other, p in chosen.items() if other != k)
            if held not in valve.choices:
                rows = []
                for i, row in enumerate(problem.rows):
                    regressors = row.healthy.copy()
                    for other, p in held:
                        response = valves[other].responses[i]
                        if response is not None:
                            regressors[other] = response[p]
                    rows.append((regressors, None))
                valve.choices[held] = problem.best_grid_replay(valve, rows)
            chosen[k] = valve.choices[held]
    return chosen


def _reselect(problem: _Problem, k: int, valve: _Valve, replays: Mapping[int, FloatArray],
              jumps: Mapping[int, FloatArray]) -> int:
    """Valve ``k``'s best grid replay with the other members' fitted replays held."""
    others = {j: u for j, u in replays.items() if j != k}
    other_jumps = {j: d for j, d in jumps.items() if j != k}
    rows = []
    for i, row in enumerate(problem.rows):
        regressors = row.healthy.copy()
        for j, u in others.items():
            if row.present[j]:
                regressors[j] = problem.signal_response(i, j, u)
        extra = [problem.signal_response(i, j, d) for j, d in other_jumps.items()
                 if row.present[j]]
        rows.append((regressors, np.array(extra) if extra else None))
    return problem.best_grid_replay(valve, rows)


def _jump_index(problem: _Problem, i: int, k: int, jumps: Mapping[int, FloatArray]) -> int:
    """Position of valve ``k``'s jump column among row ``i``'s (see :func:`_row_fit`)."""
    return [j for j in jumps if problem.rows[i].present[j]].index(k)


@njit(cache=True)
def _superpose(taus: NDArray[np.int64], changes: FloatArray, step: FloatArray,
               picks: NDArray[np.int64], out: FloatArray) -> None:
    """A filter's response (from zero state) at the samples ``picks`` (ascending), into
    ``out``, to an input that steps by ``changes`` at the samples ``taus`` (ascending):
    the sum of its step response ``step`` shifted to every change (a slip moved changes
    the valve in a few steps only), the changes added in their order at each sample."""
    for q in range(picks.size):
        total = 0.0
        for c in range(taus.size):
            if taus[c] > picks[q]:
                break
            total += changes[c] * step[picks[q] - taus[c]]
        out[q] = total


@njit(cache=True)
def _block_sum(x: FloatArray, first: int, count: int) -> float:
    """``np.sum`` of at most 128 elements as numpy adds them: eight accumulators from
    eight on, the rest one by one."""
    if count < 8:
        total = 0.0
        for q in range(first, first + count):
            total += x[q]
        return total
    r0, r1, r2, r3 = x[first], x[first + 1], x[first + 2], x[first + 3]
    r4, r5, r6, r7 = x[first + 4], x[first + 5], x[first + 6], x[first + 7]
    end = first + count - count % 8
    for q in range(first + 8, end, 8):
        r0, r1, r2, r3 = r0 + x[q], r1 + x[q + 1], r2 + x[q + 2], r3 + x[q + 3]
        r4, r5, r6, r7 = r4 + x[q + 4], r5 + x[q + 5], r6 + x[q + 6], r7 + x[q + 7]
    total = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    for q in range(end, first + count):
        total += x[q]
    return total


@njit(cache=True)
def _numpy_sum(x: FloatArray) -> float:
    """``np.sum(x)`` with numpy's bits: its pairwise summation, blocks of up to 128
    (:func:`_block_sum`) added in halves of a multiple of eight elements.  The recursion
    runs on a stack of its own (numba's cache cannot load a recursive function), made only
    for more than one block."""
    if x.size <= 128:
        return _block_sum(x, 0, x.size)
    first, count = np.zeros(64, np.int64), np.zeros(64, np.int64)
    left, left_done = np.zeros(64), np.zeros(64, np.bool_)
    top, count[0] = 0, x.size
    while True:
        if count[top] > 128:  # the left half first
            half = count[top] // 2 - count[top] // 2 % 8
            first[top + 1], count[top + 1], left_done[top + 1] = first[top], half, False
            top += 1
            continue
        value = _block_sum(x, first[top], count[top])
        top -= 1
        while top >= 0 and left_done[top]:  # both halves of this frame are summed
            value = left[top] + value
            top -= 1
        if top < 0:
            return value
        left[top], left_done[top] = value, True  # then its right half
        half = count[top] // 2 - count[top] // 2 % 8
        first[top + 1], count[top + 1] = first[top] + half, count[top] - half
        left_done[top + 1] = False
        top += 1


@njit(cache=True)
def _move_each_slip(op: FloatArray, base: FloatArray, jump: FloatArray,
                    slips: NDArray[np.int64], residual: FloatArray, scale: FloatArray,
                    steps: FloatArray, start: int, stride: int, tail: int) -> None:
    """The loop of :func:`_refine_slips` over the slips of one replay, in place on its
    levels ``base``, its slip directions ``jump`` and the PV residuals (one row per PV the
    valve drives, with its gain and jump coefficient in ``scale`` and its entry's step
    response in ``steps``).  Each trial moves slip ``t`` to ``t + shift``: its level
    becomes the OP there, and every PV changes by its entry's response to the change of
    the valve's levels and directions, up to the next slip."""
    stop, rows, trials = base.size, residual.shape[0], 2 * SLIP_SHIFT + 1
    responses = np.empty((rows, trials, residual.shape[1]))
    squares = np.empty(residual.shape[1])
    change, held = np.empty(trials), np.empty(rows)
    fixed = np.empty(stop + 1, dtype=np.int64)
    breaks, taus = np.empty(stop + 2, dtype=np.int64), np.empty(stop + 2, dtype=np.int64)
    changes = np.empty(stop + 2)
    for j in range(slips.size):
        t = slips[j]
        before = slips[j - 1] if j > 0 else 0
        after = slips[j + 1] if j + 1 < slips.size else stop
        earliest = max(-SLIP_SHIFT, before + 1 - t)
        count = min(SLIP_SHIFT, after - 1 - t) + 1 - earliest
        low, high = t + earliest, min(after + tail, stop)
        q0 = max(0, -(-(low - start) // stride))
        q1 = max(q0, -(-(high - start) // stride))
        if count < 2 or q1 == q0:
            continue
        picks = start + stride * np.arange(q0, q1) - low
        # the change of the valve (at sample ``low + k``) is constant between the moved
        # slip and the replay's own steps (the slip itself, and a neighbour already moved
        # into the stretch), and zero from the next slip on: its breaks but the moved slip
        n_fixed = 1
        fixed[0] = 0
        for k in range(1, after - low):
            if base[low + k] != base[low + k - 1] or jump[low + k] != jump[low + k - 1]:
                fixed[n_fixed] = k
                n_fixed += 1
        if after < high:
            fixed[n_fixed] = after - low
            n_fixed += 1
        for i in range(rows):
            r = residual[i, q0:q1]
            for q in range(r.size):
                squares[q] = r[q] * r[q]
            held[i] = _numpy_sum(squares[:q1 - q0])
        change[:count] = 0.0
        for m in range(count):
            moved = t + earliest + m - low
            n_breaks, placed = 0, False
            for f in range(n_fixed):  # the moved slip in its place among the breaks
                if not placed and moved <= fixed[f]:
                    placed = True
                    if moved < fixed[f]:
                        breaks[n_breaks] = moved
                        n_breaks += 1
                breaks[n_breaks] = fixed[f]
                n_breaks += 1
            if not placed:
                breaks[n_breaks] = moved
                n_breaks += 1
            for i in range(rows):
                n_changes, previous = 0, 0.0
                for b in range(n_breaks):
                    k = breaks[b]
                    value = 0.0
                    if k < after - low:
                        trial_base = base[t - 1] if k < moved else op[t + earliest + m]
                        trial_jump = jump[t - 1] if k < moved else jump[t]
                        value = (scale[i, 0] * (trial_base - base[low + k])
                                 + scale[i, 1] * (trial_jump - jump[low + k]))
                    if value - previous != 0.0:
                        taus[n_changes], changes[n_changes] = k, value - previous
                        n_changes += 1
                    previous = value
                r, dz = residual[i, q0:q1], responses[i, m, :q1 - q0]
                _superpose(taus[:n_changes], changes[:n_changes], steps[i], picks, dz)
                for q in range(r.size):
                    d = r[q] - dz[q]
                    squares[q] = d * d
                change[m] += _numpy_sum(squares[:r.size]) - held[i]
        best = int(np.argmin(change[:count]))
        if change[best] < 0 and earliest + best != 0:
            moved = t + earliest + best
            base[low:moved], base[moved:after] = base[t - 1], op[moved]
            jump[low:moved], jump[moved:after] = jump[t - 1], jump[t]
            for i in range(rows):
                residual[i, q0:q1] -= responses[i, best, :q1 - q0]


def _refine_slips(problem: _Problem, k: int, replays: dict[int, FloatArray],
                  jumps: dict[int, FloatArray]) -> None:
    """Move each slip of valve ``k`` by up to :data:`SLIP_SHIFT` samples where that lowers
    the misfit (gains and jump coefficients held), its level the OP at the new instant;
    ``replays[k]`` (the levels before the jump) and ``jumps[k]`` are updated in place."""
    base, jump = replays[k].copy(), jumps[k].copy()
    rows = [i for i in range(problem.n) if problem.filters[i][k] is not None]
    residual, scale = [], []
    for i in rows:
        _, gains, res, coefficients = _row_fit(problem, i, replays, jumps)
        residual.append(res)
        scale.append((gains[k] * problem.weights[i],
                      coefficients[_jump_index(problem, i, k, jumps)] * problem.weights[i]))
    _move_each_slip(problem.ops[k], base, jump, _slips(base, jump), np.array(residual),
                    np.array(scale), np.array([problem.steps[i][k] for i in rows]),
                    problem.fit.start, problem.fit.step, problem.settle)
    replays[k], jumps[k] = base, jump


def _shifted(op: FloatArray, base: FloatArray, jump: FloatArray, shift: int
             ) -> tuple[FloatArray, FloatArray]:
    """A replay's levels and jumps with every slip ``shift`` samples later (earlier if
    negative), each level the OP at its new instant."""
    slips = _slips(base, jump)
    moved = np.clip(slips + shift, 1, op.size - 1)
    index = np.zeros(op.size, dtype=np.int64)
    index[moved] = moved
    index = np.maximum.accumulate(index)
    after = np.zeros(op.size)
    after[moved] = jump[slips]
    new_jump = np.where(index > 0, after[index], jump[0])
    new_base = np.where(index > 0, op[index], base[0])
    return np.asarray(new_base, dtype=np.float64), np.asarray(new_jump, dtype=np.float64)


def _shift_slips(problem: _Problem, k: int, replays: dict[int, FloatArray],
                 jumps: dict[int, FloatArray]) -> None:
    """Move every slip of valve ``k`` by the same number of samples (up to
    :data:`GLOBAL_SHIFT`) where the misfit is least: slips all placed early or late hold
    the fitted gains where they are, and one slip moved alone cannot undo that."""
    trials = [_shifted(problem.ops[k], replays[k], jumps[k], shift)
              for shift in range(-GLOBAL_SHIFT, GLOBAL_SHIFT + 1)]
    # the other members' responses are the same in every trial, and the trials' own
    # responses in a PV are filtered together
    held = [{(j, jump): problem.signal_response(i, j, u)
             for jump, signals in ((False, replays), (True, jumps))
             for j, u in signals.items() if j != k and problem.rows[i].present[j]}
            for i in range(problem.n)]
    levels, directions = (np.array(signals) for signals in zip(*trials, strict=True))
    own = [{(k, False): problem.response(i, k, levels),
            (k, True): problem.response(i, k, directions)} if problem.rows[i].present[k] else {}
           for i in range(problem.n)]
    misfits = [sum(_row_fit(problem, i, {**replays, k: base}, {**jumps, k: jump},
                            {**held[i], **{key: z[m] for key, z in own[i].items()}})[0]
                   for i in range(problem.n)) for m, (base, jump) in enumerate(trials)]
    replays[k], jumps[k] = trials[int(np.argmin(misfits))]


def _slip_band(op: FloatArray, base: FloatArray, jump: FloatArray) -> float:
    """He's ``S = fs + fd`` from a replay's slips: the OP travel between a slip and the next
    one when that goes the other way (the median over the window)."""
    slips = _slips(base, jump)
    reverses = jump[slips[1:]] != jump[slips[:-1]]
    travel = np.abs(np.diff(op[slips]))[reverses]
    return float(np.median(travel)) if travel.size else 0.0


def _fit_set(problem: _Problem, members: tuple[int, ...], valves: Mapping[int, _Valve]
             ) -> tuple[float, dict[int, FloatArray], dict[int, FloatArray],
                        dict[int, tuple[float, float]]]:
    """Fit one candidate set: its members' grid replays by coordinate descent, then the
    slips of those whose band narrows at turns fitted and moved, then each member chosen
    again with the others' fitted replays held.  Returns the misfit, each member's
    replay (its levels before the jump where it has slip directions), the slip directions
    by member and each member's grid ``fs`` and ``fd``."""
    chosen = _descend(problem, members, valves)
    replays = {k: valves[k].replay(chosen[k]) for k in members}
    jumps = {}
    for k in members:
        if valves[k].slips_at_turns(chosen[k]):
            jumps[k] = _slip_directions(replays[k])
            replays[k] = replays[k] + valves[k].fd[chosen[k]] * jumps[k]
    for _ in range(SLIP_ROUNDS):
        for k in jumps:
            _shift_slips(problem, k, replays, jumps)
            _refine_slips(problem, k, replays, jumps)
    misfit = _set_misfit(problem, replays, jumps)
    bands = {k: (float(valves[k].fs[p]), float(valves[k].fd[p])) for k, p in chosen.items()}
    for k in members if len(members) > 1 else ():
        trial = _replace(problem, k, valves[k], replays, jumps)
        if trial[0] < misfit:
            misfit, replays, jumps, band = trial
            bands[k] = band
    return misfit, replays, jumps, bands


def _replace(problem: _Problem, k: int, valve: _Valve, replays: Mapping[int, FloatArray],
             jumps: Mapping[int, FloatArray]
             ) -> tuple[float, dict[int, FloatArray], dict[int, FloatArray], tuple[float, float]]:
    """Valve ``k`` chosen again on its grid with the other members' replays held (its slips
    fitted as in :func:`_fit_set`): the misfit, replays and slip directions of the set with
    that choice, and its grid ``fs`` and ``fd``."""
    p = _reselect(problem, k, valve, replays, jumps)
    trial, trial_jumps = dict(replays), {j: d for j, d in jumps.items() if j != k}
    trial[k] = valve.replay(p)
    if valve.slips_at_turns(p):
        trial_jumps[k] = _slip_directions(trial[k])
        trial[k] = trial[k] + valve.fd[p] * trial_jumps[k]
        for _ in range(SLIP_ROUNDS):
            _refine_slips(problem, k, trial, trial_jumps)
    return (_set_misfit(problem, trial, trial_jumps), trial, trial_jumps,
            (float(valve.fs[p]), float(valve.fd[p])))


_SetFit = tuple[float, dict[int, FloatArray], dict[int, FloatArray], dict[int, tuple[float, float]]]
"""A set's fit as :func:`_fit_set` returns it."""


def _borrow(problem: _Problem, members: tuple[int, ...],
            found: Mapping[tuple[int, ...], _SetFit]) -> _SetFit:
    """The fit of ``members``, or one that replays some of them as another set's fit does
    (the rest as before) where that fits the PVs better.  Each set's descent ends where its
    own start leads it: with valve 1 sticky (calibration seed 100) the pair {1, 2}
    replays valve 1 to the noise (misfit 8,491 over 11,391 PV samples) while valve 1
    alone ends at 248,113; with the pair's replay of valve 1 it fits 8,470, and the
    sets are compared by the best replays of their members found for any set."""
    best = found[members]
    for other, (_, replays, jumps, fitted) in found.items():
        shared = set(members) & set(other)
        if other == members or not shared:
            continue
        trial = {k: (replays if k in shared else best[1])[k] for k in members}
        trial_jumps = {k: signals[k] for k in members
                       if k in (signals := jumps if k in shared else best[2])}
        misfit = _set_misfit(problem, trial, trial_jumps)
        if misfit < best[0]:
            bands = {k: (fitted if k in shared else best[3])[k] for k in members}
            best = (misfit, trial, trial_jumps, bands)
    return best


def replay_sticky_sets(
    loops: Mapping[str, tuple[ArrayLike, ArrayLike]],
    ts: float,
    process: ProcessMatrix,
) -> ReplayLocalisation:
    """Fit every candidate set of sticky valves by replaying it through the unit's matrix.

    Parameters
    ----------
    loops : mapping of str to (array_like, array_like)
        ``loop id -> (OP, PV)`` in the row and column order of ``process``.
    ts : float
        Sampling interval, s.
    process : n x n nested sequence of TransferFunction or None
        ``G[i][j]`` from valve ``j`` to PV ``i``.

    Returns
    -------
    ReplayLocalisation
    """
    names = tuple(loops)
    n = len(names)
    if len(process) != n or any(len(row) != n for row in process):
        raise ModelSpecError(f"the process matrix must be {n} x {n}, one row per loop")
    ops = [np.asarray(loops[k][0], dtype=np.float64) for k in names]
    pvs = [np.asarray(loops[k][1], dtype=np.float64) for k in names]
    problem = _Problem(ops, pvs, process, ts)
    healthy = _set_misfit(problem, {})
    samples = n * problem.rows[0].target.size
    valves = {k: _Valve(problem, k) for k in range(n)}
    sets = [members for size in range(1, n + 1)
            for members in itertools.combinations(range(n), size)]
    found: dict[tuple[int, ...], _SetFit] = {}
    for members in sets:
        found[members] = _fit_set(problem, members, valves)
        for k in members if len(members) > 1 else ():
            # grown from the set without k, as fitted (or borrowed) before
            smaller = _borrow(problem, tuple(j for j in members if j != k), found)
            grown = _replace(problem, k, valves[k], smaller[1], smaller[2])
            if grown[0] < found[members][0]:
                found[members] = (*grown[:3], {**smaller[3], k: grown[3]})
    fits = []
    for members in sets:
        misfit, replays, jumps, fitted = _borrow(problem, members, found)
        bands, steps = [], []
        for k in members:
            if k in jumps:
                _, gains, _, coefficients = _row_fit(problem, k, replays, jumps)
                band = _slip_band(ops[k], replays[k], jumps[k])
                fd = -coefficients[_jump_index(problem, k, k, jumps)] / gains[k]
                bands.append(band)
                steps.append(band - 2.0 * float(np.clip(fd, 0.0, band / 2)))
            else:
                fs, fd = fitted[k]
                bands.append(float(fs + fd))
                steps.append(float(fs - fd))
        fits.append(ReplayFit(tuple(names[k] for k in members), misfit,
                              _score(misfit, samples, len(members)),
                              tuple(bands), tuple(steps)))
    fits.sort(key=lambda f: f.score)
    return ReplayLocalisation.of(fits, healthy, samples)


def _score(misfit: float, samples: int, valves: int) -> float:
    """``m ln(misfit / m) + VALVE_PENALTY * valves`` over ``m`` PV samples: the Gaussian
    log-likelihood of the residual with its variance unknown (the model's error as well
    as the noise), plus the penalty."""
    return samples * math.log(max(misfit, 1e-300) / samples) + VALVE_PENALTY * valves
