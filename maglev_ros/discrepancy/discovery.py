"""Open-ended discovery: what the residual says when no catalogue entry explains it.

Method (hand-written, ~60 lines of numpy): the flagged cells of the residual maps left after the
best model (:mod:`.localize`) are pooled per place (the span of each guideway sensor, or the
vehicle) and band; per place the strongest band (widened to strong neighbours) and then the next
are findings, located in time, by place and in frequency (an excess inside a band that holds no twin mode is a resonance the twin
does not have: an attachment, a cable trough, a noise barrier... ; an excess at a twin mode is
more/less response of an existing mode). Reported in plain words with band and place; never
mapped onto a catalogue name.

Then each located finding is MODELLED and judged by the catalogue's acceptance gates
(:func:`model_discoveries`):
- on a girder (a span found): an added resonator (spring-mass: frequency, damping, mass ratio,
  position on the span) fitted to the residual with the twin (:mod:`.resonator`);
- on the vehicle: sparse regression of the residual magnet acceleration (measured - twin) over a
  term library of the measured gap deviation g and its rate (g, g', g^2, g^3, g g', g'|g'|),
  :func:`sparse_suspension_terms`. Sequentially thresholded least squares (STLSQ, the optimiser
  at the core of SINDy) is written here in ~15 lines instead of using PySINDy: the target (the
  residual acceleration) is measured directly, so SINDy's differentiation and library machinery
  are not needed, and the project avoids a scikit-learn dependency. Linear terms (g, g') are kept
  in the regression as nuisance (they are the calibrated gains kp, kv in disguise) but only
  nonlinear terms are ever reported.
- on the car body (always, when car-body accelerometers exist and no catalogue entry is chosen): the
  air springs' missing force from the body accelerometers' residual over the twin's air-spring
  deflections, :mod:`.air_springs` (called from the diagnosis, not from a residual-map finding: the
  body's low-band misfit is the reconstructed rail's long-wave error on every case).
A span whose first mode rings off the other spans' in the free decay after every pass
(:mod:`.span_modes`) is a finding of its own, ranked first (the most specific evidence of a local
change of one girder). A LOWERED mode is modelled as a mass added to that span: rigidly attached,
its mass at every trial position following from the measured mode (the span's twin mode moved by
the measured shift relative to the other spans), so the position is the only shape parameter fitted;
an attachment tuned well above the mode acts on it exactly so, and fitted freely its own frequency
and damping wandered along flat directions (a 55 Hz, 3 % attachment: the same training fit from 35
to 110 Hz; a free fit settled at 0.3 % damping at 40 Hz where one pass happened to excite it).
Which own frequencies would fit as well is then profiled (:func:`.resonator.frequency_profile`) and
reported as the finding's band. A RAISED mode is searched as a resonator tuned below it.
A finding is "modelled" only when its model passes the gates; otherwise it stays a located,
unexplained band/place with the reasons its best model was rejected.
"""
from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from .localize import strong_cells

# a guideway accelerometer's 0-3 Hz band is the quasi-static deflection under the passing vehicle (a
# span crossing at 20-35 m/s takes 0.35-0.6 s) and waves longer than the reconstructed rail, below
# every girder mode: a misfit there is no resonance an attached component could make, so no added
# resonator is fitted to a finding wholly below this (measured: a guideway sensor's 0-3 Hz misfit
# was the "finding" a resonator had to explain, fitted there at 13 % damping, while a 38 Hz
# attachment showed at 37-44 Hz on the same span)
RESONATOR_MIN_HZ = 3.0


def resonator_explainable(d: dict) -> bool:
    """A located finding an added girder resonator could explain: on a span, sensed by the
    guideway, with a band reaching above ``RESONATOR_MIN_HZ``."""
    return (d["location"].get("span") is not None and d.get("sensed_on") != "vehicle"
            and d.get("kind") != "torsional_mode" and d["frequency_hz"][1] > RESONATOR_MIN_HZ)


def _span_of(x, spans):
    if x is None:
        return None
    for s in spans:
        if s.start_m <= x <= s.end_m:
            return s
    return None


