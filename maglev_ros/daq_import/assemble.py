"""Contract topics from the columns an import spec names, written to a contract bag.

Each channel goes to the topic its metadata sensor names, converted to SI at the edge with the
contract's unit table (:func:`maglev_ros.contract.to_si_units`; every conversion is stated).
A topic's channels share one rate and one time grid: channels that differ are refused with a
line naming them, unless the spec asks to ``resample`` (linear interpolation onto the fastest
channel's grid, where every channel has data). Position and speed are completed from each
other when only one is given (numpy.gradient / trapezoidal integration; stated). Everything
is read and checked before the bag is opened; BagWriter writes it to a temporary directory
renamed at the end, so a failure leaves no bag (and an earlier one at the path as it was).
"""
from __future__ import annotations

import copy
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from maglev_ros.contract import (TOPIC_GUIDEWAY_ACCEL, TOPIC_GUIDEWAY_DISP, TOPIC_VEHICLE_POSITION,
                                 ContractError, to_si_units, unit_conversion)
from maglev_ros.daq_import.readers import Column, read_columns
from maglev_ros.daq_import.spec import ImportSpec
from maglev_ros.daq_import.timing import Gap, Segment, Timeline, same_grid
from maglev_ros.errors import UserError

__all__ = ["TopicResult", "ImportResult", "import_to_bag", "build_topics"]

_POS, _SPEED = "position_m", "speed_mps"


@dataclass(frozen=True)
class TopicResult:
    topic: str
    channels: tuple[str, ...]
    units: tuple[str, ...]
    rate_hz: float
    rate_from: str
    n_samples: int
    blocks: int
    start_s: float
    duration_s: float
    gaps: tuple[Gap, ...] = ()
    resampled: tuple[str, ...] = ()

    def to_dict(self) -> dict:
        return {"topic": self.topic, "channels": list(self.channels), "units": list(self.units),
                "rate_hz": self.rate_hz, "rate_from": self.rate_from, "n_samples": self.n_samples,
                "blocks": self.blocks, "start_s": self.start_s, "duration_s": self.duration_s,
                "gaps": [g.to_dict() for g in self.gaps], "resampled": list(self.resampled)}


@dataclass(frozen=True)
class ImportResult:
    """What ``maglev-ros import`` did: the bag, its topics, every unit conversion and derivation."""

    out: str
    spec: str
    metadata: str
    sources: tuple[dict, ...]
    topics: tuple[TopicResult, ...]
    conversions: tuple[dict, ...]
    derived: tuple[dict, ...] = ()
    notes: tuple[str, ...] = ()

    def to_dict(self) -> dict:
        return {"schema": "maglev-import/1", "out": self.out, "spec": self.spec,
                "metadata": self.metadata, "sources": list(self.sources),
                "topics": [t.to_dict() for t in self.topics],
                "conversions": list(self.conversions), "derived": list(self.derived),
                "notes": list(self.notes)}

    def lines(self) -> list[str]:
        out = [f"bag:       {self.out}", f"metadata:  {self.metadata}"]
        for s in self.sources:
            out.append(f"source:    {s['file']} ({s['format']})")
        for t in self.topics:
            out.append(f"topic:     {t.topic}  {t.rate_hz:g} Hz (from {t.rate_from})  "
                       f"{t.n_samples} samples  {t.blocks} blocks  {t.duration_s:.6g} s  "
                       f"[{', '.join(t.channels)}]")
            for g in t.gaps:
                out.append(f"  gap:     {g.gap_s:.6g} s (~{g.missing} samples missing) before "
                           f"{g.where}; kept as a gap in the bag")
            if t.resampled:
                out.append(f"  resampled onto the {t.rate_hz:g} Hz grid (linear): {', '.join(t.resampled)}")
        for c in self.conversions:
            out.append(f"unit:      {c['channel']} ({c['column']}): {c['unit']} -> {c['si_unit']}, "
                       f"x {c['factor']:.9g} (unit from {c['unit_from']})")
        for d in self.derived:
            out.append(f"derived:   {d['channel']}: {d['how']}")
        for n in self.notes:
            out.append(f"note:      {n}")
        return out


def _where(spec: ImportSpec, cid: str) -> str:
    return f"{spec.origin}: key channels.{cid}"


def _si(spec: ImportSpec, cid: str, topic: str, unit: str) -> tuple[str, float]:
    """(SI unit, factor) by the contract's unit table; one line naming the spec key otherwise."""
    try:
        si, factor, _ = to_si_units(topic, [cid], [unit])
    except ContractError as exc:
        raise UserError(f"{_where(spec, cid)}.unit: {exc}") from None
    return si[0], factor[0]


