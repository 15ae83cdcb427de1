"""Valve-repair tickets: stiction confirmed by repeated analyses goes to maintenance.

Opening.  The scheduler calls :func:`update_ticket_from_analysis` after each
analysis run is stored.  A ticket is opened when ``confirmations_needed``
runs on windows that do not overlap found stiction, and so did every run in
between: the loop's runs are read newest first, any run that is not ``ok``
with verdict ``stiction`` (a failed one included) ends the streak, and a run
counts as a confirmation only if its window ends before the window of the
last counted one starts.  Runs every minute on hour-long windows share most
of their data, so their verdicts are not independent: a healthy loop whose
analyses now and then find weak stiction must not get a ticket from two of
them a minute apart.  A new installation confirms from the history it finds
(:meth:`service.scheduling.rounds.RoundGrid.due_rounds`).  There
is at most one active ticket per valve asset: a further confirmation updates
the evidence of that ticket and records an ``evidence updated`` event instead
of opening another, but only when the valve's combined size has moved beyond
the interval the ticket holds (:func:`size_moved`) or the priority changes:
a sticky valve analysed every minute does not add an event every minute
(about 5,800 a day on the demo before, issue 19).  A ticket that is ``done``
or ``cancelled`` does not block a new one.  A verdict other than stiction
never closes a ticket: maintenance does that.  When ``confirmations_needed``
analyses of separate windows in a row find no stiction (for a loop of a unit,
also when the unit's diagnosis clears the valve), the active ticket gets one
``not confirmed`` event saying so, so that a planner checks the valve before
sending a crew; a later confirmation adds a ``confirmed again`` event.
Every stiction pattern of the diagnosis counts alike: a valve that sticks without a sustained cycle
(``stick_jump``, ``stuck``) gets a ticket too, whose long text names the
pattern and lists the stick-jump episodes.

Units.  In a unit of interacting loops one sticky valve makes its neighbours
cycle, and their own analyses then find stiction too (thesis chapter 2).  The
verdict the rule reads is the run's final one
(:func:`service.verdicts.valve_verdict`): for a loop of a unit, the unit's
latest ``ok`` diagnosis has the last word, so a valve it clears opens no
ticket, whatever the loop's own findings (they stay recorded in its analysis
runs).

Lifecycle (:data:`TICKET_TRANSITIONS`)::

    open -> acknowledged -> scheduled -> done
      \\___________\\______________\\____> cancelled

Every change is a :class:`~service.store.models.TicketEvent` with its actor.
Invalid transitions raise :class:`TicketStateError` (HTTP 409 at the API edge).

Priority, 1 (very high) .. 4 (low) as in SAP PM, see :func:`ticket_priority`.
CMMS fields, see :func:`service.cmms.to_cmms_notification`.  New and changed tickets are
notified by webhook and e-mail through the outbox (:mod:`service.notifications`).
"""

from __future__ import annotations

import logging
import math
from datetime import UTC, datetime
from typing import Any, Literal, get_args

from pydantic import BaseModel, ConfigDict, Field
from sqlalchemy import func, select
from sqlalchemy.orm import Session, selectinload

from analytics.diagnosis import PATTERNS
from analytics.valves import sj_to_fsfd
from service.analysis import stiction_pattern_text
from service.cmms import short_text, to_cmms_notification
from service.config import CmmsConfig, Importance
from service.store.models import AnalysisRun, Ticket, TicketEvent, UnitAnalysisRun
from service.stored import StoredDiagnosis, StoredValve

__all__ = [
    "ACTIVE_STATES",
    "ANALYSIS_ACTOR",
    "EPISODE_KEYS",
    "EVIDENCE_KEYS",
    "MAX_TICKET_EPISODES",
    "PLOT_KINDS",
    "TICKET_STATES",
    "TICKET_TRANSITIONS",
    "TicketEpisode",
    "TicketEvidence",
    "TicketNotFoundError",
    "TicketState",
    "TicketStateError",
    "change_ticket_state",
    "check_transition",
    "evidence_from_run",
    "get_ticket",
    "latest_loop_run",
    "latest_unit_run",
    "list_tickets",
    "run_episodes",
    "size_moved",
    "ticket_payload",
    "ticket_priority",
    "ticket_to_dict",
    "update_ticket_from_analysis",
]

logger = logging.getLogger(__name__)

