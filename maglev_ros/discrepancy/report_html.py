"""Self-contained HTML report of a diagnosis (plots as inline base64 PNG; no scripts, no CDN).

Sections (element ids): ``summary`` (verdict and the table ``recordings``), ``glossary`` (one plain
sentence per statistic), ``where`` (residual maps over time from each recording's start and
frequency, residual along the line, table ``mismatches`` most severe first), ``chosen`` (tables
``physics`` and ``physics-parameters``: accepted physics, its parameters with units, the twin's
value and the found one), ``parameters`` (table ``parameters``: the twin's calibrated parameters,
design vs updated with std), ``before-after`` (per-channel NRMSE; residual measured - twin before
and after, over time and as band spectra), ``tried`` (every hypothesis with its verdict).
Recordings are named by their bag's name, never by a machine path; times count from each
recording's first sample.
"""
from __future__ import annotations

import base64
import html
import io
import math
import warnings

import numpy as np

from .evaluate import model_powers
from .model import predict
from .recording import GROUP_UNIT, GROUPS

DASH = "\u2014"

# plain sentences, one per statistic the report uses (shown in the glossary and beside the tables)
GLOSSARY = {
    "band amplitude": "The RMS of a channel within one frequency band over one 0.5 s frame; twin and "
                      "recording are compared through these, so the random phase of noise does not count.",
    "residual": "Measured minus twin: what the twin does not explain.",
    "NRMSE": "Normalised root-mean-square error: the RMS of (measured - twin) band amplitudes divided by the RMS "
             "of the measured ones; 0 is a perfect match, 1 an error as large as the signal itself.",
    "held-out": "Measured on passes not used for fitting (all but the fastest pass), so a change that only "
                "fits the noise of the training pass does not improve it.",
    "log-likelihood ratio": "How much better the held-out data are explained with the physics than without, "
                            "as a natural logarithm of the probability ratio (Gaussian errors); a finding "
                            "needs at least 10, i.e. the data are e^10 (about 22 000) times more probable.",
    "delta BIC": "Change of the Bayesian information criterion on the training pass when the physics is added: "
                 "the fit's gain penalised by the number of added parameters; negative favours the physics, "
                 "acceptance needs -10 or less.",
    "severity": "How far a region's measured band power is from the twin's, in multiples of the recording's "
                "noise power in those bands; 3 or more flags a cell.",
    "nominal": "The value of the design (uncalibrated) twin, from the recording's design block; for found "
               "physics the value at which the physics is absent, i.e. the twin without it.",
    "std": "One standard deviation of a value, where the analysis gives one. The diagnosis gives none, neither "
           "for its calibrated parameters nor for found physics (shown as \u2014): its fit's own estimate was "
           "far below the true error on recordings with known truth; 'maglev-ros update' estimates one per "
           "parameter.",
}

# calibrated parameters: plain name, symbol, display unit and its factor from SI
CALIBRATED = {
    "youngs_modulus_pa": ("Young's modulus of the girders", "E", "GPa", 1e-9),
    "bearing_stiffness_n_per_m": ("bearing stiffness", "kb", "MN/m", 1e-6),
    "kp_a_per_m": ("levitation control gain on the gap", "kp", "A/m", 1.0),
    "kv_a_s_per_m": ("levitation control gain on the gap rate", "kv", "A s/m", 1.0),
    "density_kg_m3": ("density of the girders", "rho", "kg/m^3", 1.0),
}

