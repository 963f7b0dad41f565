"""``maglev-ros irregularity BAG --out OUT.csv [--json OUT.json] [--plot OUT.png]``.

Guideway irregularity by the inertial reference method from a pass recording: magnet
accelerations + gaps + vehicle position (see maglev_ros.irregularity.profile). The CSV has
columns ``position_m,irregularity_m`` with the band, filter corner (and how it was chosen), kind
and warnings in ``#`` header lines; the JSON holds the same plus the spectrum summary (Welch PSD
with confidence band, comparison with the FRA / German reference spectra, EN 13848 D1/D2 RMS).
With no options the corner and the band follow the recording (pass length and speed; see
maglev_ros.irregularity.profile) and both lines state what was achieved.
"""
from __future__ import annotations

import io
import math
import sys
from pathlib import Path

import numpy as np

from maglev_ros import outputs
from maglev_ros.errors import ContractError, UserError

NAME = "irregularity"
HELP = "guideway irregularity profile from magnet accelerations and gaps (inertial reference)"
ORDER = 50


def add_arguments(p) -> None:
    p.add_argument("bag", help="recording (rosbag2 directory or file)")
    p.add_argument("--out", required=True, help="output CSV (position_m,irregularity_m)")
    p.add_argument("--json", dest="json_out", default=None, help="also write a JSON summary")
    p.add_argument("--plot", default=None, help="also write a PNG: profile and PSD vs references")
    p.add_argument("--highpass-hz", type=float, default=None,
                   help="corner of the time-domain high-pass [Hz] (default: from the recording, "
                        "the lowest at which filter settling, 2.2/f_c s, takes at most half of the "
                        "longest clean moving stretch, i.e. 4.4/T; not below 0.2 Hz)")
    p.add_argument("--spacing-m", type=float, default=0.25,
                   help="profile grid spacing [m] (default 0.25; the shortest wavelength is 4x it)")
    p.add_argument("--magnets", default=None,
                   help="comma-separated 1-based magnet numbers to use (default: all)")
    p.add_argument("--magnet-length-m", type=float, default=0.0,
                   help="shortest trusted wavelength from a sensor that averages over a length [m] "
                        "(default 0: point gap sensors and accelerometers)")
    p.add_argument("--band-speed-mps", type=float, default=None,
                   help="speed that sets the longest wavelength (default: 5th percentile of speed)")
    p.add_argument("--max-wavelength-m", type=float, default=None,
                   help="fix the longest wavelength instead [m]; slower stretches are dropped")
    p.add_argument("--confidence", type=float, default=0.90, help="PSD confidence level")
    p.add_argument("--reference-pass", default=None, metavar="BAG",
                   help="another pass over the same line at a different speed: the delay of the vehicle "
                        "sensors behind the position is measured between the two passes' rails and applied "
                        "when significant and the metadata states none (both bags are read whole for it)")


def _check_units(cd, topic, want, channels):
    for ch in channels:
        u = cd.units[cd.channels.index(ch)] if getattr(cd, "units", None) else want
        if u != want:
            raise ContractError(f"{topic}: channel {ch} has unit {u!r}, expected {want!r}")


def read_inputs(path: str):
    """Read the three vehicle topics and the metadata; returns a dict for InertialProfiler.fit."""
    return read_inputs_checked(path)[0]


def read_inputs_checked(path: str):
    """(read_inputs' dict, the sensor-health report of what was read)."""
    from maglev_ros.bag_reader import BagReader
    from maglev_ros.contract import (TOPIC_VEHICLE_ACCEL, TOPIC_VEHICLE_GAP,
                                     TOPIC_VEHICLE_POSITION)
    if not Path(path).exists():
        raise UserError(f"{path}: no such bag")
    with BagReader(path) as r:
        md = r.metadata
        _need_topics(path, r)
        topics = (TOPIC_VEHICLE_ACCEL, TOPIC_VEHICLE_GAP, TOPIC_VEHICLE_POSITION)
        read, health = r.read_checked(topics, sensor_map=True)
        # samples placed at the time they describe (optional acquisition delay in the metadata)
        accel, gap, pos = (read[t].delayed_by(md.acquisition_delay_s(t)) for t in topics)
    return {"accel": accel, "gap": gap, "position": pos,
            **_check_inputs(path, md, accel, gap, pos)}, health


