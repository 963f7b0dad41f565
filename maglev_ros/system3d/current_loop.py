"""Electromagnet force law, its linearisation, and the current-loop (coil + voltage control) equation.

Force (001 Eq. 3): a U-magnet of N turns and pole area A at gap h with current i pulls with
F = mu0 N^2 A i^2 / (4 h^2). It follows from the coil inductance L(h) = mu0 N^2 A / (2 h) (two
pole gaps in series, flux path 2h) and F = (1/2) i^2 |dL/dh|. Linearised at (i0, h0), F0:
    dF = k_i di - k_h dh,   k_i = dF/di = 2 F0 / i0,   k_h = -dF/dh = 2 F0 / h0.
Coil: u = R i + d(L(h) i)/dt = R i + L di/dt + i (dL/dh) dh/dt, dL/dh = -L/h, so at (i0, h0) with
L0 = L(h0) the deviations obey (001 Eq. 9)
    L0 di/dt + R di - (L0 i0 / h0) dh/dt = du.
The law also fixes L0 = 2 F0 h0 / i0^2 per magnet (``implied_inductance_h``); the data give L0
separately (001 lists it as a parameter), and L0 -> 0 is the current-commanded limit.
Voltage control (001 Eq. 10, deviations from u0 = R i0):
    du = kp h + kv dh/dt - ka a,
h the loop's gap deviation, a the upward (along the force) acceleration of its magnets, both
means over the loop's magnets (a loop drives its magnets in series: same current, summed L0, R).
With du = R (kp' h + kv' h' - ka' a) and L0 -> 0 the current is i = kp' h + kv' h' - ka' a: the
current-commanded law of ``twin/levitation.py``.

Passive lateral force of a levitation magnet (001 Eq. 5, "no independent control"): with the
magnet offset y from its rail, the pole overlap shrinks; counting the fringing flux the effective
pole width is w_eff(y) with dw_eff/dy = -(2/pi) arctan(y/h) (overlap w - |y| without fringing,
smoothed over the gap height), and with L proportional to w_eff/h the co-energy gives
    F_y = F_z h w_eff'(y) / w_eff = -F_z (2 h / (pi w)) arctan(y / h)  ~  -k_y y,  k_y = 2 F0 / (pi w).
It needs no extra state; second-order terms (dF_z y) are dropped.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from maglev_ros.system3d.vehicle_data import CurrentLoop, VehicleData

MU0_H_PER_M = 4e-7 * math.pi


def inductance_h(turns: float, pole_area_m2: float, gap_m):
    """L(h) = mu0 N^2 A / (2 h)."""
    return MU0_H_PER_M * turns ** 2 * pole_area_m2 / (2.0 * np.asarray(gap_m, float))


def attraction_force_n(turns: float, pole_area_m2: float, current_a, gap_m):
    """F = mu0 N^2 A i^2 / (4 h^2) (001 Eq. 3)."""
    return MU0_H_PER_M * turns ** 2 * pole_area_m2 * np.asarray(current_a, float) ** 2 / (
        4.0 * np.asarray(gap_m, float) ** 2)


def lateral_force_n(vertical_force_n, offset_m, gap_m, pole_width_m):
    """F_y = -F_z (2 h / (pi w)) arctan(y / h): restoring force of a magnet offset y from its rail."""
    return -np.asarray(vertical_force_n) * 2.0 * gap_m / (math.pi * pole_width_m) * np.arctan(
        np.asarray(offset_m) / gap_m)


@dataclass(frozen=True)
class MagnetLinearisation:
    """Per magnet: dF = k_i di - k_h dh along the magnet's direction; F_y = -k_y (y_mag - y_rail)."""
    static_force_n: np.ndarray
    current_gain_n_per_a: np.ndarray           # k_i = 2 F0 / i0
    gap_stiffness_n_per_m: np.ndarray          # k_h = 2 F0 / h0
    lateral_stiffness_n_per_m: np.ndarray      # k_y = 2 F0 / (pi w) (levitation, passive fringing), else 0
    implied_inductance_h: np.ndarray           # 2 F0 h0 / i0^2: one magnet's L0 by the force law

    def to_dict(self) -> dict:
        return {k: np.asarray(v).tolist() for k, v in self.__dict__.items()}


def magnet_loops(data: VehicleData) -> list[CurrentLoop]:
    by_id = {lp.id: lp for lp in data.loops}
    return [by_id[m.loop] for m in data.magnets]


def linearise(data: VehicleData, static_force_n) -> MagnetLinearisation:
    f0 = np.asarray(static_force_n, float)
    loops = magnet_loops(data)
    i0 = np.array([lp.static_current_a for lp in loops])
    h0 = np.array([lp.nominal_gap_m for lp in loops])
    lev = np.array([m.role == "levitation" for m in data.magnets])
    ky = (2.0 * f0 / (math.pi * data.pole_width_m) * lev if data.passive_lateral == "fringing"
          else np.zeros_like(f0))
    return MagnetLinearisation(f0, 2 * f0 / i0, 2 * f0 / h0, ky, 2 * f0 * h0 / i0 ** 2)


@dataclass(frozen=True)
class LoopParameters:
    """Per-loop arrays of the coil and voltage law (``CurrentLoop`` fields, vectorised)."""
    inductance_h: np.ndarray
    resistance_ohm: np.ndarray
    static_current_a: np.ndarray
    nominal_gap_m: np.ndarray
    kp_v_per_m: np.ndarray
    kv_v_s_per_m: np.ndarray
    ka_v_s2_per_m: np.ndarray

    @classmethod
    def of(cls, data: VehicleData) -> "LoopParameters":
        def arr(key):
            return np.array([getattr(lp, key) for lp in data.loops], float)
        return cls(arr("inductance_h"), arr("resistance_ohm"), arr("static_current_a"), arr("nominal_gap_m"),
                   arr("kp_v_per_m"), arr("kv_v_s_per_m"), arr("ka_v_s2_per_m"))

    @property
    def back_emf_v_s_per_m(self) -> np.ndarray:
        """L0 i0 / h0: voltage per unit gap rate (the inductance change term)."""
        return self.inductance_h * self.static_current_a / self.nominal_gap_m

    def voltage_v(self, gap_m, gap_rate_mps, accel_mps2):
        """du = kp h + kv h' - ka a (deviations)."""
        return self.kp_v_per_m * gap_m + self.kv_v_s_per_m * gap_rate_mps - self.ka_v_s2_per_m * accel_mps2
