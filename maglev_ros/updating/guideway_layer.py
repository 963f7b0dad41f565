"""Guideway layer (000 Sec. 4.2.2, Eqs. 22-25): E, rho and bearing stiffness kb of the instrumented span
from measured frequencies and mode shapes (MAC), optionally pinned by a quasi-static deflection.

Objectives (MOPSO): f1 = sum_i |f_i,model - f_i,meas| / f_i,meas (weights 1, as in 000),
f2 = sum_i (1 - MAC_i). The Pareto solution chosen by GRP is then polished by a whitened least-squares
fit on the direct FE model (frequencies / sigma_f, scale-matched mode shapes / sigma_phi
[, quasi-static deflection amplitude / sigma_d]); its Jacobian gives the Fisher information, the
identifiability analysis and the standard deviations (first order, from the stated noise levels:
the modal std_frequency_hz when finite, else ``default_freq_rel_std``; sigma_phi from the shape
residual at the optimum, floored at ``min_shape_std``).

Ridge handling: modes alone leave the common scale of (E, rho, kb) free (K and M scale together). Then
the reported point is the one on the ridge nearest to the design values (in log space, inside the
bounds), E, rho and kb are flagged not identifiable and "E/rho" and "kb/rho" are reported with their
std (as identifiable combinations when determined to 1 %, ``identifiability.COMBINATION_MAX_REL_STD``).
A quasi-static midspan deflection under the vehicle's known weight (``StaticTarget``) depends on
E and kb but not on rho, which pins the scale: all three become identifiable.

Model speed: K(E, kb) = (E/E0) K_beam + kb K_bearing and M(rho) = (rho/rho0) M0 are linear, so the
twin's FE matrices (guideway.assemble_span) are assembled once and each evaluation is one small
generalised eigenproblem (~0.2 ms): the direct model is cheap enough for MOPSO, and the Elman
surrogate is optional here (``use_surrogate``; compared in bench/bench_update.py).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.linalg import eigh
from scipy.optimize import least_squares

from maglev_ros.errors import UserError
from maglev_ros.twin.design import GuidewayProps, SpanSpec
from maglev_ros.twin.guideway import assemble_span
from maglev_ros.updating.grp import grey_relational_projection
from maglev_ros.updating.identifiability import Identifiability, analyse, jacobian
from maglev_ros.updating.mopso import MOPSO, ParetoResult
from maglev_ros.updating.parameters import GUIDEWAY_PARAMS, ParameterSpace, guideway_space
from maglev_ros.updating.sampling import optimal_lhs


def mac(a: np.ndarray, b: np.ndarray) -> float:
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    den = float(a @ a) * float(b @ b)
    return float((a @ b) ** 2 / den) if den > 0 else 0.0


def _norm_shape(v: np.ndarray) -> np.ndarray:
    k = int(np.argmax(np.abs(v)))
    return v / v[k] if v[k] != 0 else v


@dataclass(frozen=True)
class ModalTarget:
    """Measured modes of one span: frequencies (n), optional std (NaN unknown), shapes (n, n_ch) at
    sensor positions ``sensor_x_m`` (n_ch,) (or None: frequencies only)."""
    frequencies_hz: np.ndarray
    std_frequency_hz: np.ndarray
    shapes: np.ndarray | None = None
    sensor_x_m: np.ndarray | None = None

    def __post_init__(self):
        f = np.asarray(self.frequencies_hz, dtype=float)
        if f.ndim != 1 or f.size == 0 or np.any(~np.isfinite(f)) or np.any(f <= 0):
            raise UserError("modes: expected at least one positive measured frequency")
        if self.shapes is not None:
            s = np.asarray(self.shapes, dtype=float)
            if s.shape[0] != f.size or self.sensor_x_m is None or s.shape[1] != np.size(self.sensor_x_m):
                raise UserError("modes: mode_shape must have one row per mode and one value per sensor position")

    @property
    def n_modes(self) -> int:
        return int(np.size(self.frequencies_hz))


@dataclass(frozen=True)
class StaticTarget:
    """Quasi-static deflection at ``sensor_x_m`` (positive up) while the magnets (static forces
    ``magnet_force_n``, upward on the magnets = downward on the rail) are at ``magnet_x_m`` (n, m)."""
    sensor_x_m: float
    magnet_x_m: np.ndarray
    magnet_force_n: np.ndarray
    displacement_m: np.ndarray
    std_rel: float = 0.01            # assumed relative std of the fitted amplitude (model + noise)


class SpanModel:
    """The twin's FE model of one span as a function of (E, rho, kb), fast (linear in the parameters)."""

    def __init__(self, span: SpanSpec, n_elements: int = 16, n_modes: int = 4):
        self.span = span
        self.n_modes = int(n_modes)
        p = span.props
        self.e0, self.rho0, self.kb0 = p.youngs_modulus_pa, p.density_kg_m3, p.bearing_stiffness_n_per_m
        if not (math.isfinite(self.kb0) and self.kb0 > 0):
            raise UserError("design.guideway.bearing_stiffness_n_per_m: updating needs a finite bearing stiffness")
        fe_a = assemble_span(span, n_elements)
        fe_b = assemble_span(replace(span, props=replace(p, bearing_stiffness_n_per_m=2 * self.kb0)), n_elements)
        self.k_bear = (fe_b.stiffness - fe_a.stiffness) / self.kb0
        self.k_beam = fe_a.stiffness - self.kb0 * self.k_bear
        self.m0 = fe_a.mass
        self.fe = fe_a
        self.n_evaluations = 0

    def matrices(self, values):
        e, rho, kb = values
        return (e / self.e0) * self.k_beam + kb * self.k_bear, (rho / self.rho0) * self.m0

    def modes(self, values, x_m=None, n_modes: int | None = None):
        """(frequencies_hz (n,), shapes (n, len(x)) normalised to max |.| = 1 or None)."""
        n = self.n_modes if n_modes is None else int(n_modes)
        K, M = self.matrices(values)
        w2, phi = eigh(K, M, subset_by_index=[0, n - 1])
        self.n_evaluations += 1
        f = np.sqrt(np.clip(w2, 0, None)) / (2 * np.pi)
        if x_m is None:
            return f, None
        S = (self.fe.shape_matrix(np.asarray(x_m, dtype=float)) @ phi).T
        return f, np.array([_norm_shape(s) for s in S])

    def static_influence(self, values, sensor_x_m: float, load_x_m: np.ndarray) -> np.ndarray:
        """Displacement at the sensor per unit upward load at each ``load_x_m`` (Maxwell reciprocity)."""
        K, _ = self.matrices(values)
        u = np.linalg.solve(K, self.fe.shape_matrix([sensor_x_m])[0])
        x = np.asarray(load_x_m, dtype=float)
        return (self.fe.shape_matrix(x.ravel()) @ u).reshape(x.shape)


