"""First-order state space of the 3D vehicle with its current loops (001 Sec. 2.4):
x' = A x + B w, y = C x + D w, x = [q (n), q' (n), di (n_loop)] (55 + 55 + 20 = 130 for 001).

Inputs w = [z_rail (m), y_rail (m), z_rail' (m), y_rail' (m)]: the vertical and lateral
displacement of the rail (irregularity + girder) at each of the m magnets, and their rates. A
levitation magnet's gap deviation is dh = z_rail - z_magnet (rail above the magnet, z up), a
guidance magnet's dh = +/-(y_rail - y_magnet) towards its rail side; in general dh = n . (rail -
magnet) with n the magnet's force direction (``Magnet.direction``).

Equations (current_loop.py for the laws), K_h, K_i, K_y per-magnet diagonals, S magnet-loop
incidence, G the loop means, B_n / B_y the generalised forces of unit forces along n / +y:
    M q'' + C q' + K q = B_n (K_i S di - K_h dh) - B_y K_y (y_magnet - y_rail)
    L0 di' + R di - (L0 i0/h0) G dh' = kp G dh + kv G dh' - ka G a,   a = B_n^T q''
Outputs (name prefixes): ``acc:`` DOF accelerations, ``disp:`` DOF displacements, ``gap:``
magnet gap deviations, ``current:`` loop current deviations, ``force:`` magnet force deviations
along n (the rail gets the opposite), ``lateral_force:`` passive lateral forces (on the magnet).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg

from maglev_ros.errors import UserError
from maglev_ros.system3d.current_loop import LoopParameters, MagnetLinearisation, linearise
from maglev_ros.system3d.vehicle import (StaticLoads, Vehicle3D, assemble, loop_incidence, magnet_directions,
                                         static_equilibrium)
from maglev_ros.system3d.vehicle_data import VehicleData


@dataclass(frozen=True)
class VehicleStateSpace3D:
    A: np.ndarray
    B: np.ndarray
    C: np.ndarray
    D: np.ndarray
    state_names: tuple[str, ...]
    input_names: tuple[str, ...]
    output_names: tuple[str, ...]
    vehicle: Vehicle3D
    static: StaticLoads
    magnets: MagnetLinearisation
    loops: LoopParameters

    @property
    def n_states(self) -> int:
        return self.A.shape[0]

    @property
    def magnet_x_m(self) -> np.ndarray:
        """Longitudinal position of each magnet's force point (for the time lags of the rail input)."""
        return np.array([m.point_m[0] for m in self.vehicle.data.magnets])

    def outputs(self, prefix: str) -> np.ndarray:
        """Indices of the outputs whose names start with ``prefix`` (e.g. ``"acc:"``, ``"gap:"``)."""
        return np.array([i for i, n in enumerate(self.output_names) if n.startswith(prefix)], dtype=int)

    def inputs(self, prefix: str) -> np.ndarray:
        return np.array([i for i, n in enumerate(self.input_names) if n.startswith(prefix)], dtype=int)

    def poles(self) -> np.ndarray:
        ev = np.linalg.eigvals(self.A)
        return ev[np.argsort(np.abs(ev))]

    def frequency_response(self, omega_rad_s: float) -> np.ndarray:
        """H(i w) = C (i w I - A)^-1 B + D, (n_out, n_in) complex.

        Solved on the balanced A (scipy ``matrix_balance``: D^-1 A D with a diagonal D): the states
        mix metres, radians, m/s and amperes, and balancing takes the condition number of
        (i w I - A) for 001's vehicle from ~7e8 to ~4e3; two refinement steps take the rounding of
        a mirror-symmetric response near the 0.33 Hz cabin sway from 1.5e-12 to 4e-15.
        """
        n = self.n_states
        Ab, (scale, _) = scipy.linalg.matrix_balance(self.A, permute=False, separate=True)
        M = 1j * omega_rad_s * np.eye(n) - Ab
        rhs = self.B / scale[:, None]
        lu = scipy.linalg.lu_factor(M)
        X = scipy.linalg.lu_solve(lu, rhs)
        for _ in range(2):   # iterative refinement: near a lightly damped mode the plain solve's rounding is amplified
            X = X + scipy.linalg.lu_solve(lu, rhs - M @ X)
        return (self.C * scale[None, :]) @ X + self.D


def passive_lateral_stiffness(vehicle: Vehicle3D, lin: MagnetLinearisation) -> np.ndarray:
    """B_y K_y B_y^T: the levitation magnets' lateral restoring stiffness on the vehicle DOFs."""
    By = vehicle.magnet_rows()[:, 1, :].T
    return By @ np.diag(lin.lateral_stiffness_n_per_m) @ By.T


