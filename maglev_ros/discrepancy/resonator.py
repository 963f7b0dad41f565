"""Open-ended discovery, modelled: an added resonator on a girder, fitted to the residual.

When the residual shows vibration in a band and on a span that no catalogue effect explains
(:mod:`.discovery`), the simplest structural explanation a rail engineer recognises is something
attached to the girder that resonates: a cable tray, a cover plate, a noise barrier panel, a
sensor bracket, a loose rail fixing. It is modelled as a spring-mass (mass ``mu`` x girder mass,
natural frequency ``f_a``, damping ratio ``zeta_a``) attached at ``x`` on one span.

Model (choices the papers leave open, made here):
- the attachment couples to the span's FE model (the diagnosing twin's guideway, per-end
  bearings included, from :func:`.model.guideway_modal`) through one extra DOF: the augmented
  eigenproblem [[K + k t t^T]] / [[M, 0], [0, m_a]] with t = (shape row at x, -1); the twin keeps
  the beam part of each augmented mode (mass-normalised over beam + attachment), so the moving
  magnet forces and the sensors see the girder only, and the attachment's inertia acts through
  the modes;
- damping of an augmented mode = the span's Rayleigh damping weighted by the beam's share of the
  modal kinetic energy plus ``zeta_a`` weighted by the attachment's share (modal damping; the
  non-proportional part is neglected: a few % error in the damping of the two coupled modes);
- modes up to the twin's cutoff are kept (at least one more than the span had).
The twin is otherwise unchanged: ``ModelSpec.resonator`` carries the attachment, and
:func:`.model.build_stepper` swaps in this modal basis, so the model's simulation, band powers,
residual and fit report (``.evaluate``) serve the resonator like any catalogue extension.

Fit: coarse grid over frequency (inside the discovered band) and position along the span (the
mode shapes at the attachment and at the sensors decide how the modes split; the grid covers
the first half only, as a symmetric span gives nearly the same fit at x and L - x, and the
report names both places), then Nelder-Mead
(scipy.optimize.minimize) over (ln f_a, x / L, ln mu, ln zeta_a) with the calibrated parameters
re-fitted linearly at every step (variable projection on the calibration Jacobian, as the
catalogue entries do, so a mere re-calibration gains nothing). Acceptance uses the catalogue's
gates (:func:`.acceptance.judge`): held-out gain, delta BIC, plausible parameters (inside the search
bounds, damping <= 5 %: a lightly damped component), collinearity;
plus one gate of its own, since a 4-parameter resonator can absorb small twin errors anywhere:
it must explain the located finding, i.e. the held-out guideway misfit inside the discovered band
drops by at least ``min_band_gain`` (15 %: clearly, though the noise floor's share of that misfit
stays).
A rigid added mass (``freq_hz`` infinite) is the limit the discovery uses for a span whose first mode
rings low (:mod:`.span_modes`): the span's own eigenproblem with M + m t t^T, its mass following from
the measured mode at every trial position (``target_hz``), and the own frequencies that would fit as
well profiled afterwards (:func:`frequency_profile`).
Hand-written: the augmented eigenproblem is ten lines of scipy.linalg.eigh; no library attaches a
resonator to our FE/modal twin.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize

from maglev_ros.twin.guideway import ModalBasis

from .acceptance import AcceptanceConfig, Verdict, collinearity, judge
from .attachment import Resonator, attached_modal
from .evaluate import RecData, fit_report, model_powers, residual_vector
from .model import ModelSpec, guideway_modal

MU_BOUNDS = (1e-3, 0.2)          # attachment mass / span mass
ZETA_BOUNDS = (2e-3, 0.3)
# an attached component is a lightly damped resonance (bolted steel 1-2 %, concrete 1.5-3 %, the
# conventional structural 5 %); fitted broader than that the "resonator" makes no peak one could find
# on the span and only bends the span's response over a wide band, which 4 free parameters can do to
# absorb model error (on a clean case 10.1 % at 41 Hz over 6-150 Hz was once accepted;
# every accepted resonator on an out-of-catalogue case so far fitted 0.2-3.3 %)
MAX_ATTACHMENT_DAMPING = 0.05


def resonator_modal(spec: ModelSpec, res: Resonator) -> ModalBasis:
    """Modal basis of the spec's guideway with ``res`` attached."""
    num = spec.effective_config().numerics
    return attached_modal(guideway_modal(spec), res, num.mode_cutoff_hz, num.min_modes_per_span)


