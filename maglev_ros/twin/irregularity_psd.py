"""Reference vertical irregularity PSDs and random profile sampling (no rclpy).

Units and conventions (read this before mixing spectra from papers)
-------------------------------------------------------------------
Every spectrum here is ONE-SIDED (defined for Omega >= 0 only, so the variance is the
integral over [0, inf)) and is a function of the SPATIAL ANGULAR frequency Omega in rad/m
(wavelength lambda = 2 pi / Omega). ``ProfilePsd(omega)`` returns S(Omega) in m^2/(rad/m).

Conversions (all provided as methods / functions):

* per cycle:   f = Omega / (2 pi) [cycle/m];   S_f(f) = 2 pi S(2 pi f)        [m^2/(cycle/m)]
* in time at constant speed v:  omega = v Omega [rad/s];  S_t(omega) = S(omega / v) / v
  [m^2/(rad/s)];  in Hz: S_hz(f_hz) = 2 pi S(2 pi f_hz / v) / v                [m^2/Hz]
* two-sided:   S_two(Omega) = S(|Omega|) / 2 on (-inf, inf).

Reference forms (constants cited in each factory):

* US FRA track classes 1-6, vertical profile, in the metric form of Chinese railway literature
  (Zhai, *Vehicle-Track Coupled Dynamics: Theory and Applications*, Springer 2020, chapter on
  track irregularity spectra, "American track spectra"; the class constants go back to the FRA
  track-geometry studies, see also Garg & Dukkipati, *Dynamics of Railway Vehicle Systems*,
  1984). The numbers below were typed from that table; check them against the printed source
  before quoting them in a report:
  S(Omega) = k A_v Omega_c^2 / (Omega^2 (Omega^2 + Omega_c^2)), k = 0.25, Omega_c = 0.8245
  rad/m for every class, A_v [cm^2 rad/m] = 1.2107, 1.0181, 0.6816, 0.5376, 0.2095, 0.0339 for
  classes 1..6 (class 6 is the best track). The book's S is in cm^2/(rad/m); here A_v is
  converted to m^2 rad/m (x 1e-4) so S is in m^2/(rad/m).
* German high-speed track, low / high disturbance (same source, sec. "German track spectra"):
  S(Omega) = A_v Omega_c^2 / ((Omega^2 + Omega_r^2)(Omega^2 + Omega_c^2)),
  Omega_c = 0.8246, Omega_r = 0.0206 rad/m, A_v = 4.032e-7 (low) / 1.080e-6 (high) m rad.
* Maglev guideway (paper 001, sec. 4.2, "PSD of guideway irregularity"): the paper adopts the
  FRA elevation form for the F-rails with its own roughness A1 = 1.5e-7 m^2 rad/m over
  Omega = 0.314 .. 6.28 rad/m (wavelengths 1 .. 20 m). The cutoff frequency and any k factor
  were lost from the paper text; we take Omega_c = 0.8245 rad/m (the FRA value of the form it
  cites) and k = 1 (the paper quotes A1 already in SI units, no class table). Choice written
  here so it can be revisited when the original equation is available.

Random profiles use the spectral representation (sum of cosines with deterministic
amplitudes and independent uniform random phases), evaluated with one inverse real FFT per
sample; each frequency bin carries the EXACT integral of S over the part of the bin inside
the requested band (analytic antiderivatives), so the ensemble variance equals the band
variance of the target PSD. Written by hand (numpy FFT) because no maintained library ships
these track spectra or this band-exact sampler.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from maglev_ros.errors import UserError

__all__ = [
    "ProfilePsd",
    "fra_class",
    "german_high_speed",
    "maglev_guideway_001",
    "psd_by_name",
    "band_from_wavelengths",
    "random_profile",
    "per_cycle_to_per_rad",
    "per_rad_to_per_cycle",
    "FRA_VERTICAL_AV_CM2_RAD_PER_M",
    "FRA_VERTICAL_OMEGA_C_RAD_PER_M",
    "FRA_K",
    "MAGLEV_001_BAND_RAD_PER_M",
]

#: FRA vertical-profile roughness A_v per track class 1..6 in cm^2 rad/m (Zhai 2020, US spectra).
FRA_VERTICAL_AV_CM2_RAD_PER_M = {1: 1.2107, 2: 1.0181, 3: 0.6816, 4: 0.5376, 5: 0.2095, 6: 0.0339}
#: FRA vertical-profile cutoff, identical for all classes [rad/m].
FRA_VERTICAL_OMEGA_C_RAD_PER_M = 0.8245
#: Factor k of the metric FRA form used in Chinese literature (Zhai 2020).
FRA_K = 0.25
#: German high-speed spectra constants (Zhai 2020).
GERMAN_OMEGA_C_RAD_PER_M = 0.8246
GERMAN_OMEGA_R_RAD_PER_M = 0.0206
GERMAN_AV_M_RAD = {"low": 4.032e-7, "high": 1.080e-6}
#: Paper 001 band and roughness of the guideway elevation irregularity.
MAGLEV_001_BAND_RAD_PER_M = (0.314, 6.28)
MAGLEV_001_A_M2_RAD_PER_M = 1.5e-7

_CM2_TO_M2 = 1.0e-4


@dataclass(frozen=True)
class ProfilePsd:
    """One-sided vertical profile PSD S(Omega) [m^2/(rad/m)], Omega in rad/m.

    form "fra":    S = k A Omega_c^2 / (Omega^2 (Omega^2 + Omega_c^2))
    form "german": S = k A Omega_c^2 / ((Omega^2 + Omega_r^2)(Omega^2 + Omega_c^2))
    ``roughness_m2_rad_per_m`` is A in m^2 rad/m (= m rad).
    """

    name: str
    form: str
    roughness_m2_rad_per_m: float
    cutoff_rad_per_m: float
    low_cutoff_rad_per_m: float = 0.0
    k: float = 1.0
    source: str = ""

    def __post_init__(self) -> None:
        if self.form not in ("fra", "german"):
            raise UserError(f"ProfilePsd.form: expected 'fra' or 'german', got {self.form!r}")
        if not (self.roughness_m2_rad_per_m > 0 and self.cutoff_rad_per_m > 0 and self.k > 0):
            raise UserError(f"ProfilePsd {self.name!r}: roughness, cutoff and k must be > 0")
        if self.form == "german" and not (0 < self.low_cutoff_rad_per_m < self.cutoff_rad_per_m):
            raise UserError(
                f"ProfilePsd {self.name!r}: german form needs 0 < low_cutoff_rad_per_m < cutoff_rad_per_m"
            )

    # ---------------------------------------------------------------- values
    def __call__(self, omega_rad_per_m: Any) -> np.ndarray:
        """S(Omega) in m^2/(rad/m); Omega in rad/m (> 0 for the FRA form, which diverges at 0)."""
        om = np.asarray(omega_rad_per_m, dtype=float)
        a = self.k * self.roughness_m2_rad_per_m
        wc2 = self.cutoff_rad_per_m**2
        if self.form == "fra":
            with np.errstate(divide="ignore"):
                return a * wc2 / (om**2 * (om**2 + wc2))
        wr2 = self.low_cutoff_rad_per_m**2
        return a * wc2 / ((om**2 + wr2) * (om**2 + wc2))

    def per_cycle(self, f_cycle_per_m: Any) -> np.ndarray:
        """S_f(f) in m^2/(cycle/m) at f in cycle/m: 2 pi S(2 pi f)."""
        f = np.asarray(f_cycle_per_m, dtype=float)
        return 2.0 * np.pi * self(2.0 * np.pi * f)

    def temporal(self, omega_rad_per_s: Any, speed_mps: float) -> np.ndarray:
        """Time-domain PSD seen at constant speed: S(omega/v)/v in m^2/(rad/s)."""
        if speed_mps <= 0:
            raise UserError(f"ProfilePsd.temporal: speed_mps must be > 0, got {speed_mps}")
        om = np.asarray(omega_rad_per_s, dtype=float)
        return self(om / speed_mps) / speed_mps

    def temporal_hz(self, freq_hz: Any, speed_mps: float) -> np.ndarray:
        """Time-domain PSD in m^2/Hz at temporal frequency f [Hz]: 2 pi S(2 pi f / v) / v."""
        f = np.asarray(freq_hz, dtype=float)
        return 2.0 * np.pi * self.temporal(2.0 * np.pi * f, speed_mps)

    def antiderivative(self, omega_rad_per_m: Any) -> np.ndarray:
        """Analytic F(Omega) with dF/dOmega = S(Omega) (partial fractions), in m^2."""
        om = np.asarray(omega_rad_per_m, dtype=float)
        a = self.k * self.roughness_m2_rad_per_m
        wc = self.cutoff_rad_per_m
        if self.form == "fra":
            # S = a [1/Omega^2 - 1/(Omega^2 + wc^2)]
            with np.errstate(divide="ignore"):
                return a * (-1.0 / om - np.arctan(om / wc) / wc)
        wr = self.low_cutoff_rad_per_m
        coef = a * wc**2 / (wc**2 - wr**2)
        # S = coef [1/(Omega^2 + wr^2) - 1/(Omega^2 + wc^2)]
        return coef * (np.arctan(om / wr) / wr - np.arctan(om / wc) / wc)

    def band_variance(self, lo_rad_per_m: Any, hi_rad_per_m: Any) -> np.ndarray:
        """Integral of S over [lo, hi] (vectorised, m^2); 0 where hi <= lo."""
        lo = np.asarray(lo_rad_per_m, dtype=float)
        hi = np.asarray(hi_rad_per_m, dtype=float)
        if self.form == "fra" and np.any(lo[hi > lo] <= 0):
            raise UserError(f"ProfilePsd {self.name!r}: FRA form has infinite variance down to Omega = 0; "
                            "give a band with lower edge > 0 rad/m")
        hi_c = np.maximum(hi, lo)
        return np.where(hi > lo, self.antiderivative(hi_c) - self.antiderivative(lo), 0.0)

    def rms_m(self, band_rad_per_m: tuple[float, float]) -> float:
        """RMS profile height [m] of the part of the spectrum inside the band (rad/m)."""
        lo, hi = _check_band(band_rad_per_m, "band_rad_per_m")
        return float(np.sqrt(self.band_variance(lo, hi)))

    def to_dict(self) -> dict:
        return {
            "name": self.name,
            "form": self.form,
            "roughness_m2_rad_per_m": self.roughness_m2_rad_per_m,
            "cutoff_rad_per_m": self.cutoff_rad_per_m,
            "low_cutoff_rad_per_m": self.low_cutoff_rad_per_m,
            "k": self.k,
            "units": "one-sided m^2/(rad/m), Omega in rad/m",
            "source": self.source,
        }


# -------------------------------------------------------------------- factories
def fra_class(track_class: int) -> ProfilePsd:
    """US FRA vertical profile, track class 1..6 (Zhai 2020 metric form, k = 0.25)."""
    if track_class not in FRA_VERTICAL_AV_CM2_RAD_PER_M:
        raise UserError(f"fra_class: track_class must be one of 1..6, got {track_class!r}")
    return ProfilePsd(
        name=f"fra{track_class}",
        form="fra",
        roughness_m2_rad_per_m=FRA_VERTICAL_AV_CM2_RAD_PER_M[track_class] * _CM2_TO_M2,
        cutoff_rad_per_m=FRA_VERTICAL_OMEGA_C_RAD_PER_M,
        k=FRA_K,
        source="US FRA vertical profile class %d; Zhai, Vehicle-Track Coupled Dynamics (2020), "
        "A_v in cm^2 rad/m converted x1e-4, k=0.25, Omega_c=0.8245 rad/m" % track_class,
    )


def german_high_speed(disturbance: str = "low") -> ProfilePsd:
    """German high-speed vertical profile, 'low' or 'high' disturbance (Zhai 2020)."""
    if disturbance not in GERMAN_AV_M_RAD:
        raise UserError(f"german_high_speed: disturbance must be 'low' or 'high', got {disturbance!r}")
    return ProfilePsd(
        name=f"german_{disturbance}",
        form="german",
        roughness_m2_rad_per_m=GERMAN_AV_M_RAD[disturbance],
        cutoff_rad_per_m=GERMAN_OMEGA_C_RAD_PER_M,
        low_cutoff_rad_per_m=GERMAN_OMEGA_R_RAD_PER_M,
        k=1.0,
        source="German high-speed %s-disturbance vertical spectrum; Zhai (2020); "
        "Omega_c=0.8246, Omega_r=0.0206 rad/m" % disturbance,
    )


def maglev_guideway_001() -> ProfilePsd:
    """Guideway elevation irregularity of paper 001 (FRA form, A1 = 1.5e-7 m^2 rad/m).

    Use with the paper's band ``MAGLEV_001_BAND_RAD_PER_M`` = (0.314, 6.28) rad/m. Omega_c =
    0.8245 rad/m and k = 1 are our choices (lost from the paper text), see module docstring.
    """
    return ProfilePsd(
        name="maglev_001",
        form="fra",
        roughness_m2_rad_per_m=MAGLEV_001_A_M2_RAD_PER_M,
        cutoff_rad_per_m=FRA_VERTICAL_OMEGA_C_RAD_PER_M,
        k=1.0,
        source="paper 001 sec. 4.2: FRA elevation form, A1=1.5e-7 m^2 rad/m, band 0.314-6.28 rad/m; "
        "Omega_c=0.8245 rad/m and k=1 assumed",
    )


def psd_by_name(name: str) -> ProfilePsd:
    """'fra1'..'fra6', 'german_low', 'german_high', 'maglev_001'."""
    key = str(name).strip().lower()
    if key.startswith("fra") and key[3:].isdigit():
        return fra_class(int(key[3:]))
    if key in ("german_low", "german_high"):
        return german_high_speed(key.split("_")[1])
    if key == "maglev_001":
        return maglev_guideway_001()
    raise UserError(
        f"irregularity PSD name: expected fra1..fra6, german_low, german_high or maglev_001, got {name!r}"
    )


# -------------------------------------------------------------------- conversions
def band_from_wavelengths(min_wavelength_m: float, max_wavelength_m: float) -> tuple[float, float]:
    """(lo, hi) in rad/m for wavelengths lambda in [min, max] m: lo = 2pi/max, hi = 2pi/min."""
    if not (0 < min_wavelength_m < max_wavelength_m):
        raise UserError(
            f"wavelength band: expected 0 < min_wavelength_m < max_wavelength_m, got "
            f"({min_wavelength_m}, {max_wavelength_m})"
        )
    return 2.0 * np.pi / max_wavelength_m, 2.0 * np.pi / min_wavelength_m


def per_rad_to_per_cycle(omega_rad_per_m: Any, s_m2_per_rad_per_m: Any) -> tuple[np.ndarray, np.ndarray]:
    """(f [cycle/m], S_f [m^2/(cycle/m)]) from (Omega [rad/m], S [m^2/(rad/m)])."""
    om = np.asarray(omega_rad_per_m, dtype=float)
    return om / (2.0 * np.pi), 2.0 * np.pi * np.asarray(s_m2_per_rad_per_m, dtype=float)


def per_cycle_to_per_rad(f_cycle_per_m: Any, s_m2_per_cycle_per_m: Any) -> tuple[np.ndarray, np.ndarray]:
    """(Omega [rad/m], S [m^2/(rad/m)]) from (f [cycle/m], S_f [m^2/(cycle/m)])."""
    f = np.asarray(f_cycle_per_m, dtype=float)
    return 2.0 * np.pi * f, np.asarray(s_m2_per_cycle_per_m, dtype=float) / (2.0 * np.pi)


def _check_band(band: Any, what: str) -> tuple[float, float]:
    try:
        lo, hi = (float(band[0]), float(band[1]))
    except Exception as exc:  # noqa: BLE001 - user input of any shape
        raise UserError(f"{what}: expected a pair (low, high), got {band!r}") from exc
    if not (0 < lo < hi and np.isfinite(hi)):
        raise UserError(f"{what}: expected 0 < low < high, got ({lo}, {hi})")
    return lo, hi


# -------------------------------------------------------------------- sampling
def _bin_weights(psd: ProfilePsd, n_fft: int, spacing_m: float, lo: float, hi: float):
    """Bin centres k dOmega (k = 1 .. n_fft/2 - 1) and the exact band integral of S per bin."""
    d_omega = 2.0 * np.pi / (n_fft * spacing_m)
    k = np.arange(1, n_fft // 2)
    centre = k * d_omega
    left = np.maximum(centre - 0.5 * d_omega, lo)
    right = np.minimum(centre + 0.5 * d_omega, hi)
    keep = right > left
    weight = np.zeros_like(centre)
    weight[keep] = psd.band_variance(left[keep], right[keep])
    return k, centre, weight


def random_profile(
    psd: ProfilePsd,
    length_m: float,
    spacing_m: float,
    wavelength_band_m: tuple[float, float] = (1.0, 20.0),
    rng: np.random.Generator | int | None = None,
    *,
    n_samples: int | None = None,
    start_m: float = 0.0,
    oversample: float = 4.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Random vertical profile(s) whose one-sided PSD is ``psd`` inside the wavelength band.

    Returns ``(x_m, r_m)``: x_m (n,) from ``start_m`` every ``spacing_m`` over ``length_m``;
    r_m (n,) for one sample, or (n_samples, n) when ``n_samples`` is given.

    r(x) = sum_k sqrt(2 W_k) cos(Omega_k (x - start) + phi_k), phi_k ~ U(0, 2 pi) independent,
    Omega_k = k dOmega on an FFT grid of period P >= max(length, oversample * max wavelength),
    W_k = integral of S over (bin k) intersected with the band, so that the ensemble variance is
    exactly the band variance integral (``psd.band_variance``). Profiles are zero-mean and
    periodic with period P (longer than the returned length).
    """
    lo, hi = band_from_wavelengths(*_check_band(wavelength_band_m, "wavelength_band_m"))
    if not (length_m > 0 and spacing_m > 0):
        raise UserError(f"random_profile: length_m and spacing_m must be > 0, got {length_m}, {spacing_m}")
    if hi >= np.pi / spacing_m:
        raise UserError(
            f"random_profile: spacing_m={spacing_m} cannot resolve the shortest wavelength "
            f"{2 * np.pi / hi:.4g} m (need spacing_m < min_wavelength/2, ideally < min_wavelength/10)"
        )
    if n_samples is not None and int(n_samples) < 1:
        raise UserError(f"random_profile: n_samples must be >= 1, got {n_samples}")
    gen = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
    n_x = int(np.floor(length_m / spacing_m + 1e-9)) + 1
    n_min = max(n_x, int(np.ceil(oversample * (2.0 * np.pi / lo) / spacing_m)))
    n_fft = 1 << int(np.ceil(np.log2(max(n_min, 16))))
    k, _centre, weight = _bin_weights(psd, n_fft, spacing_m, lo, hi)
    used = weight > 0
    k = k[used]
    amp = np.sqrt(2.0 * weight[used])
    x_m = start_m + spacing_m * np.arange(n_x)

    n_s = 1 if n_samples is None else int(n_samples)
    out = np.empty((n_s, n_x))
    # chunk so the complex spectrum stays below ~64 MB
    chunk = max(1, int(4_000_000 // (n_fft // 2 + 1)))
    for s0 in range(0, n_s, chunk):
        s1 = min(n_s, s0 + chunk)
        phase = gen.uniform(0.0, 2.0 * np.pi, size=(s1 - s0, k.size))
        spec = np.zeros((s1 - s0, n_fft // 2 + 1), dtype=complex)
        spec[:, k] = (0.5 * n_fft) * amp * np.exp(1j * phase)
        out[s0:s1] = np.fft.irfft(spec, n=n_fft, axis=1)[:, :n_x]
    return x_m, (out[0] if n_samples is None else out)
