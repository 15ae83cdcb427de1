"""Model check: what a loop simulation gets wrong, the cause, the extended model, the gain.

Issue 8 of loopwatch.  Given measured data (SP, OP, PV) and a base model of
the loop (process, PI controller, valve; or one identified from the data),
:func:`check_model` shows where the simulation is wrong, names the effect
of a catalogue that explains the mismatch, fits the extended model and
measures how much better it is on data it was not fitted to.

Modules: :mod:`~analytics.model_check.model` (the loop model, its JSON form
and the compiled simulation), :mod:`~analytics.model_check.effects` (the
catalogue and the fit of each effect), :mod:`~analytics.model_check.identify`
(a base model from data), :mod:`~analytics.model_check.check` (the check and
its result), :mod:`~analytics.model_check.cases` (random loops with a hidden
effect, for tests and benchmarks) and :mod:`~analytics.model_check.cases_independent`
(a second generator written apart from the first, the held-out set of issue 21).
"""

from analytics.model_check.check import (
    MIN_SAMPLES,
    Cause,
    CycleComparison,
    Gain,
    ModelCheck,
    Overlay,
    ScoredCandidate,
    check_model,
)
from analytics.model_check.effects import EFFECTS
from analytics.model_check.model import LoopModel

__all__ = [
    "EFFECTS",
    "MIN_SAMPLES",
    "Cause",
    "CycleComparison",
    "Gain",
    "LoopModel",
    "ModelCheck",
    "Overlay",
    "ScoredCandidate",
    "check_model",
]
