"""Vehicle assembly, static equilibrium, levitation law and closed-loop poles vs independent references."""
import math

import numpy as np
import pytest

from maglev_ros.errors import ContractError
from maglev_ros.twin.design import twin_config, with_levitation
from maglev_ros.twin.levitation import (LevitationModel, build_vehicle, closed_loop, closed_loop_poles,
                                        is_stable)
from maglev_ros.twin.vehicle import Body, Connection, Magnet, assemble, static_equilibrium, vehicle_from_design


def test_default_vehicle_has_18_dofs_and_symmetric_matrices():
    model = vehicle_from_design(twin_config().vehicle)
    assert model.n_dof == 18 and model.n_magnets == 8
    assert len(model.magnet_dofs) == 8
    for mat in (model.mass, model.damping, model.stiffness):
        np.testing.assert_allclose(mat, mat.T, atol=1e-9 * np.abs(mat).max())
    # free vehicle (no magnets): exactly two rigid-body modes (heave, pitch of the whole vehicle)
    ev = np.linalg.eigvalsh(model.stiffness)
    assert np.sum(np.abs(ev) < 1e-6 * ev.max()) == 2
    # rigid heave and rigid pitch produce no spring force
    heave = np.array([1.0 if n.endswith(".z") else 0.0 for n in model.dof_names])
    np.testing.assert_allclose(model.stiffness @ heave, 0.0, atol=1e-6)


def test_assembly_matches_hand_derived_entries():
    v = twin_config().vehicle
    model = vehicle_from_design(v)
    K = model.stiffness
    ks, kp = v.secondary.stiffness_n_per_m, v.primary.stiffness_n_per_m
    i = model.dof_index
    assert K[i("car.z"), i("car.z")] == pytest.approx(ks * len(v.secondary_x_m))
    xc = v.car_body.x_m
    assert K[i("car.pitch"), i("car.pitch")] == pytest.approx(ks * sum((x - xc) ** 2 for x in v.secondary_x_m))
    f1 = v.frames[0]
    arms_p = [v.magnet_offsets_m[k - 1] - f1.x_m for k in f1.magnets]
    arms_s = [x - f1.x_m for x in v.secondary_x_m if abs(x - f1.x_m) < 3.0]
    assert K[i("frame1.pitch"), i("frame1.pitch")] == pytest.approx(
        kp * sum(a * a for a in arms_p) + ks * sum(a * a for a in arms_s))
    assert K[i("magnet1.z"), i("frame1.z")] == pytest.approx(-kp)
    assert K[i("magnet1.z"), i("frame1.pitch")] == pytest.approx(-kp * (v.magnet_offsets_m[0] - f1.x_m))


def test_two_mass_quarter_vehicle_from_data():
    """Textbook 2-DOF: body m2 on spring k2 over magnet m1."""
    m1, m2, k2, c2 = 800.0, 6000.0, 3e5, 2e4
    model = assemble([Body("body", m2, 0.0), Body("mag", m1, 0.0)],
                     [Connection("mag", "body", 0.0, k2, c2)], [Magnet("mag", 0.0)])
    np.testing.assert_allclose(model.stiffness, [[k2, -k2], [-k2, k2]])
    np.testing.assert_allclose(model.damping, [[c2, -c2], [-c2, c2]])
    np.testing.assert_allclose(model.mass, np.diag([m2, m1]))
    eq = static_equilibrium(model)
    assert eq.magnet_force_n[0] == pytest.approx((m1 + m2) * 9.81)
    assert eq.displacement[0] == pytest.approx(-m2 * 9.81 / k2)   # spring compressed by body weight


