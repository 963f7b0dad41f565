"""Guideway irregularity for the diagnosing twin, reconstructed from each pass itself.

A real (or realistically simulated) pass is dominated in the vehicle channels by the rail
irregularity: a twin driven along a perfect guideway cannot fit it and every diagnosis on such a
recording fails (measured on the sample bag: band-amplitude NRMSE 0.99 on the magnet channels).
:func:`with_twin_irregularity` therefore reconstructs the unloaded irregularity of the pass with
:func:`maglev_ros.irregularity.twin_input.profile_for_twin` (inertial reference on the magnet
accelerations and gaps, loaded -> unloaded iteration with the given twin's girder deflection) and
attaches it to the :class:`~.recording.Recording`; :func:`.model.simulate` drives the twin with it.

Choices (documented because the method depends on them):
- The profile is rebuilt ONCE per pass with the calibrated twin (not per hypothesis): it is a
  property of the rail, and its dependence on the twin parameters is weak (corr 0.999 between
  nominal and true parameters, docs/irregularity.md). Extensions are therefore judged against the
  same input the calibrated twin had.
- Magnet <-> channel pairs come from the metadata (``magnet_channel_pairs``), never from channel
  order; the sensor delay is the stated acquisition delay of the vehicle accel topic minus that of
  the position topic (docs/contract-extensions.md), else the one the passes measure
  (:func:`measure_sensor_delay`: their rails shift against each other by speed difference x delay).
- Vehicle channels are compared only while the whole vehicle is over the valid stretch (past the
  tapers + ``margin_m``); outside it the twin input is zero and the comparison would be meaningless.
"""
from __future__ import annotations

from dataclasses import replace
from types import SimpleNamespace
from typing import Sequence

import numpy as np

from maglev_ros.errors import UserError

from .recording import Recording


def _cd(rec: Recording, group: str):
    names = [n for n, c in rec.channels.items() if c.group == group]
    if not names:
        return None
    t = rec.channels[names[0]].time_s
    data = np.column_stack([np.interp(t, rec.channels[n].time_s, rec.channels[n].values) for n in names])
    return SimpleNamespace(time_s=t, data=data, channels=tuple(names),
                           sample_rate_hz=rec.channels[names[0]].sample_rate_hz)


def pass_sensor_delay_s(rec: Recording) -> float:
    """The delay the twin runs behind a pass's stamps: the stated one, else the one measured between
    passes (``rec.sensor_delay_s``, set by :func:`measure_sensor_delay`'s caller)."""
    from maglev_ros.contract import metadata_from_dict
    from maglev_ros.irregularity.sensor_delay import stated_sensor_delay_s
    stated = stated_sensor_delay_s(metadata_from_dict(dict(rec.metadata), rec.source))
    return stated if stated is not None else max(0.0, float(rec.sensor_delay_s))


def measure_sensor_delay(recs: Sequence[Recording], highpass_hz: float | None = 0.8):
    """Delay of the vehicle sensors behind the position, from the passes' rails
    (:mod:`maglev_ros.irregularity.sensor_delay`); a ``SensorDelayEstimate``."""
    from maglev_ros.contract import metadata_from_dict
    from maglev_ros.irregularity import sensor_delay
    passes = []
    for r in recs:
        d = _vehicle_data(r)
        if d is not None and d[1]:
            acc, pairs, pos = d
            passes.append((acc, _cd(r, "gap"), pos, metadata_from_dict(dict(r.metadata), r.source), pairs, None,
                           r.name))
    return sensor_delay.measure_sensor_delay(passes, highpass_hz or 0.8)


def with_twin_irregularity(rec: Recording, spec, *, highpass_hz: float | None = 0.8, spacing_m: float | None = None,
                           margin_m: float = 1.0, max_iterations: int = 3, denoise: bool = True,
                           log=None, **profile_kw) -> Recording:
    """``rec`` with the irregularity reconstructed for the twin of ``spec`` (a :class:`.model.ModelSpec`:
    its calibrated config and spans). Unchanged (with a logged reason) when the pass has no magnet
    with both an acceleration and a gap channel, or the reconstruction fails. ``denoise``: the Wiener
    gain of the rail and error spectra measured on the pass (:mod:`maglev_ros.irregularity.denoise`;
    needs two or more magnets). ``spacing_m`` None: the grid follows the data (one sample step at the
    top speed, at most 2 cm; :func:`~maglev_ros.irregularity.twin_input.twin_spacing_m`).
    Further keywords (``band_factor``, ``trim_wavelengths``, ``edge_s``, ...) go to
    :func:`~maglev_ros.irregularity.twin_input.profile_for_twin` and its profiler."""
    say = log or (lambda s: None)
    got = _reconstruct(rec, spec, say, highpass_hz=highpass_hz, spacing_m=spacing_m,
                       max_iterations=max_iterations, **profile_kw)
    if got is None:
        return rec
    ti, info = got
    x, r = ti.as_twin_input()
    if denoise:
        x, r, g = ti.denoised_twin_input()
        _note_gain(rec, g, info, say)
    return _attach(rec, ti, (x, r), info, margin_m)


