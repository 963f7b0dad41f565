"""`maglev-ros irregularity BAG --out CSV` with no options on short passes: the corner and the band
follow the recording, and the profile matches the KNOWN rail.

References: the bundled bags' truth (`bags/<pass>.irregularity.csv`, written by the simulator,
never read by the suite), the partner simulator's true rail (`irregularity.npz` of each case in
`../shared/validation/partner-sim/`, an independent code; skipped when absent) and the synthetic
recordings of tests/irregularity_data. Both profiles are compared the same way on the same grid:
the truth is averaged over each grid bin (what binning does to the measured samples), then
band-passed with the result's stated filter (the achieved band) or with a fixed 1.5-8 m band
(issue 26: >= 0.95 in 1.5-8 m on partner passes); the fixed band is applied to the truth over its
whole length and to the profile over each valid stretch, whose first and last 8 m are dropped.
"""
from __future__ import annotations

import csv
import json
import math
from pathlib import Path
from types import SimpleNamespace as NS

import numpy as np
import pytest
from scipy import signal

from irregularity_data import bandpass_truth, make_recording
from maglev_ros.cli import main
from maglev_ros.irregularity.profile import IncrementalProfiler, InertialProfiler

REPO = Path(__file__).resolve().parents[1]
BAGS = REPO / "bags"
PARTNER = Path(__file__).resolve().parents[1].parent / "shared" / "validation" / "partner-sim"
CORR_MIN = 0.95            # issue 26 item 6 (1.5-8 m); also required in the achieved band
REL_ERR_MAX = 0.25         # RMS error in the achieved band, relative to the band-passed truth


def _bin_mean_truth(xt, rt, x_grid, dx):
    """Mean of the (linearly interpolated) truth over each grid bin [x - dx/2, x + dx/2]."""
    c = np.concatenate([[0.0], np.cumsum(0.5 * (rt[1:] + rt[:-1]) * np.diff(xt))])
    return (np.interp(x_grid + dx / 2, xt, c) - np.interp(x_grid - dx / 2, xt, c)) / dx


def _runs(mask):
    m = np.concatenate([[False], mask, [False]]).astype(np.int8)
    d = np.diff(m)
    return list(zip(np.flatnonzero(d == 1), np.flatnonzero(d == -1)))


def _score(x, y, xt, rt, band_m, dx):
    """(corr in the achieved band, relative RMS error there, corr in 1.5-8 m) against the truth."""
    j = np.arange(math.ceil(xt[0] / dx) + 1, math.floor(xt[-1] / dx))
    xg = j * dx
    tg = _bin_mean_truth(xt, rt, xg, dx)
    tg = tg - tg.mean()
    out = []
    for lo, hi in (band_m, (1.5, 8.0)):
        sos = signal.butter(4, [1 / hi, 1 / lo], btype="band", fs=1 / dx, output="sos")
        out.append(np.interp(x, xg, signal.sosfiltfilt(sos, tg)))
    t_band, t_fix = out
    ok = np.isfinite(y)
    c_band = np.corrcoef(y[ok], t_band[ok])[0, 1]
    rel = np.sqrt(np.mean((y[ok] - t_band[ok]) ** 2) / np.mean(t_band[ok] ** 2))
    sos = signal.butter(4, [1 / 8.0, 1 / 1.5], btype="band", fs=1 / dx, output="sos")
    drop = int(round(8.0 / dx))
    yf = np.full(y.shape, np.nan)
    for i0, i1 in _runs(ok):
        if i1 - i0 > 2 * drop + 20:
            f = signal.sosfiltfilt(sos, y[i0:i1] - y[i0:i1].mean())
            yf[i0 + drop:i1 - drop] = f[drop:-drop]
    m = np.isfinite(yf)
    assert m.sum() * dx > 20.0, "too little profile for the 1.5-8 m comparison"
    return float(c_band), float(rel), float(np.corrcoef(yf[m], t_fix[m])[0, 1])