@pytest.mark.parametrize("car_x", [-10.062, -8.0, -12.5])
def test_static_equilibrium_balances_forces_and_moments(car_x):
    cfg = twin_config({"vehicle": {"car_body": {"x_m": car_x}}})
    model = vehicle_from_design(cfg.vehicle)
    eq = static_equilibrium(model)
    W = cfg.vehicle.total_mass_kg * cfg.vehicle.gravity_mps2
    assert eq.magnet_force_n.sum() == pytest.approx(W, rel=1e-9)
    # moment about x = 0 of all weights equals that of the magnet forces (independent statics)
    v = cfg.vehicle
    g = v.gravity_mps2
    m_w = g * (v.car_body.mass_kg * v.car_body.x_m + sum(f.mass_kg * f.x_m for f in v.frames)
               + v.magnet_mass_kg * sum(v.magnet_offsets_m))
    assert float(eq.magnet_force_n @ np.array(v.magnet_offsets_m)) == pytest.approx(m_w, rel=1e-9)
    # magnet points stay at nominal height
    np.testing.assert_allclose(model.magnet_input.T @ eq.displacement, 0.0, atol=1e-12)
    if car_x != -10.062:
        assert np.ptp(eq.magnet_force_n) > 100.0     # unequal shares are solved, not assumed


def test_levitation_force_law_and_partials_vs_finite_differences():
    cfg = twin_config()
    vs = build_vehicle(cfg)
    lev = vs.levitation
    g0, I0 = lev.nominal_gap_m, lev.static_current_a
    np.testing.assert_allclose(lev.force(I0, g0), vs.equilibrium.magnet_force_n, rtol=1e-12)
    p = lev.partials()
    d = 1e-7

    def F(gap, rate, acc):
        return lev.force(lev.current_command(gap, rate, acc), gap)
    np.testing.assert_allclose((F(g0 + d, 0, 0) - F(g0 - d, 0, 0)) / (2 * d), p.df_dgap_n_per_m, rtol=1e-5)
    np.testing.assert_allclose((F(g0, 1e-4, 0) - F(g0, -1e-4, 0)) / 2e-4, p.df_dgap_rate_n_s_per_m, rtol=1e-5)
    np.testing.assert_allclose((F(g0, 0, 1e-3) - F(g0, 0, -1e-3)) / 2e-3, p.df_daccel_n_s2_per_m, rtol=1e-5)
    # gap grows -> more current -> force grows (the controller restores the gap)
    assert np.all(p.df_dgap_n_per_m > 0)


def test_single_magnet_poles_match_characteristic_equation():
    """1-DOF magnet of mass m: (m + m_a) s^2 + c_g s + k_g = 0 (independent closed form)."""
    m = 1500.0
    model = assemble([Body("mag", m, 0.0)], [], [Magnet("mag", 0.0)])
    eq = static_equilibrium(model)
    cfg = twin_config()
    lev = LevitationModel.from_design(cfg.levitation, eq.magnet_force_n)
    ss = closed_loop(model, lev)
    p = lev.partials()
    ref = np.roots([m - p.df_daccel_n_s2_per_m[0], p.df_dgap_rate_n_s_per_m[0], p.df_dgap_n_per_m[0]])
    np.testing.assert_allclose(np.sort_complex(ss.poles()), np.sort_complex(ref), rtol=1e-9)


def test_default_closed_loop_poles_are_stable(capsys):
    poles = closed_loop_poles(twin_config())
    with capsys.disabled():
        print("\nclosed-loop poles (Hz, rigid guideway): "
              + ", ".join(f"{p.real / (2 * math.pi):.2f}{p.imag / (2 * math.pi):+.2f}j" for p in poles[::2]))
    assert poles.size == 36
    assert is_stable(poles, margin=0.5)


@pytest.mark.parametrize("L_h", [0.001, 0.005])
def test_coil_dynamics_poles_stable_and_tend_to_instant_current(L_h):
    cfg = with_levitation(twin_config(), coil_inductance_h=L_h, coil_resistance_ohm=1.0)
    poles = closed_loop_poles(cfg)
    assert poles.size == 36 + 8
    assert is_stable(poles)
    # slowest poles close to the instant-current model's (the coil adds fast poles near -R/L)
    p0 = closed_loop_poles(twin_config())
    np.testing.assert_allclose(np.sort(np.abs(poles))[:4], np.sort(np.abs(p0))[:4], rtol=0.05)


def test_unstable_gains_are_detected():
    cfg = with_levitation(twin_config(), kp_a_per_m=1000.0)   # kI kp < kgap: negative stiffness
    assert not is_stable(closed_loop_poles(cfg))


