"""Online twin: drive the coupled twin with a recording's measured position/speed and predict
what every measured channel should read; residual = measured - predicted (no rclpy).

``OnlineTwin(metadata)`` builds the twin from the metadata's ``design`` block and ``line``
(``design.twin_config_from_metadata``) and feeds it blocks in stream order:

- ``/testline/vehicle/position`` blocks drive a ``coupling.TwinStepper``: on the first one the
  stepper starts in static equilibrium one output step before the first position sample; each
  block advances it to the block's end (last sample + one position period) with the speed ramping
  linearly to the block's last speed. If the integrated position drifts more than ``resync_m``
  from the measured one, the twin's position is reset to the measured position (a jump; the
  vehicle state is kept).
- measured blocks (/testline/guideway/accel, /displacement, /vehicle/accel, /gap) are queued until
  the twin has advanced past their last sample; then the predicted block has the same stamp,
  rate, channels (those the twin can predict) and units, with the twin's output interpolated
  linearly onto the block's sample times (exact when the grids coincide), and the residual block
  is measured - predicted on the same samples.
- an ambient record (``run.kind: ambient``, or no position stream at all) parks the vehicle far
  off the line at rest and advances the twin with the measured blocks: predictions are the
  twin's (zero) response without a vehicle, so the residual is the measured ambient vibration.

Predictable channels: guideway sensors of ``direction: vertical`` (or none) with a ``position_m``
on the line (vertical FE beams; lateral channels are skipped), magnet channels with ``magnet``.

Time step: the twin outputs at ``fs_hz`` (default: the fastest measured rate) with internal steps
of at most ``dt_max_s`` (default 0.25 ms: the Newmark period error of a 200 Hz girder mode is then
~1 %; at the 1 ms design default it is ~13 % and residuals near the span ends grow to ~10 %).

Irregularity: until ``set_irregularity`` / ``set_irregularity_profile`` is called the twin uses
one random sample of a reference PSD (``psd``, ``band_m``, ``seed``), periodic over ~3.3 km.
A profile holds between its first and last sample and its end values beyond them.

Parameters: ``set_parameters(names, values)`` adopts dotted design-block paths, e.g.
``guideway.youngs_modulus_pa``, ``levitation.kp_a_per_m``, ``vehicle.primary.stiffness_n_per_m``,
``vehicle.frames.0.mass_kg`` (an optional ``design.`` prefix is accepted), or per-span guideway
keys ``spans.<id>.<key>`` (e.g. ``spans.S3.bearing_stiffness_n_per_m``). The twin is rebuilt at
its current time, position and speed in static equilibrium (the modal state of a changed guideway
cannot be carried over), so a short transient follows an update.
"""
from __future__ import annotations

import copy
import math
from collections import deque
from dataclasses import dataclass
from typing import Any, Iterable, Mapping, Sequence

import numpy as np

from maglev_ros.contract import (TOPIC_GUIDEWAY_ACCEL, TOPIC_GUIDEWAY_DISP, TOPIC_VEHICLE_ACCEL,
                                 TOPIC_VEHICLE_GAP, TOPIC_VEHICLE_POSITION, Metadata,
                                 metadata_from_dict, unit_conversion)
from maglev_ros.errors import UserError
from maglev_ros.sensor_block import Block
from maglev_ros.twin.coupling import Irregularity, TwinStepper
from maglev_ros.twin.design import twin_config

__all__ = ["GROUP_TOPICS", "TOPIC_GROUPS", "PREDICTED_PREFIX", "RESIDUAL_PREFIX", "TwinOutput",
           "OnlineTwin", "periodic_random_irregularity", "nrmse"]

GROUP_TOPICS = {"guideway_accel": TOPIC_GUIDEWAY_ACCEL, "guideway_displacement": TOPIC_GUIDEWAY_DISP,
                "vehicle_accel": TOPIC_VEHICLE_ACCEL, "vehicle_gap": TOPIC_VEHICLE_GAP}
TOPIC_GROUPS = {t: g for g, t in GROUP_TOPICS.items()}
PREDICTED_PREFIX = "/maglev/twin/predicted/"
RESIDUAL_PREFIX = "/maglev/twin/residual/"
_DESIGN_SECTIONS = ("guideway", "vehicle", "levitation")