@dataclass(frozen=True)
class GuidewayUpdate:
    names: tuple[str, ...]
    nominal: tuple[float, ...]
    values: tuple[float, ...]
    std: tuple[float | None, ...]
    identifiable: tuple[bool, ...]
    identifiability: Identifiability
    frequencies_measured_hz: tuple[float, ...]
    frequencies_nominal_hz: tuple[float, ...]
    frequencies_updated_hz: tuple[float, ...]
    mac_nominal: tuple[float, ...]
    mac_updated: tuple[float, ...]
    pareto: ParetoResult
    grp_index: int
    n_model_evaluations: int
    wall_time_s: float
    used_static: bool
    surrogate_score: dict | None = None

    def value(self, name: str) -> float:
        return self.values[self.names.index(name)]

    def to_dict(self) -> dict:
        return {"names": list(self.names), "nominal": list(self.nominal), "values": list(self.values),
                "std": list(self.std), "identifiable": list(self.identifiable),
                "identifiability": self.identifiability.to_dict(),
                "frequencies_hz": {"measured": list(self.frequencies_measured_hz),
                                   "nominal": list(self.frequencies_nominal_hz),
                                   "updated": list(self.frequencies_updated_hz)},
                "mac": {"nominal": list(self.mac_nominal), "updated": list(self.mac_updated)},
                "pareto": self.pareto.to_dict(), "grp_index": self.grp_index,
                "n_model_evaluations": self.n_model_evaluations, "wall_time_s": self.wall_time_s,
                "used_static": self.used_static, "surrogate_score": self.surrogate_score}


GUIDEWAY_COMBINATIONS = (("E/rho", (1.0, -1.0, 0.0)), ("kb/rho", (0.0, -1.0, 1.0)),
                         ("kb/E", (-1.0, 0.0, 1.0)))


