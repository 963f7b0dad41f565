"""``maglev-ros info``: text and JSON reports on good and bad bags, exit codes, one-line errors."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from bagfactory import (GUIDEWAY_ACCEL, VEHICLE_GAP, VEHICLE_POSITION, Faults, example_topics,
                        make_metadata, write_contract_bag, write_foreign_bag)
from maglev_ros.cli import main

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def topics():
    return example_topics(duration_s=1.0, seed=11)


@pytest.fixture(scope="module")
def meta(topics):
    return make_metadata(topics)


@pytest.fixture(scope="module")
def good_bag(tmp_path_factory, topics, meta):
    return write_contract_bag(tmp_path_factory.mktemp("good") / "bag", meta, topics, block_s=0.1)


def _run(argv, capsys):
    rc = main(argv)
    out, err = capsys.readouterr()
    return rc, out, err


def test_text_report_good_bag(good_bag, topics, capsys):
    rc, out, err = _run(["info", str(good_bag)], capsys)
    assert rc == 0 and err == ""
    assert "storage:   mcap" in out
    assert "contract:  OK" in out
    for topic, (channels, units, rate, data) in topics.items():
        line = next(ln for ln in out.splitlines() if ln.startswith(f"  {topic} "))
        assert "maglev_msgs/msg/SensorBlock" in line
        assert f"{int(round(1.0 / 0.1))} msg" in line                   # 1 s in 0.1 s blocks
        assert f"{rate:g} Hz" in line and f"{len(data)} samples/channel" in line
        for ch, u in zip(channels, units):
            assert f"{ch} [{u}]" in out
    assert "/testline/metadata  std_msgs/msg/String  1 msg" in out
    assert "run pass at 6.944 m/s" in out
    assert "(1.000 s)" in out                          # header-stamp span of the data


def test_json_report_good_bag(good_bag, topics, meta, capsys):
    rc, out, err = _run(["info", "--json", str(good_bag)], capsys)
    assert rc == 0 and err == ""
    rep = json.loads(out)
    assert rep["ok"] is True and rep["errors"] == 0 and rep["issues"] == []
    assert rep["storage"] == "mcap"
    assert rep["message_count"] == 1 + 10 * len(topics)
    by = {t["topic"]: t for t in rep["topics"]}
    for topic, (channels, units, rate, data) in topics.items():
        t = by[topic]
        assert t["type"] == "maglev_msgs/msg/SensorBlock" and t["count"] == 10
        assert t["channels"] == list(channels) and t["units"] == list(units)
        assert t["sample_rate_hz"] == rate
        assert t["stats"]["samples"] == len(data)
        assert t["stats"]["sample_rates_hz"] == [rate]
        assert t["metadata_sensors"] == list(channels)
    assert rep["data_span"]["duration_s"] == pytest.approx(1.0, abs=1e-9)
    assert rep["metadata"]["run_kind"] == "pass"
    assert rep["metadata"]["magnet_offsets_m"] == meta["vehicle"]["magnet_offsets_m"]


def test_warnings_do_not_fail(tmp_path, topics, meta, capsys):
    path = write_foreign_bag(tmp_path / "b", meta, topics, block_samples=100,
                             faults=Faults(drop={GUIDEWAY_ACCEL: [3]},
                                           units={VEHICLE_POSITION: {"speed_mps": "km/h"}}))
    rc, out, err = _run(["info", str(path)], capsys)
    assert rc == 0 and err == ""
    assert "0 error(s), 2 warning(s)" in out
    assert "gap" in out and "km/h" in out and "0.277777778" in out
    rc, out, _ = _run(["info", "--json", str(path)], capsys)
    rep = json.loads(out)
    assert rc == 0 and rep["ok"] and rep["warnings"] == 2
    assert {i["kind"] for i in rep["issues"]} == {"gap", "non_si_unit"}


def test_nan_bag_prints_report_then_one_line_error(tmp_path, topics, meta, capsys):
    path = write_foreign_bag(tmp_path / "b", meta, topics, block_samples=100,
                             faults=Faults(nan={VEHICLE_GAP: [(1, 2, 0)]}))
    rc, out, err = _run(["info", str(path)], capsys)
    assert rc == 1
    assert "1 error(s)" in out and "nan" in out and "/testline/vehicle/gap [M1G]" in out
    lines = err.strip().splitlines()
    assert len(lines) == 1
    assert lines[0].startswith(f"maglev-ros info: error: {path}: 1 contract error(s)")
    assert "nan" in lines[0] and "M1G" in lines[0]
    rc, out, err = _run(["info", "--json", str(path)], capsys)
    rep = json.loads(out)
    assert rc == 1 and rep["ok"] is False and rep["errors"] == 1
    (issue,) = [i for i in rep["issues"] if i["severity"] == "error"]
    assert issue["channel"] == "M1G" and issue["kind"] == "nan"
    # sample 2 of block 1 (100 samples at 1 kHz) -> 0.102 s after the first stamp
    assert issue["time_s"] - rep["start_time_s"] == pytest.approx(0.102, abs=1e-6)
    assert len(err.strip().splitlines()) == 1


@pytest.mark.parametrize("case", ["truncated", "missing_key", "no_metadata", "not_a_bag"])
def test_bad_bags_exit_1_with_one_line(tmp_path, topics, meta, capsys, case):
    if case == "truncated":
        path = write_foreign_bag(tmp_path / "b", meta, topics, faults=Faults(truncate_fraction=0.6))
        expect = "truncated"
    elif case == "missing_key":
        path = write_foreign_bag(tmp_path / "b", meta, topics,
                                 faults=Faults(missing_metadata_key="vehicle.magnet_offsets_m"))
        expect = "metadata key vehicle.magnet_offsets_m: missing"
    elif case == "no_metadata":
        path = write_foreign_bag(tmp_path / "b", meta, topics, faults=Faults(no_metadata=True))
        expect = "/testline/metadata missing"
    else:
        path = tmp_path / "x.txt"
        path.write_text("x")
        expect = "not a bag"
    for argv in (["info", str(path)], ["info", "--json", str(path)]):
        rc, out, err = _run(argv, capsys)
        assert rc == 1 and out == ""
        lines = err.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith(f"maglev-ros info: error: {path}: ")
        assert expect in lines[0]


def test_console_entry_in_subprocess(tmp_path, topics, meta):
    """The real process: exit codes and streams as a user sees them (no traceback)."""
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    good = write_contract_bag(tmp_path / "good", meta, topics)
    res = subprocess.run([sys.executable, "-m", "maglev_ros.cli", "info", "--json", str(good)],
                         capture_output=True, text=True, env=env, cwd=ROOT, timeout=120)
    assert res.returncode == 0 and json.loads(res.stdout)["ok"]
    bad = write_foreign_bag(tmp_path / "bad", meta, topics, faults=Faults(truncate_fraction=0.3))
    res = subprocess.run([sys.executable, "-m", "maglev_ros.cli", "info", str(bad)],
                         capture_output=True, text=True, env=env, cwd=ROOT, timeout=120)
    assert res.returncode == 1 and "Traceback" not in res.stderr
    assert len(res.stderr.strip().splitlines()) == 1


def test_no_check_option(good_bag, capsys):
    rc, out, _ = _run(["info", "--no-check", str(good_bag)], capsys)
    assert rc == 0 and "not checked" in out
    rep = json.loads(_run(["info", "--no-check", "--json", str(good_bag)], capsys)[1])
    assert rep["checked"] is False and rep["data_span"] is None
    assert all("stats" not in t for t in rep["topics"])
    assert np.isclose(rep["start_time_s"], 0.0)
