"""Precise integration of the vehicle state space x' = A x + B w over a time step h (001 Sec. 5).

The transition over one step is exact: x_{n+1} = Phi x_n + int_0^h e^{A (h - s)} B w(t_n + s) ds,
Phi = e^{A h}. The input w is taken

* ``linear`` (first-order hold, the default): w varies linearly from w_n to w_{n+1} over the
  step, x_{n+1} = Phi x_n + G0 w_n + G1 w_{n+1};
* ``zero`` (zero-order hold): w = w_n over the step, G1 = 0.

Phi, G0 and G1 come from one matrix exponential of the augmented system (Van Loan):
z = [x; w; d], w' = d, d' = 0 gives expm(h [[A, B, 0], [0, 0, I], [0, 0, 0]]) = [[Phi, E12, E13],
...] and G1 = E13 / h, G0 = E12 - G1. scipy's ``expm`` (scaling and squaring with Pade) is the
same idea as Zhong's 2^N precise-integration algorithm, so it is used rather than a hand copy.

A harmonic input w(t) = w_hat e^{i w t} (a pseudo-excitation of the irregularity) is integrated
exactly: x_{n+1} = Phi x_n + e^{i w t_n} (i w I - A)^{-1} (e^{i w h} I - Phi) B w_hat, which keeps
the harmonic steady state X e^{i w t}, X = (i w I - A)^{-1} B w_hat, exact at every step.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg

from maglev_ros.errors import UserError

HOLDS = ("linear", "zero")


@dataclass(frozen=True)
class VehicleStep:
    """One-step transition of x' = A x + B w (see module docstring)."""
    A: np.ndarray
    B: np.ndarray
    time_step_s: float
    hold: str
    transition: np.ndarray          # Phi = e^{A h}
    input_now: np.ndarray           # G0
    input_next: np.ndarray          # G1 (0 for the zero-order hold)

    def _balanced(self):
        Ab, (scale, _) = scipy.linalg.matrix_balance(self.A, permute=False, separate=True)
        return Ab, scale

    def steady_state(self, omega_rad_s, w_hat: np.ndarray) -> np.ndarray:
        """(n, k): X = (i w_j I - A)^{-1} B w_hat[:, j] for each column j (balanced solve)."""
        return self._resolvent_apply(omega_rad_s, self.B @ w_hat)

    def harmonic_input(self, omega_rad_s, w_hat: np.ndarray) -> np.ndarray:
        """(n, k): (i w_j I - A)^{-1} (e^{i w_j h} I - Phi) B w_hat[:, j], the exact step increment of
        a harmonic input starting at phase 0 at the step's start."""
        om = np.asarray(omega_rad_s, float)
        bw = self.B @ w_hat
        rhs = np.exp(1j * om * self.time_step_s)[None, :] * bw - self.transition @ bw
        return self._resolvent_apply(om, rhs)

    def _resolvent_apply(self, omega_rad_s, rhs: np.ndarray) -> np.ndarray:
        om = np.asarray(omega_rad_s, float)
        Ab, s = self._balanced()
        n = self.A.shape[0]
        out = np.zeros((n, om.size), complex)
        uniq, inv = np.unique(om, return_inverse=True)
        eye = np.eye(n)
        for i, w in enumerate(uniq):       # columns sharing a frequency share a factorisation
            cols = np.flatnonzero(inv == i)
            out[:, cols] = s[:, None] * np.linalg.solve(1j * w * eye - Ab, rhs[:, cols] / s[:, None])
        return out


def discretise(A: np.ndarray, B: np.ndarray, time_step_s: float, hold: str = "linear") -> VehicleStep:
    """Phi, G0, G1 of x' = A x + B w for step ``time_step_s`` and the input ``hold``."""
    if hold not in HOLDS:
        raise UserError(f"solver.hold: expected one of {list(HOLDS)}, got {hold!r}")
    h = float(time_step_s)
    if not h > 0:
        raise UserError(f"solver.time_step_s: expected > 0, got {time_step_s}")
    n, m = B.shape
    F = np.zeros((n + 2 * m, n + 2 * m))
    F[:n, :n] = A
    F[:n, n:n + m] = B
    F[n:n + m, n + m:] = np.eye(m)
    E = scipy.linalg.expm(F * h)
    phi = E[:n, :n]
    if hold == "linear":
        g1 = E[:n, n + m:] / h
        g0 = E[:n, n:n + m] - g1
    else:
        g0, g1 = E[:n, n:n + m], np.zeros((n, m))
    return VehicleStep(A, B, h, hold, phi, g0, g1)
