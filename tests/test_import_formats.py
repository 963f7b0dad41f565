"""`maglev-ros import` round trips: a DAQ file written by its own library (csv module, nptdms
TdmsWriter, h5py, scipy.io.savemat, h5py as MATLAB v7.3, asammdf MDF.append) with known content
in non-SI units, imported, the bag read back with BagReader: values (after the unit table's
factor), rates, units and per-sample stamps equal what was written.
"""
from __future__ import annotations

import csv
import datetime
import json

import numpy as np
import pytest
import yaml

from maglev_ros.bag_reader import BagReader
from maglev_ros.cli import main as cli

T0_NS = 1_776_000_000_123_456_000          # whole microseconds: every format's time type holds it
GA, GAP, POS = "/testline/guideway/accel", "/testline/vehicle/gap", "/testline/vehicle/position"
G = 9.80665                                 # standard gravity, exact by definition
KMH = 1 / 3.6


def _truth():
    """{topic: (channels, file units, factor to SI, rate_hz, SI data (n, c))}: sines + noise."""
    rng = np.random.default_rng(7)

    def sig(rate, dur, cols, amp, off=0.0):
        t = np.arange(int(round(rate * dur))) / rate
        return np.stack([off + amp * np.sin(2 * np.pi * (4 + 3 * j) * t + j)
                         + 0.1 * amp * rng.standard_normal(t.size) for j in range(cols)], axis=1)

    tp = np.arange(120) / 100.0
    return {
        GA: (("G1LV", "G2LV", "G3LV"), ("g", "g", "g"), G, 2000.0, sig(2000.0, 1.2, 3, 0.4)),
        GAP: (("M1G", "M2G"), ("mm", "mm"), 1e-3, 1000.0, sig(1000.0, 1.2, 2, 1e-3, 0.010)),
        POS: (("position_m", "speed_mps"), ("m", "km/h"), None, 100.0,
              np.stack([20.0 + 6.9 * tp, 6.9 + 0.1 * np.sin(tp)], axis=1)),
    }


TRUTH = _truth()


def _factor(unit):
    return {"g": G, "mm": 1e-3, "m": 1.0, "km/h": KMH}[unit]


def _file_values(topic):
    chans, units, _, _, data = TRUTH[topic]
    return {c: data[:, j] / _factor(u) for j, (c, u) in enumerate(zip(chans, units))}


@pytest.fixture(scope="module")
def metadata_file(tmp_path_factory):
    from bagfactory import make_metadata

    d = tmp_path_factory.mktemp("md")
    doc = make_metadata({t: (spec[0],) for t, spec in TRUTH.items()})
    p = d / "metadata.yaml"
    p.write_text(yaml.safe_dump(doc))
    return p


def _import(tmp_path, metadata_file, source, channels, **extra):
    spec = {"metadata": str(metadata_file), "source": source, "channels": channels, "block_s": 0.1}
    spec.update(extra)
    sp = tmp_path / "import.yaml"
    sp.write_text(yaml.safe_dump(spec, sort_keys=False))
    out = tmp_path / "bag"
    js = tmp_path / "import.json"
    assert cli(["import", str(sp), "--out", str(out), "--json", str(js)]) == 0
    return out, json.loads(js.read_text())


def _check_bag(out, topics=tuple(TRUTH), t0_ns=T0_NS):
    """Values (float32 of SI), SI units, rates and every sample's stamp against the truth."""
    with BagReader(out) as bag:
        assert [i for i in bag.check() if i.severity == "error"] == []
        for topic in topics:
            chans, units, _, rate, data = TRUTH[topic]
            blocks = [b for _, b in bag.iter_blocks([topic])]
            assert {b.sample_rate_hz for b in blocks} == {rate}
            assert blocks[0].channels == chans
            si = {"g": "m/s^2", "mm": "m", "m": "m", "km/h": "m/s"}
            assert blocks[0].units == tuple(si[u] for u in units)
            got = np.concatenate([b.data for b in blocks])
            np.testing.assert_allclose(got, data.astype(np.float32), rtol=2e-6,
                                       atol=2e-7 * np.abs(data).max())
            stamps = np.concatenate([b.stamp_ns + np.round(np.arange(b.n_samples) * 1e9 / rate)
                                     for b in blocks])
            want = t0_ns + np.round(np.arange(data.shape[0]) * 1e9 / rate)
            assert np.abs(stamps - want).max() <= 1000, topic     # 1 us: text/float stamps
            assert blocks[0].stamp_ns == t0_ns


