"""The profile ``maglev-ros irregularity`` gives of a recording, from its blocks as a stream delivered
them (the irregularity node at a recording's end; no rclpy).

The verb reads whole topics from the bag, moves the samples to the time they describe (the
metadata's acquisition delays) and fits :class:`~.profile.InertialProfiler` with its defaults:
the high-pass corner and the band speed follow the whole pass. Here the same topics are built from
the blocks (:meth:`maglev_ros.bag_reader.ChannelData.from_blocks`, the bag reader's sample times)
and fitted the same way, so the profile is the verb's on the same recording (the verb reads long
recordings window by window, within 1e-5 of the peak of the whole-recording fit).
"""
from __future__ import annotations

from typing import Mapping, Sequence

from maglev_ros.contract import TOPIC_VEHICLE_ACCEL, TOPIC_VEHICLE_GAP, TOPIC_VEHICLE_POSITION, Metadata

from .profile import InertialProfiler, IrregularityResult, magnet_channel_pairs

TOPICS = {TOPIC_VEHICLE_ACCEL: "accel", TOPIC_VEHICLE_GAP: "gap", TOPIC_VEHICLE_POSITION: "position"}


def recording_profile(metadata: Metadata, blocks: Mapping[str, Sequence], highpass_hz: float | None = None,
                      spacing_m: float = 0.25, band_speed_mps: float | None = None) -> IrregularityResult:
    """The verb's profile of the recording whose blocks (SI) per topic are ``blocks``; UserError
    when a topic has no samples."""
    from maglev_ros.bag_reader import ChannelData
    md = metadata
    data = {k: ChannelData.from_blocks(t, blocks.get(t, ())).delayed_by(md.acquisition_delay_s(t))
            for t, k in TOPICS.items()}
    prof = InertialProfiler(highpass_hz=highpass_hz, spacing_m=spacing_m, band_speed_mps=band_speed_mps)
    return prof.fit(**data, magnet_offsets_m=md.magnet_offsets_m,
                    nominal_gap_m=md.nominal_gap_m if md.nominal_gap_m is not None else 0.010,
                    channel_pairs=magnet_channel_pairs(md, data["accel"].channels, data["gap"].channels))
