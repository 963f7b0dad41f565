"""The DAQ adapter's core without ROS: mapping file checks, gravity (REP 145), units, stamps,
gaps -> NaN, ordering, late/duplicate/off-grid samples, the rate check. Driver messages are
plain attribute objects (``daq_stream.sim.plain_message``); references are analytic."""
import json
import random

import numpy as np
import pytest
import yaml

from bagfactory import make_metadata
from maglev_ros.contract import metadata_from_dict
from maglev_ros.daq_stream.batcher import BlockBatcher
from maglev_ros.daq_stream.mapping import load_mapping, load_metadata_file, mapping_from_dict
from maglev_ros.daq_stream.sim import plain_message as pm
from maglev_ros.errors import UserError

GA, VA, GAP, POS = ("/testline/guideway/accel", "/testline/vehicle/accel", "/testline/vehicle/gap",
                    "/testline/vehicle/position")
G0 = 9.80665            # standard gravity, the definition of the unit g
RATE = 1000.0
T0 = 1_700_000_000_000_000_000


def _metadata(rates=None):
    doc = make_metadata({GA: (("G1", "G2"),), VA: (("M1A", "M2A"),), GAP: (("M1G",),),
                         POS: (("position_m", "speed_mps"),)})
    if rates:
        doc["acquisition"] = {t: {"sample_rate_hz": r} for t, r in rates.items()}
    return metadata_from_dict(doc, "meta.yaml")


MAPPING = {
    "block_s": 0.01,
    "rates_hz": {GA: RATE, VA: RATE, GAP: RATE, POS: 100.0},
    "channels": {
        "G1": {"topic": "/daq/gw", "type": "std_msgs/msg/Float64MultiArray", "index": 1, "unit": "g", "stamp_index": 0},
        "G2": {"topic": "/daq/gw", "type": "std_msgs/msg/Float64MultiArray", "index": 2, "unit": "mg"},
        "M1A": {"topic": "/daq/imu1", "type": "sensor_msgs/msg/Imu", "field": "linear_acceleration.z",
                "remove_gravity": True},
        "M2A": {"topic": "/daq/imu2", "type": "sensor_msgs/msg/Imu", "field": "linear_acceleration.z",
                "remove_gravity": True, "sign": -1},
        "M1G": {"topic": "/daq/gap1", "type": "sensor_msgs/msg/Range", "unit": "mm"},
        "position_m": {"topic": "/daq/odom", "type": "nav_msgs/msg/Odometry", "field": "pose.pose.position.x"},
        "speed_mps": {"topic": "/daq/odom", "type": "nav_msgs/msg/Odometry", "field": "twist.twist.linear.x",
                      "unit": "km/h"},
    },
}


def _mapping(doc=None, md=None):
    return mapping_from_dict(json.loads(json.dumps(doc or MAPPING)), md or _metadata(), "map.yaml")


def _stamp(k, rate=RATE):
    return T0 + int(round(k * 1e9 / rate))


def _vehicle_messages(n):
    """Per sample k: (driver topic, message) of every 1 kHz driver; true SI values alongside."""
    t = np.arange(n) / RATE
    a1, a2 = 0.5 * np.sin(2 * np.pi * 7 * t), 0.3 * np.cos(2 * np.pi * 3 * t)
    gap = 0.010 + 1e-4 * np.sin(2 * np.pi * 2 * t)
    g1, g2 = 0.02 * np.sin(2 * np.pi * 11 * t), 0.05 * np.cos(2 * np.pi * 5 * t)
    msgs = []
    for k in range(n):
        st = _stamp(k)
        msgs.append([("/daq/gw", pm("std_msgs/msg/Float64MultiArray", st, [st * 1e-9, g1[k] / G0, g2[k] / (G0 * 1e-3)])),
                     ("/daq/imu1", pm("sensor_msgs/msg/Imu", st, [a1[k] + G0])),        # upright: +g at rest
                     ("/daq/imu2", pm("sensor_msgs/msg/Imu", st, [-(a2[k] + G0)])),     # mounted z down
                     ("/daq/gap1", pm("sensor_msgs/msg/Range", st, [gap[k] * 1e3]))])
    return msgs, {GA: np.column_stack([g1, g2]), VA: np.column_stack([a1, a2]), GAP: gap.reshape(-1, 1)}


def _collect(out):
    by = {}
    for topic, blk in out:
        by.setdefault(topic, []).append(blk)
    return by


