"""Sensor health: the one check every recording passes before any verb analyses it.

What it finds (each an :class:`~maglev_ros.contract.Issue`):

- units: values go to SI by the contract's unit table (``contract.to_si_units``, the same function
  the nodes use per block); a converted channel is a warning, an unknown unit or one of the wrong
  kind for the topic an error naming topic, channel and unit;
- ``rate_mismatch``: the header stamps advance at a rate other than the stated ``sample_rate_hz``;
- ``flat``: a channel (near-)constant over the recording or a long stretch;
- ``clipped``: a channel held at its extreme value for runs of samples;
- ``implausible``: values outside what the quantity can physically be (:data:`BOUNDS`), or a gap
  whose level is far from the magnet's nominal gap;
- ``time_offset``: a topic whose stamps do not overlap the other topics';
- ``sensor_map``: metadata that names no sensors, or not a channel the data carry.

:func:`check_topics` runs it on the topics a verb reads (``BagReader.read_checked``): it converts
units, excludes a bad channel where the analysis stays right without it (:func:`exclusion`) and
raises one :class:`~maglev_ros.errors.UserError` line where the result would be wrong. It returns
a :class:`HealthReport` that the verbs print on stderr and store in their JSON. ``BagReader.check``
(``maglev-ros info``) runs the same scans while streaming, as warnings (rate and time offset as
errors). Every bound below comes from physics or the sensor kind, never from a data set.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Iterable, Mapping

import numpy as np

from maglev_ros.contract import (TOPIC_BODY_ACCEL, TOPIC_GUIDEWAY_ACCEL, TOPIC_GUIDEWAY_DISP,
                                 TOPIC_VEHICLE_ACCEL, TOPIC_VEHICLE_GAP, TOPIC_VEHICLE_POSITION,
                                 Issue, Metadata, UnitConversion, to_si_units)
from maglev_ros.errors import ContractError, UserError

__all__ = ["Bound", "BOUNDS", "FLAT_PP", "HealthReport", "ExcludedChannel", "TopicScan",
           "quantity_of", "stamp_rate_hz", "rate_issue", "time_offset_issues", "sensor_map_issues",
           "exclusion", "check_topics", "check_feeds", "ArrayFeed", "channel_data_to_si", "block_to_si",
           "report_lines"]

_QUANTITY = {TOPIC_GUIDEWAY_ACCEL: "acceleration", TOPIC_VEHICLE_ACCEL: "acceleration",
             TOPIC_BODY_ACCEL: "acceleration", TOPIC_GUIDEWAY_DISP: "displacement",
             TOPIC_VEHICLE_GAP: "gap"}
_POSITION_QUANTITY = {"position_m": "position", "speed_mps": "speed"}
_SI = {"acceleration": "m/s^2", "displacement": "m", "gap": "m", "position": "m", "speed": "m/s"}


@dataclass(frozen=True)
class Bound:
    """Values a quantity can physically take: [lo, hi] (lo itself excluded when ``open_lo``)."""

    lo: float
    hi: float
    reason: str
    open_lo: bool = False


BOUNDS: dict[str, Bound] = {
    "acceleration": Bound(-1e4, 1e4, "+-1000 g is beyond the range of any vibration accelerometer "
                          "of the contract's kind (guideway, magnet, car body)"),
    "gap": Bound(0.0, 0.1, "a magnet levitates about 0.01 m below its rail: <= 0 is through the rail, "
                 "> 0.1 m beyond the magnet's reach and any gap sensor's range", open_lo=True),
    "displacement": Bound(-0.1, 0.1, "a girder deflects millimetres under a vehicle (span/4000 is 6 mm "
                          "at 25 m); 0.1 m is beyond any elastic girder"),
    "position": Bound(-1e7, 1e7, "10 000 km is longer than any line"),
    "speed": Bound(-250.0, 250.0, "250 m/s is faster than any maglev has run (record 168 m/s)"),
}
#: peak-to-peak over a window below which a channel carries not even its sensor's noise
FLAT_PP: dict[str, tuple[float, str]] = {
    "acceleration": (1e-6, "below the self-noise of any accelerometer (seismic ones ~1e-6 m/s^2 rms)"),
    "gap": (1e-8, "100x below the resolution of a levitation gap sensor (~1e-6 m)"),
    "displacement": (1e-9, "below the resolution of any girder displacement sensor (>= 1e-8 m)"),
}
#: float32 carries ~7 digits: a variation below 1e-6 of the level is not recorded at all
FLAT_RELATIVE = 1e-6
FLAT_WINDOW_S = 0.25
#: a flat stretch shorter than this share of the record (and than 1 s) barely moves a spectrum or fit
FLAT_MIN_FRACTION = 0.10
FLAT_MIN_S = 1.0
#: the control holds a levitating magnet near its nominal gap: beyond x5 or /5 is a scale error
GAP_LEVEL_FACTOR = 5.0
#: the contract's nominal gap when the metadata gives none
NOMINAL_GAP_M = 0.010
#: DAQ clocks agree with their stated rate to ppm; 1 % plus one sample of stamp jitter per window
RATE_TOLERANCE = 0.01
RATE_WINDOW_SAMPLES = 200
MIN_RATE_WINDOWS = 5         # windows the median is taken over, at least (a gap spoils the windows it falls in)


def quantity_of(topic: str, channel: str) -> str | None:
    if topic == TOPIC_VEHICLE_POSITION:
        return _POSITION_QUANTITY.get(channel)
    return _QUANTITY.get(topic)


# ------------------------------------------------------------------------------- units
def channel_data_to_si(cd, where: str = ""):
    """(ChannelData in SI, conversions made); ContractError for an unknown or wrong-kind unit."""
    si, factors, conv = to_si_units(cd.topic, cd.channels, cd.units, where)
    if not conv:
        return cd, conv
    return dataclasses.replace(cd, units=si, data=cd.data * np.asarray(factors)), conv


def block_to_si(topic: str, block, where: str = ""):
    """(Block in SI, conversions made): what a node does with each block it receives."""
    si, factors, conv = to_si_units(topic, block.channels, block.units, where)
    if not conv:
        return block, conv
    data = (block.data * np.asarray(factors, dtype=np.float64)).astype(np.float32)
    return dataclasses.replace(block, units=si, data=data), conv


# ------------------------------------------------------------------------ stated rate
def _window_blocks(n_blocks: int, counts) -> int:
    """Blocks per rate window: RATE_WINDOW_SAMPLES samples, but at least MIN_RATE_WINDOWS windows
    (on a short recording a window over every block holds any gap it has: median of one)."""
    k = max(1, math.ceil(RATE_WINDOW_SAMPLES / max(float(np.median(counts)), 1.0)))
    return max(1, min(k, (n_blocks - 1) // MIN_RATE_WINDOWS, n_blocks - 1))


def stamp_rate_hz(stamps_ns, counts) -> float | None:
    """The rate the header stamps advance at [Hz]: median over windows of consecutive blocks with
    >= RATE_WINDOW_SAMPLES samples (robust to a dropped, doubled or shifted block)."""
    st = np.asarray(stamps_ns, dtype=np.int64)
    n = np.asarray(counts, dtype=np.int64)
    order = np.argsort(st, kind="stable")
    st, n = st[order], n[order]
    keep = np.concatenate([[True], np.diff(st) > 0])
    st, n = st[keep], n[keep]
    if st.size < 2:
        return None
    k = _window_blocks(st.size, n)
    csum = np.concatenate([[0], np.cumsum(n)])
    samples = csum[k:st.size] - csum[:st.size - k]
    dt_s = (st[k:] - st[:-k]) * 1e-9
    return float(np.median(samples / dt_s))


def rate_issue(topic: str, rates_hz, stamps_ns, counts) -> Issue | None:
    """An error when the stamps advance at a rate other than the stated ``sample_rate_hz``
    (per block; each stretch of blocks with one stated rate is checked on its own)."""
    rt = np.asarray(rates_hz, dtype=np.float64)
    st = np.asarray(stamps_ns, dtype=np.int64)
    n = np.asarray(counts, dtype=np.int64)
    order = np.argsort(st, kind="stable")
    rt, st, n = rt[order], st[order], n[order]
    edges = np.flatnonzero(np.diff(rt) != 0) + 1
    for a, b in zip(np.concatenate([[0], edges]), np.concatenate([edges, [rt.size]])):
        stated = float(rt[a])
        got = stamp_rate_hz(st[a:b], n[a:b])
        if got is None or not stated > 0:
            continue
        per_window = _window_blocks(b - a, n[a:b]) * float(np.median(n[a:b]))
        if abs(got / stated - 1.0) > RATE_TOLERANCE + 1.0 / per_window:
            return Issue("error", topic, None, float(st[a]) * 1e-9, "rate_mismatch",
                         f"header stamps advance at {got:.6g} Hz but sample_rate_hz says "
                         f"{stated:.6g} Hz")
    return None


# ------------------------------------------------------------------------ channel scan
class TopicScan:
    """Flat, clipped and implausible channels of one topic, fed block by block (bounded memory)
    or with the whole array at once; values must already be SI."""

    def __init__(self, topic: str, channels, rate_hz: float, nominal_gap_m: float | None = None):
        self.topic = topic
        self.channels = tuple(channels)
        self.rate_hz = float(rate_hz)
        self.quantities = [quantity_of(topic, c) for c in self.channels]
        c = len(self.channels)
        self.window = max(8, int(round(FLAT_WINDOW_S * self.rate_hz)))
        self.g0 = float(nominal_gap_m) if nominal_gap_m else NOMINAL_GAP_M
        self.n = 0
        b = [BOUNDS.get(q) for q in self.quantities]
        self._lo = np.array([x.lo if x else -np.inf for x in b])
        self._hi = np.array([x.hi if x else np.inf for x in b])
        self._open = np.array([bool(x and x.open_lo) for x in b])
        self.n_out = np.zeros(c, dtype=np.int64)
        self.worst = np.zeros(c)
        # sensors (not position/speed, which may be constant) are scanned for flat and clipped
        self._sensor = np.array([q in FLAT_PP for q in self.quantities])
        self._floor = np.array([FLAT_PP[q][0] if q in FLAT_PP else 0.0 for q in self.quantities])
        self._wmin = np.full(c, np.inf)
        self._wmax = np.full(c, -np.inf)
        self._wsum = np.zeros(c)
        self._wn = 0
        self._flat: list[np.ndarray] = []
        self._mean: list[np.ndarray] = []
        self._lsb = np.full(c, np.inf)
        # per sign (+1 max, -1 min): extreme value, samples in runs (>= 2) at it, runs, steepest edge
        self._ext = {s: [np.full(c, -np.inf), np.zeros(c, np.int64), np.zeros(c, np.int64),
                         np.zeros(c)] for s in (1, -1)}

    def add(self, data: np.ndarray) -> None:
        x = np.asarray(data, dtype=np.float64)
        if x.ndim != 2 or x.size == 0 or not np.isfinite(x).all():
            return                    # NaN/inf blocks are the contract check's, not ours
        self.n += x.shape[0]
        out = (x > self._hi) | (x < self._lo) | (self._open & (x <= self._lo))
        cnt = out.sum(axis=0)
        if cnt.any():
            self.n_out += cnt
            self.worst = np.maximum(self.worst, np.where(out, np.abs(x), 0.0).max(axis=0))
        self._windows(x)
        if x.shape[0] > 1:
            d = np.abs(np.diff(x, axis=0))
            d[d == 0] = np.inf
            self._lsb = np.minimum(self._lsb, d.min(axis=0))
        for s in (1, -1):
            self._extreme(s * x, s)

    def _windows(self, x: np.ndarray) -> None:
        W, i, n = self.window, 0, x.shape[0]
        if self._wn:
            k = min(W - self._wn, n)
            self._accumulate(x[:k])
            i = k
            if self._wn == W:
                self._close()
        full = (n - i) // W
        if full:
            blk = x[i:i + full * W].reshape(full, W, -1)
            mn, mx, mean = blk.min(axis=1), blk.max(axis=1), blk.mean(axis=1)
            self._flat.extend(self._is_flat(mn, mx, mean))
            self._mean.extend(mean)
            i += full * W
        if i < n:
            self._accumulate(x[i:])

    def _accumulate(self, x: np.ndarray) -> None:
        self._wmin = np.minimum(self._wmin, x.min(axis=0))
        self._wmax = np.maximum(self._wmax, x.max(axis=0))
        self._wsum += x.sum(axis=0)
        self._wn += x.shape[0]

    def _close(self) -> None:
        mean = self._wsum / self._wn
        self._flat.extend(self._is_flat(self._wmin[None], self._wmax[None], mean[None]))
        self._mean.append(mean)
        self._wmin[:] = np.inf
        self._wmax[:] = -np.inf
        self._wsum[:] = 0.0
        self._wn = 0

    def _is_flat(self, mn, mx, mean):
        floor = np.maximum(self._floor, FLAT_RELATIVE * np.abs(mean))
        return list(((mx - mn) <= floor) & self._sensor)

    def _extreme(self, x: np.ndarray, s: int) -> None:
        val, n_run, runs, edge = self._ext[s]
        bmax = x.max(axis=0)
        for j in np.flatnonzero(self._sensor & (bmax >= val)):
            v = bmax[j]
            if v > val[j]:
                val[j], n_run[j], runs[j], edge[j] = v, 0, 0, 0.0
            at = np.concatenate([[False], x[:, j] == v, [False]])
            dd = np.diff(at.astype(np.int8))
            starts, stops = np.flatnonzero(dd == 1), np.flatnonzero(dd == -1)
            long = stops - starts >= 2
            if not long.any():
                continue
            starts, stops = starts[long], stops[long]
            n_run[j] += int((stops - starts).sum())
            runs[j] += starts.size
            steps = [v - x[a - 1, j] for a in starts if a > 0]
            steps += [v - x[b, j] for b in stops if b < x.shape[0]]
            if steps:
                edge[j] = max(edge[j], max(steps))

    def issues(self) -> list[Issue]:
        """Warnings per channel (kinds ``flat``, ``clipped``, ``implausible``), one per channel."""
        if self._wn >= self.window // 2 or (self._wn and not self._flat):
            self._close()
        out = []
        total_s = self.n / self.rate_hz if self.rate_hz > 0 else 0.0
        flat = np.array(self._flat).reshape(-1, len(self.channels)) if self._flat else None
        means = np.array(self._mean).reshape(-1, len(self.channels)) if self._mean else None
        for j, ch in enumerate(self.channels):
            q = self.quantities[j]
            unit = _SI.get(q, "")
            if self.n_out[j]:
                b = BOUNDS[q]
                out.append(Issue("warning", self.topic, ch, None, "implausible",
                                 f"implausible: {self.n_out[j]} of {self.n} samples outside "
                                 f"{'(' if b.open_lo else '['}{b.lo:g}, {b.hi:g}] {unit}, largest "
                                 f"|value| {self.worst[j]:.3g} {unit} ({b.reason})"))
                continue
            if q == "gap" and means is not None:
                level = float(np.median(means[:, j]))
                if not self.g0 / GAP_LEVEL_FACTOR <= level <= self.g0 * GAP_LEVEL_FACTOR:
                    out.append(Issue("warning", self.topic, ch, None, "implausible",
                                     f"implausible: median gap {level:.3g} m is not within a factor "
                                     f"{GAP_LEVEL_FACTOR:g} of the nominal gap {self.g0:g} m (the control "
                                     "holds a levitating magnet near it: a scale or unit error)"))
                    continue
            if flat is not None and self._sensor[j]:
                run = _longest_run(flat[:, j])
                run_s = run * self.window / self.rate_hz
                if run and run_s >= min(total_s, max(FLAT_MIN_S, FLAT_MIN_FRACTION * total_s)) - 1e-9:
                    floor = self._floor[j]
                    out.append(Issue("warning", self.topic, ch, None, "flat",
                                     f"flat-lined: peak-to-peak below {floor:g} {unit} (or 1e-6 of its "
                                     f"level) over {min(run_s, total_s):.3g} s of {total_s:.3g} s "
                                     f"({FLAT_PP[q][1]})"))
                    continue
            for s in (1, -1):
                val, n_run, runs, edge = (self._ext[s][k][j] for k in range(4))
                if not self._sensor[j] or n_run < 3:
                    continue
                # a quantised or float32-rounded peak is reached by one step; a clipped signal
                # arrives at the limit with its own slope
                step = max(2.0 * self._lsb[j] if np.isfinite(self._lsb[j]) else 0.0,
                           8.0 * float(np.spacing(np.float32(abs(val)))))
                if edge > step:
                    out.append(Issue("warning", self.topic, ch, None, "clipped",
                                     f"clipped: {int(n_run)} samples held at the extreme "
                                     f"{s * val:.6g} {unit} in {int(runs)} run(s) (a sensor or "
                                     "converter at its range limit)"))
                    break
        return out


def _longest_run(mask: np.ndarray) -> int:
    m = np.concatenate([[False], np.asarray(mask, bool), [False]])
    d = np.diff(m.astype(np.int8))
    lens = np.flatnonzero(d == -1) - np.flatnonzero(d == 1)
    return int(lens.max()) if lens.size else 0


# ------------------------------------------------------------------------ across topics
def time_offset_issues(intervals: Mapping[str, tuple[float, float]], severity: str = "error") -> list[Issue]:
    """Topics whose [first, last] stamp interval overlaps none of the other topics'."""
    out = []
    if len(intervals) < 2:
        return out
    for t, (a, b) in intervals.items():
        others = [iv for u, iv in intervals.items() if u != t]
        if any(a < y and x < b for x, y in others):
            continue
        ref = float(np.median([x for x, _ in others]))
        lo, hi = min(x for x, _ in others), max(y for _, y in others)
        out.append(Issue(severity, t, None, a, "time_offset",
                         f"stamps {a:.6f}..{b:.6f} s do not overlap the other topics' "
                         f"({lo:.6f}..{hi:.6f} s): offset {a - ref:+.6g} s"))
    return out


