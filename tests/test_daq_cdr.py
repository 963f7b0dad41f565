"""The adapter's CDR field reader (daq_stream/cdr.py) against rosbags' serialiser: every supported
type, frame ids of every length mod 8 (alignment), multi-array layouts with dimensions; big-endian
bytes and short arrays are refused (the node then deserialises with rclpy)."""
import numpy as np
import pytest
from rosbags.typesys import Stores, get_typestore

from maglev_ros.daq_stream.cdr import field_reader

TS = get_typestore(Stores.ROS2_HUMBLE)
T = TS.types


def _header(frame, stamp_ns):
    sec, nsec = divmod(stamp_ns, 1_000_000_000)
    return T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec), frame_id=frame)


def _v3(x, y, z):
    return T["geometry_msgs/msg/Vector3"](x=x, y=y, z=z)


def _ser(msg, typename, little=True):
    if little:
        return bytes(TS.serialize_cdr(msg, typename))
    return bytes(TS.serialize_cdr(msg, typename, little_endian=False))


STAMP = 1_700_000_123_456_789_012


@pytest.mark.parametrize("frame", ["", "a", "ab", "abc", "abcd", "abcde", "abcdef", "abcdefg"])
def test_imu_range_odometry_fields_at_any_frame_id_length(frame):
    imu = T["sensor_msgs/msg/Imu"](
        header=_header(frame, STAMP), orientation=T["geometry_msgs/msg/Quaternion"](x=0.1, y=0.2, z=0.3, w=0.4),
        orientation_covariance=np.arange(9.0), angular_velocity=_v3(1.5, 2.5, 3.5),
        angular_velocity_covariance=np.arange(9.0) + 10, linear_acceleration=_v3(-0.25, 0.125, 9.80665),
        linear_acceleration_covariance=np.arange(9.0) + 20)
    fields = ["linear_acceleration.z", "linear_acceleration.x", "angular_velocity.y", "orientation.w"]
    stamp, vals = field_reader("sensor_msgs/msg/Imu", fields)(_ser(imu, "sensor_msgs/msg/Imu"))
    assert stamp == STAMP and vals == [9.80665, -0.25, 2.5, 0.4]

    rng = T["sensor_msgs/msg/Range"](header=_header(frame, STAMP), radiation_type=1, field_of_view=0.01,
                                     min_range=0.0, max_range=0.05, range=0.0123)
    stamp, vals = field_reader("sensor_msgs/msg/Range", ["range"])(_ser(rng, "sensor_msgs/msg/Range"))
    assert stamp == STAMP and vals == [np.float32(0.0123)]

    P = T["geometry_msgs/msg/Point"]
    pose = T["geometry_msgs/msg/PoseWithCovariance"](
        pose=T["geometry_msgs/msg/Pose"](position=P(x=123.25, y=-1.0, z=2.0),
                                         orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0)),
        covariance=np.arange(36.0))
    twist = T["geometry_msgs/msg/TwistWithCovariance"](
        twist=T["geometry_msgs/msg/Twist"](linear=_v3(6.944, 0.5, -0.5), angular=_v3(0.01, 0.02, 0.03)),
        covariance=np.arange(36.0) + 100)
    for child in ("", "veh", "vehicle"):
        odom = T["nav_msgs/msg/Odometry"](header=_header(frame, STAMP), child_frame_id=child, pose=pose, twist=twist)
        stamp, vals = field_reader("nav_msgs/msg/Odometry", ["pose.pose.position.x", "twist.twist.linear.x",
                                                             "twist.twist.angular.z", "pose.pose.position.z"])(
            _ser(odom, "nav_msgs/msg/Odometry"))
        assert stamp == STAMP and vals == [123.25, 6.944, 0.03, 2.0]


@pytest.mark.parametrize("labels", [[], ["x"], ["channels", "samples"], ["abc", "", "defgh"]])
def test_float64_multiarray_elements_and_stamp(labels):
    D = T["std_msgs/msg/MultiArrayDimension"]
    layout = T["std_msgs/msg/MultiArrayLayout"](dim=[D(label=lab, size=3, stride=1) for lab in labels], data_offset=0)
    data = np.array([1700000002.0055, 1.5, -2.25, 3.125])
    msg = T["std_msgs/msg/Float64MultiArray"](layout=layout, data=data)
    buf = _ser(msg, "std_msgs/msg/Float64MultiArray")
    stamp, vals = field_reader("std_msgs/msg/Float64MultiArray", [3, 1], stamp_index=0)(buf)
    assert vals == [3.125, 1.5] and stamp == 1700000002005500000
    with pytest.raises(IndexError):
        field_reader("std_msgs/msg/Float64MultiArray", [4])(buf)
    stamp, vals = field_reader("std_msgs/msg/Float64", ["data"])(_ser(T["std_msgs/msg/Float64"](data=-7.5),
                                                                       "std_msgs/msg/Float64"))
    assert stamp is None and vals == [-7.5]


def test_big_endian_bytes_are_refused():
    msg = T["std_msgs/msg/Float64"](data=1.0)
    with pytest.raises(ValueError):
        field_reader("std_msgs/msg/Float64", ["data"])(_ser(msg, "std_msgs/msg/Float64", little=False))
