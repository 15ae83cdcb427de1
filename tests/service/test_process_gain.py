"""The process gain a sticky valve is sized with, from the plant file (issue 19).

A stiction limit cycle pins the PV step of a slip, ``K J``, better than the slip
``J`` (:func:`analytics.quantification.quantify_with_gain`).  The plant file gives
the gain through a loop's ``process_model`` or, for a loop of a unit, through the
unit's process matrix; then the other valves' effect on the loop's PV is taken
out first (:func:`service.analysis.sizing_pv`).
"""

from typing import Any

import numpy as np
import pytest

from analytics.lti import TransferFunction, process_gain
from analytics.scenarios import COLUMN_PROCESS
from analytics.synthetic_cases import synthetic_library
from connectors.plant_sim import COLUMN_LOOPS, SINGLE_LOOPS, PlantSimulator
from service.analysis import (
    analyse_window,
    dead_time_samples,
    independent_gains,
    sizing_pv,
    to_percent_of_span,
)
from service.config import PlantConfig
from service.demo import demo_plant_config


def plant(loop: dict[str, Any], units: list[dict[str, Any]] | None = None) -> PlantConfig:
    return PlantConfig.model_validate({"units": units or [], "loops": [
        {"id": "FIC-1", "tags": {"op": "FIC1.OP", "pv": "FIC1.PV"}, "ts": 1.0, **loop}]})