TicketState = Literal["open", "acknowledged", "scheduled", "done", "cancelled"]
TICKET_STATES: tuple[TicketState, ...] = get_args(TicketState)
TICKET_TRANSITIONS: dict[str, tuple[TicketState, ...]] = {
    "open": ("acknowledged", "cancelled"),
    "acknowledged": ("scheduled", "cancelled"),
    "scheduled": ("done", "cancelled"),
    "done": (),
    "cancelled": (),
}
"""The states each state may move to."""
ACTIVE_STATES: tuple[TicketState, ...] = ("open", "acknowledged", "scheduled")
"""States in which a ticket blocks a new one for the same valve."""

ANALYSIS_ACTOR = "analysis"
"""Actor of the ticket changes made by the scheduler's analyses."""
PLOT_KINDS = ("trend", "signature", "spectrum")

EVIDENCE_KEYS: dict[str, bool] = {
    "run_id": True,
    "window_start": True,
    "window_end": True,
    "confidence": True,
    "S": False,
    "J": False,
    "period_s": False,
    "amplitude_op": False,
    "amplitude_pv": False,
    "pattern": False,
    "op_travel": False,
    "episode_stick_band": False,
    "episode_S": False,
    "size_check": False,
    "episodes": False,
    "S_interval": False,
    "J_interval": False,
    "size_windows": False,
}
"""Keys of the ``evidence`` argument; True for required, False for None-when-unknown.

``run_id``: the analysis run; ``window_start``/``window_end``: its window
(UNIX s); ``confidence``: of the stiction verdict (0..1); ``S``, ``J``:
stiction in % of valve span; ``period_s``: oscillation period;
``amplitude_op``, ``amplitude_pv``: oscillation amplitude (half peak-to-peak)
in % of span; ``pattern``: how the sticky valve shows, one of
:data:`analytics.diagnosis.PATTERNS`; ``op_travel``: OP travel over the window
(% of span); ``episode_stick_band``: the stick band read off the episodes (%
of span); ``episode_S``: S from OP's travel between its turns and the slips
(:mod:`analytics.stiction.episode_size`), the size estimate of a valve that sticks
without a cycle; ``size_check``: whether it agrees with the window's Hammerstein S;
``episodes``: the stick-jump episodes, a list of dicts with the keys
:data:`EPISODE_KEYS` (None or missing: none); ``S_interval``,
``J_interval``: ``[low, high]``, the 95 % intervals of S and J, which are the
valve's size combined over ``size_windows`` windows that do not overlap
(:func:`service.verdicts.valve_size`).  The stored evidence adds
``loop_id``, ``valve_asset``, ``fs``, ``fd`` (He's parameters, % of span),
``confirmations``, ``plots`` and ``episodes_found``, the number of episodes
the analysis found; it keeps only the latest :data:`MAX_TICKET_EPISODES` of
them.  Evidence stored before a key existed reads as None for it, ``[]`` for
``episodes`` and 0 for ``episodes_found`` (:func:`ticket_to_dict`).
"""

EPISODE_KEYS = ("start", "jump", "end", "op_travel", "pv_jump")
"""Keys of one stick-jump episode of the evidence: the valve holds from ``start``
until it slips at ``jump``, PV settles at ``end`` (UNIX s); ``op_travel`` is the
OP travel during the hold, ``pv_jump`` the PV jump (% of span)."""

MAX_TICKET_EPISODES = 20
"""Episodes a ticket keeps and lists (the latest ones): enough to show the pattern
without burying the long text of a valve that slips every minute."""

_NON_NUMERIC_KEYS = ("pattern", "episodes", "S_interval", "J_interval", "size_check")
_NO_CYCLE_PATTERNS = ("stick_jump", "stuck")


class TicketEpisode(BaseModel):
    """One stick-jump episode of a ticket's evidence (:data:`EPISODE_KEYS`).  The ticket
    routes answer with it: a field's docstring is its OpenAPI description."""

    model_config = ConfigDict(frozen=True, use_attribute_docstrings=True)

    start: float
    """The valve holds from here, UNIX s."""
    jump: float
    """It slips, UNIX s."""
    end: float
    """PV has settled, UNIX s."""
    op_travel: float
    """OP travel during the hold, % of span."""
    pv_jump: float
    """PV jump at the slip, % of span."""


