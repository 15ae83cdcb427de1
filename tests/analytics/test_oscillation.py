"""Tests of analytics.oscillation against signals whose period, amplitude and
regularity are known by construction, against coloured noise that must not be
reported, and against the labelled industrial loops of the ISDB."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest
from scipy import signal as sps

from analytics.errors import DataError
from analytics.oscillation import (
    REGULARITY_CAP,
    LoopOscillation,
    OscillationReport,
    detect_loop_oscillation,
    detect_oscillations,
)
from tests.shared_data import isdb_labels, load_isdb_loop

N = 2000


def _sine(
    period: float,
    amplitude: float = 1.0,
    noise: float = 0.0,
    seed: int = 0,
    n: int = N,
    phase: float = 0.3,
) -> np.ndarray:
    rng = np.random.default_rng(seed)
    k = np.arange(n)
    return amplitude * np.sin(2 * np.pi * k / period + phase) + noise * rng.standard_normal(n)


def _noise(sd: float, seed: int, n: int = N) -> np.ndarray:
    return sd * np.random.default_rng(seed).standard_normal(n)


def _ar1(phi: float, seed: int, n: int = N) -> np.ndarray:
    e = np.random.default_rng(seed).standard_normal(n)
    return sps.lfilter([1.0], [1.0, -phi], e)


def _jittered(cv: float, seed: int, mean_period: float = 60.0, n: int = 3000) -> np.ndarray:
    """Half sine waves of random length: cycle-to-cycle period spread ``cv``."""
    rng = np.random.default_rng(seed)
    parts, sign, total = [], 1.0, 0
    while total < n:
        h = max(3, round(float(rng.normal(mean_period / 2, cv * mean_period / 2))))
        parts.append(sign * np.sin(np.pi * np.arange(h) / h))
        sign, total = -sign, total + h
    return np.concatenate(parts)[:n] + 0.1 * rng.standard_normal(n)


# ----------------------------------------------------------------------------
# single sinusoid


@pytest.mark.parametrize("period", [9.0, 23.0, 50.0, 137.0, 400.0])
@pytest.mark.parametrize("ts", [1.0, 0.2, 60.0])
def test_sinusoid_period_within_2_percent(period: float, ts: float) -> None:
    x = _sine(period, amplitude=1.0, noise=0.5, seed=int(period))
    rep = detect_oscillations(x, ts)
    assert rep.detected
    assert len(rep.oscillations) == 1
    osc = rep.oscillations[0]
    assert osc.period_s == pytest.approx(period * ts, rel=0.02)
    assert osc.frequency_hz == pytest.approx(1.0 / osc.period_s)
    assert osc.regularity > 1.0
    assert 0.0 < osc.power_fraction <= 1.0


@pytest.mark.parametrize("seed", range(5))
def test_sinusoid_amplitude_2_within_10_percent(seed: int) -> None:
    x = 7.0 + 0.01 * np.arange(N) + _sine(80.0, amplitude=2.0, noise=0.5, seed=seed)
    osc = detect_oscillations(x, 1.0).dominant
    assert osc is not None
    assert osc.amplitude == pytest.approx(2.0, rel=0.10)
    # Variance share of a sine of amplitude 2 (2.0) in sine + noise (2.25).
    assert osc.power_fraction == pytest.approx(2.0 / 2.25, abs=0.05)


def test_noise_free_sinusoid_is_capped_regular() -> None:
    osc = detect_oscillations(_sine(64.0), 1.0).dominant
    assert osc is not None
    assert osc.regularity == REGULARITY_CAP
    assert osc.period_s == pytest.approx(64.0, rel=0.002)


# ----------------------------------------------------------------------------
# noise must not be reported


@pytest.mark.parametrize("n", [1000, 10000])
def test_white_noise_not_detected(n: int) -> None:
    hits = [
        s
        for s in range(20)
        if detect_oscillations(np.random.default_rng(s).standard_normal(n), 1.0).detected
    ]
    assert hits == []


@pytest.mark.parametrize("phi", [0.5, 0.9, 0.99])
def test_ar1_noise_not_detected(phi: float) -> None:
    # Monte Carlo over 1000 series per case gave 0-2 % false detections for
    # strongly red noise; allow one of twenty fixed seeds.
    hits = [s for s in range(20) if detect_oscillations(_ar1(phi, s), 1.0).detected]
    assert len(hits) <= 1, f"AR(1) phi={phi} reported as oscillating for seeds {hits}"


def test_random_walk_not_detected() -> None:
    hits = [
        s
        for s in range(20)
        if detect_oscillations(np.cumsum(np.random.default_rng(s).standard_normal(N)), 1.0).detected
    ]
    assert len(hits) <= 1, f"random walk reported as oscillating for seeds {hits}"


def test_regularity_falls_with_the_cycle_length_spread() -> None:
    """Half-cycle lengths spread by 5 % give a regular oscillation at the right
    period; spread by 60 % the cycles are irregular: the industrial loops the
    Jelali & Huang benchmark flags as oscillating (chemicals_loop21) have that
    spread, so such a signal may be reported, but with a regularity near
    Thornhill's limit of 1, well below that of 30 % and 5 % spreads."""
    medians = {}
    for spread in (0.05, 0.3, 0.6):
        regularity = []
        for s in range(10):
            osc = detect_oscillations(_jittered(spread, s), 1.0).dominant
            regularity.append(0.0 if osc is None else osc.regularity)
            if spread == 0.05:
                assert osc is not None and osc.regularity > 10
                assert osc.period_s == pytest.approx(60.0, rel=0.05)
            if spread == 0.6:
                assert regularity[-1] < 3
        medians[spread] = float(np.median(regularity))
    assert medians[0.05] > medians[0.3] > medians[0.6]


