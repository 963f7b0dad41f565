"""Vertical multibody vehicle assembled from data (000's 18-DOF model; 001's "fully computerized" assembly).

A vehicle is a list of rigid ``Body``s (heave, plus pitch when it has a pitch inertia), a list of
``Connection``s (linear spring + dashpot joining a point of one body to the same-x point of
another), and a list of magnets (points on bodies where the levitation force acts). ``assemble``
builds M, C, K by adding each connection's contribution T^T k T with T the row that maps the DOFs
to the relative vertical displacement of the two attachment points; nothing about the topology is
coded by hand, so another vehicle is another data set.

Conventions: z positive upward; pitch theta positive nose-up, so the vertical displacement of a
point at x on a body with reference x_b is z + theta (x - x_b) (x positive forward, relative to
the vehicle reference point). Magnet forces are positive upward on the vehicle.

The default vehicle (``vehicle_from_design``): car body (heave, pitch), 4 levitation frames (heave,
pitch), 8 magnets (heave) = 18 DOF; primary suspension joins each magnet to its frame at the
magnet's x; each secondary air spring joins the car body to the nearest frame at its x.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from maglev_ros.errors import UserError
from maglev_ros.twin.design import VehicleDesign


@dataclass(frozen=True)
class Body:
    name: str
    mass_kg: float
    x_m: float
    pitch_inertia_kg_m2: float | None = None     # None: heave only


@dataclass(frozen=True)
class Connection:
    """Spring-dashpot between ``body_a`` and ``body_b`` at longitudinal position ``x_m``."""
    body_a: str
    body_b: str
    x_m: float
    stiffness_n_per_m: float
    damping_n_s_per_m: float
    name: str = ""


@dataclass(frozen=True)
class Magnet:
    body: str
    x_m: float


@dataclass(frozen=True)
class VehicleModel:
    """Assembled linear vehicle: M z'' + C z' + K z = B F + gravity."""
    bodies: tuple[Body, ...]
    connections: tuple[Connection, ...]
    magnets: tuple[Magnet, ...]
    dof_names: tuple[str, ...]
    mass: np.ndarray             # (n, n)
    damping: np.ndarray          # (n, n)
    stiffness: np.ndarray        # (n, n)
    magnet_input: np.ndarray     # B (n, n_mag): generalised forces of unit upward magnet forces
    gravity_load_n: np.ndarray   # (n,) generalised gravity load (negative on heave DOFs)

    @property
    def n_dof(self) -> int:
        return len(self.dof_names)

    @property
    def n_magnets(self) -> int:
        return len(self.magnets)

    @property
    def magnet_x_m(self) -> np.ndarray:
        return np.array([m.x_m for m in self.magnets])

    @property
    def magnet_dofs(self) -> np.ndarray:
        """Index of the heave DOF of each magnet's body (the magnet DOFs of the 18-DOF model)."""
        return np.array([self.dof_names.index(f"{m.body}.z") for m in self.magnets])

    @property
    def total_mass_kg(self) -> float:
        return float(sum(b.mass_kg for b in self.bodies))

    def point_row(self, body: str, x_m: float) -> np.ndarray:
        """Row mapping the DOFs to the vertical displacement of the point at x on ``body``."""
        return _point_row(self.bodies, self.dof_names, body, x_m)

    def dof_index(self, name: str) -> int:
        return self.dof_names.index(name)


def _point_row(bodies, dof_names, body: str, x_m: float) -> np.ndarray:
    row = np.zeros(len(dof_names))
    b = next((bb for bb in bodies if bb.name == body), None)
    if b is None:
        raise UserError(f"vehicle: connection or magnet refers to unknown body {body!r}")
    row[dof_names.index(f"{body}.z")] = 1.0
    if b.pitch_inertia_kg_m2 is not None:
        row[dof_names.index(f"{body}.pitch")] = x_m - b.x_m
    return row


