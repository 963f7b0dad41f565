"""Stage 5, judge: the fitted hypotheses against each other, and what the twin after carries.

Sensor scale faults are told from model error by their band signature against the peers
(:mod:`..scale_signature`), accelerometer biases by their 1 s means (:mod:`..bias_signature`); a
scale-like misfit another sensor of the same span shares is the span, not one sensor; a fault the
twin's own level hides (the whole group off) is judged against the peers' level. Of the hypotheses
every gate accepted, the best on the held-out passes is chosen, and a second effect of another kind
on top when it clearly improves the held-out fit again; a sensor bias when it fits its own channel
better. Instrument findings judged against the peers' level are reported but leave the twin as is.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from maglev_ros.progress import NULL, Progress

from ..acceptance import AcceptanceConfig, Verdict, judge_where_it_acts
from ..bias_signature import BiasSignature, bias_signature
from ..catalogue import VEHICLE_WIDE
from ..evaluate import fit_report, levitation_items, model_powers
from ..fitting import _GAINS, HypFit
from ..model import ModelSpec
from ..recording import Recording
from ..scale_signature import (MIN_ABS_LOG_SCALE, PeerReferencedFit, ScaleSignature, peer_referenced_fit,
                              scale_signature)
from .calibrate import Calibration
from .fit import Fits
from .localize import Localization
from .propose import guideway_spans


@dataclass(eq=False)
class Judgement:
    fits: list                        # (HypFit, Verdict, delta BIC), verdicts updated by this stage
    chosen: list                      # the accepted ones the report names, best first
    final_spec: ModelSpec             # the twin after: calibrated + chosen physics
    rd_fin: list                      # the passes as that twin sees them (its own rail)
    by_peers: dict                    # id(HypFit) -> PeerReferencedFit (judged against the peers' level)
    signatures: dict                  # id(HypFit) -> (ScaleSignature | BiasSignature, Verdict)
    sig_of: dict                      # channel -> ScaleSignature | None
    local_ev: dict                    # id(HypFit) -> held-out NRMSE on its channels (before, after)


def judge_hypotheses(cal: Calibration, loc: Localization, fr: Fits, config,
                     progress: Progress = NULL) -> Judgement:
    cfg = config
    base, rd_all, rd_train, rd_test = cal.base, cal.data.rd_all, cal.data.rd_train, cal.data.rd_test
    same_heldout, mp_base = cal.same_heldout, loc.model_powers
    fits, local_ev, own_rail, held_before = list(fr.fits), dict(fr.local_ev), fr.own_rail, fr.held_before
    progress.stage("held-out judgement (peers, combinations)")
    # the scale-fault signature of every channel with a sensor_error fit, computed once
    recs = [({n: c.group for n, c in rd.rec.channels.items()}, rd.pm, mp, rd.masks)
            for rd, mp in zip(rd_all, mp_base)]
    sig_of = {ch: scale_signature(ch, recs) for hf, _, _ in fits if hf.hyp.effect == "sensor_error"
              for ch in hf.hyp.location["channels"][:1]}
    # a scale-like misfit that another sensor of the same span shares is the span, not one sensor
    for n, why in _span_wide(sig_of, recs, rd_train[0].rec, base.spec).items():
        sig_of[n] = None
        fits = [(hf, Verdict(v.accepted, v.reasons + (why,), v.heldout_before, v.heldout_after, v.delta_bic), d)
                if hf.hyp.effect == "sensor_error" and hf.hyp.location["channels"][:1] == [n] and not v.accepted
                else (hf, v, d) for hf, v, d in fits]
    signatures = _scale_signatures(fits, sig_of, local_ev, cfg.acceptance)
    fits = [(hf, signatures[id(hf)][1], d) if id(hf) in signatures else (hf, v, d) for hf, v, d in fits]
    fits = [_scale_needs_its_signature(hf, v, d, sig_of) for hf, v, d in fits]
    biases = _bias_signatures(fits, [rd.rec for rd in rd_all], local_ev, cfg.acceptance)
    signatures.update(biases)
    fits = [(hf, biases[id(hf)][1], d) if id(hf) in biases else (hf, v, d) for hf, v, d in fits]
    def scale_carries(hf):
        nr, _ = fit_report(hf.hyp.apply(base.spec, np.array([0.0, *map(float, hf.params[1:])])), rd_test)
        return not cfg.acceptance.clear_gain(held_before, nr)
    fits = _peer_check(fits, rd_train[0].rec, {ch for ch, sg in sig_of.items() if sg is not None and sg.holds},
                       cfg.acceptance.max_delta_bic, scale_carries)
    # a scale fault whose signature holds but which the twin's own level hides (the whole group off)
    peer_ref = _peer_referenced(fits, sig_of, recs, same_heldout, cfg.acceptance, base.spec, held_before)
    fits = [peer_ref[id(hf)][0] if id(hf) in peer_ref else (hf, v, d) for hf, v, d in fits]
    by_peers = {id(t[0]): pf for t, pf in peer_ref.values()}
    local_ev.update({id(t[0]): (pf.heldout_before, pf.heldout_after) for t, pf in peer_ref.values()})
    accepted = _one_form_per_effect([(hf, v, d) for hf, v, d in fits if v.accepted and id(hf) not in by_peers],
                                    local_ev)
    accepted.sort(key=lambda t: t[1].heldout_after)
    chosen = []
    final_spec = base.spec
    rd_fin = rd_all        # the passes as the final twin sees them (its own rail, levitation physics)
    if accepted:
        best = accepted[0]
        chosen.append(best)
        final_spec = best[0].spec
        rd_fin = own_rail.get(id(best[0]), rd_all)
        rd_fin_test = rd_fin[:1] if same_heldout else rd_fin[1:]
        # a second, different effect on top (e.g. a faulty sensor plus a structural change)
        for hf, v, d in accepted[1:]:
            if hf.hyp.effect != best[0].hyp.effect and len(chosen) < 2 and id(hf) not in biases:
                combo = combine(final_spec, hf)
                # levitation physics on top is judged, as alone, with the rail its own twin reconstructs
                # (a 2 ms delay on a damaged zone's rail: magnets 0.201 -> 0.184; it was accepted alone
                # at 0.132 -> 0.065 on its own)
                rd_combo = (cal.prepare(combo, floor_spec=base.spec, log=None).rd_all
                            if fr.evidence.rebuild and hf.hyp.category in VEHICLE_WIDE else rd_fin)
                rd_combo_test = rd_combo[:1] if same_heldout else rd_combo[1:]
                nr_c, _ = fit_report(combo, rd_combo_test)
                now, _ = fit_report(final_spec, rd_fin_test)
                if cfg.acceptance.clear_gain(now, nr_c) \
                        or _helps_where_it_acts(hf, combo, final_spec, rd_fin_test, rd_combo_test, nr_c, now, local_ev,
                                                cfg.acceptance):
                    chosen.append((hf, v, d))
                    final_spec = combo
                    rd_fin, rd_fin_test = rd_combo, rd_combo_test
    # a sensor bias acts on its channel alone: carried when it fits that channel better on the held-out
    # passes, whatever else the twin carries
    for hf, v, d in accepted:
        if id(hf) in biases and all(hf is not c[0] for c in chosen):
            combo = combine(final_spec, hf)
            if _helps_its_channel(hf, combo, final_spec, rd_fin[:1] if same_heldout else rd_fin[1:], cfg.acceptance):
                chosen.append((hf, v, d))
                final_spec = combo
    # instrument findings judged against the peers' level: reported, the twin is left as is. Re-judged
    # against the twin with the physics chosen above: a bearing at 5 % of its stiffness made the
    # quarter-span sensor next to it read 3.4x its peers' level against the calibrated twin, and
    # that was also called a sensor fault)
    recs_final = recs
    if chosen and any(id(hf) in by_peers for hf, _, _ in fits):
        recs_final = [(g, pm, model_powers(final_spec, rd), mk) for (g, pm, _, mk), rd in zip(recs, rd_fin)]
    for hf, v, d in fits:
        if id(hf) not in by_peers or not v.accepted:
            continue
        n = hf.hyp.location["channels"][0]
        if recs_final is not recs:
            sig_n = scale_signature(n, recs_final)
            pf_n = peer_referenced_fit(n, recs_final[:1], recs_final[:1] if same_heldout else recs_final[1:])
            why = _peer_gates(hf.hyp, sig_n, pf_n, cfg.acceptance)
            if why:
                fits = [(f, Verdict(False, (f"against the twin with {', '.join(c[0].hyp.label for c in chosen)}: "
                                            f"{why}",), v.heldout_before, v.heldout_after, d), d2)
                        if f is hf else (f, v2, d2) for f, v2, d2 in fits]
                continue
            by_peers[id(hf)] = pf_n
            sig_of[n] = sig_n
            local_ev[id(hf)] = (pf_n.heldout_before, pf_n.heldout_after)
        chosen.append((hf, v, d))
    return Judgement(fits, chosen, final_spec, rd_fin, by_peers, signatures, sig_of, local_ev)


def judged_where_it_acts(hf, local_ev: dict) -> bool:
    """Levitation physics with held-out evidence on the channels it acts on (it was accepted there)."""
    return hf.hyp.category in VEHICLE_WIDE and id(hf) in local_ev and bool(hf.hyp.location.get("channels"))


def _helps_where_it_acts(hf, combo: ModelSpec, now_spec: ModelSpec, rd_now: list, rd_combo: list,
                         whole_combo: float, whole_now: float, local_ev: dict, acc: AcceptanceConfig) -> bool:
    """Levitation physics on top of another effect is judged by the held-out gates it was accepted by
    (:func:`..acceptance.judge_where_it_acts`: on the channels it acts on, the rest not worse). On the
    whole recording a control delay on top of a damaged zone (the magnets' items 0.20 -> 0.18) was
    lost among the guideway sensors. ``rd_now``/``rd_combo``: the held-out passes as each twin sees them."""
    if not judged_where_it_acts(hf, local_ev):
        return False
    at = levitation_items(set(hf.hyp.location["channels"]))
    before, _ = fit_report(now_spec, rd_now, at)
    after, _ = fit_report(combo, rd_combo, at)
    # only the held-out gates: BIC, plausibility and collinearity were judged when it was accepted
    return judge_where_it_acts(whole_now, whole_combo, before, after, -math.inf, (True, ""), 0.0, acc).accepted


def _one_form_per_effect(accepted: list, local_ev: dict) -> list:
    """Of the accepted forms of one levitation effect (a transport delay, a first-order lag), the one
    that fits best on the channels it acts on: the forms differ only there, and the whole recording
    also carries what the calibration traded for the effect (a transport delay fitted the magnets'
    held-out items 2x better than a lag, but the guideway calibrated without it fitted worse with it,
    so the lag won on the whole recording)."""
    best: dict = {}
    for t in accepted:
        if judged_where_it_acts(t[0], local_ev):
            cur = best.get(t[0].hyp.effect)
            if cur is None or local_ev[id(t[0])][1] < local_ev[id(cur[0])][1]:
                best[t[0].hyp.effect] = t
    return [t for t in accepted if not judged_where_it_acts(t[0], local_ev) or best.get(t[0].hyp.effect) is t]


SIBLING_LOG_SCALE = 0.10   # |ln| off the peers in every pass; healthy channels: min over passes <= 0.073


def _span_wide(sig_of: dict, recs: list, rec: Recording, spec: ModelSpec) -> dict:
    """Channels whose scale-fault signature holds while another guideway sensor of the SAME span is
    off its peers the same way (>= SIBLING_LOG_SCALE in every recording): channel -> why. Two
    sensors of one span reading high together is the span (a bearing at 30 % of its stiffness made
    both S3 sensors read 1.3-1.6x their peers and both were called faulty),
    not two faulty sensors."""
    span_of = guideway_spans(rec, spec, ("guideway_accel",))
    out = {}
    for n, sg in sig_of.items():
        if sg is None or not sg.holds or n not in span_of:
            continue
        sign = np.sign(sg.log_scale_per_pass[0])
        for m in sorted(span_of):
            if m == n or span_of[m] != span_of[n]:
                continue
            sm = scale_signature(m, recs)
            if sm is not None and all(np.sign(x) == sign and abs(x) >= SIBLING_LOG_SCALE for x in sm.log_scale_per_pass):
                out[n] = (f"{m} on the same span {span_of[n]} reads {'high' if sign > 0 else 'low'} against its peers "
                          f"too (x{sm.relative_scale:.2f}): a change of the span, not one faulty sensor")
                break
    return out


def _rejected_sensor_fits(fits: list, local_ev: dict):
    """(fit, verdict, delta BIC, channel, held-out NRMSE on the channel before, after) of every
    sensor scale/offset/drift fit the held-out gates rejected that has evidence on its channel."""
    for hf, v, d in fits:
        h = hf.hyp
        if v.accepted or h.effect != "sensor_error" or h.label.endswith(".dropout") or id(hf) not in local_ev:
            continue
        yield (hf, v, d, h.location["channels"][0], *local_ev[id(hf)])


def _accepted_on_its_channel(v: Verdict, n: str, before: float, after: float, by: str) -> Verdict:
    return Verdict(True, (f"accepted on its channel (held-out NRMSE of {n} {before:.3f} -> {after:.3f}) by {by}",),
                   v.heldout_before, v.heldout_after, v.delta_bic)


def _scale_signatures(fits: list, sig_of: dict, local_ev: dict, acc: AcceptanceConfig) -> dict:
    """A scale fault of one channel barely moves the whole-recording fit, which the held-out gates
    judge (see :mod:`.scale_signature`). A sensor_error fit rejected by them is accepted
    when its channel shows the scale-fault signature against its peers in every recording, the fitted
    scale goes the same way, it beats the calibrated twin on BIC with plausible values, and its
    held-out fit on the channel itself improves clearly (>= 4x the relative gain the whole recording
    needs). Returns id(HypFit) -> (signature, new verdict) for those accepted."""
    out = {}
    for hf, v, d, n, before, after in _rejected_sensor_fits(fits, local_ev):
        sig = sig_of.get(n)
        if sig is None or not sig.holds:
            continue
        if (np.sign(float(hf.params[0])) == np.sign(sig.log_scale_per_pass[0]) and d <= acc.max_delta_bic
                and hf.hyp.plausible(hf.params)[0] and after <= before * (1 - 4 * acc.min_rel_gain)):
            out[id(hf)] = (sig, _accepted_on_its_channel(v, n, before, after,
                                                         f"the scale-fault signature: {sig.explain()}"))
    return out


def _bias_signatures(fits: list, recordings: list[Recording], local_ev: dict, acc: AcceptanceConfig) -> dict:
    """A bias of one accelerometer barely moves the whole-recording fit (:mod:`..bias_signature`). A
    sensor_error fit rejected by the held-out gates is accepted when its channel's 1 s means stand out
    from its peers' in every recording (the signature holds), it beats the calibrated twin on BIC with
    plausible values, and it clears the held-out gates on its own channel. Returns
    id(HypFit) -> (signature, new verdict) for those accepted."""
    out = {}
    for hf, v, d, n, before, after in _rejected_sensor_fits(fits, local_ev):
        sig = bias_signature(n, recordings)
        if sig is None or not sig.holds:
            continue
        if d <= acc.max_delta_bic and hf.hyp.plausible(hf.params)[0] and acc.clear_gain(before, after):
            out[id(hf)] = (sig, _accepted_on_its_channel(v, n, before, after, f"the bias signature: {sig.explain()}"))
    return out


def _helps_its_channel(hf, combo: ModelSpec, now_spec: ModelSpec, rd_test: list, acc: AcceptanceConfig) -> bool:
    """The held-out gates on the one channel a sensor error acts on (the others are unchanged)."""
    ch = {hf.hyp.location["channels"][0]}
    return acc.clear_gain(fit_report(now_spec, rd_test, ch)[0], fit_report(combo, rd_test, ch)[0])


def _scale_needs_its_signature(hf, v: Verdict, d: float, sig_of: dict) -> tuple:
    """A sensor_error accepted by the held-out gates with a clear scale (|ln s| >= the signature's
    ``MIN_ABS_LOG_SCALE``) on a channel whose misfit against its peers is NOT the same factor in every
    band and recording (:mod:`.scale_signature`) is rejected: a scale fault multiplies every band alike,
    a local structural change (an attachment detuning its span's first mode: +16 % at 18-22 Hz, -40 % at
    26-31 Hz) does not. With the twin's own error small (prewarped modes), one channel's misfit moves
    the whole held-out NRMSE by ~10 % and passed those gates: a 38 Hz attachment on a span was called
    a 0.78 scale fault of the sensor next to it."""
    h = hf.hyp
    if not v.accepted or h.effect != "sensor_error" or h.label.endswith(".dropout"):
        return hf, v, d
    sig = sig_of.get(h.location["channels"][0])
    ln_s = float(hf.params[0])
    if sig is None or sig.holds or abs(ln_s) < MIN_ABS_LOG_SCALE:
        return hf, v, d
    why = (f"fitted scale x{math.exp(ln_s):.2f}, but a scale fault reads the same factor in every band and "
           f"recording and this channel does not ({sig.explain()}): the structure near it or the twin, "
           "not the instrument")
    return hf, Verdict(False, (why,), v.heldout_before, v.heldout_after, v.delta_bic), d


def _peer_gates(h, sig: ScaleSignature | None, pf: PeerReferencedFit | None, acc: AcceptanceConfig) -> str:
    """Why a scale fault judged against its peers' level fails ('' when it passes): the signature
    must hold, the fitted scale go its way with plausible value, delta BIC <= the catalogue's, and the
    held-out gain on the channel be >= 4x the relative gain the whole recording needs."""
    if sig is None or not sig.holds:
        return "its scale-fault signature against its peers does not hold"
    if pf is None:
        return "not testable against its peers"
    p = np.array([pf.log_scale, 0.0, 0.0])
    ok, why = h.plausible(p)
    if not ok:
        return why
    if np.sign(pf.log_scale) != np.sign(sig.log_scale_per_pass[0]):
        return "the fitted scale goes against the signature"
    if pf.delta_bic > acc.max_delta_bic:
        return f"delta BIC {pf.delta_bic:+.1f} against its peers' level (needs <= {acc.max_delta_bic:g})"
    if pf.heldout_after > pf.heldout_before * (1 - 4 * acc.min_rel_gain):
        return (f"held-out error against its peers' level {pf.heldout_before:.3f} -> {pf.heldout_after:.3f} is "
                f"not a clear improvement")
    return ""


def _peer_referenced(fits: list, sig_of: dict, recs: list, same_heldout: bool, acc: AcceptanceConfig,
                     base_spec_: ModelSpec, held_before: float) -> dict:
    """A sensor_error fit still rejected although its channel shows the scale-fault signature: judged
    against its peers' level (:class:`.scale_signature.PeerReferencedFit`, :func:`_peer_gates`).
    Returns id(HypFit) -> ((new HypFit, Verdict, delta BIC), the peer fit). The new fit leaves the
    twin unchanged (``spec`` = the calibrated twin), so its whole-recording held-out NRMSE stays
    ``held_before``; the peer-referenced errors are its evidence on its own channel."""
    out = {}
    for hf, v, d in fits:
        h = hf.hyp
        if v.accepted or h.effect != "sensor_error" or h.label.endswith(".dropout"):
            continue
        n = h.location["channels"][0]
        sig = sig_of.get(n)
        if sig is None or not sig.holds:
            continue
        pf = peer_referenced_fit(n, recs[:1], recs[:1] if same_heldout else recs[1:])
        if _peer_gates(h, sig, pf, acc):
            continue
        nf = HypFit(h, np.array([pf.log_scale, 0.0, 0.0]), np.zeros_like(hf.cal_delta), hf.rss, base_spec_, 0)
        out[id(hf)] = ((nf, Verdict(True, (f"accepted against its peers' level (held-out error of {n} "
                                           f"{pf.heldout_before:.3f} -> {pf.heldout_after:.3f}) by the scale-fault "
                                           f"signature: {sig.explain()}",),
                                    held_before, held_before, pf.delta_bic), pf.delta_bic), pf)
    return out


def _peer_check(fits: list, rec: Recording, scale_faulty: set[str] = frozenset(), acc_bic: float = -10.0,
                scale_carries=lambda hf: True) -> list:
    """The sensor_error signature is ONE channel off while the others agree with the twin: a
    scale/offset/drift fit that a channel of the same group (same quantity, e.g. the other
    magnet's gap) matches by at least half its training delta BIC points to a mismatch common to
    the group (the model, or the irregularity rebuilt from those very channels), not one sensor.
    Such fits are rejected with that reason (dropouts are data facts and are kept), unless the
    channel shows the scale-fault signature against its peers and that peer does not
    (``scale_faulty``: the channels whose signature holds, :mod:`.scale_signature`): then the peer's gain is the group's model
    error, not a common mismatch (a 0.75 scale on G3Q was rejected because G3A, same span, improved
    too, while only G3Q was off its peers in every band: -0.19/-0.26 in ln, all bands).
    A fit whose held-out gain needs its scale is also rejected when a peer fits a scale of the same
    sign and at least half its size with BIC support of its own (``acc_bic``): the twin's level of
    that quantity is off. ``scale_carries(fit)``: True when its offset and drift alone do not clear the
    held-out gate (the diagnosis judges that on the held-out passes; default: every fit)."""
    group = {n: c.group for n, c in rec.channels.items()}
    sens = {hf.hyp.location["channels"][0]: (d, float(hf.params[0])) for hf, v, d in fits
            if hf.hyp.effect == "sensor_error" and not hf.hyp.label.endswith(".dropout")}
    out = []
    for hf, v, d in fits:
        if v.accepted and hf.hyp.effect == "sensor_error" and not hf.hyp.label.endswith(".dropout"):
            n = hf.hyp.location["channels"][0]
            peers = [(p, dp, lp) for p, (dp, lp) in sens.items() if p != n and group.get(p) == group.get(n)]
            why = None
            if peers and d < 0:
                p, dp, _ = min(peers, key=lambda t: t[1])
                if dp <= 0.5 * d and not (n in scale_faulty and p not in scale_faulty):
                    why = (f"{p} (same quantity) improves almost as much (delta BIC {dp:+.0f} vs {d:+.0f}): a mismatch "
                           "common to those channels, not one faulty sensor")
            ln_s = float(hf.params[0])
            # a fit carried by its scale that a peer of the same quantity shares by at least half its log
            # scale, with BIC support of its own: the two gap sensors of a clean case both read ~1.25-1.29x
            # the twin (ln 0.22 / 0.25; delta BIC -95 / -200, so the rule above missed it by 5 points) and
            # one was called faulty. Carried by its scale, not by a drift: a true
            # 2e-5 m/s drift of M1G was fitted with x1.14 beside it, drift "within the noise" by the
            # hypothesis' 3-sigma test over the record, yet it alone made the held-out gain
            shared = [(p, dp, lp) for p, dp, lp in peers if not (n in scale_faulty and p not in scale_faulty)
                      and dp <= acc_bic and np.sign(lp) == np.sign(ln_s) and abs(lp) >= 0.5 * abs(ln_s)]
            if why is None and shared and scale_carries(hf):
                p, dp, lp = shared[0]
                why = (f"{p} (same quantity) reads x{math.exp(lp):.2f} against the twin too (delta BIC {dp:+.0f}): "
                       "a scale common to those channels (the twin's level), not one faulty sensor")
            if why:
                v = Verdict(False, v.reasons + (why,), v.heldout_before, v.heldout_after, v.delta_bic)
        out.append((hf, v, d))
    return out


def combine(spec: ModelSpec, hf: HypFit) -> ModelSpec:
    """Add the extension of ``hf`` to ``spec`` (keeping spec's calibrated parameters, but for
    levitation physics with the gains kp, kv it was fitted with: they are part of it, a delay
    refined jointly with them took kp from +33 % to +3 %, and with the calibrated kp kept it
    fitted the magnets worse than no delay)."""
    out = hf.hyp.apply(spec, hf.params)
    if hf.hyp.category in VEHICLE_WIDE:
        cal = np.array(out.cal, dtype=float)
        cal[_GAINS] = np.asarray(hf.spec.cal, dtype=float)[_GAINS]
        out = out.with_(cal=tuple(float(x) for x in cal))
    return out
