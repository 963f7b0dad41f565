"""Issue 27, sensor health: damaged recordings land in a clear one-line error, a warning with a
correct result, or an exclusion the output states; never a silently wrong result.

Each damaged bag is built here from an undamaged one (bagfactory's writer; the magnet pass of
irregularity_data, the guideway modes of modal_data) and the verb's result on it is compared with
its result on the undamaged bag: a converted unit must give the SI bag's result, an excluded
channel the result of the bag without that channel.
"""
from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest

from bagfactory import (GUIDEWAY_ACCEL, GUIDEWAY_DISP, VEHICLE_ACCEL, VEHICLE_GAP, VEHICLE_POSITION,
                        example_topics, make_metadata, write_contract_bag)
from irregularity_data import make_recording
from maglev_ros.bag_reader import BagReader
from maglev_ros.bag_writer import BagWriter
from maglev_ros.cli import main
from maglev_ros.errors import UserError
from maglev_ros.sensor_block import Block
from modal_data import guideway_model, simulate_ambient

G = 9.80665
ROOT = Path(__file__).resolve().parents[1]


# ------------------------------------------------------------------------------ recordings
@pytest.fixture(scope="module")
def magnet_pass():
    """{topic: (channels, units, rate, data)} of a 4-magnet pass in SI and its metadata."""
    rec = make_recording(40, 31, "constant", length_m=200.0, fs_hz=500.0,
                         magnet_offsets_m=(0.0, -1.548, -3.096, -4.644))
    topics = {VEHICLE_ACCEL: (rec.accel.channels, rec.accel.units, 500.0, rec.accel.data),
              VEHICLE_GAP: (rec.gap.channels, rec.gap.units, 500.0, rec.gap.data),
              VEHICLE_POSITION: (rec.position.channels, rec.position.units, 100.0, rec.position.data)}
    md = make_metadata({VEHICLE_ACCEL: topics[VEHICLE_ACCEL], VEHICLE_GAP: topics[VEHICLE_GAP]},
                       magnet_offsets_m=rec.magnet_offsets_m, nominal_speed_mps=rec.info["speed_mps"])
    return topics, md


@pytest.fixture(scope="module")
def ambient():
    """15 guideway accelerometers of a span with known modes, 40 s ambient at 500 Hz."""
    model = guideway_model(None)
    y = simulate_ambient(model, 500.0, 40.0, noise_frac=0.05, seed=3)
    topics = {GUIDEWAY_ACCEL: (model.channels, ("m/s^2",) * 15, 500.0, y)}
    return topics, make_metadata(topics, kind="ambient"), model


def _with(topics, topic, channel=None, units=None, data=None, scale=None):
    """A copy of ``topics`` with one topic's unit list, data or one channel changed."""
    out = dict(topics)
    ch, un, rate, d = topics[topic]
    d = np.array(d, dtype=float)
    un = list(un)
    j = None if channel is None else list(ch).index(channel)
    if units is not None:
        if j is None:
            un = [units] * len(un)
        else:
            un[j] = units
    if scale is not None:
        if j is None:
            d = d * scale
        else:
            d[:, j] = d[:, j] * scale
    if data is not None:
        d[:, j] = data(d[:, j])
    out[topic] = (ch, tuple(un), rate, d)
    return out


def _write_shifted(path, md, topics, shift_s=None, stated_hz=None, block_s=0.1):
    """Like bagfactory.write_contract_bag, but one topic's stamps shifted (``shift_s``: {topic: s})
    or its blocks stating another rate than their stamps advance at (``stated_hz``: {topic: Hz})."""
    shift_s, stated_hz = shift_s or {}, stated_hz or {}
    events = []
    for topic, (channels, units, rate, data) in topics.items():
        data = np.asarray(data, np.float32)
        bs = max(1, int(round(block_s * rate)))
        for first in range(0, data.shape[0], bs):
            stamp = int(round((first / rate + shift_s.get(topic, 0.0)) * 1e9))
            events.append((stamp, topic, Block.from_arrays(stamp, stated_hz.get(topic, rate), channels,
                                                           units, data[first:first + bs])))
    events.sort(key=lambda e: (e[0], e[1]))
    with BagWriter(path, md, metadata_stamp_ns=min(e[0] for e in events)) as w:
        for stamp, topic, blk in events:
            w.write_block(topic, blk)
    return path


