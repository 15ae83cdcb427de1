"""Which valves of a unit stick, from the unit's own model: the harmonic-balance fingerprint.

With a process matrix ``G`` and the configured controllers ``Gc`` a cycle of
a unit can be read against the harmonic balance of thesis Eqs. 3.11-3.14.
At the fundamental of the common period the linear process is exact: the PV
phasors ``y`` are ``G(jw) u`` with ``u`` the valve-output phasors, and a
valve passes ``u_k = N_k(A_k) x_k`` on from its OP phasor ``x_k`` of amplitude
``A_k``; a healthy valve has ``N = 1``, a sticky one the describing function
of thesis Eq. 3.4 (ERRATA item 1), which depends on ``A_k`` -- the
amplitude-consistency that ERRATA item 9 adds to ``det H = 0``: each sticky
valve's DF is taken at the amplitude its own OP has in the measured cycle.

:func:`locate_sticky_valves` does, for one measured cycle:

1. **Linear check** (:func:`linear_check`): the loop with every valve healthy
   (``N = 1``) under the configured tunings, by the generalised Nyquist count
   of ``det(I + P(s))`` (MacFarlane & Postlethwaite); its margin is the
   smallest distance of the characteristic loci from -1.  A stable linear
   loop cannot sustain a cycle by itself: the cycle is a nonlinearity or an
   external disturbance, never the tuning.
2. **Fingerprint** (:func:`measure_fingerprint`): the common period and every
   loop's OP and PV phasor at it and at its third harmonic (amplitude and
   phase relative to the others; the common phase cancels below).
3. **Candidate sets**: for every non-empty set ``C`` of valves, the valves in
   ``C`` get a gain ``N_k`` at the fundamental (the DF of thesis Eq. 3.4 with
   their own ``S`` and ``J`` free, or any lagging gain, see :func:`_gain_set`)
   and a third harmonic of their own ``e_k``; the others pass their OP
   unchanged.  The misfit is the weighted residual of the process side of
   the balance at both frequencies, ``sum_i |y_i - sum_k G_ik N_k x_k|^2 /
   s_i^2`` (and at ``3w`` with ``x_k + e_k``), ``s_i`` the phasor's noise plus
   :data:`MODEL_ERROR` of its size.  The controller side ``x = -Gc y`` does
   not depend on ``C``; its residual says whether model and data agree at all
   (``controller_residual``).  The sets are ranked by misfit plus
   :data:`VALVE_PENALTY` per valve; a set is admitted only if it beats the
   healthy unit, leaves at most :data:`FIT_SHARE` of its misfit and at most
   :data:`MAX_MISFIT` (it fits within the model's error), and each of
   its valves distorts (``|e_k| / |x_k| >=``
   :data:`MIN_DISTORTION`): an external sine makes a healthy valve look like
   a lagging gain at the fundamental, but it adds no harmonic.
4. **Forward check**: the winning set with its fitted ``S`` and ``J`` goes
   through the multi-loop harmonic-balance solver
   (:func:`analytics.limit_cycle.predict_limit_cycles`); the stable predicted
   cycle nearest the measured period is reported beside it.

Each valve's residual involves only its own column of ``G`` times its own OP,
so a valve whose OP hardly moves cannot be told healthy or sticky from the
cycle; it is left healthy (the penalty).  A sticky valve whose OP swings far
beyond its band (``A >> S``) has ``N`` close to 1 and is nearly healthy at the
fundamental; the method cannot see it either (``benchmarks/plantwide.py``
gives the figures).

References
----------
.. [1] Thesis chapter 3: Eqs. 3.4, 3.11-3.14, 3.20; ERRATA items 1, 6, 9.
.. [2] MacFarlane & Postlethwaite (1977), "The generalized Nyquist stability
   criterion and multivariable root loci", Int. J. Control 25:81-127.
.. [3] Choudhury, Thornhill & Shah (2005), "Modelling valve stiction",
   Control Eng. Practice 13:641-658.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from functools import cache
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from analytics.describing import choudhury_df
from analytics.errors import DataError, ModelSpecError
from analytics.limit_cycle import ProcessMatrix, predict_limit_cycles
from analytics.limit_cycle import limit_cycle_predictor as _predictor
from analytics.simulation import PIDController
from analytics.types import ComplexArray, FloatArray
from analytics.valves import ChoudhuryValve, IdealValve, ValveModel

__all__ = [
    "FIT_SHARE",
    "MIN_DISTORTION",
    "MIN_OP_SHARE",
    "MODEL_ERROR",
    "VALVE_PENALTY",
    "CandidateFit",
    "Fingerprint",
    "LinearCheck",
    "ModelLocalisation",
    "UnitModel",
    "linear_check",
    "locate_sticky_valves",
    "measure_fingerprint",
]


MODEL_ERROR = 0.2
"""Relative error of a predicted PV phasor allowed for the model (a process
gain 20 % off moves it by about that much)."""

VALVE_PENALTY = 6.0
"""Misfit (in units of the weighted squared residual) that one more sticky valve
must remove to be named; chosen among 2-12 on simulated columns with seeds
100-103 (every sticky set, S and J within 30 % of Table 2.3, exact and 20 %
wrong gains, external sines), not on the seeds the tests and the benchmark
score."""

MIN_OP_SHARE = 0.01
"""A valve is a candidate only if its OP's amplitude at the cycle is at least this
share of the largest OP amplitude: a valve whose OP hardly moves can be neither
blamed nor cleared by the cycle (its loop is still in the balance, healthy)."""

FIT_SHARE = 0.5
"""A set is named only if it leaves at most this share of the misfit of healthy
valves: a set that explains a sliver of a cycle (its other valves being
cleared by the distortion floor) does not name the cycle's source."""

