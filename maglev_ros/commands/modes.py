"""``maglev-ros modes BAG [--json OUT] [--plot OUT.png]``: guideway modes of a recording.

Reads ``/testline/guideway/accel`` and identifies the modes with SSI-cov
(:class:`maglev_ros.modal.ssi_cov.SSICov`). For a ``pass`` recording only the free decay after
the vehicle has left the instrumented span is used (:mod:`maglev_ros.modal.free_decay`): from
``/testline/vehicle/position`` (rearmost magnet past the end of the last instrumented span) when
the bag has it, else from the response envelope.

With no options the settings follow the recording (:mod:`maglev_ros.modal.bands`): modes are
looked for from 1 Hz (raised for a short record) to 0.4 x the sampling rate, in bands of at
most a decade, each decimated and given block rows and orders by stated rules; the modes of all
bands are merged. Given options override. Accelerometers on several spans that move apart (their
coherence at chance level) are identified span by span as well (:mod:`maglev_ros.modal.groups`).
Prints the settings and a table; ``--json`` writes the ``maglev-modes/1`` document (settings under
``source.settings``); ``--plot`` writes the stabilization diagram over the spectrum.
"""
from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from maglev_ros import outputs
from maglev_ros.errors import UserError

if TYPE_CHECKING:  # the science stack is imported when the verb runs, not at CLI start
    from maglev_ros.modal.bands import BandPlan
    from maglev_ros.modal.ssi_cov import ModalResult

NAME = "modes"
HELP = "identify guideway modes (SSI-cov; free decay for a vehicle pass)"
ORDER = 40

TOPIC_ACCEL = "/testline/guideway/accel"
TOPIC_POSITION = "/testline/vehicle/position"


def add_arguments(p) -> None:
    p.add_argument("bag", metavar="BAG", help="rosbag2 directory, .mcap/.db3 file")
    p.add_argument("--json", metavar="OUT", help="write the maglev-modes/1 JSON document here")
    p.add_argument("--plot", metavar="OUT.png", help="write the stabilization diagram here")
    p.add_argument("--fmin-hz", type=float, default=None,
                   help="lowest mode frequency (default: 1 Hz, raised for a short record)")
    p.add_argument("--fmax-hz", type=float, default=None,
                   help="highest mode frequency (default: 0.4 x the sampling rate)")
    p.add_argument("--block-rows", type=int, default=None,
                   help="SSI block rows i in every band (default: 2 periods of the band's lowest "
                        "frequency)")
    p.add_argument("--max-order", type=int, default=None,
                   help="highest model order (default: channels x block rows / 2, at most 100)")
    p.add_argument("--decimate-to-hz", type=float, default=None,
                   help="identify in one band decimated to at least this rate (default: "
                        "bands of at most a decade, each at >= 2.5 x its top frequency)")
    p.add_argument("--scale-channels", choices=("auto", "yes", "no"), default="auto",
                   help="divide each channel by its std before SSI (auto: when units differ)")
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


@dataclass(frozen=True)
class BagModes:
    """Modes of one recording, what was read (``info``, JSON-ready) and the settings used."""
    result: ModalResult
    info: dict
    plan: BandPlan
    health: Any = None        # maglev_ros.health.HealthReport of what was read


def identify_bag(path, fmin_hz=None, fmax_hz=None, block_rows=None, max_order=None,
                 decimate_to_hz=None, window="auto", scale_channels=None):
    """Open the bag and identify; returns (ModalResult, info dict), see :func:`identify_modes`."""
    out = identify_modes(path, fmin_hz, fmax_hz, block_rows, max_order, decimate_to_hz, window,
                         scale_channels)
    return out.result, out.info


