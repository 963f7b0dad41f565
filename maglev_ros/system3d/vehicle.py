"""3D multibody vehicle assembled from ``VehicleData`` by the point map (001's "fully computerized"
assembly, in 3D).

Each body has six small motions about its centre c, q_b = (x, y, z, rx, ry, rz). A point p of the
body moves by d = T q_b, T = [I | -[r]x], r = p - c (d = u + theta x r). A connection at point p
between bodies a and b (or a and the ground) strains by d_a - d_b; with the diagonal stiffness
k = diag(kx, ky, kz) and damping c in the vehicle axes it adds T_ab^T k T_ab to K and T_ab^T c T_ab
to C (T_ab = T_a - T_b on the full 6-per-body coordinates). M is diag(m, m, m, Ixx, Iyy, Izz) per
body. Nothing about the topology is coded: another vehicle is another data file.

A body keeps only its DOF subset. ``absent_dofs`` says what an absent DOF does:
* ``held``: it is fixed at 0 (a prescribed motion, e.g. running at constant speed): the matrices
  are the retained rows/columns.
* ``quasi_static``: it is massless and follows the retained DOFs so that its generalised spring
  forces vanish, q_c = -K_cc^+ K_cr q_r (static condensation; K_cc^+ the pseudo-inverse, exact for
  a positive semi-definite K). Then K_red = P^T K P, C_red = P^T C P, loads P^T f with
  P = [I; -K_cc^+ K_cr], M_red = M_rr. With longitudinal springs (001's fixed sliding tables)
  between bodies whose centres differ in height or lateral position, ``held`` stiffens pitch and
  yaw of the whole vehicle by k_x (dz)^2 and k_x (dy)^2, ``quasi_static`` does not.

Gravity -m g acts on each body's z (through P, so with ``held`` a body without z gives its weight
to the constraint). ``static_equilibrium`` finds the levitation loops' static forces with every
loop's mean gap at its nominal value (current_loop.py gives the force law).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from maglev_ros.errors import UserError
from maglev_ros.twin.design import TwinConfig
from maglev_ros.system3d.vehicle_data import (DOF_NAMES, GROUND, Connection, CurrentLoop, Magnet, RigidBody,
                                              VehicleData)

N_BODY_DOF = len(DOF_NAMES)


def skew(r) -> np.ndarray:
    """[r]x: skew(r) @ v = r x v."""
    x, y, z = r
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def point_map(centre_m, point_m) -> np.ndarray:
    """T (3 x 6): displacement of ``point_m`` from the 6 motions of a body centred at ``centre_m``."""
    r = np.asarray(point_m, float) - np.asarray(centre_m, float)
    return np.hstack([np.eye(3), -skew(r)])


@dataclass(frozen=True)
class Vehicle3D:
    """Assembled linear vehicle: M q'' + C q' + K q = f (q the retained DOFs, ``dof_names``)."""
    data: VehicleData
    dof_names: tuple[str, ...]        # "body.dof"
    mass: np.ndarray
    damping: np.ndarray
    stiffness: np.ndarray
    reduction: np.ndarray             # P (6 n_bodies x n): all body motions from the retained DOFs
    gravity_load_n: np.ndarray        # (n,)

    @property
    def n_dof(self) -> int:
        return len(self.dof_names)

    def dof_index(self, name: str) -> int:
        return self.dof_names.index(name)

    def point_rows(self, body: str, point_m) -> np.ndarray:
        """(3, n): x, y, z displacement of a point of ``body`` from the retained DOFs."""
        return _full_point_rows(self.data, body, point_m) @ self.reduction

    def magnet_rows(self) -> np.ndarray:
        """(n_mag, 3, n): displacement of each magnet's force point."""
        return np.stack([self.point_rows(m.body, m.point_m) for m in self.data.magnets])

    def rigid_body_mode_count(self, rel_tol: float = 1e-9) -> int:
        """Zero-frequency modes of M q'' + K q = 0 (eigenvalues of M^-1/2 K M^-1/2 below rel_tol * max)."""
        lam = np.linalg.eigvalsh(_mass_normalised(self.mass, self.stiffness))
        return int(np.sum(np.abs(lam) <= rel_tol * np.max(np.abs(lam))))

    def natural_frequencies_hz(self) -> np.ndarray:
        lam = np.linalg.eigvalsh(_mass_normalised(self.mass, self.stiffness))
        return np.sqrt(np.clip(lam, 0.0, None)) / (2 * np.pi)


def _mass_normalised(M: np.ndarray, K: np.ndarray) -> np.ndarray:
    w, V = np.linalg.eigh(M)
    Mh = V @ np.diag(w ** -0.5) @ V.T
    S = Mh @ K @ Mh
    return 0.5 * (S + S.T)


def _body_index(data: VehicleData) -> dict[str, int]:
    return {b.name: i for i, b in enumerate(data.bodies)}


