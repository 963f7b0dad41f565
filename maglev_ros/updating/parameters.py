"""Updating parameters: names, units, nominal values and physical ranges (parameter space).

Ranges are choices (000's Table 2 values were lost from the text): guideway E, rho, kb within
+-30 % of the design values (concrete scatter, reinforcement, bearing ageing), controller gains within
+-45 % of the design values; every updated value is clipped into these ranges. Internally the
optimisers work on log(p / p_nominal) (all parameters are positive scale-like quantities; ridges
such as E/rho are straight lines in log space).
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Mapping, Sequence

import numpy as np

from maglev_ros.errors import UserError

GUIDEWAY_PARAMS = ("youngs_modulus_pa", "density_kg_m3", "bearing_stiffness_n_per_m")
MAGNET_PARAMS = ("kp_a_per_m", "kv_a_s_per_m", "ka_a_s2_per_m")
UNITS = {"youngs_modulus_pa": "Pa", "density_kg_m3": "kg/m^3", "bearing_stiffness_n_per_m": "N/m",
         "kp_a_per_m": "A/m", "kv_a_s_per_m": "A s/m", "ka_a_s2_per_m": "A s^2/m",
         "static_current_a": "A"}
SYMBOLS = {"youngs_modulus_pa": "E", "density_kg_m3": "rho", "bearing_stiffness_n_per_m": "kb",
           "kp_a_per_m": "kp", "kv_a_s_per_m": "kv", "ka_a_s2_per_m": "ka", "static_current_a": "I0"}
GUIDEWAY_REL_RANGE = 0.30
MAGNET_REL_RANGE = 0.45


@dataclass(frozen=True)
class ParameterSpec:
    name: str
    unit: str
    nominal: float
    lower: float
    upper: float

    @property
    def symbol(self) -> str:
        return SYMBOLS.get(self.name, self.name)

    def to_dict(self) -> dict:
        return asdict(self)


class ParameterSpace:
    """An ordered set of positive parameters with bounds; maps values <-> log-ratio theta <-> unit cube."""

    def __init__(self, specs: Sequence[ParameterSpec]):
        if not specs:
            raise UserError("parameter space: expected at least one parameter")
        for s in specs:
            if not (0 < s.lower <= s.nominal <= s.upper) or not math.isfinite(s.upper):
                raise UserError(f"parameter {s.name}: expected 0 < lower <= nominal <= upper, got "
                                f"{s.lower}, {s.nominal}, {s.upper}")
        self.specs = tuple(specs)

    @classmethod
    def around(cls, nominal: Mapping[str, float], rel_range: float | Mapping[str, float]) -> "ParameterSpace":
        specs = []
        for name, v in nominal.items():
            rr = rel_range[name] if isinstance(rel_range, Mapping) else rel_range
            specs.append(ParameterSpec(name, UNITS.get(name, ""), float(v), float(v) * (1 - rr), float(v) * (1 + rr)))
        return cls(specs)

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(s.name for s in self.specs)

    @property
    def dim(self) -> int:
        return len(self.specs)

    @property
    def nominal(self) -> np.ndarray:
        return np.array([s.nominal for s in self.specs])

    @property
    def lower(self) -> np.ndarray:
        return np.array([s.lower for s in self.specs])

    @property
    def upper(self) -> np.ndarray:
        return np.array([s.upper for s in self.specs])

    @property
    def theta_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        return np.log(self.lower / self.nominal), np.log(self.upper / self.nominal)

    def to_theta(self, values) -> np.ndarray:
        return np.log(np.asarray(values, dtype=float) / self.nominal)

    def from_theta(self, theta) -> np.ndarray:
        return self.nominal * np.exp(np.asarray(theta, dtype=float))

    def from_unit(self, u) -> np.ndarray:
        lo, hi = self.theta_bounds
        return self.from_theta(lo + np.asarray(u, dtype=float) * (hi - lo))

    def clip(self, values) -> np.ndarray:
        return np.clip(np.asarray(values, dtype=float), self.lower, self.upper)

    def as_dict(self, values) -> dict[str, float]:
        return {n: float(v) for n, v in zip(self.names, np.asarray(values, dtype=float))}

    def to_dict(self) -> dict:
        return {"parameters": [s.to_dict() for s in self.specs]}


def guideway_space(config, rel_range: float = GUIDEWAY_REL_RANGE) -> ParameterSpace:
    g = config.guideway
    if math.isinf(g.bearing_stiffness_n_per_m):
        raise UserError("design.guideway.bearing_stiffness_n_per_m: updating needs a finite nominal bearing stiffness")
    return ParameterSpace.around({n: getattr(g, n) for n in GUIDEWAY_PARAMS}, rel_range)


def magnet_space(config, rel_range: float = MAGNET_REL_RANGE) -> ParameterSpace:
    lev = config.levitation
    for n in MAGNET_PARAMS:
        if not getattr(lev, n) > 0:
            raise UserError(f"design.levitation.{n}: updating needs a positive nominal gain, got {getattr(lev, n)}")
    return ParameterSpace.around({n: getattr(lev, n) for n in MAGNET_PARAMS}, rel_range)
