"""Stick-jump episodes and stuck sections (analytics/stiction/stick_jump.py) on
signals whose answer is known by construction, and on simulated loops whose
valve is known."""

import numpy as np
import pytest

from analytics.lti import TransferFunction
from analytics.simulation import Disturbance, Loop, PIDController, simulate
from analytics.stiction.evidence import NO_STICTION, STICTION, UNDECIDED, LoopWindow
from analytics.stiction.stick_jump import (
    SMOOTHING_SCALES,
    StickJumpDetector,
    StuckSectionsDetector,
    analyse_window,
    find_stick_episodes,
    loop_gain_sign,
    robust_noise,
    travel_increments,
    valve_travel,
)
from analytics.synthetic_cases import synthetic_library, transient_library
from analytics.valves import IdealValve, KanoValve, ValveModel

FLOW = TransferFunction.fopdt(1.2, 8.0, 2.0)


def _flow_loop(valve: ValveModel, *, gain: float = 1.2, seed: int = 3, ts: float = 1.0):
    """A flow loop with slow integral action and set-point steps: with a sticky
    valve it holds and jumps without a sustained cycle (Kano et al. 2004)."""
    action = "reverse" if gain > 0 else "direct"
    controller = PIDController.ideal(0.3, 60.0)
    controller = PIDController(controller.kp, controller.ki, action=action)
    loop = Loop(controller, valve, setpoint=[(200.0, 51.5), (900.0, 49.5), (1500.0, 50.5)],
                pv_bias=50.0, disturbances=(Disturbance("noise", 0.05, at="measurement",
                                                        seed=seed),))
    result = simulate(TransferFunction.fopdt(gain, 8.0, 2.0), loop, dt=ts, duration=2100.0)
    return LoopWindow(ts, result.op[0], result.pv[0], sp=result.sp[0],
                      process_type="self-regulating"), result.mv[0]


def test_robust_noise_reads_white_noise_and_ignores_jumps():
    rng = np.random.default_rng(1)
    x = 0.3 * rng.standard_normal(5000)
    x[2500:] += 10.0  # one large jump does not inflate the estimate
    assert robust_noise(x) == pytest.approx(0.3, rel=0.05)


def test_travel_is_the_path_of_a_backlash_on_op():
    op = np.concatenate([np.linspace(0.0, 10.0, 101), np.linspace(10.0, 0.0, 101)[1:]])
    # Up 10 less the half band, then down 10 less the whole band (the reversal).
    assert valve_travel(op, 0.5) == pytest.approx(9.5 + 9.0)
    assert travel_increments(op, 0.5).sum() == pytest.approx(valve_travel(op, 0.5))
    noise = 0.1 * np.random.default_rng(2).standard_normal(1000)
    assert valve_travel(noise, 0.5) == 0.0


@pytest.mark.parametrize("gain", [1.2, -1.2])
def test_the_process_gain_sign_is_read_from_the_controller(gain):
    window, _ = _flow_loop(IdealValve(), gain=gain)
    assert loop_gain_sign(window.op, window.pv, window.sp) == np.sign(gain)


def test_a_sticky_valve_without_a_cycle_gives_episodes_of_its_stick_band():
    S, J = 2.0, 0.5
    window, mv = _flow_loop(KanoValve(S, J))
    analysis = analyse_window(window)
    assert analysis is not None and analysis.gain_sign == 1
    assert len(analysis.episodes) >= 2 and not analysis.contrary
    for episode in analysis.episodes:
        # The valve really held through the episode's hold (PV leaves it a lag
        # and a dead time, 10 s, after the slip) and slipped at its end ...
        assert np.ptp(mv[episode.start:episode.jump_at - 12]) < 0.05 * S
        assert np.ptp(mv[episode.start:episode.end]) > 0.5 * J
        # ... while OP pushed through a stick band (Kano's model: S after a
        # reversal, J in the same direction), and PV jumped the way OP pushed.
        assert 0.8 * J <= abs(episode.op_travel) <= 1.1 * S
        assert np.sign(episode.pv_jump) == np.sign(episode.op_travel)
    assert StickJumpDetector().detect(window).decision == STICTION


def test_a_healthy_valve_under_the_same_controller_gives_no_episode():
    window, _ = _flow_loop(IdealValve())
    analysis = analyse_window(window)
    assert analysis is not None and not analysis.episodes
    assert StickJumpDetector().detect(window).decision == NO_STICTION
    assert StuckSectionsDetector().detect(window).decision == UNDECIDED


