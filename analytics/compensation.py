"""Stiction compensation: a compensator between the controller and a sticky valve.

A compensator sees, every sample, the time, the setpoint, the measured PV and
the controller output OP, and returns the signal sent to the valve (thesis
Fig. 4.2). Four are implemented:

* :class:`NoCompensation` - the valve gets OP;
* :class:`Knocker` - Hagglund's pulses in the direction of the OP trend [1]_;
* :class:`ConstantReinforcement` - ``+-a`` in the sign of the OP change
  ([2]_, thesis Eq. 1.3);
* :class:`ModelBasedCompensator` - the thesis chapter 4 method [3]_: learn
  ``OP_ss`` through the inverse of He's stiction model, hold OP there, then
  place the valve with two moves.

:func:`simulate_compensated` runs one loop with a compensator;
:func:`compare_compensators` and :func:`model_based_sensitivity` reproduce the
chapter 4 comparison and thesis Tables 4.3-4.4.

References
----------
.. [1] T. Hagglund, "A friction compensator for pneumatic control valves",
   J. Process Control 12 (2002) 897-904.
.. [2] L. Z. X. Ivan and S. Lakshminarayanan, "A new unified approach to valve
   stiction quantification and compensation", Ind. Eng. Chem. Res. 48 (2009)
   3474-3483; thesis section 1.2.4, Eq. 1.3.
.. [3] Thesis chapter 4, Eqs. 4.1-4.14, Tables 4.2-4.4 (example:
   G = 0.66 e^-2.6s/(6.7s+1), Gc = 0.1 + 0.09/s, He valve fs = 3, fd = 2).
.. [4] Q. P. He, J. Wang, M. Pottmann and S. J. Qin, "A curve fitting method
   for detecting valve stiction in oscillating control loops", Ind. Eng. Chem.
   Res. 46 (2007) 4549-4560 (the stiction model the chapter 4 method inverts).
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import ClassVar, Literal

import numpy as np

from analytics.errors import ModelSpecError
from analytics.lti import DiscreteEntry, TransferFunction, discretise
from analytics.scenarios import chapter4
from analytics.simulation import Loop
from analytics.types import FloatArray
from analytics.valves import HeValve, ValveStepper

#: How far past the static-friction band an input is placed to make a He valve
#: slip by exactly its minimum jump ``fs - fd`` (``u - y > fs`` is strict).
_BREAKAWAY_EPS = 1e-9


def _require(condition: bool, message: str) -> None:
    if not condition:
        raise ModelSpecError(message)


def _finite_positive(name: str, value: float) -> None:
    _require(
        isinstance(value, int | float) and math.isfinite(value) and value > 0,
        f"{name} must be a finite number > 0, got {value!r}",
    )


def _samples(name: str, seconds: float, dt: float) -> int:
    """Whole samples in ``seconds``; refuses a duration shorter than one sample."""
    n = round(seconds / dt)
    _require(n >= 1, f"{name}={seconds} s is shorter than one sample (dt={dt} s)")
    return n


def _sign(x: float) -> float:
    return float(np.sign(x))


# ---------------------------------------------------------------- compensators
class CompensatorRun(ABC):
    """A compensator in operation: state advanced one sample per :meth:`step`.

    Attributes
    ----------
    held_output : float or None
        ``None`` while the controller runs free; a value while the compensator
        holds the controller output (thesis sec. 4.2.3): the simulator then puts
        the controller in tracking so that OP equals this value and resumes
        bumplessly.
    """

    held_output: float | None = None

    @abstractmethod
    def step(self, t: float, sp: float, pv: float, op: float) -> float:
        """Signal sent to the valve at time ``t`` given SP, PV and the controller's OP."""


class Compensator(ABC):
    """Settings of a compensator; :meth:`start` returns a fresh :class:`CompensatorRun`."""

    name: ClassVar[str]

    @abstractmethod
    def start(self, *, dt: float, op: float) -> CompensatorRun:
        """Switch the compensator on with sampling period ``dt`` and current OP ``op``."""


class _PassThrough(CompensatorRun):
    def step(self, t: float, sp: float, pv: float, op: float) -> float:
        return op


@dataclass(frozen=True, kw_only=True)
class NoCompensation(Compensator):
    """The valve receives the controller output unchanged.

    Examples
    --------
    >>> NoCompensation().start(dt=1.0, op=50.0).step(0.0, 2.0, 1.9, 50.3)
    50.3
    """

    name: ClassVar[str] = "none"

    def start(self, *, dt: float, op: float) -> CompensatorRun:
        return _PassThrough()


