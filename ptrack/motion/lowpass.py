"""A zero-phase low-pass filter for trajectories: a second-order Butterworth run forwards and backwards, as
`scipy.signal.filtfilt(*scipy.signal.butter(2, cutoff / (fps / 2)), x, axis=0)` computes it (odd extension of 3 x 3
samples at each end, each pass started in the steady state of its first sample), in numpy: importing scipy.signal
costs about 0.6 s, which is a twentieth of a quick footage run (`scripts/bench_video.py`).

    b, a = butterworth2(cutoff_hz, fps)    # the filter's coefficients, (3,) each, a[0] = 1
    y = filtfilt(b, a, x)                  # x (T, ...) -> y (T, ...), T > PAD

Shapes: T samples along the first axis; any trailing axes are filtered alike."""

from __future__ import annotations

import math

import numpy as np

#: samples of odd extension at each end (scipy's default, 3 x the filter's length): a series must be longer
PAD = 9


def butterworth2(cutoff_hz: float, fps: float) -> tuple[np.ndarray, np.ndarray]:
    """The second-order Butterworth low-pass at `cutoff_hz` for samples at `fps` (0 < cutoff < fps / 2), by the
    bilinear transform with the cutoff prewarped: -> b, a (3,) each, a[0] = 1."""
    if not 0 < cutoff_hz < fps / 2:
        raise ValueError(f"butterworth2: the cutoff {cutoff_hz} Hz must lie in (0, {fps / 2}) at {fps} fps")
    k = math.tan(math.pi * cutoff_hz / fps)
    norm = 1.0 / (1.0 + math.sqrt(2.0) * k + k * k)
    b0 = k * k * norm
    b = np.array([b0, 2.0 * b0, b0])
    a = np.array([1.0, 2.0 * (k * k - 1.0) * norm, (1.0 - math.sqrt(2.0) * k + k * k) * norm])
    return b, a


def _steady_state(b: np.ndarray, a: np.ndarray) -> np.ndarray:
    """The filter's state after a unit step has run forever (scipy's `lfilter_zi`): -> (2,)."""
    companion_t = np.array([[-a[1], 1.0], [-a[2], 0.0]])
    return np.linalg.solve(np.eye(2) - companion_t, b[1:] - a[1:] * b[0])


def _run(b: np.ndarray, a: np.ndarray, x: np.ndarray, state: np.ndarray) -> np.ndarray:
    """The filter along axis 0 of x (T, ...), transposed direct form II, from `state` (2, ...) -> (T, ...)."""
    y = np.empty_like(x)
    z0, z1 = state[0].copy(), state[1].copy()
    for n in range(x.shape[0]):
        xn = x[n]
        yn = b[0] * xn + z0
        z0 = b[1] * xn - a[1] * yn + z1
        z1 = b[2] * xn - a[2] * yn
        y[n] = yn
    return y


def filtfilt(b: np.ndarray, a: np.ndarray, x: np.ndarray) -> np.ndarray:
    """x (T, ...) with T > `PAD` through the filter (b, a) (`butterworth2`) forwards, then backwards: no phase
    shift, the gain squared. -> (T, ...) float64."""
    x = np.asarray(x, dtype=np.float64)
    if x.shape[0] <= PAD:
        raise ValueError(f"filtfilt: {x.shape[0]} samples; the filter's end padding needs more than {PAD}")
    ext = np.concatenate([2 * x[0] - x[PAD:0:-1], x, 2 * x[-1] - x[-2 : -PAD - 2 : -1]])
    zi = _steady_state(b, a).reshape(2, *([1] * (x.ndim - 1)))
    y = _run(b, a, ext, zi * ext[0])
    y = _run(b, a, y[::-1], zi * y[-1])[::-1]
    return y[PAD:-PAD]
