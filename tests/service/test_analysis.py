"""One loop window through :func:`service.analysis.analyse_window` with a mode tag.

In manual the operator holds OP: the window's stretch in manual says nothing
about the controller or the valve's stick band, and a held OP looks like a
frozen transmitter.  The diagnosis is made on the longest stretch in auto or
cascade; the KPIs still see the whole window (service factor, travel).
"""

import numpy as np
import pytest

from analytics.synthetic_cases import synthetic_library
from service.analysis import analyse_window

MANUAL, AUTO = 16.0, 8.0
LOOP = {"ts": 1.0, "process_type": "self-regulating", "mode_map": {"16": "manual", "8": "auto"}}


@pytest.fixture(scope="module")
def sticky_hour():
    """An hour of a flow loop whose Kano valve (S = 4, J = 2) makes a limit cycle."""
    case = next(c for c in synthetic_library(3600) if c.name == "flow-kano-S4-J2-ts1")
    sim = case.simulate()
    return np.arange(3600.0), sim.op[0], sim.pv[0]


def with_manual(op, pv, stretch):
    """OP held by the operator over ``stretch``, PV settled at its value with a little noise."""
    op, pv = op.copy(), pv.copy()
    op[stretch] = op[stretch.start]
    pv[stretch] = pv[stretch.start] + 0.05 * np.random.default_rng(0).standard_normal(
        len(range(*stretch.indices(op.size))))
    mode = np.full(op.size, AUTO)
    mode[stretch] = MANUAL
    return op, pv, mode


def test_the_stretch_in_auto_is_diagnosed_and_the_manual_one_left_out(sticky_hour):
    t, op, pv = sticky_hour
    op, pv, mode = with_manual(op, pv, slice(0, 2200))
    # Without the mode the held OP reads as a frozen signal: nothing can be judged.
    blind = analyse_window(LOOP, 1.0, t, {"op": op, "pv": pv, "sp": None, "mv": None})
    assert not blind["quality"]["usable"] and "frozen" in blind["stiction"]["reason"]
    assert "manual" not in blind

    seen = analyse_window(LOOP, 1.0, t, {"op": op, "pv": pv, "sp": None, "mv": None,
                                          "mode": mode})
    assert seen["stiction"]["verdict"] == "stiction"
    assert seen["samples"] == 1400
    assert seen["manual"] == {
        "share": 2200 / 3600, "judged_from": 2200.0, "judged_to": 3599.0,
        "judged_samples": 1400,
        "note": "in manual 61 % of the window: diagnosed on its 23 min in auto or cascade"}
    # Episode and plot times count from the first sample diagnosed, not the window's.
    assert seen["first_sample_at"] == 2200.0
    # The KPIs are of the whole window, the time in manual counted.
    assert seen["kpis"]["service_factor"]["manual"] == pytest.approx(2200 / 3600)


def test_too_little_time_in_auto_is_said_so_not_called_unusable_data(sticky_hour):
    t, op, pv = sticky_hour
    op, pv, mode = with_manual(op, pv, slice(60, 3600))
    result = analyse_window(LOOP, 1.0, t, {"op": op, "pv": pv, "sp": None, "mv": None,
                                            "mode": mode})
    assert not result["quality"]["usable"]
    assert result["stiction"]["verdict"] == "undecided"
    assert result["stiction"]["reason"] == (
        "in manual 98 % of the window: the 60 s in auto or cascade are too few to judge")
    assert result["manual"]["judged_samples"] == 60
