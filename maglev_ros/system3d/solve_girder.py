"""The girder's equations in the coordinates the coupled solver integrates, and the Newmark step.

``girder_dynamics(girder, model, cutoff_hz)``: ``full`` keeps every free DOF (M, C, K of
``girder.py``); ``modal`` keeps the modes up to ``cutoff_hz`` (mass-normalised, u = Phi eta):
M = I, K = diag(w^2), C = Phi^T C Phi (diagonal for Rayleigh or modal damping, kept full so any
damping works). Rail rows in those coordinates are the rail interpolation rows times the basis.

Newmark average acceleration (beta = 1/4, gamma = 1/2: unconditionally stable, no numerical
damping), written with the displacement at t_{n+1} as unknown:
    (K + a0 M + a1 C) u_{n+1} = f_{n+1} + M (a0 u_n + a2 u'_n + u''_n) + C (a1 u_n + u'_n)
    u'_{n+1} = a1 (u_{n+1} - u_n) - u'_n,   u''_{n+1} = a0 (u_{n+1} - u_n) - a2 u'_n - u''_n
with a0 = 4/h^2, a1 = 2/h, a2 = 4/h. The effective stiffness is factorised once (Cholesky).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg

from maglev_ros.errors import UserError
from maglev_ros.system3d.girder import Girder

MODELS = ("modal", "full")


@dataclass(frozen=True)
class GirderDynamics:
    """M eta'' + C eta' + K eta = basis^T f on ``n`` coordinates (u_free = basis @ eta)."""
    girder: Girder
    model: str
    mass: np.ndarray
    damping: np.ndarray
    stiffness: np.ndarray
    basis: np.ndarray               # (n_free, n)
    freq_hz: np.ndarray             # modal: the kept modes' frequencies; full: empty

    @property
    def n(self) -> int:
        return self.mass.shape[0]

    def to_dict(self) -> dict:
        return {"model": self.model, "coordinates": self.n,
                "mode_freq_hz": [round(float(f), 5) for f in self.freq_hz]}


def girder_dynamics(girder: Girder, model: str = "modal", cutoff_hz: float | None = None) -> GirderDynamics:
    if model not in MODELS:
        raise UserError(f"solver.girder_model: expected one of {list(MODELS)}, got {model!r}")
    if model == "full":
        return GirderDynamics(girder, model, girder.mass, girder.damping, girder.stiffness,
                              np.eye(girder.n_free), np.zeros(0))
    if cutoff_hz is None or not cutoff_hz > 0:
        raise UserError(f"solver.mode_cutoff_hz: expected a frequency > 0 for the modal girder, got {cutoff_hz!r}")
    w2, phi = scipy.linalg.eigh(girder.stiffness, girder.mass,
                                subset_by_value=(-np.inf, (2 * np.pi * cutoff_hz) ** 2))
    if not w2.size:
        raise UserError(f"solver.mode_cutoff_hz: no girder mode below {cutoff_hz} Hz")
    c = phi.T @ girder.damping @ phi
    return GirderDynamics(girder, model, np.eye(w2.size), 0.5 * (c + c.T), np.diag(w2), phi,
                          np.sqrt(np.clip(w2, 0, None)) / (2 * np.pi))


@dataclass(frozen=True)
class Newmark:
    """Average-acceleration constants and the factorised effective stiffness of one GirderDynamics."""
    dynamics: GirderDynamics
    time_step_s: float

    def __post_init__(self) -> None:
        h = self.time_step_s
        d = self.dynamics
        object.__setattr__(self, "a0", 4.0 / h ** 2)
        object.__setattr__(self, "a1", 2.0 / h)
        object.__setattr__(self, "a2", 4.0 / h)
        keff = d.stiffness + self.a0 * d.mass + self.a1 * d.damping
        object.__setattr__(self, "effective_stiffness", keff)
        object.__setattr__(self, "_factor", scipy.linalg.cho_factor(keff) if d.n else None)

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        """K_eff^{-1} rhs (columns)."""
        return scipy.linalg.cho_solve(self._factor, rhs)

    def history_load(self, u, v, a) -> np.ndarray:
        """M (a0 u + a2 u' + u'') + C (a1 u + u'): the known part of the step's right-hand side."""
        d = self.dynamics
        return d.mass @ (self.a0 * u + self.a2 * v + a) + d.damping @ (self.a1 * u + v)

    def update(self, u_new, u, v, a):
        """(u'_{n+1}, u''_{n+1}) from u_{n+1} and the state at t_n."""
        du = u_new - u
        return self.a1 * du - v, self.a0 * du - self.a2 * v - a
