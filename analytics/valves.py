"""Control-valve models: ideal, stiction (data-driven and physics-based) and deadband.

Every model maps the controller output OP (``u``, % of valve travel) to the
valve position MV (``y``, same units) and is usable two ways:

* over a whole OP series at once with :meth:`ValveModel.simulate`, and
* one sample at a time with :meth:`ValveModel.stepper` (used by closed-loop
  simulation).

Both paths run the same compiled update of each model (the series loop of
:func:`valve_series` keeps the state in locals, the step of :func:`valve_step`
in the state vector), so they cannot drift apart. Compiled callers use the
kernels directly with the arrays of :meth:`ValveModel.params_array` and
:meth:`ValveModel.initial_state`: the closed-loop simulator :func:`valve_step`,
quantification (which runs a model thousands of times) :func:`valve_series`.

Units: all parameters are in % of valve travel (the thesis's "% lift"), like
the signals. Positions are not clipped to 0-100 %; the controller limits OP.

References
----------
.. [1] Stenman, Gustafsson & Forsman (2003), "A segmentation-based method for
   detection of stiction in control valves", Int. J. Adapt. Control 17:625-634.
   Thesis Eq. 1.1 with ERRATA item 2.
.. [2] Choudhury, Thornhill & Shah (2005), "Modelling valve stiction",
   Control Eng. Practice 13:641-658.
.. [3] Kano, Maruta, Kugemoto & Shimizu (2004), "Practical model and detection
   algorithm for valve stiction", IFAC DYCOPS, Boston.
.. [4] He, Wang, Pottmann & Qin (2007), "A curve fitting method for detecting
   valve stiction in oscillating control loops", Ind. Eng. Chem. Res.
   46:4549-4560.
.. [5] Karnopp (1985), "Computer simulation of stick-slip friction in
   mechanical dynamic systems", J. Dyn. Syst. Meas. Control 107:100-103; the
   valve form follows Garcia (2008), "Comparison of friction models applied
   to a control valve", Control Eng. Practice 16:1231-1243.
"""

from __future__ import annotations

import math
import numbers
from abc import ABC, abstractmethod
from dataclasses import asdict, dataclass
from typing import Any, ClassVar

import numpy as np
from numba import njit
from numpy.typing import ArrayLike, NDArray

from analytics.errors import ValveModelError

# Model codes understood by :func:`valve_step`.
IDEAL, STENMAN, CHOUDHURY, KANO, HE, KARNOPP = 0, 1, 2, 3, 4, 5

# Layout of the state vector shared by every model.
POSITION = 0  # y: valve position (MV)
LAST_INPUT = 1  # previous OP sample
STICK_POINT = 2  # OP at which the valve stuck (x_ss of [2], u_s of [3])
STUCK = 3  # 1.0 while the valve is stuck, else 0.0
MOTION = 4  # sign of the valve's last motion (+1, -1, 0 = unknown)
INPUT_SLOPE = 5  # sign of the previous OP change (Choudhury's v_old)
VELOCITY = 6  # stem velocity, %/s (physics model only)
STATE_SIZE = 7


def sj_to_fsfd(S: float, J: float) -> tuple[float, float]:
    """Convert stick band plus deadband ``S`` and slip jump ``J`` to He's (fs, fd).

    Thesis Eq. 1.2: ``fs = (S + J) / 2`` and ``fd = (S - J) / 2``.

    Examples
    --------
    >>> sj_to_fsfd(4.0, 2.0)
    (3.0, 1.0)
    """
    _check_sj(S, J)
    return (S + J) / 2.0, (S - J) / 2.0


def fsfd_to_sj(fs: float, fd: float) -> tuple[float, float]:
    """Convert He's static and dynamic friction (fs, fd) to (S, J); inverse of Eq. 1.2.

    Examples
    --------
    >>> fsfd_to_sj(3.0, 2.0)
    (5.0, 1.0)
    """
    _check_fsfd(fs, fd)
    return fs + fd, fs - fd


def _check_finite_nonnegative(**values: float) -> None:
    for name, value in values.items():
        if not isinstance(value, numbers.Real) or isinstance(value, bool):
            raise ValveModelError(f"{name} must be a number, got {value!r}")
        if not math.isfinite(value):
            raise ValveModelError(f"{name} must be finite, got {value}")
        if value < 0:
            raise ValveModelError(f"{name} must be >= 0 (% of travel), got {value}")


