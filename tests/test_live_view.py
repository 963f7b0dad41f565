"""The live view's core (no ROS): decimation, residual map, result messages, scene and layout,
against values computed by hand here."""
from __future__ import annotations

import json
import math
import re
from pathlib import Path

import numpy as np
import pytest

from maglev_ros import live_view as lv
from maglev_ros.discrepancy.features import BAND_EDGES_HZ
from maglev_ros.live_view import messages as lm
from maglev_ros.live_view import scene as ls
from maglev_ros.live_view.decimate import Decimator, series_messages
from maglev_ros.live_view.residual_map import ResidualMap, grid_cells
from maglev_ros.sensor_block import Block

LAYOUT = Path(__file__).resolve().parents[1] / "maglev_ros" / "config" / "foxglove_layout.json"


def _block(t0_s, rate, cols, names=("a", "b")):
    return Block.from_arrays(int(round(t0_s * 1e9)), rate, names, ("m",) * len(names), np.stack(cols, axis=1))


# ------------------------------------------------------------------------------ decimation
def test_bins_are_min_max_mean_of_the_samples_in_each_bin_across_blocks():
    d = Decimator(display_rate_hz=2.0)                  # 0.5 s bins; samples every 0.1 s
    a1 = np.arange(8.0)                                  # t = 0.0 .. 0.7
    b1 = np.array([0.0, np.nan, 2, 3, 4, np.nan, np.nan, np.nan])
    bins = d.add(_block(0.0, 10.0, [a1, b1]))
    # bin [0, 0.5): samples 0..4 complete (t = 0.5 is the first sample of the next bin)
    assert list(bins.start_ns) == [0] and list(bins.count) == [5]
    assert list(bins.min[0]) == [0, 0] and list(bins.max[0]) == [4, 4]
    assert bins.mean[0][0] == 2.0 and bins.mean[0][1] == pytest.approx((0 + 2 + 3 + 4) / 4)
    # the next block completes [0.5, 1.0) (5, 6, 7 from before, 8, 9 now) and leaves [1.0, 1.5) open
    a2 = np.arange(8.0, 12.0)                            # t = 0.8 .. 1.1
    bins = d.add(_block(0.8, 10.0, [a2, np.full(4, np.nan)]))
    assert list(bins.start_ns) == [500_000_000] and list(bins.count) == [5]
    assert (bins.min[0][0], bins.max[0][0], bins.mean[0][0]) == (5, 9, 7)
    assert np.isnan(bins.mean[0][1]) and np.isnan(bins.min[0][1])      # no finite sample: no value
    last = d.flush()
    assert list(last.start_ns) == [1_000_000_000] and last.mean[0][0] == 10.5 and last.count[0] == 2
    assert d.flush() is None


def test_a_bin_is_sent_once_the_block_reaches_its_end_and_a_gap_closes_the_open_one():
    d = Decimator(display_rate_hz=2.0)
    bins = d.add(_block(0.0, 10.0, [np.arange(5.0), np.zeros(5)]))      # 0.0 .. 0.4, ends at 0.5
    assert list(bins.start_ns) == [0] and d.flush() is None
    d.add(_block(1.0, 10.0, [np.array([1.0, 2.0]), np.zeros(2)]))        # 1.0, 1.1: open
    bins = d.add(_block(3.0, 10.0, [np.array([7.0]), np.zeros(1)]))      # a gap: [1.0, 1.5) closes
    assert list(bins.start_ns) == [1_000_000_000] and bins.mean[0][0] == 1.5


def test_series_messages_name_channels_and_send_null_for_no_value():
    d = Decimator(display_rate_hz=2.0)
    bins = d.add(_block(0.0, 10.0, [np.arange(5.0), np.full(5, np.nan)]))
    (t_ns, m), = series_messages(bins, "twin rev 2")
    assert t_ns == 0 and m["source"] == "twin rev 2" and m["bin_s"] == 0.5 and m["n"] == 5
    assert m["mean"] == {"a": 2.0, "b": None} and m["max"]["a"] == 4.0
    json.dumps(m, allow_nan=False)


