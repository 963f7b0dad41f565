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
  the position topic (docs/contract-extensions.md).
- Vehicle channels are compared only while the whole vehicle is over the valid stretch (past the
  tapers + ``margin_m``); outside it the twin input is zero and the comparison would be meaningless.
"""
from __future__ import annotations

from dataclasses import replace
from types import SimpleNamespace

import numpy as np

from maglev_ros.errors import UserError

from .recording import Recording

TOPIC_ACCEL = "/testline/vehicle/accel"
TOPIC_GAP = "/testline/vehicle/gap"
TOPIC_POS = "/testline/vehicle/position"


def _cd(rec: Recording, group: str):
    names = [n for n, c in rec.channels.items() if c.group == group]
    if not names:
        return None
    t = rec.channels[names[0]].time_s
    data = np.column_stack([np.interp(t, rec.channels[n].time_s, rec.channels[n].values) for n in names])
    return SimpleNamespace(time_s=t, data=data, channels=tuple(names),
                           sample_rate_hz=rec.channels[names[0]].sample_rate_hz)


def sensor_delay_s(metadata) -> float:
    """Delay of the vehicle sensor samples relative to the position samples [s] (>= 0)."""
    d = metadata.acquisition_delay_s(TOPIC_ACCEL) - metadata.acquisition_delay_s(TOPIC_POS)
    return max(0.0, float(d))


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
    from maglev_ros.contract import metadata_from_dict
    from maglev_ros.irregularity.profile import magnet_channel_pairs
    from maglev_ros.irregularity.twin_input import profile_for_twin
    say = log or (lambda s: None)
    if rec.kind != "pass" or rec.position_time_s is None:
        return rec
    acc, gap = _cd(rec, "vehicle_accel"), _cd(rec, "gap")
    if acc is None or gap is None:
        say(f"{rec.source}: no magnet accelerations and gaps: the twin runs on a perfect guideway")
        return rec
    md = metadata_from_dict(dict(rec.metadata), rec.source)
    pairs = magnet_channel_pairs(md, acc.channels, gap.channels)
    if not pairs:
        say(f"{rec.source}: no magnet with both accel and gap channels: the twin runs on a perfect guideway")
        return rec
    pos = SimpleNamespace(time_s=rec.position_time_s, data=np.column_stack([rec.position_m, rec.speed_mps]),
                          channels=("position_m", "speed_mps"), sample_rate_hz=None)
    tau = sensor_delay_s(md)
    try:
        ti = profile_for_twin(acc, gap, pos, md, spec.effective_config(), spec.effective_spans(),
                              highpass_hz=highpass_hz, spacing_m=spacing_m, channel_pairs=pairs,
                              sensor_delay_s=tau, max_iterations=max_iterations, dt_max_s=spec.dt_max_s,
                              **profile_kw)
    except (UserError, ValueError, np.linalg.LinAlgError) as exc:
        say(f"{rec.source}: irregularity reconstruction failed ({exc}): the twin runs on a perfect guideway")
        return rec
    info = ti.to_dict()
    info["channel_pairs"] = {int(k): list(v) for k, v in pairs.items()}
    x, r = ti.as_twin_input()
    if denoise:
        x, r, g = ti.denoised_twin_input()
        if g is None:
            say(f"{rec.source}: one magnet (or too short a common stretch): the irregularity is not denoised")
        else:
            info["denoise"] = g.to_dict()
    return replace(rec, irregularity=(x, r), irregularity_valid_m=ti.valid_range_m,
                   irregularity_margin_m=float(ti.taper_m + margin_m), sensor_delay_s=tau,
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
