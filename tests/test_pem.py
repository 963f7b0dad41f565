"""Pseudo-excitation method: against independent references.

(a) time-invariant quarter car on a rigid base: evolutionary PSD / variance after transients
    vs the classic stationary result |H(v Omega)|^2 S(Omega) (frequency-domain formula,
    scipy quadrature); static mean vs K^-1 f.
(b) PD-controlled magnets + car body crossing a simply supported modal beam (time-varying):
    quasi-static mean vs the beam influence-line formula F a (3L^2 - 4a^2) / 48 EI; stationary
    multi-magnet (time-lag) response on the rigid approach vs frequency-domain quadrature;
    PEM vs Monte Carlo (600 sampled profiles through the same integrator).
"""

import numpy as np
import pytest
from scipy import integrate

from maglev_ros.errors import UserError
from maglev_ros.twin import irregularity_psd as ip
from maglev_ros.twin.pem import (
    LinearMovingSystem,
    MonteCarlo,
    OutputMatrices,
    PseudoExcitation,
    SystemMatrices,
    linearised_magnet_gains,
    vehicle_on_modal_beam,
)


# ---------------------------------------------------------------- (a) quarter car
def quarter_car(speed_mps, body_force_n=0.0):
    """Magnet (PD levitation to a rigid rail) + car body on an air spring. DOFs [z_m, z_b].
    Body mode ~1 Hz with 40 % damping so start-up transients die out within the 5 s run."""
    m1, m2, ks, cs = 1500.0, 5000.0, 2.0e5, 2.5e4
    g = linearised_magnet_gains(63.8e3, 25.0, 0.010, 7000.0, 40.0, 0.1)
    ke, ce, ma = g.k_gap_n_per_m, g.c_gap_n_s_per_m, g.added_mass_kg
    M = np.diag([m1 + ma, m2])
    C = np.array([[ce + cs, -cs], [-cs, cs]])
    K = np.array([[ke + ks, -ks], [-ks, ks]])
    Br = np.array([[ke], [0.0]])
    Brd = np.array([[ce], [0.0]])
    f = np.array([0.0, body_force_n])
    mats = SystemMatrices(M, C, K, Br, Brd, f)
    Cu = np.array([[0, 0], [0, 0], [-1.0, 0], [0, 1.0]])
    Cv = np.zeros((4, 2))
    Ca = np.array([[0, 1.0], [1.0, 0], [0, 0], [0, 0]])
    Dr = np.array([[0.0], [0.0], [1.0], [0.0]])
    outs = OutputMatrices(Cu, Cv, Ca, Dr, None)
    sysm = LinearMovingSystem(
        n_dof=2, input_offsets_m=[0.0], speed_mps=speed_mps, start_m=0.0,
        matrices_at=lambda t, x: mats, outputs_at=lambda t, x: outs,
        output_names=("body_accel", "magnet_accel", "gap", "body_disp"), time_invariant=True,
    )
    return sysm, mats, outs


def freq_response(mats, outs, omega_rad_s, phases=None):
    """Classic stationary transfer y/r at temporal frequency omega (rad/s); phases e^{i Omega d_k}."""
    w = omega_rad_s
    n_in = mats.input_r.shape[1]
    ph = np.ones(n_in) if phases is None else phases
    A = -w**2 * mats.mass + 1j * w * mats.damping + mats.stiffness
    b = (mats.input_r + 1j * w * mats.input_r_rate) @ ph
    q = np.linalg.solve(A, b)
    y = (outs.disp + 1j * w * outs.vel - w**2 * outs.acc) @ q
    if outs.r_gain is not None:
        y = y + outs.r_gain @ ph
    if outs.r_rate_gain is not None:
        y = y + 1j * w * (outs.r_rate_gain @ ph)
    return y


