"""BagWriter / BagReader round trips, contract errors, check() issues and read_topic repairs.

References are independent of the reader: the arrays handed to the writers (as float32), the
sample-time formula of the contract (header stamp + i / rate, computed in the test from the
stamps the writer was told to use), and the faults the foreign writer injected.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import tracemalloc
from pathlib import Path

import numpy as np
import pytest

from bagfactory import (CONTRACT_MSG_DIR, GUIDEWAY_ACCEL, VEHICLE_ACCEL, VEHICLE_GAP, VEHICLE_POSITION, Faults,
                        example_topics, expected_times_s, foreign_typestore, make_metadata,
                        write_contract_bag, write_foreign_bag)
from maglev_ros.bag_reader import BagReader, ChannelData
from maglev_ros.bag_writer import BagWriter
from maglev_ros.contract import SENSORBLOCK_TYPE, TOPIC_METADATA
from maglev_ros.errors import ContractError, UserError
from maglev_ros.sensor_block import Block, block_to_msg, msg_text, msg_to_block, typestore

T0_FOREIGN = 1_700_000_000_000_000_000
ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def topics():
    return example_topics(duration_s=1.0, seed=3)


@pytest.fixture(scope="module")
def meta(topics):
    return make_metadata(topics)


def _assert_topics_exact(bag: BagReader, topics: dict, t0_ns: int, block_samples) -> None:
    for topic, (channels, units, rate, data) in topics.items():
        cd = bag.read_topic(topic)
        bs = block_samples[topic] if isinstance(block_samples, dict) else block_samples
        assert cd.channels == tuple(channels) and cd.units == tuple(units)
        assert cd.sample_rate_hz == rate
        assert cd.data.dtype == np.float64
        np.testing.assert_array_equal(cd.data, np.asarray(data, np.float32).astype(np.float64))
        np.testing.assert_array_equal(cd.time_s, expected_times_s(t0_ns, len(data), rate, bs))
        assert cd.issues == ()


# --------------------------------------------------------------------------- round trips
@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_own_writer_round_trip_bit_exact(tmp_path, topics, meta, storage):
    path = write_contract_bag(tmp_path / "bag", meta, topics, block_s=0.1, storage=storage,
                              t0_ns=5_000_000_000)
    with BagReader(path) as bag:
        assert bag.storage == storage
        assert bag.metadata.raw == meta
        bs = {t: int(round(0.1 * spec[2])) for t, spec in topics.items()}
        _assert_topics_exact(bag, topics, 5_000_000_000, bs)
        assert bag.start_time_s == 5.0
        info = bag.topics[GUIDEWAY_ACCEL]
        assert info.count == 10 and info.block_samples == 200 and info.sample_rate_hz == 2000.0
        assert info.channels == ("G1LV", "G2LV", "G3LV")
        assert bag.topics[TOPIC_METADATA].count == 1
        assert bag.check() == []


@pytest.mark.parametrize("storage, name", [("mcap", "bag"), ("sqlite3", "bag"), ("ros1", "bag.bag")])
def test_foreign_writer_round_trip_bit_exact(tmp_path, topics, meta, storage, name):
    sizes = [37, 200, 113]          # irregular block lengths
    path = write_foreign_bag(tmp_path / name, meta, topics, block_samples=sizes, storage=storage,
                             lag_ns=40_000_000, jitter_ns=5_000_000)
    with BagReader(path) as bag:
        assert bag.storage == storage
        assert bag.metadata.raw == meta
        _assert_topics_exact(bag, topics, T0_FOREIGN, sizes)
        # the bag's receive time lags the header stamp, the reader reports header stamps
        assert bag.topics[GUIDEWAY_ACCEL].first_lag_ns >= 40_000_000
        assert bag.start_time_s == T0_FOREIGN * 1e-9
        assert bag.check() == []


def test_iter_blocks_one_per_message_and_block_fields(tmp_path, topics, meta):
    path = write_contract_bag(tmp_path / "bag", meta, topics, block_s=0.05)
    with BagReader(path) as bag:
        seen = {}
        for topic, blk in bag.iter_blocks():
            assert isinstance(blk, Block) and blk.data.dtype == np.float32
            seen.setdefault(topic, []).append(blk)
        for topic, (channels, units, rate, data) in topics.items():
            blocks = seen[topic]
            assert len(blocks) == bag.topics[topic].count
            n = int(round(0.05 * rate))
            for k, blk in enumerate(blocks):
                assert blk.stamp_ns == int(round(k * n * 1e9 / rate))
                assert blk.sample_rate_hz == rate and blk.channels == tuple(channels)
                np.testing.assert_array_equal(blk.data, np.asarray(data[k * n:(k + 1) * n], np.float32))
                np.testing.assert_allclose(blk.times_s(), (k * n + np.arange(n)) / rate, rtol=0,
                                           atol=1e-12)
        only = [t for t, _ in bag.iter_blocks(topics=[VEHICLE_GAP])]
        assert set(only) == {VEHICLE_GAP} and len(only) == 20


def test_windows(tmp_path, topics, meta):
    path = write_foreign_bag(tmp_path / "bag", meta, topics, block_samples=100, lag_ns=200_000_000)
    rate = topics[GUIDEWAY_ACCEL][2]
    with BagReader(path) as bag:
        # blocks of 0.05 s at 2 kHz; window [0.23, 0.43) s overlaps blocks 4..8
        blocks = [b for _, b in bag.iter_blocks(GUIDEWAY_ACCEL, start_s=0.23, duration_s=0.2)]
        assert [round((b.stamp_ns - T0_FOREIGN) / 5e7) for b in blocks] == [4, 5, 6, 7, 8]
        cd = bag.read_topic(GUIDEWAY_ACCEL, start_s=0.23, duration_s=0.2)
        i0, i1 = int(0.23 * rate), int(0.43 * rate)
        np.testing.assert_array_equal(cd.data, topics[GUIDEWAY_ACCEL][3][i0:i1].astype(np.float32))
        assert cd.time_s[0] - T0_FOREIGN * 1e-9 == pytest.approx(0.23, abs=1e-6)
        assert cd.n_samples == i1 - i0
        # a window at the end, open-ended
        tail = bag.read_topic(VEHICLE_GAP, start_s=0.9)
        assert tail.n_samples == 100


def test_iter_raw_gives_cdr_with_header_stamps(tmp_path, topics, meta):
    for storage, name in (("mcap", "a"), ("ros1", "b.bag")):
        path = write_foreign_bag(tmp_path / name, meta, topics, storage=storage, lag_ns=50_000_000)
        ours = typestore()
        with BagReader(path) as bag:
            raws = list(bag.iter_raw())
            blocks = list(bag.iter_blocks())
        assert raws[0][0] == TOPIC_METADATA
        meta_msg = ours.deserialize_cdr(raws[0][3], "std_msgs/msg/String")
        assert json.loads(meta_msg.data) == meta
        sb = [r for r in raws if r[1] == SENSORBLOCK_TYPE]
        assert len(sb) == len(blocks)
        for (topic, _mt, stamp, raw), (btopic, blk) in zip(sb, blocks):
            assert isinstance(raw, bytes) and topic == btopic
            back = msg_to_block(ours.deserialize_cdr(raw, SENSORBLOCK_TYPE))
            assert stamp == blk.stamp_ns == back.stamp_ns
            assert back == blk


def test_iter_raw_window(tmp_path, topics, meta):
    path = write_foreign_bag(tmp_path / "w", meta, topics, block_samples=100, lag_ns=300_000_000)
    with BagReader(path) as bag:
        raws = list(bag.iter_raw(start_s=0.2, duration_s=0.3))
    assert raws[0][0] == TOPIC_METADATA
    rel = [(r[2] - T0_FOREIGN) * 1e-9 for r in raws[1:]]
    assert min(rel) >= 0.2 - 1e-9 and max(rel) < 0.5
    # 100-sample blocks: accel every 0.05 s (2 kHz, 2 topics), gap every 0.1 s, position 1 s
    n_expected = 2 * 6 + 3
    assert len(rel) == n_expected


def test_block_message_conversion_and_msg_text():
    blk = Block.from_arrays(1_234_567_890_123, 500.0, ["a", "b"], ["m", "m/s"],
                            np.arange(10.0).reshape(5, 2), frame_id="vehicle")
    msg = block_to_msg(blk)
    assert msg.header.stamp.sec == 1234 and msg.header.stamp.nanosec == 567_890_123
    assert list(msg.data) == list(range(10))
    assert msg_to_block(msg) == blk
    # our .msg text is the contract's, field for field
    assert msg_text("SensorBlock") == (CONTRACT_MSG_DIR / "SensorBlock.msg").read_text()
    with pytest.raises(UserError, match="2 channels"):
        Block.from_arrays(0, 1.0, ["a", "b"], ["m", "m"], np.zeros((4, 3)))


def test_write_message_other_types(tmp_path, meta):
    store = typestore()
    Mode = store.types["maglev_msgs/msg/ModalMode"]
    Est = store.types["maglev_msgs/msg/ModalEstimate"]
    from maglev_ros.sensor_block import make_header
    est = Est(header=make_header(2_000_000_000), method="ssi-cov", window_s=60.0,
              modes=[Mode(id="M1", status="new", frequency_hz=4.2, damping_ratio=0.02,
                          std_frequency_hz=0.01, std_damping_ratio=0.003, mpc=0.99,
                          channels=["G1LV"], mode_shape=np.array([1.0]))])
    with BagWriter(tmp_path / "b", meta) as w:
        w.write_message("/maglev/modes", "maglev_msgs/msg/ModalEstimate", est, 2_100_000_000)
    with BagReader(tmp_path / "b") as bag:
        assert bag.topics["/maglev/modes"].msgtype == "maglev_msgs/msg/ModalEstimate"
        (raw,) = [r for r in bag.iter_raw() if r[0] == "/maglev/modes"]
    assert raw[2] == 2_000_000_000            # header stamp, not receive time
    back = store.deserialize_cdr(raw[3], "maglev_msgs/msg/ModalEstimate")
    assert back.modes[0].frequency_hz == 4.2 and back.method == "ssi-cov"


# ------------------------------------------------------------------------------ writer
def test_writer_refuses_overwrite_and_is_atomic(tmp_path, topics, meta):
    path = write_contract_bag(tmp_path / "bag", meta, topics)
    with pytest.raises(UserError, match="already exists"):
        write_contract_bag(path, meta, topics)
    # a crash inside the with-block leaves neither a half bag nor temp files
    target = tmp_path / "crash"
    with pytest.raises(RuntimeError):
        with BagWriter(target, meta) as w:
            w.write_block(VEHICLE_GAP, Block.from_arrays(0, 100.0, ["M1G"], ["m"], np.zeros(10)))
            raise RuntimeError("boom")
    assert not target.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bag"]
    # overwrite=True replaces the old bag
    small = {VEHICLE_GAP: topics[VEHICLE_GAP]}
    write_contract_bag(path, make_metadata(small), small, overwrite=True)
    with BagReader(path) as bag:
        assert bag.sensor_topics == [VEHICLE_GAP]


def test_writer_validates_metadata_and_inputs(tmp_path, meta):
    bad = dict(meta)
    del bad["run"]
    with pytest.raises(ContractError, match="run.kind"):
        BagWriter(tmp_path / "x", bad)
    with pytest.raises(UserError, match="storage"):
        BagWriter(tmp_path / "x", meta, storage="zip")
    with BagWriter(tmp_path / "y", meta) as w:
        with pytest.raises(UserError, match="written by BagWriter"):
            w.write_block(TOPIC_METADATA, Block.from_arrays(0, 1.0, ["a"], ["m"], np.zeros(1)))
    assert not (tmp_path / "x").exists()


# ---------------------------------------------------------------------- contract errors
def _one_line_error(excinfo, path) -> str:
    msg = str(excinfo.value)
    assert "\n" not in msg and msg.startswith(str(path))
    return msg


def test_open_errors(tmp_path, topics, meta):
    with pytest.raises(ContractError, match="no such bag") as ei:
        BagReader(tmp_path / "nope").open()
    _one_line_error(ei, tmp_path / "nope")
    txt = tmp_path / "notes.txt"
    txt.write_text("hello")
    with pytest.raises(ContractError, match="not a bag"):
        BagReader(txt).open()
    fake = tmp_path / "fake.mcap"
    fake.write_bytes(b"\x89MCAP0\r\n" + b"\0" * 100)
    with pytest.raises(ContractError, match="cannot open bag"):
        BagReader(fake).open()
    empty = tmp_path / "emptydir"
    empty.mkdir()
    with pytest.raises(ContractError, match="not a bag"):
        BagReader(empty).open()


@pytest.mark.parametrize("storage, name", [("mcap", "bag"), ("sqlite3", "bag"), ("ros1", "x.bag")])
def test_truncated_bag_is_one_line_error(tmp_path, topics, meta, storage, name):
    path = write_foreign_bag(tmp_path / name, meta, topics, storage=storage,
                             faults=Faults(truncate_fraction=0.5))
    with pytest.raises(ContractError) as ei:
        with BagReader(path) as bag:       # may fail on open or while streaming
            bag.check()
            for t in bag.sensor_topics:
                bag.read_topic(t)
    assert "truncated or corrupt" in _one_line_error(ei, path)


def test_missing_metadata_topic(tmp_path, topics, meta):
    path = write_foreign_bag(tmp_path / "b", meta, topics, faults=Faults(no_metadata=True))
    with pytest.raises(ContractError, match="/testline/metadata missing") as ei:
        BagReader(path).open()
    _one_line_error(ei, path)
    with BagReader(path, strict=False) as bag:
        assert bag.metadata is None
        issues = bag.check()
        assert issues[0].kind == "metadata" and issues[0].severity == "error"
        bag.read_topic(GUIDEWAY_ACCEL)            # data still readable


@pytest.mark.parametrize("key", ["schema", "line.spans", "sensors", "run.kind",
                                 "vehicle.magnet_offsets_m"])
def test_missing_metadata_key_in_bag(tmp_path, topics, meta, key):
    path = write_foreign_bag(tmp_path / "b", meta, topics, faults=Faults(missing_metadata_key=key))
    with pytest.raises(ContractError) as ei:
        BagReader(path).open()
    msg = _one_line_error(ei, path)
    assert f"metadata key {key}: missing" in msg


# ------------------------------------------------------------------------ check() kinds
def _kinds(issues):
    return sorted({(i.kind, i.severity) for i in issues})


def test_check_detects_timing_faults(tmp_path, topics, meta):
    faults = Faults(drop={GUIDEWAY_ACCEL: [4]}, duplicate={VEHICLE_ACCEL: [2]},
                    swap={VEHICLE_ACCEL: [6]}, overlap={VEHICLE_GAP: [3]})
    path = write_foreign_bag(tmp_path / "b", meta, topics, block_samples=100, faults=faults,
                             lag_ns=10_000_000)
    with BagReader(path) as bag:
        issues = bag.check()
    by = {(i.topic, i.kind): i for i in issues}
    assert _kinds(issues) == [("duplicate", "warning"), ("gap", "warning"),
                              ("out_of_order", "warning"), ("overlap", "warning")]
    # dropped block 4 of 100 samples at 2 kHz: gap of 0.05 s starting where block 4 began
    gap = by[(GUIDEWAY_ACCEL, "gap")]
    assert gap.time_s == pytest.approx(T0_FOREIGN * 1e-9 + 4 * 0.05, abs=1e-6)
    assert "0.05 s" in gap.message and "~100 samples" in gap.message
    assert by[(VEHICLE_ACCEL, "duplicate")].time_s == pytest.approx(T0_FOREIGN * 1e-9 + 0.1, abs=1e-6)
    assert by[(VEHICLE_ACCEL, "out_of_order")].time_s == pytest.approx(T0_FOREIGN * 1e-9 + 0.3, abs=1e-6)
    # block 3 of the gap topic (100 samples at 1 kHz) stamped half a block early: overlap of
    # 0.05 s at 0.25 s, then a gap of 0.05 s before block 4 at 0.4 s
    ov = by[(VEHICLE_GAP, "overlap")]
    assert ov.time_s == pytest.approx(T0_FOREIGN * 1e-9 + 0.25, abs=1e-6)
    assert "0.05" in ov.message
    assert by[(VEHICLE_GAP, "gap")].time_s == pytest.approx(T0_FOREIGN * 1e-9 + 0.35, abs=1e-6)


def test_check_detects_data_and_unit_faults(tmp_path, topics, meta):
    faults = Faults(nan={VEHICLE_GAP: [(2, 7, 1)]}, inf={GUIDEWAY_ACCEL: [(0, 0, 2), (3, 5, 2)]},
                    units={GUIDEWAY_ACCEL: {"G2LV": "g"}, VEHICLE_POSITION: {"speed_mps": "km/h"}},
                    short_units={VEHICLE_ACCEL: [1]}, extra_channel={VEHICLE_GAP: "M9G"},
                    bad_length={VEHICLE_POSITION: [1]})
    path = write_foreign_bag(tmp_path / "b", meta, topics, block_samples=50, faults=faults)
    with BagReader(path) as bag:
        issues = bag.check()
    by = {(i.topic, i.channel, i.kind): i for i in issues}
    nan = by[(VEHICLE_GAP, "M2G", "nan")]
    assert nan.severity == "error" and nan.time_s == pytest.approx(T0_FOREIGN * 1e-9 + 0.107, abs=1e-6)
    inf = by[(GUIDEWAY_ACCEL, "G3LV", "nan")]
    assert "2 NaN/inf sample(s) in 2 block(s)" in inf.message
    assert inf.time_s == pytest.approx(T0_FOREIGN * 1e-9, abs=1e-6)
    assert "9.80665" in by[(GUIDEWAY_ACCEL, "G2LV", "non_si_unit")].message
    assert (VEHICLE_POSITION, "speed_mps", "non_si_unit") in by
    assert by[(VEHICLE_ACCEL, None, "units_mismatch")].severity == "error"
    assert by[(VEHICLE_GAP, "M9G", "unknown_channel")].severity == "warning"
    assert by[(VEHICLE_POSITION, None, "data_length")].severity == "error"
    # errors are listed first
    sev = [i.severity for i in issues]
    assert sev == sorted(sev, key=lambda s: s != "error")


def test_check_rate_change_channels_changed_missing_channel(tmp_path, meta):
    md = dict(meta)
    with BagWriter(tmp_path / "b", md) as w:
        stamp = 0
        for k in range(6):
            rate = 1000.0 if k < 3 else 500.0
            chans = ("M1G", "M2G") if k != 5 else ("M1G", "M2G", "X")
            w.write_block(VEHICLE_GAP, Block.from_arrays(stamp, rate, chans, ("m",) * len(chans),
                                                         np.zeros((50, len(chans)))))
            stamp += int(50 / rate * 1e9)
        w.write_block(GUIDEWAY_ACCEL, Block.from_arrays(0, 2000.0, ["G1LV"], ["m/s^2"],
                                                        np.zeros((10, 1))))
    with BagReader(tmp_path / "b") as bag:
        issues = bag.check()
        kinds = {(i.topic, i.channel, i.kind) for i in issues}
        assert (VEHICLE_GAP, None, "rate_change") in kinds
        assert (VEHICLE_GAP, None, "channels_changed") in kinds
        assert (VEHICLE_GAP, "X", "unknown_channel") in kinds
        # sensors listed in metadata on a recorded topic but absent from the data
        assert (GUIDEWAY_ACCEL, "G2LV", "missing_channel") in kinds
        assert not any(i.kind in ("gap", "overlap") for i in issues)  # rate change is seamless
        rc = next(i for i in issues if i.kind == "rate_change")
        assert rc.time_s == pytest.approx(0.15) and "1000 Hz to 500 Hz" in rc.message
        # strict read_topic refuses the channel change; non-strict skips that block
        with pytest.raises(ContractError, match="channels/units change"):
            bag.read_topic(VEHICLE_GAP)
    with BagReader(tmp_path / "b", strict=False) as bag:
        cd = bag.read_topic(VEHICLE_GAP)
    assert cd.n_samples == 250
    expect = np.concatenate([np.arange(150) / 1000.0, 0.15 + np.arange(100) / 500.0])
    np.testing.assert_allclose(cd.time_s, expect, rtol=0, atol=1e-12)
    assert {i.kind for i in cd.issues} == {"channels_changed", "rate_change"}


def test_issue_flood_is_capped(tmp_path, topics, meta):
    faults = Faults(drop={GUIDEWAY_ACCEL: list(range(1, 80, 2))})
    path = write_foreign_bag(tmp_path / "b", meta, topics, block_samples=20, faults=faults)
    with BagReader(path) as bag:
        gaps = [i for i in bag.check() if i.kind == "gap"]
    assert len(gaps) == 21 and "20 more" in gaps[-1].message


# -------------------------------------------------------------------- read_topic repairs
def test_read_topic_sorts_and_drops_duplicates(tmp_path, topics, meta):
    faults = Faults(duplicate={GUIDEWAY_ACCEL: [1, 7]}, swap={GUIDEWAY_ACCEL: [3, 12]})
    path = write_foreign_bag(tmp_path / "b", meta, topics, block_samples=100, faults=faults)
    channels, units, rate, data = topics[GUIDEWAY_ACCEL]
    with BagReader(path) as bag:
        cd = bag.read_topic(GUIDEWAY_ACCEL)
    np.testing.assert_array_equal(cd.data, data.astype(np.float32))
    np.testing.assert_array_equal(cd.time_s, expected_times_s(T0_FOREIGN, len(data), rate, 100))
    kinds = [i.kind for i in cd.issues]
    assert kinds.count("duplicate") == 2 and kinds.count("out_of_order") == 1


def test_read_topic_trims_overlap_and_keeps_gap(tmp_path, topics, meta):
    faults = Faults(overlap={VEHICLE_GAP: [3]}, drop={VEHICLE_GAP: [7]})
    path = write_foreign_bag(tmp_path / "b", meta, topics, block_samples=100, faults=faults)
    _, _, rate, data = topics[VEHICLE_GAP]
    with BagReader(path) as bag:
        cd = bag.read_topic(VEHICLE_GAP)
    assert np.all(np.diff(cd.time_s) > 0)
    # overlap: the first 50 samples of block 3 (stamped 50 samples early) fall inside block 2
    # and are dropped; its last 50 land at 0.30..0.35 s; block 7 is missing (a gap, no fill)
    f32 = data.astype(np.float32)
    assert cd.n_samples == 300 + 50 + 300 + 200
    np.testing.assert_array_equal(cd.data[:300], f32[:300])
    np.testing.assert_array_equal(cd.data[300:350], f32[350:400])   # tail of block 3's payload
    np.testing.assert_array_equal(cd.data[350:], f32[np.r_[400:700, 800:1000]])
    t_rel = cd.time_s - T0_FOREIGN * 1e-9
    np.testing.assert_allclose(t_rel[300:350], 0.30 + np.arange(50) / rate, atol=1e-6)
    assert t_rel[650] - t_rel[649] == pytest.approx(0.101, abs=1e-6)  # the gap is kept
    assert {i.kind for i in cd.issues} == {"overlap"}


def test_read_topic_nan_strict_and_lenient(tmp_path, topics, meta):
    path = write_foreign_bag(tmp_path / "b", meta, topics, block_samples=100,
                             faults=Faults(nan={VEHICLE_GAP: [(4, 10, 0)]}))
    with BagReader(path) as bag:
        with pytest.raises(ContractError, match=r"vehicle/gap \[M1G\]: 1 NaN/inf") as ei:
            bag.read_topic(VEHICLE_GAP)
        _one_line_error(ei, path)
        bag.read_topic(VEHICLE_ACCEL)       # other topics are fine
    with BagReader(path, strict=False) as bag:
        cd = bag.read_topic(VEHICLE_GAP)
    assert np.isnan(cd.data[410, 0]) and np.isfinite(np.delete(cd.data[:, 0], 410)).all()
    (issue,) = cd.issues
    assert issue.kind == "nan" and issue.channel == "M1G"


# --------------------------------------------------------------------- memory / rclpy
def test_iter_blocks_streams_with_bounded_memory(tmp_path):
    channels = tuple(f"C{i}" for i in range(17))
    md = make_metadata({GUIDEWAY_ACCEL: (channels,)}, kind="ambient")
    base = np.random.default_rng(0).standard_normal((200, 17)).astype(np.float32)
    n_blocks = 1000                   # 1000 * 200 * 17 * 4 B = 13.6 MB of samples
    with BagWriter(tmp_path / "big", md) as w:
        for k in range(n_blocks):
            w.write_block(GUIDEWAY_ACCEL, Block(k * 100_000_000, "", 2000.0, channels,
                                                ("m/s^2",) * 17, base))
    with BagReader(tmp_path / "big") as bag:
        tracemalloc.start()
        n = 0
        for _, blk in bag.iter_blocks():
            n += blk.n_samples
        _, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
    assert n == n_blocks * 200
    assert peak < 8e6, f"peak {peak / 1e6:.1f} MB while streaming 13.6 MB"


def test_core_modules_do_not_import_rclpy(tmp_path, topics, meta):
    path = write_contract_bag(tmp_path / "bag", meta, topics)
    code = (
        "import sys\n"
        "import maglev_ros.contract, maglev_ros.sensor_block, maglev_ros.bag_reader, "
        "maglev_ros.bag_writer, maglev_ros.commands.info\n"
        "from maglev_ros.bag_reader import BagReader\n"
        f"with BagReader({str(path)!r}) as b:\n"
        "    b.check(); [b.read_topic(t) for t in b.sensor_topics]\n"
        "assert 'rclpy' not in sys.modules, 'rclpy imported'\n"
        "print('ok')\n"
    )
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env,
                         cwd=ROOT, timeout=120)
    assert res.returncode == 0, res.stderr
    assert res.stdout.strip() == "ok"


def test_foreign_typestore_matches_ours():
    """A type registered from the contract's .msg text hashes like ours (same definition)."""
    assert foreign_typestore().hash_rihs01(SENSORBLOCK_TYPE) == typestore().hash_rihs01(SENSORBLOCK_TYPE)