MAX_MISFIT = 100.0
"""Largest misfit a named set may leave, whatever the healthy unit's: a set that
fits within the model's error.  Right sets left at most 36 on the calibration
columns (seeds 100-103, gains exact or 20 % off; 55 on the scored seeds 200-203);
on the demo column a fast 25 s cycle that the unit's matrix does not describe
left 9,700 for its best set against 35,000 for healthy valves, which the relative
test (:data:`FIT_SHARE`) alone let through as a sticky valve."""

MIN_DISTORTION = 0.015
"""Least third harmonic a named valve must add to its output, relative to its OP's
fundamental.  A sticky valve distorts (0.013-1.9 on the calibration columns), a
healthy valve passing on an external sine does not (at most 0.003); chosen
with :data:`VALVE_PENALTY` (0.01-0.05 tried)."""


@dataclass(frozen=True)
class UnitModel:
    """A unit's own model: its process matrix and configured controllers.

    Attributes
    ----------
    loops : tuple of str
        Loop ids in the row and column order of ``process``.
    process : n x n nested sequence of TransferFunction or None
        ``G[i][j]`` from valve ``j`` to PV ``i`` (% of span; thesis Eq. 2.10
        for the column).
    controllers : tuple of PIDController
        The configured controller of each loop.
    hold_delay : float or None
        Dead time of the controllers' zero-order hold, s; None for half the
        sampling interval of the data.
    """

    loops: tuple[str, ...]
    process: ProcessMatrix
    controllers: tuple[PIDController, ...]
    hold_delay: float | None = None

    def __post_init__(self) -> None:
        n = len(self.loops)
        if len(set(self.loops)) != n or n == 0:
            raise ModelSpecError(f"a unit model needs distinct loop ids, got {self.loops}")
        if len(self.controllers) != n:
            raise ModelSpecError(f"{n} loops but {len(self.controllers)} controllers")
        if len(self.process) != n or any(len(row) != n for row in self.process):
            raise ModelSpecError(f"the process matrix must be {n} x {n}, one row per loop")


@dataclass(frozen=True)
class LinearCheck:
    """The unit's loops with every valve healthy, under the configured tunings.

    Attributes
    ----------
    stable : bool or None
        Closed-loop stability (None when the Nyquist count is undetermined).
    margin : float
        Smallest distance of the characteristic loci (the eigenvalues of
        ``P(jw)``) from -1 over frequency: 0 on the stability boundary; for
        one loop it is the inverse of the peak sensitivity.
    margin_omega : float
        Where that minimum lies, rad/s.
    note : str
        What it means for a sustained cycle.
    """

    stable: bool | None
    margin: float
    margin_omega: float
    note: str


