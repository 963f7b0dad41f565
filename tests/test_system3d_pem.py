"""system3d PEM: rigid approach vs |H|^2 S, mirror symmetry under elevation, PEM vs Monte Carlo."""
from __future__ import annotations

import numpy as np
import pytest

from maglev_ros.system3d.irregularity import PROCESSES
from maglev_ros.system3d.pem import FrequencyGrid, PseudoExcitation3D, monte_carlo
from maglev_ros.system3d.solve_coupled import CoupledSolver, ResponsePoint
from maglev_ros.system3d.solve_girder import girder_dynamics
from maglev_ros.system3d.train import Train
from system3d_cases import (SPEED_MPS, paper_irregularity, paper_state_space, reduced_paper_solver, small_girder,
                            small_vehicle_state_space)

HALF_GAUGE_M = 1.0


@pytest.fixture(scope="module")
def paper_ss():
    return paper_state_space()


@pytest.fixture(scope="module")
def irr():
    return paper_irregularity()


def _rails_of_process(k: int, side: str) -> tuple[float, float]:
    """(vertical, lateral) rail motion per unit of process k on one side, written out:
    z = e +- b theta, y = a +- g/2 (left +, right -)."""
    s = 1.0 if side == "left" else -1.0
    return [(1.0, 0.0), (s * HALF_GAUGE_M, 0.0), (0.0, 1.0), (0.0, s * 0.5)][k]


def _stationary_psd(ss, irr, outputs, omega_rad_per_m, magnet_x_m):
    """sum_k |H(Omega v) w_k|^2 S_k(Omega): w_k the rail input of process k with the phase
    e^{i Omega x_r} at each magnet and the rates i Omega v."""
    v = SPEED_MPS
    rows = [ss.output_names.index(n) for n in outputs]
    out = np.zeros((len(rows), omega_rad_per_m.size))
    for j, om in enumerate(omega_rad_per_m):
        H = ss.frequency_response(om * v)[rows]
        S = [irr.psds[p](om) for p in PROCESSES]
        ph = np.exp(1j * om * magnet_x_m)
        for k in range(4):
            zy = np.array([_rails_of_process(k, mg.side) for mg in ss.vehicle.data.magnets])
            w = np.concatenate([zy[:, 0] * ph, zy[:, 1] * ph, 1j * om * v * zy[:, 0] * ph, 1j * om * v * zy[:, 1] * ph])
            out[:, j] += np.abs(H @ w) ** 2 * S[k]
    return out


@pytest.mark.parametrize("start", ["steady", "rest"])
def test_rigid_approach_pem_is_the_stationary_psd(paper_ss, irr, start):
    """No girder: the PEM's PSD of vertical and lateral outputs is |H|^2 S within 1.5 %; from rest
    the vertical ones after the transients have decayed (8 s)."""
    outs = (ResponsePoint("cabin_z", car=1, body="cabin", direction="z"),
            ResponsePoint("bogie_z", car=1, body="bogie_l3", direction="z"),
            ResponsePoint("current", car=1, quantity="current", loop="l3_front"),
            ResponsePoint("cabin_y", car=1, body="cabin", direction="y"),
            ResponsePoint("bogie_y", car=1, body="bogie_l3", direction="y"))
    names = ("acc:cabin.z", "acc:bogie_l3.z", "current:l3_front", "acc:cabin.y", "acc:bogie_l3.y")
    train = Train(1, 16.1, SPEED_MPS, 3.0, paper_ss.magnet_x_m)
    sol = CoupledSolver(paper_ss, train, 0.01, outputs=outs)
    grid = FrequencyGrid.build(0.314, 6.28, 6, "log", "midpoint")
    n = 20 if start == "steady" else 800
    res = PseudoExcitation3D(sol, irr, grid, start=start).run(n)
    ref = _stationary_psd(paper_ss, irr, names, grid.centre_rad_per_m, train.magnet_positions_m(0.0)[0])
    check = range(5) if start == "steady" else range(3)
    for i in check:
        np.testing.assert_allclose(res.psd[i, -1], ref[i], rtol=0.015)
    assert np.all(np.abs(res.mean) < 1e-12 * np.abs(ref).max())       # no girder: no mean response


@pytest.mark.parametrize("basis", ["dense", "eigen"])
def test_symmetric_vehicle_under_elevation_has_no_lateral_roll_yaw(paper_ss, irr, basis):
    """Elevation only (PEM) and the static loads (mean) on the girder: lateral, roll and yaw
    outputs (|mean| and SD) <= 1e-12 of the vertical response (the largest RMS of the vertical
    accelerations; roll: z of a left minus a right cabin point; yaw: y of a nose point; roll +
    lateral: y of a roof point; a mirror pair of bogies: the sum of their y). Seen with both
    vehicle bases: <= 5e-13 (rounding of left/right terms that cancel)."""
    outs = (ResponsePoint("z_left", car=1, body="cabin", direction="z", point_m=(0.0, 1.4, 1.6)),
            ResponsePoint("z_right", car=1, body="cabin", direction="z", point_m=(0.0, -1.4, 1.6)),
            ResponsePoint("y_centre", car=1, body="cabin", direction="y"),
            ResponsePoint("y_roof", car=1, body="cabin", direction="y", point_m=(0.0, 0.0, 3.1)),
            ResponsePoint("y_nose", car=1, body="cabin", direction="y", point_m=(7.5, 0.0, 1.6)),
            ResponsePoint("girder_y", girder_x_m=35.0, direction="y"),
            ResponsePoint("girder_z", girder_x_m=35.0, direction="z"),
            ResponsePoint("bogie_l_y", car=1, body="bogie_l2", direction="y"),
            ResponsePoint("bogie_r_y", car=1, body="bogie_r2", direction="y"),
            ResponsePoint("bogie_z", car=1, body="bogie_l2", direction="z"))
    sol = reduced_paper_solver(paper_ss, "monolithic", outputs=outs, vehicle_basis=basis)
    grid = FrequencyGrid.build(0.314, 6.28, 5, "log")
    res = PseudoExcitation3D(sol, irr, grid, processes=("elevation",), start="rest").run(250)
    vertical = res.rms[[0, 6, 9]].max()
    assert vertical > 0.1
    for stat in (res.mean, res.sd):
        assert np.abs(stat[0] - stat[1]).max() <= 1e-12 * vertical
        assert np.abs(stat[2:6]).max() <= 1e-12 * vertical
    assert np.abs(res.mean[7] + res.mean[8]).max() <= 1e-12 * vertical     # mirror pair: opposite y
    # while each bogie moves (a scenario value, not the symmetry bound: 3.5e-4 with the soft
    # lateral air springs, 1e-3 with the former stiff tables; the pair cancels to <= 1e-12 above)
    assert res.sd[7].max() > 1e-4 * vertical


