"""The adapter's mapping file: which driver topic and message field is which contract channel.

```yaml
block_s: 0.1                          # SensorBlock length [s]
rates_hz: {/testline/vehicle/position: 200}    # optional; else the metadata's acquisition rate
channels:
  M1A: {topic: /daq/imu_m1, type: sensor_msgs/msg/Imu, field: linear_acceleration.z, unit: m/s^2,
        remove_gravity: true}
  M1G: {topic: /daq/gap_m1, type: sensor_msgs/msg/Range, field: range, unit: m}
  G3LV: {topic: /daq/guideway, type: std_msgs/msg/Float64MultiArray, index: 4, unit: g, stamp_index: 0}
  position_m: {topic: /daq/odom, type: nav_msgs/msg/Odometry, field: pose.pose.position.x}
```
Each channel goes to the contract topic the metadata's ``sensors.<id>.topic`` names
(``position_m`` and ``speed_mps`` to ``/testline/vehicle/position``). Errors name the mapping file
and the key, in one line. Field paths are checked against a table of the supported types' numeric
fields (no rclpy here, and a typo must fail at load, not at the first message).
"""
from __future__ import annotations

import math
import operator
from dataclasses import dataclass, field
from pathlib import Path

from maglev_ros.contract import (DATA_TOPICS, POSITION_CHANNEL_UNITS, TOPIC_VEHICLE_POSITION, Metadata,
                                 expected_unit, unit_conversion)
from maglev_ros.errors import UserError
from maglev_ros.metadata_file import load_yaml, metadata_from_file

__all__ = ["DRIVER_TYPES", "STANDARD_GRAVITY_MPS2", "ChannelSpec", "DriverTopic", "DaqMapping",
           "load_mapping", "mapping_from_dict", "load_metadata_file", "DEFAULT_BLOCK_S"]

# REP 145: an accelerometer reports specific force, so an upright IMU at rest reads +g on z; the
# value is the unit table's factor of 'g' (standard gravity)
STANDARD_GRAVITY_MPS2 = 9.80665
DEFAULT_BLOCK_S = 0.1

_XYZ = ("x", "y", "z")
# type -> (has a std_msgs/Header, numeric field paths a channel may take; None: an array by index)
DRIVER_TYPES: dict[str, tuple[bool, tuple[str, ...] | None]] = {
    "sensor_msgs/msg/Imu": (True, tuple(f"{v}.{a}" for v in ("linear_acceleration", "angular_velocity")
                                          for a in _XYZ) + tuple(f"orientation.{a}" for a in (*_XYZ, "w"))),
    "sensor_msgs/msg/Range": (True, ("range",)),
    "nav_msgs/msg/Odometry": (True, tuple(f"pose.pose.position.{a}" for a in _XYZ)
                              + tuple(f"twist.twist.{v}.{a}" for v in ("linear", "angular") for a in _XYZ)),
    "std_msgs/msg/Float64": (False, ("data",)),
    "std_msgs/msg/Float64MultiArray": (False, None),
}
_DEFAULT_FIELD = {"sensor_msgs/msg/Range": "range", "std_msgs/msg/Float64": "data"}
_CHANNEL_KEYS = {"topic", "type", "field", "index", "unit", "remove_gravity", "sign", "stamp_index"}
_TOP_KEYS = {"block_s", "rates_hz", "channels", "gravity_mps2"}


@dataclass(frozen=True)
class ChannelSpec:
    """One contract channel: where it comes from and how its raw value becomes SI.

    value_si = raw * factor * sign - (gravity if remove_gravity)."""

    name: str
    contract_topic: str
    driver_topic: str
    msg_type: str
    field: str | None                   # dotted attribute path (None: ``index`` into ``data``)
    index: int | None
    unit: str
    si_unit: str
    factor: float
    sign: float = 1.0
    remove_gravity: bool = False
    stamp_index: int | None = None      # Float64MultiArray: element holding the sample time [s]

    def getter(self):
        """raw value of this channel from a driver message (any object with the attributes)."""
        if self.index is not None:
            i = self.index
            return lambda msg: msg.data[i]
        return operator.attrgetter(self.field)


@dataclass(frozen=True)
class DriverTopic:
    """One topic a driver publishes: its type, where its stamps come from, the channels it feeds."""

    topic: str
    msg_type: str
    has_header: bool
    stamp_index: int | None             # Float64MultiArray: element holding the sample time [s]
    channels: tuple[ChannelSpec, ...]

    @property
    def stamp_source(self) -> str:
        if self.has_header:
            return "header"
        return "element" if self.stamp_index is not None else "receive"


