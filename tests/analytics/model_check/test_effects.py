"""analytics.model_check.effects: the catalogue's fits, checked against one model at a time,
a known lattice and a plain one-move-at-a-time compass search."""

from dataclasses import replace

import numpy as np
import pytest

from analytics.model_check.effects import ReplayData, _compass, fit_effect, pv_grid
from analytics.model_check.model import PeriodicLoad
from analytics.valves import HeValve
from tests.analytics.model_check.common import model_with, walk


class TestPvGrid:
    def test_grid_of_a_rounded_signal_is_found(self) -> None:
        rng = np.random.default_rng(2)
        pv = 50.0 + np.cumsum(rng.normal(0.0, 0.3, 3000))
        grid = pv_grid(0.07 + 0.25 * np.round((pv - 0.07) / 0.25))
        assert grid is not None
        assert grid.resolution == pytest.approx(0.25, rel=1e-6)
        assert grid.origin == pytest.approx(0.07, abs=1e-6)
        assert pv_grid(pv) is None


class TestFrictionSearch:
    """The friction searches: many frictions at a time, the same answers."""

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


HIDDEN = {
    # effect: (the true loop's change of the base model, the parameters to find, rel. tolerance)
    "gain_mismatch": ({"process": {"K": 2.1}}, {"K": 2.1}, 1e-9),
    "deadtime_mismatch": ({"process": {"theta": 6.0}}, {"theta": 6.0}, 0.0),
    "time_constant_mismatch": ({"process": {"tau": 25.0}}, {"tau": 25.0}, 1e-3),
    "valve_characteristic": ({"valve": {"curvature": 2.5}}, {"curvature": 2.5}, 1e-3),
    "external_disturbance": ({"load": PeriodicLoad(0.5, 90.0, 0.3)},
                             {"amplitude": 0.5, "period": 90.0, "phase": 0.3}, 1e-3),
}


@pytest.mark.parametrize("effect", HIDDEN)
def test_each_fit_finds_the_effect_hidden_in_noise_free_data(effect: str) -> None:
    """The PV of a true loop that differs from the base model in one parameter,
    replayed from a random OP: the effect's fit gives that parameter back."""
    change, expected, rel = HIDDEN[effect]
    base = model_with()
    parts = {name: value if not isinstance(value, dict)
             else replace(getattr(base, name), **value) for name, value in change.items()}
    truth = replace(base, **parts)
    op = walk()
    t = np.arange(op.size, dtype=float)
    pv = 50.0 + truth.replay(op)[1] + (truth.load.series(t) if truth.load else 0.0)
    data = ReplayData(op, pv, 1.0, warm_up=100, folds=4)
    found = fit_effect(effect, data, base, data.predict(base), period_s=None)
    assert found.note == ""
    for name, value in expected.items():
        assert found.parameters[name] == pytest.approx(value, rel=rel), name
    assert data.predict(found.model).sse_fit < 1e-6 * data.predict(base).sse_fit
