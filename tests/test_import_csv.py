"""`maglev-ros import` of CSV exports as they come from a DAQ, and of mistakes in what is given.

- a messy but well-described file (preamble lines, ';' and decimal comma, a units row, trailing
  delimiters, a blank line, one missing row, mm and g) imports right: the gap is kept and named
  by the file line after it, the values are the written ones in SI;
- a broken file fails with one line naming the file line and the problem, and leaves no bag;
- a bad spec or metadata fails with one line naming the file and the key; an earlier bag at the
  output path stays as it was, and a failure while writing leaves nothing behind;
- a topic's channels at different rates are refused, or interpolated with ``resample: true``;
- position and speed are completed from each other (analytic references: x = x0 + v t).
"""
from __future__ import annotations

import hashlib
import json

import numpy as np
import pytest
import yaml

from maglev_ros.bag_reader import BagReader
from maglev_ros.cli import main as cli

GA, GAP, POS = "/testline/guideway/accel", "/testline/vehicle/gap", "/testline/vehicle/position"
G = 9.80665
RATE = 1000.0
N = 400
T0_ISO, T0_NS = "2026-04-12T10:31:00Z", 1_775_989_860 * 10**9


def _truth():
    t = np.arange(N) / RATE
    return {"G1LV": 0.3 * np.sin(2 * np.pi * 7 * t), "G2LV": 0.2 * np.cos(2 * np.pi * 11 * t) + 0.01,
            "M1G": 0.010 + 0.001 * np.sin(2 * np.pi * 3 * t)}


TRUTH = _truth()
COLS = {"G1LV": ("Acc G1 left", "g", G), "G2LV": ("Acc G2 left", "g", G), "M1G": ("Gap 1", "mm", 1e-3)}


def _metadata(tmp_path, drop_speed=False, **edit):
    from bagfactory import make_metadata

    topics = {GA: (("G1LV", "G2LV"),), GAP: (("M1G",),), POS: (("position_m", "speed_mps"),)}
    doc = make_metadata(topics)
    if drop_speed:
        del doc["sensors"]["speed_mps"]
    for path, val in edit.items():
        obj = doc
        keys = path.split("__")
        for k in keys[:-1]:
            obj = obj[k]
        if val is None:
            del obj[keys[-1]]
        else:
            obj[keys[-1]] = val
    p = tmp_path / "metadata.yaml"
    p.write_text(yaml.safe_dump(doc, sort_keys=False))
    return p


def _write_messy(path, drop=(), dup=(), bad=None, short=None, swap=None, empty=None):
    """The messy export; returns {sample index: file line number} of the rows written."""
    lines = ["Dewesoft X3 export;;;;", "Project;Testline S3;;;", "Sample rate;1000 Hz;;;", "",
             "Time;Acc G1 left;Acc G2 left;Gap 1;", "[s];[g];[g];[mm];"]
    order = list(range(N))
    if swap is not None:
        order[swap], order[swap + 1] = order[swap + 1], order[swap]
    where = {}
    for k, i in enumerate(order):
        if i in drop:
            continue
        if k == 200:
            lines.append("")                                   # a blank line inside the data
        cells = [f"{i / RATE:.3f}"] + [f"{TRUTH[c][i] / COLS[c][2]:.9g}" for c in ("G1LV", "G2LV", "M1G")]
        cells = [x.replace(".", ",") for x in cells]
        if bad == i:
            cells[3] = "12,3x"
        if empty == i:
            cells[2] = ""
        if short == i:
            cells = cells[:3]
        for _ in range(2 if i in dup else 1):
            lines.append(";".join(cells) + ";")
            where.setdefault(i, len(lines))
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return where


def _spec(tmp_path, md, extra_channels=None, **top):
    doc = {"metadata": md.name,
           "source": {"file": "run.csv", "delimiter": ";", "decimal": ",", "header_rows": 4,
                      "units_row": True, "time": {"column": "Time", "unit": "s", "start": T0_ISO}},
           "block_s": 0.05,
           "channels": {c: {"column": COLS[c][0], "unit": COLS[c][1]} for c in COLS}}
    doc["channels"].update(extra_channels or {})
    doc.update(top)
    p = tmp_path / "import.yaml"
    p.write_text(yaml.safe_dump(doc, sort_keys=False))
    return p


