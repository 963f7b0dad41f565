"""Rational track-irregularity spectra of the four processes (elevation, cross-level,
alignment, gauge), one-sided in the spatial angular frequency Omega [rad/m].

Every form is S(Omega) = c Omega^(2p) / prod_i (Omega^2 + a_i^2) with distinct poles a_i >= 0
and p in {0, 1}; its variance over a band has a closed form by partial fractions,
Omega^(2p) / prod (Omega^2 + a_i^2) = sum_i r_i / (Omega^2 + a_i^2), r_i = (-a_i^2)^p /
prod_{j != i} (a_j^2 - a_i^2), with antiderivatives atan(Omega / a) / a (a > 0) or -1/Omega
(a = 0). Named forms (constants: Zhai, *Vehicle-Track Coupled Dynamics*, Springer 2020, track
spectra chapter; the same forms as ``twin/irregularity_psd.py``, which has only the vertical
profile):

* ``fra_profile``      k A Oc^2 / (O^2 (O^2 + Oc^2))                      elevation, alignment [m]
* ``fra_crosslevel``   4 k A Oc^2 / ((O^2 + Oc^2)(O^2 + Os^2))             cross-level height
                       difference, gauge [m] (US FRA)
* ``german_profile``   k A Oc^2 / ((O^2 + Or^2)(O^2 + Oc^2))               elevation, alignment [m]
* ``german_crosslevel``  k A Oc^2 O^2 / ((O^2 + Or^2)(O^2 + Oc^2)(O^2 + Os^2))  gauge [m]; with
                       ``per_half_gauge_squared`` A / b^2: the cross-level ANGLE [rad] (German)

A in m^2 rad/m (= m rad), cutoffs Oc, Or, Os in rad/m, k a dimensionless factor (0.25 in the
metric FRA tables, 1 for the German ones). Written by hand: no maintained library ships these
spectra (the same reasoning as ``twin/irregularity_psd.py``).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from maglev_ros.errors import UserError
from maglev_ros.system3d.scenario_values import number

FORMS = ("fra_profile", "fra_crosslevel", "german_profile", "german_crosslevel")
_NEEDS = {"fra_profile": ("omega_c",), "fra_crosslevel": ("omega_c", "omega_s"),
          "german_profile": ("omega_c", "omega_r"), "german_crosslevel": ("omega_c", "omega_r", "omega_s")}


@dataclass(frozen=True)
class RationalPsd:
    """One-sided S(Omega) = coefficient Omega^(2 numerator_power) / prod(Omega^2 + pole^2)."""

    name: str
    coefficient: float
    numerator_power: int
    poles_rad_per_m: tuple[float, ...]
    unit: str = "m"                  # unit of the process: S in unit^2/(rad/m)
    source: str = ""

    def __post_init__(self) -> None:
        poles = np.asarray(self.poles_rad_per_m, float)
        if not (self.coefficient > 0 and np.all(poles >= 0) and poles.size >= 1):
            raise UserError(f"irregularity PSD {self.name!r}: coefficient > 0 and poles >= 0 expected")
        if self.numerator_power not in (0, 1) or self.numerator_power >= poles.size:
            raise UserError(f"irregularity PSD {self.name!r}: numerator power must be 0 or 1 and below the pole count")
        if np.unique(poles).size != poles.size:
            raise UserError(f"irregularity PSD {self.name!r}: poles must be distinct, got {self.poles_rad_per_m}")
        if self.numerator_power == 1 and np.any(poles == 0):
            raise UserError(f"irregularity PSD {self.name!r}: a pole at 0 with Omega^2 in the numerator cancels")

    def __call__(self, omega_rad_per_m: Any) -> np.ndarray:
        om2 = np.asarray(omega_rad_per_m, float) ** 2
        den = np.ones_like(om2)
        for a in self.poles_rad_per_m:
            den = den * (om2 + a * a)
        with np.errstate(divide="ignore"):
            return self.coefficient * om2**self.numerator_power / den

    def _residues(self) -> np.ndarray:
        a2 = np.asarray(self.poles_rad_per_m, float) ** 2
        r = np.empty_like(a2)
        for i in range(a2.size):
            others = np.delete(a2, i)
            r[i] = (-a2[i]) ** self.numerator_power / np.prod(others - a2[i])
        return r

    def antiderivative(self, omega_rad_per_m: Any) -> np.ndarray:
        """F with dF/dOmega = S (partial fractions), in unit^2."""
        om = np.asarray(omega_rad_per_m, float)
        out = np.zeros_like(om)
        for a, r in zip(self.poles_rad_per_m, self._residues()):
            with np.errstate(divide="ignore"):
                out = out + r * (np.arctan(om / a) / a if a > 0 else -1.0 / om)
        return self.coefficient * out

    def band_variance(self, lo_rad_per_m: Any, hi_rad_per_m: Any) -> np.ndarray:
        """Integral of S over [lo, hi] (vectorised); 0 where hi <= lo."""
        lo = np.asarray(lo_rad_per_m, float)
        hi = np.asarray(hi_rad_per_m, float)
        if 0.0 in self.poles_rad_per_m and self.numerator_power == 0 and np.any(lo[hi > lo] <= 0):
            raise UserError(f"irregularity PSD {self.name!r}: infinite variance down to Omega = 0; give a band with lower edge > 0")
        hi_c = np.maximum(hi, lo)
        return np.where(hi > lo, self.antiderivative(hi_c) - self.antiderivative(lo), 0.0)

    def to_dict(self) -> dict:
        return {"name": self.name, "coefficient": self.coefficient, "numerator_power": self.numerator_power,
                "poles_rad_per_m": list(self.poles_rad_per_m), "unit": self.unit,
                "units": f"one-sided {self.unit}^2/(rad/m), Omega in rad/m", "source": self.source}


def rational_psd(name: str, form: str, roughness_m2_rad_per_m: float, cutoffs_rad_per_m: dict, k: float = 1.0,
                 half_gauge_m: float | None = None, unit: str = "m", source: str = "") -> RationalPsd:
    """One of ``FORMS`` with its roughness A, cutoffs {omega_c, omega_r, omega_s} and factor k;
    ``half_gauge_m`` b (German cross-level angle: A / b^2, unit rad)."""
    if form not in FORMS:
        raise UserError(f"irregularity {name}.form: expected one of {', '.join(FORMS)}, got {form!r}")
    missing = [c for c in _NEEDS[form] if c not in cutoffs_rad_per_m]
    if missing:
        raise UserError(f"irregularity {name}: form {form} needs cutoffs {', '.join(missing)} (rad/m)")
    oc = float(cutoffs_rad_per_m["omega_c"])
    coef = k * roughness_m2_rad_per_m * oc * oc
    if half_gauge_m is not None:
        coef /= half_gauge_m**2
    if form == "fra_profile":
        return RationalPsd(name, coef, 0, (0.0, oc), unit, source)
    if form == "fra_crosslevel":
        return RationalPsd(name, 4.0 * coef, 0, (oc, float(cutoffs_rad_per_m["omega_s"])), unit, source)
    if form == "german_profile":
        return RationalPsd(name, coef, 0, (float(cutoffs_rad_per_m["omega_r"]), oc), unit, source)
    return RationalPsd(name, coef, 1, (float(cutoffs_rad_per_m["omega_r"]), oc,
                                       float(cutoffs_rad_per_m["omega_s"])), unit, source)


def psd_from_dict(name: str, d: dict, half_gauge_m: float, where: str) -> RationalPsd:
    """From a plain mapping {form, roughness_m2_rad_per_m, k, omega_c, omega_r, omega_s,
    per_half_gauge_squared, unit, source}."""
    if not isinstance(d, dict):
        raise UserError(f"{where}: expected a mapping, got {d!r}")
    form = str(d.get("form", ""))
    cut = {c: number(d, c, where, positive=True) for c in ("omega_c", "omega_r", "omega_s") if c in d}
    per_b = bool(d.get("per_half_gauge_squared", False))
    unit = str(d.get("unit", "rad" if per_b else "m"))
    return rational_psd(name, form, number(d, "roughness_m2_rad_per_m", where, positive=True), cut,
                        k=number(d, "k", where, default=1.0, positive=True),
                        half_gauge_m=half_gauge_m if per_b else None, unit=unit, source=str(d.get("source", "")))