@pytest.mark.parametrize(
    "psd_name,speed,band_m,dt",
    [("maglev_001", 20.0, (0.5, 80.0), 6.25e-4), ("german_high", 60.0, (1.0, 50.0), 4e-4)],
)
def test_time_invariant_pem_equals_stationary_transfer(psd_name, speed, band_m, dt):
    psd = ip.psd_by_name(psd_name)
    sysm, mats, outs = quarter_car(speed, body_force_n=1000.0)
    pem = PseudoExcitation(psd, band_m, n_freq=160, time_step_s=dt, psd_stride=int(round(0.5 / dt)))
    res = pem.run(sysm, 5.0)
    om = res.omega_rad_per_m
    H = np.array([freq_response(mats, outs, speed * o) for o in om])  # (n_f, n_out)
    ref_psd = np.abs(H) ** 2 * psd(om)[:, None]  # unit^2 / (rad/m)
    last = res.psd[-1].T  # (n_f, n_out)
    assert res.psd_time_s[-1] == pytest.approx(5.0)
    for k in range(3):  # accelerations and gap (body_disp has a ~1/Omega^2 pole-free low end too)
        np.testing.assert_allclose(last[:, k], ref_psd[:, k], rtol=0.015, atol=1e-6 * ref_psd[:, k].max())
    lo, hi = ip.band_from_wavelengths(*band_m)
    for k, name in enumerate(res.output_names):
        var_ref, _ = integrate.quad(lambda o: float(np.abs(freq_response(mats, outs, speed * o)[k]) ** 2 * psd(o)),
                                    lo, hi, limit=400, epsrel=1e-8)
        assert res.variance[-1, k] == pytest.approx(var_ref, rel=0.01), name
    # temporal PSD conversion: integral over omega [rad/s] gives the same variance
    w, s_t = res.temporal_psd()
    assert np.sum(s_t[-1, 0] * res.bin_width_rad_per_m * speed) == pytest.approx(res.variance[-1, 0], rel=1e-9)
    # deterministic part: constant body force -> static offset K^-1 f after transients
    static = np.linalg.solve(mats.stiffness, mats.force_det)
    assert res.mean[-1, 3] == pytest.approx(static[1], rel=1e-4)
    assert abs(res.mean[-1, 0]) < 1e-6
    assert np.allclose(res.rms, np.sqrt(res.mean**2 + res.variance))
    assert np.allclose(res.upper_3sigma - res.lower_3sigma, 6 * res.sd)


def test_frequency_by_frequency_equals_batched():
    psd = ip.maglev_guideway_001()
    for sysm, dur in ((quarter_car(25.0, 500.0)[0], 0.3), (vehicle_on_modal_beam(n_modes=2, start_m=5.0), 0.3)):
        kw = dict(n_freq=6, time_step_s=1e-3, psd_stride=1)
        a = PseudoExcitation(psd, (1.0, 20.0), **kw).run(sysm, dur)
        b = PseudoExcitation(psd, (1.0, 20.0), freq_batch=1, **kw).run(sysm, dur)
        assert a.n_integrations == 1 and b.n_integrations == 6
        np.testing.assert_allclose(b.variance, a.variance, rtol=1e-6, atol=1e-9 * a.variance.max())
        np.testing.assert_allclose(b.mean, a.mean, rtol=1e-6, atol=1e-9 * np.abs(a.mean).max())
        np.testing.assert_allclose(b.psd, a.psd, rtol=1e-6, atol=1e-9 * a.psd.max())


# ---------------------------------------------------------------- (b) moving vehicle on a beam
def _ss_midspan_influence(a, L, EI):
    """Midspan deflection of a simply supported beam per unit point load at a (downward)."""
    a = np.where(a > L / 2, L - a, a)
    inside = (a >= 0) & (a <= L / 2)
    return np.where(inside, a * (3 * L**2 - 4 * a**2) / (48 * EI), 0.0)


def test_quasi_static_mean_follows_influence_line():
    L, EI, mbar = 24.768, 2.0e10, 3750.0
    mb, mm, offs = 20000.0, 1500.0, np.array([0.0, -2.58, -5.16, -7.74])
    v = 1.5
    sysm = vehicle_on_modal_beam(speed_mps=v, start_m=-0.5, span_m=L, n_modes=9, mass_per_length_kg_m=mbar,
                                 bending_stiffness_n_m2=EI, car_body_mass_kg=mb, magnet_mass_kg=mm,
                                 magnet_offsets_m=offs)
    res = PseudoExcitation(ip.maglev_guideway_001(), n_freq=1, time_step_s=4e-3).run(sysm, (L + 8.5) / v)
    F0 = (mb / 4 + mm) * 9.81
    x_ref = sysm.position_m(res.time_s)
    ref = -F0 * sum(_ss_midspan_influence(x_ref + d, L, EI) for d in offs)
    k = res.output_index("midspan_disp")
    peak = np.abs(ref).max()
    assert np.abs(res.mean[:, k] - ref).max() < 0.03 * peak
    assert res.mean[:, k].min() == pytest.approx(ref.min(), rel=0.02)


