"""The contract every detector of the battery keeps (analytics/stiction/evidence.py)."""

import dataclasses

import numpy as np
import pytest

from analytics.oscillation import detect_loop_oscillation
from analytics.stiction.battery import DEFAULT_DETECTORS
from analytics.stiction.evidence import UNDECIDED, LoopWindow, MethodEvidence
from analytics.synthetic_cases import synthetic_library

DETECTORS = {d.name: d for d in DEFAULT_DETECTORS}


@pytest.fixture(scope="module")
def sticky_window() -> LoopWindow:
    case = next(c for c in synthetic_library(3000) if c.name == "flow-kano-S4-J2-ts1")
    r = case.simulate()
    osc = detect_loop_oscillation(r.op[0], r.pv[0], case.ts)
    return LoopWindow(case.ts, r.op[0], r.pv[0], sp=r.sp[0], process_type=case.process_type,
                      period_s=osc.period_s)


def test_names_are_unique_and_settings_keyword_only():
    assert len(DETECTORS) == len(DEFAULT_DETECTORS) == 8
    for detector in DEFAULT_DETECTORS:
        assert dataclasses.is_dataclass(detector)
        params = dataclasses.fields(detector)
        assert all(f.kw_only for f in params), detector.name
        with pytest.raises(dataclasses.FrozenInstanceError):
            setattr(detector, params[0].name, 0)


@pytest.mark.parametrize("name", sorted(DETECTORS))
def test_evidence_is_well_formed_and_deterministic(name, sticky_window):
    detector = DETECTORS[name]
    first = detector.detect(sticky_window)
    assert isinstance(first, MethodEvidence)
    assert first.method == name
    assert 0.0 <= first.confidence <= 1.0
    assert first.note
    assert first.index is None or np.isfinite(first.index)
    assert detector.detect(sticky_window) == first


@pytest.mark.parametrize("name", sorted(DETECTORS))
def test_without_an_oscillation_period_every_method_abstains(name, sticky_window):
    window = dataclasses.replace(sticky_window, period_s=None)
    evidence = DETECTORS[name].detect(window)
    assert evidence.decision == UNDECIDED
    assert evidence.note


@pytest.mark.parametrize("name", sorted(DETECTORS))
def test_a_missing_signal_gives_evidence_not_an_exception(name, sticky_window):
    for window in (dataclasses.replace(sticky_window, op=None),
                   dataclasses.replace(sticky_window, pv=None, sp=None)):
        evidence = DETECTORS[name].detect(window)
        assert evidence.method == name
        if evidence.decision == UNDECIDED:
            assert evidence.note