@dataclass(frozen=True, kw_only=True)
class Knocker(Compensator):
    """Hagglund's knocker [1]_: pulses added to OP in the direction of its trend.

    Every ``period`` seconds a pulse of height ``amplitude`` and duration
    ``width`` is added to OP, signed like the change of OP since the previous
    pulse started, ``a sign(u(t_p) - u(t_p - h_k))`` ([1]_ Eq. 1). The pulses
    keep kicking the stem in the direction the controller wants it to go, so
    it slips before the full stick band has built up.

    Parameters
    ----------
    amplitude : float
        Pulse height ``a``, % of travel, > 0. The main tuning knob: of the
        order of the stick band.
    width : float
        Pulse width ``tau``, s; one scan of the DCS is the natural choice.
    period : float
        Time between pulse starts ``h_k``, s, > ``width``.

    References
    ----------
    .. [1] T. Hagglund, J. Process Control 12 (2002) 897-904, section 3.

    Examples
    --------
    >>> run = Knocker(amplitude=2.0, width=1.0, period=3.0).start(dt=1.0, op=50.0)
    >>> [run.step(k, 0.0, 0.0, 50.0 + 0.1 * k) for k in range(7)]
    [50.0, 50.1, 50.2, 52.3, 50.4, 50.5, 52.6]
    """

    amplitude: float
    width: float = 1.0
    period: float = 5.0
    name: ClassVar[str] = "knocker"

    def __post_init__(self) -> None:
        _finite_positive("knocker amplitude", self.amplitude)
        _finite_positive("knocker width", self.width)
        _finite_positive("knocker period", self.period)
        _require(
            self.period > self.width,
            f"knocker period={self.period} s must exceed the pulse width={self.width} s",
        )

    def start(self, *, dt: float, op: float) -> CompensatorRun:
        return _KnockerRun(
            self.amplitude,
            _samples("knocker width", self.width, dt),
            _samples("knocker period", self.period, dt),
            op,
        )


class _KnockerRun(CompensatorRun):
    def __init__(self, amplitude: float, width: int, period: int, op: float) -> None:
        self._amplitude = amplitude
        self._width = width
        self._period = period
        self._op_at_pulse = op
        self._direction = 0.0
        self._k = 0

    def step(self, t: float, sp: float, pv: float, op: float) -> float:
        phase = self._k % self._period
        if phase == 0:
            self._direction = _sign(op - self._op_at_pulse)
            self._op_at_pulse = op
        self._k += 1
        return op + self._amplitude * self._direction if phase < self._width else op


@dataclass(frozen=True, kw_only=True)
class ConstantReinforcement(Compensator):
    """Constant reinforcement [2]_: ``alpha_k = a sign(OP_k - OP_{k-1})`` added to OP.

    Thesis Eq. 1.3 (``a_cr``). No addition while OP does not change.

    Parameters
    ----------
    amplitude : float
        ``a_cr``, % of travel, > 0.

    References
    ----------
    .. [2] Ivan & Lakshminarayanan, Ind. Eng. Chem. Res. 48 (2009) 3474-3483;
       thesis section 1.2.4, Eq. 1.3.

    Examples
    --------
    >>> run = ConstantReinforcement(amplitude=1.5).start(dt=1.0, op=50.0)
    >>> [run.step(k, 0.0, 0.0, u) for k, u in enumerate([50.2, 50.4, 50.4, 50.1])]
    [51.7, 51.9, 50.4, 48.6]
    """

    amplitude: float
    name: ClassVar[str] = "constant reinforcement"

    def __post_init__(self) -> None:
        _finite_positive("constant reinforcement amplitude", self.amplitude)

    def start(self, *, dt: float, op: float) -> CompensatorRun:
        return _ReinforcementRun(self.amplitude, op)


class _ReinforcementRun(CompensatorRun):
    def __init__(self, amplitude: float, op: float) -> None:
        self._amplitude = amplitude
        self._previous_op = op

    def step(self, t: float, sp: float, pv: float, op: float) -> float:
        alpha = self._amplitude * _sign(op - self._previous_op)
        self._previous_op = op
        return op + alpha


def he_inverse(valve: HeValve, target: float, position: float) -> float:
    """Valve input that brings a He valve from ``position`` as close as it can to ``target``.

    Thesis Eq. 4.3, ``OP_hat = S^-1(MV_hat, MV_{t-1}, fs, fd)``, with the
    rule of Eq. 4.5 (pick the nearest reachable position). He's model [4]_
    moves the stem only when ``|u - y| > fs`` and then to ``u -+ fd``, so from
    ``y`` the reachable positions are ``y`` itself and anything at least
    ``fs - fd`` away. With ``d = target - y``:

    * ``|d| > fs - fd``: send ``target + fd sign(d)``, the valve lands on target;
    * ``(fs - fd)/2 <= |d| <= fs - fd``: the smallest slip, landing at
      ``y + (fs - fd) sign(d)``, is nearer than staying;
    * otherwise send ``y``: no net force, the valve stays.

    References
    ----------
    .. [3] Thesis Eqs. 4.2-4.5 and Fig. 4.3.
    .. [4] He et al. (2007), the model being inverted.

    Examples
    --------
    >>> valve = HeValve(fs=3.0, fd=2.0)
    >>> he_inverse(valve, 55.0, 50.0)  # far: land exactly on target
    57.0
    >>> he_inverse(valve, 50.3, 50.0)  # too close to slip to: stay
    50.0
    >>> round(valve.stepper(50.0).step(he_inverse(valve, 50.8, 50.0)), 6)  # minimum slip
    51.0
    """
    slip = valve.fs - valve.fd
    gap = target - position
    if abs(gap) > slip:
        return target + valve.fd * _sign(gap)
    if abs(gap) >= 0.5 * slip and slip > 0:
        return position + (valve.fs + _BREAKAWAY_EPS) * _sign(gap)
    return position


