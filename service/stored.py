"""Typed views of the analysis results the store keeps as JSON.

A loop's run keeps its diagnosis in ``AnalysisRun.result``: the
:meth:`analytics.diagnosis.LoopDiagnosis.to_dict` form with what
:func:`service.analysis.analyse_window` adds (``health``, ``first_sample_at``,
``kpis``, ``manual``) and the final verdict on the valve
(``valve``, :func:`service.verdicts.settle_run`).  A unit's run keeps
:meth:`analytics.plantwide.UnitDiagnosis.to_dict` in ``UnitAnalysisRun.result``, which
the service reads with ``UnitDiagnosis.from_dict(..., lenient=True)``.

:meth:`analytics.diagnosis.LoopDiagnosis.from_dict` and
:meth:`analytics.plantwide.UnitDiagnosis.from_dict` rebuild the analytics objects
from that JSON, without what it does not keep (the Hammerstein search and fit
trace, the oscillation methods' results), and refuse a field that is missing.
Runs stored by older versions lack fields: :meth:`StoredDiagnosis.from_dict` reads
the analysis through ``LoopDiagnosis.from_dict(..., lenient=True)``, which reads a
missing field as its default (documented there), and the service's additions here.
The JSON itself is not changed.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from analytics.diagnosis import LoopDiagnosis
from analytics.kpi import LoopKpis
from analytics.oscillation import LoopOscillation
from analytics.stiction.battery import StictionVerdict

__all__ = [
    "GainFlags",
    "ManualStretch",
    "SizeWindow",
    "StoredDiagnosis",
    "StoredKpis",
    "StoredValve",
    "ValveSize",
]


def _section(d: Mapping[str, Any] | None, key: str) -> Mapping[str, Any]:
    """``d[key]`` when it is a mapping, else an empty one (absent or null)."""
    value = None if d is None else d.get(key)
    return value if isinstance(value, Mapping) else {}


def _float(value: Any) -> float | None:
    return None if value is None else float(value)


def _interval(value: Any) -> tuple[float, float] | None:
    return None if not value else (float(value[0]), float(value[1]))


@dataclass(frozen=True)
class GainFlags:
    """What a size window's J rests on: a process gain the configuration gives
    (``gain_given``, from ``gain_source``), or only the product ``K J``
    (``J_product_only``); windows stored before the flags read False / None."""

    gain_given: bool = False
    gain_source: str | None = None
    J_product_only: bool = False

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> GainFlags:
        return cls(bool(d.get("gain_given")), d.get("gain_source"),
                   bool(d.get("J_product_only")))


@dataclass(frozen=True)
class SizeWindow:
    """One window combined into the valve's size (``valve.size_windows[]``)."""

    window_start: float
    window_end: float
    S: float
    S_interval: tuple[float, float]
    J: float
    J_interval: tuple[float, float]
    gain_given: bool = False
    """J sized with a process gain the configuration gives (``gain_source`` says which)."""
    gain_source: str | None = None
    J_product_only: bool = False
    """J known only through the product ``K J``."""
    fit_r2: float | None = None
    """Output-error R^2 of the window's fit (its weight in the combination)."""

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> SizeWindow:
        """A stored window; one stored before the gain flags reads them as False / None,
        and one stored before its R^2 as None."""
        return cls(float(d["window_start"]), float(d["window_end"]), float(d["S"]),
                   (float(d["S_interval"][0]), float(d["S_interval"][1])), float(d["J"]),
                   (float(d["J_interval"][0]), float(d["J_interval"][1])),
                   bool(d.get("gain_given")), d.get("gain_source"),
                   bool(d.get("J_product_only")), _float(d.get("fit_r2")))

    @property
    def flags(self) -> GainFlags:
        """What the window's J rests on."""
        return GainFlags(self.gain_given, self.gain_source, self.J_product_only)

    def to_dict(self) -> dict[str, Any]:
        return {"window_start": self.window_start, "window_end": self.window_end,
                "S": self.S, "S_interval": list(self.S_interval),
                "J": self.J, "J_interval": list(self.J_interval),
                "gain_given": self.gain_given, "gain_source": self.gain_source,
                "J_product_only": self.J_product_only, "fit_r2": self.fit_r2}


@dataclass(frozen=True)
class StoredValve:
    """``valve``: the final verdict on the valve (:func:`service.verdicts.valve_verdict`)."""

    verdict: str | None = None
    confidence: float = 0.0
    reason: str = ""
    S: float | None = None
    J: float | None = None
    decided_by: str = "loop"
    own_verdict: str | None = None
    unit_id: str | None = None
    unit_run_id: int | None = None
    sticky_valves: tuple[str, ...] = ()
    S_interval: tuple[float, float] | None = None
    J_interval: tuple[float, float] | None = None
    windows_combined: int = 0
    """How many windows the size combines (``len(size_windows)``)."""

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> StoredValve:
        return cls(d.get("verdict"), float(d.get("confidence") or 0.0), str(d.get("reason", "")),
                   _float(d.get("S")), _float(d.get("J")), str(d.get("decided_by") or "loop"),
                   d.get("own_verdict"), d.get("unit_id"), d.get("unit_run_id"),
                   tuple(d.get("sticky_valves") or ()), _interval(d.get("S_interval")),
                   _interval(d.get("J_interval")), len(d.get("size_windows") or ()))

    @property
    def by_unit(self) -> bool:
        """Whether the unit's diagnosis decided it (not the loop's own)."""
        return self.decided_by == "unit"

    def decision_dict(self) -> dict[str, Any]:
        """The decision's part of the stored ``valve`` (without the combined size's
        ``S_interval``, ``J_interval`` and ``size_windows``, :class:`ValveSize`)."""
        return {"verdict": self.verdict, "confidence": self.confidence, "S": self.S,
                "J": self.J, "reason": self.reason, "decided_by": self.decided_by,
                "own_verdict": self.own_verdict, "unit_id": self.unit_id,
                "unit_run_id": self.unit_run_id, "sticky_valves": list(self.sticky_valves)}


