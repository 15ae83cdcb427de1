"""Multi-loop stiction detection and plant-wide oscillation diagnosis (thesis chapter 2).

* :mod:`~analytics.plantwide.groups` -- which signals of a unit share an
  oscillation (period and spectral similarity), and whether a cycle keeps a
  constant amplitude.
* :mod:`~analytics.plantwide.decomposition` -- thesis step 2: the number of
  known shapes (sticky valves) in the PV cycles, chosen on held-out cycles.
* :mod:`~analytics.plantwide.fingerprint` -- with the unit's own model
  (process matrix and tunings, thesis chapter 3): the linear check and every
  candidate set of sticky valves held against the harmonic balance of the
  measured cycle.
* :mod:`~analytics.plantwide.replay` -- with the unit's model, every candidate set
  of sticky valves replayed in the time domain from the valves' own OPs, fitted to
  every PV.
* :mod:`~analytics.plantwide.unit` -- :func:`diagnose_unit`, the whole
  diagnosis of a unit: groups, shapes, the surrogate ranking of step 3, the
  own-valve test and, with a model, the fingerprint, which name the sticky
  valves.
"""

from analytics.plantwide.decomposition import (
    CycleFit,
    ShapeDecomposition,
    decompose_cycles,
    fit_cycle,
)
from analytics.plantwide.fingerprint import (
    MIN_DISTORTION,
    CandidateFit,
    Fingerprint,
    LinearCheck,
    ModelLocalisation,
    UnitModel,
    linear_check,
    locate_sticky_valves,
    measure_fingerprint,
)
from analytics.plantwide.groups import (
    RAYLEIGH_ENVELOPE_CV,
    GroupMember,
    OscillationGroup,
    envelope_variation,
    find_oscillation_groups,
)
from analytics.plantwide.replay import (
    ReplayFit,
    ReplayLocalisation,
    replay_sticky_sets,
)
from analytics.plantwide.unit import (
    GroupDiagnosis,
    LoopEvidence,
    UnitDiagnosis,
    ValveFinding,
    diagnose_unit,
)

__all__ = [
    "MIN_DISTORTION",
    "RAYLEIGH_ENVELOPE_CV",
    "CandidateFit",
    "CycleFit",
    "Fingerprint",
    "GroupDiagnosis",
    "GroupMember",
    "LinearCheck",
    "LoopEvidence",
    "ModelLocalisation",
    "OscillationGroup",
    "ReplayFit",
    "ReplayLocalisation",
    "ShapeDecomposition",
    "UnitDiagnosis",
    "UnitModel",
    "ValveFinding",
    "decompose_cycles",
    "diagnose_unit",
    "envelope_variation",
    "find_oscillation_groups",
    "fit_cycle",
    "linear_check",
    "locate_sticky_valves",
    "measure_fingerprint",
    "replay_sticky_sets",
]
