"""A fitted Hammerstein stiction model replayed on the measured OP.

:func:`analytics.quantification.quantify_stiction` fits a valve model and a
first-order process to a window; :func:`stiction_model_path` runs that valve
and process on the window's OP again, from a sample where the valve's state is
known, so that a plot can draw the model's MV and its predicted PV over the
measured signature (:func:`service.plots.signature_figure`).  A diagnosis keeps
the last periods of that path (:class:`ModelTrace`, :func:`model_trace`), which
the plot draws as stored.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from analytics.lti import TransferFunction, simulate_open_loop
from analytics.quantification import VALVE_MODELS, StictionEstimate
from analytics.serial import Reader
from analytics.signals import detrend
from analytics.types import FloatArray
from analytics.valves import ValveModel

__all__ = ["MODEL_CYCLES_KEPT", "MODEL_DECIMALS", "MODEL_LEAD_PERIODS", "MODEL_POINTS",
           "ModelTrace", "StictionModelPath", "model_trace", "stiction_model_path"]

MODEL_CYCLES_KEPT = 3
"""Periods of the replayed model a diagnosis keeps (the last ones): the signature plot
draws these, more would hide the samples."""

MODEL_LEAD_PERIODS = 4
"""Periods replayed before those kept (:func:`model_trace`): the model starts at an OP
maximum of the first three, so at least one period of lead-in precedes what is kept."""

MODEL_POINTS = 300
"""Samples kept of each of the trace's signals at most (every k-th beyond): a slow
cycle's three periods would otherwise store thousands of numbers with every run."""

MODEL_DECIMALS = 4
"""Decimals the trace keeps (0.0001 % of span: below a transmitter's resolution and the
two decimals of a pixel the plot writes), so a trace stores at most about 8 kB of JSON."""


@dataclass(frozen=True)
class ModelTrace:
    """The fitted model's path over the window's last :data:`MODEL_CYCLES_KEPT` periods,
    as a diagnosis keeps it (:meth:`StictionModelPath.trace`): the measured OP, the
    model's MV and predicted PV at the same samples (every k-th, at most
    :data:`MODEL_POINTS`, to :data:`MODEL_DECIMALS`), ``r2`` and ``label`` of the
    replay (over the last ``MODEL_CYCLES_KEPT + MODEL_LEAD_PERIODS`` periods)."""

    op: tuple[float, ...]
    mv: tuple[float, ...]
    pv: tuple[float, ...]
    r2: float
    label: str

    def to_dict(self) -> dict[str, Any]:
        """JSON form (the ``model_trace`` of a loop diagnosis)."""
        return {"op": list(self.op), "mv": list(self.mv), "pv": list(self.pv),
                "r2": self.r2, "label": self.label}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any], where: str = "model trace") -> ModelTrace:
        """The trace of :meth:`to_dict`'s form (``to_dict(from_dict(d)) == d``)."""
        read = Reader(d, where)
        return cls(tuple(read("op")), tuple(read("mv")), tuple(read("pv")), read("r2"),
                   read("label"))


