"""Twin extensions built by composition: per-end bearings, car-body bending, control lag, sensor errors."""
import math

import numpy as np
import pytest
from scipy.linalg import eigh

from maglev_ros.discrepancy.model import (ModelSpec, _free_free_shape, base_spec, body_point_row,
                                          flexible_vehicle)
from maglev_ros.twin.design import GuidewayProps, SpanSpec, twin_config, with_levitation
from maglev_ros.twin.guideway import assemble_span
from maglev_ros.twin.levitation import LevitationModel, build_vehicle, closed_loop
from maglev_ros.twin.vehicle import static_equilibrium, vehicle_from_design

L = 12.384
P = GuidewayProps(4.0e10, 2500.0, 1.5, 0.5, 3.0e10, 0.02)
SPAN = SpanSpec("S1", 0.0, L, P)


def _f1(fe):
    w, _ = fe.eig()
    return w[0] / (2 * math.pi)


def test_one_rigid_end_lies_between_all_elastic_and_all_rigid():
    kb = P.bearing_stiffness_n_per_m
    both = _f1(assemble_span(SPAN, 16))
    mixed = assemble_span(SPAN, 16, kb_ends=(math.inf, kb))
    rigid = _f1(assemble_span(SPAN, 16, kb_ends=(math.inf, math.inf)))
    assert mixed.stiffness.shape[0] == 2 * 17 - 1          # only the rigid end's DOF removed
    assert both < _f1(mixed) < rigid


def test_rigid_ends_give_the_simply_supported_frequency():
    fe = assemble_span(SPAN, 16, kb_ends=(math.inf, math.inf))
    ref = (math.pi / L) ** 2 * math.sqrt(P.bending_stiffness_n_m2 / P.mass_per_length_kg_m) / (2 * math.pi)
    assert _f1(fe) == pytest.approx(ref, rel=1e-3)


def test_one_soft_bearing_lowers_the_mode_towards_rigid_rotation():
    kb = P.bearing_stiffness_n_per_m
    f = [_f1(assemble_span(SPAN, 16, kb_ends=(kb, kb * r))) for r in (1.0, 0.1, 0.01, 1e-4)]
    assert all(a > b for a, b in zip(f, f[1:]))
    # one end on a vanishing spring: the girder rotates about the other bearing as a rigid body,
    # f = sqrt(3 k_end / m_total) / 2 pi (rigid bar pinned at one end, spring at the other)
    k = kb * 1e-4
    ref = math.sqrt(3 * k / (P.mass_per_length_kg_m * L)) / (2 * math.pi)
    assert f[-1] == pytest.approx(ref, rel=0.02)


def test_free_free_shape_generalised_mass_is_a_quarter():
    psi = _free_free_shape(25.0)
    x = np.linspace(0, 25.0, 2001)
    assert psi(0.0) == pytest.approx(1.0) and psi(25.0) == pytest.approx(1.0, abs=1e-6)
    assert np.trapezoid(psi(x) ** 2, x) / 25.0 == pytest.approx(0.25, rel=1e-3)


@pytest.mark.parametrize("fb", [6.0, 10.0])
def test_flexible_car_body_adds_a_mode_near_its_bending_frequency(fb):
    cfg = twin_config()
    vm = flexible_vehicle(vehicle_from_design(cfg.vehicle), fb, 0.02)
    assert vm.n_dof == 19
    # undamped free vibration of the vehicle on springs (magnets held): a mode within 15 % of fb,
    # stiffened only by the air springs
    w2 = eigh(vm.stiffness, vm.mass, eigvals_only=True)
    f = np.sqrt(np.clip(w2, 0, None)) / (2 * math.pi)
    assert np.min(np.abs(f - fb)) / fb < 0.15
    eq0 = static_equilibrium(vehicle_from_design(cfg.vehicle))
    eq1 = static_equilibrium(vm)
    assert np.allclose(eq1.magnet_force_n.sum(), eq0.magnet_force_n.sum())