# ----------------------------------------------------------------------------
# several oscillations, stiction-like shapes


def test_two_sinusoids_50_and_230_both_found() -> None:
    x = _sine(50.0, 1.0) + _sine(230.0, 1.0, phase=1.1) + _noise(0.3, 1)
    rep = detect_oscillations(x, 1.0)
    periods = sorted(o.period_s for o in rep.oscillations)
    assert len(periods) == 2
    assert periods[0] == pytest.approx(50.0, rel=0.02)
    assert periods[1] == pytest.approx(230.0, rel=0.02)
    for o in rep.oscillations:
        assert o.regularity > 1
        assert o.amplitude == pytest.approx(1.0, rel=0.1)


def test_multiple_oscillations_sorted_by_power() -> None:
    x = _sine(50.0, 1.0) + _sine(230.0, 0.5, phase=1.1) + _noise(0.3, 2)
    rep = detect_oscillations(x, 1.0)
    assert [round(o.period_s / 10) for o in rep.oscillations] == [5, 23]
    assert rep.oscillations[0].power_fraction > rep.oscillations[1].power_fraction
    assert rep.oscillations[1].amplitude == pytest.approx(0.5, rel=0.1)


@pytest.mark.parametrize("period", [40.0, 80.0, 250.0])
def test_square_wave_found_with_fundamental_period(period: float) -> None:
    k = np.arange(N)
    x = sps.square(2 * np.pi * k / period) + _noise(0.2, 3)
    rep = detect_oscillations(x, 1.0)
    # odd harmonics (3f, 5f, ...) are the same oscillation, not new ones
    assert len(rep.oscillations) == 1
    osc = rep.oscillations[0]
    assert osc.period_s == pytest.approx(period, rel=0.02)
    assert osc.regularity > 1
    assert osc.amplitude == pytest.approx(4 / np.pi, rel=0.1)  # fundamental of a unit square


def test_strong_third_harmonic_is_the_same_oscillation() -> None:
    """A non-sinusoidal limit cycle (fundamental + 50 % third harmonic) is one
    oscillation at the fundamental, not two."""
    x = _sine(90.0) + _sine(30.0, 0.5, phase=0.4) + _noise(0.1, 6)
    rep = detect_oscillations(x, 1.0)
    assert [round(o.period_s) for o in rep.oscillations] == [90]


@pytest.mark.parametrize("period", [40.0, 120.0, 300.0])
def test_triangle_wave_found(period: float) -> None:
    k = np.arange(N)
    x = sps.sawtooth(2 * np.pi * k / period, 0.5) + _noise(0.2, 4)
    rep = detect_oscillations(x, 1.0)
    assert len(rep.oscillations) == 1
    assert rep.oscillations[0].period_s == pytest.approx(period, rel=0.02)
    assert rep.oscillations[0].amplitude == pytest.approx(8 / np.pi**2, rel=0.1)


def test_stiction_limit_cycle_from_simulated_loop() -> None:
    """PI loop on a first-order process with a sticky valve (stick-slip: the
    valve stays put until the demanded move exceeds the stick band, then
    jumps): the classic stiction limit cycle, OP triangular, PV square-ish."""
    n, ts = 6000, 1.0
    kp, ti, tau, stick = 1.0, 10.0, 10.0, 0.5
    rng = np.random.default_rng(5)
    op, pv, y_true = np.zeros(n), np.zeros(n), np.zeros(n)
    mv = integ = y = 0.0
    for i in range(n):
        e = 1.0 - y  # set point 1
        integ += e * ts / ti
        u = kp * (e + integ)
        if abs(u - mv) > stick:  # valve slips to the demanded position
            mv = u
        y += ts / tau * (mv - y)
        op[i], pv[i], y_true[i] = u, y + 0.01 * rng.standard_normal(), y
    res = detect_loop_oscillation(op[1000:], pv[1000:], ts)
    assert res.detected and res.periods_consistent
    assert res.regularity is not None and res.regularity > 1
    assert res.period_s == pytest.approx(_zero_crossing_period(y_true[1000:]) * ts, rel=0.02)