def _irregularity(bag, tmp_path, capsys, name="p"):
    out, js = tmp_path / f"{name}.csv", tmp_path / f"{name}.json"
    rc = main(["irregularity", str(bag), "--out", str(out), "--json", str(js)])
    cap = capsys.readouterr()
    if rc:
        return rc, cap.err, None, None
    rows = [r for r in csv.reader(l for l in out.read_text().splitlines() if not l.startswith("#"))][1:]
    prof = np.array([[float(a), float(b) if b else np.nan] for a, b in rows])
    return rc, cap.err, prof, json.loads(js.read_text())


def _one_line_error(err, *needles):
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert "Traceback" not in err
    for n in needles:
        assert n in lines[0], (n, lines[0])
    return lines[0]


# ----------------------------------------------------------------------------------- units
def test_units_in_g_um_and_kmh_are_converted_and_give_the_si_result(magnet_pass, tmp_path, capsys):
    topics, md = magnet_pass
    si = write_contract_bag(tmp_path / "si", md, topics)
    bad = _with(_with(topics, VEHICLE_ACCEL, units="g", scale=1 / G), VEHICLE_GAP, units="um", scale=1e6)
    bad = _with(bad, VEHICLE_POSITION, channel="speed_mps", units="km/h", scale=3.6)
    nonsi = write_contract_bag(tmp_path / "nonsi", md, bad)
    rc0, _, ref, _ = _irregularity(si, tmp_path, capsys, "si")
    rc1, err, got, doc = _irregularity(nonsi, tmp_path, capsys, "nonsi")
    assert rc0 == 0 and rc1 == 0
    assert "unit 'g' converted to 'm/s^2'" in err and "unit 'um' converted to 'm'" in err
    assert "unit 'km/h' converted to 'm/s'" in err
    conv = {(c["channel"], c["unit"]) for c in doc["health"]["converted_units"]}
    assert conv == {*((f"M{k}A", "g") for k in range(1, 5)), *((f"M{k}G", "um") for k in range(1, 5)),
                    ("speed_mps", "km/h")}
    np.testing.assert_array_equal(got[:, 0], ref[:, 0])
    m = np.isfinite(ref[:, 1])
    assert m.sum() > 100 and np.array_equal(m, np.isfinite(got[:, 1]))
    # float32 storage of the values in g / um rounds differently: agreement to 1e-4 of the profile
    assert np.max(np.abs(got[m, 1] - ref[m, 1])) <= 1e-4 * np.max(np.abs(ref[m, 1]))


def test_guideway_displacement_in_um_reaches_the_loaders_in_metres(tmp_path):
    topics = example_topics(duration_s=2.0, seed=1)
    disp = np.column_stack([2e-3 * np.sin(np.linspace(0, 20, 2000))]) + 1e-5 * np.random.default_rng(0).standard_normal((2000, 1))
    topics[GUIDEWAY_DISP] = (("D1",), ("m",), 1000.0, disp)
    md = make_metadata(topics)
    si = write_contract_bag(tmp_path / "si", md, topics)
    um = write_contract_bag(tmp_path / "um", md, _with(topics, GUIDEWAY_DISP, units="um", scale=1e6))
    from maglev_ros.discrepancy.recording import load_recording
    a, b = load_recording(si), load_recording(um)
    np.testing.assert_allclose(b.channels["D1"].values, a.channels["D1"].values, rtol=1e-6, atol=1e-12)
    assert [c.to_dict()["unit"] for c in b.health.converted] == ["um"]


@pytest.mark.parametrize("unit, needle", [("furlong/s^2", "is not in the contract's unit table"),
                                          ("mm", "expects 'm/s^2'")])
