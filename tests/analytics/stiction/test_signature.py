"""Tests of the valve-signature methods (analytics.stiction.signature) against
Lissajous ellipses whose width is known in closed form, the describing function
of the (S, J) valve (thesis Eq. 3.4, ERRATA item 1), closed-loop simulations
with sticky and healthy valves, and the labelled ISDB loops."""

from __future__ import annotations

import dataclasses
import json
import math
from functools import cache

import numpy as np
import pytest

from analytics.describing import choudhury_df
from analytics.errors import DataError
from analytics.lti import TransferFunction
from analytics.oscillation import detect_loop_oscillation
from analytics.simulation import Disturbance, Loop, PIDController, simulate
from analytics.stiction.evidence import (
    INTEGRATING,
    NO_STICTION,
    SELF_REGULATING,
    STICTION,
    UNDECIDED,
    LoopWindow,
    MethodEvidence,
)
from analytics.stiction.signature import (
    EllipseDetector,
    EllipseFit,
    ParallelogramDetector,
    fit_signature_ellipse,
)
from analytics.valves import ChoudhuryValve, HeValve, IdealValve, KanoValve, ValveModel
from tests.shared_data import isdb_labels, load_isdb_loop

# Processes of the simulated loops (gain 1, % of span).  In the flow loop the time
# constant is 1/12 to 1/22 of the stiction cycle, so PV follows the valve; in the
# slow loop it is 1/6 to 1/16; the level loop integrates.
PROCESSES = {
    "flow": TransferFunction.fopdt(1.0, 2.0, 0.5),
    "slow": TransferFunction.fopdt(1.0, 10.0, 2.0),
    "level": TransferFunction.integrating(0.02, 3.0),
}
# (Kc, Ti, dt, duration): PI tunings and sampling of each process.
Tuning = tuple[float, float, float, float]
FLOW_PI = (0.2, 1.0, 0.1, 1400.0)
SLOW_PI = (0.5, 10.0, 0.5, 5000.0)
SLOW_FAST_PI = (1.0, 5.0, 0.5, 5000.0)
LEVEL_PI = (5.0, 50.0, 1.0, 8000.0)
SETTLE_S = 1000.0


@cache
def closed_loop(
    process: str,
    valve: ValveModel,
    tuning: Tuning,
    *,
    noise: float = 0.05,
    sine: tuple[float, float] | None = None,
    seed: int = 1,
) -> LoopWindow:
    """A simulated window with OP, PV and MV, its period from the oscillation module.

    ``sine`` is an external disturbance ``(amplitude, period_s)`` on PV; the
    measurement carries white noise of standard deviation ``noise``.  The first
    ``SETTLE_S`` seconds (a set-point step and the start-up) are dropped.
    """
    kc, ti, dt, duration = tuning
    disturbances = [Disturbance("noise", noise, at="measurement", seed=seed)]
    if sine is not None:
        disturbances.append(Disturbance("sine", sine[0], period=sine[1]))
    loop = Loop(
        PIDController.ideal(kc, ti), valve=valve, setpoint=[(10.0, 51.0)],
        disturbances=tuple(disturbances),
    )
    result = simulate(PROCESSES[process], loop, dt=dt, duration=duration)
    keep = slice(int(SETTLE_S / dt), None)
    op, pv, mv = result.op[0][keep], result.pv[0][keep], result.mv[0][keep]
    oscillation = detect_loop_oscillation(op, pv, dt)
    return LoopWindow(
        ts=dt, op=op, pv=pv, mv=mv, period_s=oscillation.period_s,
        process_type=INTEGRATING if process == "level" else SELF_REGULATING,
    )


def without_mv(window: LoopWindow) -> LoopWindow:
    return dataclasses.replace(window, mv=None)


def apparent_stiction(window: LoopWindow, use_mv: bool) -> float:
    """Apparent stiction of the OP-MV (or OP-PV) ellipse of a simulated window."""
    valve = window.mv if use_mv else window.pv
    assert window.op is not None and valve is not None and window.period_samples is not None
    return fit_signature_ellipse(window.op, valve, window.period_samples).apparent_stiction


def index_of(ev: MethodEvidence) -> float:
    assert ev.index is not None, ev.note
    return ev.index


def lissajous(phase: float, *, op_amplitude: float = 2.0, pv_amplitude: float = 1.0,
              period: float = 100.0, cycles: int = 20) -> tuple[np.ndarray, np.ndarray]:
    k = np.arange(int(cycles * period))
    op = 40.0 + op_amplitude * np.sin(2 * np.pi * k / period)
    pv = 60.0 + pv_amplitude * np.sin(2 * np.pi * k / period - phase)
    return op, pv


