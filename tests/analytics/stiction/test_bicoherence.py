"""Bicoherence NGI/NLI: checked against analytic limits and closed-loop simulations.

References: Choudhury, Shah & Thornhill, Automatica 40 (2004) 1719-1728 and
their 2008 book; Kim & Powers (1979) for the normalisation.
"""

import numpy as np
import pytest

from analytics.errors import DataError
from analytics.stiction.bicoherence import (
    BicoherenceDetector,
    bicoherence_indices,
    squared_bicoherence,
)
from analytics.stiction.evidence import NO_STICTION, STICTION, UNDECIDED, LoopWindow
from tests.analytics.stiction.test_surrogate import (
    Case,
    aggressive,
    isdb_window,
    linear_sine,
    sticky_he,
)
from tests.shared_data import isdb_labels

ALPHA = 0.05


def wandering_phase(size: int, step: float, rng: np.random.Generator) -> np.ndarray:
    """A random-walk phase: tones with it are not coherent from segment to segment."""
    return np.cumsum(rng.normal(0.0, step, size))


class TestSquaredBicoherence:
    def test_quadratic_phase_coupling_gives_one(self) -> None:
        # Tones at bins 4 and 2 of a 32-sample segment and at their sum: with
        # the third phase locked to the sum of the other two, bic^2 = 1
        # (Kim & Powers 1979); with an independent third phase, bic^2 -> 0.
        rng = np.random.default_rng(0)
        k = np.arange(8192)
        a, b, c = (wandering_phase(k.size, 0.05, rng) for _ in range(3))

        def tone(bin_: int, phase: np.ndarray) -> np.ndarray:
            return np.cos(2 * np.pi * bin_ * k / 32 + phase)

        coupled = tone(4, a) + tone(2, b) + tone(6, a + b)
        independent = tone(4, a) + tone(2, b) + tone(6, c)
        for x, low, high in ((coupled, 0.95, 1.0), (independent, 0.0, 0.05)):
            f1, f2, bic2, _ = squared_bicoherence(x)
            at = (f1 == 4 / 32) & (f2 == 2 / 32)
            assert low <= bic2[at][0] <= high

    def test_gaussian_noise_follows_the_chi_square_limit(self) -> None:
        # Under Gaussianity 2K bic^2 ~ chi^2(2): mean bic^2 = 1/K and a
        # fraction alpha of the bifrequencies exceeds c_alpha / (2K).
        fractions, scaled_means = [], []
        for seed in range(6):
            x = np.random.default_rng(seed).standard_normal(8192)
            _, _, bic2, segments = squared_bicoherence(x, epsilon_quantile=0.0)
            fractions.append(np.mean(bic2 > -2 * np.log(ALPHA) / (2 * segments)))
            scaled_means.append(bic2.mean() * segments)
        assert 0.02 < np.mean(fractions) < 0.10
        assert 0.8 < np.mean(scaled_means) < 1.25

    def test_does_not_depend_on_scale_offset_or_sign(self) -> None:
        x = np.random.default_rng(3).standard_normal(2000) ** 2
        reference = squared_bicoherence(x)[2]
        np.testing.assert_allclose(squared_bicoherence(50.0 - 7.0 * x)[2], reference, rtol=1e-9)

    def test_principal_domain(self) -> None:
        f1, f2, bic2, segments = squared_bicoherence(np.random.default_rng(0).standard_normal(64))
        assert segments == 3
        assert bic2.size == 64  # sum over k1 = 1..15 of min(k1, 16 - k1)
        assert np.all((f2 > 0) & (f2 <= f1) & (f1 + f2 <= 0.5))

    @pytest.mark.parametrize(
        ("x", "message"),
        [(np.ones(100), "constant"), (np.arange(20.0), "fewer than one segment")],
        ids=["constant", "too_short"],
    )
    def test_refuses_what_it_cannot_estimate(self, x: np.ndarray, message: str) -> None:
        with pytest.raises(DataError, match=message):
            squared_bicoherence(x)