class GuidewayLayer:
    """fit(span, target: ModalTarget, static: StaticTarget | None) -> GuidewayUpdate."""

    def __init__(self, rel_range: float = 0.30, n_particles: int = 100, archive_size: int = 80,
                 n_iterations: int = 200, n_grid: int = 7, use_surrogate: bool = False, n_samples: int = 400,
                 default_freq_rel_std: float = 1e-3, min_shape_std: float = 2e-3, n_elements: int = 16,
                 seed: int = 0, surrogate_kwargs: dict | None = None):
        self.rel_range = rel_range
        self.mopso = dict(n_particles=n_particles, archive_size=archive_size, n_iterations=n_iterations,
                          n_grid=n_grid, inertia=0.5, c1=1.0, c2=2.0, seed=seed)
        self.use_surrogate, self.n_samples = bool(use_surrogate), int(n_samples)
        self.default_freq_rel_std, self.min_shape_std = float(default_freq_rel_std), float(min_shape_std)
        self.n_elements, self.seed = int(n_elements), seed
        self.surrogate_kwargs = surrogate_kwargs or {}

    def fit(self, span: SpanSpec, target: ModalTarget, static: StaticTarget | None = None) -> GuidewayUpdate:
        t_start = time.perf_counter()
        space = ParameterSpace.around({n: getattr(span.props, n) for n in GUIDEWAY_PARAMS}, self.rel_range)
        n_meas = target.n_modes
        model = SpanModel(span, self.n_elements, n_modes=n_meas + 2)
        fm = np.asarray(target.frequencies_hz, dtype=float)
        xs = None if target.shapes is None else np.asarray(target.sensor_x_m, dtype=float)
        shp = None if target.shapes is None else np.array([_norm_shape(s) for s in np.asarray(target.shapes, float)])
        # pair measured modes with model modes at the nominal point (MAC, then frequency)
        f_nom, s_nom = model.modes(space.nominal, xs)
        pair = []
        for i in range(n_meas):
            cand = [j for j in range(f_nom.size) if j not in pair]
            if shp is not None:
                score = [mac(shp[i], s_nom[j]) - abs(np.log(f_nom[j] / fm[i])) for j in cand]
            else:
                score = [-abs(np.log(f_nom[j] / fm[i])) for j in cand]
            pair.append(cand[int(np.argmax(score))])
        pair = np.array(pair)

        ref = None if s_nom is None else s_nom[pair]

        def direct(values):
            f, s = model.modes(values, xs)
            if s is None:
                return f[pair], None
            s = s[pair]
            # unit norm, sign of the nominal shape: a smooth map for the surrogate
            s = s / np.linalg.norm(s, axis=1, keepdims=True)
            return f[pair], s * np.where(np.sum(s * ref, axis=1) < 0, -1.0, 1.0)[:, None]

        def objectives_from(f, s):
            o1 = np.sum(np.abs(f - fm) / fm)
            o2 = 0.0 if s is None else float(np.sum([1 - mac(s[i], shp[i]) for i in range(n_meas)]))
            return o1, o2

        surrogate_score = None
        if self.use_surrogate:
            from maglev_ros.updating.surrogate import train_and_score
            U = optimal_lhs(self.n_samples, space.dim, seed=self.seed)
            Xs = np.array([space.from_unit(u) for u in U])
            outs = [direct(x) for x in Xs]
            Y = np.array([np.concatenate([np.log(f), [] if s is None else s.ravel()]) for f, s in outs])
            sur, sc = train_and_score(Xs, Y, seed=self.seed, log_outputs=False, **self.surrogate_kwargs)
            ftest = None
            surrogate_score = {"n_samples": self.n_samples, "outputs": "log f + shapes", **sc.to_dict()}

            def batch(theta):
                Yp = sur.predict(space.from_theta(theta))
                res = []
                for y in Yp:
                    f = np.exp(y[:n_meas])
                    s = None if shp is None else y[n_meas:].reshape(n_meas, -1)
                    res.append(objectives_from(f, s))
                return np.array(res)
        else:
            def batch(theta):
                return np.array([objectives_from(*direct(v)) for v in space.from_theta(theta)])

        lo, hi = space.theta_bounds
        pareto = MOPSO(**self.mopso).minimize(batch, lo, hi, x0=np.zeros((1, space.dim)))
        grp = grey_relational_projection(pareto.f)
        theta0 = pareto.x[grp.index]

        # ---- local polish on the direct model (whitened residuals) -------------------------
        sf = np.asarray(target.std_frequency_hz, dtype=float)
        sf = np.where(np.isfinite(sf) & (sf > 0), sf, self.default_freq_rel_std * fm)
        static_u = None
        if static is not None:
            static_u = model.static_influence(space.nominal, static.sensor_x_m, static.magnet_x_m) @ (
                -np.asarray(static.magnet_force_n, dtype=float))
            uu = float(static_u @ static_u)
            if uu <= 0:
                raise UserError("guideway displacement: the vehicle never loads the span of the displacement sensor")
            amp_meas = float(np.asarray(static.displacement_m) @ static_u) / uu

        def shape_res(s):
            out = []
            for i in range(n_meas):
                a = float(s[i] @ shp[i]) / float(s[i] @ s[i])
                out.append(a * s[i] - shp[i])
            return np.concatenate(out)

        def residual(theta, sigma_phi):
            v = space.from_theta(theta)
            f, s = direct(v)
            r = [(f - fm) / sf]
            if shp is not None:
                r.append(shape_res(s) / sigma_phi)
            if static is not None:
                d = model.static_influence(v, static.sensor_x_m, static.magnet_x_m) @ (-np.asarray(static.magnet_force_n))
                amp = float(d @ static_u) / float(static_u @ static_u)
                r.append(np.array([(amp - amp_meas) / (static.std_rel * abs(amp_meas))]))
            return np.concatenate(r)

        sigma_phi = 1.0
        theta = theta0.copy()
        for _ in range(2):       # second pass with sigma_phi re-estimated from the shape residual
            sol = least_squares(residual, theta, args=(sigma_phi,), bounds=(lo, hi), x_scale=0.05,
                                xtol=1e-12, ftol=1e-12, gtol=1e-12, max_nfev=200)
            theta = sol.x
            if shp is not None:
                rs = shape_res(direct(space.from_theta(theta))[1])
                dof = max(rs.size - n_meas, 1)
                sigma_phi = max(float(np.sqrt(rs @ rs / dof)), self.min_shape_std)
            else:
                break
        J, _ = jacobian(lambda th: residual(th, sigma_phi), theta, step=1e-5)
        values = space.from_theta(theta)
        ident = analyse(J, space.names, values, GUIDEWAY_COMBINATIONS, rel_tol=1e-4, max_rel_std=0.1)
        self.last_jacobian_ = J
        if ident.ridge_directions:
            # nearest-to-design point on the ridge (inside the bounds): predictions are unchanged
            N = np.array(ident.ridge_directions)
            t = -(N @ theta)
            if N.shape[0] == 1:
                n = N[0]
                with np.errstate(divide="ignore", invalid="ignore"):
                    ta, tb = (lo - theta) / n, (hi - theta) / n
                tmin = np.nanmax(np.where(n != 0, np.minimum(ta, tb), -np.inf))
                tmax = np.nanmin(np.where(n != 0, np.maximum(ta, tb), np.inf))
                t = np.clip(t, tmin, tmax)
            theta = np.clip(theta + N.T @ np.atleast_1d(t), lo, hi)
            values = space.from_theta(theta)
            ident = analyse(J, space.names, values, GUIDEWAY_COMBINATIONS, rel_tol=1e-4, max_rel_std=0.1)
        values = space.clip(values)
        f_up, s_up = direct(values)
        mac_nom = [mac(s_nom[pair][i], shp[i]) for i in range(n_meas)] if shp is not None else []
        mac_up = [mac(s_up[i], shp[i]) for i in range(n_meas)] if shp is not None else []
        std = tuple(None if not np.isfinite(s) else float(s) for s in ident.param_std)
        return GuidewayUpdate(
            names=space.names, nominal=tuple(map(float, space.nominal)), values=tuple(map(float, values)),
            std=std, identifiable=ident.identifiable, identifiability=ident,
            frequencies_measured_hz=tuple(map(float, fm)), frequencies_nominal_hz=tuple(map(float, f_nom[pair])),
            frequencies_updated_hz=tuple(map(float, f_up)), mac_nominal=tuple(map(float, mac_nom)),
            mac_updated=tuple(map(float, mac_up)), pareto=ParetoResult(space.from_theta(pareto.x), pareto.f,
                                                                        pareto.n_evaluations, pareto.n_iterations),
            grp_index=grp.index, n_model_evaluations=model.n_evaluations,
            wall_time_s=time.perf_counter() - t_start, used_static=static is not None,
            surrogate_score=surrogate_score)
