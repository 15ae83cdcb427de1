"""Linear time-invariant process models with dead time and their exact sampling.

A :class:`TransferFunction` is a proper rational transfer function in the
Laplace variable ``s`` times a pure delay ``exp(-delay * s)``.
:func:`discretise` turns it into an exact zero-order-hold (ZOH) state-space
recursion, including a dead time that is not a multiple of the sample time.
:class:`FirstOrderProcess` is the one first-order process with dead time
(self-regulating or integrating) of tuning, quantification and the model
check, with its transfer function, its sampled lag and the closed forms of
thesis chapter 5 (Eqs. 5.9-5.40).

References
----------
.. [1] G. F. Franklin, J. D. Powell and M. L. Workman, *Digital Control of
   Dynamic Systems*, 3rd ed., Addison-Wesley, 1998, ch. 4, "State-space models
   for systems with delay" (ZOH model with a fractional delay, equivalent to the
   modified z-transform).
.. [2] K. J. Astrom and B. Wittenmark, *Computer-Controlled Systems: Theory and
   Design*, 3rd ed., Prentice Hall, 1997, ch. 2, "Sampling a continuous-time
   state-space system", subsection on systems with time delay.
.. [3] C. F. Van Loan, "Computing integrals involving the matrix exponential",
   *IEEE Trans. Automatic Control* 23(3), 395-404, 1978.
.. [4] C. Moler and C. Van Loan, "Nineteen dubious ways to compute the exponential
   of a matrix, twenty-five years later", *SIAM Review* 45(1), 3-49, 2003,
   section 3 (Taylor series) and method 3 (scaling and squaring).
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.optimize
import scipy.signal
from numba import njit
from numpy.typing import ArrayLike, NDArray

from analytics.errors import ModelSpecError
from analytics.types import INTEGRATING, SELF_REGULATING, ComplexArray, FloatArray, ProcessType

#: Relative tolerance under which ``delay / dt`` is taken to be an integer.
_INTEGER_DELAY_RTOL = 1e-9

#: Parameters accepted by :meth:`TransferFunction.from_dict`, per model type:
#: (required keys, optional keys).
_MODEL_KEYS: dict[str, tuple[tuple[str, ...], tuple[str, ...]]] = {
    "fopdt": (("K", "tau"), ("theta",)),
    "integrating": (("K",), ("theta",)),
    "second_order": (("K", "tau1", "tau2"), ("theta",)),
    "underdamped": (("K", "wn", "zeta"), ("theta",)),
    "lead_lag": (("K", "tau_lead", "tau_lag1"), ("tau_lag2", "theta")),
}


def _coefficients(name: str, values: Sequence[float]) -> tuple[float, ...]:
    """Validate a polynomial coefficient vector and return it as a float tuple."""
    try:
        array = np.asarray(values, dtype=float)
    except (TypeError, ValueError) as exc:
        raise ModelSpecError(f"{name} must be a sequence of numbers: {exc}") from exc
    if array.ndim != 1 or array.size == 0:
        raise ModelSpecError(f"{name} must be a non-empty 1-D sequence, got shape {array.shape}")
    if not np.all(np.isfinite(array)):
        raise ModelSpecError(f"{name} contains non-finite coefficients: {array.tolist()}")
    return tuple(float(v) for v in array)


def _finite(name: str, value: float) -> float:
    if not math.isfinite(value):
        raise ModelSpecError(f"{name} must be finite, got {value}")
    return float(value)


def _positive(name: str, value: float) -> float:
    if not (math.isfinite(value) and value > 0.0):
        raise ModelSpecError(f"{name} must be finite and > 0, got {value}")
    return float(value)


def _non_negative(name: str, value: float) -> float:
    if not (math.isfinite(value) and value >= 0.0):
        raise ModelSpecError(f"{name} must be finite and >= 0, got {value}")
    return float(value)


def _s_multiplicity(coeffs: tuple[float, ...]) -> int:
    """Number of trailing zero coefficients, i.e. the multiplicity of the root s = 0."""
    return len(coeffs) - len(np.trim_zeros(np.asarray(coeffs), "b"))


@dataclass(frozen=True)
class TransferFunction:
    """Rational transfer function with dead time, ``G(s) = num(s)/den(s) exp(-delay s)``.

    Parameters
    ----------
    num, den : tuple of float
        Polynomial coefficients in descending powers of ``s``. Leading zeros of
        ``num`` are stripped (an all-zero numerator becomes ``(0.0,)``); the
        leading coefficient of ``den`` must be non-zero. The transfer function
        must be proper: ``deg num <= deg den``.
    delay : float, default 0.0
        Dead time ``theta`` in seconds, finite and ``>= 0``.

    Raises
    ------
    ModelSpecError
        If a coefficient is not finite, ``den`` is empty or has a zero leading
        coefficient, the transfer function is improper, or the delay is negative.
    """

    num: tuple[float, ...]
    den: tuple[float, ...]
    delay: float = 0.0

    def __post_init__(self) -> None:
        num = _coefficients("num", self.num)
        den = _coefficients("den", self.den)
        num = tuple(np.trim_zeros(np.asarray(num), "f").tolist()) or (0.0,)
        if den[0] == 0.0:
            raise ModelSpecError(f"den must have a non-zero leading coefficient, got {den}")
        if len(num) > len(den):
            raise ModelSpecError(
                f"improper transfer function: num degree {len(num) - 1} exceeds "
                f"den degree {len(den) - 1}"
            )
        try:
            delay = float(self.delay)
        except (TypeError, ValueError) as exc:
            raise ModelSpecError(f"delay (theta) must be a number: {exc}") from exc
        if not (math.isfinite(delay) and delay >= 0.0):
            raise ModelSpecError(f"delay (theta) must be finite and >= 0, got {self.delay}")
        object.__setattr__(self, "num", num)
        object.__setattr__(self, "den", den)
        object.__setattr__(self, "delay", delay)

    # ------------------------------------------------------------------ constructors
    @classmethod
    def fopdt(cls, K: float, tau: float, theta: float = 0.0) -> TransferFunction:
        """First order plus dead time, ``K exp(-theta s) / (tau s + 1)`` with ``tau > 0``
        (:class:`FirstOrderProcess`, self-regulating)."""
        process = FirstOrderProcess(SELF_REGULATING, _finite("K", K), _positive("tau", tau), theta)
        return process.transfer_function()

    @classmethod
    def integrating(cls, K: float, theta: float = 0.0) -> TransferFunction:
        """Integrating process with dead time, ``K exp(-theta s) / s``
        (:class:`FirstOrderProcess`, integrating without a lag)."""
        return FirstOrderProcess(INTEGRATING, _finite("K", K), 0.0, theta).transfer_function()

    @classmethod
    def second_order(
        cls, K: float, tau1: float, tau2: float, theta: float = 0.0
    ) -> TransferFunction:
        """Overdamped second order, ``K exp(-theta s) / ((tau1 s + 1)(tau2 s + 1))``.

        Both time constants must be ``> 0``.
        """
        t1, t2 = _positive("tau1", tau1), _positive("tau2", tau2)
        return cls((_finite("K", K),), (t1 * t2, t1 + t2, 1.0), theta)

    @classmethod
    def underdamped(cls, K: float, wn: float, zeta: float, theta: float = 0.0) -> TransferFunction:
        """Standard second order, ``K wn^2 exp(-theta s) / (s^2 + 2 zeta wn s + wn^2)``.

        Requires ``wn > 0`` and ``zeta >= 0`` (``zeta >= 1`` is accepted and gives
        real poles).
        """
        w, z = _positive("wn", wn), _non_negative("zeta", zeta)
        return cls((_finite("K", K) * w * w,), (1.0, 2.0 * z * w, w * w), theta)

    @classmethod
    def lead_lag(
        cls,
        K: float,
        tau_lead: float,
        tau_lag1: float,
        tau_lag2: float = 0.0,
        theta: float = 0.0,
    ) -> TransferFunction:
        """Lead-lag, ``K (tau_lead s + 1) exp(-theta s) / ((tau_lag1 s + 1)(tau_lag2 s + 1))``.

        ``tau_lag1 > 0``, ``tau_lag2 >= 0`` (0 drops the second lag) and
        ``tau_lead`` is any finite number (negative for an inverse response).
        Example: the distillation-column element
        ``g33 = 0.87 (11.61 s + 1) e^{-s} / ((3.89 s + 1)(18.8 s + 1))`` is
        ``lead_lag(0.87, 11.61, 3.89, 18.8, 1.0)``.
        """
        k, lead = _finite("K", K), _finite("tau_lead", tau_lead)
        t1, t2 = _positive("tau_lag1", tau_lag1), _non_negative("tau_lag2", tau_lag2)
        den = np.trim_zeros(np.polymul([t1, 1.0], [t2, 1.0]), "f")
        return cls((k * lead, k), tuple(den.tolist()), theta)

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> TransferFunction:
        """Build a model from a mapping, e.g. parsed JSON.

        Accepted forms: ``{"type": t, <parameters>}`` where ``t`` is one of
        ``fopdt``, ``integrating``, ``second_order``, ``underdamped``,
        ``lead_lag`` and the parameters are the keyword arguments of the
        constructor of that name (``theta`` and ``tau_lag2`` are optional,
        default 0); or ``{"num": [...], "den": [...], "theta": delay}`` with
        ``theta`` optional. Unknown keys are rejected.

        Raises
        ------
        ModelSpecError
            Unknown type, missing or unknown key, or invalid value; the message
            names the offending key.
        """
        if "type" in d:
            kind = d["type"]
            if not isinstance(kind, str) or kind not in _MODEL_KEYS:
                raise ModelSpecError(
                    f"unknown model type {kind!r}; expected one of {sorted(_MODEL_KEYS)}"
                )
            required, optional = _MODEL_KEYS[kind]
            allowed = {"type", *required, *optional}
        else:
            kind = None
            required, allowed = ("num", "den"), {"num", "den", "theta"}
        for key in required:
            if key not in d:
                raise ModelSpecError(f"missing key {key!r} for model type {kind or 'num/den'!r}")
        unknown = sorted(set(d) - allowed)
        if unknown:
            raise ModelSpecError(f"unknown key(s) {unknown} for model type {kind or 'num/den'!r}")
        if kind is None:
            return cls(d["num"], d["den"], d.get("theta", 0.0))
        params: dict[str, float] = {}
        for key in allowed - {"type"}:
            if key in d:
                try:
                    params[key] = float(d[key])
                except (TypeError, ValueError) as exc:
                    raise ModelSpecError(f"{key} must be a number, got {d[key]!r}") from exc
        constructor = getattr(cls, kind)
        result: TransferFunction = constructor(**params)
        return result

    def to_dict(self) -> dict[str, Any]:
        """Return ``{"num": [...], "den": [...], "theta": delay}`` (see :meth:`from_dict`)."""
        return {"num": list(self.num), "den": list(self.den), "theta": self.delay}

    # ------------------------------------------------------------------ analysis
    def frequency_response(self, omega: ArrayLike) -> NDArray[np.complex128]:
        """Complex ``G(j omega)`` including the dead time, for ``omega`` in rad/s.

        At ``omega = 0`` an integrating model gives a complex infinity/NaN
        (with a numpy division warning), like any pole on the imaginary axis.
        """
        s = 1j * np.asarray(omega, dtype=float)
        return np.asarray(
            np.polyval(self.num, s) / np.polyval(self.den, s) * np.exp(-self.delay * s),
            dtype=np.complex128,
        )

    @property
    def integrators(self) -> int:
        """Poles at ``s = 0`` net of zeros there (negative for a net zero at ``s = 0``)."""
        return _s_multiplicity(self.den) - _s_multiplicity(self.num)

    @property
    def is_integrating(self) -> bool:
        """True if ``G`` has a pole at ``s = 0`` once common factors of ``s`` are cancelled."""
        return any(self.num) and self.integrators > 0

    @property
    def dc_gain(self) -> float:
        """Steady-state gain ``G(0)``.

        Common factors of ``s`` are cancelled first. Integrating models return
        an infinity signed like their velocity gain (``+inf`` for ``K/s`` with
        ``K > 0``); models with a zero at ``s = 0`` return 0.
        """
        if not any(self.num):
            return 0.0
        n_num, n_den = _s_multiplicity(self.num), _s_multiplicity(self.den)
        ratio = self.num[-1 - n_num] / self.den[-1 - n_den]
        if n_den > n_num:
            return math.copysign(math.inf, ratio)
        return ratio if n_num == n_den else 0.0

    def poles(self) -> NDArray[np.complex128]:
        """Roots of ``den`` as given (no pole-zero cancellation)."""
        return np.asarray(np.roots(self.den), dtype=np.complex128)

    @property
    def is_stable(self) -> bool:
        """True if every pole has a strictly negative real part.

        Integrating models are therefore *not* asymptotically stable; see
        :attr:`is_integrating` to tell them apart from unstable ones.
        """
        return bool(np.all(self.poles().real < 0.0))


@dataclass(frozen=True)
class FirstOrderProcess:
    """A first-order process with dead time, self-regulating or integrating.

    ``K e^{-theta s} / (tau s + 1)`` (self-regulating, thesis Eq. 5.9) or
    ``K e^{-theta s} / (s (tau s + 1))`` (integrating; ``tau = 0`` is the
    ``K e^{-theta s} / s`` of thesis Eq. 5.31). The one process type of
    tuning (the closed forms of thesis chapter 5 below), stiction
    quantification (the identified linear part) and the model check (its
    sampled recursion, :meth:`delay_samples` and :meth:`pole`); simulation
    and compensation take its :meth:`transfer_function`.

    Attributes
    ----------
    kind : {"self-regulating", "integrating"}
    K : float
        Gain: PV units per % (self-regulating) or PV units per % per second
        (integrating).
    tau : float
        Time constant of the lag, s; 0: no lag.
    theta : float
        Dead time, s.

    Raises
    ------
    ModelSpecError
        Unknown kind, a parameter that is not a finite number, or a negative
        ``tau`` or ``theta``.
    """

    kind: ProcessType
    K: float
    tau: float
    theta: float

    def __post_init__(self) -> None:
        if self.kind not in (SELF_REGULATING, INTEGRATING):
            raise ModelSpecError(
                f"process type must be {SELF_REGULATING!r} or {INTEGRATING!r}, got {self.kind!r}"
            )
        for name in ("K", "tau", "theta"):
            value = getattr(self, name)
            if not (isinstance(value, numbers.Real) and math.isfinite(value)):
                raise ModelSpecError(f"process {name} must be a finite number, got {value!r}")
        if self.tau < 0 or self.theta < 0:
            raise ModelSpecError(
                f"process tau and theta must be >= 0 s, got tau={self.tau}, theta={self.theta}"
            )

    @property
    def integrating(self) -> bool:
        """True for an integrating process."""
        return self.kind == INTEGRATING

    @classmethod
    def of(cls, process: TransferFunction, *, hold_delay: float = 0.0) -> FirstOrderProcess:
        """Recognise the process classes of thesis chapter 5: ``K/(tau s + 1)`` with
        ``tau > 0`` or ``K/s``, with dead time; ``hold_delay`` is added to it.

        Raises
        ------
        ModelSpecError
            If ``process`` is neither (with dead time), or its gain is zero.

        Examples
        --------
        >>> FirstOrderProcess.of(TransferFunction.fopdt(0.4346, 27.58, 6.0), hold_delay=0.5)
        FirstOrderProcess(kind='self-regulating', K=0.4346, tau=27.58, theta=6.5)
        """
        num, den = process.num, process.den
        theta = process.delay + hold_delay
        if len(num) == 1 and num[0] != 0 and len(den) == 2:
            lead, constant = den
            if constant == 0:
                return cls(INTEGRATING, num[0] / lead, 0.0, theta)
            if lead / constant > 0:
                return cls(SELF_REGULATING, num[0] / constant, lead / constant, theta)
        raise ModelSpecError(
            "the chapter 5 analysis covers K e^-theta s/(tau s + 1) with tau > 0 and "
            f"K e^-theta s/s; got num={list(num)}, den={list(den)}"
        )

    def transfer_function(self) -> TransferFunction:
        """The process as a :class:`TransferFunction` (no lag for ``tau = 0``).

        Examples
        --------
        >>> FirstOrderProcess("integrating", 0.02, 3.0, 1.0).transfer_function()
        TransferFunction(num=(0.02,), den=(3.0, 1.0, 0.0), delay=1.0)
        """
        lag = (self.tau, 1.0) if self.tau > 0 else (1.0,)
        den = (*lag, 0.0) if self.integrating else lag
        return TransferFunction((self.K,), den, self.theta)

    # ------------------------------------------------------------------ sampled
    def delay_samples(self, dt: float) -> int:
        """The dead time in whole samples of ``dt``, ``d = round(theta / dt)``."""
        return round(self.theta / dt)

    def pole(self, dt: float) -> float:
        """The lag sampled every ``dt`` under a zero-order hold, ``exp(-dt / tau)``
        (0 without a lag; Astrom & Wittenmark 1997, ch. 2)."""
        return math.exp(-dt / self.tau) if self.tau > 0 else 0.0

    # ------------------------------------------------------------------ thesis ch. 5
    def open_loop_response(self, kc: float, ti: float, omega: ArrayLike) -> ComplexArray:
        """``G(jw) Gc(jw)`` in the closed forms of thesis chapter 5.

        Self-regulating: Eqs. 5.21-5.22 (5.12 without delay); integrating:
        Eq. 5.35 divided by ``Kc`` (the lag of ``tau > 0`` as for a
        self-regulating process); the controller ``Kc (1 - j/(tau_I w))``
        (Eq. 5.23; ``ti = inf`` for P control). Their products are Eqs. 5.13,
        5.15, 5.32, 5.34 and 5.36.
        """
        w = np.asarray(omega, dtype=np.float64)
        cos, sin = np.cos(self.theta * w), np.sin(self.theta * w)
        tw = self.tau * w
        real = self.K * (cos - tw * sin) / (1 + tw**2)
        imag = -self.K * (sin + tw * cos) / (1 + tw**2)
        if self.integrating:  # divided by j w
            real, imag = imag / w, -real / w
        controller = kc * (1 - 1j / (ti * w))
        return np.asarray((real + 1j * imag) * controller, dtype=np.complex128)

    def phase_lag(self, ti: float, omega: FloatArray) -> FloatArray:
        """``-arg G(jw) Gc(jw)``, continuous from ``w -> 0``.

        ``theta w + atan(tau w)``, plus ``pi/2`` for an integrating process and
        ``pi/2 - atan(tau_I w)`` with integral action: the ``beta``, ``alpha``
        of thesis Eqs. 5.29-5.30.
        """
        lag = self.theta * omega
        lag = lag + (np.pi / 2 if self.integrating else np.arctan(self.tau * omega))
        if self.integrating and self.tau > 0:
            lag = lag + np.arctan(self.tau * omega)
        if math.isfinite(ti):
            lag = lag + np.pi / 2 - np.arctan(ti * omega)
        return np.asarray(lag, dtype=np.float64)

    def crossing_frequencies(self, ti: float) -> tuple[float | None, float | None]:
        """``(w*, w**)``: first crossings of the imaginary and the real axis, rad/s.

        The roots of thesis Eqs. 5.18-5.19 (P), 5.27-5.28 (PI,
        self-regulating) and 5.39-5.40 (PI, integrating), as corrected in
        :mod:`analytics.tuning`: the first ``w > 0`` at which the phase lag
        passes ``pi/2 + k pi`` (F) or ``k pi`` (H). They do not depend on
        ``Kc``. None without dead time, where the curve never reaches the axis
        (thesis sections 5.3.1, 5.4.1).
        """
        if self.theta <= 0:
            return None, None
        scale = max(self.theta, self.tau, ti if math.isfinite(ti) else 0.0)
        grid = np.geomspace(1e-6 / scale, 4 * np.pi / self.theta, 4000)
        lag = self.phase_lag(ti, grid)

        def first(offset: float) -> float | None:
            level = np.floor((lag - offset) / np.pi)
            steps = np.flatnonzero(level[1:] != level[:-1])
            if steps.size == 0:
                return None
            k = int(steps[0])
            target = offset + np.pi * max(level[k], level[k + 1])
            return float(
                scipy.optimize.brentq(
                    lambda w: float(self.phase_lag(ti, np.array([w]))[0]) - target,
                    grid[k],
                    grid[k + 1],
                    xtol=1e-14,
                    rtol=1e-13,
                )
            )

        return first(np.pi / 2), first(0.0)

    def low_frequency_real(self, kc: float, ti: float) -> float:
        """``lim Re G Gc`` as ``w -> 0`` (thesis Tables 5.2-5.8); ``-inf`` for PI on
        an integrating process. Its modulus is the ``d`` of Eq. 5.24 and Fig. 5.9."""
        gain = self.K * kc
        if self.integrating:
            return -math.inf if math.isfinite(ti) else -gain * (self.theta + self.tau)
        return gain * (1 - (self.theta + self.tau) / ti)


@dataclass(frozen=True, eq=False)
class DiscreteEntry:
    """Exact ZOH sampling of a :class:`TransferFunction` at period ``dt``.

    With ``u_k`` the input held on ``[k dt, (k+1) dt)`` and the dead time
    ``theta = delay_samples * dt + eps`` (``0 <= eps < dt``)::

        x_{k+1} = Ad x_k + B0 u_{k-d} + B1 u_{k-d-1}
        y_k     = C x_k + D u_{k-d-1}

    where ``d = delay_samples``. ``y_k`` is the continuous output just before
    ``t_k = k dt``, ``y(t_k^-)``, so it never depends on ``u_k`` and can be
    sampled before the new input is applied. It equals ``y(t_k)`` whenever
    the output is continuous at ``t_k``, i.e. unless ``D != 0`` and
    ``eps == 0`` (then ``y(t_k)`` would jump to ``C x_k + D u_{k-d}``).

    Attributes
    ----------
    Ad : ndarray, shape (m, m)
    B0, B1 : ndarray, shape (m,)
        ``B1`` is identically zero when ``fractional`` is False.
    C : ndarray, shape (m,)
    D : float
    delay_samples : int
        Whole samples of dead time, ``d``.
    fractional : bool
        True if ``eps > 0``.
    dt : float
        Sample period in seconds.

    Notes
    -----
    ``m`` is the order of the :func:`scipy.signal.tf2ss` realisation; a pure gain
    (order 0) is realised with ``m = 1`` and ``Ad = 1``, ``B0 = B1 = C = 0``.
    The arrays are read-only.
    """

    Ad: FloatArray
    B0: FloatArray
    B1: FloatArray
    C: FloatArray
    D: float
    delay_samples: int
    fractional: bool
    dt: float

    def frequency_response(self, omega: ArrayLike) -> NDArray[np.complex128]:
        """Frequency response of the sampled model ``H(z)`` at ``z = exp(j omega dt)``.

        ``H(z) = z^{-d} (C (zI - Ad)^{-1} (B0 + B1 z^{-1}) + D z^{-1})``, the map
        from the sequence ``u_k`` to ``y_k``. At low frequency it approaches
        ``G(j omega) exp(-j omega dt / 2)``, the half-sample lag being that of
        the hold.
        """
        z = np.exp(1j * np.asarray(omega, dtype=float) * self.dt)
        flat = z.reshape(-1)
        m = self.Ad.shape[0]
        lhs = flat[:, None, None] * np.eye(m) - self.Ad
        rhs = (self.B0 + self.B1 / flat[:, None])[..., None]
        h = (self.C @ np.linalg.solve(lhs, rhs))[:, 0] + self.D / flat
        return np.asarray((h * flat ** (-self.delay_samples)).reshape(z.shape))


def _frozen(x: ArrayLike) -> FloatArray:
    """Contiguous read-only float64 copy of ``x``."""
    array = np.array(x, dtype=np.float64)
    array.setflags(write=False)
    return array


def _hold_matrices(a: FloatArray, b: FloatArray, h: float) -> tuple[FloatArray, FloatArray]:
    """Return ``exp(A h)`` and ``(integral_0^h exp(A s) ds) B`` from one block exponential.

    ``expm([[A, B], [0, 0]] h) = [[exp(A h), Gamma(h) B], [0, 1]]`` ([3]_), valid
    for singular ``A``.
    """
    m = a.shape[0]
    block = np.zeros((m + 1, m + 1))
    block[:m, :m] = a
    block[:m, m] = b
    expo = exact_expm(block * h)
    return expo[:m, :m], expo[:m, m]


_TAYLOR_TERMS = 20


@njit(cache=True)
def _matmul(left: FloatArray, right: FloatArray) -> FloatArray:
    """``left @ right`` summed in index order (no BLAS kernel, no fused multiply-add)."""
    rows, inner, cols = left.shape[0], left.shape[1], right.shape[1]
    out = np.zeros((rows, cols))
    for i in range(rows):
        for j in range(cols):
            acc = 0.0
            for k in range(inner):
                acc += left[i, k] * right[k, j]
            out[i, j] = acc
    return out


@njit(cache=True)
def exact_expm(a: FloatArray) -> FloatArray:
    """``exp(A)`` of a small matrix, identical to the last bit on every CPU.

    Scaling and squaring ([4]_): ``A`` is halved until its infinity norm is at most
    1/2 (exact: powers of two), the Taylor series is summed to 20 terms by Horner's
    rule (truncation below ``0.5**21 / 21!``, far under rounding) and squared back.
    Every product is an ordered scalar loop: :func:`scipy.linalg.expm` goes through
    BLAS, whose kernels (chosen per CPU) round differently, and a stick-slip
    simulation amplifies a last-bit difference in ``Ad`` into another trajectory.
    """
    m = a.shape[0]
    norm = 0.0
    for i in range(m):
        norm = max(norm, np.sum(np.abs(a[i])))
    squarings = 0
    scaled = a.copy()
    while norm > 0.5:
        scaled = scaled * 0.5
        norm *= 0.5
        squarings += 1
    expo = np.eye(m)
    for k in range(_TAYLOR_TERMS, 0, -1):
        expo = np.eye(m) + _matmul(scaled, expo) / k
    for _ in range(squarings):
        expo = _matmul(expo, expo)
    return expo


def discretise(tf: TransferFunction, dt: float) -> DiscreteEntry:
    """Exact zero-order-hold discretisation with integer plus fractional dead time.

    The dead time is split as ``theta = d dt + eps`` with ``0 <= eps < dt``; a
    ratio ``theta / dt`` within a relative ``1e-9`` of an integer counts as an
    integer (``eps = 0``). Over one sample the delayed input equals
    ``u_{k-d-1}`` for the first ``eps`` seconds and ``u_{k-d}`` afterwards, so
    for the realisation ``(A, B, C, D) = tf2ss(num, den)``::

        Ad = exp(A dt)
        B0 = (integral_0^{dt-eps} exp(A s) ds) B
        B1 = exp(A (dt-eps)) (integral_0^{eps} exp(A s) ds) B

    ([1]_ ch. 4, [2]_ ch. 2). No approximation is involved: the
    recursion reproduces the continuous response at the sampling instants for
    any piecewise-constant input. See :class:`DiscreteEntry` for the output
    equation.

    Parameters
    ----------
    tf : TransferFunction
    dt : float
        Sample period in seconds, finite and ``> 0``.

    Returns
    -------
    DiscreteEntry

    Raises
    ------
    ModelSpecError
        If ``dt`` is not finite and positive.
    """
    dt = _positive("dt", dt)
    ratio = tf.delay / dt
    if abs(ratio - round(ratio)) <= _INTEGER_DELAY_RTOL * max(1.0, ratio):
        d, eps = round(ratio), 0.0
    else:
        d = math.floor(ratio)
        eps = tf.delay - d * dt
    a, b, c, dd = scipy.signal.tf2ss(tf.num, tf.den)
    b_vec = b[:, 0].astype(float)
    ad, _ = _hold_matrices(a, b_vec, dt)
    phi_late, b0 = _hold_matrices(a, b_vec, dt - eps)
    b1 = _matmul(phi_late, _hold_matrices(a, b_vec, eps)[1][:, None])[:, 0]
    ad, b0, b1, c_vec = (_frozen(x) for x in (ad, b0, b1, c[0, :]))
    return DiscreteEntry(ad, b0, b1, c_vec, float(dd[0, 0]), d, eps > 0.0, dt)


def simulate_open_loop(tf: TransferFunction, u: ArrayLike, dt: float) -> FloatArray:
    """Reference simulation of ``tf`` driven by the ZOH input sequence ``u``.

    Runs the :class:`DiscreteEntry` recursion from a zero state with
    ``u_k = 0`` for ``k < 0``; ``y[k]`` is the output at ``t_k = k dt`` under
    the ``y(t_k^-)`` convention of :class:`DiscreteEntry`.

    Parameters
    ----------
    tf : TransferFunction
    u : array_like, shape (n,)
        Input held on ``[k dt, (k+1) dt)``.
    dt : float
        Sample period in seconds.

    Returns
    -------
    ndarray, shape (n,)
    """
    model = discretise(tf, dt)
    u_arr = np.asarray(u, dtype=float)
    if u_arr.ndim != 1:
        raise ModelSpecError(f"u must be 1-D, got shape {u_arr.shape}")
    # padded[k + 1] = u_{k-d}, padded[k] = u_{k-d-1}
    padded = np.concatenate([np.zeros(model.delay_samples + 1), u_arr])[: u_arr.size]
    # x_k = Ad x_{k-1} + B0 p_k + B1 p_{k-1} and y_k = C x_k + D p_k, from rest: the
    # transfer function C (zI - Ad)^-1 (B0 z + B1) + D, run by lfilter (a Python loop of
    # BLAS matrix-vector products cost ten times as much, on every core).
    n = model.Ad.shape[0]
    if n == 0:
        return np.asarray(model.D * padded, dtype=np.float64)
    c = model.C[None, :]
    num0, den = scipy.signal.ss2tf(model.Ad, model.B0[:, None], c, np.zeros((1, 1)))
    num1, _ = scipy.signal.ss2tf(model.Ad, model.B1[:, None], c, np.zeros((1, 1)))
    num = np.append(num0[0, 1:], 0.0) + num1[0] + model.D * den
    return np.asarray(scipy.signal.lfilter(num, den, padded), dtype=np.float64)


def process_gain(tf: TransferFunction) -> tuple[ProcessType, float]:
    """The gain of ``tf`` as stiction quantification takes it, with the process type.

    ``G(0)`` of a self-regulating model; ``lim s->0 s G(s)`` of a model with one
    integrator (PV units per % per second, the ``K`` of ``K / s``).

    Raises
    ------
    ModelSpecError
        Two or more integrators, a zero at ``s = 0``, or no gain.

    Examples
    --------
    >>> process_gain(TransferFunction.fopdt(1.2, 8.0, 2.0))
    ('self-regulating', 1.2)
    >>> process_gain(TransferFunction.integrating(0.02, 4.0))
    ('integrating', 0.02)
    """
    integrators = tf.integrators
    if integrators == 0:
        kind, gain = SELF_REGULATING, tf.dc_gain
    elif integrators == 1:
        kind, gain = INTEGRATING, TransferFunction((*tf.num, 0.0), tf.den).dc_gain
    else:
        raise ModelSpecError(f"a model with {integrators} integrators at s = 0 has no gain "
                             "that quantification can take")
    if not (math.isfinite(gain) and gain != 0.0):
        raise ModelSpecError(f"the model's gain is {gain}: a zero at s = 0, or no gain")
    return kind, gain
