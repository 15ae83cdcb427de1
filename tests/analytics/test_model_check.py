"""Model check (analytics.model_check).

The loop model is checked against independent code (analytics.simulation,
analytics.valves) and analytic answers (He's slips on a slow ramp, the
exponential characteristic, the mean of a rounded Gaussian); the check is
checked against loops that hide one known effect (issue 8: at least 9 of 10
random cases of every effect named correctly, the extended model better on
held-out data, and no-effect cases named ``none``), and run on real loops.
"""

import csv
import json
import math
from dataclasses import replace

import numpy as np
import pytest
from scipy.special import erf

from analytics.errors import DataError, ModelSpecError
from analytics.lti import TransferFunction
from analytics.model_check import EFFECTS, LoopModel, check_model
from analytics.model_check.cases import CATALOGUE, _levels, hidden_effect_case
from analytics.model_check.cases_independent import _TrueLoop, independent_case
from analytics.model_check.check import (
    ScoredCandidate,
    _nested_verdict,
    _select,
    noise_std,
    relevant_lattice,
    valve_synchronisation,
)
from analytics.model_check.effects import ReplayData, _compass, pv_grid
from analytics.model_check.identify import identify_controller
from analytics.model_check.model import Quantiser, StictionZone
from analytics.oscillation import detect_loop_oscillation
from analytics.scenarios import chapter4
from analytics.simulation import Disturbance, Loop, PIDController, simulate
from analytics.valves import ChoudhuryValve, HeValve, KanoValve, valve_from_dict
from tests.shared_data import SHARED_DATA, isdb_labels, load_isdb_loop, require_file

BASE = {
    "dt": 1.0,
    "op_bias": 45.0,
    "process": {"type": "fopdt", "K": 1.5, "tau": 12.0, "theta": 3.0},
    "controller": {"type": "PI", "Kc": 0.5, "Ti": 10.0},
    "valve": {"model": "he", "fs": 3.0, "fd": 1.0},
}


def model_with(**changes: object) -> LoopModel:
    return LoopModel.from_dict({**BASE, **changes})


def slow_ramp(low: float, high: float, step: float = 0.01) -> np.ndarray:
    up = np.arange(low, high, step)
    return np.concatenate([up, up[::-1]])


# ----------------------------------------------------------------------------
# the loop model


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


class TestMeasurement:
    @pytest.mark.parametrize("level", [0.5, 0.2, 0.45, 1.3, -2.05])
    def test_expected_rounded_value_matches_the_gaussian_integral(self, level) -> None:
        # E[round(y + n)] = sum_m m (Phi(m + 1/2 - y) - Phi(m - 1/2 - y)), by direct summation.
        grid, sigma = Quantiser(1.0, 0.0, noise=0.3), 0.3
        cells = np.arange(-20, 21)
        cdf = 0.5 * (1 + erf((cells[:, None] + np.array([-0.5, 0.5]) - level) / (sigma * 2**0.5)))
        direct = float(np.sum(cells * (cdf[:, 1] - cdf[:, 0])))
        assert grid.expected(np.array([level]))[0] == pytest.approx(direct, abs=1e-12)

    def test_grid_of_a_rounded_signal_is_found(self) -> None:
        rng = np.random.default_rng(2)
        pv = 50.0 + np.cumsum(rng.normal(0.0, 0.3, 3000))
        grid = pv_grid(0.07 + 0.25 * np.round((pv - 0.07) / 0.25))
        assert grid is not None
        assert grid.resolution == pytest.approx(0.25, rel=1e-6)
        assert grid.origin == pytest.approx(0.07, abs=1e-6)
        assert pv_grid(pv) is None

    def test_noise_level_from_second_differences(self) -> None:
        rng = np.random.default_rng(5)
        t = np.arange(20000)
        stick_slip = np.floor(t / 400.0) % 2  # a square wave: steps the MAD ignores
        assert noise_std(np.sin(t / 80.0) + stick_slip + rng.normal(0, 0.2, t.size)) == (
            pytest.approx(0.2, rel=0.05)
        )


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