def _check_sj(S: float, J: float) -> None:
    _check_finite_nonnegative(S=S, J=J)
    if J > S:
        raise ValveModelError(f"slip jump J={J} cannot exceed the stick band S={S}")


def _check_fsfd(fs: float, fd: float) -> None:
    _check_finite_nonnegative(fs=fs, fd=fd)
    if fd > fs:
        raise ValveModelError(f"dynamic friction fd={fd} cannot exceed static friction fs={fs}")


@njit(cache=True)
def _sign(x: float) -> float:
    if x > 0.0:
        return 1.0
    if x < 0.0:
        return -1.0
    return 0.0


@njit(cache=True, inline="always")
def _band_update(
    S: float,
    J: float,
    choudhury: bool,
    y: float,
    last_input: float,
    stick_point: float,
    stuck: float,
    motion: float,
    input_slope: float,
    u: float,
) -> tuple[float, float, float, float, float]:
    """Choudhury [2] and Kano [3]: stick band S and slip jump J.

    A stuck valve moves once OP has travelled more than ``S`` from the stick
    point against the valve's last motion, or more than ``J`` along it; a
    moving valve lags OP by ``(S - J) / 2``. A valve at rest with no known
    last motion sits mid-band and needs ``(S + J) / 2``. Choudhury's model
    moves the stick point to the turning point of OP at every reversal of OP
    (so noise keeps a stuck valve stuck); Kano's keeps the point where the
    valve stopped until it moves again, which is the difference Kano et al.
    introduced to handle stochastic inputs.

    Works on scalars (the state entries of the same names) so that a series
    keeps them in registers; returns the new position, stick point, stuck
    flag, motion and input slope.
    """
    slope = _sign(u - last_input)
    if stuck == 0.0:
        if slope != motion:
            stuck = 1.0
            stick_point = last_input
    elif choudhury and slope != 0.0 and slope != input_slope:
        stick_point = last_input
    if stuck == 1.0 and slope != 0.0:
        travel = slope * (u - stick_point)
        if motion == 0.0:
            threshold = 0.5 * (S + J)
        elif slope == motion:
            threshold = J
        else:
            threshold = S
        # A slip never carries the valve against OP (Choudhury's moving stick
        # point could otherwise throw it backwards after two OP reversals).
        ahead = slope * (u - slope * 0.5 * (S - J) - y) > 0.0
        if travel > threshold and ahead:
            stuck = 0.0
            motion = slope
    if stuck == 0.0:
        y = u - motion * 0.5 * (S - J)
    if slope != 0.0:
        input_slope = slope
    return y, stick_point, stuck, motion, input_slope


@njit(cache=True)
def band_step(params: np.ndarray, state: np.ndarray, u: float, code: int) -> float:
    """Choudhury et al. (2005) [2] / Kano et al. (2004) [3] step; updates ``state``, returns MV."""
    y, stick_point, stuck, motion, input_slope = _band_update(
        params[0], params[1], code == CHOUDHURY, state[POSITION], state[LAST_INPUT],
        state[STICK_POINT], state[STUCK], state[MOTION], state[INPUT_SLOPE], u,
    )
    state[POSITION] = y
    state[STICK_POINT] = stick_point
    state[STUCK] = stuck
    state[MOTION] = motion
    state[INPUT_SLOPE] = input_slope
    return y


@njit(cache=True)
def _karnopp_step(params: np.ndarray, state: np.ndarray, u: float, dt: float) -> float:
    """Force balance with Karnopp friction [5], in units of % of travel.

    ``x'' = wn^2 (u - x - F_friction - fv x')``: the actuator force is scaled
    so that OP = x at rest without friction. Inside the stick zone
    (|v| < v_eps) friction balances the net force up to ``fs_force``;
    outside it is Coulomb ``fc_force sign(v)`` plus viscous ``fv v``.
    Integrated with semi-implicit Euler on sub-steps of at most 0.05/wn.
    """
    fs_force = params[0]
    fc_force = params[1]
    fv = params[2]
    wn = params[3]
    n_sub = max(1, int(math.ceil(dt * wn / 0.05)))  # noqa: RUF046 (numba: ceil may be float)
    h = dt / n_sub
    w2 = wn * wn
    v_eps = 1e-6 * max(1.0, fs_force) * wn
    x = state[POSITION]
    v = state[VELOCITY]
    for _ in range(n_sub):
        net = u - x
        if abs(v) < v_eps:
            if abs(net) <= fs_force:
                v = 0.0
                continue
            accel = w2 * (net - fc_force * _sign(net))
        else:
            accel = w2 * (net - fc_force * _sign(v) - fv * v)
        v_new = v + h * accel
        if v != 0.0 and v_new * v < 0.0:
            v_new = 0.0  # velocity crosses zero: stick and re-check breakaway next step
        v = v_new
        x += h * v
    state[POSITION] = x
    state[VELOCITY] = v
    return x


