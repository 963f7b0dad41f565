"""Online twin: drive the coupled twin with a recording's measured position/speed and predict
what every measured channel should read; residual = measured - predicted (no rclpy).

``OnlineTwin(metadata)`` builds the twin from the metadata's ``design`` block and ``line``
(``design.twin_config_from_metadata``) and feeds it blocks in stream order:

- ``/testline/vehicle/position`` blocks drive a ``coupling.TwinStepper``: on the first one the
  stepper starts in static equilibrium one output step before the first position sample; each
  block advances it to the block's end (last sample + one position period) with the speed ramping
  linearly to the block's last speed, unless that would leave the trajectory the stream gives
  (``trajectory.TrajectoryTracker``: a quadratic fit to the last second of positions) by more
  than the fit's uncertainty: then the speed ramps to the fit's, corrected to land on it (the
  integrated speed channel random-walks away from the positions). Further off than ``resync_m``,
  the twin's position is reset (a jump of the position system; the vehicle state is kept).
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

Irregularity (``irregularity_source``; the vehicle channels are only judged against a measured one):

- ``"vehicle"`` (default): the twin measures the irregularity itself from the recording's vehicle
  streams it already receives: an :class:`~maglev_ros.irregularity.profile.IncrementalProfiler`
  (inertial reference method) fed /testline/vehicle/{accel,gap,position}, configured for a
  point-magnet twin like :mod:`maglev_ros.irregularity.twin_input` (``magnet_length_m`` 0,
  ``spacing_m`` 0.02 m, ``highpass_hz`` 0.8 Hz, band speed 80 % of the metadata's nominal speed,
  the last magnet span + 20 longest wavelengths of profile kept (:func:`profile_length_m`);
  override with ``profiler_options``). Why not the irregularity node's /maglev/irregularity: that
  is a geometry product (3 m magnet length, 0.25 m grid) whose band leaves out the short waves
  (stator-pack joints, < 3 m) that dominate the magnet accelerations, so a twin driven by it
  cannot reproduce them. The profile is "loaded" (it contains the girder deflection under the
  magnets, which the twin adds again); within the 0.8 Hz band at test-line speeds that deflection
  (span-length waves) is mostly outside the band, so the error is small (choice: no loaded ->
  unloaded iteration online).
- ``"topic"``: the profile comes from ``set_irregularity_profile`` calls (the irregularity node's
  message), with the same coverage rules.
- ``"random"``: one random sample of a reference PSD (``psd``, ``band_m``, ``seed``), periodic over
  ~3.3 km -- an invented profile: vehicle residuals are never valid.
- an explicit ``irregularity=`` (the known truth in a test, a surveyed profile): used everywhere,
  vehicle residuals always valid.

Coverage and lag: with a measured source, positions without a valid profile sample take zero
irregularity (joined by a half-cosine taper of ``taper_m`` inside each valid stretch). The leading
magnet measures the rail before the trailing ones arrive, but the profiler can only finish a stretch
after its filter edges (~1-2 s at 0.8 Hz): the twin therefore steps the vehicle only up to the time
at which the profile reaches ``ahead_m`` beyond the leading magnet, lagging the stream by at most
``max_lag_s`` (beyond that it steps on with zero irregularity ahead). The profile is refreshed at most every
``profile_period_s`` of stream time (a refresh re-processes the profiler's uncommitted tail). Guideway outputs come from
the same stepper, so they lag by the same amount; they are always marked valid (the girder
deflection is dominated by the moving load). Guideway ACCELERATIONS do carry the dynamic magnet
forces that the irregularity excites: with a reconstructed profile (even the offline unloaded one
of ``twin_input``) their NRMSE with the true parameters is 0.2-0.5 on the paper pass (displacement
0.02), so judge guideway parameters by displacements and modes rather than by raw accelerations. A vehicle output sample is VALID
when every magnet of the vehicle has been over the measured stretch (inside its tapers) for at
least ``settle_s`` (the control transient after entering from zero irregularity, and the static
start). Invalid vehicle samples get NaN residuals and the output's ``valid`` flag is False (the
node does not publish such residual blocks; predictions are published).
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

from maglev_ros.contract import (TOPIC_BODY_ACCEL, TOPIC_GUIDEWAY_ACCEL, TOPIC_GUIDEWAY_DISP, TOPIC_VEHICLE_ACCEL,
                                 TOPIC_VEHICLE_GAP, TOPIC_VEHICLE_POSITION, Metadata,
                                 metadata_from_dict, unit_conversion)
from maglev_ros.errors import UserError
from maglev_ros.sensor_block import Block
from maglev_ros.twin.coupling import Irregularity, TwinStepper
from maglev_ros.twin.design import twin_config
from maglev_ros.twin.trajectory import TrajectoryTracker, ramp_speed

__all__ = ["GROUP_TOPICS", "TOPIC_GROUPS", "PREDICTED_PREFIX", "RESIDUAL_PREFIX", "TwinOutput",
           "OnlineTwin", "periodic_random_irregularity", "nrmse", "IRREGULARITY_SOURCES"]

GROUP_TOPICS = {"guideway_accel": TOPIC_GUIDEWAY_ACCEL, "guideway_displacement": TOPIC_GUIDEWAY_DISP,
                "vehicle_accel": TOPIC_VEHICLE_ACCEL, "vehicle_gap": TOPIC_VEHICLE_GAP,
                "body_accel": TOPIC_BODY_ACCEL}
TOPIC_GROUPS = {t: g for g, t in GROUP_TOPICS.items()}
PREDICTED_PREFIX = "/maglev/twin/predicted/"
RESIDUAL_PREFIX = "/maglev/twin/residual/"
_DESIGN_SECTIONS = ("guideway", "vehicle", "levitation")
IRREGULARITY_SOURCES = ("vehicle", "topic", "random")
_PROFILER_KEYS = {TOPIC_VEHICLE_ACCEL: "accel", TOPIC_VEHICLE_GAP: "gap"}


def _as_irr(obj):
    from maglev_ros.twin.coupling import as_irregularity
    return as_irregularity(obj)


# the measured profile the twin keeps: from its rearmost magnet back this many of the band's longest
# wavelengths (the band filter's start-up transient at the kept profile's old end has died out well
# before the magnets: predictions equal those with a 2 km profile to 1e-7), so a refresh costs the
# same at the start of a run as after kilometres
PROFILE_CONTEXT_WAVELENGTHS = 20.0


def profile_length_m(profiler, magnet_offsets_m) -> float:
    """Length of measured profile the twin needs: the vehicle's magnet span plus
    :data:`PROFILE_CONTEXT_WAVELENGTHS` of the profiler's longest wavelength."""
    span = float(np.ptp(magnet_offsets_m)) if np.size(magnet_offsets_m) else 0.0
    return span + PROFILE_CONTEXT_WAVELENGTHS * profiler.longest_wavelength_m()


