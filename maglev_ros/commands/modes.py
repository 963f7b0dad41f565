"""``maglev-ros modes BAG [--json OUT] [--plot OUT.png]``: guideway modes of a recording.

Reads ``/testline/guideway/accel`` and identifies the modes with SSI-cov
(:class:`maglev_ros.modal.ssi_cov.SSICov`). For a ``pass`` recording only the free decay after
the vehicle has left the instrumented span is used (:mod:`maglev_ros.modal.free_decay`): from
``/testline/vehicle/position`` (rearmost magnet past the end of the last instrumented span) when
the bag has it, else from the response envelope. Prints a table; ``--json`` writes the
``maglev-modes/1`` document; ``--plot`` writes the stabilization diagram over the spectrum.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from maglev_ros.errors import UserError

NAME = "modes"
HELP = "identify guideway modes (SSI-cov; free decay for a vehicle pass)"
ORDER = 40

TOPIC_ACCEL = "/testline/guideway/accel"
TOPIC_POSITION = "/testline/vehicle/position"


def add_arguments(p) -> None:
    p.add_argument("bag", metavar="BAG", help="rosbag2 directory, .mcap/.db3 file")
    p.add_argument("--json", metavar="OUT", help="write the maglev-modes/1 JSON document here")
    p.add_argument("--plot", metavar="OUT.png", help="write the stabilization diagram here")
    p.add_argument("--fmin-hz", type=float, default=1.0, help="lowest mode frequency (default 1)")
    p.add_argument("--fmax-hz", type=float, default=150.0, help="highest mode frequency (default 150)")
    p.add_argument("--block-rows", type=int, default=40, help="SSI block rows i (default 40)")
    p.add_argument("--max-order", type=int, default=80, help="highest model order (default 80)")
    p.add_argument("--decimate-to-hz", type=float, default=None,
                   help="decimate to at least this rate (default: about 3.3 x fmax)")
    p.add_argument("--window", choices=("auto", "all", "free-decay"), default="auto",
                   help="data used: auto = free decay for a pass, everything for ambient")


def _span_end_m(md, channels) -> float | None:
    """End (x) of the last span carrying one of the channels (None if unknown)."""
    spans = {s.id: s for s in md.spans}
    ends = []
    for ch in channels:
        s = md.sensors.get(ch)
        if s is not None and s.span in spans:
            sp = spans[s.span]
            ends.append(sp.start_m + sp.length_m)
    return max(ends) if ends else None


def identify_bag(path, fmin_hz=1.0, fmax_hz=150.0, block_rows=40, max_order=80,
                 decimate_to_hz=None, window="auto"):
    """Open the bag and identify; returns (ModalResult, info dict)."""
    from maglev_ros.bag_reader import BagReader
    from maglev_ros.modal.free_decay import identify_free_decay, select_free_decay
    from maglev_ros.modal.ssi_cov import SSICov

    with BagReader(path) as r:
        if TOPIC_ACCEL not in r.topics:
            raise UserError(f"{path}: topic {TOPIC_ACCEL} not in bag; expected guideway "
                            f"accelerations (topics: {', '.join(sorted(r.topics)) or 'none'})")
        cd = r.read_topic(TOPIC_ACCEL)
        md = r.metadata
        kind = md.run_kind if md is not None else "ambient"
        pos = r.read_topic(TOPIC_POSITION) if TOPIC_POSITION in r.topics else None
    fs = float(cd.sample_rate_hz)
    if fmax_hz >= 0.45 * fs:
        raise UserError(f"--fmax-hz: {fmax_hz} Hz must be below 0.45 x the sampling rate "
                        f"{fs} Hz of {TOPIC_ACCEL}")
    if decimate_to_hz is None and fs > 4.0 * fmax_hz:
        decimate_to_hz = 3.3 * fmax_hz
    data = np.asarray(cd.data, dtype=float)
    use_decay = window == "free-decay" or (window == "auto" and kind == "pass")
    info = {"bag": str(path), "topic": TOPIC_ACCEL, "run_kind": kind, "fs_hz": fs,
            "n_samples": int(data.shape[0]), "channels": list(cd.channels)}
    est = SSICov(block_rows=block_rows, orders=range(2, max_order + 1, 2),
                 decimate_to_hz=decimate_to_hz, freq_range_hz=(fmin_hz, fmax_hz),
                 uncertainty="cluster" if use_decay else "blocks")
    if use_decay:
        t = cd.time_s - cd.time_s[0]
        kw = {}
        if pos is not None and "position_m" in pos.channels and md is not None:
            end = _span_end_m(md, cd.channels)
            offs = md.magnet_offsets_m or (0.0,)
            if end is not None:
                kw = dict(position_m=pos.channel("position_m"),
                          position_time_s=pos.time_s - cd.time_s[0], span_end_m=end,
                          rear_offset_m=min(offs))
        win = select_free_decay(data, fs, time_s=t, **kw)
        info["free_decay_window"] = win.to_dict()
        res = identify_free_decay(data, fs, win, est, channels=cd.channels)
    else:
        res = est.fit(data, fs, cd.channels)
    return res, info


def run(args) -> int:
    bag = Path(args.bag)
    if not bag.exists():
        raise UserError(f"{bag}: no such bag (expected a rosbag2 directory or .mcap/.db3 file)")
    res, info = identify_bag(bag, args.fmin_hz, args.fmax_hz, args.block_rows, args.max_order,
                             args.decimate_to_hz, args.window)
    print(f"{bag}: {info['run_kind']} recording, {len(info['channels'])} channels at "
          f"{info['fs_hz']:g} Hz, identified at {res.fs_hz:.1f} Hz")
    if "free_decay_window" in info:
        w = info["free_decay_window"]
        print(f"free decay ({w['method']}): {w['start_s']:.2f} .. {w['stop_s']:.2f} s")
    print(f"{'id':>4s} {'f [Hz]':>9s} {'+-':>7s} {'zeta [%]':>9s} {'+-':>6s} {'MPC':>6s}")
    for m in res.modes:
        sf = m.std_frequency_hz if np.isfinite(m.std_frequency_hz) else float("nan")
        sz = m.std_damping_ratio if np.isfinite(m.std_damping_ratio) else float("nan")
        print(f"{m.id:>4s} {m.frequency_hz:9.3f} {sf:7.3f} {100 * m.damping_ratio:9.3f} "
              f"{100 * sz:6.3f} {m.mpc:6.3f}")
    if not res.modes:
        print("no stable modes found")
    if args.json:
        doc = res.to_dict()
        doc["source"] = info
        Path(args.json).write_text(json.dumps(doc, indent=1))
    if args.plot:
        from maglev_ros.modal.plot import save_stabilization_diagram
        save_stabilization_diagram(res, args.plot, title=f"{bag.name}: {info['run_kind']}",
                                   freq_range_hz=(args.fmin_hz, args.fmax_hz))
    return 0
