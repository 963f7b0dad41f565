"""Test-signal generators for the modal-identification tests (known truth).

A guideway span is modelled by its modes: simply supported beam-like shapes sin(k pi x / L)
sampled at 5 sections x 3 sensors (left vertical, right vertical, lateral) = 15 channels.
The modal parameters follow the paper's identified guideway (23.49, 41.76, 43.77, 79.69 Hz)
plus higher modes. Each modal coordinate obeys q'' + 2 zeta w q' + w^2 q = p(t) and is simulated
exactly in discrete time (zero-order-hold discretization of the SDOF state space, so the discrete
poles are exactly exp(lambda dt) of the continuous truth). Accelerations are the outputs.

Randomized variants (``seed``) perturb frequencies (+-1 %), damping ratios and the shapes, so tests
do not hinge on one particular structure.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.signal import butter, cont2discrete, lfilter, ss2tf

SPAN_M = 24.768
SECTION_X_M = SPAN_M * np.arange(1, 6) / 6.0
HALF_WIDTH_M = 1.4


@dataclass
class ModalModel:
    frequency_hz: np.ndarray            # (m,)
    damping_ratio: np.ndarray           # (m,)
    shapes: np.ndarray                  # (n_channels, m) real
    channels: tuple
    kinds: tuple                        # per mode: ("vertical", k) / ("torsion", k) / ("lateral", k)
    shape_perturbation: np.ndarray      # (n_channels, m) additive perturbation used

    def shape_at(self, x_m: float, y_m: float = 0.0) -> np.ndarray:
        """Vertical modal displacement at deck position (x along the span, y lateral offset)."""
        out = np.zeros(self.frequency_hz.size)
        if not 0.0 <= x_m <= SPAN_M:
            return out
        for r, (kind, k) in enumerate(self.kinds):
            s = np.sin(k * np.pi * x_m / SPAN_M)
            if kind == "vertical":
                out[r] = s
            elif kind == "torsion":
                out[r] = s * y_m / HALF_WIDTH_M
            else:
                out[r] = 0.0
        return out


NOMINAL = [  # (frequency_hz, damping_ratio, kind, half-waves)
    (23.49, 0.015, "vertical", 1),
    (41.76, 0.012, "lateral", 1),
    (43.77, 0.018, "torsion", 1),
    (79.69, 0.020, "vertical", 2),
    (104.3, 0.016, "torsion", 2),
    (131.8, 0.022, "lateral", 2),
    (176.0, 0.020, "vertical", 3),
]


def guideway_model(seed: int | None = None) -> ModalModel:
    """Nominal model (seed None) or a randomized variant."""
    rng = np.random.default_rng(seed)
    freqs, zetas, kinds, cols = [], [], [], []
    channels = []
    for j, x in enumerate(SECTION_X_M):
        channels += [f"G{j + 1}LV", f"G{j + 1}RV", f"G{j + 1}LA"]
    for f, z, kind, k in NOMINAL:
        if seed is not None:
            f = f * (1.0 + rng.uniform(-0.01, 0.01))
            z = rng.uniform(0.008, 0.025)
        s = np.sin(k * np.pi * SECTION_X_M / SPAN_M)
        col = np.zeros(15)
        if kind == "vertical":
            col[0::3], col[1::3], col[2::3] = s, s, 0.05 * s
        elif kind == "torsion":
            col[0::3], col[1::3], col[2::3] = s, -s, 0.3 * s
        else:
            col[0::3], col[1::3], col[2::3] = 0.1 * s, -0.1 * s, s
        freqs.append(f)
        zetas.append(z)
        kinds.append((kind, k))
        cols.append(col)
    shapes = np.array(cols).T
    pert = np.zeros_like(shapes)
    if seed is not None:
        pert = 0.08 * rng.standard_normal(shapes.shape) * np.abs(shapes).max(axis=0)
    shapes = shapes + pert
    shapes = shapes / np.abs(shapes).max(axis=0)
    return ModalModel(np.array(freqs), np.array(zetas), shapes, tuple(channels), tuple(kinds), pert)


def _modal_filters(model: ModalModel, fs_hz: float):
    """Discrete (ZOH) transfer functions modal force -> modal acceleration, per mode."""
    out = []
    dt = 1.0 / fs_hz
    for f, z in zip(model.frequency_hz, model.damping_ratio):
        w = 2 * np.pi * f
        a = np.array([[0.0, 1.0], [-w * w, -2 * z * w]])
        b = np.array([[0.0], [1.0]])
        c = np.array([[-w * w, -2 * z * w]])     # acceleration = p - 2 z w q' - w^2 q
        d = np.array([[1.0]])
        ad, bd, cd, dd, _ = cont2discrete((a, b, c, d), dt, method="zoh")
        num, den = ss2tf(ad, bd, cd, dd)
        out.append((num[0], den))
    return out


def modal_response(model: ModalModel, modal_force: np.ndarray, fs_hz: float) -> np.ndarray:
    """Channel accelerations (n, n_channels) for modal forces (n, m)."""
    q = np.empty_like(modal_force)
    for r, (num, den) in enumerate(_modal_filters(model, fs_hz)):
        q[:, r] = lfilter(num, den, modal_force[:, r])
    return q @ model.shapes.T


def add_sensor_noise(y: np.ndarray, noise_frac: float, rng) -> np.ndarray:
    """White noise with std = noise_frac * (std of each channel's signal)."""
    return y + noise_frac * y.std(axis=0) * rng.standard_normal(y.shape)


def simulate_ambient(model: ModalModel, fs_hz: float = 500.0, duration_s: float = 120.0,
                     noise_frac: float = 0.05, excitation: str = "white", seed: int = 0,
                     transient_s: float = 5.0) -> np.ndarray:
    """Ambient response to spatially white random forces at the 15 sensor DOFs.

    excitation "white": white forces; "filtered": forces low-passed (2nd-order Butterworth at
    0.36 fs, a well-damped coloured input) with an extra broad peak (4th-order band-pass
    30-60 Hz added), i.e. non-white ambient loading.
    """
    rng = np.random.default_rng(seed)
    n0 = int(round(transient_s * fs_hz))
    n = int(round(duration_s * fs_hz)) + n0
    f = rng.standard_normal((n, model.shapes.shape[0]))
    if excitation == "filtered":
        b, a = butter(2, 0.36 * fs_hz, fs=fs_hz)
        bb, ab = butter(2, [30.0, 60.0], btype="bandpass", fs=fs_hz)
        f = lfilter(b, a, f, axis=0) + 0.7 * lfilter(bb, ab, rng.standard_normal(f.shape), axis=0)
    elif excitation != "white":
        raise ValueError(excitation)
    p = f @ model.shapes
    y = modal_response(model, p, fs_hz)[n0:]
    return add_sensor_noise(y, noise_frac, rng)


def simulate_pass(model: ModalModel, fs_hz: float = 500.0, speed_mps: float = 30.0,
                  axle_offsets_m=(0.0, -3.0, -6.0, -9.0, -12.0), lateral_offset_m: float = 0.35,
                  lead_s: float = 1.0, after_s: float = 6.0, noise_frac: float = 0.02,
                  ambient_frac: float = 0.0005, seed: int = 0):
    """A train of moving loads crossing the span, then free decay.

    Returns (accel (n, 15), time_s (n,), position_m (n,), exit_time_s): ``position_m`` is the
    reference (front) point; the last load leaves the span at ``exit_time_s``. A weak ambient
    excitation (``ambient_frac`` of the pass forces' rms) continues throughout. Sensor noise std =
    ``noise_frac`` x the channel std over the whole record.
    """
    rng = np.random.default_rng(seed)
    offs = np.asarray(axle_offsets_m, dtype=float)
    t_span = (SPAN_M - offs.min()) / speed_mps
    duration = lead_s + t_span + after_s
    n = int(round(duration * fs_hz))
    t = np.arange(n) / fs_hz
    pos = (t - lead_s) * speed_mps
    p = np.zeros((n, model.frequency_hz.size))
    # evaluate modal loads on a per-sample basis (vectorized over samples)
    for off in offs:
        x = pos + off
        on = (x >= 0) & (x <= SPAN_M)
        for r, (kind, k) in enumerate(model.kinds):
            s = np.sin(k * np.pi * x[on] / SPAN_M)
            if kind == "vertical":
                p[on, r] -= s
            elif kind == "torsion":
                p[on, r] -= s * lateral_offset_m / HALF_WIDTH_M
    # ride irregularity makes the loads fluctuate
    p *= 1.0 + 0.2 * rng.standard_normal((n, 1))
    rms = np.sqrt(np.mean(p[p != 0] ** 2)) if np.any(p) else 1.0
    p += ambient_frac * rms * (rng.standard_normal((n, model.shapes.shape[0])) @ model.shapes)
    y = modal_response(model, p, fs_hz)
    y = add_sensor_noise(y, noise_frac, rng)
    exit_time = lead_s + t_span
    return y, t, pos, exit_time


def assert_modes_match(result_modes, model: ModalModel, fmax_hz: float, fmin_hz: float = 5.0,
                       freq_tol: float = 0.002, damping_tol: float = 0.003, mac_min: float = 0.98,
                       which=None):
    """Match identified modes to the truth; returns dict of worst errors and the spurious list."""
    from maglev_ros.modal.stabilization import mac
    truth = [r for r in range(model.frequency_hz.size)
             if fmin_hz <= model.frequency_hz[r] <= fmax_hz and (which is None or r in which)]
    found = [m for m in result_modes if fmin_hz <= m.frequency_hz <= fmax_hz]
    used = set()
    worst = {"freq_rel": 0.0, "damping_abs": 0.0, "mac_min": 1.0, "missing": [], "spurious": []}
    for r in truth:
        f0 = model.frequency_hz[r]
        best, bd = None, np.inf
        for k, m in enumerate(found):
            if k in used:
                continue
            shape = np.array([m.mode_shape[c] for c in model.channels])
            d = abs(m.frequency_hz - f0) / f0 + (1.0 - mac(shape, model.shapes[:, r]))
            if d < bd:
                best, bd = k, d
        if best is None or abs(found[best].frequency_hz - f0) / f0 > 0.03:
            worst["missing"].append(float(f0))
            continue
        used.add(best)
        m = found[best]
        shape = np.array([m.mode_shape[c] for c in model.channels])
        worst["freq_rel"] = max(worst["freq_rel"], abs(m.frequency_hz - f0) / f0)
        worst["damping_abs"] = max(worst["damping_abs"], abs(m.damping_ratio - model.damping_ratio[r]))
        worst["mac_min"] = min(worst["mac_min"], mac(shape, model.shapes[:, r]))
    worst["spurious"] = [found[k].frequency_hz for k in range(len(found)) if k not in used]
    return worst


def simulate_drifting(model: ModalModel, fs_hz: float, duration_s: float, drift_to_hz: dict,
                      vanish_at_s: dict, noise_frac: float = 0.05, seed: int = 0,
                      segment_s: float = 2.0) -> np.ndarray:
    """Ambient response whose mode r drifts linearly from its frequency to ``drift_to_hz[r]``
    over the record and whose mode r' stops being excited at ``vanish_at_s[r']`` (its response
    then decays freely within a second). Piecewise-constant coefficients per ``segment_s``, the
    filter state carried across segments."""
    rng = np.random.default_rng(seed)
    n = int(round(duration_s * fs_hz))
    nseg = int(round(segment_s * fs_hz))
    f = rng.standard_normal((n, model.shapes.shape[0]))
    p = f @ model.shapes
    t = np.arange(n) / fs_hz
    for r, tv in vanish_at_s.items():
        p[t >= tv, r] = 0.0
    q = np.zeros_like(p)
    zis = [None] * model.frequency_hz.size
    for s0 in range(0, n, nseg):
        s1 = min(n, s0 + nseg)
        frac = (s0 + s1) / 2 / n
        freqs = model.frequency_hz.copy()
        for r, f_end in drift_to_hz.items():
            freqs[r] = model.frequency_hz[r] + frac * (f_end - model.frequency_hz[r])
        seg_model = ModalModel(freqs, model.damping_ratio, model.shapes, model.channels,
                               model.kinds, model.shape_perturbation)
        for r, (num, den) in enumerate(_modal_filters(seg_model, fs_hz)):
            zi = zis[r] if zis[r] is not None else np.zeros(max(len(num), len(den)) - 1)
            q[s0:s1, r], zis[r] = lfilter(num, den, p[s0:s1, r], zi=zi)
    y = q @ model.shapes.T
    return add_sensor_noise(y, noise_frac, rng)


def cramer_rao_std(model: ModalModel, fs_hz: float, duration_s: float, noise_frac: float = 0.05,
                   grid_hz: float = 0.05) -> tuple[np.ndarray, np.ndarray]:
    """Cramer-Rao lower bound of the modal estimates for records of :func:`simulate_ambient`
    (white excitation): (std of frequency / frequency, std of damping ratio) per mode.

    Whittle (asymptotic) Fisher information of the 15-channel Gaussian process,
    ``F_ij = sum over the N/2 Fourier frequencies of tr(S^-1 dS/d_i S^-1 dS/d_j)``, with S the
    exact cross-spectral matrix of the simulated structure (ZOH modal filters, the modal force
    covariance ``Phi^T Phi`` of the spatially white forces, white sensor noise of
    ``noise_frac`` x channel std). Unknowns: every frequency and damping ratio, plus one force
    scale per mode and the noise level (nuisance); the shapes are taken as known, which can only
    lower the bound. The sum is evaluated on a ``grid_hz`` grid (the integrand is smooth on the
    scale of the narrowest half-power bandwidth) and scaled to N/2 frequencies. For a single
    lightly damped mode it reduces to ``var(f)/f^2 = var(zeta) = zeta / (2 pi f T)``.
    """
    n = duration_s * fs_hz
    w = np.pi * np.arange(1, int(0.5 * fs_hz / grid_hz)) / (0.5 * fs_hz / grid_hz)
    m = model.frequency_hz.size
    l = model.shapes.shape[0]
    sp = model.shapes.T @ model.shapes

    def spectrum(freq, zeta, scale, noise_var):
        mm = ModalModel(freq, zeta, model.shapes, model.channels, model.kinds, model.shape_perturbation)
        h = np.array([_freqz(num, den, w) for num, den in _modal_filters(mm, fs_hz)]).T
        g = model.shapes[None] * (h * np.sqrt(scale))[:, None, :]            # (F, l, m)
        s = g @ sp @ g.conj().transpose(0, 2, 1)
        return s + np.diag(noise_var)[None]

    f0, z0, one = model.frequency_hz, model.damping_ratio, np.ones(m)
    s_sig = spectrum(f0, z0, one, np.zeros(l))
    noise_var = noise_frac ** 2 * np.real(np.einsum("fii->fi", s_sig)).mean(axis=0)
    s0 = s_sig + np.diag(noise_var)[None]
    derivs = []
    for r in range(m):
        for kind, eps in (("f", 1e-6), ("z", 1e-7), ("s", 1e-5)):
            args_p, args_m = [f0.copy(), z0.copy(), one.copy()], [f0.copy(), z0.copy(), one.copy()]
            k = "fzs".index(kind)
            if kind == "f":
                args_p[0][r] *= 1 + eps
                args_m[0][r] *= 1 - eps
            else:
                args_p[k][r] += eps
                args_m[k][r] -= eps
            derivs.append((spectrum(*args_p, noise_var) - spectrum(*args_m, noise_var)) / (2 * eps))
    derivs.append(np.broadcast_to(np.diag(noise_var)[None], s0.shape))    # d S / d log(noise)
    s_inv = np.linalg.inv(s0)
    a = np.array([s_inv @ d for d in derivs])                                  # (P, F, l, l)
    p = a.shape[0]
    flat = a.reshape(p, -1)
    flat_t = a.transpose(0, 1, 3, 2).reshape(p, -1)
    fim = np.real(flat @ flat_t.T) * (0.5 * n / w.size)
    cov = np.linalg.inv(fim)
    sf = np.sqrt(np.diag(cov)[0::3][:m])
    sz = np.sqrt(np.diag(cov)[1::3][:m])
    return sf, sz


def _freqz(num, den, w):
    z = np.exp(-1j * w)
    return np.polyval(num[::-1], z) / np.polyval(den[::-1], z)
