"""``maglev-ros random-vibration paper001 --out DIR --quick``: files, schema, car times, errors."""
from __future__ import annotations

import json
import sys
from pathlib import Path

import matplotlib.image
import numpy as np
import pytest
import yaml

from maglev_ros.cli import main
from maglev_ros.system3d.vehicle_data import CONFIG_DIR


@pytest.fixture(scope="module")
def quick_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("rv") / "paper001"
    assert main(["random-vibration", "paper001", "--out", str(out), "--quick", "--quiet"]) == 0
    return out


def test_quick_run_writes_the_document_and_plots(quick_run):
    doc = json.loads((quick_run / "random_vibration.json").read_text())       # read back by the stdlib
    assert doc["schema"] == "maglev-random-vibration/1"
    car2 = doc["cars_on_girder"][1]
    assert car2["car"] == 2
    assert car2["enter_s"] == pytest.approx(2.39, abs=0.05) and car2["leave_s"] == pytest.approx(13.05, abs=0.05)
    s = doc["summary"]
    for name in ("cabin2_acc_z", "cabin2_acc_y", "girder_mid_acc_z", "girder_mid_acc_y", "car2_current_l3_front"):
        assert s[name]["max_sd"] > 0
        assert s[name]["max_rms"] >= s[name]["max_sd"] - 1e-15
    # the mean is the weight moving over the girder: vertical only (the vehicle is mirror-symmetric)
    assert s["girder_mid_acc_y"]["max_abs_mean"] < 1e-9 * s["girder_mid_acc_z"]["max_abs_mean"]
    ser = doc["series"]["girder_mid_acc_z"]
    t = np.array(doc["series_time_s"])
    before = t < doc["cars_on_girder"][0]["enter_s"]
    assert np.all(np.array(ser["sd"])[before] == 0) and np.all(np.array(ser["mean"])[before] == 0)
    rms = np.array(ser["rms"])
    np.testing.assert_allclose(rms ** 2, np.array(ser["mean"]) ** 2 + np.array(ser["sd"]) ** 2, rtol=1e-9, atol=1e-30)
    psd = np.array(ser["psd"])
    assert psd.shape == (len(doc["psd_time_s"]), doc["frequency_grid"]["n"])
    run = doc["runs"]["pem_run"]
    assert run["iterations_max"] >= 2                                        # separated iteration ran
    sc = doc["scenario"]
    assert len(run["iterations_per_step"]) == run["steps"] == round(sc["duration_s"] / sc["time_step_s"])
    for png in ("rms_envelopes.png", "psd_maps.png"):
        img = matplotlib.image.imread(quick_run / png)
        assert img.shape[0] > 200 and img.shape[1] > 200


def test_unknown_scenario_is_one_line(tmp_path, capsys):
    assert main(["random-vibration", "no_such_case", "--out", str(tmp_path / "o"), "--quiet"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no_such_case" in err[0]


def test_bad_scenario_key_is_one_line(tmp_path, capsys):
    doc = yaml.safe_load((CONFIG_DIR / "paper001.yaml").read_text())
    doc["vehicle"] = str(CONFIG_DIR / "paper001_vehicle.yaml")
    doc["girder"] = str(CONFIG_DIR / "paper001_girder.yaml")
    doc["irregularity"] = str(CONFIG_DIR / "paper001_irregularity.yaml")
    doc["train"]["front_start_m"] = 10.0                    # starts on the girder
    p = tmp_path / "bad.yaml"
    p.write_text(yaml.safe_dump(doc))
    assert main(["random-vibration", str(p), "--out", str(tmp_path / "o"), "--quiet", "--quick"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "front_start_m" in err[0]
    assert not (tmp_path / "o").exists()


def test_unknown_solver_key_is_one_line(tmp_path, capsys):
    doc = yaml.safe_load((CONFIG_DIR / "paper001.yaml").read_text())
    for k in ("vehicle", "girder", "irregularity"):
        doc[k] = str(CONFIG_DIR / doc[k])
    doc["solver"]["couplng"] = "monolithic"
    p = tmp_path / "typo.yaml"
    p.write_text(yaml.safe_dump(doc))
    assert main(["random-vibration", str(p), "--out", str(tmp_path / "o"), "--quiet"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "solver.couplng" in err[0]


def test_paper_rows_of_the_bench_read_the_summary(quick_run):
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
    import bench_paper001 as bp
    doc = json.loads((quick_run / "random_vibration.json").read_text())
    rs = bp.rows(doc)
    assert rs[0]["within_2x"]                                   # car 2's times: 2.39 / 13.05 s
    by = {r["quantity"]: r for r in rs}
    r = by["girder midpoint vertical, max mean"]
    assert r["ours"] == doc["summary"]["girder_mid_acc_z"]["max_abs_mean"] and r["paper"] == 0.09
    assert r["ratio"] == pytest.approx(r["ours"] / 0.09) and r["within_2x"] == (0.5 <= r["ratio"] <= 2)
    assert by["cabin vertical, max SD (implied)"]["paper"] == pytest.approx((0.32 - 0.16) / 3)