def identify_modes(path, fmin_hz=None, fmax_hz=None, block_rows=None, max_order=None,
                   decimate_to_hz=None, window="auto", scale_channels=None) -> BagModes:
    """Open the bag (or a :class:`~maglev_ros.bag_memory.MemoryBag`: a recording a node received)
    and identify. Settings left at None are chosen from the recording
    (:func:`maglev_ros.modal.bands.plan_bands`); ``info["settings"]`` states them and where
    each came from. ``scale_channels`` None: divide each channel by its std only when the
    channels' units differ."""
    from maglev_ros.bag_memory import open_reader, source_name
    from maglev_ros.bag_windows import read_checked_windows

    with open_reader(path) as r:
        path = source_name(path)
        if TOPIC_ACCEL not in r.topics:
            raise UserError(f"{path}: topic {TOPIC_ACCEL} not in bag; expected guideway "
                            f"accelerations (topics: {', '.join(sorted(r.topics)) or 'none'})")
        md = r.metadata
        kind = md.run_kind if md is not None else "ambient"
        # a pass places the sensors on their spans (free-decay window): that needs the sensor map;
        # the accelerations stay in the bag, read window by window: memory stays bounded
        read, health = read_checked_windows(
            r, [TOPIC_ACCEL], [TOPIC_POSITION] if TOPIC_POSITION in r.topics else [],
            sensor_map=kind == "pass")
        args = (path, r, md, kind, read[TOPIC_ACCEL], read.get(TOPIC_POSITION), fmin_hz, fmax_hz, block_rows,
                max_order, decimate_to_hz, window, scale_channels)
        out = _identify_streamed(*args)
        groups = _span_groups(md, out.info["channels"])
        test = _test_window(out, r, read[TOPIC_ACCEL])
        if len(groups) > 1:
            out = _with_span_groups(out, groups, args, test)
        out = _spectral_peaks_only(out, test)
    return BagModes(out.result, out.info, out.plan, health)


# at most this many samples decide whether spans move apart (a few minutes at 1 kHz: Welch has dozens
# of segments; the bag may be longer than memory)
GROUP_TEST_SAMPLES = 2 ** 18


def _test_window(out: BagModes, r, acc):
    """The accelerations the identification used (the free-decay window of a pass), at most
    GROUP_TEST_SAMPLES of them: what the span-group and spectral-peak tests look at."""
    from maglev_ros.bag_windows import read_window
    t0 = acc.first_time_s
    win = out.info.get("free_decay_window")
    lo = t0 + (win["start_s"] if win else 0.0)
    hi = min(t0 + win["stop_s"] if win else np.inf, lo + GROUP_TEST_SAMPLES / float(acc.sample_rate_hz))
    return read_window(r, acc, lo, hi)


def _with_span_groups(out: BagModes, groups, args, cd) -> BagModes:
    """Each span's sensors identified alone too when the spans move apart (:mod:`maglev_ros.modal.groups`:
    identical spans ring at one frequency and their joint poles never stabilize). ``cd``: :func:`_test_window`."""
    from maglev_ros.modal.groups import independent_groups, merge_group_modes, spectral_peaks
    chans = out.info["channels"]
    cols = [[list(cd.channels).index(n) for n in names] for _, names in groups]
    data = np.asarray(cd.data, dtype=float)
    apart, evidence = independent_groups(data, float(cd.sample_rate_hz), cols)
    out.info["span_groups"] = {"spans": [sid for sid, _ in groups], "identified_apart": apart, **evidence}
    if not apart:
        return out
    parts = [(names, _identify_streamed(*args, cols=[chans.index(n) for n in names]).result) for _, names in groups]
    keep = [spectral_peaks(data[:, c], float(cd.sample_rate_hz), part) for c, (_, part) in zip(cols, parts)]
    merged, added = merge_group_modes(out.result, parts, keep)
    out.info["channel_groups"] = [
        {"span": sid, "channels": list(names), "modes_added": a,
         "not_spectral_peaks_hz": [round(m.frequency_hz, 3) for k, m in enumerate(part.modes) if k not in kp]}
        for (sid, names), a, (_, part), kp in zip(groups, added, parts, keep)]
    return BagModes(merged, out.info, out.plan)


def _spectral_peaks_only(out: BagModes, cd) -> BagModes:
    """Every reported mode is a spectral peak of its own in the data it was identified on (``cd``:
    :func:`_test_window`): a pole that stabilizes over the model orders without a resonance in any
    channel's PSD (a ghost between two modes of a broadband record) is not reported; one too close to
    another mode for the PSD to resolve is kept (the test cannot decide). Dropped ones are listed in
    ``not_spectral_peaks_hz``."""
    from maglev_ros.modal.groups import spectral_peaks, without_modes
    f = out.result.frequencies_hz()
    cols = [list(cd.channels).index(n) for n in out.info["channels"] if n in cd.channels]
    data = np.asarray(cd.data, dtype=float)[:, cols]
    keep = spectral_peaks(data, float(cd.sample_rate_hz), out.result, undecided=True) if f.size else set()
    drop = set(range(f.size)) - keep
    out.info["not_spectral_peaks_hz"] = [round(float(f[k]), 3) for k in sorted(drop)]
    if not drop:
        return out
    return BagModes(without_modes(out.result, drop), out.info, out.plan)