@dataclass(frozen=True)
class ValveSize:
    """The valve's size combined over the windows of its streak of stiction verdicts
    (:func:`service.verdicts.valve_size`): the size part of the stored ``valve``."""

    S: float | None
    J: float | None
    S_interval: tuple[float, float] | None = None
    J_interval: tuple[float, float] | None = None
    size_windows: tuple[SizeWindow, ...] = ()
    J_note: str | None = None
    """What the combined J rests on (:func:`service.verdicts.j_note`)."""

    def to_dict(self) -> dict[str, Any]:
        return {"S": self.S, "J": self.J,
                "S_interval": None if self.S_interval is None else list(self.S_interval),
                "J_interval": None if self.J_interval is None else list(self.J_interval),
                "size_windows": [w.to_dict() for w in self.size_windows],
                "J_note": self.J_note}


@dataclass(frozen=True)
class ManualStretch:
    """``manual``: the stretch in auto or cascade a window with manual samples was
    diagnosed on (:func:`service.analysis.manual_stretch`)."""

    share: float
    judged_from: float | None
    judged_to: float | None
    judged_samples: int
    note: str

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> ManualStretch:
        return cls(float(d.get("share", 0.0)), _float(d.get("judged_from")),
                   _float(d.get("judged_to")), int(d.get("judged_samples", 0)),
                   str(d.get("note", "")))

    def to_dict(self) -> dict[str, Any]:
        return {"share": self.share, "judged_from": self.judged_from,
                "judged_to": self.judged_to, "judged_samples": self.judged_samples,
                "note": self.note}


@dataclass(frozen=True)
class StoredKpis:
    """The KPIs the service scores and reports (``kpis``,
    :meth:`analytics.kpi.LoopKpis.to_dict`); None where not computed."""

    oscillation_index: float | None = None
    harris_normalised: float | None = None
    harris_ratio: float | None = None
    saturation: float | None = None
    within_limits: float | None = None
    error_std: float | None = None
    service_factor: float | None = None
    travel_per_day: float | None = None
    reversals_per_day: float | None = None
    dead_time_note: str | None = None

    @classmethod
    def from_dict(cls, d: Mapping[str, Any] | None) -> StoredKpis:
        """The figures of stored KPIs (:meth:`analytics.kpi.LoopKpis.from_dict`, lenient)."""
        k = LoopKpis.from_dict(d, lenient=True)
        return cls(
            oscillation_index=k.oscillation_index,
            harris_normalised=None if k.harris is None else k.harris.normalised,
            harris_ratio=None if k.harris is None else k.harris.ratio,
            saturation=k.saturation,
            within_limits=None if k.error is None else k.error.within_limits,
            error_std=None if k.error is None else k.error.std,
            service_factor=None if k.service_factor is None else k.service_factor.normal,
            travel_per_day=k.travel_per_day, reversals_per_day=k.reversals_per_day,
            dead_time_note=k.dead_time_note if d else None,  # no KPIs: nothing to say
        )


@dataclass(frozen=True)
class StoredDiagnosis:
    """A loop run's stored diagnosis (``AnalysisRun.result``) as the service reads it: the
    analysis (:meth:`analytics.diagnosis.LoopDiagnosis.from_dict`, lenient) and what the
    service added to it."""

    analysis: LoopDiagnosis
    gain_source: str | None = None
    """``quantification.gain_source``: where a given process gain came from."""
    health: float | None = None
    first_sample_at: float | None = None
    kpis: StoredKpis = field(default_factory=StoredKpis)
    manual: ManualStretch | None = None
    valve: StoredValve | None = None

    @classmethod
    def from_dict(cls, d: Mapping[str, Any] | None) -> StoredDiagnosis:
        d = d or {}
        manual, valve = d.get("manual"), d.get("valve")
        return cls(
            analysis=LoopDiagnosis.from_dict(d, lenient=True),
            gain_source=_section(d, "quantification").get("gain_source"),
            health=d.get("health"), first_sample_at=d.get("first_sample_at"),
            kpis=StoredKpis.from_dict(d.get("kpis")),
            manual=None if manual is None else ManualStretch.from_dict(manual),
            valve=None if not valve else StoredValve.from_dict(valve),
        )

    @property
    def oscillation(self) -> LoopOscillation:
        """The analysis's oscillation (a lenient read always has one)."""
        assert self.analysis.oscillation is not None
        return self.analysis.oscillation

    @property
    def analysed_period(self) -> float | None:
        """The period the analysis used (also for an irregular cycle), else the detected
        one."""
        period = self.analysis.cycle_period_s or self.oscillation.period_s
        return None if period is None else float(period)

    @property
    def final(self) -> StoredValve | StictionVerdict:
        """The final verdict on the valve (``valve``) when settled, else the loop's own."""
        return self.valve if self.valve is not None else self.analysis.stiction

    @property
    def final_by_unit(self) -> bool:
        """Whether the final verdict is the unit's diagnosis's."""
        return self.valve is not None and self.valve.by_unit