def _run_cli(bag, tmp_path, *extra):
    out, js = tmp_path / "p.csv", tmp_path / "p.json"
    assert main(["irregularity", str(bag), "--out", str(out), "--json", str(js), *extra]) == 0
    lines = out.read_text().splitlines()
    head = [l for l in lines if l.startswith("#")]
    rows = list(csv.reader([l for l in lines if not l.startswith("#")]))[1:]
    x = np.array([float(r[0]) for r in rows])
    y = np.array([float(r[1]) if r[1] else np.nan for r in rows])
    return x, y, head, json.loads(js.read_text())["profile"]


def _pass_facts(bag):
    """Record length [s] (samples / rate) and slowest speed [m/s] of a pass, read from the bag."""
    from maglev_ros.commands.irregularity import read_inputs
    inp = read_inputs(str(bag))
    a = inp["accel"]
    v_min = float(np.min(inp["position"].channel("speed_mps")))
    return inp, a.time_s.size / a.sample_rate_hz, v_min


def _check_defaults(bag, xt, rt, tmp_path, capsys):
    x, y, head, prof = _run_cli(bag, tmp_path)
    printed = capsys.readouterr().out
    _, dur_s, v_min = _pass_facts(bag)
    corner = prof["corner"]
    lo, hi = prof["min_wavelength_m"], prof["max_wavelength_m"]
    # the corner is the stated rule for this pass: settling 2.2/f_c is half the moving stretch
    assert corner["rule"] == "auto"
    assert corner["usable_s"] <= dur_s + 1e-6 and corner["usable_s"] > 0.9 * dur_s
    assert prof["highpass_hz"] == pytest.approx(max(0.2, 4.4 / corner["usable_s"]), rel=1e-6)
    # the band: point sensors (4 grid steps), longest wave = band speed / (2 f_c)
    assert lo == pytest.approx(4 * 0.25)
    assert hi == pytest.approx(prof["band_speed_mps"] / (2 * prof["highpass_hz"]))
    assert prof["band_speed_mps"] >= 0.98 * v_min
    assert lo <= 1.5 and hi >= 8.0                  # the 1.5-8 m band lies inside
    # stated in the CSV header and on the terminal
    assert any("valid band" in l and f"{hi:.4g} m" in l for l in head)
    assert any("high-pass corner" in l and "auto" in l for l in head)
    assert f"valid band {lo:.3g}-{hi:.3g} m" in printed
    c_band, rel, c_fix = _score(x, y, xt, rt, (lo, hi), 0.25)
    print(f"\n[{bag.parent.name}/{bag.name}] {dur_s:.1f} s, f_c {prof['highpass_hz']:.3f} Hz, band "
          f"{lo:.3g}-{hi:.3g} m: corr {c_band:.4f} (rel {rel:.3f}), 1.5-8 m corr {c_fix:.4f}")
    assert c_band >= CORR_MIN and rel <= REL_ERR_MAX, (c_band, rel)
    assert c_fix >= CORR_MIN, c_fix
    return prof


@pytest.mark.parametrize("name", ["paper_pass", "paper_pass2"])
def test_bundled_pass_defaults_match_truth(name, tmp_path, capsys):
    truth = np.loadtxt(BAGS / f"{name}.irregularity.csv", delimiter=",", skiprows=1)
    _check_defaults(BAGS / name, truth[:, 0], truth[:, 1], tmp_path, capsys)


# the slowest and longest, the fastest and shortest, and two mid passes of the partner set
PARTNER_PASSES = ["H10/pass", "H07/pass", "H04/pass2", "H13/pass"]


@pytest.mark.parametrize("case", PARTNER_PASSES)
def test_partner_pass_defaults_match_truth(case, tmp_path, capsys):
    bag = PARTNER / case
    if not bag.exists():
        pytest.skip(f"{bag} not present (shared validation data)")
    z = np.load(bag.parent / "irregularity.npz")
    _check_defaults(bag, z["x_m"], z["r_m"], tmp_path, capsys)


def test_explicit_flags_override(tmp_path):
    _, _, head, prof = _run_cli(BAGS / "paper_pass", tmp_path, "--highpass-hz", "0.5",
                                "--magnet-length-m", "2")
    assert prof["highpass_hz"] == 0.5 and prof["corner"]["rule"] == "given"
    assert prof["min_wavelength_m"] == pytest.approx(2.0)
    assert prof["max_wavelength_m"] == pytest.approx(prof["band_speed_mps"] / 1.0)
    assert any("0.5 Hz (given)" in l for l in head)


