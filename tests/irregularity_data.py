"""Synthetic magnet recordings from a KNOWN guideway irregularity, for the irregularity tests.

Independent of maglev_ros: the profile is drawn from a reference PSD typed in here from the
literature, the magnets move by a simple model that is not the project's twin:

* the magnet follows the rail through a 2nd-order levitation-control transfer function
  ``wn^2 / (s^2 + 2 zeta wn s + wn^2)`` (wn = 2 pi * 6 Hz, zeta = 0.7 by default), plus
* a low-frequency car-body motion (a few sinusoids, 0.4-1.5 Hz, mm amplitudes) that the magnet
  shares.

The accelerometer measures the exact second derivative (from the ODE state) plus white noise,
1/f noise and an optional bias; the gap sensor measures ``g0 + r(x_m) - z_m`` plus white noise;
the position channel (100 Hz) gives the reference point position and speed. Everything is SI.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from types import SimpleNamespace

import numpy as np
from scipy import signal

# German high-speed track spectrum, low-disturbance form (one-sided, m^2/(rad/m)), as given in
# e.g. Zhai, Vehicle-Track Coupled Dynamics (2020): S(W) = A Wc^2 / ((W^2 + Wr^2)(W^2 + Wc^2)).
GER_LOW_A = 4.032e-7       # m^2 rad/m
GER_WC = 0.8246            # rad/m
GER_WR = 0.0206            # rad/m


def german_low_psd_rad(omega_rad_m: np.ndarray) -> np.ndarray:
    w = np.asarray(omega_rad_m, float)
    return GER_LOW_A * GER_WC ** 2 / ((w ** 2 + GER_WR ** 2) * (w ** 2 + GER_WC ** 2))


def random_profile(length_m: float, dx_m: float, rng: np.random.Generator, scale: float = 1.0,
                   psd=german_low_psd_rad, min_wavelength_m: float = 0.5,
                   max_wavelength_m: float = 400.0) -> tuple[np.ndarray, np.ndarray]:
    """Gaussian profile with one-sided PSD ``scale^2 * psd(Omega)`` (Omega in rad/m): complex
    Gaussian Fourier coefficients with E|c_k|^2 = 2 S_f(k) dk on the FFT grid (so amplitudes are
    Rayleigh, as for a true Gaussian process, not fixed)."""
    n = int(np.ceil(length_m / dx_m)) + 1
    nfft = int(2 ** np.ceil(np.log2(n)))
    k = np.fft.rfftfreq(nfft, dx_m)                      # cycles/m
    dk = k[1] - k[0]
    om = 2 * np.pi * k
    s_cyc = np.zeros_like(k)
    sel = (k >= 1.0 / max_wavelength_m) & (k <= 1.0 / min_wavelength_m)
    s_cyc[sel] = 2 * np.pi * psd(om[sel]) * scale ** 2  # m^2/(cycle/m), one-sided
    amp = np.sqrt(2 * s_cyc * dk)
    c = (rng.standard_normal(k.size) + 1j * rng.standard_normal(k.size)) / np.sqrt(2)
    spec = amp * c * nfft / 2
    r = np.fft.irfft(spec, nfft)[:n]
    return np.arange(n) * dx_m, r


def add_features(x: np.ndarray, r: np.ndarray, features) -> np.ndarray:
    """Discrete features: (kind, x0_m, length_m, height_m); 'bump' = raised cosine,
    'step' = smooth step over length."""
    r = r.copy()
    for kind, x0, length, h in features:
        u = (x - x0) / length
        if kind == "bump":
            m = (u >= 0) & (u <= 1)
            r[m] += h * 0.5 * (1 - np.cos(2 * np.pi * u[m]))
        elif kind == "step":
            r += h * np.clip(0.5 * (1 - np.cos(np.pi * np.clip(u, 0, 1))), 0, 1)
        else:
            raise ValueError(kind)
    return r


def speed_profile(kind: str, t: np.ndarray, v_mps: float) -> np.ndarray:
    """'constant', 'uneven' (+-25 % slow sinusoidal variation), 'stop' (brake to 0, wait 3 s,
    accelerate again at 1 m/s^2)."""
    if kind == "constant":
        return np.full_like(t, v_mps)
    if kind == "uneven":
        return v_mps * (1 + 0.25 * np.sin(2 * np.pi * t / 23.0 + 0.7))
    if kind == "stop":
        T = t[-1]
        tb = 0.45 * T                       # start braking
        dec = 1.0
        t0 = tb + v_mps / dec               # standstill
        t1 = t0 + 3.0                        # start accelerating
        v = np.full_like(t, v_mps)
        m = (t >= tb) & (t < t0)
        v[m] = v_mps - dec * (t[m] - tb)
        v[(t >= t0) & (t < t1)] = 0.0
        m = t >= t1
        v[m] = np.minimum(v_mps, dec * (t[m] - t1))
        return v
    raise ValueError(kind)


def colored_noise(n: int, fs: float, rms_white: float, corner_hz: float,
                  rng: np.random.Generator, f_min_hz: float = 0.005) -> np.ndarray:
    """White noise of ``rms_white`` over 0..fs/2 plus 1/f noise whose PSD equals the white
    level at ``corner_hz`` (PSD = S_w (1 + corner/f) for f > f_min)."""
    nfft = int(2 ** np.ceil(np.log2(n)))
    f = np.fft.rfftfreq(nfft, 1 / fs)
    sw = rms_white ** 2 / (fs / 2)
    psd = sw * (1 + corner_hz / np.maximum(f, f_min_hz))
    psd[0] = 0
    df = f[1]
    amp = np.sqrt(psd * df / 2) * nfft
    z = amp * (rng.standard_normal(f.size) + 1j * rng.standard_normal(f.size)) / np.sqrt(2)
    x = np.fft.irfft(z, nfft)[:n]
    return x


@dataclass
class Recording:
    accel: SimpleNamespace
    gap: SimpleNamespace
    position: SimpleNamespace
    magnet_offsets_m: list
    nominal_gap_m: float
    truth_x_m: np.ndarray
    truth_r_m: np.ndarray
    t_s: np.ndarray
    x_ref_m: np.ndarray
    speed_mps: np.ndarray
    deflection: np.ndarray | None = None     # (n, n_mag) rail deflection under each magnet
    info: dict = field(default_factory=dict)

    def truth_at(self, x_m: np.ndarray) -> np.ndarray:
        return np.interp(x_m, self.truth_x_m, self.truth_r_m)


def _cd(t, data, channels, units, fs):
    data = np.asarray(data, float)
    if data.ndim == 1:
        data = data[:, None]
    return SimpleNamespace(time_s=np.asarray(t, float), data=data, channels=tuple(channels),
                           units=tuple(units), sample_rate_hz=float(fs))


def make_recording(speed_kmh: float = 30.0, seed: int = 0, speed_kind: str = "constant",
                   duration_s: float | None = None, length_m: float = 500.0,
                   fs_hz: float = 1000.0, fs_pos_hz: float = 100.0,
                   magnet_offsets_m=(0.0, -1.548, -3.096), nominal_gap_m: float = 0.010,
                   accel_noise_rms: float = 0.02, flicker_corner_hz: float = 0.5,
                   bias_mps2=0.0, gap_noise_m: float = 5e-6, profile_scale: float = 1.0,
                   features=(("bump", 180.0, 8.0, 2e-3), ("step", 320.0, 12.0, -1.5e-3)),
                   lev_hz: float = 6.0, lev_zeta: float = 0.7, body: bool = True,
                   deflection_amp_m: float = 0.0) -> Recording:
    """A pass over ``length_m`` of line at ``speed_kmh`` (see speed_profile for kinds).

    ``bias_mps2`` may be a scalar or one value per magnet. ``deflection_amp_m`` > 0 adds a
    quasi-static girder deflection under each magnet (sagging -amp * sin^2 over 12.384 m spans)
    to the rail position the magnet sees; ``Recording.deflection`` holds it.
    """
    rng = np.random.default_rng(seed)
    v = speed_kmh / 3.6
    x_start = 40.0
    if duration_s is None:
        duration_s = length_m / v + (12.0 if speed_kind == "stop" else 0.0)
        if speed_kind == "stop":
            duration_s += v / 1.0
    n = int(duration_s * fs_hz)
    t = np.arange(n) / fs_hz
    spd = speed_profile(speed_kind, t, v)
    xref = x_start + np.concatenate([[0.0], np.cumsum(0.5 * (spd[1:] + spd[:-1]) / fs_hz)])
    total = xref[-1] + 60.0
    xr, r = random_profile(total + 20.0, 0.02, rng, scale=profile_scale)
    r = add_features(xr, r, [(k, x0 + x_start, L, h) for k, x0, L, h in features])

    # car body motion shared by all magnets (plus a small pitch-like phase difference)
    nb = 3
    bf = rng.uniform(0.4, 1.5, nb)
    ba = rng.uniform(0.5e-3, 2e-3, nb) if body else np.zeros(nb)
    bp = rng.uniform(0, 2 * np.pi, nb)

    wn = 2 * np.pi * lev_hz
    sysl = signal.StateSpace([[0, 1], [-wn ** 2, -2 * lev_zeta * wn]], [[0], [wn ** 2]],
                             [[1, 0], [0, 1]], [[0], [0]])
    biases = np.broadcast_to(np.asarray(bias_mps2, float), (len(magnet_offsets_m),))
    acc, gap, defl = [], [], []
    for k, off in enumerate(magnet_offsets_m):
        xm = xref + off
        rm = np.interp(xm, xr, r)
        if deflection_amp_m > 0:
            w = -deflection_amp_m * np.sin(np.pi * (xm % 12.384) / 12.384) ** 2
        else:
            w = np.zeros_like(xm)
        rail = rm + w
        _, y, _ = signal.lsim(sysl, rail, t, X0=[rail[0], 0.0])
        z, zd = y[:, 0], y[:, 1]
        zdd = wn ** 2 * (rail - z) - 2 * lev_zeta * wn * zd
        ph = 2 * np.pi * bf * (off / 20.0)
        zb = sum(ba[i] * np.sin(2 * np.pi * bf[i] * t + bp[i] + ph[i]) for i in range(nb))
        zbdd = sum(-ba[i] * (2 * np.pi * bf[i]) ** 2 * np.sin(2 * np.pi * bf[i] * t + bp[i] + ph[i])
                   for i in range(nb))
        zm = z + zb
        am = zdd + zbdd
        am_meas = am + colored_noise(n, fs_hz, accel_noise_rms, flicker_corner_hz, rng) + biases[k]
        g_meas = nominal_gap_m + rail - zm + gap_noise_m * rng.standard_normal(n)
        acc.append(am_meas)
        gap.append(g_meas)
        defl.append(w)
    step = int(round(fs_hz / fs_pos_hz))
    tp = t[::step]
    names = [f"M{k + 1}" for k in range(len(magnet_offsets_m))]
    return Recording(
        accel=_cd(t, np.column_stack(acc), [f"{m}A" for m in names], ["m/s^2"] * len(names), fs_hz),
        gap=_cd(t, np.column_stack(gap), [f"{m}G" for m in names], ["m"] * len(names), fs_hz),
        position=_cd(tp, np.column_stack([xref[::step], spd[::step]]), ["position_m", "speed_mps"],
                     ["m", "m/s"], fs_pos_hz),
        magnet_offsets_m=list(magnet_offsets_m), nominal_gap_m=nominal_gap_m,
        truth_x_m=xr, truth_r_m=r, t_s=t, x_ref_m=xref, speed_mps=spd,
        deflection=np.column_stack(defl) if deflection_amp_m > 0 else None,
        info={"speed_mps": v, "seed": seed, "speed_kind": speed_kind})


def bandpass_truth(x_grid_m: np.ndarray, truth: np.ndarray, min_wavelength_m: float,
                   max_wavelength_m: float, order: int = 4) -> np.ndarray:
    """The reference: the true profile on the result grid, band-passed with the filter the result
    states (zero-phase Butterworth band-pass of the given order in wavenumber)."""
    dx = x_grid_m[1] - x_grid_m[0]
    sos = signal.butter(order, [1.0 / max_wavelength_m, 1.0 / min_wavelength_m], btype="band",
                        fs=1.0 / dx, output="sos")
    return signal.sosfiltfilt(sos, truth)