# found-physics parameters: unit and the twin's value (without that physics); None: not defined there
PHYSICS_PARAMS = {
    "stiffness_loss": ("1", 0.0),
    "stiffness_factor": ("1", 1.0),
    "delay_s": ("s", 0.0),
    "bending_frequency_hz": ("Hz", "rigid body"),
    "log10_modal_force_psd_at_20hz": ("log10(N^2/Hz), unit modal mass", "no ambient vibration"),
    "spectral_slope": ("1", None),
    "ambient_rms_mps2": ("m/s^2", 0.0),
    "level_factor": ("1", "no ambient vibration"),
    "measured_on": (None, None),
    "scale": ("1", 1.0),
    "offset": (None, 0.0),               # unit of its channel
    "drift_per_s": (None, 0.0),          # unit of its channel per second
    "current_headroom_a": ("A", "unlimited"),
    "headroom_over_peak_demand": ("1", "unlimited"),
    "static_current_a": ("A", "same"),
    "scale_relative_to_peers": ("1", 1.0),
    "group_level_vs_twin": ("1", 1.0),
    "stiffness_change_n_per_m": ("N/m", 0.0),
    "damping_change_n_s_per_m": ("N s/m", 0.0),
    "cubic_stiffness_n_per_m3": ("N/m^3", 0.0),
    "quadratic_stiffness_n_per_m2": ("N/m^2", 0.0),
    "quadratic_damping_n_s2_per_m2": ("N s^2/m^2", 0.0),
    "force_share_at_largest_deflection": ("1", 0.0),
    "largest_deflection_m": ("m", None),
}
# unit from a key's suffix (the report's naming convention), longest suffix first
SUFFIX_UNIT = (("_n_s2_per_m2", "N s^2/m^2"), ("_n_s_per_m", "N s/m"), ("_n_per_m3", "N/m^3"),
               ("_n_per_m2", "N/m^2"), ("_n_per_m", "N/m"), ("_a_s_per_m", "A s/m"), ("_a_per_m", "A/m"),
               ("_mps2", "m/s^2"), ("_mps", "m/s"), ("_pa", "Pa"), ("_hz", "Hz"), ("_s", "s"), ("_m", "m"),
               ("_a", "A"))


def _png(fig) -> str:
    import matplotlib.pyplot as plt
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=80, bbox_inches="tight")
    plt.close(fig)
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode("ascii")


def _img(src: str, alt: str) -> str:
    return f'<img src="{src}" alt="{html.escape(alt)}" class="plot"/>'


def _fmt(x, digits: int = 4) -> str:
    """``digits`` significant digits, without an exponent between 1e-3 and 1e6."""
    if x is None:
        return DASH
    if isinstance(x, str):
        return x
    x = float(x)
    if not math.isfinite(x):
        return DASH
    if x == 0 or not 1e-3 <= abs(x) < 1e6:
        return f"{x:.{digits}g}"
    mag = math.floor(math.log10(abs(x)))
    text = f"{round(x, digits - 1 - mag):.{max(0, digits - 1 - mag)}f}"
    return text.rstrip("0").rstrip(".") if "." in text else text


def _unit_of(key: str) -> str:
    for suf, unit in SUFFIX_UNIT:
        if key.endswith(suf):
            return unit
    return "1"


def _note(key: str) -> str:
    return f"<p class='note'>{html.escape(key)}: {html.escape(GLOSSARY[key])}</p>"


def _table(rows: list[list], head: list[str], tid: str | None = None) -> str:
    h = "".join(f"<th>{html.escape(x)}</th>" for x in head)
    b = "".join("<tr>" + "".join(f"<td>{html.escape(str(c))}</td>" for c in r) + "</tr>" for r in rows)
    idattr = f' id="{tid}"' if tid else ""
    return f"<table{idattr}><thead><tr>{h}</tr></thead><tbody>{b}</tbody></table>"


# ---------------------------------------------------------------------------------------------
def _severity_colorbar(fig, im, axes, vmax: float) -> None:
    """One colorbar for all rows, ticked in plain multiples of the noise (the colour is log10(1 + x))."""
    cb = fig.colorbar(im, ax=list(axes), fraction=0.03, pad=0.02)
    ticks = [x for x in (0, 1, 3, 10, 30, 100, 300, 1000, 3000, 10000) if math.log10(1 + x) <= vmax + 1e-9]
    cb.set_ticks([math.log10(1 + x) for x in ticks])
    cb.set_ticklabels([f"{x:g}" for x in ticks])
    cb.set_label("|measured - twin| band power\nin multiples of the noise power", fontsize=8)


