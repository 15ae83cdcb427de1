"""The multi-loop stiction diagnosis of a unit (``GET /api/v1/units/{id}/diagnosis``):
:meth:`analytics.plantwide.UnitDiagnosis.to_dict` with the valves named by their tags
(:func:`service.verdicts.named_valves`) and where the diagnosis comes from.

The models keep keys they do not name: the unit diagnosis grows, and stored
diagnoses were written by earlier versions.
"""

from __future__ import annotations

from typing import Any, Literal

from service.api.schemas.base import OpenSchema


class UnitValveFinding(OpenSchema):
    """A valve named sticky (:class:`analytics.plantwide.ValveFinding`)."""

    loop: str
    """The loop whose valve sticks."""
    valve: str
    """The valve's tag (its loop's ``valve_asset``, or the loop id)."""
    confidence: float | None = None
    """0 to 1."""
    period_s: float | None = None
    """Period of the oscillation it drives, s."""
    S: float | None = None
    """Stick band this window shows, % of OP span; null for a fast cycle.  The valve's
    size on the loop list, the loop page and the ticket is its estimate combined over
    its confirming windows (the loop's ``valve.S``), which moves less."""
    J: float | None = None
    """Slip jump this window shows, % of OP span; null for a fast cycle (combined as S
    is on the other pages)."""
    J_product_only: bool = False
    """J is not resolved by this window: fitted without the process gain it pins only
    ``K J``, and J may sit at a bound of its search (0 or S)."""
    reason: str | None = None
    """The evidence in one sentence."""


class GroupMemberPublic(OpenSchema):
    """One signal's share in the oscillation (:class:`analytics.plantwide.GroupMember`)."""

    signal: str | None = None
    """The signal's name (``op_<loop>``, ``pv_<loop>`` or a measurement)."""
    period_s: float | None = None
    """Its own oscillation period, s."""
    regularity: float | None = None
    """Thornhill's regularity r of its oscillation."""
    power_fraction: float | None = None
    """Share of the signal's detrended variance at the oscillation."""
    amplitude: float | None = None
    """Half peak-to-peak of the band-passed oscillation, in the signal's units."""
    similarity: float | None = None
    """Cosine similarity of its spectrum around the group frequency with the strongest
    member's (1 for that member)."""


class ShapeDecompositionPublic(OpenSchema):
    """The oscillation's cycle shapes decomposed into sources
    (:class:`analytics.plantwide.ShapeDecomposition`; thesis chapter 2)."""

    k: int | None = None
    """Known shapes (sticky valves) chosen by the one-standard-error rule."""
    n: int | None = None
    """Valves that can act on the PVs (the group's loops)."""
    held_out_error: list[float] | None = None
    """Mean held-out squared error per cycle point for k = 0, 1, ..., summed over the
    PVs (thesis Tables 2.4-2.6, cross-validated)."""
    held_out_se: list[float] | None = None
    """Standard error of each entry's per-cycle difference to the best one."""
    structures: dict[str, list[str]] | None = None
    """Each PV's structure with k shapes, in the notation of thesis Table 2.7."""
    cycles: dict[str, int] | None = None
    """Complete cycles used per PV."""


class RankedSignalPublic(OpenSchema):
    """One OP or PV in the group's nonlinearity ranking."""

    signal: str | None = None
    nonlinearity: float | None = None
    """Surrogate nonlinearity index N (thesis Eq. 2.9; above 1: nonlinear)."""


class LoopEvidencePublic(OpenSchema):
    """What the unit diagnosis found about one loop of the group
    (:class:`analytics.plantwide.LoopEvidence`)."""

    loop: str | None = None
    nonlinearity_op: float | None = None
    """Surrogate nonlinearity index of OP at the group's period; null where it could not
    be computed."""
    nonlinearity_pv: float | None = None
    """The same of PV."""
    own_valve_gain: float | None = None
    """Output-error R^2 a stiction model of the loop's own valve adds over a healthy one."""
    half_gains: list[float | None] | None = None
    """The same gain in the first and in the second half of the window."""
    S: float | None = None
    """Stick band of the identified valve model, % of OP span."""
    J: float | None = None
    """Slip jump of the identified valve model, % of OP span."""
    J_product_only: bool | None = None
    """The window pins only K J, not J."""
    sticky: bool | None = None
    """The stiction model fits well and is needed in the whole window and in each half."""
    note: str | None = None
    """The outcome in one sentence."""


class OscillationGroup(OpenSchema):
    """One plant-wide oscillation and its diagnosis
    (:class:`analytics.plantwide.GroupDiagnosis`)."""

    period_s: float | None = None
    """Period of the common oscillation, s."""
    cycles: float | None = None
    """Cycles of it in the window."""
    loops: list[str] | None = None
    """The loops that share it."""
    members: list[GroupMemberPublic] | None = None
    """The signals that oscillate with it: ``signal``, ``period_s``, ``regularity``,
    ``power_fraction``, ``amplitude``, ``similarity``."""
    shape_decomposition: ShapeDecompositionPublic | None = None
    """The decomposition of the oscillation's shapes into sources (thesis chapter 2):
    ``k`` sources of ``n`` signals, held-out errors, structures and cycles."""
    ranking: list[RankedSignalPublic] | None = None
    """Every OP and PV by surrogate nonlinearity index, most nonlinear first:
    ``signal``, ``nonlinearity``."""
    evidence: list[LoopEvidencePublic] | None = None
    """Per loop: OP and PV nonlinearity, the gain of a stiction model of its own valve,
    S and J, whether it sticks, and a note."""
    sticky_valves: list[str]
    """Tags of the valves named sticky for this oscillation."""
    sticky_loops: list[str]
    """Their loops."""
    envelope_cv: float | None = None
    """Coefficient of variation of the oscillation's envelope."""
    note: str | None = None
    """The group's verdict in words."""
    model: dict[str, Any] | None = None
    """What the unit's model predicts for the group (null without a model)."""


class LinearCheckPublic(OpenSchema):
    """The unit's model with healthy valves under the configured tunings."""

    stable: bool | None = None
    margin: float | None = None
    """Stability margin."""
    margin_omega: float | None = None
    """Frequency of the margin, rad/s."""
    note: str | None = None


class UnitDiagnosisPublic(OpenSchema):
    """Which valves of the unit stick: oscillation groups, the shape decomposition, the
    surrogate ranking of every OP and PV, and the named valves with their confidence."""

    unit_id: str
    source: Literal["scheduler", "on_demand"]
    """The scheduler's latest diagnosis, or one computed now from each loop's latest
    window."""
    round_end: float | None
    """End of the scheduler's round that diagnosed it, UNIX s (null on demand)."""
    window_end: float | None
    """End of the windows diagnosed, UNIX s."""
    loops_without_complete_window: list[str]
    """Loops of the unit left out: no complete OP and PV window."""
    loops: list[str] | None = None
    """The loops analysed."""
    samples: int | None = None
    """Window length, samples."""
    ts: float | None = None
    """Sampling interval, s."""
    k: int | None = None
    """Number of sticky valves found."""
    sticky_valves: list[UnitValveFinding]
    """The valves named sticky, most confident first; empty when no valve is to blame."""
    groups: list[OscillationGroup]
    """Every plant-wide oscillation found, with its diagnosis."""
    model_used: bool | None = None
    """Whether the unit's process matrix and tunings were used."""
    linear: LinearCheckPublic | None = None
    """The model's check with healthy valves (null without a model)."""
    note: str | None = None
    """What the diagnosis rests on."""