@dataclass(frozen=True)
class TwinOutput:
    """Prediction and residual for one measured block."""
    group: str
    measured: Block
    predicted: Block
    residual: Block
    valid: bool = True              # False: some residual samples are NaN (vehicle not covered)

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


class _History:
    """Twin output rows (times and named column blocks) appended per step, dropped from the front:
    amortised growth in place (concatenating the whole history per measured block was a tenth of
    the twin's time)."""

    def __init__(self, keys: Sequence[str]):
        self.keys = tuple(keys)
        self._t = np.empty(0)
        self._cols: dict[str, np.ndarray] = {}
        self._lo = self._hi = 0

    @property
    def n_rows(self) -> int:
        return self._hi - self._lo

    def append(self, t: np.ndarray, cols: Mapping[str, np.ndarray]) -> None:
        n = t.size
        if self._hi + n > self._t.size:
            live = self.n_rows
            cap = max(2 * (live + n), 1024)
            t_new = np.empty(cap)
            t_new[:live] = self._t[self._lo:self._hi]
            self._t = t_new
            for k in self.keys:
                old = self._cols.get(k)
                a = np.empty((cap, cols[k].shape[1]))
                if old is not None:
                    a[:live] = old[self._lo:self._hi]
                self._cols[k] = a
            self._lo, self._hi = 0, live
        self._t[self._hi:self._hi + n] = t
        for k in self.keys:
            self._cols[k][self._hi:self._hi + n] = cols[k]
        self._hi += n

    def view(self) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        lo, hi = self._lo, self._hi
        return self._t[lo:hi], {k: a[lo:hi] for k, a in self._cols.items()}

    def drop(self, n: int) -> None:
        """Forget the n oldest rows."""
        self._lo = min(self._lo + int(n), self._hi)


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

    def __init__(self, metadata: Metadata | Mapping, *, irregularity: Any = None,
                 irregularity_source: str = "vehicle", psd: str = "maglev_001",
                 band_m: Sequence[float] = (1.0, 20.0), seed: int = 0, method: str = "newmark",
                 fs_hz: float | None = None, dt_max_s: float | None = 2.5e-4, resync_m: float = 0.05,
                 max_pending_s: float = 30.0, parameters: Mapping[str, float] | None = None,
                 max_lag_s: float = 6.0, ahead_m: float = 0.5, taper_m: float = 0.5, settle_s: float = 0.5,
                 profile_period_s: float = 1.0, profiler_options: Mapping[str, Any] | None = None):
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
        if irregularity_source not in IRREGULARITY_SOURCES:
            raise UserError(f"twin irregularity_source: expected one of {', '.join(IRREGULARITY_SOURCES)}, "
                            f"got {irregularity_source!r}")
        self.irregularity_source = "fixed" if irregularity is not None else irregularity_source
        self._irr = None if irregularity is None else _as_irr(irregularity)
        self._default_irr = None
        self.max_lag_s, self.ahead_m = float(max_lag_s), float(ahead_m)
        self.taper_m, self.settle_s = float(taper_m), float(settle_s)
        self.profile_period_s = float(profile_period_s)
        self.profile_stretches: list[tuple[float, float]] = []   # covered (inside the tapers)
        self.n_profile_updates = 0
        self.n_forced = 0                      # position blocks stepped without a profile ahead
        self._profiler = None
        self._profiler_options = dict(profiler_options or {})
        self._profile_at_s = -math.inf         # stream time of the last profile refresh
        self._newest_s = -math.inf             # newest measured sample time seen (stream seconds)
        self._pos_queue: deque[Block] = deque()
        self._uncovered_s = -math.inf          # twin time of the last vehicle sample not covered
        self.stepper: TwinStepper | None = None
        self.t0_ns: int | None = None
        self.revision = 0
        self.frame_id = "twin"
        self.n_resync = 0
        self._track = TrajectoryTracker()
        self.n_dropped = 0
        # predictable channels
        self.guideway_x: dict[str, float] = {}
        self.magnet_of: dict[str, int] = {}
        self.body_x: dict[str, float] = {}          # car-body sensors (optional topic): x on the body
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
            elif s.topic == TOPIC_BODY_ACCEL and self.kind == "pass" and s.raw.get("body_x_m") is not None:
                self.body_x[sid] = float(s.raw["body_x_m"])
        self._sensor_names = tuple(self.guideway_x)
        self._body_names = tuple(self.body_x)
        self.config = self._build_config()
        if parameters:
            self.set_parameters(list(parameters), list(parameters.values()))
        # buffers
        # measured blocks waiting for the twin: [topic, block, first, last sample time (twin s; None
        # until the twin has started)], in arrival order
        self._pending: deque[list] = deque()
        self._pending_newest_ns = -math.inf     # >= the newest stamp pending (drop_stale's quick test)
        self._hist = _History(("gd", "ga", "ma", "mg", "ba", "ok"))
        self._seen_position = False
        self._seen_vehicle = False
        self._offsets = np.asarray(md.magnet_offsets_m if self.kind == "pass" else (), float)
        if self.irregularity_source == "vehicle" and self.kind == "pass" and self._offsets.size:
            from maglev_ros.irregularity.profile import IncrementalProfiler, magnet_channel_pairs
            opts = {"highpass_hz": 0.8, "spacing_m": 0.02, "magnet_length_m": 0.0,
                    "band_speed_mps": 0.8 * md.nominal_speed_mps if md.nominal_speed_mps else None}
            opts.update(self._profiler_options)
            try:
                def make(**o):
                    return IncrementalProfiler(md.magnet_offsets_m, md.nominal_gap_m or 0.010,
                                               channel_pairs=magnet_channel_pairs(md), **o)
                if "max_profile_m" not in opts:    # the band (so the length) is known once configured
                    opts["max_profile_m"] = profile_length_m(make(**opts), self._offsets)
                self._profiler = make(**opts)
            except TypeError as exc:
                raise UserError(f"twin profiler_options: {exc}") from None

    # ---------------------------------------------------------------------------- config
    def _build_config(self, design: dict | None = None):
        d = self.design if design is None else design
        veh = self.metadata.vehicle
        return twin_config(d or None, magnet_offsets_m=veh.get("magnet_offsets_m"),
                           nominal_gap_m=veh.get("nominal_gap_m"))

    def _line(self, spans: list[dict] | None = None) -> dict:
        return {"spans": self.spans if spans is None else spans}

    def set_parameters(self, names: Sequence[str], values: Sequence[float],
                       source_revision: int | None = None) -> dict[str, float]:
        """Adopt parameter values (dotted design paths, see module docstring); rebuilds the twin.
        ``source_revision``: the TwinParameters revision adopted; outputs computed from then on
        carry ``frame_id`` "twin rev <n>" (the updater ignores residuals of older revisions)."""
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
        if source_revision is not None:
            self.frame_id = f"twin rev {int(source_revision)}"
        if self.stepper is not None:
            self._rebuild()
        return adopted

    # ---------------------------------------------------------------------------- irregularity
    def _irregularity(self):
        if self._irr is not None:
            return self._irr
        if self.irregularity_source != "random":
            return _as_irr(None)                   # no measured profile yet: zero (the expected value)
        if self._default_irr is None:
            name, band, seed = self._psd
            start = min(s.start_m for s in self.metadata.spans) - 1000.0
            self._default_irr = periodic_random_irregularity(name, band, seed, start_m=start)
        return self._default_irr

    def set_irregularity(self, irregularity: Any) -> None:
        """Use this KNOWN irregularity (anything ``coupling.as_irregularity`` takes) from now on,
        everywhere; vehicle residuals are then always valid (``irregularity_source`` becomes fixed)."""
        self.irregularity_source = "fixed"
        self._profiler = None
        self._apply_irr(irregularity)

    def _apply_irr(self, irregularity: Any) -> None:
        self._irr = _as_irr(irregularity)
        if self.stepper is not None:
            self.stepper.set_irregularity(self._irr)

    @property
    def vehicle_judged(self) -> bool:
        """Whether vehicle residuals can ever be valid (not with an invented irregularity)."""
        return self.irregularity_source != "random"

    def _set_measured(self, x: np.ndarray, r: np.ndarray) -> None:
        """A measured profile (NaN = not measured): zero outside its valid stretches, half-cosine
        tapers of ``taper_m`` inside them; coverage = the stretches inside the tapers."""
        ok = np.isfinite(r)
        if ok.sum() < 2:
            return
        dx = float(np.median(np.diff(x)))
        w = np.zeros(r.size)
        stretches = []
        edges = np.flatnonzero(np.diff(np.concatenate([[0], ok.astype(np.int8), [0]])))
        for i0, i1 in zip(edges[::2], edges[1::2]):
            lo, hi = float(x[i0]), float(x[i1 - 1])
            if hi - lo <= 2 * self.taper_m + dx:
                continue
            xs = x[i0:i1]
            d = np.minimum(xs - lo, hi - xs) / max(self.taper_m, 1e-12)
            w[i0:i1] = np.where(d >= 1.0, 1.0, 0.5 - 0.5 * np.cos(np.pi * np.clip(d, 0.0, 1.0)))
            stretches.append((lo + self.taper_m, hi - self.taper_m))
        if not stretches:
            return
        self.profile_stretches = stretches
        self.n_profile_updates += 1
        self._apply_irr((x, np.where(ok, r, 0.0) * w))

    def set_irregularity_profile(self, start_position_m: float, spacing_m: float, values: Sequence[float]) -> bool:
        """From an IrregularityProfile message: samples every ``spacing_m`` from ``start_position_m``
        (NaN = not measured). Used with the coverage rules (module docstring) unless the twin
        measures its own profile (``irregularity_source`` vehicle) or has a known one (fixed):
        then the message is ignored and False is returned. A random source switches to topic."""
        r = np.asarray(values, dtype=float)
        ok = np.isfinite(r)
        if ok.sum() < 2 or not spacing_m > 0:
            raise UserError(f"irregularity profile: expected >= 2 finite samples and spacing_m > 0, "
                            f"got {int(ok.sum())} finite of {r.size} samples, spacing {spacing_m!r}")
        if self.irregularity_source in ("vehicle", "fixed"):
            return False
        self.irregularity_source = "topic"
        self._set_measured(float(start_position_m) + float(spacing_m) * np.arange(r.size), r)
        return True

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
        self._uncovered_s = max(self._uncovered_s, st.time_s)     # restart transient: settle again

    def _start(self, stamp_ns: int, position_m: float, speed_mps: float) -> None:
        if self.fs_hz is None:
            rates = [e[1].sample_rate_hz for e in self._pending]
            self.fs_hz = max(rates) if rates else 1000.0
        dt_ns = int(round(1e9 / self.fs_hz))
        self.t0_ns = int(stamp_ns) - dt_ns
        self.stepper = self._new_stepper(0.0, position_m - speed_mps * dt_ns * 1e-9, speed_mps)
        self._track = TrajectoryTracker()
        self._uncovered_s = 0.0                                   # static start: settle first

    def _rel(self, stamp_ns: int) -> float:
        return (int(stamp_ns) - self.t0_ns) * 1e-9

    def _covered(self, position_m: np.ndarray) -> np.ndarray:
        """Per reference position: every magnet inside one covered profile stretch."""
        x = np.asarray(position_m, float)
        if self.irregularity_source == "fixed":
            return np.ones(x.size, bool)
        if self.irregularity_source == "random" or not self.profile_stretches or not self._offsets.size:
            return np.zeros(x.size, bool)
        lo_x, hi_x = x + self._offsets.min(), x + self._offsets.max()
        ok = np.zeros(x.size, bool)
        for lo, hi in self.profile_stretches:
            ok |= (lo_x >= lo) & (hi_x <= hi)
        return ok

    def _record(self, res) -> None:
        if res.n_samples == 0:
            return
        cov = self._covered(res.position_m)
        t = res.time_s
        if self.irregularity_source == "fixed":
            ok = cov
        else:   # valid once every magnet has been covered for settle_s (also after a (re)start)
            last_bad = np.maximum.accumulate(np.where(cov, -np.inf, t))
            last_bad = np.maximum(last_bad, self._uncovered_s)
            self._uncovered_s = float(last_bad[-1])
            ok = cov & (t - last_bad >= self.settle_s)
        # car body (rigid: heave + pitch at each sensor's x)
        vm = self.stepper.vehicle.model
        rows = np.array([vm.point_row("car", self.body_x[n]) for n in self._body_names]).reshape(-1, vm.n_dof)
        self._hist.append(t, {"gd": res.guideway_disp_m, "ga": res.guideway_accel_mps2, "ma": res.magnet_accel_mps2,
                              "mg": res.magnet_gap_m, "ba": res.vehicle_acc_mps2 @ rows.T,
                              "ok": ok.astype(float)[:, None]})

    def _advance(self, t_end_s: float, speed_mps: float | None) -> None:
        self._record(self.stepper.advance(t_end_s, speed_mps))

    def on_position(self, block: Block) -> list[TwinOutput]:
        try:
            block.channel("position_m")
            block.channel("speed_mps")
        except UserError as exc:
            raise UserError(f"{TOPIC_VEHICLE_POSITION}: {exc}") from None
        if block.n_samples == 0:
            return []
        self._seen_position = True
        self._note_time(block)
        self._pos_queue.append(block)
        self._pump()
        return self._flush()

    def _note_time(self, block: Block) -> None:
        end = block.stamp_ns * 1e-9 + (block.n_samples - 1) / block.sample_rate_hz
        self._newest_s = max(self._newest_s, end)

    def _refresh_profile(self, force: bool = False) -> None:
        if self._profiler is None or not (force or self._newest_s - self._profile_at_s >= self.profile_period_s):
            return
        self._profile_at_s = self._newest_s
        try:
            res = self._profiler.result()
        except UserError:          # not enough of all three vehicle topics yet
            return
        self._set_measured(np.asarray(res.position_m, float), np.asarray(res.irregularity_m, float))

    def _ready(self, block: Block) -> bool:
        """May the vehicle be stepped to the end of this position block?"""
        if self.irregularity_source in ("fixed", "random"):
            return True
        end_s = block.stamp_ns * 1e-9 + block.n_samples / block.sample_rate_hz
        lag_s = self._newest_s - end_s
        if lag_s >= self.max_lag_s or (self.irregularity_source == "vehicle" and not self._seen_vehicle
                                       and lag_s >= 1.0):
            self.n_forced += 1       # no profile in time (or no vehicle streams to measure one)
            return True
        pos = block.channel("position_m").astype(float)
        lead = float(np.max(pos)) + float(self._offsets.max(initial=0.0)) + self.ahead_m
        if self.profile_stretches and self.profile_stretches[-1][1] >= lead:
            return True
        self._refresh_profile()
        return bool(self.profile_stretches) and self.profile_stretches[-1][1] >= lead

    def _pump(self) -> None:
        while self._pos_queue and self._ready(self._pos_queue[0]):
            self._step_position(self._pos_queue.popleft())

    def _step_position(self, block: Block) -> None:
        pos = block.channel("position_m").astype(float)
        vel = block.channel("speed_mps").astype(float)
        if self.stepper is None:
            self._start(block.stamp_ns, float(pos[0]), float(vel[0]))
        dt = 1.0 / block.sample_rate_hz
        t_first = self._rel(block.stamp_ns)
        t_last = t_first + (block.n_samples - 1) * dt
        self._track.add(t_first + dt * np.arange(block.n_samples), pos, vel)
        t_next = t_last + dt
        x_next, v_next, x_sd = self._track.estimate(t_next)
        h = t_next - self.stepper.time_s
        v = float(vel[-1])
        miss = self.stepper.position_m + 0.5 * (self.stepper.speed_mps + v) * h - x_next
        if abs(miss) > self.resync_m:
            # further off than any ramp should bring back: a jump of the position system
            self.stepper.position_m -= miss
            self.n_resync += 1
        elif abs(miss) > 3.0 * x_sd + 4.0 * float(np.spacing(np.float32(x_next))):
            # the speed channel's integral left the positions' trajectory by more than its
            # uncertainty (and the float32 samples' resolution): ramp back onto it
            v = ramp_speed(self.stepper, t_next, x_next, v_next)
        self._advance(t_next, v)

    @property
    def queued_position_blocks(self) -> int:
        """Position blocks received but not yet stepped (waiting for the profile)."""
        return len(self._pos_queue)

    def finish(self) -> list[TwinOutput]:
        """End of the recording: step every queued position block with the final profile."""
        self._refresh_profile(force=True)
        while self._pos_queue:
            self._step_position(self._pos_queue.popleft())
        return self._flush()

    def on_block(self, topic: str, block: Block) -> list[TwinOutput]:
        """Feed one block of any recording topic; returns the outputs finished by it."""
        if topic == TOPIC_VEHICLE_POSITION:
            if self._profiler is not None and block.n_samples:
                self._profiler.partial_fit(position=block)
            return self.on_position(block)
        if topic not in TOPIC_GROUPS or block.n_samples == 0:
            return []
        self._pending.append([topic, block, None, None])
        self._pending_newest_ns = max(self._pending_newest_ns, block.stamp_ns)
        self._note_time(block)
        if self._profiler is not None and topic in _PROFILER_KEYS:
            self._seen_vehicle = True
            self._profiler.partial_fit(**{_PROFILER_KEYS[topic]: block})
        if self._pos_queue:
            self._pump()
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
            self._pending_newest_ns = -math.inf
            return
        if (self._pending_newest_ns - self._pending[0][1].stamp_ns) * 1e-9 <= self.max_pending_s:
            return                  # the newest pending stamp is at most the running maximum
        newest = self._pending_newest_ns = max(e[1].stamp_ns for e in self._pending)
        while self._pending and (newest - self._pending[0][1].stamp_ns) * 1e-9 > self.max_pending_s:
            self._pending.popleft()
            self.n_dropped += 1

    # ---------------------------------------------------------------------------- predictions
    def _flush(self) -> list[TwinOutput]:
        if self.stepper is None or not self._pending or not self._hist.n_rows:
            return []
        t, buf = self._hist.view()
        t_cov = t[-1] + 1e-9
        for e in reversed(self._pending):        # sample times once the twin's clock is known
            if e[2] is not None:
                break
            blk = e[1]
            e[2] = self._rel(blk.stamp_ns)
            e[3] = e[2] + (blk.n_samples - 1) / blk.sample_rate_hz
        out = []
        if any(e[3] <= t_cov for e in self._pending):
            keep = deque()
            for e in self._pending:
                topic, blk, first, last = e
                if last > t_cov:
                    keep.append(e)
                    continue
                tb = first + np.arange(blk.n_samples) / blk.sample_rate_hz
                # the history's stretch around the block (np.interp copies the strided columns it
                # is given; over the whole history that copy was most of a prediction's time)
                lo = max(int(np.searchsorted(t, tb[0], side="right")) - 1, 0)
                hi = int(np.searchsorted(t, tb[-1], side="left")) + 1
                o = self._predict(topic, blk, tb, t[lo:hi], {k: v[lo:hi] for k, v in buf.items()})
                if o is not None:
                    out.append(o)
            self._pending = keep
        # trim history older than the oldest pending block (keep 1 s margin)
        t_keep = min(min((e[2] for e in self._pending), default=t[-1]), t[-1]) - 1.0
        i = int(np.searchsorted(t, t_keep))
        if i > 0:
            self._hist.drop(i)
        return out

    def _predict(self, topic: str, blk: Block, tb: np.ndarray, t: np.ndarray, buf: dict) -> TwinOutput | None:
        group = TOPIC_GROUPS[topic]
        cols, src = [], []
        for j, ch in enumerate(blk.channels):
            if topic in (TOPIC_GUIDEWAY_ACCEL, TOPIC_GUIDEWAY_DISP):
                if ch in self.guideway_x:
                    cols.append(j)
                    src.append(("ga" if topic == TOPIC_GUIDEWAY_ACCEL else "gd", self._sensor_names.index(ch)))
            elif topic == TOPIC_BODY_ACCEL:
                if ch in self.body_x:
                    cols.append(j)
                    src.append(("ba", self._body_names.index(ch)))
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
        res = meas - pred
        valid = True
        if topic in (TOPIC_VEHICLE_ACCEL, TOPIC_VEHICLE_GAP, TOPIC_BODY_ACCEL):
            ok = np.interp(tb, t, buf["ok"][:, 0]) > 0.999       # nearest output samples all valid
            if not ok.all():
                res[~ok] = np.nan
                valid = False
        p_blk = Block.from_arrays(blk.stamp_ns, blk.sample_rate_hz, chans, units, pred, self.frame_id)
        r_blk = Block.from_arrays(blk.stamp_ns, blk.sample_rate_hz, chans, units, res, self.frame_id)
        return TwinOutput(group, blk, p_blk, r_blk, valid)

    def feed(self, items: Iterable[tuple[str, Block]]) -> list[TwinOutput]:
        """Convenience: feed (topic, block) pairs in stream order; returns all outputs."""
        out = []
        for topic, blk in items:
            out += self.on_block(topic, blk)
        return out + self.finish()
