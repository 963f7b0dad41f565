"""Continuous 3D girder: space-frame FE model over shared-node spans, supports, damping, modes.

The girder is one straight line of ``span_lengths_m`` from ``start_m``; spans share their end
nodes (a continuous girder), each span has ``elements_per_span`` 12-DOF elements
(``girder_element``). Supports are data: at a node's x, each DOF (x, y, z, rx, ry, rz) is
restrained or carries a spring (N/m or N m/rad). The section can vary along the girder with a
parabolic haunch at given piers (the depth ratio h(x) scales each rigidity and mass by
h^exponent). Damping is data: Rayleigh C = a M + b K with a ratio on two modes or two
frequencies (or a, b given), modal damping C = M Phi diag(2 zeta w) Phi^T M, or none.
Matrices are on the free DOFs (restrained ones removed); ``free_dofs`` maps them to the full
node-major list (node k: 6k .. 6k + 5). Modes: ``scipy.linalg.eigh`` on (K, M), each mode
labelled by where its kinetic energy lies (vertical: w, theta_y; lateral: v, theta_z; torsion;
axial). Rail motion: ``girder_rails``.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.linalg import eigh

from maglev_ros.errors import UserError
from maglev_ros.system3d.girder_element import (DOF_NAMES, N_NODE_DOF, GirderSection,
                                                element_matrices)
from maglev_ros.system3d.scenario_values import load_yaml, number, plain, require

#: DOF groups of each kind of motion, by node DOF index.
MOTION_DOFS = {"axial": (0,), "lateral": (1, 5), "vertical": (2, 4), "torsion": (3,)}
_SECTION_KEYS = tuple(GirderSection.__dataclass_fields__)


@dataclass(frozen=True)
class Support:
    """A bearing at a node: restrained DOFs and springs on others (N/m, N m/rad)."""

    x_m: float
    restrained: tuple[str, ...] = ()
    springs: tuple[tuple[str, float], ...] = ()

    def __post_init__(self) -> None:
        where = f"girder support at x={self.x_m} m"
        names = list(self.restrained) + [k for k, _ in self.springs]
        for name in names:
            if name not in DOF_NAMES:
                raise UserError(f"{where}: unknown DOF {name!r}, expected one of {', '.join(DOF_NAMES)}")
        if len(set(names)) != len(names):
            raise UserError(f"{where}: a DOF is listed twice (restrained and/or spring): {names}")
        for name, k in self.springs:
            if not (np.isfinite(k) and k > 0):
                raise UserError(f"{where}: spring on {name!r} must be finite and > 0, got {k}")

    def to_dict(self) -> dict:
        return {"x_m": self.x_m, "restrained": list(self.restrained), "springs": dict(self.springs)}


@dataclass(frozen=True)
class Haunch:
    """Parabolic variation of the section near piers: h(x) = 1 + (r - 1)(1 - d/L_h)^2 for a
    distance d < L_h to the nearest pier in ``piers_x_m``, else 1; each quantity of the section
    (keys of ``GirderSection``) is scaled by h^exponent (missing exponent: 0, unchanged)."""

    piers_x_m: tuple[float, ...]
    length_m: float
    depth_ratio: float
    exponents: tuple[tuple[str, float], ...]

    def __post_init__(self) -> None:
        if not (self.length_m > 0 and self.depth_ratio > 0):
            raise UserError(f"girder haunch: length_m and depth_ratio must be > 0, got {self.length_m}, {self.depth_ratio}")
        for key, _ in self.exponents:
            if key not in _SECTION_KEYS:
                raise UserError(f"girder haunch.exponents: unknown key {key!r}, expected one of {', '.join(_SECTION_KEYS)}")

    def depth(self, x_m: np.ndarray) -> np.ndarray:
        x = np.asarray(x_m, float)
        d = np.min(np.abs(x[:, None] - np.asarray(self.piers_x_m, float)[None, :]), axis=1)
        s = np.clip(d / self.length_m, 0.0, 1.0)
        return 1.0 + (self.depth_ratio - 1.0) * (1.0 - s) ** 2

    def section_at(self, base: GirderSection, x_m: float) -> GirderSection:
        h = float(self.depth(np.array([x_m]))[0])
        exps = dict(self.exponents)
        return GirderSection(**{k: getattr(base, k) * h ** exps.get(k, 0.0) for k in _SECTION_KEYS})

    def to_dict(self) -> dict:
        return {"piers_x_m": list(self.piers_x_m), "length_m": self.length_m,
                "depth_ratio": self.depth_ratio, "exponents": dict(self.exponents)}


@dataclass(frozen=True)
class Damping:
    """kind 'rayleigh' (ratio on ``modes`` (1-based) or ``frequencies_hz``, or explicit
    ``alpha_per_s``/``beta_s``), 'modal' (one ratio on every mode) or 'none'."""

    kind: str = "rayleigh"
    ratio: float = 0.0
    modes: tuple[int, int] | None = None
    frequencies_hz: tuple[float, float] | None = None
    alpha_per_s: float | None = None
    beta_s: float | None = None

    def __post_init__(self) -> None:
        if self.kind not in ("rayleigh", "modal", "none"):
            raise UserError(f"girder damping.kind: expected rayleigh, modal or none, got {self.kind!r}")
        if self.kind == "rayleigh":
            explicit = self.alpha_per_s is not None or self.beta_s is not None
            given = sum(v is not None for v in (self.modes, self.frequencies_hz)) + explicit
            if given != 1:
                raise UserError("girder damping: rayleigh needs exactly one of modes, frequencies_hz or alpha_per_s/beta_s")
        if self.kind in ("rayleigh", "modal") and not 0 <= self.ratio < 1 and self.alpha_per_s is None:
            raise UserError(f"girder damping.ratio: expected 0 <= ratio < 1, got {self.ratio}")

    def to_dict(self) -> dict:
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in self.__dict__.items() if v is not None}


@dataclass(frozen=True)
class GirderSpec:
    """Everything that defines the girder (data, SI)."""

    name: str
    span_lengths_m: tuple[float, ...]
    elements_per_span: int
    section: GirderSection
    supports: tuple[Support, ...]
    damping: Damping = field(default_factory=lambda: Damping(kind="none"))
    haunch: Haunch | None = None
    start_m: float = 0.0

    def __post_init__(self) -> None:
        if not self.span_lengths_m or not all(L > 0 for L in self.span_lengths_m):
            raise UserError(f"girder {self.name!r} spans: expected lengths > 0 m, got {self.span_lengths_m}")
        if int(self.elements_per_span) < 1:
            raise UserError(f"girder {self.name!r} elements_per_span: expected >= 1, got {self.elements_per_span}")

    @property
    def length_m(self) -> float:
        return float(sum(self.span_lengths_m))

    @property
    def end_m(self) -> float:
        return self.start_m + self.length_m

    @property
    def support_x_m(self) -> np.ndarray:
        return self.start_m + np.concatenate([[0.0], np.cumsum(self.span_lengths_m)])

    def to_dict(self) -> dict:
        return {"name": self.name, "span_lengths_m": list(self.span_lengths_m),
                "elements_per_span": self.elements_per_span, "start_m": self.start_m,
                "section": self.section.to_dict(), "supports": [s.to_dict() for s in self.supports],
                "damping": self.damping.to_dict(),
                "haunch": None if self.haunch is None else self.haunch.to_dict()}

    # ------------------------------------------------------------------ data
    @classmethod
    def from_dict(cls, raw: dict, where: str = "girder") -> "GirderSpec":
        """From a (tagged or plain) mapping, see ``config/system3d/paper001_girder.yaml``."""
        d = plain(raw, where)
        spans = require(d, "spans_m", where)
        if not isinstance(spans, list) or not spans:
            raise UserError(f"{where}.spans_m: expected a list of span lengths in m, got {spans!r}")
        try:
            spans_t = tuple(float(s) for s in spans)
        except (TypeError, ValueError) as exc:
            raise UserError(f"{where}.spans_m: expected numbers, got {spans!r}") from exc
        section = section_from_dict(require(d, "section", where), f"{where}.section")
        sup_raw = require(d, "supports", where)
        if not isinstance(sup_raw, list):
            raise UserError(f"{where}.supports: expected a list, got {type(sup_raw).__name__}")
        start = number(d, "start_m", where, default=0.0)
        supports = []
        for i, s in enumerate(sup_raw):
            w = f"{where}.supports[{i}]"
            if not isinstance(s, dict):
                raise UserError(f"{w}: expected a mapping, got {s!r}")
            if "x_m" in s:
                x = number(s, "x_m", w)
            elif "at_support" in s:
                k = int(s["at_support"])
                if not 0 <= k <= len(spans_t):
                    raise UserError(f"{w}.at_support: expected 0..{len(spans_t)}, got {k}")
                x = start + float(sum(spans_t[:k]))
            else:
                raise UserError(f"{w}: missing key 'x_m' (or 'at_support', the support index 0..{len(spans_t)})")
            springs = s.get("springs") or {}
            if not isinstance(springs, dict):
                raise UserError(f"{w}.springs: expected a mapping DOF -> stiffness, got {springs!r}")
            supports.append(Support(x, tuple(str(r) for r in (s.get("restrained") or [])),
                                    tuple((str(k), float(v)) for k, v in springs.items())))
        damping = Damping(kind="none")
        if "damping" in d:
            dd = d["damping"]
            w = f"{where}.damping"
            damping = Damping(kind=str(dd.get("kind", "rayleigh")), ratio=float(dd.get("ratio", 0.0)),
                              modes=tuple(int(m) for m in dd["modes"]) if "modes" in dd else None,
                              frequencies_hz=tuple(float(f) for f in dd["frequencies_hz"]) if "frequencies_hz" in dd else None,
                              alpha_per_s=float(dd["alpha_per_s"]) if "alpha_per_s" in dd else None,
                              beta_s=float(dd["beta_s"]) if "beta_s" in dd else None)
            for key in ("modes", "frequencies_hz"):
                if getattr(damping, key) is not None and len(getattr(damping, key)) != 2:
                    raise UserError(f"{w}.{key}: expected two entries")
        haunch = None
        if d.get("haunch"):
            h = d["haunch"]
            w = f"{where}.haunch"
            haunch = Haunch(tuple(float(x) for x in require(h, "piers_x_m", w)), number(h, "length_m", w),
                            number(h, "depth_ratio", w),
                            tuple((str(k), float(v)) for k, v in (h.get("exponents") or {}).items()))
        return cls(name=str(d.get("name", "girder")), span_lengths_m=spans_t,
                   elements_per_span=int(number(d, "elements_per_span", where, default=20)),
                   section=section, supports=tuple(supports), damping=damping, haunch=haunch, start_m=start)


def section_from_dict(d: dict, where: str) -> GirderSection:
    """A section either as rigidities (the ``GirderSection`` keys) or as ``material``
    (youngs_modulus_pa, poisson_ratio or shear_modulus_pa, density_kg_m3) + ``geometry``
    (area_m2, iy_m4, iz_m4, torsion_constant_m4, polar_moment_m4 (default iy + iz)) +
    optional ``superimposed`` (mass_per_length_kg_m, polar_mass_kg_m) carried without stiffness."""
    if not isinstance(d, dict):
        raise UserError(f"{where}: expected a mapping, got {d!r}")
    if "material" not in d:
        return GirderSection(**{k: number(d, k, where, positive=True) for k in _SECTION_KEYS})
    mat, geo = d["material"], require(d, "geometry", where)
    e = number(mat, "youngs_modulus_pa", f"{where}.material", positive=True)
    if "shear_modulus_pa" in mat:
        g = number(mat, "shear_modulus_pa", f"{where}.material", positive=True)
    else:
        g = e / (2.0 * (1.0 + number(mat, "poisson_ratio", f"{where}.material")))
    rho = number(mat, "density_kg_m3", f"{where}.material", positive=True)
    w = f"{where}.geometry"
    a, iy, iz = (number(geo, k, w, positive=True) for k in ("area_m2", "iy_m4", "iz_m4"))
    j = number(geo, "torsion_constant_m4", w, positive=True)
    ip = number(geo, "polar_moment_m4", w, default=iy + iz, positive=True)
    extra = d.get("superimposed") or {}
    m_extra = number(extra, "mass_per_length_kg_m", f"{where}.superimposed", default=0.0)
    j_extra = number(extra, "polar_mass_kg_m", f"{where}.superimposed", default=0.0)
    return GirderSection(axial_rigidity_n=e * a, vertical_bending_rigidity_n_m2=e * iy,
                         lateral_bending_rigidity_n_m2=e * iz, torsional_rigidity_n_m2=g * j,
                         mass_per_length_kg_m=rho * a + m_extra, polar_mass_kg_m=rho * ip + j_extra)


def load_girder(path: str | Path) -> GirderSpec:
    """The girder of a scenario file (its ``girder`` mapping)."""
    raw = load_yaml(path)
    return GirderSpec.from_dict(require(raw, "girder", str(path)), f"{path}: girder")


# ---------------------------------------------------------------------- model
@dataclass(frozen=True)
class GirderModes:
    """Mass-normalised modes on the free DOFs, ascending; ``kind`` where the kinetic energy lies."""

    freq_hz: np.ndarray             # (n,)
    vectors: np.ndarray             # (n_free, n), Phi^T M Phi = I
    kind: tuple[str, ...]           # 'vertical' | 'lateral' | 'torsion' | 'axial'
    energy_fraction: np.ndarray     # (n, 4) in the order of MOTION_DOFS

    @property
    def omega_rad_s(self) -> np.ndarray:
        return 2.0 * np.pi * self.freq_hz

    def of_kind(self, kind: str) -> np.ndarray:
        """Indices of the modes of one kind, ascending in frequency."""
        if kind not in MOTION_DOFS:
            raise UserError(f"mode kind: expected one of {', '.join(MOTION_DOFS)}, got {kind!r}")
        return np.array([i for i, k in enumerate(self.kind) if k == kind], dtype=int)

    def to_dict(self) -> dict:
        return {"freq_hz": self.freq_hz.tolist(), "kind": list(self.kind),
                "energy_fraction": {k: self.energy_fraction[:, i].round(4).tolist()
                                    for i, k in enumerate(MOTION_DOFS)}}


@dataclass(frozen=True)
class Girder:
    """Assembled girder (free DOFs). Build with ``assemble_girder(spec)``."""

    spec: GirderSpec
    node_x_m: np.ndarray            # (n_nodes,)
    free_dofs: np.ndarray           # (n_free,) indices into the full node-major DOF list
    mass: np.ndarray                # (n_free, n_free)
    stiffness: np.ndarray
    damping: np.ndarray
    rayleigh_alpha_per_s: float | None
    rayleigh_beta_s: float | None

    @property
    def n_nodes(self) -> int:
        return int(self.node_x_m.size)

    @property
    def n_free(self) -> int:
        return int(self.free_dofs.size)

    @property
    def element_length_m(self) -> np.ndarray:
        return np.diff(self.node_x_m)

    def full_to_free(self) -> np.ndarray:
        """(6 n_nodes,) free index of each full DOF, -1 where restrained."""
        out = -np.ones(N_NODE_DOF * self.n_nodes, dtype=int)
        out[self.free_dofs] = np.arange(self.n_free)
        return out

    def node_at(self, x_m: float) -> int:
        """Index of the node at ``x_m`` (UserError if none within 1 mm)."""
        k = int(np.argmin(np.abs(self.node_x_m - x_m)))
        if abs(self.node_x_m[k] - x_m) > 1e-3:
            raise UserError(f"girder {self.spec.name!r}: no node at x={x_m} m (nearest {self.node_x_m[k]:.4g} m)")
        return k

    def dof(self, x_m: float, name: str) -> int:
        """Free index of DOF ``name`` of the node at ``x_m`` (UserError if restrained)."""
        if name not in DOF_NAMES:
            raise UserError(f"girder DOF: expected one of {', '.join(DOF_NAMES)}, got {name!r}")
        i = self.full_to_free()[N_NODE_DOF * self.node_at(x_m) + DOF_NAMES.index(name)]
        if i < 0:
            raise UserError(f"girder {self.spec.name!r}: DOF {name!r} at x={x_m} m is restrained")
        return int(i)

    def expand(self, u_free: np.ndarray) -> np.ndarray:
        """(n_nodes, 6) nodal values (restrained DOFs 0) of a free-DOF vector."""
        full = np.zeros(N_NODE_DOF * self.n_nodes)
        full[self.free_dofs] = np.asarray(u_free, float)
        return full.reshape(self.n_nodes, N_NODE_DOF)

    def static_displacement(self, load_free: np.ndarray) -> np.ndarray:
        """K u = f on the free DOFs (UserError if the supports leave a mechanism)."""
        try:
            u = np.linalg.solve(self.stiffness, np.asarray(load_free, float))
        except np.linalg.LinAlgError as exc:
            raise UserError(f"girder {self.spec.name!r}: supports leave a mechanism (singular stiffness)") from exc
        return u

    def modes(self, n_modes: int | None = None) -> GirderModes:
        """The lowest ``n_modes`` (all if None) modes, mass-normalised."""
        sub = None if n_modes is None else [0, min(int(n_modes), self.n_free) - 1]
        w2, phi = eigh(self.stiffness, self.mass, subset_by_index=sub)
        return _label_modes(self, w2, phi)


def _label_modes(g: Girder, w2: np.ndarray, phi: np.ndarray) -> GirderModes:
    node_dof = g.free_dofs % N_NODE_DOF
    frac = np.zeros((phi.shape[1], len(MOTION_DOFS)))
    for i, dofs in enumerate(MOTION_DOFS.values()):
        rows = np.flatnonzero(np.isin(node_dof, dofs))
        p = phi[rows]
        # kinds are uncoupled in M (straight girder, shear centre = mass centre), so this splits phi^T M phi
        frac[:, i] = np.einsum("im,ij,jm->m", p, g.mass[np.ix_(rows, rows)], p)
    frac /= frac.sum(axis=1, keepdims=True)
    names = tuple(MOTION_DOFS)
    kind = tuple(names[i] for i in np.argmax(frac, axis=1))
    # sign: largest nodal translation/rotation positive, so mode shapes are reproducible
    idx = np.argmax(np.abs(phi), axis=0)
    sgn = np.sign(phi[idx, np.arange(phi.shape[1])])
    sgn[sgn == 0] = 1.0
    freq = np.sqrt(np.clip(w2, 0.0, None)) / (2.0 * np.pi)
    return GirderModes(freq, phi * sgn, kind, frac)


def _mesh(spec: GirderSpec) -> np.ndarray:
    xs = [np.array([spec.start_m])]
    x0 = spec.start_m
    for L in spec.span_lengths_m:
        xs.append(x0 + L * np.arange(1, spec.elements_per_span + 1) / spec.elements_per_span)
        x0 += L
    return np.concatenate(xs)


def assemble_girder(spec: GirderSpec) -> Girder:
    """Assemble K, M (and C) of the continuous girder and apply its supports."""
    x = _mesh(spec)
    n_nodes = x.size
    ndof = N_NODE_DOF * n_nodes
    K = np.zeros((ndof, ndof))
    M = np.zeros((ndof, ndof))
    le = np.diff(x)
    mid = 0.5 * (x[:-1] + x[1:])
    for e in range(le.size):
        sec = spec.section if spec.haunch is None else spec.haunch.section_at(spec.section, mid[e])
        ke, me = element_matrices(sec, le[e])
        s = slice(N_NODE_DOF * e, N_NODE_DOF * e + 12)
        K[s, s] += ke
        M[s, s] += me
    restrained = set()
    tol = 1e-6 * max(spec.length_m, 1.0)
    for sup in spec.supports:
        k = int(np.argmin(np.abs(x - sup.x_m)))
        if abs(x[k] - sup.x_m) > max(tol, 1e-3):
            raise UserError(f"girder {spec.name!r} support at x={sup.x_m} m: no FE node there "
                            f"(nodes every span / elements_per_span; nearest {x[k]:.4g} m)")
        for name in sup.restrained:
            restrained.add(N_NODE_DOF * k + DOF_NAMES.index(name))
        for name, kval in sup.springs:
            i = N_NODE_DOF * k + DOF_NAMES.index(name)
            K[i, i] += kval
    free = np.array([i for i in range(ndof) if i not in restrained], dtype=int)
    Kf = K[np.ix_(free, free)]
    Mf = M[np.ix_(free, free)]
    g = Girder(spec, x, free, Mf, Kf, np.zeros_like(Kf), None, None)
    C, a, b = _damping(g)
    return Girder(spec, x, free, Mf, Kf, C, a, b)


def _damping(g: Girder) -> tuple[np.ndarray, float | None, float | None]:
    d = g.spec.damping
    if d.kind == "none":
        return np.zeros_like(g.stiffness), None, None
    if d.kind == "modal":
        w2, phi = eigh(g.stiffness, g.mass)
        w = np.sqrt(np.clip(w2, 0.0, None))
        mp = g.mass @ phi
        return (mp * (2.0 * d.ratio * w)) @ mp.T, None, None
    if d.alpha_per_s is not None or d.beta_s is not None:
        a, b = float(d.alpha_per_s or 0.0), float(d.beta_s or 0.0)
    else:
        if d.modes is not None:
            i, j = d.modes
            if not (1 <= i < j <= g.n_free):
                raise UserError(f"girder damping.modes: expected 1 <= i < j <= {g.n_free}, got {d.modes}")
            w2 = eigh(g.stiffness, g.mass, eigvals_only=True, subset_by_index=[0, j - 1])
            w1, w2_ = np.sqrt(np.clip(w2[[i - 1, j - 1]], 0.0, None))
        else:
            w1, w2_ = 2.0 * np.pi * np.asarray(d.frequencies_hz, float)
        if not (w1 > 0 and w2_ > w1):
            raise UserError(f"girder {g.spec.name!r} damping: Rayleigh needs two distinct frequencies > 0, got "
                            f"{w1 / 2 / np.pi:.4g} and {w2_ / 2 / np.pi:.4g} Hz (a free girder's rigid modes are 0 Hz)")
        a = 2.0 * d.ratio * w1 * w2_ / (w1 + w2_)
        b = 2.0 * d.ratio / (w1 + w2_)
    return a * g.mass + b * g.stiffness, a, b
