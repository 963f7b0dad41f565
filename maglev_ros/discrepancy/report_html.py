"""Self-contained HTML report of a diagnosis (plots as inline base64 PNG; no scripts, no CDN).

Sections (element ids): ``summary``, ``where`` (residual maps over time/position and frequency, residual
along the line), ``tried`` (every hypothesis with its verdict), ``chosen`` (the accepted physics),
``before-after`` (measured vs twin before/after: per-channel NRMSE, time series, band spectra).
"""
from __future__ import annotations

import base64
import html
import io
import json

import numpy as np

from .evaluate import model_powers
from .model import predict, reference_value
from .recording import GROUP_UNIT, GROUPS


def _png(fig) -> str:
    import matplotlib.pyplot as plt
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=80, bbox_inches="tight")
    plt.close(fig)
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode("ascii")


def _img(src: str, alt: str) -> str:
    return f'<img src="{src}" alt="{html.escape(alt)}" class="plot"/>'


def _maps_figure(rmap, title: str):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    rd = rmap.rd
    g = rd.grid
    groups = []
    for grp in GROUPS:
        names = [n for n, c in rd.rec.channels.items() if c.group == grp]
        if names:
            groups.append((grp, names))
    fig, axes = plt.subplots(len(groups), 1, figsize=(8, 2.0 * len(groups) + 0.6), squeeze=False, sharex=True)
    t = g.t_center_s
    for ax, (grp, names) in zip(axes[:, 0], groups):
        sev = np.max([np.where(rmap.flags[n], np.log10(1 + np.abs(rmap.severity[n])), 0.0) for n in names], axis=0)
        im = ax.imshow(sev.T, origin="lower", aspect="auto", cmap="magma", vmin=0.0, vmax=max(1.0, float(sev.max())),
                       extent=(t[0] - g.frame_s / 4, t[-1] + g.frame_s / 4, 0, g.n_bands))
        ax.set_yticks(np.arange(g.n_bands)[::3] + 0.5)
        ax.set_yticklabels([f"{e:.0f}" for e in g.edges_hz[:-1][::3]])
        ax.set_ylabel(f"{grp}\nband [Hz]")
        fig.colorbar(im, ax=ax, label="log10(1 + residual/noise)")
        if rd.rec.position_time_s is not None and ax is axes[0, 0]:
            ax2 = ax.secondary_xaxis("top", functions=(lambda tt, rd=rd: np.interp(tt, rd.rec.position_time_s, rd.rec.position_m),
                                                        lambda xx, rd=rd: np.interp(xx, rd.rec.position_m, rd.rec.position_time_s)))
            ax2.set_xlabel("vehicle position [m]")
    axes[-1, 0].set_xlabel("time [s]")
    fig.suptitle(title)
    return fig


def _along_line(maps):
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(8, 2.6))
    for m in maps:
        rd = m.rd
        if rd.rec.position_time_s is None:
            continue
        x = rd.rec.position_at(rd.grid.t_center_s)
        tot = np.zeros(rd.grid.n_frames)
        for n in rd.rec.channels:
            tot += np.sum(np.where(m.flags[n], np.abs(m.severity[n]), 0.0), axis=1)
        ax.semilogy(x, 1 + tot, ".-", label=rd.rec.source)
    for s in (maps[0].rd.rec.metadata.get("line") or {}).get("spans", []):
        ax.axvline(s["start_m"], color="0.7", lw=0.8)
        ax.axvline(s["start_m"] + s["length_m"], color="0.7", lw=0.8)
    ax.set_xlabel("vehicle reference position [m] (grey: span ends)")
    ax.set_ylabel("1 + flagged residual / noise")
    ax.legend(fontsize=7)
    return fig


def _nrmse_bars(before: dict, after: dict):
    import matplotlib.pyplot as plt
    names = list(before)
    fig, ax = plt.subplots(figsize=(8, 2.6))
    x = np.arange(len(names))
    ax.bar(x - 0.2, [before[n] for n in names], 0.4, label="twin (calibrated)")
    ax.bar(x + 0.2, [after.get(n, np.nan) for n in names], 0.4, label="twin + accepted physics")
    ax.set_xticks(x)
    ax.set_xticklabels(names, rotation=45, fontsize=8)
    ax.set_ylabel("band-amplitude NRMSE")
    ax.legend(fontsize=8)
    return fig


