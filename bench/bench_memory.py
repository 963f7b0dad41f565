"""Peak memory against recording length: ``modes`` and ``irregularity`` must stay bounded like
``info`` and a replay-like read of the bag.

Writes, for each length (default 2, 10 and 30 min), an ambient recording (10 guideway
accelerometers at 1 kHz: seven damped modes driven by white noise, plus sensor noise) and a pass
recording (4 magnets' accelerations and gaps at 1 kHz, position and speed at 100 Hz, about
7 m/s over a random rail), both generated block by block. Then runs, each in its own
subprocess, and reads that process' peak RSS (``os.wait4``):

  info          maglev-ros info BAG                        (the peer: streams the bag)
  read          every message of the bag through BagReader.iter_raw (what replay does)
  modes         maglev-ros modes AMBIENT --json OUT
  irregularity  maglev-ros irregularity PASS --out OUT.csv --json OUT.json

and prints peak RSS [MB] per length, the ratio to ``info`` on the same bag, and wall time.
Target: modes and irregularity flat in length (bounded by their window, not the recording),
within about 2 x info. ``--diagnose`` also runs the README demo's diagnosis on the sample bags
(a few minutes) against its target of 1.5 GB peak RSS.

    .venv/bin/python bench/bench_memory.py [--minutes 2 10 30] [--keep DIR] [--diagnose]
"""
from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy import signal

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from maglev_ros.bag_writer import BagWriter  # noqa: E402
from maglev_ros.contract import (TOPIC_GUIDEWAY_ACCEL, TOPIC_VEHICLE_ACCEL,  # noqa: E402
                                 TOPIC_VEHICLE_GAP, TOPIC_VEHICLE_POSITION)
from maglev_ros.sensor_block import Block  # noqa: E402

FS_HZ = 1000.0
FS_POS_HZ = 100.0
BLOCK_S = 0.1
CHUNK_S = 60.0                       # generated per chunk: the generator's memory stays bounded
SPAN_M = 24.768
MODES = [(23.49, 0.015), (41.76, 0.012), (43.77, 0.018), (79.69, 0.02), (104.3, 0.016),
         (131.8, 0.022), (176.0, 0.02)]
MAGNET_OFFSETS_M = (0.0, -1.548, -3.096, -4.644)
SPEED_MPS = 6.944
T0_NS = 1_700_000_000_000_000_000


def _spans(n):
    return [{"id": f"S{k + 1}", "start_m": k * SPAN_M, "length_m": SPAN_M} for k in range(n)]


def _write_chunk(w, topic, t_first_s, rate, channels, units, data, frame):
    bs = int(round(BLOCK_S * rate))
    first = int(round(t_first_s * rate))
    for i in range(0, data.shape[0], bs):
        stamp = T0_NS + int(round((first + i) * 1e9 / rate))
        w.write_block(topic, Block.from_arrays(stamp, rate, channels, units, data[i:i + bs], frame))