def test_channel_data_accessors():
    cd = ChannelData("/t", ("a", "b"), ("m", "m/s"), 10.0, np.arange(3) / 10.0,
                     np.arange(6.0).reshape(3, 2))
    np.testing.assert_array_equal(cd.channel("b"), [1.0, 3.0, 5.0])
    assert cd.unit("b") == "m/s"
    with pytest.raises(UserError, match="no channel 'c'"):
        cd.channel("c")


# ------------------------------------------------------------------ fast SensorBlock decoder
@pytest.mark.parametrize("frame", ["", "g", "vehicle", "gü"])
@pytest.mark.parametrize("channels", [("a",), ("G1LV", "xxxxxxx", "é"), tuple(f"C{i}" for i in range(17))])
@pytest.mark.parametrize("n", [0, 1, 7])
def test_fast_decoder_matches_rosbags(frame, channels, n):
    from maglev_ros.sensor_block import SensorBlockDecoder

    store = typestore()
    rng = np.random.default_rng(n)
    dec = SensorBlockDecoder()
    for rep in range(3):                      # repeated strings exercise the cache
        blk = Block.from_arrays(-5 * 10**9 + rep if frame else 1_700_000_000_123_456_789 + rep,
                                1234.5, channels, ["m"] * len(channels),
                                rng.standard_normal((n, len(channels))), frame)
        raw = bytes(store.serialize_cdr(block_to_msg(blk), SENSORBLOCK_TYPE))
        ref = store.deserialize_cdr(raw, SENSORBLOCK_TYPE)
        got = dec.decode(raw)
        assert got.stamp_ns == ref.header.stamp.sec * 10**9 + ref.header.stamp.nanosec
        assert got.frame_id == ref.header.frame_id == frame
        assert got.sample_rate_hz == ref.sample_rate_hz
        assert got.channels == tuple(ref.channels) and got.units == tuple(ref.units)
        np.testing.assert_array_equal(got.data, ref.data)
    # big-endian or garbage -> None (caller falls back to rosbags)
    assert dec.decode(b"\x00\x00" + raw[2:]) is None
    assert dec.decode(raw[:-8]) is None