def discover(maps, modal, spans, min_cells: int = 3, max_findings: int = 5, rel_extend: float = 0.3) -> list[dict]:
    """Located findings from the flagged cells of residual maps (after the best model).

    Flagged cells are pooled per place (a guideway sensor's span, or the vehicle) and band
    (severity summed over cells, channels and recordings). Per place the band with the largest
    score is a finding, widened to contiguous neighbour bands scoring >= ``rel_extend`` x its score
    (a resonance between two band centres feeds both triangular bands); its bands are then removed
    and the next peak of that place is a second finding. Findings are ranked by score.
    A vehicle finding is placed along the line by where the sensing magnet (or car-body point) was
    in its flagged frames (:func:`_vehicle_place`): a girder that rings under the vehicle shows in the
    magnets while they cross that span."""
    agg: dict = {}
    for m in maps:
        rd = m.rd
        g = rd.grid
        for n, f in m.flags.items():
            if f.sum() < min_cells and not strong_cells(m, n).any():
                continue
            ch = rd.rec.channels[n]
            sp = _span_of(ch.position_m, spans) if not ch.on_vehicle else None
            place = ("vehicle" if ch.on_vehicle else (sp.span_id if sp is not None else "line"))
            a = agg.setdefault(place, {"score": np.zeros(g.n_bands), "chan": {}, "t": {}, "edges": g.edges_hz,
                                       "span": sp, "group": ch.group, "xs": {}})
            sev = np.where(f, np.abs(m.severity[n]), 0.0)
            bs = sev.sum(axis=0)
            a["score"] += bs
            x_sensor = _sensor_x(rd.rec, ch, g.t_center_s) if ch.on_vehicle else None
            if x_sensor is not None:
                for fr, b in zip(*np.nonzero(f)):
                    a["xs"].setdefault(int(b), []).append((float(x_sensor[fr]), float(sev[fr, b])))
            for b in np.flatnonzero(bs > 0):
                a["chan"].setdefault(b, {})
                a["chan"][b][n] = a["chan"][b].get(n, 0.0) + float(bs[b])
                fr = np.flatnonzero(f[:, b])
                t0 = float(g.t_center_s[fr.min()] - g.frame_s / 2)
                t1 = float(g.t_center_s[fr.max()] + g.frame_s / 2)
                lo, hi = a["t"].get(b, (t0, t1))
                a["t"][b] = (min(lo, t0), max(hi, t1))
    finds = []
    for place, a in agg.items():
        sc = a["score"].copy()
        for _ in range(2):
            if not (sc > 0).any():
                break
            b = int(np.argmax(sc))
            lo = hi = b
            while lo - 1 >= 0 and sc[lo - 1] >= rel_extend * sc[b]:
                lo -= 1
            while hi + 1 < sc.size and sc[hi + 1] >= rel_extend * sc[b]:
                hi += 1
            bands = list(range(lo, hi + 1))
            chans: dict = {}
            for k in bands:
                for n, v in a["chan"].get(k, {}).items():
                    chans[n] = chans.get(n, 0.0) + v
            ts = [a["t"][k] for k in bands if k in a["t"]]
            xs = [xw for k in bands for xw in a["xs"].get(k, [])]
            span, pos = (a["span"], None) if place != "vehicle" else _vehicle_place(xs, spans)
            finds.append({"place": place, "span": span, "position_m": pos,
                          "band": (float(a["edges"][lo]), float(a["edges"][hi + 1])),
                          "score": float(sc[bands].sum()), "channels": chans,
                          "time_s": [min(t[0] for t in ts), max(t[1] for t in ts)], "group": a["group"]})
            sc[bands] = 0.0
    finds.sort(key=lambda d: -d["score"])
    out = []
    for fd in finds[:max_findings]:
        f0, f1 = fd["band"]
        modes_in = [float(f) for f in modal.freq_hz if f0 <= f <= f1]
        order = sorted(fd["channels"], key=fd["channels"].get, reverse=True)
        top = order[0]
        sp = fd["span"]
        span = sp.span_id if sp is not None else None
        pos = [sp.start_m, sp.end_m] if sp is not None else fd["position_m"]
        what = ("more vibration of an existing guideway mode than the twin predicts" if modes_in else
                "a resonance the twin does not have (e.g. an attached component, a loose cover or cable tray, "
                "a secondary structure on the girder)")
        where = f"span {span}" if span else ("the vehicle" if fd["place"] == "vehicle" else "the line")
        if fd["place"] == "vehicle" and span:
            where = f"the vehicle while it crosses span {span}"
        out.append({"kind": "resonance" if not modes_in else "mode_amplitude",
                    "frequency_hz": [f0, f1], "channels": order,
                    "sensed_on": "vehicle" if fd["place"] == "vehicle" else "guideway",
                    "location": {"position_m": pos, "span": span}, "time_s": fd["time_s"],
                    "twin_modes_in_band_hz": sorted(set(round(f, 3) for f in modes_in)), "score": fd["score"],
                    "explanation": f"Unexplained {f0:.0f}-{f1:.0f} Hz vibration on {where} (strongest at {top}): "
                                   f"{what}. No catalogue effect explains it; inspect {where} for it."})
    return out