# ------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class ResonatorFit:
    resonator: Resonator
    span_id: str
    position_m: float
    mass_kg: float
    cal_delta: tuple[float, ...]
    verdict: Verdict
    n_sims: int
    spec: ModelSpec = None          # calibrated spec the resonator was fitted with (not JSON)
    band_nrmse: tuple[float, float] = (0.0, 0.0)    # held-out guideway NRMSE in the band, before/after
    span_length_m: float = 0.0
    train_gain: float = 0.0         # share of the calibrated twin's training misfit it removes
    supported_hz: tuple[float, float] | None = None   # frequencies fitting as well (frequency_profile)
    x_supported_m: tuple[float, ...] | None = None    # trial positions (from the span start) fitting as well

    @property
    def position_range_m(self) -> tuple[float, float]:
        """The fitted place and its mirror image on the span (x <-> L - x); with ``x_supported_m``, the
        stretch between the outermost positions that fit nearly as well and their mirror images."""
        start = self.position_m - self.resonator.x_rel_m
        x = self.resonator.x_rel_m if self.x_supported_m is None else min(self.x_supported_m)
        a, b = start + x, start + self.span_length_m - x
        return (min(a, b), max(a, b))

    @property
    def accepted(self) -> bool:
        return self.verdict.accepted

    def to_dict(self) -> dict:
        r = self.resonator
        return {"kind": "added_resonator", "span": self.span_id, "position_m": float(self.position_m),
                "position_range_m": [float(x) for x in self.position_range_m],
                "freq_hz": None if r.rigid else float(r.freq_hz), "rigid": r.rigid,
                "damping_ratio": None if r.rigid else float(r.damping_ratio),
                "mass_ratio": float(r.mass_ratio), "mass_kg": float(self.mass_kg),
                "accepted": bool(self.verdict.accepted), "reasons": list(self.verdict.reasons),
                "evidence": {"heldout_nrmse_before": self.verdict.heldout_before,
                             "heldout_nrmse_after": self.verdict.heldout_after,
                             "delta_bic": self.verdict.delta_bic,
                             "heldout_band_nrmse_before": float(self.band_nrmse[0]),
                             "heldout_band_nrmse_after": float(self.band_nrmse[1])},
                "simulations": int(self.n_sims),
                **({"supported_frequency_hz": [float(x) for x in self.supported_hz]} if self.supported_hz else {})}

    def explanation(self, band_hz, what: str | None = None) -> str:
        """Plain words; ``what`` names the finding explained (default: the vibration in ``band_hz``)."""
        r = self.resonator
        f0, f1 = band_hz
        ev = self.verdict
        t = self.mass_kg
        mass = f"{t / 1000:.1f} t" if t >= 1000 else f"{t:.0f} kg"
        xm = self.position_m - r.x_rel_m + self.span_length_m - r.x_rel_m
        p0, p1 = self.position_range_m
        if self.supported_hz:
            how = (f"added to the span (fitted as a rigid mass; a component resonating anywhere between "
                   f"{self.supported_hz[0]:.0f} and {self.supported_hz[1]:.0f} Hz fits at least 90 % as well: the "
                   f"recordings see it only through the mass it adds to the span's modes, not its own frequency "
                   f"or damping)")
        elif r.rigid:
            how = "added to the span as a rigid mass"
        else:
            how = f"resonating at {r.freq_hz:.1f} Hz (damping {100 * r.damping_ratio:.1f} %)"
        core = (f"A component of about {mass} ({100 * r.mass_ratio:.1f} % of the girder's mass) {how}, "
                + (f"attached about {r.x_rel_m:.1f} m into "
                   f"span {self.span_id} (x = {self.position_m:.1f} m, or the mirror place x = {xm:.1f} m: a symmetric "
                   f"span tells them apart only through the sensor layout), "
                   if self.x_supported_m is None or p1 - p0 < 1.0 else
                   f"somewhere between x = {p0:.1f} and {p1:.1f} m on span {self.span_id} (best x = "
                   f"{self.position_m:.1f} m; the recordings hardly tell where on the span), "))
        if ev.accepted:
            return (core + f"explains {what or f'the unexplained {f0:.0f}-{f1:.0f} Hz vibration'}: held-out NRMSE "
                    f"{ev.heldout_before:.3f} -> {ev.heldout_after:.3f}, delta BIC {ev.delta_bic:+.0f}. Inspect span "
                    f"{self.span_id} near x = {self.position_m:.0f} m for a loose or resonant attachment (cable tray, "
                    f"cover plate, noise-barrier panel, bracket, loose fixing). This is not a catalogue effect.")
        return (core + f"was the best added resonator for {what or f'the {f0:.0f}-{f1:.0f} Hz residual'} but is NOT supported: "
                + "; ".join(ev.reasons) + ".")


