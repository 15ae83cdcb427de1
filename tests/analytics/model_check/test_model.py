"""analytics.model_check.model: the loop model, its JSON form and its compiled simulation.

Checked against independent code (analytics.simulation, analytics.valves) and
analytic answers (He's slips on a slow ramp, the exponential characteristic,
the mean of a rounded Gaussian); the JSON form round-trips bit for bit.
"""

import json
import math
from dataclasses import replace

import numpy as np
import pytest
from scipy.special import erf

from analytics.errors import ModelSpecError
from analytics.lti import TransferFunction
from analytics.model_check import LoopModel
from analytics.model_check.model import Quantiser, StictionZone
from analytics.simulation import Disturbance, Loop, PIDController, simulate
from analytics.valves import ChoudhuryValve, HeValve, KanoValve, valve_from_dict
from tests.analytics.model_check.common import (
    BASE,
    FRICTIONS,
    friction_model,
    model_with,
    slow_ramp,
    walk,
)


class TestLoopModelAgainstSimulation:
    """LoopModel.simulate follows analytics.simulation.simulate, sample for sample."""

    @pytest.mark.parametrize(
        "process",
        [
            {"type": "fopdt", "K": 1.5, "tau": 12.0, "theta": 3.0},
            {"type": "integrating", "K": 0.02, "theta": 4.0},
        ],
        ids=["fopdt", "integrating"],
    )
    @pytest.mark.parametrize(
        "valve",
        [
            {"model": "he", "fs": 3.0, "fd": 1.0},
            {"model": "choudhury", "S": 4.0, "J": 1.5},
            {"model": "kano", "S": 4.0, "J": 1.5},
            None,
        ],
        ids=["he", "choudhury", "kano", "healthy"],
    )
    def test_same_signals_as_the_simulator(self, process: dict, valve: dict | None) -> None:
        dt, n = 1.0, 3000
        load = {"kind": "sine", "amplitude": 0.4, "period": 70.0, "phase": 0.3}
        model = LoopModel.from_dict({**BASE, "process": process, "valve": valve, "load": load})
        t = np.arange(n) * dt
        noise = Disturbance("noise", 0.05, at="measurement", seed=7)
        sine = Disturbance("sine", 0.4, at="output", period=70.0, phase=0.3)
        sp = np.where(t >= 100.0, 53.0, 50.0)
        ours = model.simulate(sp, noise=noise.series(t), pv_bias=50.0)
        g = (
            TransferFunction.fopdt(1.5, 12.0, 3.0)
            if process["type"] == "fopdt"
            else TransferFunction.integrating(0.02, 4.0)
        )
        loop = Loop(
            PIDController.ideal(0.5, 10.0, op_bias=45.0), valve_from_dict(valve),
            setpoint=[(100.0, 53.0)], pv_bias=50.0, disturbances=(noise, sine),
        )
        theirs = simulate(g, loop, dt=dt, duration=(n - 1) * dt)
        # The simulator samples the process by matrix exponential, this model by
        # exp(-dt / tau): they differ by about 1e-10, until a valve that barely
        # slips at one sample slips at the next in the other (a stick-slip loop
        # amplifies any difference).  Compare up to that sample, if any.
        flips = np.flatnonzero(np.abs(ours.mv - theirs.mv[0]) > 1e-8)
        same = flips[0] if flips.size else n
        assert same >= 500
        for mine, other in ((ours.op, theirs.op), (ours.mv, theirs.mv), (ours.pv, theirs.pv)):
            np.testing.assert_allclose(mine[:same], other[0][:same], atol=1e-8)

    def test_replay_of_the_measured_op_reproduces_the_pv(self) -> None:
        # Driven by the OP the loop produced, a correct model gives the noise-free PV.
        model = model_with()
        sp = np.where(np.arange(3000) >= 100, 53.0, 50.0)
        clean = model.simulate(sp, pv_bias=50.0)
        mv, x = model.replay(clean.op, initial_position=model.op_bias)
        np.testing.assert_allclose(mv, clean.mv, atol=1e-12)
        np.testing.assert_allclose(50.0 + x, clean.pv, atol=1e-9)


