"""An attachment on a girder span: a spring-mass resonator or a rigid point mass, and the modal
basis of the span with it attached (the physics only; finding one is :mod:`.resonator`)."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.linalg import eigh

from maglev_ros.twin.guideway import ModalBasis


@dataclass(frozen=True)
class Resonator:
    """A spring-mass attached to span ``span_index`` at ``x_rel_m`` from the span start; an infinite
    ``freq_hz`` is a rigidly attached point mass (no own mode, no own damping)."""
    span_index: int
    x_rel_m: float
    freq_hz: float
    mass_ratio: float
    damping_ratio: float = 0.03

    @property
    def rigid(self) -> bool:
        return not math.isfinite(self.freq_hz)

    def to_dict(self) -> dict:
        return {"span_index": int(self.span_index), "x_rel_m": float(self.x_rel_m),
                "freq_hz": None if self.rigid else float(self.freq_hz), "rigid": self.rigid,
                "mass_ratio": float(self.mass_ratio), "damping_ratio": None if self.rigid else float(self.damping_ratio)}


def attached_modal(base: ModalBasis, res: Resonator, mode_cutoff_hz: float,
                   min_modes_per_span: int) -> ModalBasis:
    """Modal basis ``base`` with ``res`` attached (beam part of the augmented modes); the span's
    modes are re-solved up to ``mode_cutoff_hz`` (at least ``min_modes_per_span``)."""
    freqs, zetas, owner, vecs = [], [], [], []
    for i, fe in enumerate(base.spans_fe):
        sel = base.span_index == i
        if i != res.span_index:
            freqs.append(base.freq_hz[sel]); zetas.append(base.damping_ratio[sel])
            owner.append(np.full(int(sel.sum()), i)); vecs.append(base.vectors[i])
            continue
        n = fe.mass.shape[0]
        ma = res.mass_ratio * fe.span.props.mass_per_length_kg_m * fe.span.length_m
        if res.rigid:
            # a rigid point mass: the span's own DOFs, mass matrix + ma t t^T (t: shape row at x)
            t = fe.shape_matrix([fe.span.start_m + res.x_rel_m])[0]
            w2, phi = eigh(fe.stiffness, fe.mass + ma * np.outer(t, t))
            k = int(sel.sum())
            wk = np.sqrt(np.clip(w2[:k], 1e-18, None))
            freqs.append(wk / (2 * math.pi)); zetas.append(fe.rayleigh_a / (2 * wk) + fe.rayleigh_b * wk / 2)
            owner.append(np.full(k, i)); vecs.append(phi[:, :k])
            continue
        ka = ma * (2 * math.pi * res.freq_hz) ** 2
        t = np.append(fe.shape_matrix([fe.span.start_m + res.x_rel_m])[0], -1.0)
        K = np.zeros((n + 1, n + 1)); M = np.zeros((n + 1, n + 1))
        K[:n, :n] = fe.stiffness; M[:n, :n] = fe.mass; M[n, n] = ma
        K += ka * np.outer(t, t)
        w2, phi = eigh(K, M)
        w = np.sqrt(np.clip(w2, 0.0, None))
        f = w / (2 * math.pi)
        k = min(w.size, max(int(np.sum(f <= mode_cutoff_hz)), int(sel.sum()) + 1, min_modes_per_span))
        wk = np.maximum(w[:k], 1e-9)
        z_beam = fe.rayleigh_a / (2 * wk) + fe.rayleigh_b * wk / 2
        share = np.clip(phi[n, :k] ** 2 * ma, 0.0, 1.0)      # attachment's share of modal kinetic energy
        freqs.append(f[:k]); zetas.append((1 - share) * z_beam + share * res.damping_ratio)
        owner.append(np.full(k, i)); vecs.append(phi[:n, :k])
    return ModalBasis(np.concatenate(freqs), np.concatenate(zetas), np.concatenate(owner), base.spans_fe,
                      tuple(vecs))
