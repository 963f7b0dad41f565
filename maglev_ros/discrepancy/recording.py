"""Recordings as the discrepancy core sees them: channels grouped, vehicle position, metadata.

``Recording`` is built from a contract bag (:func:`load_recording`) or in memory (tests, the
online node). Channel groups: ``guideway_accel``, ``guideway_disp``, ``vehicle_accel``, ``gap``
and, where the recording has the optional car-body topic (docs/contract-extensions.md),
``body_accel``.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import PurePath
from typing import Any, Mapping

import numpy as np

from maglev_ros.errors import ContractError, UserError

GROUPS = ("guideway_accel", "guideway_disp", "vehicle_accel", "gap", "body_accel")
TOPIC_GROUP = {
    "/testline/guideway/accel": "guideway_accel",
    "/testline/guideway/displacement": "guideway_disp",
    "/testline/vehicle/accel": "vehicle_accel",
    "/testline/vehicle/gap": "gap",
    "/testline/vehicle/body_accel": "body_accel",
}
GROUP_UNIT = {"guideway_accel": "m/s^2", "guideway_disp": "m", "vehicle_accel": "m/s^2", "gap": "m",
              "body_accel": "m/s^2"}


@dataclass(frozen=True, eq=False)
class Channel:
    """One measured channel: ``group``, sample times, values and where it is."""
    name: str
    group: str
    time_s: np.ndarray
    values: np.ndarray
    sample_rate_hz: float
    position_m: float | None = None      # guideway sensors
    magnet: int | None = None            # vehicle sensors (1-based)
    body_x_m: float | None = None        # car-body sensors: x relative to the vehicle reference point

    @property
    def on_vehicle(self) -> bool:
        return self.group in ("vehicle_accel", "gap", "body_accel")


@dataclass(frozen=True, eq=False)
class Recording:
    metadata: Mapping
    channels: Mapping[str, Channel]
    kind: str = "pass"                    # "pass" or "ambient"
    position_time_s: np.ndarray | None = None
    position_m: np.ndarray | None = None
    speed_mps: np.ndarray | None = None
    source: str = "<memory>"
    # guideway irregularity driving the twin on this pass (reconstructed from the pass itself,
    # see :mod:`.irregularity`): (x_m, r_m) arrays, the stretch where it is valid [m] and the
    # delay of the sensor samples behind their stamps (the twin's output is delayed alike)
    irregularity: tuple | None = None
    irregularity_valid_m: tuple[float, float] | None = None
    irregularity_margin_m: float = 0.0
    sensor_delay_s: float = 0.0
    irregularity_info: Mapping | None = None
    health: Any = None                    # maglev_ros.health.HealthReport of the bag it was read from

    @property
    def name(self) -> str:
        """The recording as reports name it: the bag's own name, never the machine path it was read from."""
        return PurePath(self.source).name or self.source

    @property
    def t0_s(self) -> float:
        return float(min(c.time_s[0] for c in self.channels.values()))

    @property
    def t1_s(self) -> float:
        return float(max(c.time_s[-1] for c in self.channels.values()))

    def position_at(self, t_s) -> np.ndarray | None:
        if self.position_time_s is None:
            return None
        return np.interp(t_s, self.position_time_s, self.position_m)

    def names(self, group: str | None = None) -> list[str]:
        return [n for n, c in self.channels.items() if group is None or c.group == group]


def recording_from_arrays(metadata: Mapping, signals: Mapping[str, tuple[np.ndarray, np.ndarray]],
                          position: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
                          source: str = "<memory>") -> Recording:
    """Build a Recording from the metadata and name -> (time_s, values) arrays; sensor entries of
    the metadata give each channel its topic (group), position or magnet."""
    sensors = metadata.get("sensors", {})
    chans = {}
    for name, (t, v) in signals.items():
        s = sensors.get(name)
        if s is None:
            raise ContractError(f"{source}: sensors.{name}: channel has no sensor entry in the metadata")
        group = TOPIC_GROUP.get(s.get("topic", ""))
        if group is None:
            continue
        t = np.asarray(t, dtype=float)
        v = np.asarray(v, dtype=float)
        rate = float(1.0 / np.median(np.diff(t))) if t.size > 1 else 0.0
        chans[name] = Channel(name, group, t, v, rate,
                              None if s.get("position_m") is None else float(s["position_m"]),
                              None if s.get("magnet") is None else int(s["magnet"]),
                              None if s.get("body_x_m") is None else float(s["body_x_m"]))
    if not chans:
        raise ContractError(f"{source}: no guideway/vehicle SensorBlock channels found")
    kind = str((metadata.get("run") or {}).get("kind", "pass"))
    if position is not None:
        pt, px, pv = (np.asarray(a, dtype=float) for a in position)
    else:
        pt = px = pv = None
    return Recording(metadata, chans, kind, pt, px, pv, source)


def load_recording(path) -> Recording:
    """Read a contract bag into a Recording (all sensor topics, position if present)."""
    from maglev_ros.bag_reader import BagReader
    with BagReader(path) as bag:
        md = dict(bag.metadata.raw)
        signals = {}
        position = None
        # the sensor-health check: SI units, bad channels left out where safe, else one error
        read, health = bag.read_checked([t for t in bag.topics if t in TOPIC_GROUP
                                         or t == "/testline/vehicle/position"], sensor_map=True)
        for topic, cd in read.items():
            if topic in TOPIC_GROUP:
                for i, ch in enumerate(cd.channels):
                    signals[ch] = (cd.time_s, cd.data[:, i])
            else:
                if "position_m" not in cd.channels:
                    raise ContractError(f"{path}: /testline/vehicle/position: channel 'position_m' missing")
                pos = cd.channel("position_m")
                spd = cd.channel("speed_mps") if "speed_mps" in cd.channels else np.gradient(pos, cd.time_s)
                position = (cd.time_s, pos, spd)
    rec = recording_from_arrays(md, signals, position, source=str(path))
    if rec.kind == "pass" and rec.position_time_s is None:
        raise ContractError(f"{path}: /testline/vehicle/position: a pass recording needs the vehicle position")
    return replace(rec, health=health)


def require_pass(rec: Recording, what: str = "--pass") -> None:
    if rec.kind != "pass":
        raise UserError(f"{rec.source}: run.kind: expected 'pass' for {what}, got {rec.kind!r}")
