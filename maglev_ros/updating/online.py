"""Online updater core (no rclpy): decides when the evidence changed materially, runs the guideway
layer on new modal estimates and the magnet layer when enough residual evidence exists, keeps every
accepted update in a durable ``ParameterHistory`` and yields what the node publishes.

Decisions (choices; the paper updates offline):

- Guideway layer: on a modal estimate whose matched modes differ from those of the last accepted
  guideway update by more than ``max(n_sigma * std_f, freq_rel_tol * f)`` in any frequency (or
  match a different number of modes), or the first one. Accepted when the updated frequencies fit
  the measured ones better than the current parameters do and every value lies inside the physical
  ranges of ``parameters.py`` (the layer clips; an update that hits a bound is still accepted but
  flagged in the provenance).
- Magnet layer: the vehicle-acceleration residual stream (/maglev/twin/residual/vehicle_accel) is
  compared with the measured magnet accelerations of the same stamps (buffered from
  /testline/vehicle/accel for ``max_window_s + max_lag_s``: the twin lags the stream while it
  waits for the measured irregularity). Only valid residual blocks count: a block with NaN (the
  twin had no measured irregularity under every magnet) or a gap of more than ``max_gap_s`` in the
  residual stream restarts the evidence window, so vehicle residuals are judged only where the
  twin used the measured profile. When at least ``magnet_min_s`` seconds of contiguous valid
  evidence exist (at most ``max_window_s``) and its NRMSE exceeds ``nrmse_trigger``, the magnet
  layer runs on the ``max_window_s`` of vehicle streams ENDING with that window (accel, gap,
  position cut to it: the irregularity reconstruction needs several seconds of context for its
  high-pass edges; it starts after the last sample slower than ``min_speed_mps``) with the current
  guideway, and only if the window contains what it needs: accel + gap of the same magnets and position over the window,
  speed above ``min_speed_mps`` throughout, and a valid irregularity
  (``irregularity.twin_input.profile_for_twin`` succeeds on the window; no fallback reconstruction
  online). Otherwise it logs once why it waits (``wait``; the node prints ``log``). Accepted when
  its NRMSE on that window is below the current parameters' NRMSE.
- Stale residuals: the twin stamps its outputs' ``frame_id`` "twin rev <n>" with the revision of
  the parameters it adopted; residual blocks of a revision older than the accepted one (computed
  before the twin adopted the update, the twin lags the stream) are not judged.
- Restart: ``restore()`` (after the metadata) returns the last accepted record of this line in the
  history (republished as is); records of another line are never loaded, and the message says so.
- Storing: an update is accepted only once the history stored it; one the history refuses (a
  non-finite parameter value, another writer, a failed write) is not adopted and goes to
  ``warnings`` with the reason, as do damaged history lines (which the node logs as warnings).

Published parameter names are the twin's dotted design paths (``guideway.youngs_modulus_pa``,
``levitation.kp_a_per_m``) that ``twin.online.OnlineTwin.set_parameters`` adopts.
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass
from typing import Any, Mapping, Sequence

import numpy as np

from maglev_ros.contract import (TOPIC_VEHICLE_ACCEL, TOPIC_VEHICLE_GAP, TOPIC_VEHICLE_POSITION, Metadata,
                                 metadata_from_dict)
from maglev_ros.errors import UserError
from maglev_ros.twin.design import line_spans, twin_config_from_metadata, with_guideway, with_levitation
from maglev_ros.updating.guideway_layer import GuidewayLayer, SpanModel
from maglev_ros.updating.history import ParameterHistory, line_key
from maglev_ros.updating.magnet_layer import MagnetLayer, make_evidence
from maglev_ros.updating.parameters import GUIDEWAY_PARAMS, MAGNET_PARAMS, UNITS
from maglev_ros.updating.pipeline import TWIN_NAMES, _runs, modal_target


def _twin_revision(frame_id: str) -> int | None:
    """The parameter revision a residual block was computed with (frame_id "twin rev <n>")."""
    parts = str(frame_id).split()
    if len(parts) == 3 and parts[0] == "twin" and parts[1] == "rev" and parts[2].isdigit():
        return int(parts[2])
    return None


@dataclass(frozen=True)
class Publication:
    """What the node publishes on /maglev/twin/parameters (TwinParameters fields)."""
    revision: int
    names: tuple[str, ...]
    values: tuple[float, ...]
    units: tuple[str, ...]
    std: tuple[float, ...]            # NaN unknown
    identifiable: tuple[bool, ...]
    provenance_json: str

    def to_dict(self) -> dict:
        return {"revision": self.revision, "names": list(self.names), "values": list(self.values),
                "units": list(self.units), "std": [None if not math.isfinite(s) else s for s in self.std],
                "identifiable": list(self.identifiable), "provenance_json": self.provenance_json}


@dataclass(frozen=True)
class Restored:
    """What ``restore`` found: the publication to republish (None: start from the design) and why."""
    publication: Publication | None
    message: str
    warnings: tuple[str, ...] = ()     # damaged history lines (skipped, set aside) to log


def publication_from_record(rec: Mapping) -> Publication:
    params = rec["parameters"]
    names = tuple(params)
    std = tuple(float("nan") if params[n].get("std") is None else float(params[n]["std"]) for n in names)
    prov = {"revision": rec["revision"], "time_unix_s": rec.get("time_unix_s"), "data_used": rec.get("data_used", {}),
            "fit": rec.get("fit", {})}
    return Publication(int(rec["revision"]), tuple(TWIN_NAMES.get(n, n) for n in names),
                       tuple(float(params[n]["value"]) for n in names), tuple(params[n].get("unit", "") for n in names),
                       std, tuple(bool(params[n].get("identifiable", False)) for n in names),
                       json.dumps(prov, default=float))


class OnlineUpdater:
    def __init__(self, history_path, *, freq_rel_tol: float = 2e-3, n_sigma: float = 3.0, max_modes: int = 4,
                 guideway_layer: GuidewayLayer | None = None, magnet_layer: MagnetLayer | None = None,
                 magnet_min_s: float = 3.0, nrmse_trigger: float = 0.15, max_window_s: float = 8.0,
                 magnet_fs_hz: float = 500.0, max_lag_s: float = 10.0, max_gap_s: float = 0.05,
                 min_speed_mps: float = 0.1, highpass_hz: float = 1.0):
        self.history = ParameterHistory(history_path)
        self.freq_rel_tol, self.n_sigma, self.max_modes = float(freq_rel_tol), float(n_sigma), int(max_modes)
        self.guideway_layer = guideway_layer or GuidewayLayer(n_particles=40, n_iterations=40, archive_size=40)
        self.magnet_layer = magnet_layer or MagnetLayer(n_samples=30, polish_max_nfev=15)
        self.magnet_min_s, self.nrmse_trigger = float(magnet_min_s), float(nrmse_trigger)
        self.max_window_s, self.magnet_fs_hz = float(max_window_s), float(magnet_fs_hz)
        self.max_lag_s, self.max_gap_s = float(max_lag_s), float(max_gap_s)
        self.min_speed_mps, self.highpass_hz = float(min_speed_mps), float(highpass_hz)
        self.last_residual_nrmse: float | None = None
        self._said: set[str] = set()
        self._revision = 0
        self.md: Metadata | None = None
        self.nominal = None
        self.current: dict[str, dict] = {}          # accepted parameters (maglev-params/1 entries)
        self._last_freqs: np.ndarray | None = None
        self._buf: dict[str, list] = {TOPIC_VEHICLE_ACCEL: [], TOPIC_VEHICLE_GAP: [], TOPIC_VEHICLE_POSITION: []}
        self._res: list = []
        self.log: list[str] = []
        self.warnings: list[str] = []               # refused records, damaged history lines: the node warns

    # ------------------------------------------------------------------ state
    @property
    def revision(self) -> int:
        """Revision of the accepted parameters (0: none yet)."""
        return int(self._revision)

    def restore(self) -> Restored:
        """Continue from the last record of this line's history (call after ``set_metadata``).

        Records of other lines (another ``line``/``design`` block) are never loaded; the message
        says what was loaded, or why nothing was."""
        if self.md is None:
            raise UserError("/testline/metadata: not received yet; the parameter history is per line")
        where = "memory only" if self.history.path is None else str(self.history.path)
        recs = self.history.records()
        warnings = tuple(self.history.take_warnings())
        key = line_key(self.md.raw)
        mine = [r for r in recs if r.get("line") == key]
        others = len(recs) - len(mine)
        other_note = (f"; {others} record(s) of other lines or of unknown line there are not used"
                      if others else "")
        if not mine:
            self.current, self._revision, self._last_freqs = {}, 0, None
            return Restored(None, f"parameter history {where}: nothing for this line yet (line "
                                  f"{key}), starting from the design{other_note}", warnings)
        rec = mine[-1]
        self.current = {n: dict(v) for n, v in rec["parameters"].items()}
        self._revision = int(rec["revision"])
        f = (rec.get("data_used") or {}).get("frequencies_hz")
        self._last_freqs = None if f is None else np.asarray(f, float)
        src = (rec.get("data_used") or {}).get("recording") or "an earlier run"
        return Restored(publication_from_record(rec),
                        f"parameter history {where}: continuing from revision {rec['revision']} of this "
                        f"line (line {key}, from {src}){other_note}", warnings)

    def set_metadata(self, metadata: Mapping | Metadata) -> None:
        self.md = metadata if isinstance(metadata, Metadata) else metadata_from_dict(dict(metadata), "/testline/metadata")
        self.nominal = twin_config_from_metadata(self.md.raw)

    def config(self):
        """Twin config with the accepted parameters."""
        if self.nominal is None:
            raise UserError("/testline/metadata: not received yet; the updater needs the design and sensor positions")
        g = {n: self.current[n]["value"] for n in GUIDEWAY_PARAMS if n in self.current}
        m = {n: self.current[n]["value"] for n in MAGNET_PARAMS if n in self.current}
        return with_levitation(with_guideway(self.nominal, **g), **m)

    def _accept(self, params: dict, data_used: dict, fit: dict) -> Publication | None:
        merged = {**self.current, **params}
        line = line_key(self.md.raw) if self.md is not None else None
        if self.md is not None:     # which recording the update came from, for the restart message
            data_used = {**data_used, "recording": (self.md.description or "unnamed recording")[:120]}
        try:
            rec = self.history.append(merged, data_used, fit, line=line)
        except UserError as exc:                # not stored = not accepted: the twin keeps the current set
            self.warnings.extend(self.history.take_warnings())
            self.warnings.append(f"update refused: {exc}")
            return None
        self.warnings.extend(self.history.take_warnings())
        self.current = merged
        self._revision = int(rec["revision"])
        return publication_from_record(rec)

    def new_recording(self) -> None:
        """A recording has ended: its buffered streams and residual evidence are dropped (the next
        recording's windows never reach into this one)."""
        for b in self._buf.values():
            b.clear()
        self._res.clear()

    def accept_recording_update(self, document: Mapping, data_used: Mapping) -> Publication | None:
        """The ``maglev-params/1`` document of the whole-recording update (``pipeline.update_from_bags``,
        what ``maglev-ros update`` writes), stored and adopted as it is: it replaces the parameters
        it holds (an ambient-only update holds the guideway's; the gains stay as they were)."""
        params = {n: dict(v) for n, v in document["parameters"].items()}
        fit = {"layer": "recording end (maglev-ros update pipeline)",
               "frequencies_hz": document.get("frequencies_hz"), "mac": document.get("mac"),
               "magnet_accel_nrmse": document.get("magnet_accel_nrmse"),
               "combinations": document.get("identifiable_combinations", [])}
        pub = self._accept(params, dict(data_used), fit)
        if pub is not None:
            f = (document.get("frequencies_hz") or {}).get("measured")
            self._last_freqs = None if f is None else np.asarray(f, float)
            self.log.append(f"recording-end update accepted: rev {pub.revision} ("
                            + ", ".join(f"{n} {v['value']:.5g}" for n, v in params.items()) + ")")
        return pub

    # ------------------------------------------------------------------ guideway layer
    def changed(self, freqs: np.ndarray, std: np.ndarray) -> bool:
        if self._last_freqs is None or self._last_freqs.size != freqs.size:
            return True
        tol = np.maximum(self.n_sigma * np.where(np.isfinite(std), std, 0.0), self.freq_rel_tol * freqs)
        return bool(np.any(np.abs(freqs - self._last_freqs) > tol))

    def on_modes(self, modes: Sequence[Any], stamp_s: float | None = None) -> Publication | None:
        """A modal estimate (list of SSI-cov modes / ModalMode msgs / dicts). Returns the publication
        of an accepted update, or None (no material change, or rejected)."""
        job = self.take_modes_job(modes, stamp_s)
        return None if job is None else self.accept_modes_update(self.compute_modes_update(job))

    def take_modes_job(self, modes: Sequence[Any], stamp_s: float | None = None) -> dict | None:
        """The quick part of :meth:`on_modes`: the layer's target from the estimate, or None when
        nothing changed materially. The job holds what the fit needs, so that
        :meth:`compute_modes_update` can run without the caller's lock (a node's worker thread)."""
        if self.md is None:
            self.log.append("modes before metadata: ignored")
            return None
        live = [m for m in modes if str(getattr(m, "status", "tracked") if not isinstance(m, Mapping)
                                        else m.get("status", "tracked")) != "lost"]
        cfg = self.config()
        span, tgt, info = modal_target(live, self.md, cfg, self.max_modes)
        f = np.asarray(tgt.frequencies_hz, float)
        if not self.changed(f, np.asarray(tgt.std_frequency_hz, float)):
            return None
        # the layer works around the CURRENT values (its ranges are relative to the span's design)
        nominal_span = [s for s in line_spans(self.md.raw["line"], self.nominal) if s.span_id == span.span_id][0]
        return {"span": span, "nominal_span": nominal_span, "target": tgt, "info": info, "f": f,
                "std": np.asarray(tgt.std_frequency_hz, float), "stamp_s": stamp_s, "max_modes": self.max_modes, "layer": self.guideway_layer}

    @staticmethod
    def compute_modes_update(job: dict) -> dict:
        """The guideway layer's fit of a :meth:`take_modes_job` job (the long part; touches no state)."""
        span, f = job["span"], job["f"]
        up = job["layer"].fit(job["nominal_span"], job["target"])
        cur_vals = [getattr(span.props, n) for n in GUIDEWAY_PARAMS]
        f_cur = SpanModel(span, n_modes=job["max_modes"] + 2).modes(cur_vals)[0]
        err_cur = float(np.max(np.abs(np.sort(f_cur)[:f.size] / f - 1))) if f.size else float("inf")
        err_up = float(np.max(np.abs(np.asarray(up.frequencies_updated_hz) / f - 1)))
        return {**job, "up": up, "err_cur": err_cur, "err_up": err_up}

    def accept_modes_update(self, result: dict) -> Publication | None:
        """Accept (store, adopt) or reject a :meth:`compute_modes_update` result."""
        up, f, span, info = result["up"], result["f"], result["span"], result["info"]
        err_cur, err_up = result["err_cur"], result["err_up"]
        self._last_freqs = f
        if not err_up < err_cur and self.current:
            self.log.append(f"guideway update rejected: max frequency error {err_up:.4f} >= current {err_cur:.4f}")
            return None
        rel_range = result["layer"].rel_range
        space_lo = [s * (1 - rel_range) for s in up.nominal]
        space_hi = [s * (1 + rel_range) for s in up.nominal]
        at_bound = [n for n, v, lo, hi in zip(up.names, up.values, space_lo, space_hi)
                    if v <= lo * (1 + 1e-6) or v >= hi * (1 - 1e-6)]
        params = {n: {"value": float(v), "unit": UNITS[n], "std": None if s is None else float(s),
                      "identifiable": bool(ok)}
                  for n, v, s, ok in zip(up.names, up.values, up.std, up.identifiable)}
        data_used = {"kind": "modes", "stamp_s": result["stamp_s"], "frequencies_hz": f.tolist(),
                     "span": span.span_id, "matched_fe_modes": info["matched_fe_modes"]}
        fit = {"layer": "guideway", "max_freq_error_before": err_cur, "max_freq_error_after": err_up,
               "combinations": [c.to_dict() for c in up.identifiability.combinations if c.identifiable],
               "at_bound": at_bound, "n_model_evaluations": up.n_model_evaluations}
        return self._accept(params, data_used, fit)

    # ------------------------------------------------------------------ magnet layer
    def wait(self, key: str, text: str) -> None:
        """Log why the magnet layer waits, once per reason (``key``) until the layer next runs."""
        if key not in self._said:
            self._said.add(key)
            self.log.append(f"magnet layer waits: {text}")

    def on_vehicle_block(self, topic: str, block) -> None:
        if topic in self._buf:
            self._buf[topic].append(block)
            self._trim(topic)

    def _trim(self, topic: str) -> None:
        b = self._buf[topic]
        horizon = self.max_window_s + self.max_lag_s
        while len(b) > 1 and (b[-1].times_s()[-1] - b[0].times_s()[0]) > horizon:
            b.pop(0)

    def _series(self, topic: str, t0: float = -math.inf, t1: float = math.inf):
        b = [x for x in self._buf[topic] if x.n_samples and x.times_s()[-1] >= t0 and x.times_s()[0] <= t1]
        if not b:
            return None, None, ()
        t = np.concatenate([x.times_s() for x in b])
        d = np.concatenate([np.asarray(x.data, float) for x in b])
        keep = (t >= t0) & (t <= t1)
        return t[keep], d[keep], b[-1].channels

    def residual_ready(self, block) -> float | None:
        """Buffer a /maglev/twin/residual/vehicle_accel block; returns the residual NRMSE when the
        magnet layer should run: at least ``magnet_min_s`` of contiguous, valid (finite) residual
        evidence of a moving vehicle whose NRMSE exceeds ``nrmse_trigger``. A block with a NaN
        sample (the twin did not have the measured irregularity under every magnet) or a gap in the
        residual stream restarts the evidence window."""
        if block.n_samples == 0:
            return None
        rev = _twin_revision(getattr(block, "frame_id", ""))
        if rev is not None and rev < self.revision:
            self._res.clear()
            self.wait(f"stale{self.revision}", f"residuals of twin revision {rev}: waiting for the twin to adopt "
                                               f"revision {self.revision}")
            return None
        data = np.asarray(block.data, float)
        if not np.all(np.isfinite(data)):
            self._res.clear()
            self.wait("invalid", "the twin's vehicle residual is not valid yet (no measured irregularity "
                                 "under every magnet)")
            return None
        if self._res:
            gap_s = block.times_s()[0] - self._res[-1].times_s()[-1]
            if gap_s > 2.0 / block.sample_rate_hz + self.max_gap_s or gap_s <= 0:
                self._res.clear()
        self._res.append(block)
        while len(self._res) > 1 and (self._res[-1].times_s()[-1] - self._res[0].times_s()[0]) > self.max_window_s:
            self._res.pop(0)
        span_s = self._res[-1].times_s()[-1] - self._res[0].times_s()[0]
        if self.md is None:
            self.wait("metadata", "no /testline/metadata yet")
            return None
        if span_s < self.magnet_min_s:
            self.wait("short", f"{span_s:.1f} s of valid residual evidence, need {self.magnet_min_s:g} s")
            return None
        tr = np.concatenate([x.times_s() for x in self._res])
        r = np.concatenate([np.asarray(x.data, float) for x in self._res])
        ta, a, ach = self._series(TOPIC_VEHICLE_ACCEL, tr[0], tr[-1])
        both = np.zeros(tr.size, bool) if ta is None else (tr >= ta[0]) & (tr <= ta[-1])
        if not both.any() or tr[both][-1] - tr[both][0] < self.magnet_min_s:
            self.wait("accel", f"measured {TOPIC_VEHICLE_ACCEL} covers less than {self.magnet_min_s:g} s of the "
                               f"residual window {tr[0]:.2f}-{tr[-1]:.2f} s")
            return None
        tr, r = tr[both], r[both]
        rch = self._res[-1].channels
        pairs = [(i, ach.index(c)) for i, c in enumerate(rch) if c in ach]
        if not pairs:
            self.wait("channels", f"no residual channel of {', '.join(rch)} is on {TOPIC_VEHICLE_ACCEL}")
            return None
        meas = np.stack([np.interp(tr, ta, a[:, j]) for _, j in pairs], axis=1)
        res = r[:, [i for i, _ in pairs]]
        e = float(np.sqrt(np.mean(res ** 2)) / max(np.sqrt(np.mean(meas ** 2)), 1e-300))
        self.last_residual_nrmse = e
        if e <= self.nrmse_trigger:
            self.wait("fits", f"vehicle residual NRMSE {e:.3f} <= trigger {self.nrmse_trigger:g}: gains fit")
            return None
        # the layer's irregularity reconstruction needs context: a full max_window_s of vehicle
        # streams ending with the residual window (the evidence keeps growing meanwhile)
        t_first = min((b[0].times_s()[0] for b in self._buf.values() if b), default=math.inf)
        if t_first > tr[-1] - self.max_window_s + 0.05:
            self.wait("context", f"residual NRMSE {e:.3f} > trigger, but only {max(tr[-1] - t_first, 0):.1f} s of "
                                 f"vehicle streams buffered, the magnet layer takes {self.max_window_s:g} s")
            return None
        return e

    def on_residual(self, block) -> Publication | None:
        """``residual_ready`` then, when warranted, ``run_magnet_layer`` (synchronous)."""
        job = self.take_magnet_job(block)
        if job is None:
            return None
        return self.accept_magnet_update(self.compute_magnet_update(job, job["residual_nrmse"]))

    def take_magnet_job(self, block) -> dict | None:
        """``residual_ready``; when the layer should run, the snapshot of its window (the residual
        evidence window then starts afresh). For a caller that runs the layer elsewhere."""
        e = self.residual_ready(block)
        if e is None:
            return None
        job = self.snapshot_magnet_job()
        job["residual_nrmse"] = e
        self._res.clear()
        return job

    def run_magnet_layer(self, residual_nrmse: float | None = None) -> Publication | None:
        """Synchronous: snapshot (the current residual window), compute, accept."""
        return self.accept_magnet_update(self.compute_magnet_update(self.snapshot_magnet_job(), residual_nrmse))

    def snapshot_magnet_job(self) -> dict:
        """Copies of what the magnet layer needs: the vehicle streams over the ``max_window_s``
        ending with the residual evidence window (the irregularity reconstruction needs several
        seconds of context: its high-pass edges), position with 1 s margins, metadata, current
        config; ``compute_magnet_update`` then runs without the caller's lock."""
        if self._res:
            t1 = self._res[-1].times_s()[-1]
            t0 = min(self._res[0].times_s()[0], t1 - self.max_window_s)
        else:
            t0, t1 = -math.inf, math.inf
        series = {tp: self._series(tp, t0 - (1.0 if tp == TOPIC_VEHICLE_POSITION else 0.0),
                                   t1 + (1.0 if tp == TOPIC_VEHICLE_POSITION else 0.0)) for tp in self._buf}
        return {"series": series, "window_s": (t0, t1), "md": self.md,
                "config": self.config() if self.nominal is not None else None}

    def compute_magnet_update(self, job: dict, residual_nrmse: float | None = None) -> dict | None:
        """The magnet layer on a snapshot (long; touches no state). Returns a result for
        ``accept_magnet_update`` (with a ``log`` line when the window lacks what the layer needs:
        accel + gap + position of the magnets over the window, speed > ``min_speed_mps``
        throughout, a valid irregularity from ``profile_for_twin``; the layer is not run then)."""
        md, cfg = job["md"], job["config"]
        ta, a, ach = job["series"][TOPIC_VEHICLE_ACCEL]
        tg, g, gch = job["series"][TOPIC_VEHICLE_GAP]
        tp, p, pch = job["series"][TOPIC_VEHICLE_POSITION]
        if md is None or cfg is None:
            return {"log": "magnet layer: no metadata yet", "wait": "metadata"}
        for name, tt, n_min in ((TOPIC_VEHICLE_ACCEL, ta, 64), (TOPIC_VEHICLE_GAP, tg, 64),
                                (TOPIC_VEHICLE_POSITION, tp, 4)):
            if tt is None or tt.size < n_min:
                return {"log": f"magnet layer: {name} not buffered over the residual window", "wait": "buffer"}
        if "position_m" not in pch or "speed_mps" not in pch:
            return {"log": f"magnet layer: {TOPIC_VEHICLE_POSITION} lacks position_m/speed_mps", "wait": "position"}
        sens = md.sensors
        ma = {sens[c].magnet: i for i, c in enumerate(ach) if c in sens and sens[c].magnet}
        mg = {sens[c].magnet: i for i, c in enumerate(gch) if c in sens and sens[c].magnet}
        mags = sorted(set(ma) & set(mg))
        if not mags:
            return {"log": "magnet layer: no magnet has both an acceleration and a gap channel", "wait": "magnets"}
        lo, hi = max(ta[0], tg[0], tp[0]), min(ta[-1], tg[-1], tp[-1])
        # start after the last slow (or invalid) position sample: the window must be a moving pass
        spd_all = p[:, pch.index("speed_mps")]
        slow = (tp <= hi) & ~(np.isfinite(spd_all) & (spd_all > self.min_speed_mps))
        if slow.any():
            lo = max(lo, float(tp[slow][-1]) + 1e-9)
        keep = (ta >= lo) & (ta <= hi)
        if hi - lo < self.magnet_min_s or keep.sum() < 64:
            why = ("vehicle slower than %g m/s" % self.min_speed_mps) if slow.any() else "accel/gap/position overlap"
            return {"log": f"magnet layer: only {max(hi - lo, 0):.1f} s of moving window with accel+gap+position "
                           f"({why}), need {self.magnet_min_s:g} s", "wait": "window"}
        keep_p = (tp >= lo - 1.0) & (tp <= hi + 1.0)
        from types import SimpleNamespace as NS
        from maglev_ros.irregularity.twin_input import profile_for_twin
        fs = 1.0 / float(np.median(np.diff(ta[keep])))
        acc = NS(time_s=ta[keep], data=a[keep], channels=tuple(ach), sample_rate_hz=fs)
        keep_g = (tg >= lo) & (tg <= hi)
        fs_g = 1.0 / float(np.median(np.diff(tg[keep_g])))
        gap = NS(time_s=tg[keep_g], data=g[keep_g], channels=tuple(gch), sample_rate_hz=fs_g)
        posd = p[keep_p][:, [pch.index("position_m"), pch.index("speed_mps")]]
        pos = NS(time_s=tp[keep_p], data=posd, channels=("position_m", "speed_mps"), sample_rate_hz=None,
                 channel=lambda n, _d=posd: _d[:, ("position_m", "speed_mps").index(n)])
        pairs = {m: [ach[ma[m]], gch[mg[m]]] for m in mags}
        line = md.raw["line"]
        try:
            ti = profile_for_twin(acc, gap, pos, md, cfg, line, highpass_hz=self.highpass_hz, channel_pairs=pairs)
        except (UserError, ValueError, np.linalg.LinAlgError) as exc:
            return {"log": f"magnet layer: no valid irregularity on the window ({type(exc).__name__}: {exc})",
                    "wait": "irregularity"}
        t = acc.time_s
        a_m = np.asarray(acc.data, float)[:, [ach.index(pairs[m][0]) for m in mags]]
        v_max = float(np.max(np.abs(posd[:, 1])))
        band = (ti.highpass_hz, min(v_max / ti.min_wavelength_m, 0.45 * fs))
        try:
            ev = make_evidence(t, a_m, mags, pos.time_s, posd[:, 0], posd[:, 1], ti.denoised_twin_input()[:2],
                               md.magnet_offsets_m, valid_range_m=_runs(ti.valid, ti.position_m), band_hz=band,
                               model_fs_hz=self.magnet_fs_hz, skip_s=0.3, margin_m=ti.taper_m + 1.0,
                               label="online window", irregularity_method="profile_for_twin")
        except UserError as exc:
            return {"log": f"magnet layer: {exc}", "wait": "evidence"}
        up = self.magnet_layer.fit(cfg, line, [ev])
        data_used = {"kind": "vehicle window", "t0_s": float(t[0]), "duration_s": float(t[-1] - t[0]),
                     "magnets": mags, "irregularity": "irregularity.twin_input.profile_for_twin",
                     "irregularity_band_m": [ti.min_wavelength_m, ti.max_wavelength_m],
                     "residual_nrmse": residual_nrmse}
        return {"update": up, "data_used": data_used, "log": None}

    def accept_magnet_update(self, result: dict | None) -> Publication | None:
        if result is None:
            return None
        if result.get("log"):
            if result.get("wait"):
                self.wait(result["wait"], result["log"].removeprefix("magnet layer: "))
            else:
                self.log.append(result["log"])
        up = result.get("update")
        if up is None:
            return None
        self._said.clear()
        if not up.nrmse_updated < up.nrmse_nominal:     # "nominal" of the layer = the current gains
            self.log.append(f"magnet update rejected: NRMSE {up.nrmse_updated:.3f} >= {up.nrmse_nominal:.3f}")
            return None
        params = {n: {"value": float(v), "unit": UNITS[n], "std": None if s is None else float(s),
                      "identifiable": bool(ok)} for n, v, s, ok in zip(up.names, up.values, up.std, up.identifiable)}
        fit = {"layer": "magnet", "nrmse_before": up.nrmse_nominal, "nrmse_after": up.nrmse_updated,
               "combinations": [c.to_dict() for c in up.identifiability.combinations if c.identifiable],
               "uncertainty": up.uncertainty, "n_model_evaluations": up.n_model_evaluations}
        pub = self._accept(params, result["data_used"], fit)
        if pub is not None:
            self.log.append(f"magnet update accepted: NRMSE {up.nrmse_nominal:.3f} -> {up.nrmse_updated:.3f}")
        return pub