def sensor_map_issues(md: Metadata | None, topic: str, channels: Iterable[str],
                      severity: str = "error") -> list[Issue]:
    """Channels the metadata does not place: no sensors at all, no entry, entry on another topic,
    a vehicle accel/gap sensor without its magnet."""
    if topic == TOPIC_VEHICLE_POSITION:
        return []
    channels = list(channels)
    sensors = md.sensors if md is not None else {}
    if not sensors:
        return [Issue(severity, topic, None, None, "sensor_map",
                      f"metadata key sensors: names no sensors, so channels {', '.join(channels)} "
                      "cannot be placed (by position or magnet) other than by guessing their order")]
    out = []
    for ch in channels:
        s = sensors.get(ch)
        if s is None:
            out.append(Issue(severity, topic, ch, None, "sensor_map",
                             f"metadata key sensors.{ch}: missing; the channel recorded on {topic} has "
                             "no sensor entry to place it"))
        elif s.topic != topic:
            out.append(Issue(severity, topic, ch, None, "sensor_map",
                             f"metadata key sensors.{ch}.topic: {s.topic!r}, but the channel is "
                             f"recorded on {topic}"))
        elif topic in (TOPIC_VEHICLE_ACCEL, TOPIC_VEHICLE_GAP) and s.magnet is None:
            out.append(Issue(severity, topic, ch, None, "sensor_map",
                             f"metadata key sensors.{ch}.magnet: missing; the vehicle channel cannot "
                             "be given to a magnet"))
    return out