def persistent_findings(persistent, modal, spans, disc: list[dict]) -> list[dict]:
    """Findings from persistent band misfits (:func:`.localize.persistent_mismatches`) on spans that
    ``disc`` does not already hold with an overlapping band: a girder sensor's band response off its
    peers' by 1.4x or more in every pass, which no single frame flags (an attachment detuning the
    span's mode shows so)."""
    out = []
    for m in persistent:
        sp = _span_of(0.5 * (m.position_m[0] + m.position_m[1]), spans) if m.position_m else None
        if sp is None:
            continue
        f0, f1 = m.frequency_hz
        if any(d["location"].get("span") == sp.span_id and d.get("sensed_on") != "vehicle"
               and d["frequency_hz"][0] < f1 and f0 < d["frequency_hz"][1] for d in disc + out):
            continue
        modes_in = [float(f) for f in modal.freq_hz if f0 * 0.88 <= f <= f1 * 1.12]
        what = (f"its response there is {m.peer_amplitude_ratio or 1.0:.1f}x (amplitude) off that of the other "
                f"girder sensors, relative to the twin, in every pass")
        out.append({"kind": "mode_amplitude" if modes_in else "resonance", "frequency_hz": [f0, f1],
                    "channels": list(m.channels), "sensed_on": "guideway",
                    "location": {"position_m": [sp.start_m, sp.end_m], "span": sp.span_id},
                    "time_s": [float(m.time_s[0]), float(m.time_s[1])],
                    "twin_modes_in_band_hz": sorted(set(round(f, 3) for f in modes_in)),
                    # ranked after the frame-flagged findings (whose scores sum severities over cells)
                    "score": float((m.peer_amplitude_ratio or 1.0) ** 2),
                    "persistent": True,
                    "explanation": f"Persistent {f0:.0f}-{f1:.0f} Hz misfit on span {sp.span_id} "
                                   f"({', '.join(m.channels)}): {what}. No catalogue effect explains it; "
                                   f"inspect span {sp.span_id} for it."})
    return out


def mode_shift_findings(detuned, spans) -> list[dict]:
    """Findings from spans whose first mode rings off the other spans' in the free decay after every
    pass (:func:`.span_modes.detuned_spans`): the most specific evidence of a local change of one
    girder (its mass, stiffness or supports), ranked before every band finding."""
    out = []
    for s in detuned:
        sp = next((x for x in spans if x.span_id == s.span_id), None)
        if sp is None:
            continue
        m = s.to_mismatch()
        f0, f1 = m.frequency_hz
        out.append({"kind": "mode_shift", "frequency_hz": [float(f0), float(f1)], "channels": list(s.channels),
                    "sensed_on": "guideway", "location": {"position_m": [sp.start_m, sp.end_m], "span": sp.span_id},
                    "time_s": [float(m.time_s[0]), float(m.time_s[1])],
                    "twin_modes_in_band_hz": [round(float(s.twin_hz), 3)], "score": float(m.severity),
                    "rank": 1, "mode_shift": float(s.shift),
                    # the span's first mode in the twin's terms: its own eigenfrequency moved by the shift
                    # relative to the other spans (what they share is the calibration's)
                    "target_hz": float(s.twin_hz * math.exp(s.shift)),
                    "explanation": f"The twin misses a local change of span {sp.span_id}: {s.words()}. No catalogue "
                                   f"effect explains it; inspect span {sp.span_id} for it."})
    return out