def two_move_inputs(
    valve: HeValve, stuck: float, target: float, margin: float, first_up: bool | None = None
) -> tuple[float, float]:
    """The two valve inputs ``(OP_mid, OP_end)`` that move a stuck He valve to ``target``.

    Thesis Eqs. 4.11-4.13. The first move goes away from the target, the
    second comes back to it: up first when the valve must close
    (``stuck > target``, thesis Remark after Table 4.1), down first otherwise.
    For He's model [4]_ the second move, downwards, lands at ``OP_end + fd``,
    so ``OP_end = target - fd``; it slips only if ``MV_mid - OP_end > fs``,
    which with ``MV_mid = OP_mid - fd`` needs ``OP_mid > target + fs``, and
    the first move itself slips only if ``OP_mid > stuck + fs``. Hence
    ``OP_mid = max(stuck, target) + fs + margin`` (mirrored for opening).
    ``first_up`` overrides the direction rule.
    The thesis prints the break-away condition as ``|dOP| > (fs + fd)/2``;
    for He's model it is ``|OP - MV| > fs`` (derived here), and ``margin``
    absorbs errors in ``fs`` and in the estimate of ``stuck`` (Eq. 4.14).

    References
    ----------
    .. [3] Thesis section 4.2.4, Eqs. 4.11-4.13, Fig. 4.6 and Table 4.1.

    Examples
    --------
    >>> valve = HeValve(fs=3.0, fd=2.0)
    >>> two_move_inputs(valve, stuck=53.5, target=53.0, margin=2.0)
    (58.5, 51.0)
    >>> stepper = valve.stepper(53.5)
    >>> [stepper.step(u) for u in (58.5, 51.0)]
    [56.5, 53.0]
    """
    if first_up is None:
        first_up = stuck > target
    direction = 1.0 if first_up else -1.0
    far_side = max(stuck, target) if direction > 0 else min(stuck, target)
    op_mid = far_side + direction * (valve.fs + margin)
    return op_mid, target - direction * valve.fd


Phase = Literal["learning", "holding", "regulating", "regulated"]


