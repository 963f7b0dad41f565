"""The diagnosis on a live stream: recordings assembled from blocks, diagnosed by the same stages.

:class:`RecordingAssembler` collects SensorBlocks of the contract's sensor and position topics
under the current metadata and, when the recording ends (new metadata, or the stream stops), makes
the :class:`.recording.Recording` that :func:`.recording.load_recording` makes of the same bag (same
sample times, same arrays). :class:`LiveDiagnoser` keeps the line's ambient recording and the last
passes and runs :func:`.diagnose.diagnose` on them after each completed pass, so the live graph's
diagnosis is the offline ``maglev-ros diagnose`` of the same recordings, not a second algorithm.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Mapping

import numpy as np

from maglev_ros.contract import TOPIC_VEHICLE_POSITION, to_si_units
from maglev_ros.sensor_block import Block

from .diagnose import DiagnoseConfig, Diagnosis, diagnose
from .recording import TOPIC_GROUP, Recording, recording_from_arrays


@dataclass
class _TopicBlocks:
    blocks: list = field(default_factory=list)

    def add(self, block: Block) -> None:
        self.blocks.append(block)

    def arrays(self, topic: str) -> tuple[tuple[str, ...], np.ndarray, np.ndarray]:
        """Channels, sample times [s] and samples (float64, SI), blocks in stamp order, an exact
        repeat of a block dropped (a reliable stream re-sent after a reconnect). Units are converted
        as the bag readers do (the contract's table, in float64); an unknown unit raises ContractError."""
        bs = sorted(self.blocks, key=lambda b: b.stamp_ns)
        keep = [b for i, b in enumerate(bs) if i == 0 or b.stamp_ns != bs[i - 1].stamp_ns]
        chans = keep[0].channels
        keep = [b for b in keep if b.channels == chans and b.n_samples]
        # the bag reader's sample times: stamp + j / rate, in float64
        t = np.concatenate([b.stamp_ns * 1e-9 + np.arange(b.n_samples) / b.sample_rate_hz for b in keep])
        x = np.concatenate([np.asarray(b.data, np.float64) for b in keep])
        _, factors, conv = to_si_units(topic, chans, keep[0].units, "live stream ")
        return chans, t, (x * np.asarray(factors) if conv else x)


class RecordingAssembler:
    """Blocks and metadata in, :class:`Recording` out when the recording is complete."""

    def __init__(self, source: str = "<live>"):
        self.source = source
        self.metadata: Mapping | None = None
        self._topics: dict[str, _TopicBlocks] = {}
        self.n_recordings = 0

    @property
    def has_data(self) -> bool:
        return any(tb.blocks for tb in self._topics.values())

    def set_metadata(self, metadata: Mapping) -> Recording | None:
        """A new recording's metadata; returns the previous recording if it holds data."""
        done = self.finish() if self.metadata is not None and dict(metadata) != dict(self.metadata) else None
        self.metadata = dict(metadata)
        return done

    def add_block(self, topic: str, block: Block) -> None:
        if topic in TOPIC_GROUP or topic == TOPIC_VEHICLE_POSITION:
            self._topics.setdefault(topic, _TopicBlocks()).add(block)

    def finish(self, metadata: Mapping | None = None) -> Recording | None:
        """The recording so far (None without metadata or data), under ``metadata`` if given (a live
        stream names its recording's metadata only once it has ended); the assembler starts a new one.
        ContractError when it cannot be a recording (a unit outside the contract's table, a channel
        the metadata does not place)."""
        topics, self._topics = self._topics, {}
        if metadata is not None:
            self.metadata = dict(metadata)
        if self.metadata is None or not any(tb.blocks for tb in topics.values()):
            return None
        signals, position = {}, None
        # topics by name, as the bag reader lists them: the channels' order (and every sum over
        # them) is then load_recording's whichever topic's block came first
        for topic, tb in sorted(topics.items()):
            chans, t, x = tb.arrays(topic)
            if topic == TOPIC_VEHICLE_POSITION:
                if "position_m" in chans:
                    pos = x[:, chans.index("position_m")]
                    spd = x[:, chans.index("speed_mps")] if "speed_mps" in chans else np.gradient(pos, t)
                    position = (t, pos, spd)
                continue
            for i, ch in enumerate(chans):
                signals[ch] = (t, x[:, i])
        self.n_recordings += 1
        return recording_from_arrays(self.metadata, signals, position,
                                     source=f"{self.source}#{self.n_recordings}")


class LiveDiagnoser:
    """Diagnoses each completed pass with the ambient recording and up to ``max_passes`` passes
    (the newest; the fastest of them trains, the others are held out, as offline)."""

    def __init__(self, config: DiagnoseConfig = DiagnoseConfig(), max_passes: int = 2,
                 ambient: Recording | None = None):
        self.config = config
        self.max_passes = int(max_passes)
        self.ambient = ambient
        self.passes: list[Recording] = []

    def add_recording(self, rec: Recording) -> Diagnosis | None:
        """An ambient recording is kept for the next diagnoses (None returned); a pass is diagnosed."""
        if rec.kind == "ambient":
            self.ambient = rec
            return None
        if rec.kind != "pass" or rec.position_time_s is None:
            return None
        self.passes = [*self.passes, rec][-self.max_passes:]
        return diagnose(self.passes, self.ambient, self.config)


def diagnosis_events(rep: Mapping) -> list[dict]:
    """The report's findings as mismatch events (one per missing-physics entry, then the located
    mismatches no entry covers): channels, time and position span, band, severity, effect,
    category, explanation, and the entry itself as detail."""
    out = []
    for m in rep.get("missing_physics", []):
        loc = m.get("location") or {}
        ev = m.get("evidence") if isinstance(m.get("evidence"), Mapping) else {}
        before, after = ev.get("heldout_nrmse_before"), ev.get("heldout_nrmse_after")
        out.append({"channels": list(loc.get("channels") or []), "time_s": [np.nan, np.nan],
                    "position_m": _pair(loc.get("position_m")), "frequency_hz": _pair(m.get("frequency_hz")),
                    # how much larger the held-out misfit is without the physics
                    "severity": float(before / after) if before and after else np.nan,
                    "effect": m.get("effect", ""), "category": m.get("category", ""),
                    "explanation": m.get("explanation", ""), "detail": m})
    found = [e.get("effect") or e.get("category") for e in rep.get("missing_physics", [])]
    for m in rep.get("mismatches", []):
        out.append({"channels": list(m.get("channels") or []), "time_s": list(m.get("time_s") or [np.nan, np.nan]),
                    "position_m": _pair(m.get("position_m")), "frequency_hz": _pair(m.get("frequency_hz")),
                    "severity": float(m.get("severity", np.nan)), "effect": "", "category": "",
                    "explanation": mismatch_explanation(m, found), "detail": m})
    return out


def mismatch_explanation(m: Mapping, found: list[str]) -> str:
    """One line on a located mismatch of the calibrated twin: whether the twin with the found
    physics still shows it (most of its cells no longer flagged: explained)."""
    after = m.get("after_found_physics")
    sev = m.get("severity")
    if not after:
        return "located mismatch of the calibrated twin (the diagnosis names its physics above, if any)"
    what = ", ".join(found) if found else "nothing found"
    if after["flagged_share"] < 0.5:
        return (f"located mismatch of the calibrated twin, explained by the found physics ({what}): "
                f"severity {sev:.3g} -> {after['severity']:.3g}, {100 * after['flagged_share']:.0f} % of its cells left")
    return (f"located mismatch that the found physics ({what}) does not explain: severity {sev:.3g} -> "
            f"{after['severity']:.3g}, {100 * after['flagged_share']:.0f} % of its cells left")


def _pair(v) -> list:
    if v is None:
        return [np.nan, np.nan]
    v = [float(x) for x in (v if isinstance(v, (list, tuple)) else [v])]
    return v if len(v) == 2 else [v[0], v[-1]]
