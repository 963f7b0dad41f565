"""The 12-DOF Euler-Bernoulli space-frame element of a straight girder along global x.

Axes (shared by ``system3d``): x along the line, y lateral (positive left), z vertical up,
right-handed; rotations theta_x (roll / torsion), theta_y (pitch), theta_z (yaw). Node DOFs in
the order ``DOF_NAMES`` = (u, v, w, theta_x, theta_y, theta_z); element DOFs are node i's six
then node j's six. The girder is straight along x, so element and global axes coincide (no
rotation matrix). Bending in the vertical x-z plane uses EI_y with theta_y = -dw/dx, in the
lateral x-y plane EI_z with theta_z = +dv/dx; axial EA and St-Venant torsion GJ are linear.
Consistent mass: rho A on u, v, w (Hermite cubic for v, w, linear for u) and the polar mass
rho I_p on theta_x (linear); rotary inertia of the bending rotations is neglected
(Euler-Bernoulli). Written by hand (~40 lines of textbook matrices, e.g. Przemieniecki,
*Theory of Matrix Structural Analysis*, 1968, ch. 5 and 11): the FE packages installed here
(PyNiteFEA) build models node by node with names and do not expose element matrices or shape
functions for a moving-load coupling.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from maglev_ros.errors import UserError

#: Node DOF names in their order (also the keys of support restraints and springs).
DOF_NAMES = ("x", "y", "z", "rx", "ry", "rz")
N_NODE_DOF = 6

# element DOF indices of the four independent actions
_AXIAL = np.array([0, 6])
_TORSION = np.array([3, 9])
_LATERAL = np.array([1, 5, 7, 11])      # v_i, theta_z_i, v_j, theta_z_j   (theta_z = dv/dx)
_VERTICAL = np.array([2, 4, 8, 10])     # w_i, theta_y_i, w_j, theta_y_j   (theta_y = -dw/dx)
_VERTICAL_SIGN = np.array([1.0, -1.0, 1.0, -1.0])


@dataclass(frozen=True)
class GirderSection:
    """Cross-section rigidities and masses per length of a girder (SI)."""

    axial_rigidity_n: float             # EA
    vertical_bending_rigidity_n_m2: float   # EI_y (bending in the x-z plane)
    lateral_bending_rigidity_n_m2: float    # EI_z (bending in the x-y plane)
    torsional_rigidity_n_m2: float      # G J (St-Venant)
    mass_per_length_kg_m: float         # rho A (+ superimposed mass carried by the girder)
    polar_mass_kg_m: float              # rho I_p (mass moment of inertia per length about x)

    def __post_init__(self) -> None:
        for key, val in asdict(self).items():
            if not (np.isfinite(val) and val > 0):
                raise UserError(f"girder section {key}: expected a finite value > 0, got {val!r}")

    def to_dict(self) -> dict:
        return asdict(self)


def hermite(xi, le: float) -> np.ndarray:
    """Hermite cubics at xi in [0, 1] for (w_i, w'_i, w_j, w'_j), w' = dw/dx: (..., 4)."""
    xi = np.asarray(xi, dtype=float)
    xi2, xi3 = xi * xi, xi * xi * xi
    return np.stack([1 - 3 * xi2 + 2 * xi3, le * (xi - 2 * xi2 + xi3), 3 * xi2 - 2 * xi3,
                     le * (-xi2 + xi3)], axis=-1)


def hermite_dx(xi, le: float) -> np.ndarray:
    """d/dx of ``hermite``: (..., 4)."""
    xi = np.asarray(xi, dtype=float)
    xi2 = xi * xi
    return np.stack([(-6 * xi + 6 * xi2) / le, 1 - 4 * xi + 3 * xi2, (6 * xi - 6 * xi2) / le,
                     -2 * xi + 3 * xi2], axis=-1)


def _beam_k(ei: float, le: float) -> np.ndarray:
    l2 = le * le
    return ei / le**3 * np.array([[12, 6 * le, -12, 6 * le], [6 * le, 4 * l2, -6 * le, 2 * l2],
                                  [-12, -6 * le, 12, -6 * le], [6 * le, 2 * l2, -6 * le, 4 * l2]])


def _beam_m(m: float, le: float) -> np.ndarray:
    l2 = le * le
    return m * le / 420.0 * np.array([[156, 22 * le, 54, -13 * le], [22 * le, 4 * l2, 13 * le, -3 * l2],
                                      [54, 13 * le, 156, -22 * le], [-13 * le, -3 * l2, -22 * le, 4 * l2]])


def _bar(c: float) -> np.ndarray:
    return c * np.array([[1.0, -1.0], [-1.0, 1.0]])


def _bar_mass(c: float) -> np.ndarray:
    return c / 6.0 * np.array([[2.0, 1.0], [1.0, 2.0]])


def element_matrices(section: GirderSection, le: float) -> tuple[np.ndarray, np.ndarray]:
    """(K, M), each 12x12, of one element of length ``le`` [m]."""
    if not le > 0:
        raise UserError(f"girder element length: expected > 0 m, got {le}")
    s = section
    k = np.zeros((12, 12))
    m = np.zeros((12, 12))
    k[np.ix_(_AXIAL, _AXIAL)] = _bar(s.axial_rigidity_n / le)
    m[np.ix_(_AXIAL, _AXIAL)] = _bar_mass(s.mass_per_length_kg_m * le)
    k[np.ix_(_TORSION, _TORSION)] = _bar(s.torsional_rigidity_n_m2 / le)
    m[np.ix_(_TORSION, _TORSION)] = _bar_mass(s.polar_mass_kg_m * le)
    k[np.ix_(_LATERAL, _LATERAL)] = _beam_k(s.lateral_bending_rigidity_n_m2, le)
    m[np.ix_(_LATERAL, _LATERAL)] = _beam_m(s.mass_per_length_kg_m, le)
    sgn = np.outer(_VERTICAL_SIGN, _VERTICAL_SIGN)  # theta_y = -dw/dx
    k[np.ix_(_VERTICAL, _VERTICAL)] = sgn * _beam_k(s.vertical_bending_rigidity_n_m2, le)
    m[np.ix_(_VERTICAL, _VERTICAL)] = sgn * _beam_m(s.mass_per_length_kg_m, le)
    return k, m


def point_shape_rows(xi, le, derivative: int = 0) -> dict[str, np.ndarray]:
    """Rows (..., 12) mapping element DOFs to the section's motion at xi in [0, 1] of elements
    of length ``le`` (a float or an array shaped like xi).

    Keys: "u", "v", "w", "rx" (displacements u, v, w of the shear centre and the torsion angle),
    for ``derivative`` 0, or their x-derivatives for ``derivative`` 1.
    """
    xi = np.asarray(xi, dtype=float)
    le = np.broadcast_to(np.asarray(le, dtype=float), xi.shape)
    out = {key: np.zeros(xi.shape + (12,)) for key in ("u", "v", "w", "rx")}
    if derivative == 0:
        h = hermite(xi, le)
        lin = np.stack([1.0 - xi, xi], axis=-1)
    elif derivative == 1:
        h = hermite_dx(xi, le)
        lin = np.stack([-np.ones_like(xi), np.ones_like(xi)], axis=-1) / le[..., None]
    else:
        raise UserError(f"girder shape functions: derivative must be 0 or 1, got {derivative!r}")
    out["u"][..., _AXIAL] = lin
    out["rx"][..., _TORSION] = lin
    out["v"][..., _LATERAL] = h
    out["w"][..., _VERTICAL] = h * _VERTICAL_SIGN
    return out