@dataclass(frozen=True, kw_only=True)
class ModelBasedCompensator(Compensator):
    """The model-based compensator of thesis chapter 4 [3]_.

    Three phases, restarted whenever the setpoint changes (sec. 4.2.2):

    1. **learning** (``learning_time``): each sample the desired valve
       position is the controller output, ``MV_hat_t = OP_t`` (Eq. 4.1); the
       valve gets ``OP_hat_t = S^-1(MV_hat_t, MV_{t-1})`` (Eqs. 4.3-4.5,
       :func:`he_inverse`), i.e. OP plus the friction force ``F_t`` (Eq. 4.4).
       The valve then behaves like a fine quantiser and the loop nearly
       settles. ``OP_ss`` is a mean over the second half of the phase (the
       first half lets the transient after switch-on or a setpoint change
       die out): by default of the modelled valve position, not of OP as in
       Eq. 4.6 (see Notes).
    2. **holding** (``settle_time``): OP is held at ``OP_ss`` (sec. 4.2.3);
       the valve stays where it happened to stop (Eq. 4.10), the PV settles.
    3. **regulating**: the stuck position is estimated from the settled PV
       with the steady-state process model (Eq. 4.14),
       ``MV_t = OP_ss + (PV - SP) / K``, and two moves of ``move_duration``
       each (:func:`two_move_inputs`) place the valve at ``OP_ss``
       (Eqs. 4.11-4.13). The compensator then holds the valve there.

    ``MV_{t-1}`` is not measured: the compensator runs ``valve`` as an
    internal model fed with what it sends, starting at rest at the OP it is
    switched on with. With exact parameters a He valve's position after a
    slip does not depend on where it was, so the model locks on at the first
    slip.

    With ``regulation_attempts > 1`` the regulation repeats while
    ``|PV - SP| > pv_tolerance``, shifting the target by ``-(PV - SP)/K``
    each time (an extension: the thesis regulates once).

    Parameters
    ----------
    valve : HeValve
        Estimated stiction of the valve (``fs``, ``fd``), from quantification.
    process_gain : float
        Estimated steady-state gain ``K`` of the process, PV % per valve %.
    learning_time, settle_time : float
        Durations of the learning and holding phases, s (thesis sec. 4.3:
        learning 1000-1500 s; holding from 1700 s, regulation at 2000 s).
    move_duration : float
        Duration of each of the two regulating moves, s.
    move_margin : float
        Extra input beyond ``fs`` in the first move, % of travel.
    regulation_attempts : int
        Regulations allowed per setpoint.
    pv_tolerance : float
        No regulation while ``|PV - SP|`` is within this, % of span.
    learn_from : {"valve", "op"}
        Average the modelled valve position (default) or OP (Eq. 4.6 as
        printed) to learn ``OP_ss``.

    Notes
    -----
    During learning the valve can only stay or slip by at least
    ``fs - fd``, so the PI loop dithers between two valve positions and OP
    hovers near the switching threshold between them: the mean OP of
    Eq. 4.6 is biased by up to ``(fs - fd)/2`` depending on where the
    positions fall (0.24 % in the chapter 4 example switched on at 1000 s,
    a PV offset of 0.16 after regulation). Integral action makes the mean PV
    equal SP, hence for a linear process the mean valve position equals
    ``MV_ss`` exactly, and with the target ``MV_ss = OP_ss`` of Eq. 4.13 that
    is the quantity to learn.

    References
    ----------
    .. [3] Thesis chapter 4, Eqs. 4.1-4.14.

    Examples
    --------
    The chapter 4 loop, compensated from 1000 s, settles on its setpoint:

    >>> from analytics.scenarios import chapter4
    >>> model = chapter4()
    >>> comp = ModelBasedCompensator(valve=HeValve(fs=3.0, fd=2.0), process_gain=0.66)
    >>> res = simulate_compensated(
    ...     model.process, model.loops[0], comp, dt=1.0, duration=3000.0, compensate_from=1000.0
    ... )
    >>> round(res.run.op_ss_, 2), round(float(res.pv[-1]), 2)
    (53.03, 52.0)
    """

    valve: HeValve
    process_gain: float
    learning_time: float = 500.0
    settle_time: float = 300.0
    move_duration: float = 1.0
    move_margin: float = 2.0
    regulation_attempts: int = 1
    pv_tolerance: float = 0.02
    learn_from: Literal["valve", "op"] = "valve"
    name: ClassVar[str] = "model-based"

    def __post_init__(self) -> None:
        _require(
            isinstance(self.valve, HeValve),
            f"the model-based compensator inverts He's model: valve must be a HeValve, "
            f"got {type(self.valve).__name__}",
        )
        _require(
            isinstance(self.process_gain, int | float)
            and math.isfinite(self.process_gain)
            and self.process_gain != 0,
            f"process_gain K must be finite and non-zero, got {self.process_gain!r}",
        )
        for name in ("learning_time", "settle_time", "move_duration"):
            _finite_positive(name, getattr(self, name))
        _require(
            math.isfinite(self.move_margin) and self.move_margin >= 0,
            f"move_margin must be finite and >= 0, got {self.move_margin}",
        )
        _require(
            isinstance(self.regulation_attempts, int) and self.regulation_attempts >= 1,
            f"regulation_attempts must be an integer >= 1, got {self.regulation_attempts!r}",
        )
        _require(
            math.isfinite(self.pv_tolerance) and self.pv_tolerance >= 0,
            f"pv_tolerance must be finite and >= 0, got {self.pv_tolerance}",
        )

    def start(self, *, dt: float, op: float) -> ModelBasedRun:
        return ModelBasedRun(self, dt=dt, op=op)


