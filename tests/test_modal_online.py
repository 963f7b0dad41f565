"""Online modal identification: the core driver (no ROS) and the modal_id node over a real graph."""

import numpy as np
import pytest

from maglev_ros.bag_writer import BagWriter
from maglev_ros.modal.tracking import OnlineModalConfig, OnlineModalID
from maglev_ros.sensor_block import Block
from modal_data import assert_modes_match, guideway_model, simulate_ambient
from rosgraph import replay_through_node, ros_env

FS = 2000.0
# one band, the settings these tests were written with (the defaults now follow the stream)
FIXED = {"decimate_to_hz": 500.0, "fmin_hz": 5.0, "block_rows": 40, "max_order": 60, "n_blocks": 6}


@pytest.fixture(scope="module")
def model():
    return guideway_model(seed=3)


def test_online_updates_every_update_s_and_tracks_the_true_modes(model):
    y = simulate_ambient(model, fs_hz=FS, duration_s=80.0, seed=11)
    online = OnlineModalID(OnlineModalConfig(window_s=60.0, update_s=2.0, fmax_hz=120.0, **FIXED))
    t0 = 1000.0
    updates = []
    nb = int(0.1 * FS)
    for i in range(0, y.shape[0], nb):
        updates += online.push(t0 + i / FS, y[i:i + nb], model.channels, FS)
    times = np.array([u.time_s for u in updates])
    assert times.size == 11 and times[0] == pytest.approx(t0 + 60.0, abs=0.01)  # window full
    assert np.allclose(np.diff(times), 2.0, atol=1e-6)          # one update per 2 s of stream
    last = updates[-1]
    worst = assert_modes_match(last.modes, model, fmax_hz=120.0, freq_tol=0.005)
    assert not worst["missing"] and not worst["spurious"], worst
    assert worst["freq_rel"] < 0.005 and worst["mac_min"] > 0.95
    # ids are stable across the last updates
    ids = [tuple((m.id, round(m.frequency_hz)) for m in u.modes) for u in updates[-4:]]
    assert len(set(ids)) == 1


def test_online_defaults_follow_the_recording_and_track_the_verbs_modes():
    """bags/paper_ambient (120 s at 500 Hz): the node's old fixed 120 s window filled once and it
    published modes=[]. By default the first estimate comes once the record is as long as the
    verb's rules need to reach 1 Hz (40 s), with the verb's settings for such a record at the
    stream's rate, and the window then grows with the recording."""
    from maglev_ros.bag_reader import BagReader
    from maglev_ros.commands.modes import identify_modes
    from maglev_ros.modal.bands import plan_bands
    ref = identify_modes("bags/paper_ambient").result
    online = OnlineModalID(OnlineModalConfig(update_s=10.0))     # defaults; fewer updates: cheaper
    ups, t0 = [], None
    with BagReader("bags/paper_ambient") as r:
        for _, b in r.iter_blocks("/testline/guideway/accel"):
            t0 = b.stamp_s if t0 is None else t0
            ups += online.push(b.stamp_s, b.data, b.channels, b.sample_rate_hz)
    fs, n_ch = 500.0, len(ref.channels)
    assert online.config.first_window_s == 40.0
    assert online.plan.bands == plan_bands(fs, int(40.0 * fs), n_ch).bands
    assert online.plan.fmax_hz == 0.4 * fs
    assert len(ups) == 9 and ups[0].time_s == pytest.approx(t0 + 40.0)   # (120 - 40) / 10 + 1
    assert online.window_s == pytest.approx(120.0)                      # the whole recording by its end
    # the first window holds a third of the record: its frequency std is ~sqrt(3) x the verb's
    # (0.03 / 0.06 Hz); 1 % of the frequency is more than 4 of those
    for u in ups[1:]:                            # a mode gets its id on its second sighting
        assert len(u.modes) == len(ref.modes)
        for m, r in zip(u.modes, ref.modes):
            assert m.frequency_hz == pytest.approx(r.frequency_hz, rel=0.01)
    assert [m.id for m in ups[-1].modes] == [m.id for m in ups[1].modes]   # ids kept


@pytest.mark.ros
def test_modal_id_node_publishes_tracked_modes_from_a_replay(tmp_path, model):
    dur = 36.0
    y = simulate_ambient(model, fs_hz=FS, duration_s=dur, seed=5).astype(np.float32)
    chans = tuple(model.channels)
    md = {"schema": "maglev-testline/1",
          "line": {"spans": [{"id": "S1", "start_m": 0.0, "length_m": 24.768}]},
          "sensors": {c: {"topic": "/testline/guideway/accel", "quantity": "acceleration",
                          "direction": "vertical", "span": "S1", "position_m": float(i),
                          "side": "left"} for i, c in enumerate(chans)},
          "run": {"kind": "ambient"}}
    bag = tmp_path / "ambient"
    t0 = 1_700_000_000_000_000_000
    with BagWriter(bag, md) as w:
        nb = int(0.1 * FS)
        for i in range(0, y.shape[0], nb):
            w.write_block("/testline/guideway/accel",
                          Block(t0 + int(round(i / FS * 1e9)), "guideway", FS, chans,
                                ("m/s^2",) * len(chans), y[i:i + nb]))
    got = replay_through_node(ros_env(20), "maglev_ros.nodes.modal_id",
                              ["-p", "window_s:=20.0", "-p", "fmax_hz:=120.0", "-p", "skip_when_busy:=false",
                               *[a for k, v in FIXED.items() for a in ("-p", f"{k}:={v}")]], bag,
                              ["maglev_msgs/msg/ModalEstimate:/maglev/modes"], tmp_path / "modes.json",
                              rate=10, wait_subscribers=2, idle_s=5.0)
    msgs = got["/maglev/modes"]
    stamps = np.array([m["header"]["stamp"]["sec"] + m["header"]["stamp"]["nanosec"] * 1e-9
                       for m in msgs])
    assert len(msgs) >= 7, len(msgs)                       # (36 - 20) / 2 updates, minus edges
    assert np.all(np.diff(stamps) <= 2.0 + 0.11)           # an update at least every 2 s of stream
    f1 = model.frequency_hz[0]
    modes = [m for m in msgs[-1]["modes"] if m["status"] != "lost"]
    assert any(abs(m["frequency_hz"] - f1) / f1 < 0.01 for m in modes)
    assert all(m["id"].startswith("M") and len(m["mode_shape"]) == len(chans) for m in modes)