class _Objective:
    """Training misfit of the calibrated twin with a resonator on one span, the calibrated
    parameters re-fitted linearly (variable projection on the calibration Jacobian), over
    p = (ln f_a, x / L, ln mu, ln zeta_a) with a soft box (Nelder-Mead has no bounds)."""

    def __init__(self, base, rd_train, span_index: int, f_range_hz, zeta_max: float, rigid: bool = False,
                 target_hz: float | None = None, mode_hz: float | None = None):
        from .fitting import CAL_HI, CAL_LO, PRIOR_SIGMA
        self.base, self.rd_train, self.span_index = base, rd_train, int(span_index)
        self.L = base.spec.spans[span_index].length_m
        self.box = ((math.log(f_range_hz[0]), math.log(f_range_hz[1])), (0.02, 0.98),
                    (math.log(MU_BOUNDS[0]), math.log(MU_BOUNDS[1])), (math.log(ZETA_BOUNDS[0]), math.log(zeta_max)))
        J = np.asarray(base.jac)
        lam = (0.02 / PRIOR_SIGMA) ** 2
        self._J, self._lam, self._lo, self._hi = J, lam, CAL_LO, CAL_HI
        self._A = J.T @ J + lam * np.eye(J.shape[1])
        self._th0 = np.asarray(base.theta, float)
        self.n_sims = [0]
        self.rigid = bool(rigid)
        # the span's first mode the attachment must give (its mass follows from it, see mass_for_target)
        self.target_hz = target_hz
        self._mu: dict = {}
        # a mode of the span the attachment must make (measured on the ambient recording): its own
        # frequency follows from its place and mass (see freq_for_mode)
        self.mode_hz = mode_hz
        self._f: dict = {}

    def freq_for_mode(self, xf: float, lmu: float) -> float | None:
        """ln of the own frequency that puts a mode of the span at ``mode_hz`` with the attachment at
        x = xf L and mass ratio exp(lmu), inside the searched range; None when none does. Bisection
        on the count of span modes below ``mode_hz``, which drops by one where a mode crosses it."""
        key = (round(float(xf), 6), round(float(lmu), 6))
        if key not in self._f:
            def below(lf):
                r = Resonator(self.span_index, float(np.clip(xf, 0.02, 0.98)) * self.L, float(math.exp(lf)),
                              float(math.exp(lmu)), 0.02)
                m = resonator_modal(self.base.spec, r)
                return int(np.sum(m.freq_hz[m.span_index == self.span_index] < self.mode_hz))
            lo, hi = self.box[0]
            n_lo, n_hi = below(lo), below(hi)
            if n_lo == n_hi:
                self._f[key] = None
            else:
                for _ in range(14):                 # 2^-14 of the range in ln f: < 0.01 %
                    mid = 0.5 * (lo + hi)
                    if below(mid) == n_lo:
                        lo = mid
                    else:
                        hi = mid
                self._f[key] = 0.5 * (lo + hi)
        return self._f[key]

    def mass_for_target(self, xf: float, lf: float) -> float | None:
        """Mass ratio that puts the span's lowest mode at ``target_hz`` with the attachment at x = xf L
        (rigid, or tuned at exp(lf)); None when no mass inside ``MU_BOUNDS`` does."""
        key = (round(float(xf), 6), round(float(lf), 6))
        if key not in self._mu:
            from scipy.optimize import brentq

            def f1(lmu):
                r = Resonator(self.span_index, float(np.clip(xf, 0.02, 0.98)) * self.L,
                              math.inf if self.rigid else float(math.exp(lf)), float(math.exp(lmu)), 0.02)
                m = resonator_modal(self.base.spec, r)
                return float(np.min(m.freq_hz[m.span_index == self.span_index])) - self.target_hz
            lo, hi = math.log(MU_BOUNDS[0]), math.log(MU_BOUNDS[1])
            a, b = f1(lo), f1(hi)
            self._mu[key] = (math.exp(brentq(f1, lo, hi, xtol=1e-4)) if a * b < 0 else None)
        return self._mu[key]

    def project(self, r):
        d = -np.linalg.solve(self._A, self._J.T @ r + self._lam * self._th0)
        d = np.clip(self._th0 + d, self._lo, self._hi) - self._th0
        return r + self._J @ d, d

    def clip(self, p) -> np.ndarray:
        return np.array([min(max(v, lo), hi) for v, (lo, hi) in zip(p, self.box)])

    def make(self, p) -> Resonator | None:
        lf, xf, lmu, lz = p
        if self.mode_hz is not None:
            lf = self.freq_for_mode(xf, lmu)
            if lf is None:
                return None
        if self.target_hz is not None:
            mu = self.mass_for_target(xf, lf)
            if mu is None:
                return None
            lmu = math.log(mu)
        return Resonator(self.span_index, float(np.clip(xf, 0.02, 0.98)) * self.L,
                         math.inf if self.rigid else float(math.exp(lf)), float(math.exp(lmu)), float(math.exp(lz)))

    def cost(self, p) -> float:
        pen = sum(1e3 * (max(0.0, lo - v) + max(0.0, v - hi)) ** 2 for k, (v, (lo, hi)) in enumerate(zip(p, self.box))
                  if not (k == 2 and self.target_hz is not None)        # the mass follows from the target
                  and not (k == 0 and self.mode_hz is not None))        # the frequency from the mode
        res = self.make(self.clip(p))
        if res is None:             # no plausible mass gives the measured mode there
            return float(self.base.r0 @ self.base.r0) * 10 + pen
        self.n_sims[0] += 1
        try:
            r = residual_vector(self.base.spec.with_(resonator=res), self.rd_train)
        except Exception:           # unstable twin at this trial: worst cost
            return float(self.base.r0 @ self.base.r0) * 10 + pen
        rp, _ = self.project(r)
        return float(rp @ rp) + pen