def _run(args, capsys):
    rc = cli(args)
    cap = capsys.readouterr()
    return rc, cap.out, cap.err.strip()


@pytest.mark.parametrize("chunk_rows", [50_000, 64])
def test_messy_but_described_csv_imports_right(tmp_path, capsys, monkeypatch, chunk_rows):
    from maglev_ros.daq_import import readers

    monkeypatch.setattr(readers, "_CSV_CHUNK_ROWS", chunk_rows)     # 64: the gap inside chunk 1
    where = _write_messy(tmp_path / "run.csv", drop=(57,))
    spec = _spec(tmp_path, _metadata(tmp_path))
    out, js = tmp_path / "bag", tmp_path / "imp.json"
    rc, text, err = _run(["import", str(spec), "--out", str(out), "--json", str(js)], capsys)
    assert rc == 0, err
    rep = json.loads(js.read_text())
    (ga,) = [t for t in rep["topics"] if t["topic"] == GA]
    assert ga["rate_hz"] == RATE and ga["n_samples"] == N - 1
    assert [(g["where"], g["missing"]) for g in ga["gaps"]] == [(f"line {where[58]}", 1)]
    assert ga["gaps"][0]["gap_s"] == pytest.approx(2 / RATE)
    assert f"before line {where[58]}" in text
    conv = {c["channel"]: (c["unit"], c["factor"], c["unit_from"]) for c in rep["conversions"]}
    assert conv == {"G1LV": ("g", G, "spec"), "G2LV": ("g", G, "spec"), "M1G": ("mm", 1e-3, "spec")}
    keep = np.delete(np.arange(N), 57)
    with BagReader(out) as bag:
        issues = bag.check()
        assert [i.kind for i in issues if i.severity == "error"] == []
        assert {i.kind for i in issues if i.topic == GA} == {"gap"}
        for topic, chans in ((GA, ("G1LV", "G2LV")), (GAP, ("M1G",))):
            blocks = [b for _, b in bag.iter_blocks([topic])]
            data = np.concatenate([b.data for b in blocks])
            for j, c in enumerate(chans):
                np.testing.assert_allclose(data[:, j], TRUTH[c][keep].astype(np.float32), rtol=1e-6,
                                           atol=1e-7 * np.abs(TRUTH[c]).max())
            stamps = np.concatenate([b.stamp_ns + np.round(np.arange(b.n_samples) * 1e9 / RATE).astype(np.int64)
                                     for b in blocks])
            np.testing.assert_array_equal(stamps, T0_NS + np.round(keep * 1e9 / RATE).astype(np.int64))
            assert blocks[0].units == (("m/s^2",) * 2 if topic == GA else ("m",))


def test_gaps_fail_refuses_a_gap_naming_the_line(tmp_path, capsys):
    where = _write_messy(tmp_path / "run.csv", drop=(57,))
    spec = _spec(tmp_path, _metadata(tmp_path), gaps="fail")
    rc, _, err = _run(["import", str(spec), "--out", str(tmp_path / "bag")], capsys)
    assert rc == 1 and "\n" not in err
    assert f"line {where[58]}: gap of 0.002 s (~1 samples missing) before it (gaps: fail)" in err
    assert not (tmp_path / "bag").exists()


@pytest.mark.parametrize("fault, sample, message", [
    ({"dup": (120,)}, 120, "duplicated time"),
    ({"swap": 300}, 300, "time goes backwards"),
    ({"bad": 77}, 77, "column 'Gap 1': '12,3x' is not a number"),
    ({"empty": 90}, 90, "column 'Acc G2 left': empty cell"),
    ({"short": 33}, 33, "4 fields, expected 5 (as in the names row)"),
])
def test_broken_csv_fails_naming_the_line(tmp_path, capsys, monkeypatch, fault, sample, message):
    from maglev_ros.daq_import import readers

    monkeypatch.setattr(readers, "_CSV_CHUNK_ROWS", 50)     # the faults lie in later chunks
    where = _write_messy(tmp_path / "run.csv", **fault)
    line = where[sample] + (1 if "dup" in fault else 0)
    if "swap" in fault:
        line = where[sample]                     # sample 300 written after 301: its line is the bad one
    spec = _spec(tmp_path, _metadata(tmp_path))
    out = tmp_path / "bag"
    rc, _, err = _run(["import", str(spec), "--out", str(out)], capsys)
    assert rc == 1
    assert "\n" not in err and "Traceback" not in err
    assert f"run.csv: line {line}" in err and message in err, err
    assert not out.exists() and not list(tmp_path.glob(".bag*"))


