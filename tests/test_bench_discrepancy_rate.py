"""bench_discrepancy's --partner-rate: a recording resampled to another DAQ rate keeps its content
below the new Nyquist (analytic sines) and its stamps."""
import sys
from pathlib import Path

import numpy as np

from maglev_ros.discrepancy.recording import Channel, Recording

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))

import bench_discrepancy as bd  # noqa: E402


def test_at_rate_keeps_the_band_below_the_new_nyquist_and_drops_what_lies_above():
    fs = 1000.0
    t = 100.0 + np.arange(20000) / fs
    low, high = 0.3 * np.sin(2 * np.pi * 60.0 * t), 0.3 * np.sin(2 * np.pi * 180.0 * t)
    fast = Channel("M1A", "vehicle_accel", t, 0.01 + low + high, fs, magnet=1)
    slow = Channel("G3D", "guideway_disp", t[::5], low[::5], 200.0, position_m=30.0)
    rec = Recording({}, {"M1A": fast, "G3D": slow})
    out = bd.at_rate(rec, 250.0)
    ch = out.channels["M1A"]
    assert ch.sample_rate_hz == 250.0 and ch.values.size == 5000
    assert ch.time_s[0] == t[0] and np.allclose(np.diff(ch.time_s), 1 / 250.0)
    mid = slice(500, 4500)
    ref = 0.01 + 0.3 * np.sin(2 * np.pi * 60.0 * ch.time_s[mid])     # 180 Hz lies above the new Nyquist
    assert np.sqrt(np.mean((ch.values[mid] - ref) ** 2)) < 0.01 * 0.3
    assert out.channels["G3D"] is slow                                  # slower than the new rate: untouched
    assert bd.at_rate(rec, None) is rec


def test_lowpassed_halves_the_power_at_its_corner_and_the_causal_filter_delays():
    fs = 1000.0
    t = np.arange(40000) / fs
    f_c = 0.2 * fs / 2                                                   # 100 Hz corner
    sines = {f: np.sin(2 * np.pi * f * t) for f in (20.0, f_c, 300.0)}
    rec = Recording({}, {f"G{i}LV": Channel(f"G{i}LV", "guideway_accel", t, 2.0 + v, fs, position_m=10.0 * i)
                         for i, v in enumerate(sines.values(), 1)})
    mid = slice(5000, 35000)
    gain = {f: np.std(bd.lowpassed(rec, 0.2).channels[f"G{i}LV"].values[mid]) / np.std(v[mid])
            for i, (f, v) in enumerate(sines.items(), 1)}
    # zero-phase = the Butterworth magnitude squared: 1 well below the corner, 1/2 at it, (1/3)^8 a decade on
    assert abs(gain[20.0] - 1.0) < 1e-3
    assert abs(gain[f_c] - 0.5) < 5e-3
    assert gain[300.0] < 1.5 * (f_c / 300.0) ** 8
    out = bd.lowpassed(rec, 0.2, causal=True).channels["G1LV"].values
    assert abs(np.mean(out[mid]) - 2.0) < 1e-3                          # the mean is kept
    # the causal filter's phase at 20 Hz: scipy's own frequency response of the same filter
    from scipy import signal
    _, h = signal.sosfreqz(signal.butter(4, 0.2, output="sos"), worN=[20.0], fs=fs)
    ref = np.abs(h[0]) * np.sin(2 * np.pi * 20.0 * t + np.angle(h[0])) + 2.0
    assert np.max(np.abs(out[mid] - ref[mid])) < 1e-3
    assert bd.lowpassed(rec, None) is rec