def test_multi_magnet_time_lag_on_rigid_approach_matches_stationary_quadrature():
    speed = 30.0
    sysm = vehicle_on_modal_beam(speed_mps=speed, start_m=-215.0, n_modes=2)
    psd = ip.german_high_speed("low")
    band_m = (1.0, 20.0)
    res = PseudoExcitation(psd, band_m, n_freq=300, time_step_s=1e-3).run(sysm, 6.0)
    x_end = sysm.position_m(6.0)
    assert x_end + sysm.input_offsets_m.max() < 0  # still on the rigid approach
    mats = sysm.matrices_at(6.0, x_end)
    outs = sysm.outputs_at(6.0, x_end)
    lo, hi = ip.band_from_wavelengths(*band_m)
    offs = sysm.input_offsets_m
    for name in ("car_body_accel", "gap1"):
        k = res.output_index(name)

        def integrand(o):
            return float(np.abs(freq_response(mats, outs, speed * o, np.exp(1j * o * offs))[k]) ** 2 * psd(o))

        var_ref, _ = integrate.quad(integrand, lo, hi, limit=1000, epsrel=1e-7)
        assert res.variance[-1, k] == pytest.approx(var_ref, rel=0.02), name
    # the lag matters: all magnets in phase would give a clearly different body response
    k = res.output_index("car_body_accel")
    var_inphase, _ = integrate.quad(lambda o: float(np.abs(freq_response(mats, outs, speed * o, np.ones(4))[k]) ** 2
                                                    * psd(o)), lo, hi, limit=1000)
    assert abs(var_inphase / res.variance[-1, k] - 1) > 0.1


@pytest.mark.parametrize("seed", [7, 8])
def test_pem_matches_monte_carlo_on_beam_crossing(seed):
    n_samples = 600
    speed = 30.0
    sysm = vehicle_on_modal_beam(speed_mps=speed, start_m=-30.0, n_modes=3)
    psd = ip.maglev_guideway_001()
    band_m = (1.0, 20.0)
    dur = (30.0 + 24.768 + 10.0) / speed
    pem = PseudoExcitation(psd, band_m, n_freq=200, time_step_s=1e-3).run(sysm, dur)
    x, r = ip.random_profile(psd, 110.0, 0.02, band_m, np.random.default_rng(seed), n_samples=n_samples,
                             start_m=-40.0)
    mc = MonteCarlo(time_step_s=1e-3, keep_histories=n_samples).run(sysm, x, r, dur)
    assert mc.n_samples == n_samples
    for name in ("car_body_accel", "midspan_accel"):
        k = pem.output_index(name)
        w = pem.sd[:, k] > 0.2 * pem.sd[:, k].max()
        assert w.sum() > 500
        rms_ratio = np.sqrt(np.mean(mc.rms[w, k] ** 2) / np.mean(pem.rms[w, k] ** 2))
        sd_ratio = np.sqrt(np.mean(mc.sd[w, k] ** 2) / np.mean(pem.sd[w, k] ** 2))
        assert abs(rms_ratio - 1) < 0.03, (name, rms_ratio)
        assert abs(sd_ratio - 1) < 0.03, (name, sd_ratio)
        # pointwise: sampling error of an SD estimate is ~ 1/sqrt(2N)
        assert np.abs(mc.sd[w, k] / pem.sd[w, k] - 1).max() < 5 / np.sqrt(2 * n_samples)
        # mean: sampling error sd/sqrt(N)
        assert np.abs(mc.mean[:, k] - pem.mean[:, k]).max() < 5 * pem.sd[:, k].max() / np.sqrt(n_samples)
        # 3-sigma rule: sampled histories stay inside mean +- 3 SD (Gaussian: 99.73 %)
        h = mc.histories[:, w, k]
        inside3 = np.mean(np.abs(h - pem.mean[w, k]) <= 3 * pem.sd[w, k])
        inside1 = np.mean(np.abs(h - pem.mean[w, k]) <= pem.sd[w, k])
        assert inside3 > 0.99 and abs(inside1 - 0.683) < 0.03
    # run-averaged RMS against the Monte Carlo estimate's own standard error
    mc_rms, mc_se = mc.time_rms_and_se()
    pem_rms = pem.time_rms()
    for k in range(len(pem.output_names)):
        assert abs(mc_rms[k] - pem_rms[k]) < 4 * mc_se[k] + 1e-3 * pem_rms[k], pem.output_names[k]
    # the vehicle's weight gives a real moving-load mean at midspan, zero before arrival
    k = pem.output_index("midspan_disp")
    assert pem.mean[:, k].min() < -1e-3 and pem.mean[0, k] == 0.0


