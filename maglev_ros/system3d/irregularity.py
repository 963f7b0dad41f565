"""Four guideway irregularity processes mapped to the left/right rails, their spectra and samples.

Processes (independent, zero-mean, stationary along x; spectra in ``irregularity_spectra``):
elevation e [m], cross-level c, alignment a [m], gauge g [m]. The cross-level is either an
angle theta [rad] (``cross_level_unit: rad``, German form with A / b^2) or a height difference
Delta = z_L - z_R [m] (``m``, FRA form). With b the half distance between the rails (left
rail at +b, y positive left, z up, as ``girder_rails``):

    z_L = e + b theta   (= e + Delta / 2)        y_L = a + g / 2
    z_R = e - b theta   (= e - Delta / 2)        y_R = a - g / 2

and back e = (z_L + z_R)/2, theta = (z_L - z_R)/(2 b), a = (y_L + y_R)/2, g = y_L - y_R.
``mapping`` is that 4x4 matrix T (rails (z_L, z_R, y_L, y_R) = T (e, c, a, g)); the rails'
cross-spectral matrix is T diag(S_e, S_c, S_a, S_g) T^T and the pseudo-excitation of process k
(for the PEM) is the rail vector T[:, k] sqrt(S_k). Samples use the band-exact spectral sampler
of ``twin/irregularity_psd.random_profile`` with independent phases per process.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from maglev_ros.errors import UserError
from maglev_ros.system3d.irregularity_spectra import RationalPsd, psd_from_dict
from maglev_ros.system3d.scenario_values import load_yaml, number, plain, require
from maglev_ros.twin.irregularity_psd import band_from_wavelengths, random_profile

PROCESSES = ("elevation", "cross_level", "alignment", "gauge")
RAILS = ("z_left", "z_right", "y_left", "y_right")


@dataclass(frozen=True)
class IrregularitySample:
    """Sampled processes and the rail irregularities they make, on one x grid (m)."""

    x_m: np.ndarray
    processes: dict[str, np.ndarray]    # PROCESSES -> (n,) or (n_samples, n)
    rails: dict[str, np.ndarray]        # RAILS -> same shape


@dataclass(frozen=True)
class TrackIrregularity:
    """The four processes, the half rail distance b and the wavelength band they are used in."""

    psds: dict[str, RationalPsd]
    half_gauge_m: float
    wavelength_band_m: tuple[float, float]
    cross_level_unit: str = "rad"

    def __post_init__(self) -> None:
        if set(self.psds) != set(PROCESSES):
            raise UserError(f"irregularity processes: expected exactly {', '.join(PROCESSES)}, got {sorted(self.psds)}")
        if not self.half_gauge_m > 0:
            raise UserError(f"irregularity half_gauge_m: expected > 0, got {self.half_gauge_m}")
        if self.cross_level_unit not in ("rad", "m"):
            raise UserError(f"irregularity cross_level unit: expected 'rad' (angle) or 'm' (height difference), got {self.cross_level_unit!r}")
        band_from_wavelengths(*self.wavelength_band_m)

    @property
    def band_rad_per_m(self) -> tuple[float, float]:
        return band_from_wavelengths(*self.wavelength_band_m)

    # -------------------------------------------------------------- mapping
    @property
    def mapping(self) -> np.ndarray:
        """T (4x4): (z_L, z_R, y_L, y_R) = T (e, c, a, g)."""
        half_c = self.half_gauge_m if self.cross_level_unit == "rad" else 0.5
        return np.array([[1.0, half_c, 0.0, 0.0],
                         [1.0, -half_c, 0.0, 0.0],
                         [0.0, 0.0, 1.0, 0.5],
                         [0.0, 0.0, 1.0, -0.5]])

    def rails_from_processes(self, processes: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        p = np.stack([np.asarray(processes[k], float) for k in PROCESSES])
        r = np.tensordot(self.mapping, p, axes=1)
        return dict(zip(RAILS, r))

    def processes_from_rails(self, rails: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        r = np.stack([np.asarray(rails[k], float) for k in RAILS])
        p = np.tensordot(np.linalg.inv(self.mapping), r, axes=1)
        return dict(zip(PROCESSES, p))

    # -------------------------------------------------------------- spectra
    def process_psd(self, omega_rad_per_m) -> np.ndarray:
        """(n, 4) one-sided PSDs of the processes at Omega (rad/m), in PROCESSES order."""
        om = np.atleast_1d(np.asarray(omega_rad_per_m, float))
        return np.stack([self.psds[k](om) for k in PROCESSES], axis=-1)

    def rail_cross_spectrum(self, omega_rad_per_m) -> np.ndarray:
        """(n, 4, 4) one-sided cross-spectral matrix of (z_L, z_R, y_L, y_R) [m^2/(rad/m)]."""
        s = self.process_psd(omega_rad_per_m)
        t = self.mapping
        return np.einsum("ik,nk,jk->nij", t, s, t)

    def pseudo_excitation(self, omega_rad_per_m) -> np.ndarray:
        """(n, 4 processes, 4 rails): rail amplitudes T[:, k] sqrt(S_k(Omega)) of each process's
        pseudo-excitation; the PEM adds the response power of the four (they are independent)."""
        s = self.process_psd(omega_rad_per_m)
        return np.sqrt(s)[:, :, None] * self.mapping.T[None, :, :]

    def band_variance(self) -> dict[str, float]:
        """Variance of each process inside the band (unit^2)."""
        lo, hi = self.band_rad_per_m
        return {k: float(self.psds[k].band_variance(lo, hi)) for k in PROCESSES}

    # -------------------------------------------------------------- samples
    def sample(self, length_m: float, spacing_m: float, rng=None, n_samples: int | None = None,
               start_m: float = 0.0) -> IrregularitySample:
        """Random processes with the stated PSDs in the band (independent phases), and the rails."""
        gen = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
        procs = {}
        x = None
        for k in PROCESSES:
            x, procs[k] = random_profile(self.psds[k], length_m, spacing_m, self.wavelength_band_m, gen,
                                         n_samples=n_samples, start_m=start_m)
        return IrregularitySample(x, procs, self.rails_from_processes(procs))

    def to_dict(self) -> dict:
        return {"half_gauge_m": self.half_gauge_m, "wavelength_band_m": list(self.wavelength_band_m),
                "cross_level_unit": self.cross_level_unit,
                "processes": {k: self.psds[k].to_dict() for k in PROCESSES},
                "band_rms": {k: float(np.sqrt(v)) for k, v in self.band_variance().items()}}

    @classmethod
    def from_dict(cls, raw: dict, where: str = "irregularity") -> "TrackIrregularity":
        d = plain(raw, where)
        b = number(d, "half_gauge_m", where, positive=True)
        band = require(d, "wavelength_band_m", where)
        if not (isinstance(band, list) and len(band) == 2):
            raise UserError(f"{where}.wavelength_band_m: expected [min, max] in m, got {band!r}")
        procs = require(d, "processes", where)
        if not isinstance(procs, dict):
            raise UserError(f"{where}.processes: expected a mapping of {', '.join(PROCESSES)}")
        missing = [k for k in PROCESSES if k not in procs]
        if missing:
            raise UserError(f"{where}.processes: missing {', '.join(missing)}")
        psds = {k: psd_from_dict(k, procs[k], b, f"{where}.processes.{k}") for k in PROCESSES}
        return cls(psds, b, (float(band[0]), float(band[1])), psds["cross_level"].unit)


def load_irregularity(path: str | Path) -> TrackIrregularity:
    """The ``irregularity`` mapping of a scenario file."""
    raw = load_yaml(path)
    return TrackIrregularity.from_dict(require(raw, "irregularity", str(path)), f"{path}: irregularity")
