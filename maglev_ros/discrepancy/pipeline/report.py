"""Stage 7, report: the ``maglev-diagnosis/1`` JSON, what was found, what was not and why.

``missing_physics``: the chosen catalogue effects (their place, band, parameters in a rail engineer's
words and the held-out evidence), an accepted air-spring law and an accepted added resonator (out of
the catalogue, its own name and category); ``rejected``: every hypothesis that was tried and lost,
and what could not be tested with these recordings; ``fit_before`` / ``fit_after``: the calibrated
twin and the twin after (which carries what was found); ``calibration``: what the base twin was set
to before any hypothesis, how well it fits per channel group and what limits that fit
(``fit_floor``: the gap sensors' noise in the rail it is driven by, :mod:`..floor`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from maglev_ros.progress import NULL, Progress

from .. import catalogue as cat
from ..acceptance import Verdict
from ..bias_signature import BiasSignature
from ..catalogue import VEHICLE_WIDE
from ..evaluate import fit_report, model_powers, per_group
from ..fitting import IDENTIFIABLE_LLR, HypFit, profile_spread
from ..floor import rail_floor
from ..localize import Mismatch, region_after, residual_map
from ..mode_pattern import mode_pattern
from ..model import ModelSpec
from ..recording import Recording
from ..scale_signature import PeerReferencedFit, ScaleSignature
from .calibrate import Calibration
from .discover import Discovery
from .fit import RECALIBRATED, Fits
from .judge import Judgement, judged_where_it_acts
from .localize import Localization
from .propose import Proposal
from .recalibrate import recalibrate

SCHEMA = "maglev-diagnosis/1"


@dataclass(frozen=True, eq=False)
class Diagnosis:
    report: dict
    extras: dict = field(default_factory=dict, repr=False)   # arrays for plots (not JSON)

    def to_dict(self) -> dict:
        return self.report


def rejections(cal: Calibration, prop: Proposal, fr: Fits, jd: Judgement, config) -> list[dict]:
    """Every hypothesis tried that was not chosen, and what these recordings cannot test, with why."""
    cfg = config
    rd_all = cal.data.rd_all
    fits, chosen, same_heldout = jd.fits, jd.chosen, cal.same_heldout
    screened, phys, tried, n_eff = prop.screened, prop.fitted_in_full, fr.untestable, fr.n_eff
    rejected = []
    unseen = prop.unmeasured_spans
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
        form = next((c for c in chosen if c[0].hyp.effect == hf.hyp.effect and judged_where_it_acts(c[0], jd.local_ev)
                     and judged_where_it_acts(hf, jd.local_ev)), None)
        if v.accepted and form is not None:
            why = (f"another form of {hf.hyp.effect}: on the channels they act on it fits the held-out passes "
                   f"less well ({jd.local_ev[id(hf)][1]:.3f} vs {jd.local_ev[id(form[0])][1]:.3f} for "
                   f"{form[0].hyp.label})")
        elif v.accepted and all(c[0].hyp.effect != hf.hyp.effect for c in chosen):
            on_top = [c[0].hyp.label for c in chosen if id(c[0]) not in jd.by_peers]
            why = (f"improves the fit alone (held-out NRMSE {v.heldout_before:.3f} -> {v.heldout_after:.3f}) but "
                   + (f"not clearly on top of {', '.join(on_top)}" if len(on_top) < 2 else
                      "the twin after carries two effects already"))
        else:
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
    return rejected


def build_report(cal: Calibration, loc: Localization, prop: Proposal, fr: Fits, jd: Judgement, dc: Discovery,
                 ambient: Recording | None, config, progress: Progress = NULL):
    nominal, base, damping = cal.nominal, cal.base, cal.damping
    passes, rd_all = cal.data.passes, cal.data.rd_all
    same_heldout, notes, raw_passes = cal.same_heldout, cal.notes, cal.prepare.raw_passes
    nr_before, pc_before = cal.fit_nrmse, cal.fit_per_channel
    floor = rail_floor(base.spec, rd_all, nr_before)
    rd_amb, maps, found, detuned = loc.ambient, loc.maps, loc.found, loc.detuned
    fits, by_peers, signatures, sig_of, local_ev = jd.fits, jd.by_peers, jd.signatures, jd.sig_of, jd.local_ev
    disc, chosen, final_spec, rd_fin, maps_after = dc.findings, dc.chosen, dc.final_spec, dc.rd_fin, dc.maps_after
    rejected = rejections(cal, prop, fr, jd, config) + dc.rejected
    air_missing = _air_spring_entry(dc.air_entry) if dc.air_entry else None
    # an accepted out-of-catalogue model is missing physics like a catalogue one, and the twin after
    # carries it (as it was judged)
    found_models = [(d.pop("_fit"), d) for d in disc if "_fit" in d]
    found_missing = []
    if found_models and final_spec.resonator is None:
        rf, d = found_models[0]
        final_spec = (final_spec if chosen else rf.spec).with_(resonator=rf.resonator)
        found_missing.append(_resonator_entry(rf, d))
        maps_after = [residual_map(rd, model_powers(final_spec, rd)) for rd in rd_fin]
    recal = None
    if final_spec is not base.spec:
        progress.stage("re-calibrate the twin with the found physics")
        recal = recalibrate(cal, final_spec, rd_fin, config)
        if recal.kept:
            final_spec, rd_fin = recal.spec, recal.rd_all
            maps_after = [residual_map(rd, model_powers(final_spec, rd)) for rd in rd_fin]
    progress.stage("report")
    nr_after, pc_after = fit_report(final_spec, rd_fin)
    missing = [catalogue_entry(hf, v, d, final_spec, local_ev.get(id(hf)),
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
        "mismatches": _mismatch_entries(found + [s.to_mismatch() for s in detuned], [*raw_passes, ambient],
                                        _maps_by_source(loc, final_spec, maps_after))
                      + _pattern_entries(loc, cal, final_spec, ambient, [*raw_passes, ambient]),
        "missing_physics": missing,
        "rejected": rejected,
        "updated_parameters": final_spec.calibrated_values(),
        "parameter_details": _parameter_details(nominal, final_spec),
        "calibration": {"parameters": base.spec.calibrated_values(), "damping": damping.to_dict(),
                        "fit_per_group": per_group(pc_before, {n: c.group for rd in rd_all
                                                                for n, c in rd.rec.channels.items()}),
                        **({"fit_floor": floor.to_dict()} if floor is not None else {}),
                        **({"heldout_guard": cal.guard.to_dict()} if cal.guard else {}),
                        **({"sensor_delay": cal.sensor_delay} if cal.sensor_delay else {}),
                        **({"instrument_band": [lim.to_dict() for lim in cal.prepare.band_limits.values()]}
                           if cal.prepare.band_limits else {}),
                        **({"mode_pattern": loc.mode_pattern.to_dict()} if loc.mode_pattern else {}),
                        **({"mode_patterns": [p.to_dict() for p in loc.mode_patterns]}
                           if len(loc.mode_patterns) > 1 else {}),
                        **({"with_found_physics": recal.to_dict()} if recal is not None else {})},
    }
    if disc:
        report["discovery"] = [d for d in disc]
    groups = {n: c.group for rd in rd_all for n, c in rd.rec.channels.items()}
    for key, pc in (("fit_before", pc_before), ("fit_after", pc_after)):
        report[key]["per_group"] = per_group(pc, groups)
    report["irregularity"] = ([_irregularity_summary(p) for p in passes]
                              + [{"note": _named(n, [*raw_passes, ambient])} for n in notes])
    extras = {"rd_all": rd_all, "rd_after": rd_fin, "maps_before": maps, "maps_after": maps_after, "base_spec": base.spec,
              "final_spec": final_spec, "fits": fits, "rd_ambient": rd_amb, "discovery": disc,
              "heldout_is_training": same_heldout}
    return Diagnosis(report, extras)


def catalogue_entry(hf: HypFit, v: Verdict, dbic: float, spec: ModelSpec,
           local: tuple[float, float] | None, sig: ScaleSignature | BiasSignature | None = None,
           peer_fit: PeerReferencedFit | None = None) -> dict:
    h = hf.hyp
    text, params = h.describe(hf.params, spec)
    if isinstance(sig, BiasSignature):
        text += f" Told from the motion of what it sits on by its 1 s means: {sig.explain()}."
        params = {**params, "bias_level_relative_to_peers": min(sig.level_ratio_per_rec)}
    elif sig is not None:
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


def _irregularity_summary(rec: Recording) -> dict:
    """How the twin was driven on one pass (JSON-ready)."""
    if rec.irregularity is None:
        return {"source": rec.name, "method": "none (perfect guideway)"}
    info = rec.irregularity_info or {}
    return {"source": rec.name, "method": "irregularity.twin_input.profile_for_twin (calibrated twin)",
            "valid_m": list(rec.irregularity_valid_m), "sensor_delay_s": rec.sensor_delay_s,
            "rms_m": info.get("rms_m"), "iterations": info.get("iterations"),
            "converged": info.get("converged"), "band": {k: info.get("band", {}).get(k) for k in
                                                         ("min_wavelength_m", "max_wavelength_m", "highpass_hz")},
            "spacing_m": info.get("spacing_m"), "denoise": info.get("denoise"),
            "shared": {k: (info.get("shared") or {}).get(k) for k in ("used", "reason", "split_wavelength_m")}
            if info.get("shared") else None}


def _named(text: str, recs: Sequence[Recording | None]) -> str:
    """``text`` with each recording's machine path replaced by its name (reports carry no paths)."""
    for r in sorted((r for r in recs if r is not None), key=lambda r: -len(r.source)):
        text = text.replace(r.source, r.name)
    return text