def test_monte_carlo_batches_equal_and_bad_inputs():
    sysm = vehicle_on_modal_beam(n_modes=2, start_m=3.0)
    psd = ip.maglev_guideway_001()
    x, r = ip.random_profile(psd, 40.0, 0.02, (1.0, 20.0), 3, n_samples=3, start_m=-10.0)
    a = MonteCarlo(1e-3).run(sysm, x, r, 0.4)
    b = MonteCarlo(1e-3, sample_batch=1).run(sysm, x, r, 0.4)
    # batched (explicit inverse per step) and one-by-one (LAPACK getrs) agree to round-off
    np.testing.assert_allclose(a.sd, b.sd, rtol=1e-6, atol=1e-9 * a.sd.max())
    np.testing.assert_allclose(a.histories, b.histories, rtol=1e-6, atol=1e-9 * np.abs(a.histories).max())
    with pytest.raises(UserError, match="cover"):
        MonteCarlo(1e-3).run(sysm, x, r, 5.0)
    with pytest.raises(UserError):
        MonteCarlo(1e-3).run(sysm, x, r[:, :-1], 0.1)
    with pytest.raises(UserError):
        PseudoExcitation(psd, (20.0, 1.0))
    with pytest.raises(UserError):
        PseudoExcitation(psd, time_step_s=0.0)
    bad = LinearMovingSystem(
        n_dof=2, input_offsets_m=[0.0], speed_mps=10.0, start_m=0.0,
        matrices_at=lambda t, x: SystemMatrices(np.eye(2), np.eye(2), np.eye(2), np.ones((2, 2)), np.ones((2, 1)),
                                                np.zeros(2)),
        outputs_at=lambda t, x: OutputMatrices(np.eye(2), np.eye(2), np.eye(2)),
        output_names=("a", "b"), time_invariant=True,
    )
    with pytest.raises(UserError, match="input_r"):
        PseudoExcitation(psd, n_freq=2).run(bad, 0.01)
    with pytest.raises(UserError, match="kp_a_per_m"):
        linearised_magnet_gains(6e4, 25.0, 0.01, 1000.0, 40.0, 0.1)
    d = PseudoExcitation(psd, n_freq=3, time_step_s=1e-3).run(sysm, 0.01).to_dict()
    assert d["method"] == "pseudo-excitation" and len(d["time_s"]) == 11


# ---------------------------------------------------------------- adapter to the twin's model
def _twin_system(n_spans, speed, **kw):
    design = pytest.importorskip("maglev_ros.twin.design")
    pytest.importorskip("maglev_ros.twin.levitation")
    from maglev_ros.twin.pem import coupled_twin_system

    cfg = design.twin_config()
    return cfg, design.default_line(cfg, n_spans), coupled_twin_system(cfg, design.default_line(cfg, n_spans),
                                                                       speed_mps=speed, **kw)