# ----------------------------------------------------------------------------
# fit_signature_ellipse


class TestFitSignatureEllipse:
    @pytest.mark.parametrize("phase_deg", [10, 30, 60, 90, 120, 170])
    @pytest.mark.parametrize("pv_amplitude", [0.01, 1.0, 50.0])
    def test_width_of_a_lissajous_ellipse(self, phase_deg: float, pv_amplitude: float) -> None:
        # x = A sin t, y = B sin(t - phi): the chord through the centre along x is
        # 2 A |sin phi| whatever B, the extent along x is 2 A.
        phase = math.radians(phase_deg)
        op, pv = lissajous(phase, pv_amplitude=pv_amplitude)
        fit = fit_signature_ellipse(op, pv, 100)
        assert fit.apparent_stiction == pytest.approx(4.0 * abs(math.sin(phase)), rel=0.01)
        assert fit.op_amplitude == pytest.approx(2.0, rel=0.01)
        assert fit.width_ratio == pytest.approx(abs(math.sin(phase)), rel=0.01)
        assert fit.centre == pytest.approx((40.0, 60.0), abs=1e-3 * (1 + pv_amplitude))
        assert fit.residual < 0.03

    @pytest.mark.parametrize("phase_deg", [20, 45, 90, 135])
    def test_apparent_stiction_is_choudhurys_formula_of_the_axes(self, phase_deg: float) -> None:
        # Choudhury et al. (2006): 2 m n / sqrt(m^2 sin^2 alpha + n^2 cos^2 alpha).
        op, pv = lissajous(math.radians(phase_deg), pv_amplitude=1.5)
        fit = fit_signature_ellipse(op, pv, 100)
        m, n = fit.semi_axes
        alpha = fit.angle
        assert m >= n > 0
        assert -math.pi / 2 < alpha <= math.pi / 2
        formula = 2 * m * n / math.sqrt(m**2 * math.sin(alpha) ** 2 + n**2 * math.cos(alpha) ** 2)
        assert fit.apparent_stiction == pytest.approx(formula, rel=1e-9)

    @pytest.mark.parametrize(
        ("S", "J", "A"),
        [(4.0, 2.0, 2.5), (4.0, 2.0, 5.0), (4.0, 2.0, 10.0), (4.0, 0.0, 3.0),
         (4.0, 4.0, 5.0), (2.0, 1.0, 3.0)],
    )
    def test_op_mv_width_matches_the_describing_function(
        self, S: float, J: float, A: float
    ) -> None:
        # A Choudhury valve driven by A sin(wt) passes the fundamental N(A) A sin(wt + arg N):
        # the OP-MV ellipse is 2 A |sin(arg N)| wide (thesis Eq. 3.4, ERRATA item 1).
        period = 200
        k = np.arange(20 * period)
        op = 50.0 + A * np.sin(2 * np.pi * k / period)
        mv = ChoudhuryValve(S, J).simulate(op)
        N = complex(choudhury_df([A], S, J)[0])
        fit = fit_signature_ellipse(op, mv, period)
        assert fit.apparent_stiction == pytest.approx(2 * A * abs(N.imag) / abs(N), rel=0.015)

    def test_a_healthy_valve_gives_a_segment_of_zero_width(self) -> None:
        op, _ = lissajous(0.0)
        fit = fit_signature_ellipse(op, IdealValve().simulate(op), 100)
        assert fit.apparent_stiction == 0.0
        assert fit.semi_axes[1] == 0.0
        assert fit.width_ratio == 0.0

    @pytest.mark.parametrize("phase_deg", [0, 60, 90])
    def test_the_fit_is_its_json_read_back(self, phase_deg: float) -> None:
        """``from_dict`` inverts ``to_dict`` through JSON text, the degenerate segment
        (``phase 0``, MV = OP) included; a diagnosis stored without the geometry is
        refused with the missing key."""
        op, pv = lissajous(math.radians(phase_deg), pv_amplitude=1.5)
        fit = fit_signature_ellipse(op, op if phase_deg == 0 else pv, 100)
        stored = json.loads(json.dumps(fit.to_dict()))
        assert EllipseFit.from_dict(stored) == fit
        assert stored["width_ratio"] == fit.width_ratio
        old = {k: stored[k] for k in ("apparent_stiction", "width_ratio", "op_amplitude",
                                      "residual")}
        with pytest.raises(KeyError, match="centre"):
            EllipseFit.from_dict(old)

    def test_band_limited_noise_is_not_an_ellipse(self) -> None:
        rng = np.random.default_rng(3)
        op, pv = rng.standard_normal((2, 20000))
        assert fit_signature_ellipse(op, pv, 50).residual > 0.4

    def test_invalid_input(self) -> None:
        op, pv = lissajous(1.0, cycles=3)
        with pytest.raises(DataError, match="at least 4"):
            fit_signature_ellipse(op, pv, 100)
        op, pv = lissajous(1.0)
        with pytest.raises(DataError, match="equal length"):
            fit_signature_ellipse(op, pv[:-1], 100)
        with pytest.raises(DataError, match=r"pv .*does not oscillate"):
            fit_signature_ellipse(op, np.full_like(op, 3.0), 100)


