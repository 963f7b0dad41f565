"""Multi-band SSI-cov of a record read chunk by chunk: :func:`identify_bands` without holding
the record (no rclpy).

:func:`maglev_ros.modal.bands.identify_bands` holds the record, its demeaned and scaled copies,
each band's decimated copy and, for the Whittle polish, the full-length FFT of every mode's
filtered signal: about ten times the record in float64, growing with its length.
Covariance-driven SSI needs none of that, only the output covariances, which are sums over
the record. :func:`identify_bands_chunked` makes a few passes over a re-iterable source of
chunks (:class:`ArrayChunks`, :class:`TopicChunks`) and keeps per band only what the sums need:

1. the channel means (and stds when channels are scaled), summed row by row in record order
   like numpy's column reductions, so they are the same floats;
2. each band decimated by a streamed ``resample_poly`` (:class:`Decimator`: the same FIR on the
   same samples, same floats) and its mean;
3. the block covariances by the segment FFTs of :func:`~maglev_ros.modal.ssi_cov.output_covariances`,
   segment for segment, and the singular-value spectrum by the segment groups of
   :func:`~maglev_ros.modal.stabilization.sv_spectrum`;
4. SSI-cov from the covariances (:meth:`SSICov.fit_covariances`, unchanged);
5. for the Whittle polish, each mode's periodogram over its band only: the DFT of the modal
   filter output at those bins, summed over pieces by Bluestein chirp-z transforms
   (:class:`BandDFT`).

Steps 1-4 give the same floats as the whole-record path; step 5 sums the same DFT in another
order, so polished frequencies agree to ~1e-15 and damping to ~1e-12 (measured on the sample
and partner ambient recordings; tests/test_faults_memory.py states the tolerance). Memory: one chunk, a
decimator and covariance buffer per band (segment + lags), the spectrum's group of segments,
and, for the polish, the complex DFT over each mode's band (16 bytes per bin; the band is
+-20 half-power half-widths at the record's resolution, so it grows with the record: about
10 MB for 30 min of the paper's guideway modes).
"""
from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import scipy.fft as sfft
from scipy.signal import resample_poly

from maglev_ros.errors import UserError
from maglev_ros.modal.bands import BandPlan, BandResult, _rescale_shapes, merge_band_results
from maglev_ros.modal.polish import WhittlePolish
from maglev_ros.modal.ssi_cov import ModalResult, SSICov, blas_threads, decimation_factor
from maglev_ros.modal.stabilization import Spectrum, StabilityCriteria, spectrum_group

#: samples x channels per chunk of an in-memory array source (4 MB of float64)
CHUNK_VALUES = 500_000
#: the polish's chirp-z transforms run over pieces of at most this many samples
DFT_PIECE = 65536