def _sensor_x(rec, ch, t_s: np.ndarray):
    """x along the line of a vehicle sensor at times ``t_s`` (its magnet's or body point's offset
    from the vehicle reference point), None without position or offset."""
    x_ref = rec.position_at(t_s)
    if x_ref is None:
        return None
    if ch.magnet is not None:
        offs = (rec.metadata.get("vehicle") or {}).get("magnet_offsets_m") or []
        return x_ref + float(offs[ch.magnet - 1]) if ch.magnet <= len(offs) else None
    return x_ref + ch.body_x_m if ch.body_x_m is not None else None


VEHICLE_SPAN_SHARE = 0.6     # share of a vehicle finding's score on one span that places it there


def _vehicle_place(xs: list, spans):
    """(span, position range) of a vehicle finding from (x, severity) of its flagged cells: the span
    holding >= ``VEHICLE_SPAN_SHARE`` of the severity, else no span and the 10-90 % severity-weighted
    stretch on the line (None when nothing was on the line)."""
    on = [(x, w) for x, w in xs if _span_of(x, spans) is not None]
    tot = sum(w for _, w in on)
    if not on or tot <= 0:
        return None, None
    share = {}
    for x, w in on:
        sid = _span_of(x, spans).span_id
        share[sid] = share.get(sid, 0.0) + w / tot
    best = max(share, key=share.get)
    if share[best] >= VEHICLE_SPAN_SHARE:
        return next(s for s in spans if s.span_id == best), None
    x = np.array([p for p, _ in on])
    w = np.array([q for _, q in on])
    o = np.argsort(x)
    c = np.cumsum(w[o]) / w.sum()
    return None, [float(x[o][np.searchsorted(c, 0.1)]), float(x[o][min(np.searchsorted(c, 0.9), x.size - 1)])]