class ModelBasedRun(CompensatorRun):
    """:class:`ModelBasedCompensator` in operation; learned values end in ``_``.

    Attributes
    ----------
    phase : {"learning", "holding", "regulating", "regulated"}
    op_ss_ : float
        Learned steady-state controller output, ``= MV_ss`` (Eqs. 4.6, 4.13);
        NaN until learned.
    stuck_position_ : float
        Valve position estimated before the last regulation (Eq. 4.14).
    op_mid_, op_end_ : float
        Valve inputs of the last two moves (Eqs. 4.11-4.12).
    regulations_ : int
        Regulations done for the current setpoint.
    pv_errors_ : list of float
        Settled ``PV - SP`` at the end of each holding phase for the current
        setpoint: before the first regulation, then after each one.
    """

    def __init__(self, settings: ModelBasedCompensator, *, dt: float, op: float) -> None:
        self.settings = settings
        self._learning = _samples("learning_time", settings.learning_time, dt)
        self._settle = _samples("settle_time", settings.settle_time, dt)
        self._move = _samples("move_duration", settings.move_duration, dt)
        self._model: ValveStepper = settings.valve.stepper(op, dt)
        self._sp = math.nan
        self.op_ss_ = math.nan
        self.stuck_position_ = math.nan
        self.op_mid_ = math.nan
        self.op_end_ = math.nan
        self._begin_learning()

    @property
    def first_move(self) -> float:
        """Force added by the first move, ``OP_mid - OP_ss`` (thesis Table 4.2, f1)."""
        return self.op_mid_ - self.op_ss_

    @property
    def second_move(self) -> float:
        """Force added by the second move, ``OP_end - OP_mid`` (thesis Table 4.2, f2)."""
        return self.op_end_ - self.op_mid_

    def _enter(self, phase: Phase) -> None:
        self.phase: Phase = phase
        self._elapsed = 0
        self._sum = 0.0
        self._count = 0

    def _begin_learning(self) -> None:
        self._enter("learning")
        self.held_output = None
        self.regulations_ = 0
        self.pv_errors_: list[float] = []

    def _advance(self, sp: float) -> None:
        """Phase transitions due at this sample."""
        if self.phase == "learning" and self._elapsed >= self._learning:
            self.op_ss_ = self._sum / self._count
            self.held_output = self._target = self._valve_input = self.op_ss_
            self._enter("holding")
        elif self.phase == "holding" and self._elapsed >= self._settle:
            pv_error = self._sum / self._count - sp
            self.pv_errors_.append(pv_error)
            if (
                abs(pv_error) <= self.settings.pv_tolerance
                or self.regulations_ >= self.settings.regulation_attempts
            ):
                self._enter("regulated")
                return
            offset = pv_error / self.settings.process_gain  # Eq. 4.14, MV_t - MV_ss
            self.stuck_position_ = self._target + offset
            if self.regulations_ == 0:
                self._first_up = offset > 0
            else:
                # The last landing missed by `offset` (an error in OP_ss or in fd): aim
                # past it, arriving from the same side so that the miss repeats.
                self._target -= offset
            self.op_mid_, self.op_end_ = two_move_inputs(
                self.settings.valve,
                self.stuck_position_,
                self._target,
                self.settings.move_margin,
                self._first_up,
            )
            self.regulations_ += 1
            self._enter("regulating")
        elif self.phase == "regulating" and self._elapsed >= 2 * self._move:
            self._valve_input = self.op_end_
            self._enter("holding")

    def step(self, t: float, sp: float, pv: float, op: float) -> float:
        if sp != self._sp and not math.isnan(self._sp):
            self._begin_learning()
        self._sp = sp
        self._advance(sp)
        if self.phase == "learning":
            valve_input = he_inverse(self.settings.valve, op, self._model.position)
            if self._elapsed >= self._learning // 2:
                self._sum += op if self.settings.learn_from == "op" else self._model.position
                self._count += 1
        elif self.phase == "regulating":
            valve_input = self.op_mid_ if self._elapsed < self._move else self.op_end_
        else:
            valve_input = self._valve_input
            if self.phase == "holding" and self._elapsed >= self._settle // 2:
                self._sum += pv
                self._count += 1
        self._elapsed += 1
        self._model.step(valve_input)
        return valve_input


# ---------------------------------------------------------------- closed loop
class _SampledProcess:
    """The :class:`analytics.lti.DiscreteEntry` recursion on plain floats, one sample a call.

    ``y_k = C x_k + D u_{k-d-1}``, ``x_{k+1} = Ad x_k + B0 u_{k-d} + B1 u_{k-d-1}``;
    ``u`` is the process input in deviation from ``op_bias``, zero before ``k = 0``.
    """

    def __init__(self, entry: DiscreteEntry, n_samples: int) -> None:
        self.ad: list[list[float]] = entry.Ad.tolist()
        self.b0: list[float] = entry.B0.tolist()
        self.b1: list[float] = entry.B1.tolist()
        self.c: list[float] = entry.C.tolist()
        self.d = entry.D
        self.delay = entry.delay_samples
        self.x = [0.0] * len(self.c)
        # u[k + delay + 1] = u_k, so u[k + 1] = u_{k-d} and u[k] = u_{k-d-1}
        self.u = [0.0] * (n_samples + self.delay + 1)

    def output(self, k: int) -> float:
        """``y_k``, available before ``u_k`` is known."""
        return sum(c * x for c, x in zip(self.c, self.x, strict=True)) + self.d * self.u[k]

    def advance(self, k: int, u_k: float) -> None:
        """Apply ``u_k`` and step the state to sample ``k + 1``."""
        self.u[k + self.delay + 1] = u_k
        u0, u1 = self.u[k + 1], self.u[k]
        self.x = [
            sum(a * x for a, x in zip(row, self.x, strict=True)) + b0 * u0 + b1 * u1
            for row, b0, b1 in zip(self.ad, self.b0, self.b1, strict=True)
        ]