def test_design_block_overrides_defaults():
    design = {
        "guideway": {"youngs_modulus_pa": 3.6e10, "damping_ratio": 0.03},
        "vehicle": {"car_body": {"mass_kg": 30000.0}, "magnet_mass_kg": 800.0,
                    "primary": {"stiffness_n_per_m": 3.0e6},
                    "secondary": {"damping_n_s_per_m": 1.0e4, "x_m": [0.0, -6.192, -12.384, -18.576]}},
        "levitation": {"static_current_a": 30.0, "kp_a_per_m": 6000.0, "kv_a_s_per_m": 35.0,
                       "ka_a_s2_per_m": 0.1},
        "unknown_key": {"ignored": True},
    }
    d = twin_config()
    c = twin_config(design)
    assert c.guideway.youngs_modulus_pa == 3.6e10 and c.guideway.damping_ratio == 0.03
    assert c.guideway.area_m2 == d.guideway.area_m2
    assert c.vehicle.car_body.mass_kg == 30000.0
    assert c.vehicle.car_body.pitch_inertia_kg_m2 == d.vehicle.car_body.pitch_inertia_kg_m2
    assert c.vehicle.magnet_mass_kg == 800.0
    assert c.vehicle.primary.stiffness_n_per_m == 3.0e6
    assert c.vehicle.primary.damping_n_s_per_m == d.vehicle.primary.damping_n_s_per_m
    assert c.vehicle.secondary.damping_n_s_per_m == 1.0e4
    assert c.vehicle.secondary_x_m == (0.0, -6.192, -12.384, -18.576)
    assert (c.levitation.static_current_a, c.levitation.kp_a_per_m, c.levitation.kv_a_s_per_m,
            c.levitation.ka_a_s2_per_m) == (30.0, 6000.0, 35.0, 0.1)
    vs = build_vehicle(c)
    W = (30000.0 + 4 * 1000.0 + 8 * 800.0) * 9.81
    assert vs.equilibrium.magnet_force_n.sum() == pytest.approx(W)
    np.testing.assert_allclose(vs.levitation.force(30.0, 0.010), vs.equilibrium.magnet_force_n)
    assert is_stable(vs.state_space.poles())
    assert c.to_dict()["vehicle"]["car_body"]["mass_kg"] == 30000.0


def test_design_frames_and_magnet_offsets():
    design = {"vehicle": {"frames": [{"mass_kg": 500.0, "pitch_inertia_kg_m2": 300.0, "x_m": -0.5, "magnets": [1, 2]},
                                     {"mass_kg": 500.0, "pitch_inertia_kg_m2": 300.0, "x_m": -4.5, "magnets": [3, 4]}],
                          "car_body": {"x_m": -2.5, "mass_kg": 10000.0, "pitch_inertia_kg_m2": 1e5},
                          "secondary": {"x_m": [0.0, -1.0, -4.0, -5.0]}}}
    c = twin_config(design, magnet_offsets_m=[0.0, -1.0, -4.0, -5.0])
    model = vehicle_from_design(c.vehicle)
    assert model.n_dof == 2 + 2 * 2 + 4
    assert is_stable(closed_loop_poles(c))


@pytest.mark.parametrize("design,key", [
    ({"guideway": {"area_m2": "1.5"}}, "design.guideway.area_m2"),
    ({"guideway": {"density_kg_m3": -1.0}}, "design.guideway.density_kg_m3"),
    ({"vehicle": {"car_body": {"mass_kg": None}}}, "design.vehicle.car_body.mass_kg"),
    ({"vehicle": {"frames": [{"magnets": [1, 2, 3, 4, 5, 6, 7, 9]}]}}, r"design.vehicle.frames\[0\].magnets"),
    ({"vehicle": {"frames": [{"magnets": [1, 2]}]}}, "design.vehicle.frames"),
    ({"levitation": {"kp_a_per_m": [1]}}, "design.levitation.kp_a_per_m"),
    ({"vehicle": []}, "design.vehicle"),
])
def test_bad_design_block_names_the_key(design, key):
    with pytest.raises(ContractError, match=key):
        twin_config(design)