class TicketEvidence(BaseModel):
    """A ticket's stored evidence (:func:`_checked_evidence`): the analysis that opened or
    last confirmed the ticket, and the valve's size, as the ticket rule, its long text and
    the ticket routes read it (fields in the stored order; a field's docstring is its
    OpenAPI description).  Keys stored before they existed read as their defaults; keys
    of other versions are kept."""

    model_config = ConfigDict(frozen=True, use_attribute_docstrings=True, extra="allow")

    loop_id: str = ""
    valve_asset: str = ""
    run_id: int
    """The analysis run (``GET /api/v1/runs/{id}``)."""
    window_start: float
    """Its window, UNIX s."""
    window_end: float
    confidence: float
    """Of the stiction verdict, 0..1."""
    S: float | None = None
    """Stiction, % of valve span: the valve's size combined over ``size_windows``
    windows."""
    J: float | None = None
    """Slip jump, % of valve span."""
    period_s: float | None = None
    """Oscillation period, s (null: no sustained cycle)."""
    amplitude_op: float | None = None
    """Oscillation amplitude (half peak-to-peak) of OP, % of span."""
    amplitude_pv: float | None = None
    """The same of PV."""
    pattern: str | None = None
    """How the sticky valve shows: ``limit_cycle``, ``irregular_cycle``, ``stick_jump`` or
    ``stuck`` (:data:`analytics.diagnosis.PATTERNS`)."""
    op_travel: float | None = None
    """OP travel over the window, % of span."""
    episode_stick_band: float | None = None
    """The stick band read off the episodes, % of span."""
    episode_S: float | None = None
    """S from OP's travel between its turns and the slips
    (:mod:`analytics.stiction.episode_size`)."""
    size_check: str | None = None
    """Whether ``episode_S`` agrees with the window's Hammerstein S."""
    episodes: tuple[TicketEpisode, ...] = ()
    """The latest stick-jump episodes (at most :data:`MAX_TICKET_EPISODES`)."""
    S_interval: tuple[float, float] | None = None
    """``[low, high]``, the 95 % interval of S."""
    J_interval: tuple[float, float] | None = None
    """``[low, high]``, the 95 % interval of J."""
    size_windows: int | None = None
    """Windows that do not overlap combined into S and J."""
    episodes_found: int = 0
    """Episodes the analysis found (``episodes`` keeps the latest)."""
    fs: float | None = None
    """He's static friction, % of span."""
    fd: float | None = None
    """He's dynamic friction, % of span."""
    confirmations: int = 0
    """Analysis runs on windows that do not overlap that found stiction when the evidence
    was stored: the plant's ``confirmations_needed`` at the time."""
    plots: dict[str, str] = Field(default_factory=dict)
    """The loop's plots by kind (trend, signature, spectrum): API paths."""


_DEFAULTS_OF_LATER_KEYS: dict[str, Any] = {
    "pattern": None, "op_travel": None, "episode_stick_band": None, "episode_S": None,
    "size_check": None, "episodes": [],
    "episodes_found": 0, "S_interval": None, "J_interval": None, "size_windows": None,
}
"""What stored evidence older than these keys reads as."""

RUNS_READ_PER_BATCH = 100
"""Runs fetched at a time while looking back for confirmations (one window of minute
rounds is 60 of them)."""

# Severity classes: 0 minor, 1 moderate, 2 severe.  Either a badly sticking
# valve or a large process cycle makes the repair urgent, so the larger class
# of the two counts.  Thresholds are class lower bounds in % of span.
_S_CLASSES = (2.0, 5.0)
_AMPLITUDE_PV_CLASSES = (1.0, 3.0)
_UNKNOWN_SEVERITY = 1
_PRIORITY: dict[str, tuple[int, int, int]] = {
    # severity: minor, moderate, severe
    "low": (4, 4, 3),
    "medium": (4, 3, 2),
    "high": (3, 2, 1),
    "critical": (2, 1, 1),
}


class TicketStateError(ValueError):
    """The state change is not allowed from the ticket's current state."""


class TicketNotFoundError(LookupError):
    """No ticket with that id."""


def _check_state(state: str) -> None:
    if state not in TICKET_STATES:
        raise ValueError(f"unknown ticket state {state!r} (expected {', '.join(TICKET_STATES)})")


def check_transition(from_state: str, to_state: str) -> None:
    """Raise :class:`TicketStateError` unless ``from_state -> to_state`` is allowed."""
    _check_state(to_state)
    allowed = TICKET_TRANSITIONS[from_state]
    if to_state not in allowed:
        raise TicketStateError(
            f"cannot move a ticket that is {from_state} to {to_state} "
            f"(possible: {', '.join(allowed) or 'none, the ticket is closed'})"
        )


def _severity_class(value: float, bounds: tuple[float, float]) -> int:
    return sum(value >= bound for bound in bounds)


