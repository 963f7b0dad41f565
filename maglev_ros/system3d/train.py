"""A train of identical cars moving at constant speed along x: where each magnet is, and when a car
is over the girder.

Car c (0-based, 0 at the front) has its centre at s_c(t) = front_start_m - car_length_m / 2 -
c * car_length_m + speed_mps * t (cars touch: spacing = car length) and covers
[s_c - L/2, s_c + L/2]. The vehicle frame's x origin is the car centre, so magnet r of car c is
at s_c(t) + x_r. A car is "on the girder" from the time its front reaches the girder's start
until its rear leaves the girder's end (paper 001 Sec. 6.2's entry and exit times).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from maglev_ros.errors import UserError


@dataclass(frozen=True)
class Train:
    n_cars: int
    car_length_m: float
    speed_mps: float
    front_start_m: float            # x of the first car's front at t = 0
    magnet_x_m: np.ndarray          # (m,) magnet x in the vehicle frame (origin: car centre)

    def __post_init__(self) -> None:
        if int(self.n_cars) < 1:
            raise UserError(f"train.cars: expected >= 1, got {self.n_cars}")
        if not self.car_length_m > 0:
            raise UserError(f"train.car_length_m: expected > 0, got {self.car_length_m}")
        if not self.speed_mps > 0:
            raise UserError(f"train.speed_mps: expected > 0, got {self.speed_mps}")
        mx = np.asarray(self.magnet_x_m, float)
        if mx.size and np.max(np.abs(mx)) > self.car_length_m / 2 + 1e-9:
            raise UserError(f"train.car_length_m: {self.car_length_m} m is shorter than the vehicle's magnet "
                            f"span (magnets up to {np.max(np.abs(mx)):.3g} m from the car centre)")
        object.__setattr__(self, "magnet_x_m", mx)

    def car_centre_m(self, t_s) -> np.ndarray:
        """(n_cars,) or (n_t, n_cars) car centre positions."""
        c = np.arange(self.n_cars)
        t = np.asarray(t_s, float)
        return (self.front_start_m - self.car_length_m * (c + 0.5)) + self.speed_mps * t[..., None]

    def magnet_positions_m(self, t_s: float) -> np.ndarray:
        """(n_cars, m) global x of every magnet at time t."""
        return self.car_centre_m(t_s)[:, None] + self.magnet_x_m[None, :]

    def on_span_s(self, car: int, start_m: float, end_m: float) -> tuple[float, float]:
        """(t_in, t_out): car ``car`` (1-based) front at ``start_m`` and rear past ``end_m``."""
        if not 1 <= car <= self.n_cars:
            raise UserError(f"train: car {car} not in 1..{self.n_cars}")
        front0 = self.front_start_m - self.car_length_m * (car - 1)
        t_in = (start_m - front0) / self.speed_mps
        t_out = (end_m - (front0 - self.car_length_m)) / self.speed_mps
        return float(t_in), float(t_out)

    def to_dict(self) -> dict:
        return {"cars": int(self.n_cars), "car_length_m": self.car_length_m, "speed_mps": self.speed_mps,
                "front_start_m": self.front_start_m}
