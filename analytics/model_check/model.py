"""The loop model that the model check simulates, with the effects a base model can miss.

A :class:`LoopModel` is one control loop in the discrete-time convention of
issue 8, which is also that of :func:`analytics.simulation.simulate` for a
whole-sample dead time.  At sample ``k``::

    PV_k   = Q(pv_bias + x_k + load(t_k) + noise_k)            measured PV
    e_k    = SP_k - PV_k
    I_k    = I_{k-1} + (Kc dt / Ti) e_k,   I_0 = op_bias          (anti-windup by tracking)
    OP_k   = min(max(Kc e_k + I_k, 0), 100)
    MV_k   = valve(OP_k)                                          (at rest at op_bias)
    u_k    = flow(MV_k) - flow(op_bias)
    x_{k+1} = a x_k + (1 - a) K u_{k-d}                          FOPDT, a = exp(-dt / tau)
    x_{k+1} = x_k + dt K z_{k+1},  z_{k+1} = b z_k + (1 - b) u_{k-d}   integrating (lag b)

with ``d = round(theta / dt)``.  The base model has a linear valve
characteristic (``flow(MV) = MV``), no load and no quantiser ``Q``; the
extensions are

* a valve whose friction depends on the direction of travel (``opening`` /
  ``closing``) or on the position (``zone``: different friction inside a band
  of travel), stepped by the compiled kernel of :mod:`analytics.valves` with
  the parameters scheduled per sample;
* an installed flow characteristic ``flow(x) = (100 / c) (exp(c (x - op_bias) / 100) - 1)``,
  whose gain is 1 at ``op_bias`` and changes by the factor ``e^c`` over the
  whole travel (``c > 0``: equal-percentage-like, ``c < 0``: quick-opening);
* a periodic load ``A sin(2 pi t / P + phi)`` added to PV;
* a quantiser ``Q(y) = origin + q round((y - origin) / q)`` (PV resolution).

The model is also driven open loop by a measured OP (:meth:`LoopModel.replay`):
valve, characteristic and process give the PV deviation ``x`` that the check
compares with the measured PV.  :meth:`LoopModel.replay_frictions` does so for
many valve frictions at once (the friction searches of the check).

References
----------
.. [1] Thesis section 3.4.6: a mismatch between model and experiment may come
   from the two time-invariant stiction parameters "even for different
   locations of the stem" or from mismatched process dynamics.
.. [2] Thesis section 5.5.3 (a valve sticky only around 25 % of travel) and
   Fig. 5.14 (a valve sticking only when moving up).
.. [3] He, Wang, Pottmann & Qin (2007), Ind. Eng. Chem. Res. 46:4549-4560, and
   Choudhury, Thornhill & Shah (2005), Control Eng. Practice 13:641-658: the
   valve models whose parameters are scheduled here.
.. [4] ISA-75.11.01 (inherent flow characteristics of control valves): the
   equal-percentage characteristic is exponential in travel.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numba import njit
from numpy.typing import ArrayLike
from scipy.special import erfc

from analytics.errors import DataError, ModelSpecError, ValveModelError
from analytics.lti import FirstOrderProcess
from analytics.simulation import PIDController
from analytics.types import INTEGRATING, SELF_REGULATING, FloatArray, ProcessType
from analytics.valves import (
    HE,
    LAST_INPUT,
    POSITION,
    ChoudhuryValve,
    DeadbandValve,
    HeValve,
    IdealValve,
    KanoValve,
    ValveModel,
    band_step,
    he_update,
    valve_from_dict,
)

__all__ = [
    "PROCESS_JSON_TYPES",
    "LoopModel",
    "PeriodicLoad",
    "Quantiser",
    "SimulatedLoop",
    "StictionZone",
    "Valve",
    "controller_from_dict",
    "controller_to_dict",
    "friction_of",
    "friction_valve",
    "process_from_dict",
    "process_to_dict",
]

FrictionValve = HeValve | ChoudhuryValve | KanoValve


def _number(where: str, value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ModelSpecError(f"{where} must be a number, got {value!r}")
    number = float(value) if isinstance(value, float) or abs(value) < 2**1023 else math.inf
    if not math.isfinite(number):
        raise ModelSpecError(f"{where} must be finite, got {value}")
    return number


def _object(where: str, spec: Any, required: tuple[str, ...], optional: tuple[str, ...]) -> dict:
    """``spec`` as a dict with exactly the allowed keys (errors name ``where``)."""
    if not isinstance(spec, dict):
        raise ModelSpecError(f"{where} must be a JSON object, got {spec!r}")
    missing = [key for key in required if key not in spec]
    if missing:
        raise ModelSpecError(f"{where} lacks the key(s) {', '.join(map(repr, missing))}")
    unknown = sorted(set(spec) - set(required) - set(optional))
    if unknown:
        allowed = ", ".join(map(repr, required + optional))
        raise ModelSpecError(
            f"{where} has unknown key(s) {', '.join(map(repr, unknown))}; allowed: {allowed}"
        )
    return spec


# ----------------------------------------------------------------------------
# parts


PROCESS_JSON_TYPES: dict[ProcessType, str] = {SELF_REGULATING: "fopdt", INTEGRATING: "integrating"}
"""The process ``type`` of the model's JSON form for each process type (issue 8 names a
self-regulating process by its model, first order plus dead time)."""


def _check_process(kind: ProcessType, K: float, tau: float) -> None:
    """What the model check needs of a :class:`~analytics.lti.FirstOrderProcess` beyond
    its own checks: a gain and, for a self-regulating process, a lag."""
    if K == 0:
        raise ModelSpecError("process K must not be 0 (the valve would not act on PV)")
    if kind == SELF_REGULATING and not tau > 0:
        raise ModelSpecError(f"an FOPDT process needs tau > 0 s, got {tau}")


def process_from_dict(spec: Any) -> FirstOrderProcess:
    """The process of ``{"type": "fopdt", "K", "tau", "theta"}`` or
    ``{"type": "integrating", "K", "theta"[, "tau"]}`` (``tau``: a lag, s)."""
    json_type = spec.get("type") if isinstance(spec, dict) else None
    kind = next((k for k, name in PROCESS_JSON_TYPES.items() if name == json_type), None)
    if kind == SELF_REGULATING:
        spec = _object("process", spec, ("type", "K", "tau"), ("theta",))
    elif kind == INTEGRATING:
        spec = _object("process", spec, ("type", "K"), ("theta", "tau"))
    else:
        raise ModelSpecError(
            f"process 'type' must be 'fopdt' or 'integrating', got {spec!r}"
        )
    K = _number("process K", spec["K"])
    tau = _number("process tau", spec.get("tau", 0.0))
    theta = _number("process theta", spec.get("theta", 0.0))
    _check_process(kind, K, tau)
    return FirstOrderProcess(kind, K, tau, theta)


def process_to_dict(process: FirstOrderProcess) -> dict[str, Any]:
    """JSON form, the inverse of :func:`process_from_dict`."""
    out: dict[str, Any] = {"type": PROCESS_JSON_TYPES[process.kind], "K": process.K}
    if not process.integrating or process.tau > 0:
        out["tau"] = process.tau
    out["theta"] = process.theta
    return out


def _check_op_bias(op_bias: float, limits: tuple[float, float]) -> None:
    low, high = limits
    if not low <= op_bias <= high:
        raise ModelSpecError(f"op_bias={op_bias} lies outside the OP limits {limits}")


def controller_from_dict(spec: Any, op_bias: float = 50.0) -> PIDController:
    """The PI controller of ``{"type": "PI", "Kc", "Ti"[, "op_limits"]}`` (``Ti`` absent
    or null: P-only), its integrator starting from the loop's ``op_bias``.

    The law is ``OP = Kc (e + (1 / Ti) integral(e))`` with ``e = SP - PV``: a
    negative ``Kc`` is a direct-acting controller.  ``Kc`` and ``Ti`` are kept
    as read (:attr:`analytics.simulation.PIDController.ideal_form`), so
    :func:`controller_to_dict` writes them back bit for bit.

    Examples
    --------
    >>> c = controller_from_dict({"type": "PI", "Kc": 0.1, "Ti": 11.0})
    >>> c.kp / c.ki, controller_to_dict(c)  # Ti from the gains would be 1 ulp off
    (10.999999999999998, {'type': 'PI', 'Kc': 0.1, 'Ti': 11.0})
    """
    spec = _object("controller", spec, ("Kc",), ("type", "Ti", "op_limits"))
    if spec.get("type", "PI") not in ("PI", "P"):
        raise ModelSpecError(f"controller type must be 'PI', got {spec['type']!r}")
    ti = spec.get("Ti")
    limits = spec.get("op_limits", [0.0, 100.0])
    if not (isinstance(limits, list | tuple) and len(limits) == 2):
        raise ModelSpecError(f"controller op_limits must be [low, high], got {limits!r}")
    Kc = _number("controller Kc", spec["Kc"])
    Ti = math.inf if ti is None else _number("controller Ti", ti)
    op_limits = (_number("op_limits[0]", limits[0]), _number("op_limits[1]", limits[1]))
    if not Ti > 0:
        raise ModelSpecError(f"controller Ti must be > 0 s, got {Ti}")
    if not op_limits[0] < op_limits[1]:
        raise ModelSpecError(f"controller op_limits must have low < high, got {op_limits}")
    _check_op_bias(op_bias, op_limits)
    return PIDController.ideal(Kc, Ti, op_limits=op_limits, op_bias=op_bias)


def controller_to_dict(controller: PIDController) -> dict[str, Any]:
    """JSON form, the inverse of :func:`controller_from_dict`."""
    gains = controller.as_ideal()
    out: dict[str, Any] = {"type": "PI", "Kc": gains.Kc}
    if math.isfinite(gains.Ti):
        out["Ti"] = gains.Ti
    if controller.op_limits != (0.0, 100.0):
        out["op_limits"] = list(controller.op_limits)
    return out


def _check_pi(controller: PIDController) -> None:
    """What the model check simulates of a :class:`~analytics.simulation.PIDController`."""
    if controller.kd != 0 or controller.action != "reverse":
        raise ModelSpecError(
            "the model check simulates a PI controller on e = SP - PV (a negative Kc acts "
            f"directly): no derivative action, action 'reverse'; got kd={controller.kd}, "
            f"action {controller.action!r}"
        )


def friction_parameters(like: FrictionValve, S: ArrayLike, j: ArrayLike) -> FloatArray:
    """The two parameters of :func:`friction_valve` (He's ``fs, fd``; ``S, J`` of the
    band models) for arrays of ``S`` and ``j``, as the last axis of the result.

    Examples
    --------
    >>> friction_parameters(HeValve(1.0, 0.5), [4.0, 2.0], 0.5).tolist()
    [[3.0, 1.0], [1.5, 0.5]]
    """
    S_a = np.maximum(np.asarray(S, dtype=np.float64), 0.0)
    j_a = np.minimum(np.maximum(np.asarray(j, dtype=np.float64), 0.0), 1.0)
    out = np.empty((*np.broadcast_shapes(S_a.shape, j_a.shape), 2))
    if isinstance(like, HeValve):
        out[..., 0], out[..., 1] = 0.5 * S_a * (1.0 + j_a), 0.5 * S_a * (1.0 - j_a)
    else:
        out[..., 0], out[..., 1] = S_a, j_a * S_a
    return out


def friction_valve(like: FrictionValve, S: float, j: float) -> FrictionValve:
    """A valve of the same model as ``like`` with stick band ``S`` and ``J = j S``.

    He's ``(fs, fd)`` follow thesis Eq. 1.2: ``fs = S (1 + j) / 2``, ``fd = S (1 - j) / 2``.

    Examples
    --------
    >>> friction_valve(HeValve(1.0, 0.5), 4.0, 0.5)
    HeValve(fs=3.0, fd=1.0)
    """
    first, second = friction_parameters(like, S, j).tolist()
    return type(like)(first, second)


def friction_of(valve: FrictionValve) -> tuple[float, float]:
    """``(S, j)`` of a friction valve, ``j = J / S`` (0 without friction)."""
    S, J = (valve.S, valve.J)
    return float(S), float(J / S) if S > 0 else 0.0


@dataclass(frozen=True)
class StictionZone:
    """Friction inside a band of travel ``low <= MV <= high`` (the base friction outside)."""

    low: float
    high: float
    valve: FrictionValve

    def __post_init__(self) -> None:
        if not self.low < self.high:
            raise ModelSpecError(f"zone needs low < high, got {self.low} and {self.high}")


def _friction_fields(valve: FrictionValve) -> dict[str, float]:
    return {k: v for k, v in valve.to_dict().items() if k != "model"}


@dataclass(frozen=True)
class Valve:
    """The base valve model plus direction- or position-dependent friction and a characteristic.

    Attributes
    ----------
    base : HeValve, ChoudhuryValve or KanoValve
        Friction everywhere not overridden (``HeValve(0, 0)`` for a healthy valve).
    opening, closing : same model as ``base`` or None
        Friction while the valve moves up (opening) or down (closing).
    zone : StictionZone or None
        Friction inside a band of travel, in both directions.
    curvature : float
        ``c`` of the installed characteristic (0: linear), see the module docstring.
    """

    base: FrictionValve
    opening: FrictionValve | None = None
    closing: FrictionValve | None = None
    zone: StictionZone | None = None
    curvature: float = 0.0

    def __post_init__(self) -> None:
        for name in ("opening", "closing"):
            part = getattr(self, name)
            if part is not None and type(part) is not type(self.base):
                raise ModelSpecError(f"valve {name} must be a {self.base.name} valve like the base")
        if self.zone is not None and type(self.zone.valve) is not type(self.base):
            raise ModelSpecError(f"valve zone must be a {self.base.name} valve like the base")

    @classmethod
    def from_dict(cls, spec: Any) -> Valve:
        """Base valve JSON (:func:`analytics.valves.valve_from_dict`) plus optional
        ``opening``, ``closing``, ``zone`` and ``characteristic`` objects.

        The friction objects take the base model's parameters (``fs``, ``fd``
        for He; ``S``, ``J`` for Choudhury and Kano).  A healthy (null) or
        deadband base valve becomes the equivalent He valve.
        """
        if spec is None:
            return cls(HeValve(0.0, 0.0))
        if not isinstance(spec, dict):
            raise ModelSpecError(f"valve must be a JSON object or null, got {spec!r}")
        extras = ("opening", "closing", "zone", "characteristic")
        name = spec.get("model")
        if not isinstance(name, str):
            raise ModelSpecError(f"valve 'model' must name the valve model, got {name!r}")
        numbers = {
            k: _number(f"valve {k}", v) for k, v in spec.items() if k not in (*extras, "model")
        }
        try:
            base_model = valve_from_dict({"model": name, **numbers})
        except ValveModelError as exc:
            raise ModelSpecError(f"valve: {exc}") from None
        base = _as_friction(base_model)
        kind = type(base)
        fields = tuple(_friction_fields(base))

        def part(name: str, value: Any) -> FrictionValve:
            value = _object(f"valve {name}", value, fields, ())
            try:
                return kind(**{k: _number(f"valve {name} {k}", value[k]) for k in fields})
            except ValveModelError as exc:
                raise ModelSpecError(f"valve {name}: {exc}") from None

        opening = part("opening", spec["opening"]) if "opening" in spec else None
        closing = part("closing", spec["closing"]) if "closing" in spec else None
        zone = None
        if "zone" in spec:
            raw = _object("valve zone", spec["zone"], ("low", "high", *fields), ())
            zone_valve = part("zone", {k: raw[k] for k in fields})
            zone = StictionZone(
                _number("valve zone low", raw["low"]), _number("valve zone high", raw["high"]),
                zone_valve,
            )
        curvature = 0.0
        if "characteristic" in spec:
            raw = _object("valve characteristic", spec["characteristic"], ("type", "curvature"), ())
            if raw["type"] != "exponential":
                raise ModelSpecError(
                    f"valve characteristic type must be 'exponential', got {raw['type']!r}"
                )
            curvature = _number("valve characteristic curvature", raw["curvature"])
        return cls(base, opening, closing, zone, curvature)

    def to_dict(self) -> dict[str, Any]:
        """JSON form, the inverse of :meth:`from_dict`."""
        out: dict[str, Any] = self.base.to_dict()
        if self.opening is not None:
            out["opening"] = _friction_fields(self.opening)
        if self.closing is not None:
            out["closing"] = _friction_fields(self.closing)
        if self.zone is not None:
            out["zone"] = {
                "low": self.zone.low, "high": self.zone.high, **_friction_fields(self.zone.valve)
            }
        if self.curvature != 0.0:
            out["characteristic"] = {"type": "exponential", "curvature": self.curvature}
        return out

    def friction_table(
        self,
        *,
        opening: FloatArray | None = None,
        closing: FloatArray | None = None,
        zone: FloatArray | None = None,
    ) -> FloatArray:
        """Parameter rows for :func:`_scheduled_valve_step`: outside the zone opening,
        outside closing, inside opening, inside closing (shape (4, 2)).

        ``opening``, ``closing`` or ``zone`` (friction parameters, see
        :func:`friction_parameters`, of shape (2,) or (m, 2)) replace the valve's
        own, as :func:`dataclasses.replace` would; with m of them the result
        holds m tables (shape (m, 4, 2)), for a search over many frictions.
        """
        if opening is None:
            opening = (self.opening or self.base).params_array()
        if closing is None:
            closing = (self.closing or self.base).params_array()
        if zone is None and self.zone is not None:
            zone = self.zone.valve.params_array()
        rows = (opening, closing, *((opening, closing) if zone is None else (zone, zone)))
        table = np.empty((*np.broadcast_shapes(*(row.shape for row in rows))[:-1], 4, 2))
        for i, row in enumerate(rows):
            table[..., i, :] = row
        return table

    def zone_bounds(self) -> tuple[float, float]:
        """Band of travel of the zone friction (an empty band without a zone)."""
        return (self.zone.low, self.zone.high) if self.zone is not None else (math.inf, -math.inf)


def _as_friction(valve: ValveModel) -> FrictionValve:
    if isinstance(valve, IdealValve):
        return HeValve(0.0, 0.0)
    if isinstance(valve, DeadbandValve):
        return HeValve(valve.deadband / 2.0, valve.deadband / 2.0)
    if isinstance(valve, HeValve | ChoudhuryValve):  # KanoValve is a ChoudhuryValve
        return valve
    raise ModelSpecError(
        f"the model check supports he, choudhury, kano or deadband valves (or null), "
        f"not {valve.name!r}"
    )


@dataclass(frozen=True)
class PeriodicLoad:
    """An unmeasured periodic load ``amplitude sin(2 pi t / period + phase)`` on PV."""

    amplitude: float
    period: float
    phase: float

    def __post_init__(self) -> None:
        if not self.period > 0:
            raise ModelSpecError(f"load period must be > 0 s, got {self.period}")

    def series(self, t: FloatArray) -> FloatArray:
        """The load at times ``t`` (s)."""
        return np.asarray(
            self.amplitude * np.sin(2.0 * np.pi * t / self.period + self.phase), dtype=np.float64
        )


@dataclass(frozen=True)
class Quantiser:
    """Measured PV on a grid: ``origin + resolution round((pv + n - origin) / resolution)``.

    ``noise`` is the standard deviation of the white noise ``n`` ahead of the
    rounding; it decides how often a PV close to a cell edge is reported in
    the neighbouring cell.
    """

    resolution: float
    origin: float = 0.0
    noise: float = 0.0

    def __post_init__(self) -> None:
        if not self.resolution > 0:
            raise ModelSpecError(f"PV resolution must be > 0, got {self.resolution}")
        if not self.noise >= 0:
            raise ModelSpecError(f"measurement noise must be >= 0, got {self.noise}")

    def apply(self, pv: FloatArray) -> FloatArray:
        """``pv`` rounded to the grid."""
        q, o = self.resolution, self.origin
        return np.asarray(o + q * np.round((pv - o) / q), dtype=np.float64)

    def expected(self, pv: FloatArray) -> FloatArray:
        """Mean reported value ``E[Q(pv + n)]`` (the best prediction of the record).

        Cell ``m`` (value ``origin + m q``) is reported with probability
        ``Phi((m + 1/2) q - z) - Phi((m - 1/2) q - z)``, ``z = pv - origin``.

        Examples
        --------
        >>> grid = Quantiser(1.0, 0.0, noise=0.2)
        >>> grid.expected(np.array([0.5, 0.2, 3.0])).round(3).tolist()
        [0.5, 0.067, 3.0]
        """
        if self.noise == 0.0:
            return self.apply(pv)
        q, o = self.resolution, self.origin
        z = (pv - o) / q
        centre = np.round(z)
        reach = math.ceil(5.0 * self.noise / q) + 1
        scale = self.noise / q * math.sqrt(2.0)
        # E[round(z + n/q)] = centre + sum over edges above of P(cross up) - below of P(cross down)
        out = centre.copy()
        for m in range(reach):
            out += 0.5 * erfc((centre + m + 0.5 - z) / scale)
            out -= 0.5 * erfc((z - (centre - m - 0.5)) / scale)
        return np.asarray(o + q * out, dtype=np.float64)


@dataclass(frozen=True)
class SimulatedLoop:
    """Closed-loop signals of :meth:`LoopModel.simulate` (measured PV, as a historian has it)."""

    t: FloatArray
    sp: FloatArray
    op: FloatArray
    mv: FloatArray
    pv: FloatArray


# ----------------------------------------------------------------------------
# compiled kernels


@njit(cache=True, inline="always")
def _scheduled_valve_step(
    code: int,
    table: FloatArray,
    zone_low: float,
    zone_high: float,
    state: FloatArray,
    params: FloatArray,
    u: float,
) -> float:
    """One step of a valve whose parameters depend on direction and position.

    The direction is that of the move being tried: ``u - MV`` for He's model
    (the residual force), the OP slope for the (S, J) band models.  The row
    of ``table`` is chosen from it and from whether the valve sits inside the
    zone and copied into ``params`` (two values: He's fs, fd or the band
    models' S, J), and the step is that of :func:`analytics.valves.valve_step`
    for the model (its He or band-model branch, called directly: the generic
    dispatch costs several times the step itself).
    """
    position = state[POSITION]
    push = u - position if code == HE else u - state[LAST_INPUT]
    row = 1 if push < 0.0 else 0
    if zone_low <= position <= zone_high:
        row += 2
    if code == HE:
        y = he_update(table[row, 0], table[row, 1], position, u)
    else:  # Choudhury or Kano (friction valves only, see ``_as_friction``)
        params[0] = table[row, 0]
        params[1] = table[row, 1]
        y = band_step(params, state, u, code)
    state[POSITION] = y
    state[LAST_INPUT] = u
    return y


@njit(cache=True, inline="always")
def _flow(mv: float, curvature: float, reference: float) -> float:
    """Installed characteristic relative to the reference position (slope 1 there)."""
    if curvature == 0.0:
        return mv - reference
    return 100.0 / curvature * math.expm1(curvature * (mv - reference) / 100.0)


@njit(cache=True)
def _valve_positions(
    code: int, tables: FloatArray, bands: FloatArray, states: FloatArray, op: FloatArray
) -> FloatArray:
    """Positions of valves stepped through the OP samples ``op``, one row per friction
    table ``tables[i]``, zone ``bands[i] = (low, high)`` and state ``states[i]``.

    The valves are stepped together, sample by sample: each step of a valve
    waits for the one before, but the valves do not wait for each other.  A
    kernel of its own (:func:`_replay` calls it for the lead-in and for the
    record): two inlined valve steps in one compiled function make it several
    times slower.
    """
    mv = np.empty((tables.shape[0], op.size))
    params = np.empty(2)
    for k in range(op.size):
        for i in range(tables.shape[0]):
            mv[i, k] = _scheduled_valve_step(
                code, tables[i], bands[i, 0], bands[i, 1], states[i], params, op[k]
            )
    return mv


@njit(cache=True)
def _response(
    mv: FloatArray,
    dt: float,
    curvature: float,
    reference: float,
    delay: int,
    pole: float,
    K: float,
    integrating: bool,
) -> FloatArray:
    """PV deviation ``x`` for every row of valve positions ``mv``, through the
    characteristic and the process at rest at the first input (rows stepped
    together, as in :func:`_valve_positions`)."""
    m, n = mv.shape
    x = np.empty((m, n))
    lag = np.empty(m)
    level = np.empty(m)
    for i in range(m):
        lag[i] = _flow(mv[i, 0], curvature, reference)
        level[i] = 0.0 if integrating else K * lag[i]
    for k in range(n):
        d = max(k - delay, 0)
        for i in range(m):
            x[i, k] = level[i]
            ud = _flow(mv[i, d], curvature, reference)
            if integrating:
                lag[i] = pole * lag[i] + (1.0 - pole) * ud
                level[i] += dt * K * lag[i]
            else:
                level[i] = pole * level[i] + (1.0 - pole) * K * ud
    return x


@njit(cache=True)
def _replay(
    code: int,
    tables: FloatArray,
    bands: FloatArray,
    state: FloatArray,
    lead_in: FloatArray,
    op: FloatArray,
    dt: float,
    curvature: float,
    reference: float,
    delay: int,
    pole: float,
    K: float,
    integrating: bool,
) -> tuple[FloatArray, FloatArray]:
    """MV and the PV deviation ``x`` for a measured OP, one row per friction table
    ``tables[i]`` and zone ``bands[i]``.  Every valve starts from ``state`` and is
    stepped through ``lead_in`` first; the process starts at rest at the first input."""
    states = np.empty((tables.shape[0], state.size))
    for i in range(tables.shape[0]):
        states[i] = state
    _valve_positions(code, tables, bands, states, lead_in)
    mv = _valve_positions(code, tables, bands, states, op)
    return mv, _response(mv, dt, curvature, reference, delay, pole, K, integrating)


@njit(cache=True)
def _closed_loop(
    sp: FloatArray,
    load: FloatArray,
    noise: FloatArray,
    dt: float,
    kc: float,
    ki: float,
    op_low: float,
    op_high: float,
    op_bias: float,
    code: int,
    table: FloatArray,
    zone_low: float,
    zone_high: float,
    state: FloatArray,
    curvature: float,
    delay: int,
    pole: float,
    K: float,
    integrating: bool,
    pv_bias: float,
    resolution: float,
    origin: float,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """The loop of the module docstring, sample by sample (anti-windup as in
    :func:`analytics.simulation.simulate`)."""
    n = sp.shape[0]
    op = np.empty(n)
    mv = np.empty(n)
    pv = np.empty(n)
    u = np.zeros(n)
    level = 0.0
    lag = 0.0
    integral = op_bias
    params = np.empty(2)
    for k in range(n):
        y = pv_bias + level + load[k] + noise[k]
        if resolution > 0.0:
            y = origin + resolution * np.round((y - origin) / resolution)
        pv[k] = y
        err = sp[k] - y
        integral += ki * dt * err
        out = kc * err + integral
        if out > op_high:
            integral = min(integral, op_high - kc * err)
            out = op_high
        elif out < op_low:
            integral = max(integral, op_low - kc * err)
            out = op_low
        op[k] = out
        mv[k] = _scheduled_valve_step(code, table, zone_low, zone_high, state, params, out)
        u[k] = _flow(mv[k], curvature, op_bias)
        ud = u[k - delay] if k >= delay else 0.0
        if integrating:
            lag = pole * lag + (1.0 - pole) * ud
            level += dt * K * lag
        else:
            level = pole * level + (1.0 - pole) * K * ud
    return op, mv, pv


# ----------------------------------------------------------------------------
# the model


@dataclass(frozen=True)
class LoopModel:
    """One loop: process, PI controller, valve and the optional load and quantiser.

    The JSON form (:meth:`from_dict`, :meth:`to_dict`) is the base model of
    issue 8 plus the extensions::

        {"dt": 1.0, "op_bias": 50,
         "process": {"type": "fopdt", "K": 1.2, "tau": 20, "theta": 4},
         "controller": {"type": "PI", "Kc": 0.8, "Ti": 20},
         "valve": {"model": "he", "fs": 3, "fd": 1,
                   "opening": {"fs": 5, "fd": 2}, "closing": {"fs": 3, "fd": 1},
                   "zone": {"low": 20, "high": 30, "fs": 4, "fd": 1},
                   "characteristic": {"type": "exponential", "curvature": 2.5}},
         "pv_bias": 50,
         "load": {"kind": "sine", "amplitude": 0.5, "period": 120, "phase": 0.3},
         "measurement": {"resolution": 0.25, "origin": 0, "noise": 0.01}}

    ``pv_bias`` (the PV at rest with MV at ``op_bias``) is optional: the check
    estimates it from the data when it is absent.

    The controller is the package's :class:`~analytics.simulation.PIDController`
    as a PI controller on ``e = SP - PV`` (read and written by
    :func:`controller_from_dict`, :func:`controller_to_dict`).  The model has one
    operating point: the controller's ``op_bias`` is set to the loop's (valve at
    rest, process at zero deviation, integrator's start).
    """

    dt: float
    process: FirstOrderProcess
    controller: PIDController
    valve: Valve
    op_bias: float = 50.0
    pv_bias: float | None = None
    load: PeriodicLoad | None = None
    quantiser: Quantiser | None = None

    def __post_init__(self) -> None:
        if not (math.isfinite(self.dt) and self.dt > 0):
            raise ModelSpecError(f"dt must be > 0 s, got {self.dt}")
        _check_process(self.process.kind, self.process.K, self.process.tau)
        _check_op_bias(self.op_bias, self.controller.op_limits)
        _check_pi(self.controller)
        if self.controller.op_bias != self.op_bias:  # one operating point, the loop's
            object.__setattr__(self, "controller", replace(self.controller, op_bias=self.op_bias))

    @classmethod
    def from_dict(cls, spec: Any) -> LoopModel:
        """Parse and validate the JSON form; errors name the offending key."""
        spec = _object(
            "the model",
            spec,
            ("dt", "process", "controller"),
            ("valve", "op_bias", "pv_bias", "load", "measurement"),
        )
        load = None
        if "load" in spec and spec["load"] is not None:
            raw = _object("load", spec["load"], ("kind", "amplitude", "period"), ("phase",))
            if raw["kind"] != "sine":
                raise ModelSpecError(f"load kind must be 'sine', got {raw['kind']!r}")
            load = PeriodicLoad(
                _number("load amplitude", raw["amplitude"]),
                _number("load period", raw["period"]),
                _number("load phase", raw.get("phase", 0.0)),
            )
        quantiser = None
        if "measurement" in spec and spec["measurement"] is not None:
            raw = _object("measurement", spec["measurement"], ("resolution",), ("origin", "noise"))
            quantiser = Quantiser(
                _number("measurement resolution", raw["resolution"]),
                _number("measurement origin", raw.get("origin", 0.0)),
                _number("measurement noise", raw.get("noise", 0.0)),
            )
        pv_bias = spec.get("pv_bias")
        op_bias = _number("op_bias", spec.get("op_bias", 50.0))
        return cls(
            dt=_number("dt", spec["dt"]),
            process=process_from_dict(spec["process"]),
            controller=controller_from_dict(spec["controller"], op_bias),
            valve=Valve.from_dict(spec.get("valve")),
            op_bias=op_bias,
            pv_bias=None if pv_bias is None else _number("pv_bias", pv_bias),
            load=load,
            quantiser=quantiser,
        )

    def to_dict(self) -> dict[str, Any]:
        """JSON form, the inverse of :meth:`from_dict`."""
        out: dict[str, Any] = {
            "dt": self.dt,
            "process": process_to_dict(self.process),
            "controller": controller_to_dict(self.controller),
            "valve": self.valve.to_dict(),
            "op_bias": self.op_bias,
        }
        if self.pv_bias is not None:
            out["pv_bias"] = self.pv_bias
        if self.load is not None:
            load = self.load
            out["load"] = {
                "kind": "sine", "amplitude": load.amplitude, "period": load.period,
                "phase": load.phase,
            }
        if self.quantiser is not None:
            q = self.quantiser
            out["measurement"] = {"resolution": q.resolution, "origin": q.origin, "noise": q.noise}
        return out

    def with_dt(self, dt: float) -> LoopModel:
        """The same continuous-time model sampled every ``dt`` seconds."""
        return replace(self, dt=float(dt))

    def _valve_state(self, position: float) -> FloatArray:
        return self.valve.base.initial_state(position)

    def replay(
        self, op: ArrayLike, *, initial_position: float | None = None, lead_in: ArrayLike = ()
    ) -> tuple[FloatArray, FloatArray]:
        """Drive valve and process open loop with a measured OP series.

        Returns MV and the PV deviation ``x`` (PV less ``pv_bias``, without load
        and quantiser).  The valve starts at rest at ``initial_position``
        (default: the first OP sample) and is stepped through the OP samples
        ``lead_in`` before ``op`` (the way it arrived); the process starts at
        rest at the first MV (an integrator at 0).

        Examples
        --------
        A step of OP through a He valve (fs = 2, fd = 1) into a pure gain of 2:

        >>> model = LoopModel.from_dict({
        ...     "dt": 1, "process": {"type": "fopdt", "K": 2, "tau": 1e-9},
        ...     "controller": {"Kc": 1, "Ti": 10}, "valve": {"model": "he", "fs": 2, "fd": 1}})
        >>> mv, x = model.replay([50.0, 51.0, 53.0, 53.0])
        >>> mv.tolist(), x.tolist()
        ([50.0, 50.0, 52.0, 52.0], [0.0, 0.0, 0.0, 4.0])
        """
        series, before, state = self._replay_start(op, initial_position, lead_in)
        mv, x = _replay(
            self.valve.base.code,
            self.valve.friction_table()[None],
            np.array([self.valve.zone_bounds()]),
            state,
            before,
            series,
            *self._replay_process(series.size),
        )
        return mv[0], x[0]

    def replay_frictions(
        self,
        op: ArrayLike,
        tables: ArrayLike,
        bands: ArrayLike,
        *,
        initial_position: float | None = None,
        lead_in: ArrayLike = (),
    ) -> FloatArray:
        """The PV deviation ``x`` of :meth:`replay` for the model with other valve friction.

        Row ``i`` of the result has the friction table ``tables[i]`` (see
        :meth:`Valve.friction_table`) and the zone band ``bands[i] = (low, high)``:
        one compiled call for the frictions a search tries.
        """
        series, before, state = self._replay_start(op, initial_position, lead_in)
        return _replay(
            self.valve.base.code,
            np.ascontiguousarray(tables, dtype=np.float64),
            np.ascontiguousarray(bands, dtype=np.float64),
            state,
            before,
            series,
            *self._replay_process(series.size),
        )[1]

    def _replay_start(
        self, op: ArrayLike, initial_position: float | None, lead_in: ArrayLike
    ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """OP and lead-in of :meth:`replay` as checked arrays, and the valve's initial state."""
        series = np.ascontiguousarray(op, dtype=np.float64)
        before = np.ascontiguousarray(lead_in, dtype=np.float64)
        if series.ndim != 1 or series.size == 0 or before.ndim != 1:
            raise DataError(f"OP must be a non-empty 1-D series, got shape {series.shape}")
        start = before[0] if before.size else series[0]
        state = self._valve_state(float(start if initial_position is None else initial_position))
        return series, before, state

    def _replay_process(self, n: int) -> tuple[float, float, float, int, float, float, bool]:
        """Characteristic and process arguments of :func:`_replay` for ``n`` samples."""
        return (
            self.dt,
            self.valve.curvature,
            self.op_bias,
            min(self.process.delay_samples(self.dt), n),  # a longer one acts as n
            self.process.pole(self.dt),
            self.process.K,
            self.process.integrating,
        )

    def simulate(
        self,
        sp: ArrayLike,
        *,
        noise: ArrayLike | None = None,
        pv_bias: float | None = None,
    ) -> SimulatedLoop:
        """Closed-loop simulation from rest (PV at ``pv_bias``, valve at ``op_bias``).

        Parameters
        ----------
        sp : array_like
            Setpoint at every sample; its length sets the duration.
        noise : array_like, optional
            Measurement noise added to PV before the quantiser (the controller sees it).
        pv_bias : float, optional
            PV at rest; default the model's ``pv_bias``, else the first setpoint.
        """
        sp_a = np.ascontiguousarray(sp, dtype=np.float64)
        n = sp_a.size
        if sp_a.ndim != 1 or n == 0 or not np.all(np.isfinite(sp_a)):
            raise DataError("the setpoint must be a non-empty 1-D series of finite numbers")
        noise_a = np.zeros(n) if noise is None else np.ascontiguousarray(noise, dtype=np.float64)
        if noise_a.shape != sp_a.shape:
            raise DataError(f"noise has shape {noise_a.shape}, the setpoint {sp_a.shape}")
        bias = pv_bias if pv_bias is not None else self.pv_bias
        bias = float(sp_a[0]) if bias is None else float(bias)
        t = np.arange(n, dtype=np.float64) * self.dt
        load = self.load.series(t) if self.load is not None else np.zeros(n)
        low, high = self.valve.zone_bounds()
        q = self.quantiser
        op, mv, pv = _closed_loop(
            sp_a,
            load,
            noise_a,
            self.dt,
            self.controller.kp,
            self.controller.ki,
            self.controller.op_limits[0],
            self.controller.op_limits[1],
            self.op_bias,
            self.valve.base.code,
            self.valve.friction_table(),
            low,
            high,
            self._valve_state(self.op_bias),
            self.valve.curvature,
            min(self.process.delay_samples(self.dt), n),  # a longer one acts as n
            self.process.pole(self.dt),
            self.process.K,
            self.process.integrating,
            bias,
            q.resolution if q is not None else 0.0,
            q.origin if q is not None else 0.0,
        )
        return SimulatedLoop(t, sp_a, op, mv, pv)
