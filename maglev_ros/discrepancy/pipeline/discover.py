"""Stage 6, discover: what the catalogue does not hold, modelled and judged by the same gates.

When nothing was chosen: the located findings left after the twin (resonances, persistent band
misfits, detuned span modes) are modelled as an added girder resonator or sparse suspension terms
(:mod:`..discovery`), and the air springs' force law from the car-body accelerometers
(:mod:`..air_springs`). When a chosen catalogue effect can be mimicked by a local attachment (a
guideway sensor's scale error, a girder stiffness loss), an added resonator on that span competes
and wins on a clearly better held-out fit.
"""
from __future__ import annotations

from dataclasses import dataclass

from maglev_ros.progress import NULL, Progress

from ..air_springs import AirSpringTermFinder
from ..discovery import AMBIENT_SOURCE, discover, mode_shift_findings, model_discoveries, persistent_findings, resonator_explainable
from ..evaluate import fit_report, model_powers
from ..localize import residual_map
from ..model import ModelSpec, guideway_modal
from .calibrate import Calibration
from .judge import Judgement, combine
from .localize import Localization
from .propose import Proposal


@dataclass(eq=False)
class Discovery:
    findings: list[dict]              # located findings with the model tried (report key "discovery")
    chosen: list                      # the chosen catalogue effects that still stand
    final_spec: ModelSpec             # the twin after (with an accepted air-spring law)
    rd_fin: list                      # the passes as that twin sees them
    maps_after: list                  # residual maps against it
    air_entry: dict | None            # an accepted air-spring finding (missing physics)
    rejected: list[dict]              # what lost, and why


def discover_stage(cal: Calibration, loc: Localization, prop: Proposal, jd: Judgement, config,
                   progress: Progress = NULL) -> Discovery:
    cfg = config
    base, rd_all, rd_train, rd_test = cal.base, cal.data.rd_all, cal.data.rd_train, cal.data.rd_test
    notes, maps, persistent, detuned = cal.notes, loc.maps, loc.persistent, loc.detuned
    chosen, final_spec, rd_fin, by_peers = list(jd.chosen), jd.final_spec, jd.rd_fin, jd.by_peers
    span_of = prop.span_of
    rejected: list[dict] = []
    progress.stage("discovery")
    # ---- discovery when mismatches remain unexplained
    disc = []
    air_entry = None
    groups_of = {n: c.group for rd in rd_all for n, c in rd.rec.channels.items()}
    maps_after = [residual_map(rd, model_powers(final_spec, rd)) for rd in rd_fin]
    if not chosen:
        # a mode the ambient recording shows and the twin lacks is the most direct evidence there is
        # (no vehicle, no rail): it is modelled first
        disc = ambient_mode_findings(cal, loc)
        disc += discover(maps_after, guideway_modal(final_spec), base_spec_spans(final_spec))
        disc += persistent_findings(persistent, guideway_modal(final_spec), base_spec_spans(final_spec), disc)
        disc += mode_shift_findings(detuned, base_spec_spans(final_spec))
        if disc:
            # model what was found (added girder resonator / sparse suspension terms), judged by
            # the catalogue's gates; an accepted resonator is missing physics (see the report stage)
            disc = model_discoveries(disc, base, rd_train, rd_test, cfg.acceptance, log=notes.append)
        # the air springs, from the car-body accelerometers (their low-band misfit is the rail's
        # long-wave error on every case, so no mismatch points there: always tried when they exist)
        air = air_spring_finding(base.spec, rd_train, rd_test, cfg.acceptance, notes.append)
        if air is not None and air["model"]["accepted"]:
            disc.insert(0, air)
            # a supported law is missing physics of the suspension (no catalogue entry has that
            # category): the twin after carries it (simulated with it, as it was judged)
            law = {**air["model"]["linear_terms"], **air["model"]["terms"]}
            final_spec = final_spec.with_(air_spring_force=tuple(law.items()))
            air_entry = air
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
        disc = span_findings(maps, base.spec, spans_acc, 1)
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
            rejected += resonator_rejections(disc, "it fits, but the sensor error explains the misfit as well "
                                                    f"or better (held-out NRMSE {held_chosen:.3f})")
            disc = []
    elif any(hf.hyp.effect == "girder_stiffness_loss" for hf, _, _ in chosen):
        # an attachment on a girder (added mass below its own frequency) lowers the span's first
        # mode as a stiffness loss does: the loss competes with an added resonator on its span, fitted
        # on the calibrated twin's misfit, and must fit the held-out data at least as well (a 38 Hz
        # attachment on a span was named a 9 % stiffness loss of that span)
        hf0 = next(hf for hf, _, _ in chosen if hf.hyp.effect == "girder_stiffness_loss")
        span = hf0.hyp.location.get("span")
        cand = span_findings(maps, base.spec, {span}, 2, persistent)
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
                final_spec = hf.spec if i == 0 else combine(final_spec, hf)
            maps_after = ([residual_map(rd, model_powers(final_spec, rd)) for rd in rd_all]
                          if final_spec is not base.spec else maps)
            disc = ok[:1]
        else:
            rejected += resonator_rejections(cand, "it fits, but the stiffness loss explains the misfit better "
                                                    f"(held-out NRMSE {held_chosen:.3f})")
    return Discovery(disc, chosen, final_spec, rd_fin, maps_after, air_entry, rejected)


