"""Bounded memory (issue 27, item 7): ``modes`` and ``irregularity`` read long recordings window
by window and ``diagnose`` keeps bounded caches, with the results of the whole-recording path.

Each streamed piece is checked against an independent reference on data generated here: the
window reader against ``read_topic`` / ``read_checked``, the streamed decimation against
``scipy.signal.resample_poly``, the streamed dropout scan against ``detect_dropouts``, and the
streamed verbs against their whole-recording computation on a recording cut into many windows
(and against the simulated truth). Peak-RSS targets live in bench/bench_memory.py, not here.
"""
from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace as NS

import numpy as np
import pytest
from scipy.signal import resample_poly

from bagfactory import (GUIDEWAY_ACCEL, VEHICLE_ACCEL, VEHICLE_GAP, VEHICLE_POSITION, Faults,
                        make_metadata, write_contract_bag, write_foreign_bag)
from irregularity_data import bandpass_truth, make_recording
from maglev_ros import bag_windows
from maglev_ros.bag_reader import BagReader
from maglev_ros.cli import main
from modal_data import assert_modes_match, guideway_model, simulate_ambient

BAGS = Path(__file__).resolve().parents[1] / "bags"


# ------------------------------------------------------------------------ window reading
def _concatenated(windows):
    ws = list(windows)
    return NS(time_s=np.concatenate([w.time_s for w in ws]), data=np.concatenate([w.data for w in ws]),
              channels=ws[0].channels, units=ws[0].units)


def test_windows_are_the_whole_read_sample_for_sample(tmp_path):
    """A foreign bag with jittered receive times, a swapped, a duplicated and an overlapping
    block: the windows concatenated are read_topic's samples, bit for bit; through the health
    check (one channel in g, one flat-lined and excluded) they are read_checked's arrays."""
    rng = np.random.default_rng(4)
    fs, n = 200.0, 4000
    y = rng.standard_normal((n, 3))
    y[:, 2] = 0.25                                     # flat: excluded by the health check
    y[:, 1] /= 9.80665                                 # recorded in g
    topics = {GUIDEWAY_ACCEL: (("G1LV", "G2LV", "G3LV"), ("m/s^2", "g", "m/s^2"), fs, y)}
    md = make_metadata(topics, kind="ambient")
    faults = Faults(swap={GUIDEWAY_ACCEL: [7, 90]}, duplicate={GUIDEWAY_ACCEL: [30]},
                    overlap={GUIDEWAY_ACCEL: [55]})
    bag = write_foreign_bag(tmp_path / "amb", md, topics, faults=faults)
    with BagReader(bag) as r:
        whole = r.read_topic(GUIDEWAY_ACCEL)
        span = bag_windows.scan_topic(r, GUIDEWAY_ACCEL)
        wins = list(bag_windows.iter_windows(r, span, window_s=1.7))
        read, health = r.read_checked([GUIDEWAY_ACCEL])
        read_w, health_w = bag_windows.read_checked_windows(r, [GUIDEWAY_ACCEL])
        checked = list(bag_windows.iter_windows(r, read_w[GUIDEWAY_ACCEL], window_s=1.3))
    assert len(wins) > 10 and {i.kind for i in whole.issues} >= {"out_of_order", "duplicate",
                                                                 "overlap"}
    cat = _concatenated(wins)
    assert np.array_equal(cat.time_s, whole.time_s) and np.array_equal(cat.data, whole.data)
    ref = read[GUIDEWAY_ACCEL]
    cat = _concatenated(checked)
    assert cat.channels == ref.channels == ("G1LV", "G2LV") and cat.units == ref.units
    assert np.array_equal(cat.time_s, ref.time_s) and np.array_equal(cat.data, ref.data)
    assert health_w.to_dict() == health.to_dict()
    assert health.excluded_channels == ["G3LV"]
    assert read_w[GUIDEWAY_ACCEL].n_samples == ref.n_samples


