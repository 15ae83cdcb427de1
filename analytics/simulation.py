"""Closed-loop simulation of single and multi-loop control systems with sticky valves.

A plant is an ``n x n`` matrix of transfer functions with dead times
(:class:`analytics.lti.TransferFunction`, entry ``(i, j)`` from valve ``j``
to PV ``i``), each loop has a PI/PID controller and a valve model
(:mod:`analytics.valves`). The linear part is discretised exactly under a
zero-order hold (:func:`analytics.lti.discretise`), the controller is the
digital PI/PID of a DCS, and the valve is stepped with the same compiled
kernel used everywhere else. The whole loop runs in one compiled function.

Sample ``k`` follows the convention of a DCS scan: the PV is measured, the
controller computes OP, the valve moves to MV, and MV is held until sample
``k + 1``. All signals are in % of span; the process works in deviations from
the operating point ``(op_bias, pv_bias)``, so a plant started with
``SP = pv_bias`` is at rest.

References
----------
.. [1] Astrom & Hagglund (2006), *Advanced PID Control*, ISA, sec. 3.5-3.6
   (integrator anti-windup by tracking, derivative filter on the measurement).
.. [2] Thesis sections 2.4 and 3.3 (the 3x3 column, Eqs. 2.10-2.13, 3.24-3.26)
   and chapter 4 (the single-loop example).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, Literal, NamedTuple

import numpy as np
from numba import njit
from numpy.typing import NDArray

from analytics.errors import ModelSpecError
from analytics.lti import TransferFunction, discretise
from analytics.types import FloatArray
from analytics.valves import (
    IdealValve,
    ValveModel,
    valve_from_dict,
    valve_step,
)


class IdealGains(NamedTuple):
    """The gains of a PID controller in the ideal form ``Kc (1 + 1/(Ti s) + Td s)``
    (thesis Eq. 5.2).

    Attributes
    ----------
    Kc : float
        Proportional gain (negative: the other action, as in thesis Eq. 2.12).
    Ti : float
        Integral time, s; ``inf`` without integral action.
    Td : float
        Derivative time, s.

    Examples
    --------
    >>> IdealGains(2.0, 10.0).parallel()
    (2.0, 0.2, 0.0)
    """

    Kc: float
    Ti: float = math.inf
    Td: float = 0.0

    def parallel(self) -> tuple[float, float, float]:
        """``(kp, ki, kd) = (Kc, Kc / Ti, Kc Td)``, ``ki = 0`` for ``Ti = inf``."""
        return self.Kc, 0.0 if math.isinf(self.Ti) else self.Kc / self.Ti, self.Kc * self.Td


@dataclass(frozen=True)
class PIDController:
    """Digital PID controller in parallel form ``kp e + ki integral(e) + kd de/dt``.

    Use :meth:`ideal` for ``Kc (1 + 1/(Ti s) + Td s)`` (thesis Eq. 5.2) and
    :meth:`parallel` for ``Kp + Ki/s`` (thesis Eqs. 2.11-2.13).  The one
    controller type of the package: simulation, compensation, tuning,
    limit-cycle prediction and the model check use it.

    At sample ``k``: ``e_k = SP_k - PV_k`` (reverse action) or ``PV_k - SP_k``
    (direct), ``I_k = I_{k-1} + ki dt e_k`` starting from ``op_bias``,
    ``OP_k = kp e_k + I_k + D_k``, limited to ``op_limits``. When OP saturates
    the integrator tracks the limit (anti-windup, [1] sec. 3.5). The derivative
    acts on the measurement through a first-order filter with time constant
    ``Td / derivative_filter`` (backward difference).

    Parameters
    ----------
    kp, ki, kd : float
        Proportional gain, integral gain (1/s), derivative gain (s).
    action : {"reverse", "direct"}
        Reverse: OP rises when PV falls below SP.
    op_limits : (float, float)
        Output range, % of span.
    op_bias : float
        OP at rest (initial integrator value), % of span.
    derivative_filter : float
        ``N`` of the derivative filter.
    ideal_form : IdealGains or None
        The gains the controller was given in by :meth:`ideal`, from which ``kp``,
        ``ki``, ``kd`` are derived (:meth:`IdealGains.parallel`); None for one given
        in parallel gains.  Kept because the derivation does not invert exactly
        (``Kc / (Kc / Ti)`` may differ from ``Ti`` in the last bit): a model written
        in the ideal form reads back as written (:meth:`as_ideal`).

    Examples
    --------
    >>> c = PIDController.ideal(0.1, 11.0)
    >>> c.kp / c.ki, c.as_ideal().Ti
    (10.999999999999998, 11.0)
    """

    kp: float
    ki: float = 0.0
    kd: float = 0.0
    action: Literal["reverse", "direct"] = "reverse"
    op_limits: tuple[float, float] = (0.0, 100.0)
    op_bias: float = 50.0
    derivative_filter: float = 10.0
    ideal_form: IdealGains | None = None

    def __post_init__(self) -> None:
        for name in ("kp", "ki", "kd", "op_bias", "derivative_filter"):
            value = getattr(self, name)
            if not isinstance(value, int | float) or not math.isfinite(value):
                raise ModelSpecError(f"controller {name} must be a finite number, got {value!r}")
        if self.action not in ("reverse", "direct"):
            raise ModelSpecError(
                f"controller action must be 'reverse' or 'direct', got {self.action!r}"
            )
        low, high = self.op_limits
        if not low < high:
            raise ModelSpecError(
                f"controller op_limits must be (low, high) with low < high, got {self.op_limits}"
            )
        if not low <= self.op_bias <= high:
            raise ModelSpecError(
                f"controller op_bias={self.op_bias} lies outside op_limits {self.op_limits}"
            )
        if self.derivative_filter <= 0:
            raise ModelSpecError("controller derivative_filter must be > 0")
        if self.ideal_form is not None:
            _check_ideal(self.ideal_form)
            if (self.kp, self.ki, self.kd) != self.ideal_form.parallel():
                raise ModelSpecError(
                    f"controller gains kp={self.kp}, ki={self.ki}, kd={self.kd} are not "
                    f"those of its ideal form {self.ideal_form}"
                )

    @classmethod
    def ideal(
        cls, Kc: float, Ti: float = math.inf, Td: float = 0.0, **options: Any
    ) -> PIDController:
        """``Kc (1 + 1/(Ti s) + Td s)``; ``Ti = inf`` gives P or PD control."""
        form = IdealGains(Kc, Ti, Td)
        _check_ideal(form)
        kp, ki, kd = form.parallel()
        return cls(kp=kp, ki=ki, kd=kd, ideal_form=form, **options)

    @classmethod
    def parallel(cls, Kp: float, Ki: float = 0.0, Kd: float = 0.0, **options: Any) -> PIDController:
        """``Kp + Ki/s + Kd s`` (negative gains allowed, as in thesis Eq. 2.12)."""
        return cls(kp=Kp, ki=Ki, kd=Kd, **options)

    @classmethod
    def from_dict(cls, spec: dict[str, Any]) -> PIDController:
        """``{"Kc", "Ti"[, "Td"]}`` or ``{"Kp", "Ki"[, "Kd"]}`` plus optional
        ``action``, ``op_limits``, ``op_bias``."""
        if not isinstance(spec, dict):
            raise ModelSpecError(f"a controller must be an object, got {spec!r}")
        options: dict[str, Any] = {
            k: spec[k] for k in ("action", "op_bias", "derivative_filter") if k in spec
        }
        if "op_limits" in spec:
            options["op_limits"] = tuple(spec["op_limits"])
        try:
            if "Kc" in spec:
                return cls.ideal(
                    spec["Kc"], spec.get("Ti", math.inf), spec.get("Td", 0.0), **options
                )
            if "Kp" in spec:
                return cls.parallel(spec["Kp"], spec.get("Ki", 0.0), spec.get("Kd", 0.0), **options)
        except TypeError as exc:
            raise ModelSpecError(f"controller {spec!r}: {exc}") from None
        raise ModelSpecError(
            f"a controller needs 'Kc' (with 'Ti') or 'Kp' (with 'Ki'), got keys {sorted(spec)}"
        )

    def as_ideal(self) -> IdealGains:
        """This controller in the ideal form: the gains it was given in, else
        ``Kc = kp``, ``Ti = kp / ki`` (inf without integral action), ``Td = kd / kp``.

        Raises
        ------
        ModelSpecError
            The parallel gains have no ideal form (``kp = 0`` with integral or
            derivative action, or ``ki``, ``kd`` of the other sign than ``kp``).
        """
        if self.ideal_form is not None:
            return self.ideal_form
        if self.kp == 0 and (self.ki != 0 or self.kd != 0):
            raise ModelSpecError("a controller without proportional gain has no ideal form")
        form = IdealGains(
            self.kp,
            math.inf if self.ki == 0 else self.kp / self.ki,
            0.0 if self.kd == 0 else self.kd / self.kp,
        )
        if not form.Ti > 0 or form.Td < 0:
            raise ModelSpecError(
                f"Kp = {self.kp:g}, Ki = {self.ki:g}, Kd = {self.kd:g} have no ideal form "
                "(integral or derivative gain of the other sign)"
            )
        return form

    def stepper(self, dt: float, pv0: float) -> PIDStepper:
        """This controller one sample a call (:class:`PIDStepper`), from PV ``pv0``."""
        return PIDStepper(self, dt, pv0)

    def derivative_filter_time(self, dt: float) -> float:
        """Derivative filter time constant ``Td / N`` (``dt`` when ``kp = 0`` leaves
        ``Td`` undefined; 0 without derivative action)."""
        if self.kd == 0:
            return 0.0
        return abs(self.kd / self.kp) / self.derivative_filter if self.kp != 0 else dt

    def to_dict(self) -> dict[str, Any]:
        """JSON form in parallel gains."""
        return {
            "Kp": self.kp,
            "Ki": self.ki,
            "Kd": self.kd,
            "action": self.action,
            "op_limits": list(self.op_limits),
            "op_bias": self.op_bias,
        }


def _check_ideal(form: IdealGains) -> None:
    if not form.Ti > 0:
        raise ModelSpecError(f"integral time Ti must be > 0 s, got {form.Ti}")
    if form.Td < 0:
        raise ModelSpecError(f"derivative time Td must be >= 0 s, got {form.Td}")


class PIDStepper:
    """A :class:`PIDController` one sample a call, for loops simulated in Python.

    Same recursion as the compiled :func:`_closed_loop` (integral from
    ``op_bias``, derivative on the filtered measurement, anti-windup by
    tracking the output limits), plus tracking of an externally held output
    (a compensator that overrides OP, :mod:`analytics.compensation`).
    """

    def __init__(self, controller: PIDController, dt: float, pv0: float) -> None:
        self.c = controller
        self.dt = dt
        self.sign = 1.0 if controller.action == "reverse" else -1.0
        self.tf = controller.derivative_filter_time(dt)
        self.integral = controller.op_bias
        self.deriv = 0.0
        self.pv_prev = pv0
        self._proportional = 0.0

    def step(self, sp: float, pv: float) -> float:
        c = self.c
        err = self.sign * (sp - pv)
        self.integral += c.ki * self.dt * err
        if self.tf > 0.0:
            self.deriv = (self.tf * self.deriv - c.kd * self.sign * (pv - self.pv_prev)) / (
                self.tf + self.dt
            )
        self.pv_prev = pv
        self._proportional = c.kp * err
        out = self._proportional + self.integral + self.deriv
        low, high = c.op_limits
        if out > high or out < low:
            return self.track(min(max(out, low), high))
        return out

    def track(self, out: float) -> float:
        """Force the output to ``out`` and set the integral so the next step is bumpless."""
        self.integral = out - self._proportional - self.deriv
        return out


@dataclass(frozen=True)
class Disturbance:
    """An additive disturbance on one loop.

    Parameters
    ----------
    kind : {"step", "sine", "noise"}
        Step of ``magnitude`` at ``time``; sinusoid ``magnitude sin(2 pi t / period + phase)``;
        zero-mean Gaussian noise of standard deviation ``magnitude``.
    magnitude : float
        Step size, sine amplitude or noise standard deviation, % of span.
    at : {"output", "measurement", "input"}
        Added to the process output (a load on PV), to the measured PV only
        (sensor noise) or to the valve position (a load on the process input).
    """

    kind: Literal["step", "sine", "noise"]
    magnitude: float
    at: Literal["output", "measurement", "input"] = "output"
    time: float = 0.0
    period: float = 0.0
    phase: float = 0.0
    seed: int | None = None

    def __post_init__(self) -> None:
        if self.kind not in ("step", "sine", "noise"):
            raise ModelSpecError(f"disturbance kind must be step, sine or noise, got {self.kind!r}")
        if self.at not in ("output", "measurement", "input"):
            raise ModelSpecError(
                f"disturbance 'at' must be output, measurement or input, got {self.at!r}"
            )
        if not math.isfinite(self.magnitude):
            raise ModelSpecError(f"disturbance magnitude must be finite, got {self.magnitude}")
        if self.kind == "sine" and not self.period > 0:
            raise ModelSpecError(f"a sine disturbance needs a period > 0 s, got {self.period}")
        if self.kind == "noise" and self.magnitude < 0:
            raise ModelSpecError(f"noise standard deviation must be >= 0, got {self.magnitude}")

    def series(self, t: FloatArray) -> FloatArray:
        """The disturbance at the sample times ``t``."""
        if self.kind == "step":
            return np.where(t >= self.time, self.magnitude, 0.0)
        if self.kind == "sine":
            wave: FloatArray = np.sin(2.0 * np.pi * t / self.period + self.phase)
            return np.multiply(self.magnitude, wave)
        return np.random.default_rng(self.seed).normal(0.0, self.magnitude, size=t.shape)


Setpoint = float | Sequence[tuple[float, float]]


def in_stretches(t: FloatArray, stretches: Sequence[tuple[float, float]]) -> NDArray[np.bool_]:
    """Whether each time of ``t`` lies in one of the ``(start, end)`` stretches
    (``start <= t < end``), as :attr:`Loop.manual` lists them.

    >>> in_stretches(np.arange(5.0), [(1.0, 3.0)]).tolist()
    [False, True, True, False, False]
    """
    out = np.zeros(t.shape, dtype=bool)
    for start, end in stretches:
        out |= (t >= start) & (t < end)
    return out


@dataclass(frozen=True)
class Loop:
    """One control loop: controller, valve, setpoint schedule and disturbances.

    ``setpoint`` is a constant or a schedule ``[(time, value), ...]`` of steps;
    before the first step the setpoint is ``pv_bias``.  ``manual`` lists the
    stretches ``(start, end)`` (s, ``start <= t < end``) the loop spends in
    manual: OP is held at its last value and the integrator tracks it, so the
    return to automatic is bumpless (Astrom and Hagglund 2006, *Advanced PID
    Control*, sec. 3.5).
    """

    controller: PIDController
    valve: ValveModel = field(default_factory=IdealValve)
    setpoint: Setpoint | None = None
    pv_bias: float = 50.0
    disturbances: tuple[Disturbance, ...] = ()
    name: str = ""
    manual: tuple[tuple[float, float], ...] = ()

    def setpoint_series(self, t: FloatArray) -> FloatArray:
        """Setpoint at the sample times ``t``."""
        if self.setpoint is None:
            return np.full(t.shape, self.pv_bias)
        if isinstance(self.setpoint, int | float):
            return np.full(t.shape, float(self.setpoint))
        sp = np.full(t.shape, self.pv_bias)
        for time, value in sorted(self.setpoint):
            sp[t >= time] = value
        return sp


@dataclass(frozen=True)
class SimulationResult:
    """Time series of a closed-loop simulation; arrays are ``(n_loops, samples)``.

    ``pv`` is the measured PV (with sensor noise), what a historian records.
    """

    t: FloatArray
    sp: FloatArray
    op: FloatArray
    mv: FloatArray
    pv: FloatArray
    names: tuple[str, ...]

    @property
    def dt(self) -> float:
        """Sampling period, s."""
        return float(self.t[1] - self.t[0]) if self.t.size > 1 else 0.0

    def columns(self) -> dict[str, FloatArray]:
        """Named columns ``time, sp_<loop>, op_<loop>, mv_<loop>, pv_<loop>``.

        A single loop gets the plain names ``sp, op, mv, pv``.
        """
        out = {"time": self.t}
        single = len(self.names) == 1
        for i, name in enumerate(self.names):
            suffix = "" if single else f"_{name}"
            out[f"sp{suffix}"] = self.sp[i]
            out[f"op{suffix}"] = self.op[i]
            out[f"mv{suffix}"] = self.mv[i]
            out[f"pv{suffix}"] = self.pv[i]
        return out


@njit(cache=True)
def _closed_loop(
    n_samples: int,
    dt: float,
    pv_bias: FloatArray,
    sp: FloatArray,
    load_out: FloatArray,
    load_meas: FloatArray,
    load_in: FloatArray,
    kp: FloatArray,
    ki: FloatArray,
    kd: FloatArray,
    tf: FloatArray,
    sign: FloatArray,
    op_lo: FloatArray,
    op_hi: FloatArray,
    op_bias: FloatArray,
    manual: NDArray[np.bool_],
    valve_code: NDArray[np.int64],
    valve_params: FloatArray,
    valve_state: FloatArray,
    ad: FloatArray,
    b0: FloatArray,
    b1: FloatArray,
    c: FloatArray,
    d: FloatArray,
    delay: NDArray[np.int64],
    entry_in: NDArray[np.int64],
    entry_out: NDArray[np.int64],
) -> tuple[FloatArray, FloatArray, FloatArray]:
    n = pv_bias.shape[0]
    n_entries = ad.shape[0]
    order = ad.shape[1]
    op = np.empty((n, n_samples))
    mv = np.empty((n, n_samples))
    pv = np.empty((n, n_samples))
    u = np.zeros((n, n_samples))  # process input, deviation from op_bias
    x = np.zeros((n_entries, order))
    x_new = np.zeros(order)
    integral = op_bias.copy()
    deriv = np.zeros(n)
    pv_prev = pv_bias.copy()
    for k in range(n_samples):
        for i in range(n):
            pv[i, k] = pv_bias[i] + load_out[i, k] + load_meas[i, k]
        for e in range(n_entries):
            y = 0.0
            for m in range(order):
                y += c[e, m] * x[e, m]
            lag = k - delay[e] - 1
            if lag >= 0:
                y += d[e] * u[entry_in[e], lag]
            pv[entry_out[e], k] += y
        for i in range(n):
            err = sign[i] * (sp[i, k] - pv[i, k])
            integral[i] += ki[i] * dt * err
            if tf[i] > 0.0:
                deriv[i] = (tf[i] * deriv[i] - kd[i] * sign[i] * (pv[i, k] - pv_prev[i])) / (
                    tf[i] + dt
                )
            pv_prev[i] = pv[i, k]
            out = kp[i] * err + integral[i] + deriv[i]
            if manual[i, k]:  # OP held; the integrator tracks it (bumpless transfer)
                out = op[i, k - 1] if k > 0 else op_bias[i]
                integral[i] = out - kp[i] * err - deriv[i]
            elif out > op_hi[i]:
                integral[i] = min(integral[i], op_hi[i] - kp[i] * err - deriv[i])
                out = op_hi[i]
            elif out < op_lo[i]:
                integral[i] = max(integral[i], op_lo[i] - kp[i] * err - deriv[i])
                out = op_lo[i]
            op[i, k] = out
            mv[i, k] = valve_step(valve_code[i], valve_params[i], valve_state[i], out, dt)
            u[i, k] = mv[i, k] - op_bias[i] + load_in[i, k]
        for e in range(n_entries):
            j = entry_in[e]
            u0 = u[j, k - delay[e]] if k - delay[e] >= 0 else 0.0
            u1 = u[j, k - delay[e] - 1] if k - delay[e] - 1 >= 0 else 0.0
            for r in range(order):
                acc = b0[e, r] * u0 + b1[e, r] * u1
                for m in range(order):
                    acc += ad[e, r, m] * x[e, m]
                x_new[r] = acc
            for r in range(order):
                x[e, r] = x_new[r]
    return op, mv, pv


ProcessMatrix = Sequence[Sequence[TransferFunction | None]]


def _as_matrix(
    process: TransferFunction | ProcessMatrix, n_loops: int
) -> list[list[TransferFunction | None]]:
    if isinstance(process, TransferFunction):
        matrix: list[list[TransferFunction | None]] = [[process]]
    else:
        matrix = [list(row) for row in process]
    if len(matrix) != n_loops or any(len(row) != n_loops for row in matrix):
        shape = f"{len(matrix)} x {[len(row) for row in matrix]}"
        raise ModelSpecError(
            f"the process matrix must be {n_loops} x {n_loops} "
            f"(one row and column per loop), got {shape}"
        )
    for i in range(n_loops):
        if matrix[i][i] is None:
            raise ModelSpecError(
                f"process entry ({i + 1},{i + 1}) is missing: "
                f"loop {i + 1} has no effect on its own PV"
            )
    return matrix


def simulate(
    process: TransferFunction | ProcessMatrix,
    loops: Loop | Sequence[Loop],
    *,
    dt: float,
    duration: float,
) -> SimulationResult:
    """Simulate a closed-loop system.

    Parameters
    ----------
    process : TransferFunction or n x n nested sequence
        Single-loop process, or the matrix ``G[i][j]`` from valve ``j`` to PV
        ``i``; ``None`` entries mean no coupling.
    loops : Loop or sequence of Loop
        One per PV, in the order of the matrix.
    dt : float
        Sampling period, s.
    duration : float
        Simulated time, s; ``floor(duration / dt) + 1`` samples from ``t = 0``.

    Examples
    --------
    A healthy FOPDT loop settles at a new setpoint:

    >>> g = TransferFunction.fopdt(K=1.0, tau=10.0, theta=2.0)
    >>> loop = Loop(PIDController.ideal(Kc=1.0, Ti=10.0), setpoint=[(10.0, 60.0)])
    >>> res = simulate(g, loop, dt=0.5, duration=300.0)
    >>> round(float(res.pv[0, -1]), 3)
    60.0
    """
    loop_list = [loops] if isinstance(loops, Loop) else list(loops)
    if not loop_list:
        raise ModelSpecError("at least one loop is needed")
    if not (math.isfinite(dt) and dt > 0):
        raise ModelSpecError(f"sampling period dt must be > 0 s, got {dt}")
    if not (math.isfinite(duration) and duration >= dt):
        raise ModelSpecError(f"duration must be at least one sample (dt={dt} s), got {duration}")
    matrix = _as_matrix(process, len(loop_list))
    n = len(loop_list)
    n_samples = math.floor(duration / dt + 1e-9) + 1
    t: FloatArray = np.arange(n_samples, dtype=np.float64) * dt

    entries = [
        (i, j, discretise(g, dt))
        for i, row in enumerate(matrix)
        for j, g in enumerate(row)
        if g is not None
    ]
    order = max(1, max(entry.Ad.shape[0] for _, _, entry in entries))
    ad = np.zeros((len(entries), order, order))
    b0 = np.zeros((len(entries), order))
    b1 = np.zeros((len(entries), order))
    c = np.zeros((len(entries), order))
    for e, (_, _, entry) in enumerate(entries):
        m = entry.Ad.shape[0]
        ad[e, :m, :m], b0[e, :m], b1[e, :m], c[e, :m] = entry.Ad, entry.B0, entry.B1, entry.C
    d = np.array([entry.D for _, _, entry in entries])
    delay = np.array([entry.delay_samples for _, _, entry in entries], dtype=np.int64)
    entry_out = np.array([i for i, _, _ in entries], dtype=np.int64)
    entry_in = np.array([j for _, j, _ in entries], dtype=np.int64)

    loads = {at: np.zeros((n, n_samples)) for at in ("output", "measurement", "input")}
    for i, loop in enumerate(loop_list):
        for disturbance in loop.disturbances:
            loads[disturbance.at][i] += disturbance.series(t)
    ctrl = [loop.controller for loop in loop_list]
    n_params = max(loop.valve.params_array().size for loop in loop_list)
    valve_params = np.zeros((n, n_params))
    for i, loop in enumerate(loop_list):
        p = loop.valve.params_array()
        valve_params[i, : p.size] = p
    valve_state = np.array(
        [loop.valve.initial_state(loop.controller.op_bias) for loop in loop_list]
    )
    sp = np.array([loop.setpoint_series(t) for loop in loop_list])
    op, mv, pv = _closed_loop(
        n_samples,
        float(dt),
        np.array([loop.pv_bias for loop in loop_list], dtype=np.float64),
        sp,
        loads["output"],
        loads["measurement"],
        loads["input"],
        np.array([ct.kp for ct in ctrl], dtype=np.float64),
        np.array([ct.ki for ct in ctrl], dtype=np.float64),
        np.array([ct.kd for ct in ctrl], dtype=np.float64),
        np.array([ct.derivative_filter_time(dt) for ct in ctrl]),
        np.array([1.0 if ct.action == "reverse" else -1.0 for ct in ctrl]),
        np.array([ct.op_limits[0] for ct in ctrl], dtype=np.float64),
        np.array([ct.op_limits[1] for ct in ctrl], dtype=np.float64),
        np.array([ct.op_bias for ct in ctrl], dtype=np.float64),
        np.array([in_stretches(t, loop.manual) for loop in loop_list]),
        np.array([loop.valve.code for loop in loop_list], dtype=np.int64),
        valve_params,
        valve_state,
        ad,
        b0,
        b1,
        c,
        d,
        delay,
        entry_in,
        entry_out,
    )
    names = tuple(loop.name or f"loop{i + 1}" for i, loop in enumerate(loop_list))
    return SimulationResult(t=t, sp=sp, op=op, mv=mv, pv=pv, names=names)


def _disturbance_from_dict(spec: dict[str, Any]) -> Disturbance:
    if not isinstance(spec, dict):
        raise ModelSpecError(f"a disturbance must be an object, got {spec!r}")
    try:
        return Disturbance(**spec)
    except TypeError as exc:
        raise ModelSpecError(f"disturbance {spec!r}: {exc}") from None


def _per_loop(spec: dict[str, Any], plural: str, singular: str, n: int) -> list[Any]:
    if plural in spec:
        items = spec[plural]
        if not isinstance(items, list) or len(items) != n:
            raise ModelSpecError(
                f"'{plural}' must be a list with one entry per loop ({n}), got {items!r}"
            )
        return items
    if singular in spec:
        if n != 1:
            raise ModelSpecError(
                f"'{singular}' is for a single loop; this model has {n} loops: use '{plural}'"
            )
        return [spec[singular]]
    return [None] * n


@dataclass(frozen=True)
class ClosedLoopModel:
    """A closed-loop system read from JSON, ready to :meth:`run`.

    The JSON form (shared with ``loopwatch predict``)::

        {"dt": 0.1, "duration": 2000,
         "process": {"type": "fopdt", "K": 0.66, "tau": 6.7, "theta": 2.6}
                    or {"matrix": [[entry or null, ...], ...]},
         "controllers": [{"Kc": 1, "Ti": 10} or {"Kp": 0.1, "Ki": 0.09}, ...],
         "valves": [{"model": "he", "fs": 3, "fd": 2} or null, ...],
         "setpoints": [value or [[time, value], ...], ...],
         "pv_bias": [...], "names": [...],
         "disturbances": [[{"kind": "noise", "magnitude": 0.1, "at": "measurement"}], ...]}

    A single loop may use the singular keys ``controller``, ``valve``,
    ``setpoint``.
    """

    process: TransferFunction | tuple[tuple[TransferFunction | None, ...], ...]
    loops: tuple[Loop, ...]
    dt: float
    duration: float

    @classmethod
    def from_dict(cls, spec: dict[str, Any]) -> ClosedLoopModel:
        """Parse and validate the JSON form; errors name the offending key."""
        if not isinstance(spec, dict):
            raise ModelSpecError("a model must be a JSON object")
        for key in ("dt", "process"):
            if key not in spec:
                raise ModelSpecError(f"the model lacks the required key '{key}'")
        proc = spec["process"]
        process: TransferFunction | tuple[tuple[TransferFunction | None, ...], ...]
        if isinstance(proc, dict) and "matrix" in proc:
            process = tuple(
                tuple(None if g is None else TransferFunction.from_dict(g) for g in row)
                for row in proc["matrix"]
            )
            n = len(process)
            _as_matrix(process, n)
        else:
            process = TransferFunction.from_dict(proc)
            n = 1
        controllers = _per_loop(spec, "controllers", "controller", n)
        valves = _per_loop(spec, "valves", "valve", n)
        setpoints = _per_loop(spec, "setpoints", "setpoint", n)
        biases = spec.get("pv_bias", [50.0] * n)
        if isinstance(biases, int | float):
            biases = [biases] * n
        names = spec.get("names", [f"loop{i + 1}" for i in range(n)])
        disturbances = spec.get("disturbances", [[] for _ in range(n)])
        if n == 1 and disturbances and isinstance(disturbances[0], dict):
            disturbances = [disturbances]
        for key, items in (("pv_bias", biases), ("names", names), ("disturbances", disturbances)):
            if len(items) != n:
                raise ModelSpecError(
                    f"'{key}' must have one entry per loop ({n}), got {len(items)}"
                )
        loops = []
        for i in range(n):
            if controllers[i] is None:
                raise ModelSpecError(f"loop {i + 1} has no controller")
            controller = PIDController.from_dict(controllers[i])
            setpoint = setpoints[i]
            if isinstance(setpoint, list):
                setpoint = [tuple(step) for step in setpoint]
            loops.append(
                Loop(
                    controller=controller,
                    valve=valve_from_dict(valves[i]),
                    setpoint=setpoint,
                    pv_bias=float(biases[i]),
                    disturbances=tuple(_disturbance_from_dict(x) for x in disturbances[i]),
                    name=str(names[i]),
                )
            )
        return cls(
            process=process,
            loops=tuple(loops),
            dt=float(spec["dt"]),
            duration=float(spec.get("duration", 1000.0)),
        )

    def run(self, *, duration: float | None = None) -> SimulationResult:
        """Simulate this model (optionally for another ``duration``)."""
        return simulate(self.process, self.loops, dt=self.dt, duration=duration or self.duration)