def assemble(bodies: Sequence[Body], connections: Sequence[Connection], magnets: Sequence[Magnet],
             gravity_mps2: float = 9.81) -> VehicleModel:
    """Assemble M, C, K, magnet input matrix and gravity load from the data."""
    names = [b.name for b in bodies]
    if len(set(names)) != len(names):
        raise UserError(f"vehicle: duplicate body names in {names}")
    dofs: list[str] = []
    for b in bodies:
        dofs.append(f"{b.name}.z")
        if b.pitch_inertia_kg_m2 is not None:
            dofs.append(f"{b.name}.pitch")
    n = len(dofs)
    M = np.zeros((n, n))
    g = np.zeros(n)
    for b in bodies:
        i = dofs.index(f"{b.name}.z")
        M[i, i] = b.mass_kg
        g[i] = -b.mass_kg * gravity_mps2
        if b.pitch_inertia_kg_m2 is not None:
            j = dofs.index(f"{b.name}.pitch")
            M[j, j] = b.pitch_inertia_kg_m2
    K = np.zeros((n, n))
    C = np.zeros((n, n))
    for c in connections:
        t = _point_row(bodies, dofs, c.body_a, c.x_m) - _point_row(bodies, dofs, c.body_b, c.x_m)
        K += c.stiffness_n_per_m * np.outer(t, t)
        C += c.damping_n_s_per_m * np.outer(t, t)
    B = np.stack([_point_row(bodies, dofs, m.body, m.x_m) for m in magnets], axis=1)
    return VehicleModel(tuple(bodies), tuple(connections), tuple(magnets), tuple(dofs), M, C, K, B, g)


def vehicle_from_design(v: VehicleDesign) -> VehicleModel:
    """The 18-DOF (for the default data) vertical vehicle of 000 from a ``VehicleDesign``."""
    bodies = [Body("car", v.car_body.mass_kg, v.car_body.x_m, v.car_body.pitch_inertia_kg_m2)]
    for i, f in enumerate(v.frames):
        bodies.append(Body(f"frame{i + 1}", f.mass_kg, f.x_m, f.pitch_inertia_kg_m2))
    for k, x in enumerate(v.magnet_offsets_m):
        bodies.append(Body(f"magnet{k + 1}", v.magnet_mass_kg, x, None))
    conns = []
    for i, f in enumerate(v.frames):
        for k in f.magnets:
            conns.append(Connection(f"magnet{k}", f"frame{i + 1}", v.magnet_offsets_m[k - 1],
                                    v.primary.stiffness_n_per_m, v.primary.damping_n_s_per_m,
                                    f"primary{k}"))
    frame_x = np.array([f.x_m for f in v.frames])
    for j, x in enumerate(v.secondary_x_m):
        i = int(np.argmin(np.abs(frame_x - x)))
        conns.append(Connection(f"frame{i + 1}", "car", x, v.secondary.stiffness_n_per_m,
                                v.secondary.damping_n_s_per_m, f"secondary{j + 1}"))
    magnets = [Magnet(f"magnet{k + 1}", x) for k, x in enumerate(v.magnet_offsets_m)]
    return assemble(bodies, conns, magnets, v.gravity_mps2)


@dataclass(frozen=True)
class StaticEquilibrium:
    """Vehicle at rest with every magnet point at its nominal height (gap = g0 on a perfect rail)."""
    displacement: np.ndarray      # (n,) DOFs from the unloaded spring state (spring deflections)
    magnet_force_n: np.ndarray    # (n_mag,) upward magnet forces that hold the vehicle

    def to_dict(self) -> dict:
        return {"displacement": self.displacement.tolist(), "magnet_force_n": self.magnet_force_n.tolist()}


def static_equilibrium(model: VehicleModel) -> StaticEquilibrium:
    """Solve K u = g + B F with B^T u = 0 (all magnet points at nominal height).

    Saddle-point system [[K, -B], [B^T, 0]] [u; F] = [g; 0]: gives the spring deflections and the
    magnet load shares together, for any topology (also statically indeterminate ones).
    """
    n, m = model.n_dof, model.n_magnets
    B = model.magnet_input
    A = np.zeros((n + m, n + m))
    A[:n, :n] = model.stiffness
    A[:n, n:] = -B
    A[n:, :n] = B.T
    rhs = np.concatenate([model.gravity_load_n, np.zeros(m)])
    try:
        sol = np.linalg.solve(A, rhs)
    except np.linalg.LinAlgError:
        raise UserError("vehicle: static equilibrium is singular (a body is not held by any spring "
                        "or magnet)") from None
    return StaticEquilibrium(sol[:n], sol[n:])