class TestIdentification:
    @pytest.mark.parametrize("measured_sp", [True, False])
    def test_controller_from_a_simulated_loop(self, measured_sp: bool) -> None:
        # Thesis ch. 4 loop, PI 0.1 + 0.09/s: Kc = 0.1, Ti = 0.1 / 0.09 s.
        res = chapter4().run()
        sp = res.sp[0] if measured_sp else None
        fit = identify_controller(res.op[0][50:], res.pv[0][50:], res.dt, sp if sp is None
                                  else sp[50:])
        assert fit.controller.as_ideal().Kc == pytest.approx(0.1, rel=1e-6)
        assert fit.controller.as_ideal().Ti == pytest.approx(0.1 / 0.09, rel=1e-6)
        assert fit.r2 == pytest.approx(1.0, abs=1e-9)
        if not measured_sp:
            assert fit.setpoint == pytest.approx(float(res.sp[0][-1]), rel=1e-6)

    def test_check_without_a_model_identifies_one(self) -> None:
        res = chapter4().run()
        result = check_model(res.op[0], res.pv[0], res.dt, sp=res.sp[0])
        assert result.model_source == "identified"
        assert result.base_model.process.kind == "self-regulating"
        # the Hammerstein model (fitted on block means) replays the loop closely
        assert result.nmse_base_test < 0.1
        assert any("Hammerstein" in note for note in result.notes)


# ----------------------------------------------------------------------------
# the friction searches: many frictions at a time, the same answers


FRICTIONS = np.array([[3.0, 1.0], [1.2, 0.2]])
"""Two frictions in a valve model's own parameters (He's fs, fd; S, J of the band models)."""


def friction_model(name: str) -> LoopModel:
    keys = ("fs", "fd") if name == "he" else ("S", "J")
    return model_with(valve={"model": name, **dict(zip(keys, FRICTIONS[0], strict=True))})


def walk(n: int = 3000, seed: int = 3) -> np.ndarray:
    return 50.0 + np.cumsum(np.random.default_rng(seed).normal(0.0, 0.8, n))


class TestFrictionSearch:
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

    @pytest.mark.parametrize("horizon", [None, 40], ids=["free run", "horizon"])
    @pytest.mark.parametrize("load", [False, True], ids=["no load", "load"])
    def test_friction_errors_are_the_fit_errors_of_each_model(self, horizon, load) -> None:
        op = walk()
        truth = model_with(valve={"model": "he", "fs": 3.0, "fd": 1.0,
                                  "opening": {"fs": 2.0, "fd": 0.5}})
        pv = 50.0 + truth.replay(op)[1] + np.random.default_rng(4).normal(0.0, 0.05, op.size)
        model = model_with(load={"kind": "sine", "amplitude": 0.3, "period": 90.0}) if load \
            else model_with()
        data = ReplayData(op, pv, 1.0, warm_up=100, folds=4, horizon=horizon,
                          ramp=horizon is not None)
        params = np.array([[2.0, 0.5], [3.0, 1.0], [0.5, 0.5]])
        errors = data.friction_errors(model, model.valve.friction_table(opening=params),
                                      model.valve.zone_bounds())
        for i, friction in enumerate(params):
            one = replace(model, valve=replace(model.valve, opening=HeValve(*friction)))
            assert errors[i] == pytest.approx(data.predict(one).sse_fit, rel=1e-9)
        assert np.argmin(errors) == 0  # the true friction opening

    def test_compass_searches_side_by_side_are_those_one_at_a_time(self) -> None:
        def bumpy(p: np.ndarray) -> float:
            return float(np.sum(np.sin(3.0 * p) + 0.1 * (p - 1.0) ** 2))

        def one_at_a_time(start, steps, lower, upper, halvings=7):
            # Kolda, Lewis & Torczon (2003), Alg. 3.2, polled one move at a time
            x, step = np.clip(start, lower, upper), steps.copy()
            best = bumpy(x)
            for _ in range(halvings):
                improved = True
                while improved:
                    improved = False
                    for i in range(x.size):
                        for sign in (1.0, -1.0):
                            trial = x.copy()
                            trial[i] = min(max(trial[i] + sign * step[i], lower[i]), upper[i])
                            if trial[i] != x[i] and bumpy(trial) < best:
                                x, best, improved = trial, bumpy(trial), True
                step /= 2.0
            return x, best

        lower, upper, steps = np.full(3, -4.0), np.full(3, 4.0), np.full(3, 0.7)
        starts = np.random.default_rng(5).uniform(-4.0, 4.0, (10, 3))
        point, value = _compass(lambda ps: np.array([bumpy(p) for p in ps]), starts, steps,
                                lower, upper)
        expected = min((one_at_a_time(s, steps, lower, upper) for s in starts),
                       key=lambda found: found[1])
        np.testing.assert_array_equal(point, expected[0])
        assert value == expected[1]

    def test_random_loops_draw_their_levels_as_one_set_at_a_time(self) -> None:
        rng, reference = np.random.default_rng(0), np.random.default_rng(0)
        while True:  # the rejection sampling the block-wise draws must reproduce
            values = reference.uniform(-18.0, 18.0, 5)
            if np.min(np.diff(np.sort(values))) >= 8.0:
                break
        np.testing.assert_array_equal(_levels(rng, 5, 18.0, 8.0), values)
        assert rng.uniform() == reference.uniform()  # the generators are left alike