def test_unknown_or_wrong_kind_unit_is_one_line_error_naming_topic_channel_unit(magnet_pass, tmp_path,
                                                                                capsys, unit, needle):
    topics, md = magnet_pass
    bag = write_contract_bag(tmp_path / "u", md, _with(topics, VEHICLE_ACCEL, channel="M2A", units=unit))
    rc, err, _, _ = _irregularity(bag, tmp_path, capsys)
    assert rc == 1
    _one_line_error(err, VEHICLE_ACCEL, "[M2A]", repr(unit), needle)
    # info keeps reporting it as a warning, as before
    assert main(["info", str(bag), "--json"]) == 0
    rep = json.loads(capsys.readouterr().out)
    assert any(i["kind"] in ("non_si_unit", "unit_mismatch") and i["channel"] == "M2A" for i in rep["issues"])


def test_nodes_and_verbs_share_one_unit_conversion():
    from maglev_ros.bag_reader import ChannelData
    from maglev_ros.health import block_to_si, channel_data_to_si
    x = np.arange(12, dtype=np.float32).reshape(6, 2) / 7
    blk = Block.from_arrays(0, 100.0, ("M1A", "M2A"), ("g", "m/s^2"), x)
    cd = ChannelData(VEHICLE_ACCEL, ("M1A", "M2A"), ("g", "m/s^2"), 100.0, np.arange(6) / 100.0,
                     x.astype(float))
    b, conv_b = block_to_si(VEHICLE_ACCEL, blk)
    c, conv_c = channel_data_to_si(cd)
    assert b.units == c.units == ("m/s^2", "m/s^2") and conv_b == conv_c
    np.testing.assert_array_equal(b.data, (x.astype(float) * [G, 1.0]).astype(np.float32))
    np.testing.assert_allclose(c.data[:, 0], x[:, 0].astype(float) * G)


# ------------------------------------------------------------------------------ stated rate
def test_stated_rate_half_the_stamps_is_an_error_naming_both_rates(magnet_pass, tmp_path, capsys):
    topics, md = magnet_pass
    bag = _write_shifted(tmp_path / "half", md, topics, stated_hz={VEHICLE_GAP: 250.0})
    rc, err, _, _ = _irregularity(bag, tmp_path, capsys)
    assert rc == 1
    _one_line_error(err, VEHICLE_GAP, "500 Hz", "250 Hz")
    assert main(["info", str(bag)]) == 1
    cap = capsys.readouterr()
    assert "rate_mismatch" in cap.out and "500 Hz" in cap.out and "250 Hz" in cap.out
    _one_line_error(cap.err, "rate_mismatch", VEHICLE_GAP)


# ------------------------------------------------------------------------------ time offset
def test_topic_shifted_by_an_hour_is_an_error_naming_topic_and_offset(magnet_pass, tmp_path, capsys):
    topics, md = magnet_pass
    bag = _write_shifted(tmp_path / "late", md, topics, shift_s={VEHICLE_POSITION: 3600.0})
    rc, err, _, _ = _irregularity(bag, tmp_path, capsys)
    assert rc == 1
    line = _one_line_error(err, VEHICLE_POSITION, "do not overlap", "offset +3600")
    assert VEHICLE_ACCEL not in line.split("offset")[0].split(":")[1]   # names the shifted topic
    assert main(["info", str(bag), "--json"]) == 1
    rep = json.loads(capsys.readouterr().out)
    off = [i for i in rep["issues"] if i["kind"] == "time_offset"]
    assert [i["topic"] for i in off] == [VEHICLE_POSITION] and "+3600" in off[0]["message"]


