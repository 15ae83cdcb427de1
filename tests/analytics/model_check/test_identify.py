"""analytics.model_check.identify: a base model identified from data, against loops
whose controller and process are known."""

import numpy as np
import pytest

from analytics.model_check import check_model
from analytics.model_check.identify import identify_controller, identify_model
from analytics.scenarios import chapter4
from tests.analytics.model_check.common import model_with

NOISE = np.random.default_rng(1).normal(0.0, 0.05, 3000)


def setpoints() -> np.ndarray:
    """Ten levels of 300 s within 5 % of PV = 50."""
    return 50.0 + np.repeat(np.random.default_rng(1).uniform(-5.0, 5.0, 10), 300)


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


    def test_samples_at_an_output_limit_do_not_spoil_the_controller_fit(self) -> None:
        # Anti-windup by tracking keeps the velocity form exact once OP leaves the limit.
        model = model_with(valve=None, controller={"type": "PI", "Kc": 0.5, "Ti": 10.0,
                                                   "op_limits": [40.0, 48.0]})
        sim = model.simulate(setpoints(), noise=NOISE, pv_bias=50.0)
        assert np.count_nonzero(sim.op == 48.0) > 100  # held at the limit for a while
        fit = identify_controller(sim.op, sim.pv, 1.0, setpoints())
        assert fit.controller.as_ideal()[:2] == pytest.approx((0.5, 10.0), rel=1e-9)
        assert fit.r2 == pytest.approx(1.0, abs=1e-9)

    @pytest.mark.parametrize("process", [{"type": "fopdt", "K": 1.5, "tau": 12.0, "theta": 3.0},
                                         {"type": "integrating", "K": 0.02, "theta": 4.0}],
                             ids=["fopdt", "integrating"])
    def test_a_healthy_loop_gives_its_gain_and_its_controller(self, process) -> None:
        truth = model_with(valve=None, process=process)
        sim = truth.simulate(setpoints(), noise=NOISE, pv_bias=50.0)
        model, _, _ = identify_model(sim.op, sim.pv, 1.0, setpoints())
        gain = model.process.K
        assert model.process.kind == truth.process.kind
        assert gain == pytest.approx(truth.process.K, rel=0.1)
        assert model.controller.as_ideal()[:2] == pytest.approx((0.5, 10.0), rel=1e-9)
        assert model.op_bias == pytest.approx(np.median(sim.op))