def _mismatch_entries(found: Sequence[Mismatch], recs: Sequence[Recording | None],
                      maps: dict | None = None) -> list[dict]:
    """``mismatches`` of the report, most severe first, each with (optional keys) the recording's name
    and its time from that recording's first sample (None when it spans several recordings), and
    ``after_found_physics`` (``maps``: source -> (map before, map against the final twin)): its
    cells' mean severity and the share still flagged once the found physics is in the twin."""
    by_source = {r.source: r for r in recs if r is not None}
    out = []
    for m in sorted(found, key=lambda m: -m.severity):
        r = by_source.get(m.recording)
        e = {**m.to_dict(), "recording": r.name if r is not None else _named(m.recording, recs),
             "time_from_start_s": None if r is None else [m.time_s[0] - r.t0_s, m.time_s[1] - r.t0_s]}
        pair = (maps or {}).get(m.recording)
        after = region_after(m, *pair) if pair else None
        if after is not None:
            e["after_found_physics"] = after
        out.append(e)
    return out


def _pattern_entries(loc: Localization, cal: Calibration, final_spec: ModelSpec, ambient: Recording | None,
                     recs: Sequence[Recording | None]) -> list[dict]:
    """Each instrumented span's mode ratio as a mismatch when it is off the twin's, and whether the twin
    after (with the found physics) still has it off (``after_found_physics``)."""
    out = []
    for p in loc.mode_patterns:
        if not p.flagged:
            continue
        m = p.to_mismatch()
        e = {**m.to_dict(), "recording": _named(m.recording, recs), "time_from_start_s": None}
        span = next((d for d in cal.damping.each_span if d.span_id == p.span_id), None)
        if final_spec is not cal.base.spec and span is not None:
            q = mode_pattern(span, final_spec, ambient)
            if q is not None:
                e["after_found_physics"] = {"ratio_shift": math.exp(q.log_ratio_shift) - 1,
                                            "standard_errors": q.n_sigma, "explained": not q.flagged}
        out.append(e)
    return out


