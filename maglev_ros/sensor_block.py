"""One SensorBlock as numpy (:class:`Block`), the suite's .msg texts, and a rosbags typestore.

The typestore is rosbags' ROS 2 Humble store with every ``maglev_msgs`` type registered from
its .msg text, so bags are read and written without rclpy (the science core never imports it).

:class:`SensorBlockDecoder` is a hand-written little-endian CDR decoder for SensorBlock only:
rosbags' generic decoder re-decodes the channel/unit strings of every message, which dominates
read time; ours reuses them when their bytes repeat. It is used only when the bag's SensorBlock
definition equals ours, is checked against rosbags in the tests, and falls back to rosbags.
"""
from __future__ import annotations

import functools
import math
import os
import struct
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from maglev_ros.contract import SENSORBLOCK_TYPE, STRING_TYPE
from maglev_ros.errors import ContractError, UserError

__all__ = ["Block", "MSG_PACKAGE", "MSG_NAMES", "msg_dir", "msg_text", "typestore",
           "msgtype_name", "block_to_msg", "msg_to_block", "string_msg", "make_header",
           "serialize", "deserialize", "SENSORBLOCK_TYPE", "STRING_TYPE", "SensorBlockDecoder",
           "DecodedBlock", "BLOCK_FAULT_KINDS", "MAX_RATE_HZ", "block_fault", "StreamCheck"]

MSG_PACKAGE = "maglev_msgs"
# Order matters for registration only through dependencies (ModalMode before ModalEstimate).
MSG_NAMES = ("SensorBlock", "ModalMode", "ModalEstimate", "IrregularityProfile",
             "TwinParameters", "MismatchReport")


@dataclass(frozen=True, eq=False)
class Block:
    """One SensorBlock: ``data`` is (n_samples, n_channels) float32, row-major like the message.

    ``stamp_ns`` is the header stamp (acquisition time of the first sample) in nanoseconds.
    """

    stamp_ns: int
    frame_id: str
    sample_rate_hz: float
    channels: tuple[str, ...]
    units: tuple[str, ...]
    data: np.ndarray

    @property
    def n_samples(self) -> int:
        return int(self.data.shape[0])

    @property
    def stamp_s(self) -> float:
        return self.stamp_ns * 1e-9

    @property
    def duration_s(self) -> float:
        """Time covered by the block: n_samples / rate (the next block should start here)."""
        return self.n_samples / self.sample_rate_hz if self.sample_rate_hz > 0 else 0.0

    @property
    def end_ns(self) -> int:
        """Expected stamp of the following block [ns]."""
        return self.stamp_ns + int(round(self.duration_s * 1e9))

    def times_s(self) -> np.ndarray:
        """Sample times [s]: stamp + i / rate."""
        return self.stamp_ns * 1e-9 + np.arange(self.n_samples) / self.sample_rate_hz

    def channel(self, name: str) -> np.ndarray:
        try:
            return self.data[:, self.channels.index(name)]
        except ValueError:
            raise UserError(f"block has no channel {name!r} (channels: {', '.join(self.channels)})") from None

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Block):
            return NotImplemented
        return (self.stamp_ns == other.stamp_ns and self.frame_id == other.frame_id
                and self.sample_rate_hz == other.sample_rate_hz and self.channels == other.channels
                and self.units == other.units and self.data.shape == other.data.shape
                and np.array_equal(self.data, other.data, equal_nan=True))

    __hash__ = None  # type: ignore[assignment]

    @classmethod
    def from_arrays(cls, stamp_ns: int, sample_rate_hz: float, channels, units, data,
                    frame_id: str = "") -> "Block":
        """Build a block, checking shapes; ``data`` is (n_samples, n_channels), cast to float32."""
        arr = np.ascontiguousarray(np.asarray(data, dtype=np.float32))
        if arr.ndim == 1 and len(channels) == 1:
            arr = arr.reshape(-1, 1)
        channels, units = tuple(channels), tuple(units)
        if arr.ndim != 2 or arr.shape[1] != len(channels):
            raise UserError(f"block data shape {arr.shape} does not match {len(channels)} channels")
        if len(units) != len(channels):
            raise UserError(f"block has {len(channels)} channels but {len(units)} units")
        if not sample_rate_hz > 0:
            raise UserError(f"block sample_rate_hz must be > 0, got {sample_rate_hz!r}")
        return cls(int(stamp_ns), frame_id, float(sample_rate_hz), channels, units, arr)



# ------------------------------------------------------------------------- block validation
# data_length, units_mismatch and bad_rate as BagReader.check names the same issues in a bag
BLOCK_FAULT_KINDS = ("no_channels", "data_length", "units_mismatch", "bad_rate", "empty", "layout_changed")
# No contract stream samples near 1 MHz (its fastest are kHz): a larger rate is a corrupted field,
# and a consumer stepping or allocating at it would hang.
MAX_RATE_HZ = 1e6