def _conversions(js):
    return {c["channel"]: (c["unit"], c["si_unit"], c["factor"]) for c in js["conversions"]}


def test_csv_round_trip(tmp_path, metadata_file):
    """Three CSV files, one per rate: epoch-seconds time, ISO time, relative ms + start."""
    iso = datetime.datetime.fromtimestamp(T0_NS // 10**9, datetime.timezone.utc)
    for topic, name in ((GA, "acc.csv"), (GAP, "gap.csv"), (POS, "pos.csv")):
        chans, units, _, rate, data = TRUTH[topic]
        n = data.shape[0]
        vals = _file_values(topic)
        with open(tmp_path / name, "w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(["Time"] + [f"col {c}" for c in chans])
            for i in range(n):
                ns = T0_NS + round(i * 1e9 / rate)
                if topic == GA:
                    t = f"{ns // 10**9}.{ns % 10**9:09d}"
                elif topic == GAP:
                    t = (iso + datetime.timedelta(microseconds=(ns - T0_NS // 10**9 * 10**9) // 1000)
                         ).strftime("%Y-%m-%dT%H:%M:%S.%fZ")
                else:
                    t = repr((ns - T0_NS) / 1e6)
                w.writerow([t] + [repr(float(vals[c][i])) for c in chans])
    start = f"{iso.strftime('%Y-%m-%dT%H:%M:%S')}.{T0_NS % 10**9:09d}Z"
    chans = {}
    for topic, name in ((GA, "acc.csv"), (GAP, "gap.csv"), (POS, "pos.csv")):
        time = {"column": "Time", "absolute": True} if topic != POS else \
            {"column": "Time", "unit": "ms", "start": start}
        for c, u in zip(TRUTH[topic][0], TRUTH[topic][1]):
            chans[c] = {"column": f"col {c}", "unit": u, "source": {"file": name, "time": time}}
    out, js = _import(tmp_path, metadata_file,
                      {"file": "acc.csv", "time": {"column": "Time", "absolute": True}}, chans)
    _check_bag(out)
    conv = _conversions(js)
    assert conv["G1LV"] == ("g", "m/s^2", G) and conv["M2G"] == ("mm", "m", 1e-3)
    assert conv["speed_mps"][:2] == ("km/h", "m/s") and conv["speed_mps"][2] == pytest.approx(KMH)
    assert "position_m" not in conv                     # already SI: nothing to state


def test_tdms_round_trip(tmp_path, metadata_file):
    """Waveform channels (wf_increment, wf_start_time, unit_string): rate, start and units
    come from the file's properties; the spec names only the channels."""
    from nptdms import ChannelObject, GroupObject, RootObject, TdmsWriter

    start = np.datetime64(T0_NS, "ns").astype("datetime64[us]")
    objs = [RootObject(properties={"name": "run"})]
    for topic, group in ((GA, "Guideway"), (GAP, "Magnets"), (POS, "Position")):
        chans, units, _, rate, _ = TRUTH[topic]
        objs.append(GroupObject(group))
        vals = _file_values(topic)
        for c, u in zip(chans, units):
            objs.append(ChannelObject(group, c, vals[c], properties={
                "wf_increment": 1.0 / rate, "wf_start_time": start, "wf_start_offset": 0.0,
                "unit_string": u}))
    with TdmsWriter(tmp_path / "run.tdms") as w:
        w.write_segment(objs)
    groups = {GA: "Guideway", GAP: "Magnets", POS: "Position"}
    chans = {c: {"column": f"{groups[t]}/{c}"} for t in TRUTH for c in TRUTH[t][0]}
    out, js = _import(tmp_path, metadata_file, {"file": "run.tdms"}, chans)
    _check_bag(out)
    assert {c["unit_from"] for c in js["conversions"]} == {"file"}
    assert {t["topic"]: t["rate_from"] for t in js["topics"]}[GA] == "TDMS wf_increment"


def test_hdf5_round_trip(tmp_path, metadata_file):
    """Datasets per channel (rate and unit as attributes) for the accelerations; one 2-D table
    with column names and a time dataset for the gaps; a compound table for the position."""
    import h5py

    with h5py.File(tmp_path / "run.h5", "w") as f:
        vals = _file_values(GA)
        for c in TRUTH[GA][0]:
            ds = f.create_dataset(f"acc/{c}", data=vals[c])
            ds.attrs["sample_rate_hz"] = 2000.0
            ds.attrs["unit"] = "g"
        vals = _file_values(GAP)
        tab = f.create_dataset("gaps", data=np.stack([vals["M1G"], vals["M2G"]], axis=1))
        tab.attrs["columns"] = ["M1G gap", "M2G gap"]
        f.create_dataset("gap_time", data=np.arange(tab.shape[0]) / 1000.0)
        vals = _file_values(POS)
        rec = np.zeros(len(vals["position_m"]), dtype=[("t", "f8"), ("x", "f8"), ("v", "f8")])
        rec["t"], rec["x"], rec["v"] = np.arange(rec.size) / 100.0, vals["position_m"], vals["speed_mps"]
        f.create_dataset("pos", data=rec)
    start = T0_NS / 1e9
    chans = {c: {"column": f"/acc/{c}"} for c in TRUTH[GA][0]}
    gsrc = {"dataset": "gaps", "time": {"column": "/gap_time", "start": start}}
    chans["M1G"] = {"column": "M1G gap", "unit": "mm", "source": gsrc}
    chans["M2G"] = {"column": "M2G gap", "unit": "mm", "source": gsrc}
    psrc = {"dataset": "pos", "time": {"column": "t", "start": start}}
    chans["position_m"] = {"column": "x", "unit": "m", "source": psrc}
    chans["speed_mps"] = {"column": "v", "unit": "km/h", "source": psrc}
    out, _ = _import(tmp_path, metadata_file, {"file": "run.h5", "time": {"start": start}}, chans)
    # start as epoch float seconds: 0.12345600 s of fraction survive to well under 1 us
    _check_bag(out)


def test_mat_v5_round_trip(tmp_path, metadata_file):
    """Variables per channel, a struct of channels, a matrix with a cellstr of names."""
    from scipy.io import savemat

    va, vg, vp = _file_values(GA), _file_values(GAP), _file_values(POS)
    savemat(tmp_path / "run.mat", {
        "G1LV": va["G1LV"][:, None], "acc": {"G2LV": va["G2LV"], "G3LV": va["G3LV"]},
        "gaps": np.stack([vg["M1G"], vg["M2G"]], axis=1),
        "gap_names": np.array(["M1G", "M2G"], dtype=object),
        "tg": np.arange(vg["M1G"].size) / 1000.0,
        "pos": np.stack([vp["position_m"], vp["speed_mps"]], axis=1),
        "ta": np.arange(va["G1LV"].size) / 2000.0, "tp": np.arange(vp["speed_mps"].size) / 100.0,
    })
    _mat_import_and_check(tmp_path, metadata_file, "run.mat")


def _mat_import_and_check(tmp_path, metadata_file, name):
    start = T0_NS / 1e9
    chans = {"G1LV": {"column": "G1LV", "unit": "g"},
             "G2LV": {"column": "acc.G2LV", "unit": "g"},
             "G3LV": {"column": "acc.G3LV", "unit": "g"}}
    gsrc = {"dataset": "gaps", "columns": "gap_names", "time": {"column": "tg", "start": start}}
    chans.update({c: {"column": c, "unit": "mm", "source": gsrc} for c in ("M1G", "M2G")})
    psrc = {"dataset": "pos", "columns": ["x", "v"], "time": {"column": "tp", "start": start}}
    chans["position_m"] = {"column": "x", "unit": "m", "source": psrc}
    chans["speed_mps"] = {"column": 1, "unit": "km/h", "source": psrc}
    out, _ = _import(tmp_path, metadata_file, {"file": name, "time": {"column": "ta", "start": start}},
                     chans)
    _check_bag(out)


def test_mat_v73_round_trip(tmp_path, metadata_file):
    """MATLAB v7.3 as MATLAB writes it: HDF5 behind a 512-byte header, arrays column-major
    (a samples x 2 matrix is stored 2 x samples), structs as groups, cellstr as references."""
    import h5py

    va, vg, vp = _file_values(GA), _file_values(GAP), _file_values(POS)
    path = tmp_path / "run73.mat"
    with h5py.File(path, "w", userblock_size=512) as f:
        def put(name, matlab_array):
            a = np.asarray(matlab_array, dtype=np.float64)
            a = a[:, None] if a.ndim == 1 else a                     # a MATLAB column vector
            ds = f.create_dataset(name, data=a.T)                    # column-major: stored transposed
            ds.attrs["MATLAB_class"] = np.bytes_("double")
        put("G1LV", va["G1LV"])
        put("acc/G2LV", va["G2LV"])
        put("acc/G3LV", va["G3LV"])
        f["acc"].attrs["MATLAB_class"] = np.bytes_("struct")
        put("gaps", np.stack([vg["M1G"], vg["M2G"]], axis=1))        # MATLAB n x 2 -> stored 2 x n
        put("pos", np.stack([vp["position_m"], vp["speed_mps"]], axis=1))
        put("tg", np.arange(vg["M1G"].size) / 1000.0)
        put("ta", np.arange(va["G1LV"].size) / 2000.0)
        put("tp", np.arange(vp["speed_mps"].size) / 100.0)
        refs = f.create_group("#refs#")
        rs = []
        for i, s in enumerate(("M1G", "M2G")):
            d = refs.create_dataset(f"s{i}", data=np.array([[ord(ch)] for ch in s], dtype=np.uint16))
            d.attrs["MATLAB_class"] = np.bytes_("char")
            rs.append(d.ref)
        names = f.create_dataset("gap_names", data=np.array([rs], dtype=h5py.ref_dtype).T)
        names.attrs["MATLAB_class"] = np.bytes_("cell")
    with open(path, "r+b") as fh:
        fh.write(b"MATLAB 7.3 MAT-file, Platform: GLNXA64, Created on: Fri Nov 27 12:00:00 2026 HDF5 schema 1.00 .")
    _mat_import_and_check(tmp_path, metadata_file, "run73.mat")


def test_mdf4_round_trip(tmp_path, metadata_file):
    """ASAM MDF4 by asammdf: one channel group per rate, timestamps and units in the file."""
    from asammdf import MDF, Signal

    mdf = MDF(version="4.10")
    mdf.header.start_time = datetime.datetime.fromtimestamp(T0_NS // 10**9, datetime.timezone.utc) \
        + datetime.timedelta(microseconds=(T0_NS % 10**9) // 1000)
    for topic in TRUTH:
        chans, units, _, rate, data = TRUTH[topic]
        vals = _file_values(topic)
        t = np.arange(data.shape[0]) / rate
        mdf.append([Signal(vals[c], t, name=c, unit=u) for c, u in zip(chans, units)])
    mdf.save(tmp_path / "run.mf4", overwrite=True)
    mdf.close()
    chans = {c: {"column": c} for t in TRUTH for c in TRUTH[t][0]}
    out, js = _import(tmp_path, metadata_file, {"file": "run.mf4"}, chans)
    _check_bag(out)
    assert _conversions(js)["G1LV"] == ("g", "m/s^2", G)
