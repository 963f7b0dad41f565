"""system3d solvers: precise integration, Newmark girder, separated iteration vs monolithic, train timing."""
from __future__ import annotations

import numpy as np
import pytest
import scipy.integrate
import scipy.signal

from maglev_ros.errors import UserError
from maglev_ros.system3d.girder import GirderSpec, assemble_girder
from maglev_ros.system3d.girder_rails import RailInterpolation, RailLayout
from maglev_ros.system3d.pem import FrequencyGrid, pseudo_inputs
from maglev_ros.system3d.scenario import build, load_scenario
from maglev_ros.system3d.solve_coupled import CoupledSolver, ResponsePoint
from maglev_ros.system3d.solve_girder import girder_dynamics
from maglev_ros.system3d.solve_vehicle import discretise
from maglev_ros.system3d.train import Train
from system3d_cases import (PAPER_OUTPUTS, SPEED_MPS, paper_irregularity, paper_state_space, reduced_paper_solver,
                            small_vehicle_state_space)


@pytest.fixture(scope="module")
def paper_ss():
    return paper_state_space()


def _stable_system(n=6, m=2, seed=3):
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(n, n))
    A -= (np.max(np.linalg.eigvals(A).real) + 1.0) * np.eye(n)
    return A, rng.normal(size=(n, m))


@pytest.mark.parametrize("hold", ["linear", "zero"])
def test_precise_integration_matches_lsim(hold):
    """x_{n+1} = Phi x_n + G0 w_n + G1 w_{n+1} against scipy.signal.lsim (input linear between
    samples, or held with interp=False)."""
    A, B = _stable_system()
    h, n = 0.05, 60
    t = np.arange(n + 1) * h
    w = np.stack([np.sin(3 * t), np.cos(1.3 * t) + t], axis=1)
    st = discretise(A, B, h, hold)
    x = np.zeros((A.shape[0], n + 1))
    for k in range(n):
        x[:, k + 1] = st.transition @ x[:, k] + st.input_now @ w[k] + st.input_next @ w[k + 1]
    sys_ = (A, B, np.eye(A.shape[0]), np.zeros(B.shape))
    _, _, ref = scipy.signal.lsim(sys_, w, t, interp=hold == "linear")
    np.testing.assert_allclose(x.T, ref, atol=1e-9 * np.abs(ref).max())


def test_harmonic_input_is_exact():
    """The harmonic step increment against an ODE solve of x' = A x + B w e^{i w t}."""
    A, B = _stable_system()
    h, om = 0.1, 7.0
    w_hat = np.array([[1.0 + 0.5j], [-0.3j]])
    st = discretise(A, B, h)
    x0 = np.array([0.2, -0.1, 0.0, 0.3, 0.1, -0.2], complex)
    t0 = 0.37
    sol = scipy.integrate.solve_ivp(lambda tt, xx: A @ xx + (B @ w_hat)[:, 0] * np.exp(1j * om * tt),
                                    (t0, t0 + h), x0, rtol=1e-12, atol=1e-14)
    ours = st.transition @ x0 + np.exp(1j * om * t0) * st.harmonic_input([om], w_hat)[:, 0]
    np.testing.assert_allclose(ours, sol.y[:, -1], atol=1e-10)
    X = st.steady_state([om], w_hat)[:, 0]                  # X e^{iwt} is a solution
    np.testing.assert_allclose((1j * om * np.eye(6) - A) @ X, (B @ w_hat)[:, 0], atol=1e-12)


def _single_span(length_m=30.0, elements=10):
    spec = GirderSpec.from_dict({
        "name": "ss", "spans_m": [length_m], "elements_per_span": elements,
        "section": {"axial_rigidity_n": 2e11, "vertical_bending_rigidity_n_m2": 4e10,
                    "lateral_bending_rigidity_n_m2": 1e11, "torsional_rigidity_n_m2": 5e10,
                    "mass_per_length_kg_m": 8000.0, "polar_mass_kg_m": 9000.0},
        "supports": [{"at_support": 0, "restrained": ["x", "y", "z", "rx"]}, {"at_support": 1, "restrained": ["y", "z", "rx"]}],
        "damping": {"kind": "rayleigh", "ratio": 0.05, "frequencies_hz": [3.0, 20.0]}})
    g = assemble_girder(spec)
    return g, RailInterpolation(g, RailLayout(1.0, 1.0))


