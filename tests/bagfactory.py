"""Test-bag generators (reused by every helper's tests).

- :func:`make_metadata`: a valid contract metadata dict for given topics/channels.
- :func:`write_contract_bag`: a contract bag written with maglev_ros' own BagWriter.
- :func:`write_foreign_bag`: a contract bag written with plain rosbags only (no maglev_ros
  code), types registered from the contract's own .msg text, with its own block sizes, receive
  times lagging the header stamps, rosbag2 MCAP / sqlite3 or ROS1 storage, and optional
  :class:`Faults` (dropped / duplicated / swapped / overlapping blocks, NaN/inf samples, non-SI
  units, short unit lists, missing metadata key or topic, truncated storage file).
- :func:`example_topics`: a small multi-topic data set with known content.

``topics`` everywhere is ``{topic: (channels, units, rate_hz, data)}`` with data of shape
(n_samples, n_channels); the bag holds it as float32. Block k of a topic starts at sample
``k * block_samples`` and is stamped ``t0_ns + round(first_sample * 1e9 / rate_hz)``.
"""
from __future__ import annotations

import copy
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

# the contract's own .msg text (shared/ beside the repository; the repo's docs/contract/msg links to
# msg_defs/msg, which carries it unchanged: a layout test compares the two when shared/ is there)
_SHARED_MSG_DIR = Path(__file__).resolve().parents[2] / "shared" / "contract" / "msg"
CONTRACT_MSG_DIR = (_SHARED_MSG_DIR if _SHARED_MSG_DIR.is_dir()
                    else Path(__file__).resolve().parents[1] / "docs" / "contract" / "msg")
SENSORBLOCK_TYPE = "maglev_msgs/msg/SensorBlock"
METADATA_TOPIC = "/testline/metadata"

GUIDEWAY_ACCEL = "/testline/guideway/accel"
GUIDEWAY_DISP = "/testline/guideway/displacement"
VEHICLE_ACCEL = "/testline/vehicle/accel"
VEHICLE_GAP = "/testline/vehicle/gap"
VEHICLE_POSITION = "/testline/vehicle/position"

_QUANTITY = {GUIDEWAY_ACCEL: "acceleration", GUIDEWAY_DISP: "displacement",
             VEHICLE_ACCEL: "acceleration", VEHICLE_GAP: "gap"}


# ------------------------------------------------------------------------------- metadata
def make_metadata(topics: dict, kind: str = "pass", n_spans: int = 3, span_length_m: float = 12.384,
                  magnet_offsets_m=(0.0, -1.548, -3.096, -4.644), nominal_speed_mps: float = 6.944,
                  design: dict | None = None, extra: dict | None = None) -> dict:
    """A valid contract metadata document listing every channel of ``topics``.

    ``topics``: {topic: (channels, ...)} (only the channel list is used). Guideway sensors get
    span/position/side; vehicle sensors get magnet numbers cycling over the magnets.
    """
    spans = [{"id": f"S{i + 1}", "start_m": i * span_length_m, "length_m": span_length_m}
             for i in range(n_spans)]
    sensors = {}
    for topic, spec in topics.items():
        channels = spec[0]
        for j, ch in enumerate(channels):
            s = {"topic": topic}
            if topic in (GUIDEWAY_ACCEL, GUIDEWAY_DISP):
                span = j % n_spans
                s.update({"quantity": _QUANTITY[topic], "direction": "vertical",
                          "span": f"S{span + 1}",
                          "position_m": (span + 0.5) * span_length_m, "side": "left"})
            elif topic in (VEHICLE_ACCEL, VEHICLE_GAP):
                s.update({"quantity": _QUANTITY[topic],
                          "magnet": 1 + j % len(magnet_offsets_m)})
                if topic == VEHICLE_ACCEL:
                    s["direction"] = "vertical"
            elif topic == VEHICLE_POSITION:
                s["quantity"] = "position" if ch == "position_m" else "speed"
            sensors[ch] = s
    doc = {
        "schema": "maglev-testline/1",
        "description": "bagfactory test recording",
        "line": {"spans": spans},
        "sensors": sensors,
        "run": {"kind": kind},
    }
    if kind == "pass":
        doc["vehicle"] = {"magnet_offsets_m": list(magnet_offsets_m), "nominal_gap_m": 0.010}
        doc["run"]["nominal_speed_mps"] = nominal_speed_mps
    if design is not None:
        doc["design"] = design
    if extra:
        doc.update(extra)
    return doc