def _stack(blocks):
    return np.concatenate([b.data for b in blocks]), np.concatenate(
        [b.stamp_ns + np.round(np.arange(b.n_samples) * 1e9 / b.sample_rate_hz).astype(np.int64) for b in blocks])


def test_gravity_units_and_stamps():
    b = BlockBatcher(_mapping())
    msgs, truth = _vehicle_messages(50)
    out = [x for per in msgs for topic, m in per for x in b.add_message(topic, m)]
    by = _collect(out)
    for topic in (GA, VA, GAP):
        blocks = by[topic]
        assert [blk.n_samples for blk in blocks] == [10] * 5           # 0.01 s at 1 kHz
        assert all(blk.stamp_ns == _stamp(10 * i) for i, blk in enumerate(blocks))   # first sample's stamp
        data, stamps = _stack(blocks)
        np.testing.assert_array_equal(stamps, [_stamp(k) for k in range(50)])
        np.testing.assert_allclose(data, truth[topic], atol=2e-6 * np.abs(truth[topic]).max())
    assert by[VA][0].channels == ("M1A", "M2A") and by[VA][0].units == ("m/s^2", "m/s^2")
    assert by[GAP][0].units == ("m",) and by[GA][0].units == ("m/s^2", "m/s^2")
    st = b.stats()
    assert st.total("samples") == 50 * 5 and st.total("missing") == st.total("late") == 0
    assert all(t.stamp_rate_hz == pytest.approx(RATE) and not t.rate_mismatch for t in st.topics if t.topic != POS)


def test_a_resting_upright_imu_reads_plus_g_and_gives_zero():
    doc = {"block_s": 0.01, "rates_hz": {VA: RATE}, "channels": {"M1A": MAPPING["channels"]["M1A"]}}
    b = BlockBatcher(_mapping(doc))
    out = [x for k in range(10) for x in b.add_message("/daq/imu1", pm("sensor_msgs/msg/Imu", _stamp(k), [G0]))]
    [(topic, blk)] = out
    assert topic == VA and np.all(blk.data == 0.0)


def test_odometry_position_and_speed_in_si_at_their_own_rate():
    b = BlockBatcher(_mapping({**MAPPING, "block_s": 0.1}))
    out = []
    for k in range(3):
        st = _stamp(k, 100.0)
        out += b.add_message("/daq/odom", pm("nav_msgs/msg/Odometry", st, [5.0 + 0.1 * k, 36.0]))
    out += b.flush()
    [(topic, blk)] = out
    assert topic == POS and blk.channels == ("position_m", "speed_mps") and blk.units == ("m", "m/s")
    assert blk.sample_rate_hz == 100.0 and blk.n_samples == 3       # flush: the open block cut after its last sample
    np.testing.assert_allclose(blk.data[:, 0], [5.0, 5.1, 5.2], rtol=1e-7)
    np.testing.assert_allclose(blk.data[:, 1], 10.0, rtol=1e-7)      # 36 km/h


def test_channels_of_a_topic_aligned_by_stamp_whatever_the_arrival_order():
    msgs, truth = _vehicle_messages(40)
    flat = [x for per in msgs for x in per]
    a = BlockBatcher(_mapping())
    ref = _collect([x for topic, m in flat for x in a.add_message(topic, m)] + a.flush())
    rng = random.Random(3)
    # DDS keeps each driver topic's order but interleaves the topics arbitrarily: merge them at random
    queues = {t: [x for x in flat if x[0] == t] for t in dict.fromkeys(t for t, _ in flat)}
    shuffled = []
    while any(queues.values()):
        t = rng.choice([t for t, q in queues.items() if q])
        n = rng.randint(1, 7)
        shuffled += queues[t][:n]
        del queues[t][:n]
    assert shuffled != flat and sorted(map(id, shuffled)) == sorted(map(id, flat))
    b = BlockBatcher(_mapping())
    got = _collect([x for topic, m in shuffled for x in b.add_message(topic, m)] + b.flush())
    for topic in ref:      # the same samples at the same stamps (block boundaries follow the first arrival)
        (d1, s1), (d2, s2) = _stack(got[topic]), _stack(ref[topic])
        np.testing.assert_array_equal(s1, s2)
        np.testing.assert_array_equal(d1, d2)
        assert got[topic][0].channels == ref[topic][0].channels
    st = b.stats()
    assert st.total("missing") == st.total("late") == st.total("duplicate") == 0


