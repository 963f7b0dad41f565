"""The Foxglove bridge over a real ROS 2 graph, seen by a WebSocket client.

One short generated recording (2 s; contract topics plus twin outputs, modes, a mismatch, the
parameters, a profile and a diagnosis, so every kind of view is fed) is replayed into the bridge
node while a Foxglove WebSocket client (tests/foxglove_client.py, its own decoding) subscribes to
every channel. The checks compare what the client decodes with the recording itself: each display
bin with numpy's min / max / mean of the recorded samples in that bin, the vehicle transform with
the recorded position at its stamp, the results with the values written.
"""
from __future__ import annotations

import io
import json
import os
import re
import socket
import threading
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rclpy")
pytest.importorskip("maglev_msgs")
pytest.importorskip("foxglove")
pytest.importorskip("websockets")

from bagfactory import (GUIDEWAY_ACCEL, GUIDEWAY_DISP, VEHICLE_ACCEL, VEHICLE_GAP,  # noqa: E402
                        VEHICLE_POSITION, example_topics, make_metadata)
from foxglove_client import FoxgloveClient  # noqa: E402
from maglev_ros.launch_graph import NodeSpec  # noqa: E402
from rosgraph import ros_env  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
LAYOUT = ROOT / "maglev_ros" / "config" / "foxglove_layout.json"
T0_NS = 1_700_000_000_000_000_000
DURATION_S = 2.0
TWIN_SCALE = 0.9                     # the written "prediction" is 0.9 x the measurement
PARAMS = {"levitation.kp_a_per_m": 7047.0, "levitation.kv_a_s_per_m": 39.8, "guideway.youngs_modulus_pa": 3.9e10}
MODES = [("M1", 23.52, 0.021), ("M2", 92.27, 0.012)]
MISMATCH = {"position_start_m": 5.0, "position_end_m": 8.0, "severity": 12.5, "channels": ["M1A"]}


def _write_results(path: Path, topics: dict) -> None:
    """Append the graph's results to the recording (rosbags objects of our message types)."""
    from maglev_ros.bag_writer import BagWriter
    from maglev_ros.sensor_block import Block, make_header, typestore
    st = typestore()
    T = st.types
    md = make_metadata(topics)
    with BagWriter(path, md, overwrite=True, metadata_stamp_ns=T0_NS) as w:
        events = []
        for topic, (channels, units, rate, data) in topics.items():
            data = np.asarray(data, np.float32)
            n = int(round(0.1 * rate))
            for first in range(0, len(data), n):
                stamp = T0_NS + int(round(first * 1e9 / rate))
                blk = Block.from_arrays(stamp, rate, channels, units, data[first:first + n], "vehicle")
                events.append((stamp, 0, topic, blk))
                group = {GUIDEWAY_ACCEL: "guideway_accel", GUIDEWAY_DISP: "guideway_displacement",
                         VEHICLE_ACCEL: "vehicle_accel", VEHICLE_GAP: "vehicle_gap"}.get(topic)
                if group:
                    pred = Block.from_arrays(stamp, rate, channels, units, data[first:first + n] * TWIN_SCALE,
                                             "twin rev 1")
                    res = Block.from_arrays(stamp, rate, channels, units,
                                            data[first:first + n] - data[first:first + n] * TWIN_SCALE, "twin rev 1")
                    events.append((stamp, 1, f"/maglev/twin/predicted/{group}", pred))
                    events.append((stamp, 2, f"/maglev/twin/residual/{group}", res))
        events.sort(key=lambda e: (e[0], e[1], e[2]))
        for stamp, _, topic, blk in events:
            w.write_block(topic, blk, log_time_ns=stamp)
        ts = T0_NS + int(1.9e9)
        for k, t in enumerate((T0_NS + int(1.0e9), T0_NS + int(1.95e9))):
            modes = [T["maglev_msgs/msg/ModalMode"](
                id=i, status="new" if k == 0 else "tracked", frequency_hz=f, damping_ratio=z,
                std_frequency_hz=0.01, std_damping_ratio=0.001, mpc=0.99, channels=["G1LV"],
                mode_shape=np.array([1.0])) for i, f, z in MODES]
            w.write_message("/maglev/modes", "maglev_msgs/msg/ModalEstimate",
                            T["maglev_msgs/msg/ModalEstimate"](header=make_header(t, "", st), method="ssi-cov",
                                                               window_s=10.0, modes=modes), t)
        w.write_message("/maglev/mismatch", "maglev_msgs/msg/MismatchReport", T["maglev_msgs/msg/MismatchReport"](
            header=make_header(ts, "", st), channels=MISMATCH["channels"], t0_s=1.0, t1_s=1.5,
            position_start_m=MISMATCH["position_start_m"], position_end_m=MISMATCH["position_end_m"],
            f0_hz=10.0, f1_hz=14.0, severity=MISMATCH["severity"], effect="", category="", explanation="x",
            detail_json=json.dumps({"runs": []})), ts)
        names = list(PARAMS)
        w.write_message("/maglev/twin/parameters", "maglev_msgs/msg/TwinParameters",
                        T["maglev_msgs/msg/TwinParameters"](
                            header=make_header(ts, "", st), revision=3, names=names,
                            values=np.array([PARAMS[n] for n in names]), units=["A/m", "A s/m", "Pa"],
                            std=np.array([10.0, float("nan"), 1e9]), identifiable=np.array([True, False, True]),
                            provenance_json="{}"), ts)
        w.write_message("/maglev/irregularity", "maglev_msgs/msg/IrregularityProfile",
                        T["maglev_msgs/msg/IrregularityProfile"](
                            header=make_header(ts, "", st), start_position_m=1.0, spacing_m=0.02,
                            irregularity_m=1e-3 * np.sin(np.arange(500) * 0.05), std_m=np.zeros(0),
                            min_wavelength_m=0.1, max_wavelength_m=20.0, kind="loaded", sources=["M1A"]), ts)
        w.write_message("/maglev/diagnosis", "std_msgs/msg/String", T["std_msgs/msg/String"](data=json.dumps(
            {"schema": "maglev-diagnosis/1", "missing_physics": [{"name": "control_delay", "category": "control"}]})),
            ts)