# --------------------------------------------------------------------- flat / clipped / x1e30
def test_flat_midspan_accelerometer_is_excluded_and_modes_stay_right(ambient, tmp_path, capsys):
    topics, md, model = ambient
    ok = write_contract_bag(tmp_path / "ok", md, topics)
    flat = write_contract_bag(tmp_path / "flat", md, _with(topics, GUIDEWAY_ACCEL, channel="G3LV",
                                                          data=lambda x: np.full_like(x, 0.0123)))
    assert main(["modes", str(ok), "--json", str(tmp_path / "ok.json")]) == 0
    capsys.readouterr()
    assert main(["modes", str(flat), "--json", str(tmp_path / "flat.json")]) == 0
    err = capsys.readouterr().err
    assert "[G3LV]" in err and "flat-lined" in err and "excluded from the analysis" in err
    ref, got = (json.loads((tmp_path / f"{n}.json").read_text()) for n in ("ok", "flat"))
    assert [e["channel"] for e in got["health"]["excluded_channels"]] == ["G3LV"]
    assert "G3LV" not in got["source"]["channels"] and all("G3LV" not in m["mode_shape"] for m in got["modes"])
    f_ref = sorted(m["frequency_hz"] for m in ref["modes"])
    f_got = sorted(m["frequency_hz"] for m in got["modes"])
    assert len(f_ref) == len(f_got) >= 5
    # the same modes as without the fault, each within 0.5 % of the model's frequency
    for fr, fg in zip(f_ref, f_got):
        assert abs(fg / fr - 1) < 0.005
    true = model.frequency_hz[model.frequency_hz < 0.4 * 500.0]
    assert all(np.min(np.abs(np.array(f_got) - f)) / f < 0.01 for f in true)
    # info: a warning, exit 0
    assert main(["info", str(flat)]) == 0
    out = capsys.readouterr().out
    assert "flat" in out and "G3LV" in out


def test_every_guideway_channel_x1e30_is_one_line_error(ambient, tmp_path, capsys):
    topics, md, _ = ambient
    bag = write_contract_bag(tmp_path / "huge", md, _with(topics, GUIDEWAY_ACCEL, scale=1e30))
    assert main(["modes", str(bag)]) == 1
    _one_line_error(capsys.readouterr().err, GUIDEWAY_ACCEL, "implausible", "cannot be left out")
    assert main(["info", str(bag)]) == 0              # info: warnings (exit 0), one per channel
    assert sum("implausible" in line for line in capsys.readouterr().out.splitlines()) == 15


@pytest.mark.parametrize("fault", ["flat", "x1e30", "clipped"])
def test_only_sensor_of_a_magnet_damaged_is_one_line_error(magnet_pass, tmp_path, capsys, fault):
    topics, md = magnet_pass
    ch, _, _, d = topics[VEHICLE_GAP if fault == "flat" else VEHICLE_ACCEL]
    if fault == "flat":
        bad = _with(topics, VEHICLE_GAP, channel="M2G", data=lambda x: np.full_like(x, 0.0101))
    elif fault == "x1e30":
        bad = _with(topics, VEHICLE_ACCEL, channel="M2A", scale=1e30)
    else:
        lim = 0.5 * np.max(np.abs(d[:, 1]))
        bad = _with(topics, VEHICLE_ACCEL, channel="M2A", data=lambda x: np.clip(x, -lim, lim))
    bag = write_contract_bag(tmp_path / fault, md, bad)
    rc, err, _, _ = _irregularity(bag, tmp_path, capsys)
    assert rc == 1
    word = {"flat": "flat-lined", "x1e30": "implausible", "clipped": "clipped"}[fault]
    _one_line_error(err, "[M2G]" if fault == "flat" else "[M2A]", word, "magnet 2")


def test_clipped_guideway_channel_is_excluded_by_the_loaders_and_warned_by_info(tmp_path, capsys):
    topics = example_topics(duration_s=4.0, seed=2)
    d = topics[GUIDEWAY_ACCEL][3]
    lim = 0.6 * np.max(np.abs(d[:, 1]))
    md = make_metadata(topics)
    bag = write_contract_bag(tmp_path / "clip", md, _with(topics, GUIDEWAY_ACCEL, channel="G2LV",
                                                         data=lambda x: np.clip(x, -lim, lim)))
    from maglev_ros.discrepancy.recording import load_recording
    rec = load_recording(bag)
    assert "G2LV" not in rec.channels and {"G1LV", "G3LV"} <= set(rec.channels)
    assert [(e.channel, e.kind) for e in rec.health.excluded] == [("G2LV", "clipped")]
    assert main(["info", str(bag)]) == 0
    out = capsys.readouterr().out
    assert "clipped" in out and "G2LV" in out and "contract:  0 error(s)" in out