def example_topics(duration_s: float = 2.0, seed: int = 0, accel_rate_hz: float = 2000.0,
                   gap_rate_hz: float = 1000.0, position_rate_hz: float = 100.0,
                   speed_mps: float = 6.944) -> dict:
    """Guideway accel (3 ch), vehicle accel (2 ch), gap (2 ch) and position (2 ch) with known
    content: sines plus seeded noise; position = speed * t exactly."""
    rng = np.random.default_rng(seed)

    def sines(rate, n_ch, amp, offset=0.0):
        t = np.arange(int(round(duration_s * rate))) / rate
        cols = [offset + amp * np.sin(2 * np.pi * (3.0 + 2.0 * j) * t + j)
                + 0.05 * amp * rng.standard_normal(t.size) for j in range(n_ch)]
        return np.stack(cols, axis=1)

    tp = np.arange(int(round(duration_s * position_rate_hz))) / position_rate_hz
    return {
        GUIDEWAY_ACCEL: (("G1LV", "G2LV", "G3LV"), ("m/s^2",) * 3, accel_rate_hz,
                         sines(accel_rate_hz, 3, 0.5)),
        VEHICLE_ACCEL: (("M1A", "M2A"), ("m/s^2",) * 2, accel_rate_hz, sines(accel_rate_hz, 2, 1.0)),
        VEHICLE_GAP: (("M1G", "M2G"), ("m", "m"), gap_rate_hz, sines(gap_rate_hz, 2, 1e-3, 0.010)),
        VEHICLE_POSITION: (("position_m", "speed_mps"), ("m", "m/s"), position_rate_hz,
                           np.stack([speed_mps * tp, np.full(tp.size, speed_mps)], axis=1)),
    }


# -------------------------------------------------------------------------- block layout
def _block_plan(n_samples: int, block_samples) -> list[tuple[int, int]]:
    """[(first_sample, n)] covering n_samples; block_samples is an int or a cycling sequence."""
    sizes = [int(block_samples)] if np.isscalar(block_samples) else [int(b) for b in block_samples]
    out, i, k = [], 0, 0
    while i < n_samples:
        n = min(sizes[k % len(sizes)], n_samples - i)
        out.append((i, n))
        i += n
        k += 1
    return out


def block_stamp_ns(t0_ns: int, first_sample: int, rate_hz: float) -> int:
    return int(t0_ns) + int(round(first_sample * 1e9 / rate_hz))


def expected_times_s(t0_ns: int, n_samples: int, rate_hz: float, block_samples) -> np.ndarray:
    """Sample times a reader must report: block stamp (ns, as written) + j / rate."""
    parts = []
    for first, n in _block_plan(n_samples, block_samples):
        parts.append(block_stamp_ns(t0_ns, first, rate_hz) * 1e-9 + np.arange(n) / rate_hz)
    return np.concatenate(parts) if parts else np.zeros(0)


def write_contract_bag(path, metadata: dict, topics: dict, block_s: float = 0.1,
                       storage: str = "mcap", t0_ns: int = 0, lag_ns: int = 0,
                       overwrite: bool = False) -> Path:
    """Write ``topics`` with maglev_ros' BagWriter; blocks of round(block_s * rate) samples,
    written in stamp order across topics; receive time = stamp + lag_ns."""
    from maglev_ros.bag_writer import BagWriter
    from maglev_ros.sensor_block import Block

    frame = {GUIDEWAY_ACCEL: "guideway", GUIDEWAY_DISP: "guideway"}
    events = []
    for topic, (channels, units, rate, data) in topics.items():
        data = np.asarray(data, dtype=np.float32).reshape(len(data), -1)
        bs = max(1, int(round(block_s * rate)))
        for first, n in _block_plan(data.shape[0], bs):
            stamp = block_stamp_ns(t0_ns, first, rate)
            events.append((stamp, topic, Block.from_arrays(stamp, rate, channels, units,
                                                           data[first:first + n],
                                                           frame.get(topic, "vehicle"))))
    events.sort(key=lambda e: (e[0], e[1]))
    with BagWriter(path, metadata, storage=storage, overwrite=overwrite,
                   metadata_stamp_ns=min([t0_ns] + [e[0] for e in events])) as w:
        for stamp, topic, blk in events:
            w.write_block(topic, blk, log_time_ns=stamp + lag_ns)
    return Path(path)