def _maps_figure(rmap, title: str):
    import matplotlib.pyplot as plt
    rd = rmap.rd
    g = rd.grid
    t0 = rd.rec.t0_s
    groups = [(grp, names) for grp in GROUPS
              if (names := [n for n, c in rd.rec.channels.items() if c.group == grp])]
    sevs = [np.max([np.where(rmap.flags[n], np.log10(1 + np.abs(rmap.severity[n])), 0.0) for n in names], axis=0)
            for _, names in groups]
    vmax = max(1.0, max(float(s.max()) for s in sevs))
    fig, axes = plt.subplots(len(groups), 1, figsize=(9, 1.7 * len(groups) + 0.9), squeeze=False, sharex=True)
    t = g.t_center_s - t0
    im = None
    for ax, (grp, _), sev in zip(axes[:, 0], groups, sevs):
        im = ax.imshow(sev.T, origin="lower", aspect="auto", cmap="magma", vmin=0.0, vmax=vmax,
                       extent=(t[0] - g.frame_s / 4, t[-1] + g.frame_s / 4, 0, g.n_bands))
        ax.set_yticks(np.arange(g.n_bands)[::3] + 0.5)
        ax.set_yticklabels([f"{e:.0f}" for e in g.edges_hz[:-1][::3]])
        ax.set_ylabel(f"{grp}\nband [Hz]", fontsize=8)
        if rd.rec.position_time_s is not None and ax is axes[0, 0]:
            pt, px = rd.rec.position_time_s - t0, rd.rec.position_m
            ax2 = ax.secondary_xaxis("top", functions=(lambda tt, pt=pt, px=px: np.interp(tt, pt, px),
                                                        lambda xx, pt=pt, px=px: np.interp(xx, px, pt)))
            ax2.set_xlabel("vehicle position [m]", fontsize=8)
    axes[-1, 0].set_xlabel(f"time from the start of {rd.rec.name} [s]")
    _severity_colorbar(fig, im, axes[:, 0], vmax)
    fig.suptitle(title)
    return fig


def _along_line(maps):
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(9, 2.6))
    for m in maps:
        rd = m.rd
        if rd.rec.position_time_s is None:
            continue
        x = rd.rec.position_at(rd.grid.t_center_s)
        tot = np.zeros(rd.grid.n_frames)
        for n in rd.rec.channels:
            tot += np.sum(np.where(m.flags[n], np.abs(m.severity[n]), 0.0), axis=1)
        ax.semilogy(x, 1 + tot, ".-", label=rd.rec.name)
    for s in (maps[0].rd.rec.metadata.get("line") or {}).get("spans", []):
        ax.axvline(s["start_m"], color="0.7", lw=0.8)
        ax.axvline(s["start_m"] + s["length_m"], color="0.7", lw=0.8)
    ax.set_xlabel("vehicle reference position [m] (grey: span ends)")
    ax.set_ylabel("1 + flagged severity\n(sum over channels)")
    ax.legend(fontsize=7, title="recording", title_fontsize=7)
    return fig


def _nrmse_bars(before: dict, after: dict, floor: dict | None = None):
    """Per-channel NRMSE before and after; ``floor``: per channel, the part the rail's reconstruction
    noise alone makes (a tick across both bars: what no model of the physics can go below)."""
    import matplotlib.pyplot as plt
    names = list(before)
    fig, ax = plt.subplots(figsize=(9, 2.6))
    x = np.arange(len(names))
    ax.bar(x - 0.2, [before[n] for n in names], 0.4, label="before: calibrated twin")
    ax.bar(x + 0.2, [after.get(n, np.nan) for n in names], 0.4, label="after: twin + accepted physics")
    if floor:
        ax.hlines([floor.get(n, np.nan) for n in names], x - 0.42, x + 0.42, colors="k", linewidths=1.5,
                  label="gap noise in the rail alone")
    ax.set_xticks(x)
    ax.set_xticklabels(names, rotation=45, fontsize=8)
    ax.set_ylabel("band-amplitude NRMSE")
    ax.legend(fontsize=8)
    return fig