def test_twin_adapter_quasi_static_mean_matches_fe_static_solution():
    from maglev_ros.twin.guideway import Guideway
    from maglev_ros.twin.levitation import build_vehicle

    speed = 2.0
    cfg, line, sysm = _twin_system(2, speed)
    span = line[1]
    xs = 0.5 * (span.start_m + span.end_m)
    dur = (span.end_m - sysm.start_m + 20.0) / speed
    res = PseudoExcitation(ip.maglev_guideway_001(), n_freq=1, time_step_s=5e-3).run(sysm, dur)
    f0 = build_vehicle(cfg).levitation.static_force_n
    gw = Guideway(line, cfg.numerics.n_elements_per_span)
    x_ref = sysm.position_m(res.time_s[::20])
    ref = np.array([gw.static_displacement(xr + sysm.input_offsets_m, -f0, [xs])[0] for xr in x_ref])
    got = res.mean[::20, res.output_index(f"guideway_disp@{xs:g}")]
    peak = np.abs(ref).max()
    assert peak > 1e-4
    # modal truncation (modes < 300 Hz) and slow-speed dynamics: a few % of the peak
    assert np.abs(got - ref).max() < 0.04 * peak
    assert got.min() == pytest.approx(ref.min(), rel=0.03)


def test_twin_adapter_pem_matches_monte_carlo():
    speed, n_samples = 30.0, 500
    cfg, line, sysm = _twin_system(2, speed)
    psd = ip.maglev_guideway_001()
    band_m = (1.0, 20.0)
    dur = (line[-1].end_m - sysm.start_m + 5.0) / speed
    pem = PseudoExcitation(psd, band_m, n_freq=160, time_step_s=1e-3).run(sysm, dur)
    x, r = ip.random_profile(psd, 110.0, 0.02, band_m, np.random.default_rng(21), n_samples=n_samples,
                             start_m=sysm.start_m + sysm.input_offsets_m.min() - 1.0)
    mc = MonteCarlo(time_step_s=1e-3).run(sysm, x, r, dur)
    xs = 0.5 * (line[1].start_m + line[1].end_m)
    for name in ("car_body_accel", f"guideway_accel@{xs:g}", "gap1"):
        k = pem.output_index(name)
        w = pem.sd[:, k] > 0.2 * pem.sd[:, k].max()
        rms_ratio = np.sqrt(np.mean(mc.rms[w, k] ** 2) / np.mean(pem.rms[w, k] ** 2))
        sd_ratio = np.sqrt(np.mean(mc.sd[w, k] ** 2) / np.mean(pem.sd[w, k] ** 2))
        assert abs(rms_ratio - 1) < 0.03 and abs(sd_ratio - 1) < 0.03, (name, rms_ratio, sd_ratio)


def test_twin_adapter_structure_matches_levitation_closed_loop_and_is_reciprocal():
    from maglev_ros.twin.levitation import build_vehicle

    cfg, line, sysm = _twin_system(2, 1e-9)
    veh = build_vehicle(cfg)
    nv = veh.model.n_dof
    # off the guideway: vehicle block == the levitation module's closed loop on a rigid rail
    off = sysm.matrices_at(0.0, line[0].start_m - 100.0)
    A = veh.state_space.A
    np.testing.assert_allclose(-np.linalg.solve(off.mass[:nv, :nv], off.stiffness[:nv, :nv]), A[nv:2 * nv, :nv],
                               rtol=1e-9, atol=1e-9 * np.abs(A).max())
    np.testing.assert_allclose(-np.linalg.solve(off.mass[:nv, :nv], off.damping[:nv, :nv]),
                               A[nv:2 * nv, nv:2 * nv], rtol=1e-9, atol=1e-9 * np.abs(A).max())
    assert not off.stiffness[:nv, nv:].any() and not off.force_det.any()
    # on the guideway at ~zero speed: gap stiffness and damping couple reciprocally (symmetric K, C)
    on = sysm.matrices_at(0.0, line[0].start_m + 15.0)
    assert np.abs(on.stiffness[:nv, nv:]).max() > 0
    np.testing.assert_allclose(on.stiffness, on.stiffness.T, rtol=1e-9, atol=1e-9 * np.abs(on.stiffness).max())
    np.testing.assert_allclose(on.damping, on.damping.T, rtol=1e-9, atol=1e-9 * np.abs(on.damping).max())
    # the guideway carries the vehicle's weight: sum of magnet loads = total weight (mode-free check)
    f0 = veh.levitation.static_force_n
    assert f0.sum() == pytest.approx(veh.model.total_mass_kg * cfg.vehicle.gravity_mps2, rel=1e-9)
