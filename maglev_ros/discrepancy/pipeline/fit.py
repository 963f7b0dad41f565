"""Stage 4, fit: each proposed hypothesis fitted on the training pass and measured on the held-out ones.

Per hypothesis: fitted with the calibrated parameters re-fitted (:func:`..fitting.fit_hypothesis`);
levitation physics (control, magnetic force) acts on the vehicle's channels only, so it is fitted
there, judged there against the calibrated twin with kp, kv re-fitted on the same rows (its null,
:meth:`Evidence.vehicle_null`) and with the rail its own twin reconstructs; everything else is
judged on the whole recording. Each fit gets its first verdict here (held-out NRMSE and
log-likelihood, delta BIC, plausibility, collinearity with a calibrated parameter: :mod:`..acceptance`);
the judgement across hypotheses (peers, signatures, combinations) is the next stage. Dropouts
found in the data are fitted as sensor errors of their channel.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from maglev_ros.parallel import SERIAL, Executor
from maglev_ros.progress import NULL, Progress

from .. import catalogue as cat
from ..acceptance import REST_WORSE, AcceptanceConfig, Verdict, collinearity, judge, judge_where_it_acts
from ..catalogue import VEHICLE_WIDE
from ..evaluate import RecData, Selection, fit_report, levitation_items, residual_rows, residual_vector, split_frames
from ..fitting import BaseFit, HypFit, bic, fit_gains, fit_hypothesis, safe_residual
from ..recording import Recording
from .calibrate import Calibration
from .localize import Localization
from .propose import Proposal

RECALIBRATED = "accepted with the levitation gains re-calibrated on the whole recording"


def _key(loc):
    """Cache key of an extension's location (a set of channels or a :class:`..evaluate.Selection`)."""
    return loc if isinstance(loc, Selection) else frozenset(loc or ())


@dataclass(frozen=True)
class Null:
    """Measures of the null model of levitation physics over its channels (see ``vehicle_null``)."""
    rss_train: float
    n_train: int                       # effective count of its training rows
    heldout_nrmse: float
    heldout: tuple[float, int]         # (held-out RSS, effective count)