def _zero_crossing_period(x: np.ndarray) -> float:
    """Independent reference: mean spacing of the upward zero crossings of a
    noise-free signal."""
    x = x - x.mean()
    up = np.flatnonzero((x[:-1] < 0) & (x[1:] >= 0))
    return float((up[-1] - up[0]) / (up.size - 1))


# ----------------------------------------------------------------------------
# Hagglund's IAE method


def test_iae_limit_is_the_half_cycle_iae_of_a_sine() -> None:
    """IAE over a half cycle of A sin(wt) is 2A/w, so with a just below A all
    half cycles count as load disturbances and with a just above A none do
    (10 % margins: the discrete sum over 49-51 samples per half cycle)."""
    period, amp, ts = 100.0, 2.0, 0.5
    x = _sine(period, amp)
    half_cycles = 2 * N / period
    below = detect_oscillations(x, ts, iae_amplitude=0.9 * amp).methods["iae"]
    above = detect_oscillations(x, ts, iae_amplitude=1.1 * amp).methods["iae"]
    assert below.statistic >= half_cycles - 2
    assert below.detected
    assert below.period_s == pytest.approx(period * ts, rel=0.01)
    # n_lim = 10 per T_sup = 25 periods, scaled to the 20-period window
    assert below.threshold == pytest.approx(10 * (N / period) / 25, rel=0.02)
    assert above.statistic == 0
    assert not above.detected


def test_methods_are_reported() -> None:
    rep = detect_oscillations(_sine(50.0, noise=0.2), 1.0)
    assert set(rep.methods) == {"spectral_peak", "acf_regularity", "iae"}
    assert rep.methods["acf_regularity"].detected
    assert rep.methods["acf_regularity"].statistic > 1
    assert rep.methods["spectral_peak"].statistic >= rep.methods["spectral_peak"].threshold
    assert rep.methods["iae"].detected


def test_constant_signal_not_detected_without_error() -> None:
    rep = detect_oscillations(np.full(500, 3.0), 1.0)
    assert not rep.detected and rep.oscillations == ()


def test_invalid_input_raises() -> None:
    x = _sine(50.0)
    x[10] = np.nan
    with pytest.raises(DataError, match="NaN"):
        detect_oscillations(x, 1.0)
    with pytest.raises(DataError, match="samples"):
        detect_oscillations(np.zeros(20), 1.0)
    with pytest.raises(DataError):
        detect_oscillations(np.zeros((100, 2)), 1.0)
    with pytest.raises(DataError):
        detect_oscillations(_sine(50.0), 0.0)
    with pytest.raises(DataError, match="op has shape"):
        detect_loop_oscillation(_sine(50.0), _sine(50.0)[:-5], 1.0)
    with pytest.raises(DataError):
        detect_loop_oscillation(None, None, 1.0)


# ----------------------------------------------------------------------------
# loop-level convenience


def test_loop_op_only() -> None:
    res = detect_loop_oscillation(_sine(70.0, 3.0, noise=0.3), None, 2.0)
    assert res.detected
    assert res.period_s == pytest.approx(140.0, rel=0.02)
    assert res.amplitude_op == pytest.approx(3.0, rel=0.1)
    assert res.amplitude_pv is None and res.pv is None
    assert res.periods_consistent is None


def test_loop_pv_only() -> None:
    res = detect_loop_oscillation(None, _sine(70.0, 0.4, noise=0.1), 2.0)
    assert res.detected and res.op is None and res.amplitude_op is None
    assert res.amplitude_pv == pytest.approx(0.4, rel=0.1)


def test_loop_both_consistent() -> None:
    op = _sine(90.0, 3.0, noise=0.3, seed=1)
    pv = _sine(90.0, 1.5, noise=0.3, seed=2, phase=2.0)
    res = detect_loop_oscillation(op, pv, 1.0)
    assert res.detected and res.periods_consistent is True
    assert res.period_s == pytest.approx(90.0, rel=0.02)
    assert res.amplitude_op == pytest.approx(3.0, rel=0.1)
    assert res.amplitude_pv == pytest.approx(1.5, rel=0.1)
    assert res.regularity is not None and res.regularity > 1


def test_loop_one_signal_oscillates_other_amplitude_measured() -> None:
    op = _sine(60.0, 2.0, noise=0.2)
    pv = np.random.default_rng(9).standard_normal(N)  # e.g. a noisy flow PV
    res = detect_loop_oscillation(op, pv, 1.0)
    assert res.detected and res.periods_consistent is None
    assert res.period_s == pytest.approx(60.0, rel=0.02)
    assert res.amplitude_pv is not None and res.amplitude_pv < 1.0