def _env() -> dict:
    return ros_env(215)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def live(tmp_path_factory):
    """The recording replayed by the launcher with the live view beside it (``launch --view``'s
    node spec), a WebSocket client reading meanwhile; its view after the graph stopped."""
    from maglev_ros import launch_graph
    from maglev_ros.launcher import launch
    tmp = tmp_path_factory.mktemp("foxglove")
    topics = example_topics(DURATION_S, seed=3)
    t = np.arange(int(DURATION_S * 1000)) / 1000
    topics[GUIDEWAY_DISP] = (("G2D",), ("m",), 1000.0, (1e-4 * np.sin(2 * np.pi * 4 * t))[:, None])
    bag = tmp / "rec"
    _write_results(bag, topics)
    port = _free_port()
    log = io.StringIO()
    result = {}

    def run():
        try:
            result["code"] = launch("_view", bag=str(bag), env=_env(), linger_s=4.0, out=log,
                                    overrides={"replay": {"rate": 1.0, "progress": False},
                                               "foxglove_bridge": {"map_period_s": 0.3}},
                                    extra=[launch_graph.view_node("127.0.0.1", port)])
        except BaseException as exc:  # reported by the test below
            result["error"] = exc
    with pytest.MonkeyPatch.context() as mp:
        mp.setitem(launch_graph.GRAPHS, "_view", [NodeSpec("replay", "maglev_ros.nodes.replay", needs_bag=True)])
        graph = threading.Thread(target=run)
        graph.start()
        try:
            client = FoxgloveClient(launch_graph.view_urls("127.0.0.1", port)[1], timeout_s=60)
        except OSError:
            graph.join(30)
            raise AssertionError(f"the live view did not start: {result} {log.getvalue()}") from None
        # reads while the replay runs and lingers, until the launcher stops the bridge
        client.wait_for(lambda c: not graph.is_alive(), 120)
        graph.join(60)
    client.close()
    assert result.get("code") == 0, (result, log.getvalue())
    yield {"client": client, "topics": topics, "log": log.getvalue()}