def span_findings(maps, spec: ModelSpec, spans: set, n: int, persistent=None) -> list[dict]:
    """The ``n`` strongest located findings (frame findings, plus persistent ones when given) of the
    guideway sensors on ``spans``: what an added resonator there must explain."""
    modal, all_spans = guideway_modal(spec), base_spec_spans(spec)
    found = discover(maps, modal, all_spans, max_findings=12)
    if persistent is not None:
        found += persistent_findings(persistent, modal, all_spans, found)
    return [d for d in found if d["location"].get("span") in spans and resonator_explainable(d)][:n]


def resonator_rejections(disc: list[dict], why_if_accepted: str) -> list[dict]:
    """``rejected`` entries for resonators that lost a rivalry with a catalogue effect."""
    out = []
    for d in disc:
        m = d.get("model") or {}
        why = why_if_accepted if m.get("accepted") else "; ".join(m.get("reasons") or ["not fitted"])
        out.append({"effect": "added_resonator",
                    "why": f"discovery (resonator on span {d['location'].get('span')}): {why}"})
    return out


def air_spring_finding(spec: ModelSpec, rd_train, rd_test, acceptance, log) -> dict | None:
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


def base_spec_spans(spec: ModelSpec):
    return spec.spans


def ambient_mode_findings(cal: Calibration, loc: Localization) -> list[dict]:
    """Findings for the modes the ambient recording shows on an instrumented span that no twin mode of
    that span claims (:class:`..damping.ExtraMode`): vertical (left and right in phase) and clear of the
    spectral estimate's scatter; a torsional one is reported, not modelled (the twin is vertical)."""
    if loc.ambient is None:
        return []
    rec = loc.ambient.rec
    out = []
    for dm in cal.damping.each_span:
        sp = next((s for s in cal.base.spec.spans if s.span_id == dm.span_id), None)
        if sp is None:
            continue
        for m in dm.extra_modes:
            if m.in_the_data:
                out.append(_ambient_mode_finding(m, dm, sp, rec))
    return out


def _ambient_mode_finding(m, dm, sp, rec) -> dict:
    half = max(0.05, 2 * m.damping_ratio) * m.freq_hz
    d = {"kind": "resonance", "frequency_hz": [float(m.freq_hz - half), float(m.freq_hz + half)],
         "channels": list(dm.channels), "sensed_on": "guideway",
         "location": {"position_m": [sp.start_m, sp.end_m], "span": sp.span_id},
         "time_s": [float(rec.t0_s), float(rec.t1_s)], "twin_modes_in_band_hz": [], "score": float(m.peak_ratio),
         "rank": 2, "source": AMBIENT_SOURCE, "mode_hz": float(m.freq_hz),
         "explanation": (f"The ambient recording of span {sp.span_id} rings at {m.freq_hz:.1f} Hz "
                         f"(damping {100 * m.damping_ratio:.1f} %, spectral peak {m.peak_ratio:.1f}x the local level), "
                         f"where the twin has no mode of that span")}
    if not m.vertical:
        d["kind"] = "torsional_mode"
        d["sensed_on"] = "guideway (left and right in opposite phase)"
        d["explanation"] += ": left and right move in opposite phase, a torsional mode the vertical twin leaves out."
    else:
        d["explanation"] += ": something attached to the girder, or a mode the twin leaves out."
    return d