@dataclass(frozen=True)
class CompensationResult:
    """Time series of a compensated single-loop simulation.

    Attributes
    ----------
    t, sp, pv : ndarray
        Time (s), setpoint and measured PV.
    op : ndarray
        Controller output (held values while the compensator holds it).
    valve_input : ndarray
        Signal the compensator sent to the valve.
    mv : ndarray
        Valve position.
    compensate_from : float
        Time the compensator was switched on, s.
    run : CompensatorRun
        The compensator at the end of the run (learned attributes).
    """

    t: FloatArray
    sp: FloatArray
    pv: FloatArray
    op: FloatArray
    valve_input: FloatArray
    mv: FloatArray
    compensate_from: float
    run: CompensatorRun = field(repr=False)

    @property
    def dt(self) -> float:
        """Sampling period, s."""
        return float(self.t[1] - self.t[0]) if self.t.size > 1 else 0.0


def simulate_compensated(
    process: TransferFunction,
    loop: Loop,
    compensator: Compensator,
    *,
    dt: float,
    duration: float,
    compensate_from: float = 0.0,
) -> CompensationResult:
    """Simulate one loop with ``compensator`` between its controller and valve.

    The conventions are those of :func:`analytics.simulation.simulate`
    (exact ZOH process, DCS-style PID, deviations from ``(op_bias,
    pv_bias)``, the loop's setpoint schedule and disturbances); before
    ``compensate_from`` the valve receives OP. The process is stepped in
    Python around the compiled valve kernel, since the compensator is
    arbitrary Python: about 10 us per sample.

    Parameters
    ----------
    process : TransferFunction
    loop : Loop
    compensator : Compensator
    dt, duration : float
        Sampling period and simulated time, s.
    compensate_from : float
        Time at which the compensator is switched on, s.

    Returns
    -------
    CompensationResult

    References
    ----------
    .. [3] Thesis Fig. 4.2 (position of the compensator in the loop).

    Examples
    --------
    Without compensation the chapter 4 loop keeps its stiction limit cycle:

    >>> model = chapter4()
    >>> res = simulate_compensated(model.process, model.loops[0], NoCompensation(),
    ...                            dt=1.0, duration=3000.0)
    >>> round(float(np.ptp(res.pv[2000:])), 1)  # PV swings, % of span
    0.7
    """
    _finite_positive("dt", dt)
    _require(
        math.isfinite(duration) and duration >= dt,
        f"duration must be at least one sample (dt={dt} s), got {duration}",
    )
    _require(
        math.isfinite(compensate_from) and compensate_from >= 0,
        f"compensate_from must be a finite time >= 0 s, got {compensate_from}",
    )
    n_samples = math.floor(duration / dt + 1e-9) + 1
    t: FloatArray = np.arange(n_samples, dtype=np.float64) * dt
    sp = loop.setpoint_series(t)
    loads = {at: np.zeros(n_samples) for at in ("output", "measurement", "input")}
    for disturbance in loop.disturbances:
        loads[disturbance.at] += disturbance.series(t)
    pv_offset = loop.pv_bias + loads["output"] + loads["measurement"]

    plant = _SampledProcess(discretise(process, dt), n_samples)
    op_bias = loop.controller.op_bias
    controller = loop.controller.stepper(dt, loop.pv_bias)
    valve = loop.valve.stepper(op_bias, dt)
    run: CompensatorRun = _PassThrough()
    switch_on = math.ceil(compensate_from / dt - 1e-9)

    times, sps, input_loads = t.tolist(), sp.tolist(), loads["input"].tolist()
    pv, op, valve_input, mv = ([0.0] * n_samples for _ in range(4))
    for k, pv_k in enumerate(pv_offset.tolist()):
        pv[k] = pv_k = pv_k + plant.output(k)
        op[k] = controller.step(sps[k], pv_k)
        if k == switch_on:
            run = compensator.start(dt=dt, op=op[k])
        valve_input[k] = run.step(times[k], sps[k], pv_k, op[k])
        if run.held_output is not None:
            op[k] = controller.track(run.held_output)
        mv[k] = valve.step(valve_input[k])
        plant.advance(k, mv[k] - op_bias + input_loads[k])
    pv_a, op_a, valve_input_a, mv_a = (np.array(x) for x in (pv, op, valve_input, mv))
    return CompensationResult(
        t, sp, pv_a, op_a, valve_input_a, mv_a, float(t[min(switch_on, n_samples - 1)]), run
    )


# ---------------------------------------------------------------- comparison
@dataclass(frozen=True)
class CompensationMetrics:
    """How well a compensated loop performs over a window.

    Attributes
    ----------
    method : str
        Compensator name.
    iae : float
        Integral of ``|SP - PV|`` over the window, % s.
    valve_travel : float
        ``sum |MV_k - MV_{k-1}|``, % of travel: stem wear.
    valve_reversals : int
        Changes of direction of the stem.
    final_pv_error : float
        Mean ``|SP - PV|`` over the last tenth of the window, %.
    """

    method: str
    iae: float
    valve_travel: float
    valve_reversals: int
    final_pv_error: float