@njit(cache=True, inline="always")
def _stenman_update(d: float, y_prev: float, u: float) -> float:
    """Thesis Eq. 1.1 (ERRATA item 2): hold while |u - y_prev| < d, else jump to u."""
    return y_prev if abs(u - y_prev) < d else u


@njit(cache=True, inline="always")
def he_update(fs: float, fd: float, y_prev: float, u: float) -> float:
    """He et al. (2007) [4]: move to within ``fd`` of ``u`` once ``|u - y_prev|`` exceeds ``fs``."""
    residual = u - y_prev
    if residual > fs:
        return u - fd
    if residual < -fs:
        return u + fd
    return y_prev


@njit(cache=True)
def valve_step(code: int, params: np.ndarray, state: np.ndarray, u: float, dt: float) -> float:
    """Advance one valve by one sample of OP ``u`` and return its position.

    ``state`` (length :data:`STATE_SIZE`) is updated in place. ``dt`` is only
    used by the physics-based model.
    """
    if code == IDEAL:
        y = u
    elif code == STENMAN:
        y = _stenman_update(params[0], state[POSITION], u)
    elif code == HE:
        y = he_update(params[0], params[1], state[POSITION], u)
    elif code == CHOUDHURY or code == KANO:  # noqa: SIM109 (plain compares compile in numba)
        y = band_step(params, state, u, code)
    else:
        y = _karnopp_step(params, state, u, dt)
    state[POSITION] = y
    state[LAST_INPUT] = u
    return y


@njit(cache=True)
def valve_series(
    code: int, params: np.ndarray, state: np.ndarray, op: np.ndarray, dt: float
) -> np.ndarray:
    """Positions of a valve over an OP series, starting from ``state``.

    The compiled kernel behind :meth:`ValveModel.simulate`, for callers that
    run many models from their own compiled code: it checks nothing.  The
    state is updated in place by the models that need more than the position
    (the band and physics models); the others keep their state in a local.
    """
    n = op.shape[0]
    out = np.empty(n)
    if code == HE:
        y = state[POSITION]
        for k in range(n):
            y = he_update(params[0], params[1], y, op[k])
            out[k] = y
    elif code == STENMAN:
        y = state[POSITION]
        for k in range(n):
            y = _stenman_update(params[0], y, op[k])
            out[k] = y
    elif code == CHOUDHURY or code == KANO:  # noqa: SIM109 (plain compares compile in numba)
        S, J, choudhury = params[0], params[1], code == CHOUDHURY
        y, last_input = state[POSITION], state[LAST_INPUT]
        stick_point, stuck = state[STICK_POINT], state[STUCK]
        motion, input_slope = state[MOTION], state[INPUT_SLOPE]
        for k in range(n):
            u = op[k]
            y, stick_point, stuck, motion, input_slope = _band_update(
                S, J, choudhury, y, last_input, stick_point, stuck, motion, input_slope, u
            )
            last_input = u
            out[k] = y
        state[POSITION], state[LAST_INPUT] = y, last_input
        state[STICK_POINT], state[STUCK] = stick_point, stuck
        state[MOTION], state[INPUT_SLOPE] = motion, input_slope
    else:
        for k in range(n):
            out[k] = valve_step(code, params, state, op[k], dt)
    return out


class ValveStepper:
    """A valve being stepped one OP sample at a time (closed-loop simulation)."""

    def __init__(self, model: ValveModel, position: float, dt: float) -> None:
        self.model = model
        self.dt = float(dt)
        self._params = model.params_array()
        self.state = model.initial_state(position)

    @property
    def position(self) -> float:
        """Current valve position MV (% of travel)."""
        return float(self.state[POSITION])

    def step(self, op: float) -> float:
        """Apply one OP sample and return the new valve position."""
        if not math.isfinite(op):
            raise ValveModelError(f"OP must be finite, got {op}")
        return float(valve_step(self.model.code, self._params, self.state, float(op), self.dt))


