"""What the DAQ simulator publishes (no rclpy): a contract recording turned into the per-sample
streams drivers publish, with the metadata and mapping files that bring them back.

From a contract bag: guideway topics that share their sample times -> one
``std_msgs/Float64MultiArray`` ``/daq/guideway`` per sample (element 0 the sample time [s], then
accelerations in g and displacements in mm: several channels per message, non-SI units);
each vehicle / car-body accelerometer -> ``sensor_msgs/Imu`` ``/daq/imu_<id>`` with
``linear_acceleration.z`` the specific force a z-up IMU reports (REP 145: acceleration + g);
each gap -> ``sensor_msgs/Range`` ``/daq/gap_<id>`` [m] (REP 117); position and speed ->
``nav_msgs/Odometry`` ``/daq/odom`` (``pose.pose.position.x``, ``twist.twist.linear.x``).
The metadata is the bag's with each topic's rate as ``acquisition.<topic>.sample_rate_hz``.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from maglev_ros.contract import (TOPIC_BODY_ACCEL, TOPIC_GUIDEWAY_ACCEL, TOPIC_GUIDEWAY_DISP, TOPIC_VEHICLE_ACCEL,
                                 TOPIC_VEHICLE_GAP, TOPIC_VEHICLE_POSITION)
from maglev_ros.daq_stream.mapping import STANDARD_GRAVITY_MPS2
from maglev_ros.errors import UserError

__all__ = ["SimStream", "SimSource", "source_from_bag", "write_config", "plain_message", "MULTIARRAY_UNITS"]

MULTIARRAY_UNITS = {TOPIC_GUIDEWAY_ACCEL: "g", TOPIC_GUIDEWAY_DISP: "mm"}
GUIDEWAY_TOPIC = "/daq/guideway"


@dataclass(frozen=True)
class SimStream:
    """One driver topic: per message its stamp and the raw values the message carries."""

    topic: str
    msg_type: str
    stamps_ns: np.ndarray           # (n,) int64
    values: np.ndarray              # (n, k) float64, as published (Float64MultiArray: the whole data)


@dataclass(frozen=True)
class SimSource:
    metadata: dict
    mapping: dict
    streams: tuple[SimStream, ...]
    # contract topic -> (stamps_ns (n,), SI data (n, c), channels): what the adapter should give back
    truth: dict

    @property
    def samples(self) -> int:
        return sum(int(d.size) for _, d, _ in self.truth.values())

    def order(self) -> tuple[np.ndarray, np.ndarray]:
        """(stream index, row) of every message in publication order: by stamp, then stream."""
        idx = np.concatenate([np.full(len(s.stamps_ns), i) for i, s in enumerate(self.streams)])
        rows = np.concatenate([np.arange(len(s.stamps_ns)) for s in self.streams])
        stamps = np.concatenate([s.stamps_ns for s in self.streams])
        o = np.lexsort((idx, stamps))
        return idx[o], rows[o]


def _topic_samples(reader, topic: str, t_lo: int, t_hi: int):
    """(stamps_ns, data float64, channels, units) of ``topic``'s samples stamped in [t_lo, t_hi)."""
    stamps, rows, chans, units = [], [], None, None
    for _, blk in reader.iter_blocks([topic]):
        chans, units = blk.channels, blk.units
        st = blk.stamp_ns + np.round(np.arange(blk.n_samples) * 1e9 / blk.sample_rate_hz).astype(np.int64)
        keep = (st >= t_lo) & (st < t_hi)
        stamps.append(st[keep])
        rows.append(np.asarray(blk.data, dtype=np.float64)[keep])
        rate = blk.sample_rate_hz
    if chans is None:
        return None
    return np.concatenate(stamps), np.concatenate(rows), chans, units, rate