def _span_groups(md, channels) -> list[tuple[str, list[str]]]:
    """(span id, its channels) for every span the metadata places accelerometers on, in line order."""
    if md is None:
        return []
    groups: dict[str, list[str]] = {}
    for ch in channels:
        s = md.sensors.get(ch)
        span = s.span if s is not None else None
        if s is not None and not span and s.position_m is not None:      # placed by position alone
            span = next((sp.id for sp in md.spans if sp.start_m <= s.position_m <= sp.end_m), None)
        if span:
            groups.setdefault(span, []).append(ch)
    order = [sp.id for sp in md.spans]
    return sorted(groups.items(), key=lambda kv: order.index(kv[0]) if kv[0] in order else len(order))


def _channel_scaling(units, scale_channels) -> tuple[bool, str]:
    """Whether each channel is brought to unit std, and why (``scale_channels`` None: by the units)."""
    if scale_channels is not None:
        return scale_channels, "user"
    # one unit: amplitudes are commensurable and like sensors' noise weighs them alike;
    # mixed units have no common scale, so each channel is brought to unit std
    if len(set(units)) > 1:
        return True, "channels' units differ"
    return False, f"all channels in {units[0] if units else '?'}: recorded amplitudes kept"


def _identify_streamed(path, r, md, kind, acc, pos, fmin_hz, fmax_hz, block_rows, max_order,
                       decimate_to_hz, window, scale_channels, cols=None) -> BagModes:
    """identify_modes' processing of the accelerations ``acc`` (a CheckedTopic of the open bag
    ``r``; only its columns ``cols`` when given): every pass reads them in windows
    (:mod:`maglev_ros.bag_windows`) and the identification sums over chunks
    (:mod:`maglev_ros.modal.chunked`), with the whole-array path's results (:func:`_identify_whole`)."""
    from maglev_ros.bag_windows import iter_windows, read_window
    from maglev_ros.modal.bands import plan_bands
    from maglev_ros.modal.chunked import TopicChunks, identify_bands_chunked
    from maglev_ros.modal.free_decay import exit_time_s, position_window_streamed

    fs = float(acc.sample_rate_hz)
    channels, units = acc.channels, acc.units
    n = acc.n_samples
    use_decay = window == "free-decay" or (window == "auto" and kind == "pass")
    end = _span_end_m(md, channels) if md is not None else None      # all channels: one window for all
    if use_decay and not (pos is not None and "position_m" in pos.channels and end is not None):
        # the envelope rule needs each channel's median over the record: read it whole
        cd = read_window(r, acc, -np.inf, np.inf)
        return _identify_whole(path, cd, md, kind, pos, fmin_hz, fmax_hz, block_rows, max_order,
                               decimate_to_hz, window, scale_channels, cols)
    if cols is not None:
        channels, units = [channels[c] for c in cols], [units[c] for c in cols]
    info = {"bag": str(path), "topic": TOPIC_ACCEL, "run_kind": kind, "fs_hz": fs,
            "n_samples": int(n), "channels": list(channels)}
    start, stop = 0, n
    if use_decay:
        t_first = acc.first_time_s
        t_exit = exit_time_s(pos.channel("position_m"), pos.time_s - t_first, end,
                             min(md.magnet_offsets_m or (0.0,)))
        win = position_window_streamed((w.time_s - t_first for w in iter_windows(r, acc)), fs,
                                       t_exit)
        info["free_decay_window"] = win.to_dict()
        start, stop = win.start_index, win.stop_index
    scale_channels, scale_src = _channel_scaling(units, scale_channels)
    try:
        plan = plan_bands(fs, stop - start, len(channels), stationary=not use_decay,
                          fmin_hz=fmin_hz, fmax_hz=fmax_hz, block_rows=block_rows,
                          max_order=max_order, decimate_to_hz=decimate_to_hz,
                          scale_channels=scale_channels, scale_source=scale_src)
    except UserError as e:
        raise UserError(f"{path} ({TOPIC_ACCEL}): {e}") from None
    info["settings"] = plan.to_dict()
    chunks = TopicChunks(r, acc, start, stop)
    if cols is not None:
        from maglev_ros.modal.groups import ColumnChunks
        chunks = ColumnChunks(chunks, cols)
    res, _ = identify_bands_chunked(chunks, fs, plan, channels)
    return BagModes(res, info, plan)