# ---------------------------------------------------------------------------- residual map
SPEED = 10.0


def _map_metadata(kind="pass"):
    return {"schema": "maglev-testline/1", "line": {"spans": [{"id": "S1", "start_m": 0.0, "length_m": 20.0},
                                                               {"id": "S2", "start_m": 20.0, "length_m": 20.0}]},
            "sensors": {"M1A": {"topic": "/testline/vehicle/accel", "magnet": 1},
                        "M2A": {"topic": "/testline/vehicle/accel", "magnet": 2},
                        "B1": {"topic": "/testline/vehicle/body_accel", "body_x_m": -2.5},
                        "G1": {"topic": "/testline/guideway/accel", "position_m": 30.0}},
            "vehicle": {"magnet_offsets_m": [0.0, -3.0]}, "run": {"kind": kind}}


def test_frames_are_placed_where_the_load_is():
    m = ResidualMap(position_bin_m=1.0)
    m.set_metadata(_map_metadata())
    t = np.arange(0, 4.0, 0.01)
    m.add_position(t, 5.0 + SPEED * t)
    assert m.place("M2A", 1.0) == pytest.approx(15.0 - 3.0)
    assert m.place("B1", 1.0) == pytest.approx(12.5)
    assert m.place("G1", 1.0) == pytest.approx(15.0)       # a pass: where the vehicle is
    assert m.place("M1A", 9.0) is None                      # no position there yet
    m.set_metadata(_map_metadata("ambient"))
    assert m.place("G1", 1.0) == 30.0                       # no vehicle: the sensor's own place


def test_map_cells_hold_the_rms_of_the_frames_placed_in_them():
    """A 24 Hz sine (band 22-26 Hz) of amplitude 1 in the first frame and 2 in the second, both
    while magnet 1 is in the 12 m bin: the cell's total power over bands is the mean of the two
    frames' mean squares, (0.5 + 2) / 2 = 1.25; the other magnet's cells are elsewhere."""
    m = ResidualMap(position_bin_m=1.0, frame_s=0.5)
    m.set_metadata(_map_metadata())
    fs = 1000.0
    t = np.arange(0, 1.0, 1 / fs)
    # the vehicle stands at 12.4 m (M1A in bin 12, M2A at 9.4 m in bin 9)
    m.add_position(np.array([-1.0, 5.0]), np.array([12.4, 12.4]))
    amp = np.where(t < 0.5, 1.0, 2.0)
    x = amp * np.sin(2 * np.pi * 24.0 * t)
    assert m.add_block("vehicle_accel", _block(0.0, fs, [x, 0.1 * x], ("M1A", "M2A"))) == 2
    r = m.rms("vehicle_accel")
    assert r.shape == (len(BAND_EDGES_HZ) - 1, 40)
    filled = sorted(set(np.flatnonzero(np.isfinite(r).any(axis=0))))
    assert filled == [9, 12]
    total = np.nansum(r[:, 12] ** 2)
    assert total == pytest.approx(1.25, rel=0.02)
    assert np.nansum(r[:, 9] ** 2) == pytest.approx(0.0125, rel=0.02)
    band = int(np.searchsorted(BAND_EDGES_HZ, 24.0) - 1)
    assert np.nanargmax(r[:, 12]) == band
    # bands above 0.7 x Nyquist are left out (NaN), as the discrepancy detector does
    assert np.all(np.isnan(r[BAND_EDGES_HZ[1:] > 0.7 * fs / 2, 12]))
    msg = m.message("vehicle_accel")
    assert msg["mapped"] == 4 and msg["unplaced"] == 0 and msg["position_m"][12] == 12.5
    assert msg["bands"][band]["rms"][12] == pytest.approx(r[band, 12]) and msg["bands"][band]["rms"][0] is None