# ----------------------------------------------------------------------------
# the check on hidden effects

SEEDS = range(10)


def parameters_recovered(effect: str, case, found: dict) -> bool:
    """The fitted extension against the hidden one."""
    true = case.true_model
    if effect == "gain_mismatch":
        return found["K"] == pytest.approx(true.process.K, rel=0.03)
    if effect == "deadtime_mismatch":
        return found["theta"] == true.process.theta
    if effect == "time_constant_mismatch":
        return found["tau"] == pytest.approx(true.process.tau, rel=0.15)
    if effect == "valve_characteristic":
        return found["curvature"] == pytest.approx(true.valve.curvature, rel=0.15)
    if effect == "measurement_quantization":
        return found["resolution"] == pytest.approx(true.quantiser.resolution, rel=0.02)
    if effect == "external_disturbance":
        return found["period"] == pytest.approx(true.load.period, rel=0.01) and found[
            "amplitude"
        ] == pytest.approx(true.load.amplitude, rel=0.15)
    if effect == "asymmetric_stiction":
        stuck = "opening" if true.valve.opening is not None else "closing"
        other = "closing" if stuck == "opening" else "opening"
        valve = check_valve(found)
        return getattr(valve, stuck).S > getattr(valve, other).S
    zone = true.valve.zone
    return found["low"] < zone.high and found["high"] > zone.low


def check_valve(found: dict):
    """The asymmetric valve of a candidate's parameters (He or band model keys)."""
    if "opening_fs" in found:
        return type("V", (), {
            "opening": HeValve(found["opening_fs"], found["opening_fd"]),
            "closing": HeValve(found["closing_fs"], found["closing_fd"]),
        })
    return type("V", (), {
        "opening": ChoudhuryValve(found["opening_S"], found["opening_J"]),
        "closing": ChoudhuryValve(found["closing_S"], found["closing_J"]),
    })


@pytest.mark.slow
@pytest.mark.timeout(300)
@pytest.mark.parametrize("effect", CATALOGUE)
def test_hidden_effect_is_named_and_the_extension_gains(effect: str) -> None:
    named, recovered = 0, 0
    for seed in SEEDS:
        case = hidden_effect_case(effect, seed)
        result = check_model(case.op, case.pv, case.ts, sp=case.sp, model=case.base_model)
        if effect == "none":
            assert result.cause.effect == "none", f"seed {seed}: {result.findings}"
            continue
        if result.cause.effect != effect:
            continue
        named += 1
        assert result.gain.nmse_after < result.gain.nmse_before
        recovered += parameters_recovered(effect, case, result.cause.parameters)
    if effect != "none":
        assert named >= 9, f"{effect}: {named} of 10 named"
        assert recovered >= named - 1, f"{effect}: parameters of {recovered} of {named} recovered"


@pytest.fixture(scope="module")
def asymmetric():
    case = hidden_effect_case("asymmetric_stiction", 2, samples=4000)
    return case, check_model(case.op, case.pv, case.ts, sp=case.sp, model=case.base_model)