def ticket_priority(*, S: float | None, amplitude_pv: float | None, importance: Importance) -> int:
    """Repair priority, 1 (very high) .. 4 (low), from severity and loop importance.

    Severity is the larger of the valve class (S < 2, 2..5, >= 5 % of span)
    and the process class (PV amplitude < 1, 1..3, >= 3 % of span): minor,
    moderate or severe.  Unknown values do not count; with neither known the
    severity is moderate (stiction was confirmed, its size is not).

    ==========  =====  ========  ======
    importance  minor  moderate  severe
    ==========  =====  ========  ======
    low         4      4         3
    medium      4      3         2
    high        3      2         1
    critical    2      1         1
    ==========  =====  ========  ======

    >>> ticket_priority(S=6.0, amplitude_pv=0.5, importance="high")
    1
    """
    if importance not in _PRIORITY:
        raise ValueError(
            f"unknown loop importance {importance!r} (expected {', '.join(_PRIORITY)})"
        )
    classes = []
    if S is not None:
        classes.append(_severity_class(S, _S_CLASSES))
    if amplitude_pv is not None:
        classes.append(_severity_class(amplitude_pv, _AMPLITUDE_PV_CLASSES))
    severity = max(classes) if classes else _UNKNOWN_SEVERITY
    return _PRIORITY[importance][severity]


def evidence_from_run(run: AnalysisRun) -> dict[str, Any]:
    """The ``evidence`` argument of :func:`update_ticket_from_analysis` from a stored run.

    Reads the run's columns, and from its ``result`` (the
    :meth:`analytics.diagnosis.LoopDiagnosis.to_dict` form as
    :func:`service.analysis.analyse_window` stores it) the oscillation
    amplitudes and the stiction pattern and episodes (:func:`run_episodes`).
    """
    diagnosis = StoredDiagnosis.from_dict(run.result)
    valve, analysis = diagnosis.valve or StoredValve(), diagnosis.analysis
    return {
        "run_id": run.id,
        "window_start": run.window_start,
        "window_end": run.window_end,
        "confidence": run.confidence,
        "S": run.S,
        "J": run.J,
        "period_s": run.period_s,
        "amplitude_op": diagnosis.oscillation.amplitude_op,
        "amplitude_pv": diagnosis.oscillation.amplitude_pv,
        "pattern": analysis.pattern,
        "op_travel": analysis.op_travel,
        "episode_stick_band": analysis.episode_stick_band,
        "episode_S": None if analysis.episode_size is None else analysis.episode_size.S,
        "size_check": None if analysis.size_comparison is None else analysis.size_comparison.note,
        "episodes": run_episodes(run),
        "S_interval": None if valve.S_interval is None else list(valve.S_interval),
        "J_interval": None if valve.J_interval is None else list(valve.J_interval),
        "size_windows": valve.windows_combined or None,
    }


def _is_finite_number(value: object) -> bool:
    return (isinstance(value, int | float) and not isinstance(value, bool)
            and math.isfinite(value))


def run_episodes(run: AnalysisRun) -> list[dict[str, float]]:
    """The stick-jump episodes of the run's diagnosis at UNIX times (:data:`EPISODE_KEYS`).

    The diagnosis counts their times in seconds from the window's first sample,
    ``first_sample_at`` of :func:`service.analysis.analyse_window`; a result
    without it counts from the window start.  A result without episodes (or
    older than them): ``[]``.
    """
    diagnosis = StoredDiagnosis.from_dict(run.result)
    origin = (_window(run)[0] if diagnosis.first_sample_at is None
              else diagnosis.first_sample_at)
    ts = diagnosis.analysis.ts
    return [
        {"start": origin + e.start * ts, "jump": origin + e.jump_at * ts,
         "end": origin + e.end * ts, "op_travel": e.op_travel, "pv_jump": e.pv_jump}
        for e in diagnosis.analysis.episodes
    ]


def _checked_episodes(where: str, episodes: object) -> list[dict[str, float]]:
    """The evidence's episodes, validated (:data:`EPISODE_KEYS`); None reads as none."""
    if episodes is None:
        return []
    if not isinstance(episodes, list):
        raise ValueError(f"{where}: 'episodes' must be a list, got {episodes!r}")
    for k, episode in enumerate(episodes):
        if not isinstance(episode, dict) or set(episode) != set(EPISODE_KEYS):
            raise ValueError(f"{where}: episode {k} must be a dict with the keys "
                             f"{', '.join(EPISODE_KEYS)}, got {episode!r}")
        bad = [key for key in EPISODE_KEYS if not _is_finite_number(episode[key])]
        if bad:
            raise ValueError(f"{where}: episode {k}: {', '.join(bad)} must be finite numbers, "
                             f"got {episode!r}")
        if not episode["start"] <= episode["jump"] <= episode["end"]:
            raise ValueError(f"{where}: episode {k} must hold, jump and settle in that order, "
                             f"got {episode!r}")
    return [{key: episode[key] for key in EPISODE_KEYS} for episode in episodes]