def test_frames_off_the_line_or_without_a_position_are_counted_not_mapped():
    m = ResidualMap(position_bin_m=1.0, frame_s=0.5)
    m.set_metadata(_map_metadata())
    x = np.sin(np.arange(500) * 0.3)
    m.add_block("vehicle_accel", _block(0.0, 1000.0, [x], ("M1A",)))       # no position yet
    m.add_position(np.array([0.0, 10.0]), np.array([60.0, 60.0]))         # beyond the line's 40 m
    m.add_block("vehicle_accel", _block(0.5, 1000.0, [x], ("M1A",)))
    assert m.message("vehicle_accel")["unplaced"] == 2 and m.message("vehicle_accel")["mapped"] == 0


def test_grid_cells_are_rows_of_bands_with_rms_and_its_log():
    r = np.array([[1.0, np.nan, 100.0], [0.01, 10.0, np.nan]])
    cols, stride, fields, data = grid_cells(r)
    cells = np.frombuffer(data, "<f4").reshape(2, 3, 2)
    assert (cols, stride, fields) == (3, 8, [("rms", 0), ("log10_rms", 4)])
    np.testing.assert_array_equal(cells[..., 0], r.astype(np.float32))
    np.testing.assert_allclose(cells[..., 1], [[0, np.nan, 2], [-2, 1, np.nan]], equal_nan=True)


# -------------------------------------------------------------------------------- messages
def test_parameters_nest_by_name_and_unknown_std_is_null():
    m = lm.parameters_message({"revision": 4, "names": ["levitation.kp_a_per_m", "guideway.youngs_modulus_pa"],
                               "values": [7047.0, 3.9e10], "units": ["A/m", "Pa"], "std": [12.0, math.nan],
                               "identifiable": [True, False], "provenance_json": '{"fit": 1}'}, 3.5)
    assert m["values"] == {"levitation": {"kp_a_per_m": 7047.0}, "guideway": {"youngs_modulus_pa": 3.9e10}}
    assert m["std"]["guideway"]["youngs_modulus_pa"] is None and m["provenance"] == {"fit": 1}
    assert m["table"][1] == {"name": "guideway.youngs_modulus_pa", "value": 3.9e10, "unit": "Pa", "std": None,
                             "identifiable": False}
    json.dumps(m, allow_nan=False)


def test_profile_is_thinned_to_means_of_consecutive_samples():
    x, v = lm.profile_points(2.0, 0.5, np.arange(10.0), max_points=4)      # groups of 3: 0-2, 3-5, 6-8, 9
    np.testing.assert_allclose(v, [1.0, 4.0, 7.0, 9.0])
    np.testing.assert_allclose(x, [2.5, 4.0, 5.5, 6.5])
    x, v = lm.profile_points(0.0, 1.0, [1.0, np.nan, 3.0], max_points=10)
    assert list(x) == [0.0, 1.0, 2.0] and np.isnan(v[1])


def test_modes_history_and_mismatch_log():
    est = {"header": {"stamp": {"sec": 10, "nanosec": 500_000_000}}, "method": "ssi-cov", "window_s": 30.0,
           "modes": [{"id": "M1", "status": "new", "frequency_hz": 23.5, "damping_ratio": 0.02,
                      "std_frequency_hz": math.nan, "channels": ["G1"], "mode_shape": [1.0]},
                     {"id": "M2", "status": "lost", "frequency_hz": 92.3, "damping_ratio": 0.01}]}
    m = lm.modes_message(est)
    assert m["t_s"] == 10.5 and m["frequency_hz"] == {"M1": 23.5} and m["modes"][0]["std_frequency_hz"] is None
    h = lm.ModeHistory()
    h.add(m)
    est["modes"][0]["frequency_hz"] = 23.1
    est["header"]["stamp"]["sec"] = 20
    rows = h.add(lm.modes_message(est))["modes"]
    assert [r["id"] for r in rows] == ["M1", "M2"]
    assert (rows[0]["updates"], rows[0]["frequency_min_hz"], rows[0]["frequency_max_hz"], rows[0]["first_t_s"],
            rows[0]["last_t_s"]) == (2, 23.1, 23.5, 10.5, 20.5)
    log = lm.MismatchLog(length=2)
    for k in range(3):
        out = log.add(lm.mismatch_message({"channels": ["M1A", "M2A"], "severity": float(k),
                                           "position_start_m": math.nan, "detail_json": "not json"}))
    assert out["count"] == 2 and [e["severity"] for e in out["events"]] == [2.0, 1.0]
    assert out["events"][0]["channels"] == "M1A M2A" and out["events"][0]["position_start_m"] is None


