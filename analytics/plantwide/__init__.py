"""Multi-loop stiction detection and plant-wide oscillation diagnosis (thesis chapter 2).

* :mod:`~analytics.plantwide.groups` -- which signals of a unit share an
  oscillation (period and spectral similarity), and whether a cycle keeps a
  constant amplitude.
* :mod:`~analytics.plantwide.decomposition` -- thesis step 2: the number of
  known shapes (sticky valves) in the PV cycles, chosen on held-out cycles.
* :mod:`~analytics.plantwide.unit` -- :func:`diagnose_unit`, the whole
  diagnosis of a unit: groups, shapes, the surrogate ranking of step 3 and
  the own-valve test that names the sticky valves.
"""

from analytics.plantwide.decomposition import (
    CycleFit,
    ShapeDecomposition,
    decompose_cycles,
    fit_cycle,
)
from analytics.plantwide.groups import (
    RAYLEIGH_ENVELOPE_CV,
    GroupMember,
    OscillationGroup,
    envelope_variation,
    find_oscillation_groups,
)
from analytics.plantwide.unit import (
    GroupDiagnosis,
    LoopEvidence,
    UnitDiagnosis,
    ValveFinding,
    diagnose_unit,
)

__all__ = [
    "RAYLEIGH_ENVELOPE_CV",
    "CycleFit",
    "GroupDiagnosis",
    "GroupMember",
    "LoopEvidence",
    "OscillationGroup",
    "ShapeDecomposition",
    "UnitDiagnosis",
    "ValveFinding",
    "decompose_cycles",
    "diagnose_unit",
    "envelope_variation",
    "find_oscillation_groups",
    "fit_cycle",
]