def static_loads(vehicle: Vehicle3D) -> tuple[StaticLoads, MagnetLinearisation]:
    """Static equilibrium with the passive lateral stiffness of the forces it finds (fixed point:
    start from an equal weight share; the lateral stiffness only holds lateral/yaw motions)."""
    data = vehicle.data
    lev = np.array([m.role == "levitation" for m in data.magnets])
    guess = np.where(lev, vehicle.data.total_mass_kg * data.gravity_mps2 / max(int(lev.sum()), 1), 0.0)
    lin = linearise(data, guess)
    for _ in range(3):
        st = static_equilibrium(vehicle, passive_lateral_stiffness(vehicle, lin))
        lin = linearise(data, st.magnet_force_n)
    bad = np.flatnonzero(lev & (st.magnet_force_n <= 0))
    if bad.size:
        raise UserError(f"vehicle {data.name}: magnet {data.magnets[bad[0]].name!r} would have to push "
                        f"({st.magnet_force_n[bad[0]]:.4g} N) to hold the vehicle at the nominal gaps; check masses and positions")
    return st, lin


def build_state_space(source: VehicleData | Vehicle3D) -> VehicleStateSpace3D:
    vehicle = source if isinstance(source, Vehicle3D) else assemble(source)
    data = vehicle.data
    for i, lp in enumerate(data.loops):
        if lp.inductance_h <= 0:
            raise UserError(f"vehicle {data.name}: loops[{i}].inductance_h must be > 0 for the current "
                            f"state space (L0 -> 0 is the current-commanded law of twin/levitation.py)")
    st, lin = static_loads(vehicle)
    lp = LoopParameters.of(data)
    n, m, nl = vehicle.n_dof, len(data.magnets), len(data.loops)
    rows = vehicle.magnet_rows()
    dirs = magnet_directions(data)
    Bn = np.einsum("rjn,rj->nr", rows, dirs)
    By = rows[:, 1, :].T
    S = loop_incidence(data)
    G = (S / S.sum(axis=0)).T
    Ki, Kh, Ky = (np.diag(v) for v in (lin.current_gain_n_per_a, lin.gap_stiffness_n_per_m,
                                        lin.lateral_stiffness_n_per_m))
    Nz, Ny = np.diag(dirs[:, 2]), np.diag(dirs[:, 1])
    Z = np.zeros
    M, C, K = vehicle.mass, vehicle.damping, vehicle.stiffness
    Mi = np.linalg.inv(M)
    Keff = K - Bn @ Kh @ Bn.T + By @ Ky @ By.T
    acc_x = Mi @ np.hstack([-Keff, -C, Bn @ Ki @ S])
    acc_w = Mi @ np.hstack([-Bn @ Kh @ Nz, -Bn @ Kh @ Ny + By @ Ky, Z((n, 2 * m))])
    gap_x = np.hstack([-Bn.T, Z((m, n)), Z((m, nl))])
    gap_w = np.hstack([Nz, Ny, Z((m, 2 * m))])
    rate_x = np.hstack([Z((m, n)), -Bn.T, Z((m, nl))])
    rate_w = np.hstack([Z((m, 2 * m)), Nz, Ny])
    di_x = np.hstack([Z((nl, 2 * n)), np.eye(nl)])
    a_x, a_w = G @ Bn.T @ acc_x, G @ Bn.T @ acc_w
    Li = np.diag(1.0 / lp.inductance_h)
    E = lp.back_emf_v_s_per_m
    dcur_x = Li @ (-np.diag(lp.resistance_ohm) @ di_x + np.diag(E + lp.kv_v_s_per_m) @ G @ rate_x
                   + np.diag(lp.kp_v_per_m) @ G @ gap_x - np.diag(lp.ka_v_s2_per_m) @ a_x)
    dcur_w = Li @ (np.diag(E + lp.kv_v_s_per_m) @ G @ rate_w + np.diag(lp.kp_v_per_m) @ G @ gap_w
                   - np.diag(lp.ka_v_s2_per_m) @ a_w)
    A = np.vstack([np.hstack([Z((n, n)), np.eye(n), Z((n, nl))]), acc_x, dcur_x])
    B = np.vstack([Z((n, 4 * m)), acc_w, dcur_w])
    disp_x = np.hstack([np.eye(n), Z((n, n + nl))])
    force_x, force_w = Ki @ S @ di_x - Kh @ gap_x, -Kh @ gap_w
    lat_x = -Ky @ np.hstack([By.T, Z((m, n + nl))])
    lat_w = np.hstack([Z((m, m)), Ky, Z((m, 2 * m))])
    Cout = np.vstack([acc_x, disp_x, gap_x, di_x, force_x, lat_x])
    Dout = np.vstack([acc_w, Z((n, 4 * m)), gap_w, Z((nl, 4 * m)), force_w, lat_w])
    dofs, mags, ids = vehicle.dof_names, [mg.name for mg in data.magnets], [p.id for p in data.loops]
    states = tuple(dofs) + tuple(f"{d}.rate" for d in dofs) + tuple(f"current:{i}" for i in ids)
    inputs = tuple(f"{k}:{nm}" for k in ("rail_z", "rail_y", "rail_z_rate", "rail_y_rate") for nm in mags)
    outputs = (tuple(f"acc:{d}" for d in dofs) + tuple(f"disp:{d}" for d in dofs) + tuple(f"gap:{nm}" for nm in mags)
               + tuple(f"current:{i}" for i in ids) + tuple(f"force:{nm}" for nm in mags)
               + tuple(f"lateral_force:{nm}" for nm in mags))
    return VehicleStateSpace3D(A, B, Cout, Dout, states, inputs, outputs, vehicle, st, lin, lp)