def _identify_whole(path, cd, md, kind, pos, fmin_hz=None, fmax_hz=None, block_rows=None,
                    max_order=None, decimate_to_hz=None, window="auto",
                    scale_channels=None, cols=None) -> BagModes:
    """identify_modes on the whole topic ``cd`` in memory (as read, health-checked; only its
    columns ``cols`` when given, the free-decay window chosen on all of them)."""
    from maglev_ros.modal.bands import identify_bands, plan_bands
    from maglev_ros.modal.free_decay import select_free_decay

    fs = float(cd.sample_rate_hz)
    data = np.asarray(cd.data, dtype=float)
    use_decay = window == "free-decay" or (window == "auto" and kind == "pass")
    info = {"bag": str(path), "topic": TOPIC_ACCEL, "run_kind": kind, "fs_hz": fs,
            "n_samples": int(data.shape[0]), "channels": list(cd.channels)}
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
        data = data[win.start_index:win.stop_index]
    names, units = list(cd.channels), list(cd.units)
    if cols is not None:
        data, names, units = data[:, cols], [names[c] for c in cols], [units[c] for c in cols]
        info["channels"] = names
    scale_channels, scale_src = _channel_scaling(units, scale_channels)
    try:
        plan = plan_bands(fs, data.shape[0], data.shape[1], stationary=not use_decay,
                          fmin_hz=fmin_hz, fmax_hz=fmax_hz, block_rows=block_rows,
                          max_order=max_order, decimate_to_hz=decimate_to_hz,
                          scale_channels=scale_channels, scale_source=scale_src)
    except UserError as e:
        raise UserError(f"{path} ({TOPIC_ACCEL}): {e}") from None
    info["settings"] = plan.to_dict()
    res, _ = identify_bands(data, fs, plan, names)
    return BagModes(res, info, plan)


def run(args) -> int:
    bag = Path(args.bag)
    if not bag.exists():
        raise UserError(f"{bag}: no such bag (expected a rosbag2 directory or .mcap/.db3 file)")
    # the outputs can be written: checked before the identification, not after
    if args.json is not None:
        outputs.check_file(args.json, "--json")
    if args.plot is not None:
        outputs.check_figure(args.plot, "--plot")
    out = identify_modes(bag, args.fmin_hz, args.fmax_hz, args.block_rows, args.max_order,
                         args.decimate_to_hz, args.window,
                         {"auto": None, "yes": True, "no": False}[args.scale_channels])
    res, info, plan = out.result, out.info, out.plan
    for line in out.health.lines():
        print(f"maglev-ros modes: {line}", file=sys.stderr)
    print(f"{bag}: {info['run_kind']} recording, {len(info['channels'])} channels at "
          f"{info['fs_hz']:g} Hz, {info['n_samples'] / info['fs_hz']:.4g} s")
    if "free_decay_window" in info:
        w = info["free_decay_window"]
        print(f"free decay ({w['method']}): {w['start_s']:.2f} .. {w['stop_s']:.2f} s")
    for line in plan.describe():
        print(line)
    print(f"{'id':>4s} {'f [Hz]':>9s} {'+-':>7s} {'zeta [%]':>9s} {'+-':>6s} {'MPC':>6s}")
    for m in res.modes:
        sf = m.std_frequency_hz if np.isfinite(m.std_frequency_hz) else float("nan")
        sz = m.std_damping_ratio if np.isfinite(m.std_damping_ratio) else float("nan")
        print(f"{m.id:>4s} {m.frequency_hz:9.3f} {sf:7.3f} {100 * m.damping_ratio:9.3f} "
              f"{100 * sz:6.3f} {m.mpc:6.3f}")
    if not res.modes:
        print("no stable modes found")
    if info.get("not_spectral_peaks_hz"):
        print("not reported (stable poles without a spectral peak of their own): "
              + ", ".join(f"{x:g} Hz" for x in info["not_spectral_peaks_hz"]))
    with outputs.Batch() as batch:          # the JSON and the plot replace the earlier pair together
        if args.json:
            doc = res.to_dict()
            doc["source"] = info
            doc["health"] = out.health.to_dict()
            batch.write_json(args.json, doc, indent=1, option="--json")
        if args.plot:
            from maglev_ros.modal.plot import save_stabilization_diagram
            save_stabilization_diagram(res, args.plot, title=f"{bag.name}: {info['run_kind']}",
                                       freq_range_hz=(plan.fmin_hz, plan.fmax_hz), batch=batch,
                                       option="--plot")
    return 0