def open_inputs(r, path: str, window_s: float | None = None, sensor_delay_s: float = 0.0):
    """(the inputs of :func:`read_inputs` for the open bag ``r``, with the accelerations and gaps
    left in the bag: ``source`` reads them window by window
    (:func:`maglev_ros.irregularity.streamed.profile_streamed`); the sensor-health report).
    ``sensor_delay_s``: a measured delay of the accelerations and gaps added to the stated ones."""
    from maglev_ros.bag_windows import read_checked_windows
    from maglev_ros.contract import (TOPIC_VEHICLE_ACCEL, TOPIC_VEHICLE_GAP,
                                     TOPIC_VEHICLE_POSITION)
    from maglev_ros.irregularity.streamed import VehicleTopics
    md = r.metadata
    _need_topics(path, r)
    read, health = read_checked_windows(r, [TOPIC_VEHICLE_ACCEL, TOPIC_VEHICLE_GAP],
                                        [TOPIC_VEHICLE_POSITION], sensor_map=True)
    accel, gap = read[TOPIC_VEHICLE_ACCEL], read[TOPIC_VEHICLE_GAP]
    pos = read[TOPIC_VEHICLE_POSITION].delayed_by(md.acquisition_delay_s(TOPIC_VEHICLE_POSITION))
    src = VehicleTopics(r, accel, gap, md.acquisition_delay_s(TOPIC_VEHICLE_ACCEL) + sensor_delay_s,
                        md.acquisition_delay_s(TOPIC_VEHICLE_GAP) + sensor_delay_s, pos, window_s)
    return {"source": src, **_check_inputs(path, md, accel, gap, pos)}, health


def _need_topics(path, r) -> None:
    from maglev_ros.contract import (TOPIC_VEHICLE_ACCEL, TOPIC_VEHICLE_GAP,
                                     TOPIC_VEHICLE_POSITION)
    md = r.metadata
    for topic in (TOPIC_VEHICLE_ACCEL, TOPIC_VEHICLE_GAP, TOPIC_VEHICLE_POSITION):
        if topic not in r.topics:
            kind = md.run_kind
            raise ContractError(f"{path}: topic {topic} missing (the irregularity needs "
                                "vehicle accel, gap and position"
                                + (f"; run.kind is {kind!r}: no vehicle pass)"
                                   if kind and kind != "pass" else ")"))


def _check_inputs(path, md, accel, gap, pos) -> dict:
    """Magnet offsets, nominal gap and channel pairs of the recording, after checking units and
    channels (``accel``, ``gap``: anything with ``channels`` and ``units``)."""
    from maglev_ros.contract import TOPIC_VEHICLE_ACCEL, TOPIC_VEHICLE_GAP, TOPIC_VEHICLE_POSITION
    from maglev_ros.irregularity.profile import magnet_channel_pairs
    offsets = md.magnet_offsets_m
    if not offsets:
        raise ContractError(f"{path}: metadata key vehicle.magnet_offsets_m missing or empty")
    g0 = md.nominal_gap_m if md.nominal_gap_m is not None else 0.010
    pairs = magnet_channel_pairs(md, accel.channels, gap.channels)
    used_a = [a for a, _ in pairs.values()] if pairs else list(accel.channels[:len(offsets)])
    used_g = [g for _, g in pairs.values()] if pairs else list(gap.channels[:len(offsets)])
    _check_units(accel, TOPIC_VEHICLE_ACCEL, "m/s^2", used_a)
    _check_units(gap, TOPIC_VEHICLE_GAP, "m", used_g)
    for ch in ("position_m", "speed_mps"):
        if ch not in pos.channels:
            raise ContractError(f"{path}: {TOPIC_VEHICLE_POSITION}: channel {ch} missing")
    return {"magnet_offsets_m": offsets, "nominal_gap_m": g0, "channel_pairs": pairs}


