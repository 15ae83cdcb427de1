"""Tests of analytics.signals against closed forms: a sampled sine's crossings, the
autocorrelation of a sine and of white noise, a line's trend and a sine's spectrum."""

import numpy as np
import pytest

from analytics.signals import (
    autocorrelation,
    detrend,
    power_spectrum,
    spectrum,
    upward_crossings,
    zero_crossings,
)


def test_crossings_of_a_sampled_sine_are_its_zeros():
    """sin(2 pi t / 40): zeros every 20 samples, upward ones at 0, 40, 80, ..."""
    t = np.arange(401.0)
    y = np.sin(2 * np.pi * (t + 0.3) / 40)  # no sample falls on a zero
    np.testing.assert_allclose(zero_crossings(y), np.arange(19.7, 400, 20), atol=0.02)
    np.testing.assert_allclose(upward_crossings(y), np.arange(39.7, 400, 40), atol=0.02)


def test_autocorrelation_of_a_sine_is_a_cosine_and_of_white_noise_a_spike():
    n = 20000
    t = np.arange(n)
    # biased estimate: the lag-k value of a sine is (1 - k/n) cos(2 pi k / P)
    acf = autocorrelation(np.sin(2 * np.pi * t / 50), 100)
    k = np.arange(101)
    np.testing.assert_allclose(acf, (1 - k / n) * np.cos(2 * np.pi * k / 50), atol=2e-3)
    white = autocorrelation(np.random.default_rng(1).standard_normal(n), 20)
    assert white[0] == 1.0 and np.abs(white[1:]).max() < 4 / np.sqrt(n)


def test_autocorrelation_leaves_out_missing_samples_and_refuses_too_few():
    x = np.array([1.0, np.nan, -1.0, 1.0, -1.0])
    np.testing.assert_allclose(autocorrelation(x, 3), autocorrelation(x[np.isfinite(x)], 3))
    with pytest.raises(ValueError, match="at least 2 finite samples"):
        autocorrelation([np.nan, 1.0], 3)


def test_detrend_removes_a_line_and_keeps_what_is_orthogonal_to_it():
    k = np.arange(200.0)
    wave = np.cos(2 * np.pi * k / 200)  # orthogonal to constants and (nearly) to the ramp
    wave -= np.polyval(np.polyfit(k, wave, 1), k)
    np.testing.assert_allclose(detrend(3.0 + 0.25 * k + wave), wave, atol=1e-12)
    assert detrend([5.0]).tolist() == [0.0]


@pytest.mark.parametrize("n", [240, 241])
def test_spectrum_of_a_sine_peaks_at_its_frequency_and_keeps_parseval(n):
    """A sine of 12 samples: the peak at 1/12 cycles per sample, with or without padding,
    and the channels sum to n times the signal's energy (Parseval, one-sided)."""
    x = np.sin(2 * np.pi * np.arange(n) / 12) + 0.1
    for pad in (False, True):
        s = spectrum(x - x.mean(), pad=pad)
        assert s.n == n and s.P.size == s.nfft // 2 + 1 and s.f[1] == 1.0 / s.nfft
        assert (s.nfft == n) if not pad else (s.nfft >= 2 * n)
        assert s.f[int(np.argmax(s.P))] == pytest.approx(1 / 12, abs=1 / s.nfft)
        twice = 2.0 * s.P[1:] if s.nfft % 2 else np.append(2.0 * s.P[1:-1], s.P[-1])
        assert s.P[0] + twice.sum() == pytest.approx(s.nfft * np.sum((x - x.mean()) ** 2))
        assert s.total == pytest.approx(s.P[1:].sum())
    padded = spectrum(x, pad=True)  # no wrap-around: the padded transform inverts to x
    np.testing.assert_allclose(np.fft.irfft(padded.X, padded.nfft)[:n], x, atol=1e-12)


def test_power_spectrum_peaks_at_a_sine_s_period_and_refuses_too_few_samples():
    """The plotted spectrum: periods longest first (the window first), power 1 at the peak."""
    ts, n = 2.0, 400
    x = 5.0 + np.sin(2 * np.pi * ts * np.arange(n) / 40.0)  # period 40 s: channel 20
    periods, power = power_spectrum(x, ts)
    assert periods[0] == n * ts and np.all(np.diff(periods) < 0)
    assert periods[int(np.argmax(power))] == pytest.approx(40.0) and power.max() == 1.0
    with pytest.raises(ValueError, match="at least 8 finite samples, got 3"):
        power_spectrum([1.0, 2.0, 3.0, np.nan], 1.0)