@pytest.mark.parametrize("model", ["full", "modal"])
def test_slow_crossing_follows_the_static_influence_line(model):
    """At 2 m/s the midspan deflection of a simply supported span is the static one of the
    vehicle's magnet forces: sum_k F_k a b_k (L^2 - a^2 - b_k^2)/(6 E I L) (point loads, midspan
    x = a = L/2, b_k = L - x_k for loads right of midspan, mirrored left)."""
    ss = small_vehicle_state_space()
    g, rails = _single_span()
    L, EI = 30.0, 4e10
    dyn = girder_dynamics(g, model, 40.0)
    v = 2.0
    train = Train(1, 4.0, v, -2.5, ss.magnet_x_m)
    out = (ResponsePoint("mid", girder_x_m=15.0, quantity="displacement", direction="z"),)
    sol = CoupledSolver(ss, train, 0.02, dyn, rails, coupling="monolithic", outputs=out)
    ys = []
    n = int((L + 5.0) / v / 0.02)
    rec = sol.run(n, record=lambda k, t, y: ys.append(y[0, 0]))
    F0 = ss.static.magnet_force_n

    def influence(xk):           # deflection at midspan (down positive) of a unit load at xk
        b = np.where(xk <= L / 2, xk, L - xk)
        return np.where((xk > 0) & (xk < L), b * (3 * L ** 2 - 4 * b ** 2) / (48 * EI), 0.0)
    ref = np.array([-np.sum(F0 * influence(train.magnet_positions_m(t)[0])) for t in rec.time_s])
    peak = np.abs(ref).max()
    assert peak > 1e-4                                           # ~0.3 mm: a real load
    assert np.abs(np.array(ys) - ref).max() < 0.01 * peak      # dynamics and modal truncation within 1 %


def test_separated_iteration_agrees_with_monolithic(paper_ss):
    """Mean run and PEM columns (all four processes): every output within 1e-6 of its peak."""
    irr = paper_irregularity()
    grid = FrequencyGrid.build(0.314, 6.28, 4, "log")
    res = {}
    for coupling in ("separated", "monolithic"):
        sol = reduced_paper_solver(paper_ss, coupling)
        mean, pem = [], []
        n = 330                                   # the car crosses the 70 m girder and leaves it
        rec = sol.run(n, record=lambda k, t, y: mean.append(y[:, 0]))
        h = pseudo_inputs(sol, irr, grid)
        sol.run(n, harmonic=h, static_load=False, record=lambda k, t, y: pem.append(y))
        res[coupling] = (np.array(mean), np.array(pem), rec)
    (m_s, p_s, rec_s), (m_m, p_m, _) = res["separated"], res["monolithic"]
    it = rec_s.iterations[1:]
    assert it.max() > 1 and it.min() >= 1            # iterations reported per step; coupled steps iterate
    vertical = [i for i, o in enumerate(PAPER_OUTPUTS) if o.direction == "z" or o.quantity == "current"]
    for i in vertical:
        assert np.abs(m_s[:, i] - m_m[:, i]).max() <= 1e-6 * np.abs(m_m[:, i]).max()
    for i in range(len(PAPER_OUTPUTS)):
        assert np.abs(p_s[:, i] - p_m[:, i]).max() <= 1e-6 * np.abs(p_m[:, i]).max()


def test_paper001_second_car_on_the_girder_from_2_39_to_13_05_s():
    """The scenario's speed, car length, start and girder give paper 001's times (+-0.05 s):
    t_in = (0 - (x_front - L)) / v, t_out = (280 m - (x_front - 2 L)) / v for the second car."""
    sc = load_scenario("paper001")
    assert sc.speed_mps == pytest.approx(100 / 3.6, rel=1e-5)
    t_in = (0.0 - (sc.front_start_m - sc.car_length_m)) / sc.speed_mps
    t_out = (85 + 110 + 85 - (sc.front_start_m - 2 * sc.car_length_m)) / sc.speed_mps
    assert t_in == pytest.approx(2.39, abs=0.05) and t_out == pytest.approx(13.05, abs=0.05)
    b = build(sc.quick_variant())
    car2 = b.on_girder_s()[1]
    assert car2["enter_s"] == pytest.approx(t_in, abs=1e-9) and car2["leave_s"] == pytest.approx(t_out, abs=1e-9)
    # the girder rows under car 2's magnets are zero before it enters and after it leaves
    R, _ = b.solver.rail_rows(car2["enter_s"] - 0.01)
    assert not np.any(R[1])
    R, _ = b.solver.rail_rows(car2["leave_s"] + 0.01)
    assert not np.any(R[1])


def test_rail_rows_follow_the_moving_magnets(paper_ss):
    """The slope rows R' times v are the time derivative of the rail rows R seen by magnets moving
    at v (central difference in time), and each magnet reads the rail of its side."""
    sol = reduced_paper_solver(paper_ss, "monolithic", front_start_m=40.0, cutoff_hz=80.0)
    t, dt = 0.3, 1e-5
    R, Rs = sol.rail_rows(t)
    Rp, _ = sol.rail_rows(t + dt)
    Rm, _ = sol.rail_rows(t - dt)
    assert np.any(R) and np.any(Rs)
    np.testing.assert_allclose(SPEED_MPS * Rs, (Rp - Rm) / (2 * dt), atol=1e-6 * np.abs(SPEED_MPS * Rs).max())
    # each magnet reads its own rail: for a mirror pair at the same x, z_left - z_right = 2 b theta_x
    # and z_left + z_right = 2 w of the shear centre (rows of the section, independent of the sides)
    m = sol.n_mag
    mags = paper_ss.vehicle.data.magnets
    x = sol.train.magnet_positions_m(t)[0]
    pairs = [(i, j) for i in range(m) for j in range(m) if mags[i].side == "left" and mags[j].side == "right"
             and mags[i].point_m[0] == mags[j].point_m[0]]
    assert len(pairs) == m // 2
    basis = sol.dynamics.basis
    for i, j in pairs:
        sec = sol.rails.section_rows([x[i]])
        np.testing.assert_allclose(R[0, i] - R[0, j], 2 * 1.0 * (sec["rx"] @ basis)[0], atol=1e-12)
        np.testing.assert_allclose(R[0, i] + R[0, j], 2 * (sec["w"] @ basis)[0], atol=1e-12)
        np.testing.assert_allclose(R[0, m + i], R[0, m + j], atol=1e-12)        # lateral: same v - z_r theta


