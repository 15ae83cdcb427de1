"""A base model identified from measured data, for a model check without a given model.

Valve and process come from the Hammerstein identification of the
loop-diagnosis work (:func:`analytics.quantification.quantify_stiction`):
He or Kano stiction ``(S, J)`` and a first-order process with dead time, or
an integrator.  It needs an oscillating loop; otherwise a healthy valve and
the first-order or integrating process whose replay of the measured OP fits
PV best (gain by least squares over a grid of time constants and delays) is
used.

The PI controller (its OP limits at least 0-100 % and wide enough for the
measured OP, which may be scaled otherwise) follows from the velocity form of
its law: with
``e = SP - PV``, ``OP_k - OP_{k-1} = Kc (e_k - e_{k-1}) + (Kc dt / Ti) e_k``
holds exactly at every sample where OP is not limited, so ``Kc`` and
``Kc / Ti`` are a least-squares fit, and an unknown constant setpoint is a
third coefficient (``Ki dt SP``).

References
----------
.. [1] Jelali (2008), J. Process Control 18:632-642, and thesis Appendix A
   (Hammerstein identification of stiction and process).
.. [2] Astrom & Hagglund (2006), *Advanced PID Control*, ISA, sec. 3.5
   (the velocity form of the PI algorithm).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from analytics.errors import DataError
from analytics.lti import FirstOrderProcess
from analytics.model_check.effects import ReplayData
from analytics.model_check.model import LoopModel, Valve
from analytics.quantification import quantify_stiction
from analytics.simulation import PIDController
from analytics.types import INTEGRATING, SELF_REGULATING, FloatArray
from analytics.valves import HeValve, KanoValve

__all__ = ["ControllerFit", "identify_controller", "identify_model"]


@dataclass(frozen=True)
class ControllerFit:
    """A PI controller fitted to measured OP, PV (and SP).

    Attributes
    ----------
    controller : PIDController
        A PI controller on ``e = SP - PV``, in the ideal form ``Kc``, ``Ti``.
    setpoint : float or None
        The constant setpoint fitted when none was measured.
    r2 : float
        Fraction of the variance of the OP increments the law explains.
    note : str
        Why the fit is doubtful (empty when it is not).
    """

    controller: PIDController
    setpoint: float | None
    r2: float
    note: str


def identify_controller(
    op: FloatArray, pv: FloatArray, ts: float, sp: FloatArray | None = None
) -> ControllerFit:
    """Fit ``Kc`` and ``Ti`` of a PI controller (and a constant SP when ``sp`` is None).

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> pv = 50 + rng.normal(0, 1, 300)
    >>> e = 52.0 - pv
    >>> op = 40 + 0.8 * e + 0.8 / 20 * np.cumsum(e)
    >>> fit = identify_controller(op, pv, 1.0)
    >>> gains = fit.controller.as_ideal()
    >>> round(gains.Kc, 3), round(gains.Ti, 2), round(fit.setpoint, 2)
    (0.8, 20.0, 52.0)
    """
    # OP held at a limit (its extreme values) does not follow the law
    free = (op[1:] > op.min()) & (op[1:] < op.max())
    d_op = np.diff(op)[free]
    if sp is None:
        columns = [-np.diff(pv), -ts * pv[1:], np.full(pv.size - 1, ts)]
    else:
        e = sp - pv
        columns = [np.diff(e), ts * e[1:]]
    design = np.column_stack(columns)[free]
    coef = np.linalg.lstsq(design, d_op, rcond=None)[0] if d_op.size > 3 else np.zeros(3)
    total = float(np.sum((d_op - d_op.mean()) ** 2)) if d_op.size else 0.0
    r2 = 1.0 - float(np.sum((d_op - design @ coef) ** 2)) / total if total > 0 else 0.0
    kc, ki = float(coef[0]), float(coef[1])
    setpoint = float(coef[2] / ki) if sp is None and ki != 0 else None
    note = ""
    if kc == 0.0 or ki * kc <= 0.0:
        note = "OP does not follow a PI law of PV (cascade, manual or feedforward?)"
        ki = 0.0
        kc = kc or 1e-3
        setpoint = float(np.mean(pv)) if sp is None else None
    elif r2 < 0.5:
        note = f"a PI law explains only {r2:.0%} of the OP moves"
    ti = kc / ki if ki != 0.0 else math.inf
    limits = (min(0.0, float(op.min())), max(100.0, float(op.max())))
    return ControllerFit(PIDController.ideal(kc, ti, op_limits=limits), setpoint, r2, note)


def _linear_process(
    op: FloatArray, pv: FloatArray, ts: float, op_bias: float, controller: PIDController
) -> LoopModel:
    """The healthy-valve FOPDT or integrating model (with ``controller``) whose OP replay
    fits PV best."""
    n = op.size
    longest = max(3, min(n // 20, 60))
    best: tuple[float, LoopModel] | None = None
    for kind in (SELF_REGULATING, INTEGRATING):
        horizon = max(20, n // 20) if kind == INTEGRATING else None
        data = ReplayData(
            op, pv, ts, warm_up=longest, folds=1, horizon=horizon, ramp=kind == INTEGRATING,
            held_out="none",
        )
        taus = np.geomspace(ts, max(2 * ts, n * ts / 10), 12)
        for tau in taus if kind == SELF_REGULATING else [0.0]:
            for delay in range(longest):
                trial = LoopModel(
                    ts, FirstOrderProcess(kind, 1.0, float(tau), delay * ts), controller,
                    Valve(HeValve(0.0, 0.0)), op_bias,
                )
                fit = data.predict(trial, fit_gain=True)
                if fit.scale != 0.0 and (best is None or fit.sse_fit < best[0]):
                    process = replace(trial.process, K=fit.scale)
                    best = (fit.sse_fit, replace(trial, process=process))
    if best is None:
        raise DataError("PV does not respond to OP: no process model can be identified")
    return best[1]


def identify_model(
    op: FloatArray, pv: FloatArray, ts: float, sp: FloatArray | None = None
) -> tuple[LoopModel, ControllerFit, tuple[str, ...]]:
    """Identify valve, process and controller of one loop from its data.

    Returns the model, the controller fit (with the constant setpoint when
    ``sp`` is None) and notes on how the model was found.
    """
    notes: list[str] = []
    op_bias = float(np.median(op))
    estimate = quantify_stiction(op, pv, ts)
    fit = identify_controller(op, pv, ts, sp)
    if estimate.S is not None and estimate.model is not None and estimate.search is not None:
        p = estimate.model
        valve = (
            HeValve(estimate.fs or 0.0, estimate.fd or 0.0)
            if estimate.search.valve_model == "he"
            else KanoValve(estimate.S, estimate.J or 0.0)
        )
        process = p if p.integrating else replace(p, tau=max(p.tau, ts / 100.0))
        model = LoopModel(ts, process, fit.controller, Valve(valve), op_bias)
        notes.append(
            f"valve and process identified by Hammerstein fit ({estimate.search.valve_model} "
            f"valve, output-error R2 {estimate.fit_r2:.2f})"
        )
    else:
        model = _linear_process(op, pv, ts, op_bias, fit.controller)
        notes.append(
            f"no stiction model could be identified ({'; '.join(estimate.issues)}): "
            "healthy valve, process fitted to the OP replay"
        )
    gains = fit.controller.as_ideal()
    notes.append(
        f"PI controller identified from the OP moves: Kc = {gains.Kc:.3g}, "
        f"Ti = {gains.Ti:.3g} s (R2 {fit.r2:.2f})"
        + (f"; {fit.note}" if fit.note else "")
    )
    return model, fit, tuple(notes)