def test_load_steps_on_a_healthy_valve_are_not_stick_jumps():
    controller = PIDController.ideal(0.3, 60.0)
    loop = Loop(controller, IdealValve(), setpoint=50.0, pv_bias=50.0, disturbances=(
        Disturbance("step", 2.0, at="output", time=300.0),
        Disturbance("step", -3.0, at="output", time=1100.0),
        Disturbance("noise", 0.05, at="measurement", seed=4)))
    result = simulate(FLOW, loop, dt=1.0, duration=2000.0)
    window = LoopWindow(1.0, result.op[0], result.pv[0], sp=result.sp[0])
    analysis = analyse_window(window)
    assert analysis is not None and not analysis.episodes
    assert StickJumpDetector().detect(window).decision != STICTION


def test_pv_that_holds_through_an_op_reversal_is_stuck():
    rng = np.random.default_rng(5)
    # OP rises 40 -> 42 with PV following, then the valve sticks: OP goes on to 44
    # and back to 41 while PV holds, and the valve finally slips back.
    op = np.concatenate([np.linspace(40, 42, 300), np.linspace(42, 44, 200),
                         np.linspace(44, 41, 600), np.full(300, 41.0)])
    pv = 50.0 + 1.5 * (np.minimum(op, 42.0) - 40.0)
    pv[300:1100] = 53.0
    pv[1100:] = 51.5
    pv += 0.05 * rng.standard_normal(op.size)
    evidence = StuckSectionsDetector().detect(LoopWindow(1.0, op, pv))
    assert evidence.decision == STICTION, evidence.note
    assert evidence.details["hold_reversal"] == pytest.approx(2.0, rel=0.1)
    # The same OP with PV following it is no stuck section.
    following = 50.0 + 1.5 * (op - 40) + 0.05 * rng.standard_normal(op.size)
    assert StuckSectionsDetector().detect(LoopWindow(1.0, op, following)).decision == UNDECIDED


def test_a_zig_zag_through_a_hold_is_as_large_as_its_largest_leg():
    """Six swings of 1.5 while PV holds are a reversal of 1.5, not the 9 the legs
    add up to: OP that swings within a stick band never went further out."""
    rng = np.random.default_rng(8)
    swings = 42.0 + 0.75 * (2.0 / np.pi) * np.arcsin(np.sin(np.linspace(0, 12 * np.pi, 720)))
    op = np.concatenate([np.linspace(40, 42, 300), swings, np.full(300, 42.0)])
    pv = 50.0 + 1.5 * (np.minimum(op[:300], 42.0) - 40.0)
    pv = np.concatenate([pv, np.full(1020, 53.0)]) + 0.05 * rng.standard_normal(op.size)
    analysis = analyse_window(LoopWindow(1.0, op, pv))
    assert analysis is not None
    assert analysis.hold_reversal == pytest.approx(1.5, rel=0.15)


def test_too_little_valve_movement_is_not_judged():
    op = 40 + 0.2 * np.random.default_rng(6).standard_normal(1000)
    pv = 50 + 0.1 * np.random.default_rng(7).standard_normal(1000)
    for detector in (StickJumpDetector(), StuckSectionsDetector()):
        evidence = detector.detect(LoopWindow(1.0, op, pv))
        assert evidence.decision == UNDECIDED


def test_slips_into_a_moving_valve_are_episodes():
    """A slip need not end in another hold: on a stiction cycle the valve moves
    on with OP after it, and PV answers the slip fast first, then slower."""
    case = next(c for c in synthetic_library() if c.name == "flow-he-S4-J2-ts1")
    result = case.simulate()
    mv = result.mv[0]
    window = LoopWindow(case.ts, result.op[0], result.pv[0], sp=result.sp[0],
                        process_type="self-regulating")
    analysis = analyse_window(window)
    assert analysis is not None and not analysis.contrary
    moving_on = [e for e in analysis.episodes if e.end - e.jump_at < 10]
    assert len(moving_on) >= 10
    for episode in analysis.episodes:
        # The valve held through the hold (PV leaves it 10 s of lag and dead
        # time after the slip) and moved at its end, the way OP pushed.
        assert np.ptp(mv[episode.start:episode.jump_at - 12]) < 0.05
        assert np.sign(mv[episode.end + 5] - mv[episode.start]) == np.sign(episode.op_travel)