def _maps_by_source(loc: Localization, final_spec: ModelSpec, maps_after: list) -> dict:
    """source -> (residual map against the calibrated twin, against the final one), every recording
    the mismatches come from (the passes, and the ambient one)."""
    after = {m.rd.rec.source: m for m in maps_after}
    out = {m.rd.rec.source: (m, after[m.rd.rec.source]) for m in loc.maps if m.rd.rec.source in after}
    if loc.ambient_map is not None:
        rd = loc.ambient
        out[rd.rec.source] = (loc.ambient_map, residual_map(rd, model_powers(final_spec, rd)))
    return out


CAL_UNITS = {"youngs_modulus_pa": "Pa", "bearing_stiffness_n_per_m": "N/m", "kp_a_per_m": "A/m",
             "kv_a_s_per_m": "A s/m", "density_kg_m3": "kg/m^3"}


def _parameter_details(nominal: ModelSpec, final: ModelSpec) -> dict:
    """Each calibrated parameter: unit, design value and updated value. No std: the calibration's
    linearised one, even cluster-robust over the channels, was 8-70x below the true error on the
    bundled sample bags (model error, not noise, rules it); ``maglev-ros update`` estimates one."""
    nom = nominal.calibrated_values()
    return {k: {"unit": CAL_UNITS.get(k, ""), "nominal": float(nom[k]), "updated": float(v), "std": None}
            for k, v in final.calibrated_values().items()}