def test_errors_are_one_line(paper_ss):
    g, rails = _single_span()
    train = Train(1, 16.1, SPEED_MPS, -10.0, paper_ss.magnet_x_m)
    with pytest.raises(UserError, match="coupling"):
        CoupledSolver(paper_ss, train, 0.01, girder_dynamics(g, "full"), rails, coupling="loose")
    with pytest.raises(UserError, match="mode_cutoff_hz"):
        girder_dynamics(g, "modal", None)
    with pytest.raises(UserError, match="car_length_m"):
        Train(1, 5.0, SPEED_MPS, 0.0, paper_ss.magnet_x_m)
    with pytest.raises(UserError, match="outputs.x.body"):
        CoupledSolver(paper_ss, train, 0.01, outputs=(ResponsePoint("x", car=1, body="roof"),))
    with pytest.raises(UserError, match="hold"):
        discretise(np.eye(2), np.eye(2), 0.1, "cubic")


def test_crossing_at_speed_matches_the_moving_force_modal_solution():
    """The mean run's girder acceleration (the weight moving over the girder, 001's "mean")
    against the textbook moving-force solution of a simply supported Euler-Bernoulli beam: exact
    sine modes, w_n = (n pi / L)^2 sqrt(EI / m), q_n'' + 2 z_n w_n q_n' + w_n^2 q_n =
    (2 / (m L)) sum_k F_k sin(n pi x_k(t) / L), solved by solve_ivp; z_n from the same Rayleigh
    coefficients. At 28 m/s the speed parameter v / (2 f1 L) is 0.12 (001's is about 0.12 too).
    A light vehicle (320 kg on a 240 t span): the vehicle-girder interaction the reference leaves
    out is then ~0.5 % (seen: 4 % with 3.2 t, 1.0 % / 0.57 % with 320 kg at h = 1 / 0.5 ms)."""
    ss = small_vehicle_state_space(320.0)
    L, EI, m = 30.0, 4e10, 8000.0
    g, rails = _single_span(L, elements=20)
    dyn = girder_dynamics(g, "modal", 80.0)                          # vertical n = 1..4
    v, h = 28.0, 0.001
    train = Train(1, 4.0, v, -2.5, ss.magnet_x_m)
    out = (ResponsePoint("mid", girder_x_m=L / 2, quantity="acceleration", direction="z"),)
    sol = CoupledSolver(ss, train, h, dyn, rails, coupling="monolithic", outputs=out)
    ys = []
    n_steps = int((L + 6.0) / v / h) + 200                            # crossing plus 0.2 s of free vibration
    rec = sol.run(n_steps, record=lambda k, t, y: ys.append(y[0, 0]))
    F0 = ss.static.magnet_force_n                                     # magnet pulls the rail down: load -F0 along z
    a, b = g.rayleigh_alpha_per_s, g.rayleigh_beta_s
    modes = np.arange(1, 5)
    wn = (modes * np.pi / L) ** 2 * np.sqrt(EI / m)
    zn = a / (2 * wn) + b * wn / 2

    def rhs(t, s):
        q, qd = s[:4], s[4:]
        x = train.magnet_positions_m(t)[0]
        on = (x > 0) & (x < L)
        f = 2 / (m * L) * np.array([np.sum(-F0[on] * np.sin(k * np.pi * x[on] / L)) for k in modes])
        return np.concatenate([qd, f - 2 * zn * wn * qd - wn ** 2 * q])
    t = np.asarray(rec.time_s)
    ref_sol = scipy.integrate.solve_ivp(rhs, (t[0], t[-1]), np.zeros(8), t_eval=t, rtol=1e-9, atol=1e-14, max_step=h)
    acc = np.array([rhs(tt, s)[4:] for tt, s in zip(t, ref_sol.y.T)])   # q_n''
    ref = acc @ np.sin(modes * np.pi / 2)
    peak = np.abs(ref).max()
    assert peak > 1e-3                                                  # a real acceleration (m/s^2)
    assert np.abs(np.array(ys) - ref).max() < 0.02 * peak