def frequency_profile(base, rd_train, fit: "ResonatorFit", freqs_hz, target_hz: float) -> list[tuple[float, float]]:
    """(f, training misfit reduction as a share of the calibrated twin's misfit) of an attachment tuned
    at each f on the fitted span, its mass following from the measured mode ``target_hz`` and its
    position re-fitted: how well the data determine its own frequency. One tuned well above the mode
    it detunes acts on it as a mass, whatever its frequency: the profile is then flat (measured with
    mass and damping free too: a 55 Hz, 3 % mass attachment fitted 0.51-0.585 of the misfit at any
    frequency from 29 to 110 Hz)."""
    rss0 = float(base.r0 @ base.r0)
    out = []
    for f in freqs_hz:
        ob = _Objective(base, rd_train, fit.resonator.span_index, (f, f), MAX_ATTACHMENT_DAMPING, target_hz=target_hz)
        c = _best_position(ob, math.log(f), math.log(0.02))[1]
        out.append((float(f), (rss0 - c) / rss0 if rss0 > 0 else 0.0))
    return out


def _best_position(ob: "_Objective", lf: float, lz: float, grid=(0.1, 0.2, 0.3, 0.4, 0.5),
                   maxiter: int = 6) -> tuple[float, float, list]:
    """(x / L, cost, every (x / L, cost) tried) minimising the objective over the position on the
    first half of the span (the other parameters fixed or, with a target mode, following from it):
    grid, then a bounded refine."""
    from scipy.optimize import minimize_scalar
    costs = [ob.cost((lf, xf, 0.0, lz)) for xf in grid]
    k = int(np.argmin(costs))
    lo, hi = max(0.02, grid[k] - 0.1), min(0.5, grid[k] + 0.1)
    opt = minimize_scalar(lambda xf: ob.cost((lf, xf, 0.0, lz)), bounds=(lo, hi), method="bounded",
                          options={"maxiter": maxiter, "xatol": 0.01})
    tried = list(zip(grid, costs)) + [(float(opt.x), float(opt.fun))]
    best = (float(opt.x), float(opt.fun)) if opt.fun < costs[k] else (float(grid[k]), float(costs[k]))
    return (*best, tried)