def _checked_evidence(
    loop_id: str, valve_asset: str, evidence: dict[str, Any], confirmations: int
) -> dict[str, Any]:
    """Validate the analysis evidence and complete it into the stored form."""
    where = f"evidence of loop {loop_id!r}"
    unknown = sorted(set(evidence) - set(EVIDENCE_KEYS))
    if unknown:
        raise ValueError(f"{where}: unknown keys {unknown} (expected {', '.join(EVIDENCE_KEYS)})")
    for key, required in EVIDENCE_KEYS.items():
        value = evidence.get(key)
        if value is None:
            if required:
                raise ValueError(f"{where}: {key!r} is required")
            continue
        if key not in _NON_NUMERIC_KEYS and not _is_finite_number(value):
            raise ValueError(f"{where}: {key!r} must be a finite number, got {value!r}")
    pattern = evidence.get("pattern")
    if pattern is not None and pattern not in PATTERNS:
        raise ValueError(f"{where}: 'pattern' must be one of {', '.join(PATTERNS)} or None, "
                         f"got {pattern!r}")
    size_check = evidence.get("size_check")
    if size_check is not None and not isinstance(size_check, str):
        raise ValueError(f"{where}: 'size_check' must be a sentence or None, got {size_check!r}")
    episodes = _checked_episodes(where, evidence.get("episodes"))
    for key in ("S_interval", "J_interval"):
        interval = evidence.get(key)
        if interval is not None and not (
                isinstance(interval, list | tuple) and len(interval) == 2
                and all(_is_finite_number(x) for x in interval)
                and evidence.get(key[0]) is not None
                and interval[0] <= evidence[key[0]] <= interval[1]):
            raise ValueError(f"{where}: {key!r} must be [low, high] around {key[0]}, "
                             f"got {interval!r}")
    S, J = evidence.get("S"), evidence.get("J")
    fs = fd = None
    if S is not None and J is not None:
        try:
            fs, fd = sj_to_fsfd(S, J)
        except ValueError as exc:
            raise ValueError(f"{where}: {exc}") from None
    return {
        "loop_id": loop_id,
        "valve_asset": valve_asset,
        **{key: evidence.get(key) for key in EVIDENCE_KEYS},
        **{key: list(evidence[key]) for key in ("S_interval", "J_interval")
           if evidence.get(key) is not None},
        "episodes": episodes[-MAX_TICKET_EPISODES:],
        "episodes_found": len(episodes),
        "fs": fs,
        "fd": fd,
        "confirmations": confirmations,
        "plots": {kind: f"/api/v1/loops/{loop_id}/plots/{kind}" for kind in PLOT_KINDS},
    }


def _confirming_runs(session: Session, loop_id: str, needed: int,
                     verdict: str = "stiction") -> list[AnalysisRun]:
    """Up to ``needed`` runs that found ``verdict`` on windows that do not overlap, newest
    first, from the loop's unbroken streak of such findings (module docstring)."""
    newest_first = (
        select(AnalysisRun)
        .where(AnalysisRun.loop_id == loop_id)
        .order_by(AnalysisRun.started_at.desc(), AnalysisRun.id.desc())
        .execution_options(yield_per=RUNS_READ_PER_BATCH)
    )
    confirmations: list[AnalysisRun] = []
    with session.scalars(newest_first) as runs:
        for run in runs:
            if run.status != "ok" or run.verdict != verdict:
                break
            if not confirmations or _window(run)[1] <= _window(confirmations[-1])[0]:
                confirmations.append(run)
                if len(confirmations) == needed:
                    break
    return confirmations


def _window(run: AnalysisRun) -> tuple[float, float]:
    """The run's window (start, end); a run without one stands for the instant it started."""
    start = run.started_at if run.window_start is None else run.window_start
    return start, run.started_at if run.window_end is None else run.window_end


def latest_loop_run(session: Session, loop_id: str) -> AnalysisRun | None:
    """The loop's newest analysis that ended ``ok``, or None."""
    return session.scalars(
        select(AnalysisRun).where(AnalysisRun.loop_id == loop_id, AnalysisRun.status == "ok")
        .order_by(AnalysisRun.id.desc()).limit(1)
    ).first()


