"""Rail points on the girder: left/right rail motion at any x from the girder DOFs.

Each rail is a rigid offset of the girder section: its running line is at (y_r, z_r) relative
to the shear centre (left rail y_r = track_centre_y + half_gauge, right rail track_centre_y -
half_gauge, both at z_r = rail_height above the shear centre). A rigid section rotation
theta = (theta_x, theta_y, theta_z) moves the point by theta x r, so

    vertical  z_rail(x) = w(x) + y_r theta_x(x)
    lateral   y_rail(x) = v(x) - z_r theta_x(x)

with w, v the Hermite-cubic and theta_x the linear interpolation of the element holding x
(``girder_element.point_shape_rows``). ``matrix`` gives the (n_x, n_free) rows N such that the
rail motion is N u (displacement), N u_dot (velocity at a fixed x) and, with ``derivative=1``,
the slope N' u (for a point moving at speed v: d/dt = N u_dot + v N' u). Forces (F_y, F_z) at
a rail point enter the girder as the generalised load N^T F (virtual work), which carries the
torque y_r F_z - z_r F_y of an eccentric force. Points off the girder give zero rows (ground).
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from maglev_ros.errors import UserError
from maglev_ros.system3d.girder import Girder
from maglev_ros.system3d.girder_element import N_NODE_DOF, point_shape_rows
from maglev_ros.system3d.scenario_values import number, plain

SIDES = ("left", "right")
DIRECTIONS = ("z", "y")


@dataclass(frozen=True)
class RailLayout:
    """Where the two rails sit on the section, relative to its shear centre (m)."""

    half_gauge_m: float             # b: left rail at +b, right at -b from the track centre
    rail_height_m: float = 0.0      # z_r of both rails above the shear centre
    track_centre_y_m: float = 0.0   # lateral offset of the track centre from the shear centre

    def __post_init__(self) -> None:
        if not self.half_gauge_m > 0:
            raise UserError(f"rails.half_gauge_m: expected > 0 m, got {self.half_gauge_m}")

    def offset(self, side: str) -> tuple[float, float]:
        """(y_r, z_r) of one rail."""
        if side not in SIDES:
            raise UserError(f"rail side: expected 'left' or 'right', got {side!r}")
        sgn = 1.0 if side == "left" else -1.0
        return self.track_centre_y_m + sgn * self.half_gauge_m, self.rail_height_m

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, raw: dict, where: str = "rails") -> "RailLayout":
        d = plain(raw, where)
        return cls(number(d, "half_gauge_m", where, positive=True), number(d, "rail_height_m", where, default=0.0),
                   number(d, "track_centre_y_m", where, default=0.0))


class RailInterpolation:
    """Rail-point rows of one girder for a rail layout (config in the constructor, x in the calls)."""

    def __init__(self, girder: Girder, rails: RailLayout):
        self.girder = girder
        self.rails = rails
        self._f2f = girder.full_to_free()

    def _locate(self, x_m) -> tuple[np.ndarray, ...]:
        x = np.atleast_1d(np.asarray(x_m, dtype=float))
        nodes = self.girder.node_x_m
        inside = (x >= nodes[0] - 1e-9) & (x <= nodes[-1] + 1e-9)
        e = np.clip(np.searchsorted(nodes, x, side="right") - 1, 0, nodes.size - 2)
        le = nodes[e + 1] - nodes[e]
        xi = np.clip((x - nodes[e]) / le, 0.0, 1.0)
        return x, e, xi, le, inside

    def section_rows(self, x_m, derivative: int = 0) -> dict[str, np.ndarray]:
        """Rows (n_x, n_free) of the shear centre's u, v, w and theta_x (or their x-derivatives)."""
        x, e, xi, le, inside = self._locate(x_m)
        out = {}
        cols = N_NODE_DOF * e[:, None] + np.arange(12)[None, :]        # full DOFs of each point's element
        fcols = self._f2f[cols]
        rows_idx = np.repeat(np.arange(x.size)[:, None], 12, axis=1)
        keep = (fcols >= 0) & inside[:, None]
        per_point = point_shape_rows(xi, le, derivative)
        for k, vals in per_point.items():
            mat = np.zeros((x.size, self.girder.n_free))
            mat[rows_idx[keep], fcols[keep]] = vals[keep]   # (point, DOF) pairs are unique
            out[k] = mat
        return out

    def matrix(self, x_m, side: str, direction: str, derivative: int = 0) -> np.ndarray:
        """(n_x, n_free): rail ``side`` motion in ``direction`` ('z' vertical, 'y' lateral) at x."""
        if direction not in DIRECTIONS:
            raise UserError(f"rail direction: expected 'z' (vertical) or 'y' (lateral), got {direction!r}")
        y_r, z_r = self.rails.offset(side)
        rows = self.section_rows(x_m, derivative)
        if direction == "z":
            return rows["w"] + y_r * rows["rx"]
        return rows["v"] - z_r * rows["rx"]

    def rail_motion(self, u_free, x_m, derivative: int = 0) -> dict[str, np.ndarray]:
        """{'z_left', 'z_right', 'y_left', 'y_right'}: (n_x,) each, for a DOF vector (displacement
        or velocity, n_free) or (n_free, n_t) for a history."""
        u = np.asarray(u_free, float)
        return {f"{d}_{s}": self.matrix(x_m, s, d, derivative) @ u for d in DIRECTIONS for s in SIDES}

    def load_vector(self, x_m, side: str, force_z_n=0.0, force_y_n=0.0) -> np.ndarray:
        """(n_free,) generalised girder load of forces F_z (up) and F_y (left) on rail ``side`` at x
        (arrays sum over points)."""
        fz = np.broadcast_to(np.asarray(force_z_n, float), np.atleast_1d(x_m).shape)
        fy = np.broadcast_to(np.asarray(force_y_n, float), np.atleast_1d(x_m).shape)
        return self.matrix(x_m, side, "z").T @ fz + self.matrix(x_m, side, "y").T @ fy
