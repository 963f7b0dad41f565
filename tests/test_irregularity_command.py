"""`maglev-ros irregularity`: a contract bag written from a synthetic recording with known truth
goes in; the CSV (with '#' header lines), JSON and PNG come out, and the CSV profile matches the
band-passed truth. Contract mistakes give one-line errors naming the topic/key."""
from __future__ import annotations

import csv
import json

import numpy as np
import pytest

from irregularity_data import bandpass_truth, make_recording
from maglev_ros.bag_writer import BagWriter
from maglev_ros.cli import main

T0_NS = 1_000_000_000


def _write_bag(rec, path, drop_topic=None, gap_unit="m", metadata_edit=None):
    sensors = {}
    for k in range(len(rec.magnet_offsets_m)):
        sensors[f"M{k + 1}A"] = {"topic": "/testline/vehicle/accel", "quantity": "acceleration",
                                 "direction": "vertical", "magnet": k + 1}
        sensors[f"M{k + 1}G"] = {"topic": "/testline/vehicle/gap", "quantity": "gap",
                                 "magnet": k + 1}
    md = {"schema": "maglev-testline/1",
          "line": {"spans": [{"id": "S1", "start_m": 0.0, "length_m": 1000.0}]},
          "sensors": sensors,
          "vehicle": {"magnet_offsets_m": rec.magnet_offsets_m,
                      "nominal_gap_m": rec.nominal_gap_m},
          "run": {"kind": "pass", "nominal_speed_mps": rec.info["speed_mps"]}}
    if metadata_edit:
        metadata_edit(md)
    with BagWriter(path, md) as w:
        for topic, cd in (("/testline/vehicle/accel", rec.accel), ("/testline/vehicle/gap", rec.gap),
                          ("/testline/vehicle/position", rec.position)):
            if topic == drop_topic:
                continue
            units = cd.units
            if topic.endswith("gap"):
                units = [gap_unit] * len(units)
            nb = int(round(0.1 * cd.sample_rate_hz))
            for i in range(0, cd.time_s.size, nb):
                w.write_arrays(topic, T0_NS + int(round(cd.time_s[i] * 1e9)), cd.sample_rate_hz,
                               cd.channels, units, cd.data[i:i + nb])
    return md


@pytest.fixture(scope="module")
def rec():
    return make_recording(40, 31, "constant", length_m=350.0, fs_hz=500.0,
                          bias_mps2=[0.03, 0.0, 0.0])


def test_command_outputs_match_truth(rec, tmp_path):
    bag = tmp_path / "pass"
    _write_bag(rec, bag)
    out, js, png = tmp_path / "p.csv", tmp_path / "p.json", tmp_path / "p.png"
    rc = main(["irregularity", str(bag), "--out", str(out), "--json", str(js), "--plot", str(png)])
    assert rc == 0
    lines = out.read_text().splitlines()
    head = [l for l in lines if l.startswith("#")]
    assert any("valid band" in l for l in head)
    assert any("high-pass corner: 0.2 Hz" in l for l in head)
    assert any("warning accel_bias [M1A]" in l for l in head)
    assert any("EN 13848 D1" in l for l in head)
    rows = list(csv.reader([l for l in lines if not l.startswith("#")]))
    assert rows[0] == ["position_m", "irregularity_m"]
    x = np.array([float(r[0]) for r in rows[1:]])
    y = np.array([float(r[1]) if r[1] else np.nan for r in rows[1:]])
    d = json.loads(js.read_text())
    prof = d["profile"]
    lo, hi = prof["min_wavelength_m"], prof["max_wavelength_m"]
    assert hi == pytest.approx(40 / 3.6 / 0.4, rel=0.01)
    # stamps are absolute stream time, positions come from the position topic: compare on x
    truth = bandpass_truth(x, rec.truth_at(x), lo, hi)
    m = np.isfinite(y)
    assert m.sum() > 200
    c = np.corrcoef(y[m], truth[m])[0, 1]
    rel = np.sqrt(np.mean((y[m] - truth[m]) ** 2)) / np.sqrt(np.mean(truth[m] ** 2))
    assert c >= 0.95 and rel <= 0.10
    assert d["spectrum"]["dof"] > 2
    assert {b["band"] for b in d["band_rms"]} == {"D1", "D2"}
    assert d["reference_comparison"] and "mean_log10_ratio" in d["reference_comparison"][0]
    assert png.stat().st_size > 10_000


def test_missing_topic_is_one_line_error(rec, tmp_path, capsys):
    bag = tmp_path / "nogap"
    _write_bag(rec, bag, drop_topic="/testline/vehicle/gap")
    rc = main(["irregularity", str(bag), "--out", str(tmp_path / "x.csv")])
    assert rc == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "/testline/vehicle/gap" in err[0]


def test_wrong_gap_unit_is_refused(rec, tmp_path, capsys):
    bag = tmp_path / "mm"
    _write_bag(rec, bag, gap_unit="mm")
    rc = main(["irregularity", str(bag), "--out", str(tmp_path / "x.csv")])
    assert rc == 1
    err = capsys.readouterr().err
    assert "/testline/vehicle/gap" in err and "'m'" in err