@dataclass(frozen=True)
class ValveModel(ABC):
    """Base class: a valve model is a frozen set of parameters plus a kernel code."""

    code: ClassVar[int]
    name: ClassVar[str]

    @abstractmethod
    def params_array(self) -> NDArray[np.float64]:
        """Parameters in the order :func:`valve_step` reads them."""

    def initial_state(self, position: float) -> NDArray[np.float64]:
        """State of a valve at rest at ``position`` with OP equal to it."""
        if not math.isfinite(position):
            raise ValveModelError(f"initial valve position must be finite, got {position}")
        state = np.zeros(STATE_SIZE)
        state[POSITION] = state[LAST_INPUT] = state[STICK_POINT] = position
        state[STUCK] = 1.0
        return state

    def simulate(
        self, op: ArrayLike, *, dt: float = 1.0, initial_position: float | None = None
    ) -> NDArray[np.float64]:
        """Valve positions for a whole OP series.

        The valve starts at rest at ``initial_position`` (default: the first
        OP sample).

        Examples
        --------
        >>> HeValve(fs=3.0, fd=2.0).simulate([0.0, 2.0, 3.5, 4.0, 6.0]).tolist()
        [0.0, 0.0, 1.5, 1.5, 4.0]
        """
        series = np.ascontiguousarray(op, dtype=np.float64)
        if series.ndim != 1:
            raise ValveModelError(f"OP must be one-dimensional, got shape {series.shape}")
        if series.size == 0:
            return series.copy()
        bad = np.flatnonzero(~np.isfinite(series))
        if bad.size:
            raise ValveModelError(
                f"OP holds {bad.size} non-finite value(s), first at index {bad[0]}"
            )
        start = float(series[0]) if initial_position is None else float(initial_position)
        return valve_series(
            self.code, self.params_array(), self.initial_state(start), series, float(dt)
        )

    @property
    def stick_band(self) -> float:
        """OP travel needed to reverse a stuck valve (S of the (S, J) models), % of travel."""
        return 0.0

    def stepper(self, position: float, dt: float = 1.0) -> ValveStepper:
        """A :class:`ValveStepper` at rest at ``position``."""
        return ValveStepper(self, position, dt)

    def to_dict(self) -> dict[str, Any]:
        """JSON form, the inverse of :func:`valve_from_dict`."""
        return {"model": self.name, **asdict(self)}


@dataclass(frozen=True)
class IdealValve(ValveModel):
    """A healthy valve: MV = OP."""

    code: ClassVar[int] = IDEAL
    name: ClassVar[str] = "ideal"

    def params_array(self) -> NDArray[np.float64]:
        return np.zeros(1)


@dataclass(frozen=True)
class StenmanValve(ValveModel):
    """One-parameter stiction model of Stenman et al. [1] (thesis Eq. 1.1).

    Parameters
    ----------
    d : float
        Stiction band, % of travel.
    """

    d: float
    code: ClassVar[int] = STENMAN
    name: ClassVar[str] = "stenman"

    def __post_init__(self) -> None:
        _check_finite_nonnegative(d=self.d)

    @property
    def stick_band(self) -> float:
        return self.d

    def params_array(self) -> NDArray[np.float64]:
        return np.array([self.d], dtype=np.float64)


@dataclass(frozen=True)
class ChoudhuryValve(ValveModel):
    """Two-parameter stiction model of Choudhury et al. [2].

    Parameters
    ----------
    S : float
        Stick band plus deadband, % of travel.
    J : float
        Slip jump, % of travel (``0 <= J <= S``; ``J = 0`` is a pure deadband).
    """

    S: float
    J: float
    code: ClassVar[int] = CHOUDHURY
    name: ClassVar[str] = "choudhury"

    def __post_init__(self) -> None:
        _check_sj(self.S, self.J)

    @property
    def stick_band(self) -> float:
        return self.S

    def params_array(self) -> NDArray[np.float64]:
        return np.array([self.S, self.J], dtype=np.float64)


@dataclass(frozen=True)
class KanoValve(ChoudhuryValve):
    """Two-parameter stiction model of Kano et al. [3]: (S, J) with a fixed stop point."""

    code: ClassVar[int] = KANO
    name: ClassVar[str] = "kano"