def test_dropout_scan_in_pieces_is_detect_dropouts():
    """Stuck values, NaN runs, zero blocks and time gaps cut anywhere by the pieces: the same bad
    samples and the same warnings as detect_dropouts on the whole channel."""
    from maglev_ros.irregularity.integration import detect_dropouts
    from maglev_ros.irregularity.streamed import DropoutScan, _mask
    rng = np.random.default_rng(11)
    fs = 1000.0
    for _ in range(60):
        n = int(rng.integers(2, 3000))
        t = np.arange(n) / fs + 100.0
        x = rng.standard_normal(n)
        for _ in range(int(rng.integers(1, 6))):
            a, m = int(rng.integers(0, n)), int(rng.integers(1, 400))
            kind = rng.integers(0, 4)
            if kind == 0:
                x[a:a + m] = x[a]
            elif kind == 1:
                x[a:a + m] = np.nan
            elif kind == 2:
                x[a:a + m] = 0.0
            else:
                t[a:] += rng.uniform(0.002, 0.05)
        bad, warns = detect_dropouts(t, x, fs, "C")
        scan = DropoutScan(fs, "C")
        i = 0
        while i < n:
            k = int(rng.integers(1, 300))
            scan.push(t[i:i + k], x[i:i + k])
            i += k
        intervals, warns_s = scan.finish()
        assert np.array_equal(_mask(intervals, 0, n), bad)
        assert [w.to_dict() for w in warns_s] == [w.to_dict() for w in warns]


def test_decimator_in_pieces_is_resample_poly():
    from maglev_ros.modal.chunked import Decimator
    rng = np.random.default_rng(5)
    x = rng.standard_normal((12345, 4))
    for q in (1, 3, 7, 29):
        dec = Decimator(q, x.shape[0])
        parts, i = [], 0
        while i < x.shape[0]:
            k = int(rng.integers(1, 900))
            parts.append(dec.push(x[i:i + k]))
            i += k
        ref = x if q == 1 else resample_poly(x, 1, q, axis=0)
        assert np.array_equal(np.concatenate(parts), ref)


# --------------------------------------------------------------------------------- modes
def _mode_table(modes):
    return (np.array([m.frequency_hz for m in modes]), np.array([m.damping_ratio for m in modes]),
            np.array([m.std_frequency_hz for m in modes]))


@pytest.mark.parametrize("scale", [None, True])
def test_streamed_modes_equal_the_whole_record(tmp_path, monkeypatch, scale):
    """40 s of ambient vibration read in 5 s windows: the same band plan, the same SSI poles,
    clusters and shapes (bit for bit: the same sums in the same order), the Whittle-polished
    frequencies and damping within 1e-9 and 1e-8 (the polish's band DFT is summed by chirp-z
    pieces instead of one FFT), and the simulated modes found."""
    from maglev_ros.commands.modes import identify_modes
    from maglev_ros.modal.bands import identify_bands, plan_bands
    model = guideway_model(None)
    fs = 500.0
    y = simulate_ambient(model, fs, 40.0, noise_frac=0.05, seed=7)
    topics = {GUIDEWAY_ACCEL: (model.channels, ("m/s^2",) * 15, fs, y)}
    bag = write_contract_bag(tmp_path / "amb", make_metadata(topics, kind="ambient"), topics)
    monkeypatch.setattr(bag_windows, "WINDOW_VALUES", 15 * 500 * 5)
    got = identify_modes(bag, scale_channels=scale)
    with BagReader(bag) as r:
        cd = r.read_topic(GUIDEWAY_ACCEL)
        assert len(list(bag_windows.iter_windows(r, bag_windows.scan_topic(r, GUIDEWAY_ACCEL)))) >= 8
    plan = plan_bands(fs, cd.n_samples, 15, stationary=True, scale_channels=bool(scale),
                      scale_source=got.plan.sources["scale_channels"])
    ref, _ = identify_bands(cd.data, fs, plan, cd.channels)
    assert got.info["settings"] == plan.to_dict() and got.info["n_samples"] == cd.n_samples
    res = got.result
    assert res.method == ref.method and "whittle" in res.method
    assert len(res.modes) == len(ref.modes) >= 5
    assert [m.mode_shape for m in res.modes] == [m.mode_shape for m in ref.modes]
    assert np.array_equal(res.stabilization.frequency_hz, ref.stabilization.frequency_hz)
    assert np.array_equal(res.spectrum.singular_values, ref.spectrum.singular_values)
    (f, z, sf), (f0, z0, sf0) = _mode_table(res.modes), _mode_table(ref.modes)
    assert np.allclose(f, f0, rtol=1e-9, atol=0) and np.allclose(z, z0, rtol=1e-8, atol=0)
    assert np.allclose(sf, sf0, rtol=1e-6, atol=0)
    chk = assert_modes_match(res.modes, model, 150.0)
    assert chk["missing"] == [] and chk["freq_rel"] < 0.01