@dataclass(frozen=True)
class TwinOutput:
    """Prediction and residual for one measured block."""
    group: str
    measured: Block
    predicted: Block
    residual: Block

    @property
    def predicted_topic(self) -> str:
        return PREDICTED_PREFIX + self.group

    @property
    def residual_topic(self) -> str:
        return RESIDUAL_PREFIX + self.group


def nrmse(residual: np.ndarray, measured: np.ndarray) -> np.ndarray:
    """Per column: RMS(residual) / standard deviation of the measured signal."""
    r = np.asarray(residual, float)
    m = np.asarray(measured, float)
    return np.sqrt(np.mean(r ** 2, axis=0)) / np.maximum(np.std(m, axis=0), 1e-300)


def periodic_random_irregularity(psd_name: str = "maglev_001", band_m: Sequence[float] = (1.0, 20.0),
                                 seed: int = 0, start_m: float = 0.0, spacing_m: float = 0.05,
                                 n_log2: int = 16) -> Irregularity:
    """One random profile of a reference PSD, periodic with period 2**n_log2 * spacing_m."""
    from maglev_ros.twin.irregularity_psd import psd_by_name, random_profile
    n = 1 << int(n_log2)
    x, r = random_profile(psd_by_name(psd_name), (n - 1) * spacing_m + 0.5 * spacing_m, spacing_m,
                          (float(band_m[0]), float(band_m[1])), rng=np.random.default_rng(seed), start_m=start_m)
    x, r = x[:n], r[:n]
    period = n * spacing_m
    xs = np.append(x, x[0] + period)
    rs = np.append(r, r[0])
    ss = np.gradient(rs, xs)

    def wrap(q):
        return start_m + np.mod(np.asarray(q, float) - start_m, period)
    return Irregularity(lambda q: np.interp(wrap(q), xs, rs), lambda q: np.interp(wrap(q), xs, ss))


def _set_path(doc: dict, parts: list[str], value: float, name: str) -> None:
    node: Any = doc
    for i, p in enumerate(parts[:-1]):
        nxt = parts[i + 1]
        if isinstance(node, list):
            if not p.isdigit() or int(p) >= len(node):
                raise UserError(f"twin parameter {name!r}: {p!r} is not an index of a list of {len(node)}")
            node = node[int(p)]
            continue
        if node.get(p) is None:
            node[p] = [] if nxt.isdigit() else {}
        node = node[p]
    last = parts[-1]
    if isinstance(node, list):
        if not last.isdigit() or int(last) >= len(node):
            raise UserError(f"twin parameter {name!r}: {last!r} is not an index of a list of {len(node)}")
        node[int(last)] = value
    elif isinstance(node, dict):
        node[last] = value
    else:
        raise UserError(f"twin parameter {name!r}: {'.'.join(parts[:-1])} is not a mapping")