def _bag_bins(channels, rate_hz, data, width_ns):
    """The recorded samples' display bins, computed here: {bin start ns: (min, max, mean) per channel}."""
    t_ns = T0_NS + np.round(np.arange(len(data)) * 1e9 / rate_hz).astype(np.int64)
    k = t_ns // width_ns
    out = {}
    for kk in np.unique(k):
        seg = np.asarray(data, np.float32)[k == kk].astype(float)
        out[int(kk) * width_ns] = (seg.min(axis=0), seg.max(axis=0), seg.mean(axis=0))
    return out


@pytest.mark.parametrize("topic,kind,scale", [(VEHICLE_ACCEL, "measured", 1.0), (GUIDEWAY_ACCEL, "measured", 1.0),
                                              (VEHICLE_ACCEL, "predicted", TWIN_SCALE),
                                              (VEHICLE_GAP, "residual", 1 - TWIN_SCALE)])
def test_series_bins_equal_the_recorded_samples(live, topic, kind, scale):
    channels, _, rate, data = live["topics"][topic]
    group = topic.removeprefix("/testline/").replace("/", "_")
    got = live["client"].messages.get(f"/maglev/view/{group}/{kind}", [])
    assert len(got) >= 0.9 * DURATION_S * 50, len(got)      # 50 Hz bins, best-effort: most arrive
    d = np.asarray(data, np.float32)
    ref = _bag_bins(channels, rate, d if scale == 1.0 else
                    (d * np.float32(TWIN_SCALE) if kind == "predicted" else d - d * np.float32(TWIN_SCALE)), 20_000_000)
    for t_ns, m in got:
        assert t_ns == round(m["t_s"] * 1e9, -3) or abs(t_ns - m["t_s"] * 1e9) < 1e3
        lo, hi, mean = ref[t_ns]
        for j, ch in enumerate(channels):
            assert m["min"][ch] == pytest.approx(lo[j], rel=1e-6, abs=1e-12)
            assert m["max"][ch] == pytest.approx(hi[j], rel=1e-6, abs=1e-12)
            assert m["mean"][ch] == pytest.approx(mean[j], rel=1e-5, abs=1e-9)


def test_vehicle_transform_is_the_recorded_position(live):
    channels, _, rate, data = live["topics"][VEHICLE_POSITION]
    tfs = live["client"].messages.get("/maglev/view/tf", [])
    assert len(tfs) >= 10
    x_rec = np.asarray(data, np.float32)[:, channels.index("position_m")]
    t_rec = T0_NS + np.round(np.arange(len(x_rec)) * 1e9 / rate).astype(np.int64)
    for t_ns, tf in tfs:
        assert tf["parent_frame_id"] == "line" and tf["child_frame_id"] == "vehicle"
        stamp = tf["timestamp"]
        assert int(stamp.get("seconds", 0)) * 10**9 + int(stamp.get("nanos", 0)) == t_ns
        i = int(np.flatnonzero(t_rec == t_ns)[0])
        assert tf["translation"].get("x", 0.0) == pytest.approx(float(x_rec[i]), abs=1e-6)   # proto3: 0 is left out


def test_scene_draws_the_metadata_spans_and_the_mismatch(live):
    md = make_metadata(live["topics"])
    updates = [m for _, m in live["client"].messages.get("/maglev/view/scene", [])]
    ents = {e["id"]: e for u in updates for e in u.get("entities", [])}
    for s in md["line"]["spans"]:
        cube = ents[f"span/{s['id']}"]["cubes"][0]
        assert cube["pose"]["position"]["x"] == pytest.approx(s["start_m"] + s["length_m"] / 2)
        assert cube["size"]["x"] == pytest.approx(s["length_m"], abs=0.1)
    veh = ents["vehicle"]
    assert veh["frame_id"] == "vehicle" and len(veh["cubes"]) == 1 + len(md["vehicle"]["magnet_offsets_m"])
    box = next(e for i, e in ents.items() if i.startswith("mismatch/"))["cubes"][0]
    assert box["pose"]["position"]["x"] == pytest.approx(
        (MISMATCH["position_start_m"] + MISMATCH["position_end_m"]) / 2)