def analyse(inputs: dict, args):
    from maglev_ros.irregularity.profile import InertialProfiler
    from maglev_ros.irregularity.spectra import band_rms, compare_reference, profile_psd
    mags = None
    if args.magnets:
        try:
            mags = [int(m) for m in str(args.magnets).split(",") if m.strip()]
        except ValueError:
            raise UserError(f"--magnets: expected comma-separated integers, got {args.magnets!r}")
    prof = InertialProfiler(highpass_hz=args.highpass_hz, spacing_m=args.spacing_m, magnets=mags,
                            magnet_length_m=args.magnet_length_m,
                            band_speed_mps=args.band_speed_mps,
                            max_wavelength_m=args.max_wavelength_m)
    if "source" in inputs:       # a recording read window by window
        from maglev_ros.irregularity.streamed import profile_streamed
        res = profile_streamed(inputs["source"], prof, inputs["magnet_offsets_m"],
                               inputs["nominal_gap_m"], inputs["channel_pairs"])
    else:
        res = prof.fit(**inputs)
    spec, comp, notes = None, [], []
    try:
        spec = profile_psd(res.position_m, res.irregularity_m, confidence=args.confidence,
                           min_wavelength_m=res.min_wavelength_m,
                           max_wavelength_m=res.max_wavelength_m)
        comp = compare_reference(spec)
    except UserError as exc:
        notes.append(f"no spectrum: {exc}")
    rms = band_rms(res.position_m, res.irregularity_m, res.min_wavelength_m,
                   res.max_wavelength_m, spectrum=spec)
    return res, spec, comp, rms, notes


def _corner_text(res) -> str:
    c = res.corner
    return c.describe() if c is not None else f"{res.highpass_hz:.3g} Hz"


def header_lines(res, rms, bag) -> list[str]:
    lines = [f"# maglev-ros irregularity of {bag}",
             f"# kind: {res.kind} (loaded: includes girder deflection under the vehicle)",
             f"# valid band: {res.min_wavelength_m:.4g} m <= wavelength <= "
             f"{res.max_wavelength_m:.4g} m (half-amplitude corners of a zero-phase Butterworth "
             f"order {res.filter_order} band-pass)",
             f"# time high-pass corner: {_corner_text(res)}; band speed "
             f"{res.band_speed_mps:.4g} m/s; grid spacing {res.spacing_m:g} m",
             "# magnets: " + ", ".join(f"{n} at {o:+.4g} m" for n, o in
                                       zip(res.magnet_names, res.magnet_offsets_m))]
    for a, b, c in res.agreement:
        lines.append(f"# agreement {a}-{b}: correlation {c:.4f}")
    for d in rms:
        if d["available"]:
            lines.append(f"# EN 13848 {d['band']} ({d['min_wavelength_m']:g}-"
                         f"{d['max_wavelength_m']:g} m): rms {d['rms_m']:.4g} m")
        else:
            lines.append(f"# EN 13848 {d['band']}: unavailable ({d['reason']})")
    for w in res.warnings:
        lines.append(f"# warning {w.kind} [{w.channel}]: {w.message}")
    lines.append("# empty irregularity_m: no valid estimate at that position")
    return lines


def csv_text(res, rms, bag) -> str:
    """The CSV: ``#`` header lines, then ``position_m,irregularity_m`` (empty where invalid)."""
    fh = io.StringIO()
    for line in header_lines(res, rms, bag):
        fh.write(line.replace("\n", " ") + "\n")
    fh.write("position_m,irregularity_m\n")
    for x, y in zip(res.position_m, res.irregularity_m):
        fh.write(f"{x:.4f},{'' if not math.isfinite(y) else f'{y:.6e}'}\n")
    return fh.getvalue()


def write_csv(path: str, res, rms, bag, batch=None) -> None:
    """Write the CSV atomically, or stage it in ``batch`` (:class:`maglev_ros.outputs.Batch`)."""
    with outputs.batch_or_new(batch) as b:
        b.write_text(path, csv_text(res, rms, bag), option="--out")


def summary_dict(res, spec, comp, rms, notes, bag) -> dict:
    d = {"bag": str(bag), "profile": res.to_dict(include_profile=True),
         "spectrum": None if spec is None else spec.to_dict(include_arrays=True),
         "reference_comparison": comp, "band_rms": rms, "notes": notes}
    return d