def test_streamed_free_decay_modes_equal_the_whole_record(monkeypatch):
    """The sample pass read in 2 s windows: the same free-decay window (from the position
    topic) and the same modes, bit for bit (no polish on a free decay)."""
    from maglev_ros.commands.modes import _identify_whole, identify_modes
    bag = BAGS / "paper_pass"
    monkeypatch.setattr(bag_windows, "WINDOW_VALUES", 10 * 2000 * 2)
    got = identify_modes(bag)
    with BagReader(bag) as r:
        read, _ = r.read_checked([GUIDEWAY_ACCEL, VEHICLE_POSITION], sensor_map=True)
        ref = _identify_whole(bag, read[GUIDEWAY_ACCEL], r.metadata, "pass", read[VEHICLE_POSITION])
    info = dict(got.info)
    assert info.pop("not_spectral_peaks_hz") == []          # the spectral-peak check is the reader's, after
    assert info == ref.info and got.info["free_decay_window"]["method"] == "position"
    assert got.result.to_dict(diagram=True) == ref.result.to_dict(diagram=True)


# -------------------------------------------------------------------------- irregularity
def _pass_bag(tmp_path, seed=3):
    """A 60 s pass at uneven speed over a known rail, 3 magnets at 1 kHz, written by the foreign
    writer with a dropped accel block (a time gap), a stuck gap sensor and an accel stuck twice."""
    rec = make_recording(30.0, seed, "uneven", duration_s=60.0, length_m=520.0)
    acc, gap = rec.accel.data.copy(), rec.gap.data.copy()
    acc[21000:21300, 1] = acc[21000, 1]
    acc[22500:22600, 1] = acc[22500, 1]                 # 1.2 s between: too short a stretch
    gap[40000:40200, 2] = gap[40000, 2]
    topics = {VEHICLE_ACCEL: (rec.accel.channels, rec.accel.units, 1000.0, acc),
              VEHICLE_GAP: (rec.gap.channels, rec.gap.units, 1000.0, gap),
              VEHICLE_POSITION: (rec.position.channels, rec.position.units, 100.0,
                                 rec.position.data)}
    md = make_metadata(topics, kind="pass", magnet_offsets_m=rec.magnet_offsets_m)
    bag = write_foreign_bag(tmp_path / "pass", md, topics, block_s=0.1,
                            faults=Faults(drop={VEHICLE_ACCEL: [333]}))
    return bag, rec


def _streamed(bag, prof, window_s):
    from maglev_ros.commands.irregularity import open_inputs
    from maglev_ros.irregularity.streamed import profile_streamed
    with BagReader(bag) as r:
        inp, _ = open_inputs(r, str(bag), window_s=window_s)
        return profile_streamed(inp["source"], prof, inp["magnet_offsets_m"],
                                inp["nominal_gap_m"], inp["channel_pairs"])


def _same_profile(s, b, top_speed_mps):
    """The streamed profile ``s`` against the batch fit ``b``: same grid, band and warnings;
    values within 1e-5 of the peak (within a few 1/f_c of the ends of a clean stretch the
    batch FFT wraps the stretch's other end around over its 2/f_c zero pad, which a cut piece
    does not see) and within 1e-8 of the peak farther than 5 / f_c of travel from any end of
    a magnet's stretch."""
    assert np.array_equal(s.position_m, b.position_m)
    assert s.corner == b.corner and s.highpass_hz == b.highpass_hz
    assert s.band_speed_mps == pytest.approx(b.band_speed_mps, rel=1e-12)
    assert s.max_wavelength_m == pytest.approx(b.max_wavelength_m, rel=1e-12)
    assert s.min_wavelength_m == pytest.approx(b.min_wavelength_m, rel=1e-12)
    assert [w.to_dict() for w in s.warnings] == [w.to_dict() for w in b.warnings]
    assert np.allclose(s.bias_mps2, b.bias_mps2, rtol=1e-9, atol=0)
    assert np.array_equal(np.isfinite(s.irregularity_m), np.isfinite(b.irregularity_m))
    v = np.isfinite(b.irregularity_m)
    peak = np.max(np.abs(b.irregularity_m[v]))
    d = np.abs(s.irregularity_m[v] - b.irregularity_m[v])
    assert d.max() <= 1e-5 * peak
    fin = np.isfinite(b.magnet_profiles_m)
    ends = np.concatenate([b.position_m[np.flatnonzero(np.diff(f.astype(np.int8)) != 0)]
                           for f in fin] + [b.position_m[[0, -1]]])
    reach_m = 5.0 / b.highpass_hz * top_speed_mps
    inner = np.min(np.abs(b.position_m[v][:, None] - ends[None, :]), axis=1) > reach_m
    assert d[inner].max(initial=0.0) <= 1e-8 * peak
    return inner.sum() / v.sum()