# ------------------------------------------------------------------------ foreign writer
@dataclass
class Faults:
    """Faults the foreign writer can inject. Block indices count the blocks of one topic."""

    drop: dict = field(default_factory=dict)          # topic -> [k]: block k not written (gap)
    duplicate: dict = field(default_factory=dict)     # topic -> [k]: block k written twice
    swap: dict = field(default_factory=dict)          # topic -> [k]: block k arrives after k+1
    overlap: dict = field(default_factory=dict)       # topic -> [k]: block k stamped half a block early
    nan: dict = field(default_factory=dict)           # topic -> [(k, sample, channel)] -> NaN
    inf: dict = field(default_factory=dict)           # topic -> [(k, sample, channel)] -> +inf
    units: dict = field(default_factory=dict)         # topic -> {channel: unit string}
    short_units: dict = field(default_factory=dict)   # topic -> [k]: last unit missing in block k
    extra_channel: dict = field(default_factory=dict)  # topic -> name of an unlisted extra channel
    bad_length: dict = field(default_factory=dict)    # topic -> [k]: last value of block k dropped
    missing_metadata_key: str | None = None           # dotted key removed, e.g. "run.kind"
    no_metadata: bool = False                         # no /testline/metadata topic at all
    metadata_text: str | None = None                  # this text on the metadata topic instead of the JSON
    truncate_fraction: float | None = None            # keep this fraction of the storage file


def _meta_text(doc: dict, faults: "Faults") -> str:
    return json.dumps(doc) if faults.metadata_text is None else faults.metadata_text


def _drop_key(doc: dict, dotted: str) -> dict:
    doc = copy.deepcopy(doc)
    parts = dotted.split(".")
    obj = doc
    for p in parts[:-1]:
        obj = obj[p]
    del obj[parts[-1]]
    return doc


