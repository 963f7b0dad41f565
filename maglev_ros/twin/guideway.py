"""Guideway: Euler-Bernoulli FE beams over the spans of a line, elastic bearings, modal analysis.

Each span of ``line.spans`` is one girder, simply supported on a vertical elastic bearing of
stiffness ``kb`` at each end (kb = inf: rigid support, the vertical DOF is removed), free in
rotation at the ends. Spans do not share nodes (independent girders, as on the Shanghai line).
Elements are Hermite-cubic beams with consistent mass (vertical bending only; a 3D beam with
lateral bending and torsion is not implemented). Damping is Rayleigh, C = a M + b K, with
``damping_ratio`` on the first two modes of each span; in modal coordinates it is diagonal with
zeta_j = a / (2 w_j) + b w_j / 2.

Hand-written because the FE model is ~40 DOF per span: a full FE package (and its meshing) would
add far more than the 30 lines of element matrices used here; eigenproblems use scipy.linalg.eigh.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np
from scipy.linalg import eigh

from maglev_ros.errors import UserError
from maglev_ros.twin.design import SpanSpec


def hermite(xi: np.ndarray, le: float) -> np.ndarray:
    """Hermite cubic shape functions at local coordinate xi in [0, 1]: (..., 4) for DOFs
    (w_i, theta_i, w_j, theta_j); theta = dw/dx."""
    xi = np.asarray(xi, dtype=float)
    xi2, xi3 = xi * xi, xi * xi * xi
    return np.stack([1 - 3 * xi2 + 2 * xi3, le * (xi - 2 * xi2 + xi3), 3 * xi2 - 2 * xi3,
                     le * (-xi2 + xi3)], axis=-1)


def hermite_dx(xi: np.ndarray, le: float) -> np.ndarray:
    """d/dx of ``hermite`` (slopes): (..., 4)."""
    xi = np.asarray(xi, dtype=float)
    xi2 = xi * xi
    return np.stack([(-6 * xi + 6 * xi2) / le, 1 - 4 * xi + 3 * xi2, (6 * xi - 6 * xi2) / le,
                     -2 * xi + 3 * xi2], axis=-1)


def beam_element(ei_n_m2: float, m_kg_m: float, le: float) -> tuple[np.ndarray, np.ndarray]:
    """Element stiffness and consistent mass (4x4) of an Euler-Bernoulli beam element."""
    l2 = le * le
    k = ei_n_m2 / le ** 3 * np.array([[12, 6 * le, -12, 6 * le], [6 * le, 4 * l2, -6 * le, 2 * l2],
                                      [-12, -6 * le, 12, -6 * le], [6 * le, 2 * l2, -6 * le, 4 * l2]])
    m = m_kg_m * le / 420.0 * np.array([[156, 22 * le, 54, -13 * le], [22 * le, 4 * l2, 13 * le, -3 * l2],
                                        [54, 13 * le, 156, -22 * le], [-13 * le, -3 * l2, -22 * le, 4 * l2]])
    return k, m


@dataclass(frozen=True)
class SpanFE:
    """Assembled FE model of one span on its bearings (free DOFs only)."""
    span: SpanSpec
    n_elements: int
    mass: np.ndarray            # (n, n)
    stiffness: np.ndarray       # (n, n)
    free_dofs: np.ndarray       # indices into the full nodal DOF list (w0, th0, w1, th1, ...)
    rayleigh_a: float           # C = a M + b K
    rayleigh_b: float

    @property
    def element_length_m(self) -> float:
        return self.span.length_m / self.n_elements

    @property
    def damping(self) -> np.ndarray:
        return self.rayleigh_a * self.mass + self.rayleigh_b * self.stiffness

    def _interp(self, x_m: np.ndarray, deriv: bool) -> np.ndarray:
        """(len(x), n_free) matrix mapping free DOFs to w(x) (or dw/dx) for x inside the span."""
        x = np.atleast_1d(np.asarray(x_m, dtype=float)) - self.span.start_m
        le = self.element_length_m
        e = np.clip(np.floor(x / le).astype(int), 0, self.n_elements - 1)
        xi = x / le - e
        n = (hermite_dx if deriv else hermite)(xi, le)
        full = np.zeros((x.size, 2 * (self.n_elements + 1)))
        rows = np.arange(x.size)
        for a in range(4):
            full[rows, 2 * e + a] = n[:, a]
        inside = (x >= -1e-12) & (x <= self.span.length_m + 1e-12)
        full[~inside] = 0.0
        return full[:, self.free_dofs]

    def shape_matrix(self, x_m) -> np.ndarray:
        return self._interp(x_m, False)

    def slope_matrix(self, x_m) -> np.ndarray:
        return self._interp(x_m, True)

    def static_displacement(self, load_x_m: Sequence[float], load_n: Sequence[float], x_m) -> np.ndarray:
        """Static vertical displacement at ``x_m`` under point loads (positive up)."""
        f = self.shape_matrix(load_x_m).T @ np.asarray(load_n, dtype=float)
        u = np.linalg.solve(self.stiffness, f)
        return self.shape_matrix(x_m) @ u

    def eig(self) -> tuple[np.ndarray, np.ndarray]:
        """Circular frequencies (rad/s, ascending) and mass-normalised modes (free DOFs)."""
        w2, phi = eigh(self.stiffness, self.mass)
        w2 = np.clip(w2, 0.0, None)
        # sign: largest nodal displacement positive
        wd = phi[self._w_rows()]
        idx = np.argmax(np.abs(wd), axis=0)
        sgn = np.sign(wd[idx, np.arange(phi.shape[1])])
        sgn[sgn == 0] = 1.0
        return np.sqrt(w2), phi * sgn

    def _w_rows(self) -> np.ndarray:
        return np.flatnonzero(self.free_dofs % 2 == 0)


def assemble_span(span: SpanSpec, n_elements: int = 16,
                  kb_ends: tuple[float, float] | None = None, ei_factors=None) -> SpanFE:
    """FE model of one span on its two vertical bearings, with Rayleigh damping on modes 1-2.

    ``kb_ends`` (start, end) overrides the span's bearing stiffness per end (e.g. one degraded
    bearing); ``inf`` at an end is a rigid support there. ``ei_factors``: one factor on the bending
    stiffness per element, from the span's start (e.g. a damaged zone); the mass is unchanged.
    """
    if n_elements < 2:
        raise UserError(f"n_elements_per_span: expected >= 2, got {n_elements}")
    fac = np.ones(n_elements) if ei_factors is None else np.asarray(ei_factors, float)
    if fac.shape != (n_elements,) or not np.all(fac > 0):
        raise UserError(f"ei_factors: expected {n_elements} positive factors, got {np.shape(fac)}")
    p = span.props
    le = span.length_m / n_elements
    ke, me = beam_element(p.bending_stiffness_n_m2, p.mass_per_length_kg_m, le)
    ndof = 2 * (n_elements + 1)
    K = np.zeros((ndof, ndof))
    M = np.zeros((ndof, ndof))
    for e in range(n_elements):
        s = slice(2 * e, 2 * e + 4)
        K[s, s] += ke * fac[e]
        M[s, s] += me
    kb = p.bearing_stiffness_n_per_m
    removed = []
    for dof, k in zip((0, 2 * n_elements), kb_ends if kb_ends is not None else (kb, kb)):
        if math.isinf(k):
            removed.append(dof)
        else:
            K[dof, dof] += k
    free = np.array([i for i in range(ndof) if i not in removed])
    K = K[np.ix_(free, free)]
    M = M[np.ix_(free, free)]
    w2 = eigh(K, M, eigvals_only=True, subset_by_index=[0, 1])
    w1, w2_ = np.sqrt(np.clip(w2, 1e-12, None))
    z = p.damping_ratio
    a = 2 * z * w1 * w2_ / (w1 + w2_)
    b = 2 * z / (w1 + w2_)
    return SpanFE(span, n_elements, M, K, free, a, b)


def _inside(x: np.ndarray, sp: SpanSpec, last: bool) -> np.ndarray:
    """x on span ``sp``: half-open [start, end) so a point on a joint loads one span only."""
    return (x >= sp.start_m) & ((x < sp.end_m) | (last & (x <= sp.end_m)))


@dataclass(frozen=True)
class ModalBasis:
    """Truncated modal model of the whole line: each mode lives on one span (zero elsewhere).

    q_j'' + 2 zeta_j w_j q_j' + w_j^2 q_j = phi_j(x)^T f, w(x, t) = sum_j phi_j(x) q_j(t),
    with phi_j mass-normalised (generalised mass 1 kg).
    """
    freq_hz: np.ndarray            # (nm,)
    damping_ratio: np.ndarray      # (nm,)
    span_index: np.ndarray         # (nm,) span each mode belongs to
    spans_fe: tuple[SpanFE, ...]
    vectors: tuple[np.ndarray, ...]  # per span: (n_free, n_modes_of_span)

    @property
    def omega_rad_s(self) -> np.ndarray:
        return 2 * np.pi * self.freq_hz

    @property
    def n_modes(self) -> int:
        return int(self.freq_hz.size)

    def _table(self) -> tuple:
        """Per span: start, end, element count and length, the spans in order of their starts, each
        span's first mode column (cols, n_spans + 1), its modes' nodal values on its full nodal DOF
        list padded to the most modes of a span (T_pad, (n_spans, ndof, max modes)) and its mode
        count. A mode lives on one span, so no table spans all modes (it grew with the square of
        the line's length)."""
        tab = self.__dict__.get("_tab")
        if tab is None:
            n_el = max(fe.n_elements for fe in self.spans_fe)
            ndof = 2 * (n_el + 1)
            nmods = np.array([vec.shape[1] for vec in self.vectors], dtype=np.int64)
            T_pad = np.zeros((len(self.spans_fe), ndof, max(int(nmods.max(initial=0)), 1)))
            for k, (fe, vec) in enumerate(zip(self.spans_fe, self.vectors)):
                T_pad[k][fe.free_dofs, :vec.shape[1]] = vec
            starts = np.array([fe.span.start_m for fe in self.spans_fe])
            ends = np.array([fe.span.end_m for fe in self.spans_fe])
            nels = np.array([fe.n_elements for fe in self.spans_fe], dtype=np.int64)
            les = np.array([fe.element_length_m for fe in self.spans_fe])
            order = np.argsort(starts).astype(np.int64)
            cols = np.concatenate([[0], np.cumsum(nmods)]).astype(np.int64)
            tab = (starts, ends, nels, les, order, cols, T_pad, nmods)
            object.__setattr__(self, "_tab", tab)
        return tab

    def _locate(self, x: np.ndarray) -> tuple:
        """Per point: span index k, on-the-line flag, element index e, local coordinate xi, element
        length; and which spans hold a point."""
        starts, ends, nels, les, order = self._table()[:5]
        n = x.size
        k, e = np.empty(n, np.int64), np.empty(n, np.int64)
        valid = np.empty(n, np.bool_)
        xi, le = np.empty(n), np.empty(n)
        touched = np.zeros(len(self.spans_fe), np.bool_)
        _LOCATE(x, np.ascontiguousarray(starts[order]), order, starts, ends, les, nels, k, valid, e, xi, le,
                touched)
        return k, valid, e, xi, le, touched

    def span_of(self, x_m) -> np.ndarray:
        """Index (into ``spans_fe``) of the span each point loads, -1 off the line."""
        x = np.atleast_1d(np.asarray(x_m, dtype=float)).ravel()
        k, valid, *_ = self._locate(x)
        return np.where(valid, k, -1)

    def mode_columns(self, spans) -> np.ndarray:
        """Indices of the modes of ``spans`` (span indices, ascending): ascending mode indices."""
        cols = self._table()[5]
        return np.concatenate([np.arange(cols[s], cols[s + 1]) for s in spans] or [np.zeros(0, np.int64)])

    def _eval(self, x_m, derivs: tuple[bool, ...], spans=None, own: bool = False) -> list:
        """Shapes (False) and/or slopes (True) at x_m, one (len(x), n_columns) array each; ``own``:
        the columns of the spans the points lie on, those spans first in the list."""
        cols, T_pad, nmods = self._table()[5:]
        x = np.atleast_1d(np.asarray(x_m, dtype=float)).ravel()
        k, valid, e, xi, le, touched = self._locate(x)
        if own:
            spans = np.flatnonzero(touched)
        if spans is None:            # every mode of the line: columns as in the basis
            first, n_out = cols[:-1].astype(np.int64), self.n_modes
        else:                        # the modes of ``spans`` only, in that order (mode_columns)
            first = np.full(len(self.spans_fe), -1, np.int64)
            n_out = 0
            for s in spans:
                first[s] = n_out
                n_out += cols[s + 1] - cols[s]
            missing = np.flatnonzero(touched & (first < 0))
            if missing.size:
                raise ValueError(f"shapes: points lie on span {int(missing[0])}, which is not among {list(spans)}")
        outs = []
        for deriv in derivs:
            out = np.zeros((x.size, n_out))
            _HERMITE_ROWS(k, valid, e, xi, le, T_pad, nmods, first, bool(deriv), out)
            outs.append(out)
        return [spans] + outs if own else outs

    def shapes_at(self, x_m, spans=None) -> np.ndarray:
        """Mode shapes phi_j(x): (len(x), n_modes); zero off the spans. ``spans`` (ascending span
        indices covering every point on the line): only their modes' columns (``mode_columns``)."""
        return self._eval(x_m, (False,), spans)[0]

    def slopes_at(self, x_m, spans=None) -> np.ndarray:
        """d phi_j / dx at x: (len(x), n_modes) (``spans`` as for ``shapes_at``)."""
        return self._eval(x_m, (True,), spans)[0]

    def local_shapes_at(self, x_m) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(spans, shapes, slopes): the spans the points lie on (ascending) and ``shapes_at`` /
        ``slopes_at`` with those spans' columns only (``mode_columns(spans)``)."""
        spans, phi, dphi = self._eval(x_m, (False, True), own=True)
        return spans, phi, dphi


def _locate_points(x, starts_sorted, order, starts, ends, les, nels, k, valid, e, xi, le, touched):
    """``ModalBasis._locate`` point by point: the span of x is the last span (by start) with start
    <= x, half-open except the last span; element and local coordinate on it."""
    last_span = order[order.size - 1]
    for p in range(x.size):
        xp = x[p]
        pos = np.searchsorted(starts_sorted, xp, side="right") - 1
        s = order[max(pos, 0)]
        ok = pos >= 0 and (xp < ends[s] or (s == last_span and xp <= ends[s]))
        k[p] = s
        valid[p] = ok
        ln = les[s]
        xl = xp - starts[s]
        ep = min(max(int(np.floor(xl / ln)), 0), nels[s] - 1) if ok else 0
        e[p] = ep
        xi[p] = xl / ln - ep
        le[p] = ln
        if ok:
            touched[s] = True


def _hermite_rows(k, valid, e, xi, le, T_pad, nmods, first, deriv, out):
    """out[p, first[k] + j] = mode j of span k = k[p] at point p: the Hermite interpolation of its
    nodal values on element e[p] at local coordinate xi[p] (written by hand: a point only needs its
    own span's few modes; numpy's per-span gathers were most of the twin's shape evaluation)."""
    for p in range(k.size):
        if not valid[p]:
            continue
        s = k[p]
        c0 = first[s]
        x1 = xi[p]
        x2 = x1 * x1
        ln = le[p]
        if deriv:
            h0 = (-6 * x1 + 6 * x2) / ln
            h1 = 1 - 4 * x1 + 3 * x2
            h2 = (6 * x1 - 6 * x2) / ln
            h3 = -2 * x1 + 3 * x2
        else:
            x3 = x2 * x1
            h0 = 1 - 3 * x2 + 2 * x3
            h1 = ln * (x1 - 2 * x2 + x3)
            h2 = 3 * x2 - 2 * x3
            h3 = ln * (-x2 + x3)
        r = 2 * e[p]
        for j in range(nmods[s]):
            out[p, c0 + j] = h0 * T_pad[s, r, j] + h1 * T_pad[s, r + 1, j] + h2 * T_pad[s, r + 2, j] \
                + h3 * T_pad[s, r + 3, j]


try:  # optional accelerator (as in coupling: the same code runs as plain Python without numba)
    import numba as _numba
    _HERMITE_ROWS = _numba.njit(cache=True)(_hermite_rows)
    _LOCATE = _numba.njit(cache=True)(_locate_points)
except Exception:  # pragma: no cover
    _HERMITE_ROWS = _hermite_rows
    _LOCATE = _locate_points


class Guideway:
    """FE guideway over ``spans`` (from ``design.line_spans``)."""

    def __init__(self, spans: Sequence[SpanSpec], n_elements_per_span: int = 16):
        if not spans:
            raise UserError("line.spans: expected at least one span")
        self.spans = tuple(spans)
        self.n_elements_per_span = int(n_elements_per_span)
        self.spans_fe = tuple(assemble_span(s, self.n_elements_per_span) for s in self.spans)

    @property
    def start_m(self) -> float:
        return self.spans[0].start_m

    @property
    def end_m(self) -> float:
        return max(s.end_m for s in self.spans)

    def span_at(self, x_m: float) -> int | None:
        for i, s in enumerate(self.spans):
            if s.start_m <= x_m <= s.end_m:
                return i
        return None

    def frequencies_hz(self, span_index: int = 0, n_modes: int = 4) -> np.ndarray:
        w, _ = self.spans_fe[span_index].eig()
        return w[:n_modes] / (2 * np.pi)

    def modes(self, cutoff_hz: float = 300.0, min_modes_per_span: int = 2,
              max_modes_per_span: int | None = None) -> ModalBasis:
        """Modes of every span below ``cutoff_hz`` (at least ``min_modes_per_span``)."""
        freqs, zetas, owner, vecs = [], [], [], []
        for i, fe in enumerate(self.spans_fe):
            w, phi = fe.eig()
            f = w / (2 * np.pi)
            n = max(int(np.sum(f <= cutoff_hz)), min_modes_per_span)
            if max_modes_per_span is not None:
                n = min(n, max_modes_per_span)
            n = min(n, w.size)
            freqs.append(f[:n])
            zetas.append(fe.rayleigh_a / (2 * w[:n]) + fe.rayleigh_b * w[:n] / 2)
            owner.append(np.full(n, i))
            vecs.append(phi[:, :n])
        return ModalBasis(np.concatenate(freqs), np.concatenate(zetas), np.concatenate(owner),
                          self.spans_fe, tuple(vecs))

    def static_displacement(self, load_x_m: Sequence[float], load_n: Sequence[float], x_m) -> np.ndarray:
        """Static displacement (positive up) at ``x_m`` under vertical point loads (positive up)."""
        lx = np.atleast_1d(np.asarray(load_x_m, dtype=float))
        lp = np.atleast_1d(np.asarray(load_n, dtype=float))
        x = np.atleast_1d(np.asarray(x_m, dtype=float))
        out = np.zeros(x.size)
        for fe in self.spans_fe:
            sp = fe.span
            last = fe is self.spans_fe[-1]
            sel = _inside(lx, sp, last)
            xs = _inside(x, sp, last)
            if sel.any() and xs.any():
                out[xs] += fe.static_displacement(lx[sel], lp[sel], x[xs])
        return out
