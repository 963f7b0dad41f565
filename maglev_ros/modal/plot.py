"""Stabilization diagram over the averaged singular-value spectrum (matplotlib, Agg; no rclpy).

The picture engineers expect: every pole of every model order as a marker at (frequency, order),
coloured by its stability (new / stable frequency / + damping / + shape), the selected physical
modes as vertical lines, and on a second axis the first singular values of the cross-PSD matrix
(log scale) so the poles can be read against the spectrum's peaks.
"""
from __future__ import annotations

import numpy as np

from maglev_ros.modal.ssi_cov import ModalResult

_STYLE = {0: ("x", "0.6", "new / unstable"), 1: ("^", "tab:orange", "stable f"),
          2: ("s", "tab:blue", "stable f, zeta"), 3: ("o", "tab:green", "stable f, zeta, MAC")}


def stabilization_figure(result: ModalResult, title: str = "", freq_range_hz=None):
    """A matplotlib Figure of the stabilization diagram of ``result``."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(11, 6.5))
    st = result.stabilization
    fmax = freq_range_hz[1] if freq_range_hz else 0.5 * result.fs_hz
    fmin = freq_range_hz[0] if freq_range_hz else 0.0
    if st is not None and len(st):
        top = 3 if st.shapes is not None else 2
        for code, (mk, col, lab) in _STYLE.items():
            if code > top:
                continue
            sel = st.stable == code
            if np.any(sel):
                ax.plot(st.frequency_hz[sel], st.order[sel], mk, ms=4 if code else 3, color=col,
                        mfc="none" if code < top else col, label=lab, alpha=0.8)
        ax.set_ylim(0, st.order.max() + 2)
    for m in result.modes:
        ax.axvline(m.frequency_hz, color="k", lw=0.8, ls="--", alpha=0.6)
        ax.text(m.frequency_hz, ax.get_ylim()[1], f"{m.id} {m.frequency_hz:.2f} Hz ",
                fontsize=7, va="top", ha="right", rotation=90)
    ax.set_xlabel("frequency [Hz]")
    ax.set_ylabel("model order")
    ax.set_xlim(fmin, fmax)
    if fmin > 0 and fmax / fmin > 20:       # a multi-band search spans decades: log axis
        ax.set_xscale("log")
    if result.spectrum is not None:
        ax2 = ax.twinx()
        sp = result.spectrum
        sel = (sp.frequency_hz >= fmin) & (sp.frequency_hz <= fmax)
        for k in range(sp.singular_values.shape[1]):
            ax2.semilogy(sp.frequency_hz[sel], sp.singular_values[sel, k], lw=1.0 if k == 0 else 0.6,
                         color="tab:purple", alpha=1.0 if k == 0 else 0.4,
                         label="1st singular value" if k == 0 else None)
        ax2.set_ylabel("singular values of the cross-PSD [unit^2/Hz]")
        ax2.legend(loc="upper right", fontsize=8)
        ax.set_zorder(ax2.get_zorder() + 1)             # poles drawn over the spectrum
        ax.patch.set_visible(False)
    ax.legend(loc="upper left", fontsize=8)
    ax.set_title(title or f"stabilization diagram ({result.method}, fs {result.fs_hz:.1f} Hz)")
    fig.tight_layout()
    return fig


def save_stabilization_diagram(result: ModalResult, path, title: str = "", freq_range_hz=None,
                               batch=None, option: str | None = None):
    """Write the diagram to ``path`` atomically, or stage it in ``batch``
    (:class:`maglev_ros.outputs.Batch`) to be renamed with the other outputs."""
    import matplotlib.pyplot as plt
    from maglev_ros.outputs import batch_or_new
    fig = stabilization_figure(result, title, freq_range_hz)
    try:
        with batch_or_new(batch) as b:
            b.write_figure(path, fig, option, dpi=120)
    finally:
        plt.close(fig)