SIMPLEX_STEPS = np.array([0.04, 0.08, 0.7, 0.7])   # first simplex steps in (ln f, x / L, ln mu, ln zeta)


def _grid_then_simplex(cost, starts, free, maxfev: int) -> np.ndarray:
    """The best of ``starts`` (the first of equals), then a Nelder-Mead simplex over its coordinates
    ``free`` (the others held); the simplex's point only when it is no worse."""
    c0, p0 = None, None
    for p in starts:
        c = cost(p)
        if c0 is None or c < c0:
            c0, p0 = c, p
    free = list(free)

    def sub(q):
        p = p0.copy()
        p[free] = q
        return cost(p)
    q0 = p0[free]
    res = minimize(sub, q0, method="Nelder-Mead",
                   options={"maxfev": maxfev, "xatol": 1e-3, "fatol": 1e-9,
                            "initial_simplex": np.vstack([q0, q0 + np.diag(SIMPLEX_STEPS[free])])})
    if res.fun > c0:
        return p0
    p = p0.copy()
    p[free] = res.x
    return p


def supported_band(profile: list[tuple[float, float]], best_gain: float, share: float = 0.9) -> tuple[float, float]:
    """The frequency range over which a resonator explains at least ``share`` of the best fit's misfit
    reduction (the profile's grid points; ``best_gain`` the fitted resonator's own share)."""
    top = max([best_gain] + [g for _, g in profile])
    ok = [f for f, g in profile if g >= share * top]
    return (min(ok), max(ok)) if ok else (math.nan, math.nan)


