"""The test-line recording contract, version 1 (docs/contract/RECORDING.md).

Topic names, the metadata JSON (``/testline/metadata``) parsed and validated into a
:class:`Metadata`, unit checks, and the :class:`Issue` record that contract checks report.

Validation is hand-written rather than done with a JSON-schema library: the contract asks for
one-line errors that name the bag and the exact key path, which generic validators do not give.
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from typing import Any, Mapping

from maglev_ros.errors import ContractError

__all__ = [
    "CONTRACT_SCHEMA", "TOPIC_METADATA", "TOPIC_GUIDEWAY_ACCEL", "TOPIC_GUIDEWAY_DISP",
    "TOPIC_VEHICLE_ACCEL", "TOPIC_VEHICLE_GAP", "TOPIC_VEHICLE_POSITION", "TOPIC_BODY_ACCEL", "DATA_TOPICS",
    "SENSORBLOCK_TYPE", "STRING_TYPE", "SI_UNITS", "NON_SI_UNITS", "TOPIC_UNITS",
    "Span", "Sensor", "Metadata", "Issue", "parse_metadata", "metadata_from_dict", "metadata_issues",
    "unit_conversion", "is_si_unit", "check_units", "expected_unit", "UnitConversion", "si_factor",
    "to_si_units",
]

CONTRACT_SCHEMA = "maglev-testline/1"

TOPIC_METADATA = "/testline/metadata"
TOPIC_GUIDEWAY_ACCEL = "/testline/guideway/accel"
TOPIC_GUIDEWAY_DISP = "/testline/guideway/displacement"
TOPIC_VEHICLE_ACCEL = "/testline/vehicle/accel"
TOPIC_VEHICLE_GAP = "/testline/vehicle/gap"
TOPIC_VEHICLE_POSITION = "/testline/vehicle/position"
#: optional extension (docs/contract-extensions.md): car-body vertical accelerations, each sensor
#: entry with ``body_x_m`` (x of the point relative to the vehicle reference point)
TOPIC_BODY_ACCEL = "/testline/vehicle/body_accel"
DATA_TOPICS = (TOPIC_GUIDEWAY_ACCEL, TOPIC_GUIDEWAY_DISP, TOPIC_VEHICLE_ACCEL,
               TOPIC_VEHICLE_GAP, TOPIC_VEHICLE_POSITION, TOPIC_BODY_ACCEL)

SENSORBLOCK_TYPE = "maglev_msgs/msg/SensorBlock"
STRING_TYPE = "std_msgs/msg/String"

#: Unit strings accepted as SI (base or coherent derived units, "1" for dimensionless).
SI_UNITS = frozenset({
    "m/s^2", "m", "m/s", "rad", "rad/s", "rad/s^2", "s", "Hz", "N", "Pa", "A", "V", "T",
    "kg", "K", "W", "N/m", "1",
})

#: Common non-SI unit strings: unit -> (SI unit, factor); value_si = value * factor.
NON_SI_UNITS: dict[str, tuple[str, float]] = {
    "g": ("m/s^2", 9.80665),
    "mg": ("m/s^2", 9.80665e-3),
    "mm/s^2": ("m/s^2", 1e-3),
    "cm/s^2": ("m/s^2", 1e-2),
    # spellings DAQ exports use for SI units themselves (maglev-ros import states the rename)
    "m/s2": ("m/s^2", 1.0),
    "m/s²": ("m/s^2", 1.0),
    "m/s/s": ("m/s^2", 1.0),
    "mm/s2": ("m/s^2", 1e-3),
    "mm/s²": ("m/s^2", 1e-3),
    "cm/s2": ("m/s^2", 1e-2),
    "cm/s²": ("m/s^2", 1e-2),
    "gal": ("m/s^2", 1e-2),
    "ft/s^2": ("m/s^2", 0.3048),
    "mm": ("m", 1e-3),
    "cm": ("m", 1e-2),
    "um": ("m", 1e-6),
    "µm": ("m", 1e-6),
    "μm": ("m", 1e-6),   # Greek mu (U+03BC), beside the micro sign above
    "km": ("m", 1e3),
    "in": ("m", 0.0254),
    "ft": ("m", 0.3048),
    "mm/s": ("m/s", 1e-3),
    "cm/s": ("m/s", 1e-2),
    "km/h": ("m/s", 1.0 / 3.6),
    "kmh": ("m/s", 1.0 / 3.6),
    "kph": ("m/s", 1.0 / 3.6),
    "mph": ("m/s", 0.44704),
    "deg": ("rad", math.pi / 180.0),
    "kN": ("N", 1e3),
    "kPa": ("Pa", 1e3),
    "MPa": ("Pa", 1e6),
    "mA": ("A", 1e-3),
    "ms": ("s", 1e-3),
    "kHz": ("Hz", 1e3),
}

#: SI unit the contract expects on each data topic (position: per channel).
TOPIC_UNITS: dict[str, str] = {
    TOPIC_GUIDEWAY_ACCEL: "m/s^2",
    TOPIC_GUIDEWAY_DISP: "m",
    TOPIC_VEHICLE_ACCEL: "m/s^2",
    TOPIC_VEHICLE_GAP: "m",
    TOPIC_BODY_ACCEL: "m/s^2",
}
POSITION_CHANNEL_UNITS = {"position_m": "m", "speed_mps": "m/s"}

_SIDES = ("left", "right", "center")
_DIRECTIONS = ("vertical", "lateral")
_RUN_KINDS = ("pass", "ambient")


@dataclass(frozen=True)
class Issue:
    """One contract problem found in a bag.

    severity: "error" (the data cannot be trusted as is) or "warning".
    time_s: stream time where it happens (header stamp, seconds), or None.
    kind: short machine-readable name (e.g. "gap", "nan", "non_si_unit").
    """

    severity: str
    topic: str | None
    channel: str | None
    time_s: float | None
    kind: str
    message: str

    def to_dict(self) -> dict:
        return {"severity": self.severity, "topic": self.topic, "channel": self.channel,
                "time_s": self.time_s, "kind": self.kind, "message": self.message}

    def __str__(self) -> str:
        where = self.topic or ""
        if self.channel:
            where += f" [{self.channel}]"
        at = "" if self.time_s is None else f" at t={self.time_s:.6f} s"
        return f"{self.severity}: {self.kind}: {where}{at}: {self.message}"


@dataclass(frozen=True)
class Span:
    """One guideway span of ``line.spans``; ``extra`` holds any other keys (e.g. design overrides)."""

    id: str
    start_m: float
    length_m: float
    extra: Mapping[str, Any] = field(default_factory=dict)

    @property
    def end_m(self) -> float:
        return self.start_m + self.length_m


@dataclass(frozen=True)
class Sensor:
    """One entry of ``sensors``: the channel id and where it is."""

    id: str
    topic: str
    quantity: str | None = None
    direction: str | None = None
    span: str | None = None
    position_m: float | None = None
    side: str | None = None
    magnet: int | None = None
    raw: Mapping[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class Metadata:
    """Validated metadata of a recording. ``raw`` is the whole JSON document (unknown keys kept)."""

    raw: Mapping[str, Any]
    source: str = "<metadata>"

    @property
    def schema(self) -> str:
        return self.raw["schema"]

    @property
    def description(self) -> str:
        return str(self.raw.get("description", ""))

    @property
    def spans(self) -> tuple[Span, ...]:
        out = []
        for s in self.raw["line"]["spans"]:
            extra = {k: v for k, v in s.items() if k not in ("id", "start_m", "length_m")}
            out.append(Span(str(s["id"]), float(s["start_m"]), float(s["length_m"]), extra))
        return tuple(out)

    @property
    def sensors(self) -> dict[str, Sensor]:
        out = {}
        for sid, s in self.raw["sensors"].items():
            out[sid] = Sensor(
                id=sid, topic=s["topic"], quantity=s.get("quantity"),
                direction=s.get("direction"), span=s.get("span"),
                position_m=None if s.get("position_m") is None else float(s["position_m"]),
                side=s.get("side"),
                magnet=None if s.get("magnet") is None else int(s["magnet"]), raw=s)
        return out

    def sensors_on_topic(self, topic: str) -> dict[str, Sensor]:
        """Sensors recorded on ``topic``, in metadata order (id -> Sensor)."""
        return {k: v for k, v in self.sensors.items() if v.topic == topic}

    @property
    def vehicle(self) -> dict:
        return dict(self.raw.get("vehicle") or {})

    @property
    def magnet_offsets_m(self) -> tuple[float, ...]:
        return tuple(float(x) for x in self.vehicle.get("magnet_offsets_m", ()))

    @property
    def nominal_gap_m(self) -> float | None:
        g = self.vehicle.get("nominal_gap_m")
        return None if g is None else float(g)

    @property
    def run(self) -> dict:
        return dict(self.raw["run"])

    @property
    def run_kind(self) -> str:
        return self.raw["run"]["kind"]

    @property
    def nominal_speed_mps(self) -> float | None:
        v = self.raw["run"].get("nominal_speed_mps")
        return None if v is None else float(v)

    @property
    def design(self) -> dict | None:
        d = self.raw.get("design")
        return None if d is None else dict(d)

    def acquisition_delay_s(self, topic: str) -> float:
        """Delay of a topic's samples behind their stamps from the acquisition chain [s].

        Optional extension of the contract (docs/contract-extensions.md): ``acquisition:
        {topic: {"delay_s": d}}`` says that the sample stamped t describes the physics at
        t - d (e.g. the group delay of a causal anti-alias filter). 0 when not given.
        """
        entry = (self.raw.get("acquisition") or {}).get(topic) or {}
        d = entry.get("delay_s", 0.0) if isinstance(entry, dict) else 0.0
        if isinstance(d, bool) or not isinstance(d, (int, float)) or not math.isfinite(d) or d < 0:
            raise ContractError(f"{self.source}: metadata key acquisition.{topic}.delay_s: "
                                f"expected a non-negative number of seconds, got {d!r}")
        return float(d)

    def to_dict(self) -> dict:
        return json.loads(json.dumps(self.raw))

    def to_json(self) -> str:
        return json.dumps(self.raw, sort_keys=False)


def _is_number(x: Any) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


def metadata_from_dict(doc: Any, source: str) -> Metadata:
    """Validate a metadata document (already parsed JSON) and wrap it in :class:`Metadata`.

    Raises ContractError "<source>: metadata key <path>: <what is wrong>" on the first problem.
    """
    def fail(path: str, what: str) -> ContractError:
        return ContractError(f"{source}: metadata key {path}: {what}")

    def need(obj: Mapping, key: str, path: str) -> Any:
        if key not in obj:
            raise fail(path, "missing (required by the recording contract)")
        return obj[key]

    if not isinstance(doc, dict):
        raise ContractError(f"{source}: metadata must be a JSON object, got {type(doc).__name__}")
    schema = need(doc, "schema", "schema")
    if schema != CONTRACT_SCHEMA:
        raise fail("schema", f"expected {CONTRACT_SCHEMA!r}, got {schema!r}")
    line = need(doc, "line", "line.spans")
    if not isinstance(line, dict):
        raise fail("line", "expected an object")
    spans = need(line, "spans", "line.spans")
    if not isinstance(spans, list):
        raise fail("line.spans", "expected a list of spans")
    span_ids = set()
    for i, s in enumerate(spans):
        p = f"line.spans[{i}]"
        if not isinstance(s, dict):
            raise fail(p, "expected an object")
        sid = need(s, "id", f"{p}.id")
        if not isinstance(sid, str) or not sid:
            raise fail(f"{p}.id", f"expected a non-empty string, got {sid!r}")
        span_ids.add(sid)
        for key in ("start_m", "length_m"):
            v = need(s, key, f"{p}.{key}")
            if not _is_number(v):
                raise fail(f"{p}.{key}", f"expected a finite number, got {v!r}")
        if s["length_m"] <= 0:
            raise fail(f"{p}.length_m", f"expected > 0, got {s['length_m']!r}")

    sensors = need(doc, "sensors", "sensors")
    if not isinstance(sensors, dict):
        raise fail("sensors", "expected an object mapping channel id -> sensor")
    for sid, s in sensors.items():
        p = f"sensors.{sid}"
        if not isinstance(s, dict):
            raise fail(p, "expected an object")
        topic = need(s, "topic", f"{p}.topic")
        if not isinstance(topic, str) or not topic.startswith("/"):
            raise fail(f"{p}.topic", f"expected a topic name, got {topic!r}")
        if s.get("position_m") is not None and not _is_number(s["position_m"]):
            raise fail(f"{p}.position_m", f"expected a finite number, got {s['position_m']!r}")
        if s.get("side") is not None and s["side"] not in _SIDES:
            raise fail(f"{p}.side", f"expected one of {', '.join(_SIDES)}, got {s['side']!r}")
        if s.get("direction") is not None and s["direction"] not in _DIRECTIONS:
            raise fail(f"{p}.direction",
                       f"expected one of {', '.join(_DIRECTIONS)}, got {s['direction']!r}")
        mag = s.get("magnet")
        if mag is not None and (not isinstance(mag, int) or isinstance(mag, bool) or mag < 1):
            raise fail(f"{p}.magnet", f"expected a 1-based magnet number, got {mag!r}")
        if topic == TOPIC_BODY_ACCEL and not _is_number(s.get("body_x_m")):
            raise fail(f"{p}.body_x_m", "expected the x of the car-body point relative to the vehicle "
                       f"reference point [m] (a finite number) for a sensor on {TOPIC_BODY_ACCEL}, "
                       f"got {s.get('body_x_m')!r}")

    run = need(doc, "run", "run.kind")
    if not isinstance(run, dict):
        raise fail("run", "expected an object")
    kind = need(run, "kind", "run.kind")
    if kind not in _RUN_KINDS:
        raise fail("run.kind", f"expected one of {', '.join(_RUN_KINDS)}, got {kind!r}")
    if run.get("nominal_speed_mps") is not None and not _is_number(run["nominal_speed_mps"]):
        raise fail("run.nominal_speed_mps", f"expected a number, got {run['nominal_speed_mps']!r}")

    vehicle = doc.get("vehicle")
    if vehicle is not None and not isinstance(vehicle, dict):
        raise fail("vehicle", "expected an object")
    if kind == "pass":
        if vehicle is None:
            raise fail("vehicle.magnet_offsets_m", "missing (required for run.kind 'pass')")
        offs = need(vehicle, "magnet_offsets_m", "vehicle.magnet_offsets_m")
        if not isinstance(offs, list) or not offs or not all(_is_number(x) for x in offs):
            raise fail("vehicle.magnet_offsets_m", f"expected a non-empty list of numbers, got {offs!r}")
        for sid, s in sensors.items():
            mag = s.get("magnet")
            if mag is not None and mag > len(offs):
                raise fail(f"sensors.{sid}.magnet",
                           f"magnet {mag} but vehicle.magnet_offsets_m lists {len(offs)} magnets")
    if vehicle is not None and vehicle.get("nominal_gap_m") is not None:
        g = vehicle["nominal_gap_m"]
        if not _is_number(g) or g <= 0:
            raise fail("vehicle.nominal_gap_m", f"expected a positive number, got {g!r}")
    design = doc.get("design")
    if design is not None and not isinstance(design, dict):
        raise fail("design", "expected an object")
    return Metadata(raw=doc, source=source)


def metadata_issues(md: Metadata) -> list[Issue]:
    """Soft problems of valid metadata (warnings, not errors): a sensor's ``span`` that is not
    listed in ``line.spans`` (the contract's own example does this), a guideway sensor whose
    ``position_m`` lies outside its span."""
    issues = []
    spans = {s.id: s for s in md.spans}
    for sid, s in md.sensors.items():
        if s.span is None:
            continue
        sp = spans.get(s.span)
        if sp is None:
            issues.append(Issue("warning", s.topic, sid, None, "unknown_span",
                                f"metadata key sensors.{sid}.span: span {s.span!r} is not listed "
                                f"in line.spans ({', '.join(spans) or 'none'})"))
        elif s.position_m is not None and not (sp.start_m - 1e-9 <= s.position_m <= sp.end_m + 1e-9):
            issues.append(Issue("warning", s.topic, sid, None, "position_outside_span",
                                f"metadata key sensors.{sid}.position_m: {s.position_m} m is outside "
                                f"span {sp.id} [{sp.start_m}, {sp.end_m}] m"))
    return issues


def parse_metadata(text: str | bytes, source: str) -> Metadata:
    """Parse the metadata JSON text of a recording; ``source`` names the bag in errors."""
    if isinstance(text, bytes):
        text = text.decode("utf-8", errors="replace")
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as exc:
        raise ContractError(f"{source}: metadata is not valid JSON ({exc.msg} at line {exc.lineno} "
                            f"column {exc.colno})") from None
    except RecursionError:
        # the contract's document is a few levels deep; a hostile or broken one must not crash us
        raise ContractError(f"{source}: metadata is nested too deeply to be the contract's document "
                            f"(expected a few levels of objects)") from None
    return metadata_from_dict(doc, source)


# ----------------------------------------------------------------------------------- units
def is_si_unit(unit: str) -> bool:
    return unit in SI_UNITS


def unit_conversion(unit: str) -> tuple[str, float] | None:
    """(SI unit, factor) for a known non-SI unit string, None when unknown (or already SI)."""
    if unit in SI_UNITS:
        return unit, 1.0
    return NON_SI_UNITS.get(unit)


def expected_unit(topic: str, channel: str) -> str | None:
    """The SI unit the contract prescribes for ``channel`` on ``topic`` (None: no rule)."""
    if topic == TOPIC_VEHICLE_POSITION:
        return POSITION_CHANNEL_UNITS.get(channel)
    return TOPIC_UNITS.get(topic)


def check_units(topic: str, channels: tuple[str, ...] | list[str],
                units: tuple[str, ...] | list[str], time_s: float | None = None) -> list[Issue]:
    """Unit problems of one block's channel list: non-SI strings and units wrong for the topic."""
    issues = []
    for ch, u in zip(channels, units):
        if u not in SI_UNITS:
            conv = NON_SI_UNITS.get(u)
            if conv is not None:
                msg = (f"unit {u!r} is not SI; expected {conv[0]!r} "
                       f"(multiply by {conv[1]:.9g} to convert)")
            else:
                msg = f"unit {u!r} is not a known SI unit string (accepted: {', '.join(sorted(SI_UNITS))})"
            issues.append(Issue("warning", topic, ch, time_s, "non_si_unit", msg))
            continue
        want = expected_unit(topic, ch)
        if want is not None and u != want:
            issues.append(Issue("warning", topic, ch, time_s, "unit_mismatch",
                                f"unit {u!r} but the contract expects {want!r} on this topic"))
    return issues


@dataclass(frozen=True)
class UnitConversion:
    """One channel's recorded unit and how it becomes SI: value_si = value * factor."""

    topic: str
    channel: str
    unit: str
    si_unit: str
    factor: float

    def to_dict(self) -> dict:
        return {"topic": self.topic, "channel": self.channel, "unit": self.unit,
                "si_unit": self.si_unit, "factor": self.factor}


def si_factor(topic: str, channel: str, unit: str) -> tuple[str, float] | None:
    """(SI unit, factor) of ``channel`` on ``topic`` by the unit table, None when the unit is
    unknown or its SI unit is not the one the contract prescribes for the topic."""
    conv = unit_conversion(unit)
    if conv is None:
        return None
    want = expected_unit(topic, channel)
    return None if want is not None and conv[0] != want else conv


def to_si_units(topic: str, channels, units, where: str = "") -> tuple[
        tuple[str, ...], tuple[float, ...], tuple[UnitConversion, ...]]:
    """SI units, the factor per channel and the conversions made, for one channel list.

    The one conversion every reader of recordings uses (verbs through the health check, nodes
    per block). Raises ContractError naming topic, channel and unit for a unit the table does
    not know or one of the wrong kind for the topic (e.g. 'mm' on an acceleration topic).
    """
    si, factors, done = [], [], []
    for ch, u in zip(channels, units):
        conv = unit_conversion(u)
        if conv is None:
            raise ContractError(f"{where}{topic} [{ch}]: unit {u!r} is not in the contract's unit "
                                f"table (SI: {', '.join(sorted(SI_UNITS))}; convertible: "
                                f"{', '.join(NON_SI_UNITS)})")
        want = expected_unit(topic, ch)
        if want is not None and conv[0] != want:
            raise ContractError(f"{where}{topic} [{ch}]: unit {u!r} measures in {conv[0]!r}; the "
                                f"contract expects {want!r} on this topic")
        si.append(conv[0])
        factors.append(float(conv[1]))
        if u != conv[0]:
            done.append(UnitConversion(topic, ch, u, conv[0], float(conv[1])))
    return tuple(si), tuple(factors), tuple(done)