@pytest.mark.parametrize("edit_spec, edit_md, expect", [
    ({"chanels": {}}, {}, "import.yaml: key chanels: unknown key"),
    ({"extra_channels": {"G9LV": {"column": "x", "unit": "g"}}}, {}, "import.yaml: key channels.G9LV: not a sensor"),
    ({"extra_channels": {"G1LV": {"column": "Acc G1 left", "unit": "mm"}}}, {},
     "import.yaml: key channels.G1LV.unit: /testline/guideway/accel [G1LV]: unit 'mm' measures in 'm'; "
     "the contract expects 'm/s^2'"),
    ({"extra_channels": {"G1LV": {"column": "Acc G1 left", "unit": "m/s^2"}}}, {},
     "import.yaml: key channels.G1LV.unit: 'm/s^2' but "),
    ({"extra_channels": {"G1LV": {"column": "Acc G1 left", "unit": "furlong"}}}, {},
     "import.yaml: key channels.G1LV.unit: "),
    ({"extra_channels": {"G1LV": {"column": "Acc G7", "unit": "g"}}}, {}, "run.csv: no column 'Acc G7'"),
    ({"block_s": -1}, {}, "import.yaml: key block_s: expected a number > 0"),
    ({}, {"run__kind": None}, "metadata.yaml: metadata key run.kind: missing"),
    ({}, {"sensors__G1LV__side": "up"}, "metadata.yaml: metadata key sensors.G1LV.side: expected one of"),
    ({}, {"vehicle__magnet_offsets_m": "front"}, "metadata.yaml: metadata key vehicle.magnet_offsets_m"),
])
def test_bad_spec_or_metadata_is_one_line_and_keeps_the_old_bag(tmp_path, capsys, edit_spec, edit_md, expect):
    _write_messy(tmp_path / "run.csv")
    good = _spec(tmp_path, _metadata(tmp_path))
    out = tmp_path / "bag"
    assert cli(["import", str(good), "--out", str(out)]) == 0
    capsys.readouterr()
    before = {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in out.iterdir()}
    md = _metadata(tmp_path, **edit_md)
    extra = edit_spec.pop("extra_channels", None)
    spec = _spec(tmp_path, md, extra, **edit_spec)
    rc, _, err = _run(["import", str(spec), "--out", str(out), "--overwrite"], capsys)
    assert rc == 1 and "\n" not in err and expect in err, err
    if "furlong" in str(edit_spec):
        assert "not in the contract's unit table" in err
    assert {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in out.iterdir()} == before
    assert not list(tmp_path.glob(".bag*"))


def test_spec_yaml_syntax_error_names_the_line(tmp_path, capsys):
    p = tmp_path / "import.yaml"
    p.write_text("metadata: metadata.yaml\nsource: {file: run.csv\nchannels: {}\n")
    rc, _, err = _run(["import", str(p), "--out", str(tmp_path / "bag")], capsys)
    assert rc == 1 and err.startswith(f"maglev-ros import: error: {p}: not valid YAML at line")


def test_failure_while_writing_leaves_no_bag(tmp_path, monkeypatch):
    from maglev_ros.bag_writer import BagWriter
    from maglev_ros.errors import UserError

    _write_messy(tmp_path / "run.csv")
    spec = _spec(tmp_path, _metadata(tmp_path))
    real, calls = BagWriter.write_block, []

    def failing(self, topic, block, log_time_ns=None):
        calls.append(topic)
        if len(calls) == 5:
            raise UserError("disk gone")
        return real(self, topic, block, log_time_ns)
    monkeypatch.setattr(BagWriter, "write_block", failing)
    assert cli(["import", str(spec), "--out", str(tmp_path / "bag")]) == 1
    assert len(calls) == 5
    assert not (tmp_path / "bag").exists() and not list(tmp_path.glob(".bag*"))