def test_the_demo_column_loops_take_their_own_matrix_entry_and_the_single_loops_theirs():
    config = demo_plant_config()
    gains = independent_gains(config)
    assert sorted(gains) == sorted(loop.id for loop in config.loops)
    # the single loops configure the process they are simulated with (% per % of span)
    for loop in SINGLE_LOOPS:
        case = next(c for c in synthetic_library(100) if c.name == loop.source)
        kind, gain = process_gain(case.process)
        assert gains[loop.id]["K"] == pytest.approx(gain)
        assert gains[loop.id]["process_type"] == kind == case.process_type
        assert gains[loop.id]["source"] == "the loop's process_model"
        assert config.loop(loop.id).process_model["theta"] == case.process.delay
    fv502 = gains["AIC-502"]
    assert fv502["process_type"] == "self-regulating" and sorted(fv502["couplings"]) == [
        "AIC-501", "TIC-503"]
    # the configured gains are the simulated column's (thesis Eq. 2.10), in % per % of span
    for i, loop in enumerate(COLUMN_LOOPS):
        spans = {s: high - low for s, (low, high) in loop.ranges}
        assert gains[loop.id]["K"] == pytest.approx(
            COLUMN_PROCESS[i][i].dc_gain * spans["op"] / spans["pv"])
    assert fv502["K"] == pytest.approx(-2.36)
    # their Harris index takes its dead time from that entry too (the overview said
    # "dead time unknown" for the column's loops)
    for i, loop in enumerate(COLUMN_LOOPS):
        configured = config.loop(loop.id)
        assert configured.process_model is None
        theta = COLUMN_PROCESS[i][i].delay
        assert gains[loop.id]["dead_time_s"] == pytest.approx(theta) and theta > 0
        assert dead_time_samples(configured.model_dump(), gains[loop.id]) == int(
            theta // configured.ts) + 1


@pytest.mark.parametrize(("loop", "expected"), [
    ({"process_model": {"type": "fopdt", "K": 1.2, "tau": 8.0, "theta": 2.0}},
     ("self-regulating", 1.2)),
    ({"process_type": "integrating", "process_model": {"type": "integrating", "K": 0.02}},
     ("integrating", 0.02)),
    ({"process_model": {"num": [0.5], "den": [10.0, 1.0, 0.0]}}, ("integrating", 0.5)),
    ({"process_model": {"theta": 3.0}}, None),  # the dead time only, for the Harris index
    ({"process_type": "integrating",
      "process_model": {"type": "fopdt", "K": 1.2, "tau": 8.0}}, None),  # contradicts it
    ({}, None),
])
def test_a_loops_process_model_gives_its_gain(loop, expected):
    gain = independent_gains(plant(loop)).get("FIC-1")
    assert (None if gain is None else (gain["process_type"], gain["K"])) == expected
    if gain is not None:
        assert gain["source"] == "the loop's process_model" and gain["couplings"] == {}


def test_a_unit_loop_whose_own_entry_has_no_gain_or_that_the_matrix_leaves_out_has_none():
    fopdt = {"type": "fopdt", "K": 1.0, "tau": 5.0}
    double_integrator = {"num": [1.0], "den": [1.0, 0.0, 0.0]}
    units = [{"id": "u", "process": {"loops": ["FIC-1", "FIC-2"],
                                     "matrix": [[double_integrator, fopdt], [fopdt, fopdt]]}}]
    config = PlantConfig.model_validate({"units": units, "loops": [
        {"id": name, "unit": "u", "tags": {"op": f"{name}.OP", "pv": f"{name}.PV"}, "ts": 1.0}
        for name in ("FIC-1", "FIC-2", "FIC-3")]})
    gains = independent_gains(config)
    assert sorted(gains) == ["FIC-2"] and gains["FIC-2"]["couplings"] == {"FIC-1": fopdt}


@pytest.fixture(scope="module")
def column_second_hour():
    """The demo's column from 1 h to 2 h of its simulation (the second window the demo's
    history rounds analyse), in % of span, with the configuration the demo serves."""
    sim = PlantSimulator(modbus_port=None, origin=0.0, horizon_s=7200.0)
    config = demo_plant_config()
    ts = sim.sample_interval("AIC-502")
    k = np.arange(round(3600 / ts), round(7200 / ts))
    signals = {(loop.id, s): np.array([sim.value(f"{loop.id}.{s.upper()}", int(i)) for i in k])
               for loop in config.loops if loop.unit == "column" for s in ("op", "pv")}
    return config, ts, k * ts, signals


def test_fv502_is_sized_with_its_own_entry_once_the_other_valves_are_subtracted(
        column_second_hour):
    """Issue 19: FV-502 (He S 4, J 2) read J 0.71 and 4.18 in the demo's first two windows;
    its cycle pins K J only.  With the column's matrix: S and J within 15 %."""
    config, ts, t, signals = column_second_hour
    gain = independent_gains(config)["AIC-502"]
    loop = config.loop("AIC-502").model_dump(mode="json")
    own = {"op": signals["AIC-502", "op"], "pv": signals["AIC-502", "pv"], "sp": None,
           "mv": None}
    inputs = {other: to_percent_of_span(signals[other, "op"], config.loop(other).ranges["op"])
              for other in gain["couplings"]}  # as the scheduler adds them
    sized = analyse_window(loop, ts, t, own, {**gain, "inputs": inputs})
    q = sized["quantification"]
    assert sized["stiction"]["verdict"] == "stiction" and q is not None
    assert q["gain_given"] and q["gain_source"] == gain["source"]
    assert q["process"]["K"] == pytest.approx(-2.36)
    assert (q["S"], q["J"]) == pytest.approx((4.0, 2.0), rel=0.15)

    fitted = analyse_window(loop, ts, t, own)["quantification"]
    assert not fitted["gain_given"] and fitted["J_product_only"]
    assert any(i.startswith("J is not told from the process gain") for i in fitted["issues"])
    # without the other valves' OPs the matrix gain is not used: the PV steps are not
    # those of this valve alone (a fit with -2.36 on PV as measured: R^2 0.65 against 0.90)
    partial = analyse_window(loop, ts, t, own, {**gain, "inputs": {"AIC-501": inputs["AIC-501"]}})
    assert not partial["quantification"]["gain_given"]


def test_the_matrix_entries_are_those_the_plant_simulates():
    """The configured model is the independent source of the gain: the demo's plant file
    holds the simulated column's transfer functions (not read from the simulator inside
    the analysis)."""
    entry = demo_plant_config().units[0].process
    assert entry is not None
    g22 = TransferFunction.from_dict(entry.matrix[1][1])
    assert g22.dc_gain == pytest.approx(COLUMN_PROCESS[1][1].dc_gain)
    assert g22.delay == COLUMN_PROCESS[1][1].delay


def test_an_input_window_lacking_its_last_samples_still_serves_but_a_gappy_one_not():
    """A window cut from the buffers may lack its last samples (the demo's column: FV-502's
    first history window was sized with the gain fitted for it); a gappy one is not used."""
    coupling = {"B": {"type": "fopdt", "K": 2.0, "tau": 5.0}}
    u = np.linspace(0.0, 1.0, 1000)
    late = u.copy()
    late[-2:] = np.nan
    gappy = u.copy()
    gappy[::50] = np.nan
    exact = sizing_pv(np.zeros(1000), 1.0, coupling, {"B": u})
    filled = sizing_pv(np.zeros(1000), 1.0, coupling, {"B": late})
    assert exact is not None and filled is not None
    np.testing.assert_allclose(filled, exact, atol=1e-3)
    assert sizing_pv(np.zeros(1000), 1.0, coupling, {"B": gappy}) is None
    assert sizing_pv(np.zeros(1000), 1.0, coupling, {}) is None