def test_loop_no_oscillation() -> None:
    rng = np.random.default_rng(10)
    res = detect_loop_oscillation(rng.standard_normal(N), rng.standard_normal(N), 1.0)
    assert not res.detected
    assert res.period_s is None and res.amplitude_op is None and res.amplitude_pv is None


# ----------------------------------------------------------------------------
# real plant data (International Stiction Data Base, 14 loops)


def _periodogram_period(x: np.ndarray, ts: float) -> float:
    """Independent reference: highest raw periodogram bin (numpy only) in the
    searched range of periods."""
    n = x.size
    k = np.arange(n)
    xd = x - np.polyval(np.polyfit(k, x, 1), k)
    p = np.abs(np.fft.rfft(xd)) ** 2
    f = np.fft.rfftfreq(n)
    ok = (f >= 1 / (0.3 * n)) & (f <= 1 / 6)
    return float(ts / f[ok][np.argmax(p[ok])])


@dataclass(frozen=True)
class _IsdbResult:
    loop: str
    label: str
    ts: float
    op: OscillationReport
    pv: OscillationReport
    ref_op: float
    ref_pv: float
    both: LoopOscillation

    def report(self, signal: str) -> OscillationReport:
        return self.op if signal == "op" else self.pv


def _isdb_results() -> list[_IsdbResult]:
    rows = []
    for row in isdb_labels():
        _, op, pv = load_isdb_loop(row["loop"])
        ts = float(row["ts_s"])
        rows.append(
            _IsdbResult(
                loop=row["loop"],
                label=row["oscillating"],
                ts=ts,
                op=detect_oscillations(op, ts),
                pv=detect_oscillations(pv, ts),
                ref_op=_periodogram_period(op, ts),
                ref_pv=_periodogram_period(pv, ts),
                both=detect_loop_oscillation(op, pv, ts),
            )
        )
    lines = [
        f"{'loop':7s} {'osc':4s} {'T_op[s]':>9s} {'r_op':>6s} {'T_pv[s]':>9s} {'r_pv':>6s}"
        f" {'prom_op':>7s} {'prom_pv':>7s}"
    ]
    for r in rows:
        cells = []
        for rep in (r.op, r.pv):
            d = rep.dominant
            cells += [
                f"{d.period_s:9.1f}" if d else f"{'-':>9s}",
                f"{d.regularity:6.2f}" if d else f"{'-':>6s}",
            ]
        prom = [f"{rep.methods['spectral_peak'].statistic:7.2f}" for rep in (r.op, r.pv)]
        lines.append(f"{r.loop:7s} {r.label:4s} " + " ".join(cells + prom))
    print("\n" + "\n".join(lines))
    return rows


@pytest.fixture(scope="module")
def isdb_results() -> list[_IsdbResult]:
    return _isdb_results()


@pytest.mark.parametrize("signal", ["op", "pv"])
def test_isdb_oscillating_loops_detected_from_one_signal(
    isdb_results: list[_IsdbResult], signal: str
) -> None:
    yes = [r for r in isdb_results if r.label == "yes"]
    assert len(yes) == 13
    missed = [r.loop for r in yes if not r.report(signal).detected]
    assert missed == [], f"oscillating loops not detected from {signal.upper()} alone: {missed}"


def test_isdb_periods_agree_with_independent_estimates(isdb_results: list[_IsdbResult]) -> None:
    """Period from OP agrees with the one from PV (same loop) and with the
    raw periodogram peak.  25 %: CHEM24's PV has two near-equal spectral
    peaks (440 s and 536 s) and the periodogram of 1000-sample loops is coarse
    (CHEM2: bins at 200 s and 250 s)."""
    bad: list[tuple[object, ...]] = []
    for r in isdb_results:
        if r.label != "yes":
            continue
        if not r.both.periods_consistent:
            bad.append((r.loop, "OP/PV periods inconsistent"))
        for signal, t_ref in (("op", r.ref_op), ("pv", r.ref_pv)):
            dom = r.report(signal).dominant
            assert dom is not None
            if abs(dom.period_s / t_ref - 1) > 0.25:
                bad.append((r.loop, signal, dom.period_s, t_ref))
    assert bad == []


def test_isdb_pap7_non_oscillating_loop_not_reported(isdb_results: list[_IsdbResult]) -> None:
    """PAP7 is labelled non-oscillating.  Its OP carries a faint 30 s ripple
    (visible in the raw ACF) on top of step disturbances, but no band stands
    out of the spectral background (prominence 2.35 < 2.5), so no oscillation."""
    (pap7,) = [r for r in isdb_results if r.loop == "PAP7"]
    assert pap7.label == "no"
    assert not pap7.op.detected
    assert not pap7.pv.detected
    assert not pap7.both.detected