# ------------------------------------------------------------------------------------------
def model_discoveries(disc: list[dict], base, rd_train, rd_test, acceptance, max_resonators: int = 2,
                      finder=None, log=None, worst_span_fallback: bool = True) -> list[dict]:
    """Fit a model to each located finding (see module doc); returns the entries, updated in place
    with ``model`` (what was fitted, its parameters and evidence) and a rail-engineer explanation."""
    from .resonator import MAX_ATTACHMENT_DAMPING, ResonatorFinder, frequency_profile, supported_band
    finder = finder or ResonatorFinder(acceptance, n_freq=6)
    spans = base.spec.spans
    idx = {s.span_id: i for i, s in enumerate(spans)}
    # girder resonators for what the guideway sensors found on a span; what only the vehicle felt
    # (even while crossing one span) goes to the suspension-term regression below
    cands = [d for d in disc if d["location"].get("span") in idx and resonator_explainable(d)]
    cands.sort(key=lambda d: (-d.get("rank", 0), -d["score"]))
    seen = set()
    fits = []
    only_span = None
    for d in cands:
        key = (d["location"]["span"], tuple(d["frequency_hz"]))
        if key in seen or len(fits) >= max_resonators or only_span not in (None, d["location"]["span"]):
            continue
        seen.add(key)
        try:
            f0, f1 = d["frequency_hz"]
            # a new resonance shows inside its band; more/less response of an existing mode can come
            # from an attachment tuned well below it (it acts as a mass above its own frequency)
            # (and, found by a persistent misfit, one tuned above it: there it acts as added mass and
            # lowers the mode; measured: a 38 Hz attachment detuned the 18-22 Hz band of its span)
            top = 2.5 if d.get("persistent") else 1.12
            search = ((max(RESONATOR_MIN_HZ, f0 * 0.88), f1 * 1.12) if d["kind"] == "resonance"
                      else (max(2.0, 0.3 * f0), f1 * top))
            zeta_max, band_fit = None, d["frequency_hz"]
            rigid = d["kind"] == "mode_shift" and d["mode_shift"] < 0
            if d["kind"] == "mode_shift":
                # the misfit a detuned mode leaves is in the bands around it (its energy moved there)
                band_fit = (f0 * 0.85, f1 * 1.15)
                # lowered: an added mass, its size from the measured mode (module docstring); raised: a
                # component tuned below the mode, searched below it
                search = None if rigid else (RESONATOR_MIN_HZ, f0 * 0.85)
                zeta_max = MAX_ATTACHMENT_DAMPING
            # a mode the ambient recording shows was located there (no vehicle): the attachment is made
            # to have it, and is not judged on the passes' band, where the forced response dominates
            mode_hz = None if rigid else d.get("mode_hz")
            rf = finder.fit(base, rd_train, rd_test, band_fit, idx[d["location"]["span"]], search,
                            zeta_max=zeta_max, rigid=rigid, target_hz=d.get("target_hz") if rigid else None,
                            band_gate=mode_hz is None, mode_hz=mode_hz)
            if rf.accepted and rigid:
                # which own frequencies would fit as well? (a component tuned above the mode: mass-like)
                f_top = _usable_top_hz(rd_train, d["channels"])
                prof = frequency_profile(base, rd_train, rf, np.geomspace(f1 * 1.2, f_top, 7), d["target_hz"])
                lo, hi = supported_band(prof + [(f_top, rf.train_gain)], rf.train_gain)
                if np.isfinite(lo):
                    rf = replace(rf, supported_hz=(lo, hi))
        except Exception as exc:          # an unstable twin etc.: the finding stays located only
            d["model"] = {"kind": "added_resonator", "accepted": False, "reasons": [f"fit failed ({exc})"]}
            if log:
                log(f"discovery: resonator fit failed on {key}: {exc}")
            continue
        fits.append((rf, d))
        if rf.accepted:
            if d["kind"] != "mode_shift" or only_span is not None:
                break           # one modelled explanation per diagnosis (the strongest finding first)
            # an added mass explains the detuned mode; a resonator fitted to a band finding of the same
            # span may explain more (where its own frequency shows): tried, the better held-out fit wins
            # (measured: a 38 Hz attachment placed 1.2 m off as an added mass, 0.1 m off as a resonator)
            only_span = d["location"]["span"]
    if worst_span_fallback and not any(rf.accepted for rf, _ in fits):
        # a local change can stay under the localization gates in every cell (a 10-30 % amplitude
        # change of one span's response); the span whose guideway sensors fit worst after
        # calibration is then the finding, over the whole usable band, judged by the same gates
        d = _worst_span_finding(base, rd_train)
        if d is not None and len(fits) < max_resonators + 1:
            try:
                rf = finder.fit(base, rd_train, rd_test, d["frequency_hz"], idx[d["location"]["span"]],
                                (d["frequency_hz"][0] * 0.88, d["frequency_hz"][1] * 1.12))
                if rf.accepted:
                    disc.insert(0, d)
                    fits.append((rf, d))
            except Exception as exc:
                if log:
                    log(f"discovery: resonator fit on the worst-fitting span failed: {exc}")
    best = min((t for t in fits if t[0].accepted), key=lambda t: t[0].verdict.heldout_after, default=None)
    for rf, d in fits:
        d["model"] = rf.to_dict()
        if best is not None and rf is not best[0] and rf.accepted:
            d["model"]["accepted"] = False
            d["model"]["reasons"] = [f"also improves the held-out fit, but less than the resonator on span "
                                     f"{best[0].span_id} at "
                                     f"{'(rigid)' if best[0].resonator.rigid else f'{best[0].resonator.freq_hz:.1f} Hz'}"]
        if d["model"]["accepted"]:
            d["_fit"] = rf            # for the caller's twin after (not JSON: popped before the report)
            # the finding is now the modelled resonator: its band is where the resonator lives; the
            # band where the residual showed (e.g. an existing mode it detunes) is kept beside it
            d["kind"] = "added_resonator"
            d["residual_band_hz"] = list(d["frequency_hz"])
            f = rf.resonator.freq_hz
            if rf.resonator.rigid:
                d["frequency_hz"] = list(d["residual_band_hz"])
            else:
                d["frequency_hz"] = [float(f * (1 - max(0.05, 2 * rf.resonator.damping_ratio))),
                                     float(f * (1 + max(0.05, 2 * rf.resonator.damping_ratio)))]
            if d.get("mode_hz") is not None:
                # the ambient recording measured the coupled mode it makes: the band spans both
                lo, hi = d["frequency_hz"]
                d["frequency_hz"] = [min(lo, d["residual_band_hz"][0]), max(hi, d["residual_band_hz"][1])]
            if rf.supported_hz:
                # an added mass: the own frequencies the data support (up to the usable band's top when
                # a rigid mass fits as well), not a sharper claim than they make
                d["frequency_hz"] = [float(x) for x in rf.supported_hz]
            d["explanation"] = rf.explanation(d["residual_band_hz"], _what(d))
            d["location"] = {"position_m": [float(x) for x in rf.position_range_m], "span": rf.span_id}
        else:
            d["explanation"] = (d["explanation"] + " " + rf.explanation(d["frequency_hz"], _what(d))
                                + (f" It {d['model']['reasons'][0]}." if rf.accepted else ""))
    def unplaced(d):
        return d.get("sensed_on") == "vehicle" or not d["location"].get("span")
    if any(unplaced(d) for d in disc):
        try:
            terms = sparse_suspension_terms(base.spec, rd_train, rd_test)
        except Exception as exc:
            terms = None
            if log:
                log(f"discovery: sparse suspension regression failed: {exc}")
        if terms is not None:
            for d in disc:
                if unplaced(d):
                    d["model"] = terms
                    if terms.get("accepted"):
                        d["kind"] = "suspension_term"
                    d["explanation"] = d["explanation"] + " " + terms["explanation"]
                    break
    return disc