class TestApparentStictionTracksS:
    """The closed-loop apparent stiction is a steady fraction of S for one loop.

    Found with Kano valves, J = S / 2, S = 1 to 8: 0.88-0.90 S in the flow loop
    (OP-PV and OP-MV); 0.64-0.78 S (OP-PV) and 0.69-0.84 S (OP-MV) in the slow
    loop, the lower values for S = 1-2, where the noise makes the cycle irregular.
    """

    @pytest.mark.parametrize(
        ("process", "tuning", "use_mv", "low", "high", "spread"),
        [
            ("flow", FLOW_PI, False, 0.85, 0.95, 1.05),
            ("flow", FLOW_PI, True, 0.85, 0.95, 1.05),
            ("slow", SLOW_PI, False, 0.6, 0.85, 1.25),
            ("slow", SLOW_PI, True, 0.65, 0.9, 1.25),
        ],
    )
    def test_proportional_to_S(
        self, process: str, tuning: Tuning, use_mv: bool, low: float, high: float, spread: float
    ) -> None:
        ratios = [
            apparent_stiction(closed_loop(process, KanoValve(S, S / 2), tuning), use_mv) / S
            for S in (1.0, 2.0, 4.0, 8.0)
        ]
        assert low <= min(ratios) and max(ratios) <= high
        assert max(ratios) / min(ratios) < spread

    @pytest.mark.parametrize(("fs", "fd"), [(2.0, 1.0), (3.0, 2.0), (4.0, 1.0)])
    def test_he_valve_within_the_stick_band(self, fs: float, fd: float) -> None:
        # He's S = fs + fd (thesis Eq. 1.2): apparent stiction 0.85-0.97 S here.
        width = apparent_stiction(closed_loop("slow", HeValve(fs, fd), SLOW_FAST_PI), False)
        assert 0.75 * (fs + fd) <= width <= fs + fd


# ----------------------------------------------------------------------------
# EllipseDetector


STICKY_LOOPS = [
    ("flow", KanoValve(2.0, 1.0), FLOW_PI),
    ("flow", KanoValve(4.0, 4.0), FLOW_PI),
    ("slow", KanoValve(4.0, 2.0), SLOW_PI),
    ("slow", HeValve(3.0, 2.0), SLOW_FAST_PI),
]