def latest_unit_run(session: Session, unit_id: str, *, ok_only: bool = False
                    ) -> UnitAnalysisRun | None:
    """The unit's newest stored diagnosis (by window end), or its newest ``ok`` one."""
    query = select(UnitAnalysisRun).where(UnitAnalysisRun.unit_id == unit_id)
    if ok_only:
        query = query.where(UnitAnalysisRun.status == "ok")
    return session.scalars(
        query.order_by(UnitAnalysisRun.window_end.desc(), UnitAnalysisRun.id.desc()).limit(1)
    ).first()


def _utc(t: float) -> datetime:
    return datetime.fromtimestamp(t, UTC)


def _pct(value: float | None) -> str:
    return "not quantified" if value is None else f"{value:.2f} %"


def _utc_clock(t: float) -> str:
    return _utc(t).strftime("%Y-%m-%d %H:%M:%S")


def _describe_size(e: TicketEvidence) -> str:
    """The stiction size: Hammerstein S and J (with whether the episodes agree), else S
    from the episodes: OP's travel from its turns to the slips, else the holds' travel."""
    if e.S is None and e.episode_S is not None:
        return (f"Stiction: S about {e.episode_S:.2f} % of valve span (OP's travel from its "
                f"turns to the slips in the episodes), J = {_pct(e.J)}.")
    if e.S is None and e.episode_stick_band is not None:
        return (f"Stiction: S about {e.episode_stick_band:.2f} % of valve span (from the "
                f"episodes), J = {_pct(e.J)}.")
    check = "" if e.size_check is None else f" Latest window: {e.size_check}."
    size = (f"Stiction: S = {_pct(e.S)}, J = {_pct(e.J)} of valve span "
            f"(fs = {_pct(e.fs)}, fd = {_pct(e.fd)})")
    if e.S_interval is None or e.J_interval is None:
        return size + "." + check
    (s_lo, s_hi), (j_lo, j_hi) = e.S_interval, e.J_interval
    return (f"{size}, combined over {e.size_windows} windows that do not overlap; "
            f"intervals S {s_lo:.2f} to {s_hi:.2f} %, J {j_lo:.2f} to {j_hi:.2f} % (nominal "
            "95 %; on simulated valves they hold the true size in about 5 cases of 6)."
            + check)


def size_moved(old: dict[str, Any], new: dict[str, Any]) -> bool:
    """Whether the valve's size in evidence ``new`` lies beyond the uncertainty of the
    size in ``old``: S or J outside the interval stored, or, where ``old`` has none, a
    different value (evidence stored before the intervals: one update adopts them).

    >>> old = {"S": 4.0, "J": 2.0, "S_interval": [3.8, 4.2], "J_interval": [1.7, 2.3]}
    >>> size_moved(old, {"S": 4.1, "J": 1.8}), size_moved(old, {"S": 4.5, "J": 2.0})
    (False, True)
    """
    for key in ("S", "J"):
        interval, value = old.get(f"{key}_interval"), new.get(key)
        if interval is None:
            if value != old.get(key):
                return True
        elif value is None or not interval[0] <= value <= interval[1]:
            return True
    return False


def _describe_episodes(e: TicketEvidence) -> list[str]:
    """A heading and one line per episode (each fits a SAP long-text line); none without."""
    episodes = e.episodes
    if not episodes:
        return []
    shown = (f"{len(episodes)}" if len(episodes) == e.episodes_found
             else f"the latest {len(episodes)} of {e.episodes_found}")
    return [
        f"Stick-jump episodes ({shown}; times UTC): the valve held from the start until it "
        "jumped, PV settled at the end; OP travel while it held and PV jump in % of span.",
        *(f"Episode {k}: hold {_utc_clock(x.start)}, jump {_utc_clock(x.jump)}, settled "
          f"{_utc_clock(x.end)}; OP travel {x.op_travel:.2f} %, PV jump "
          f"{x.pv_jump:.2f} %."
          for k, x in enumerate(episodes, 1)),
    ]


def _describe(e: TicketEvidence) -> str:
    """The ticket's long text, one paragraph per line."""
    period = "unknown" if e.period_s is None else f"{e.period_s:.1f} s"
    window = " to ".join(
        _utc(t).isoformat(timespec="seconds") for t in (e.window_start, e.window_end)
    )
    pattern = stiction_pattern_text(e.pattern, e.op_travel)
    oscillation = (
        "Oscillation: none sustained." if e.pattern in _NO_CYCLE_PATTERNS
        else f"Oscillation: period {period}, amplitude OP {_pct(e.amplitude_op)}, "
             f"PV {_pct(e.amplitude_pv)} of span."
    )
    return "\n".join([
        f"Valve stiction confirmed by {e.confirmations} analyses of separate windows of "
        f"loop {e.loop_id} (valve {e.valve_asset}).",
        *([] if pattern is None else [f"Pattern: {pattern}."]),
        _describe_size(e),
        oscillation,
        *_describe_episodes(e),
        f"Confidence {e.confidence:.2f}; analysis run {e.run_id}, window {window}.",
        "Plots: " + ", ".join(f"{kind} {url}" for kind, url in e.plots.items()),
    ])