AMBIENT_SOURCE = "ambient modes"


def _what(d: dict) -> str | None:
    """What a finding is, in words, where its band alone does not say it (a detuned first mode)."""
    if d.get("mode_shift") is None:
        return None
    lo, hi = d.get("residual_band_hz") or d["frequency_hz"]
    return (f"why the span's first mode rings {100 * (math.exp(d['mode_shift']) - 1):+.1f} % off the other spans' "
            f"({lo:.2f}-{hi:.2f} Hz, measured and twin)")


def _usable_top_hz(rds, channels) -> float:
    """Top of the usable bands of ``channels`` (the anti-alias filter's pass band)."""
    rd = rds[0]
    e = rd.grid.edges_hz
    return float(max(e[1:][rd.masks[c]].max() for c in channels if c in rd.masks))


def _worst_span_finding(base, rds) -> dict | None:
    """The span whose guideway sensors fit worst (mean per-channel NRMSE) as a whole-band finding."""
    from .evaluate import fit_report
    _, pc = fit_report(base.spec, rds)
    rd = rds[0]
    per: dict = {}
    for n, v in pc.items():
        ch = rd.rec.channels.get(n)
        if ch is None or not ch.group.startswith("guideway"):
            continue
        sp = _span_of(ch.position_m, base.spec.spans)
        if sp is not None:
            per.setdefault(sp.span_id, []).append(v)
    if len(per) < 2:
        return None
    sid = max(per, key=lambda k: np.mean(per[k]))
    sp = next(s for s in base.spec.spans if s.span_id == sid)
    e = rd.grid.edges_hz
    chans = [n for n, c in rd.rec.channels.items() if c.group.startswith("guideway") and _span_of(c.position_m, [sp])]
    f_top = _usable_top_hz(rds, chans)
    return {"kind": "resonance", "frequency_hz": [float(e[2]), f_top], "channels": chans,
            "location": {"position_m": [sp.start_m, sp.end_m], "span": sid},
            "time_s": [float(rd.rec.t0_s), float(rd.rec.t1_s)], "twin_modes_in_band_hz": [], "score": 0.0,
            "explanation": f"Span {sid}'s sensors fit worst after calibration (mean NRMSE {np.mean(per[sid]):.3f} vs "
                           f"{np.mean([np.mean(v) for k, v in per.items() if k != sid]):.3f} elsewhere), with no single "
                           f"band standing out."}


# ------------------------------------------------------------------------------------------
TERM_NAMES = ("g", "g_rate", "g^2", "g^3", "g*g_rate", "g_rate*|g_rate|")
LINEAR_TERMS = ("g", "g_rate")


def term_library(gap_dev_m: np.ndarray, fs_hz: float) -> np.ndarray:
    """(n, 6) candidate terms of the gap deviation g [m] and its rate g' [m/s] (central differences)."""
    g = np.asarray(gap_dev_m, float)
    gd = np.gradient(g, 1.0 / fs_hz)
    return np.stack([g, gd, g ** 2, g ** 3, g * gd, gd * np.abs(gd)], axis=1)