@dataclass(frozen=True)
class DaqMapping:
    source: str
    block_s: float
    gravity_mps2: float
    rates_hz: dict                      # contract topic -> sample rate [Hz]
    channels: tuple[ChannelSpec, ...]   # contract topics in DATA_TOPICS order, channels in metadata order
    drivers: dict = field(default_factory=dict)   # driver topic -> DriverTopic

    @property
    def contract_topics(self) -> tuple[str, ...]:
        return tuple(dict.fromkeys(c.contract_topic for c in self.channels))

    def on_topic(self, topic: str) -> tuple[ChannelSpec, ...]:
        return tuple(c for c in self.channels if c.contract_topic == topic)

    def block_samples(self, topic: str) -> int:
        return max(1, int(round(self.block_s * self.rates_hz[topic])))

    def to_dict(self) -> dict:
        return {"source": self.source, "block_s": self.block_s, "gravity_mps2": self.gravity_mps2,
                "rates_hz": dict(self.rates_hz),
                "channels": {c.name: {"contract_topic": c.contract_topic, "topic": c.driver_topic,
                                      "type": c.msg_type, "field": c.field, "index": c.index, "unit": c.unit,
                                      "si_unit": c.si_unit, "factor": c.factor, "sign": c.sign,
                                      "remove_gravity": c.remove_gravity} for c in self.channels},
                "stamps": {d.topic: d.stamp_source for d in self.drivers.values()}}


def load_metadata_file(path) -> Metadata:
    """The recording's metadata from a YAML or JSON file (the same reader as ``import``)."""
    return metadata_from_file(path)


def load_mapping(path, metadata: Metadata) -> DaqMapping:
    path = Path(path)
    return mapping_from_dict(load_yaml(path, "mapping file"), metadata, str(path))


def _number(x) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


def _metadata_rate(md: Metadata, topic: str) -> float | None:
    entry = (md.raw.get("acquisition") or {}).get(topic)
    if not isinstance(entry, dict) or entry.get("sample_rate_hz") is None:
        return None
    r = entry["sample_rate_hz"]
    if not _number(r) or r <= 0:
        raise UserError(f"{md.source}: metadata key acquisition.{topic}.sample_rate_hz: expected a rate "
                        f"> 0 [Hz], got {r!r}")
    return float(r)


