"""Tests for ptrack.motion.lowpass: the second-order Butterworth filter run forwards and backwards, in numpy."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import signal

from ptrack.motion.lowpass import PAD, butterworth2, filtfilt


@pytest.mark.parametrize(("fps", "hz", "frames"), [(60, 6, 100), (30, 6, PAD + 1), (120, 6, 400), (30, 14.9, 50)])
def test_the_filter_is_scipys(fps, hz, frames):
    """The coefficients are scipy.signal.butter(2, hz / (fps / 2))'s and the result scipy.signal.filtfilt's (its
    default odd padding), to float64 rounding (a few units of 1e-13 on a random walk of 400 steps)."""
    b, a = butterworth2(hz, fps)
    ref_b, ref_a = signal.butter(2, hz / (fps / 2))
    np.testing.assert_allclose(b, ref_b, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(a, ref_a, rtol=1e-12, atol=1e-15)
    x = np.random.default_rng(0).standard_normal((frames, 5, 3)).cumsum(0)
    np.testing.assert_allclose(filtfilt(b, a, x), signal.filtfilt(ref_b, ref_a, x, axis=0), rtol=0, atol=1e-9)


def test_a_constant_passes_and_a_fast_wave_is_removed():
    b, a = butterworth2(6.0, 60.0)
    np.testing.assert_allclose(filtfilt(b, a, np.full(50, 2.5)), 2.5, atol=1e-12)
    t = np.arange(200) / 60.0
    slow, fast = np.sin(2 * np.pi * 1.0 * t), 0.5 * np.sin(2 * np.pi * 25.0 * t)
    out = filtfilt(b, a, slow + fast)
    assert np.abs(out - slow)[20:-20].max() < 0.01


def test_bad_cutoff_or_too_short():
    with pytest.raises(ValueError, match="cutoff"):
        butterworth2(30.0, 60.0)
    with pytest.raises(ValueError, match="cutoff"):
        butterworth2(0.0, 60.0)
    with pytest.raises(ValueError, match="padding"):
        filtfilt(*butterworth2(6.0, 60.0), np.zeros(PAD))
