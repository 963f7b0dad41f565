"""Stabilization diagram, pole clustering and mode-shape quality indicators (no rclpy).

Shared by :mod:`maglev_ros.modal.ssi_cov` and :mod:`maglev_ros.modal.transmissibility`.

A pole computed at model order ``n`` is *stable* when the nearest pole of the previous order
(in the combined frequency/MAC distance) lies within ``freq_tol`` (relative frequency change),
``damping_tol`` (relative damping change) and ``mac_tol`` (1 - MAC). Stable poles are then grouped
by agglomerative (average-linkage) hierarchical clustering on the distance
``d = |f_a - f_b| / max(f_a, f_b) + w_mac (1 - MAC_ab)`` (Magalhaes et al. 2009, the usual
automated-OMA choice) and a cluster is a physical mode when it holds poles from at least
``min_cluster_fraction`` of the computed orders. A cluster whose shape repeats (MAC > 0.8) that of
a better-supported cluster within 15 % in frequency is dropped as a mathematical "shadow" (seen at
high orders next to close pairs). The mode value is the cluster median; the representative pole
(for the mode shape) is the member closest to that median.

Hand-written rather than a library: the only maintained automated-OMA peers (koma-python,
pyOMA2) pull heavy GUI/plotting stacks and are much slower; the clustering itself is scipy's.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.cluster.hierarchy import fcluster, linkage
from scipy.spatial.distance import squareform


# --------------------------------------------------------------------------------------------
# mode-shape utilities
# --------------------------------------------------------------------------------------------
def mac(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Modal assurance criterion between the columns of ``a`` (l, p) and ``b`` (l, q) -> (p, q).

    Works for real and complex shapes; 1-D inputs give a scalar.
    """
    a2 = np.atleast_2d(np.asarray(a).T).T if np.ndim(a) == 1 else np.asarray(a)
    b2 = np.atleast_2d(np.asarray(b).T).T if np.ndim(b) == 1 else np.asarray(b)
    num = np.abs(a2.conj().T @ b2) ** 2
    den = np.outer(np.sum(np.abs(a2) ** 2, axis=0), np.sum(np.abs(b2) ** 2, axis=0))
    out = num / np.where(den > 0, den, np.inf)
    if np.ndim(a) == 1 and np.ndim(b) == 1:
        return float(out[0, 0])
    return out


def mpc(phi: np.ndarray) -> float:
    """Modal phase collinearity (Pappa et al. 1993): 1 for a real (mono-phase) shape."""
    phi = np.asarray(phi, dtype=complex)
    re, im = phi.real, phi.imag
    sxx, syy, sxy = re @ re, im @ im, re @ im
    tot = sxx + syy
    if tot <= 0:
        return 0.0
    return float(((sxx - syy) ** 2 + 4.0 * sxy ** 2) / tot ** 2)


def mpd(phi: np.ndarray) -> float:
    """Mean phase deviation in degrees (Reynders et al. 2012): amplitude-weighted deviation of the
    component phases from the best straight line through the shape in the complex plane."""
    phi = np.asarray(phi, dtype=complex)
    amp = np.abs(phi)
    if amp.sum() <= 0:
        return 90.0
    _, _, vt = np.linalg.svd(np.column_stack([phi.real, phi.imag]), full_matrices=False)
    v12, v22 = vt[1, 0], vt[1, 1]
    num = np.abs(phi.real * v22 - phi.imag * v12)
    den = np.hypot(v12, v22) * np.where(amp > 0, amp, 1.0)
    ang = np.arccos(np.clip(num / den, -1.0, 1.0))
    return float(np.degrees(np.sum(amp * ang) / np.sum(amp)))


def real_mode_shape(phi: np.ndarray) -> np.ndarray:
    """Real-valued shape: rotate the complex shape to the angle that maximizes the energy of its
    real part, take the real part, scale to max |value| = 1 with the largest component positive."""
    phi = np.asarray(phi, dtype=complex)
    # angle maximizing ||Re(e^{-i t} phi)||^2 = (|phi|^2 + Re(e^{-2it} sum phi^2)) / 2
    t = 0.5 * np.angle(np.sum(phi ** 2))
    r = (phi * np.exp(-1j * t)).real
    k = int(np.argmax(np.abs(r)))
    if r[k] == 0:
        return r
    return r / r[k]


# --------------------------------------------------------------------------------------------
# poles table
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class PoleTable:
    """All poles of a multi-order identification, one row per pole.

    ``shapes`` (n_poles, n_channels) complex, may be None (transmissibility fits give no shapes).
    ``stable`` codes: 0 new/unstable, 1 stable frequency, 2 stable freq+damping,
    3 stable freq+damping+MAC (or freq+damping when no shapes). ``cluster`` = mode index or -1.
    """
    order: np.ndarray
    frequency_hz: np.ndarray
    damping_ratio: np.ndarray
    shapes: np.ndarray | None
    mpc: np.ndarray
    stable: np.ndarray
    cluster: np.ndarray

    def __len__(self) -> int:
        return int(self.order.size)

    def to_dict(self) -> dict:
        return {
            "order": self.order.astype(int).tolist(),
            "frequency_hz": self.frequency_hz.tolist(),
            "damping_ratio": self.damping_ratio.tolist(),
            "mpc": self.mpc.tolist(),
            "stable": self.stable.astype(int).tolist(),
            "cluster": self.cluster.astype(int).tolist(),
        }