def with_twin_irregularities(recs: Sequence[Recording], spec, *, share: bool = True,
                             highpass_hz: float | None = 0.8, margin_m: float = 1.0, max_iterations: int = 3,
                             log=None, **profile_kw) -> list[Recording]:
    """:func:`with_twin_irregularity` for several passes over one line, on one grid (the finest any
    pass resolves), their short waves shared when they measured one rail at one position (``share``;
    :func:`~maglev_ros.irregularity.twin_input.shared_twin_inputs`: twice the magnets, half the noise;
    what was done is stated in each pass's ``irregularity_info["shared"]``)."""
    from maglev_ros.irregularity.twin_input import shared_twin_inputs, twin_spacing_m
    say = log or (lambda s: None)
    spacing = profile_kw.pop("spacing_m", None)
    if spacing is None:
        steps = []
        for r in recs:
            d = _vehicle_data(r)
            if d is not None and d[1]:
                dt_s = spec.dt_max_s or spec.effective_config().numerics.dt_max_s
                steps.append(twin_spacing_m(d[0], d[2], len(d[1]), dt_s))
        spacing = min(steps) if steps else None
    got = [_reconstruct(r, spec, say, highpass_hz=highpass_hz, spacing_m=spacing, max_iterations=max_iterations,
                        **profile_kw) for r in recs]
    done = [(i, g) for i, g in enumerate(got) if g is not None]
    out = list(recs)
    if share and len(done) >= 2:
        inputs, shared = shared_twin_inputs([ti for _, (ti, _) in done])
    else:
        inputs, shared = None, None
    for n, (i, (ti, info)) in enumerate(done):
        if shared is not None and shared.used:
            xr, g = inputs[n], shared.gain
        else:
            *xr, g = ti.denoised_twin_input()
        _note_gain(recs[i], g, info, say)
        if shared is not None:
            info["shared"] = shared.to_dict()
            if not shared.used:
                say(f"{recs[i].source}: short waves not shared with the other passes ({shared.reason})")
        out[i] = _attach(recs[i], ti, tuple(xr), info, margin_m)
    return out


def _vehicle_data(rec: Recording):
    """(accel, channel pairs, position) of a pass, ChannelData-like; None without them."""
    from maglev_ros.contract import metadata_from_dict
    from maglev_ros.irregularity.profile import magnet_channel_pairs
    if rec.kind != "pass" or rec.position_time_s is None:
        return None
    acc, gap = _cd(rec, "vehicle_accel"), _cd(rec, "gap")
    if acc is None or gap is None:
        return None
    md = metadata_from_dict(dict(rec.metadata), rec.source)
    pairs = magnet_channel_pairs(md, acc.channels, gap.channels)
    pos = SimpleNamespace(time_s=rec.position_time_s, data=np.column_stack([rec.position_m, rec.speed_mps]),
                          channels=("position_m", "speed_mps"), sample_rate_hz=None)
    return acc, pairs, pos


def _reconstruct(rec: Recording, spec, say, *, highpass_hz, spacing_m, max_iterations, **profile_kw):
    """(TwinIrregularity, info) of one pass, or None (reason logged)."""
    from maglev_ros.contract import metadata_from_dict
    from maglev_ros.irregularity.twin_input import profile_for_twin

    from .model import stepper_customizer
    data = _vehicle_data(rec)
    if data is None:
        if rec.kind == "pass" and rec.position_time_s is not None:
            say(f"{rec.source}: no magnet accelerations and gaps: the twin runs on a perfect guideway")
        return None
    acc, pairs, pos = data
    if not pairs:
        say(f"{rec.source}: no magnet with both accel and gap channels: the twin runs on a perfect guideway")
        return None
    gap = _cd(rec, "gap")
    md = metadata_from_dict(dict(rec.metadata), rec.source)
    tau = pass_sensor_delay_s(rec)
    try:
        ti = profile_for_twin(acc, gap, pos, md, spec.effective_config(), spec.effective_spans(),
                              highpass_hz=highpass_hz, spacing_m=spacing_m, channel_pairs=pairs,
                              sensor_delay_s=tau, max_iterations=max_iterations, dt_max_s=spec.dt_max_s,
                              customize_stepper=stepper_customizer(spec), **profile_kw)
    except (UserError, ValueError, np.linalg.LinAlgError) as exc:
        say(f"{rec.source}: irregularity reconstruction failed ({exc}): the twin runs on a perfect guideway")
        return None
    info = ti.to_dict()
    info["channel_pairs"] = {int(k): list(v) for k, v in pairs.items()}
    return ti, info


def _note_gain(rec: Recording, g, info: dict, say) -> None:
    if g is None:
        say(f"{rec.source}: one magnet (or too short a common stretch): no noise spectrum measured, the rail "
            "keeps the band of the 2 cm grid")
    else:
        info["denoise"] = g.to_dict()
        info["rail_gain"] = g           # its spectra: the rail's remaining uncertainty (.floor)


def _attach(rec: Recording, ti, xr, info: dict, margin_m: float) -> Recording:
    return replace(rec, irregularity=xr, irregularity_valid_m=ti.valid_range_m,
                   irregularity_margin_m=float(ti.taper_m + margin_m), sensor_delay_s=ti.sensor_delay_s,
                   irregularity_info=info)


def vehicle_over_valid(rec: Recording, t_s: np.ndarray, magnet_offsets_m) -> np.ndarray:
    """True where every magnet is over the valid irregularity (past tapers + margin)."""
    if rec.irregularity_valid_m is None or rec.position_time_s is None:
        return np.ones(np.shape(t_s), bool)
    lo, hi = rec.irregularity_valid_m
    mg = rec.irregularity_margin_m
    x = np.interp(np.asarray(t_s, float) - rec.sensor_delay_s, rec.position_time_s, rec.position_m)
    offs = np.asarray(magnet_offsets_m, float)
    return (x + offs.min() >= lo + mg) & (x + offs.max() <= hi - mg)
