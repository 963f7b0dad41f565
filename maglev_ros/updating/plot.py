"""Figures of a two-layer update (paper 000 Tables 4-5, Figs. 12-14): Pareto fronts with the GRP
choice, measured / nominal / updated frequencies with a MAC table, magnet acceleration time
histories measured vs nominal vs updated. matplotlib (Agg), imported lazily."""
from __future__ import annotations

from pathlib import Path

import numpy as np


def _plt():
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


def save_update_plots(up, out_dir, batch=None) -> list[str]:
    """``up``: ``pipeline.TwoLayerUpdate``. Writes pareto.png, frequencies.png, magnet_accel.png
    (only with a magnet layer) and magnet_accel_heldout.png (only with a held-out pass; an earlier
    one of either is removed) into ``out_dir`` (created),
    all renamed into place together, or staged in ``batch`` (:class:`maglev_ros.outputs.Batch`);
    returns the paths."""
    from maglev_ros.outputs import batch_or_new
    with batch_or_new(batch) as b:
        return _save(up, b.make_dir(out_dir, "--plot"), b)


def _save(up, out: Path, batch) -> list[str]:
    plt = _plt()
    paths = []
    layers = [("guideway layer", up.guideway, ("f1 = sum |f - f_meas| / f_meas", "f2 = sum (1 - MAC)"))]
    if up.magnet is not None:
        layers.append(("magnet layer", up.magnet, ("f1 = NRMSE of magnet acceleration", "f2 = 1 - correlation")))
    fig, axes = plt.subplots(1, len(layers), figsize=(5.5 * len(layers), 4.2), squeeze=False)
    for ax, (title, lay, labels) in zip(axes[0], layers):
        f = np.asarray(lay.pareto.f)
        ax.plot(f[:, 0], f[:, 1], "o", ms=4, mfc="none", label=f"Pareto archive ({f.shape[0]})")
        ax.plot(f[lay.grp_index, 0], f[lay.grp_index, 1], "r*", ms=14, label="GRP choice")
        ax.set_xlabel(labels[0])
        ax.set_ylabel(labels[1])
        ax.set_title(f"{title}: {lay.pareto.method}, {lay.pareto.n_evaluations} evaluations")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    p = out / "pareto.png"
    _write(batch, p, fig, plt)
    paths.append(str(p))

    doc = up.document
    fm = np.array(doc["frequencies_hz"]["measured"])
    fn = np.array(doc["frequencies_hz"]["nominal"])
    fu = np.array(doc["frequencies_hz"]["updated"])
    fig, (ax, axt) = plt.subplots(1, 2, figsize=(11, 4.2), gridspec_kw={"width_ratios": [1.1, 1.3]})
    k = np.arange(fm.size)
    ax.bar(k - 0.25, fm, 0.25, label="measured")
    ax.bar(k, fn, 0.25, label="nominal model")
    ax.bar(k + 0.25, fu, 0.25, label="updated model")
    ax.set_xticks(k, [f"mode {i + 1}" for i in k])
    ax.set_ylabel("frequency [Hz]")
    ax.set_yscale("log")
    ax.legend(fontsize=8)
    ax.set_title("guideway frequencies")
    rows = []
    macs_n, macs_u = doc["mac"]["nominal"] or [float("nan")] * fm.size, doc["mac"]["updated"] or [float("nan")] * fm.size
    for i in range(fm.size):
        rows.append([f"{fm[i]:.3f}", f"{fn[i]:.3f}", f"{100 * (fn[i] / fm[i] - 1):+.2f}", f"{fu[i]:.3f}",
                     f"{100 * (fu[i] / fm[i] - 1):+.2f}", f"{macs_n[i]:.4f}", f"{macs_u[i]:.4f}"])
    axt.axis("off")
    tab = axt.table(cellText=rows, rowLabels=[f"mode {i + 1}" for i in k],
                    colLabels=["meas. Hz", "nominal Hz", "err %", "updated Hz", "err %", "MAC nom.", "MAC upd."],
                    loc="center")
    tab.auto_set_font_size(False)
    tab.set_fontsize(8)
    tab.scale(1.0, 1.4)
    pars = doc["parameters"]
    txt = "\n".join(f"{n}: {v['value']:.4g} {v['unit']}" + ("" if v["std"] is None else f" +- {v['std']:.2g}")
                    + ("" if v["identifiable"] else " (not identifiable alone)") for n, v in pars.items())
    axt.text(0.0, 0.02, txt, fontsize=7, family="monospace", transform=axt.transAxes, va="bottom")
    fig.tight_layout()
    p = out / "frequencies.png"
    _write(batch, p, fig, plt)
    paths.append(str(p))

    e = doc["magnet_accel_nrmse"] or {}
    h = up.provenance.get("heldout") or {}
    for name, series, err, what in (("magnet_accel.png", up.magnet_series, e, "fitted"),
                                    ("magnet_accel_heldout.png", up.heldout_series, h, "held out, never fitted")):
        p = out / name
        if not series:
            batch.remove(p)                         # not beside plots of an update it is not from
            continue
        _magnet_figure(plt, batch, p, series, err, what)
        paths.append(str(p))
    return paths


def _magnet_figure(plt, batch, path: Path, series: dict, err: dict, what: str) -> None:
    """Measured vs nominal vs updated magnet accelerations of the first pass in ``series``."""
    label, (t, meas, nom, upd, mags) = next(iter(series.items()))
    n = meas.shape[1]
    fig, axes = plt.subplots(n, 1, figsize=(10, 2.1 * n + 0.6), sharex=True, squeeze=False)
    for j, ax in enumerate(axes[:, 0]):
        ax.plot(t, meas[:, j], "k-", lw=0.8, label="measured")
        ax.plot(t, nom[:, j], "-", color="tab:orange", lw=0.8, label="nominal model")
        ax.plot(t, upd[:, j], "--", color="tab:blue", lw=0.8, label="updated model")
        ax.set_ylabel(f"magnet {mags[j]}\n[m/s^2]")
        ax.grid(alpha=0.3)
    axes[0, 0].legend(fontsize=8, ncol=3, loc="upper right")
    axes[0, 0].set_title(f"{label} ({what}): magnet acceleration, NRMSE nominal "
                         f"{err.get('nominal', float('nan')):.3f} -> updated {err.get('updated', float('nan')):.3f}")
    axes[-1, 0].set_xlabel("time [s]")
    fig.tight_layout()
    _write(batch, path, fig, plt)


def _write(batch, path: Path, fig, plt) -> None:
    try:
        batch.write_figure(path, fig, "--plot", dpi=110)
    finally:
        plt.close(fig)