def block_fault(channels, units, sample_rate_hz, n_values: int) -> tuple[str, str] | None:
    """Why a SensorBlock's fields cannot make a usable :class:`Block`: ``(kind, reason)``, or None.

    ``kind`` is one of :data:`BLOCK_FAULT_KINDS`; ``reason`` is one line naming the field.
    """
    nch = len(channels)
    if nch == 0:
        return "no_channels", "channels is empty"
    if n_values % nch:
        return "data_length", f"data has {n_values} values, not a multiple of {nch} channels"
    if len(units) != nch:
        return "units_mismatch", f"{nch} channels but {len(units)} units"
    rate = float(sample_rate_hz)
    if not (math.isfinite(rate) and 0 < rate <= MAX_RATE_HZ):
        return "bad_rate", f"sample_rate_hz must be in (0, {MAX_RATE_HZ:g}] Hz, got {sample_rate_hz!r}"
    if n_values == 0:
        return "empty", "data holds no samples"
    return None


class StreamCheck:
    """The check of a live stream's blocks, topic by topic: :func:`block_fault`, then the layout.

    The first good block of a topic sets its layout (channels, units, sample rate); a later block
    with another layout is a fault ("layout_changed"): consumers index channels by position and
    step at the topic's rate, so a block that changes them mid-stream would be misread.
    """

    def __init__(self) -> None:
        self.layout: dict[str, tuple] = {}

    def fault(self, topic: str, channels, units, sample_rate_hz, n_values: int) -> tuple[str, str] | None:
        found = block_fault(channels, units, sample_rate_hz, n_values)
        if found is not None:
            return found
        layout = (tuple(channels), tuple(units), float(sample_rate_hz))
        first = self.layout.setdefault(topic, layout)
        if layout != first:
            return "layout_changed", (f"channels {list(layout[0])} [{', '.join(layout[1])}] at {layout[2]:g} Hz "
                                      f"differ from the topic's first block: {list(first[0])} "
                                      f"[{', '.join(first[1])}] at {first[2]:g} Hz")
        return None

    def new_stream(self) -> None:
        """A new recording starts (new metadata): its topics may have another layout."""
        self.layout.clear()


# ------------------------------------------------------------------------------- msg texts
def _candidate_msg_dirs() -> list[Path]:
    dirs = []
    env = os.environ.get("MAGLEV_MSG_DIR")
    if env:
        dirs.append(Path(env))
    here = Path(__file__).resolve().parent
    dirs.append(here / "msg")                              # package data of a wheel (setup.py)
    dirs.append(here.parent / "msg_defs" / "msg")          # source checkout, editable install
    dirs.append(Path(sys.prefix) / "share" / MSG_PACKAGE / "msg")   # maglev_msgs in a venv
    for prefix in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep):
        if prefix:
            dirs.append(Path(prefix) / "share" / MSG_PACKAGE / "msg")
    return dirs


@functools.lru_cache(maxsize=None)
def msg_dir() -> Path:
    """Directory holding the maglev_msgs .msg files (source tree, venv share/ or AMENT prefix)."""
    for d in _candidate_msg_dirs():
        if (d / "SensorBlock.msg").is_file():
            return d
    raise UserError("cannot find the maglev_msgs .msg files (looked in "
                    + ", ".join(str(d) for d in _candidate_msg_dirs())
                    + "); reinstall maglev_ros from its source tree, or set MAGLEV_MSG_DIR "
                    "to a directory holding SensorBlock.msg")


@functools.lru_cache(maxsize=None)
def msg_text(name: str) -> str:
    """The .msg text of ``maglev_msgs/msg/<name>``."""
    return (msg_dir() / f"{name}.msg").read_text()


def msgtype_name(name: str) -> str:
    """'SensorBlock' -> 'maglev_msgs/msg/SensorBlock'."""
    return name if "/" in name else f"{MSG_PACKAGE}/msg/{name}"