def test_car_body_point_rows_rigid_lever_and_free_free_bending_shape():
    cfg = twin_config()
    rigid = vehicle_from_design(cfg.vehicle)
    xc = cfg.vehicle.car_body.x_m
    row = body_point_row(rigid, xc + 3.0)
    assert row[rigid.dof_names.index("car.z")] == 1.0
    assert row[rigid.dof_names.index("car.pitch")] == pytest.approx(3.0)
    flex = flexible_vehicle(rigid, 8.0)
    xs = cfg.vehicle.secondary_x_m
    mid, half = 0.5 * (max(xs) + min(xs)), 0.65 * (max(xs) - min(xs))
    k = flex.dof_names.index("car.bend")
    # first free-free bending mode of a uniform beam: ends 1, centre -0.6078 (tabulated ratio)
    assert body_point_row(flex, mid + half)[k] == pytest.approx(1.0, abs=1e-6)
    assert body_point_row(flex, mid - half)[k] == pytest.approx(1.0, abs=1e-6)
    assert body_point_row(flex, mid)[k] == pytest.approx(-0.6078, abs=2e-4)
    assert np.array_equal(body_point_row(flex, mid)[:k], body_point_row(rigid, mid))


def test_control_lag_keeps_the_levitation_stable_and_moves_the_poles():
    cfg = twin_config()
    p0 = build_vehicle(cfg).state_space.poles()
    p1 = build_vehicle(with_levitation(cfg, coil_inductance_h=0.004)).state_space.poles()
    assert np.all(p1.real < 0)
    assert p1.size == p0.size + 8   # one current state per magnet


def test_sensor_error_applies_scale_offset_drift():
    from maglev_ros.discrepancy.model import predict
    from maglev_ros.discrepancy.recording import recording_from_arrays
    md = {"schema": "maglev-testline/1", "line": {"spans": [{"id": "S1", "start_m": 0.0, "length_m": L}]},
          "sensors": {"G1": {"topic": "/testline/guideway/accel", "position_m": L / 2}},
          "run": {"kind": "ambient"}}
    t = np.arange(0, 2, 0.002)
    rec = recording_from_arrays(md, {"G1": (t, np.zeros_like(t))})
    spec = base_spec(md).with_(sensor_error=(("G1", 2.0, 0.1, 0.05),))
    y = predict(spec, rec)["G1"]
    assert np.allclose(y, 0.1 + 0.05 * (t - t[0]))


def test_an_accelerometers_bias_is_re_estimated_on_each_recording():
    """An accelerometer's offset and drift change between recordings: with the channel re-zeroed, each
    recording gets its own (the injected ones, within the least-squares line's standard errors), not
    the values of the pass the error was fitted on; the scale stays the one given."""
    from maglev_ros.discrepancy.model import predict
    from maglev_ros.discrepancy.recording import recording_from_arrays
    md = {"schema": "maglev-testline/1", "line": {"spans": [{"id": "S1", "start_m": 0.0, "length_m": L}]},
          "sensors": {"G1": {"topic": "/testline/guideway/accel", "position_m": L / 2}},
          "run": {"kind": "ambient"}}
    t = np.arange(0, 10, 0.002)
    rng = np.random.default_rng(5)
    sigma = 0.004
    spec = base_spec(md).with_(sensor_error=(("G1", 1.0, 0.011, 0.0016),), sensor_rezeroed=("G1",))
    # the least-squares line's standard errors for white noise of std sigma over n samples in T seconds
    n, T = t.size, t[-1] - t[0]
    se_offset, se_drift = 2 * sigma / math.sqrt(n), math.sqrt(12) * sigma / (T * math.sqrt(n))
    for offset, drift in ((0.011, 0.0016), (0.021, -0.0027)):
        rec = recording_from_arrays(md, {"G1": (t, offset + drift * t + sigma * rng.standard_normal(t.size))})
        y = predict(spec, rec)["G1"]
        assert abs(y[0] - offset) < 4 * se_offset
        assert abs((y[-1] - y[0]) / T - drift) < 4 * se_drift


# ---------------------------------------------------------------------------------------------
# magnet_nonlinearity: smooth current saturation in the twin's force kernel
def _sat_run(limit, speed=25.0, dur=2.5, sides="both"):
    from maglev_ros.twin.coupling import TwinStepper
    from maglev_ros.twin.design import default_line
    cfg = twin_config()
    line = default_line(cfg, 3)
    irr = lambda x: 1e-3 * np.sin(2 * np.pi * x / 5.0)     # 5 Hz at 25 m/s
    st = TwinStepper(cfg, line, sensors={"m": 18.0}, irregularity=irr, fs_out_hz=1000.0,
                     start_speed_mps=speed, current_limit_a=limit, current_limit_sides=sides)
    return cfg, st.advance(dur, speed)