def test_quantised_channel_is_not_called_clipped_or_flat(tmp_path, capsys):
    """A 16-bit gap sensor on a slow signal reaches its peaks by one step: neither clipped nor flat."""
    topics = example_topics(duration_s=4.0, seed=4)
    lsb = 20e-3 / 2 ** 16
    md = make_metadata(topics)
    bag = write_contract_bag(tmp_path / "q", md, _with(topics, VEHICLE_GAP, channel="M1G",
                                                      data=lambda x: np.round(x / lsb) * lsb))
    assert main(["info", str(bag), "--json"]) == 0
    rep = json.loads(capsys.readouterr().out)
    assert not [i for i in rep["issues"] if i["kind"] in ("clipped", "flat", "implausible")]


def test_gap_in_metres_labelled_mm_is_refused_as_implausible(magnet_pass, tmp_path, capsys):
    topics, md = magnet_pass
    bag = write_contract_bag(tmp_path / "mm", md, _with(topics, VEHICLE_GAP, units="mm"))
    rc, err, _, _ = _irregularity(bag, tmp_path, capsys)
    assert rc == 1
    _one_line_error(err, VEHICLE_GAP, "median gap", "after converting 'mm' to 'm'")


# ------------------------------------------------------------------------------ sensor map
@pytest.mark.parametrize("edit, needle", [
    (lambda md: md.update(sensors={}), "metadata key sensors: names no sensors"),
    (lambda md: md["sensors"].pop("M3A"), "metadata key sensors.M3A: missing"),
    (lambda md: md["sensors"]["M2G"].pop("magnet"), "metadata key sensors.M2G.magnet: missing")])
def test_sensor_map_missing_is_one_line_error_not_assignment_by_order(magnet_pass, tmp_path, capsys,
                                                                      edit, needle):
    topics, md = magnet_pass
    md = json.loads(json.dumps(md))
    edit(md)
    bag = write_contract_bag(tmp_path / "map", md, topics)
    rc, err, _, _ = _irregularity(bag, tmp_path, capsys)
    assert rc == 1
    _one_line_error(err, needle)
    from maglev_ros.discrepancy.recording import load_recording
    from maglev_ros.updating.pipeline import read_pass
    for loader in (load_recording, read_pass):
        with pytest.raises(UserError, match=needle.replace(".", r"\.")):
            loader(bag)
    assert main(["info", str(bag)]) == 0          # info: warnings only


def test_read_checked_reports_nothing_on_the_sample_bags():
    for name in ("paper_ambient", "paper_pass"):
        with BagReader(ROOT / "bags" / name) as bag:
            read, health = bag.read_checked(bag.sensor_topics, sensor_map=True)
            assert bag.check() == []
        assert health.warnings == () and health.excluded == ()
        assert all(cd.n_samples > 0 for cd in read.values())


# ------------------------------------------------------------- update / diagnose loaders
def test_update_and_diagnose_loaders_read_g_as_the_si_bag(magnet_pass, tmp_path):
    """kp from accelerations in g read as m/s^2 came out 3575 instead of 9425: the loaders of
    update (read_pass) and diagnose (load_recording) now see the SI values."""
    from maglev_ros.discrepancy.recording import load_recording
    from maglev_ros.updating.pipeline import read_pass
    topics, md = magnet_pass
    si = write_contract_bag(tmp_path / "si", md, topics)
    g = write_contract_bag(tmp_path / "g", md, _with(topics, VEHICLE_ACCEL, units="g", scale=1 / G))
    from maglev_ros.twin.design import twin_config_from_metadata
    with BagReader(ROOT / "bags" / "paper_pass") as r:      # any twin: the bags have no displacement
        cfg = twin_config_from_metadata(r.metadata.raw)
    a, b = read_pass(si, cfg), read_pass(g, cfg)
    assert b.accel.units == ("m/s^2",) * 4
    np.testing.assert_allclose(b.accel.data, a.accel.data, rtol=2e-7, atol=1e-9)
    assert [c["unit"] for c in b.info["health"]["converted_units"]] == ["g"] * 4
    ra, rb = load_recording(si), load_recording(g)
    np.testing.assert_allclose(rb.channels["M2A"].values, ra.channels["M2A"].values, rtol=2e-7, atol=1e-9)


