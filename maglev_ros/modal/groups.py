"""Modes of channel groups identified on their own, merged into the joint identification (no rclpy).

Identical structures that move independently (decoupled spans of one design, each with its own
sensors) ring at one frequency: identified together their poles are repeated, the shape at each
model order is an arbitrary mixture of the structures' own, and no pole stabilizes (three
simply supported 12.4 m spans under ambient excitation: no mode at all). Whether the groups (a
span's sensors each) move apart is read from the data (:func:`independent_groups`: their
coherence, weighted by where the energy is, no higher than independent records give by chance);
then each group is identified alone as well (one structure's groups, identified apart, only add
biased copies of its modes). A group's mode joins the joint result unless a
joint mode already explains it: its frequency within the joint mode's half-power half-width
(two modes closer than that are not told apart by a spectrum) or three combined standard errors,
and its shape on the group's channels like the joint one's (MAC above 1/2, the suite's matching
bar). An added mode's shape is zero on the other groups' channels: it was measured only there.
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import replace

import numpy as np

from maglev_ros.modal.peaks import spectral_peak
from maglev_ros.modal.ssi_cov import ModalResult
from maglev_ros.modal.stabilization import PoleTable, mac

SAME_MAC = 0.5
N_STD = 3.0


class ColumnChunks:
    """The columns ``cols`` of a re-iterable chunk source (:class:`~maglev_ros.modal.chunked.TopicChunks`)."""

    def __init__(self, source, cols: Sequence[int]):
        self.source, self.cols = source, list(cols)
        self.n_samples = source.n_samples
        self.n_channels = len(self.cols)

    def __iter__(self):
        for x in self.source:
            yield x[:, self.cols]


CHANCE_LEVEL = 0.99     # coherence of independent records stays below its 99th percentile


def independent_groups(data: np.ndarray, fs_hz: float, groups: Sequence[Sequence[int]]) -> tuple[bool, dict]:
    """Whether the channel groups (column indices of ``data``, (n, channels)) move independently, and
    the evidence: for every pair of groups the largest, over their channel pairs, of the coherence
    weighted by the two channels' power (sum of gamma^2 Pa Pb / sum of Pa Pb, Welch with K segments),
    against the 99th percentile of one bin's coherence for independent records, 1 - 0.01^(1/(K-1))."""
    from scipy.signal import csd, welch
    x = np.asarray(data, dtype=float)
    x = x - x.mean(axis=0)
    n = x.shape[0]
    nper = int(2 ** max(6, int(math.log2(max(n // 8, 64)))))
    k = max(2, 2 * n // nper - 1)
    bar = 1.0 - (1.0 - CHANCE_LEVEL) ** (1.0 / (k - 1))
    p = {c: welch(x[:, c], fs_hz, nperseg=nper)[1] for g in groups for c in g}
    worst = 0.0
    for a in range(len(groups)):
        for b in range(a + 1, len(groups)):
            for ca in groups[a]:
                for cb in groups[b]:
                    pab = np.abs(csd(x[:, ca], x[:, cb], fs_hz, nperseg=nper)[1]) ** 2
                    w = p[ca] * p[cb]
                    if np.sum(w) > 0:
                        worst = max(worst, float(np.sum(pab) / np.sum(w)))   # sum gamma^2 w / sum w
    return worst <= bar, {"weighted_coherence": worst, "chance_99": bar, "segments": k}


def spectral_peaks(x: np.ndarray, fs_hz: float, part: ModalResult, undecided: bool = False) -> set[int]:
    """Indices of ``part``'s modes that are spectral peaks of their own in the columns ``x`` (samples
    x its channels; :mod:`.peaks`): a group of two sensors cannot tell a pole on the skirt of its
    span's mode from a mode by its shape (a 2-channel span placed one at 18.5 Hz, 1 %, beside its
    23.5 Hz mode). ``undecided``: whether a mode too close to another for the PSD to resolve counts."""
    f = np.array([m.frequency_hz for m in part.modes], dtype=float)
    out = set()
    for k in range(f.size):
        ratio, needed = spectral_peak(x.T, fs_hz, float(f[k]), np.delete(f, k))
        if (ratio >= needed > 0) or (undecided and needed == 0):
            out.add(k)
    return out


def _same(joint: ModalResult, j: int, part: ModalResult, k: int, cols: list[int]) -> bool:
    mj, mk = joint.modes[j], part.modes[k]
    f = mj.frequency_hz
    s = math.hypot(*(x if np.isfinite(x) else 0.0 for x in (mj.std_frequency_hz, mk.std_frequency_hz)))
    if abs(mk.frequency_hz - f) > max(mj.damping_ratio * f, N_STD * s):
        return False
    return float(mac(np.asarray(joint.complex_shapes[j])[cols], np.asarray(part.complex_shapes[k]))) > SAME_MAC


def merge_group_modes(joint: ModalResult, parts: Sequence[tuple[Sequence[str], ModalResult]],
                      keep: Sequence[set[int]] | None = None) -> tuple[ModalResult, list[int]]:
    """``joint`` (all channels) with the modes of ``parts`` ((group channels, their result)) no joint
    mode explains; ids renumbered by frequency. ``keep``: per part, the indices of its modes that may
    be added (default: all). Returns the result and how many each part added."""
    channels = tuple(joint.channels)
    modes = [(m, np.asarray(joint.complex_shapes[i]), ("joint", i)) for i, m in enumerate(joint.modes)]
    added = []
    for g, (names, part) in enumerate(parts):
        cols = [channels.index(n) for n in names]
        n_add = 0
        for k, m in enumerate(part.modes):
            if keep is not None and k not in keep[g]:
                continue
            if any(_same(joint, j, part, k, cols) for j in range(len(joint.modes))):
                continue
            phi = np.zeros(len(channels), dtype=complex)
            phi[cols] = np.asarray(part.complex_shapes[k])
            shape = {c: 0.0 for c in channels}
            shape.update({str(c): float(v) for c, v in m.mode_shape.items()})
            modes.append((replace(m, mode_shape=shape), phi, (g, k)))
            n_add += 1
        added.append(n_add)
    if not any(added):
        return joint, added
    modes.sort(key=lambda t: t[0].frequency_hz)
    label = {src: i for i, (_, _, src) in enumerate(modes)}
    tables = []
    for g, res in [("joint", joint)] + list(enumerate(p for _, p in parts)):
        st = res.stabilization
        if st is None or len(st) == 0:
            continue
        shapes = None
        if st.shapes is not None:
            if g == "joint":
                shapes = st.shapes
            else:
                cols = [channels.index(n) for n in parts[g][0]]
                shapes = np.zeros((len(st), len(channels)), dtype=complex)
                shapes[:, cols] = st.shapes
        lab = np.array([label.get((g, int(c)), -1) if c >= 0 else -1 for c in st.cluster], dtype=int)
        tables.append(PoleTable(st.order, st.frequency_hz, st.damping_ratio, shapes, st.mpc, st.stable, lab))
    table = None
    if tables:
        with_shapes = all(t.shapes is not None for t in tables)
        table = PoleTable(*(np.concatenate([getattr(t, f) for t in tables]) if f != "shapes" or with_shapes else None
                            for f in ("order", "frequency_hz", "damping_ratio", "shapes", "mpc", "stable", "cluster")))
    out = replace(joint, modes=tuple(replace(m, id=f"M{i + 1}") for i, (m, _, _) in enumerate(modes)),
                  stabilization=table, complex_shapes=tuple(phi for _, phi, _ in modes),
                  method=f"{joint.method}; per span group")
    return out, added


def without_modes(res: ModalResult, drop: set[int]) -> ModalResult:
    """``res`` without its modes ``drop`` (indices): their stabilization poles unclustered, ids renumbered."""
    if not drop:
        return res
    keep = [i for i in range(len(res.modes)) if i not in drop]
    new = {old: k for k, old in enumerate(keep)}
    st = res.stabilization
    if st is not None and len(st):
        lab = np.array([new.get(int(c), -1) if c >= 0 else -1 for c in st.cluster], dtype=int)
        st = replace(st, cluster=lab)
    shapes = tuple(res.complex_shapes[i] for i in keep) if len(res.complex_shapes) == len(res.modes) else ()
    return replace(res, modes=tuple(replace(res.modes[i], id=f"M{k + 1}") for k, i in enumerate(keep)),
                   stabilization=st, complex_shapes=shapes)
