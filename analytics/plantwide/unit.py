"""Which valves of a unit stick: the multi-loop diagnosis of thesis chapter 2.

In a unit of interacting loops one sticky valve makes many loops oscillate,
and the single-loop methods then blame every valve whose loop cycles.
:func:`diagnose_unit` works on the unit as a whole:

1. **Plant-wide oscillations** (:func:`~analytics.plantwide.groups.find_oscillation_groups`):
   the OPs, PVs (and any further measurements) that share an oscillation
   form a group; each distinct oscillation has a source of its own.
2. **Thesis step 2** (:func:`~analytics.plantwide.decomposition.decompose_cycles`):
   the PV cycles of the group's loops are decomposed into ``k`` known shapes
   plus sinusoids; ``k`` is chosen on held-out cycles.
3. **Thesis step 3**: every OP and PV of the group is ranked by the surrogate
   nonlinearity index (thesis Eqs. 2.5-2.9, Thornhill 2005; ``K = 8``,
   ``M = 50``, 30 samples per cycle).
4. **Own-valve test** (the Hammerstein identification that the thesis names
   as the alternative for step 3, :func:`analytics.quantification.quantify_stiction`):
   a valve is named sticky when a stiction model of *that* valve, driven by
   its own OP, explains its own PV better than a healthy valve -- in the
   whole window and again in each half of it on its own (held-out
   replication, so that the two extra parameters of the valve model do not
   fit noise).  A healthy valve in a loop shaken by a neighbour's cycle
   passes its OP through unchanged; a stiction model of it adds nothing.

5. **The unit's own model** (optional, :mod:`analytics.plantwide.fingerprint`,
   thesis chapter 3): with the process matrix and the configured controllers,
   the linear loops are checked and each cycle's fingerprint is held against
   the harmonic balance (thesis Eqs. 3.11-3.14, ERRATA item 9) of every set
   of sticky valves; and the window is replayed through the model for every sticky
   set (:mod:`analytics.plantwide.replay`), whose best set names the valves.

Without a model the named valves are those of step 4; with one, those of the
replay (or, when the window is too short for it, of steps 4 and the fingerprint); the
shape count of step 2 and the nonlinearity ranking of step 3 are reported
beside them.  On the simulated column (thesis section 2.4) the ranking by
the surrogate index does not single out the sticky valves -- every signal of
a unit in a stiction limit cycle is nonlinear, and the noise decides the
order -- and the shape count grows with the dynamics of the healthy loops,
which are not sinusoidal there; the own-valve test separates them
(``tests/analytics/test_plantwide.py`` and ``benchmarks/plantwide.py`` show
the figures).

A cycle of only a few samples per period (a limit cycle at the scan rate, or
aliased by slow sampling) is too fast for shapes, surrogates or a Hammerstein
fit.  When such a cycle is confined to the signals of one loop and keeps a
constant amplitude (:func:`~analytics.oscillation.envelope_variation`
well below the Rayleigh value of a noise-driven resonance), the loop itself
holds the nonlinearity that sustains it, and its valve is named with a
lower confidence.

References
----------
.. [1] Thesis chapter 2: section 2.3.5 (steps 1-3), section 2.4 (the
   simulated column, Tables 2.3-2.8).
.. [2] N. F. Thornhill, "Finding the source of nonlinearity in a process with
   plant-wide oscillation", IEEE Trans. Control Syst. Technol. 13 (2005)
   434-443.
.. [3] M. Jelali, "Estimation of valve stiction in control loops using
   separable least-squares and global search algorithms", J. Process
   Control 18 (2008) 632-642.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from analytics.diagnosis import HAMMERSTEIN_GAIN_SCALE
from analytics.errors import DataError
from analytics.oscillation import LIMIT_CYCLE_ENVELOPE_CV, MIN_SAMPLES
from analytics.plantwide.decomposition import ShapeDecomposition, decompose_cycles
from analytics.plantwide.fingerprint import (
    CandidateFit,
    Fingerprint,
    LinearCheck,
    ModelLocalisation,
    UnitModel,
    linear_check,
    locate_sticky_valves,
)
from analytics.plantwide.groups import (
    GroupMember,
    OscillationGroup,
    envelope_variation,
    find_oscillation_groups,
)
from analytics.plantwide.replay import ReplayFit, ReplayLocalisation, replay_sticky_sets
from analytics.quantification import MIN_FIT_R2, MIN_R2_GAIN, StictionEstimate, quantify_stiction
from analytics.serial import Reader
from analytics.stiction.evidence import margin_confidence
from analytics.stiction.surrogate import MIN_PERIOD_SAMPLES, surrogate_nonlinearity_index
from analytics.types import FloatArray

__all__ = [
    "LIMIT_CYCLE_ENVELOPE_CV",
    "MODEL_CONFIDENCE",
    "MODEL_NOTE",
    "GroupDiagnosis",
    "LoopEvidence",
    "UnitDiagnosis",
    "ValveFinding",
    "diagnose_unit",
]


MODEL_NOTE = ("diagnosed from the data alone; the unit's process matrix and controller "
              "tunings would make it stronger: with them every sticky set is tested "
              "against the harmonic balance of the measured cycle")
"""What the report says when no model was given."""

MODEL_CONFIDENCE = 0.7
"""Confidence of a valve named by the model's fingerprint alone (the data's own-valve
test did not confirm it); a valve both name keeps the higher of the two."""

FAST_CYCLE_CONFIDENCE = 0.6
"""Highest confidence for a valve named from a fast cycle: the localisation and
the constant envelope show a nonlinearity inside the loop, but no test of the
valve itself can run on two or three samples per period."""


@dataclass(frozen=True)
class LoopEvidence:
    """What the unit diagnosis found about one loop of an oscillation group.

    Attributes
    ----------
    loop : str
        The loop's id.
    nonlinearity_op, nonlinearity_pv : float or None
        Surrogate nonlinearity index ``N`` of OP and PV at the group's period
        (thesis Eq. 2.9; ``N > 1`` is nonlinear); None where it could not be
        computed.
    own_valve_gain : float or None
        Output-error R^2 that a stiction model of the loop's valve adds over a
        healthy valve (:func:`analytics.quantification.quantify_stiction`).
    half_gains : tuple of (float or None)
        The same gain in the first and in the second half of the window (only
        computed when the whole window shows stiction).
    S, J : float or None
        Stick band and slip jump of the identified valve model (% of OP span).
    sticky : bool
        True when the stiction model fits well and is needed in the whole
        window and in each half.
    note : str
        One sentence on the outcome.
    J_product_only : bool
        The window pins only the PV step of a slip, ``K J``, not J: fitted
        without a known process gain, J fits about as well with the gain
        halved or doubled
        (:attr:`analytics.quantification.StictionEstimate.J_product_only`),
        and J often ends at a bound of its search (0 or S).
    """

    loop: str
    nonlinearity_op: float | None
    nonlinearity_pv: float | None
    own_valve_gain: float | None
    half_gains: tuple[float | None, float | None]
    S: float | None
    J: float | None
    sticky: bool
    note: str
    J_product_only: bool = False

    @property
    def nonlinearity(self) -> float | None:
        """The larger of the OP and PV indices (the loop's place in the ranking)."""
        known = [v for v in (self.nonlinearity_op, self.nonlinearity_pv) if v is not None]
        return max(known) if known else None


@dataclass(frozen=True)
class GroupDiagnosis:
    """The diagnosis of one plant-wide oscillation.

    Attributes
    ----------
    period_s : float
        The group's period, s.
    cycles : float
        Periods in the window.
    members : tuple of GroupMember
        The signals that share the oscillation (strongest first).
    loops : tuple of str
        Loops with their OP or PV among the members: the valves that could be
        the source; with a model, also a loop whose valve it names for the cycle
        and whose OP moves at it as much as the OP of one of those.
    decomposition : ShapeDecomposition or None
        Thesis step 2 on the PVs of ``loops`` (None when it could not run;
        see ``note``).
    evidence : tuple of LoopEvidence
        One entry per loop, sticky ones first, then by nonlinearity index.
    sticky_valves : tuple of str
        The loops whose valves are named sticky for this oscillation.
    envelope_cv : float or None
        Envelope variation of the strongest member (computed for fast cycles,
        where it decides).
    note : str
        How the group was diagnosed, or why it was not.
    model : ModelLocalisation or None
        The harmonic-balance fingerprint of the cycle against the unit's model
        (:func:`~analytics.plantwide.fingerprint.locate_sticky_valves`); None
        without a model or when the cycle is too short or too fast for it.
    replay : ReplayLocalisation or None
        The unit's window replayed through its model for every sticky set
        (:func:`~analytics.plantwide.replay.replay_sticky_sets`, the same for every
        group); with it, the model's named valves are the replay's.
    """

    period_s: float
    cycles: float
    members: tuple[GroupMember, ...]
    loops: tuple[str, ...]
    decomposition: ShapeDecomposition | None
    evidence: tuple[LoopEvidence, ...]
    sticky_valves: tuple[str, ...]
    envelope_cv: float | None
    note: str
    model: ModelLocalisation | None = None
    replay: ReplayLocalisation | None = None

    @property
    def ranking(self) -> tuple[tuple[str, float], ...]:
        """Every OP and PV of the group's loops by decreasing surrogate index (thesis
        step 3), as ``(signal, N)``."""
        pairs = [
            (f"{role}_{e.loop}", value)
            for e in self.evidence
            for role, value in (("op", e.nonlinearity_op), ("pv", e.nonlinearity_pv))
            if value is not None
        ]
        return tuple(sorted(pairs, key=lambda pair: pair[1], reverse=True))

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-ready form (an item of :meth:`UnitDiagnosis.to_dict`'s ``groups``)."""
        return _group_dict(self)


@dataclass(frozen=True)
class ValveFinding:
    """A valve named sticky.

    Attributes
    ----------
    loop : str
        The loop whose valve sticks.
    confidence : float
        0 to 1.
    period_s : float
        Period of the oscillation it drives, s.
    S, J : float or None
        Identified stick band and slip jump (% of OP span); None for a fast
        cycle.
    reason : str
        The evidence in one sentence.
    J_product_only : bool
        J is not resolved: the window pins only ``K J`` (see
        :attr:`LoopEvidence.J_product_only`).
    """

    loop: str
    confidence: float
    period_s: float
    S: float | None
    J: float | None
    reason: str
    J_product_only: bool = False

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-ready form (an item of :meth:`UnitDiagnosis.to_dict`'s
        ``sticky_valves``)."""
        return {"loop": self.loop, "confidence": self.confidence, "period_s": self.period_s,
                "S": self.S, "J": self.J, "J_product_only": self.J_product_only,
                "reason": self.reason}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any], where: str = "finding", *,
                  lenient: bool = False) -> ValveFinding:
        """The finding of :meth:`to_dict`'s form (see :meth:`UnitDiagnosis.from_dict`)."""
        f = Reader(d, where, lenient=lenient)
        return cls(f("loop"), f("confidence", 0.0), f("period_s"), f("S"), f("J"),
                   f("reason", ""), bool(f.get("J_product_only")))


@dataclass(frozen=True)
class UnitDiagnosis:
    """Result of :func:`diagnose_unit`.

    Attributes
    ----------
    loops : tuple of str
        The loops analysed.
    samples : int
        Window length.
    ts : float
        Sampling interval, s.
    groups : tuple of GroupDiagnosis
        Every plant-wide oscillation found, with its diagnosis.
    sticky_valves : tuple of ValveFinding
        The valves named sticky, most confident first; empty when no valve
        is to blame.
    linear : LinearCheck or None
        The unit's model with healthy valves under the configured tunings
        (None without a model).
    """

    loops: tuple[str, ...]
    samples: int
    ts: float
    groups: tuple[GroupDiagnosis, ...]
    sticky_valves: tuple[ValveFinding, ...]
    linear: LinearCheck | None = None

    @property
    def k(self) -> int:
        """Number of sticky valves found."""
        return len(self.sticky_valves)

    def valve_decisions(self) -> tuple[list[str], list[str]]:
        """The loops whose valves the diagnosis names sticky, and those it clears.

        A valve is cleared when the own-valve test of its loop ran on a shared
        oscillation (``own_valve_gain`` known) and did not name it: its loop
        cycles because a neighbour's sticky valve drives it (thesis chapter 2,
        section 2.3.5).  Loops in no diagnosed oscillation are neither.

        >>> UnitDiagnosis.from_dict({"sticky_valves": [{"loop": "b"}], "groups": [
        ...     {"evidence": [{"loop": "a", "own_valve_gain": 0.0},
        ...      {"loop": "b", "own_valve_gain": 0.2},
        ...      {"loop": "c", "own_valve_gain": None}]}]}, lenient=True).valve_decisions()
        (['b'], ['a'])
        """
        sticky = [finding.loop for finding in self.sticky_valves]
        tested = {e.loop for group in self.groups for e in group.evidence
                  if e.own_valve_gain is not None}
        return sticky, sorted(tested - set(sticky))

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-ready form (the ``loopwatch unit-analyze --json`` contract)."""
        return {
            "loops": list(self.loops),
            "samples": self.samples,
            "ts": self.ts,
            "k": self.k,
            "sticky_valves": [f.to_dict() for f in self.sticky_valves],
            "groups": [g.to_dict() for g in self.groups],
            "model_used": self.linear is not None,
            "linear": None if self.linear is None else {
                "stable": self.linear.stable, "margin": self.linear.margin,
                "margin_omega": self.linear.margin_omega, "note": self.linear.note},
            "note": (MODEL_NOTE if self.linear is None else self.linear.note),
        }

    @classmethod
    def from_dict(cls, d: Mapping[str, Any], *, lenient: bool = False) -> UnitDiagnosis:
        """The diagnosis of :meth:`to_dict`'s form (a stored or a ``unit-analyze --json``
        one): ``to_dict(from_dict(d)) == d``.

        ``k``, ``model_used``, ``note`` and each group's ``ranking`` are derived, so not
        read.  What :meth:`to_dict` does not keep is left empty: each decomposition's
        ``per_signal_error``, and of a group's model localisation the phases, third
        harmonics and noise of the fingerprint (its phasors are the stored amplitudes,
        phase 0), the candidates' ``harmonic_misfit`` and ``distortion`` and the
        ``no_valve_harmonic_misfit`` (NaN and empty).  Diagnoses stored before the unit's
        model was used have no ``linear`` and no group ``model``, and those stored before
        the replay no group ``replay``: None; findings stored before
        ``J_product_only`` read False.  ``lenient`` reads a partial diagnosis (the
        service's view of a stored one): a missing field reads None, except the lists
        (empty), ``confidence`` (0), ``reason`` and ``note`` (empty), ``sticky`` (False)
        and ``half_gains`` (None, None).

        Raises
        ------
        DataError
            A field is missing or of the wrong kind; the message names it and where
            (``groups[0].evidence[1]``).
        """
        read = Reader(d, "unit diagnosis", lenient=lenient)
        return cls(
            loops=tuple(read("loops", ())), samples=read("samples"), ts=read("ts"),
            groups=tuple(_group_from_dict(g) for g in read.items("groups")),
            sticky_valves=tuple(ValveFinding.from_dict(f.d, f.where, lenient=lenient)
                                for f in read.items("sticky_valves")),
            linear=None if read.get("linear") is None else _linear_from_dict(read.part("linear")),
        )


def _linear_from_dict(read: Reader) -> LinearCheck:
    return LinearCheck(read("stable"), read("margin"), read("margin_omega"), read("note"))


def _group_from_dict(read: Reader) -> GroupDiagnosis:
    """The inverse of :func:`_group_dict` (see :meth:`UnitDiagnosis.from_dict`)."""
    shapes = None if read("shape_decomposition") is None else read.part("shape_decomposition")
    return GroupDiagnosis(
        period_s=read("period_s"), cycles=read("cycles"), loops=tuple(read("loops", ())),
        members=tuple(
            GroupMember(m("signal"), m("period_s"), m("regularity"), m("power_fraction"),
                        m("amplitude"), m("similarity"))
            for m in read.items("members")),
        decomposition=None if shapes is None else ShapeDecomposition(
            k=shapes("k"), n=shapes("n"), held_out_error=tuple(shapes("held_out_error")),
            held_out_se=tuple(shapes("held_out_se")), per_signal_error={},
            structures={name: tuple(s) for name, s in shapes("structures").items()},
            cycles=dict(shapes("cycles"))),
        evidence=tuple(
            LoopEvidence(e("loop"), e("nonlinearity_op"), e("nonlinearity_pv"),
                         e("own_valve_gain"),
                         (None, None) if e("half_gains") is None and e.lenient
                         else e.pair("half_gains"),
                         e("S"), e("J"), e("sticky", False), e("note", ""),
                         bool(e.get("J_product_only")))
            for e in read.items("evidence")),
        sticky_valves=tuple(read("sticky_valves", ())), envelope_cv=read("envelope_cv"),
        note=read("note", ""),
        model=None if read.get("model") is None else _localisation_from_dict(read.part("model")),
        replay=None if read.get("replay") is None else _replay_from_dict(read.part("replay")),
    )


def _replay_from_dict(read: Reader) -> ReplayLocalisation:
    """:meth:`ReplayLocalisation.to_dict`'s form back (``sticky_valves`` and ``note``
    are derived, so not read)."""
    return ReplayLocalisation.of(
        [ReplayFit(tuple(c("loops")), c("misfit"), c("score"), tuple(c("S")), tuple(c("J")))
         for c in read.items("candidates")],
        read("no_valve_misfit"), read("samples"))


def _localisation_from_dict(read: Reader) -> ModelLocalisation:
    """:meth:`ModelLocalisation.to_dict`'s form back (see :meth:`UnitDiagnosis.from_dict`
    for what it does not keep)."""
    return ModelLocalisation(
        linear=_linear_from_dict(read.part("linear")),
        fingerprint=Fingerprint(read("period_s"), tuple(complex(a) for a in read("op_amplitudes")),
                                tuple(complex(a) for a in read("pv_amplitudes")), (), (), ()),
        controller_residual=tuple(read("controller_residual")),
        candidates=tuple(
            CandidateFit(tuple(c("loops")), c("misfit"), math.nan, c("score"), tuple(c("S")),
                         tuple(c("J")), ())
            for c in read.items("candidates")),
        no_valve_misfit=read("no_valve_misfit"), no_valve_harmonic_misfit=math.nan,
        sticky_valves=tuple(read("sticky_valves")),
        predicted_period_s=read("predicted_period_s"), note=read("note"),
    )


def _group_dict(group: GroupDiagnosis) -> dict[str, Any]:
    d = group.decomposition
    return {
        "period_s": group.period_s,
        "cycles": group.cycles,
        "loops": list(group.loops),
        "members": [
            {"signal": m.signal, "period_s": m.period_s, "regularity": m.regularity,
             "power_fraction": m.power_fraction, "amplitude": m.amplitude,
             "similarity": m.similarity}
            for m in group.members
        ],
        "shape_decomposition": None if d is None else {
            "k": d.k,
            "n": d.n,
            "held_out_error": list(d.held_out_error),
            "held_out_se": list(d.held_out_se),
            "structures": {name: list(s) for name, s in d.structures.items()},
            "cycles": dict(d.cycles),
        },
        "ranking": [{"signal": s, "nonlinearity": n} for s, n in group.ranking],
        "evidence": [
            {"loop": e.loop, "nonlinearity_op": e.nonlinearity_op,
             "nonlinearity_pv": e.nonlinearity_pv, "own_valve_gain": e.own_valve_gain,
             "half_gains": list(e.half_gains), "S": e.S, "J": e.J,
             "J_product_only": e.J_product_only, "sticky": e.sticky, "note": e.note}
            for e in group.evidence
        ],
        "sticky_valves": list(group.sticky_valves),
        "envelope_cv": group.envelope_cv,
        "note": group.note,
        "model": None if group.model is None else group.model.to_dict(),
        "replay": None if group.replay is None else group.replay.to_dict(),
    }


def _checked(name: str, x: ArrayLike) -> FloatArray:
    a = np.asarray(x, dtype=np.float64)
    if a.ndim != 1:
        raise DataError(f"{name} must be one-dimensional, got shape {a.shape}")
    bad = np.flatnonzero(~np.isfinite(a))
    if bad.size:
        raise DataError(
            f"{name} has {bad.size} missing or non-finite value(s), the first at index {bad[0]}"
        )
    return a


def _unit_signals(
    loops: Mapping[str, tuple[ArrayLike, ArrayLike]],
    measurements: Mapping[str, ArrayLike],
) -> tuple[dict[str, FloatArray], dict[str, str]]:
    """All signals by name (``op_<loop>``, ``pv_<loop>``, measurements) and the loop of each
    OP and PV; every input checked."""
    if not loops:
        raise DataError("a unit needs at least one loop")
    signals: dict[str, FloatArray] = {}
    owner: dict[str, str] = {}
    for loop, pair in loops.items():
        if not isinstance(loop, str) or not loop:
            raise DataError(f"loop ids must be non-empty strings, got {loop!r}")
        if len(pair) != 2:
            raise DataError(f"loop {loop!r}: expected (op, pv), got {len(pair)} signals")
        for role, x in zip(("op", "pv"), pair, strict=True):
            name = f"{role}_{loop}"
            signals[name] = _checked(f"loop {loop!r}: {role.upper()}", x)
            owner[name] = loop
    for name, x in measurements.items():
        if name in signals:
            raise DataError(f"measurement {name!r} has the name of a loop signal")
        signals[name] = _checked(f"measurement {name!r}", x)
    sizes = {name: a.size for name, a in signals.items()}
    if len(set(sizes.values())) > 1:
        raise DataError(f"signals differ in length: {sizes}")
    samples = next(iter(sizes.values()))
    if samples < MIN_SAMPLES:
        raise DataError(f"{samples} samples per signal, at least {MIN_SAMPLES} are needed")
    return signals, owner


def _estimate_holds(estimate: StictionEstimate) -> bool:
    """A stiction model that fits (R^2 >= MIN_FIT_R2) and is needed (``stiction_found``)."""
    return bool(
        estimate.stiction_found and estimate.fit_r2 is not None and estimate.fit_r2 >= MIN_FIT_R2
    )


def _gain(estimate: StictionEstimate) -> float | None:
    if estimate.fit_r2 is None or estimate.search is None:
        return None
    return estimate.fit_r2 - estimate.search.r2_ideal_valve


def _own_valve_test(
    op: FloatArray, pv: FloatArray, ts: float, period_s: float
) -> tuple[StictionEstimate, tuple[StictionEstimate | None, StictionEstimate | None], bool]:
    """The Hammerstein test of one valve in the whole window and, if it holds, in each half."""
    whole = quantify_stiction(op, pv, ts, period_s=period_s)
    if not _estimate_holds(whole):
        return whole, (None, None), False
    middle = op.size // 2
    halves = (
        quantify_stiction(op[:middle], pv[:middle], ts, period_s=period_s),
        quantify_stiction(op[middle:], pv[middle:], ts, period_s=period_s),
    )
    return whole, halves, all(_estimate_holds(h) for h in halves)


def _nonlinearity(
    x: FloatArray, period_samples: float, settings: Mapping[str, int]
) -> float | None:
    try:
        return surrogate_nonlinearity_index(x, period_samples, **settings).index
    except DataError:
        return None


def _loop_evidence(
    loop: str, op: FloatArray, pv: FloatArray, ts: float, period_s: float,
    surrogate_settings: Mapping[str, int],
) -> LoopEvidence:
    period_samples = period_s / ts
    n_op = _nonlinearity(op, period_samples, surrogate_settings)
    n_pv = _nonlinearity(pv, period_samples, surrogate_settings)
    whole, halves, sticky = _own_valve_test(op, pv, ts, period_s)
    gain = _gain(whole)
    half_gains = tuple(None if h is None else _gain(h) for h in halves)
    if sticky:
        size = (f"S = {whole.S:.2f}; J not resolved without the process gain, only "
                f"K J = {whole.slip_step:.2f}" if whole.J_product_only
                else f"S = {whole.S:.2f}, J = {whole.J:.2f}" + (
                    "" if whole.J_interval is None else
                    f", 95 % interval of J {whole.J_interval[0]:.2f} to {whole.J_interval[1]:.2f}"))
        note = (f"a stiction model of its own valve ({size}) raises the fit of its PV by "
                f"{gain:.2f} in R2, in each half of the window too")
    elif _estimate_holds(whole):
        note = "stiction of its own valve fits the whole window but not both halves of it"
    elif whole.S is None:
        note = "its own valve could not be identified: " + "; ".join(whole.issues)
    elif whole.fit_r2 is None or whole.fit_r2 < MIN_FIT_R2:
        note = (f"its own valve explains little of its PV (fit R2 "
                f"{0.0 if whole.fit_r2 is None else whole.fit_r2:.2f}, stiction adds "
                f"{0.0 if gain is None else gain:+.3f}): the cycle reaches it from elsewhere")
    else:
        note = (f"a healthy valve explains its PV as well (stiction adds "
                f"{0.0 if gain is None else gain:+.3f} in R2, fit R2 "
                f"{0.0 if whole.fit_r2 is None else whole.fit_r2:.2f})")
    return LoopEvidence(
        loop=loop,
        nonlinearity_op=n_op,
        nonlinearity_pv=n_pv,
        own_valve_gain=gain,
        half_gains=(half_gains[0], half_gains[1]),
        S=whole.S if sticky else None,
        J=whole.J if sticky else None,
        sticky=sticky,
        note=note,
        J_product_only=sticky and whole.J_product_only,
    )


def _evidence_order(e: LoopEvidence) -> tuple[bool, float, float]:
    return (e.sticky, e.own_valve_gain or 0.0, e.nonlinearity or -math.inf)


def _fast_cycle(
    group: OscillationGroup, loops: tuple[str, ...], signals: Mapping[str, FloatArray],
    ts: float, cycles: float,
) -> GroupDiagnosis:
    """A cycle too fast for shapes and models: localisation and a constant envelope."""
    period = group.period_s / ts
    envelope = envelope_variation(signals[group.members[0].signal], period)
    named: tuple[str, ...] = ()
    if len(loops) != 1:
        note = (f"a cycle of {period:.1f} samples shared by {len(loops)} loops: too fast to "
                "test shapes or valve models, and not confined to one loop")
    elif envelope >= LIMIT_CYCLE_ENVELOPE_CV:
        note = (f"a cycle of {period:.1f} samples in loop {loops[0]} whose amplitude varies "
                f"like a noise-driven resonance (envelope variation {envelope:.2f}, "
                f"limit cycles stay below {LIMIT_CYCLE_ENVELOPE_CV:.2f})")
    else:
        named = loops
        note = (f"a sustained limit cycle of {period:.1f} samples (envelope variation "
                f"{envelope:.2f}) confined to loop {loops[0]}: the nonlinearity that drives "
                "it sits in that loop; too fast for shape or valve-model tests")
    evidence = tuple(
        LoopEvidence(loop, None, None, None, (None, None), None, None, loop in named, note)
        for loop in loops
    )
    return GroupDiagnosis(group.period_s, cycles, group.members, loops, None, evidence,
                          named, envelope, note)


def _diagnose_group(
    group: OscillationGroup,
    owner: Mapping[str, str],
    signals: Mapping[str, FloatArray],
    ts: float,
    *,
    min_cycles: float,
    max_k: int,
    surrogate_settings: Mapping[str, int],
    model: UnitModel | None,
    replay: ReplayLocalisation | None = None,
) -> GroupDiagnosis:
    loops = tuple(dict.fromkeys(owner[m.signal] for m in group.members if m.signal in owner))
    samples = next(iter(signals.values())).size
    period = group.period_s / ts
    cycles = samples / period
    if not loops:
        return GroupDiagnosis(group.period_s, cycles, group.members, loops, None, (), (), None,
                              "no loop takes part: a disturbance seen only in measurements")
    if cycles < min_cycles:
        return GroupDiagnosis(
            group.period_s, cycles, group.members, loops, None, (), (), None,
            f"only {cycles:.1f} cycles in the window; at least {min_cycles:g} are needed "
            "to tell a valve from the rest of the loop",
        )
    if period < MIN_PERIOD_SAMPLES:
        return _fast_cycle(group, loops, signals, ts, cycles)
    decomposition = None
    notes = []
    try:
        decomposition = decompose_cycles(
            {f"pv_{loop}": signals[f"pv_{loop}"] for loop in loops}, period,
            n_valves=len(loops), max_k=max_k,
        )
    except DataError as exc:
        notes.append(f"no shape decomposition: {exc}")
    evidence = sorted(
        (
            _loop_evidence(loop, signals[f"op_{loop}"], signals[f"pv_{loop}"], ts,
                           group.period_s, surrogate_settings)
            for loop in loops
        ),
        key=_evidence_order,
        reverse=True,
    )
    named = tuple(e.loop for e in evidence if e.sticky)
    localisation = None
    if model is not None:
        localisation = locate_sticky_valves(
            {loop: (signals[f"op_{loop}"], signals[f"pv_{loop}"]) for loop in model.loops},
            ts, model.process, model.controllers, period_s=group.period_s,
            hold_delay=model.hold_delay,
        )
        joined, refused = _model_valves_outside(localisation, model.loops, loops)
        loops = (*loops, *joined)
        notes.append(f"unit model: {localisation.note}" + (
            f" ({', '.join(refused)} not named here: its OP hardly moves at this cycle, "
            "less than the OP of every loop that shares it)" if refused else ""))
        if replay is None:
            named = tuple(dict.fromkeys(
                [*named, *(loop for loop in localisation.sticky_valves if loop in loops)]))
        else:  # the replay decides, for the loops of this group
            named = tuple(loop for loop in replay.sticky_valves if loop in loops)
            outside = [loop for loop in replay.sticky_valves if loop not in loops]
            notes.append(f"replayed through the unit model over the whole window: {replay.note}"
                         + (f" ({', '.join(outside)} outside this group's loops, so not "
                            "named here)" if outside else ""))
    if named:
        notes.insert(0, f"sticky: {', '.join(named)} (own-valve stiction model, replicated "
                        "in both halves of the window, or the unit model's fingerprint)")
    elif any((e.nonlinearity or 0.0) > 1.0 for e in evidence):
        notes.insert(0, "nonlinear cycle, but no valve of the group explains it: look for "
                        "another nonlinearity or a source outside the unit")
    else:
        notes.insert(0, "no valve of the group explains the cycle and no signal is nonlinear: "
                        "a linear oscillation (tuning or an external disturbance)")
    return GroupDiagnosis(group.period_s, cycles, group.members, loops, decomposition,
                          tuple(evidence), named, None, "; ".join(notes), localisation, replay)


def _model_valves_outside(
    localisation: ModelLocalisation, model_loops: tuple[str, ...], loops: tuple[str, ...]
) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """The valves the unit model names for a cycle outside the loops of its group: those
    whose OP moves at the cycle at least as much as the OP of a loop of the group (the
    group missed them, their signals carrying a stronger cycle), and the rest.

    The harmonic balance runs over every loop of the model: it may blame a valve whose
    OP hardly moves at the cycle (the demo column's FV-502 at TIC-503's 25 s cycle, 3 %
    of TIC-503's OP), while a loop of a second cycle can miss the group of the cycle it
    drives (the column with three sticky valves: valve 3 drives the 325 s cycle with the
    largest OP amplitude, its signals grouped at 129 s).
    """
    amplitude = dict(zip(model_loops, (abs(v) for v in localisation.fingerprint.op),
                         strict=True))
    floor = min((amplitude[loop] for loop in loops if loop in amplitude), default=math.inf)
    outside = [loop for loop in localisation.sticky_valves if loop not in loops]
    return (tuple(loop for loop in outside if amplitude[loop] >= floor),
            tuple(loop for loop in outside if amplitude[loop] < floor))


def _finding(group: GroupDiagnosis, loop: str) -> ValveFinding:
    """The finding of one named valve: the own-valve test's, the model's, or both."""
    evidence = next((e for e in group.evidence if e.loop == loop), None)
    found = None if evidence is None or not evidence.sticky else _data_finding(group, evidence)
    replayed = None if group.replay is None else group.replay.fit_of(group.replay.sticky_valves)
    if replayed is not None and loop in replayed.loops:
        k = replayed.loops.index(loop)
        reason = f"the unit model's replay names it: {group.replay.note}"  # type: ignore[union-attr]
        confidence = MODEL_CONFIDENCE
        if found is not None:
            confidence = max(found.confidence, MODEL_CONFIDENCE)
            reason = f"{found.reason}; {reason}"
        return ValveFinding(loop, confidence, group.period_s, replayed.S[k], replayed.J[k],
                            reason)
    model = group.model
    fit = None if model is None else model.fit_of(model.sticky_valves)
    if model is None or fit is None or loop not in fit.loops:
        if found is None:
            raise ValueError(f"no evidence names loop {loop!r}")
        return found
    if found is not None:
        return dataclasses.replace(
            found, confidence=max(found.confidence, MODEL_CONFIDENCE),
            reason=f"{found.reason}; the unit model's fingerprint names it too")
    k = fit.loops.index(loop)
    return ValveFinding(loop, MODEL_CONFIDENCE, group.period_s, fit.S[k], fit.J[k],
                        f"the unit model's fingerprint names it: {model.note}")


def _data_finding(group: GroupDiagnosis, evidence: LoopEvidence) -> ValveFinding:
    loop = evidence.loop
    if group.envelope_cv is not None:
        confidence = FAST_CYCLE_CONFIDENCE * margin_confidence(
            group.envelope_cv, LIMIT_CYCLE_ENVELOPE_CV, LIMIT_CYCLE_ENVELOPE_CV / 2
        )
        return ValveFinding(loop, confidence, group.period_s, None, None, evidence.note)
    gains = [g for g in (evidence.own_valve_gain, *evidence.half_gains) if g is not None]
    confidence = margin_confidence(min(gains), MIN_R2_GAIN, HAMMERSTEIN_GAIN_SCALE)
    return ValveFinding(loop, confidence, group.period_s, evidence.S, evidence.J, evidence.note,
                        evidence.J_product_only)


def diagnose_unit(
    loops: Mapping[str, tuple[ArrayLike, ArrayLike]],
    ts: float,
    *,
    measurements: Mapping[str, ArrayLike] | None = None,
    min_cycles: float = 8.0,
    max_k: int = 3,
    neighbours: int = 8,
    surrogates: int = 50,
    samples_per_cycle: int = 30,
    seed: int = 0,
    model: UnitModel | None = None,
) -> UnitDiagnosis:
    """Find the sticky valves of a unit of interacting loops (see the module docstring).

    Parameters
    ----------
    loops : mapping of str to (array_like, array_like)
        ``loop id -> (OP, PV)``, equally long, uniformly sampled, finite.
    ts : float
        Sampling interval, s.
    measurements : mapping of str to array_like, optional
        Further measurements of the unit (no valve of their own); they join
        the plant-wide grouping, so that a cycle seen in a loop and in the
        measurements around it counts as one.
    min_cycles : float
        Fewest periods of an oscillation in the window before a valve is
        blamed for it (the surrogate index needs 8; Thornhill's defaults
        hold for more than 12).
    max_k : int
        Most shapes the decomposition tries.
    neighbours, surrogates, samples_per_cycle, seed : int
        ``K``, ``M``, ``S_n`` and the seed of the surrogate index (thesis
        Remark 5).
    model : UnitModel, optional
        The unit's process matrix and configured controllers (its loops among
        those of ``loops``).  With it the linear loop is checked and every
        cycle's fingerprint is held against the harmonic balance of every
        sticky set (:func:`~analytics.plantwide.fingerprint.locate_sticky_valves`);
        the valves it names join those of the own-valve test.

    Returns
    -------
    UnitDiagnosis

    Raises
    ------
    DataError
        If there is no loop, ``ts`` is not positive, or a signal is not
        one-dimensional, finite, as long as the others and at least
        :data:`analytics.oscillation.MIN_SAMPLES` long (the message names
        the loop and signal), or the model names a loop that is not given.

    Examples
    --------
    >>> from analytics.scenarios import column3x3
    >>> run = column3x3(sticky=(1,)).run()
    >>> late = run.t >= 2000
    >>> unit = {name: (run.op[i][late], run.pv[i][late]) for i, name in enumerate(run.names)}
    >>> result = diagnose_unit(unit, run.dt)
    >>> [f.loop for f in result.sticky_valves]
    ['loop1']
    """
    if not (math.isfinite(ts) and ts > 0):
        raise DataError(f"sampling interval ts must be positive and finite, got {ts!r}")
    signals, owner = _unit_signals(loops, measurements or {})
    settings = {"neighbours": neighbours, "surrogates": surrogates,
                "samples_per_cycle": samples_per_cycle, "seed": seed}
    missing = [] if model is None else [loop for loop in model.loops if loop not in loops]
    if missing:
        raise DataError(f"the unit model's loops {missing} have no OP and PV in the data")
    oscillations = find_oscillation_groups(signals, ts)
    replay = None
    if model is not None and oscillations:
        try:
            replay = replay_sticky_sets({loop: (signals[f"op_{loop}"], signals[f"pv_{loop}"])
                                         for loop in model.loops}, ts, model.process)
        except DataError:  # too short a window for the replay: the fingerprint decides
            replay = None
    groups = tuple(
        _diagnose_group(g, owner, signals, ts, min_cycles=min_cycles, max_k=max_k,
                        surrogate_settings=settings, model=model, replay=replay)
        for g in oscillations
    )
    best: dict[str, ValveFinding] = {}
    for group in groups:
        for loop in group.sticky_valves:
            finding = _finding(group, loop)
            if loop not in best or finding.confidence > best[loop].confidence:
                best[loop] = finding
    return UnitDiagnosis(
        loops=tuple(loops),
        samples=next(iter(signals.values())).size,
        ts=float(ts),
        groups=groups,
        sticky_valves=tuple(sorted(best.values(), key=lambda f: f.confidence, reverse=True)),
        linear=None if model is None else linear_check(
            model.process, model.controllers,
            hold_delay=ts / 2 if model.hold_delay is None else model.hold_delay),
    )
