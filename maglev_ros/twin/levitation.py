"""Levitation magnets: force law, feedback control, linearisation, closed-loop vehicle state space.

Force (contract): F = C (I / gap)^2, upward on the magnet and downward on the rail. C is set per
magnet so that F at the static current I0 and the nominal gap g0 carries that magnet's share of
the vehicle weight, and the shares come from solving the vehicle's static equilibrium
(``vehicle.static_equilibrium``), not from an equal split.

Control (000): I = I0 + kp (gap - g0) + kv d(gap)/dt - ka a_m, a_m the magnet's upward
acceleration. gap = g0 + y - z_m with y the rail-underside displacement at the magnet
(irregularity r + guideway deflection w) and z_m the magnet displacement from its static position.

Optional coil dynamics (001 Eq. 9-11 style, voltage control with the same feedback form): with
``coil_inductance_h`` L > 0 the current obeys L dI/dt + R I = u, u = R (I0 + kp dg + kv dg' - ka a_m),
i.e. the current lags the control law with time constant L/R. The gap-rate term of the magnet's
inductance change (back-EMF, 001 Eq. 9) is neglected: a careful simplification for a current-fed
chopper, stated here because the paper's equation text was lost.

Optional transport delay (``control_delay_s`` tau > 0, without coil dynamics): a digital controller
acts on measurements tau old, I(t) = law(t - tau). exp(-s tau) is realised per magnet by the (2,2)
Pade all-pass (1 - s tau/2 + (s tau)^2/12) / (1 + s tau/2 + (s tau)^2/12) = 1 - s tau / D(s): two
states xi, I = law - tau xi_2, a2 xi_2' = law - xi_1 - a1 xi_2, xi_1' = xi_2 (a1 = tau/2,
a2 = tau^2/12). Its gain is exactly 1 and its phase within 2 % of -w tau up to w tau = 2 (a
first-order lag, the coil's, instead halves the gain there: a 2.5 ms delay acts at 60-120 Hz).

Linearisation about the static state: dF = kI dI - kgap dgap, kI = 2 F0 / I0, kgap = 2 F0 / g0.
Without coil dynamics dF = k_g dgap + c_g dgap' - m_a a_m with k_g = kI kp - kgap, c_g = kI kv,
m_a = kI ka. ``closed_loop`` builds the linear state space x' = A x + B [y; y'; N] of the vehicle
with these forces (N = nonlinear remainder F - F_lin, an input so the time integrators can add it).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from maglev_ros.errors import UserError
from maglev_ros.twin.design import LevitationDesign, TwinConfig
from maglev_ros.twin.vehicle import StaticEquilibrium, VehicleModel, static_equilibrium, vehicle_from_design


@dataclass(frozen=True)
class LinearForce:
    """Partial derivatives of the magnet force (per magnet arrays) at the static state."""
    df_dgap_n_per_m: np.ndarray            # through the control law (no coil): k_g
    df_dgap_rate_n_s_per_m: np.ndarray     # c_g
    df_daccel_n_s2_per_m: np.ndarray       # -m_a
    df_dcurrent_n_per_a: np.ndarray        # kI (current held)
    df_dgap_fixed_current_n_per_m: np.ndarray  # -kgap (current held)

    def to_dict(self) -> dict:
        return {k: np.asarray(v).tolist() for k, v in self.__dict__.items()}


@dataclass(frozen=True)
class LevitationModel:
    nominal_gap_m: float
    static_current_a: float
    kp_a_per_m: float
    kv_a_s_per_m: float
    ka_a_s2_per_m: float
    coil_inductance_h: float
    coil_resistance_ohm: float
    static_force_n: np.ndarray     # (n_mag,)
    force_coeff: np.ndarray        # C (n_mag,) [N m^2 / A^2]
    control_delay_s: float = 0.0

    @classmethod
    def from_design(cls, d: LevitationDesign, static_force_n: np.ndarray) -> "LevitationModel":
        f0 = np.asarray(static_force_n, dtype=float)
        if np.any(f0 <= 0):
            raise UserError(f"vehicle: static equilibrium needs a non-positive (pushing) force on magnet(s) "
                            f"{(np.flatnonzero(f0 <= 0) + 1).tolist()}; check masses and x positions")
        c = f0 * d.nominal_gap_m ** 2 / d.static_current_a ** 2
        if d.control_delay_s < 0 or (d.control_delay_s > 0 and d.coil_inductance_h > 0):
            raise UserError(f"levitation: control_delay_s must be >= 0 and is available without coil dynamics "
                            f"only (coil_inductance_h 0), got {d.control_delay_s} s with {d.coil_inductance_h} H")
        return cls(d.nominal_gap_m, d.static_current_a, d.kp_a_per_m, d.kv_a_s_per_m, d.ka_a_s2_per_m,
                   d.coil_inductance_h, d.coil_resistance_ohm, f0, c, float(d.control_delay_s))

    @property
    def has_coil(self) -> bool:
        return self.coil_inductance_h > 0.0

    def current_command(self, gap_m, gap_rate_mps, accel_mps2):
        """Control law I = I0 + kp (gap - g0) + kv gap' - ka a_m."""
        return (self.static_current_a + self.kp_a_per_m * (gap_m - self.nominal_gap_m)
                + self.kv_a_s_per_m * gap_rate_mps - self.ka_a_s2_per_m * accel_mps2)

    def force(self, current_a, gap_m):
        """F = C (I / gap)^2 (upward on the magnet)."""
        return self.force_coeff * (current_a / gap_m) ** 2

    def partials(self) -> LinearForce:
        f0 = self.static_force_n
        k_i = 2 * f0 / self.static_current_a
        k_gap = 2 * f0 / self.nominal_gap_m
        return LinearForce(k_i * self.kp_a_per_m - k_gap, k_i * self.kv_a_s_per_m, -k_i * self.ka_a_s2_per_m,
                           k_i, -k_gap)