class TestValveExtensions:
    @pytest.mark.parametrize(
        "valve", [HeValve(3.0, 1.0), ChoudhuryValve(4.0, 1.5), KanoValve(4.0, 1.5)],
        ids=["he", "choudhury", "kano"],
    )
    def test_without_extensions_the_valve_is_the_base_model(self, valve) -> None:
        op = 50.0 + np.cumsum(np.random.default_rng(3).normal(0.0, 0.8, 4000))
        model = model_with(valve=valve.to_dict())
        np.testing.assert_array_equal(model.replay(op)[0], valve.simulate(op))

    def test_asymmetric_he_valve_slips_by_fs_minus_fd_each_way(self) -> None:
        # He et al. (2007): on a slow ramp the valve moves in slips of fs - fd.
        valve = {"model": "he", "fs": 3.0, "fd": 1.0, "closing": {"fs": 1.5, "fd": 0.5}}
        op = slow_ramp(20.0, 60.0)
        mv = model_with(valve=valve).replay(op)[0]
        slips = np.diff(mv)
        up, down = slips[slips > 0], slips[slips < 0]
        assert up[1:] == pytest.approx(2.0, abs=0.011)  # opening: 3 - 1
        assert down[1:] == pytest.approx(-1.0, abs=0.011)  # closing: 1.5 - 0.5

    def test_zone_friction_acts_only_inside_its_band(self) -> None:
        valve = {"model": "he", "fs": 0.0, "fd": 0.0,
                 "zone": {"low": 40.0, "high": 60.0, "fs": 2.0, "fd": 1.0}}
        op = slow_ramp(20.0, 80.0)[:6000]  # rising only
        lag = op - model_with(valve=valve).replay(op)[0]
        assert np.all(lag[op < 40.0] == 0.0)
        inside = (op > 42.0) & (op < 60.0)
        assert np.all((lag[inside] >= 1.0 - 1e-9) & (lag[inside] <= 2.0 + 0.011))
        assert np.all(lag[op > 63.0] == 0.0)

    @pytest.mark.parametrize("curvature", [-3.0, 2.5])
    def test_exponential_characteristic_has_its_closed_form_gain(self, curvature) -> None:
        model = model_with(
            process={"type": "fopdt", "K": 2.0, "tau": 5.0},
            valve={"model": "he", "fs": 0.0, "fd": 0.0,
                   "characteristic": {"type": "exponential", "curvature": curvature}},
        )
        for move in (20.0, -15.0, 0.01):
            op = np.full(400, model.op_bias)
            op[10:] += move
            x = model.replay(op)[1]
            expected = 2.0 * 100.0 / curvature * math.expm1(curvature * move / 100.0)
            assert x[-1] == pytest.approx(expected, rel=1e-9)
        assert x[-1] == pytest.approx(2.0 * 0.01, rel=1e-3)  # slope 1 at op_bias


class TestQuantiser:
    @pytest.mark.parametrize("level", [0.5, 0.2, 0.45, 1.3, -2.05])
    def test_expected_rounded_value_matches_the_gaussian_integral(self, level) -> None:
        # E[round(y + n)] = sum_m m (Phi(m + 1/2 - y) - Phi(m - 1/2 - y)), by direct summation.
        grid, sigma = Quantiser(1.0, 0.0, noise=0.3), 0.3
        cells = np.arange(-20, 21)
        cdf = 0.5 * (1 + erf((cells[:, None] + np.array([-0.5, 0.5]) - level) / (sigma * 2**0.5)))
        direct = float(np.sum(cells * (cdf[:, 1] - cdf[:, 0])))
        assert grid.expected(np.array([level]))[0] == pytest.approx(direct, abs=1e-12)


