"""The vehicle's measured trajectory, and the twin driven along it.

A recording gives the vehicle's position and speed as two noisy channels. Integrating the speed
random-walks away from the positions (millimetres over a pass, at 5 m/s a millisecond of timing
error, which a magnet's response to the rail's short waves does not forgive), and the raw
positions carry their own noise. So the twin is driven along the positions smoothed by a local
cubic fit over ``smooth_s`` (Savitzky-Golay: the vehicle's speed changes over seconds, the sensor
noise from sample to sample). Each block ramps the speed to the trajectory's speed (the fit's
derivative) at the block's end, plus the correction that brings the position back onto the
trajectory; the position error then dies out within two blocks (the correction is half the
error a plain ramp would leave, which makes the two-step recursion deadbeat). Before the first and after the last position sample the trajectory is
extrapolated with the end speeds (the twin starts one sample before the first sensor sample).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np
from scipy.signal import savgol_filter

from .coupling import output_index

SMOOTH_S = 1.0          # window of the local cubic fit of the positions [s]
POLYORDER = 3


@dataclass(frozen=True, eq=False)
class MeasuredTrajectory:
    """Smoothed position (and speed) of the vehicle reference point against time."""
    time_s: np.ndarray
    position_m: np.ndarray
    speed_mps: np.ndarray

    @classmethod
    def from_samples(cls, time_s, position_m, speed_mps, smooth_s: float = SMOOTH_S) -> "MeasuredTrajectory":
        t = np.asarray(time_s, float)
        x = np.asarray(position_m, float)
        v = np.asarray(speed_mps, float)
        if t.size >= 2:
            dt = float(np.median(np.diff(t)))
            n = int(round(smooth_s / dt)) | 1           # odd window
            if dt > 0 and n > POLYORDER + 1 and n <= t.size:
                x, v = (savgol_filter(x, n, POLYORDER, deriv=d, delta=dt, mode="interp") for d in (0, 1))
        return cls(t, x, v)

    def position_at(self, t_s) -> np.ndarray:
        """Position at times ``t_s``: linear inside the record, extrapolated with the end speeds."""
        t = np.asarray(t_s, float)
        tp, x, v = self.time_s, self.position_m, self.speed_mps
        out = np.interp(t, tp, x)
        return out + np.where(t < tp[0], (t - tp[0]) * v[0], 0.0) + np.where(t > tp[-1], (t - tp[-1]) * v[-1], 0.0)

    def speed_at(self, t_s) -> np.ndarray:
        return np.interp(np.asarray(t_s, float), self.time_s, self.speed_mps)


def ramp_speed(stepper, t_next_s: float, position_m: float, speed_mps: float) -> float:
    """The speed to ramp ``stepper`` to by ``t_next_s``: the trajectory's speed there plus the
    correction that brings its position back onto the trajectory (see the module)."""
    h = t_next_s - float(stepper.time_s)
    x_ramp = stepper.position_m + 0.5 * (stepper.speed_mps + speed_mps) * h
    return speed_mps + (position_m - x_ramp) / h


class TrajectoryTracker:
    """The trajectory as a live stream knows it: the newest position and speed from a quadratic
    fitted to the last ``window_s`` of position AND speed samples, each weighted by its own noise
    (measured from the stream: second differences of the positions, first differences of the
    speeds). Causal, so the window is short (a quadratic over 1 s misses a 0.2 m/s^3 jerk by
    1.5 mm at its end; over 0.5 s by 0.2 mm) and the speeds carry what the few positions cannot."""

    def __init__(self, window_s: float = 0.5):
        self.window_s = float(window_s)
        self._t = np.empty(0)
        self._x = np.empty(0)
        self._v = np.empty(0)

    def add(self, time_s, position_m, speed_mps) -> None:
        self._t = np.concatenate([self._t, np.asarray(time_s, float)])
        self._x = np.concatenate([self._x, np.asarray(position_m, float)])
        self._v = np.concatenate([self._v, np.asarray(speed_mps, float)])
        keep = self._t >= self._t[-1] - self.window_s
        self._t, self._x, self._v = self._t[keep], self._x[keep], self._v[keep]

    def estimate(self, t_s: float) -> tuple[float, float, float]:
        """(position, speed, standard error of the position) at ``t_s`` (at or just after the
        newest sample)."""
        t, x, v = self._t, self._x, self._v
        if t.size < 8:
            # too few samples to smooth: the newest one, carried forward at its speed
            return float(x[-1] + v[-1] * (t_s - t[-1])), float(v[-1]), 0.0
        # white-noise levels (floored at float32 resolution: exact streams have none)
        sx = max(float(np.std(np.diff(x, 2))) / math.sqrt(6.0), 4.0 * float(np.spacing(np.float32(x[-1]))))
        sv = max(float(np.std(np.diff(v))) / math.sqrt(2.0), 4.0 * float(np.spacing(np.float32(v[-1]))))
        tau = t - t[-1]
        rows = np.vstack([np.column_stack([tau * tau, tau, np.ones_like(tau)]) / sx,
                          np.column_stack([2 * tau, np.ones_like(tau), np.zeros_like(tau)]) / sv])
        rhs = np.concatenate([x / sx, v / sv])
        c = np.linalg.lstsq(rows, rhs, rcond=None)[0]
        dt = t_s - t[-1]
        x0 = np.array([dt * dt, dt, 1.0])
        cov = np.linalg.inv(rows.T @ rows)               # the weights are the noise: unit variance
        return float(x0 @ c), float(2 * c[0] * dt + c[1]), math.sqrt(max(float(x0 @ cov @ x0), 0.0))


def drive(stepper, trajectory: MeasuredTrajectory, t_end_s: float, block_s: float = 0.25,
          advance: Callable | None = None) -> list:
    """Advance ``stepper`` (a :class:`~maglev_ros.twin.coupling.TwinStepper`) to its last output
    sample at or before ``t_end_s`` along ``trajectory``, block by block (speed ramps, see the
    module). ``advance(stepper, t, speed)`` replaces ``stepper.advance(t, speed)`` (e.g. with a
    force law added). Returns the blocks' results."""
    step = advance or (lambda st, t, v: st.advance(t, v))
    fs = float(stepper.fs_out_hz)
    parts = []
    while True:
        t_now = float(stepper.time_s)
        k_out = output_index(min(t_now + block_s, t_end_s), stepper.t0_s, fs)
        t_next = stepper.t0_s + k_out / fs
        if t_next <= t_now + 0.5 / fs:
            break
        parts.append(step(stepper, t_next, ramp_speed(stepper, t_next, float(trajectory.position_at(t_next)),
                                                      float(trajectory.speed_at(t_next)))))
        if float(stepper.time_s) <= t_now:
            # no progress (a target that rounds onto the current sample) must end, not loop forever
            break
    return parts