@dataclass(frozen=True)
class VehicleStateSpace:
    """x' = A x + B u, u = [y (n_mag), y' (n_mag), N (n_mag)]; x = [z, z', (dI | xi_1, xi_2)].

    Output maps (x, u) -> per-magnet quantities: ``out_*`` = (C, D) pairs, value = C x + D u.
    """
    A: np.ndarray
    B: np.ndarray
    n_dof: int
    n_magnets: int
    has_coil: bool
    out_z: tuple[np.ndarray, np.ndarray]
    out_zd: tuple[np.ndarray, np.ndarray]
    out_acc: tuple[np.ndarray, np.ndarray]
    out_dcurrent: tuple[np.ndarray, np.ndarray]   # current minus I0
    out_dof_acc: tuple[np.ndarray, np.ndarray]    # all DOF accelerations

    @property
    def n_states(self) -> int:
        return self.A.shape[0]

    def poles(self) -> np.ndarray:
        ev = np.linalg.eigvals(self.A)
        return ev[np.argsort(np.abs(ev))]


def closed_loop(vehicle: VehicleModel, lev: LevitationModel) -> VehicleStateSpace:
    """Linear closed-loop vehicle with the rail displacement at the magnets as input."""
    if not lev.has_coil:
        return _law_loop(vehicle, lev)
    # coil dynamics: x = [z, z', dI]
    n, m = vehicle.n_dof, vehicle.n_magnets
    M, C, K, Bm = vehicle.mass, vehicle.damping, vehicle.stiffness, vehicle.magnet_input
    p = lev.partials()
    Z = np.zeros
    I_n = np.eye(n)
    ki, kgap = p.df_dcurrent_n_per_a, -p.df_dgap_fixed_current_n_per_m
    Kt = K - Bm @ np.diag(kgap) @ Bm.T
    Mi = np.linalg.inv(M)
    acc_x = np.hstack([-Mi @ Kt, -Mi @ C, Mi @ Bm @ np.diag(ki)])
    acc_u = np.hstack([-Mi @ Bm @ np.diag(kgap), Z((n, m)), Mi @ Bm])
    cz = np.hstack([Bm.T, Z((m, n)), Z((m, m))])
    czd = np.hstack([Z((m, n)), Bm.T, Z((m, m))])
    ca, da = Bm.T @ acc_x, Bm.T @ acc_u
    rl = lev.coil_resistance_ohm / lev.coil_inductance_h
    sel_y = np.hstack([np.eye(m), Z((m, 2 * m))])
    sel_yd = np.hstack([Z((m, m)), np.eye(m), Z((m, m))])
    ci_state = np.hstack([Z((m, 2 * n)), np.eye(m)])
    di_x = rl * (-lev.kp_a_per_m * cz - lev.kv_a_s_per_m * czd - lev.ka_a_s2_per_m * ca - ci_state)
    di_u = rl * (lev.kp_a_per_m * sel_y + lev.kv_a_s_per_m * sel_yd - lev.ka_a_s2_per_m * da)
    A = np.vstack([np.hstack([Z((n, n)), I_n, Z((n, m))]), acc_x, di_x])
    B = np.vstack([Z((n, 3 * m)), acc_u, di_u])
    zero_d = Z((m, 3 * m))
    return VehicleStateSpace(A, B, n, m, True, (cz, zero_d), (czd, zero_d), (ca, da), (ci_state, zero_d),
                             (acc_x, acc_u))