def write_ambient(path: Path, minutes: float, seed: int = 0) -> Path:
    """Ambient vibration of one span: modal coordinates (white noise through each mode's
    resonator, filter states carried across chunks) on sine shapes at 5 sections x 2 sides."""
    rng = np.random.default_rng(seed)
    xs = SPAN_M * np.arange(1, 6) / 6.0
    channels = tuple(f"G{j + 1}{s}V" for j in range(5) for s in "LR")
    shapes = np.array([[np.sin((1 + r % 3) * np.pi * x / SPAN_M) * (1 if s == "L" or r % 2 == 0 else -1)
                        for r in range(len(MODES))] for x in xs for s in "LR"])
    filt = []
    for f, z in MODES:
        p = np.exp((-z + 1j * np.sqrt(1 - z * z)) * 2 * np.pi * f / FS_HZ)
        filt.append(([1.0, -2.0, 1.0], [1.0, -2 * p.real, abs(p) ** 2]))
    zi = [np.zeros(2) for _ in MODES]
    meta = {"schema": "maglev-testline/1", "description": "bench_memory ambient",
            "line": {"spans": _spans(3)},
            "sensors": {c: {"topic": TOPIC_GUIDEWAY_ACCEL, "quantity": "acceleration",
                            "direction": "vertical", "span": "S2",
                            "position_m": SPAN_M + xs[k // 2], "side": "left" if c[2] == "L" else "right"}
                        for k, c in enumerate(channels)},
            "run": {"kind": "ambient"}}
    n_total = int(round(minutes * 60 * FS_HZ))
    chunk = int(CHUNK_S * FS_HZ)
    with BagWriter(path, meta) as w:
        for i0 in range(0, n_total, chunk):
            n = min(chunk, n_total - i0)
            q = np.empty((n, len(MODES)))
            for r, (b, a) in enumerate(filt):
                q[:, r], zi[r] = signal.lfilter(b, a, rng.standard_normal(n), zi=zi[r])
            y = q @ shapes.T
            y += 0.05 * y.std() * rng.standard_normal(y.shape)
            _write_chunk(w, TOPIC_GUIDEWAY_ACCEL, i0 / FS_HZ, FS_HZ, channels,
                         ("m/s^2",) * len(channels), y, "guideway")
    return path


def write_pass(path: Path, minutes: float, seed: int = 0) -> Path:
    """A long pass at about 7 m/s (+-10 % slow speed variation) over a random rail (sum of
    random sinusoids, 2-120 m wavelengths, mm amplitudes): the magnets follow the rail through a
    6 Hz second-order levitation loop; accel = the loop's output acceleration + noise, gap =
    g0 + rail - magnet + noise."""
    rng = np.random.default_rng(seed)
    lam = np.exp(rng.uniform(np.log(2.0), np.log(120.0), 300))
    amp = 1.5e-3 * (lam / 120.0) ** 1.0 * rng.rayleigh(1.0, lam.size) / np.sqrt(lam.size / 20)
    ph = rng.uniform(0, 2 * np.pi, lam.size)

    def rail(x):
        return np.sin(np.outer(x, 2 * np.pi / lam) + ph) @ amp

    wn, zeta = 2 * np.pi * 6.0, 0.7
    # the loop's magnet position and acceleration outputs as discrete transfer functions (zoh)
    sysd = signal.cont2discrete(tuple(np.array(m, float) for m in (
        [[0, 1], [-wn * wn, -2 * zeta * wn]], [[0], [wn * wn]],
        [[1, 0], [-wn * wn, -2 * zeta * wn]], [[0], [wn * wn]])), 1.0 / FS_HZ, method="zoh")
    tfs = [signal.ss2tf(*sysd[:4])[0][j] for j in (0, 1)]
    den = signal.ss2tf(*sysd[:4])[1]
    zis = [[None, None] for _ in MAGNET_OFFSETS_M]
    acc_ch = tuple(f"M{k + 1}A" for k in range(len(MAGNET_OFFSETS_M)))
    gap_ch = tuple(f"M{k + 1}G" for k in range(len(MAGNET_OFFSETS_M)))
    sensors = {c: {"topic": TOPIC_VEHICLE_ACCEL, "quantity": "acceleration", "direction": "vertical",
                   "magnet": k + 1} for k, c in enumerate(acc_ch)}
    sensors.update({c: {"topic": TOPIC_VEHICLE_GAP, "quantity": "gap", "magnet": k + 1}
                    for k, c in enumerate(gap_ch)})
    sensors["position_m"] = {"topic": TOPIC_VEHICLE_POSITION, "quantity": "position"}
    sensors["speed_mps"] = {"topic": TOPIC_VEHICLE_POSITION, "quantity": "speed"}
    n_total = int(round(minutes * 60 * FS_HZ))
    length_m = SPEED_MPS * 1.15 * n_total / FS_HZ + 100.0
    meta = {"schema": "maglev-testline/1", "description": "bench_memory pass",
            "line": {"spans": _spans(int(length_m // SPAN_M) + 1)}, "sensors": sensors,
            "vehicle": {"magnet_offsets_m": list(MAGNET_OFFSETS_M), "nominal_gap_m": 0.010},
            "run": {"kind": "pass", "nominal_speed_mps": SPEED_MPS}}
    chunk = int(CHUNK_S * FS_HZ)
    step = int(FS_HZ / FS_POS_HZ)
    x0 = 20.0
    with BagWriter(path, meta) as w:
        for i0 in range(0, n_total, chunk):
            n = min(chunk, n_total - i0)
            t = (i0 + np.arange(n)) / FS_HZ
            # x(t) of v(t) = V (1 + 0.1 sin(2 pi t / 97 s)), integrated exactly
            x = x0 + SPEED_MPS * (t - 0.1 * 97.0 / (2 * np.pi) * (np.cos(2 * np.pi * t / 97.0) - 1))
            v = SPEED_MPS * (1 + 0.1 * np.sin(2 * np.pi * t / 97.0))
            acc = np.empty((n, len(MAGNET_OFFSETS_M)))
            gap = np.empty_like(acc)
            for k, off in enumerate(MAGNET_OFFSETS_M):
                r = rail(x + off)
                out = np.empty((n, 2))
                for j in (0, 1):
                    if zis[k][j] is None:          # at rest on the rail's first height
                        zis[k][j] = signal.lfilter_zi(tfs[j], den) * r[0]
                    out[:, j], zis[k][j] = signal.lfilter(tfs[j], den, r, zi=zis[k][j])
                acc[:, k] = out[:, 1] + 0.02 * rng.standard_normal(n)
                gap[:, k] = 0.010 + r - out[:, 0] + 5e-6 * rng.standard_normal(n)
            sel = slice(0, n, step)
            pos = np.column_stack([x[sel], v[sel]])
            _write_chunk(w, TOPIC_VEHICLE_ACCEL, i0 / FS_HZ, FS_HZ, acc_ch, ("m/s^2",) * 4, acc, "vehicle")
            _write_chunk(w, TOPIC_VEHICLE_GAP, i0 / FS_HZ, FS_HZ, gap_ch, ("m",) * 4, gap, "vehicle")
            _write_chunk(w, TOPIC_VEHICLE_POSITION, i0 / FS_HZ, FS_POS_HZ, ("position_m", "speed_mps"),
                         ("m", "m/s"), pos, "vehicle")
    return path


READ_SNIPPET = ("import sys; from maglev_ros.bag_reader import BagReader\n"
                "with BagReader(sys.argv[1]) as r:\n"
                "    n = sum(len(raw) for *_, raw in r.iter_raw())\n")


# a small launcher runs the command: a child forked straight from this (large) process would
# report this process' RSS as its own peak (Linux carries the peak across fork and exec)
LAUNCHER = ("import os, subprocess, sys\n"
            "p = subprocess.Popen(sys.argv[1:], stdout=subprocess.DEVNULL)\n"
            "_, status, ru = os.wait4(p.pid, 0)\n"
            "print(ru.ru_maxrss, os.waitstatus_to_exitcode(status))\n")


def peak_rss_mb(argv) -> tuple[float, float, int]:
    """(peak RSS of the command in MB, wall s, exit code); its stdout is discarded."""
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    t = time.perf_counter()
    p = subprocess.run([sys.executable, "-c", LAUNCHER, *map(str, argv)], capture_output=True,
                       text=True, env=env, cwd=ROOT)
    wall = time.perf_counter() - t
    kb, code = (int(v) for v in p.stdout.split())
    if code != 0:
        err = p.stderr.strip().splitlines()
        print(f"  ! {' '.join(map(str, argv[2:5]))}: exit {code}: {err[-1] if err else ''}")
    return kb / 1024.0, wall, code


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--minutes", type=float, nargs="+", default=[2.0, 10.0, 30.0])
    ap.add_argument("--keep", default=None, help="write the recordings here and keep them")
    ap.add_argument("--only", nargs="+", default=["info", "read", "modes", "irregularity"])
    ap.add_argument("--diagnose", action="store_true",
                    help="also the demo's diagnose on bags/ (target: peak RSS < 1.5 GB)")
    a = ap.parse_args()
    work = Path(a.keep) if a.keep else Path(tempfile.mkdtemp(prefix="bench_memory_"))
    work.mkdir(parents=True, exist_ok=True)
    py = sys.executable
    cli = [py, "-m", "maglev_ros.cli"]
    rows = []
    try:
        for m in a.minutes:
            amb, pas = work / f"ambient_{m:g}min", work / f"pass_{m:g}min"
            t = time.perf_counter()
            if not amb.exists():
                write_ambient(amb, m)
            if not pas.exists():
                write_pass(pas, m)
            print(f"{m:g} min: recordings ready ({time.perf_counter() - t:.0f} s)", flush=True)
            runs = {"info": (cli + ["info", str(amb)], cli + ["info", str(pas)]),
                    "read": ([py, "-c", READ_SNIPPET, str(amb)], [py, "-c", READ_SNIPPET, str(pas)]),
                    "modes": (cli + ["modes", str(amb), "--json", str(work / "modes.json")], None),
                    "irregularity": (None, cli + ["irregularity", str(pas), "--out",
                                                  str(work / "irr.csv"), "--json",
                                                  str(work / "irr.json")])}
            row = {"minutes": m}
            for name in a.only:
                for which, argv in zip(("ambient", "pass"), runs[name]):
                    if argv is None:
                        continue
                    mb, wall, code = peak_rss_mb(argv)
                    row[(name, which)] = (mb, wall, code)
                    print(f"  {name:13s} {which:8s} {mb:8.0f} MB {wall:7.1f} s", flush=True)
            rows.append(row)
    finally:
        if not a.keep:
            shutil.rmtree(work, ignore_errors=True)
    print()
    print(f"{'minutes':>8s} | {'info amb':>9s} {'info pass':>9s} | {'read amb':>9s} "
          f"{'read pass':>9s} | {'modes':>8s} {'x info':>7s} | {'irreg.':>8s} {'x info':>7s}")
    for row in rows:
        def mb(k):
            v = row.get(k)
            return f"{v[0]:9.0f}" if v else f"{'-':>9s}"

        def ratio(k, peer):
            v, p = row.get(k), row.get(peer)
            return f"{v[0] / p[0]:7.2f}" if v and p else f"{'-':>7s}"
        print(f"{row['minutes']:8g} | {mb(('info', 'ambient'))} {mb(('info', 'pass'))} | "
              f"{mb(('read', 'ambient'))} {mb(('read', 'pass'))} | {mb(('modes', 'ambient'))[1:]} "
              f"{ratio(('modes', 'ambient'), ('info', 'ambient'))} | "
              f"{mb(('irregularity', 'pass'))[1:]} {ratio(('irregularity', 'pass'), ('info', 'pass'))}")
    print("peak RSS in MB (os.wait4 of each subprocess); ratio to info on the same recording")
    if a.diagnose:
        bags = ROOT / "bags"
        with tempfile.TemporaryDirectory() as out:
            mb, wall, code = peak_rss_mb(cli + ["diagnose", "--ambient", str(bags / "paper_ambient"),
                                                "--pass", str(bags / "paper_pass"), "--pass",
                                                str(bags / "paper_pass2"), "--out", out, "--quiet"])
        print(f"diagnose on bags/ (the demo's call): {mb:.0f} MB peak RSS (target < 1500 MB), "
              f"{wall:.0f} s, exit {code}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