# -------------------------------------------------------------------------- exclusion
def exclusion(topic: str, channel: str, md: Metadata | None, healthy: Iterable[str]) -> str | None:
    """None when ``channel`` may be left out of the analysis and the result stays right, else why not.

    Guideway accelerometers: while another healthy one is left (modes, shapes and fits use the
    others). Guideway displacement and car-body accelerations: always (both topics are optional).
    Magnet accelerations and gaps: only when the magnet has another healthy sensor of that kind.
    The vehicle position: never.
    """
    healthy = [h for h in healthy if h != channel]
    if topic in (TOPIC_GUIDEWAY_DISP, TOPIC_BODY_ACCEL):
        return None
    if topic == TOPIC_GUIDEWAY_ACCEL:
        return None if healthy else f"no healthy channel would be left on {topic}"
    if topic in (TOPIC_VEHICLE_ACCEL, TOPIC_VEHICLE_GAP):
        sensors = md.sensors if md is not None else {}
        s = sensors.get(channel)
        what = "acceleration" if topic == TOPIC_VEHICLE_ACCEL else "gap"
        if s is None or s.magnet is None:
            return f"the metadata gives channel {channel} no magnet"
        if any(sensors.get(h) is not None and sensors[h].magnet == s.magnet for h in healthy):
            return None
        return f"it is the only {what} sensor of magnet {s.magnet}"
    return "the vehicle position cannot be left out"


