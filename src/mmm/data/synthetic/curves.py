"""Time curves of the procedural animation: minimum-jerk easing, keyframe and Hermite interpolation
through knots, Gaussian smoothing along the frames and smooth random noise.
"""

from __future__ import annotations

import numpy as np


def smoothstep(x):
    """Minimum-jerk ease 0 -> 1 on [0, 1] (clipped outside)."""
    x = np.clip(x, 0.0, 1.0)
    return x * x * x * (x * (x * 6.0 - 15.0) + 10.0)


def keyframes(t: np.ndarray, times, values) -> np.ndarray:
    """Piecewise minimum-jerk interpolation through keys (zero velocity at each key); values (K, ...)."""
    times = np.asarray(times, dtype=np.float64)
    values = np.asarray(values, dtype=np.float64)
    idx = np.clip(np.searchsorted(times, t, side="right") - 1, 0, len(times) - 2)
    t0, t1 = times[idx], times[idx + 1]
    u = smoothstep((t - t0) / np.maximum(t1 - t0, 1e-9))
    u = u.reshape(u.shape + (1,) * (values.ndim - 1))
    return values[idx] + (values[idx + 1] - values[idx]) * u


def hermite(t: np.ndarray, times, values, slopes) -> np.ndarray:
    """Piecewise cubic Hermite through (time, value, slope) knots; constant outside."""
    times, values, slopes = (np.asarray(a, dtype=np.float64) for a in (times, values, slopes))
    idx = np.clip(np.searchsorted(times, t, side="right") - 1, 0, len(times) - 2)
    h = np.maximum(times[idx + 1] - times[idx], 1e-9)
    u = np.clip((t - times[idx]) / h, 0.0, 1.0)
    u2, u3 = u * u, u * u * u
    out = (
        (2 * u3 - 3 * u2 + 1) * values[idx]
        + (u3 - 2 * u2 + u) * h * slopes[idx]
        + (-2 * u3 + 3 * u2) * values[idx + 1]
        + (u3 - u2) * h * slopes[idx + 1]
    )
    out = np.where(t < times[0], values[0], out)
    return np.where(t > times[-1], values[-1], out)


def gaussian_smooth(x: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian filter along axis 0 with edge replication."""
    if sigma <= 0:
        return x.copy()
    radius = int(3.0 * sigma + 0.5)
    k = np.exp(-0.5 * (np.arange(-radius, radius + 1) / sigma) ** 2)
    k /= k.sum()
    pad = np.concatenate([np.repeat(x[:1], radius, axis=0), x, np.repeat(x[-1:], radius, axis=0)], axis=0)
    flat = pad.reshape(pad.shape[0], -1)
    out = np.stack([np.convolve(flat[:, j], k, mode="valid") for j in range(flat.shape[1])], axis=1)
    return out.reshape(x.shape)


def smooth_noise(rng: np.random.Generator, n: int, sigma: float, dims: int = 1) -> np.ndarray:
    """Smooth random signal (n, dims) with unit standard deviation (frame-correlated by sigma)."""
    pad = int(3 * sigma) + 1
    white = rng.standard_normal((n + 2 * pad, dims))
    sm = gaussian_smooth(white, sigma)[pad : pad + n]
    return sm / max(float(sm.std()), 1e-6)
