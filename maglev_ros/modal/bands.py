"""SSI-cov settings chosen from the recording, and identification in several frequency bands
(no rclpy).

One SSI-cov run cannot serve modes from ~1 Hz to a few hundred Hz: its block rows must span
a period or two of the lowest mode at a rate high enough for the highest, i.e. thousands of
rows. :func:`plan_bands` therefore splits the searched range ``fmin_hz .. fmax_hz`` into
equal-ratio bands of at most a decade; each band is decimated to its own rate, gets block rows
covering ``PERIODS`` periods of its lowest frequency and an order range from its Hankel size.
Neighbouring bands overlap by ``MARGIN``; :func:`identify_bands` runs SSI-cov per band and
:func:`merge_band_results` keeps, of a mode found in two bands (frequency within
``DUPLICATE_FREQ``, MAC above ``DUPLICATE_MAC``), the estimate from the band where it lies
farthest from the band's edges.

Every rule is one line below; none is fitted to a data set.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from maglev_ros.errors import UserError
from maglev_ros.modal.ssi_cov import (
    ModalResult, SSICov, anti_alias_memory_lags, decimation_factor,
)
from maglev_ros.modal.stabilization import (
    PoleTable, StabilityCriteria, mac, mpc, mpd, real_mode_shape, sv_spectrum,
)

# lowest mode looked for by default: frames, towers and long spans start near 1 Hz (guideway
# spans at 10-50 Hz); a shorter record raises it (LAG_FRACTION)
FMIN_DEFAULT_HZ = 1.0
# highest mode looked for: below the corner of common acquisition anti-alias filters (0.4 fs)
FMAX_FRACTION = 0.4
# one band spans at most a decade: block rows stay ~2.5 x PERIODS x ratio (~50), Hankel small
MAX_BAND_RATIO = 10.0
# block rows cover this many periods of a band's lowest frequency (the lags must see it oscillate)
PERIODS = 2.0
# longest covariance lag at most 10 % of the record (Bendat & Piersol's rule for correlations)
LAG_FRACTION = 0.1
# interior band edges overlap by 15 %: a mode on an edge sits inside a neighbouring band
MARGIN = 1.15
# model orders up to half the Hankel rank bound (channels x block rows), capped: beyond it the
# extra states only fit noise and cost time
MAX_ORDER_CAP = 100
# blocks for the batch-means uncertainty of a stationary record (fewer if the record is short;
# below 3 the cluster spread is used)
N_BLOCKS = 10
# the same mode found in two bands: frequencies within 2 % and shapes alike
DUPLICATE_FREQ = 0.02
DUPLICATE_MAC = 0.8


@dataclass(frozen=True)
class Band:
    """One SSI-cov run: modes kept in ``search`` (core plus overlap), owned in ``core``."""
    core_hz: tuple[float, float]
    search_hz: tuple[float, float]
    fs_hz: float                        # identification rate after decimation
    decimation: int
    block_rows: int
    max_order: int
    n_blocks: int                       # 1: cluster-spread uncertainty

    def to_dict(self) -> dict:
        return {"core_hz": [float(x) for x in self.core_hz],
                "search_hz": [float(x) for x in self.search_hz],
                "fs_hz": float(self.fs_hz), "decimation": int(self.decimation),
                "block_rows": int(self.block_rows), "lag_s": self.block_rows / self.fs_hz,
                "orders": [2, int(self.max_order)], "n_blocks": int(self.n_blocks)}


@dataclass(frozen=True)
class BandPlan:
    """The settings of a multi-band identification and where each came from."""
    fmin_hz: float
    fmax_hz: float
    duration_s: float
    bands: tuple[Band, ...]
    sources: dict                       # setting -> "user" or the one-line rule that set it
    scale_channels: bool = False

    def to_dict(self) -> dict:
        return {"fmin_hz": float(self.fmin_hz), "fmax_hz": float(self.fmax_hz),
                "duration_s": float(self.duration_s), "scale_channels": self.scale_channels,
                "bands": [b.to_dict() for b in self.bands], "sources": dict(self.sources)}

    def describe(self) -> list[str]:
        """Plain lines for the terminal."""
        s = self.sources
        out = [f"searched {self.fmin_hz:.3g} .. {self.fmax_hz:.4g} Hz (fmin: {s['fmin_hz']}; "
               f"fmax: {s['fmax_hz']})"]
        for k, b in enumerate(self.bands):
            out.append(f"  band {k + 1}: {b.core_hz[0]:8.3g} .. {b.core_hz[1]:<8.4g} Hz at "
                       f"{b.fs_hz:7.4g} Hz (/{b.decimation}), block rows {b.block_rows} "
                       f"({b.block_rows / b.fs_hz:.3g} s), orders 2..{b.max_order}")
        out.append(f"  rules: bands {s['bands']}; block rows {s['block_rows']}; "
                   f"orders {s['max_order']}")
        how = "scaled to unit std before SSI" if self.scale_channels else "as recorded"
        out.append(f"  channels {how} ({s['scale_channels']})")
        return out


def _even(n: float) -> int:
    return max(2, 2 * int(n // 2))


def plan_bands(fs_hz: float, n_samples: int, n_channels: int, *, stationary: bool = True,
               fmin_hz: float | None = None, fmax_hz: float | None = None,
               block_rows: int | None = None, max_order: int | None = None,
               decimate_to_hz: float | None = None, scale_channels: bool = False,
               scale_source: str = "user") -> BandPlan:
    """Bands, rates, block rows and orders for a record of ``n_samples`` at ``fs_hz``.

    Given settings win; ``decimate_to_hz`` makes one band at that rate. ``stationary`` (ambient)
    records get block uncertainty, free decays the cluster spread.
    """
    fs = float(fs_hz)
    dur = n_samples / fs
    shift = anti_alias_memory_lags()
    src = {}
    if fmax_hz is None:
        fmax = FMAX_FRACTION * fs
        src["fmax_hz"] = f"{FMAX_FRACTION} x the sampling rate (acquisition anti-alias corner)"
    else:
        fmax = float(fmax_hz)
        src["fmax_hz"] = "user"
        if not 0 < fmax < 0.45 * fs:
            raise UserError(f"--fmax-hz: {fmax_hz} Hz must be above 0 and below 0.45 x the "
                            f"sampling rate {fs:g} Hz")
    # the longest lag, PERIODS / fmin x 2 (2i lags), must stay within LAG_FRACTION of the record
    fmin_record = 2.0 * PERIODS / (LAG_FRACTION * dur)
    if fmin_hz is None:
        fmin = max(FMIN_DEFAULT_HZ, fmin_record)
        src["fmin_hz"] = (f"lowest mode looked for, {FMIN_DEFAULT_HZ:g} Hz"
                          if fmin == FMIN_DEFAULT_HZ else
                          f"{2 * PERIODS / LAG_FRACTION:g} / {dur:.3g} s of data used "
                          f"(longest lag <= {LAG_FRACTION:g} x record)")
    else:
        fmin = float(fmin_hz)
        src["fmin_hz"] = "user"
        if fmin <= 0:
            raise UserError(f"--fmin-hz: expected a positive frequency, got {fmin_hz}")
    if fmin >= fmax:
        raise UserError(f"--fmin-hz: {fmin:.3g} Hz is not below fmax {fmax:.4g} Hz (record of "
                        f"{dur:.3g} s at {fs:g} Hz); expected a longer record or a lower --fmin-hz")
    if decimate_to_hz is not None:
        q = decimation_factor(fs, decimate_to_hz)
        if fmax >= 0.45 * fs / q:
            raise UserError(f"--decimate-to-hz: {decimate_to_hz} Hz gives {fs / q:g} Hz, too low "
                            f"for fmax {fmax:.4g} Hz (expected a rate above {fmax / 0.45:.4g} Hz)")
        edges = [fmin, fmax]
        src["bands"] = "user (--decimate-to-hz: one band)"
    else:
        n_bands = max(1, math.ceil(math.log(fmax / fmin) / math.log(MAX_BAND_RATIO) - 1e-9))
        ratio = (fmax / fmin) ** (1.0 / n_bands)
        edges = [fmin * ratio ** k for k in range(n_bands)] + [fmax]
        src["bands"] = (f"equal-ratio bands of at most {MAX_BAND_RATIO:g}x, overlapping "
                        f"{MARGIN - 1:.0%}, each decimated to >= fmax_band / {FMAX_FRACTION}")
    src["block_rows"] = ("user" if block_rows is not None else
                         f"{PERIODS:g} periods of the band's lowest frequency, longest lag "
                         f"<= {LAG_FRACTION:g} x record")
    src["scale_channels"] = scale_source
    src["max_order"] = ("user" if max_order is not None else
                        f"channels x block rows / 2, at most {MAX_ORDER_CAP}")
    bands = []
    for k in range(len(edges) - 1):
        lo, hi = edges[k], edges[k + 1]
        s_lo = lo / MARGIN if k > 0 else lo
        s_hi = hi * MARGIN if k < len(edges) - 2 else hi
        if decimate_to_hz is not None:
            q = decimation_factor(fs, decimate_to_hz)
        else:
            q = max(1, int(math.floor(FMAX_FRACTION * fs / s_hi + 1e-9)))
        fs_b = fs / q
        n_b = n_samples // q
        if block_rows is not None:
            i = int(block_rows)
        else:
            i = math.ceil(PERIODS * fs_b / s_lo)
            # the longest lag, 2i, stays within LAG_FRACTION of the data (fmin makes that so to
            # a sample or two; a band whose lowest frequency the user set gets fewer rows)
            i = max(4, min(i, int(LAG_FRACTION * n_b / 2)))
        need = 4 * i + shift
        nb = min(N_BLOCKS, n_b // need) if stationary else 1
        if nb < 3:
            nb = 1
        if n_b < need:
            raise UserError(f"data: {n_b} samples at {fs_b:g} Hz are too few for block rows {i} "
                            f"(need {need}); expected a longer record or a higher --fmin-hz")
        mo = (int(max_order) if max_order is not None
              else _even(min(n_channels * i / 2, MAX_ORDER_CAP)))
        if mo > n_channels * i:
            raise UserError(f"--max-order: {mo} exceeds channels x block rows = {n_channels * i}; "
                            f"expected a lower order or more block rows")
        bands.append(Band((lo, hi), (s_lo, s_hi), fs_b, q, i, mo, nb))
    return BandPlan(fmin, fmax, dur, tuple(bands), src, scale_channels)


@dataclass(frozen=True)
class BandResult:
    band: Band
    result: ModalResult


def identify_bands(data: np.ndarray, fs_hz: float, plan: BandPlan, channels=None,
                   criteria: StabilityCriteria | None = None,
                   nperseg: int | None = None) -> tuple[ModalResult, tuple[BandResult, ...]]:
    """SSI-cov in every band of ``plan`` on ``data`` (n_samples, n_channels) and the merged
    result. With ``plan.scale_channels`` each channel is divided by its std first (SSI then
    weighs channels alike whatever their units or gains); reported shapes are scaled back."""
    y = np.asarray(data, dtype=float)
    y = y - y.mean(axis=0)
    scale = np.ones(y.shape[1])
    if plan.scale_channels:
        sd = y.std(axis=0)
        if np.any(~(sd > 0)):
            bad = [str(c) for c, s in zip(channels or range(y.shape[1]), sd) if not s > 0]
            raise UserError(f"data: channel(s) {', '.join(bad)} are constant; expected signals")
        scale = sd
    yn = y / scale
    per_band = []
    for b in plan.bands:
        est = SSICov(block_rows=b.block_rows, orders=range(2, b.max_order + 1, 2),
                     decimate_to_hz=fs_hz / b.decimation, freq_range_hz=b.search_hz,
                     criteria=criteria, uncertainty="blocks" if b.n_blocks >= 3 else "cluster",
                     n_blocks=b.n_blocks, spectrum=False)
        per_band.append(BandResult(b, est.fit(yn, fs_hz, channels)))
    merged = merge_band_results(per_band)
    merged = _rescale_shapes(merged, scale)
    # spectrum at the recorded rate, fine enough to show the lowest band's peaks
    nps = nperseg or int(min(y.shape[0], 2 ** math.ceil(math.log2(8.0 * fs_hz / plan.fmin_hz))))
    merged = replace(merged, spectrum=sv_spectrum(y, fs_hz, nperseg=max(nps, 16)))
    return merged, tuple(per_band)


def _edge_distance(f_hz: float, core_hz) -> float:
    """log distance of f to the nearer core edge (negative outside the core)."""
    return min(math.log(f_hz / core_hz[0]), math.log(core_hz[1] / f_hz))


def merge_band_results(per_band) -> ModalResult:
    """One result from the bands' results: duplicates across bands are resolved in favour of
    the band where the mode lies farthest inside; the stabilization diagram shows each band's
    poles in its core range."""
    cands = []
    for kb, br in enumerate(per_band):
        res = br.result
        for km, m in enumerate(res.modes):
            cands.append((_edge_distance(m.frequency_hz, br.band.core_hz), kb, km))
    cands.sort(key=lambda c: -c[0])
    kept = []
    for edge, kb, km in cands:
        res = per_band[kb].result
        m, phi = res.modes[km], res.complex_shapes[km]
        dup = False
        for kb2, km2 in kept:
            r2 = per_band[kb2].result
            f2 = r2.modes[km2].frequency_hz
            # a mode in a band's overlap margin, inside the core of a band that found the same shape
            # within the margin's width: the copy a mode just beyond the first band's search edge leaves
            # there, off by the edge (23.5 Hz read 22.5 Hz with 2 channels); the owner's estimate stands
            copy = edge < 0 and kb2 != kb and _edge_distance(m.frequency_hz, per_band[kb2].band.core_hz) >= 0
            close = (abs(math.log(m.frequency_hz / f2)) < math.log(MARGIN) if copy
                     else abs(m.frequency_hz - f2) / f2 < DUPLICATE_FREQ)
            if close and mac(phi, r2.complex_shapes[km2]) > DUPLICATE_MAC:
                dup = True
                break
        if not dup:
            kept.append((kb, km))
    kept.sort(key=lambda k: per_band[k[0]].result.modes[k[1]].frequency_hz)
    modes, shapes = [], []
    new_label = {}
    for j, (kb, km) in enumerate(kept):
        res = per_band[kb].result
        modes.append(replace(res.modes[km], id=f"M{j + 1}"))
        shapes.append(res.complex_shapes[km])
        new_label[(kb, km)] = j
    tables = []
    for kb, br in enumerate(per_band):
        st = br.result.stabilization
        if st is None or len(st) == 0:
            continue
        lo, hi = br.band.core_hz
        sel = (st.frequency_hz >= lo) & (st.frequency_hz < hi)
        lab = np.array([new_label.get((kb, int(c)), -1) if c >= 0 else -1 for c in st.cluster[sel]],
                       dtype=int)
        tables.append(PoleTable(st.order[sel], st.frequency_hz[sel], st.damping_ratio[sel],
                                None if st.shapes is None else st.shapes[sel], st.mpc[sel],
                                st.stable[sel], lab))
    table = None
    if tables:
        table = PoleTable(*(np.concatenate([getattr(t, f) for t in tables])
                            for f in ("order", "frequency_hz", "damping_ratio", "shapes", "mpc",
                                      "stable", "cluster")))
    results = [br.result for br in per_band]
    methods = ", ".join(dict.fromkeys(r.method for r in results))        # bands' own, in order
    uncs = ", ".join(dict.fromkeys(r.uncertainty for r in results))
    top = max(results, key=lambda r: r.fs_hz)
    return ModalResult(tuple(modes), table, None, top.fs_hz, top.channels, methods, uncs,
                       tuple(shapes))


def _rescale_shapes(res: ModalResult, scale: np.ndarray) -> ModalResult:
    """Shapes identified on std-scaled channels back to recorded units (phi = C psi scales with
    each channel)."""
    if np.all(scale == 1.0):
        return res
    modes, shapes = [], []
    for m, phi in zip(res.modes, res.complex_shapes):
        phi = np.asarray(phi) * scale
        shape = real_mode_shape(phi)
        modes.append(replace(m, mode_shape={ch: float(x) for ch, x in zip(res.channels, shape)},
                             mpc=mpc(phi), mpd=mpd(phi)))
        shapes.append(phi)
    return replace(res, modes=tuple(modes), complex_shapes=tuple(shapes))
