"""analytics.model_check.cases_independent: the second case generator (issue 21),
written apart from the first, against the loop model."""

import numpy as np
import pytest

from analytics.model_check import LoopModel
from analytics.model_check.cases_independent import _TrueLoop, independent_case
from analytics.valves import ChoudhuryValve, HeValve, KanoValve
from tests.analytics.model_check.common import BASE


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