def _full_point_rows(data: VehicleData, body: str, point_m) -> np.ndarray:
    """(3, 6 n_bodies) point map on all body motions (zero for the ground)."""
    rows = np.zeros((3, N_BODY_DOF * len(data.bodies)))
    if body == GROUND:
        return rows
    i = _body_index(data)[body]
    rows[:, N_BODY_DOF * i:N_BODY_DOF * (i + 1)] = point_map(data.bodies[i].centre_m, point_m)
    return rows


def _connection_rows(data: VehicleData, c: Connection) -> np.ndarray:
    return _full_point_rows(data, c.body_a, c.point_m) - _full_point_rows(data, c.body_b, c.point_m)


def full_matrices(data: VehicleData) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """M, C, K and gravity load on all six motions of every body (before the DOF subsets)."""
    nf = N_BODY_DOF * len(data.bodies)
    M = np.zeros((nf, nf))
    g = np.zeros(nf)
    for i, b in enumerate(data.bodies):
        M[N_BODY_DOF * i:N_BODY_DOF * (i + 1), N_BODY_DOF * i:N_BODY_DOF * (i + 1)] = np.diag(
            [b.mass_kg] * 3 + list(b.inertia_kg_m2))
        g[N_BODY_DOF * i + 2] = -b.mass_kg * data.gravity_mps2
    K = np.zeros((nf, nf))
    C = np.zeros((nf, nf))
    for c in data.connections:
        T = _connection_rows(data, c)
        K += T.T @ np.diag(c.stiffness_n_per_m) @ T
        C += T.T @ np.diag(c.damping_n_s_per_m) @ T
    return M, C, K, g


def assemble(data: VehicleData) -> Vehicle3D:
    """M, C, K and gravity load on the retained DOFs (module docstring)."""
    M, C, K, g = full_matrices(data)
    kept = [N_BODY_DOF * i + DOF_NAMES.index(d) for i, b in enumerate(data.bodies) for d in b.dofs]
    names = tuple(f"{b.name}.{d}" for b in data.bodies for d in b.dofs)
    absent = [j for j in range(M.shape[0]) if j not in set(kept)]
    P = np.zeros((M.shape[0], len(kept)))
    P[kept, np.arange(len(kept))] = 1.0
    if data.absent_dofs == "quasi_static" and absent:
        Kcc = K[np.ix_(absent, absent)]
        P[absent, :] = -np.linalg.pinv(Kcc, rcond=1e-12, hermitian=True) @ K[np.ix_(absent, kept)]
    Kr = P.T @ K @ P
    Cr = P.T @ C @ P
    Mr = M[np.ix_(kept, kept)]
    return Vehicle3D(data, names, Mr, Cr, Kr, P, P.T @ g)


# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class StaticLoads:
    """Vehicle at rest with each levitation loop's mean gap nominal (rail perfect)."""
    displacement: np.ndarray          # (n,) retained DOFs from the unloaded springs
    magnet_force_n: np.ndarray        # (n_mag,) static attractive force of each magnet (along its direction)
    gap_offset_m: np.ndarray          # (n_mag,) each magnet's static gap minus its loop's nominal gap

    def to_dict(self) -> dict:
        return {k: np.asarray(v).tolist() for k, v in self.__dict__.items()}


def loop_incidence(data: VehicleData) -> np.ndarray:
    """S (n_mag, n_loop): 1 where a magnet is driven by a loop."""
    ids = [lp.id for lp in data.loops]
    S = np.zeros((len(data.magnets), len(ids)))
    for r, m in enumerate(data.magnets):
        S[r, ids.index(m.loop)] = 1.0
    return S


def magnet_directions(data: VehicleData) -> np.ndarray:
    return np.array([m.direction for m in data.magnets])