def foreign_typestore(ros1: bool = False):
    """Plain rosbags typestore with SensorBlock registered from the contract's .msg text."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    text = (CONTRACT_MSG_DIR / "SensorBlock.msg").read_text()
    store.register(get_types_from_msg(text, SENSORBLOCK_TYPE))
    return store


def write_foreign_bag(path, metadata: dict, topics: dict, block_samples=None,
                      block_s: float = 0.05, storage: str = "mcap", t0_ns: int = 1_700_000_000_000_000_000,
                      lag_ns: int = 3_000_000, jitter_ns: int = 2_000_000, faults: Faults | None = None,
                      seed: int = 0, version: int = 8) -> Path:
    """Write a contract bag with plain rosbags only (no maglev_ros), like third-party tooling.

    ``storage``: "mcap", "sqlite3" (rosbag2 directory ``path``) or "ros1" (``path`` must end in
    .bag). ``block_samples``: int or cycling sequence of block lengths (default block_s * rate).
    Receive time = stamp + lag_ns + uniform jitter in [0, jitter_ns), kept non-decreasing in
    arrival order; the metadata is received first. Header stamps start at ``t0_ns`` (default a
    wall-clock epoch time, unlike our own writer's zero-based stamps). Returns the bag path.
    """
    faults = faults or Faults()
    path = Path(path)
    rng = np.random.default_rng(seed)
    ros1 = storage == "ros1"
    store = foreign_typestore(ros1)
    Msg = store.types[SENSORBLOCK_TYPE]
    Header = store.types["std_msgs/msg/Header"]
    Time = store.types["builtin_interfaces/msg/Time"]
    String = store.types["std_msgs/msg/String"]

    # build the arrival sequence: (arrival key, topic, stamp_ns, msg)
    events = []
    for topic, (channels, units, rate, data) in topics.items():
        data = np.asarray(data, dtype=np.float32).reshape(len(data), -1)
        bs = block_samples if block_samples is not None else max(1, int(round(block_s * rate)))
        plan = _block_plan(data.shape[0], bs)
        units = list(units)
        for ch, u in faults.units.get(topic, {}).items():
            units[list(channels).index(ch)] = u
        for k, (first, n) in enumerate(plan):
            if k in faults.drop.get(topic, ()):
                continue
            blk = data[first:first + n].copy()
            chans = list(channels)
            us = list(units)
            for (kk, s, c) in faults.nan.get(topic, ()):
                if kk == k:
                    blk[s, c] = np.nan
            for (kk, s, c) in faults.inf.get(topic, ()):
                if kk == k:
                    blk[s, c] = np.inf
            if topic in faults.extra_channel:
                chans.append(faults.extra_channel[topic])
                us.append(us[-1])
                blk = np.concatenate([blk, blk[:, -1:]], axis=1)
            if k in faults.short_units.get(topic, ()):
                us = us[:-1]
            stamp = block_stamp_ns(t0_ns, first, rate)
            if k in faults.overlap.get(topic, ()):
                stamp -= int(round(n * 1e9 / rate / 2))
            sec, nsec = divmod(stamp, 1_000_000_000)
            hdr = Header(seq=k, stamp=Time(sec=sec, nanosec=nsec), frame_id="test") if ros1 else \
                Header(stamp=Time(sec=sec, nanosec=nsec), frame_id="test")
            flat = np.ascontiguousarray(blk).reshape(-1)
            if k in faults.bad_length.get(topic, ()):
                flat = flat[:-1].copy()
            msg = Msg(header=hdr, sample_rate_hz=float(rate), channels=chans, units=us, data=flat)
            # arrival: when the block is complete (its last sample) plus transport lag
            arrive = stamp + int(n * 1e9 / rate) + lag_ns + int(rng.integers(0, max(jitter_ns, 1)))
            events.append([arrive, topic, k, stamp, msg])
            if k in faults.duplicate.get(topic, ()):
                events.append([arrive + 1, topic, k, stamp, msg])
    # swapped blocks: block k arrives just after block k+1
    for topic, ks in faults.swap.items():
        by_k = {e[2]: e for e in events if e[1] == topic}
        for k in ks:
            if k in by_k and k + 1 in by_k:
                by_k[k][0] = by_k[k + 1][0] + 1
    events.sort(key=lambda e: e[0])

    meta_doc = metadata
    if faults.missing_metadata_key:
        meta_doc = _drop_key(metadata, faults.missing_metadata_key)
    meta_time = min([t0_ns] + [e[0] for e in events])

    if ros1:
        from rosbags.rosbag1 import Writer as Writer1

        if path.suffix != ".bag":
            raise ValueError("ROS1 bag path must end in .bag")
        with Writer1(path) as w:
            conns = {}
            if not faults.no_metadata:
                c = w.add_connection(METADATA_TOPIC, "std_msgs/msg/String", typestore=store)
                w.write(c, meta_time, store.serialize_ros1(String(data=_meta_text(meta_doc, faults)),
                                                           "std_msgs/msg/String"))
            for arrive, topic, _k, _stamp, msg in events:
                if topic not in conns:
                    conns[topic] = w.add_connection(topic, SENSORBLOCK_TYPE, typestore=store)
                w.write(conns[topic], arrive, store.serialize_ros1(msg, SENSORBLOCK_TYPE))
        storage_file = path
    else:
        from rosbags.rosbag2 import StoragePlugin, Writer

        plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
        with Writer(path, version=version, storage_plugin=plugin) as w:
            conns = {}
            if not faults.no_metadata:
                c = w.add_connection(METADATA_TOPIC, "std_msgs/msg/String", typestore=store)
                w.write(c, meta_time, store.serialize_cdr(String(data=_meta_text(meta_doc, faults)),
                                                          "std_msgs/msg/String"))
            for arrive, topic, _k, _stamp, msg in events:
                if topic not in conns:
                    conns[topic] = w.add_connection(topic, SENSORBLOCK_TYPE, typestore=store)
                w.write(conns[topic], arrive, store.serialize_cdr(msg, SENSORBLOCK_TYPE))
        storage_file = next(p for p in path.iterdir() if p.suffix in (".mcap", ".db3"))
    if faults.truncate_fraction is not None:
        size = storage_file.stat().st_size
        with open(storage_file, "r+b") as fh:
            fh.truncate(int(size * faults.truncate_fraction))
    return path


def foreign_block_plan(topics: dict, block_samples=None, block_s: float = 0.05) -> dict:
    """{topic: block_samples argument} the foreign writer used (for expected_times_s)."""
    return {t: (block_samples if block_samples is not None else max(1, int(round(block_s * spec[2]))))
            for t, spec in topics.items()}
