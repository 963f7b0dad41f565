"""Where along the line and in which band the twin misses: residual RMS per (position bin, band).

Each twin group's residual stream is cut into consecutive ``frame_s`` frames (0.5 s, as the
discrepancy detector's); in each frame every channel's band powers are those of
:func:`maglev_ros.discrepancy.features.band_powers` (Hann frame, triangular bands of
``BAND_EDGES_HZ``, bands above 0.7 x Nyquist left out). The frame is placed on the line at the
position of the load that channel feels at the frame's centre time: a magnet channel at the
vehicle position plus its magnet offset, a car-body channel plus its ``body_x_m``, a guideway
channel at the vehicle position (where the load is while that sensor misfits, as the discrepancy
localizer reports it) or, with no vehicle on the line (ambient recording, no position yet), at the
sensor's own ``position_m``. A cell's value is sqrt(mean band power) over every (channel, frame)
that fell into it: the residual RMS of that band there, in the group's unit. Frames whose place is
unknown or off the line are counted, not mapped. A new recording (new metadata) starts a new map.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from maglev_ros.discrepancy.features import BAND_EDGES_HZ, FRAME_S, FrameGrid, band_powers, usable_bands

POSITION_BIN_M = 1.0
POSITION_KEEP_S = 600.0       # vehicle position history kept for placing frames (the twin lags < 10 s)


@dataclass
class _Stream:
    """A group's residual samples not yet cut into frames (contiguous)."""
    channels: tuple[str, ...]
    rate_hz: float
    t0_ns: int
    data: np.ndarray            # (n, n_ch)
    unit: str