def test_a_dropped_sample_is_nan_at_its_slot_never_shifted():
    doc = {"block_s": 0.01, "rates_hz": {VA: RATE},
           "channels": {c: MAPPING["channels"][c] for c in ("M1A", "M2A")}}
    b = BlockBatcher(_mapping(doc))
    dropped = {3, 4, 15}
    out = []
    for k in range(20):
        out += b.add_message("/daq/imu2", pm("sensor_msgs/msg/Imu", _stamp(k), [-(k + G0)]))
        if k not in dropped:
            out += b.add_message("/daq/imu1", pm("sensor_msgs/msg/Imu", _stamp(k), [k + G0]))
    data, stamps = _stack([blk for _, blk in out])
    assert len(data) == 20
    m1 = data[:, 0]
    assert np.isnan(m1[sorted(dropped)]).all()
    keep = [k for k in range(20) if k not in dropped]
    np.testing.assert_allclose(m1[keep], keep, atol=1e-5)          # every other sample at its own slot
    np.testing.assert_allclose(data[:, 1], np.arange(20), atol=1e-5)
    [c1, c2] = b.stats().topics[0].channels
    assert (c1.missing, c1.gaps, c1.gap_samples) == (3, 2, 3) and c2.missing == 0


def test_late_duplicate_and_lagging_channel():
    doc = {"block_s": 0.01, "rates_hz": {VA: RATE},
           "channels": {c: MAPPING["channels"][c] for c in ("M1A", "M2A")}}
    b = BlockBatcher(_mapping(doc), max_wait_s=0.02)
    wall = {"s": 0.0}
    imu1 = lambda k, v=0.0: b.add_message("/daq/imu1", pm("sensor_msgs/msg/Imu", _stamp(k), [v + G0]),  # noqa: E731
                                          now_s=wall["s"])
    imu2 = lambda k: b.add_message("/daq/imu2", pm("sensor_msgs/msg/Imu", _stamp(k), [-G0]), now_s=wall["s"])  # noqa: E731
    out = []
    for k in range(10):
        out += imu1(k) + imu2(k)
    assert len(out) == 1                                  # both channels reached the block's end
    out += imu1(5, 99.0)                                  # late: its block is out
    for k in range(10, 20):
        out += imu2(k)                                    # imu1 falls silent
    out += imu1(12) + imu1(12, 7.0)                       # a sample and its duplicate
    assert len(out) == 1                                  # block 1 waits for imu1 ...
    for k in range(20, 41):
        out += imu2(k)
    assert len(out) == 1 and b.poll(now_s=0.019) == []   # ... imu2 is max_wait_s past its end (stream) ...
    out += b.poll(now_s=0.02)
    assert len(out) == 2                                  # ... and it waited max_wait_s (wall)
    blk = out[1][1]
    assert np.isnan(blk.data[:, 0]).sum() == 9 and blk.data[2, 0] == 0.0 and not np.isnan(blk.data[:, 1]).any()
    [c1, c2] = b.stats().topics[0].channels
    assert (c1.late, c1.duplicate, c1.missing) == (1, 1, 9) and c2.missing == 0


def test_stamps_off_the_stated_rate_are_reported():
    doc = {"block_s": 0.01, "rates_hz": {VA: RATE}, "channels": {"M1A": MAPPING["channels"]["M1A"]}}
    b = BlockBatcher(_mapping(doc))
    for k in range(100):       # the sensor really samples at 1020 Hz
        b.add_message("/daq/imu1", pm("sensor_msgs/msg/Imu", T0 + int(round(k * 1e9 / 1020.0)), [G0]))
    [t] = b.stats().topics
    assert t.stamp_rate_hz == pytest.approx(1020.0, rel=1e-6) and t.rate_mismatch
    assert t.channels[0].off_grid > 0


def test_a_block_without_any_sample_is_skipped_and_the_next_keeps_its_stamp():
    doc = {"block_s": 0.01, "rates_hz": {VA: RATE}, "channels": {"M1A": MAPPING["channels"]["M1A"]}}
    b = BlockBatcher(_mapping(doc))
    out = []
    for k in list(range(10)) + list(range(30, 40)):           # a pause of two blocks
        out += b.add_message("/daq/imu1", pm("sensor_msgs/msg/Imu", _stamp(k), [G0]))
    assert [blk.stamp_ns for _, blk in out] == [_stamp(0), _stamp(30)]
    assert b.stats().topics[0].empty_blocks == 2