@dataclass(frozen=True)
class StabilityCriteria:
    """Tolerances for the stabilization diagram and the selection of physical poles."""
    freq_tol: float = 0.01            # relative frequency change to the previous order
    damping_tol: float = 0.10         # relative damping change to the previous order
    mac_tol: float = 0.02             # 1 - MAC to the previous order's pole
    min_damping: float = 0.0          # physical poles: damping ratio range (exclusive low)
    max_damping: float = 0.15
    min_mpc: float = 0.5              # reject poles with lower MPC (0 = keep all; mixed
    #                                   velocity/acceleration channels need 0)
    cluster_distance: float = 0.02    # cut of the average-linkage dendrogram
    mac_weight: float = 1.0           # weight of (1 - MAC) in the cluster distance
    min_cluster_fraction: float = 0.25  # a mode must be stable in this fraction of the orders
    min_cluster_size: int = 3
    duplicate_mac: float = 0.8        # shadow clusters: MAC above this with a better-supported
    duplicate_freq: float = 0.15      # cluster within this relative frequency are dropped


def stability_flags(order: np.ndarray, freq: np.ndarray, zeta: np.ndarray,
                    shapes: np.ndarray | None, crit: StabilityCriteria) -> np.ndarray:
    """Stability code per pole against the previous computed order (see :class:`PoleTable`)."""
    stable = np.zeros(order.size, dtype=np.int8)
    orders = np.unique(order)
    idx_by_order = {o: np.flatnonzero(order == o) for o in orders}
    for prev, cur in zip(orders[:-1], orders[1:]):
        ip, ic = idx_by_order[prev], idx_by_order[cur]
        if ip.size == 0 or ic.size == 0:
            continue
        df = np.abs(freq[ic][:, None] - freq[ip][None, :]) / np.maximum(freq[ic][:, None], 1e-12)
        if shapes is not None:
            m = mac(shapes[ic].T, shapes[ip].T)
            dist = df + (1.0 - m)
        else:
            m = None
            dist = df
        j = np.argmin(dist, axis=1)
        rows = np.arange(ic.size)
        ok_f = df[rows, j] <= crit.freq_tol
        zc, zp = zeta[ic], zeta[ip][j]
        ok_d = np.abs(zc - zp) <= crit.damping_tol * np.maximum(np.abs(zc), 1e-12)
        ok_m = (1.0 - m[rows, j]) <= crit.mac_tol if m is not None else np.ones(ic.size, bool)
        code = np.where(ok_f, 1, 0)
        code = np.where(ok_f & ok_d, 2, code)
        code = np.where(ok_f & ok_d & ok_m, 3, code)
        stable[ic] = code
    return stable


@dataclass(frozen=True)
class PoleCluster:
    members: np.ndarray               # indices into the pole table
    representative: int               # index of the member closest to the median
    frequency_hz: float
    damping_ratio: float
    std_frequency_hz: float           # spread (std) within the cluster
    std_damping_ratio: float


def cluster_poles(table_order: np.ndarray, freq: np.ndarray, zeta: np.ndarray,
                  shapes: np.ndarray | None, mpc_values: np.ndarray, stable: np.ndarray,
                  crit: StabilityCriteria, freq_range_hz: tuple[float, float],
                  n_orders: int) -> tuple[list[PoleCluster], np.ndarray]:
    """Select physical poles: fully stable, in range, then hierarchical clustering.

    Returns clusters sorted by frequency and the cluster label per pole (-1 when none).
    """
    full = 3 if shapes is not None else 2
    cand = np.flatnonzero((stable >= full) & (zeta > crit.min_damping) & (zeta < crit.max_damping)
                          & (freq >= freq_range_hz[0]) & (freq <= freq_range_hz[1])
                          & (mpc_values >= crit.min_mpc))
    labels_all = np.full(freq.size, -1, dtype=int)
    if cand.size < max(crit.min_cluster_size, 1):
        return [], labels_all
    f = freq[cand]
    d = np.abs(f[:, None] - f[None, :]) / np.maximum(f[:, None], f[None, :])
    if shapes is not None:
        d = d + crit.mac_weight * (1.0 - mac(shapes[cand].T, shapes[cand].T))
    d = np.maximum(0.5 * (d + d.T), 0.0)
    np.fill_diagonal(d, 0.0)
    if cand.size == 1:
        labels = np.array([1])
    else:
        z = linkage(squareform(d, checks=False), method="average")
        labels = fcluster(z, t=crit.cluster_distance, criterion="distance")
    min_size = max(crit.min_cluster_size, int(np.ceil(crit.min_cluster_fraction * n_orders)))
    clusters: list[PoleCluster] = []
    for lab in np.unique(labels):
        mem = cand[labels == lab]
        # one pole per order: keep the one closest to the cluster median frequency
        fmed = np.median(freq[mem])
        keep = []
        for o in np.unique(table_order[mem]):
            mo = mem[table_order[mem] == o]
            keep.append(mo[np.argmin(np.abs(freq[mo] - fmed))])
        mem = np.array(sorted(keep))
        if mem.size < min_size:
            continue
        fm, zm = float(np.median(freq[mem])), float(np.median(zeta[mem]))
        score = np.abs(freq[mem] - fm) / fm + np.abs(zeta[mem] - zm) / max(zm, 1e-9) * 0.1
        rep = int(mem[np.argmin(score)])
        clusters.append(PoleCluster(
            members=mem, representative=rep, frequency_hz=fm, damping_ratio=zm,
            std_frequency_hz=float(np.std(freq[mem], ddof=1)) if mem.size > 1 else float("nan"),
            std_damping_ratio=float(np.std(zeta[mem], ddof=1)) if mem.size > 1 else float("nan")))
    clusters.sort(key=lambda c: c.frequency_hz)
    if shapes is not None and len(clusters) > 1:
        clusters = _drop_shape_duplicates(clusters, shapes, crit)
    for k, c in enumerate(clusters):
        labels_all[c.members] = k
    return clusters, labels_all