def test_results_arrive_with_the_values_written(live):
    got = live["client"].messages
    modes = got["/maglev/view/modes"][-1][1]
    assert modes["frequency_hz"] == pytest.approx({i: f for i, f, _ in MODES})
    hist = got["/maglev/view/modes/history"][-1][1]["modes"]
    assert [(r["id"], r["updates"]) for r in hist] == [("M1", 2), ("M2", 2)]
    params = got["/maglev/view/parameters"][-1][1]
    assert params["revision"] == 3
    assert params["values"]["levitation"]["kp_a_per_m"] == PARAMS["levitation.kp_a_per_m"]
    assert params["std"]["levitation"]["kv_a_s_per_m"] is None          # NaN: unknown
    mm = got["/maglev/view/mismatch"][-1][1]
    assert (mm["severity"], mm["channels"], mm["f1_hz"]) == (MISMATCH["severity"], MISMATCH["channels"], 14.0)
    assert got["/maglev/view/mismatch/log"][-1][1]["count"] == 1
    prof = got["/maglev/view/irregularity"][-1][1]
    assert prof["points"] == 500 and prof["position_m"][10] == pytest.approx(1.0 + 10 * 0.02)
    assert prof["irregularity_m"][10] == pytest.approx(1e-3 * np.sin(0.5))
    diag = got["/maglev/view/diagnosis"][-1][1]
    assert diag["summary"] == [{"name": "control_delay", "category": "control"}]


def test_residual_map_and_its_grid_cover_the_pass(live):
    got = live["client"].messages
    m = got["/maglev/view/vehicle_accel/residual_map"][-1][1]
    assert m["mapped"] > 0 and m["unit"] == "m/s^2"
    rows = np.array([[np.nan if v is None else v for v in b["rms"]] for b in m["bands"]])
    filled = np.flatnonzero(np.isfinite(rows).any(axis=0))
    x = np.asarray(m["position_m"])[filled]
    # magnets ride at 0 .. -4.644 m of a vehicle that went 0 -> 13.9 m
    assert x.min() >= -1 - 4.644 and x.max() <= 6.944 * DURATION_S + 1
    grid = got["/maglev/view/vehicle_accel/residual_map/grid"][-1][1]
    cells = np.frombuffer(grid["data"], "<f4").reshape(-1, grid["column_count"], 2)
    np.testing.assert_allclose(cells[..., 0], rows, rtol=1e-6, equal_nan=True)


def test_server_time_follows_the_stream_and_layout_channels_are_advertised(live):
    assert "incompatible QoS" not in live["log"] and "Traceback" not in live["log"], live["log"]
    c = live["client"]
    assert not c.unadvertised and not c.other, (c.unadvertised, c.other)     # no channel taken back, no error
    assert T0_NS <= c.server_time_ns <= T0_NS + int((DURATION_S + 0.2) * 1e9)
    from test_live_view import layout_paths
    paths = layout_paths(json.loads(LAYOUT.read_text()))
    missing = {p.split(".")[0] for p in paths} - set(c.channels)
    assert not missing, sorted(missing)
    # every field a panel reads is in the schema its channel advertises (the app's path check)
    for path in paths:
        topic, _, rest = path.partition(".")
        ch = c.channels[topic]
        if ch["encoding"] != "json" or not rest:
            continue
        node = json.loads(ch["schema"])
        for name, index in re.findall(r"(?:^|\.)(\w+)|\[(\d+|:)\]", rest):
            if not name:
                node = node["items"]
            else:   # a named field, or one of an object's named-by-data fields (a stream's channels)
                node = node.get("properties", {}).get(name) or node["additionalProperties"]
        assert node.get("type") in ("number", "integer", "array", "object"), (path, node)


def test_a_port_in_use_is_one_line_naming_it():
    import subprocess
    import sys
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        res = subprocess.run([sys.executable, "-m", "maglev_ros.nodes.foxglove_bridge", "--ros-args",
                              "-p", f"port:={port}"], env=_env(), capture_output=True, text=True, timeout=120)
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert res.returncode == 1 and len(lines) == 1, res.stderr
    assert f"127.0.0.1:{port}" in lines[0] and "port" in lines[0] and "Traceback" not in res.stderr