def _two_files(tmp_path, rate2, linear=False):
    """run.csv at 1 kHz, slow.csv with G2LV at rate2 (a linear signal when ``linear``)."""
    _write_messy(tmp_path / "run.csv")
    n2 = int(N / RATE * rate2)
    t2 = np.arange(n2) / rate2
    v = 0.5 + 2.0 * t2 if linear else np.sin(t2)
    rows = ["t,a"] + [f"{a!r},{b!r}" for a, b in zip(t2.tolist(), (v / G).tolist())]
    (tmp_path / "slow.csv").write_text("\n".join(rows) + "\n")
    return {"G2LV": {"column": "a", "unit": "g",
                     "source": {"file": "slow.csv", "delimiter": ",", "decimal": ".", "header_rows": 0,
                                "units_row": False, "time": {"column": "t", "start": T0_ISO}}}}


def test_topic_rates_differ_refused_unless_resample(tmp_path, capsys):
    extra = _two_files(tmp_path, 250.0, linear=True)
    md = _metadata(tmp_path)
    rc, _, err = _run(["import", str(_spec(tmp_path, md, extra)), "--out", str(tmp_path / "bag")], capsys)
    assert rc == 1 and "\n" not in err
    assert f"topic {GA}: channels G1LV (1000 Hz) and G2LV (250 Hz) differ in sample rate" in err
    assert "resample: true" in err and not (tmp_path / "bag").exists()
    js = tmp_path / "imp.json"
    spec = _spec(tmp_path, md, extra, resample=True)
    assert cli(["import", str(spec), "--out", str(tmp_path / "bag"), "--json", str(js)]) == 0
    (ga,) = [t for t in json.loads(js.read_text())["topics"] if t["topic"] == GA]
    assert ga["resampled"] == ["G2LV"] and ga["rate_hz"] == RATE
    with BagReader(tmp_path / "bag") as bag:
        blocks = [b for _, b in bag.iter_blocks([GA])]
    data = np.concatenate([b.data for b in blocks])
    # the slow channel ends at (n2 - 1) / 250 s: the grid is cut where every channel has data
    n_common = int((N / RATE * 250 - 1) / 250 * RATE) + 1
    t = np.arange(n_common) / RATE
    assert data.shape[0] == n_common
    # linear interpolation of a linear signal is exact
    np.testing.assert_allclose(data[:, 1], (0.5 + 2.0 * t).astype(np.float32), rtol=2e-6)
    np.testing.assert_allclose(data[:, 0], TRUTH["G1LV"][:n_common].astype(np.float32), rtol=1e-6, atol=1e-7)


def _pos_csv(tmp_path, drop=()):
    # 10 s: the health check's stamp-rate windows (200 samples) must not all span the gap
    t = np.arange(1000) / 100.0
    keep = [i for i in range(t.size) if i not in drop]
    rows = ["Time,Pos,v"] + [f"{float(t[i])!r},{float(5.0 + 7.0 * t[i])!r},{7.0 * 3.6!r}" for i in keep]
    (tmp_path / "pos.csv").write_text("\n".join(rows) + "\n")
    return t[keep]


def _pos_spec(tmp_path, md, which, **top):
    src = {"file": "pos.csv", "time": {"column": "Time", "start": T0_ISO}}
    chans = {"position_m": {"column": "Pos", "unit": "m"}, "speed_mps": {"column": "v", "unit": "km/h"}}
    doc = {"metadata": md.name, "source": src, "channels": {c: chans[c] for c in which}}
    doc.update(top)
    p = tmp_path / "import.yaml"
    p.write_text(yaml.safe_dump(doc, sort_keys=False))
    return p


def _read_pos(out):
    with BagReader(out) as bag:
        blocks = [b for _, b in bag.iter_blocks([POS])]
        assert [i for i in bag.check() if i.severity == "error"] == []
        md = bag.metadata
    return blocks[0].channels, np.concatenate([b.data for b in blocks]), md