@dataclass(eq=False)
class Evidence:
    """Where a hypothesis is fitted and judged, and the reference models it is judged against
    (computed once per place)."""
    cal: Calibration
    rebuild: bool                      # the passes' rail is rebuilt for a twin with levitation physics
    nulls: dict = field(default_factory=dict)
    halves: dict = field(default_factory=dict)
    test0: dict = field(default_factory=dict)   # channels (None: all) -> (held-out RSS, count) of the calibrated twin

    def where(self, h, part="held"):
        """Channels an extension acts on (its location), None for the whole recording; for
        levitation physics the items it is fitted (``part="fit"``) and judged on there
        (:func:`..evaluate.levitation_items`); for amplitude-dependent levitation physics with the
        training pass split in time: fitted on its first half, its second half held out too."""
        chans = set(h.location.get("channels") or [])
        if not chans:
            return None
        if h.category not in VEHICLE_WIDE:
            return chans
        lev = levitation_items(chans)
        if h.effect in cat.AMPLITUDE_DEPENDENT:
            rd0 = self.cal.data.rd_train[0]
            if lev not in self.halves:
                self.halves[lev] = split_frames(self.cal.base.spec, rd0, lev)
            if self.halves[lev] is not None:
                return lev.on_frames(rd0, self.halves[lev][0 if part == "fit" else 1])
        return lev

    def held_of(self, h, tr, te):
        """The held-out recordings of ``h``'s measures where it acts: the other passes, and the
        training pass too when it is split in time (its held-out frames: ``where(h)``)."""
        split = isinstance(sel := self.where(h), Selection) and bool(sel.frames)
        return [tr[0]] + list(te) if split and not self.cal.same_heldout else te

    def null_key(self, h):
        return (_key(self.where(h, "fit")), _key(self.where(h)))

    def null_of(self, h) -> Null | None:
        """The null of ``h`` if it was computed."""
        return self.nulls.get(self.null_key(h))

    def vehicle_null(self, h) -> Null:
        """The calibrated twin with kp, kv re-fitted on the rows ``h`` is fitted on (with its own
        rail): what levitation physics fitted there must beat; its measures where ``h`` is judged."""
        key = self.null_key(h)
        if key not in self.nulls:
            base, rd_train, rd_test = self.cal.base, self.cal.data.rd_train, self.cal.data.rd_test
            fit_on, judged_on = self.where(h, "fit"), self.where(h)
            sp = fit_gains(base, rd_train, residual_rows(base.spec, rd_train, fit_on))
            tr, te = rd_train, rd_test
            if self.rebuild:
                own_set = self.cal.prepare(sp, floor_spec=base.spec, log=None)
                tr, te = own_set.rd_train, own_set.rd_test
            held = self.held_of(h, tr, te)
            r_tr, r_te = residual_vector(sp, tr, fit_on), residual_vector(sp, held, judged_on)
            self.nulls[key] = Null(float(r_tr @ r_tr), max(10, r_tr.size // 2), fit_report(sp, held, judged_on)[0],
                                   (float(r_te @ r_te), max(10, r_te.size // 2)))
        return self.nulls[key]

    def held_llr(self, spec, chans=None, rds=None, ref=None):
        """Held-out log-likelihood ratio against the calibrated twin (over ``chans`` and their
        features only, when given; ``rds``: the held-out passes with the extended twin's own rail;
        ``ref``: (held-out RSS, effective count) of another reference model over ``chans``)."""
        base, rd_test = self.cal.base, self.cal.data.rd_test
        key = _key(chans) if chans else None
        if ref is None and key not in self.test0:
            r0 = residual_vector(base.spec, rd_test, chans)
            self.test0[key] = (float(r0 @ r0), max(10, r0.size // 2))
        rss0, n = ref or self.test0[key]
        r = residual_vector(spec, rd_test if rds is None else rds, chans)
        return 0.5 * n * math.log(max(rss0, 1e-300) / max(float(r @ r), 1e-300))


@dataclass(eq=False)
class Fits:
    fits: list                          # (HypFit, Verdict, delta BIC) per fitted hypothesis
    local_ev: dict                      # id(HypFit) -> held-out NRMSE on its channels (before, after)
    own_rail: dict                      # id(HypFit) -> every pass prepared with the rail its twin reconstructs
    untestable: list[dict]              # {effect, label, why}: screening or fitting failed
    evidence: Evidence
    held_before: float                  # the calibrated twin's whole held-out NRMSE
    n_eff: int                          # effective count of the training residuals
    bic0: float                         # the calibrated twin's training BIC


@dataclass(eq=False)
class _Outcome:
    """What fitting one hypothesis gives: its fit and first verdict, or why it failed, its held-out
    NRMSE where it acts, the passes with its own rail, and the reference models it computed (kept
    by the caller: a worker's copy of the evidence is lost with the worker)."""
    fit: tuple | None = None            # (HypFit, Verdict, delta BIC)
    failed: dict | None = None          # {effect, label, why}
    local_ev: tuple | None = None       # (before, after)
    own_rail: list | None = None
    nulls: dict = field(default_factory=dict)
    halves: dict = field(default_factory=dict)
    test0: dict = field(default_factory=dict)


@dataclass(eq=False)
class _FitOne:
    """Fits one hypothesis (a work item of an executor: a pure function of its inputs; the twin's
    simulation cache only saves time)."""
    cal: Calibration
    config: object
    ev: Evidence
    held_before: float
    n_eff: int
    bic0: float

    def __call__(self, h) -> _Outcome:
        out = self._fit(h)
        ev = self.ev
        out.nulls, out.halves, out.test0 = dict(ev.nulls), dict(ev.halves), dict(ev.test0)
        return out

    def _fit(self, h) -> _Outcome:
        cal, config, ev = self.cal, self.config, self.ev
        base, rd_train, rd_test = cal.base, cal.data.rd_train, cal.data.rd_test
        held_before, n_eff, bic0 = self.held_before, self.n_eff, self.bic0
        where, held_of = ev.where, ev.held_of
        out = _Outcome()
        try:
            # ambient vibration on the training pass alone: the ambient recording was taken at another time
            # (for the modes) and its level says nothing of the passes' (0.033-0.040 m/s^2 on a foreign line
            # whose passes had 0.010 before the vehicle came, or 0.019-0.026 with an ambient source on)
            if h.category in VEHICLE_WIDE:
                hf = fit_hypothesis(base, h, rd_train, select=where(h, "fit"))
            else:
                hf = fit_hypothesis(base, h, rd_train)
        except Exception as exc:
            out.failed = {"effect": h.effect, "label": h.label, "why": f"fit failed ({exc})"}
            return out
        rd_train_h, rd_test_h = rd_train, rd_test
        dbic = None
        if ev.rebuild and h.category in VEHICLE_WIDE:
            # levitation physics changes the magnet forces and so the girder deflection that the
            # loaded -> unloaded reconstruction removes: the extended twin is judged with the rail
            # its own twin reconstructs (measured: a true 8 ms delay, fitted as 8.9 ms: held-out NRMSE
            # 0.335 -> 0.376 on the calibrated twin's rail, guideway G3A 0.39 -> 0.80, but 0.335 ->
            # 0.175 on its own; the calibrated twin on that rail: 0.416, so the rail alone is no gain);
            # its training misfit too
            own_set = cal.prepare(hf.spec, floor_spec=base.spec, log=None)
            own, rd_train_h, rd_test_h = own_set.rd_all, own_set.rd_train, own_set.rd_test
            out.own_rail = own
            r_own = safe_residual(hf.spec, rd_train_h)
            hf.rss = float(r_own @ r_own) if r_own is not None else math.inf
        null = None
        if h.category in VEHICLE_WIDE and where(h) and np.isfinite(hf.rss):
            # penalised criterion on the rows it was fitted on (its channels), as gate 1 is judged
            # there, against the calibrated twin with kp, kv re-fitted on the same rows; the rest of
            # the recording is held to "not worse" on held-out data (over every row, a 10 % headroom
            # over the peak current demand gave delta BIC +242 from the guideway sensors)
            null = ev.vehicle_null(h)
            r_l = residual_vector(hf.spec, rd_train_h, where(h, "fit"))
            dbic = bic(float(r_l @ r_l), null.n_train, hf.k) - bic(null.rss_train, null.n_train, 0)
        if dbic is None:
            dbic = bic(hf.rss, n_eff, hf.k) - bic0
        if dbic > 0 and h.effect == "sensor_error":
            # clearly nothing: skip the held-out simulation
            out.fit = (hf, judge(held_before, held_before, dbic, h.plausible(hf.params), 0.0,
                                 config.acceptance), dbic)
            return out
        held_after, _ = fit_report(hf.spec, rd_test_h)
        # the held-out fit is also reported where the extension acts (its channels): judged
        # there, a 9 % scale "error" of one guideway sensor on a clean case (model error of
        # that channel) passed every gate, so acceptance stays on the whole recording
        at = where(h)
        if at:
            before = (null.heldout_nrmse if null is not None
                      else fit_report(base.spec, held_of(h, rd_train, rd_test), at)[0])
            out.local_ev = (before, fit_report(hf.spec, held_of(h, rd_train_h, rd_test_h), at)[0])
        col = 0.0
        if h.needs_sim:
            jcol = residual_vector(h.apply(base.spec, np.array(h.trial)), rd_train) - base.r0
            col = collinearity(jcol, base.jac)
        if at and h.category in VEHICLE_WIDE:
            # levitation physics acts on every vehicle channel and on nothing else: the held-out
            # gain is judged there, and the rest of the recording must not get worse (whole-recording
            # held-out NRMSE was dominated by the guideway sensors: a 6 ms delay fitted as 2-4 ms cut
            # the vehicle channels' held-out NRMSE 0.179 -> 0.121 but the whole 0.153 -> 0.150)
            gains = dict(reference="the calibrated twin with kp, kv re-fitted there",
                         absorbed_by="the levitation gains kp, kv re-fitted on these channels",
                         separated_by=cat.SEPARATED_BY.get(h.effect)) if null is not None else {}
            v = judge_where_it_acts(held_before, held_after, *out.local_ev, dbic, h.plausible(hf.params),
                                    col, config.acceptance,
                                    ev.held_llr(hf.spec, at, held_of(h, rd_train_h, rd_test_h),
                                                null.heldout if null is not None else None),
                                    **gains)
            if null is not None and v.reasons and all(r.startswith(REST_WORSE) for r in v.reasons):
                hf, v = recalibrated_whole(base, hf, v, rd_train_h, rd_test_h, held_before, config.acceptance)
        else:
            v = judge(held_before, held_after, dbic, h.plausible(hf.params), col, config.acceptance,
                      ev.held_llr(hf.spec))
        out.fit = (hf, v, dbic)
        return out


def fit_hypotheses(cal: Calibration, loc: Localization, prop: Proposal, config,
                   progress: Progress = NULL, executor: Executor = SERIAL) -> Fits:
    """Every proposed hypothesis fitted and given its first verdict; the hypotheses are independent
    work items of ``executor`` (the results do not depend on where they run)."""
    base, rd_train, rd_test = cal.base, cal.data.rd_train, cal.data.rd_test
    phys, cheap, physics = prop.fitted_in_full, prop.cheap, prop.simulated
    drops = loc.dropouts
    tried = list(prop.untestable)
    fits: list[tuple[HypFit, Verdict, float]] = []
    n_eff = max(10, base.r0.size // 2)
    rss0 = float(base.r0 @ base.r0)
    bic0 = bic(rss0, n_eff, 0)
    held_before, _ = fit_report(base.spec, rd_test)
    local_ev: dict[int, tuple[float, float]] = {}
    own_rail: dict[int, list[RecData]] = {}
    ev = Evidence(cal, config.irregularity and any(p.irregularity is not None for p in cal.data.passes))
    one = _FitOne(cal, config, ev, held_before, n_eff, bic0)
    # two stages: physics takes a simulation per step (10-150 s each), the rest ~1 s (one ETA misled)
    stages = [(f"fit {len(phys)} of {len(physics)} physics hypotheses (simulated)", phys, len(phys))]
    if cheap:
        stages.append((f"fit {len(cheap) + len(drops)} sensor and ambient hypotheses", cheap,
                       len(cheap) + len(drops)))
    for name, hyps, total in stages:
        progress.stage(name, total=total)
        outs = executor.map(one, hyps, done=lambda i, hyps=hyps: progress.advance(note=hyps[i].label))
        for o in outs:
            # the reference models a worker computed (the same values wherever computed)
            for mine, theirs in ((ev.nulls, o.nulls), (ev.halves, o.halves), (ev.test0, o.test0)):
                for k, val in theirs.items():
                    mine.setdefault(k, val)
            if o.failed is not None:
                tried.append(o.failed)
                continue
            fits.append(o.fit)
            hf = o.fit[0]
            if o.own_rail is not None:
                own_rail[id(hf)] = o.own_rail
            if o.local_ev is not None:
                local_ev[id(hf)] = o.local_ev
    if drops and not cheap:
        progress.stage(f"fit {len(drops)} sensor and ambient hypotheses", total=len(drops))
    for (n, t0, t1, val) in drops:
        fits.append(dropout_fit(base, n, t0, t1, drops, rd_train, rd_test, held_before, bic0, n_eff))
        local_ev[id(fits[-1][0])] = (fit_report(base.spec, rd_test, {n})[0],
                                     fit_report(fits[-1][0].spec, rd_test, {n})[0])
        progress.advance(note=f"{n} dropout")
    return Fits(fits, local_ev, own_rail, tried, ev, held_before, n_eff, bic0)


def recalibrated_whole(base: BaseFit, hf: HypFit, v: Verdict, rd_train, rd_test, held_before: float,
                       acceptance: AcceptanceConfig) -> tuple[HypFit, Verdict]:
    """Levitation physics that passed every gate on its channels but made the rest of the recording
    worse, with kp and kv re-fitted on the magnets' channels (the null re-fits them there too): the
    trade may be that re-fit's, not the physics'. The physics is then re-calibrated with the gains
    on EVERY channel (E, kb held) and accepted when that twin does not make the whole held-out fit
    worse (the same 2.5 % allowance); it becomes the reported model. Measured on the benchmark's
    cases: only true effects were ever rejected by that gate alone (4 ms delays; a saturation at
    1.25x the demand); with the gains re-fitted on the magnets' channels alone the girder
    sensors went 0.172 -> 0.225 (G3A) with or without the saturation, the saturation with the
    calibrated gains 0.172 -> 0.168."""
    h = hf.hyp
    try:
        sp = h.apply(base.spec, hf.params)
        rows = np.ones(residual_vector(sp, rd_train).size, bool)
        sp_all = fit_gains(BaseFit(sp, base.theta, base.jac, base.r0, 0), rd_train, rows)
        whole, _ = fit_report(sp_all, rd_test)
    except Exception as exc:        # an unstable twin: the verdict stands
        return hf, Verdict(False, v.reasons + (f"re-calibrating the gains on every channel failed ({exc})",),
                           v.heldout_before, v.heldout_after, v.delta_bic)
    tol = 1 + 0.5 * acceptance.min_rel_gain
    if not whole <= held_before * tol:
        return hf, Verdict(False, v.reasons + (
            f"with kp, kv re-calibrated on every channel too (whole held-out NRMSE {held_before:.3f} -> "
            f"{whole:.3f})",), v.heldout_before, v.heldout_after, v.delta_bic)
    cal = sp_all.calibrated_values()
    why = (f"{RECALIBRATED} (kp {cal['kp_a_per_m']:.0f} "
           f"A/m, kv {cal['kv_a_s_per_m']:.1f} A s/m): whole held-out NRMSE {held_before:.3f} -> {whole:.3f}; "
           f"with kp, kv re-fitted on its channels only it was {v.heldout_after:.3f}, a trade of the girder "
           f"sensors' fit for the magnets' that the gains make without the physics too")
    hf.spec = sp_all           # in place: the fit is known by its id (own rail, local evidence)
    return hf, Verdict(True, (why,), v.heldout_before, float(whole), v.delta_bic)


def dropout_fit(base, n, t0, t1, drops, rd_train, rd_test, held_before, bic0, n_eff):
    """A channel frozen from t0 to t1 (a data fact) as the sensor error of that channel."""
    spec = base.spec.with_(dropouts=tuple(drops))
    r = residual_vector(spec, rd_train)
    rss = float(r @ r)
    held_after, _ = fit_report(spec, rd_test)
    dbic = bic(rss, n_eff, 1) - bic0

    recs = frozen_in(n, t0, t1, [rd.rec for rd in (*rd_train, *rd_test)])
    # seconds from the start of the recording(s) holding it, when they agree on that
    rel = ([t0 - recs[0].t0_s, t1 - recs[0].t0_s]
           if recs and all(r.t0_s == recs[0].t0_s for r in recs) else None)

    def desc(p, sp, n=n, t0=t0, t1=t1, rel=rel, names=" and ".join(r.name for r in recs)):
        when = (f"{t0:.2f} s and {t1:.2f} s" if rel is None else
                f"{rel[0]:.2f} s and {rel[1]:.2f} s after the start of {names}")
        return (f"Sensor {n} stops reporting between {when} (the value stays frozen): "
                f"a dropout of the instrument or its data link, not a change of the structure.",
                {"channel": n, "kind": "dropout", "t0_s": t0, "t1_s": t1,
                 **({} if rel is None else {"recording": names, "from_start_s": rel})})
    h = cat.Hypothesis("sensor_error", f"sensor_error@{n}.dropout", ("duration_s",), (0.0,), (np.inf,),
                       (t1 - t0,), lambda sp, p: spec, needs_sim=False,
                       location={"position_m": None, "span": None, "channels": [n]}, describe=desc)
    v = judge(held_before, min(held_after, held_before), dbic, (True, ""), 0.0,
              AcceptanceConfig(min_rel_gain=0.0, min_abs_gain=0.0, max_delta_bic=-10.0))
    return HypFit(h, np.array([t1 - t0]), np.zeros_like(base.theta), rss, spec, 0), v, dbic


def frozen_in(channel: str, t0_s: float, t1_s: float, recs: Sequence[Recording]) -> list[Recording]:
    """The recordings whose ``channel`` holds a single value from t0_s to t1_s (a dropout found by
    :func:`detect_dropouts`; several when their stamps coincide)."""
    hits: dict[int, Recording] = {}
    for r in recs:
        c = r.channels.get(channel)
        if c is None:
            continue
        i0, i1 = np.searchsorted(c.time_s, [t0_s, t1_s])
        if i1 < c.time_s.size and c.time_s[i0] == t0_s and c.time_s[i1] == t1_s and np.ptp(c.values[i0:i1 + 1]) == 0:
            hits[id(r)] = r
    return list(hits.values())