class TestCheckResult:
    def test_json_has_the_fields_of_issue_8(self, asymmetric) -> None:
        _, result = asymmetric
        out = json.loads(json.dumps(result.to_dict(overlay=True)))
        assert {"nmse", "period_measured_s", "period_simulated_s", "amplitude_measured",
                "amplitude_simulated"} <= set(out["baseline"])
        assert out["cause"]["effect"] == "asymmetric_stiction"
        assert 0.0 <= out["cause"]["confidence"] <= 1.0
        assert [c["effect"] for c in out["candidates"]] == list(EFFECTS)
        # issue 21: the runner-up and every cause, each with its own gain
        assert out["cause"]["runner_up"] in EFFECTS
        assert out["causes"][0] == out["cause"]
        for cause in out["causes"]:
            assert {"effect", "confidence", "parameters", "runner_up", "nmse_before",
                    "nmse_after"} <= set(cause)
            assert cause["nmse_after"] < cause["nmse_before"]
        assert {"nmse_before", "nmse_after", "period_error_before", "period_error_after",
                "amplitude_error_before", "amplitude_error_after"} <= set(out["gain"])
        assert LoopModel.from_dict(out["extended_model"]) == result.extended_model
        assert len(out["overlay"]["pv"]) == len(out["overlay"]["pv_extended"]) == 4000
        assert all(isinstance(f, str) and f.endswith(".") for f in out["findings"])

    def test_extension_brings_the_closed_loop_cycle_closer(self, asymmetric) -> None:
        case, result = asymmetric
        measured = detect_loop_oscillation(case.op, case.pv, case.ts)
        assert result.cycle_base.period_measured == pytest.approx(measured.period_s, rel=0.1)
        before, after = result.gain.before, result.gain.after
        # The base model's loop does not cycle; with the sticky opening it does.  (The
        # fitted friction is close, not exact: a valve dithered by noise slips at
        # other samples for the slightest change of fs or fd.)
        assert before.period_simulated is None
        assert abs(after.period_error) < 0.25
        assert abs(after.amplitude_error) < abs(before.amplitude_error)

    def test_a_sticky_valve_forgets_its_start_after_a_large_move(self) -> None:
        op = np.concatenate([np.full(50, 50.0) + 0.1 * np.sin(np.arange(50)), [60.0, 60.0]])
        assert valve_synchronisation(model_with(), op) == 50  # the jump to 60 at sample 50


@pytest.fixture(scope="module")
def quiet_case():
    return hidden_effect_case("none", 0, samples=1000)


class TestBadData:
    @pytest.mark.parametrize(
        ("mutate", "message"),
        [
            (lambda c: {"pv": np.where(np.arange(c.pv.size) == 17, np.nan, c.pv)},
             "PV holds 1 missing or non-finite value.*first at sample 17"),
            (lambda c: {"sp": c.sp[:-1]}, "SP has 999 samples, OP has 1000"),
            (lambda c: {"op": c.op[:200], "pv": c.pv[:200], "sp": c.sp[:200]},
             "at least 300 samples"),
            (lambda c: {"op": np.full(c.op.size, 40.0)}, "OP never moves"),
            (lambda c: {"ts": -1.0}, "positive number of seconds"),
            (lambda c: {"effects": ("gain_mismatch", "gremlins")}, "unknown effect"),
            (lambda c: {"pv": np.full(c.pv.size, 50.0)}, "PV never moves"),
        ],
    )
    def test_refused_with_the_reason(self, quiet_case, mutate, message) -> None:
        case = quiet_case
        args = {"op": case.op, "pv": case.pv, "ts": case.ts, "sp": case.sp,
                "model": case.base_model} | mutate(case)
        with pytest.raises(DataError, match=message):
            check_model(**args)

    @pytest.mark.parametrize(
        ("process", "message"),
        [
            ({"type": "fopdt", "K": 1.0, "tau": 1e12}, r"tau = 1e\+12 s is more than 1e\+06 times"),
            ({"type": "integrating", "K": 1.0, "theta": 1e300}, r"theta = 1e\+300 s"),
            ({"type": "fopdt", "K": 1e300, "tau": 5.0}, "more than 1e\\+06 times the measured PV"),
        ],
    )
    def test_models_beyond_what_the_data_can_check_are_refused(
        self, quiet_case, process, message
    ) -> None:
        with pytest.raises(ModelSpecError, match=message):
            check_model(quiet_case.op, quiet_case.pv, 1.0, sp=quiet_case.sp,
                        model={**BASE, "process": process})

    def test_bad_model_dict_is_a_model_error(self, quiet_case) -> None:
        with pytest.raises(ModelSpecError, match="process"):
            check_model(quiet_case.op, quiet_case.pv, 1.0, model={**BASE, "process": None})


