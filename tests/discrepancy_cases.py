"""Concealed-effect test recordings for the discrepancy diagnosis, generated from the twin.

Each case = one ambient recording + two passes (different speeds) of a vehicle over a 3-span
line, with ONE concealed effect (or none: "clean", only parameter changes against the design
block; or an out-of-catalogue effect). Truth is kept in ``Case.truth``; the recordings carry only
what a real recording carries (contract metadata with a nominal design block).

The generator deliberately differs from what the diagnosis runs, in ways real recordings differ
(``variant``): a finer FE mesh, a smaller integration step and 1 kHz simulation decimated to
500 Hz through a causal anti-alias filter (Butterworth or Chebyshev, varying corner), white or
pink/red sensor noise at varying levels, design values off the truth by several percent, and in
the held-out variant an extra current-loop lag and the separated (precise-integration) solver.
Effects are implemented here independently where that is cheap: a degraded bearing as an elastic
pad in series with the nominal bearing, ambient vibration as random coloured point forces at
random places on every girder (modal superposition; every ambient recording rings this way at a
level of its own, the ``ambient_excitation`` effect adds it to the passes too), sensor faults on the recorded samples, a
girder attachment (tuned-mass-like resonator) by an augmented FE eigenproblem. Magnet
nonlinearity is the twin kernel's smooth current saturation with a headroom set from the
truth's own unsaturated peak current demand on the fastest pass. A cubic suspension term (out of
the catalogue: ``suspension_cubic``) stiffens the secondary air springs by k3 d^3, added here by
operator splitting around the linear truth stepper (:func:`advance_cubic`), with k3 set from the
linear truth's own largest air-spring deflection on the fastest pass.

Every case runs over a random guideway irregularity (as every real line has one; the diagnosis
must then go through the irregularity it reconstructs from each pass): one profile per case,
shared by its passes, from a reference PSD with a random roughness scale, wavelength band and
seed. The tune split draws from the FRA class-6 shape (k = 0.25) and the paper-001 shape (FRA
form, k = 1); the held-out split uses the German high-speed shape (low-wavenumber cut-off,
other slope), never used while tuning.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np
from scipy import signal
from scipy.linalg import eigh

from maglev_ros.discrepancy.model import body_point_row, flexible_vehicle
from maglev_ros.discrepancy.recording import TOPIC_GROUP, Recording, recording_from_arrays
from maglev_ros.twin.coupling import PassResult, TwinStepper
from maglev_ros.twin.spring_force import advance_with_spring_force
from maglev_ros.twin.design import SpanSpec, line_spans, twin_config, with_levitation
from maglev_ros.twin.guideway import Guideway, ModalBasis, SpanFE, beam_element
from maglev_ros.twin.irregularity_psd import psd_by_name, random_profile
from maglev_ros.twin.levitation import LevitationModel, VehicleSystem, closed_loop
from maglev_ros.twin.vehicle import static_equilibrium

L_SPAN = 12.384
N_SPANS = 3
FS_OUT = 500.0
CATEGORY = {"bearing_stiffness": "boundary_condition", "control_delay": "control",
            "magnet_nonlinearity": "magnetic_force", "ambient_excitation": "excitation",
            "girder_stiffness_loss": "guideway_structure", "carbody_flexibility": "vehicle_structure",
            "sensor_error": "instrumentation"}
OOC = ("girder_attachment", "suspension_cubic")


@dataclass
class Case:
    case_id: str
    effect: str | None                  # catalogue name, one of OOC (out of catalogue) or None
    magnitude: float
    truth: dict
    ambient: Recording
    passes: list
    split: str                          # "tune" or "heldout"
    variant: dict = field(default_factory=dict)

    @property
    def category(self) -> str | None:
        return CATEGORY.get(self.effect) if self.effect else None


def metadata(design: dict, kind: str, speed: float, n_spans: int = N_SPANS, body_sensors: bool = True) -> dict:
    spans = [{"id": f"S{i + 1}", "start_m": i * L_SPAN, "length_m": L_SPAN} for i in range(n_spans)]
    sensors = {}
    for i in range(n_spans):
        sensors[f"G{i + 1}A"] = {"topic": "/testline/guideway/accel", "quantity": "acceleration",
                                 "direction": "vertical", "span": f"S{i + 1}",
                                 "position_m": (i + 0.5) * L_SPAN, "side": "center"}
        sensors[f"G{i + 1}Q"] = {"topic": "/testline/guideway/accel", "quantity": "acceleration",
                                 "direction": "vertical", "span": f"S{i + 1}",
                                 "position_m": (i + 0.2) * L_SPAN, "side": "center"}
    j = min(1, n_spans - 1)
    sensors[f"G{j + 1}D"] = {"topic": "/testline/guideway/displacement", "quantity": "displacement",
                             "direction": "vertical", "span": f"S{j + 1}", "position_m": (j + 0.5) * L_SPAN,
                             "side": "center"}
    cfg = twin_config()
    if kind == "pass":
        for k in (1, 8):
            sensors[f"M{k}A"] = {"topic": "/testline/vehicle/accel", "quantity": "acceleration",
                                 "direction": "vertical", "magnet": k}
            sensors[f"M{k}G"] = {"topic": "/testline/vehicle/gap", "quantity": "gap", "magnet": k}
        if body_sensors:
            # car-body floor accelerometers (optional topic, docs/contract-extensions.md): over the
            # front air spring and at the body's centre
            xs = cfg.vehicle.secondary_x_m
            for name, x in (("B1A", max(xs)), ("B2A", cfg.vehicle.car_body.x_m)):
                sensors[name] = {"topic": "/testline/vehicle/body_accel", "quantity": "acceleration",
                                 "direction": "vertical", "body_x_m": float(x)}
    return {"schema": "maglev-testline/1", "description": "concealed-effect case",
            "line": {"spans": spans}, "sensors": sensors,
            "vehicle": {"magnet_offsets_m": list(cfg.vehicle.magnet_offsets_m), "nominal_gap_m": 0.010},
            "run": {"kind": kind, "nominal_speed_mps": speed}, "design": design}


# ------------------------------------------------------------------------------------------
def _span_fe_series_pad(span: SpanSpec, n_el: int, k_pad_left: float, k_pad_right: float) -> SpanFE:
    """Span on bearings with an elastic pad in series at each end (k = 1/(1/kb + 1/k_pad))."""
    p = span.props
    le = span.length_m / n_el
    ke, me = beam_element(p.bending_stiffness_n_m2, p.mass_per_length_kg_m, le)
    nd = 2 * (n_el + 1)
    K = np.zeros((nd, nd)); M = np.zeros((nd, nd))
    for e in range(n_el):
        s = slice(2 * e, 2 * e + 4)
        K[s, s] += ke; M[s, s] += me
    for dof, kp in ((0, k_pad_left), (2 * n_el, k_pad_right)):
        K[dof, dof] += 1.0 / (1.0 / p.bearing_stiffness_n_per_m + 1.0 / kp)
    free = np.arange(nd)
    w = np.sqrt(np.clip(eigh(K, M, eigvals_only=True, subset_by_index=[0, 1]), 1e-12, None))
    z = p.damping_ratio
    return SpanFE(span, n_el, M, K, free, 2 * z * w[0] * w[1] / (w[0] + w[1]), 2 * z / (w[0] + w[1]))


def _attachment_modes(gw: Guideway, span_i: int, x_rel: float, f_att: float, mass_ratio: float,
                      zeta_att: float, cutoff_hz: float) -> ModalBasis:
    """Modal basis with a spring-mass attached to span ``span_i`` at ``x_rel`` (augmented eigenproblem;
    modes keep their beam part; attachment damping folded into modal damping)."""
    base = gw.modes(cutoff_hz, 2)
    freqs, zetas, owner, vecs = [], [], [], []
    for i, fe in enumerate(gw.spans_fe):
        sel = base.span_index == i
        if i != span_i:
            freqs.append(base.freq_hz[sel]); zetas.append(base.damping_ratio[sel])
            owner.append(np.full(sel.sum(), i)); vecs.append(base.vectors[i])
            continue
        n = fe.mass.shape[0]
        m_span = fe.span.props.mass_per_length_kg_m * fe.span.length_m
        ma = mass_ratio * m_span
        ka = ma * (2 * math.pi * f_att) ** 2
        row = fe.shape_matrix([fe.span.start_m + x_rel])[0]
        K = np.zeros((n + 1, n + 1)); M = np.zeros((n + 1, n + 1))
        K[:n, :n] = fe.stiffness; M[:n, :n] = fe.mass
        M[n, n] = ma
        t = np.append(row, -1.0)
        K += ka * np.outer(t, t)
        w2, phi = eigh(K, M)
        f = np.sqrt(np.clip(w2, 0, None)) / (2 * math.pi)
        k = max(int(np.sum(f <= cutoff_hz)), 3)
        wv = 2 * math.pi * f[:k]
        zb = fe.rayleigh_a / (2 * wv) + fe.rayleigh_b * wv / 2
        part = phi[n, :k] ** 2 * ma      # share of attachment kinetic energy
        freqs.append(f[:k]); zetas.append((1 - part) * zb + part * zeta_att)
        owner.append(np.full(k, i)); vecs.append(phi[:n, :k])
    return ModalBasis(np.concatenate(freqs), np.concatenate(zetas), np.concatenate(owner), gw.spans_fe,
                      tuple(vecs))


def _lead_s(v: float, n_spans: int, offs: np.ndarray, variant: dict) -> float:
    """Seconds recorded before the vehicle enters / after it leaves: a pass of at least
    ``variant["min_pass_s"]`` (8.5 s: at 34 m/s 7.5 s left the 0.8 Hz reconstruction no valid
    stretch) and never less than 1.5 s of approach."""
    over = (n_spans * L_SPAN + offs.max() - offs.min()) / v
    return max(1.5, 0.5 * (variant.get("min_pass_s", 8.5) - over))


TUNE_PSDS = (("fra6", (0.6, 1.3)), ("maglev_001", (0.8, 2.0)))     # (PSD, amplitude scale range)
HELDOUT_PSDS = (("german_low", (0.6, 1.4)), ("german_high", (0.5, 1.0)))
BLIND_PSDS = (("fra5", (0.5, 1.1)), ("german_low", (0.8, 1.5)))


def guideway_profile(rng, split: str, x_lo: float, x_hi: float) -> tuple[np.ndarray, np.ndarray, dict]:
    """Random unloaded guideway irregularity (x_m, r_m) over [x_lo, x_hi] and what was drawn."""
    choices = {"tune": TUNE_PSDS, "blind": BLIND_PSDS}.get(split, HELDOUT_PSDS)
    name, (s_lo, s_hi) = choices[int(rng.integers(len(choices)))]
    scale = float(rng.uniform(s_lo, s_hi))
    band = (float(rng.uniform(0.6, 1.2)), float(rng.uniform(25.0, 45.0)))
    x, r = random_profile(psd_by_name(name), x_hi - x_lo, 0.02, band, rng, start_m=x_lo)
    r = scale * r
    return x, r, {"psd": name, "scale": scale, "wavelength_band_m": band, "rms_m": float(np.std(r))}


def _structural_effect_modes(gw: Guideway, spans, eff: str | None, tp: dict, numerics) -> ModalBasis | None:
    """The guideway's modes with the case's structural effect (a bearing pad, an attachment) built into
    ``gw``; None when the effect leaves the guideway as designed. Shared by the passes and the ambient."""
    if eff == "bearing_stiffness":
        fes = list(gw.spans_fe)
        i, end = tp["span_index"], tp["end"]
        kb = spans[i].props.bearing_stiffness_n_per_m
        # pad stiffness so that the series stiffness is kb * factor
        f = tp["factor"]
        kpad = kb * f / (1 - f)
        fes[i] = _span_fe_series_pad(spans[i], numerics.n_elements_per_span,
                                     kpad if end == 0 else 1e30, kpad if end == 1 else 1e30)
        gw.spans_fe = tuple(fes)
        return gw.modes(numerics.mode_cutoff_hz, numerics.min_modes_per_span)
    if eff == "girder_attachment":
        return _attachment_modes(gw, tp["span_index"], tp["x_rel_m"], tp["freq_hz"], tp["mass_ratio"], 0.03,
                                 numerics.mode_cutoff_hz)
    return None


def _truth_stepper(cfg, spans, sensors, v, x0, eff: str | None, tp: dict, variant: dict,
                   irregularity=None) -> TwinStepper:
    if eff == "control_delay" or variant.get("extra_lag_s", 0) > 0:
        lag = (tp.get("lag_s", 0.0) if eff == "control_delay" else 0.0) + variant.get("extra_lag_s", 0.0)
        cfg = with_levitation(cfg, coil_inductance_h=lag * cfg.levitation.coil_resistance_ohm)
    # output every internal step (:func:`at_1khz` low-passes before the 1 kHz samples): guideway modes
    # above the step's range ring at its prewarp cap and would fold into the band if sampled directly
    dt = variant.get("dt_s", 5e-4)
    st = TwinStepper(cfg, spans, sensors=sensors, irregularity=irregularity, fs_out_hz=1.0 / dt,
                     start_position_m=x0, start_speed_mps=v,
                     init="rest", method=variant.get("method", "newmark"), dt_max_s=dt)
    modal = _structural_effect_modes(st.guideway, spans, eff, tp, cfg.numerics)
    changed = modal is not None
    if changed:
        st.modal = modal
        st.sensor_shapes = st.modal.shapes_at(st.sensor_x_m)
    if eff == "magnet_nonlinearity":
        st.current_limit_a = float(tp["current_limit_a"])
    if eff == "carbody_flexibility":
        vm = flexible_vehicle(st.vehicle.model, tp["bend_hz"], 0.03)
        eq = static_equilibrium(vm)
        lev = LevitationModel.from_design(cfg.levitation, eq.magnet_force_n)
        st.vehicle = VehicleSystem(vm, eq, lev, closed_loop(vm, lev))
        changed = True
    if changed:
        st._setup_matrices()
        st._x = np.zeros(st._nx); st._u = np.zeros(3 * st._m)
        nq = st.modal.n_modes
        st._q, st._qd, st._qdd = np.zeros(nq), np.zeros(nq), np.zeros(nq)
        st._F = st.vehicle.levitation.static_force_n.copy()
    st._init_static()
    return st


def secondary_springs(model) -> tuple[tuple, np.ndarray]:
    """The secondary air springs of a ``VehicleModel`` and their rows T (n_sec, n_dof): d = T z is
    each spring's relative vertical displacement from static equilibrium (z: the DOFs).

    Found by topology, not by name: the levitation frames are the bodies a magnet's body is joined
    to (primary suspension), the car body is the heaviest body, and a secondary air spring is a
    connection joining the car body to a frame. T is built as ``vehicle.assemble`` builds a
    connection's row: point row of ``body_a`` at the spring's x minus that of ``body_b`` (default
    model: frame minus car, so d > 0 compresses the spring)."""
    mag_bodies = {m.body for m in model.magnets}
    frames = ({c.body_b for c in model.connections if c.body_a in mag_bodies}
              | {c.body_a for c in model.connections if c.body_b in mag_bodies}) - mag_bodies
    car = max(model.bodies, key=lambda b: b.mass_kg).name
    sec = tuple(c for c in model.connections if {c.body_a, c.body_b} in ({car, f} for f in frames))
    if not sec:
        raise RuntimeError("suspension_cubic: no connection joins the car body to a levitation frame")
    rows = np.stack([model.point_row(c.body_a, c.x_m) - model.point_row(c.body_b, c.x_m) for c in sec])
    return sec, rows


def advance_cubic(st: TwinStepper, t_end_s: float, v: float, k3: float, kick_every: int = 1
                  ) -> tuple[PassResult, np.ndarray]:
    """``st.advance(t_end_s, v)`` with a cubic force F = k3 d^3 added in every secondary air spring
    (stiffening: it acts like the linear spring force k d, equal and opposite on car body and frame),
    by operator splitting around the linear truth (the twin's
    :func:`maglev_ros.twin.spring_force.advance_with_spring_force`: the truth is advanced
    ``kick_every`` output samples, 1 ms at the 1 kHz truth rate, then the cubic force's impulse is
    added to the DOF velocities). The springs are found here by topology (:func:`secondary_springs`),
    not by the twin's names. The recorded car-body accelerations carry the cubic force's share;
    magnet accelerations, gaps and currents need nothing (no air spring acts on a magnet's body).
    Returns the concatenated PassResult (same form as one ``advance``) and F (n, n_sec) [N] at the
    output samples. With k3 = 0 the result equals one ``advance`` call to floating point."""
    _, rows = secondary_springs(st.vehicle.model)
    return advance_with_spring_force(st, t_end_s, v, rows, lambda d, d_rate: k3 * d ** 3, every=kick_every)


def power_band(x: np.ndarray, fs: float, share: float = 0.9) -> tuple[float, float]:
    """Band holding the central ``share`` of the power of x (n,) or (n, k) (summed over columns):
    Welch PSD (4 s segments, mean removed), cumulative power from (1 - share)/2 to (1 + share)/2."""
    x = np.asarray(x, float).reshape(len(x), -1)
    f, p = signal.welch(x, fs=fs, nperseg=min(4096, x.shape[0]), axis=0)
    c = np.cumsum(p.sum(axis=1))
    if not c[-1] > 0:
        return 0.0, 0.0                   # no power (k3 = 0)
    c = c / c[-1]
    lo = f[int(np.searchsorted(c, 0.5 * (1 - share)))]
    hi = f[min(int(np.searchsorted(c, 0.5 * (1 + share))), f.size - 1)]
    return float(lo), float(hi)


# the diagnosis' band grid (maglev_ros.discrepancy.features.BAND_EDGES_HZ, copied: the generator
# states its own reference)
SIGNATURE_EDGES_HZ = (3.0, 6.0, 10.0, 14.0, 18.0, 22.0, 26.0, 31.0, 37.0, 44.0, 52.0, 62.0, 74.0, 88.0, 105.0,
                      125.0, 150.0)


def signature_bands(sig_eff: dict, sig_none: dict, sensors: dict, span_id: str, fs_hz: float,
                    noise_std: float, min_rel: float = 0.15, min_snr: float = 3.0) -> list[list[float]]:
    """Bands where an effect changes the recording of its span's guideway accelerometers: the band
    amplitude (Welch, whole pass) with the effect differs from the same pass without it by at least
    ``min_rel``, where the signal stands ``min_snr`` above the sensors' white noise (what an
    instrument could see). Adjacent bands merged; [[f0, f1], ...]."""
    names = [k for k, s in sensors.items() if s.get("span") == span_id and s["quantity"] == "acceleration"
             and s["topic"] == "/testline/guideway/accel"]
    e = np.asarray(SIGNATURE_EDGES_HZ)
    hit = np.zeros(e.size - 1, bool)
    for k in names:
        f, pa = signal.welch(sig_eff[k], fs_hz, nperseg=1024)
        _, pb = signal.welch(sig_none[k], fs_hz, nperseg=1024)
        df = f[1] - f[0]
        for b in range(e.size - 1):
            m = (f >= e[b]) & (f < e[b + 1])
            a, c = pa[m].sum() * df, pb[m].sum() * df
            noise = noise_std ** 2 * (e[b + 1] - e[b]) / (FS_OUT / 2)
            if max(a, c) >= min_snr * noise and abs(math.sqrt(a / max(c, 1e-300)) - 1) >= min_rel:
                hit[b] = True
    out: list[list[float]] = []
    for b in np.flatnonzero(hit):
        if out and out[-1][1] == e[b]:
            out[-1][1] = float(e[b + 1])
        else:
            out.append([float(e[b]), float(e[b + 1])])
    return out


def _noise(rng, n, std, colour: str) -> np.ndarray:
    w = rng.standard_normal(n)
    if colour == "pink":
        f = np.fft.rfftfreq(n)
        f[0] = f[1]
        w = np.fft.irfft(np.fft.rfft(w) / np.sqrt(f / f[-1]), n)
    elif colour == "red":
        w = signal.lfilter([1.0], [1.0, -0.9], w)
    return std * w / (np.std(w) + 1e-30)


def at_1khz(t_s: np.ndarray, signals: dict[str, np.ndarray]) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Signals sampled every internal step (t_s) brought to 1 kHz by scipy's polyphase anti-aliasing
    resampler (an oversampled simulation's anti-alias step): the sample times t_s[0] + k ms."""
    from fractions import Fraction
    fs = 1.0 / float(np.median(np.diff(t_s)))
    r = Fraction(1000.0 / fs).limit_denominator(100)
    if r == 1:
        return t_s, signals
    out = {k: signal.resample_poly(y - y[0], r.numerator, r.denominator) + y[0] for k, y in signals.items()}
    n = min(y.size for y in out.values())
    return t_s[0] + np.arange(n) * 1e-3, {k: y[:n] for k, y in out.items()}


