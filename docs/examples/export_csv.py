"""Stand-in for a DAQ's CSV export: a contract bag written out the way a rail DAQ exports a run.

    python docs/examples/export_csv.py BAG OUT_DIR

Writes OUT_DIR/run.csv (guideway and magnet channels at their common rate: three preamble
lines, a names row, a units row; ';' between fields, decimal comma; accelerations in g, gaps and
displacements in mm, time in seconds from the first sample) and OUT_DIR/position.csv (the
position channel at its own rate: position in m, speed in km/h), the files the README's "Bring
your own data" example imports back with `maglev-ros import`.
"""
from __future__ import annotations

import argparse
import datetime
import sys
from pathlib import Path

import numpy as np

from maglev_ros.bag_reader import BagReader
from maglev_ros.contract import (TOPIC_GUIDEWAY_ACCEL, TOPIC_GUIDEWAY_DISP, TOPIC_VEHICLE_ACCEL,
                                 TOPIC_VEHICLE_GAP, TOPIC_VEHICLE_POSITION, unit_conversion)

# contract channel id -> the column name this export gives it (how a DAQ operator names channels)
def column_name(channel: str, topic: str) -> str:
    if topic == TOPIC_GUIDEWAY_ACCEL:       # G3LV -> "Acc G3 left"
        side = {"L": "left", "R": "right"}.get(channel[2], channel[2])
        return f"Acc {channel[:2]} {side}"
    if topic == TOPIC_GUIDEWAY_DISP:
        return f"Disp {channel[:-1]}"
    if topic == TOPIC_VEHICLE_ACCEL:
        return f"Acc {channel[:-1]}"
    if topic == TOPIC_VEHICLE_GAP:
        return f"Gap {channel[:-1]}"
    return {"position_m": "Pos", "speed_mps": "v"}[channel]


EXPORT_UNIT = {TOPIC_GUIDEWAY_ACCEL: "g", TOPIC_GUIDEWAY_DISP: "mm", TOPIC_VEHICLE_ACCEL: "g",
               TOPIC_VEHICLE_GAP: "mm", "position_m": "m", "speed_mps": "km/h"}


def _write(path: Path, preamble: list[str], names: list[str], units: list[str], t0_ns: int,
           time_ns: np.ndarray, cols: list[np.ndarray]) -> None:
    rel = (time_ns - t0_ns) * 1e-9
    with open(path, "w", encoding="utf-8", newline="") as fh:
        for line in preamble:
            fh.write(line + "\n")
        fh.write(";".join(["Time"] + names) + "\n")
        fh.write(";".join(["s"] + units) + "\n")
        for i in range(rel.size):
            cells = [f"{rel[i]:.7f}"] + [f"{c[i]:.9g}" for c in cols]
            fh.write(";".join(cells).replace(".", ",") + "\n")


def export(bag_path: str, out_dir: str) -> tuple[Path, Path | None]:
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    data, t_ns = {}, {}
    with BagReader(bag_path) as bag:
        for t in (TOPIC_GUIDEWAY_ACCEL, TOPIC_GUIDEWAY_DISP, TOPIC_VEHICLE_ACCEL, TOPIC_VEHICLE_GAP,
                  TOPIC_VEHICLE_POSITION):
            if t in bag.topics:
                data[t] = bag.read_topic(t)
                # sample times in integer ns from the block stamps (float epoch seconds hold 0.2 us)
                t_ns[t] = np.concatenate([b.stamp_ns + np.round(np.arange(b.n_samples) * 1e9
                                                                / b.sample_rate_hz).astype(np.int64)
                                          for _, b in bag.iter_blocks([t])])
                if t_ns[t].size != data[t].n_samples:
                    sys.exit(f"{bag_path}: {t} has repaired blocks; export it with its own tool")
    fast = [t for t in data if t != TOPIC_VEHICLE_POSITION]
    t0_ns = int(min(v[0] for v in t_ns.values()))
    for t in fast[1:]:
        if not np.array_equal(t_ns[t], t_ns[fast[0]]):
            sys.exit(f"{bag_path}: {t} is not sampled at the times of {fast[0]}; one CSV cannot hold both")
    start = datetime.datetime.fromtimestamp(t0_ns // 1_000_000_000, datetime.timezone.utc)
    iso = start.strftime("%Y-%m-%dT%H:%M:%S") + f".{t0_ns % 1_000_000_000:09d}Z"
    preamble = ["DAQ export (stand-in written by docs/examples/export_csv.py)",
                f"source;{Path(bag_path).name}", f"start;{iso}"]
    names, units, cols = [], [], []
    for t in fast:
        for ch in data[t].channels:
            u = EXPORT_UNIT[t]
            names.append(column_name(ch, t))
            units.append(u)
            cols.append(data[t].channel(ch) / unit_conversion(u)[1])
    run_csv = out / "run.csv"
    _write(run_csv, preamble, names, units, t0_ns, t_ns[fast[0]], cols)
    pos_csv = None
    if TOPIC_VEHICLE_POSITION in data:
        pos_csv = out / "position.csv"
        p = data[TOPIC_VEHICLE_POSITION]
        chans = list(p.channels)
        _write(pos_csv, preamble, [column_name(c, "") for c in chans],
               [EXPORT_UNIT[c] for c in chans], t0_ns, t_ns[TOPIC_VEHICLE_POSITION],
               [p.channel(c) / unit_conversion(EXPORT_UNIT[c])[1] for c in chans])
    print(f"wrote {run_csv}" + (f" and {pos_csv}" if pos_csv else "") + f" (first sample at {iso})")
    return run_csv, pos_csv


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("bag")
    ap.add_argument("out_dir")
    a = ap.parse_args(argv)
    export(a.bag, a.out_dir)
    return 0


if __name__ == "__main__":
    sys.exit(main())