# --------------------------------------------------------------------------- the report
@dataclass(frozen=True)
class ExcludedChannel:
    topic: str
    channel: str
    kind: str
    reason: str

    def to_dict(self) -> dict:
        return {"topic": self.topic, "channel": self.channel, "kind": self.kind, "reason": self.reason}


@dataclass(frozen=True)
class HealthReport:
    """What the health check of one recording found and did (JSON: :meth:`to_dict`)."""

    source: str
    warnings: tuple[Issue, ...] = ()
    converted: tuple[UnitConversion, ...] = ()
    excluded: tuple[ExcludedChannel, ...] = ()

    @property
    def excluded_channels(self) -> list[str]:
        return [e.channel for e in self.excluded]

    def to_dict(self) -> dict:
        return {"bag": self.source, "excluded_channels": [e.to_dict() for e in self.excluded],
                "converted_units": [c.to_dict() for c in self.converted],
                "warnings": [w.to_dict() for w in self.warnings]}

    def lines(self) -> list[str]:
        """One stderr line per finding."""
        return report_lines(self.to_dict())


def report_lines(report: Mapping) -> list[str]:
    """The stderr lines of a :meth:`HealthReport.to_dict` document (what a verb prints)."""
    out = []
    for w in report.get("warnings", ()):
        where = (w.get("topic") or "") + (f" [{w['channel']}]" if w.get("channel") else "")
        out.append(f"warning: {report.get('bag')}: {where}: {w['message']}")
    return out