def _series(rd, name, spec_before, spec_after, rd_after=None):
    """``rd_after``: the pass as the twin after sees it (its own rail), ``rd`` if None."""
    import matplotlib.pyplot as plt
    rd_after = rd if rd_after is None else rd_after
    ch = rd.rec.channels[name]
    pb = predict(spec_before, rd.rec)[name]
    pa = predict(spec_after, rd_after.rec)[name]
    fig, axes = plt.subplots(1, 2, figsize=(10, 2.8))
    ref = reference_value(rd.rec, name)
    axes[0].plot(ch.time_s, ch.values - ref, lw=0.6, color="k", label="measured")
    axes[0].plot(ch.time_s, pb - ref, lw=0.8, label="twin before")
    axes[0].plot(ch.time_s, pa - ref, lw=0.8, ls="--", label="twin after")
    axes[0].set_xlabel("time [s]")
    axes[0].set_ylabel(f"{name} [{GROUP_UNIT[ch.group]}]")
    axes[0].legend(fontsize=7)
    mb, ma = model_powers(spec_before, rd)[name], model_powers(spec_after, rd_after)[name]
    fc = rd.grid.band_center_hz
    msk = rd.masks[name]
    axes[1].semilogy(fc[msk], np.sqrt(np.nanmean(rd.pm[name], axis=0))[msk], "k.-", label="measured")
    axes[1].semilogy(fc[msk], np.sqrt(np.nanmean(mb, axis=0))[msk], ".-", label="twin before")
    axes[1].semilogy(fc[msk], np.sqrt(np.nanmean(ma, axis=0))[msk], ".--", label="twin after")
    axes[1].set_xlabel("band centre [Hz]")
    axes[1].set_ylabel("band RMS")
    axes[1].legend(fontsize=7)
    fig.suptitle(f"{name} ({rd.rec.source})")
    return fig


def _table(rows: list[list], head: list[str]) -> str:
    h = "".join(f"<th>{html.escape(x)}</th>" for x in head)
    b = "".join("<tr>" + "".join(f"<td>{html.escape(str(c))}</td>" for c in r) + "</tr>" for r in rows)
    return f"<table><thead><tr>{h}</tr></thead><tbody>{b}</tbody></table>"


