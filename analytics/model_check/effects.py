"""The effects a base loop model can miss, and how each is fitted to measured data.

Every candidate extension is scored the same way (:class:`ReplayData`): the
measured OP drives valve and process (:meth:`LoopModel.replay`), so the
comparison does not depend on the phase of a free-running limit cycle; the
PV operating point (and, for an integrator, the unknown balance point, a
ramp) is fitted by least squares; the parameters of the extension are fitted
on alternate blocks of the record and scored on the blocks in between, which
they never saw (:func:`analytics.model_check.check.check_model` does this
both ways).

Catalogue (:data:`EFFECTS`, simplest first; the check prefers the simpler of
two effects that explain the data equally well):

``gain_mismatch``
    Process gain ``K``: least squares (the response is linear in ``K``).
``deadtime_mismatch``
    Dead time: every whole number of samples up to twice the base delay plus
    a quarter of the record's dominant period.
``time_constant_mismatch``
    Time constant (for an integrator: a lag before it): log grid and a
    bounded refinement.
``valve_characteristic``
    Curvature ``c`` of the installed characteristic (gain ``e^{c (x - op_bias)/100}``).
``measurement_quantization``
    PV on a grid of ``resolution``: read from the measured PV itself (its
    increments are whole multiples of one step); the noise ahead of the
    rounding is fitted, and the replay predicts the mean reported value.
``external_disturbance``
    A sinusoidal load on PV: the frequency of the largest peak of the
    residual's periodogram, refined by least squares with amplitude and phase.
``asymmetric_stiction``
    Friction ``(S, J)`` opening and closing separately: grid, then compass search.
``position_dependent_stiction``
    Friction ``(S, J)`` inside a band of travel ``[low, high]``, the base
    friction outside: grid over bands between OP deciles and evenly spaced
    points of its travel, then compass search.  The band holds at most 80 %
    of the samples (the valve must be seen outside it) and is at least half
    its stick band wide.

The two friction searches try thousands of frictions; they are costed many at
a time (:meth:`ReplayData.friction_errors`: one compiled replay of the valves
and the process for a grid chunk, or for the next points of the compass
searches, which run side by side), and no point is costed twice.

References
----------
.. [1] Thesis section 3.4.6 (the three reasons for a mismatch between model
   and experiment), section 5.5.3 and Fig. 5.14 (position- and
   direction-dependent stiction).
.. [2] Ljung (1999), *System Identification*, 2nd ed., sec. 16.4: model
   validation by simulation on fresh data (cross-validation).
.. [3] Bergmeir & Benitez (2012), "On the use of cross-validation for time
   series predictor evaluation", Information Sciences 191:192-213 (blocked
   cross-validation).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Generator, Sequence
from copy import copy
from dataclasses import dataclass, replace
from itertools import pairwise
from typing import Any, Literal

import numpy as np
from numba import njit
from numpy.typing import ArrayLike, NDArray
from scipy import fft as sfft
from scipy.optimize import minimize_scalar

from analytics.model_check.model import (
    FrictionValve,
    LoopModel,
    PeriodicLoad,
    Quantiser,
    StictionZone,
    friction_of,
    friction_parameters,
    friction_valve,
)
from analytics.types import BoolArray, FloatArray

__all__ = [
    "EFFECTS",
    "STARTS",
    "Candidate",
    "Prediction",
    "ReplayData",
    "describe_parameters",
    "fit_effect",
    "pv_grid",
]

HeldOut = Literal["odd", "even", "none"]

EFFECTS = (
    "gain_mismatch",
    "deadtime_mismatch",
    "time_constant_mismatch",
    "valve_characteristic",
    "measurement_quantization",
    "external_disturbance",
    "asymmetric_stiction",
    "position_dependent_stiction",
)
"""Effects the check tries, simplest first (``none`` is the base model)."""

FRICTION_CHUNK = 16
"""Frictions replayed together by :meth:`ReplayData.friction_errors` (bounds the memory
of a search grid)."""


@dataclass(frozen=True)
class Prediction:
    """A model's replay of the measured OP, against the measured PV.

    Attributes
    ----------
    pv : ndarray
        Simulated measured PV at every sample.
    mv : ndarray
        Simulated valve position.
    sse_fit, sse_test : float
        Squared error on the fitting blocks and on the held-out blocks.
    pv_bias : float
        Fitted PV with MV at ``op_bias`` (free run; else the first PV sample).
    scale : float
        Fitted factor on the process response (1 unless asked for).
    """

    pv: FloatArray
    mv: FloatArray
    sse_fit: float
    sse_test: float
    pv_bias: float
    scale: float = 1.0


@dataclass(frozen=True)
class Candidate:
    """One effect fitted to the data.

    Attributes
    ----------
    effect : str
        A name of :data:`EFFECTS`.
    parameters : dict
        The fitted parameters of the extension.
    model : LoopModel
        The base model with the extension.
    prediction : Prediction
        Its replay of the measured OP.
    note : str
        Why the effect could not be fitted (then ``model`` is the base model).
    search_point : tuple of float
        Coordinates of the compass search's result (friction fits only), from
        which a refit on more data can start.
    """

    effect: str
    parameters: dict[str, float]
    model: LoopModel
    prediction: Prediction
    note: str = ""
    search_point: tuple[float, ...] = ()


class ReplayData:
    """Measured OP and PV, the blocks fitted and held out, and the scoring of a model.

    The first ``warm_up`` samples (valve and process settle from the assumed
    initial rest) are not scored.  The rest is cut into ``2 * folds`` equal
    blocks; the ``held_out`` ones (odd, even or none) test, the others fit.

    By default the model is replayed free-running over the whole record with
    one fitted offset, the PV at rest (and with ``ramp`` a fitted ramp, which
    takes up an error of an integrator's balance point ``op_bias``).  An
    integrating process turns any small error of the model valve or an
    unmeasured load change into a lasting drift of the level, so it may
    instead be predicted ``horizon`` samples ahead at a time: each stretch
    starts from the measured level (the mean over the ``anchor`` samples just
    before it; an integrating output disturbance, as in Ljung 1999, sec.
    16.6), and the fitted ramp runs from there.

    Parameters
    ----------
    op, pv : ndarray
        Measured signals, equally long.
    ts : float
        Sampling interval, s.
    warm_up : int
        Samples not scored at the start.
    folds : int
        Pairs of fitting and held-out blocks.
    horizon : int, optional
        Prediction horizon in samples (None: free run).
    ramp : bool
        Fit a ramp with the offset in free run.
    anchor : int
        Samples averaged for the starting level of each stretch.
    valve_start : (float, ndarray), optional
        Position at which the replayed valve starts at rest and the OP
        samples it is stepped through before the record (default: at rest at
        the first OP sample).
    held_out : {"odd", "even", "none"}
        The blocks held out from fitting.
    """

    def __init__(
        self,
        op: FloatArray,
        pv: FloatArray,
        ts: float,
        *,
        warm_up: int,
        folds: int,
        horizon: int | None = None,
        ramp: bool = False,
        anchor: int = 5,
        valve_start: tuple[float, FloatArray] | None = None,
        held_out: HeldOut = "odd",
    ) -> None:
        n = op.size
        self.valve_start = valve_start or (float(op[0]), np.empty(0))
        self.op = op
        self.pv = pv
        self.ts = ts
        self.t = np.arange(n, dtype=np.float64) * ts
        self.warm_up = warm_up
        edges = np.linspace(warm_up, n, max(2 * folds, 1) + 1).round().astype(int)
        self.blocks = [(int(a), int(b)) for a, b in pairwise(edges)]
        self._block_of = np.full(n, -1)
        for i, (a, b) in enumerate(self.blocks):
            self._block_of[a:b] = i
        self.horizon = horizon
        if horizon is None:
            self._stretch = np.zeros(n, dtype=int)
            k = np.arange(n, dtype=np.float64)
            ones = np.ones(n)
            self.columns: FloatArray = np.column_stack([ones, k / n] if ramp else [ones])
        else:
            self._anchor = max(1, min(anchor, warm_up, horizon))
            self._starts = np.arange(warm_up, n, horizon)
            self._stretch = np.clip(np.arange(n) - warm_up, 0, None) // horizon
            k = np.arange(n, dtype=np.float64)
            self.columns = (k - self._anchored(k))[:, None] / n  # the ramp since the anchor
        self._target = pv - self._anchored(pv)
        self._hold_out(held_out)

    def _hold_out(self, which: HeldOut) -> None:
        scored = self._block_of >= 0
        odd = scored & (self._block_of % 2 == 1)
        self.held_out = which
        self.test: BoolArray = {"odd": odd, "even": scored & ~odd, "none": ~scored}[which]
        self.fit: BoolArray = scored & ~self.test
        self._fit_samples = np.flatnonzero(self.fit)
        self._columns_fit = self.columns[self.fit]
        self._solve = np.linalg.pinv(self._columns_fit)
        pv_fit, pv_test = self.pv[self.fit], self.pv[self.test]
        self.sst_fit = float(np.sum((pv_fit - pv_fit.mean()) ** 2))
        self.sst_test = float(np.sum((pv_test - pv_test.mean()) ** 2)) if pv_test.size else 0.0

    def holding_out(self, which: HeldOut) -> ReplayData:
        """The same set-up with other blocks held out (``"odd"``, ``"even"`` or ``"none"``)."""
        other = copy(self)
        other._hold_out(which)
        return other

    def replay(self, model: LoopModel) -> tuple[FloatArray, FloatArray]:
        """MV and PV deviation of ``model`` driven by the measured OP (valve start as set)."""
        position, lead_in = self.valve_start
        return model.replay(self.op, initial_position=position, lead_in=lead_in)

    def _anchored(self, v: FloatArray) -> FloatArray:
        """Per sample, the mean of ``v`` (a series, or columns of series) over the anchor
        of its stretch (0 in free run)."""
        if self.horizon is None:
            return np.zeros_like(v)
        total = np.concatenate([np.zeros((1, *v.shape[1:])), np.cumsum(v, axis=0)])
        means = (total[self._starts] - total[self._starts - self._anchor]) / self._anchor
        return np.asarray(means[self._stretch], dtype=np.float64)

    def fit_columns(self, x: FloatArray, extra: FloatArray) -> tuple[float, FloatArray]:
        """Squared error on the fitting blocks and coefficients of ``extra`` (columns
        added to the response ``x``), fitted with the offset or ramp."""
        target = self.pv - self._anchored(self.pv) - (x - self._anchored(x))
        design = np.column_stack([self.columns, extra - self._anchored(extra)])[self.fit]
        coef = np.linalg.lstsq(design, target[self.fit], rcond=None)[0]
        sse = float(np.sum((target[self.fit] - design @ coef) ** 2))
        return sse, np.asarray(coef[self.columns.shape[1]:], dtype=np.float64)

    def fit_error(self, model: LoopModel) -> float:
        """``predict(model).sse_fit``, the cost of the parameter searches, without building
        the whole prediction."""
        valve = model.valve
        return float(self.friction_errors(model, valve.friction_table(), valve.zone_bounds())[0])

    def friction_errors(self, model: LoopModel, tables: FloatArray, bands: ArrayLike) -> FloatArray:
        """:meth:`fit_error` of ``model`` with each valve friction table of ``tables`` and
        zone band of ``bands`` (see :meth:`LoopModel.replay_frictions`; one table and band
        or as many of each), replayed in one compiled call per chunk."""
        tables = tables.reshape(-1, *tables.shape[-2:])
        bands_a = np.broadcast_to(np.asarray(bands, dtype=np.float64), (tables.shape[0], 2))
        position, lead_in = self.valve_start
        errors = np.empty(tables.shape[0])
        target = self._target
        if model.load is not None:  # an additive load: the target less the (anchored) load
            load = model.load.series(self.t)
            target = target - (load - self._anchored(load))
        for start in range(0, tables.shape[0], FRICTION_CHUNK):
            chunk = slice(start, start + FRICTION_CHUNK)
            x = model.replay_frictions(
                self.op, tables[chunk], bands_a[chunk], initial_position=position, lead_in=lead_in
            )
            if model.quantiser is not None:
                errors[chunk] = [self._fit_sse(self._simulated_pv(model, row)[0]) for row in x]
                continue
            if self.horizon is not None:
                x -= self._anchored(x.T).T
            errors[chunk] = _fit_errors(
                x, target, self._fit_samples, self._columns_fit, self._solve
            )
        return errors

    def predict(self, model: LoopModel, *, fit_gain: bool = False) -> Prediction:
        """Replay ``model``; the offset or ramp (and with ``fit_gain`` a scale of the
        response) are fitted on the fitting blocks."""
        mv, x = self.replay(model)
        pv, coef = self._simulated_pv(model, x, fit_gain=fit_gain)
        return Prediction(
            pv=pv,
            mv=mv,
            sse_fit=self._fit_sse(pv),
            sse_test=float(np.sum((self.pv - pv)[self.test] ** 2)),
            pv_bias=float(coef[0]) if self.horizon is None else float(self.pv[0]),
            scale=float(coef[-1]) if fit_gain else 1.0,
        )

    def _fit_sse(self, pv: FloatArray) -> float:
        """Squared error of a simulated PV on the fitting blocks."""
        return float(np.sum((self.pv - pv)[self.fit] ** 2))

    def _simulated_pv(
        self, model: LoopModel, x: FloatArray, *, fit_gain: bool = False
    ) -> tuple[FloatArray, FloatArray]:
        """The PV of :meth:`predict` for the replayed response ``x`` and the fitted
        coefficients (offset or ramp, then the scale with ``fit_gain``)."""
        if model.load is not None:
            x = x + model.load.series(self.t)
        level = self._anchored(self.pv)
        response = x - self._anchored(x)
        target = self.pv - level
        if fit_gain:
            design = np.column_stack([self.columns, response])
            fixed = np.zeros_like(response)
            coef = np.linalg.lstsq(design[self.fit], target[self.fit], rcond=None)[0]
        else:
            design, fixed = self.columns, response
            coef = self._solve @ (target - fixed)[self.fit]
        pv = level + fixed + design @ coef
        if model.quantiser is not None:
            scale = float(coef[-1]) if fit_gain else 1.0
            pv = self._on_grid(model.quantiser, pv, scale * x, float(coef[0]))
        return np.asarray(pv, dtype=np.float64), np.asarray(coef, dtype=np.float64)

    def _on_grid(self, grid: Quantiser, pv: FloatArray, x: FloatArray, ramp: float) -> FloatArray:
        """The reported values of ``pv`` on ``grid``, with the level refitted.

        The least-squares level of the unrounded PV is biased by up to half a
        step (a PV that sits in one cell for long stretches), and so is a
        stretch's starting level averaged from rounded values.  The level is
        therefore searched again within half a step: once for the whole record
        in free run (on the fitting blocks); with a horizon, per stretch, on
        the stretch before it (a few anchor samples rarely cross a cell edge).
        ``x`` is the response and ``ramp`` its fitted ramp coefficient
        (horizon only).
        """
        shifts = np.linspace(-0.5, 0.5, 21) * grid.resolution
        if self.horizon is None:
            rows = self.fit
            errors = np.array(
                [np.sum((self.pv[rows] - grid.expected(pv[rows] + d)) ** 2) for d in shifts]
            )
            return grid.expected(pv + shifts[_plateau_centre(errors)])
        reach = min(self.horizon, self.warm_up)  # the whole stretch before, as far as it goes
        window = self._starts[:, None] + np.arange(-reach, 0)
        k = window.astype(np.float64)
        # each stretch's prediction, carried back over the stretch before it
        guess = (
            self.pv[window].mean(axis=1, keepdims=True)
            + x[window] - x[window].mean(axis=1, keepdims=True)
            + ramp * (k - k.mean(axis=1, keepdims=True)) / self.pv.size
        )
        errors = np.stack(
            [np.sum((self.pv[window] - grid.expected(guess + d)) ** 2, axis=1) for d in shifts],
            axis=1,
        )
        best = np.array([_plateau_centre(row) for row in errors])
        return grid.expected(pv + shifts[best][self._stretch])

    def nmse(self, prediction: Prediction) -> tuple[float, float]:
        """Normalised squared error on the fitting and on the held-out blocks."""
        return prediction.sse_fit / self.sst_fit, prediction.sse_test / self.sst_test


@njit(cache=True)
def _fit_errors(
    response: FloatArray,
    target: FloatArray,
    samples: NDArray[np.intp],
    columns: FloatArray,
    solve: FloatArray,
) -> FloatArray:
    """Squared error of ``target - response`` on ``samples`` after the least-squares fit
    of ``columns`` (their rows at ``samples``; ``solve`` is their pseudo-inverse), for
    each row of ``response``: the cost of :meth:`ReplayData.fit_error`, compiled."""
    errors = np.empty(response.shape[0])
    residual = np.empty(samples.size)
    for i in range(response.shape[0]):
        for k in range(samples.size):
            residual[k] = target[samples[k]] - response[i, samples[k]]
        coef = solve @ residual
        sse = 0.0
        for k in range(samples.size):
            error = residual[k]
            for j in range(coef.size):
                error -= columns[k, j] * coef[j]
            sse += error * error
        errors[i] = sse
    return errors


# ----------------------------------------------------------------------------
# search helpers


def _plateau_centre(values: FloatArray) -> int:
    """Index of the middle of the run of smallest values (rounding makes errors flat)."""
    lowest = np.flatnonzero(values <= values.min() * (1.0 + 1e-9) + 1e-300)
    return int(lowest[lowest.size // 2])


def _scalar_search(cost: Callable[[float], float], grid: Sequence[float]) -> tuple[float, float]:
    """Minimise ``cost`` over ``grid``, then by bounded search between the best point's
    neighbours."""
    values = [cost(x) for x in grid]
    best = int(np.argmin(values))
    lo, hi = grid[max(best - 1, 0)], grid[min(best + 1, len(grid) - 1)]
    x_best, c_best = float(grid[best]), float(values[best])
    if hi > lo:
        found = minimize_scalar(cost, bounds=(lo, hi), method="bounded", options={"xatol": 1e-3})
        if float(found.fun) < c_best:
            x_best, c_best = float(found.x), float(found.fun)
    return x_best, c_best


def _compass_search(
    start: FloatArray, steps: FloatArray, lower: FloatArray, upper: FloatArray, halvings: int
) -> Generator[FloatArray, float, tuple[FloatArray, float]]:
    """Compass search: try +-step on each coordinate, keep improvements, halve the steps
    when none improves (Kolda, Lewis & Torczon 2003, SIAM Review 45:385, Alg. 3.2).

    A generator, so that searches can run side by side (:func:`_compass`): it yields
    each point to cost, is sent the cost and returns the best point and its cost.
    """
    x = np.clip(np.asarray(start, dtype=np.float64), lower, upper)
    best = yield x
    step = np.asarray(steps, dtype=np.float64).copy()
    for _ in range(halvings):
        improved = True
        while improved:
            improved = False
            for i in range(x.size):
                for sign in (1.0, -1.0):
                    trial = x.copy()
                    trial[i] = min(max(trial[i] + sign * step[i], lower[i]), upper[i])
                    if trial[i] == x[i]:
                        continue
                    value = yield trial
                    if value < best:
                        x, best, improved = trial, value, True
        step /= 2.0
    return x, best


def _compass(
    costs: Callable[[FloatArray], FloatArray],
    starts: Sequence[Sequence[float]],
    steps: FloatArray,
    lower: FloatArray,
    upper: FloatArray,
    halvings: int = 7,
) -> tuple[FloatArray, float]:
    """The best of the compass searches from ``starts`` (the first of equals).

    ``costs`` gives the cost of each row of an array of points.  The searches
    run side by side: the next point of every search is costed in one call
    (one compiled replay for several frictions).
    """
    searches = [_compass_search(np.array(s), steps, lower, upper, halvings) for s in starts]
    pending = {i: next(search) for i, search in enumerate(searches)}
    found: dict[int, tuple[FloatArray, float]] = {}
    while pending:
        values = costs(np.array(list(pending.values()))).tolist()
        for i, value in zip(list(pending), values, strict=True):
            try:
                pending[i] = searches[i].send(value)
            except StopIteration as done:
                found[i] = done.value
                del pending[i]
    return min((found[i] for i in range(len(starts))), key=lambda result: result[1])


STARTS = 4
"""Best grid points from which the friction searches start a compass search."""


def _friction_grid(s_high: float) -> list[tuple[float, float]]:
    """``(S, j)`` pairs, ``j = J / S``: no friction, and S on a log grid up to ``s_high``
    with J = S / 2 (the compass search then adjusts J)."""
    return [(0.0, 0.5)] + [(float(S), 0.5) for S in s_high * np.geomspace(0.03, 1.0, 10)]


def _remembered(costs: Callable[[FloatArray], FloatArray]) -> Callable[[FloatArray], FloatArray]:
    """``costs`` of the rows of an array of points, computed once per point: a compass
    search often steps back to a point it has tried, or starts from a grid point."""
    seen: dict[tuple[float, ...], float] = {}

    def remembered(points: FloatArray) -> FloatArray:
        keys = [tuple(point) for point in points.tolist()]
        new = list(dict.fromkeys(key for key in keys if key not in seen))
        if new:
            seen.update(zip(new, costs(np.array(new)).tolist(), strict=True))
        return np.array([seen[key] for key in keys])

    return remembered


def _best(
    costs: Callable[[FloatArray], FloatArray], points: list[tuple[float, ...]]
) -> list[tuple[float, ...]]:
    """The :data:`STARTS` points of lowest cost (ties: the smaller point first)."""
    values = costs(np.array(points)).tolist()
    return [point for _, point in sorted(zip(values, points, strict=True))][:STARTS]


# ----------------------------------------------------------------------------
# the fits


def _fit_gain(data: ReplayData, base: LoopModel) -> Candidate:
    scale = data.predict(base, fit_gain=True).scale
    if scale == 0.0:
        return _not_fitted("gain_mismatch", data, base, "the fitted gain is 0")
    model = replace(base, process=replace(base.process, K=base.process.K * scale))
    return Candidate("gain_mismatch", {"K": model.process.K, "ratio": scale}, model,
                     data.predict(model))


def _fit_deadtime(data: ReplayData, base: LoopModel, longest: int) -> Candidate:
    best: tuple[float, LoopModel] | None = None
    for delay in range(longest + 1):
        model = replace(base, process=replace(base.process, theta=delay * data.ts))
        sse = data.fit_error(model)
        if best is None or sse < best[0]:
            best = (sse, model)
    assert best is not None
    model = best[1]
    return Candidate("deadtime_mismatch", {"theta": model.process.theta}, model,
                     data.predict(model))


def _fit_time_constant(data: ReplayData, base: LoopModel, longest: float) -> Candidate:
    tau0 = base.process.tau if base.process.tau > 0 else data.ts
    lowest = data.ts / 4.0 if not base.process.integrating else data.ts / 20.0
    grid = list(np.log(np.geomspace(min(lowest, tau0 / 5), max(longest, 5 * tau0), 25)))

    def model_of(log_tau: float) -> LoopModel:
        tau = math.exp(log_tau)
        if base.process.integrating and tau <= data.ts / 10.0:
            tau = 0.0
        return replace(base, process=replace(base.process, tau=tau))

    log_tau, _ = _scalar_search(lambda v: data.fit_error(model_of(v)), grid)
    model = model_of(log_tau)
    return Candidate("time_constant_mismatch", {"tau": model.process.tau}, model,
                     data.predict(model))


def _fit_characteristic(data: ReplayData, base: LoopModel) -> Candidate:
    def model_of(c: float) -> LoopModel:
        return replace(base, valve=replace(base.valve, curvature=c))

    curvature, _ = _scalar_search(
        lambda c: data.fit_error(model_of(c)), list(np.linspace(-8.0, 8.0, 33))
    )
    model = model_of(curvature)
    return Candidate("valve_characteristic", {"curvature": curvature}, model, data.predict(model))


def pv_grid(
    pv: FloatArray, *, tolerance: float = 0.1, min_on_grid: float = 0.9
) -> Quantiser | None:
    """The grid the measured PV lies on, if it does (coarse resolution or a historian's
    rounding).

    The smallest common step ``q`` of the nonzero increments is taken from
    their lower quantiles; the PV is on a grid when at least ``min_on_grid``
    of the increments are whole multiples of ``q`` (within ``tolerance q``)
    and so are the PV values about a common origin.

    Examples
    --------
    >>> pv = 0.1 + 0.5 * np.round(np.sin(np.arange(500) / 9.0) * 8.0)
    >>> grid = pv_grid(pv)
    >>> round(grid.resolution, 3), round(grid.origin, 3)
    (0.5, 0.1)
    """
    steps = np.abs(np.diff(pv))
    scale = float(np.max(np.abs(pv))) or 1.0
    moves = steps[steps > 1e-9 * scale]
    if moves.size < 20:
        return None
    smallest = float(np.quantile(moves, 0.05))
    singles = moves[np.round(moves / smallest) == 1]
    q = float(np.median(singles)) if singles.size else smallest
    ratio = moves / q
    if np.mean(np.abs(ratio - np.round(ratio)) <= tolerance) < min_on_grid:
        return None
    angle = 2.0 * np.pi * pv / q
    origin = float(np.angle(np.mean(np.exp(1j * angle))) / (2.0 * np.pi) * q) % q
    offset = (pv - origin) / q
    if np.mean(np.abs(offset - np.round(offset)) <= tolerance) < min_on_grid:
        return None
    return Quantiser(q, origin)


def _fit_quantisation(data: ReplayData, base: LoopModel) -> Candidate:
    grid = pv_grid(data.pv[data.fit])
    if grid is None:
        return _not_fitted(
            "measurement_quantization", data, base, "the measured PV does not lie on a grid"
        )
    q = grid.resolution

    def model_of(log_noise: float) -> LoopModel:
        return replace(base, quantiser=replace(grid, noise=q * math.exp(log_noise)))

    log_noise, _ = _scalar_search(
        lambda v: data.fit_error(model_of(v)), list(np.log(np.geomspace(0.01, 1.0, 11)))
    )
    model = model_of(log_noise)
    assert model.quantiser is not None
    params = {"resolution": q, "origin": grid.origin, "noise": model.quantiser.noise}
    return Candidate("measurement_quantization", params, model, data.predict(model))


def _fit_disturbance(data: ReplayData, base: LoopModel, base_fit: Prediction) -> Candidate:
    residual = np.where(data.fit, data.pv - base_fit.pv, 0.0)
    residual[data.fit] -= residual[data.fit].mean()
    n = residual.size
    nfft = sfft.next_fast_len(8 * n)
    power = np.abs(sfft.rfft(residual, nfft)) ** 2
    freq = np.arange(power.size) / nfft  # cycles per sample
    span = (n - data.warm_up) / 3.0  # at least three periods in the scored record
    allowed = (freq >= 1.0 / span) & (freq <= 1.0 / 3.0)
    if not np.any(allowed):
        return _not_fitted("external_disturbance", data, base, "the record is too short")
    peak = float(freq[np.flatnonzero(allowed)[np.argmax(power[allowed])]])
    _, x = data.replay(base)
    k = np.arange(n, dtype=np.float64)

    def solve(f: float) -> tuple[float, FloatArray]:
        return data.fit_columns(x, np.column_stack([np.sin(2 * np.pi * f * k),
                                                    np.cos(2 * np.pi * f * k)]))

    width = 2.0 / n
    found = minimize_scalar(
        lambda f: solve(f)[0], bounds=(max(peak - width, 1e-12), peak + width), method="bounded",
        options={"xatol": 1e-4 / n},
    )
    f = float(found.x) if float(found.fun) < solve(peak)[0] else peak
    a, b = solve(f)[1]
    load = PeriodicLoad(float(math.hypot(a, b)), data.ts / f, float(math.atan2(b, a)))
    model = replace(base, load=load)
    return Candidate(
        "external_disturbance",
        {"amplitude": load.amplitude, "period": load.period, "phase": load.phase},
        model, data.predict(model),
    )


def _friction_scale(data: ReplayData, base: LoopModel) -> float:
    """Largest stick band searched: three times the base one, or half the OP's 5-95 % range."""
    op = data.op[data.warm_up :]
    spread = float(np.quantile(op, 0.95) - np.quantile(op, 0.05))
    return max(3.0 * friction_of(base.valve.base)[0], 0.5 * spread, 0.5)


def _fit_asymmetric(
    data: ReplayData, base: LoopModel, seeds: Sequence[Sequence[float]] = ()
) -> Candidate:
    like = base.valve.base
    s_high = _friction_scale(data, base)

    def model_of(p: FloatArray) -> LoopModel:
        opening = friction_valve(like, p[0], p[1])
        closing = friction_valve(like, p[2], p[3])
        return replace(base, valve=replace(base.valve, opening=opening, closing=closing))

    def costs(points: FloatArray) -> FloatArray:
        """``data.fit_error(model_of(p))`` of each row ``p`` of ``points``."""
        tables = base.valve.friction_table(
            opening=friction_parameters(like, points[:, 0], points[:, 1]),
            closing=friction_parameters(like, points[:, 2], points[:, 3]),
        )
        return data.friction_errors(base, tables, base.valve.zone_bounds())

    search = _remembered(costs)
    if seeds:
        starts = [tuple(seed) for seed in seeds]
    else:
        grid = _friction_grid(s_high)
        base_friction = friction_of(like)
        # the general grid, and one direction kept at the base friction (thesis Fig. 5.14)
        starts = [(*up, *down) for up in grid for down in grid]
        for friction in grid:
            starts += [(*base_friction, *friction), (*friction, *base_friction)]
        starts = _best(search, starts)
    lower, upper = np.zeros(4), np.array([s_high, 1.0, s_high, 1.0])
    steps = np.array([0.1 * s_high, 0.25, 0.1 * s_high, 0.25])
    point, _ = _compass(search, starts, steps, lower, upper)
    model = model_of(point)
    params = _friction_params("opening", model.valve.opening)
    params |= _friction_params("closing", model.valve.closing)
    return Candidate("asymmetric_stiction", params, model, data.predict(model),
                     search_point=tuple(point))


def _fit_zone(
    data: ReplayData,
    base: LoopModel,
    seeds: Sequence[Sequence[float]] = (),
    max_coverage: float = 0.8,
) -> Candidate:
    """Friction inside a band of travel.  The band holds at most ``max_coverage`` of the
    OP samples (the valve must be seen outside it) and is at least half its stick band
    wide (a valve cannot stick and slip within a narrower one)."""
    like = base.valve.base
    s_high = _friction_scale(data, base)
    # The valve sits where OP has been, in any block: bands are placed over the OP of
    # the whole scored record, at its deciles and evenly over its travel.
    op = np.sort(data.op[data.warm_up :])
    deciles = np.quantile(op, np.linspace(0.0, 1.0, 11))
    edges = np.unique(np.concatenate([deciles, np.linspace(op[0], op[-1], 11)]))
    if not edges[-1] > edges[0]:
        return _not_fitted("position_dependent_stiction", data, base, "OP does not move")

    def model_of(p: FloatArray) -> LoopModel:
        low, high = min(p[0], p[1]), max(p[0], p[1])
        zone = StictionZone(low, max(high, low + 1e-6), friction_valve(like, p[2], p[3]))
        return replace(base, valve=replace(base.valve, zone=zone))

    def costs(points: FloatArray) -> FloatArray:
        """``data.fit_error(model_of(p))`` of each row ``p`` of ``points`` (inf for a band
        too wide or too narrow)."""
        low, high = np.minimum(points[:, 0], points[:, 1]), np.maximum(points[:, 0], points[:, 1])
        inside = np.searchsorted(op, high, "right") - np.searchsorted(op, low)
        allowed = (inside <= max_coverage * op.size) & (high - low >= 0.5 * points[:, 2])
        out = np.full(points.shape[0], math.inf)
        if np.any(allowed):
            p, low, high = points[allowed], low[allowed], high[allowed]
            tables = base.valve.friction_table(zone=friction_parameters(like, p[:, 2], p[:, 3]))
            bands = np.column_stack([low, np.maximum(high, low + 1e-6)])
            out[allowed] = data.friction_errors(base, tables, bands)
        return out

    search = _remembered(costs)
    if seeds:
        starts = [tuple(seed) for seed in seeds]
    else:
        bands = [(edges[i], edges[j]) for i in range(edges.size) for j in range(i + 1, edges.size)]
        frictions = _friction_grid(s_high)
        starts = _best(search, [(*band, *friction) for band in bands for friction in frictions])
    width = float(edges[-1] - edges[0])
    lower = np.array([edges[0] - 0.1 * width, edges[0] - 0.1 * width, 0.0, 0.0])
    upper = np.array([edges[-1] + 0.1 * width, edges[-1] + 0.1 * width, s_high, 1.0])
    steps = np.array([0.05 * width, 0.05 * width, 0.1 * s_high, 0.25])
    point, best = _compass(search, starts, steps, lower, upper)
    point = _tighten(lambda p: float(search(p[None])[0]), point, best, 0.05 * width)
    model = model_of(point)
    zone = model.valve.zone
    assert zone is not None
    params = {"low": zone.low, "high": zone.high, **_friction_params("zone", zone.valve)}
    return Candidate("position_dependent_stiction", params, model, data.predict(model),
                     search_point=tuple(point))


def _tighten(
    cost: Callable[[FloatArray], float], point: FloatArray, best: float, step: float
) -> FloatArray:
    """Move the band's edges (``point[0:2]``) inwards while the fit does not get worse.

    Where the fitting data never put the valve, an edge can move without
    changing the fit; the narrowest band the data support is the one to
    extrapolate with (the valve was not seen sticking beyond it).
    """
    point = point.copy()
    low, high = (0, 1) if point[0] <= point[1] else (1, 0)
    for edge, inwards in ((low, 1.0), (high, -1.0)):
        size = step
        while size > 1e-3 * step:
            trial = point.copy()
            trial[edge] += inwards * size
            if trial[high] > trial[low] and cost(trial) <= best:
                point = trial
            else:
                size /= 2.0
    return point


def _friction_params(prefix: str, valve: FrictionValve | None) -> dict[str, float]:
    assert valve is not None
    return {f"{prefix}_{k}": float(v) for k, v in valve.to_dict().items() if k != "model"}


def _not_fitted(effect: str, data: ReplayData, base: LoopModel, note: str) -> Candidate:
    return Candidate(effect, {}, base, data.predict(base), note)


def fit_effect(
    effect: str,
    data: ReplayData,
    base: LoopModel,
    base_fit: Prediction,
    *,
    period_s: float | None,
    seeds: Sequence[Sequence[float]] = (),
) -> Candidate:
    """Fit one effect of :data:`EFFECTS` to ``data``, starting from ``base``.

    ``period_s`` (the loop's oscillation period, if any) bounds the dead-time
    and time-constant searches.  ``seeds`` (``search_point`` of earlier fits)
    replace the coarse grid of the friction searches.
    """
    d0 = base.process.delay_samples(data.ts)
    period = (period_s or 0.0) / data.ts
    if effect == "gain_mismatch":
        return _fit_gain(data, base)
    if effect == "deadtime_mismatch":
        longest = max(2 * d0, d0 + round(period / 4), 10)
        return _fit_deadtime(data, base, min(longest, data.op.size - data.warm_up))
    if effect == "time_constant_mismatch":
        return _fit_time_constant(data, base, max(period, 50.0 * data.ts))
    if effect == "valve_characteristic":
        return _fit_characteristic(data, base)
    if effect == "measurement_quantization":
        return _fit_quantisation(data, base)
    if effect == "external_disturbance":
        return _fit_disturbance(data, base, base_fit)
    if effect == "asymmetric_stiction":
        return _fit_asymmetric(data, base, seeds)
    if effect == "position_dependent_stiction":
        return _fit_zone(data, base, seeds)
    raise ValueError(f"unknown effect {effect!r}; expected one of {EFFECTS}")


def describe_parameters(parameters: dict[str, Any]) -> str:
    """``k = v`` pairs with 3 significant digits."""
    return ", ".join(f"{k} = {v:.3g}" for k, v in parameters.items())