class TestIndices:
    @pytest.mark.parametrize("seed", [0, 1, 2])
    def test_gaussian_noise_is_gaussian(self, seed: int) -> None:
        result = bicoherence_indices(np.random.default_rng(seed).standard_normal(8192))
        assert result.segments == 511
        assert result.threshold == pytest.approx(-2 * np.log(ALPHA) / (2 * 511))
        assert result.ngi < 0.001

    def test_asymmetric_wave_is_nonlinear_and_peaks_at_the_fundamental(self) -> None:
        # A pulse train (duty 1/3) has even and odd harmonics locked to the
        # fundamental: bic^2(f0, f0) ~ 1.
        rng = np.random.default_rng(0)
        phase = 2 * np.pi * np.arange(6000) / 40 + wandering_phase(6000, 0.03, rng)
        pulses = (np.sin(phase) > 0.5) + 0.05 * rng.standard_normal(phase.size)
        result = bicoherence_indices(pulses, period_samples=40.0)
        assert result.ngi > 0.05
        assert result.nli > 0.1
        assert result.peak == pytest.approx((1.0, 1.0))
        assert result.samples_per_cycle == pytest.approx(32 / 3)

    def test_half_wave_symmetric_wave_has_no_bispectrum(self) -> None:
        # Odd harmonics only: f1 + f2 of two odd harmonics is even and absent,
        # so the bispectrum vanishes; the test cannot see such a limit cycle.
        rng = np.random.default_rng(0)
        phase = 2 * np.pi * np.arange(6000) / 40 + wandering_phase(6000, 0.03, rng)
        square = np.sign(np.sin(phase)) + 0.05 * rng.standard_normal(phase.size)
        assert bicoherence_indices(square, period_samples=40.0).ngi < 0.001

    def test_odd_cycles_per_segment_cancel_the_leakage_of_a_sinusoid(self) -> None:
        # With an even number of cycles per segment, half-overlapping segments
        # start whole cycles apart, the sinusoid's leakage has the same phase in
        # every segment and adds up to a spurious bic^2 ~ 1; with an odd number
        # it alternates in sign and cancels.
        rng = np.random.default_rng(0)
        x = np.sin(2 * np.pi * np.arange(6000) / 77.7) + 0.1 * rng.standard_normal(6000)
        assert bicoherence_indices(x, period_samples=77.7, cycles_per_segment=2).ngi > 0.05
        assert bicoherence_indices(x, period_samples=77.7).ngi < 0.001

    def test_rejects_a_period_too_short_to_hold_harmonics(self) -> None:
        with pytest.raises(DataError, match="at least 4 samples"):
            bicoherence_indices(np.sin(np.arange(1000.0)), period_samples=3.0)


class TestDetector:
    @pytest.mark.parametrize("seed", [10, 11, 12])
    def test_sticky_valve_limit_cycle_is_stiction(self, seed: int) -> None:
        evidence = BicoherenceDetector().detect(sticky_he(seed))
        assert evidence.decision == STICTION
        assert evidence.details["ngi"] > 0.001
        assert evidence.details["nli"] > 0.01
        assert evidence.confidence > 0

    @pytest.mark.parametrize("case", [linear_sine, aggressive])
    @pytest.mark.parametrize("seed", [10, 11, 12])
    def test_linear_loop_oscillations_are_no_stiction(self, case: Case, seed: int) -> None:
        evidence = BicoherenceDetector().detect(case(seed))
        assert evidence.decision == NO_STICTION
        assert evidence.index is not None and evidence.index <= 0.001

    def test_uses_the_control_error_whose_sign_and_offset_do_not_matter(self) -> None:
        window = sticky_he(10)
        with_sp = BicoherenceDetector().detect(window)
        pv_only = BicoherenceDetector().detect(
            LoopWindow(ts=1.0, op=window.op, pv=window.pv, period_s=window.period_s)
        )
        assert with_sp.index == pytest.approx(pv_only.index)

    @pytest.mark.parametrize(
        ("window", "reason"),
        [
            (LoopWindow(ts=1.0, op=np.sin(np.arange(3000) / 5), pv=None, period_s=31.4),
             "needs PV"),
            (LoopWindow(ts=1.0, op=None, pv=np.sin(np.arange(3000.0))), "no oscillation"),
            (LoopWindow(ts=1.0, op=None, pv=np.sin(np.arange(3000) * 2.0), period_s=3.1),
             "harmonics are not sampled"),
            (LoopWindow(ts=1.0, op=None, pv=np.sin(np.arange(400) / 5), period_s=31.4),
             "segments"),
            (LoopWindow(ts=1.0, op=None, pv=np.ones(3000), period_s=50.0), "constant"),
        ],
        ids=["no_pv", "no_period", "period_too_short", "too_few_cycles", "constant"],
    )
    def test_undecided_with_the_reason(self, window: LoopWindow, reason: str) -> None:
        evidence = BicoherenceDetector().detect(window)
        assert evidence.decision == UNDECIDED
        assert evidence.confidence == 0
        assert reason in evidence.note


def test_isdb_loops() -> None:
    """Jelali & Huang's labelled loops: what the method can and cannot decide.

    Eight segments need about 14 cycles, which seven loops lack (and PAP7
    does not oscillate).  Of the decidable stiction loops only CHEM29 shows
    significant quadratic phase coupling; CHEM24, PAP2 and PAP5 do not, and
    PAP4 (labelled without stiction) does: the bicoherence sees a
    nonlinearity, not its location.
    """
    decisions = {
        row["loop"]: BicoherenceDetector().detect(isdb_window(row["loop"])).decision
        for row in isdb_labels()
    }
    undecided = {name for name, decision in decisions.items() if decision == UNDECIDED}
    assert undecided == {
        "CHEM1", "CHEM2", "CHEM10", "CHEM11", "CHEM12", "CHEM23", "PAP7", "PAP9"
    }
    assert decisions["CHEM29"] == STICTION