def write_plot(path: str, res, spec, comp, batch=None) -> None:
    """Write the PNG atomically, or stage it in ``batch`` (:class:`maglev_ros.outputs.Batch`)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from maglev_ros.twin.irregularity_psd import psd_by_name
    fig, (a1, a2) = plt.subplots(2, 1, figsize=(9, 7))
    a1.plot(res.position_m, res.irregularity_m * 1e3, lw=0.8, label="mean of magnets")
    a1.set_xlabel("position [m]")
    a1.set_ylabel("irregularity [mm]")
    a1.set_title(f"{res.kind} profile, band {res.min_wavelength_m:.3g}-"
                 f"{res.max_wavelength_m:.3g} m, f_c {res.highpass_hz:.3g} Hz")
    a1.grid(True, alpha=0.3)
    if spec is not None:
        f = spec.freq_cycles_per_m
        m = f > 0
        a2.loglog(f[m], spec.psd_m2_per_cycle_per_m[m], "k", lw=1, label="measured (Welch)")
        a2.fill_between(f[m], spec.lower_m2_per_cycle_per_m[m], spec.upper_m2_per_cycle_per_m[m],
                        color="0.7", alpha=0.5, label=f"{spec.confidence:.0%} confidence")
        for name in ("fra4", "fra6", "german_low", "german_high"):
            a2.loglog(f[m], psd_by_name(name).per_cycle(f[m]), lw=0.8, ls="--", label=name)
        a2.axvspan(1.0 / res.max_wavelength_m, 1.0 / res.min_wavelength_m, color="g", alpha=0.07,
                   label="valid band")
        a2.legend(fontsize=7)
    a2.set_xlabel("spatial frequency [cycles/m]")
    a2.set_ylabel("PSD [m^2/(cycle/m)]")
    a2.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    try:
        with outputs.batch_or_new(batch) as b:
            b.write_figure(path, fig, "--plot", dpi=110)
    finally:
        plt.close(fig)


def measure_delay(bag: str, reference: str):
    """The delay of the vehicle sensors behind the position measured between two passes over one
    line (:mod:`maglev_ros.irregularity.sensor_delay`); None when either bag's metadata states one."""
    from maglev_ros.bag_reader import BagReader
    from maglev_ros.irregularity.sensor_delay import measure_sensor_delay, stated_sensor_delay_s
    read = []
    for path, opt in ((bag, "BAG"), (reference, "--reference-pass")):
        if not Path(path).exists():
            raise UserError(f"{opt} {path}: no such bag")
        with BagReader(path) as r:
            if stated_sensor_delay_s(r.metadata) is not None:
                return None
        read.append((path, read_inputs(path)))
    return measure_sensor_delay([(i["accel"], i["gap"], i["position"], i["magnet_offsets_m"], i["channel_pairs"],
                                  i["nominal_gap_m"], Path(p).name) for p, i in read])


def run(args) -> int:
    from maglev_ros.bag_reader import BagReader
    # the outputs can be written: checked before the analysis, not after
    outputs.check_file(args.out, "--out")
    if args.json_out is not None:
        outputs.check_file(args.json_out, "--json")
    if args.plot is not None:
        outputs.check_figure(args.plot, "--plot")
    if not Path(args.bag).exists():
        raise UserError(f"{args.bag}: no such bag")
    delay = measure_delay(args.bag, args.reference_pass) if args.reference_pass else None
    tau = float(delay.delay_s) if delay is not None and delay.applicable else 0.0
    # accelerations and gaps stay in the bag, read window by window: memory stays bounded
    with BagReader(args.bag) as r:
        inputs, health = open_inputs(r, args.bag, sensor_delay_s=tau)
        for line in health.lines():
            print(f"maglev-ros irregularity: {line}", file=sys.stderr)
        res, spec, comp, rms, notes = analyse(inputs, args)
    if args.reference_pass:
        notes.append("sensor delay: " + ("stated in the metadata, not measured" if delay is None else
                                         delay.reason + (" (applied)" if tau else " (not applied)")))
    # CSV, JSON and plot replace the earlier set together, or none of them does
    with outputs.Batch() as batch:
        write_csv(args.out, res, rms, args.bag, batch)
        if args.json_out:
            batch.write_json(args.json_out, summary_dict(res, spec, comp, rms, notes, args.bag)
                             | {"health": health.to_dict()}
                             | ({"sensor_delay": delay.to_dict()} if delay else {}),
                             indent=1, option="--json")
        if args.plot:
            write_plot(args.plot, res, spec, comp, batch)
    v = res.valid
    rms_all = float(np.sqrt(np.mean(res.irregularity_m[v] ** 2))) if v.any() else float("nan")
    print(f"irregularity: valid band {res.min_wavelength_m:.3g}-{res.max_wavelength_m:.3g} m at "
          f"band speed {res.band_speed_mps:.3g} m/s; time high-pass {_corner_text(res)}")
    if args.reference_pass:
        print(f"irregularity: {notes[-1]}")
    print(f"irregularity: {int(v.sum())} of {v.size} points valid, rms {rms_all * 1e3:.3g} mm, "
          f"{len(res.warnings)} warning(s); wrote {args.out}")
    return 0
