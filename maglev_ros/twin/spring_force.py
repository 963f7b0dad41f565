"""A force law added to some of the vehicle's springs (e.g. nonlinear air springs), by operator splitting.

The twin's vehicle is linear (state space around static equilibrium, :mod:`.levitation`). A force
f(d, d_rate) per spring, with d = T z the springs' deflections (rows T, z the vehicle DOFs), is
added by Lie splitting around the linear stepper: advance ``every`` output samples, then add the
force's impulse over that interval to the DOF velocities, dz_rate -= M^-1 T^T f dt, with d and
d_rate from the state at the end of the interval. The recorded DOF accelerations get the force's
instantaneous share -M^-1 T^T f added (the stepper reports the linear model's). M is the vehicle
model's mass matrix: the closed loop's acceleration feedback only adds mass on magnet DOFs, which
no secondary spring touches. First-order accurate in the output interval (1-2 ms against air-spring
periods of ~1 s and the 2-8 Hz band a nonlinear air spring shows in).

Written here because the stepper's integrator is the twin's own (prewarped, vehicle-guideway
coupled): no library integrates "this state space plus a user force" on it.
"""
from __future__ import annotations

from dataclasses import replace
from typing import Callable

import numpy as np

from .coupling import PassResult, TwinStepper, output_index


def advance_with_spring_force(st: TwinStepper, t_end_s: float, speed_mps: float, rows: np.ndarray,
                              force: Callable[[np.ndarray, np.ndarray], np.ndarray], every: int = 1
                              ) -> tuple[PassResult, np.ndarray]:
    """``st.advance(t_end_s, speed_mps)`` with ``force(d, d_rate)`` [N] (same shape as d, one column
    per row of ``rows``, acting like the linear spring force k d: + pushes body_a's point up and
    body_b's down for rows built as point(body_a) - point(body_b)) added in the springs ``rows``
    (n_springs, n_dof). d, d_rate are (n_springs,) at the state, (n, n_springs) at recorded samples.

    Returns the concatenated PassResult and f (n, n_springs) at the recorded samples. With a zero
    force the result equals one ``advance`` call to floating point."""
    model = st.vehicle.model
    nd = model.n_dof
    rows = np.asarray(rows, float)
    minv_tt = np.linalg.solve(model.mass, rows.T)                   # (n_dof, n_springs)
    fs = st.fs_out_hz
    k_now = st._k // st.n_sub
    k_end = output_index(t_end_s, st.t0_s, fs)
    parts, forces = [], []
    while k_now < k_end:
        k_next = min(k_now + every, k_end)
        r = st.advance(st.t0_s + (k_next + 0.5) / fs, speed_mps)
        x = st._x.copy()
        d_rate_now = rows @ x[nd:2 * nd]
        f = np.asarray(force(rows @ x[:nd], d_rate_now), float)
        x[nd:2 * nd] -= minv_tt @ f * ((k_next - k_now) / fs)
        st.set_vehicle_state(x)
        d_rec = r.vehicle_disp_m @ rows.T
        d_rate_rec = np.gradient(d_rec, axis=0) * fs if d_rec.shape[0] > 1 else \
            np.broadcast_to(d_rate_now, d_rec.shape)
        fr = np.asarray(force(d_rec, d_rate_rec), float).reshape(d_rec.shape)
        parts.append(replace(r, vehicle_acc_mps2=r.vehicle_acc_mps2 - fr @ minv_tt.T))
        forces.append(fr)
        k_now = k_next
    if not parts:
        return st.advance(t_end_s, speed_mps), np.zeros((0, rows.shape[0]))
    return PassResult.concat(parts), np.concatenate(forces, axis=0)