def test_streamed_irregularity_equals_the_batch_fit(tmp_path, monkeypatch):
    """The pass in 8 s windows with a 1 Hz corner (each window integrated with 10 s of margin,
    so clean stretches are cut): the batch fit's grid, band, warnings (time gap, stuck sensors,
    their short stretches) and profile within the stated tolerance; with the automatic corner
    and band speed (their whole-pass rules run over the windows), and with the band speed's
    histogram bin split again (few values allowed per bin), the same."""
    from maglev_ros.commands.irregularity import read_inputs
    from maglev_ros.irregularity import streamed
    from maglev_ros.irregularity.profile import InertialProfiler
    bag, rec = _pass_bag(tmp_path)
    inp = read_inputs(str(bag))
    batch = InertialProfiler(highpass_hz=1.0).fit(**inp)
    kinds = {w.kind for w in batch.warnings}
    assert {"time_gap", "flatline", "short_segment"} <= kinds
    got = _streamed(bag, InertialProfiler(highpass_hz=1.0), 8.0)
    assert _same_profile(got, batch, rec.speed_mps.max()) > 0.2      # 1 Hz: much is interior
    truth = bandpass_truth(got.position_m, rec.truth_at(got.position_m), got.min_wavelength_m,
                           got.max_wavelength_m)
    v = got.valid
    assert np.corrcoef(got.irregularity_m[v], truth[v])[0, 1] > 0.9
    batch = InertialProfiler().fit(**inp)
    _same_profile(_streamed(bag, InertialProfiler(), 8.0), batch, rec.speed_mps.max())
    monkeypatch.setattr(streamed, "SPEED_BIN_VALUES", 20)
    got = _streamed(bag, InertialProfiler(), 8.0)
    assert got.band_speed_mps == pytest.approx(batch.band_speed_mps, rel=1e-12)


def test_irregularity_cli_streams_and_keeps_its_outputs(tmp_path, monkeypatch):
    """The verb on the pass read in windows writes the batch fit's profile (CSV and JSON)."""
    from maglev_ros.commands.irregularity import read_inputs
    from maglev_ros.irregularity.profile import InertialProfiler
    bag, _ = _pass_bag(tmp_path, seed=4)
    monkeypatch.setattr(bag_windows, "WINDOW_VALUES", 3 * 1000 * 10)
    out, js = tmp_path / "irr.csv", tmp_path / "irr.json"
    assert main(["irregularity", str(bag), "--out", str(out), "--json", str(js),
                 "--highpass-hz", "1"]) == 0
    doc = json.loads(js.read_text())
    batch = InertialProfiler(highpass_hz=1.0).fit(**read_inputs(str(bag)))
    got = np.array([np.nan if v is None else v for v in doc["profile"]["irregularity_m"]])
    assert np.array_equal(np.isfinite(got), batch.valid)
    assert np.max(np.abs(got[batch.valid] - batch.irregularity_m[batch.valid])) \
        <= 1e-5 * np.max(np.abs(batch.irregularity_m[batch.valid]))
    assert doc["profile"]["warnings"] == [w.to_dict() for w in batch.warnings]
    rows = [ln for ln in out.read_text().splitlines() if not ln.startswith("#")][1:]
    assert len(rows) == batch.position_m.size


# ------------------------------------------------------------------------------ diagnose
def test_simulation_cache_is_bounded_and_recomputes_the_same(monkeypatch):
    """The diagnosis' simulation cache drops the least recently used results beyond its byte
    budget; a dropped simulation run again is the same, bit for bit (what keeps report.json
    unchanged by the bound)."""
    from maglev_ros.discrepancy import model
    from maglev_ros.discrepancy.recording import load_recording
    rec = load_recording(str(BAGS / "paper_pass"))
    spec = model.base_spec(rec.metadata)
    other = spec.with_(cal=(0.05, 0.0, 0.0, 0.0))
    monkeypatch.setattr(model, "_CACHE", type(model._CACHE)())
    monkeypatch.setattr(model, "_CACHE_MAX_BYTES", 1)
    first = model.simulate(spec, rec)
    model.simulate(other, rec)
    assert len(model._CACHE) == 1                       # only the last result kept
    again = model.simulate(spec, rec)
    assert again is not first
    for k, v in vars(first).items():
        if isinstance(v, np.ndarray):
            assert np.array_equal(v, getattr(again, k)), k
