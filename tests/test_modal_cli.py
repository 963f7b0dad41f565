"""``maglev-ros modes``: contract bags with simulated guideway data of known modes."""
from __future__ import annotations

import json

import numpy as np
import pytest

from bagfactory import GUIDEWAY_ACCEL, VEHICLE_POSITION, make_metadata, write_contract_bag
from maglev_ros.cli import main
from modal_data import SPAN_M, assert_modes_match, guideway_model, simulate_ambient, simulate_pass


def test_modes_ambient_bag_json_and_plot(tmp_path, capsys):
    model = guideway_model(None)
    fs = 1000.0
    y = simulate_ambient(model, fs, 90.0, noise_frac=0.05, seed=3)
    topics = {GUIDEWAY_ACCEL: (model.channels, ("m/s^2",) * 15, fs, y)}
    bag = write_contract_bag(tmp_path / "amb", make_metadata(topics, kind="ambient"), topics)
    out, png = tmp_path / "modes.json", tmp_path / "stab.png"
    assert main(["modes", str(bag), "--json", str(out), "--plot", str(png)]) == 0
    doc = json.loads(out.read_text())
    assert doc["schema"] == "maglev-modes/1"
    assert doc["source"]["run_kind"] == "ambient"
    # the metadata places the sections on three spans, but one structure carries them all: they move
    # together (coherent), so they are identified together only
    grouping = doc["source"]["span_groups"]
    assert not grouping["identified_apart"] and grouping["weighted_coherence"] > 0.9
    assert "channel_groups" not in doc["source"]
    from maglev_ros.modal.ssi_cov import Mode
    modes = [Mode(m["id"], m["frequency_hz"], m["damping_ratio"], m["mode_shape"], m["mpc"],
                  m.get("mpd", 0.0), m["std_frequency_hz"], m["std_damping_ratio"])
             for m in doc["modes"]]
    chk = assert_modes_match(modes, model, 150.0)
    assert chk["missing"] == [] and chk["spurious"] == []
    assert chk["freq_rel"] < 0.005 and chk["mac_min"] > 0.98
    assert png.stat().st_size > 20000
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "M1" in capsys.readouterr().out


def test_modes_pass_bag_uses_free_decay_from_position(tmp_path):
    model = guideway_model(2)
    fs = 500.0
    offs = (0.0, -3.0, -6.0, -9.0, -12.0)
    y, t, pos, t_exit = simulate_pass(model, fs, speed_mps=30.0, noise_frac=0.01, seed=2,
                                      axle_offsets_m=offs)
    k = np.arange(0, t.size, 5)                       # position at 100 Hz
    topics = {GUIDEWAY_ACCEL: (model.channels, ("m/s^2",) * 15, fs, y),
              VEHICLE_POSITION: (("position_m", "speed_mps"), ("m", "m/s"), 100.0,
                                 np.column_stack([pos[k], np.full(k.size, 30.0)]))}
    md = make_metadata(topics, kind="pass", n_spans=1, span_length_m=SPAN_M,
                       magnet_offsets_m=offs, nominal_speed_mps=30.0)
    bag = write_contract_bag(tmp_path / "pass", md, topics)
    out = tmp_path / "m.json"
    assert main(["modes", str(bag), "--json", str(out)]) == 0
    doc = json.loads(out.read_text())
    w = doc["source"]["free_decay_window"]
    assert w["method"] == "position"
    assert w["start_s"] == pytest.approx(t_exit + 0.1, abs=0.02)
    f = np.array([m["frequency_hz"] for m in doc["modes"]])
    for r, (kind, _) in enumerate(model.kinds):
        if kind in ("vertical", "torsion") and model.frequency_hz[r] < 150:
            assert np.min(np.abs(f - model.frequency_hz[r])) / model.frequency_hz[r] < 0.01


def test_modes_errors(tmp_path, capsys):
    assert main(["modes", str(tmp_path / "nope")]) == 1
    assert "no such bag" in capsys.readouterr().err
    topics = {VEHICLE_POSITION: (("position_m", "speed_mps"), ("m", "m/s"), 100.0,
                                 np.zeros((500, 2)))}
    bag = write_contract_bag(tmp_path / "nopos", make_metadata(topics, kind="ambient"), topics)
    assert main(["modes", str(bag)]) == 1
    err = capsys.readouterr().err
    assert "/testline/guideway/accel" in err and len(err.strip().splitlines()) == 1
