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
        k_out = math.floor((min(t_now + block_s, t_end_s) - stepper.t0_s) * fs + 1e-9)
        t_next = stepper.t0_s + k_out / fs
        if t_next <= t_now + 0.5 / fs:
            break
        h = t_next - t_now
        v_traj = float(trajectory.speed_at(t_next))
        x_ramp = stepper.position_m + 0.5 * (stepper.speed_mps + v_traj) * h
        v = v_traj + (float(trajectory.position_at(t_next)) - x_ramp) / h
        parts.append(step(stepper, t_next, v))
    return parts