@dataclass(frozen=True)
class Fingerprint:
    """The measured cycle at its fundamental.

    Attributes
    ----------
    period_s : float
        Common period, s.
    op, pv : tuple of complex
        Phasors of each loop's OP and PV at that period (phase relative to
        the first loop's OP).
    op3, pv3 : tuple of complex
        Phasors of the third harmonic (same time origin).
    pv_noise : tuple of float
        Standard error of each PV phasor from the signal's sample-to-sample
        noise.
    """

    period_s: float
    op: tuple[complex, ...]
    pv: tuple[complex, ...]
    op3: tuple[complex, ...]
    pv3: tuple[complex, ...]
    pv_noise: tuple[float, ...]

    @property
    def omega(self) -> float:
        """Angular frequency, rad/s."""
        return 2.0 * math.pi / self.period_s


@dataclass(frozen=True)
class CandidateFit:
    """One candidate set of sticky valves fitted to the fingerprint.

    Attributes
    ----------
    loops : tuple of str
        The valves assumed sticky.
    misfit : float
        Weighted squared residual of the harmonic balance at the fingerprint,
        fundamental and third harmonic.
    harmonic_misfit : float
        The third harmonic's part of it.
    score : float
        ``misfit + VALVE_PENALTY * len(loops)``; the lowest wins.
    S, J : tuple of float
        Fitted stick band and slip jump of each valve of ``loops`` (% of OP
        span; Choudhury's (S, J) model, thesis Eq. 3.4, at the OP's
        fundamental amplitude).
    distortion : tuple of float
        Third harmonic each of them adds to its output, relative to its OP's
        fundamental: a sticky valve distorts, a valve that passes on an
        external sine does not.
    """

    loops: tuple[str, ...]
    misfit: float
    harmonic_misfit: float
    score: float
    S: tuple[float, ...]
    J: tuple[float, ...]
    distortion: tuple[float, ...]