def _unit(spec: ImportSpec, cs, col: Column, topic: str) -> tuple[str, str]:
    """(unit, where it came from) of a channel: the spec's, else the file's; both must agree."""
    if cs.unit is not None:
        _si(spec, cs.id, topic, cs.unit)        # the wrong kind for the topic is named first
        if col.file_unit is not None and cs.unit != col.file_unit:
            a, b = unit_conversion(cs.unit), unit_conversion(col.file_unit)
            if a is not None and b is not None and a != b:
                raise UserError(f"{_where(spec, cs.id)}.unit: {cs.unit!r} but {col.where} states "
                                f"{col.file_unit!r}; make them agree (or drop unit: to use the file's)")
        return cs.unit, "spec"
    if col.file_unit is None:
        raise UserError(f"{_where(spec, cs.id)}.unit: missing and {col.where} states no unit "
                        "(give unit: e.g. g, mm, m/s^2)")
    return col.file_unit, "file"


def _subset(tl: Timeline, keep: np.ndarray, label) -> tuple[Timeline, np.ndarray]:
    """The samples of ``tl`` where ``keep``: a time base with stretches split where dropped."""
    idx = np.flatnonzero(keep)
    if idx.size < 2:
        raise UserError("no common time span")
    grid = tl.times_ns()
    seg_of = np.empty(tl.n, dtype=np.int64)
    for k, s in enumerate(tl.segments):
        seg_of[s.start:s.stop] = k
    brk = np.flatnonzero((np.diff(idx) != 1) | (np.diff(seg_of[idx]) != 0)) + 1
    bounds = np.concatenate([[0], brk, [idx.size]])
    segs, gaps = [], []
    for a, b in zip(bounds[:-1], bounds[1:]):
        segs.append(Segment(int(a), int(b), int(grid[idx[a]])))
        if a > 0:
            g = (grid[idx[a]] - grid[idx[a - 1]]) * 1e-9
            gaps.append(Gap(int(a), label(int(idx[a])), float(g), max(1, int(round(g * tl.rate_hz)) - 1)))
    return Timeline(tl.rate_hz, int(idx.size), tuple(segs), tuple(gaps), tl.origin), idx


def _resample_topic(topic: str, ids: list, cols: dict, values: dict) -> tuple[Timeline, dict, tuple]:
    """Every channel linearly interpolated onto the fastest one's grid, kept where all have data."""
    ref_id = max(ids, key=lambda c: cols[c].timeline.rate_hz)
    ref = cols[ref_id].timeline
    grid = ref.times_ns()
    base = int(grid[0])
    tg = (grid - base) * 1e-9
    keep = np.ones(ref.n, dtype=bool)
    for c in ids:
        tl = cols[c].timeline
        cover = np.zeros(ref.n, dtype=bool)
        for s in tl.segments:
            t_first = (s.t0_ns - base) * 1e-9
            t_last = t_first + (s.n - 1) / tl.rate_hz
            cover |= (tg >= t_first - 1e-9) & (tg <= t_last + 1e-9)
        keep &= cover
    if keep.sum() < 2:
        raise UserError(f"{topic}: channels {', '.join(ids)} have no common time span to resample onto")
    new_tl, idx = _subset(ref, keep, cols[ref_id].label)
    out, changed = {}, []
    for c in ids:
        if c == ref_id or same_grid(cols[c].timeline, ref):
            out[c] = values[c][idx]
            continue
        tl = cols[c].timeline
        src_t = (tl.times_ns() - base) * 1e-9
        v = np.empty(idx.size)
        for s in tl.segments:        # interpolate inside each stretch only, never across a gap
            sel = (tg[idx] >= src_t[s.start] - 1e-9) & (tg[idx] <= src_t[s.stop - 1] + 1e-9)
            v[sel] = np.interp(tg[idx][sel], src_t[s.start:s.stop], values[c][s.start:s.stop])
        out[c] = v
        changed.append(c)
    return new_tl, out, tuple(changed)