def stlsq(theta: np.ndarray, y: np.ndarray, threshold: float, keep=(), max_iter: int = 10) -> np.ndarray:
    """Sequentially thresholded least squares (Brunton et al. 2016) on column-normalised terms:
    coefficients whose normalised size is below ``threshold`` x the largest are dropped and the
    rest re-fitted; columns in ``keep`` are never dropped."""
    scale = np.sqrt(np.mean(theta ** 2, axis=0))
    scale[scale == 0] = 1.0
    X = theta / scale
    active = np.ones(X.shape[1], bool)
    c = np.zeros(X.shape[1])
    for _ in range(max_iter):
        c = np.zeros(X.shape[1])
        c[active] = np.linalg.lstsq(X[:, active], y, rcond=None)[0]
        big = np.abs(c) >= threshold * max(np.max(np.abs(c)), 1e-300)
        big[list(keep)] = True
        new = active & big
        if np.array_equal(new, active):
            break
        active = new
    return c / scale


def _bic_ts(rss: float, n: int, k: int) -> float:
    return n * math.log(max(rss, 1e-300) / n) + k * math.log(n)


def term_gate_reasons(before: float, after: float, dbic: float, acc,
                      what: str = "held-out residual {b:.3f} -> {a:.3f}") -> list[str]:
    """Why nonlinear terms fail the catalogue's margins against the linear terms alone: held-out error
    ``before`` -> ``after`` (relative and absolute gain) and training delta BIC. ``what`` names the
    held-out error in the message."""
    why = []
    if not acc.clear_gain(before, after):
        why.append(f"{what.format(b=before, a=after)} is not a clear improvement")
    if not dbic <= acc.max_delta_bic:
        why.append(f"delta BIC {dbic:+.1f} does not beat the linear terms (needs <= {acc.max_delta_bic:g})")
    return why


def sparse_regression_report(theta_tr, y_tr, theta_te, y_te, n_eff_tr: int, n_eff_te: int,
                             threshold: float = 0.05, acceptance=None, names=TERM_NAMES,
                             linear=LINEAR_TERMS) -> dict:
    """Nonlinear terms that explain the residual beyond the linear (calibration) terms.

    Model 0: y ~ linear terms; model 1: STLSQ over the whole library (linear terms always kept).
    Accepted when the held-out residual falls by the catalogue's margins, the training BIC drops by
    more than ``-max_delta_bic`` and a nonlinear term survives. ``n_eff_*``: effective sample sizes
    (correlated samples: about bandwidth x duration). ``names``: the library's columns, ``linear``
    those always kept (default: the gap library of :func:`term_library`)."""
    from .acceptance import AcceptanceConfig
    acc = acceptance or AcceptanceConfig()
    lin = [names.index(t) for t in linear]
    c0 = np.zeros(theta_tr.shape[1])
    c0[lin] = np.linalg.lstsq(theta_tr[:, lin], y_tr, rcond=None)[0]
    c1 = stlsq(theta_tr, y_tr, threshold, keep=lin)
    rss = lambda th, y, c: float(np.sum((y - th @ c) ** 2))
    scale_tr = len(y_tr) / n_eff_tr

    def refit(active):
        c = np.zeros(theta_tr.shape[1])
        c[active] = np.linalg.lstsq(theta_tr[:, active], y_tr, rcond=None)[0]
        return c
    # backward elimination by BIC: a nonlinear term stays only if removing it costs BIC
    while True:
        act = [j for j in range(c1.size) if c1[j] != 0 or j in lin]
        cur = _bic_ts(rss(theta_tr, y_tr, c1) / scale_tr, n_eff_tr, len(act))
        best = None
        for j in act:
            if j in lin:
                continue
            c = refit([a for a in act if a != j])
            b = _bic_ts(rss(theta_tr, y_tr, c) / scale_tr, n_eff_tr, len(act) - 1)
            if b <= cur and (best is None or b < best[0]):
                best = (b, c)
        if best is None:
            break
        c1 = best[1]
    k0, k1 = len(lin), int(np.count_nonzero(c1))
    dbic = _bic_ts(rss(theta_tr, y_tr, c1) / scale_tr, n_eff_tr, k1) - _bic_ts(rss(theta_tr, y_tr, c0) / scale_tr,
                                                                              n_eff_tr, k0)
    nr0 = math.sqrt(rss(theta_te, y_te, c0) / max(float(np.sum(y_te ** 2)), 1e-300))
    nr1 = math.sqrt(rss(theta_te, y_te, c1) / max(float(np.sum(y_te ** 2)), 1e-300))
    nonlin = {names[j]: float(c1[j]) for j in range(len(names)) if j not in lin and c1[j] != 0}
    why = [] if nonlin else ["no nonlinear term survives the sparse regression"]
    why += term_gate_reasons(nr0, nr1, dbic, acc)
    return {"kind": "suspension_term", "terms": nonlin,
            "linear_terms": {names[j]: float(c1[j]) for j in lin},
            "accepted": not why, "reasons": why,
            "evidence": {"heldout_nrmse_before": nr0, "heldout_nrmse_after": nr1, "delta_bic": float(dbic)}}


