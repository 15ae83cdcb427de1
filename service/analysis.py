"""The work one analysis worker does for one loop window or one unit.

:func:`analyse_window` and :func:`analyse_unit` run in a worker process
(local pool or Dask), so they take and return plain data: the loop's
configuration as a dict and the window's arrays; they return JSON-ready
diagnoses.  :func:`unit_windows` cuts a unit's windows from the rolling
buffers, for the scheduler and for the unit diagnosis route alike.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from analytics.diagnosis import LoopDiagnosis, diagnose_loop
from analytics.errors import ModelSpecError
from analytics.kpi import (
    LoopKpis,
    longest_normal_stretch,
    loop_health,
    loop_kpis,
    manual_samples,
)
from analytics.lti import TransferFunction, process_gain, simulate_open_loop
from analytics.plantwide import UnitModel, diagnose_unit
from analytics.simulation import PIDController
from analytics.types import FloatArray
from service.stored import ManualStretch, StoredDiagnosis

if TYPE_CHECKING:
    from service.buffer import LoopBuffers
    from service.config import LoopConfig, PlantConfig, UnitConfig

__all__ = [
    "MIN_FINITE_INPUT",
    "UnitWindows",
    "UnitWindowsError",
    "WindowAnalysis",
    "analyse_unit",
    "analyse_window",
    "dead_time_samples",
    "health_score",
    "independent_gain",
    "independent_gains",
    "manual_stretch",
    "sizing_pv",
    "stiction_pattern_text",
    "to_percent_of_span",
    "unit_model_spec",
    "unit_windows",
]


def to_percent_of_span(x: FloatArray | None, span: tuple[float, float] | None) -> FloatArray | None:
    """``100 (x - low) / (high - low)``; unchanged when no range is configured."""
    if x is None or span is None:
        return x
    low, high = span
    return np.asarray(100.0 * (x - low) / (high - low), dtype=np.float64)


STICTION_PATTERN_WORDS: dict[str, str] = {
    "limit_cycle": "limit cycle",
    "irregular_cycle": "irregular stick-slip cycle",
    "stick_jump": "stick-jump: the valve holds while OP ramps, then jumps; no sustained cycle",
    "stuck": "stuck: OP travels with no PV response",
}
"""How each stiction pattern of the diagnosis
(:data:`analytics.diagnosis.PATTERNS`) is named in alarm and ticket texts."""


def stiction_pattern_text(pattern: str | None, op_travel: float | None = None) -> str | None:
    """The stiction pattern in words (:data:`STICTION_PATTERN_WORDS`); None without one.

    A ``stuck`` valve with a known ``op_travel`` (% of span) says how far OP went.

    >>> stiction_pattern_text("stuck", 23.4)
    'stuck: OP travelled 23.4 % with no PV response'
    """
    if pattern is None:
        return None
    if pattern == "stuck" and op_travel is not None:
        return f"stuck: OP travelled {op_travel:.1f} % with no PV response"
    return STICTION_PATTERN_WORDS[pattern]


def health_score(diagnosis: StoredDiagnosis | Mapping[str, Any]) -> float | None:
    """Loop health from 0 (bad actor) to 100 (healthy) of a stored diagnosis
    (:func:`analytics.kpi.loop_health`); None when data are unusable.

    The stiction verdict scored is the final one on the valve (the diagnosis's
    ``valve``, :func:`service.verdicts.valve_verdict`) when it has one, else the
    loop's own.
    """
    stored = (diagnosis if isinstance(diagnosis, StoredDiagnosis)
              else StoredDiagnosis.from_dict(diagnosis))
    final, quality = stored.final, stored.analysis.quality
    return loop_health(
        usable=quality.usable, quality_warnings=len(quality.warnings()),
        oscillating=stored.oscillation.detected, regularity=stored.oscillation.regularity,
        stiction_confidence=final.confidence if final.verdict == "stiction" else None)


def dead_time_samples(loop: dict[str, Any], gain: dict[str, Any] | None = None) -> int | None:
    """The loop's dead time in samples for the Harris index, None when not configured.

    ``floor(theta / ts) + 1`` from the ``theta`` (s) of the loop's
    ``process_model``, else from the model its configured ``gain`` was taken
    from (:func:`independent_gain`: a unit loop's diagonal entry of the unit's
    matrix): the whole samples of the dead time plus the one of the
    zero-order hold (:func:`analytics.kpi.harris_index`).

    >>> dead_time_samples({"ts": 2.0, "process_model": {"theta": 5.0}})
    3
    >>> dead_time_samples({"ts": 2.0, "process_model": None}, {"dead_time_s": 4.0})
    3
    >>> dead_time_samples({"ts": 1.0, "process_model": None}) is None
    True
    """
    theta = (loop.get("process_model") or {}).get("theta")
    if theta is None and gain is not None:
        theta = gain.get("dead_time_s")
    if theta is None:
        return None
    return int(np.floor(float(theta) / float(loop["ts"]) + 1e-9)) + 1


def independent_gains(plant: PlantConfig) -> dict[str, dict[str, Any]]:
    """``loop id -> gain`` of the plant's loops whose configuration gives a process gain
    (:func:`independent_gain`)."""
    units = {unit.id: unit for unit in plant.units}
    gains = {}
    for loop in plant.loops:
        gain = independent_gain(loop, units.get(loop.unit) if loop.unit else None)
        if gain is not None:
            gains[loop.id] = gain
    return gains


def independent_gain(loop: LoopConfig, unit: UnitConfig | None) -> dict[str, Any] | None:
    """The loop's process gain as its configuration gives it, for sizing a sticky valve
    (:func:`analytics.quantification.quantify_with_gain`; issue 19); ``unit`` is the
    loop's unit.

    A limit cycle pins the PV step of a slip, ``K J``, better than the slip
    ``J``; a gain known from elsewhere fixes J.  It is

    * the gain of the loop's ``process_model`` (``G(0)``, or the ``K`` of an
      integrating model; :func:`analytics.lti.process_gain`): the process as
      the loop sees it in operation, as a step test of the loop gives it;
    * else, for a loop of a unit with a ``process`` matrix, the gain of the
      matrix's diagonal entry, from the loop's valve to its PV alone, with the
      row's other entries as ``couplings``: the unit's other valves move the
      loop's PV too (its neighbours answer each slip), and
      :func:`analyse_window` subtracts what their OPs do through these entries
      before it sizes the valve (``inputs``, their OP windows, which the
      scheduler adds; :func:`sizing_pv`).

    The signals are in % of span (as :func:`analyse_window` scales them), as
    the matrix and, by convention, the process model are.

    Returns
    -------
    dict or None
        ``K``, ``process_type`` (of the model), ``source`` (in words),
        ``couplings`` (``loop id -> matrix entry``; empty for a process model)
        and ``dead_time_s``, the model's dead time (:func:`dead_time_samples`);
        None when the configuration gives no gain, its model is not one with a
        gain, or its type contradicts the loop's ``process_type``.

    Examples
    --------
    >>> from service.config import PlantConfig
    >>> plant = PlantConfig.model_validate({"loops": [{
    ...     "id": "FIC-1", "tags": {"op": "O"}, "ts": 1.0,
    ...     "process_model": {"type": "fopdt", "K": 1.2, "tau": 8.0, "theta": 2.0}}]})
    >>> gain = independent_gains(plant)["FIC-1"]
    >>> gain["K"], gain["process_type"], gain["source"], gain["couplings"], gain["dead_time_s"]
    (1.2, 'self-regulating', "the loop's process_model", {}, 2.0)
    """
    couplings: dict[str, dict[str, Any]] = {}
    try:
        if loop.process_model is not None:
            model = TransferFunction.from_dict(loop.process_model)
            source = "the loop's process_model"
        elif unit is not None and unit.process is not None and loop.id in unit.process.loops:
            i = unit.process.loops.index(loop.id)
            row = unit.process.matrix[i]
            entry = row[i]
            if entry is None:
                return None
            model = TransferFunction.from_dict(entry)
            source = (f"unit {unit.id}'s process matrix (its valve's own entry; what the "
                      "unit's other valves do subtracted)")
            couplings = {other: coupling for other, coupling in zip(unit.process.loops, row,
                                                                  strict=True)
                         if other != loop.id and coupling is not None}
        else:
            return None
        kind, gain = process_gain(model)
    except (ModelSpecError, TypeError, ValueError):
        return None  # e.g. a process model that gives the dead time only
    if loop.process_type not in (None, kind):
        return None
    return {"K": gain, "process_type": kind, "source": source, "couplings": couplings,
            "dead_time_s": model.delay}


MIN_FINITE_INPUT = 0.99
"""Share of an input's samples that must be finite for :func:`sizing_pv` (a window cut
from the buffers may lack its last samples)."""


def sizing_pv(pv: FloatArray, ts: float, couplings: Mapping[str, Mapping[str, Any]],
              inputs: Mapping[str, FloatArray]) -> FloatArray | None:
    """PV less what the other inputs of ``couplings`` (``loop id -> transfer function``
    from that loop's valve to this PV, in % of span per % of OP span) do, driven by their
    OPs ``inputs`` (% of span, the window's samples, as long as ``pv``); None when an
    input is missing, of another length, or finite in less than
    :data:`MIN_FINITE_INPUT` of its samples (the others are interpolated, as the
    diagnosis fills its own signals' few gaps).

    Each input is taken as the valve position it commands (a healthy valve)
    and simulated from rest at its first sample; the offset that leaves is
    fitted away with the operating point.

    >>> pv = np.zeros(5)
    >>> sizing_pv(pv, 1.0, {"B": {"type": "fopdt", "K": 2.0, "tau": 1e-9}},
    ...           {"B": np.array([0.0, 1.0, 1.0, 1.0, 1.0])}).round(3).tolist()
    [0.0, 0.0, -2.0, -2.0, -2.0]
    """
    result = np.array(pv, dtype=np.float64)
    for other, entry in couplings.items():
        u = inputs.get(other)
        if u is None or u.shape != result.shape:
            return None
        finite = np.isfinite(u)
        if finite.mean() < MIN_FINITE_INPUT:
            return None
        if not finite.all():
            k = np.arange(u.size)
            u = np.interp(k, k[finite], u[finite])
        result -= simulate_open_loop(TransferFunction.from_dict(entry), u - u[0], ts)
    return result


def manual_stretch(diagnosis: LoopDiagnosis, manual: NDArray[np.bool_], t: FloatArray,
                   judged: slice, ts: float) -> tuple[LoopDiagnosis, ManualStretch]:
    """What a window with samples in manual was diagnosed on, for the pages and the alarms.

    The stretch (``share`` of the window in manual, the ``judged_from`` /
    ``judged_to`` times and ``judged_samples`` of the stretch in auto or
    cascade that was diagnosed, and a ``note``) and the diagnosis: when that
    stretch is too short to judge, with the note as its reason instead of
    calling the data unusable (a loop in manual is out of service, not a
    failed transmitter; ISA-18.2 suppresses its alarms by design).

    >>> from analytics.diagnosis import LoopDiagnosis, diagnose_loop
    >>> d = diagnose_loop(ts=1.0, op=np.full(3, 50.0), pv=np.full(3, 50.0))
    >>> d, m = manual_stretch(d, np.array([1, 1, 1, 0], dtype=bool), np.arange(4.0),
    ...                       slice(3, 4), 1.0)
    >>> m.share, m.judged_samples, d.stiction.reason
    (0.75, 1, 'in manual 75 % of the window: the 1 s in auto or cascade are too few to judge')
    """
    kept = t[judged]
    share = float(manual.mean())
    if kept.size and diagnosis.quality.usable:
        note = (f"in manual {100 * share:.0f} % of the window: diagnosed on its "
                f"{kept.size * ts / 60:.0f} min in auto or cascade")
    else:
        note = (f"in manual {100 * share:.0f} % of the window: the {kept.size * ts:.0f} s in "
                "auto or cascade are too few to judge")
        diagnosis = replace(diagnosis, stiction=replace(diagnosis.stiction, reason=note))
    stretch = ManualStretch(share, float(kept[0]) if kept.size else None,
                            float(kept[-1]) if kept.size else None, int(kept.size), note)
    return diagnosis, stretch


@dataclass(frozen=True)
class WindowAnalysis:
    """What :func:`analyse_window` finds in one window of one loop: a loop run's result.

    Attributes
    ----------
    diagnosis : LoopDiagnosis
        The pipeline's diagnosis of the window (of its stretch in auto or cascade).
    gain_source : str or None
        Where the process gain the valve was sized with came from (the configuration's
        words, :func:`independent_gain`); None when the gain was fitted.
    manual : ManualStretch or None
        The stretch diagnosed, when the window has samples in manual.
    first_sample_at : float or None
        Time of the diagnosed stretch's first sample (UNIX s): the stiction episodes'
        times count from it.
    kpis : LoopKpis
        The KPIs of the whole window.
    """

    diagnosis: LoopDiagnosis
    gain_source: str | None
    manual: ManualStretch | None
    first_sample_at: float | None
    kpis: LoopKpis

    def to_dict(self) -> dict[str, Any]:
        """The stored JSON (``AnalysisRun.result``, read back as
        :class:`~service.stored.StoredDiagnosis`): :meth:`LoopDiagnosis.to_dict` with the
        estimate's ``gain_source``, ``manual`` (when there is one), ``health``
        (:func:`health_score`), ``first_sample_at`` and ``kpis``."""
        diagnosis = self.diagnosis.to_dict()
        estimate = self.diagnosis.quantification
        sized = None if estimate is None else estimate.to_dict()
        if sized is not None and self.gain_source is not None:
            diagnosis |= {"quantification": {**sized, "gain_source": self.gain_source}}
        if self.manual is not None:
            diagnosis |= {"manual": self.manual.to_dict()}
        return {**diagnosis, "health": health_score(diagnosis),
                "first_sample_at": self.first_sample_at, "kpis": self.kpis.to_dict()}


def analyse_window(
    loop: dict[str, Any],
    ts: float,
    t: FloatArray,
    signals: dict[str, FloatArray | None],
    gain: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """Diagnose one window of one loop; signals are converted to % of span first.

    Parameters
    ----------
    loop : dict
        The loop's configuration (``LoopConfig.model_dump()``).
    ts, t : float, ndarray
        Sampling interval and sample times (s).
    signals : dict
        ``op``, ``pv``, ``sp``, ``mv`` arrays (NaN where missing) or None, and
        optionally ``mode``, the raw values of the loop's mode tag (its
        ``mode_map`` names them): the KPIs then give the service factor and
        leave the time in manual out of the controller's figures, and the
        diagnosis is made on the window's longest stretch in auto or cascade
        (:func:`analytics.kpi.longest_normal_stretch`; in manual OP is the
        operator's, not the controller's).
    gain : dict, optional
        The loop's process gain from its configuration (:func:`independent_gain`):
        a sticky valve is sized with it
        (:func:`analytics.quantification.quantify_with_gain`), and its
        ``process_type`` stands in for a loop that configures none.  The
        quantification then says where the gain came from (``gain_source``).
        With ``couplings``, ``inputs`` holds the coupled loops' OP windows (% of
        span) and the valve is sized on PV less what they do (:func:`sizing_pv`);
        without all of them it is sized with the gain fitted.

    Returns
    -------
    dict
        :meth:`WindowAnalysis.to_dict`: the diagnosis, and the KPIs
        (:func:`analytics.kpi.loop_kpis`) of the same window in % of span (the
        Harris index from the configured dead time, :func:`dead_time_samples`,
        else from the one the window's set-point steps or manual OP moves tell,
        :func:`analytics.kpi.identify_dead_time`; ``dead_time_note`` says which,
        or why none).  With samples in manual, ``manual`` (:func:`manual_stretch`)
        says which stretch was diagnosed.
    """
    ranges: dict[str, tuple[float, float]] = {
        k: (float(v[0]), float(v[1])) for k, v in (loop.get("ranges") or {}).items()
    }
    if "pv" in ranges:
        ranges.setdefault("sp", ranges["pv"])  # the set point is in PV units
    scaled = {name: to_percent_of_span(x, ranges.get(name)) for name, x in signals.items()
              if name != "mode"}
    mode = signals.get("mode")
    mode_mapping = None if loop.get("mode_map") is None else {
        float(raw): name for raw, name in loop["mode_map"].items()}
    manual = None if mode is None or mode_mapping is None else manual_samples(mode, mode_mapping)
    judged = longest_normal_stretch(manual) if manual is not None and manual.any() else slice(None)

    def cut(x: FloatArray | None) -> FloatArray | None:
        return None if x is None else x[judged]

    sizing = None
    pv_scaled = scaled.get("pv")
    if gain is not None and gain.get("couplings"):
        sizing = None if pv_scaled is None else sizing_pv(
            pv_scaled, ts, gain["couplings"], gain.get("inputs") or {})
        if sizing is None:
            gain = None  # the PV steps are not those of this valve alone
    process_type = loop.get("process_type") or (gain or {}).get("process_type")
    diagnosis = diagnose_loop(
        ts=ts, t=t[judged], op=cut(scaled.get("op")), pv=cut(pv_scaled),
        sp=cut(scaled.get("sp")), mv=cut(scaled.get("mv")), process_type=process_type,
        process_gain=None if gain is None else float(gain["K"]), sizing_pv=cut(sizing),
        ranges={name: (0.0, 100.0) for name in ranges},
    )
    estimate = diagnosis.quantification
    gain_source = gain["source"] if gain is not None and estimate is not None and (
        estimate.gain_given) else None
    stretch = None
    if manual is not None and manual.any():
        diagnosis, stretch = manual_stretch(diagnosis, manual, t, judged, ts)
    limits = loop.get("pv_limits")
    pv_limits = None
    if limits is not None:
        low, high = ranges.get("pv", (0.0, 100.0))
        pv_limits = (100.0 * (float(limits[0]) - low) / (high - low),
                     100.0 * (float(limits[1]) - low) / (high - low))
    cycle = diagnosis.oscillation  # None on unusable data
    kpis = loop_kpis(
        ts, op=scaled.get("op"), pv=scaled.get("pv"), sp=scaled.get("sp"),
        dead_time=dead_time_samples({**loop, "ts": ts}, gain), pv_limits=pv_limits,
        mode=mode, mode_mapping=mode_mapping,
        oscillation=None if cycle is None else {"detected": cycle.detected,
                                                "regularity": cycle.regularity},
    )
    first_sample_at = float(t[judged][0]) if t[judged].size else None
    return WindowAnalysis(diagnosis, gain_source, stretch, first_sample_at, kpis).to_dict()


class UnitWindowsError(ValueError):
    """The complete windows of a unit's loops cannot be diagnosed together."""


@dataclass(frozen=True)
class UnitWindows:
    """The latest OP and PV windows of a unit's loops, in % of span.

    Attributes
    ----------
    signals : dict
        ``loop id -> (OP, PV)`` for each loop whose window is complete (every
        point finite), as :func:`analytics.plantwide.diagnose_unit` takes them.
    intervals : dict
        ``loop id -> sampling interval`` of the same loops.
    incomplete : tuple of str
        The unit's loops left out: no OP or PV tag, a gap in the window, or
        no buffer in this process.
    """

    signals: dict[str, tuple[FloatArray, FloatArray]]
    intervals: dict[str, float]
    incomplete: tuple[str, ...]

    @property
    def ts(self) -> float:
        """The sampling interval the windows share.

        Raises
        ------
        UnitWindowsError
            They do not share one (or there is no window).
        """
        distinct = sorted(set(self.intervals.values()))
        if len(distinct) != 1:
            raise UnitWindowsError("a unit diagnosis needs one sampling interval for all "
                                   f"loops; the unit has {distinct}")
        return distinct[0]


def unit_windows(buffers: LoopBuffers, loops: Sequence[LoopConfig], window_s: float,
                 now: float) -> UnitWindows:
    """The windows ending at ``now`` of the unit made of ``loops`` (thesis chapter 2 needs
    the OP and PV of every loop over one common stretch of time)."""
    signals: dict[str, tuple[FloatArray, FloatArray]] = {}
    intervals: dict[str, float] = {}
    incomplete: list[str] = []
    for loop in loops:
        try:
            window = buffers.window(loop.id, window_s, now)
        except KeyError:  # a process that keeps no buffers (role api)
            incomplete.append(loop.id)
            continue
        op = to_percent_of_span(window.op, loop.ranges.get("op"))
        pv = to_percent_of_span(window.pv, loop.ranges.get("pv"))
        if op is None or pv is None or not (np.isfinite(op).all() and np.isfinite(pv).all()):
            incomplete.append(loop.id)
            continue
        signals[loop.id] = (op, pv)
        intervals[loop.id] = window.ts
    return UnitWindows(signals, intervals, tuple(incomplete))


def unit_model_spec(unit: UnitConfig | None, loops: Sequence[LoopConfig],
                    windows: UnitWindows) -> dict[str, Any] | None:
    """The unit's own model for its diagnosis, in plain (picklable) form: the plant file's
    ``process`` matrix and the configured controllers of its loops, in matrix order.

    None (the diagnosis then runs on the data alone) when the unit has no matrix, a
    loop of the matrix has no controller, or its window is incomplete.
    """
    if unit is None or unit.process is None:
        return None
    by_id = {loop.id: loop for loop in loops}
    controllers = []
    for loop_id in unit.process.loops:
        loop = by_id.get(loop_id)
        if loop is None or loop.controller is None or loop_id not in windows.signals:
            return None
        c = loop.controller
        controllers.append({"Kc": c.Kc, "Td": c.Td, "action": c.action,
                            **({"Ti": c.Ti} if c.type != "P" and c.Ti is not None else {})})
    return {"loops": list(unit.process.loops), "matrix": unit.process.matrix,
            "controllers": controllers}


def analyse_unit(signals: dict[str, tuple[FloatArray, FloatArray]], ts: float,
                 model: dict[str, Any] | None = None) -> dict[str, Any]:
    """Which valves of a unit stick (:func:`analytics.plantwide.diagnose_unit`, thesis
    chapters 2 and 3), JSON-ready; ``signals`` as in :class:`UnitWindows`, ``model`` as
    :func:`unit_model_spec` gives it (None: from the data alone)."""
    unit_model = None if model is None else UnitModel(
        tuple(model["loops"]),
        tuple(tuple(None if entry is None else TransferFunction.from_dict(entry)
                    for entry in row) for row in model["matrix"]),
        tuple(PIDController.from_dict(c) for c in model["controllers"]),
    )
    return diagnose_unit(signals, ts, model=unit_model).to_dict()
