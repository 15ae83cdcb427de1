"""Tests of analytics.signals against closed forms: a sampled sine's crossings and the
autocorrelation of a sine and of white noise."""

import numpy as np
import pytest

from analytics.signals import autocorrelation, upward_crossings, zero_crossings


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
