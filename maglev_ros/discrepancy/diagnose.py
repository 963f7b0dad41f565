"""Orchestration: recordings -> calibrated twin -> located mismatches -> tested physics -> report.

``Diagnoser(config).fit(passes, ambient=None) -> Diagnosis``; ``Diagnosis.to_dict()`` is the public
``maglev-diagnosis/1`` JSON. The fastest pass is the training pass (calibration and fitting), every
other pass is held out (acceptance); with a single pass the held-out set is that same pass and
the report says so in ``rejected`` (weaker evidence). Levitation physics (categories control and
magnetic_force) acts on the vehicle's channels only and is judged there (held-out NRMSE and
log-likelihood over the magnet channels and their features), provided the whole recording's
held-out NRMSE does not rise by more than half the required gain; everything else is judged on the
whole recording. Such physics is also fitted on the vehicle channels' residuals only, with kp and kv
re-fitted and E, kb held (:func:`.fitting.fit_hypothesis`), judged there against the calibrated twin
with kp, kv re-fitted on the same channels (:func:`.fitting.fit_gains`), and with the rail its own twin
reconstructs: it changes the magnet forces and so the girder deflection the loaded -> unloaded
reconstruction removes (on the calibrated twin's rail a correct 8 ms delay made the guideway
sensors' held-out fit worse, 0.335 -> 0.376; on its own rail 0.335 -> 0.175).

Which hypotheses are fitted in full: the best ``n_top`` after screening at a trial value, the best
of every further effect, and every girder/bearing hypothesis of the spans the strongest guideway
mismatches name. Sensor scale faults of guideway accelerometers are also told by their signature
against the peers (:mod:`.scale_signature`), judged against the peers' level when the twin's level
of the whole group is off, and never when another sensor of the same span is off the same way
(then it is the span). Two catalogue findings compete with an added resonator on the same span
(:mod:`.resonator`), which wins when it fits the held-out data at least as well: a sensor fault of a
guideway accelerometer (a local resonance mimics a scale error) and a girder stiffness loss (an
attachment's mass lowers the span's first mode as a loss does).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from maglev_ros.errors import UserError
from maglev_ros.progress import NULL, Progress

from . import catalogue as cat
from .catalogue import VEHICLE_WIDE
from .acceptance import AcceptanceConfig, Verdict
from .air_springs import AirSpringTermFinder
from .pipeline.calibrate import calibrate
from .pipeline.fit import RECALIBRATED, fit_hypotheses
from .pipeline.judge import combine as _combine, judge_hypotheses
from .pipeline.localize import localize
from .pipeline.propose import propose, structural_hypotheses
from .discovery import discover, mode_shift_findings, model_discoveries, persistent_findings, resonator_explainable
from .evaluate import fit_report, model_powers
from .fitting import IDENTIFIABLE_LLR, HypFit, profile_spread
from .localize import Mismatch, residual_map
from .model import ModelSpec, guideway_modal
from .recording import Recording, require_pass
from .scale_signature import PeerReferencedFit, ScaleSignature

SCHEMA = "maglev-diagnosis/1"


@dataclass(frozen=True)
class DiagnoseConfig:
    n_top: int = 4                    # physics hypotheses fully fitted after screening
    n_elements: int | None = None     # FE mesh of the diagnosing twin (None: design defaults)
    acceptance: AcceptanceConfig = AcceptanceConfig()
    base_max_nfev: int = 6
    dropout_min_s: float = 0.1
    dt_max_s: float | None = None     # integration step of the diagnosing twin (None: design numerics)
    irregularity: bool = True         # drive the twin with the irregularity reconstructed from each pass
    # the diagnosing twin's rail: reconstructed from each pass with the irregularity verb's own rule
    # (corner from the pass's clean moving stretch, band to speed / (2 corner), edges 0.6 / corner;
    # docs/irregularity.md). A fixed 0.6 Hz with the band reaching the corner itself (band factor 1)
    # cut a slow foreign pass's 1-5 m waves to 30-45 % error and its magnets' floor to NRMSE 0.3-0.4;
    # with the pass's rule the error there was 3-8 % and the magnets' NRMSE 0.18-0.19 (the true rail:
    # 0.03). None: follow the pass; a number fixes the corner [Hz]
    irregularity_highpass_hz: float | None = None
    irregularity_band_factor: float = 2.0
    irregularity_trim_wavelengths: float = 1.0
    irregularity_edge_s: float | None = None
    base_refit_nfev: int = 4          # calibration steps after the irregularity is rebuilt
    # besides the n_top best-screened: the best of every further effect and every girder/bearing
    # hypothesis of the spans the strongest guideway mismatches name (False: the n_top only)
    fit_every_effect: bool = True


@dataclass(frozen=True, eq=False)
class Diagnosis:
    report: dict
    extras: dict = field(default_factory=dict, repr=False)   # arrays for plots (not JSON)

    def to_dict(self) -> dict:
        return self.report


class Diagnoser:
    def __init__(self, config: DiagnoseConfig = DiagnoseConfig()):
        self.config = config

    # ------------------------------------------------------------------------------------
    def fit(self, passes: Sequence[Recording], ambient: Recording | None = None,
            progress: Progress = NULL) -> Diagnosis:
        if not passes:
            raise UserError("--pass: at least one pass recording is needed")
        for p in passes:
            require_pass(p)
        cfg = self.config
        # ---- calibrate
        cal = calibrate(passes, ambient, cfg, progress)
        nominal, base, damping = cal.nominal, cal.base, cal.damping
        passes, rd_all, rd_train, rd_test = cal.data.passes, cal.data.rd_all, cal.data.rd_train, cal.data.rd_test
        same_heldout, notes, raw_passes = cal.same_heldout, cal.notes, cal.prepare.raw_passes
        nr_before, pc_before = cal.fit_nrmse, cal.fit_per_channel
        # ---- localize
        loc = localize(cal, ambient, cfg, progress)
        rd_amb, maps = loc.ambient, loc.maps
        found, persistent, detuned = loc.found, loc.persistent, loc.detuned
        # ---- propose
        prop = propose(cal, loc, cfg, progress)
        screened, phys, span_of = prop.screened, prop.fitted_in_full, prop.span_of
        # ---- fit (each hypothesis fitted on the training pass and measured on the held-out ones)
        fr = fit_hypotheses(cal, loc, prop, cfg, progress)
        tried, n_eff = fr.untestable, fr.n_eff
        # ---- judge (across hypotheses: peers, signatures, the best effect and a second one on top)
        jd = judge_hypotheses(cal, loc, fr, cfg, progress)
        fits, chosen, final_spec, rd_fin = jd.fits, jd.chosen, jd.final_spec, jd.rd_fin
        by_peers, signatures, sig_of, local_ev = jd.by_peers, jd.signatures, jd.sig_of, jd.local_ev
        rejected = []
        unseen = structural_hypotheses(base.spec, rd_train[0].rec, np.ones(len(base.spec.spans)))[1]
        if unseen:
            rejected.append({"effect": "girder_stiffness_loss", "why": (
                f"not testable on span(s) {', '.join(unseen)} (nor their bearings, bearing_stiffness): no guideway "
                "sensor there; the vehicle channels alone cannot tell a span's stiffness from the rail they "
                "reconstruct")})
        body = sorted({n for rd in rd_all for n in rd.rec.names("body_accel")})
        if not body:
            # measured: a 6 or 9 Hz bending mode changes the magnet accelerations by <= 0.2 % and the
            # gap-to-rail transmissibility by <= 1.4 % (the air springs isolate the body)
            rejected.append({"effect": "carbody_flexibility", "why": (
                "not testable: the recordings have no car-body accelerometer (optional topic "
                "/testline/vehicle/body_accel); the air springs keep a car-body bending mode out of the "
                "magnet and gap channels")})
        else:
            rejected.append({"effect": "sensor_error", "why": (
                f"car-body accelerometers {', '.join(body)} not tested for sensor errors: they are compared "
                "through their ratio to the magnet accelerations above 3 Hz, which carries ~17 % model error "
                "(a fault of that size cannot be told from it)")})
        for hf, v, d in fits:
            if any(hf is c[0] for c in chosen):
                continue
            reasons = v.reasons
            if hf.hyp.effect == "control_delay" and not v.accepted and len(hf.profile) >= 3:
                # the profile's RSS is over the rows the delay was fitted on (its channels)
                null = fr.evidence.null_of(hf.hyp)
                spread = profile_spread(hf.profile, null.n_train if null is not None else n_eff)
                if spread < IDENTIFIABLE_LLR:
                    q = [x for x, _ in hf.profile]
                    reasons = reasons + (
                        f"not identifiable from these passes: with kp, kv re-fitted at each delay the training "
                        f"misfit is the same from {min(q) * 1e3:.1f} to {max(q) * 1e3:.1f} ms (log-likelihood "
                        f"spread {spread:.1f} < {IDENTIFIABLE_LLR:g}); the calibrated gains absorb a delay of "
                        "that size (a recorded magnet current, which the recording contract does not carry, or a "
                        "faster pass may separate them)",)
            why = "; ".join(reasons) if not v.accepted else (
                f"also improves the fit (held-out NRMSE {v.heldout_before:.3f} -> {v.heldout_after:.3f}) but "
                f"less than {chosen[0][0].hyp.label} for the same residual")
            rejected.append({"effect": hf.hyp.effect, "why": f"{hf.hyp.label}: {why}"})
        for _, h in screened[cfg.n_top:]:
            if any(h is p for p in phys):
                continue
            rejected.append({"effect": h.effect, "why": f"{h.label}: at its trial value it explains less of the "
                                                      f"residual than the hypotheses fitted in full (screening)"})
        for t in tried:
            rejected.append({"effect": t["effect"], "why": f"{t['label']}: {t['why']}"})
        if same_heldout:
            rejected.append({"effect": "(all)", "why": "only one pass given: the held-out check used the "
                                                      "training pass itself (weaker evidence)"})
        # ---- discovery when mismatches remain unexplained
        progress.stage("discovery")
        disc = []
        air_missing = None
        groups_of = {n: c.group for rd in rd_all for n, c in rd.rec.channels.items()}
        maps_after = [residual_map(rd, model_powers(final_spec, rd)) for rd in rd_fin]
        if not chosen:
            disc = discover(maps_after, guideway_modal(final_spec), base_spec_spans(final_spec))
            disc += persistent_findings(persistent, guideway_modal(final_spec), base_spec_spans(final_spec), disc)
            disc += mode_shift_findings(detuned, base_spec_spans(final_spec))
            if disc:
                # model what was found (added girder resonator / sparse suspension terms), judged by
                # the catalogue's gates; an accepted resonator is missing physics (see the report stage)
                disc = model_discoveries(disc, base, rd_train, rd_test, cfg.acceptance, log=notes.append)
            # the air springs, from the car-body accelerometers (their low-band misfit is the rail's
            # long-wave error on every case, so no mismatch points there: always tried when they exist)
            air = _air_spring_finding(base.spec, rd_train, rd_test, cfg.acceptance, notes.append)
            if air is not None and air["model"]["accepted"]:
                disc.insert(0, air)
                # a supported law is missing physics of the suspension (no catalogue entry has that
                # category): the twin after carries it (simulated with it, as it was judged)
                law = {**air["model"]["linear_terms"], **air["model"]["terms"]}
                final_spec = final_spec.with_(air_spring_force=tuple(law.items()))
                air_missing = _air_spring_entry(air)
                maps_after = [residual_map(rd, model_powers(final_spec, rd)) for rd in rd_fin]
            elif air is not None:
                rejected.append({"effect": "air_spring_term", "why": f"discovery (air springs): {air['explanation']}"})
        elif all(hf.hyp.effect == "sensor_error" and not hf.hyp.label.endswith(".dropout")
                 and all(groups_of.get(c, "").startswith("guideway") for c in hf.hyp.location.get("channels") or [])
                 for hf, _, _ in chosen):
            # a local resonance of the girder next to a sensor mimics that sensor's scale error: an
            # added resonator (fitted on the calibrated twin's misfit) competes, and wins only with
            # a held-out fit clearly better than the sensor error's
            accused = {c for hf, _, _ in chosen for c in hf.hyp.location.get("channels") or []}
            spans_acc = {span_of[c] for c in accused if c in span_of}
            disc = _span_findings(maps, base.spec, spans_acc, 1)
            if not disc and len(spans_acc) == 1:
                # nothing flagged on that span (a scale-like misfit stays under the localization
                # gates): the accused sensors' whole usable band is the finding to explain
                sp = next(s for s in base.spec.spans if s.span_id in spans_acc)
                e = rd_train[0].grid.edges_hz
                f_top = float(max(e[1:][rd_train[0].masks[c]].max() for c in accused if c in rd_train[0].masks))
                disc = [{"kind": "resonance", "frequency_hz": [float(e[2]), f_top], "channels": sorted(accused),
                         "location": {"position_m": [sp.start_m, sp.end_m], "span": sp.span_id},
                         "time_s": [rd_train[0].rec.t0_s, rd_train[0].rec.t1_s], "twin_modes_in_band_hz": [],
                         "score": 0.0, "explanation": f"The misfit of {', '.join(sorted(accused))} on span "
                         f"{sp.span_id}, which the catalogue attributes to the instrument, could also be the structure."}]
            if disc:
                disc = model_discoveries(disc, base, rd_train, rd_test, cfg.acceptance, max_resonators=1,
                                         log=notes.append, worst_span_fallback=False)
            ok = [d for d in disc if (d.get("model") or {}).get("accepted")]
            # (the fit of the chosen model on the whole held-out data: a fault judged against its
            # peers' level leaves the twin as is)
            held_chosen = min([fit_report(final_spec, rd_test)[0], *(v.heldout_after for hf, v, _ in chosen
                                                                     if id(hf) not in by_peers)])
            if ok and ok[0]["model"]["evidence"]["heldout_nrmse_after"] < held_chosen * (1 - cfg.acceptance.min_rel_gain):
                for hf, v, _ in chosen:
                    rejected.append({"effect": hf.hyp.effect, "why": (
                        f"{hf.hyp.label}: an added resonator on span {ok[0]['location']['span']} explains the same "
                        f"misfit better on held-out data (NRMSE {ok[0]['model']['evidence']['heldout_nrmse_after']:.3f} "
                        f"vs {v.heldout_after:.3f}): the structure, not the instrument")})
                chosen, final_spec, rd_fin = [], base.spec, rd_all
                maps_after = maps
            else:
                rejected += _resonator_rejections(disc, "it fits, but the sensor error explains the misfit as well "
                                                        f"or better (held-out NRMSE {held_chosen:.3f})")
                disc = []
        elif any(hf.hyp.effect == "girder_stiffness_loss" for hf, _, _ in chosen):
            # an attachment on a girder (added mass below its own frequency) lowers the span's first
            # mode as a stiffness loss does: the loss competes with an added resonator on its span, fitted
            # on the calibrated twin's misfit, and must fit the held-out data at least as well (a 38 Hz
            # attachment on a span was named a 9 % stiffness loss of that span)
            hf0 = next(hf for hf, _, _ in chosen if hf.hyp.effect == "girder_stiffness_loss")
            span = hf0.hyp.location.get("span")
            cand = _span_findings(maps, base.spec, {span}, 2, persistent)
            if cand:
                cand = model_discoveries(cand, base, rd_train, rd_test, cfg.acceptance, max_resonators=2,
                                         log=notes.append, worst_span_fallback=False)
            ok = [d for d in cand if (d.get("model") or {}).get("accepted")]
            held_chosen = fit_report(final_spec, rd_test)[0]
            if ok and ok[0]["model"]["evidence"]["heldout_nrmse_after"] <= held_chosen:
                rejected.append({"effect": hf0.hyp.effect, "why": (
                    f"{hf0.hyp.label}: an added resonator on span {span} explains the same misfit at least as well "
                    f"on held-out data (NRMSE {ok[0]['model']['evidence']['heldout_nrmse_after']:.3f} vs "
                    f"{held_chosen:.3f}): something attached to the girder, not a loss of its stiffness")})
                # any other chosen effect stays, with the twin rebuilt without the loss
                chosen = [c for c in chosen if c[0] is not hf0]
                final_spec, rd_fin = base.spec, rd_all
                for i, (hf, _, _) in enumerate(c for c in chosen if id(c[0]) not in by_peers):
                    final_spec = hf.spec if i == 0 else _combine(final_spec, hf)
                maps_after = ([residual_map(rd, model_powers(final_spec, rd)) for rd in rd_all]
                              if final_spec is not base.spec else maps)
                disc = ok[:1]
            else:
                rejected += _resonator_rejections(cand, "it fits, but the stiffness loss explains the misfit better "
                                                        f"(held-out NRMSE {held_chosen:.3f})")
        progress.stage("report")
        # an accepted out-of-catalogue model is missing physics like a catalogue one, and the twin after
        # carries it (as it was judged)
        found_models = [(d.pop("_fit"), d) for d in disc if "_fit" in d]
        found_missing = []
        if found_models and final_spec.resonator is None:
            rf, d = found_models[0]
            final_spec = (final_spec if chosen else rf.spec).with_(resonator=rf.resonator)
            found_missing.append(_resonator_entry(rf, d))
            maps_after = [residual_map(rd, model_powers(final_spec, rd)) for rd in rd_fin]
        nr_after, pc_after = fit_report(final_spec, rd_fin)
        missing = [self._entry(hf, v, d, final_spec, local_ev.get(id(hf)),
                               signatures[id(hf)][0] if id(hf) in signatures else sig_of.get(
                                   hf.hyp.location["channels"][0]) if id(hf) in by_peers else None,
                               by_peers.get(id(hf))) for hf, v, d in chosen]
        if air_missing:
            missing.insert(0, air_missing)
        missing += found_missing
        report = {
            "schema": SCHEMA,
            "fit_before": {"nrmse": nr_before, "per_channel": pc_before},
            "fit_after": {"nrmse": nr_after, "per_channel": pc_after},
            "mismatches": _mismatch_entries(found + [s.to_mismatch() for s in detuned], [*raw_passes, ambient]),
            "missing_physics": missing,
            "rejected": rejected,
            "updated_parameters": final_spec.calibrated_values(),
            "parameter_details": _parameter_details(nominal, final_spec),
            "calibration": {"parameters": base.spec.calibrated_values(), "damping": damping.to_dict(),
                            "fit_per_group": _per_group(pc_before, {n: c.group for rd in rd_all
                                                                    for n, c in rd.rec.channels.items()})},
        }
        if disc:
            report["discovery"] = [d for d in disc]
        groups = {n: c.group for rd in rd_all for n, c in rd.rec.channels.items()}
        for key, pc in (("fit_before", pc_before), ("fit_after", pc_after)):
            report[key]["per_group"] = _per_group(pc, groups)
        report["irregularity"] = ([_irregularity_summary(p) for p in passes]
                                  + [{"note": _named(n, [*raw_passes, ambient])} for n in notes])
        extras = {"rd_all": rd_all, "rd_after": rd_fin, "maps_before": maps, "maps_after": maps_after, "base_spec": base.spec,
                  "final_spec": final_spec, "fits": fits, "rd_ambient": rd_amb, "discovery": disc,
                  "heldout_is_training": same_heldout}
        return Diagnosis(report, extras)

    # ------------------------------------------------------------------------------------
    def _entry(self, hf: HypFit, v: Verdict, dbic: float, spec: ModelSpec,
               local: tuple[float, float] | None, sig: ScaleSignature | None = None,
               peer_fit: PeerReferencedFit | None = None) -> dict:
        h = hf.hyp
        text, params = h.describe(hf.params, spec)
        if sig is not None:
            text += (f" Told from model error by its signature: {sig.explain()} (model error differs band "
                     f"by band).")
            params = {**params, "scale_relative_to_peers": sig.relative_scale}
        if peer_fit is not None:
            text = text.replace("the other sensors agree with the twin", "the other sensors of its group agree with "
                                                                         "each other")
            g = peer_fit.group_level
            peers = ", ".join(sig.peers) if sig is not None else "the other sensors of its group"
            text += (f" Against the calibrated twin alone it does not stand out: the twin is "
                     f"{abs(1 / g - 1) * 100:.0f} % {'high' if g < 1 else 'low'} on {peers} alike (model "
                     f"error common to the group, left as is), so the fault was fitted and checked against their "
                     f"level (held-out RMS error of its band amplitudes {peer_fit.heldout_before:.3f} -> "
                     f"{peer_fit.heldout_after:.3f}); the twin is not changed for it.")
            params = {**params, "group_level_vs_twin": g}
        if local and h.category in VEHICLE_WIDE:
            held = ("the second half of the training pass, where the demand is as high, and the other passes"
                    if h.effect in cat.AMPLITUDE_DEPENDENT else "the other passes")
            text += (f" Judged on the magnets' accelerations and gap-to-rail transmissibilities, against the "
                     f"calibrated twin with kp and kv re-fitted there, on data not used for fitting ({held}): "
                     f"NRMSE {local[0]:.3f} -> {local[1]:.3f} (whole recording, held-out passes, against the "
                     f"calibrated twin: {v.heldout_before:.3f} -> {v.heldout_after:.3f}).")
            if v.reasons and v.reasons[0].startswith(RECALIBRATED):
                text += f" It is {v.reasons[0]}."
        loc = h.location
        return {"effect": h.effect, "category": h.category, "explanation": text,
                "location": {"position_m": loc.get("position_m"), "span": loc.get("span"),
                             "channels": list(loc.get("channels") or [])},
                "frequency_hz": list(h.band_hz) if h.band_hz else None,
                "parameters": params,
                "evidence": {"heldout_nrmse_before": v.heldout_before, "heldout_nrmse_after": v.heldout_after,
                             "delta_bic": float(dbic)},
                # (optional key) the held-out NRMSE over the channels the extension acts on
                **({"heldout_on_its_channels": {"channels": sorted(loc.get("channels") or []),
                                                "nrmse_before": float(local[0]), "nrmse_after": float(local[1])}}
                   if local else {})}


def _span_findings(maps, spec: ModelSpec, spans: set, n: int, persistent=None) -> list[dict]:
    """The ``n`` strongest located findings (frame findings, plus persistent ones when given) of the
    guideway sensors on ``spans``: what an added resonator there must explain."""
    modal, all_spans = guideway_modal(spec), base_spec_spans(spec)
    found = discover(maps, modal, all_spans, max_findings=12)
    if persistent is not None:
        found += persistent_findings(persistent, modal, all_spans, found)
    return [d for d in found if d["location"].get("span") in spans and resonator_explainable(d)][:n]


def _resonator_rejections(disc: list[dict], why_if_accepted: str) -> list[dict]:
    """``rejected`` entries for resonators that lost a rivalry with a catalogue effect."""
    out = []
    for d in disc:
        m = d.get("model") or {}
        why = why_if_accepted if m.get("accepted") else "; ".join(m.get("reasons") or ["not fitted"])
        out.append({"effect": "added_resonator",
                    "why": f"discovery (resonator on span {d['location'].get('span')}): {why}"})
    return out


def _air_spring_finding(spec: ModelSpec, rd_train, rd_test, acceptance, log) -> dict | None:
    """A discovery entry for a nonlinear air-spring force (:mod:`.air_springs`), or None without
    car-body accelerometers."""
    try:
        fit = AirSpringTermFinder(acceptance).fit(spec, rd_train, rd_test)
    except Exception as exc:          # an unstable twin etc.: nothing to say about the air springs
        log(f"discovery: air-spring regression failed: {exc}")
        return None
    if fit is None:
        return None
    rd = rd_train[0]
    return {"kind": "suspension_term", "category": "suspension",
            "frequency_hz": list(fit.band_hz) if fit.band_hz else None,
            "channels": list(fit.channels), "sensed_on": "vehicle",
            "location": {"position_m": None, "span": None, "place": "secondary suspension (air springs)",
                         "channels": list(fit.channels)},
            "time_s": [float(rd.rec.t0_s), float(rd.rec.t1_s)], "twin_modes_in_band_hz": [], "score": 0.0,
            "explanation": fit.explanation(), "model": fit.to_dict()}


AIR_SPRING_PARAMETERS = {"d": "stiffness_change_n_per_m", "d_rate": "damping_change_n_s_per_m",
                         "d^3": "cubic_stiffness_n_per_m3", "d^2": "quadratic_stiffness_n_per_m2",
                         "d_rate*|d_rate|": "quadratic_damping_n_s2_per_m2"}


def _air_spring_entry(air: dict) -> dict:
    """The ``missing_physics`` entry of an accepted nonlinear air-spring law (effect
    ``air_spring_nonlinearity``, category suspension: not a catalogue name). Its evidence is where it
    was judged: the car-body accelerometers at 2-8 Hz on the held-out passes, the calibrated twin
    before, the twin simulated with the law after (the law's own delta BIC is against re-fitted
    linear air springs, the stricter null)."""
    m = air["model"]
    params = {AIR_SPRING_PARAMETERS.get(k, k): float(v) for k, v in {**m["terms"], **m["linear_terms"]}.items()}
    params["force_share_at_largest_deflection"] = float(m["share_at_peak"])
    params["largest_deflection_m"] = float(m["max_deflection_m"])
    chans = list(air["channels"])
    return {"effect": "air_spring_nonlinearity", "category": "suspension", "out_of_catalogue": True,
            "explanation": air["explanation"],
            "location": {"position_m": None, "span": None, "channels": chans,
                         "place": air["location"].get("place")},
            "frequency_hz": air["frequency_hz"], "parameters": params,
            "evidence": {"heldout_nrmse_before": float(m["heldout_nrmse_twin"]),
                         "heldout_nrmse_after": float(m["heldout_nrmse_after"]),
                         "delta_bic": float(m["delta_bic"]),
                         "judged_on": m["evidence"]["judged_on"]},
            "heldout_on_its_channels": {"channels": sorted(chans), "nrmse_before": float(m["heldout_nrmse_twin"]),
                                        "nrmse_after": float(m["heldout_nrmse_after"])}}


def _resonator_entry(rf, d: dict) -> dict:
    """The ``missing_physics`` entry of an accepted added resonator (out of the catalogue: effect
    ``resonant_attachment``, or ``added_mass`` when rigid; category guideway_structure): where it sits
    (the fitted place and its mirror image on the span), the band it lives in, its fitted parameters
    and the held-out evidence it was accepted on."""
    m = d["model"]
    r = rf.resonator
    return {"effect": "added_mass" if r.rigid else "resonant_attachment", "category": "guideway_structure",
            "out_of_catalogue": True, "explanation": d["explanation"],
            "location": {"position_m": [float(x) for x in rf.position_range_m], "span": rf.span_id, "channels": []},
            "frequency_hz": [float(x) for x in d["frequency_hz"]],
            "parameters": {"own_frequency_hz": None if r.rigid else float(r.freq_hz), "mass_kg": float(rf.mass_kg),
                           "mass_ratio": float(r.mass_ratio), "position_m": float(rf.position_m),
                           "damping_ratio": None if r.rigid else float(r.damping_ratio),
                           "residual_band_hz": d.get("residual_band_hz")},
            "evidence": {"heldout_nrmse_before": m["evidence"]["heldout_nrmse_before"],
                         "heldout_nrmse_after": m["evidence"]["heldout_nrmse_after"],
                         "delta_bic": m["evidence"]["delta_bic"]}}


def _per_group(per_channel: dict, groups: dict) -> dict:
    """RMS of the per-channel NRMSE within each channel group."""
    out: dict[str, list] = {}
    for n, v in per_channel.items():
        out.setdefault(groups.get(n, "other"), []).append(v)
    return {g: float(np.sqrt(np.mean(np.square(v)))) for g, v in out.items()}


def _irregularity_summary(rec: Recording) -> dict:
    """How the twin was driven on one pass (JSON-ready)."""
    if rec.irregularity is None:
        return {"source": rec.name, "method": "none (perfect guideway)"}
    info = rec.irregularity_info or {}
    return {"source": rec.name, "method": "irregularity.twin_input.profile_for_twin (calibrated twin)",
            "valid_m": list(rec.irregularity_valid_m), "sensor_delay_s": rec.sensor_delay_s,
            "rms_m": info.get("rms_m"), "iterations": info.get("iterations"),
            "converged": info.get("converged"), "band": {k: info.get("band", {}).get(k) for k in
                                                         ("min_wavelength_m", "max_wavelength_m", "highpass_hz")}}


def _named(text: str, recs: Sequence[Recording | None]) -> str:
    """``text`` with each recording's machine path replaced by its name (reports carry no paths)."""
    for r in sorted((r for r in recs if r is not None), key=lambda r: -len(r.source)):
        text = text.replace(r.source, r.name)
    return text


