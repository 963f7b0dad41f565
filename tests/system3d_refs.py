"""Independent references for the system3d girder tests: PyNiteFEA models of the same girder
and analytic continuous-beam frequencies from the characteristic equation."""
from __future__ import annotations

import numpy as np
from scipy.optimize import brentq


def pynite_girder(node_x_m, section_props, supports, rho=1.0):
    """A PyNiteFEA model of a straight girder along X with nodes at ``node_x_m``.

    section_props: E, G, A, Iy, Iz, J (Pynite's polar mass is rho J, its mass per length rho A);
    supports: {node index: (DX, DY, DZ, RX, RY, RZ) booleans}."""
    from Pynite import FEModel3D

    E, G, A, Iy, Iz, J = section_props
    m = FEModel3D()
    m.add_material("c", E, G, 0.3, rho)
    m.add_section("s", A, Iy, Iz, J)
    for i, x in enumerate(node_x_m):
        m.add_node(f"N{i}", float(x), 0.0, 0.0)
    for i in range(len(node_x_m) - 1):
        m.add_member(f"M{i}", f"N{i}", f"N{i + 1}", "c", "s")
    for i, flags in supports.items():
        m.def_support(f"N{i}", *flags)
    return m


def pynite_nodal(model, n_nodes, combo="Combo 1"):
    """(n_nodes, 6) displacements DX, DY, DZ, RX, RY, RZ of a solved Pynite model."""
    out = np.zeros((n_nodes, 6))
    for i in range(n_nodes):
        nd = model.nodes[f"N{i}"]
        out[i] = [nd.DX[combo], nd.DY[combo], nd.DZ[combo], nd.RX[combo], nd.RY[combo], nd.RZ[combo]]
    return out


def _span_basis(beta, L, xi):
    """Values and derivatives 0..2 of cos, sin, exp(-beta x), exp(-beta (L - x)) at x = xi."""
    c, s = np.cos(beta * xi), np.sin(beta * xi)
    e1, e2 = np.exp(-beta * xi), np.exp(-beta * (L - xi))
    return np.array([[c, s, e1, e2],
                     [-beta * s, beta * c, -beta * e1, beta * e2],
                     [-beta**2 * c, -beta**2 * s, beta**2 * e1, beta**2 * e2]])


def _char_matrix(omega, spans, ei, m):
    """Homogeneous conditions of an Euler-Bernoulli beam on point supports, pinned at both ends
    (w = 0 at every support, slope and moment continuous over interior supports, moment 0 at the
    ends); exponentials instead of cosh/sinh keep it well conditioned."""
    beta = (omega**2 * m / ei) ** 0.25
    n = len(spans)
    A = np.zeros((4 * n, 4 * n))
    row = 0
    for i, L in enumerate(spans):
        b0, bL = _span_basis(beta, L, 0.0), _span_basis(beta, L, L)
        A[row, 4 * i:4 * i + 4] = b0[0]; row += 1
        A[row, 4 * i:4 * i + 4] = bL[0]; row += 1
        if i == 0:
            A[row, 0:4] = b0[2]; row += 1
        if i == n - 1:
            A[row, 4 * i:4 * i + 4] = bL[2]; row += 1
        else:
            nxt = _span_basis(beta, spans[i + 1], 0.0)
            for d in (1, 2):
                A[row, 4 * i:4 * i + 4] = bL[d]
                A[row, 4 * i + 4:4 * i + 8] = -nxt[d]
                row += 1
    return A


def continuous_beam_freqs_hz(spans, ei, m, n_modes, f_max_hz):
    """First bending frequencies of a continuous beam on rigid point supports (pinned ends),
    roots of det(conditions) = 0 found by a scan and Brent's method."""
    f = np.linspace(1e-3, f_max_hz, 4000)
    d = np.array([np.linalg.det(_char_matrix(2 * np.pi * fi, spans, ei, m)) for fi in f])
    roots = []
    for k in np.flatnonzero(np.sign(d[:-1]) * np.sign(d[1:]) < 0):
        roots.append(brentq(lambda x: np.linalg.det(_char_matrix(2 * np.pi * x, spans, ei, m)), f[k], f[k + 1]))
        if len(roots) == n_modes:
            break
    return np.array(roots)