def render(diagnosis) -> str:
    import matplotlib
    matplotlib.use("Agg")
    rep = diagnosis.report
    ex = diagnosis.extras
    parts = []
    before, after = rep["fit_before"], rep["fit_after"]
    parts.append(f'<section id="summary"><h2>Summary</h2><p>Band-amplitude NRMSE of the calibrated twin '
                 f'{before["nrmse"]:.3f}; with the accepted physics {after["nrmse"]:.3f}. '
                 f'{len(rep["mismatches"])} located mismatch(es); '
                 f'{len(rep["missing_physics"])} missing physics accepted; {len(rep["rejected"])} hypotheses rejected.</p>'
                 + ("<ul>" + "".join(f"<li><b>{html.escape(m['effect'])}</b> ({html.escape(m['category'])}): "
                                     f"{html.escape(m['explanation'])}</li>" for m in rep["missing_physics"]) + "</ul>"
                    if rep["missing_physics"] else "<p>Nothing is missing: the calibrated twin explains the "
                                                   "recordings within the noise.</p>") + "</section>")
    w = ['<section id="where"><h2>Where twin and recordings differ</h2>']
    for m in ex.get("maps_before", []):
        w.append(_img(_png(_maps_figure(m, f"residual map, calibrated twin: {m.rd.rec.source}")),
                      f"residual map {m.rd.rec.source}"))
    if ex.get("maps_before"):
        w.append(_img(_png(_along_line(ex["maps_before"])), "residual along the line"))
    w.append(_table([[", ".join(m["channels"]), f"{m['time_s'][0]:.2f}-{m['time_s'][1]:.2f}",
                      "-" if m["position_m"] is None else f"{m['position_m'][0]:.1f}-{m['position_m'][1]:.1f}",
                      "-" if m["frequency_hz"] is None else f"{m['frequency_hz'][0]:.0f}-{m['frequency_hz'][1]:.0f}",
                      f"{m['severity']:.1f}"] for m in rep["mismatches"]],
                    ["channels", "time [s]", "position [m]", "band [Hz]", "severity (x noise)"]))
    w.append("</section>")
    parts.append("".join(w))
    tried = []
    for hf, v, d in ex.get("fits", []):
        tried.append([hf.hyp.label, hf.hyp.category, ", ".join(f"{n}={p:.4g}" for n, p in zip(hf.hyp.param_names, hf.params)),
                      f"{v.heldout_before:.3f} -> {v.heldout_after:.3f}", f"{d:+.1f}",
                      "accepted" if v.accepted else "; ".join(v.reasons)])
    parts.append('<section id="tried"><h2>What was tried</h2>'
                 + _table(tried, ["hypothesis", "category", "fitted parameters", "held-out NRMSE", "delta BIC", "verdict"])
                 + "<h3>Rejected</h3>" + _table([[r["effect"], r["why"]] for r in rep["rejected"]], ["effect", "why"])
                 + "".join(f"<p class='disc'>Discovery: {html.escape(d['explanation'])}</p>" for d in rep.get("discovery", []))
                 + "</section>")
    ch_rows = [[m["effect"], m["category"], m["explanation"], json.dumps(m["parameters"]),
                f"{m['evidence']['heldout_nrmse_before']:.3f} -> {m['evidence']['heldout_nrmse_after']:.3f}",
                f"{m['evidence']['delta_bic']:+.1f}"] for m in rep["missing_physics"]]
    parts.append('<section id="chosen"><h2>Chosen physics</h2>'
                 + (_table(ch_rows, ["effect", "category", "explanation", "parameters", "held-out NRMSE", "delta BIC"])
                    if ch_rows else "<p>None accepted.</p>")
                 + "<h3>Updated parameters</h3>"
                 + _table([[k, f"{v:.4g}"] for k, v in rep["updated_parameters"].items()], ["parameter", "value"])
                 + "</section>")
    ba = ['<section id="before-after"><h2>Measured vs twin, before and after</h2>',
          _img(_png(_nrmse_bars(before["per_channel"], after["per_channel"])), "per-channel NRMSE")]
    rds = ex.get("rd_all", [])
    if rds:
        gains = {n: before["per_channel"][n] - after["per_channel"].get(n, before["per_channel"][n])
                 for n in before["per_channel"]}
        # the channels the chosen physics acts on first (a law judged on a band of them need not top
        # the whole-recording gains), then the largest gains
        own = [c for m in rep["missing_physics"][:1] for c in m["location"]["channels"] if c in gains]
        show = (sorted(own, key=gains.get, reverse=True)
                + [n for n in sorted(gains, key=gains.get, reverse=True) if n not in own])[:2]
        rd, rd_after = rds[-1], (ex.get("rd_after") or rds)[-1]
        for n in show:
            if n in rd.rec.channels:
                ba.append(_img(_png(_series(rd, n, ex["base_spec"], ex["final_spec"], rd_after)),
                               f"measured vs twin {n}"))
    ba.append("</section>")
    parts.append("".join(ba))
    css = ("body{font-family:sans-serif;max-width:1100px;margin:auto;padding:1em}table{border-collapse:collapse;"
           "font-size:12px;margin:0.5em 0}td,th{border:1px solid #bbb;padding:2px 6px;vertical-align:top}"
           "img.plot{max-width:100%;display:block;margin:0.5em 0}")
    return ("<!DOCTYPE html><html><head><meta charset='utf-8'><title>maglev-ros diagnosis</title>"
            f"<style>{css}</style></head><body><h1>Twin vs recordings: diagnosis</h1>"
            + "".join(parts) + "</body></html>")