def update_ticket_from_analysis(
    session: Session,
    loop_id: str,
    *,
    valve_asset: str | None,
    location: str | None,
    verdict: str,
    evidence: dict[str, Any],
    importance: Importance,
    confirmations_needed: int,
    now: float,
) -> Ticket | None:
    """Open or update the valve's ticket after an analysis; the ticket, or None if untouched.

    Call it after the analysis run is stored.  ``evidence`` has the keys of
    :data:`EVIDENCE_KEYS` (:func:`evidence_from_run` builds it).  A loop
    without a valve asset is ticketed under its loop id.  ``verdict`` is the run's
    final one (a unit's diagnosis may have cleared the valve, see the module
    docstring).  The ticket's
    ``malfunction_start`` is the window start of the oldest confirming run.
    Calling twice for the same run changes nothing the second time.  The
    priority (:func:`ticket_priority`) takes the stick band read off the
    episodes for S when the Hammerstein fit did not size the valve (a valve
    that sticks without a cycle).
    """
    if confirmations_needed < 1:
        raise ValueError(f"confirmations_needed must be at least 1, got {confirmations_needed}")
    if verdict == "no_stiction":
        return _note_not_confirmed(session, loop_id, valve_asset or loop_id,
                                   confirmations_needed, now)
    if verdict != "stiction":
        return None
    streak = _confirming_runs(session, loop_id, confirmations_needed)
    asset = valve_asset or loop_id
    stored = _checked_evidence(loop_id, asset, evidence, len(streak))
    if len(streak) < confirmations_needed:
        return None
    checked = TicketEvidence.model_validate(stored)
    size = next((s for s in (checked.S, checked.episode_S, checked.episode_stick_band)
                 if s is not None), None)
    priority = ticket_priority(S=size, amplitude_pv=checked.amplitude_pv,
                               importance=importance)
    ticket = _active_ticket(session, asset)
    if ticket is None:
        oldest = streak[-1]
        pattern = "" if checked.pattern is None else f", pattern {checked.pattern}"
        ticket = Ticket(
            valve_asset=asset, loop_id=loop_id, state="open", priority=priority,
            title=short_text(f"Sticky valve {asset}, loop {loop_id}"),
            description=_describe(checked), location=location,
            malfunction_start=_window(oldest)[0],
            evidence=stored, created_at=now, updated_at=now,
        )
        ticket.events.append(TicketEvent(
            at=now, from_state=None, to_state="open", actor=ANALYSIS_ACTOR,
            note=f"opened: stiction confirmed by {len(streak)} analyses of separate windows "
                 f"(run {checked.run_id}{pattern}, priority {priority})",
        ))
        session.add(ticket)
    elif ticket.evidence.get("run_id") == checked.run_id or (
            priority == ticket.priority and not size_moved(ticket.evidence, stored)
            and not _last_not_confirmed(ticket)):
        return None
    else:
        note = (f"confirmed again: run {checked.run_id}" if _last_not_confirmed(ticket)
                else f"evidence updated: run {checked.run_id}")
        if priority != ticket.priority:
            note += f", priority {ticket.priority} -> {priority}"
        ticket.events.append(TicketEvent(
            at=now, from_state=ticket.state, to_state=ticket.state, actor=ANALYSIS_ACTOR, note=note
        ))
        ticket.evidence = stored
        ticket.description = _describe(checked)
        ticket.priority = priority
        ticket.updated_at = now
    session.flush()
    return ticket


NOT_CONFIRMED = "not confirmed"
"""Start of the event a ticket gets when its valve is found healthy (module docstring)."""


def _active_ticket(session: Session, asset: str) -> Ticket | None:
    """The valve's active ticket (at most one, module docstring), locked for the update."""
    return session.scalars(
        select(Ticket)
        .where(Ticket.valve_asset == asset, Ticket.state.in_(ACTIVE_STATES))
        .order_by(Ticket.id)
        .with_for_update()
    ).first()