def _band_residual(rd, mp, name):
    """(n_frames, n_bands) measured - twin band amplitudes over the channel's usable bands (NaN elsewhere)."""
    am = np.sqrt(np.clip(rd.pm[name], 0, None))
    at = np.sqrt(np.clip(mp[name], 0, None))
    r = am - at
    r[:, ~rd.masks[name]] = np.nan
    return r, np.where(rd.masks[name][None, :], am, np.nan)


def _rms(x, axis):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)     # all-NaN rows (frames off the valid rail): NaN
        return np.sqrt(np.nanmean(np.square(x), axis=axis))


WAVE_WINDOW_S = 0.25


def _running_rms(t_s: np.ndarray, x: np.ndarray, window_s: float) -> tuple[np.ndarray, np.ndarray]:
    """RMS of ``x`` over consecutive windows of ``window_s`` and the windows' centre times."""
    n = max(1, int(round(window_s / float(np.median(np.diff(t_s)))))) if t_s.size > 1 else 1
    k = max(1, x.size // n)
    seg = x[:k * n].reshape(k, -1)
    return t_s[:k * n].reshape(k, -1).mean(axis=1), np.sqrt(np.mean(seg ** 2, axis=1))


def _residual_figure(rd, rd_after, name, mp_b, mp_a, wave_b, wave_a):
    """Residual measured - twin of one channel before (calibrated twin) and after (with the accepted
    physics): band amplitudes over time, their band spectrum, and the waveform when the physics
    changes it (a stochastic addition such as ambient vibration changes band powers only)."""
    import matplotlib.pyplot as plt
    ch = rd.rec.channels[name]
    unit = GROUP_UNIT[ch.group]
    t0 = rd.rec.t0_s
    rb, am = _band_residual(rd, mp_b, name)
    ra, _ = _band_residual(rd_after, mp_a, name)
    show_wave = wave_b is not None and wave_a is not None and \
        float(np.sqrt(np.mean((wave_b - wave_a) ** 2))) > 0.01 * float(np.sqrt(np.mean(wave_b ** 2)) or 1.0)
    ncol = 3 if show_wave else 2
    fig, axes = plt.subplots(1, ncol, figsize=(4.6 * ncol, 3.0))
    t = rd.grid.t_center_s - t0
    ax = axes[0]
    ax.semilogy(t, _rms(am, 1), color="0.7", lw=1.0, label="measured (for scale)")
    ax.semilogy(t, _rms(rb, 1), color="C3", lw=1.2, label="residual before")
    ax.semilogy(t, _rms(ra, 1), color="C2", lw=1.2, label="residual after")
    ax.set_xlabel(f"time from the start of {rd.rec.name} [s]")
    ax.set_ylabel(f"RMS over bands [{unit}]")
    ax.set_title("band-amplitude residual per frame", fontsize=9)
    ax.legend(fontsize=7)
    ax = axes[1]
    fc = rd.grid.band_center_hz
    m = rd.masks[name]
    ax.semilogy(fc[m], _rms(am, 0)[m], "o-", color="0.7", ms=3, label="measured (for scale)")
    ax.semilogy(fc[m], _rms(rb, 0)[m], "o-", color="C3", ms=3, label="residual before")
    ax.semilogy(fc[m], _rms(ra, 0)[m], "s--", color="C2", ms=3, label="residual after")
    ax.set_xlabel("band centre [Hz]")
    ax.set_ylabel(f"RMS over frames [{unit}]")
    ax.set_title("band spectrum of the residual", fontsize=9)
    ax.legend(fontsize=7)
    if show_wave:
        # as a running RMS: the raw traces before and after overlay each other and hide the change
        ax = axes[2]
        for w, c, lab in ((wave_b, "C3", "before"), (wave_a, "C2", "after")):
            tw, rw = _running_rms(ch.time_s - t0, w, WAVE_WINDOW_S)
            ax.semilogy(tw, rw, color=c, lw=1.2, label=f"residual {lab}")
        ax.set_xlabel(f"time from the start of {rd.rec.name} [s]")
        ax.set_ylabel(f"RMS per {WAVE_WINDOW_S:g} s [{unit}]")
        ax.set_title("waveform residual (measured - twin)", fontsize=9)
        ax.legend(fontsize=7)
    fig.suptitle(f"{name} on {rd.rec.name}: measured - twin, before and after")
    fig.tight_layout()
    return fig, show_wave


# ---------------------------------------------------------------------------------------------
def _recordings_rows(ex: dict) -> list[list]:
    rds = ex.get("rd_all", [])
    same = ex.get("heldout_is_training", False)
    rows = []
    for i, rd in enumerate(rds):
        rec = rd.rec
        role = ("training and held out (the only pass)" if same else
                "training (calibration and fitting; the fastest pass)" if i == 0 else "held out (acceptance)")
        spd = np.abs(rec.speed_mps) if rec.speed_mps is not None and rec.speed_mps.size else None
        rows.append([rec.name, role, f"{rec.t1_s - rec.t0_s:.1f}",
                     DASH if spd is None else f"{float(np.nanmean(spd)):.1f}", len(rec.channels)])
    amb = ex.get("rd_ambient")
    if amb is not None:
        rows.append([amb.rec.name, "ambient (no vehicle; noise and ambient vibration)",
                     f"{amb.rec.t1_s - amb.rec.t0_s:.1f}", DASH, len(amb.rec.channels)])
    return rows


def _mismatch_rows(rep: dict, recs: list) -> list[list]:
    """Mismatch table rows, most severe first; times from the start of their recording."""
    rows = []
    for m in sorted(rep["mismatches"], key=lambda m: -m["severity"]):
        rec_name, rel = m.get("recording"), m.get("time_from_start_s")
        if "recording" not in m:
            # a report without those keys: the recording whose time span holds it, when only one does
            hold = [r for r in recs if r.t0_s - 1e-6 <= m["time_s"][0] <= r.t1_s + 1e-6]
            if len(hold) == 1:
                rec_name, rel = hold[0].name, [m["time_s"][0] - hold[0].t0_s, m["time_s"][1] - hold[0].t0_s]
        rows.append([rec_name or DASH, ", ".join(m["channels"]),
                     DASH if rel is None else f"{rel[0]:.2f}-{rel[1]:.2f}",
                     DASH if m["position_m"] is None else f"{m['position_m'][0]:.1f}-{m['position_m'][1]:.1f}",
                     DASH if m["frequency_hz"] is None else f"{m['frequency_hz'][0]:.0f}-{m['frequency_hz'][1]:.0f}",
                     f"{m['severity']:.1f}"])
    return rows


def _physics_param_rows(m: dict, recs: list) -> list[list]:
    """One row per numeric parameter of a found physics: unit, the twin's value, the found one."""
    params = m.get("parameters") or {}
    where = "; ".join(f"{k} {v}" for k, v in params.items() if isinstance(v, str))
    chan_unit = ""
    chans = m.get("location", {}).get("channels") or []
    for r in recs:
        if chans and chans[0] in r.channels:
            chan_unit = GROUP_UNIT.get(r.channels[chans[0]].group, "")
            break
    rows = []
    for k, v in params.items():
        if isinstance(v, (str, bool, list, tuple)):
            continue
        unit, nominal = PHYSICS_PARAMS.get(k, (_unit_of(k), None))
        if k == "offset":
            unit = chan_unit or "channel unit"
        elif k == "drift_per_s":
            unit = f"{chan_unit or 'channel unit'}/s"
        if k == "first_mode_hz" and "stiffness_loss" in params:
            nominal = v / math.sqrt(max(1 - params["stiffness_loss"], 1e-6))
        elif k == "bearing_stiffness_n_per_m" and params.get("stiffness_factor"):
            nominal = v / params["stiffness_factor"]
        elif k in ("t0_s", "t1_s"):
            # stamps: shown from the start of their recording, or not at all
            rel = params.get("from_start_s")
            if rel is not None:
                v, k = rel[k == "t1_s"], f"{k} (from the start of {params.get('recording')})"
            else:
                hold = [r for r in recs if r.t0_s - 1e-6 <= v <= r.t1_s + 1e-6]
                if len(hold) != 1:
                    continue
                v, k = v - hold[0].t0_s, f"{k} (from the start of {hold[0].name})"
        elif nominal == "same":
            nominal = v
        if isinstance(v, dict):
            for sub, x in v.items():
                rows.append([m["effect"], f"{k} at {sub}", unit, _fmt(nominal), _fmt(x), DASH])
            continue
        rows.append([m["effect"] + (f" ({where})" if where else ""), k, unit, _fmt(nominal), _fmt(v), DASH])
    return rows


def _parameter_rows(rep: dict) -> list[list]:
    """Calibrated parameters: design value, updated value, change, std (from ``parameter_details``
    when the report has them)."""
    det = rep.get("parameter_details") or {}
    rows = []
    for k, v in rep["updated_parameters"].items():
        d = det.get(k) or {}
        name, sym, unit, f = CALIBRATED.get(k, (k, "", d.get("unit") or _unit_of(k), 1.0))
        nom, std = d.get("nominal"), d.get("std")
        rows.append([f"{name} ({sym})" if sym else name, k, unit, _fmt(None if nom is None else nom * f),
                     _fmt(v * f), DASH if not nom else f"{(v / nom - 1) * 100:+.1f} %",
                     _fmt(None if std is None else std * f, 2)])
    return rows


def _tried_rows(ex: dict) -> list[list]:
    fits = sorted(ex.get("fits", []), key=lambda t: (not t[1].accepted, t[2]))
    return [[hf.hyp.label, hf.hyp.category,
             ", ".join(f"{n}={p:.4g}" for n, p in zip(hf.hyp.param_names, hf.params)),
             f"{v.heldout_before:.3f} -> {v.heldout_after:.3f}", f"{d:+.1f}",
             "accepted" if v.accepted else "; ".join(v.reasons)] for hf, v, d in fits]


def _delay_note(rep: dict) -> str:
    """What the passes said about the delay of the vehicle sensors behind the position (when measured)."""
    d = (rep.get("calibration") or {}).get("sensor_delay")
    if not d:
        return ""
    what = "applied: the twin runs that much behind the stamps" if d.get("applied") else "not applied"
    return f"<p>Sensor delay: {html.escape(d['reason'])} ({what}).</p>"


def _fit_floor(rep: dict) -> dict:
    """The report's ``calibration.fit_floor`` ({} when absent)."""
    return (rep.get("calibration") or {}).get("fit_floor") or {}


def _floor_note(rep: dict) -> str:
    """What limits the calibrated fit (the gap noise in the rail, :mod:`.floor`), per channel group."""
    f = _fit_floor(rep)
    if not f:
        return ""
    groups = rep["calibration"].get("fit_per_group") or {}
    rows = [[g, _fmt(groups.get(g), 3), _fmt(v, 3)] for g, v in sorted(f["rail_uncertainty_per_group"].items())]
    return (f"<h3>What limits the calibrated fit</h3><p>{html.escape(f['explanation'])}</p>"
            + _table(rows, ["channel group", "calibrated NRMSE", "from the gap noise in the rail"], "fit-floor"))


def render(diagnosis) -> str:
    import matplotlib
    matplotlib.use("Agg")
    rep = diagnosis.report
    ex = diagnosis.extras
    rds = ex.get("rd_all", [])
    recs = [rd.rec for rd in rds] + ([ex["rd_ambient"].rec] if ex.get("rd_ambient") is not None else [])
    parts = []
    before, after = rep["fit_before"], rep["fit_after"]
    found = rep["missing_physics"]
    parts.append(
        '<section id="summary"><h2>Summary</h2>'
        f'<p>The calibrated twin misses the recordings by a band-amplitude NRMSE of {before["nrmse"]:.3f}; with '
        f'the accepted physics by {after["nrmse"]:.3f}. {len(rep["mismatches"])} located mismatch(es); '
        f'{len(found)} missing physics accepted; {len(rep["rejected"])} hypotheses rejected.</p>'
        + ("<ul>" + "".join(f"<li><b>{html.escape(m['effect'])}</b> ({html.escape(m['category'])}): "
                            f"{html.escape(m['explanation'])}</li>" for m in found) + "</ul>"
           if found else "<p>Nothing is missing: the calibrated twin explains the recordings within the noise.</p>")
        + _floor_note(rep)
        + "<h3>Recordings</h3>"
        + _table(_recordings_rows(ex), ["recording", "role", "duration [s]", "mean speed [m/s]", "channels"],
                 "recordings")
        + _delay_note(rep)
        + "<p class='note'>Times in this report count from each recording's first sample.</p></section>")
    parts.append('<section id="glossary"><h2>How to read the numbers</h2><dl>'
                 + "".join(f"<dt>{html.escape(k)}</dt><dd>{html.escape(v)}</dd>" for k, v in GLOSSARY.items())
                 + "</dl></section>")
    w = ['<section id="where"><h2>Where twin and recordings differ</h2>',
         "<p class='note'>Residual maps of the calibrated twin: each cell is one 0.5 s frame and one band; "
         "only cells flagged as a mismatch are coloured, by their severity.</p>"]
    maps = list(ex.get("maps_before", []))
    for m in maps:
        w.append(_img(_png(_maps_figure(m, f"residual map of the calibrated twin: {m.rd.rec.name}")),
                      f"residual map {m.rd.rec.name}"))
    amb = ex.get("rd_ambient")
    if amb is not None and ex.get("base_spec") is not None:
        from .localize import residual_map
        try:
            am = residual_map(amb, model_powers(ex["base_spec"], amb))
            w.append(_img(_png(_maps_figure(am, f"residual map of the calibrated twin: {amb.rec.name}")),
                          f"residual map {amb.rec.name}"))
        except Exception:        # no twin for a recording without line data: the table still lists it
            pass
    if maps:
        w.append(_img(_png(_along_line(maps)), "residual along the line"))
    w.append("<h3>Located mismatches, most severe first</h3>")
    w.append(_table(_mismatch_rows(rep, recs),
                    ["recording", "channels", "time from start [s]", "position [m]", "band [Hz]",
                     "severity [x noise power]"], "mismatches"))
    w.append(_note("severity"))
    # mismatches that are not a band of a residual map (the span's mode pattern) say what they are
    for m in rep["mismatches"]:
        if m.get("explanation"):
            now = m.get("after_found_physics") or {}
            tail = ("" if "explained" not in now else
                    " The twin after " + ("explains it." if now["explained"] else
                                         f"does not explain it (ratio still {100 * now['ratio_shift']:+.1f} %)."))
            w.append(f"<p class='disc'>{html.escape(m['explanation'] + tail)} (severity: standard errors)</p>")
    w.append("</section>")
    parts.append("".join(w))
    ch_rows = [[m["effect"], m["category"], ", ".join(m["location"].get("channels") or []) or DASH, m["explanation"],
                f"{m['evidence']['heldout_nrmse_before']:.3f} -> {m['evidence']['heldout_nrmse_after']:.3f}",
                f"{m['evidence']['delta_bic']:+.1f}"] for m in found]
    pp_rows = [r for m in found for r in _physics_param_rows(m, recs)]
    parts.append('<section id="chosen"><h2>Found physics</h2>'
                 + (_table(ch_rows, ["effect", "category", "channels", "explanation", "held-out NRMSE before -> after",
                                     "delta BIC"], "physics")
                    + _note("held-out") + _note("delta BIC")
                    + "<h3>Its parameters</h3>"
                    + _table(pp_rows, ["effect", "parameter", "unit", "nominal (twin without it)", "found", "std"],
                             "physics-parameters")
                    + _note("nominal")
                    if found else "<p>None accepted.</p>")
                 + "</section>")
    parts.append('<section id="parameters"><h2>Updated twin parameters</h2>'
                 + _table(_parameter_rows(rep), ["parameter", "key", "unit", "nominal (design)", "updated",
                                                 "change", "std"], "parameters")
                 + _note("nominal") + _note("std") + "</section>")
    ba = ['<section id="before-after"><h2>Measured vs twin, before and after</h2>',
          "<p class='note'>Before: the calibrated twin. After: with the accepted physics. "
          "The plots show the residual (measured - twin): where it drops, the physics explains the recording. "
          "A black tick marks the part of a channel's NRMSE the gap sensors' noise makes through the rail.</p>",
          _img(_png(_nrmse_bars(before["per_channel"], after["per_channel"],
                                _fit_floor(rep).get("rail_uncertainty_per_channel"))), "per-channel NRMSE"),
          _note("NRMSE")]
    if rds and ex.get("base_spec") is not None and ex.get("final_spec") is not None:
        gains = {n: before["per_channel"][n] - after["per_channel"].get(n, before["per_channel"][n])
                 for n in before["per_channel"]}
        # the channels the chosen physics acts on first (a law judged on a band of them need not top
        # the whole-recording gains), then the largest gains
        own = [c for m in found[:1] for c in m["location"]["channels"] if c in gains]
        show = (sorted(own, key=gains.get, reverse=True)
                + [n for n in sorted(gains, key=gains.get, reverse=True) if n not in own])[:2]
        # a held-out pass: where the evidence is
        rd, rd_after = rds[-1], (ex.get("rd_after") or rds)[-1]
        show = [n for n in show if n in rd.rec.channels]
        if show:
            mp_b, mp_a = model_powers(ex["base_spec"], rd), model_powers(ex["final_spec"], rd_after)
            try:
                pb, pa = predict(ex["base_spec"], rd.rec), predict(ex["final_spec"], rd_after.rec)
            except Exception:    # an unstable twin: band amplitudes only
                pb = pa = None
            for n in show:
                ch = rd.rec.channels[n]
                wb = None if pb is None else ch.values - pb[n]
                wa = None if pa is None else rd_after.rec.channels[n].values - pa[n]
                fig, wave = _residual_figure(rd, rd_after, n, mp_b, mp_a, wb, wa)
                ba.append(_img(_png(fig), f"residual before and after {n}"))
                if not wave:
                    ba.append(f"<p class='note'>{html.escape(n)}: the accepted physics does not change the twin's "
                              "waveform here (it adds band power, e.g. random vibration, or acts elsewhere), so "
                              "only band amplitudes are shown.</p>")
        ba.append(_note("band amplitude"))
    ba.append("</section>")
    parts.append("".join(ba))
    parts.append('<section id="tried"><h2>What was tried</h2>'
                 + _table(_tried_rows(ex), ["hypothesis", "category", "fitted parameters",
                                            "held-out NRMSE before -> after", "delta BIC", "verdict"], "tried-table")
                 + _note("log-likelihood ratio")
                 + f"<details><summary>Rejected ({len(rep['rejected'])})</summary>"
                 + _table([[r["effect"], r["why"]] for r in rep["rejected"]], ["effect", "why"], "rejected")
                 + "</details>"
                 + "".join(f"<p class='disc'>Discovery: {html.escape(d['explanation'])}</p>"
                           for d in rep.get("discovery", []))
                 + "</section>")
    css = ("body{font-family:sans-serif;max-width:1150px;margin:auto;padding:1em}table{border-collapse:collapse;"
           "font-size:12px;margin:0.5em 0}td,th{border:1px solid #bbb;padding:2px 6px;vertical-align:top}"
           "th{background:#eee}img.plot{max-width:100%;display:block;margin:0.5em 0}"
           "p.note{font-size:12px;color:#444;margin:0.2em 0}dt{font-weight:bold;margin-top:0.3em}"
           "dd{margin-left:1.5em;font-size:13px}")
    return ("<!DOCTYPE html><html><head><meta charset='utf-8'><title>maglev-ros diagnosis</title>"
            f"<style>{css}</style></head><body><h1>Twin vs recordings: diagnosis</h1>"
            + "".join(parts) + "</body></html>")