def test_current_saturation_off_or_far_away_is_the_plain_twin():
    cfg, r0 = _sat_run(None)
    _, r1 = _sat_run(1e4)               # tanh(x / L) = x / L to 1e-9 for |x| << L
    assert np.max(np.abs(r1.magnet_gap_m - r0.magnet_gap_m)) < 1e-9
    assert np.max(np.abs(r1.magnet_current_a - r0.magnet_current_a)) < 1e-6


def test_saturated_current_stays_inside_the_headroom_and_gaps_grow():
    cfg, r0 = _sat_run(None)
    i0 = cfg.levitation.static_current_a
    on = r0.time_s > 0.5                 # after the start transient
    peak = np.max(np.abs(r0.magnet_current_a - i0))
    lim = 1.3 * peak
    _, r1 = _sat_run(lim)
    d1 = np.abs(r1.magnet_current_a - i0)
    # I_eff - I0 = L tanh(.) never reaches L; the force iteration converged (Newton)
    assert d1.max() < lim
    assert r1.iterations.max() < cfg.numerics.max_iterations
    # less force authority: the magnets follow the rail less tightly (larger gap variation)
    s0 = np.std(r0.magnet_gap_m[on], axis=0)
    s1 = np.std(r1.magnet_gap_m[on], axis=0)
    assert np.all(s1 > s0)
    # tanh compression of the peak: the effective excursion is at most L tanh(I_demand / L) with
    # I_demand >= the unsaturated peak (the saturated magnet asks for more, never less)
    assert d1.max() >= lim * math.tanh(peak / lim) * 0.9


def test_a_current_limited_above_only_follows_the_demand_below_and_skews_the_magnets():
    """A supply's maximum current: above I0 the force sees I0 + L tanh((I - I0) / L), below it the
    commanded current itself. The magnets' accelerations then lose their symmetry about zero."""
    from scipy.stats import skew
    cfg, r0 = _sat_run(None)
    i0 = cfg.levitation.static_current_a
    on = r0.time_s > 0.5
    lim = 0.5 * np.max(np.abs(r0.magnet_current_a - i0))
    _, r1 = _sat_run(lim, sides="upper")
    _, r2 = _sat_run(lim)
    d1 = r1.magnet_current_a - i0
    assert d1.max() <= lim * (1 + 1e-12) and d1.min() < -lim        # limited above only
    assert r1.iterations.max() < cfg.numerics.max_iterations
    acc = r1.vehicle_acc_mps2[on][:, [r1.dof_names.index(n) for n in r1.dof_names if n.startswith("mag")][:1]]
    acc0 = r0.vehicle_acc_mps2[on][:, [r0.dof_names.index(n) for n in r0.dof_names if n.startswith("mag")][:1]]
    assert abs(float(skew(acc[:, 0]))) > abs(float(skew(acc0[:, 0]))) + 0.2
    # two-sided and one-sided limits differ only where the demand is below I0
    assert np.max(np.abs(r2.magnet_current_a - r1.magnet_current_a)) > 0.1 * lim



def test_the_twin_follows_the_measured_position_when_the_position_stream_starts_with_the_sensors():
    """Where the position stream starts with the sensors, the twin (which starts one sample before
    the first sample) must be placed by extrapolating with the speed, not at the first position:
    clamped, it ran one sample period ahead of the recording for the whole pass."""
    from dataclasses import replace
    from pathlib import Path
    from maglev_ros.discrepancy.model import simulate
    from maglev_ros.discrepancy.recording import load_recording
    rec = load_recording(Path(__file__).resolve().parents[1] / "bags" / "paper_pass")
    tp = rec.position_time_s
    t_first = max(rec.t0_s, float(tp[0]))
    keep = tp >= t_first
    chans = {n: replace(c, time_s=c.time_s[c.time_s >= t_first][:3000], values=c.values[c.time_s >= t_first][:3000])
             for n, c in rec.channels.items() if c.group in ("vehicle_accel", "gap")}
    rec = replace(rec, channels=chans, position_time_s=tp[keep], position_m=rec.position_m[keep],
                  speed_mps=rec.speed_mps[keep])
    fs = max(c.sample_rate_hz for c in chans.values())
    res = simulate(base_spec(rec.metadata), rec)
    inside = (res.time_s >= rec.position_time_s[0]) & (res.time_s <= rec.position_time_s[-1])
    measured = np.interp(res.time_s[inside], rec.position_time_s, rec.position_m)
    v = float(np.mean(rec.speed_mps))
    # within a quarter of the distance travelled in one sample period (the speed integration's drift)
    assert np.max(np.abs(res.position_m[inside] - measured)) < 0.25 * v / fs