def _drop_shape_duplicates(clusters, shapes, crit):
    """Remove "shadow" clusters: a cluster whose shape has MAC > ``crit.duplicate_mac`` with a
    cluster within ``crit.duplicate_freq`` (relative) that is stable over more orders is a
    mathematical duplicate (typically a high-order pole that mixes a close pair), not a mode."""
    rep = np.array([shapes[c.representative] for c in clusters]).T
    mm = mac(rep, rep)
    size = np.array([c.members.size for c in clusters])
    spread = np.array([c.std_frequency_hz / c.frequency_hz if np.isfinite(c.std_frequency_hz)
                       else np.inf for c in clusters])
    f = np.array([c.frequency_hz for c in clusters])
    drop = set()
    for a in range(len(clusters)):
        for b in range(len(clusters)):
            if a == b or mm[a, b] <= crit.duplicate_mac:
                continue
            if abs(f[a] - f[b]) / max(f[a], f[b]) > crit.duplicate_freq:
                continue
            # a is dropped if b is the better-supported cluster
            if (size[b], -spread[b]) > (size[a], -spread[a]):
                drop.add(a)
    return [c for k, c in enumerate(clusters) if k not in drop]


def poles_from_eigs(mu: np.ndarray, fs_hz: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Discrete eigenvalues -> (continuous poles, frequency_hz, damping_ratio)."""
    lam = np.log(mu.astype(complex)) * fs_hz
    wn = np.abs(lam)
    return lam, wn / (2 * np.pi), -lam.real / np.where(wn > 0, wn, np.inf)


@dataclass(frozen=True)
class Spectrum:
    """Averaged singular-value spectrum for the stabilization diagram (first singular values
    of the cross-PSD matrix, units^2/Hz)."""
    frequency_hz: np.ndarray
    singular_values: np.ndarray       # (n_freq, k)

    def to_dict(self) -> dict:
        return {"frequency_hz": self.frequency_hz.tolist(),
                "singular_values": self.singular_values.tolist()}


#: segments x samples x channels transformed at once by sv_spectrum (its working arrays are a
#: few times this in float64 / complex: ~10 MB each, whatever the segment length or channels)
SPECTRUM_GROUP_VALUES = 1_000_000


def spectrum_group(nperseg: int, n_channels: int) -> int:
    """Segments per batch of :func:`sv_spectrum` (1..64)."""
    return max(1, min(64, SPECTRUM_GROUP_VALUES // max(nperseg * n_channels, 1)))


def sv_spectrum(data: np.ndarray, fs_hz: float, nperseg: int = 1024, n_sv: int = 3) -> Spectrum:
    """Welch cross-PSD matrix (Hann, 50 % overlap) and its first ``n_sv`` singular values."""
    x = np.asarray(data, dtype=float)
    x = x - x.mean(axis=0)
    n = x.shape[0]
    nperseg = int(min(nperseg, n))
    step = max(nperseg // 2, 1)
    starts = np.arange(0, n - nperseg + 1, step)
    win = np.hanning(nperseg)
    scale = 1.0 / (fs_hz * np.sum(win ** 2))
    l = x.shape[1]
    nf = nperseg // 2 + 1
    s = np.zeros((nf, l, l), dtype=complex)
    g = spectrum_group(nperseg, l)
    for i0 in range(0, starts.size, g):
        seg = np.stack([x[s0:s0 + nperseg] for s0 in starts[i0:i0 + g]]) * win[None, :, None]
        f = np.fft.rfft(seg, axis=1).transpose(1, 2, 0)          # (F, l, segs)
        s += np.matmul(f, f.conj().transpose(0, 2, 1))            # batched l x l per line
    s *= 2.0 * scale / max(starts.size, 1)
    sv = np.linalg.svd(s, compute_uv=False)[:, :n_sv]
    return Spectrum(frequency_hz=np.fft.rfftfreq(nperseg, 1.0 / fs_hz), singular_values=sv)
