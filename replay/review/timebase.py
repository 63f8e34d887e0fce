"""An episode's time base as review reads it: seconds per recorded step, and a path moved to another rate.

`control_dt` is the one place that decides how long a recorded step lasts (the
quality flags, the video's clock and its frame rate all ask it), with the one
default for an episode that does not say. `resample` gives a sampled path at a
reference rate, so that a score built from finite differences (the jerk) means
the same at any control rate: where the rates divide evenly it takes the samples
as they are; elsewhere it reads them off the natural cubic spline through the
recorded samples (smooth to the second derivative, so it adds no jerk of its own).
"""

from __future__ import annotations

import math

import numpy as np

from replay.episode import Episode

DEFAULT_CONTROL_HZ = 30.0  # Hz: an episode that names no control rate and whose step times cannot tell one
EVEN = 1e-6  # how near a whole number the ratio of two rates must be for the samples to be taken as they are


def control_dt(episode: Episode) -> float:
    """Seconds per recorded step: the episode's control period, else measured from its step times,
    else 1 / DEFAULT_CONTROL_HZ."""
    meta = episode.meta
    if meta.control_hz and meta.control_dt > 0:
        return float(meta.control_dt)
    if episode.steps > 1:
        span = float(episode.time[-1] - episode.time[0])
        if span > 0:
            return span / (episode.steps - 1)
    return 1.0 / DEFAULT_CONTROL_HZ


def resample(path: np.ndarray, dt: float, ref_dt: float) -> np.ndarray:
    """`path` (T, ...) sampled every `dt` seconds from t = 0, as sampled every `ref_dt` seconds over the same span."""
    steps = len(path)
    ratio = ref_dt / dt
    if steps < 2 or (abs(ratio - round(ratio)) < EVEN and round(ratio) >= 1):
        return path[::max(1, round(ratio))]
    flat = path.reshape(steps, -1).astype(float)
    second = _spline_second_differences(flat)
    count = int(math.floor((steps - 1) / ratio + EVEN)) + 1
    at = np.arange(count) * ratio  # the reference samples' times, in recorded steps
    k = np.clip(np.floor(at).astype(int), 0, steps - 2)
    u = (at - k)[:, None]
    v = 1.0 - u
    out = v * flat[k] + u * flat[k + 1] + ((v**3 - v) * second[k] + (u**3 - u) * second[k + 1]) / 6.0
    return out.reshape((count, *path.shape[1:]))


def _spline_second_differences(flat: np.ndarray) -> np.ndarray:
    """The natural cubic spline's second derivatives at the samples (per step squared; zero at both ends):
    the tridiagonal system M[i-1] + 4 M[i] + M[i+1] = 6 (y[i-1] - 2 y[i] + y[i+1]) solved by elimination."""
    steps = len(flat)
    second = np.zeros_like(flat)
    inner = steps - 2
    if inner < 1:
        return second
    rhs = 6.0 * (flat[2:] - 2.0 * flat[1:-1] + flat[:-2])
    factor = np.empty(inner)
    carried = np.empty_like(rhs)
    previous_factor, previous = 0.0, np.zeros(flat.shape[1])
    for i in range(inner):
        pivot = 4.0 - previous_factor
        previous_factor = factor[i] = 1.0 / pivot
        previous = carried[i] = (rhs[i] - previous) / pivot
    following = np.zeros(flat.shape[1])
    for i in range(inner - 1, -1, -1):
        following = second[i + 1] = carried[i] - factor[i] * following
    return second
