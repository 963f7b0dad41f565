"""system3d rail-point interpolation: rigid-body motions reproduced exactly (torsion gives the
left/right rails +-b theta vertically), slopes, velocities, and the load vector's work."""
from __future__ import annotations

import numpy as np
import pytest

from maglev_ros.errors import UserError
from maglev_ros.system3d.girder import GirderSpec, Support, assemble_girder
from maglev_ros.system3d.girder_element import DOF_NAMES, GirderSection
from maglev_ros.system3d.girder_rails import RailInterpolation, RailLayout

B, ZR, YC = 1.0, 2.2, 0.4   # half gauge, rail height over the shear centre, track centre offset


@pytest.fixture(scope="module")
def free_girder():
    sec = GirderSection(2e11, 6e11, 2e12, 4e11, 2e4, 2e5)
    spec = GirderSpec("free", (20.0, 30.0, 25.0), 5, sec, supports=(), start_m=10.0)
    g = assemble_girder(spec)
    return g, RailInterpolation(g, RailLayout(B, ZR, YC))


def _rigid(g, translation=(0, 0, 0), rotation=(0, 0, 0), about_x_m=0.0):
    """Nodal DOFs of a small rigid motion: u = t + theta x (r - r0), r0 = (about_x, 0, 0)."""
    t, th = np.asarray(translation, float), np.asarray(rotation, float)
    r = np.zeros((g.n_nodes, 3))
    r[:, 0] = g.node_x_m - about_x_m
    disp = t + np.cross(th, r)
    full = np.hstack([disp, np.broadcast_to(th, (g.n_nodes, 3))]).ravel()
    return full[g.free_dofs]


def _exact_rail(x, side, translation, rotation, about_x_m):
    y_r = YC + (B if side == "left" else -B)
    r = np.stack([x - about_x_m, np.full_like(x, y_r), np.full_like(x, ZR)], axis=-1)
    return np.asarray(translation, float) + np.cross(np.asarray(rotation, float), r)


@pytest.mark.parametrize("rotation", [(1e-3, 0, 0), (0, 2e-4, 0), (0, 0, -3e-4), (4e-4, -1e-4, 2e-4)])
def test_rigid_body_motion_is_reproduced_exactly(free_girder, rotation):
    g, ri = free_girder
    trans = (1e-3, -2e-3, 5e-4)
    u = _rigid(g, trans, rotation, about_x_m=37.0)
    x = np.random.default_rng(0).uniform(10.0, 85.0, 40)
    for side in ("left", "right"):
        exact = _exact_rail(x, side, trans, rotation, 37.0)
        np.testing.assert_allclose(ri.matrix(x, side, "z") @ u, exact[:, 2], atol=1e-15, rtol=1e-12)
        np.testing.assert_allclose(ri.matrix(x, side, "y") @ u, exact[:, 1], atol=1e-15, rtol=1e-12)
        # slope of the rigid field: d/dx (theta x r) = theta x e_x = (0, theta_z, -theta_y)
        np.testing.assert_allclose(ri.matrix(x, side, "z", derivative=1) @ u, -rotation[1], atol=1e-15)
        np.testing.assert_allclose(ri.matrix(x, side, "y", derivative=1) @ u, rotation[2], atol=1e-15)


def test_torsion_moves_left_and_right_rails_by_plus_minus_b_theta(free_girder):
    g, ri = free_girder
    theta = 2e-3
    u = _rigid(g, rotation=(theta, 0, 0))
    x = np.linspace(10.0, 85.0, 31)
    m = ri.rail_motion(u, x)
    np.testing.assert_allclose(m["z_left"], (YC + B) * theta, rtol=1e-12)
    np.testing.assert_allclose(m["z_right"], (YC - B) * theta, rtol=1e-12)
    np.testing.assert_allclose(m["z_left"] - m["z_right"], 2 * B * theta, rtol=1e-12)
    np.testing.assert_allclose(m["y_left"], -ZR * theta, rtol=1e-12)
    # a velocity vector goes through the same rows (rail velocity at a fixed x)
    v = ri.rail_motion(u / 0.01, x)
    np.testing.assert_allclose(v["z_left"], (YC + B) * theta / 0.01, rtol=1e-12)


def test_bending_field_is_interpolated_by_the_element_cubic(free_girder):
    """A cubic w(x) (and v(x)) inside each element is reproduced exactly (Hermite interpolation)."""
    g, ri = free_girder
    xn = g.node_x_m
    full = np.zeros((g.n_nodes, 6))
    c = np.array([1e-3, -2e-5, 3e-7, -1e-9])
    w = np.polyval(c[::-1], xn)
    dw = np.polyval(np.polyder(c[::-1]), xn)
    full[:, 2], full[:, 4] = w, -dw           # theta_y = -dw/dx
    full[:, 1], full[:, 5] = -w, -dw          # v = -w, theta_z = dv/dx
    u = full.ravel()[g.free_dofs]
    x = np.linspace(10.0, 85.0, 57)
    np.testing.assert_allclose(ri.matrix(x, "left", "z") @ u, np.polyval(c[::-1], x), rtol=1e-10)
    np.testing.assert_allclose(ri.matrix(x, "right", "y") @ u, -np.polyval(c[::-1], x), rtol=1e-10)
    np.testing.assert_allclose(ri.matrix(x, "left", "z", 1) @ u, np.polyval(np.polyder(c[::-1]), x), rtol=1e-10)


def test_load_vector_does_the_work_of_the_rail_force(free_girder):
    """N^T F: its work on any DOF vector equals F times the rail motion (virtual work); a vertical
    force on the left rail at a node is a force F and a torque y_r F there."""
    g, ri = free_girder
    u = np.random.default_rng(1).normal(size=g.n_free)
    x = np.array([23.3, 51.0, 70.7])
    fz, fy = np.array([1e5, -2e5, 3e4]), np.array([-4e4, 1e4, 2e4])
    q = ri.load_vector(x, "right", force_z_n=fz, force_y_n=fy)
    work = fz @ (ri.matrix(x, "right", "z") @ u) + fy @ (ri.matrix(x, "right", "y") @ u)
    assert q @ u == pytest.approx(work, rel=1e-12)
    xn = g.node_x_m[7]
    q1 = ri.load_vector(xn, "left", force_z_n=1e5)
    assert q1[g.dof(xn, "z")] == pytest.approx(1e5)
    assert q1[g.dof(xn, "rx")] == pytest.approx((YC + B) * 1e5)
    assert np.count_nonzero(np.abs(q1) > 1e-9) == 2


def test_points_off_the_girder_and_restrained_dofs():
    sec = GirderSection(2e11, 6e11, 2e12, 4e11, 2e4, 2e5)
    sup = (Support(0.0, DOF_NAMES), Support(30.0, ("y", "z", "rx")))
    g = assemble_girder(GirderSpec("s", (30.0,), 6, sec, sup))
    ri = RailInterpolation(g, RailLayout(B))
    m = ri.matrix([-1.0, 0.0, 30.0, 31.0], "left", "z")
    assert m.shape == (4, g.n_free)
    assert not m.any()          # off the girder: ground; over restrained supports: no free DOF moves it
    with pytest.raises(UserError, match="side"):
        ri.matrix(1.0, "middle", "z")
    with pytest.raises(UserError, match="direction"):
        ri.matrix(1.0, "left", "x")
    with pytest.raises(UserError, match="half_gauge_m"):
        RailLayout(0.0)