def _mismatch_entries(found: Sequence[Mismatch], recs: Sequence[Recording | None]) -> list[dict]:
    """``mismatches`` of the report, most severe first, each with (optional keys) the recording's name
    and its time from that recording's first sample (None when it spans several recordings)."""
    by_source = {r.source: r for r in recs if r is not None}
    out = []
    for m in sorted(found, key=lambda m: -m.severity):
        r = by_source.get(m.recording)
        out.append({**m.to_dict(), "recording": r.name if r is not None else _named(m.recording, recs),
                    "time_from_start_s": None if r is None else [m.time_s[0] - r.t0_s, m.time_s[1] - r.t0_s]})
    return out


CAL_UNITS = {"youngs_modulus_pa": "Pa", "bearing_stiffness_n_per_m": "N/m", "kp_a_per_m": "A/m",
             "kv_a_s_per_m": "A s/m"}


def _parameter_details(nominal: ModelSpec, final: ModelSpec) -> dict:
    """Each calibrated parameter: unit, design value and updated value. No std: the calibration's
    linearised one, even cluster-robust over the channels, was 8-70x below the true error on the
    bundled sample bags (model error, not noise, rules it); ``maglev-ros update`` estimates one."""
    nom = nominal.calibrated_values()
    return {k: {"unit": CAL_UNITS.get(k, ""), "nominal": float(nom[k]), "updated": float(v), "std": None}
            for k, v in final.calibrated_values().items()}


def base_spec_spans(spec: ModelSpec):
    return spec.spans


def diagnose(passes: Sequence[Recording], ambient: Recording | None = None,
             config: DiagnoseConfig = DiagnoseConfig(), progress: Progress = NULL) -> Diagnosis:
    return Diagnoser(config).fit(passes, ambient, progress)