def test_fast_and_rosbags_decoding_agree_on_faulty_bag(tmp_path, topics, meta):
    faults = Faults(duplicate={GUIDEWAY_ACCEL: [1]}, swap={VEHICLE_GAP: [2]},
                    nan={VEHICLE_ACCEL: [(1, 1, 1)]}, units={GUIDEWAY_ACCEL: {"G1LV": "mm"}},
                    short_units={VEHICLE_POSITION: [0]}, drop={VEHICLE_GAP: [5]})
    path = write_foreign_bag(tmp_path / "b", meta, topics, block_samples=[30, 70], faults=faults)
    results = []
    for fast in (True, False):
        with BagReader(path, strict=False, fast_decode=fast) as bag:
            assert bag._fast is fast
            blocks = list(bag.iter_blocks())
            cds = [bag.read_topic(t) for t in (GUIDEWAY_ACCEL, VEHICLE_GAP, VEHICLE_ACCEL)]
            results.append((blocks, cds, bag.check()))
    (b1, c1, i1), (b2, c2, i2) = results
    assert [(t, b) for t, b in b1] == [(t, b) for t, b in b2]
    for x, y in zip(c1, c2):
        np.testing.assert_array_equal(x.data, y.data)
        np.testing.assert_array_equal(x.time_s, y.time_s)
        assert x.issues == y.issues
    assert i1 == i2 and len(i1) >= 6