@pytest.mark.parametrize(("dead_time", "lag"), [(60, 5), (60, 30), (120, 15)])
def test_a_delayed_answer_to_an_op_ramp_is_no_slip(dead_time, lag):
    """A healthy valve behind a long dead time: PV holds while OP ramps, then
    leaves the hold slowly, faster and faster (a ramp response), unlike a slip
    (fast first, then slower)."""
    rng = np.random.default_rng(9)
    k = np.arange(1200)
    op = 40.0 + np.clip(k - 200, 0, 300) * 0.03 - np.clip(k - 700, 0, 300) * 0.03
    delayed = np.concatenate([np.full(dead_time, op[0]), op[:-dead_time]])
    response = np.zeros(k.size)
    for i in range(1, k.size):  # first order lag
        response[i] = response[i - 1] + (delayed[i] - 40.0 - response[i - 1]) / lag
    pv = 50.0 + 1.5 * response + 0.03 * rng.standard_normal(k.size)
    analysis = analyse_window(LoopWindow(1.0, op, pv))
    assert analysis is not None and not analysis.episodes


def test_a_small_stick_band_on_a_noisy_flow_shows_at_a_coarser_smoothing():
    """S = 0.5 %, J = 0.25 % under measurement noise: the slips are one to two
    noise bands at three samples' smoothing, so only the coarser scale of
    SMOOTHING_SCALES, with half the band, finds the holds and jumps."""
    case = next(c for c in transient_library() if c.name == "flow-he-S0.5-J0.25-sp-steps-ts1")
    result = case.simulate()
    window = LoopWindow(case.ts, result.op[0], result.pv[0], sp=result.sp[0],
                        process_type="self-regulating")
    analysis = analyse_window(window)
    assert analysis is not None
    finest = find_stick_episodes(window.op, window.pv, gain_sign=analysis.gain_sign,
                                 smoothing=SMOOTHING_SCALES[0], reference=window.sp)
    assert not finest.episodes
    assert len(analysis.episodes) >= 2 and not analysis.contrary
    mv = result.mv[0]
    # The valve slipped the way OP pushed at the end of every episode; in most
    # it held still before (a coarse hold may span a slip smaller than its band).
    held = [np.ptp(mv[e.start:e.jump_at - 15]) < 0.05 * case.S for e in analysis.episodes]
    assert sum(held) >= 2 and sum(held) > len(held) / 2
    for episode in analysis.episodes:
        assert np.sign(mv[episode.end] - mv[episode.start]) == np.sign(episode.op_travel)
    assert StickJumpDetector().decide(analysis).decision == STICTION


@pytest.mark.parametrize("seed", [2001, 2002, 2003, 2004])
def test_a_level_s_slope_turning_to_close_the_level_error_is_a_slip(seed):
    """A level behind a sticky valve on a set-point ramp: integral action pushes
    the valve off the in/outflow balance to bring the level to its new set point,
    so the slope of PV jumps away from its median, the way that closes the
    level's error.  Those slips count (before, only slips back towards the
    median slope did, and most of these windows were called healthy); the same
    loop with a healthy valve stays clean.  Seeds other than the library's."""
    from analytics.synthetic_cases import TRANSIENT_PROCESSES, SyntheticCase, _events, _noise
    from analytics.valves import HeValve

    level = TRANSIENT_PROCESSES["level"]
    setpoint, loads = _events("sp-ramp", level, 2000, 5.0, seed)
    noise = _noise(level.noise_levels[seed % len(level.noise_levels)], seed)
    verdicts = {}
    for label, valve in (("stiction", HeValve(1.25, 0.75)), ("no_stiction", IdealValve())):
        case = SyntheticCase("level-ramp", label, "stick_jump", level.kind, 5.0, 2.0, 0.5,
                             valve, level.model, PIDController.ideal(level.Kc, level.Ti),
                             (*loads, noise), 2000, setpoint)
        result = case.simulate()
        window = LoopWindow(5.0, result.op[0], result.pv[0], sp=result.sp[0],
                            process_type="integrating")
        verdicts[label] = StickJumpDetector().detect(window).decision
    assert verdicts == {"stiction": STICTION, "no_stiction": UNDECIDED}