class TestEllipseDetector:
    @pytest.mark.parametrize(("process", "valve", "tuning"), STICKY_LOOPS)
    @pytest.mark.parametrize("use_mv", [False, True])
    def test_flags_sticky_valves(
        self, process: str, valve: ValveModel, tuning: Tuning, use_mv: bool
    ) -> None:
        window = closed_loop(process, valve, tuning)
        ev = EllipseDetector().detect(window if use_mv else without_mv(window))
        assert ev.decision == STICTION
        assert index_of(ev) >= 0.75
        assert ev.details["uses_mv"] == float(use_mv)
        assert 0 < ev.confidence <= 1

    def test_rejects_an_external_disturbance_faster_than_the_integral_time(self) -> None:
        # Period 30 s, Ti = 10 s (omega Ti = 2.1): OP leads PV by 25 degrees.
        window = closed_loop("slow", IdealValve(), SLOW_PI, sine=(2.0, 30.0))
        ev = EllipseDetector().detect(without_mv(window))
        assert ev.decision == NO_STICTION
        expected = 1 / math.sqrt(1 + (2 * math.pi / 30.0 * 10.0) ** 2)  # |sin arg C(jw)|
        assert index_of(ev) == pytest.approx(expected, abs=0.05)

    def test_rejects_aggressive_tuning(self) -> None:
        # Kc = 7 on K = 1, tau = 10, theta = 2 exceeds the ultimate gain: OP cycles
        # between its limits at the ultimate frequency, where PI adds little phase.
        window = closed_loop("slow", IdealValve(), (7.0, 10.0, 0.5, 5000.0), noise=0.2)
        ev = EllipseDetector().detect(without_mv(window))
        assert ev.decision == NO_STICTION
        assert index_of(ev) < 0.2

    def test_slow_disturbance_needs_mv(self) -> None:
        # A disturbance slower than Ti puts OP and PV in quadrature like stiction
        # (the documented limit of the phase rule); the OP-MV ellipse of the
        # healthy valve has zero width.
        window = closed_loop("slow", IdealValve(), SLOW_PI, sine=(2.0, 200.0))
        assert EllipseDetector().detect(without_mv(window)).decision == STICTION
        ev = EllipseDetector().detect(window)
        assert ev.decision == NO_STICTION
        assert index_of(ev) == 0.0

    def test_integrating_process_needs_mv(self) -> None:
        window = closed_loop("level", HeValve(3.0, 2.0), LEVEL_PI)
        ev = EllipseDetector().detect(without_mv(window))
        assert ev.decision == UNDECIDED
        assert "integrating" in ev.note
        assert EllipseDetector().detect(window).decision == STICTION

    def test_noise_driven_resonance_is_undecided(self) -> None:
        # Ti = 1.5 s makes the loop ring; the noise keeps it ringing with a wandering
        # amplitude that no ellipse explains.
        window = closed_loop("slow", IdealValve(), (0.8, 1.5, 0.5, 5000.0), noise=0.2)
        ev = EllipseDetector().detect(without_mv(window))
        assert ev.decision == UNDECIDED
        assert ev.details["residual"] > EllipseDetector().max_residual

    def test_undecided_without_what_it_needs(self) -> None:
        window = without_mv(closed_loop("flow", KanoValve(2.0, 1.0), FLOW_PI))
        detector = EllipseDetector()
        assert "no PV" in detector.detect(dataclasses.replace(window, pv=None)).note
        assert "no OP" in detector.detect(dataclasses.replace(window, op=None)).note
        assert "does not oscillate" in detector.detect(
            dataclasses.replace(window, period_s=None)
        ).note
        assert window.op is not None and window.pv is not None
        short = dataclasses.replace(window, op=window.op[:1500], pv=window.pv[:1500])
        assert "cycles" in detector.detect(short).note
        for ev in (detector.detect(dataclasses.replace(window, period_s=None)),
                   detector.detect(short)):
            assert ev.decision == UNDECIDED and ev.confidence == 0.0

    def test_settings_are_keyword_only(self) -> None:
        assert EllipseDetector(width_ratio_threshold=0.5).width_ratio_threshold == 0.5
        with pytest.raises(TypeError):
            EllipseDetector(0.5)  # type: ignore[call-arg]


# ----------------------------------------------------------------------------
# ParallelogramDetector