@pytest.mark.parametrize("i_lo", [0.0, 2.0])
def test_saturation_law_and_its_slope(i_lo):
    """The kernel's current law against tanh written out, and its slope against a central difference."""
    from maglev_ros.twin.coupling import _sat_current, _sat_slope
    i0, i_hi = 25.0, 1.5
    for c in np.linspace(20.0, 30.0, 41):
        x = c - i0
        want = i0 + (i_hi * np.tanh(x / i_hi) if x >= 0 else (i_lo * np.tanh(x / i_lo) if i_lo > 0 else x))
        assert _sat_current(c, i0, i_lo, i_hi) == pytest.approx(want, abs=1e-12)
        h = 1e-6
        fd = (_sat_current(c + h, i0, i_lo, i_hi) - _sat_current(c - h, i0, i_lo, i_hi)) / (2 * h)
        assert _sat_slope(c, i0, i_lo, i_hi) == pytest.approx(fd, abs=1e-6)


# ---------------------------------------------------------------------------------------------
# the twin's output as a channel recorded at a lower rate sees it: anti-aliased, not folded
def test_anti_aliasing_keeps_the_usable_band_and_removes_what_would_fold_into_it():
    """Against the analytic response: a tone at 0.6 x the channel's Nyquist keeps its amplitude
    (within 0.3 %); one at 1.4 x (it would fold onto 0.6 x) is gone (< 0.2 %)."""
    from maglev_ros.discrepancy.model import anti_aliased
    fs, fs_ch = 2000.0, 500.0
    t = np.arange(0, 4, 1 / fs)
    mid = slice(1000, -1000)
    for f, lo, hi in ((0.6 * fs_ch / 2, 0.997, 1.003), (1.4 * fs_ch / 2, 0.0, 0.002)):
        y = anti_aliased(np.sin(2 * np.pi * f * t), t, fs_ch)
        amp = np.sqrt(2) * np.std(y[mid])
        assert lo <= amp <= hi, (f, amp)
    x = np.sin(2 * np.pi * 10 * t)
    assert anti_aliased(x, t, fs) is x                  # not finer than the channel: unchanged


def test_a_channel_recorded_at_a_lower_rate_gets_the_twin_output_anti_aliased():
    """The sample pass (2 kHz) with its guideway accelerometers decimated to 500 Hz: the twin's
    band powers of a decimated channel equal those of the full-rate prediction in every band the
    500 Hz channel uses (within 1 %); sampled every other step (folded) they were not."""
    from dataclasses import replace
    from pathlib import Path
    from scipy import signal
    from maglev_ros.discrepancy.features import band_powers, frame_grid, usable_bands
    from maglev_ros.discrepancy.model import predict
    from maglev_ros.discrepancy.recording import load_recording
    rec = load_recording(Path(__file__).resolve().parents[1] / "bags" / "paper_pass")
    name = next(n for n, c in rec.channels.items() if c.group == "guideway_accel")
    ch = rec.channels[name]
    q = int(round(ch.sample_rate_hz / 500.0))
    v = signal.decimate(ch.values - ch.values.mean(), q, ftype="fir", zero_phase=True) + ch.values.mean()
    low = replace(ch, values=v, time_s=ch.time_s[::q][:v.size], sample_rate_hz=ch.sample_rate_hz / q)
    rec_low = replace(rec, channels={**rec.channels, name: low})
    spec = base_spec(rec.metadata)
    grid = frame_grid(rec)
    full = band_powers(ch.time_s, predict(spec, rec)[name], ch.sample_rate_hz, grid)
    got = band_powers(low.time_s, predict(spec, rec_low)[name], low.sample_rate_hz, grid)
    use = usable_bands(grid, low.sample_rate_hz)
    ok = np.all(np.isfinite(full) & np.isfinite(got), axis=1)
    ratio = got[ok][:, use].sum(axis=0) / full[ok][:, use].sum(axis=0)
    assert np.all(np.abs(ratio - 1) < 0.01), ratio