def _derive_position(spec: ImportSpec, tl: Timeline, have: dict) -> tuple[dict, list]:
    """Complete position_m / speed_mps from the one given (per stretch; across a gap the
    position advances by the mean of the speeds at its ends times its length)."""
    from scipy.integrate import cumulative_trapezoid

    derived = []
    if _POS in have and _SPEED not in have:
        pos = have[_POS]
        v = np.empty_like(pos)
        for s in tl.segments:
            if s.n < 2:
                raise UserError(f"{_where(spec, _POS)}: a stretch of {s.n} sample(s) between gaps; "
                                "speed cannot be differentiated from it")
            v[s.start:s.stop] = np.gradient(pos[s.start:s.stop], 1.0 / tl.rate_hz)
        have[_SPEED] = v
        derived.append({"channel": _SPEED, "how": "differentiated from position_m "
                        "(numpy.gradient: central differences, one-sided at the ends of each stretch)"})
    elif _SPEED in have and _POS not in have:
        if spec.position_start_m is None:
            raise UserError(f"{spec.origin}: key position_start_m: missing; needed to integrate "
                            "speed_mps into position_m (x of the vehicle reference point at the "
                            "first sample [m])")
        v = have[_SPEED]
        pos = np.empty_like(v)
        x = spec.position_start_m
        prev_end = None
        for s in tl.segments:
            if prev_end is not None:
                gap_s = (s.t0_ns - prev_end[0]) * 1e-9
                x += 0.5 * (prev_end[1] + v[s.start]) * gap_s
            seg = cumulative_trapezoid(v[s.start:s.stop], dx=1.0 / tl.rate_hz, initial=0.0)
            pos[s.start:s.stop] = x + seg
            x = pos[s.stop - 1]
            prev_end = (s.t0_ns + int(round((s.n - 1) * 1e9 / tl.rate_hz)), v[s.stop - 1])
        have[_POS] = pos
        derived.append({"channel": _POS, "how": f"integrated from speed_mps (trapezoidal, from "
                        f"position_start_m = {spec.position_start_m:g} m)"})
    return have, derived


def build_topics(spec: ImportSpec):
    """Read, convert and check every channel: (topics {topic: (ids, si_units, timeline, data)},
    conversions, derived, notes, metadata document to write, sources)."""
    md = spec.metadata
    sensors = md.sensors
    by_source: dict = {}
    for cs in spec.channels:
        by_source.setdefault(cs.source.key, (cs.source, []))[1].append(cs)
    cols: dict[str, Column] = {}
    sources = []
    for src, chans in by_source.values():
        got = read_columns(src, [c.column for c in chans])
        for cs in chans:
            cols[cs.id] = got[cs.column]
        sources.append({"file": str(src.file), "format": src.format})

    conversions, values, si_units = [], {}, {}
    for cs in spec.channels:
        col = cols[cs.id]
        topic = sensors[cs.id].topic
        unit, unit_from = _unit(spec, cs, col, topic)
        si, factor = _si(spec, cs.id, topic, unit)
        values[cs.id] = col.values * factor
        si_units[cs.id] = si
        if unit != si:
            conversions.append({"channel": cs.id, "topic": topic, "column": str(cs.column),
                                "unit": unit, "si_unit": si, "factor": factor,
                                "unit_from": unit_from})

    topics: dict = {}
    derived: list = []
    notes: list = []
    doc = copy.deepcopy(md.to_dict())
    for topic in dict.fromkeys(s.topic for s in sensors.values()):
        ids = [c for c in md.sensors_on_topic(topic) if c in cols]
        if not ids:
            continue
        rates = {c: cols[c].timeline.rate_hz for c in ids}
        ref = cols[ids[0]].timeline
        odd = [c for c in ids[1:] if not same_grid(cols[c].timeline, ref)]
        resampled: tuple = ()
        if odd:
            c = odd[0]
            if not spec.resample:
                if abs(rates[c] - rates[ids[0]]) > 1e-6 * rates[ids[0]]:
                    raise UserError(f"{spec.origin}: topic {topic}: channels {ids[0]} "
                                    f"({rates[ids[0]]:g} Hz) and {c} ({rates[c]:g} Hz) differ in "
                                    "sample rate; a contract topic's channels share one rate "
                                    "(set resample: true to interpolate onto the fastest)")
                raise UserError(f"{spec.origin}: topic {topic}: channels {ids[0]} and {c} are not "
                                f"sampled at the same times (start {ref.start_ns * 1e-9:.6f} s vs "
                                f"{cols[c].timeline.start_ns * 1e-9:.6f} s, {ref.n} vs "
                                f"{cols[c].timeline.n} samples, {len(ref.gaps)} vs "
                                f"{len(cols[c].timeline.gaps)} gaps); set resample: true to "
                                "interpolate onto one grid")
            tl, vals, resampled = _resample_topic(topic, ids, cols, values)
        else:
            tl, vals = ref, {c: values[c] for c in ids}
        units = {c: si_units[c] for c in ids}
        if topic == TOPIC_VEHICLE_POSITION:
            before = set(vals)
            vals, d = _derive_position(spec, tl, vals)
            derived += d
            for c in set(vals) - before:
                units[c] = "m" if c == _POS else "m/s"
                if c not in doc["sensors"]:
                    doc["sensors"][c] = {"topic": topic, "quantity": "position" if c == _POS else "speed"}
                    notes.append(f"metadata: sensor {c} added on {topic} (derived by the import)")
                elif doc["sensors"][c].get("topic") != topic:
                    raise UserError(f"{spec.metadata_origin}: metadata key sensors.{c}.topic: "
                                    f"expected {topic} for the derived {c}")
            order = [c for c in (_POS, _SPEED) if c in vals]
            ids = order + [c for c in ids if c not in order]
        if tl.gaps and spec.gaps == "fail":
            g = tl.gaps[0]
            raise UserError(f"{cols[[c for c in ids if c in cols][0]].where}: {g.where}: gap of "
                            f"{g.gap_s:.6g} s (~{g.missing} samples missing) before it (gaps: fail)")
        data = np.stack([vals[c] for c in ids], axis=1)
        topics[topic] = (tuple(ids), tuple(units[c] for c in ids), tl, data, resampled)
        missing = [c for c in md.sensors_on_topic(topic) if c not in ids]
        if missing:
            notes.append(f"{topic}: metadata sensors not imported (no column mapped): {', '.join(missing)}")
    if md.run_kind == "pass" and TOPIC_VEHICLE_POSITION not in topics:
        notes.append(f"no position or speed channel: {TOPIC_VEHICLE_POSITION} is not written "
                     "(irregularity, update and the twin need it for a pass)")
    doc["import"] = {"tool": "maglev-ros import", "sources": [Path(s["file"]).name for s in sources],
                     "conversions": conversions, "derived": derived}
    return topics, conversions, derived, notes, doc, sources