def _aa_decimate(x: np.ndarray, variant: dict) -> np.ndarray:
    kind, corner = variant.get("aa", ("butter", 0.4))
    wn = corner * FS_OUT / (1000.0 / 2)
    sos = (signal.butter(4, wn, output="sos") if kind == "butter"
           else signal.cheby1(6, 0.5, wn, output="sos"))
    y = signal.sosfilt(sos, x - x[0]) + x[0]
    return y[1::2]


def _modal_response(fq: np.ndarray, w: np.ndarray, z: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Modal displacements and accelerations (n, nm) under modal forces ``fq`` (n, nm) linear between
    samples: each mode discretized exactly (first-order hold), so a 90 Hz mode keeps its frequency
    (the trapezoidal rule at 1 ms rings it 2.5 % low)."""
    q_out, a_out = np.empty_like(fq), np.empty_like(fq)
    for j, (wj, zj) in enumerate(zip(w, z)):
        if wj >= 0.9 * np.pi / dt:
            # above 0.45 x the rate: quasi-static (discretised as a resonator it folds into the band)
            q_out[:, j] = fq[:, j] / wj ** 2
            a_out[:, j] = np.gradient(np.gradient(q_out[:, j], dt), dt)
            continue
        a_mat = np.array([[0.0, 1.0], [-wj ** 2, -2 * zj * wj]])
        c_mat = np.array([[1.0, 0.0], [-wj ** 2, -2 * zj * wj]])
        ad, bd, cd, dd, _ = signal.cont2discrete((a_mat, np.array([[0.0], [1.0]]), c_mat, np.array([[0.0], [1.0]])),
                                                 dt, method="foh")
        _, y, _ = signal.dlsim((ad, bd, cd, dd, dt), fq[:, j])
        q_out[:, j], a_out[:, j] = y[:, 0], y[:, 1]
    return q_out, a_out


def _ambient_response(rng, modal: ModalBasis, spans, sensors_x, n: int, dt: float, level: float):
    """Guideway (disp, accel) at sensors from random coloured point forces, 2 random points per span."""
    pts = np.concatenate([s.start_m + rng.uniform(0.1, 0.9, 2) * s.length_m for s in spans])
    fs = 1.0 / dt
    sos = signal.butter(2, [4.0 / (fs / 2), 70.0 / (fs / 2)], btype="band", output="sos")
    forces = np.stack([signal.sosfilt(sos, signal.lfilter([1.0], [1.0, -0.5], rng.standard_normal(n)))
                       for _ in pts], axis=1)
    phi = modal.shapes_at(pts)                     # (np, nm)
    fq = forces @ phi                               # (n, nm)
    Q, A = _modal_response(fq, modal.omega_rad_s, modal.damping_ratio, dt)
    S = modal.shapes_at(np.asarray(sensors_x))
    disp, acc = Q @ S.T, A @ S.T
    scale = level / (np.std(acc[n // 4:]) + 1e-30)   # level = RMS accel over the sensors
    return disp * scale, acc * scale


def truth_signals(res: PassResult, sensors: dict, vehicle_model) -> dict:
    """Each recorded channel's noise-free signal from a truth run (sensor entries of the metadata)."""
    out = {}
    for k, s in sensors.items():
        group = TOPIC_GROUP[s["topic"]]
        if group == "guideway_accel":
            out[k] = res.guideway_accel_mps2[:, res.sensor(k)].copy()
        elif group == "guideway_disp":
            out[k] = res.guideway_disp_m[:, res.sensor(k)].copy()
        elif group == "vehicle_accel":
            out[k] = res.magnet_accel_mps2[:, s["magnet"] - 1].copy()
        elif group == "gap":
            out[k] = res.magnet_gap_m[:, s["magnet"] - 1].copy()
        else:
            out[k] = res.vehicle_acc_mps2 @ body_point_row(vehicle_model, s["body_x_m"])
    return out


def _apply_sensor_fault(sig: dict, name: str, tp: dict, t: np.ndarray, ref: float) -> None:
    y = sig[name]
    kind = tp["kind"]
    if kind == "scale":
        sig[name] = ref + tp["value"] * (y - ref)
    elif kind == "offset":
        sig[name] = y + tp["value"]
    elif kind == "drift":
        sig[name] = y + tp["value"] * (t - t[0])
    elif kind == "dropout":
        a = int(tp["start_frac"] * y.size); b = a + int(tp["len_frac"] * y.size)
        y = y.copy(); y[a:b] = ref
        sig[name] = y


AMBIENT_RMS_MPS2 = (0.01, 0.04)   # a standing girder's ambient vibration (RMS over its accelerometers)
NOISE_STD = {"guideway_accel": 0.004, "guideway_disp": 1.5e-6, "vehicle_accel": 0.004, "gap": 1.0e-6,
             "body_accel": 0.002}


def _true_line(rng, variant: dict, design_error: dict | None, effect: str | None, tp: dict, n_spans: int):
    """(true twin config, design errors, the design block, the true spans): the design is off the truth
    by ``design_error`` (drawn when None); a girder stiffness loss is built into its span."""
    cfg_true = twin_config()
    cfg_true = replace(cfg_true, numerics=replace(cfg_true.numerics,
                                                  n_elements_per_span=variant.get("n_el", 24)))
    derr = design_error if design_error is not None else {
        "E": rng.uniform(-0.08, 0.08), "kb": rng.uniform(-0.3, 0.3), "kp": rng.uniform(-0.08, 0.08)}
    g, lev = cfg_true.guideway, cfg_true.levitation
    design = {"guideway": {"youngs_modulus_pa": g.youngs_modulus_pa / (1 + derr["E"]),
                           "bearing_stiffness_n_per_m": g.bearing_stiffness_n_per_m / (1 + derr["kb"])},
              "levitation": {"kp_a_per_m": lev.kp_a_per_m / (1 + derr["kp"])}}
    md_line = {"spans": [{"id": f"S{i + 1}", "start_m": i * L_SPAN, "length_m": L_SPAN} for i in range(n_spans)]}
    spans = list(line_spans(md_line, cfg_true))
    if effect == "girder_stiffness_loss":
        i = tp["span_index"]
        spans[i] = replace(spans[i], props=replace(spans[i].props,
                                                   youngs_modulus_pa=spans[i].props.youngs_modulus_pa * (1 - tp["loss"])))
    return cfg_true, derr, design, spans


def make_ambient(effect: str | None, params: dict, *, seed: int, n_spans: int = N_SPANS,
                 design_error: dict | None = None, variant: dict | None = None) -> tuple[Recording, ModalBasis]:
    """The ambient recording of a case alone (no passes simulated) and the true guideway modes it rings at."""
    rng = np.random.default_rng(seed)
    variant, tp = dict(variant or {}), dict(params)
    cfg_true, _, design, spans = _true_line(rng, variant, design_error, effect, tp, n_spans)
    return _ambient_recording(rng, seed, "ambient", metadata(design, "ambient", 0.0, n_spans), spans, cfg_true,
                              effect, tp, variant)


def _ambient_recording(rng, seed: int, case_id: str, md_amb: dict, spans, cfg_true, effect: str | None, tp: dict,
                       variant: dict) -> tuple[Recording, ModalBasis]:
    """The ambient recording (guideway sensors only) and the true modes it rings at."""
    gsens = {k: s["position_m"] for k, s in md_amb["sensors"].items()}
    noise_scale, colour = variant.get("noise_scale", 1.0), variant.get("noise_colour", "white")
    n_amb = int(variant.get("ambient_s", 20.0) * 1000)
    t_amb = np.arange(1, n_amb + 1) * 1e-3
    names = list(gsens)
    gw = Guideway(spans, cfg_true.numerics.n_elements_per_span)
    if effect == "ambient_excitation":
        modal = gw.modes(cfg_true.numerics.mode_cutoff_hz, 2)
        d, a = _ambient_response(rng, modal, spans, [gsens[k] for k in names], n_amb, 1e-3, tp["rms_mps2"])
    else:
        # a standing line always rings (wind, traffic, ground): the ambient recording carries the true
        # structure's modes (with a bearing pad or an attachment when the case has one) at a level of its
        # own; a separate generator leaves the passes and the sensor noise drawn as before
        rng_amb = np.random.default_rng([seed, 7])
        modal = (_structural_effect_modes(gw, spans, effect, tp, cfg_true.numerics)
                 or gw.modes(cfg_true.numerics.mode_cutoff_hz, cfg_true.numerics.min_modes_per_span))
        level = variant.get("ambient_rms_mps2", float(rng_amb.uniform(*AMBIENT_RMS_MPS2)))
        d, a = _ambient_response(rng_amb, modal, spans, [gsens[k] for k in names], n_amb, 1e-3, level)
    amb_hi = {k: d[:, j] if k.endswith("D") else a[:, j] for j, k in enumerate(names)}
    amb = {}
    for k, y in amb_hi.items():
        gname = "guideway_disp" if k.endswith("D") else "guideway_accel"
        y = _aa_decimate(y, variant)
        amb[k] = (t_amb[1::2], y + _noise(rng, y.size, NOISE_STD[gname] * noise_scale, colour))
    return recording_from_arrays(md_amb, amb, None, source=f"{case_id}/ambient"), modal


def make_case(case_id: str, effect: str | None, params: dict, *, seed: int, speeds=(22.0, 30.0),
              split: str = "tune", variant: dict | None = None, design_error: dict | None = None,
              n_spans: int = N_SPANS) -> Case:
    rng = np.random.default_rng(seed)
    variant = dict(variant or {})
    tp = dict(params)
    cfg_true, derr, design, spans = _true_line(rng, variant, design_error, effect, tp, n_spans)
    noise_scale = variant.get("noise_scale", 1.0)
    colour = variant.get("noise_colour", "white")
    md_pass = [metadata(design, "pass", v, n_spans, variant.get("body_sensors", True)) for v in speeds]
    md_amb = metadata(design, "ambient", 0.0, n_spans)
    gsens = {k: s["position_m"] for k, s in md_amb["sensors"].items()}
    passes = []
    offs_all = np.array(cfg_true.vehicle.magnet_offsets_m)
    irr_info = None
    irr = None
    if variant.get("irregularity", True):
        lead = max(_lead_s(v, n_spans, offs_all, variant) for v in speeds)
        x_lo = -offs_all.max() - max(speeds) * lead + offs_all.min() - 20.0
        x_hi = n_spans * L_SPAN - offs_all.min() + max(speeds) * lead + 20.0
        xi, ri, irr_info = guideway_profile(rng, split, x_lo, x_hi)
        irr = (xi, ri)
    plain = None          # the fastest pass without the effect (PassResult, its vehicle model)
    if effect in ("magnet_nonlinearity", "suspension_cubic", "girder_attachment"):
        v = max(speeds)
        lead = _lead_s(v, n_spans, offs_all, variant)
        x0 = -offs_all.max() - v * lead
        st = _truth_stepper(cfg_true, tuple(spans), gsens, v, x0, None, tp, variant, irr)
        plain = (st.advance((n_spans * L_SPAN - offs_all.min() + v * lead - x0) / v, v), st.vehicle)
    if effect == "magnet_nonlinearity":
        # current headroom = factor x the largest current excursion of the unsaturated truth on the
        # fastest pass (so levitation survives every pass while saturation bites at the peaks)
        res, veh = plain
        tp["peak_demand_a"] = float(np.abs(res.magnet_current_a - veh.levitation.static_current_a).max())
        tp["current_limit_a"] = tp["headroom"] * tp["peak_demand_a"]
    if effect == "suspension_cubic":
        # k3 from the LINEAR truth's largest air-spring deflection on the fastest pass: the cubic
        # force is cubic_ratio x the linear spring force k d_max at that deflection
        res, veh = plain
        sec, rows = secondary_springs(veh.model)
        k_sec = float(np.mean([c.stiffness_n_per_m for c in sec]))
        tp["k_secondary_n_per_m"] = k_sec
        tp["d_max"] = float(np.abs(res.vehicle_disp_m @ rows.T).max())         # [m]
        tp["k3"] = float(tp["cubic_ratio"]) * k_sec / tp["d_max"] ** 2         # [N/m^3]
    for v, md in zip(speeds, md_pass):
        offs = np.array(cfg_true.vehicle.magnet_offsets_m)
        # approach/departure recorded (the irregularity reconstruction needs ~6 s at 0.8 Hz)
        lead = _lead_s(v, n_spans, offs, variant)
        x0 = -offs.max() - v * lead
        dur = (n_spans * L_SPAN - offs.min() + v * lead - x0) / v
        st = _truth_stepper(cfg_true, tuple(spans), gsens, v, x0, effect, tp, variant, irr)
        if effect == "suspension_cubic":
            res, f3 = advance_cubic(st, dur, v, tp["k3"])
            if v == max(speeds):
                # where the cubic force has its power (90 % band) and its size against the linear
                # air-spring force k d, on the fastest pass
                _, rows = secondary_springs(st.vehicle.model)
                f_lin = tp["k_secondary_n_per_m"] * (res.vehicle_disp_m @ rows.T)
                tp["band_hz"] = list(power_band(f3, 1.0 / float(np.median(np.diff(res.time_s)))))
                tp["cubic_share_peak"] = float(np.abs(f3).max() / np.abs(f_lin).max())
                tp["cubic_share_rms"] = float(np.sqrt(np.mean(f3 ** 2) / np.mean(f_lin ** 2)))
        else:
            res = st.advance(dur, v)
        if not np.all(np.abs(res.magnet_gap_m - 0.010) < 0.008):
            raise RuntimeError(f"{case_id}: truth vehicle lost levitation at {v} m/s ({effect}, {tp})")
        t_hi, sig_hi = at_1khz(res.time_s, truth_signals(res, md["sensors"], st.vehicle.model))
        if effect == "girder_attachment" and v == max(speeds):
            # where the attachment shows: the same pass without it (noise-free truth signals)
            sig0 = at_1khz(plain[0].time_s, truth_signals(plain[0], md["sensors"], plain[1].model))[1]
            sig0 = {k: y[:t_hi.size] for k, y in sig0.items()}
            tp["signature_bands_hz"] = signature_bands(sig_hi, sig0, md["sensors"], f"S{tp['span_index'] + 1}",
                                                       1.0 / float(np.median(np.diff(t_hi))),
                                                       NOISE_STD["guideway_accel"] * noise_scale)
        if effect == "ambient_excitation":
            names = [k for k in md["sensors"] if md["sensors"][k]["topic"].startswith("/testline/guideway")]
            d, a = _ambient_response(rng, st.modal, spans, [gsens[k] for k in names], t_hi.size, 1e-3,
                                     tp["rms_mps2"])
            for j, k in enumerate(names):
                sig_hi[k] = sig_hi[k] + (d[:, j] if k.endswith("D") else a[:, j])
        t = t_hi[1::2]
        sig = {}
        for k, y in sig_hi.items():
            gname = TOPIC_GROUP[md["sensors"][k]["topic"]]
            y = _aa_decimate(y, variant)
            sig[k] = y + _noise(rng, y.size, NOISE_STD[gname] * noise_scale, colour)
        if effect == "sensor_error":
            ref = 0.010 if tp["channel"].endswith("G") else 0.0
            _apply_sensor_fault(sig, tp["channel"], tp, t, ref)
        pos_t = t[::5]
        pos = np.interp(pos_t, res.time_s, res.position_m) + rng.normal(0, 1e-3, pos_t.size)
        spd = np.interp(pos_t, res.time_s, res.speed_mps)
        passes.append(recording_from_arrays(md, {k: (t, y) for k, y in sig.items()}, (pos_t, pos, spd),
                                            source=f"{case_id}/pass_{v:g}"))
    ambient, _ = _ambient_recording(rng, seed, case_id, md_amb, spans, cfg_true, effect, tp, variant)
    truth = {"effect": effect, "category": CATEGORY.get(effect) if effect else None, "params": tp,
             "design_error": derr, "location": _truth_location(effect, tp), "irregularity": irr_info}
    return Case(case_id, effect, float(params.get("magnitude", 0.0)), truth, ambient, passes, split, variant)


def _truth_location(effect, tp) -> dict | None:
    if effect in ("girder_stiffness_loss", "girder_attachment"):
        i = tp["span_index"]
        x = i * L_SPAN + tp.get("x_rel_m", 0.5 * L_SPAN)
        return {"position_m": x, "span": f"S{i + 1}"}
    if effect == "bearing_stiffness":
        i, e = tp["span_index"], tp["end"]
        return {"position_m": (i + e) * L_SPAN, "span": f"S{i + 1}"}
    if effect == "sensor_error":
        return {"channel": tp["channel"]}
    if effect == "suspension_cubic":
        return {"place": "vehicle"}
    return None


TUNE_VARIANT = {"n_el": 24, "noise_colour": "white", "aa": ("butter", 0.4), "dt_s": 5e-4}
HELDOUT_VARIANT = {"n_el": 32, "noise_colour": "pink", "aa": ("cheby", 0.36), "dt_s": 4e-4,
                   "extra_lag_s": 3e-4, "noise_scale": 1.5}
BLIND_VARIANT = {"n_el": 40, "noise_colour": "white", "aa": ("cheby", 0.42), "dt_s": 3e-4,
                 "extra_lag_s": 6e-4, "noise_scale": 1.25}
VARIANTS = {"tune": TUNE_VARIANT, "heldout": HELDOUT_VARIANT, "blind": BLIND_VARIANT}


# per split: what the cases vary (the "blind" split was written in session 6 BEFORE any result on it
# was seen and is never used for tuning: other seeds, speeds, mesh, step, anti-alias filter, noise
# level, controller lag, irregularity PSDs, locations and magnitudes)
SPLITS = {
    "tune": dict(seed=1000, speeds=(22.0, 30.0), loss_spans=(0, 2), losses=(0.2, 0.35),
                 bearing_ends=((0, 1), (2, 0)), factors=(0.02, 0.1), ambient=(0.02, 0.05, 0.1),
                 sensors=("G2A", "M1A", "G3Q", "M8G"), scales=(1.35, 0.6), lags=(0.004, 0.008),
                 bends=(6.0, 9.0), attachments=((38.0, 1), (55.0, 0)), headrooms=(1.2, 1.4, 1.7),
                 bend2=12.0, lag2=0.006, bearing2=((1, 1), 0.3), attachment2=(70.0, 2, 0.65),
                 cubics=(0.5, 1.0)),
    "heldout": dict(seed=5000, speeds=(26.0, 34.0), loss_spans=(1, 2), losses=(0.2, 0.35),
                    bearing_ends=((1, 0), (2, 1)), factors=(0.02, 0.1), ambient=(0.02, 0.05, 0.1),
                    sensors=("G1A", "M8A", "G2Q", "M1G"), scales=(1.35, 0.6), lags=(0.004, 0.008),
                    bends=(6.0, 9.0), attachments=((38.0, 1), (55.0, 0)), headrooms=(1.25, 1.5, 1.8),
                    bend2=12.0, lag2=0.006, bearing2=((0, 0), 0.3), attachment2=(70.0, 0, 0.65),
                    cubics=(0.4, 0.8)),
    "blind": dict(seed=9000, speeds=(24.0, 32.0), loss_spans=(0, 1), losses=(0.25, 0.4),
                  bearing_ends=((0, 0), (1, 1)), factors=(0.05, 0.15), ambient=(0.03, 0.06, 0.12),
                  sensors=("G3A", "M1A", "G1Q", "M8G"), scales=(1.3, 0.7), lags=(0.005, 0.01),
                  bends=(7.0, 10.0), attachments=((45.0, 2), (60.0, 1)), headrooms=(1.1, 1.3, 1.6),
                  bend2=13.0, lag2=0.007, bearing2=((2, 1), 0.3), attachment2=(85.0, 0, 0.3),
                  cubics=(0.6, 1.2)),
}


def case_specs(split: str = "tune") -> list[dict]:
    """The benchmark list: every catalogue effect at several magnitudes/locations, clean and
    out-of-catalogue cases. ``split`` "tune" (used while developing), "heldout" (not tuned on at
    first; inspected in session 5, see the issue notes) or "blind" (never tuned on: other seeds,
    speeds, mesh, noise, anti-alias filter, controller lag, PSDs, locations and magnitudes)."""
    P = SPLITS[split]
    base_seed = P["seed"]
    # held-out speeds differ from the tuning speeds and reach above them (34 m/s needs the
    # reconstruction's one-sample-step gap bridging, irregularity/profile.py)
    speeds = P["speeds"]
    specs = []

    def add(effect, params):
        specs.append({"effect": effect, "params": params, "seed": base_seed + len(specs), "speeds": speeds})
    for loss in P["losses"]:
        for i in P["loss_spans"]:
            add("girder_stiffness_loss", {"span_index": i, "loss": loss, "magnitude": loss})
    for f in P["factors"]:
        for i, e in P["bearing_ends"]:
            add("bearing_stiffness", {"span_index": i, "end": e, "factor": f, "magnitude": 1 - f})
    for lv in P["ambient"]:
        add("ambient_excitation", {"rms_mps2": lv, "magnitude": lv})
    ch = P["sensors"]
    s_hi, s_lo = P["scales"]
    add("sensor_error", {"channel": ch[0], "kind": "scale", "value": s_hi, "magnitude": round(s_hi - 1, 6)})
    add("sensor_error", {"channel": ch[1], "kind": "scale", "value": s_lo, "magnitude": round(1 - s_lo, 6)})
    add("sensor_error", {"channel": ch[2], "kind": "offset", "value": 0.05, "magnitude": 0.05})
    add("sensor_error", {"channel": ch[3], "kind": "drift", "value": 2e-5, "magnitude": 2e-5})
    add("sensor_error", {"channel": ch[0], "kind": "dropout", "start_frac": 0.5, "len_frac": 0.2, "magnitude": 0.2})
    for lag in P["lags"]:
        add("control_delay", {"lag_s": lag, "magnitude": lag})
    for fb in P["bends"]:
        add("carbody_flexibility", {"bend_hz": fb, "magnitude": fb})
    for k in range(6):
        add(None, {"magnitude": 0.0})
    for fa, i in P["attachments"]:
        add("girder_attachment", {"span_index": i, "x_rel_m": 0.4 * L_SPAN, "freq_hz": fa,
                                  "mass_ratio": 0.03, "magnitude": fa})
    for hr in P["headrooms"]:
        add("magnet_nonlinearity", {"headroom": hr, "magnitude": 1.0 / hr})
    # second batch (session 4: >= 40 cases per split; appended so earlier cases keep their seeds)
    for k in range(4):
        add(None, {"magnitude": 0.0})
    add("carbody_flexibility", {"bend_hz": P["bend2"], "magnitude": P["bend2"]})
    add("control_delay", {"lag_s": P["lag2"], "magnitude": P["lag2"]})
    (i, e), f = P["bearing2"]
    add("bearing_stiffness", {"span_index": i, "end": e, "factor": f, "magnitude": round(1 - f, 6)})
    add("sensor_error", {"channel": "G2D", "kind": "drift", "value": 1e-5, "magnitude": 1e-5})
    fa, i, xr = P["attachment2"]
    add("girder_attachment", {"span_index": i, "x_rel_m": xr * L_SPAN, "freq_hz": fa, "mass_ratio": 0.03,
                              "magnitude": fa})
    # third batch: out-of-catalogue cubic stiffening of the secondary air springs (cubic force =
    # cubic_ratio x the linear spring force at the linear truth's largest deflection); appended so
    # earlier cases keep their seeds
    for cr in P["cubics"]:
        add("suspension_cubic", {"cubic_ratio": cr, "magnitude": cr})
    return specs


def build_case(i: int, spec: dict, split: str) -> Case:
    variant = VARIANTS[split]
    return make_case(f"{split}-{i:02d}-{spec['effect'] or 'clean'}", spec["effect"], spec["params"],
                     seed=spec["seed"], speeds=spec["speeds"], split=split, variant=variant)


# ------------------------------------------------------------------------------------------
def write_recording_bag(rec: Recording, path, block_s: float = 0.1) -> None:
    """Write a Recording as a contract bag (MCAP) with the project's BagWriter."""
    from maglev_ros.bag_writer import BagWriter
    from maglev_ros.sensor_block import Block
    from maglev_ros.discrepancy.recording import GROUP_UNIT, TOPIC_GROUP
    topic_of = {g: t for t, g in TOPIC_GROUP.items()}
    by_topic: dict = {}
    for n, ch in rec.channels.items():
        by_topic.setdefault(topic_of[ch.group], []).append(ch)
    with BagWriter(path, dict(rec.metadata)) as w:
        streams = []
        for topic, chans in by_topic.items():
            t = chans[0].time_s
            data = np.stack([c.values for c in chans], axis=1)
            streams.append((topic, t, data, tuple(c.name for c in chans), tuple(GROUP_UNIT[c.group] for c in chans),
                            chans[0].sample_rate_hz))
        if rec.position_time_s is not None:
            pt = rec.position_time_s
            streams.append(("/testline/vehicle/position", pt, np.stack([rec.position_m, rec.speed_mps], axis=1),
                            ("position_m", "speed_mps"), ("m", "m/s"), float(1.0 / np.median(np.diff(pt)))))
        blocks = []
        for topic, t, data, names, units, fs in streams:
            nb = max(1, int(round(block_s * fs)))
            for a in range(0, t.size, nb):
                blocks.append((int(round(t[a] * 1e9)), topic,
                               Block(int(round(t[a] * 1e9)), "testline", fs, names, units,
                                     np.ascontiguousarray(data[a:a + nb], dtype=np.float32))))
        blocks.sort(key=lambda b: b[0])
        for _, topic, b in blocks:
            w.write_block(topic, b)


def write_case_bags(case: Case, directory) -> tuple[str, list[str]]:
    from pathlib import Path
    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    amb = d / "ambient"
    write_recording_bag(case.ambient, amb)
    ps = []
    for k, p in enumerate(case.passes):
        q = d / f"pass{k + 1}"
        write_recording_bag(p, q)
        ps.append(str(q))
    return str(amb), ps


def report_science(rep: dict) -> dict:
    """What a diagnosis report found, without what names the recordings (bag path vs live stream):
    the live and the offline diagnosis of the same recordings must give exactly this."""
    import json
    return {"fit_before": rep["fit_before"]["nrmse"], "fit_after": rep["fit_after"]["nrmse"],
            "missing": [(m["effect"], json.dumps(m["parameters"], sort_keys=True, default=float))
                        for m in rep["missing_physics"]],
            "parameters": rep["updated_parameters"],
            "mismatches": [(m["channels"], m["frequency_hz"], m["severity"]) for m in rep["mismatches"]]}