class ArrayFeed:
    """A topic read whole, as :func:`check_topics` is given it: (ChannelData as read, per block
    stamp [ns], sample count and stated rate)."""

    def __init__(self, cd, stamps, counts, rates):
        self.cd, self.stamps, self.counts, self.rates = cd, stamps, counts, rates
        self.channels, self.units = cd.channels, cd.units
        self.sample_rate_hz = cd.sample_rate_hz

    @property
    def empty(self) -> bool:
        return self.cd.n_samples == 0

    def scan(self, scan: "TopicScan", factors, converted: bool) -> tuple[float, float]:
        """Feed ``scan`` the SI values; the topic's (first, end) time."""
        cd = self.cd
        self.si_data = cd.data * np.asarray(factors) if converted else cd.data
        scan.add(self.si_data)
        return float(cd.time_s[0]), float(cd.time_s[-1]) + 1.0 / cd.sample_rate_hz

    def result(self, si_units, factors, converted: bool, keep):
        """The topic in SI without the excluded channels (``keep``: column indices or None)."""
        cd = self.cd
        if converted:
            cd = dataclasses.replace(cd, units=tuple(si_units), data=self.si_data)
        if keep is not None:
            cd = dataclasses.replace(cd, channels=tuple(cd.channels[j] for j in keep),
                                     units=tuple(cd.units[j] for j in keep), data=cd.data[:, keep])
        return cd