# ----------------------------------------------------------------------------
# issue 21: the independent generator, confidence, evidence from the data, two causes


class TestIndependentGenerator:
    @pytest.mark.parametrize("valve", [HeValve(2.0, 1.0), ChoudhuryValve(3.0, 1.0),
                                       KanoValve(3.0, 1.0), HeValve(0.0, 0.0)],
                             ids=["he", "choudhury", "kano", "healthy"])
    @pytest.mark.parametrize("process", [{"type": "fopdt", "K": 1.5, "tau": 12.0, "theta": 3.0},
                                         {"type": "integrating", "K": 0.02, "theta": 4.0}],
                             ids=["fopdt", "integrating"])
    def test_its_simulator_without_effects_is_the_loop_model(self, valve, process) -> None:
        """Two simulators written apart agree sample for sample on a loop without effects."""
        spec = {**BASE, "process": process, "valve": valve.to_dict()}
        model = LoopModel.from_dict(spec)
        rng = np.random.default_rng(4)
        sp = 50.0 + np.repeat(rng.uniform(-5.0, 5.0, 6), 250)
        noise = rng.normal(0.0, 0.1, sp.size)
        op, mv, pv = _TrueLoop(model, tuple(valve.params_array())).run(sp, noise, 50.0)
        sim = model.simulate(sp, noise=noise, pv_bias=50.0)
        np.testing.assert_allclose(pv, sim.pv, atol=1e-9)
        np.testing.assert_allclose(mv, sim.mv, atol=1e-9)
        np.testing.assert_allclose(op, sim.op, atol=1e-9)

    def test_cases_are_reproducible_and_name_what_they_hide(self) -> None:
        pair = ("asymmetric_stiction", "external_disturbance")
        case = independent_case(pair, 3, samples=1500)
        again = independent_case(pair, 3, samples=1500)
        np.testing.assert_array_equal(case.pv, again.pv)
        assert case.effects == pair and case.true_model is None
        assert {"period"} <= set(case.parameters)
        with pytest.raises(ValueError, match="unknown effect"):
            independent_case("gremlins", 0)


def scored(effect: str, improvement: float, nmse: float) -> ScoredCandidate:
    return ScoredCandidate(effect, {}, nmse, nmse, improvement, "", model_with())


class TestConfidence:
    """The confidence compares held-out errors (Diebold-Mariano on batch means)."""

    rng = np.random.default_rng(5)
    noise = rng.normal(0.0, 1.0, 4800)
    base = noise + 2.0 * np.sin(np.arange(4800) / 30.0)  # the base model misses a load

    def test_two_effects_that_explain_the_data_equally_are_not_confident(self) -> None:
        residuals = {"gain_mismatch": self.noise, "external_disturbance": self.noise.copy()}
        chosen, confidence, runner_up = _select(
            [scored("gain_mismatch", 0.7, 0.3), scored("external_disturbance", 0.7, 0.3)],
            residuals, self.base, 0.05, 0.02,
        )
        assert chosen.effect == "gain_mismatch" and runner_up == "external_disturbance"
        assert confidence <= 0.6

    def test_an_effect_clearly_better_than_the_rest_is_confident(self) -> None:
        residuals = {"gain_mismatch": self.base * 0.9, "external_disturbance": self.noise}
        chosen, confidence, runner_up = _select(
            [scored("gain_mismatch", 0.19, 0.8), scored("external_disturbance", 0.7, 0.3)],
            residuals, self.base, 0.05, 0.02,
        )
        assert chosen.effect == "external_disturbance" and runner_up == "gain_mismatch"
        assert confidence > 0.99

    def test_none_names_the_closest_effect(self) -> None:
        residuals = {"gain_mismatch": self.base * 0.995, "deadtime_mismatch": self.base}
        chosen, confidence, runner_up = _select(
            [scored("gain_mismatch", 0.01, 0.99), scored("deadtime_mismatch", 0.0, 1.0)],
            residuals, self.base, 0.05, 0.02,
        )
        assert chosen is None and runner_up == "gain_mismatch" and confidence > 0.99