def compensation_metrics(
    result: CompensationResult, *, start: float | None = None, method: str = ""
) -> CompensationMetrics:
    """IAE, valve travel and reversals of ``result`` from ``start`` (default: switch-on) to the end.

    Examples
    --------
    >>> model = chapter4()
    >>> res = simulate_compensated(model.process, model.loops[0], NoCompensation(),
    ...                            dt=1.0, duration=2000.0)
    >>> compensation_metrics(res, start=1000.0).valve_reversals > 0
    True
    """
    first = int(np.searchsorted(result.t, result.compensate_from if start is None else start))
    error = np.abs(result.sp[first:] - result.pv[first:])
    _require(error.size >= 2, f"the window from {start} s holds fewer than two samples")
    moves = np.diff(result.mv[first:])
    directions = np.sign(moves[moves != 0.0])
    tail = max(1, error.size // 10)
    return CompensationMetrics(
        method=method,
        iae=float(error.sum() * result.dt),
        valve_travel=float(np.abs(moves).sum()),
        valve_reversals=int(np.count_nonzero(directions[1:] != directions[:-1])),
        final_pv_error=float(error[-tail:].mean()),
    )


CHAPTER4_VALVE = HeValve(fs=3.0, fd=2.0)
"""The sticky valve of the thesis chapter 4 example (He model)."""

CHAPTER4_GAIN = 0.66
"""Process gain of the chapter 4 example, G = 0.66 e^-2.6s/(6.7s+1)."""


def _chapter4_loop() -> tuple[TransferFunction, Loop, float]:
    """Process, loop and sampling period of :func:`analytics.scenarios.chapter4`."""
    model = chapter4()
    assert isinstance(model.process, TransferFunction)
    return model.process, model.loops[0], model.dt


def compare_compensators(
    *,
    knocker: Knocker | None = None,
    reinforcement: ConstantReinforcement | None = None,
    model_based: ModelBasedCompensator | None = None,
    compensate_from: float = 1000.0,
    duration: float = 4000.0,
) -> tuple[CompensationMetrics, ...]:
    """No compensation, knocker, constant reinforcement and the model-based method on the
    chapter 4 loop (:func:`analytics.scenarios.chapter4`, SP = 2 above the operating point).

    Every compensator is switched on at ``compensate_from`` (1000 s, when the
    thesis starts learning) and judged from then to ``duration``. Defaults: a
    knocker of amplitude ``(fs + fd)/2 = 2.5`` %, width 1 s, period 4 s
    (on a grid over 0.5-5 % and 2-10 s the lowest IAE, at 2.75 % every
    2-3 s, is 16 % lower for three times the valve travel); reinforcement
    ``a_cr = (fs + fd)/2 = 2.5`` %; the model-based compensator with the true
    ``fs, fd, K``.

    References
    ----------
    .. [1] Hagglund (2002); [2] Ivan & Lakshminarayanan (2009);
       [3] thesis section 4.3.

    Examples
    --------
    >>> rows = compare_compensators(duration=3000.0)
    >>> [row.method for row in rows]
    ['none', 'knocker', 'constant reinforcement', 'model-based']
    """
    process, loop, dt = _chapter4_loop()
    compensators: tuple[Compensator, ...] = (
        NoCompensation(),
        knocker or Knocker(amplitude=2.5, width=1.0, period=4.0),
        reinforcement or ConstantReinforcement(amplitude=2.5),
        model_based or ModelBasedCompensator(valve=CHAPTER4_VALVE, process_gain=CHAPTER4_GAIN),
    )
    return tuple(
        compensation_metrics(
            simulate_compensated(
                process,
                loop,
                compensator,
                dt=dt,
                duration=duration,
                compensate_from=compensate_from,
            ),
            method=compensator.name,
        )
        for compensator in compensators
    )


THESIS_TABLE_4_3: dict[tuple[float, float], tuple[float, float, float, float]] = {
    (3.0, 2.0): (53.0, 12.3, -14.25, 2.00),  # Table 4.2, exact parameters
    (3.0, 1.5): (52.99, 15.5, -17.6, 1.97),
    (3.0, 2.5): (53.04, 7.9, -10.0, 2.01),
    (2.5, 2.0): (53.16, 12.2, -14.1, 2.08),
    (3.5, 2.0): (53.17, 13.8, -15.65, 2.08),
}
"""Thesis Tables 4.2-4.3: (fs_hat, fd_hat) -> (OP_ss, f1, f2, PV_ss), PV above the
operating point (SP = 2)."""

THESIS_TABLE_4_4: dict[float, tuple[float, float]] = {
    -0.20: (53.8, 2.006),
    -0.15: (53.6, 2.019),
    -0.10: (53.4, 2.019),
    -0.05: (53.2, 2.006),
    0.05: (52.9, 2.009),
    0.10: (52.8, 2.032),
    0.15: (52.6, 1.973),
    0.20: (52.5, 1.98),
}
"""Thesis Table 4.4: relative error of K_hat -> (OP_ss, PV_ss)."""


@dataclass(frozen=True)
class SensitivityRow:
    """The model-based compensator on the chapter 4 loop with estimated parameters.

    Values are over several switch-on times (the outcome depends on where in
    the limit cycle the compensator starts).

    Attributes
    ----------
    fs, fd : float
        Stiction parameters given to the compensator (true: 3 and 2).
    gain_error : float
        Relative error of the process gain given to it (true K = 0.66).
    op_ss : float
        Learned ``OP_ss``, mean over switch-on times.
    first_move, second_move : float
        ``OP_mid - OP_ss`` and ``OP_end - OP_mid`` of the first regulation
        (thesis f1, f2), at the first switch-on time.
    pv_error_one_move : float
        Worst ``|PV - SP|`` after one regulation (the thesis procedure).
    pv_error_repeated : float
        Worst ``|PV - SP|`` after repeated regulations.
    thesis_op_ss, thesis_pv_error : float
        The thesis values (Tables 4.2-4.4); NaN when the case is not in them.
    """

    fs: float
    fd: float
    gain_error: float
    op_ss: float
    first_move: float
    second_move: float
    pv_error_one_move: float
    pv_error_repeated: float
    thesis_op_ss: float
    thesis_pv_error: float


SensitivityCase = tuple[float, float, float]
"""``(fs_hat, fd_hat, relative error of K_hat)``."""

THESIS_SENSITIVITY_CASES: tuple[SensitivityCase, ...] = (
    *((fs, fd, 0.0) for fs, fd in THESIS_TABLE_4_3),
    *((3.0, 2.0, error) for error in THESIS_TABLE_4_4),
)


def model_based_sensitivity(
    cases: Sequence[SensitivityCase] = THESIS_SENSITIVITY_CASES,
    *,
    switch_on_times: Sequence[float] = (1000.0, 1100.0, 1200.0, 1300.0),
    regulation_attempts: int = 3,
) -> tuple[SensitivityRow, ...]:
    """Sensitivity of the model-based compensator to errors in fs, fd and K (Tables 4.3-4.4).

    Each case runs the chapter 4 loop with the compensator switched on at each
    of ``switch_on_times`` and allowed ``regulation_attempts`` regulations;
    the PV error after the first one is the thesis procedure.

    References
    ----------
    .. [3] Thesis section 4.4, Tables 4.3 and 4.4.

    Examples
    --------
    >>> (row,) = model_based_sensitivity([(3.0, 2.0, 0.0)], switch_on_times=[1000.0])
    >>> round(row.op_ss, 2), row.pv_error_one_move < 0.05, row.thesis_op_ss
    (53.03, True, 53.0)
    """
    process, loop, dt = _chapter4_loop()
    thesis_sp = 2.0  # the thesis works in deviations from the operating point
    rows = []
    for fs, fd, gain_error in cases:
        compensator = ModelBasedCompensator(
            valve=HeValve(fs=fs, fd=fd),
            process_gain=CHAPTER4_GAIN * (1.0 + gain_error),
            regulation_attempts=regulation_attempts,
        )
        runs = []
        for start in switch_on_times:
            result = simulate_compensated(
                process,
                loop,
                compensator,
                dt=dt,
                duration=start + 2000.0,
                compensate_from=start,
            )
            assert isinstance(result.run, ModelBasedRun)
            runs.append(result.run)
        if gain_error == 0.0 and (fs, fd) in THESIS_TABLE_4_3:
            thesis_op_ss, *_, thesis_pv = THESIS_TABLE_4_3[fs, fd]
        elif (fs, fd) == (3.0, 2.0) and gain_error in THESIS_TABLE_4_4:
            thesis_op_ss, thesis_pv = THESIS_TABLE_4_4[gain_error]
        else:
            thesis_op_ss = thesis_pv = math.nan
        rows.append(
            SensitivityRow(
                fs=fs,
                fd=fd,
                gain_error=gain_error,
                op_ss=float(np.mean([run.op_ss_ for run in runs])),
                first_move=runs[0].first_move,
                second_move=runs[0].second_move,
                pv_error_one_move=max(abs(_after_first_regulation(run)) for run in runs),
                pv_error_repeated=max(abs(run.pv_errors_[-1]) for run in runs),
                thesis_op_ss=thesis_op_ss,
                thesis_pv_error=thesis_pv - thesis_sp,
            )
        )
    return tuple(rows)


def _after_first_regulation(run: ModelBasedRun) -> float:
    """Settled PV error after the first regulation (before it, if none was needed)."""
    return run.pv_errors_[min(1, len(run.pv_errors_) - 1)]