def test_inferred_schema_names_every_field():
    s = lm.infer_schema({"a": 1.0, "b": {"c": "x"}, "d": [None, 2], "e": True}, "T")
    assert s["title"] == "T" and s["properties"]["b"]["properties"]["c"] == {"type": "string"}
    assert s["properties"]["d"] == {"type": "array", "items": {"type": "integer"}}
    assert s["properties"]["e"] == {"type": "boolean"}


# ----------------------------------------------------------------------------------- scene
def test_girder_box_has_the_design_sections_area_and_second_moment():
    b, h = ls.girder_section_m(1.5, 0.5)
    assert (b, h) == pytest.approx((0.75, 2.0))
    assert b * h == pytest.approx(1.5) and b * h ** 3 / 12 == pytest.approx(0.5)


def test_scene_spans_sensors_and_vehicle_follow_the_metadata():
    md = _map_metadata()
    md["sensors"]["G1"]["side"] = "right"
    ents = {e["id"]: e for e in ls.line_entities(md) + ls.vehicle_entities(md)}
    assert ents["span/S2"]["cubes"][0]["position"][0] == pytest.approx(30.0)
    assert ents["span/S2"]["cubes"][0]["size"][0] == pytest.approx(20.0 - ls.SPAN_JOINT_M)
    width = ls.girder_width_m(md)
    assert ents["sensors"]["spheres"][0]["position"][:2] == pytest.approx([30.0, -width / 2])
    veh = ents["vehicle"]
    assert veh["frame_id"] == "vehicle" and veh["frame_locked"]
    assert [c["position"][0] for c in veh["cubes"][1:]] == [0.0, -3.0]
    assert ls.mismatch_entity({"position_start_m": None, "position_end_m": 3.0}, 0) is None
    box = ls.mismatch_entity({"position_start_m": 8.0, "position_end_m": 4.0, "severity": 3.0,
                              "channels": ["M1A"]}, 7)
    assert box["id"] == f"mismatch/{7 % ls.MISMATCH_SHOWN}" and box["cubes"][0]["position"][0] == 6.0
    assert box["cubes"][0]["size"][0] == 4.0 and box["texts"][0]["text"] == "M1A (3x)"


def test_vehicle_moves_with_exact_samples_at_most_once_per_period():
    t = np.arange(0, 100_000_000, 10_000_000)            # 10 ms samples, 0 .. 90 ms
    idx, last = ls.transform_samples(t, 33_000_000, None)
    assert list(idx) == [0, 4, 7] and last == 2           # slots 0, 1 (33..66 ms), 2 (66..99 ms)
    idx, last = ls.transform_samples(t + 50_000_000, 33_000_000, last)   # 50 .. 140 ms: slots <= 2 were sent
    assert list(idx) == [5, 9] and last == 4
    idx, last = ls.transform_samples(t, 33_000_000, 40)                   # 1.3 s back: the stream restarted
    assert list(idx) == [0, 4, 7] and last == 2
    assert ls.vehicle_transform(5, 12.5)["translation"] == [12.5, 0.0, 0.0]


# ---------------------------------------------------------------------------------- layout
def _walk(node):
    if isinstance(node, dict):
        for v in node.values():
            yield from _walk(v)
    elif isinstance(node, list):
        for v in node:
            yield from _walk(v)
    elif isinstance(node, str):
        yield node


def layout_paths(layout: dict) -> set[str]:
    """Every message path the layout's panels read (plots, tables, raw messages, 3D topics)."""
    out = set()
    for key, cfg in layout["configById"].items():
        for path_cfg in cfg.get("paths", []):
            out.add(path_cfg["value"])
        if "xAxisPath" in cfg:
            out.add(cfg["xAxisPath"]["value"])
        if "topicPath" in cfg:
            out.add(cfg["topicPath"])
        out.update(cfg.get("topics", {}))
    return out


