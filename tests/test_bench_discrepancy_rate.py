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