def static_equilibrium(vehicle: Vehicle3D, lateral_stiffness: np.ndarray | None = None) -> StaticLoads:
    """Solve (K + K_lat) u - B S f = g + B F_pre, G B^T u = 0 for u and the levitation loop forces f.

    B's column r is the generalised force of a unit force along magnet r's direction, S shares a
    loop's force equally among its magnets (same current, nominal gaps), G takes the loop means;
    guidance magnets carry their loop's preload F_pre. ``lateral_stiffness`` (n, n) is the passive
    lateral stiffness of the magnets (it holds lateral and yaw rigid-body motions).
    """
    data = vehicle.data
    rows = vehicle.magnet_rows()
    dirs = magnet_directions(data)
    B = np.einsum("rjn,rj->nr", rows, dirs)
    S = loop_incidence(data)
    lev = [j for j, lp in enumerate(data.loops) if _loop_role(data, lp) == "levitation"]
    count = S.sum(axis=0)
    Bl = B @ (S[:, lev] / count[lev])                  # unit loop force shared equally
    G = (S[:, lev] / count[lev]).T @ B.T               # loop mean displacement along the directions
    pre = np.array([data.loops[[lp.id for lp in data.loops].index(m.loop)].preload_force_n
                    if m.role == "guidance" else 0.0 for m in data.magnets])
    n, m = vehicle.n_dof, len(lev)
    K = vehicle.stiffness + (lateral_stiffness if lateral_stiffness is not None else 0.0)
    s = max(float(np.max(np.abs(np.diag(K)))), 1.0)      # scale the constraint rows like K (conditioning)
    A = np.block([[K, -s * Bl], [s * G, np.zeros((m, m))]])
    rhs = np.concatenate([vehicle.gravity_load_n + B @ pre, np.zeros(m)])
    try:
        sol = np.linalg.solve(A, rhs)
    except np.linalg.LinAlgError:      # a neutral (unloaded) rigid-body motion: take the least-norm one
        sol = np.linalg.lstsq(A, rhs, rcond=None)[0]
    if np.linalg.norm(A @ sol - rhs) > 1e-9 * max(np.linalg.norm(rhs), 1.0):
        raise UserError(f"vehicle {data.name}: no static equilibrium with every levitation loop at its nominal gap "
                        f"(a load path is missing: check connections and magnets)")
    u, f = sol[:n], s * sol[n:]
    force = pre.copy()
    lev_mag = S[:, lev].any(axis=1)
    force[lev_mag] = ((S[:, lev] / count[lev]) @ f)[lev_mag]
    dh = -np.einsum("rj,rjn,n->r", dirs, rows, u)      # moving towards the rail closes the gap
    return StaticLoads(u, force, dh - S @ ((S / count).T @ dh))


def _loop_role(data: VehicleData, loop: CurrentLoop) -> str:
    return next(m.role for m in data.magnets if m.loop == loop.id)


# ---------------------------------------------------------------------------------------------
def vertical_vehicle_data(config: TwinConfig, *, inductance_h: float = 0.0, resistance_ohm: float | None = None) -> VehicleData:
    """Today's vertical twin vehicle (``twin/vehicle.py`` ``vehicle_from_design``) as 3D data in the x-z plane.

    Car body and frames keep z and ry (pitch: today's nose-up pitch is -ry), magnets z; every
    connection is vertical at the same x as today's; one current loop per magnet with today's
    gains as voltage gains R k (the current-commanded law is the L0 -> 0 limit).
    """
    v, lev = config.vehicle, config.levitation
    big = 1.0        # rotary inertias the subsets never use (rx, rz) only need to be positive
    bodies = [RigidBody("car", v.car_body.mass_kg, (big, v.car_body.pitch_inertia_kg_m2, big),
                        (v.car_body.x_m, 0.0, 0.0), ("z", "ry"))]
    for i, f in enumerate(v.frames):
        bodies.append(RigidBody(f"frame{i + 1}", f.mass_kg, (big, f.pitch_inertia_kg_m2, big), (f.x_m, 0.0, 0.0),
                                ("z", "ry")))
    for k, x in enumerate(v.magnet_offsets_m):
        bodies.append(RigidBody(f"magnet{k + 1}", v.magnet_mass_kg, (big, big, big), (x, 0.0, 0.0), ("z",)))
    conns = []
    for i, f in enumerate(v.frames):
        for k in f.magnets:
            conns.append(Connection(f"primary{k}", f"magnet{k}", f"frame{i + 1}", (v.magnet_offsets_m[k - 1], 0.0, 0.0),
                                    "spring", (0.0, 0.0, v.primary.stiffness_n_per_m),
                                    (0.0, 0.0, v.primary.damping_n_s_per_m)))
    frame_x = np.array([f.x_m for f in v.frames])
    for j, x in enumerate(v.secondary_x_m):
        i = int(np.argmin(np.abs(frame_x - x)))
        conns.append(Connection(f"secondary{j + 1}", f"frame{i + 1}", "car", (x, 0.0, 0.0), "spring",
                                (0.0, 0.0, v.secondary.stiffness_n_per_m), (0.0, 0.0, v.secondary.damping_n_s_per_m)))
    R = lev.coil_resistance_ohm if resistance_ohm is None else resistance_ohm
    magnets, loops = [], []
    for k, x in enumerate(v.magnet_offsets_m):
        magnets.append(Magnet(f"magnet{k + 1}", f"magnet{k + 1}", (x, 0.0, 0.0), "left", "levitation", f"loop{k + 1}"))
        loops.append(CurrentLoop(f"loop{k + 1}", lev.nominal_gap_m, lev.static_current_a, inductance_h, R,
                                 R * lev.kp_a_per_m, R * lev.kv_a_s_per_m, R * lev.ka_a_s2_per_m))
    return VehicleData("vertical twin (twin/vehicle.py)", v.gravity_mps2, 0.0, "held", "none", 0.0,
                       tuple(bodies), tuple(conns), tuple(magnets), tuple(loops))