@dataclass(frozen=True)
class StictionModelPath:
    """The fitted stiction model replayed on the measured OP (:func:`stiction_model_path`).

    Attributes
    ----------
    mv : ndarray
        Valve position of the model, per sample of OP (NaN before ``start``).
    pv : ndarray
        PV the model predicts (valve, then the identified process), with the
        offset and drift of the measured PV (NaN before ``start``).
    start : int
        The sample the model starts from: an OP maximum (see the function).
    period : int
        The oscillation period, samples.
    r2 : float
        ``1 - SSE / SST`` of the predicted against the measured PV from ``start`` on.
    label : str
        The model in words, e.g. ``kano valve, S = 4.01, J = 1.98``.
    """

    mv: FloatArray
    pv: FloatArray
    start: int
    period: int
    r2: float
    label: str

    def trace(self, op: FloatArray) -> ModelTrace:
        """The path over the last :data:`MODEL_CYCLES_KEPT` periods of the replayed ``op``."""
        kept = np.arange(max(self.start, op.size - MODEL_CYCLES_KEPT * self.period), op.size)
        kept = kept[::-(-kept.size // MODEL_POINTS)]
        op_kept, mv_kept, pv_kept = (tuple(np.round(x[kept], MODEL_DECIMALS).tolist())
                                     for x in (op, self.mv, self.pv))
        return ModelTrace(op_kept, mv_kept, pv_kept, self.r2, self.label)


def stiction_model_path(
    op: ArrayLike, pv: ArrayLike, ts: float, *, valve: ValveModel, process: TransferFunction,
    period_s: float, label: str,
) -> StictionModelPath:
    """Replay a Hammerstein stiction model (valve, then linear process) on the measured OP.

    The valve's state at the first sample is unknown, and with OP swinging
    barely more than the stick band (a limit cycle) a valve started in the
    wrong place never moves.  At a maximum of OP in a stiction cycle the state
    is known: the valve has followed OP up and rests on the trailing edge of
    its band.  So the model starts at the least pronounced OP maximum of the
    first three periods (as :func:`analytics.quantification.quantify_stiction`
    starts at a turning point), at rest after two lead-in steps of one stick
    band from below, and the first samples are left out.  The process is
    driven by the deviation of MV from its value there, from rest, and the
    offset and drift (a straight line in time, which the identification
    removes from PV as well) are fitted to the measured PV by least squares.

    Raises
    ------
    ValueError
        If ``op`` and ``pv`` differ in shape, are shorter than one period or
        hold non-finite samples, or ``period_s`` is not positive.
    """
    op_values = np.asarray(op, dtype=np.float64)
    pv_values = np.asarray(pv, dtype=np.float64)
    if op_values.shape != pv_values.shape or op_values.ndim != 1:
        raise ValueError(f"stiction_model_path: op and pv must be 1-D and equally long, got "
                         f"{op_values.shape} and {pv_values.shape}")
    if not (np.isfinite(op_values).all() and np.isfinite(pv_values).all()):
        raise ValueError("stiction_model_path: op and pv must be finite (the window has gaps)")
    if not (math.isfinite(period_s) and period_s > 0):
        raise ValueError(f"stiction_model_path: period_s must be positive, got {period_s}")
    period = max(1, round(period_s / ts))
    if op_values.size < period + 1:
        raise ValueError(f"stiction_model_path: {op_values.size} samples, fewer than one "
                         f"period of {period}")
    maxima = [k + int(np.argmax(op_values[k:k + period]))
              for k in range(0, min(3 * period, op_values.size - period + 1), period)]
    start = min(maxima, key=lambda k: op_values[k])
    lead_in = op_values[start] - valve.stick_band * np.array([2.0, 1.0])
    mv_run = valve.simulate(np.concatenate([lead_in, op_values[start:]]), dt=ts)[lead_in.size:]
    response = simulate_open_loop(process, mv_run - mv_run[0], ts)
    measured = pv_values[start:]
    predicted = measured - detrend(measured - response)  # offset and drift fitted
    spread = float(np.sum((measured - measured.mean()) ** 2))
    r2 = 1.0 - float(np.sum((measured - predicted) ** 2)) / spread if spread > 0 else math.nan
    mv, pv_model = np.full(op_values.size, np.nan), np.full(op_values.size, np.nan)
    mv[start:], pv_model[start:] = mv_run, predicted
    return StictionModelPath(mv=mv, pv=pv_model, start=start, period=period, r2=r2,
                             label=label)


def model_trace(op: FloatArray, pv: FloatArray, ts: float, estimate: StictionEstimate,
                period_s: float | None) -> ModelTrace | None:
    """The estimate's valve and process replayed on the end of the window
    (:func:`stiction_model_path`), its last :data:`MODEL_CYCLES_KEPT` periods kept; None
    without a size, process, valve model or period, or with gaps in OP or PV (the valve
    model cannot run through a missing OP).

    Only the last ``MODEL_CYCLES_KEPT + MODEL_LEAD_PERIODS`` periods are replayed (a whole
    10,000-sample window cost 48 ms, half the rest of the diagnosis)."""
    S, J, process = estimate.S, estimate.J or 0.0, estimate.model
    if S is None or process is None or estimate.valve_model is None or period_s is None:
        return None
    periods = MODEL_CYCLES_KEPT + MODEL_LEAD_PERIODS
    replayed = slice(max(0, op.size - periods * max(1, round(period_s / ts))), None)
    op, pv = op[replayed], pv[replayed]
    if not (np.isfinite(op).all() and np.isfinite(pv).all()):
        return None
    return stiction_model_path(
        op, pv, ts, valve=VALVE_MODELS[estimate.valve_model](S, J),
        process=process.transfer_function(), period_s=period_s,
        label=f"fitted {estimate.valve_model} valve, S = {S:.2f} %, J = {J:.2f} %",
    ).trace(op)