@pytest.fixture(scope="module")
def healthy_case():
    return hidden_effect_case("none", 1, samples=3000)


class TestQuantisationFromTheData:
    """A PV on a lattice is quantised whatever a fit says (historian rounding after the
    controller, so the loop itself is the base model's)."""

    def test_a_coarse_lattice_is_named(self, healthy_case) -> None:
        case = healthy_case
        q = 3.0 * case.noise_std
        pv = 0.07 + q * np.round((case.pv - 0.07) / q)
        assert relevant_lattice(pv) is not None
        result = check_model(case.op, pv, case.ts, sp=case.sp, model=case.base_model)
        assert result.cause.effect == "measurement_quantization", result.findings
        assert result.cause.parameters["resolution"] == pytest.approx(q, rel=0.02)
        assert result.gain.nmse_after < result.gain.nmse_before

    def test_a_fine_rounding_is_not(self, healthy_case) -> None:
        case = healthy_case
        pv = np.round(case.pv, 3)  # a historian's three decimals, far below the noise
        assert relevant_lattice(pv) is None
        result = check_model(case.op, pv, case.ts, sp=case.sp, model=case.base_model)
        assert result.cause.effect == "none"


@pytest.mark.slow
@pytest.mark.timeout(120)
@pytest.mark.parametrize(
    ("pair", "seed"),
    [(("gain_mismatch", "measurement_quantization"), 1),
     (("asymmetric_stiction", "external_disturbance"), 0)],
)
def test_two_hidden_effects_are_both_named_and_each_gains(pair, seed) -> None:
    case = hidden_effect_case(pair, seed)
    result = check_model(case.op, case.pv, case.ts, sp=case.sp, model=case.base_model)
    assert {c.effect for c in result.causes} == set(pair), result.findings
    first, second = result.causes
    assert first.nmse_before == result.gain.nmse_before
    assert second.nmse_before == first.nmse_after > second.nmse_after == result.gain.nmse_after
    extended = result.extended_model.to_dict()
    keys = {"gain_mismatch": ("process",), "measurement_quantization": ("measurement",),
            "asymmetric_stiction": ("valve", "opening"), "external_disturbance": ("load",)}
    for effect in pair:  # the extended model holds both extensions
        part = extended
        for key in keys[effect]:
            part = part.get(key) if isinstance(part, dict) else None
        assert part, f"{effect} missing from {extended}"


@pytest.mark.slow
@pytest.mark.timeout(120)
class TestDeadTimeAgainstTimeConstant:
    """A joint fit of dead time and lag says which of the two the data need."""

    def test_a_longer_dead_time_on_an_integrating_process(self) -> None:
        case = hidden_effect_case("deadtime_mismatch", 0)
        assert case.base_model.process.kind == "integrating"
        result = check_model(case.op, case.pv, case.ts, sp=case.sp, model=case.base_model)
        assert result.cause.effect == "deadtime_mismatch"
        assert result.cause.runner_up == "time_constant_mismatch"
        assert result.cause.confidence > 0.9
        assert result.cause.parameters["theta"] == case.true_model.process.theta

    def test_both_changed_names_both(self) -> None:
        case = hidden_effect_case(("deadtime_mismatch", "time_constant_mismatch"), 2)
        result = check_model(case.op, case.pv, case.ts, sp=case.sp, model=case.base_model)
        assert {c.effect for c in result.causes} == {"deadtime_mismatch",
                                                      "time_constant_mismatch"}
        # the first cause alone is not confidently one or the other
        assert result.causes[0].confidence < 0.5