def test_half_stated_rate_stops_the_diagnosis_loader(magnet_pass, tmp_path):
    """A rate stated at half the stamps' made a rail 15x too rough and 'missing physics: none'."""
    from maglev_ros.discrepancy.recording import load_recording
    topics, md = magnet_pass
    bag = _write_shifted(tmp_path / "half", md, topics, stated_hz={VEHICLE_ACCEL: 250.0})
    with pytest.raises(UserError, match=r"vehicle/accel: header stamps advance at 500 Hz but "
                                        r"sample_rate_hz says 250 Hz") as ei:
        load_recording(bag)
    assert "\n" not in str(ei.value)


def test_update_ambient_loader_leaves_the_flat_accelerometer_out(ambient, tmp_path):
    from maglev_ros.updating.pipeline import identify_ambient
    topics, md, model = ambient
    bag = write_contract_bag(tmp_path / "flat", md, _with(topics, GUIDEWAY_ACCEL, channel="G3LV",
                                                         data=lambda x: np.zeros_like(x)))
    _, res, info = identify_ambient(bag, fmax_hz=150.0)
    assert "G3LV" not in info["channels"] and len(info["channels"]) == 14
    assert [e["channel"] for e in info["health"]["excluded_channels"]] == ["G3LV"]
    f = np.array([m.frequency_hz for m in res.modes])
    for f0 in model.frequency_hz[model.frequency_hz < 150.0]:
        assert np.min(np.abs(f - f0)) / f0 < 0.01


def test_update_and_diagnose_commands_refuse_damaged_bags_in_one_line(magnet_pass, ambient, tmp_path, capsys):
    topics, md = magnet_pass
    late = _write_shifted(tmp_path / "late", md, topics, shift_s={VEHICLE_GAP: 3600.0})
    gt, gmd, _ = ambient
    huge = write_contract_bag(tmp_path / "huge", gmd, _with(gt, GUIDEWAY_ACCEL, scale=1e30))
    assert main(["diagnose", "--pass", str(late), "--out", str(tmp_path / "d"), "--quiet"]) == 1
    _one_line_error(capsys.readouterr().err, VEHICLE_GAP, "do not overlap", "offset +3600")
    assert not (tmp_path / "d" / "report.json").exists()
    assert main(["update", "--ambient", str(huge), "--pass", str(late), "--out", str(tmp_path / "p.json"),
                 "--quiet"]) == 1
    _one_line_error(capsys.readouterr().err, GUIDEWAY_ACCEL, "implausible")
    assert not (tmp_path / "p.json").exists()


def test_shifted_topic_a_verb_does_not_read_is_a_warning(ambient, tmp_path, capsys):
    """modes of an ambient recording reads the guideway alone: a position topic an hour off is
    said, not fatal."""
    gt, gmd, _ = ambient
    topics = dict(gt)
    n = 40 * 100
    topics[VEHICLE_POSITION] = (("position_m", "speed_mps"), ("m", "m/s"), 100.0, np.zeros((n, 2)))
    bag = _write_shifted(tmp_path / "amb", gmd, topics, shift_s={VEHICLE_POSITION: 3600.0})
    with BagReader(bag) as r:
        _, health = r.read_checked(GUIDEWAY_ACCEL)
    (w,) = health.warnings
    assert (w.kind, w.topic, w.severity) == ("time_offset", VEHICLE_POSITION, "warning")
    assert "offset +3600" in w.message


def test_a_gap_in_a_short_recording_is_no_rate_mismatch_but_a_wrong_rate_is():
    """On a 2 s stream of 0.1 s blocks a window of 200 samples spans every block, gap included:
    the rate is the median over several shorter windows, so a 3-sample gap is not a wrong rate."""
    from maglev_ros.health import rate_issue
    rate, n = 100.0, 10
    stamps = (np.arange(20) * n / rate * 1e9).astype(np.int64)
    stamps[12:] += int(3 / rate * 1e9)                # three samples lost after the 12th block
    assert rate_issue("/testline/vehicle/position", np.full(20, rate), stamps, np.full(20, n)) is None
    slow = (np.arange(20) * n / 95.0 * 1e9).astype(np.int64)     # stamps really advance at 95 Hz
    issue = rate_issue("/testline/vehicle/position", np.full(20, rate), slow, np.full(20, n))
    assert issue is not None and issue.kind == "rate_mismatch"