def _spectral_samples(irr, grid, x_m, n_samples, rng):
    """Random-phase samples of the four processes on the PEM's bins (spectral representation:
    r(x) = sum_j sqrt(2 W_j) cos(Omega_j x + phi_j)), mapped to the rails by hand."""
    W = np.stack([irr.psds[p].band_variance(grid.edges_rad_per_m[:-1], grid.edges_rad_per_m[1:]) for p in PROCESSES], 1)
    procs = []
    for k in range(4):
        phi = rng.uniform(0, 2 * np.pi, size=(n_samples, grid.n, 1))
        procs.append(np.einsum("j,sjx->sx", np.sqrt(2 * W[:, k]),
                               np.cos(grid.centre_rad_per_m[None, :, None] * x_m[None, None, :] + phi)))
    e, c, a, g = procs
    b = HALF_GAUGE_M
    return {"z_left": e + b * c, "z_right": e - b * c, "y_left": a + g / 2, "y_right": a - g / 2}


def _pem_vs_mc(ss, irr, outs, train, dyn, rails, dt, duration_s, grid, n_samples, batch, seed):
    sol = CoupledSolver(ss, train, dt, dyn, rails, coupling="monolithic", outputs=outs)
    n = int(round(duration_s / dt))
    pem = PseudoExcitation3D(sol, irr, grid, start="rest").run(n)
    x = np.arange(train.magnet_positions_m(0.0).min() - 1.0, train.magnet_positions_m(n * dt).max() + 1.0, 0.05)
    rng = np.random.default_rng(seed)
    s1 = s2 = 0.0
    for b0 in range(0, n_samples, batch):
        nb = min(batch, n_samples - b0)
        mc = monte_carlo(sol, n, x, _spectral_samples(irr, grid, x, nb, rng), batch=nb)
        s1 = s1 + mc.mean * nb
        s2 = s2 + mc.variance * (nb - 1) + nb * mc.mean ** 2
    mean = s1 / n_samples
    var = (s2 - n_samples * mean ** 2) / (n_samples - 1)
    return pem, var, n


def test_pem_matches_monte_carlo_small_vehicle(irr):
    """A one-body 3D vehicle over the small girder, all four processes, 1000 samples in batches of
    250 (PEM and Monte Carlo from rest, same bins): the variance averaged over the run within 3 %,
    the SD at every step within 12 % (the estimator's spread is 1/sqrt(2 N) = 2.2 % per step)."""
    ss = small_vehicle_state_space()
    girder, rails = small_girder()
    dyn = girder_dynamics(girder, "modal", 12.0)
    train = Train(1, 4.0, SPEED_MPS, -3.0, ss.magnet_x_m)
    outs = (ResponsePoint("z", car=1, body="car", direction="z"), ResponsePoint("y", car=1, body="car", direction="y"),
            ResponsePoint("y_roof", car=1, body="car", direction="y", point_m=(1.5, 0.0, 1.5)),
            ResponsePoint("current", car=1, quantity="current", loop="L0"),
            ResponsePoint("girder_z", girder_x_m=35.0, direction="z"), ResponsePoint("girder_y", girder_x_m=35.0, direction="y"))
    grid = FrequencyGrid.build(0.314, 3.14, 16, "log", "bin")
    pem, var, n = _pem_vs_mc(ss, irr, outs, train, dyn, rails, 0.005, 2.8, grid, 1000, 250, 7)
    k0 = 60                                                          # after 0.3 s
    for i in range(len(outs)):
        assert var[i, k0:].mean() == pytest.approx(pem.variance[i, k0:].mean(), rel=0.03), outs[i].name
        ratio = np.sqrt(var[i, k0:] / pem.variance[i, k0:])
        assert np.all(np.abs(ratio - 1) < 0.12), outs[i].name


@pytest.mark.slow
def test_pem_matches_monte_carlo_reduced_paper_scenario(paper_ss, irr):
    """Paper 001's vehicle (1 car) over the small girder, 600 samples: as the small-vehicle test."""
    sol = reduced_paper_solver(paper_ss, "monolithic", time_step_s=0.005)
    pem, var, n = _pem_vs_mc(paper_ss, irr, sol.outputs, sol.train, sol.dynamics, sol.rails, 0.005, 3.0,
                             FrequencyGrid.build(0.314, 3.14, 12, "log", "bin"), 600, 200, 11)
    k0 = 60
    for i in range(len(sol.outputs)):
        assert var[i, k0:].mean() == pytest.approx(pem.variance[i, k0:].mean(), rel=0.03), sol.outputs[i].name