def source_from_bag(bag, start_s: float = 0.0, duration_s: float | None = None, offset_ns: int = 0,
                    block_s: float = 0.1) -> SimSource:
    """The driver streams of ``bag``'s samples in [first stamp + start_s, + duration_s), stamps moved
    by ``offset_ns``."""
    from maglev_ros.bag_reader import BagReader
    from maglev_ros.health import block_to_si
    from maglev_ros.sensor_block import Block
    with BagReader(bag) as r:
        md = r.metadata
        topics = [t for t in (TOPIC_GUIDEWAY_ACCEL, TOPIC_GUIDEWAY_DISP, TOPIC_VEHICLE_ACCEL, TOPIC_VEHICLE_GAP,
                              TOPIC_BODY_ACCEL, TOPIC_VEHICLE_POSITION) if t in r.topics]
        first = min(blk.stamp_ns for _, blk in r.iter_blocks(topics))
        t_lo = first + int(round(start_s * 1e9))
        t_hi = t_lo + int(round(duration_s * 1e9)) if duration_s is not None else 2**62
        data = {}
        for t in topics:
            got = _topic_samples(r, t, t_lo, t_hi)
            if got is not None and len(got[0]):
                st, d, ch, un, rate = got
                si, _ = block_to_si(t, Block.from_arrays(0, rate, ch, un, d))
                data[t] = (st + offset_ns, np.asarray(si.data, dtype=np.float64), ch, rate)
    if not data:
        raise UserError(f"{bag}: no samples of a contract data topic in the window from {start_s} s"
                        + (f" for {duration_s} s" if duration_s is not None else ""))
    meta = md.to_dict()
    meta["description"] = (meta.get("description", "") + " (streamed per sample by daq_sim)").strip()
    acq = meta.setdefault("acquisition", {})
    for t, (_, _, _, rate) in data.items():
        acq.setdefault(t, {})["sample_rate_hz"] = float(rate)
    channels: dict[str, dict] = {}
    streams: list[SimStream] = []
    truth = {t: (st, d, ch) for t, (st, d, ch, _) in data.items()}

    # guideway: one multi-channel message per sample (both topics in one where they share their times)
    gw = [t for t in (TOPIC_GUIDEWAY_ACCEL, TOPIC_GUIDEWAY_DISP) if t in data]
    groups = [gw] if len(gw) == 2 and np.array_equal(data[gw[0]][0], data[gw[1]][0]) else [[t] for t in gw]
    for gi, group in enumerate(groups):
        topic = GUIDEWAY_TOPIC if gi == 0 else GUIDEWAY_TOPIC + "_displacement"
        st = data[group[0]][0]
        cols = [st * 1e-9]
        for g in group:
            unit = MULTIARRAY_UNITS[g]
            factor = {"g": STANDARD_GRAVITY_MPS2, "mm": 1e-3}[unit]
            for j, ch in enumerate(data[g][2]):
                channels[ch] = {"topic": topic, "type": "std_msgs/msg/Float64MultiArray", "index": len(cols),
                                "unit": unit, "stamp_index": 0}
                cols.append(data[g][1][:, j] / factor)
        streams.append(SimStream(topic, "std_msgs/msg/Float64MultiArray", st, np.column_stack(cols)))
    for t in (TOPIC_VEHICLE_ACCEL, TOPIC_BODY_ACCEL):
        if t in data:
            st, d, chans, _ = data[t]
            for j, ch in enumerate(chans):
                topic = f"/daq/imu_{ch.lower()}"
                channels[ch] = {"topic": topic, "type": "sensor_msgs/msg/Imu", "field": "linear_acceleration.z",
                                "unit": "m/s^2", "remove_gravity": True}
                streams.append(SimStream(topic, "sensor_msgs/msg/Imu", st,
                                         (d[:, j] + STANDARD_GRAVITY_MPS2).reshape(-1, 1)))
    if TOPIC_VEHICLE_GAP in data:
        st, d, chans, _ = data[TOPIC_VEHICLE_GAP]
        for j, ch in enumerate(chans):
            topic = f"/daq/gap_{ch.lower()}"
            channels[ch] = {"topic": topic, "type": "sensor_msgs/msg/Range", "field": "range", "unit": "m"}
            streams.append(SimStream(topic, "sensor_msgs/msg/Range", st, d[:, j].reshape(-1, 1)))
    if TOPIC_VEHICLE_POSITION in data:
        st, d, chans, _ = data[TOPIC_VEHICLE_POSITION]
        fields = {"position_m": "pose.pose.position.x", "speed_mps": "twist.twist.linear.x"}
        cols = [c for c in chans if c in fields]
        for c in cols:
            channels[c] = {"topic": "/daq/odom", "type": "nav_msgs/msg/Odometry", "field": fields[c]}
        streams.append(SimStream("/daq/odom", "nav_msgs/msg/Odometry", st,
                                 np.column_stack([d[:, chans.index(c)] for c in cols])))
        truth[TOPIC_VEHICLE_POSITION] = (st, d[:, [chans.index(c) for c in cols]], tuple(cols))
    mapping = {"block_s": float(block_s), "channels": channels}
    return SimSource(meta, mapping, tuple(streams), truth)


def plain_message(msg_type: str, stamp_ns: int, values):
    """A stand-in of the driver message (attributes only, no rclpy) carrying ``values`` as
    :class:`SimStream` holds them: what the batching core reads, for tests and benchmarks."""
    from types import SimpleNamespace as NS
    sec, nsec = divmod(int(stamp_ns), 1_000_000_000)
    header = NS(stamp=NS(sec=sec, nanosec=nsec), frame_id="")
    v = [float(x) for x in values]
    if msg_type == "std_msgs/msg/Float64MultiArray":
        return NS(data=v)
    if msg_type == "std_msgs/msg/Float64":
        return NS(data=v[0])
    if msg_type == "sensor_msgs/msg/Imu":
        return NS(header=header, linear_acceleration=NS(x=0.0, y=0.0, z=v[0]))
    if msg_type == "sensor_msgs/msg/Range":
        return NS(header=header, range=v[0])
    if msg_type == "nav_msgs/msg/Odometry":
        return NS(header=header, pose=NS(pose=NS(position=NS(x=v[0], y=0.0, z=0.0))),
                  twist=NS(twist=NS(linear=NS(x=v[1] if len(v) > 1 else 0.0, y=0.0, z=0.0))))
    raise ValueError(f"no stand-in for {msg_type}")


def write_config(source: SimSource, out_dir) -> tuple[Path, Path]:
    """``out_dir``/daq_metadata.json and ``out_dir``/daq_mapping.yaml (atomic writes); their paths."""
    import yaml

    from maglev_ros.outputs import write_json, write_text
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    meta = write_json(out / "daq_metadata.json", source.metadata)
    text = ("# daq_sim's driver topics -> contract channels (maglev_ros/daq_stream/mapping.py)\n"
            + yaml.safe_dump(source.mapping, sort_keys=False, default_flow_style=None, width=200))
    mapping = write_text(out / "daq_mapping.yaml", text)
    return Path(meta), Path(mapping)