@dataclass(frozen=True)
class ModelLocalisation:
    """Result of :func:`locate_sticky_valves`.

    Attributes
    ----------
    linear : LinearCheck
    fingerprint : Fingerprint
    controller_residual : tuple of float
        ``|x_i + Gc_i y_i| / |x_i|`` per loop: whether the configured
        controllers explain the OP from the PV at the cycle (large values mean
        the model's tunings are not those running).
    candidates : tuple of CandidateFit
        Every non-empty set of valves whose OP moves at the cycle
        (:data:`MIN_OP_SHARE`), best first.
    no_valve_misfit : float
        Misfit with every valve healthy (what a linear unit would leave).
    no_valve_harmonic_misfit : float
        Its third harmonic's part: the distortion that no healthy valve makes.
    sticky_valves : tuple of str
        The set named: the best candidate, or empty when no set beats the
        healthy unit.
    predicted_period_s : float or None
        Period of the stable cycle the harmonic-balance solver predicts for
        the named set with its fitted S and J (None if none or nothing named).
    note : str
        The finding in words.
    """

    linear: LinearCheck
    fingerprint: Fingerprint
    controller_residual: tuple[float, ...]
    candidates: tuple[CandidateFit, ...]
    no_valve_misfit: float
    no_valve_harmonic_misfit: float
    sticky_valves: tuple[str, ...]
    predicted_period_s: float | None
    note: str

    def fit_of(self, loops: Sequence[str]) -> CandidateFit | None:
        """The fit of one candidate set (None for the empty set)."""
        wanted = set(loops)
        return next((c for c in self.candidates if set(c.loops) == wanted), None)

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-ready form."""
        fp = self.fingerprint
        return {
            "linear": {"stable": self.linear.stable, "margin": self.linear.margin,
                       "margin_omega": self.linear.margin_omega, "note": self.linear.note},
            "period_s": fp.period_s,
            "op_amplitudes": [abs(v) for v in fp.op],
            "pv_amplitudes": [abs(v) for v in fp.pv],
            "controller_residual": list(self.controller_residual),
            "no_valve_misfit": self.no_valve_misfit,
            "candidates": [
                {"loops": list(c.loops), "misfit": c.misfit, "score": c.score,
                 "S": list(c.S), "J": list(c.J)}
                for c in self.candidates
            ],
            "sticky_valves": list(self.sticky_valves),
            "predicted_period_s": self.predicted_period_s,
            "note": self.note,
        }


def linear_check(
    process: ProcessMatrix, controllers: Sequence[PIDController], *, hold_delay: float = 0.0
) -> LinearCheck:
    """Stability and margin of the unit with healthy valves (thesis Eq. 3.14 with ``N = I``).

    Examples
    --------
    The column of thesis Eq. 2.10 under tunings 2.11-2.13 is stable:

    >>> from analytics.scenarios import column3x3
    >>> model = column3x3()
    >>> check = linear_check(model.process, [loop.controller for loop in model.loops])
    >>> check.stable, round(check.margin, 2)
    (True, 0.44)
    """
    n = len(controllers)
    predictor = _predictor(process, list(controllers), [ChoudhuryValve(1.0, 0.5)] * n,
                           None, "model", hold_delay)
    roots = predictor.unstable_roots(np.ones(n, dtype=np.complex128))
    omega = np.geomspace(predictor.omega_range[0] / 10, predictor.omega_range[1], 600)
    pm, _ = predictor.linear.matrix(1j * omega)
    distance = np.abs(1.0 + np.linalg.eigvals(pm)).min(axis=1)
    k = int(np.argmin(distance))
    stable = None if roots is None else roots == 0
    if stable:
        note = ("the linear loops are stable under the configured tunings: a sustained cycle "
                "comes from a nonlinearity (a sticky valve) or an external disturbance, "
                "never from the tuning alone")
    elif stable is None:
        note = "the stability of the linear loops could not be decided"
    else:
        note = (f"the linear loops are unstable under the configured tunings ({roots} "
                "right-half-plane roots): the tuning alone makes the unit cycle or diverge")
    return LinearCheck(stable, float(distance[k]), float(omega[k]), note)


def measure_fingerprint(
    ops: Sequence[ArrayLike], pvs: Sequence[ArrayLike], ts: float,
    period_s: float | None = None,
) -> Fingerprint:
    """Common period and the OP and PV phasors at it.

    The period maximises the summed normalised power of all signals, within
    5 % of ``period_s`` or, without it, between 4 samples and an eighth of
    the window; the phasors are ``2 mean(x e^{-jwt})`` over a whole number of
    periods.
    """
    x = np.array([*map(np.asarray, ops), *map(np.asarray, pvs)], dtype=np.float64)
    n_loops = len(ops)
    samples = x.shape[1]
    x = x - x.mean(axis=1, keepdims=True)
    scale = np.maximum(x.std(axis=1, keepdims=True), 1e-12)
    if period_s is None:
        spectrum = np.abs(np.fft.rfft(x / scale, axis=1)) ** 2
        frequencies = np.fft.rfftfreq(samples, ts)
        usable = (frequencies >= 8 / (samples * ts)) & (frequencies <= 1 / (4 * ts))
        if not usable.any():
            raise DataError(f"{samples} samples are too few to find a cycle")
        period_s = 1.0 / float(frequencies[usable][np.argmax(spectrum[:, usable].sum(axis=0))])
    if samples * ts < 3 * period_s:
        raise DataError(f"{samples * ts:g} s of data hold fewer than 3 periods of {period_s:g} s")
    t = np.arange(samples) * ts
    trial = np.linspace(0.95, 1.05, 201) / period_s
    basis = np.exp(-2j * np.pi * trial[:, None] * t[None, :])
    power = (np.abs(basis @ (x / scale).T) ** 2).sum(axis=1)
    frequency = float(trial[int(np.argmax(power))])
    whole = round(math.floor(samples * ts * frequency) / frequency / ts)
    phasors = 2.0 * (x[:, :whole] @ np.exp(-2j * np.pi * frequency * t[:whole])) / whole
    third = 2.0 * (x[:, :whole] @ np.exp(-6j * np.pi * frequency * t[:whole])) / whole
    rotation = phasors[0] / abs(phasors[0])
    phasors, third = phasors / rotation, third / rotation**3
    noise = np.diff(x[n_loops:], axis=1).std(axis=1) / math.sqrt(2)
    return Fingerprint(
        period_s=1.0 / frequency,
        op=tuple(complex(v) for v in phasors[:n_loops]),
        pv=tuple(complex(v) for v in phasors[n_loops:]),
        op3=tuple(complex(v) for v in third[:n_loops]),
        pv3=tuple(complex(v) for v in third[n_loops:]),
        pv_noise=tuple(float(v) for v in 2.0 * noise / math.sqrt(whole)),
    )


@cache
def _gain_set() -> tuple[ComplexArray, FloatArray, FloatArray]:
    """The valve gains a sticky valve may have at the fundamental, with the (S/A, J/S)
    of the nearest point of the (S, J) describing function (thesis Eq. 3.4, ERRATA item 1).

    The DF depends on the ratios only: ``N(A; S, J) = N(A/S; 1, J/S)``, tabulated
    for ``S/A`` in (0, 2) and ``J/S`` in [0, 1].  A valve that rests for most of a
    slow stick-slip cycle under integral action has an OP fundamental below
    ``S/2`` and a phase lag beyond the DF's 90 degrees (see
    :mod:`analytics.limit_cycle`); so every gain that lags (``Im N <= 0``,
    ``|N| <= 1.2``) is allowed too, with the S and J of the nearest DF point.
    """
    band = np.concatenate([np.geomspace(1e-3, 1.0, 90), np.linspace(1.0, 1.998, 150)[1:]])
    jump = np.linspace(0.0, 1.0, 41)
    table = np.array([choudhury_df(1.0 / band, 1.0, j) for j in jump]).T.reshape(-1)
    ratios = np.stack(np.meshgrid(band, jump, indexing="ij"), axis=-1).reshape(-1, 2)
    radius, angle = np.meshgrid(np.linspace(0.0, 1.2, 61), np.linspace(-math.pi, 0.0, 91))
    lagging = (radius * np.exp(1j * angle)).reshape(-1)
    nearest = np.array([int(np.argmin(np.abs(table - g))) for g in lagging])
    gains = np.concatenate([table, lagging]).astype(np.complex128)
    all_ratios = np.concatenate([ratios, ratios[nearest]])
    return gains, all_ratios[:, 0], all_ratios[:, 1]


def _fit_fundamental(
    a: ComplexArray, b: ComplexArray, members: tuple[int, ...]
) -> tuple[float, list[int]]:
    """Misfit ``|b - a N|^2`` at the fundamental with each member's ``N`` in
    :func:`_gain_set` and the others 1; ``a[:, k] = w_i G_ik(jw) x_k``, ``b = w y``.

    The unconstrained least-squares ``N`` of the members (the balance is linear
    in them) is put on the set, then each member in turn is refitted over the
    whole set (coordinate descent, three passes).
    """
    allowed, _, _ = _gain_set()
    rows = np.concatenate([a.real, a.imag])
    columns = []
    for k in members:  # real and imaginary parts of N_k as unknowns
        columns += [rows[:, k], np.concatenate([-a.imag[:, k], a.real[:, k]])]
    healthy = [k for k in range(a.shape[1]) if k not in members]
    target = np.concatenate([b.real, b.imag]) - rows[:, healthy].sum(axis=1)
    solution, *_ = np.linalg.lstsq(np.array(columns).T, target, rcond=None)
    chosen = [int(np.argmin(np.abs(allowed - (re + 1j * im))))
              for re, im in zip(solution[0::2], solution[1::2], strict=True)]
    gains = np.ones(a.shape[1], dtype=np.complex128)
    for _ in range(3):
        for position, k in enumerate(members):
            gains[list(members)] = allowed[chosen]
            rest = b - a @ gains + a[:, k] * gains[k]
            errors = np.abs(rest[None, :] - a[None, :, k] * allowed[:, None]) ** 2
            chosen[position] = int(np.argmin(errors.sum(axis=1)))
    gains[list(members)] = allowed[chosen]
    return float(np.sum(np.abs(b - a @ gains) ** 2)), chosen


def _fit_third(
    a3: ComplexArray, b3: ComplexArray, members: tuple[int, ...]
) -> tuple[float, ComplexArray]:
    """Misfit at the third harmonic: the members' valves may add any harmonic of their own
    (``u_k = x_k + e_k``), a healthy valve passes its OP's (``u_k = x_k``); ``a3[:, k] =
    w_i G_ik(3jw)``, ``b3 = w (y - G x)`` at ``3 w``.  Returns the misfit and the ``e_k``."""
    rows = np.concatenate([a3.real, a3.imag])
    columns = []
    for k in members:
        columns += [rows[:, k], np.concatenate([-a3.imag[:, k], a3.real[:, k]])]
    target = np.concatenate([b3.real, b3.imag])
    solution, *_ = np.linalg.lstsq(np.array(columns).T, target, rcond=None)
    misfit = float(np.sum((target - np.array(columns).T @ solution) ** 2))
    return misfit, solution[0::2] + 1j * solution[1::2]


def _frequency_response(process: ProcessMatrix, omega: float) -> ComplexArray:
    return np.array([[0j if entry is None else complex(entry.frequency_response(
        np.array([omega]))[0]) for entry in row] for row in process])


def locate_sticky_valves(
    loops: Mapping[str, tuple[ArrayLike, ArrayLike]],
    ts: float,
    process: ProcessMatrix,
    controllers: Sequence[PIDController],
    *,
    period_s: float | None = None,
    hold_delay: float | None = None,
) -> ModelLocalisation:
    """Rank every candidate set of sticky valves by the harmonic balance at the measured cycle.

    Parameters
    ----------
    loops : mapping of str to (array_like, array_like)
        ``loop id -> (OP, PV)`` in the row and column order of ``process``
        (% of span, deviations or absolute values alike).
    ts : float
        Sampling interval, s.
    process : n x n nested sequence of TransferFunction or None
        ``G[i][j]`` from valve ``j`` to PV ``i`` (thesis Eq. 2.10 for the column).
    controllers : sequence of PIDController
        The configured controllers, one per loop.
    period_s : float, optional
        Period of the unit's cycle (e.g. of its oscillation group), s; found
        from the spectrum when not given.
    hold_delay : float, optional
        Dead time of the controllers' zero-order hold; default ``ts / 2``.

    Returns
    -------
    ModelLocalisation

    Raises
    ------
    ModelSpecError
        Sizes of loops, matrix and controllers disagree.
    DataError
        Fewer than 3 periods in the data.

    Examples
    --------
    >>> from analytics.scenarios import column3x3
    >>> model = column3x3(sticky=(2,), seed=7)
    >>> run = model.run()
    >>> late = run.t >= 2000
    >>> unit = {name: (run.op[i][late], run.pv[i][late]) for i, name in enumerate(run.names)}
    >>> found = locate_sticky_valves(unit, run.dt, model.process,
    ...                              [loop.controller for loop in model.loops])
    >>> found.sticky_valves, found.linear.stable
    (('loop2',), True)
    """
    names = tuple(loops)
    n = len(names)
    if len(controllers) != n:
        raise ModelSpecError(f"{n} loops but {len(controllers)} controllers")
    delay = ts / 2 if hold_delay is None else hold_delay
    check = linear_check(process, controllers, hold_delay=delay)
    fp = measure_fingerprint([loops[k][0] for k in names], [loops[k][1] for k in names],
                             ts, period_s)
    w = fp.omega
    g, g3 = _frequency_response(process, w), _frequency_response(process, 3 * w)
    gc = np.array([(1.0 if c.action == "reverse" else -1.0)
                   * (c.kp + c.ki / (1j * w) + c.kd * 1j * w
                      / (1 + c.derivative_filter_time(1.0) * 1j * w))
                   for c in controllers]) * np.exp(-1j * w * delay)
    x, y = np.array(fp.op), np.array(fp.pv)
    x3, y3 = np.array(fp.op3), np.array(fp.pv3)
    noise = np.array(fp.pv_noise)
    controller_residual = tuple(
        float(v) for v in np.abs(x + gc * y) / np.maximum(np.abs(x), 1e-12))
    weight = 1.0 / (MODEL_ERROR * np.abs(y) + noise)
    weight3 = 1.0 / (MODEL_ERROR * np.abs(y3) + noise)
    a, b = g * x[None, :] * weight[:, None], y * weight
    a3, b3 = g3 * weight3[:, None], (y3 - g3 @ x3) * weight3
    healthy_third = float(np.sum(np.abs(b3) ** 2))
    healthy = float(np.sum(np.abs(b - a.sum(axis=1)) ** 2)) + healthy_third
    _, band, jump = _gain_set()
    testable = [k for k in range(n) if abs(x[k]) >= MIN_OP_SHARE * np.abs(x).max()]
    candidates = []
    for size in range(1, len(testable) + 1):
        for members in itertools.combinations(testable, size):
            fundamental, chosen = _fit_fundamental(a, b, members)
            third, harmonic = _fit_third(a3, b3, members)
            s_fit = band[chosen] * np.abs(x[list(members)])
            candidates.append(CandidateFit(
                loops=tuple(names[k] for k in members),
                misfit=fundamental + third,
                harmonic_misfit=third,
                score=fundamental + third + VALVE_PENALTY * size,
                S=tuple(float(v) for v in s_fit),
                J=tuple(float(v) for v in s_fit * jump[chosen]),
                distortion=tuple(float(v) for v in np.abs(harmonic) / np.abs(x[list(members)])),
            ))
    candidates.sort(key=lambda c: c.score)
    admitted = [c for c in candidates
                if c.score < healthy and c.misfit <= min(FIT_SHARE * healthy, MAX_MISFIT)
                and min(c.distortion) >= MIN_DISTORTION]
    best = admitted[0] if admitted else candidates[0]
    named = best.loops if admitted else ()
    predicted = None
    if named:
        valves: list[ValveModel] = [IdealValve()] * n
        for loop, s, j in zip(best.loops, best.S, best.J, strict=True):
            valves[names.index(loop)] = ChoudhuryValve(s, j)
        prediction = predict_limit_cycles(process, list(controllers), valves,
                                          hold_delay=delay)
        if prediction.stable_cycles:
            predicted = min((c.period_s for c in prediction.stable_cycles),
                            key=lambda p: abs(math.log(p / fp.period_s)))
    note = _note(check, named, best, healthy, fp.period_s, predicted)
    return ModelLocalisation(check, fp, controller_residual, tuple(candidates), healthy,
                             healthy_third, named, predicted, note)


def _note(check: LinearCheck, named: tuple[str, ...], best: CandidateFit, healthy: float,
          period_s: float, predicted: float | None) -> str:
    if not named:
        cause = ("an external disturbance or a nonlinearity other than a valve"
                 if check.stable else "the tuning, an external disturbance or another "
                 "nonlinearity")
        if best.misfit > MAX_MISFIT:
            why = (f"no set fits it within the model's error (the best, "
                   f"{', '.join(best.loops)}, leaves a misfit of {best.misfit:.3g}; "
                   f"{MAX_MISFIT:g} at most): the unit model does not describe this cycle")
        elif best.score >= healthy or best.misfit > FIT_SHARE * healthy:
            why = f"healthy valves explain it as well (misfit {healthy:.3g})"
        else:
            why = (f"{', '.join(best.loops)} would fit it (misfit {best.misfit:.3g} against "
                   f"{healthy:.3g}) but add no third harmonic (at most "
                   f"{min(best.distortion):.3f} of the OP, a sticky valve adds "
                   f"{MIN_DISTORTION:g} or more)")
        return (f"no set of sticky valves explains the cycle of {period_s:.4g} s: {why}; "
                f"unless another test names a valve, it comes from {cause}")
    text = (f"sticky: {', '.join(named)} (harmonic-balance misfit {best.misfit:.3g} against "
            f"{healthy:.3g} with healthy valves)")
    if predicted is not None:
        text += (f"; with the fitted S and J the model predicts a cycle of {predicted:.4g} s "
                 f"(measured {period_s:.4g} s)")
    else:
        text += "; the model predicts no stable cycle with the fitted S and J"
    return text
