"""The mapped fields of a driver message read straight from its CDR bytes (no rclpy).

Deserialising a whole ``sensor_msgs/Imu`` into an rclpy object costs tens of microseconds (it builds
three 9-element covariance arrays); the adapter needs one double and the stamp. At 18 k messages/s
that is the adapter's budget, so it subscribes raw and reads the fields at their CDR offsets
(little-endian XCDR1, as ROS 2's rmw write it; offsets aligned relative to the payload after the
4-byte encapsulation header). Anything else (big-endian, a short buffer) raises ValueError and the
node falls back to rclpy's deserialisation. Checked against rosbags' serialiser in the tests.
"""
from __future__ import annotations

import struct
from typing import Callable

__all__ = ["field_reader", "CDR_LE"]

CDR_LE = b"\x00\x01"
_I32U32 = struct.Struct("<iI")
_U32 = struct.Struct("<I")
_F64 = struct.Struct("<d")
_F32 = struct.Struct("<f")


def _a8(p: int) -> int:
    return (p + 7) & ~7


def _a4(p: int) -> int:
    return (p + 3) & ~3


def _after_string(buf, p: int) -> int:
    """Offset (payload-relative) after the CDR string starting (unaligned) at ``p``."""
    p = _a4(p)
    (n,) = _U32.unpack_from(buf, 4 + p)
    return p + 4 + n


# offsets of numeric fields relative to the first 8-aligned offset after the header's frame_id
_IMU = {}
for _i, _a in enumerate("xyzw"):
    _IMU[f"orientation.{_a}"] = 8 * _i
for _i, _a in enumerate("xyz"):
    _IMU[f"angular_velocity.{_a}"] = 32 + 72 + 8 * _i
    _IMU[f"linear_acceleration.{_a}"] = 32 + 72 + 24 + 72 + 8 * _i
_ODOM = {}
for _i, _a in enumerate("xyz"):
    _ODOM[f"pose.pose.position.{_a}"] = 8 * _i
    _ODOM[f"twist.twist.linear.{_a}"] = 24 + 32 + 288 + 8 * _i
    _ODOM[f"twist.twist.angular.{_a}"] = 24 + 32 + 288 + 24 + 8 * _i


def field_reader(msg_type: str, fields, stamp_index: int | None = None) -> Callable:
    """``read(buf) -> (stamp_ns or None, [values])`` for ``fields`` (dotted names, or element
    indices of a Float64MultiArray) of ``msg_type``; ``stamp_index``: a Float64MultiArray element
    holding the sample time [s] (taken to the microsecond). ValueError/struct.error when the bytes
    are not a little-endian message of that type."""
    fields = list(fields)

    def check(buf):
        if bytes(buf[:2]) != CDR_LE:
            raise ValueError("not little-endian CDR")

    def header(buf):
        check(buf)
        sec, nsec = _I32U32.unpack_from(buf, 4)
        return sec * 1_000_000_000 + nsec, _after_string(buf, 8)

    if msg_type == "sensor_msgs/msg/Imu":
        offs = [_IMU[f] for f in fields]

        def read(buf):
            stamp, p = header(buf)
            base = 4 + _a8(p)
            return stamp, [_F64.unpack_from(buf, base + o)[0] for o in offs]
    elif msg_type == "sensor_msgs/msg/Range":
        if fields != ["range"] * len(fields):
            raise ValueError(f"{msg_type}: only range is read")

        def read(buf):
            stamp, p = header(buf)
            # radiation_type (uint8), then float32 field_of_view, min_range, max_range, range
            v = _F32.unpack_from(buf, 4 + _a4(p + 1) + 12)[0]
            return stamp, [v] * len(fields)
    elif msg_type == "nav_msgs/msg/Odometry":
        offs = [_ODOM[f] for f in fields]

        def read(buf):
            stamp, p = header(buf)
            base = 4 + _a8(_after_string(buf, p))          # after child_frame_id
            return stamp, [_F64.unpack_from(buf, base + o)[0] for o in offs]
    elif msg_type == "std_msgs/msg/Float64":
        def read(buf):
            check(buf)
            v = _F64.unpack_from(buf, 4)[0]
            return None, [v] * len(fields)
    elif msg_type == "std_msgs/msg/Float64MultiArray":
        idx = [int(f) for f in fields]

        def read(buf):
            check(buf)
            (ndim,) = _U32.unpack_from(buf, 4)
            p = 4
            for _ in range(ndim):                   # MultiArrayDimension: label, size, stride
                p = _a4(_after_string(buf, p)) + 8
            p = _a4(p) + 4                          # data_offset
            (n,) = _U32.unpack_from(buf, 4 + p)
            base = 4 + _a8(p + 4)
            if len(buf) < base + 8 * n:
                raise ValueError("short data")
            vals = [_F64.unpack_from(buf, base + 8 * i)[0] if i < n else _missing(i, n) for i in idx]
            stamp = None
            if stamp_index is not None:
                if stamp_index >= n:
                    _missing(stamp_index, n)
                stamp = int(round(_F64.unpack_from(buf, base + 8 * stamp_index)[0] * 1e6)) * 1000
            return stamp, vals
    else:
        raise ValueError(f"no CDR reader for {msg_type}")
    return read


def _missing(i: int, n: int):
    raise IndexError(f"element {i} of a {n}-element data")