def test_speed_differentiated_from_position(tmp_path, capsys):
    _pos_csv(tmp_path)
    md = _metadata(tmp_path, drop_speed=True)
    rc, text, err = _run(["import", str(_pos_spec(tmp_path, md, ["position_m"])),
                          "--out", str(tmp_path / "bag")], capsys)
    assert rc == 0, err
    assert "derived:   speed_mps: differentiated from position_m" in text
    assert "sensor speed_mps added" in text
    chans, data, meta = _read_pos(tmp_path / "bag")
    assert chans == ("position_m", "speed_mps") and meta.sensors["speed_mps"].topic == POS
    np.testing.assert_allclose(data[:, 1], 7.0, rtol=1e-5)          # d/dt (5 + 7 t)


def test_position_integrated_from_speed_across_a_gap(tmp_path, capsys):
    t = _pos_csv(tmp_path, drop=(80, 81, 82))
    md = _metadata(tmp_path)
    rc, _, err = _run(["import", str(_pos_spec(tmp_path, md, ["speed_mps"])), "--out", str(tmp_path / "b0")],
                      capsys)
    assert rc == 1 and "import.yaml: key position_start_m: missing" in err
    rc, text, err = _run(["import", str(_pos_spec(tmp_path, md, ["speed_mps"], position_start_m=5.0)),
                          "--out", str(tmp_path / "bag")], capsys)
    assert rc == 0, err
    assert "derived:   position_m: integrated from speed_mps" in text
    _, data, _ = _read_pos(tmp_path / "bag")
    np.testing.assert_allclose(data[:, 0], (5.0 + 7.0 * t).astype(np.float32), rtol=1e-6)
    np.testing.assert_allclose(data[:, 1], 7.0, rtol=1e-6)


def test_flags_for_one_file_without_time_column(tmp_path, capsys):
    """The simple case without a spec: a headerless-time CSV at a stated rate."""
    lines = ["acc,gap"] + [f"{float(TRUTH['G1LV'][i] / G)!r},{float(TRUTH['M1G'][i] * 1e3)!r}" for i in range(N)]
    (tmp_path / "plain.csv").write_text("\n".join(lines) + "\n")
    md = _metadata(tmp_path)
    rc, text, err = _run(["import", str(tmp_path / "plain.csv"), "--metadata", str(md),
                          "--channel", "G1LV", "acc", "g", "--channel", "M1G", "gap", "mm",
                          "--rate-hz", "1000", "--start", T0_ISO, "--out", str(tmp_path / "bag")], capsys)
    assert rc == 0, err
    assert "(from stated rate)" in text
    with BagReader(tmp_path / "bag") as bag:
        blocks = [b for _, b in bag.iter_blocks([GAP])]
    assert blocks[0].stamp_ns == T0_NS and blocks[0].sample_rate_hz == RATE
    np.testing.assert_allclose(np.concatenate([b.data for b in blocks])[:, 0],
                               TRUTH["M1G"].astype(np.float32), rtol=1e-6)


def test_metadata_init_and_check(tmp_path, capsys):
    from maglev_ros.contract import metadata_from_dict

    out = tmp_path / "metadata.yaml"
    assert cli(["metadata", "init", "--out", str(out)]) == 0
    doc = yaml.safe_load(out.read_text().replace("e10", ".0e+10"))    # plain PyYAML reads it too
    md = metadata_from_dict(doc, "template")
    assert md.run_kind == "pass" and len(md.magnet_offsets_m) == 8 and md.design is not None
    assert all(s.span in {sp.id for sp in md.spans} for s in md.sensors.values() if s.span)
    rc, text, _ = _run(["metadata", "check", str(out)], capsys)
    assert rc == 0 and "OK" in text
    rc, _, err = _run(["metadata", "init", "--out", str(out)], capsys)
    assert rc == 1 and "already exists" in err
    out.write_text(out.read_text().replace("kind: pass", "kind: passing"))
    rc, _, err = _run(["metadata", "check", str(out)], capsys)
    assert rc == 1 and "\n" not in err
    assert f"{out}: metadata key run.kind: expected one of pass, ambient, got 'passing'" in err