def check_topics(source: str, md: Metadata | None, topics: Mapping[str, tuple],
                 sensor_map: bool = False,
                 other_intervals: Mapping[str, tuple[float, float]] | None = None) -> tuple[dict, HealthReport]:
    """The health check of the topics a verb reads.

    ``topics``: {topic: (ChannelData as read, per block: stamp [ns], sample count, stated rate)}. Returns
    ({topic: ChannelData in SI without excluded channels}, HealthReport). Raises one UserError
    line (the first error; how many more) where the result would be wrong. Topics read together
    that do not overlap in time are an error; ``other_intervals`` ({topic: (start_s, end_s)} of
    topics the verb does not read) only give warnings, as the verb does not combine them.
    """
    return check_feeds(source, md, {t: ArrayFeed(*v) for t, v in topics.items()}, sensor_map,
                       other_intervals)


def check_feeds(source: str, md: Metadata | None, feeds: Mapping, sensor_map: bool = False,
                other_intervals: Mapping[str, tuple[float, float]] | None = None) -> tuple[dict, HealthReport]:
    """:func:`check_topics` on feeds: objects with ``channels``, ``units``, ``sample_rate_hz``,
    ``stamps``/``counts``/``rates`` (per block), ``empty``, ``scan(TopicScan, factors,
    converted) -> (first, end time)`` and ``result(si_units, factors, converted, keep)``, what the
    verb gets for the topic (:class:`ArrayFeed`: the whole topic; ``maglev_ros.bag_windows``: a
    topic left in the bag and read window by window)."""
    where = f"{source}: "
    errors: list[str] = []
    warnings: list[Issue] = []
    conversions: list[UnitConversion] = []
    excluded: list[ExcludedChannel] = []
    out: dict = {}
    intervals = {}
    g0 = md.nominal_gap_m if md is not None else None
    for topic, feed in feeds.items():
        if feed.empty:
            out[topic] = feed.result(feed.units, None, False, None)
            continue
        bad = rate_issue(topic, feed.rates, feed.stamps, feed.counts)
        if bad is not None:
            errors.append(f"{topic}: {bad.message}")
            continue
        try:
            si, factors, conv = to_si_units(topic, feed.channels, feed.units, where)
        except ContractError as exc:
            errors.append(str(exc)[len(where):])
            continue
        for c in conv:
            conversions.append(c)
            warnings.append(Issue("warning", topic, c.channel, None, "unit_converted",
                                  f"unit {c.unit!r} converted to {c.si_unit!r} (x{c.factor:.9g})"))
        channels = tuple(feed.channels)
        if sensor_map:
            errors += [f"{i.topic}: {i.message}" for i in sensor_map_issues(md, topic, channels)]
        scan = TopicScan(topic, channels, feed.sample_rate_hz, g0)
        span = feed.scan(scan, factors, bool(conv))
        found = {i.channel: i for i in scan.issues()}
        conv_of = {c.channel: c for c in conv}
        healthy = [c for c in channels if c not in found]
        drop = []
        for ch, issue in found.items():
            msg = issue.message
            if ch in conv_of:
                msg += f" (after converting {conv_of[ch].unit!r} to {conv_of[ch].si_unit!r})"
            why_not = exclusion(topic, ch, md, healthy)
            if why_not is None:
                drop.append(ch)
                excluded.append(ExcludedChannel(topic, ch, issue.kind, msg))
                warnings.append(dataclasses.replace(issue, message=msg + "; excluded from the analysis"))
            else:
                errors.append(f"{topic} [{ch}]: {msg}; cannot be left out: {why_not}")
        keep = [j for j, c in enumerate(channels) if c not in drop] if drop else None
        out[topic] = feed.result(si, factors, bool(conv), keep)
        intervals[topic] = span
    offset = time_offset_issues(intervals)
    errors += [f"{i.topic}: {i.message}" for i in offset]
    if other_intervals and intervals:
        # the verb's own topics are the reference: name the unread ones that lie elsewhere
        warnings += [i for i in time_offset_issues({**other_intervals, **intervals}, "warning")
                     if i.topic in other_intervals]
    if errors:
        more = f" (and {len(errors) - 1} more problem(s); `maglev-ros info` lists the recording's)" \
            if len(errors) > 1 else ""
        raise UserError(f"{where}{errors[0]}{more}")
    return out, HealthReport(source, tuple(warnings), tuple(conversions), tuple(excluded))