class OnlineTwin:
    """See module docstring. ``on_block(topic, block)`` returns the finished ``TwinOutput``s."""

    def __init__(self, metadata: Metadata | Mapping, *, irregularity: Any = None, psd: str = "maglev_001",
                 band_m: Sequence[float] = (1.0, 20.0), seed: int = 0, method: str = "newmark",
                 fs_hz: float | None = None, dt_max_s: float | None = 2.5e-4, resync_m: float = 0.05,
                 max_pending_s: float = 30.0, parameters: Mapping[str, float] | None = None):
        md = metadata if isinstance(metadata, Metadata) else metadata_from_dict(dict(metadata), "twin metadata")
        self.metadata = md
        self.kind = md.run_kind
        self.method = method
        self.fs_hz = None if not fs_hz else float(fs_hz)
        self.dt_max_s = None if not dt_max_s else float(dt_max_s)
        self.resync_m = float(resync_m)
        self.max_pending_s = float(max_pending_s)
        self.design: dict = copy.deepcopy(md.design or {})
        self.spans: list[dict] = [dict(s) for s in md.raw["line"]["spans"]]
        self.parameters: dict[str, float] = {}
        self._psd = (psd, tuple(float(b) for b in band_m), int(seed))
        self._irr = irregularity
        self._default_irr = None
        self.stepper: TwinStepper | None = None
        self.t0_ns: int | None = None
        self.revision = 0
        self.n_resync = 0
        self.n_dropped = 0
        # predictable channels
        self.guideway_x: dict[str, float] = {}
        self.magnet_of: dict[str, int] = {}
        spans = md.spans
        lo = min(s.start_m for s in spans)
        hi = max(s.end_m for s in spans)
        for sid, s in md.sensors.items():
            if s.topic in (TOPIC_GUIDEWAY_ACCEL, TOPIC_GUIDEWAY_DISP):
                if s.position_m is not None and s.direction in (None, "vertical") and lo <= s.position_m <= hi:
                    self.guideway_x[sid] = float(s.position_m)
            elif s.topic in (TOPIC_VEHICLE_ACCEL, TOPIC_VEHICLE_GAP) and s.magnet is not None:
                if self.kind == "pass" and s.magnet <= len(md.magnet_offsets_m):
                    self.magnet_of[sid] = int(s.magnet)
        self._sensor_names = tuple(self.guideway_x)
        self.config = self._build_config()
        if parameters:
            self.set_parameters(list(parameters), list(parameters.values()))
        # buffers
        self._pending: deque[tuple[str, Block]] = deque()
        self._buf_t: list[np.ndarray] = []
        self._buf: dict[str, list[np.ndarray]] = {"gd": [], "ga": [], "ma": [], "mg": []}
        self._seen_position = False

    # ---------------------------------------------------------------------------- config
    def _build_config(self, design: dict | None = None):
        d = self.design if design is None else design
        veh = self.metadata.vehicle
        return twin_config(d or None, magnet_offsets_m=veh.get("magnet_offsets_m"),
                           nominal_gap_m=veh.get("nominal_gap_m"))

    def _line(self, spans: list[dict] | None = None) -> dict:
        return {"spans": self.spans if spans is None else spans}

    def set_parameters(self, names: Sequence[str], values: Sequence[float]) -> dict[str, float]:
        """Adopt parameter values (dotted design paths, see module docstring); rebuilds the twin."""
        if len(names) != len(values):
            raise UserError(f"twin parameters: {len(names)} names but {len(values)} values")
        design = copy.deepcopy(self.design)
        spans = [dict(s) for s in self.spans]
        ids = [str(s["id"]) for s in spans]
        adopted = {}
        for name, value in zip(names, values):
            v = float(value)
            if not math.isfinite(v):
                raise UserError(f"twin parameter {name!r}: expected a finite value, got {value!r}")
            parts = [p for p in str(name).split(".") if p]
            if parts and parts[0] == "design":
                parts = parts[1:]
            if len(parts) >= 2 and parts[0] in _DESIGN_SECTIONS:
                _set_path(design, parts, v, name)
            elif len(parts) == 3 and parts[0] == "spans":
                if parts[1] not in ids:
                    raise UserError(f"twin parameter {name!r}: no span {parts[1]!r} (spans: {', '.join(ids)})")
                spans[ids.index(parts[1])][parts[2]] = v
            else:
                raise UserError(f"twin parameter {name!r}: expected guideway.<key>, vehicle.<path>, "
                                f"levitation.<key> or spans.<id>.<key>")
            adopted[str(name)] = v
        config = self._build_config(design)          # validates (ContractError names design.<path>)
        from maglev_ros.twin.design import line_spans
        line_spans(self._line(spans), config)        # validates per-span keys
        self.design, self.spans, self.config = design, spans, config
        self.parameters.update(adopted)
        self.revision += 1
        if self.stepper is not None:
            self._rebuild()
        return adopted

    # ---------------------------------------------------------------------------- irregularity
    def _irregularity(self):
        if self._irr is not None:
            return self._irr
        if self._default_irr is None:
            name, band, seed = self._psd
            start = min(s.start_m for s in self.metadata.spans) - 1000.0
            self._default_irr = periodic_random_irregularity(name, band, seed, start_m=start)
        return self._default_irr

    def set_irregularity(self, irregularity: Any) -> None:
        """Use this irregularity (anything ``coupling.as_irregularity`` takes) from now on."""
        from maglev_ros.twin.coupling import as_irregularity
        self._irr = as_irregularity(irregularity)
        if self.stepper is not None:
            self.stepper.set_irregularity(self._irr)

    def set_irregularity_profile(self, start_position_m: float, spacing_m: float, values: Sequence[float]) -> None:
        """From an IrregularityProfile message: samples every ``spacing_m`` from ``start_position_m``."""
        r = np.asarray(values, dtype=float)
        ok = np.isfinite(r)
        if ok.sum() < 2 or not spacing_m > 0:
            raise UserError(f"irregularity profile: expected >= 2 finite samples and spacing_m > 0, "
                            f"got {int(ok.sum())} finite of {r.size} samples, spacing {spacing_m!r}")
        x = float(start_position_m) + float(spacing_m) * np.arange(r.size)
        # Positions without a valid estimate (edges, dropouts) carry no information: the twin
        # takes zero there (the expected irregularity), joined linearly to the estimated stretches.
        idx = np.flatnonzero(ok)
        r = np.where(ok, r, 0.0)
        inner = (~ok) & (np.arange(r.size) > idx[0]) & (np.arange(r.size) < idx[-1])
        r[inner] = np.interp(x[inner], x[ok], r[ok])
        self.set_irregularity((x, r))

    # ---------------------------------------------------------------------------- stepping
    def _new_stepper(self, t0_s: float, position_m: float, speed_mps: float) -> TwinStepper:
        fs = self.fs_hz or 1000.0
        return TwinStepper(self.config, self._line(), sensors=dict(self.guideway_x) or None,
                           irregularity=self._irregularity(), fs_out_hz=fs, start_position_m=position_m,
                           start_speed_mps=speed_mps, t0_s=t0_s, method=self.method, init="static",
                           dt_max_s=self.dt_max_s)

    def _rebuild(self) -> None:
        st = self.stepper
        self.stepper = self._new_stepper(st.time_s, st.position_m, st.speed_mps)

    def _start(self, stamp_ns: int, position_m: float, speed_mps: float) -> None:
        if self.fs_hz is None:
            rates = [b.sample_rate_hz for _t, b in self._pending]
            self.fs_hz = max(rates) if rates else 1000.0
        dt_ns = int(round(1e9 / self.fs_hz))
        self.t0_ns = int(stamp_ns) - dt_ns
        self.stepper = self._new_stepper(0.0, position_m - speed_mps * dt_ns * 1e-9, speed_mps)

    def _rel(self, stamp_ns: int) -> float:
        return (int(stamp_ns) - self.t0_ns) * 1e-9

    def _record(self, res) -> None:
        if res.n_samples == 0:
            return
        self._buf_t.append(res.time_s)
        self._buf["gd"].append(res.guideway_disp_m)
        self._buf["ga"].append(res.guideway_accel_mps2)
        self._buf["ma"].append(res.magnet_accel_mps2)
        self._buf["mg"].append(res.magnet_gap_m)

    def _advance(self, t_end_s: float, speed_mps: float | None) -> None:
        self._record(self.stepper.advance(t_end_s, speed_mps))

    def on_position(self, block: Block) -> list[TwinOutput]:
        try:
            pos = block.channel("position_m").astype(float)
            vel = block.channel("speed_mps").astype(float)
        except UserError as exc:
            raise UserError(f"{TOPIC_VEHICLE_POSITION}: {exc}") from None
        if block.n_samples == 0:
            return []
        self._seen_position = True
        if self.stepper is None:
            self._start(block.stamp_ns, float(pos[0]), float(vel[0]))
        dt = 1.0 / block.sample_rate_hz
        t_last = self._rel(block.stamp_ns) + (block.n_samples - 1) * dt
        self._advance(t_last + dt, float(vel[-1]))
        expect = float(pos[-1]) + float(vel[-1]) * dt
        if abs(self.stepper.position_m - expect) > self.resync_m:
            self.stepper.position_m = expect
            self.n_resync += 1
        return self._flush()

    def on_block(self, topic: str, block: Block) -> list[TwinOutput]:
        """Feed one block of any recording topic; returns the outputs finished by it."""
        if topic == TOPIC_VEHICLE_POSITION:
            return self.on_position(block)
        if topic not in TOPIC_GROUPS or block.n_samples == 0:
            return []
        self._pending.append((topic, block))
        if self.stepper is None and (self.kind == "ambient"):
            self._start(block.stamp_ns, min(s.start_m for s in self.metadata.spans) - 1.0e4, 0.0)
        if self.stepper is not None and (self.kind == "ambient" or not self._seen_position):
            if self.kind == "ambient":
                end = self._rel(block.stamp_ns) + block.n_samples / block.sample_rate_hz
                if end > self.stepper.time_s:
                    self._advance(end, 0.0)
        self._drop_stale()
        return self._flush()

    def _drop_stale(self) -> None:
        if not self._pending:
            return
        newest = max(b.stamp_ns for _t, b in self._pending)
        while self._pending and (newest - self._pending[0][1].stamp_ns) * 1e-9 > self.max_pending_s:
            self._pending.popleft()
            self.n_dropped += 1

    # ---------------------------------------------------------------------------- predictions
    def _concat(self):
        if len(self._buf_t) > 1:
            self._buf_t = [np.concatenate(self._buf_t)]
            for k in self._buf:
                self._buf[k] = [np.concatenate(self._buf[k], axis=0)]
        if not self._buf_t:
            return None
        return self._buf_t[0], {k: v[0] for k, v in self._buf.items()}

    def _flush(self) -> list[TwinOutput]:
        if self.stepper is None or not self._pending:
            return []
        cat = self._concat()
        if cat is None:
            return []
        t, buf = cat
        t_cov = t[-1] + 1e-9
        out, keep = [], deque()
        while self._pending:
            topic, blk = self._pending.popleft()
            tb = self._rel(blk.stamp_ns) + np.arange(blk.n_samples) / blk.sample_rate_hz
            if tb[-1] > t_cov:
                keep.append((topic, blk))
                continue
            o = self._predict(topic, blk, tb, t, buf)
            if o is not None:
                out.append(o)
        self._pending = keep
        # trim history older than the oldest pending block (keep 1 s margin)
        t_keep = min([self._rel(b.stamp_ns) for _t, b in self._pending] + [t[-1]]) - 1.0
        i = int(np.searchsorted(t, t_keep))
        if i > 0:
            self._buf_t = [t[i:]]
            for k in self._buf:
                self._buf[k] = [buf[k][i:]]
        return out

    def _predict(self, topic: str, blk: Block, tb: np.ndarray, t: np.ndarray, buf: dict) -> TwinOutput | None:
        group = TOPIC_GROUPS[topic]
        cols, src = [], []
        for j, ch in enumerate(blk.channels):
            if topic in (TOPIC_GUIDEWAY_ACCEL, TOPIC_GUIDEWAY_DISP):
                if ch in self.guideway_x:
                    cols.append(j)
                    src.append(("ga" if topic == TOPIC_GUIDEWAY_ACCEL else "gd", self._sensor_names.index(ch)))
            elif ch in self.magnet_of:
                cols.append(j)
                src.append(("ma" if topic == TOPIC_VEHICLE_ACCEL else "mg", self.magnet_of[ch] - 1))
        if not cols:
            return None
        pred = np.empty((blk.n_samples, len(cols)))
        for c, (key, idx) in enumerate(src):
            pred[:, c] = np.interp(tb, t, buf[key][:, idx])
        units = tuple(blk.units[j] for j in cols)
        for c, u in enumerate(units):
            conv = unit_conversion(u)
            if conv is not None and conv[1] != 1.0:
                pred[:, c] /= conv[1]
        meas = blk.data[:, cols].astype(float)
        chans = tuple(blk.channels[j] for j in cols)
        p_blk = Block.from_arrays(blk.stamp_ns, blk.sample_rate_hz, chans, units, pred, "twin")
        r_blk = Block.from_arrays(blk.stamp_ns, blk.sample_rate_hz, chans, units, meas - pred, "twin")
        return TwinOutput(group, blk, p_blk, r_blk)

    def feed(self, items: Iterable[tuple[str, Block]]) -> list[TwinOutput]:
        """Convenience: feed (topic, block) pairs in stream order; returns all outputs."""
        out = []
        for topic, blk in items:
            out += self.on_block(topic, blk)
        return out