def test_float64_without_a_stamp_takes_the_receive_time():
    doc = {"block_s": 0.1, "rates_hz": {POS: 100.0},
           "channels": {"position_m": {"topic": "/daq/pos", "type": "std_msgs/msg/Float64", "unit": "km"}}}
    m = _mapping(doc)
    assert m.drivers["/daq/pos"].stamp_source == "receive"
    b = BlockBatcher(m)
    for k in range(3):
        b.add_message("/daq/pos", pm("std_msgs/msg/Float64", 0, [1.0 + k]), recv_ns=_stamp(k, 100.0) + 1000)
    [(_, blk)] = b.flush()
    assert blk.stamp_ns == _stamp(0, 100.0) + 1000
    np.testing.assert_allclose(blk.data[:, 0], [1000.0, 2000.0, 3000.0])


def test_malformed_message_is_counted():
    b = BlockBatcher(_mapping())
    assert b.add_message("/daq/gw", pm("std_msgs/msg/Float64MultiArray", 0, [1.0])) == []   # too short
    assert b.stats().malformed["/daq/gw"] == 1


def _bad(path, value):
    doc = json.loads(json.dumps(MAPPING))
    node = doc
    keys = path.split(".")
    for k in keys[:-1]:
        node = node[k]
    if value is KeyError:
        del node[keys[-1]]
    else:
        node[keys[-1]] = value
    return doc


@pytest.mark.parametrize("doc, key", [
    (_bad("channels.X9", {"topic": "/a", "type": "std_msgs/msg/Float64"}), "channels.X9"),
    (_bad("channels.M1G.type", "sensor_msgs/msg/LaserScan"), "channels.M1G.type"),
    (_bad("channels.M1A.field", "linear_acceleration.q"), "channels.M1A.field"),
    (_bad("channels.M1G.unit", "g"), "channels.M1G.unit"),
    (_bad("channels.M1G.unit", "furlong"), "channels.M1G.unit"),
    (_bad("channels.M1G.remove_gravity", True), "channels.M1G.remove_gravity"),
    (_bad("channels.M1A.stamp_index", 0), "channels.M1A.stamp_index"),
    (_bad("channels.G1.index", KeyError), "channels.G1.index"),
    (_bad("channels.M2A.sign", 2), "channels.M2A.sign"),
    (_bad("channels.M1A.colour", "red"), "channels.M1A.colour"),
    (_bad("rates_hz", {GA: RATE, VA: RATE, GAP: RATE}), f"rates_hz.{POS}"),
    (_bad("block_s", 0), "block_s"),
])
def test_mapping_mistakes_are_one_line_naming_file_and_key(doc, key):
    with pytest.raises(UserError) as err:
        _mapping(doc)
    msg = str(err.value)
    assert msg.startswith(f"map.yaml: mapping key {key}:") and "\n" not in msg, msg


def test_rates_from_the_metadata_and_a_conflict(tmp_path):
    rates = {GA: RATE, VA: RATE, GAP: RATE, POS: 100.0}
    doc = json.loads(json.dumps(MAPPING))
    del doc["rates_hz"]
    assert _mapping(doc, _metadata(rates)).rates_hz == rates
    with pytest.raises(UserError, match=rf"^map.yaml: mapping key rates_hz.{VA}: 1000.0 Hz, but the metadata"):
        _mapping(MAPPING, _metadata({**rates, VA: 2000.0}))
    # files: YAML mapping, metadata as YAML (the contract's document)
    (tmp_path / "m.yaml").write_text(yaml.safe_dump(MAPPING))
    (tmp_path / "meta.yaml").write_text(yaml.safe_dump(_metadata().to_dict()))
    m = load_mapping(tmp_path / "m.yaml", load_metadata_file(tmp_path / "meta.yaml"))
    assert m.source == str(tmp_path / "m.yaml") and len(m.channels) == 7
    with pytest.raises(UserError, match=r"mapping file not found"):
        load_mapping(tmp_path / "none.yaml", _metadata())


def test_shipped_mapping_is_the_simulators_for_the_sample_pass(tmp_path):
    from pathlib import Path

    from maglev_ros.daq_stream.sim import source_from_bag, write_config
    root = Path(__file__).resolve().parents[1]
    meta, mapping = write_config(source_from_bag(root / "bags" / "paper_pass", 0.0, 0.05), tmp_path)
    shipped = root / "maglev_ros" / "config" / "daq_mapping_paper_pass.yaml"
    assert yaml.safe_load(shipped.read_text()) == yaml.safe_load(mapping.read_text())
    md = load_metadata_file(meta)
    assert md.raw["acquisition"]["/testline/vehicle/position"]["sample_rate_hz"] == 200.0
    m = load_mapping(shipped, md)
    assert len(m.channels) == 21 and len(m.drivers) == 10