class ResidualMap:
    """Residual RMS per (band, position bin) of every twin group; see the module docstring."""

    def __init__(self, position_bin_m: float = POSITION_BIN_M, frame_s: float = FRAME_S,
                 edges_hz=BAND_EDGES_HZ) -> None:
        if not position_bin_m > 0 or not frame_s > 0:
            raise ValueError("position_bin_m and frame_s must be > 0")
        self.bin_m = float(position_bin_m)
        self.frame_s = float(frame_s)
        self.edges_hz = np.asarray(edges_hz, float)
        self.n_bands = self.edges_hz.size - 1
        self.set_metadata(None)

    # ------------------------------------------------------------------ inputs
    def set_metadata(self, metadata: dict | None) -> None:
        """A new recording: the line, the sensors' places, an empty map."""
        self.metadata = metadata
        spans = ((metadata or {}).get("line") or {}).get("spans") or []
        if spans:
            self.x0_m = min(float(s["start_m"]) for s in spans)
            x1 = max(float(s["start_m"]) + float(s["length_m"]) for s in spans)
        else:
            self.x0_m, x1 = 0.0, self.bin_m
        self.n_bins = max(1, int(math.ceil((x1 - self.x0_m) / self.bin_m - 1e-9)))
        sensors = (metadata or {}).get("sensors") or {}
        offsets = ((metadata or {}).get("vehicle") or {}).get("magnet_offsets_m") or []
        self.is_pass = ((metadata or {}).get("run") or {}).get("kind") == "pass"
        self.on_vehicle: dict[str, float] = {}     # channel -> x offset from the vehicle reference
        self.fixed_at: dict[str, float] = {}       # channel -> own position (guideway sensors)
        for ch, s in sensors.items():
            if not isinstance(s, dict):
                continue
            mag = s.get("magnet")
            if isinstance(mag, int) and 1 <= mag <= len(offsets):
                self.on_vehicle[ch] = float(offsets[mag - 1])
            elif s.get("body_x_m") is not None:
                self.on_vehicle[ch] = float(s["body_x_m"])
            elif s.get("position_m") is not None:
                self.fixed_at[ch] = float(s["position_m"])
        self.pos_t = np.zeros(0)
        self.pos_x = np.zeros(0)
        self.streams: dict[str, _Stream] = {}
        self.power: dict[str, np.ndarray] = {}     # group -> (n_bands, n_bins) summed band power
        self.count: dict[str, np.ndarray] = {}     # group -> (n_bands, n_bins) (channel, frame) cells
        self.units: dict[str, str] = {}
        self.frames: dict[str, int] = {}
        self.unplaced: dict[str, int] = {}
        self.t_last_s: dict[str, float] = {}

    def add_position(self, t_s, x_m) -> None:
        """Vehicle reference positions (times in stream seconds, increasing; a jump back by more
        than a second starts the history again: a looped replay)."""
        t = np.asarray(t_s, float)
        x = np.asarray(x_m, float)
        ok = np.isfinite(t) & np.isfinite(x)
        if self.pos_t.size and t.size and t[0] < self.pos_t[-1] - 1.0:
            self.pos_t, self.pos_x = np.zeros(0), np.zeros(0)     # time went back: the stream restarted
        if self.pos_t.size:
            ok &= t > self.pos_t[-1]
        self.pos_t = np.r_[self.pos_t, t[ok]]
        self.pos_x = np.r_[self.pos_x, x[ok]]
        if self.pos_t.size and self.pos_t[-1] - self.pos_t[0] > 2 * POSITION_KEEP_S:
            keep = self.pos_t >= self.pos_t[-1] - POSITION_KEEP_S
            self.pos_t, self.pos_x = self.pos_t[keep], self.pos_x[keep]

    def add_block(self, group: str, block) -> int:
        """A residual block of ``group``; returns the number of frames completed by it."""
        if block.n_samples == 0:
            return 0
        s = self.streams.get(group)
        contiguous = (s is not None and s.channels == tuple(block.channels)
                      and s.rate_hz == block.sample_rate_hz
                      and abs(block.stamp_ns - (s.t0_ns + round(len(s.data) * 1e9 / s.rate_hz)))
                      <= 0.5e9 / s.rate_hz)
        data = np.asarray(block.data, float)
        if contiguous:
            s.data = np.concatenate([s.data, data])
        else:                                         # first block, a gap or a new layout: start over
            s = self.streams[group] = _Stream(tuple(block.channels), float(block.sample_rate_hz),
                                              int(block.stamp_ns), data,
                                              block.units[0] if block.units else "")
        n = int(round(self.frame_s * s.rate_hz))
        done = 0
        while len(s.data) >= n >= 4:
            self._add_frame(group, s, s.data[:n])
            s.data = s.data[n:]
            s.t0_ns += int(round(n * 1e9 / s.rate_hz))
            done += 1
        return done

    # ---------------------------------------------------------------- internals
    def vehicle_x(self, t_s: float) -> float | None:
        """The vehicle reference position at ``t_s`` (None outside the positions received)."""
        if self.pos_t.size < 2 or not (self.pos_t[0] <= t_s <= self.pos_t[-1]):
            return None
        return float(np.interp(t_s, self.pos_t, self.pos_x))

    def place(self, channel: str, t_s: float) -> float | None:
        """Where on the line a residual of ``channel`` at ``t_s`` is mapped (module docstring)."""
        x = self.vehicle_x(t_s)
        if channel in self.on_vehicle:
            return None if x is None else x + self.on_vehicle[channel]
        if x is not None and self.is_pass:
            return x
        return self.fixed_at.get(channel)

    def _add_frame(self, group: str, s: _Stream, frame: np.ndarray) -> None:
        n = frame.shape[0]
        t = s.t0_ns * 1e-9 + np.arange(n) / s.rate_hz
        tc = float(t[0] + self.frame_s / 2)
        grid = FrameGrid(np.array([tc]), self.frame_s, self.edges_hz)
        usable = usable_bands(grid, s.rate_hz)
        if group not in self.power:
            self.power[group] = np.zeros((self.n_bands, self.n_bins))
            self.count[group] = np.zeros((self.n_bands, self.n_bins), dtype=np.int64)
            self.frames[group] = self.unplaced[group] = 0
        self.units[group] = s.unit
        self.t_last_s[group] = float(t[-1])
        for j, ch in enumerate(s.channels):
            x = self.place(ch, tc)
            col = None if x is None else int(math.floor((x - self.x0_m) / self.bin_m))
            if col is None or not 0 <= col < self.n_bins:
                self.unplaced[group] += 1
                continue
            p = band_powers(t, frame[:, j], s.rate_hz, grid)[0]
            ok = usable & np.isfinite(p)
            self.power[group][ok, col] += p[ok]
            self.count[group][ok, col] += 1
            self.frames[group] += int(ok.any())

    # ------------------------------------------------------------------ outputs
    def rms(self, group: str) -> np.ndarray:
        """(n_bands, n_bins) residual RMS (NaN: no frame there)."""
        if group not in self.power:
            return np.full((self.n_bands, self.n_bins), np.nan)
        c = self.count[group]
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(c > 0, np.sqrt(self.power[group] / np.maximum(c, 1)), np.nan)

    def position_centres_m(self) -> np.ndarray:
        return self.x0_m + (np.arange(self.n_bins) + 0.5) * self.bin_m

    def message(self, group: str) -> dict:
        """JSON message: per band its edges and the RMS per position bin (null: no data), the
        position bins' centres, the unit and how many (channel, frame) cells were mapped / not."""
        r = self.rms(group)
        e = self.edges_hz
        bands = [{"f0_hz": float(e[b]), "f1_hz": float(e[b + 1]),
                  "rms": [float(v) if np.isfinite(v) else None for v in r[b]]} for b in range(self.n_bands)]
        return {"t_s": self.t_last_s.get(group, 0.0), "group": group, "unit": self.units.get(group, ""),
                "position_bin_m": self.bin_m, "position_m": [float(x) for x in self.position_centres_m()],
                "bands": bands, "mapped": int(self.frames.get(group, 0)),
                "unplaced": int(self.unplaced.get(group, 0))}


def map_schema() -> dict:
    band = {"type": "object", "properties": {"f0_hz": {"type": "number"}, "f1_hz": {"type": "number"},
                                             "rms": {"type": "array", "items": {"type": "number"}}}}
    return {"title": "maglev.view.ResidualMap", "type": "object",
            "properties": {"t_s": {"type": "number"}, "group": {"type": "string"}, "unit": {"type": "string"},
                           "position_bin_m": {"type": "number"},
                           "position_m": {"type": "array", "items": {"type": "number"}},
                           "bands": {"type": "array", "items": band},
                           "mapped": {"type": "integer"}, "unplaced": {"type": "integer"}}}


GRID_BAND_HEIGHT_M = 0.25     # one band's row in the 3D grid


def grid_cells(rms: np.ndarray) -> tuple[int, int, list[tuple[str, int]], bytes]:
    """The map as a foxglove.Grid's packed cells: (column_count, cell_stride, [(field, offset)],
    data). Row = band (lowest first), column = position bin; two float32 fields per cell, ``rms``
    and ``log10_rms`` (the bands differ by decades: the colour map reads the log); NaN where empty."""
    r = np.asarray(rms, float)
    with np.errstate(divide="ignore", invalid="ignore"):
        lg = np.where(r > 0, np.log10(r), np.nan)
    cells = np.stack([r, lg], axis=-1).astype("<f4")          # (rows, cols, 2)
    return int(r.shape[1]), 8, [("rms", 0), ("log10_rms", 4)], cells.tobytes()