def import_to_bag(spec: ImportSpec, out: str | Path, overwrite: bool = False,
                  storage: str = "mcap") -> ImportResult:
    """Import the spec's channels into a contract bag at ``out`` (MCAP)."""
    from maglev_ros.bag_writer import BagWriter
    from maglev_ros.sensor_block import Block

    out = Path(out)
    if (out.exists() or out.is_symlink()) and not overwrite:
        raise UserError(f"{out}: already exists; refusing to overwrite (pass --overwrite)")
    if not (out.parent if str(out.parent) else Path(".")).is_dir():
        raise UserError(f"{out}: parent directory {out.parent} does not exist")
    topics, conversions, derived, notes, doc, sources = build_topics(spec)
    events, results = [], []
    for topic, (ids, units, tl, data, resampled) in topics.items():
        data32 = data.astype(np.float32)
        bs = max(1, int(round(spec.block_s * tl.rate_hz)))
        frame = "guideway" if topic in (TOPIC_GUIDEWAY_ACCEL, TOPIC_GUIDEWAY_DISP) else "vehicle"
        n_blocks = 0
        for s in tl.segments:
            for first in range(0, s.n, bs):
                stamp = s.t0_ns + int(round(first * 1e9 / tl.rate_hz))
                rows = data32[s.start + first:s.start + min(first + bs, s.n)]
                events.append((stamp, topic, Block.from_arrays(stamp, tl.rate_hz, ids, units, rows, frame)))
                n_blocks += 1
        results.append(TopicResult(topic, ids, units, tl.rate_hz, tl.origin, tl.n, n_blocks,
                                   tl.start_ns * 1e-9, (tl.end_ns - tl.start_ns) * 1e-9, tl.gaps,
                                   resampled))
    if not events:
        raise UserError(f"{spec.origin}: nothing to write (no channel mapped)")
    events.sort(key=lambda e: (e[0], e[1]))
    with BagWriter(out, doc, overwrite=overwrite, storage=storage,
                   metadata_stamp_ns=events[0][0]) as w:
        for stamp, topic, blk in events:
            w.write_block(topic, blk)
    return ImportResult(out=str(out), spec=spec.origin, metadata=spec.metadata_origin,
                        sources=tuple(sources), topics=tuple(results),
                        conversions=tuple(conversions), derived=tuple(derived), notes=tuple(notes))