# --------------------------------------------------------------------------------- sources
class ArrayChunks:
    """An (n, l) array served in chunks of rows (re-iterable): the in-memory source."""

    def __init__(self, data: np.ndarray, chunk_samples: int | None = None):
        self.data = np.asarray(data)
        if self.data.ndim != 2:
            raise UserError(f"data: expected a 2-D array (n_samples, n_channels), got shape "
                            f"{self.data.shape}")
        self.n_samples, self.n_channels = self.data.shape
        self.chunk_samples = int(chunk_samples or max(1, CHUNK_VALUES // max(self.n_channels, 1)))

    def __iter__(self):
        for i in range(0, self.n_samples, self.chunk_samples):
            yield np.asarray(self.data[i:i + self.chunk_samples], dtype=float)


class TopicChunks:
    """Samples ``start_index .. stop_index - 1`` of a bag topic (``src``: a
    :class:`~maglev_ros.bag_windows.CheckedTopic` or ``TopicSpan`` with ``n_samples``) as float64
    chunks, read window by window (:mod:`maglev_ros.bag_windows`); re-iterable while ``reader``
    is open. The chunks concatenated are the whole read's ``data[start:stop]``."""

    def __init__(self, reader, src, start_index: int = 0, stop_index: int | None = None,
                 window_s: float | None = None):
        self.reader, self.src = reader, src
        self.start = int(start_index)
        self.stop = int(src.n_samples if stop_index is None else stop_index)
        self.n_samples = self.stop - self.start
        self.n_channels = len(src.channels)
        self.window_s = window_s

    def __iter__(self):
        from maglev_ros.bag_windows import iter_windows
        pos = 0
        for w in iter_windows(self.reader, self.src, self.window_s):
            n = w.data.shape[0]
            lo, hi = max(self.start - pos, 0), min(self.stop - pos, n)
            pos += n
            if hi > lo:
                yield w.data[lo:hi]
            if pos >= self.stop:
                return


# ------------------------------------------------------------------------ streamed pieces
class ColumnSum:
    """Column sums of rows pushed in record order, added one row at a time like numpy's
    ``sum(axis=0)`` of a C-ordered array, hence the same floats."""

    def __init__(self, n_channels: int):
        self.total = np.zeros(n_channels)
        self.n = 0

    def push(self, x: np.ndarray) -> None:
        if x.shape[0]:
            self.total = np.add.reduce(np.concatenate([self.total[None], x]), axis=0)
            self.n += x.shape[0]

    def mean(self) -> np.ndarray:
        return self.total / self.n


class Decimator:
    """``scipy.signal.resample_poly(x, 1, q, axis=0)`` of a stream of ``n_in`` rows: output k is
    the centred FIR over rows ``kq - 10q .. kq + 10q`` (zeros outside the record); each output is
    computed by resample_poly on a piece holding all of its taps, so it is the same float."""

    def __init__(self, q: int, n_in: int):
        self.q, self.n_in = int(q), int(n_in)
        self.n_out = -(-self.n_in // self.q)
        self.half = 10 * self.q                 # resample_poly's half filter length for 1/q
        self.buf = None
        self.b0 = 0                             # record row of buf[0]
        self.seen = 0
        self.k_next = 0

    def push(self, x: np.ndarray) -> np.ndarray:
        if self.q == 1:
            return x
        self.buf = x if self.buf is None else np.concatenate([self.buf, x])
        self.seen += x.shape[0]
        q, half = self.q, self.half
        if self.seen >= self.n_in:
            k_hi = self.n_out
        else:
            k_hi = max(0, (self.seen - 1 - half) // q + 1)   # outputs whose taps are all here
        if k_hi <= self.k_next:
            return self.buf[:0]
        lo = max(0, self.k_next * q - half)
        hi = min(self.seen, (k_hi - 1) * q + half + 1)
        y = resample_poly(self.buf[lo - self.b0:hi - self.b0], 1, q, axis=0)
        out = y[self.k_next - lo // q:k_hi - lo // q]
        self.k_next = k_hi
        keep = max(0, self.k_next * q - half)
        self.buf = self.buf[keep - self.b0:]
        self.b0 = keep
        return out


class Covariances:
    """:func:`~maglev_ros.modal.ssi_cov.output_covariances` of a stream of ``n`` rows: the same
    blocks, segments and FFT sums, fed in record order; ``result()`` when all rows are in."""

    def __init__(self, n: int, max_lag: int, refs: np.ndarray, n_blocks: int = 1,
                 seg_len: int = 2048):
        self.n, self.max_lag, self.refs = int(n), int(max_lag), np.asarray(refs)
        self.edges = np.linspace(0, n, n_blocks + 1).astype(int)
        self.seg = int(max(min(seg_len, n), 1))
        self.nfft = sfft.next_fast_len(self.seg + max_lag, real=True)
        self.jobs = []                          # (block, c0, c1, last segment of the block)
        for b in range(n_blocks):
            s0, s1 = self.edges[b], self.edges[b + 1]
            m = s1 - s0 - max_lag
            if m <= 0:
                raise UserError(f"data: block of {s1 - s0} samples is shorter than {max_lag} lags; "
                                f"expected a longer record or fewer block_rows/n_blocks")
            starts = list(range(s0, s0 + m, self.seg))
            for j, c0 in enumerate(starts):
                self.jobs.append((b, c0, min(c0 + self.seg, s0 + m), j == len(starts) - 1))
        self.out = None
        self.acc = None
        self.buf = None
        self.b0 = 0
        self.next_job = 0

    def push(self, y: np.ndarray) -> None:
        if self.out is None:
            l = y.shape[1]
            self.out = np.empty((len(self.edges) - 1, self.max_lag + 1, l, self.refs.size))
        self.buf = y if self.buf is None else np.concatenate([self.buf, y])
        have = self.b0 + self.buf.shape[0]
        lag, nfft = self.max_lag, self.nfft
        while self.next_job < len(self.jobs):
            b, c0, c1, last = self.jobs[self.next_job]
            if c1 + lag > have:
                break
            if self.acc is None:
                self.acc = np.zeros((nfft // 2 + 1, self.buf.shape[1], self.refs.size), dtype=complex)
            late = sfft.rfft(self.buf[c0 - self.b0:c1 + lag - self.b0], n=nfft, axis=0)
            early = sfft.rfft(self.buf[c0 - self.b0:c1 - self.b0][:, self.refs], n=nfft, axis=0)
            self.acc += late[:, :, None] * early.conj()[:, None, :]
            if last:
                m = self.edges[b + 1] - self.edges[b] - lag
                self.out[b] = sfft.irfft(self.acc, n=nfft, axis=0)[:lag + 1] / m
                self.acc = None
            self.next_job += 1
        keep = self.jobs[self.next_job][1] if self.next_job < len(self.jobs) else have
        self.buf = self.buf[keep - self.b0:]
        self.b0 = keep

    def result(self) -> np.ndarray:
        if self.next_job < len(self.jobs):
            raise RuntimeError(f"covariances: {self.n} rows expected, stream ended early")
        return self.out


class SpectrumSum:
    """:func:`~maglev_ros.modal.stabilization.sv_spectrum` of a stream of ``n`` rows, minus
    their mean ``mean``: the same Hann segments, in the same groups."""

    def __init__(self, n: int, fs_hz: float, nperseg: int, mean: np.ndarray, n_sv: int = 3):
        self.n, self.fs, self.mean, self.n_sv = int(n), float(fs_hz), np.asarray(mean), n_sv
        self.nperseg = int(min(nperseg, n))
        step = max(self.nperseg // 2, 1)
        self.starts = np.arange(0, self.n - self.nperseg + 1, step)
        self.win = np.hanning(self.nperseg)
        self.s = None
        self.buf = None
        self.b0 = 0
        self.next_group = 0

    def push(self, y: np.ndarray) -> None:
        x = y - self.mean
        if self.s is None:
            l = y.shape[1]
            self.s = np.zeros((self.nperseg // 2 + 1, l, l), dtype=complex)
        self.buf = x if self.buf is None else np.concatenate([self.buf, x])
        have = self.b0 + self.buf.shape[0]
        G, L = spectrum_group(self.nperseg, self.buf.shape[1]), self.nperseg
        while self.next_group < self.starts.size:
            grp = self.starts[self.next_group:self.next_group + G]
            if grp[-1] + L > have:
                break
            seg = np.stack([self.buf[s0 - self.b0:s0 - self.b0 + L] for s0 in grp]) \
                * self.win[None, :, None]
            f = np.fft.rfft(seg, axis=1).transpose(1, 2, 0)
            self.s += np.matmul(f, f.conj().transpose(0, 2, 1))
            self.next_group += G
        keep = int(self.starts[self.next_group]) if self.next_group < self.starts.size else have
        self.buf = self.buf[keep - self.b0:]
        self.b0 = keep

    def result(self) -> Spectrum:
        scale = 1.0 / (self.fs * np.sum(self.win ** 2))
        s = self.s * (2.0 * scale / max(self.starts.size, 1))
        sv = np.linalg.svd(s, compute_uv=False)[:, :self.n_sv]
        return Spectrum(frequency_hz=np.fft.rfftfreq(self.nperseg, 1.0 / self.fs),
                        singular_values=sv)


class BandDFT:
    """The DFT of an ``n``-row stream filtered by ``weights`` (l, m) at each column's band of
    rfft bins (:class:`~maglev_ros.modal.polish.PolishBand`): per piece of rows and run of bins,
    Bluestein's chirp-z (the band's bins as a convolution, by FFT) with every phase taken modulo
    the record length in integers, turned by the piece's offset and summed."""

    def __init__(self, n: int, bands):
        self.n = int(n)
        self.bands = [b for b in bands if b is not None]
        self.index = [k for k, b in enumerate(bands) if b is not None]
        self.weights = (np.column_stack([b.weights for b in self.bands]) if self.bands
                        else np.zeros((0, 0)))
        self.sums = [np.zeros(b.bin_hi - b.bin_lo, dtype=complex) for b in self.bands]
        self.piece = L = min(DFT_PIECE, self.n)
        self.buf = None
        self.b0 = 0
        # the chirp convolution kernel, shared by every piece and run of L bins
        self.nfft = sfft.next_fast_len(2 * L - 1)
        kern = np.zeros(self.nfft, dtype=complex)
        kern[:2 * L - 1] = np.conj(self._chirp(np.arange(-(L - 1), L, dtype=np.int64)))
        self.kernel = sfft.fft(kern)
        self.pre = self._chirp(np.arange(L, dtype=np.int64))

    def _chirp(self, m: np.ndarray) -> np.ndarray:
        """exp(-i pi m^2 / n), the phase reduced modulo 2n in integers."""
        return np.exp(-1j * np.pi * ((m * m) % (2 * self.n)) / self.n)

    def _turn(self, k: np.ndarray, u) -> np.ndarray:
        """exp(-2 pi i k u / n), the phase reduced modulo n in integers."""
        return np.exp(-2j * np.pi * ((k * u) % self.n) / self.n)

    def push(self, y: np.ndarray, final: bool = False) -> None:
        if not self.bands:
            return
        q = y @ self.weights
        self.buf = q if self.buf is None else np.concatenate([self.buf, q])
        L = self.piece
        while self.buf.shape[0] >= L or (final and self.buf.shape[0]):
            self._add(self.buf[:L], self.b0)
            self.buf = self.buf[L:]
            self.b0 += L

    def _add(self, q: np.ndarray, offset: int) -> None:
        L = self.piece
        if q.shape[0] < L:                          # zeros add nothing to a DFT
            q = np.concatenate([q, np.zeros((L - q.shape[0], q.shape[1]))])
        u = np.arange(L, dtype=np.int64)
        for j, b in enumerate(self.bands):
            for k0 in range(b.bin_lo, b.bin_hi, L):
                # X(k0 + d) = c(d) sum_u [q_u e^(-2 pi i k0 u / n) c(u)] conj(c(d - u)),
                # c(m) = e^(-i pi m^2 / n): e^(-2 pi i d u / n) = c(d) c(u) conj(c(d - u))
                a = sfft.fft(q[:, j] * self._turn(np.int64(k0), u) * self.pre, self.nfft)
                conv = sfft.ifft(a * self.kernel)[L - 1:2 * L - 1]
                m = min(L, b.bin_hi - k0)
                k = np.arange(k0, k0 + m, dtype=np.int64)
                part = self.pre[:m] * conv[:m]
                self.sums[j][k0 - b.bin_lo:k0 - b.bin_lo + m] += self._turn(k, offset) * part

    def periodograms(self, m: int) -> list:
        out = [None] * m
        for k, s in zip(self.index, self.sums):
            out[k] = np.abs(s) ** 2 / self.n
        return out


# ---------------------------------------------------------------------------- the pipeline
def _band_estimator(b, fs_hz: float, criteria) -> SSICov:
    """The estimator identify_bands runs in band ``b``."""
    return SSICov(block_rows=b.block_rows, orders=range(2, b.max_order + 1, 2),
                  decimate_to_hz=fs_hz / b.decimation, freq_range_hz=b.search_hz,
                  criteria=criteria, uncertainty="blocks" if b.n_blocks >= 3 else "cluster",
                  n_blocks=b.n_blocks, spectrum=False)


def _check_finite(x: np.ndarray) -> None:
    if not np.all(np.isfinite(x)):
        raise UserError("data: expected finite samples, found NaN or inf")


def identify_bands_chunked(source, fs_hz: float, plan: BandPlan, channels=None,
                           criteria: StabilityCriteria | None = None,
                           nperseg: int | None = None) -> tuple[ModalResult, tuple[BandResult, ...]]:
    """:func:`~maglev_ros.modal.bands.identify_bands` on a re-iterable ``source`` of (m, l)
    chunks with ``source.n_samples`` rows in all (see the module docstring)."""
    n, l = int(source.n_samples), int(source.n_channels)
    channels = tuple(str(c) for c in (channels or [f"ch{k}" for k in range(l)]))
    if len(channels) != l:
        raise UserError(f"channels: expected {l} names, got {len(channels)}")
    fs_hz = float(fs_hz)
    # pass 1: channel means (and the stds of the demeaned channels when they are scaled)
    total = ColumnSum(l)
    for x in source:
        _check_finite(x)
        total.push(x)
    mu = total.mean()
    scale = np.ones(l)
    if plan.scale_channels:
        s1 = ColumnSum(l)
        for x in source:
            s1.push(x - mu)
        mu_y = s1.mean()
        s2 = ColumnSum(l)
        for x in source:
            d = (x - mu) - mu_y
            s2.push(d * d)
        sd = np.sqrt(s2.mean())
        if np.any(~(sd > 0)):
            bad = [c for c, s in zip(channels, sd) if not s > 0]
            raise UserError(f"data: channel(s) {', '.join(bad)} are constant; expected signals")
        scale = sd
    ests = [_band_estimator(b, fs_hz, criteria) for b in plan.bands]
    qs = [decimation_factor(fs_hz, e.decimate_to_hz) for e in ests]
    n_dec = [-(-n // q) for q in qs]
    for e, nd in zip(ests, n_dec):
        nb = e.n_blocks if e.uncertainty == "blocks" else 1
        need = (4 * e.block_rows + e.lag_shift) * max(nb, 1)
        if nd < need:
            raise UserError(f"data: {nd} samples after decimation, expected at least {need}"
                            f" for block_rows={e.block_rows}")

    def bands_stream():
        """(full-rate demeaned chunk, [each band's decimated chunk]) in record order."""
        decs = [Decimator(q, n) for q in qs]
        for x in source:
            y = x - mu
            yn = y / scale
            yield y, [d.push(yn) for d in decs]

    # pass 2: each band's mean after decimation (SSICov demeans what it identifies from)
    sums = [ColumnSum(l) for _ in ests]
    s_y = ColumnSum(l)
    for y, parts in bands_stream():
        s_y.push(y)
        for s, p in zip(sums, parts):
            s.push(p)
    means = [s.mean() for s in sums]
    # pass 3: block covariances per band and the spectrum at the recorded rate
    nps = nperseg or int(min(n, 2 ** math.ceil(math.log2(8.0 * fs_hz / plan.fmin_hz))))
    spec = SpectrumSum(n, fs_hz, max(nps, 16), s_y.mean())
    covs = []
    for e, nd in zip(ests, n_dec):
        nb = e.n_blocks if e.uncertainty == "blocks" else 1
        covs.append(Covariances(nd, e.max_lag, e._ref_indices(channels), n_blocks=max(nb, 1)))
    for y, parts in bands_stream():
        spec.push(y)
        for c, p, mb in zip(covs, parts, means):
            if p.shape[0]:
                c.push(p - mb)
    results = []
    for e, c, q in zip(ests, covs, qs):
        bc = c.result()
        nb = bc.shape[0]
        res, _ = e.fit_covariances(bc.mean(axis=0), fs_hz / q, channels,
                                   block_covs=bc if nb > 1 else None, spectrum=None)
        results.append(res)
    # pass 4 (stationary bands with modes): the Whittle polish from each mode's band DFT
    todo = [k for k, (e, r) in enumerate(zip(ests, results))
            if e.polish == "whittle" and r.uncertainty == "blocks" and r.modes]
    if todo:
        pol = WhittlePolish()
        plans = {}
        for k in todo:
            r = results[k]
            with blas_threads(ests[k].blas_threads):
                plans[k] = pol.bands(n_dec[k], fs_hz / qs[k], [m.frequency_hz for m in r.modes],
                                     [m.damping_ratio for m in r.modes], np.array(r.complex_shapes))
        dfts = {k: BandDFT(n_dec[k], plans[k]) for k in todo}
        for _, parts in bands_stream():
            for k in todo:
                if parts[k].shape[0]:
                    dfts[k].push(parts[k] - means[k])
        for k in todo:
            dfts[k].push(np.zeros((0, l)), final=True)
            r = results[k]
            with blas_threads(ests[k].blas_threads):
                pp = pol.fit_periodograms(plans[k], dfts[k].periodograms(len(r.modes)), n_dec[k],
                                          fs_hz / qs[k], [m.frequency_hz for m in r.modes],
                                          [m.damping_ratio for m in r.modes],
                                          [m.std_frequency_hz for m in r.modes])
            results[k] = SSICov.apply_polish(r, pp)
    per_band = tuple(BandResult(b, r) for b, r in zip(plan.bands, results))
    merged = merge_band_results(per_band)
    merged = _rescale_shapes(merged, scale)
    return replace(merged, spectrum=spec.result()), per_band