@functools.lru_cache(maxsize=None)
def typestore():
    """rosbags typestore: ROS 2 Humble built-ins plus every maglev_msgs type (cached)."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    types = {}
    for name in MSG_NAMES:
        types.update(get_types_from_msg(msg_text(name), msgtype_name(name)))
    store.register(types)
    return store


# ---------------------------------------------------------------------------- conversions
def make_header(stamp_ns: int, frame_id: str = "", store=None):
    store = store or typestore()
    Time = store.types["builtin_interfaces/msg/Time"]
    Header = store.types["std_msgs/msg/Header"]
    sec, nsec = divmod(int(stamp_ns), 1_000_000_000)
    return Header(stamp=Time(sec=sec, nanosec=nsec), frame_id=frame_id)


def block_to_msg(block: Block, store=None):
    """Block -> rosbags SensorBlock message object."""
    store = store or typestore()
    cls = store.types[SENSORBLOCK_TYPE]
    return cls(header=make_header(block.stamp_ns, block.frame_id, store),
               sample_rate_hz=float(block.sample_rate_hz), channels=list(block.channels),
               units=list(block.units),
               data=np.ascontiguousarray(block.data, dtype=np.float32).reshape(-1))


def stamp_ns_of(msg) -> int:
    st = msg.header.stamp
    return st.sec * 1_000_000_000 + st.nanosec


def msg_to_block(msg, where: str = "SensorBlock") -> Block:
    """rosbags SensorBlock message object -> Block (data is a read-only view, no copy).

    Raises ContractError (naming ``where``) when data length is not a multiple of the channel
    count or units do not match channels.
    """
    channels = tuple(msg.channels)
    units = tuple(msg.units)
    nch = len(channels)
    flat = msg.data
    if not isinstance(flat, np.ndarray) or flat.dtype != np.float32:
        flat = np.asarray(flat, dtype=np.float32)
    if nch == 0 or flat.size % nch:
        raise ContractError(f"{where}: data has {flat.size} values, not a multiple of "
                            f"{nch} channels")
    if len(units) != nch:
        raise ContractError(f"{where}: {nch} channels but {len(units)} units")
    st = msg.header.stamp
    return Block(st.sec * 1_000_000_000 + st.nanosec, msg.header.frame_id,
                 float(msg.sample_rate_hz), channels, units, flat.reshape(-1, nch))


def string_msg(text: str, store=None):
    store = store or typestore()
    return store.types[STRING_TYPE](data=text)


def serialize(msg, msgtype: str, store=None) -> bytes:
    store = store or typestore()
    return bytes(store.serialize_cdr(msg, msgtype_name(msgtype)))


def deserialize(raw: bytes, msgtype: str, store=None):
    store = store or typestore()
    return store.deserialize_cdr(raw, msgtype_name(msgtype))


# ------------------------------------------------------------------------ fast CDR decoder
_I32U32 = struct.Struct("<iI")
_U32 = struct.Struct("<I")
_F64 = struct.Struct("<d")


class DecodedBlock:
    """What :class:`SensorBlockDecoder` returns (attribute access like a rosbags message)."""

    __slots__ = ("stamp_ns", "frame_id", "sample_rate_hz", "channels", "units", "data")

    def __init__(self, stamp_ns, frame_id, sample_rate_hz, channels, units, data):
        self.stamp_ns = stamp_ns
        self.frame_id = frame_id
        self.sample_rate_hz = sample_rate_hz
        self.channels = channels
        self.units = units
        self.data = data


class SensorBlockDecoder:
    """Decode little-endian CDR SensorBlock bytes (ROS 2 layout of SensorBlock.msg).

    ``decode(raw)`` returns a :class:`DecodedBlock` (channels/units as tuples, data a read-only
    float32 view on ``raw``) or None when the bytes are not little-endian CDR or do not parse;
    the caller then uses rosbags. Offsets are relative to the payload after the 4-byte
    encapsulation header, as CDR alignment requires.
    """

    def __init__(self) -> None:
        self._pos = -1
        self._region = b""
        self._strings = ((), (), 0)

    def decode(self, raw) -> DecodedBlock | None:
        try:
            return self._decode(raw)
        except (struct.error, UnicodeDecodeError, ValueError, IndexError):
            return None

    @staticmethod
    def _strings_at(raw, pos: int):
        pos = (pos + 3) & ~3
        (n,) = _U32.unpack_from(raw, 4 + pos)
        pos += 4
        out = []
        for _ in range(n):
            pos = (pos + 3) & ~3
            (ln,) = _U32.unpack_from(raw, 4 + pos)
            pos += 4
            if ln < 1 or 4 + pos + ln > len(raw):
                raise ValueError("bad string")
            out.append(raw[4 + pos:4 + pos + ln - 1].decode())
            pos += ln
        return tuple(out), pos

    def _decode(self, raw) -> DecodedBlock | None:
        if len(raw) < 24 or raw[0] != 0 or raw[1] != 1:
            return None
        sec, nsec = _I32U32.unpack_from(raw, 4)
        (flen,) = _U32.unpack_from(raw, 12)
        if flen < 1:
            return None
        frame_id = raw[16:15 + flen].decode()
        pos = (12 + flen + 7) & ~7
        (rate,) = _F64.unpack_from(raw, 4 + pos)
        pos += 8
        if pos == self._pos and raw[4 + pos:4 + self._strings[2]] == self._region:
            channels, units, pos = self._strings
        else:
            start = pos
            channels, pos = self._strings_at(raw, pos)
            units, pos = self._strings_at(raw, pos)
            self._pos = start
            self._region = bytes(raw[4 + start:4 + pos])
            self._strings = (channels, units, pos)
        pos = (pos + 3) & ~3
        (n,) = _U32.unpack_from(raw, 4 + pos)
        pos += 4
        end = 4 + pos + 4 * n
        if end > len(raw) or end + 3 < len(raw):
            return None
        data = np.frombuffer(raw, dtype="<f4", count=n, offset=4 + pos)
        return DecodedBlock(sec * 1_000_000_000 + nsec, frame_id, rate, channels, units, data)


def same_sensorblock_definition(store) -> bool:
    """True when ``store`` defines SensorBlock (and its Header/Time) exactly like ours."""
    ours = typestore().fielddefs
    try:
        return all(store.fielddefs[t] == ours[t] for t in
                   (SENSORBLOCK_TYPE, "std_msgs/msg/Header", "builtin_interfaces/msg/Time"))
    except KeyError:
        return False