def _law_loop(vehicle: VehicleModel, lev: LevitationModel) -> VehicleStateSpace:
    """Closed loop with the current given by the control law, on time or ``control_delay_s`` late
    (module docstring): x = [z, z'] or, with the delay, [z, z', xi_1, xi_2]."""
    n, m = vehicle.n_dof, vehicle.n_magnets
    M, C, K, Bm = vehicle.mass, vehicle.damping, vehicle.stiffness, vehicle.magnet_input
    p = lev.partials()
    Z = np.zeros
    tau = lev.control_delay_s
    nd = 2 * m if tau > 0 else 0                       # the all-pass states
    kg, cg, ma, ki = p.df_dgap_n_per_m, p.df_dgap_rate_n_s_per_m, -p.df_daccel_n_s2_per_m, p.df_dcurrent_n_per_a
    # F - F0 = kg dgap + cg dgap' - ma a_m + N (- ki tau xi_2: the law through the force, less the all-pass part)
    Mp = M + Bm @ np.diag(ma) @ Bm.T
    Mi = np.linalg.inv(Mp)
    Kp = K + Bm @ np.diag(kg) @ Bm.T
    Cp = C + Bm @ np.diag(cg) @ Bm.T
    late = [Z((n, m)), -Mi @ Bm @ np.diag(ki * tau)] if nd else []
    acc_x = np.hstack([-Mi @ Kp, -Mi @ Cp, *late])                   # DOF accel from state
    acc_u = np.hstack([Mi @ Bm @ np.diag(kg), Mi @ Bm @ np.diag(cg), Mi @ Bm])
    cz = np.hstack([Bm.T, Z((m, n)), Z((m, nd))])
    czd = np.hstack([Z((m, n)), Bm.T, Z((m, nd))])
    ca, da = Bm.T @ acc_x, Bm.T @ acc_u
    # law: dI = kp dgap + kv dgap' - ka a, dgap = y - z_m
    sel_y = np.hstack([np.eye(m), Z((m, 2 * m))])
    sel_yd = np.hstack([Z((m, m)), np.eye(m), Z((m, m))])
    law_x = -lev.kp_a_per_m * cz - lev.kv_a_s_per_m * czd - lev.ka_a_s2_per_m * ca
    law_u = lev.kp_a_per_m * sel_y + lev.kv_a_s_per_m * sel_yd - lev.ka_a_s2_per_m * da
    rows_x = [np.hstack([Z((n, n)), np.eye(n), Z((n, nd))]), acc_x]
    rows_u = [Z((n, 3 * m)), acc_u]
    ci = law_x
    if nd:
        a1, a2 = tau / 2.0, tau * tau / 12.0
        xi1 = np.hstack([Z((m, 2 * n)), np.eye(m), Z((m, m))])
        xi2 = np.hstack([Z((m, 2 * n)), Z((m, m)), np.eye(m)])
        rows_x += [xi2, (law_x - xi1 - a1 * xi2) / a2]
        rows_u += [Z((m, 3 * m)), law_u / a2]
        ci = law_x - tau * xi2
    zero_d = Z((m, 3 * m))
    return VehicleStateSpace(np.vstack(rows_x), np.vstack(rows_u), n, m, False, (cz, zero_d), (czd, zero_d),
                             (ca, da), (ci, law_u), (acc_x, acc_u))


@dataclass(frozen=True)
class VehicleSystem:
    """Everything about the vehicle a simulation needs, built from a ``TwinConfig``."""
    model: VehicleModel
    equilibrium: StaticEquilibrium
    levitation: LevitationModel
    state_space: VehicleStateSpace


def build_vehicle(config: TwinConfig) -> VehicleSystem:
    model = vehicle_from_design(config.vehicle)
    eq = static_equilibrium(model)
    lev = LevitationModel.from_design(config.levitation, eq.magnet_force_n)
    return VehicleSystem(model, eq, lev, closed_loop(model, lev))


def closed_loop_poles(config: TwinConfig) -> np.ndarray:
    """Closed-loop poles (rad/s, complex) of the vehicle levitating on a rigid, perfect guideway."""
    return build_vehicle(config).state_space.poles()


def is_stable(poles: np.ndarray, margin: float = 0.0) -> bool:
    return bool(np.all(np.real(poles) < -margin))