class TestEffectsThatImitateEachOther:
    """The joint fit of two effects says which the data need (nested models)."""

    rng = np.random.default_rng(6)
    noise = rng.normal(0.0, 1.0, 4800)
    slow = np.sin(np.arange(4800) / 40.0)

    def test_the_effect_whose_joint_model_is_no_better_is_named(self) -> None:
        residuals = {"valve_characteristic": self.noise + 0.5 * self.slow,
                     "position_dependent_stiction": self.noise}
        effect, confidence, other = _nested_verdict(
            "valve_characteristic", "position_dependent_stiction", self.noise, residuals, 0.05
        )
        assert (effect, other) == ("position_dependent_stiction", "valve_characteristic")
        assert confidence > 0.95

    def test_when_both_are_needed_neither_is_confident(self) -> None:
        residuals = {"deadtime_mismatch": self.noise + 0.5 * self.slow,
                     "time_constant_mismatch": self.noise + 0.5 * np.roll(self.slow, 100)}
        _, confidence, _ = _nested_verdict(
            "deadtime_mismatch", "time_constant_mismatch", self.noise, residuals, 0.05
        )
        assert confidence < 0.05

    @pytest.mark.slow
    @pytest.mark.timeout(120)
    def test_a_characteristic_against_stiction_in_a_band(self) -> None:
        case = hidden_effect_case("valve_characteristic", 3)
        result = check_model(case.op, case.pv, case.ts, sp=case.sp, model=case.base_model)
        assert result.cause.effect == "valve_characteristic"
        assert result.cause.runner_up == "position_dependent_stiction"
        assert result.cause.confidence > 0.9


class TestBaseModelThatExplainsNothing:
    def test_no_confident_cause_and_the_data_that_would_decide(self, healthy_case) -> None:
        case = healthy_case
        rng = np.random.default_rng(8)
        unrelated = 50.0 + np.cumsum(rng.normal(0.0, 0.05, case.pv.size))  # not driven by OP
        result = check_model(case.op, unrelated, case.ts, sp=case.sp, model=case.base_model)
        assert result.nmse_base_test > 0.5
        explained = 1.0 - result.gain.nmse_after
        assert all(c.confidence <= max(explained, 0.0) + 1e-12 for c in result.causes)
        assert result.cause.confidence < 0.5
        assert any("would identify the process first" in f for f in result.findings)


# ----------------------------------------------------------------------------
# real loops


def plant_loop(name: str, pv_column: str, op_column: str) -> tuple[np.ndarray, np.ndarray]:
    """OP and PV of a plant export (newest row first, 1-minute sampling), oldest first,
    cut to the longest stretch without missing values (FIC-211 lost its PV for 2.5 h)."""
    path = require_file(SHARED_DATA / "plant_unlabelled" / f"{name}_20241121-27.csv")
    with path.open(newline="", encoding="utf-8-sig") as handle:
        rows = sorted(csv.DictReader(handle), key=lambda r: (r["date"], r["time"]))
    op = np.array([float(r[op_column]) if r[op_column] != "NULL" else np.nan for r in rows])
    pv = np.array([float(r[pv_column]) if r[pv_column] != "NULL" else np.nan for r in rows])
    ok = np.concatenate([[False], np.isfinite(op) & np.isfinite(pv), [False]])
    edges = np.flatnonzero(np.diff(ok.astype(int)))
    start, stop = max(zip(edges[::2], edges[1::2], strict=True), key=lambda e: e[1] - e[0])
    return op[start:stop], pv[start:stop]


@pytest.mark.slow
@pytest.mark.timeout(180)
@pytest.mark.parametrize(
    ("name", "pv_column", "op_column"),
    [("FIC-211", "FT_211", "FV_211"), ("LIC-106", "FT_115", "LV_106")],
)
def test_plant_loops_are_replayed_and_the_check_ignores_units(name, pv_column, op_column):
    op, pv = plant_loop(name, pv_column, op_column)
    result = check_model(op, pv, 60.0)
    assert result.model_source == "identified"
    assert result.nmse_base_test < 0.2  # the identified model replays a week of data
    # An offset and a scale of PV (other engineering units) change nothing.
    moved = check_model(op, 3.0 * pv + 100.0, 60.0)
    assert moved.cause.effect == result.cause.effect
    assert moved.nmse_base_test == pytest.approx(result.nmse_base_test, rel=1e-3)


@pytest.mark.slow
@pytest.mark.timeout(180)
@pytest.mark.parametrize("row", isdb_labels(), ids=lambda r: r["loop"])
def test_isdb_loops_are_checked(row: dict) -> None:
    _, op, pv = load_isdb_loop(row["loop"])
    result = check_model(op, pv, float(row["ts_s"]))
    assert result.model_source == "identified"
    assert result.cause.effect in ("none", *EFFECTS)
    if row["oscillating"] == "yes":
        assert result.cycle_base.period_measured is not None