def mapping_from_dict(doc, md: Metadata, source: str) -> DaqMapping:
    """Validate a mapping document against the recording's metadata."""
    def fail(key: str, what: str) -> UserError:
        return UserError(f"{source}: mapping key {key}: {what}")

    if not isinstance(doc, dict):
        raise UserError(f"{source}: the mapping must be a YAML mapping with 'channels', got "
                        f"{type(doc).__name__}")
    for k in doc:
        if k not in _TOP_KEYS:
            raise fail(str(k), f"unknown key (expected {', '.join(sorted(_TOP_KEYS))})")
    block_s = doc.get("block_s", DEFAULT_BLOCK_S)
    if not _number(block_s) or not 0 < block_s <= 60:
        raise fail("block_s", f"expected a block length in seconds, > 0 and <= 60, got {block_s!r}")
    gravity = doc.get("gravity_mps2", STANDARD_GRAVITY_MPS2)
    if not _number(gravity) or not 9.7 < gravity < 9.9:
        raise fail("gravity_mps2", f"expected the local gravity (9.7-9.9 m/s^2), got {gravity!r}")
    chans = doc.get("channels")
    if not isinstance(chans, dict) or not chans:
        raise fail("channels", "expected a mapping of contract channel -> {topic, type, field or index, unit}")
    sensors = md.sensors
    specs: list[ChannelSpec] = []
    for name, c in chans.items():
        key = f"channels.{name}"
        if not isinstance(c, dict):
            raise fail(key, "expected a mapping {topic, type, field or index, unit}")
        for k in c:
            if k not in _CHANNEL_KEYS:
                raise fail(f"{key}.{k}", f"unknown key (expected {', '.join(sorted(_CHANNEL_KEYS))})")
        if name in POSITION_CHANNEL_UNITS:
            ctopic = TOPIC_VEHICLE_POSITION
        elif name in sensors:
            ctopic = sensors[name].topic
            if ctopic not in DATA_TOPICS:
                raise fail(key, f"the metadata puts sensor {name} on {ctopic}, not a contract data topic")
        else:
            raise fail(key, f"{name!r} is not a sensor of the metadata {md.source} (sensors: "
                            f"{', '.join(sensors)}) nor position_m / speed_mps")
        topic = c.get("topic")
        if not isinstance(topic, str) or not topic.strip("/"):
            raise fail(f"{key}.topic", f"expected the driver's topic name, got {topic!r}")
        topic = "/" + topic.lstrip("/")
        mtype = c.get("type")
        if mtype not in DRIVER_TYPES:
            raise fail(f"{key}.type", f"expected one of {', '.join(DRIVER_TYPES)}, got {mtype!r}")
        has_header, fields = DRIVER_TYPES[mtype]
        fld, idx = c.get("field"), c.get("index")
        if fields is None:
            if fld is not None:
                raise fail(f"{key}.field", f"{mtype} has no fields to pick: give index (the element of data)")
            if not isinstance(idx, int) or isinstance(idx, bool) or idx < 0:
                raise fail(f"{key}.index", f"expected the 0-based element of data of {mtype}, got {idx!r}")
        else:
            if idx is not None:
                raise fail(f"{key}.index", f"only for std_msgs/msg/Float64MultiArray; {mtype} takes field")
            fld = fld if fld is not None else _DEFAULT_FIELD.get(mtype)
            if fld not in fields:
                raise fail(f"{key}.field", f"expected a numeric field of {mtype} ({', '.join(fields)}), got {fld!r}")
        want = expected_unit(ctopic, name)
        unit = c.get("unit", want)
        if unit is None:
            raise fail(f"{key}.unit", f"missing (no default unit on {ctopic})")
        conv = unit_conversion(str(unit))
        if conv is None:
            raise fail(f"{key}.unit", f"unit {unit!r} is not in the contract's unit table")
        if want is not None and conv[0] != want:
            raise fail(f"{key}.unit", f"unit {unit!r} measures in {conv[0]!r}; {ctopic} [{name}] expects {want!r}")
        sign = c.get("sign", 1)
        if sign not in (1, -1) or isinstance(sign, bool):
            raise fail(f"{key}.sign", f"expected 1 or -1 (-1: the sensor's axis points down), got {sign!r}")
        grav = c.get("remove_gravity", False)
        if not isinstance(grav, bool):
            raise fail(f"{key}.remove_gravity", f"expected true or false, got {grav!r}")
        if grav and conv[0] != "m/s^2":
            raise fail(f"{key}.remove_gravity", f"only for an acceleration channel, {name} is in {conv[0]}")
        sidx = c.get("stamp_index")
        if sidx is not None and (mtype != "std_msgs/msg/Float64MultiArray" or not isinstance(sidx, int)
                                 or isinstance(sidx, bool) or sidx < 0):
            raise fail(f"{key}.stamp_index", "expected the 0-based element of a Float64MultiArray's data "
                                             f"holding the sample time [s], got {sidx!r} on {mtype}")
        if sidx is not None and sidx == idx:
            raise fail(f"{key}.index", f"element {idx} is the stamp (stamp_index)")
        specs.append(ChannelSpec(str(name), ctopic, topic, mtype, None if fields is None else fld,
                                 idx, str(unit), conv[0], float(conv[1]), float(sign), grav, sidx))

    # one driver topic: one type and one stamp source
    drivers: dict[str, DriverTopic] = {}
    for s in specs:
        sidx = s.stamp_index
        d = drivers.get(s.driver_topic)
        if d is None:
            drivers[s.driver_topic] = DriverTopic(s.driver_topic, s.msg_type, DRIVER_TYPES[s.msg_type][0], sidx, (s,))
            continue
        if d.msg_type != s.msg_type:
            raise fail(f"channels.{s.name}.type", f"{s.driver_topic} is {d.msg_type} for "
                                                  f"{d.channels[0].name}, not {s.msg_type}")
        if sidx is not None and d.stamp_index is not None and sidx != d.stamp_index:
            raise fail(f"channels.{s.name}.stamp_index", f"{s.driver_topic} has its stamp in element "
                                                         f"{d.stamp_index} for {d.channels[0].name}")
        drivers[s.driver_topic] = DriverTopic(d.topic, d.msg_type, d.has_header,
                                              d.stamp_index if d.stamp_index is not None else sidx,
                                              d.channels + (s,))
    # contract order: topics as DATA_TOPICS, channels as the metadata lists them
    order = {name: i for i, name in enumerate(list(sensors) + list(POSITION_CHANNEL_UNITS))}
    specs.sort(key=lambda s: (DATA_TOPICS.index(s.contract_topic), order[s.name]))

    rates_doc = doc.get("rates_hz") or {}
    if not isinstance(rates_doc, dict):
        raise fail("rates_hz", "expected a mapping of contract topic -> sample rate [Hz]")
    used = {s.contract_topic for s in specs}
    for t, r in rates_doc.items():
        if t not in used:
            raise fail(f"rates_hz.{t}", f"no channel of the mapping goes to {t} (topics: {', '.join(sorted(used))})")
        if not _number(r) or r <= 0:
            raise fail(f"rates_hz.{t}", f"expected a sample rate > 0 [Hz], got {r!r}")
    rates = {}
    for t in sorted(used, key=DATA_TOPICS.index):
        stated, meta = rates_doc.get(t), _metadata_rate(md, t)
        if stated is not None and meta is not None and abs(stated - meta) > 1e-9 * meta:
            raise fail(f"rates_hz.{t}", f"{stated} Hz, but the metadata {md.source} says "
                                        f"acquisition.{t}.sample_rate_hz {meta} Hz")
        rate = stated if stated is not None else meta
        if rate is None:
            raise fail(f"rates_hz.{t}", f"missing: state the sample rate of {t} here or in the metadata "
                                        f"as acquisition.{t}.sample_rate_hz")
        rates[t] = float(rate)
    return DaqMapping(source, float(block_s), float(gravity), rates, tuple(specs), drivers)