def layout_topics(layout: dict) -> set[str]:
    return {p.split(".")[0] for p in layout_paths(layout)}


def _panel_ids(node) -> set[str]:
    if isinstance(node, str):
        return {node}
    return _panel_ids(node["first"]) | _panel_ids(node["second"])


def test_layout_is_valid_json_and_names_only_channels_the_bridge_advertises():
    layout = json.loads(LAYOUT.read_text())
    assert set(layout) >= {"configById", "layout", "globalVariables", "userNodes", "playbackConfig"}
    topics = layout_topics(layout)
    assert topics and topics <= lv.view_topics(), sorted(topics - lv.view_topics())
    assert {lv.VIEW_SCENE, lv.VIEW_TF, lv.VIEW_MODE_HISTORY, lv.VIEW_PARAMETERS} <= topics
    # every panel the layout places has its configuration, and every configuration is placed
    placed = _panel_ids(layout["layout"])
    for cfg in layout["configById"].values():
        for tab in cfg.get("tabs", []):
            placed |= _panel_ids(tab["layout"])
    assert placed == set(layout["configById"])
    assert all(re.fullmatch(r"[A-Za-z0-9]+![A-Za-z0-9_]+", k) for k in placed)


def test_layout_is_shipped_as_package_data():
    import tomllib
    data = tomllib.loads((LAYOUT.parents[2] / "pyproject.toml").read_text())["tool"]["setuptools"]["package-data"]
    assert any(Path(LAYOUT.name).match(p.split("/")[-1]) and p.startswith("config/") for p in data["maglev_ros"])


def test_parameter_names_are_those_the_updater_publishes():
    from maglev_ros.updating.pipeline import TWIN_NAMES
    assert set(lm.PARAMETER_NAMES) == set(TWIN_NAMES.values())
    props = lm.parameters_schema()["properties"]["values"]["properties"]
    assert props["levitation"]["properties"]["kp_a_per_m"] == {"type": "number"}


def test_view_groups_are_the_twins():
    from maglev_ros.twin import online
    assert lv.GROUP_TOPICS == online.GROUP_TOPICS
    assert (lv.PREDICTED_PREFIX, lv.RESIDUAL_PREFIX) == (online.PREDICTED_PREFIX, online.RESIDUAL_PREFIX)


def test_view_urls_open_the_live_view_in_the_foxglove_app():
    from maglev_ros.launch_graph import view_node, view_urls
    app, ws = view_urls("127.0.0.1", 8765)
    assert (app, ws) == ("https://app.foxglove.dev/?ds=foxglove-websocket&ds.url=ws://localhost:8765",
                         "ws://localhost:8765")
    assert view_urls("10.0.0.5", 9000)[1] == "ws://10.0.0.5:9000"
    spec = view_node("0.0.0.0", 9000)
    assert spec.observer and spec.params == {"host": "0.0.0.0", "port": 9000}


def test_launch_view_port_out_of_range_is_one_line(tmp_path, capsys):
    pytest.importorskip("rclpy")
    from maglev_ros.cli import main
    code = main(["launch", "monitor", "--view", "--view-port", "70000", "--out", str(tmp_path)])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 1 and len(err) == 1 and "--view-port" in err[0] and "70000" in err[0]


def test_position_history_starts_again_when_the_stream_does():
    m = ResidualMap()
    m.set_metadata(_map_metadata())
    m.add_position(np.array([10.0, 11.0, 12.0]), np.array([1.0, 2.0, 3.0]))
    m.add_position(np.array([11.5]), np.array([9.0]))          # out of order by less than 1 s: dropped
    assert m.vehicle_x(11.5) == pytest.approx(2.5)
    m.add_position(np.array([0.0, 1.0]), np.array([5.0, 6.0]))  # a loop: the history starts again
    assert m.vehicle_x(0.5) == pytest.approx(5.5) and m.vehicle_x(11.5) is None