@pytest.mark.parametrize("dur_s,kmh,fs_hz,order", [(8.0, 15, 500.0, 4), (8.0, 80, 2000.0, 4),
                                                   (20.0, 15, 2000.0, 4), (12.0, 40, 1000.0, 2)])
def test_short_synthetic_passes(dur_s, kmh, fs_hz, order):
    """8-20 s at 15-80 km/h, other sampling rates and filter orders (accelerometer with 1/f
    noise): the automatic corner leaves a valid profile matching the truth in its stated band."""
    rec = make_recording(kmh, int(dur_s * 10 + kmh), "constant", duration_s=dur_s, fs_hz=fs_hz,
                         bias_mps2=[0.02, 0.0, 0.0])
    res = InertialProfiler(filter_order=order).fit(rec.accel, rec.gap, rec.position,
                                                   rec.magnet_offsets_m, rec.nominal_gap_m)
    assert res.corner.rule == "auto"
    assert res.highpass_hz == pytest.approx(max(0.2, 4.4 / res.corner.usable_s))
    assert res.max_wavelength_m == pytest.approx(res.band_speed_mps / (2 * res.highpass_hz))
    m = res.valid
    # about half of the pass is profile, by construction of the rule (plus the magnets' spread)
    assert m.sum() * res.spacing_m >= 0.4 * kmh / 3.6 * dur_s
    truth = bandpass_truth(res.position_m, rec.truth_at(res.position_m), res.min_wavelength_m,
                           res.max_wavelength_m, order=order)
    c = np.corrcoef(res.irregularity_m[m], truth[m])[0, 1]
    rel = np.sqrt(np.mean((res.irregularity_m[m] - truth[m]) ** 2) / np.mean(truth[m] ** 2))
    assert c >= CORR_MIN and rel <= REL_ERR_MAX, (c, rel)


@pytest.mark.parametrize("told_length", [True, False])
def test_streaming_gives_the_batch_answer_with_the_same_rule(told_length):
    """The node's core: fed block by block, told the pass length or not (then the whole short
    pass is still buffered when it ends), the streaming profiler picks the batch's corner and
    band and gives the batch's profile."""
    from maglev_ros.commands.irregularity import read_inputs
    inp = read_inputs(str(BAGS / "paper_pass"))
    batch = InertialProfiler().fit(**inp)
    inc = IncrementalProfiler(inp["magnet_offsets_m"], inp["nominal_gap_m"],
                              channel_pairs=inp["channel_pairs"],
                              band_speed_mps=batch.band_speed_mps,
                              expected_pass_s=batch.corner.usable_s if told_length else None)
    if told_length:
        assert inc.cfg.highpass_hz == pytest.approx(batch.highpass_hz)

    def blk(cd, i0, i1):
        return NS(time_s=cd.time_s[i0:i1], data=cd.data[i0:i1], channels=cd.channels,
                  sample_rate_hz=cd.sample_rate_hz)
    a, g, p = inp["accel"], inp["gap"], inp["position"]
    step = int(round(0.1 * a.sample_rate_hz))
    ratio = a.sample_rate_hz / p.sample_rate_hz
    for i in range(0, a.time_s.size, step):
        inc.partial_fit(blk(a, i, i + step), blk(g, i, i + step),
                        blk(p, int(i / ratio), int((i + step) / ratio)))
    res = inc.result()
    assert res.highpass_hz == pytest.approx(batch.highpass_hz)
    assert (res.min_wavelength_m, res.max_wavelength_m) == pytest.approx(
        (batch.min_wavelength_m, batch.max_wavelength_m))
    common, ib, is_ = np.intersect1d(np.round(batch.position_m, 6), np.round(res.position_m, 6),
                                     return_indices=True)
    u, v = batch.irregularity_m[ib], res.irregularity_m[is_]
    mm = np.isfinite(u) & np.isfinite(v)
    assert mm.sum() >= 0.95 * np.isfinite(batch.irregularity_m).sum()
    assert np.sqrt(np.mean((u[mm] - v[mm]) ** 2)) < 0.02 * np.sqrt(np.mean(u[mm] ** 2))