@dataclass(frozen=True)
class HeValve(ValveModel):
    """Two-parameter stiction model of He et al. [4] (static and dynamic friction).

    Parameters
    ----------
    fs : float
        Static friction band, % of travel.
    fd : float
        Dynamic friction band, % of travel (``0 <= fd <= fs``).
    """

    fs: float
    fd: float
    code: ClassVar[int] = HE
    name: ClassVar[str] = "he"

    def __post_init__(self) -> None:
        _check_fsfd(self.fs, self.fd)

    @property
    def stick_band(self) -> float:
        return self.fs + self.fd

    def params_array(self) -> NDArray[np.float64]:
        return np.array([self.fs, self.fd], dtype=np.float64)

    @property
    def S(self) -> float:
        """Equivalent stick band plus deadband (thesis Eq. 1.2)."""
        return self.fs + self.fd

    @property
    def J(self) -> float:
        """Equivalent slip jump (thesis Eq. 1.2)."""
        return self.fs - self.fd


@dataclass(frozen=True)
class DeadbandValve(ValveModel):
    """Pure deadband (backlash): the valve lags OP by half the band, never jumps.

    It is He's model with ``fs = fd = deadband / 2`` (slip jump ``J = 0``).

    Parameters
    ----------
    deadband : float
        Full width of the band, % of travel.
    """

    deadband: float
    code: ClassVar[int] = HE
    name: ClassVar[str] = "deadband"

    def __post_init__(self) -> None:
        _check_finite_nonnegative(deadband=self.deadband)

    @property
    def stick_band(self) -> float:
        return self.deadband

    def params_array(self) -> NDArray[np.float64]:
        return np.array([self.deadband / 2.0, self.deadband / 2.0], dtype=np.float64)


@dataclass(frozen=True)
class KarnoppValve(ValveModel):
    """Physics-based valve: stem force balance with Karnopp friction [5].

    Forces are expressed as the equivalent stem travel of the spring, in % of
    travel, so that a frictionless valve settles at MV = OP.

    Parameters
    ----------
    fs_force : float
        Static (breakaway) friction.
    fc_force : float
        Coulomb (sliding) friction, ``<= fs_force``.
    fv : float
        Viscous friction, % per (%/s), i.e. seconds.
    natural_frequency : float
        Undamped natural frequency of stem and spring, rad/s.

    Notes
    -----
    A stuck valve breaks away once OP has moved ``fs_force + fc_force``
    against its last motion, which is the stick band S of the data-driven
    models; with light damping the stem then overshoots its Coulomb balance
    by up to ``2 (fs_force - fc_force)``, the slip jump J (Choudhury et al.
    [2], section 3).
    """

    fs_force: float
    fc_force: float
    fv: float = 0.0
    natural_frequency: float = 20.0
    code: ClassVar[int] = KARNOPP
    name: ClassVar[str] = "karnopp"

    def __post_init__(self) -> None:
        _check_finite_nonnegative(
            fs_force=self.fs_force,
            fc_force=self.fc_force,
            fv=self.fv,
            natural_frequency=self.natural_frequency,
        )
        if self.fc_force > self.fs_force:
            raise ValveModelError(
                f"Coulomb friction fc_force={self.fc_force} cannot exceed "
                f"static friction fs_force={self.fs_force}"
            )
        if self.natural_frequency == 0:
            raise ValveModelError("natural_frequency must be > 0 rad/s")

    @property
    def stick_band(self) -> float:
        return self.fs_force + self.fc_force

    def params_array(self) -> NDArray[np.float64]:
        return np.array(
            [self.fs_force, self.fc_force, self.fv, self.natural_frequency], dtype=np.float64
        )


VALVE_MODELS: dict[str, type[ValveModel]] = {
    cls.name: cls
    for cls in (
        IdealValve,
        StenmanValve,
        ChoudhuryValve,
        KanoValve,
        HeValve,
        DeadbandValve,
        KarnoppValve,
    )
}


def valve_from_dict(spec: dict[str, Any] | None) -> ValveModel:
    """Build a valve from its JSON form, e.g. ``{"model": "he", "fs": 3, "fd": 2}``.

    ``None`` gives an :class:`IdealValve` (a healthy valve).

    Examples
    --------
    >>> valve_from_dict({"model": "choudhury", "S": 4, "J": 2})
    ChoudhuryValve(S=4, J=2)
    """
    if spec is None:
        return IdealValve()
    if not isinstance(spec, dict) or "model" not in spec:
        raise ValveModelError(f"a valve needs a 'model' key, got {spec!r}")
    name = spec["model"]
    cls = VALVE_MODELS.get(name)
    if cls is None:
        raise ValveModelError(
            f"unknown valve model {name!r}; expected one of {sorted(VALVE_MODELS)}"
        )
    fields = {k: v for k, v in spec.items() if k != "model"}
    try:
        return cls(**fields)
    except TypeError as exc:
        raise ValveModelError(f"valve model {name!r}: {exc}") from None