class TestParallelogramDetector:
    @pytest.mark.parametrize("S", [1.0, 2.0, 3.0])
    def test_index_is_the_sticking_share_of_a_kano_valve(self, S: float) -> None:
        # A Kano valve under a triangular OP of stroke H sticks after each reversal
        # until OP has travelled S: a share S / H of the time.  The block holding
        # the turn and the slip counts as moving: one of the 12 blocks per stroke.
        stroke, period = 4.0, 240
        op = stroke * np.abs((np.arange(20 * period) % period) / (period / 2) - 1)
        window = LoopWindow(ts=1.0, op=op, pv=op, mv=KanoValve(S, S / 2).simulate(op),
                            period_s=float(period))
        ev = ParallelogramDetector().detect(window)
        assert index_of(ev) == pytest.approx(S / stroke - 2 / 24, abs=0.02)

    @pytest.mark.parametrize(
        ("process", "valve", "tuning", "use_mv"),
        [
            ("flow", KanoValve(2.0, 1.0), FLOW_PI, False),
            ("flow", KanoValve(4.0, 2.0), FLOW_PI, False),
            ("flow", KanoValve(4.0, 4.0), FLOW_PI, False),
            ("slow", KanoValve(4.0, 2.0), SLOW_PI, False),
            ("slow", KanoValve(4.0, 4.0), SLOW_PI, True),
            ("slow", HeValve(4.0, 1.0), SLOW_FAST_PI, True),
            ("level", HeValve(3.0, 2.0), LEVEL_PI, True),
        ],
    )
    def test_flags_sticky_valves(
        self, process: str, valve: ValveModel, tuning: Tuning, use_mv: bool
    ) -> None:
        window = closed_loop(process, valve, tuning)
        ev = ParallelogramDetector().detect(window if use_mv else without_mv(window))
        assert ev.decision == STICTION
        assert index_of(ev) > 0.3

    @pytest.mark.parametrize("use_mv", [False, True])
    def test_rejects_an_external_disturbance(self, use_mv: bool) -> None:
        window = closed_loop("flow", IdealValve(), FLOW_PI, sine=(2.0, 20.0))
        ev = ParallelogramDetector().detect(window if use_mv else without_mv(window))
        assert ev.decision == NO_STICTION
        assert index_of(ev) < (0.01 if use_mv else 0.13)

    def test_rejects_aggressive_tuning(self) -> None:
        window = closed_loop("slow", IdealValve(), (7.0, 10.0, 0.5, 5000.0), noise=0.2)
        ev = ParallelogramDetector().detect(without_mv(window))
        assert ev.decision == NO_STICTION
        assert index_of(ev) < 0.1

    def test_slow_process_blurs_the_signature(self) -> None:
        # PV of the slow loop keeps moving after each slip: between the thresholds.
        window = closed_loop("slow", KanoValve(4.0, 4.0), SLOW_PI)
        ev = ParallelogramDetector().detect(without_mv(window))
        assert ev.decision == UNDECIDED
        assert 0.15 <= index_of(ev) <= 0.25

    def test_integrating_process_needs_mv(self) -> None:
        window = closed_loop("level", HeValve(3.0, 2.0), LEVEL_PI)
        ev = ParallelogramDetector().detect(without_mv(window))
        assert ev.decision == UNDECIDED
        assert "integrating" in ev.note

    def test_oscillation_buried_in_noise_is_undecided(self) -> None:
        window = closed_loop("slow", IdealValve(), (0.8, 1.5, 0.5, 5000.0), noise=0.2)
        ev = ParallelogramDetector().detect(without_mv(window))
        assert ev.decision == UNDECIDED
        assert "moves per cycle" in ev.note

    def test_undecided_without_what_it_needs(self) -> None:
        window = closed_loop("flow", KanoValve(2.0, 1.0), FLOW_PI)
        detector = ParallelogramDetector()
        no_valve = dataclasses.replace(window, mv=None, pv=None)
        assert detector.detect(no_valve).decision == UNDECIDED
        assert "no PV" in detector.detect(no_valve).note
        ev = detector.detect(dataclasses.replace(window, period_s=None))
        assert ev.decision == UNDECIDED and ev.index is None

    def test_noise_on_a_flat_section_is_not_movement(self) -> None:
        # The square PV of a flow loop with white noise as large as a fifth of the
        # jump: the noise-aware steady band keeps the flat tops steady.
        rng = np.random.default_rng(0)
        t = np.arange(6000.0)
        pv = np.sign(np.sin(2 * np.pi * t / 150)) + 0.2 * rng.standard_normal(t.size)
        op = -np.cumsum(np.sign(np.sin(2 * np.pi * t / 150))) / 40
        ev = ParallelogramDetector().detect(LoopWindow(ts=1.0, op=op, pv=pv, period_s=150.0))
        assert ev.decision == STICTION
        assert index_of(ev) > 0.6


# ----------------------------------------------------------------------------
# ISDB (Jelali & Huang 2010): 10 loops labelled stiction, 4 not


@cache
def isdb_evidence() -> dict[str, tuple[str, dict[str, MethodEvidence]]]:
    out = {}
    for row in isdb_labels():
        t, op, pv = load_isdb_loop(row["loop"])
        ts = float(t[1] - t[0])
        window = LoopWindow(ts=ts, op=op, pv=pv,
                            period_s=detect_loop_oscillation(op, pv, ts).period_s)
        out[row["loop"]] = (
            row["label"],
            {d.name: d.detect(window) for d in (EllipseDetector(), ParallelogramDetector())},
        )
    return out


class TestIsdb:
    @pytest.mark.parametrize(("method", "min_hits"), [("ellipse", 7), ("parallelogram", 4)])
    def test_no_false_alarm_and_most_sticky_loops_found(self, method: str, min_hits: int) -> None:
        results = isdb_evidence()
        hits = 0
        for label, evidence in results.values():
            decision = evidence[method].decision
            if label == NO_STICTION:
                assert decision != STICTION
            elif decision == STICTION:
                hits += 1
        assert hits >= min_hits

    @pytest.mark.parametrize("method", ["ellipse", "parallelogram"])
    def test_index_ranks_sticky_loops_above_healthy_ones(self, method: str) -> None:
        sticky: list[float] = []
        healthy: list[float] = []
        for label, evidence in isdb_evidence().values():
            index = evidence[method].index
            if index is not None:
                (sticky if label == STICTION else healthy).append(index)
        assert min(sticky) > max(healthy)

    def test_pap7_does_not_oscillate(self) -> None:
        _, evidence = isdb_evidence()["PAP7"]
        assert all(ev.decision == UNDECIDED for ev in evidence.values())