class ResonatorFinder:
    """Fit an added girder resonator to the residual of a calibrated twin and judge it.

    ``fit(base, rd_train, rd_test, band_hz, span_index)``: ``base`` is the calibrated
    :class:`.fitting.BaseFit` (spec, theta, jac, r0), the resonator is searched inside ``band_hz``
    (widened by ``band_margin``) on span ``span_index``.
    """

    def __init__(self, acceptance: AcceptanceConfig = AcceptanceConfig(), n_freq: int = 5,
                 x_fracs=(0.2, 0.4), mass_ratio0: float = 0.02, zeta0: float = 0.03,
                 max_refine: int = 30, band_margin: float = 0.12, min_band_gain: float = 0.15):
        self.acceptance = acceptance
        self.n_freq = int(n_freq)
        self.x_fracs = tuple(float(x) for x in x_fracs)
        self.mass_ratio0 = float(mass_ratio0)
        self.zeta0 = float(zeta0)
        self.max_refine = int(max_refine)
        self.band_margin = float(band_margin)
        self.min_band_gain = float(min_band_gain)

    def fit(self, base, rd_train: list[RecData], rd_test: list[RecData], band_hz, span_index: int,
            search_hz=None, zeta_max: float | None = None, rigid: bool = False,
            target_hz: float | None = None, band_gate: bool = True,
            mode_hz: float | None = None) -> ResonatorFit:
        """``band_hz``: the located band (the fit must explain the misfit there); ``search_hz``: the
        range of resonator frequencies searched (default: the band widened by ``band_margin``);
        ``zeta_max``: search the damping only up to this (None: up to ``ZETA_BOUNDS``, and a fit
        broader than ``MAX_ATTACHMENT_DAMPING`` is rejected); ``rigid``: fit a rigid point mass
        (position and mass only) instead of a resonator; ``target_hz`` (with ``rigid``): the span's first
        mode measured in the recordings, from which the mass follows at every trial position;
        ``band_gate``: the held-out passes' band misfit must drop (False: the band was located on
        another recording, which the caller checks); ``mode_hz``: a mode of the span the resonator must
        make (measured on the ambient recording): its own frequency follows from its place and mass."""
        from .fitting import bic
        spec = base.spec
        span = spec.spans[span_index]
        L = span.length_m
        if search_hz is None:
            search_hz = (band_hz[0] * (1 - self.band_margin), band_hz[1] * (1 + self.band_margin))
        f_lo = max(1.0, float(search_hz[0]))
        f_hi = float(search_hz[1])
        if rigid:
            f_lo = f_hi = 1.0                    # the frequency coordinate is unused
        z_hi = ZETA_BOUNDS[1] if zeta_max is None else float(zeta_max)
        J = np.asarray(base.jac)
        th0 = np.asarray(base.theta, float)
        ob = _Objective(base, rd_train, span_index, (f_lo, f_hi), z_hi, rigid,
                        target_hz if rigid else None, None if rigid else mode_hz)
        make, cost, project = ob.make, ob.cost, ob.project
        n_sims = ob.n_sims
        if ob.target_hz is not None:
            xf, c_best, tried = _best_position(ob, 0.0, math.log(self.zeta0))
            res = make((0.0, xf, 0.0, math.log(self.zeta0)))
            if res is None:
                raise ValueError(f"no added mass within {MU_BOUNDS} gives the measured {target_hz:.2f} Hz mode")
            # the positions that fit at least 90 % as well (with the mass from the mode, the first mode alone
            # cannot tell them: only the other modes and the forced response do)
            rss0 = float(base.r0 @ base.r0)
            x_ok = tuple(sorted(x * L for x, c in tried if rss0 - c >= 0.9 * (rss0 - c_best)))
        elif ob.mode_hz is not None:
            x_ok = None
            # coarse grid: mass x position (the own frequency follows from the measured mode), then a
            # simplex over position, mass and damping
            p = _grid_then_simplex(cost, [np.array([0.0, xf, math.log(mu), math.log(self.zeta0)])
                                          for mu in np.geomspace(MU_BOUNDS[0] * 2, MU_BOUNDS[1] / 2, self.n_freq)
                                          for xf in self.x_fracs], (1, 2, 3), self.max_refine)
            res = make(ob.clip(p))
            if res is None:
                raise ValueError(f"no attachment within the searched range makes the measured {mode_hz:.2f} Hz mode")
        else:
            x_ok = None
            # coarse grid: frequency x position, then a simplex over all four
            p = _grid_then_simplex(cost, [np.array([math.log(f), xf, math.log(self.mass_ratio0), math.log(self.zeta0)])
                                          for f in np.geomspace(f_lo, f_hi, self.n_freq) for xf in self.x_fracs],
                                   (0, 1, 2, 3), self.max_refine)
            res = make(ob.clip(p))
        r = residual_vector(spec.with_(resonator=res), rd_train)
        rp, d = project(r)
        rss = float(rp @ rp)
        n_eff = max(10, base.r0.size // 2)
        k = 3 if rigid else 5                           # (f, damping,) x, mass ratio + the span chosen
        dbic = bic(rss, n_eff, k) - bic(float(base.r0 @ base.r0), n_eff, 0)
        fitted = spec.with_(cal=tuple(float(x) for x in th0 + d))
        held_before, _ = fit_report(spec, rd_test)
        held_after, _ = fit_report(fitted.with_(resonator=res), rd_test)
        r_te0 = residual_vector(spec, rd_test)
        r_te1 = residual_vector(fitted.with_(resonator=res), rd_test)
        n_test = max(10, r_te0.size // 2)
        llr = 0.5 * n_test * math.log(float(r_te0 @ r_te0) / max(float(r_te1 @ r_te1), 1e-300))
        col = collinearity(r - base.r0, J)
        plaus = self._plausible(res, f_lo, f_hi, zeta_max)
        # it must explain the located finding itself: the held-out guideway misfit in the band
        band_before, band_after = self._band_misfit(spec, None, fitted, res, rd_test, band_hz[0], band_hz[1])
        if band_gate and not band_after <= (1 - self.min_band_gain) * band_before:
            why = (f"it does not explain the located {band_hz[0]:.0f}-{band_hz[1]:.0f} Hz misfit (held-out band NRMSE "
                   f"{band_before:.3f} -> {band_after:.3f}, needs a {100 * self.min_band_gain:.0f} % drop): its gain "
                   f"is elsewhere, i.e. it only absorbs small model errors")
            plaus = (False, "; ".join(x for x in (plaus[1], why) if x))
        v = judge(held_before, held_after, dbic, plaus, col, self.acceptance, llr)
        m_span = span.props.mass_per_length_kg_m * L
        return ResonatorFit(res, span.span_id, span.start_m + res.x_rel_m, res.mass_ratio * m_span,
                            tuple(float(x) for x in d), v, n_sims[0] + 1, fitted, (band_before, band_after), L,
                            (float(base.r0 @ base.r0) - rss) / max(float(base.r0 @ base.r0), 1e-300),
                            x_supported_m=x_ok or None)

    @staticmethod
    def _band_misfit(spec0, res0, spec1, res1, rds, f_lo, f_hi) -> tuple[float, float]:
        """Held-out NRMSE of band amplitudes over the guideway channels and the bands that overlap
        [f_lo, f_hi], without and with the resonator."""
        acc = [[0.0, 0.0], [0.0, 0.0]]
        for rd in rds:
            e = rd.grid.edges_hz
            sel = (e[1:] > f_lo) & (e[:-1] < f_hi)
            for k, (sp, rs) in enumerate(((spec0, res0), (spec1, res1))):
                mp = model_powers(sp.with_(resonator=rs), rd)
                for n, ch in rd.rec.channels.items():
                    if not ch.group.startswith("guideway"):
                        continue
                    m = sel & rd.masks[n]
                    am = np.sqrt(np.clip(rd.pm[n][:, m], 0, None))
                    at = np.sqrt(np.clip(mp[n][:, m], 0, None))
                    ok = np.isfinite(am) & np.isfinite(at)
                    acc[k][0] += float(np.sum((am[ok] - at[ok]) ** 2))
                    acc[k][1] += float(np.sum(am[ok] ** 2))
        return tuple(math.sqrt(a / b) if b > 0 else 0.0 for a, b in acc)

    @staticmethod
    def _plausible(res: Resonator, f_lo: float, f_hi: float, zeta_max: float | None = None) -> tuple[bool, str]:
        why = []
        if not (MU_BOUNDS[0] * 1.01 <= res.mass_ratio <= MU_BOUNDS[1] * 0.99):
            why.append(f"attachment mass ratio {res.mass_ratio:.3f} at its bound {MU_BOUNDS}")
        if zeta_max is not None:
            pass            # searched inside the plausible range; the damping is reported as not determined
        elif not (ZETA_BOUNDS[0] * 1.01 <= res.damping_ratio <= ZETA_BOUNDS[1] * 0.99):
            why.append(f"attachment damping ratio {res.damping_ratio:.3f} at its bound {ZETA_BOUNDS}")
        elif res.damping_ratio > MAX_ATTACHMENT_DAMPING:
            why.append(f"attachment damping ratio {res.damping_ratio * 100:.1f} % is broader than a lightly "
                       f"damped attached component (<= {MAX_ATTACHMENT_DAMPING * 100:.0f} %): no resonance one "
                       f"could find, a broad change of the span's response")
        if f_hi > f_lo * 1.001 and not (f_lo * 1.001 <= res.freq_hz <= f_hi * 0.999):
            why.append(f"resonator frequency {res.freq_hz:.1f} Hz at the edge of the searched band")
        return (not why, "; ".join(why))