def _term_words(terms: dict) -> str:
    words = {"g^2": "a force growing with the square of the gap change (asymmetric: magnet pull vs release)",
             "g^3": "a cubic stiffening/softening of the levitation/suspension with the gap change",
             "g*g_rate": "damping that changes with the gap",
             "g_rate*|g_rate|": "quadratic (velocity-squared) damping"}
    return "; ".join(f"{words.get(k, k)} ({k}: {v:+.3g})" for k, v in terms.items())


def _vehicle_series(spec, rd, names):
    """(gap deviation, residual magnet accel) per magnet with both sensors, on frames the diagnosis
    compares (the vehicle over the valid irregularity)."""
    from .model import predict, reference_value
    rec = rd.rec
    pred = predict(spec, rec)
    gaps = {c.magnet: n for n, c in rec.channels.items() if c.group == "gap"}
    accs = {c.magnet: n for n, c in rec.channels.items() if c.group == "vehicle_accel"}
    out = []
    for mag in sorted(set(gaps) & set(accs)):
        gn, an = gaps[mag], accs[mag]
        ca, cg = rec.channels[an], rec.channels[gn]
        g = np.interp(ca.time_s, cg.time_s, cg.values) - reference_value(rec, gn)
        y = ca.values - pred[an]
        ok = np.isfinite(g) & np.isfinite(y)
        if rec.irregularity_valid_m is not None:
            from .irregularity import vehicle_over_valid
            ok &= vehicle_over_valid(rec, ca.time_s, spec.config.vehicle.magnet_offsets_m)
        if ok.sum() > 50:
            out.append((g[ok], y[ok], ca.sample_rate_hz))
    return out


def sparse_suspension_terms(spec, rd_train, rd_test, threshold: float = 0.05, band_hz: float = 30.0,
                            acceptance=None) -> dict | None:
    """Sparse regression of the vehicle residual (see :func:`sparse_regression_report`) with the
    twin's prediction ``spec`` on the recordings' magnet accel + gap pairs; None without such pairs."""
    def stack(rds):
        th, ys, neff = [], [], 0
        for rd in rds:
            for g, y, fs in _vehicle_series(spec, rd, None):
                th.append(term_library(g, fs)); ys.append(y)
                neff += int(2 * band_hz * g.size / fs)
        if not th:
            return None
        return np.vstack(th), np.concatenate(ys), max(neff, 10)
    tr = stack(rd_train)
    te = stack(rd_test)
    if tr is None or te is None:
        return None
    rep = sparse_regression_report(tr[0], tr[1], te[0], te[1], tr[2], te[2], threshold, acceptance)
    if rep["accepted"]:
        rep["explanation"] = ("Sparse regression of the magnet-acceleration residual over gap terms finds "
                              + _term_words(rep["terms"]) + f": held-out residual {rep['evidence']['heldout_nrmse_before']:.3f}"
                              f" -> {rep['evidence']['heldout_nrmse_after']:.3f}. The levitation/suspension is "
                              f"nonlinear beyond the twin's model; check magnet current limits, air-spring/"
                              f"secondary-suspension characteristics.")
    else:
        rep["explanation"] = ("Sparse regression of the magnet-acceleration residual over gap terms finds no "
                              "supported nonlinear term (" + "; ".join(rep["reasons"]) + ").")
    return rep
