"""Open-ended discovery: what the residual says when no catalogue entry explains it.

Method (hand-written, ~40 lines of numpy): the residual band powers left after the best model are
pooled over the flagged cells; the band with the largest excess is located in time (-> the
vehicle's place on the line), by sensor (the guideway sensor with the largest excess gives the
span) and in frequency (an excess inside a band that holds no twin mode is a resonance the twin
does not have: an attachment, a cable trough, a noise barrier... ; an excess at a twin mode is
more/less response of an existing mode). Reported in plain words with band and place; never
mapped onto a catalogue name. (Sparse regression with PySINDy over a term library would need the
full residual state trajectories; the twin's states are not measured here, so the spectral route
is used.)
"""
from __future__ import annotations

import numpy as np


def discover(maps, modal, spans, min_cells: int = 3) -> list[dict]:
    out = []
    agg = {}
    for m in maps:
        rd = m.rd
        g = rd.grid
        for n, f in m.flags.items():
            if f.sum() < min_cells:
                continue
            sev = np.where(f, np.abs(m.severity[n]), 0.0)
            band_score = sev.sum(axis=0)
            b = int(np.argmax(band_score))
            frames = np.flatnonzero(f[:, b])
            if frames.size == 0:
                continue
            ch = rd.rec.channels[n]
            key = (ch.group, b)
            t0 = float(g.t_center_s[frames.min()] - g.frame_s / 2)
            t1 = float(g.t_center_s[frames.max()] + g.frame_s / 2)
            a = agg.setdefault(key, {"score": 0.0, "channels": {}, "band": (float(g.edges_hz[b]), float(g.edges_hz[b + 1])),
                                     "time_s": [t0, t1], "group": ch.group, "rec": rd.rec})
            a["score"] += float(band_score[b])
            a["channels"][n] = a["channels"].get(n, 0.0) + float(band_score[b])
    for key, a in sorted(agg.items(), key=lambda kv: -kv[1]["score"])[:3]:
        f0, f1 = a["band"]
        modes_in = [float(f) for f in modal.freq_hz if f0 <= f <= f1]
        top = max(a["channels"], key=a["channels"].get)
        ch = a["rec"].channels[top]
        span = None
        pos = None
        if ch.position_m is not None:
            for s in spans:
                if s.start_m <= ch.position_m <= s.end_m:
                    span = s.span_id
                    pos = [s.start_m, s.end_m]
        what = ("more vibration of an existing guideway mode than the twin predicts" if modes_in else
                "a resonance the twin does not have (e.g. an attached component, a loose cover or cable tray, "
                "a secondary structure on the girder)")
        where = f"span {span}" if span else ("the vehicle" if not ch.group.startswith("guideway") else "the line")
        out.append({"kind": "resonance" if not modes_in else "mode_amplitude",
                    "frequency_hz": [f0, f1], "channels": sorted(a["channels"], key=a["channels"].get, reverse=True),
                    "location": {"position_m": pos, "span": span}, "time_s": a["time_s"],
                    "twin_modes_in_band_hz": modes_in, "score": a["score"],
                    "explanation": f"Unexplained {f0:.0f}-{f1:.0f} Hz vibration on {where} (strongest at {top}): "
                                   f"{what}. No catalogue effect explains it; inspect {where} for it."})
    return out