def _last_not_confirmed(ticket: Ticket) -> bool:
    return bool(ticket.events) and ticket.events[-1].note.startswith(NOT_CONFIRMED)


def _note_not_confirmed(session: Session, loop_id: str, asset: str, needed: int,
                        now: float) -> Ticket | None:
    """Record on the valve's active ticket, once, that ``needed`` analyses of separate
    windows in a row found no stiction; the ticket, or None if untouched.  The state
    stays (maintenance closes tickets), and a later confirmation adds ``confirmed again``."""
    ticket = _active_ticket(session, asset)
    if ticket is None or _last_not_confirmed(ticket):
        return None
    streak = _confirming_runs(session, loop_id, needed, verdict="no_stiction")
    if len(streak) < needed:
        return None
    latest = streak[0]
    ticket.events.append(TicketEvent(
        at=now, from_state=ticket.state, to_state=ticket.state, actor=ANALYSIS_ACTOR,
        note=f"{NOT_CONFIRMED}: the last {len(streak)} analyses of separate windows find no "
             f"stiction (latest run {latest.id}, window {_utc_clock(_window(latest)[0])} "
             f"to {_utc_clock(_window(latest)[1])}); check the valve before repairing it",
    ))
    ticket.updated_at = now
    session.flush()
    return ticket


def change_ticket_state(
    session: Session, ticket_id: int, to_state: str, *, actor: str, now: float, note: str = ""
) -> Ticket:
    """Move a ticket along its lifecycle (maintenance), recording who did it."""
    ticket = session.get(Ticket, ticket_id, with_for_update=True)
    if ticket is None:
        raise TicketNotFoundError(f"ticket {ticket_id} not found")
    try:
        check_transition(ticket.state, to_state)
    except TicketStateError as exc:
        raise TicketStateError(f"ticket {ticket.id} (valve {ticket.valve_asset}): {exc}") from None
    ticket.events.append(TicketEvent(
        at=now, from_state=ticket.state, to_state=to_state, actor=actor, note=note
    ))
    ticket.state = to_state
    ticket.updated_at = now
    session.flush()
    return ticket


def list_tickets(
    session: Session,
    *,
    state: str | None = None,
    loop_id: str | None = None,
    valve_asset: str | None = None,
    limit: int = 100,
    offset: int = 0,
) -> tuple[list[Ticket], int]:
    """Tickets, most urgent and newest first, and their total count."""
    query = select(Ticket)
    if state is not None:
        _check_state(state)
        query = query.where(Ticket.state == state)
    if loop_id is not None:
        query = query.where(Ticket.loop_id == loop_id)
    if valve_asset is not None:
        query = query.where(Ticket.valve_asset == valve_asset)
    count = session.scalar(select(func.count()).select_from(query.subquery())) or 0
    page = session.scalars(
        query.order_by(Ticket.priority, Ticket.created_at.desc(), Ticket.id.desc())
        .limit(limit).offset(offset)
    ).all()
    return list(page), count


def get_ticket(session: Session, ticket_id: int) -> Ticket:
    """The ticket with its events loaded, oldest event first."""
    ticket = session.get(Ticket, ticket_id, options=[selectinload(Ticket.events)])
    if ticket is None:
        raise TicketNotFoundError(f"ticket {ticket_id} not found")
    return ticket


def ticket_to_dict(ticket: Ticket) -> dict[str, Any]:
    """The ticket's fields, JSON-ready; evidence stored before a key existed gets it with
    its default (see :data:`EVIDENCE_KEYS`)."""
    return {
        "id": ticket.id,
        "valve_asset": ticket.valve_asset,
        "loop_id": ticket.loop_id,
        "state": ticket.state,
        "priority": ticket.priority,
        "title": ticket.title,
        "description": ticket.description,
        "location": ticket.location,
        "malfunction_start": ticket.malfunction_start,
        "evidence": _DEFAULTS_OF_LATER_KEYS | ticket.evidence,
        "created_at": ticket.created_at,
        "updated_at": ticket.updated_at,
    }


def ticket_payload(ticket: Ticket, cmms: CmmsConfig | None = None) -> dict[str, Any]:
    """What a notification of a ticket's change carries: the ticket, its latest change and
    its CMMS mapping."""
    last = ticket.events[-1] if ticket.events else None
    change = None if last is None else {
        "at": last.at, "from_state": last.from_state, "to_state": last.to_state,
        "actor": last.actor, "note": last.note,
    }
    return {
        "ticket": ticket_to_dict(ticket),
        "change": change,
        "cmms": to_cmms_notification(ticket, cmms),
    }