class TestJson:
    def test_extended_model_round_trips(self) -> None:
        spec = {
            **BASE,
            "pv_bias": 48.0,
            "valve": {
                "model": "choudhury", "S": 3.0, "J": 1.0,
                "opening": {"S": 5.0, "J": 2.0}, "closing": {"S": 3.0, "J": 1.0},
                "zone": {"low": 20.0, "high": 30.0, "S": 6.0, "J": 3.0},
                "characteristic": {"type": "exponential", "curvature": 2.5},
            },
            "load": {"kind": "sine", "amplitude": 0.5, "period": 120.0, "phase": 0.3},
            "measurement": {"resolution": 0.25, "origin": 0.1, "noise": 0.02},
        }
        model = LoopModel.from_dict(spec)
        assert LoopModel.from_dict(json.loads(json.dumps(model.to_dict()))) == model

    def test_controller_gains_round_trip_bit_for_bit(self) -> None:
        # Kc and Ti as written, not Kc / (Kc / Ti): issue 25's 1-ulp trap.
        rng = np.random.default_rng(25)
        kc = 10 ** rng.uniform(-3, 1, 500) * rng.choice([-1.0, 1.0], 500)
        ti = 10 ** rng.uniform(-1, 3, 500)
        inexact = 0
        for k, t in zip(kc.tolist(), ti.tolist(), strict=True):
            spec = {**BASE, "controller": {"type": "PI", "Kc": k, "Ti": t,
                                           "op_limits": [-10.0, 110.0]}}
            text = json.dumps(LoopModel.from_dict(spec).to_dict())
            again = LoopModel.from_dict(json.loads(text))
            assert json.loads(json.dumps(again.to_dict()))["controller"] == spec["controller"]
            assert again.controller.ki == k / t  # the gain the loop is simulated with
            inexact += k / (k / t) != t
        assert inexact > 10  # a Ti derived from the gains would fail this test

    def test_the_loop_sets_its_controller_to_its_operating_point(self) -> None:
        base = model_with()
        model = LoopModel(base.dt, base.process, PIDController.ideal(0.5, 10.0), base.valve,
                          op_bias=45.0)
        assert model.controller.op_bias == 45.0 and model == base
        with pytest.raises(ModelSpecError, match="no derivative action, action 'reverse'"):
            replace(base, controller=PIDController.ideal(0.5, 10.0, Td=1.0, op_bias=45.0))
        with pytest.raises(ModelSpecError, match="no derivative action, action 'reverse'"):
            replace(base, controller=PIDController.ideal(0.5, 10.0, action="direct"))

    @pytest.mark.parametrize(
        ("change", "message"),
        [
            ({"process": {"type": "fopdt", "K": 1.0}}, "process lacks the key(s) 'tau'"),
            ({"process": {"type": "fopdt", "K": 1, "tau": -2}}, "tau > 0"),
            ({"process": {"type": "soptd", "K": 1}}, "'fopdt' or 'integrating'"),
            ({"controller": {"Kc": 1, "Ti": 0}}, "Ti must be > 0"),
            ({"controller": {"Kc": "high"}}, "controller Kc must be a number"),
            ({"valve": {"model": "karnopp", "fs_force": 1, "fc_force": 0.5}}, "he, choudhury"),
            ({"valve": {"model": "he", "fs": 1, "fd": 2}}, "cannot exceed static"),
            ({"valve": {"model": "he", "fs": 2, "fd": 1, "opening": {"S": 2, "J": 1}}},
             "valve opening lacks the key(s) 'fs', 'fd'"),
            ({"valve": {"model": "he", "fs": 2, "fd": 1,
                        "zone": {"low": 30, "high": 20, "fs": 1, "fd": 0}}}, "low < high"),
            ({"valve": {"model": "he", "fs": 2, "fd": 1,
                        "characteristic": {"type": "linear", "curvature": 1}}}, "'exponential'"),
            ({"load": {"kind": "sine", "amplitude": 1, "period": 0}}, "period must be > 0"),
            ({"measurement": {"resolution": -1}}, "resolution must be > 0"),
            ({"op_bias": 150}, "outside the OP limits"),
            ({"gain": 2}, "unknown key(s) 'gain'"),
            ({"process": {"type": "fopdt", "K": 10**400, "tau": 5}}, "process K must be finite"),
            ({"valve": {"model": ["he"], "fs": 1, "fd": 0}},
             "valve 'model' must name the valve model"),
        ],
    )
    def test_bad_models_say_what_is_wrong(self, change: dict, message: str) -> None:
        with pytest.raises(ModelSpecError, match=message.replace("(", r"\(").replace(")", r"\)")):
            LoopModel.from_dict({**BASE, **change})



class TestFrictionTables:
    """Many frictions at a time (the searches of the check), the same answers as one model each."""

    @pytest.mark.parametrize("name", ["he", "choudhury", "kano"])
    def test_friction_tables_are_those_of_the_replaced_valves(self, name) -> None:
        valve = friction_model(name).valve
        kind = type(valve.base)
        tables = valve.friction_table(opening=FRICTIONS, closing=FRICTIONS[::-1])
        zones = valve.friction_table(zone=FRICTIONS)
        for i, friction in enumerate(FRICTIONS):
            other = replace(valve, opening=kind(*friction), closing=kind(*FRICTIONS[1 - i]))
            np.testing.assert_array_equal(tables[i], other.friction_table())
            zone = replace(valve, zone=StictionZone(40.0, 60.0, kind(*friction)))
            np.testing.assert_array_equal(zones[i], zone.friction_table())

    @pytest.mark.parametrize("name", ["he", "choudhury", "kano"])
    def test_replays_of_many_frictions_are_those_of_each_model(self, name) -> None:
        model = friction_model(name)
        kind = type(model.valve.base)
        bands = np.array([[45.0, 52.0], [30.0, 70.0]])
        op, lead_in = walk(), np.array([40.0, 44.0, 47.0])
        x = model.replay_frictions(op, model.valve.friction_table(zone=FRICTIONS), bands,
                                   initial_position=38.0, lead_in=lead_in)
        for i, (low, high) in enumerate(bands):
            zone = StictionZone(low, high, kind(*FRICTIONS[i]))
            one = replace(model, valve=replace(model.valve, zone=zone))
            np.testing.assert_array_equal(x[i], one.replay(op, initial_position=38.0,
                                                           lead_in=lead_in)[1])
