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
  /testline/vehicle/accel). When at least ``magnet_min_s`` seconds of residual evidence of a moving
  vehicle exist and the residual NRMSE exceeds ``nrmse_trigger``, the magnet layer runs on the
  buffered window (accel, gap, position; at most ``max_window_s``) with the current guideway.
  Accepted when its NRMSE on that window is below the current parameters' NRMSE.
- Restart: ``restore()`` returns the last accepted record of the history (republished as is).

Published parameter names are the twin's dotted design paths (``guideway.youngs_modulus_pa``,
``levitation.kp_a_per_m``) that ``twin.online.OnlineTwin.set_parameters`` adopts.
"""
from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass
from typing import Any, Mapping, Sequence

import numpy as np

from maglev_ros.contract import (TOPIC_VEHICLE_ACCEL, TOPIC_VEHICLE_GAP, TOPIC_VEHICLE_POSITION, Metadata,
                                 metadata_from_dict)
from maglev_ros.errors import UserError
from maglev_ros.twin.design import line_spans, twin_config_from_metadata, with_guideway, with_levitation
from maglev_ros.updating.guideway_layer import GuidewayLayer, SpanModel
from maglev_ros.updating.history import ParameterHistory
from maglev_ros.updating.magnet_layer import MagnetLayer, PassEvidence, nrmse
from maglev_ros.updating.parameters import GUIDEWAY_PARAMS, MAGNET_PARAMS, UNITS
from maglev_ros.updating.pipeline import TWIN_NAMES, PassRecording, modal_target, pass_evidence


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
                 magnet_fs_hz: float = 500.0):
        self.history = ParameterHistory(history_path)
        self.freq_rel_tol, self.n_sigma, self.max_modes = float(freq_rel_tol), float(n_sigma), int(max_modes)
        self.guideway_layer = guideway_layer or GuidewayLayer(n_particles=40, n_iterations=40, archive_size=40)
        self.magnet_layer = magnet_layer or MagnetLayer(n_samples=30, polish_max_nfev=15)
        self.magnet_min_s, self.nrmse_trigger = float(magnet_min_s), float(nrmse_trigger)
        self.max_window_s, self.magnet_fs_hz = float(max_window_s), float(magnet_fs_hz)
        self.md: Metadata | None = None
        self.nominal = None
        self.current: dict[str, dict] = {}          # accepted parameters (maglev-params/1 entries)
        self._last_freqs: np.ndarray | None = None
        self._buf: dict[str, list] = {TOPIC_VEHICLE_ACCEL: [], TOPIC_VEHICLE_GAP: [], TOPIC_VEHICLE_POSITION: []}
        self._res: list = []
        self.log: list[str] = []

    # ------------------------------------------------------------------ state
    def restore(self) -> Publication | None:
        rec = self.history.last()
        if rec is None:
            return None
        self.current = {n: dict(v) for n, v in rec["parameters"].items()}
        f = (rec.get("data_used") or {}).get("frequencies_hz")
        self._last_freqs = None if f is None else np.asarray(f, float)
        return publication_from_record(rec)

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

    def _accept(self, params: dict, data_used: dict, fit: dict) -> Publication:
        merged = {**self.current, **params}
        rec = self.history.append(merged, data_used, fit)
        self.current = merged
        return publication_from_record(rec)

    # ------------------------------------------------------------------ guideway layer
    def changed(self, freqs: np.ndarray, std: np.ndarray) -> bool:
        if self._last_freqs is None or self._last_freqs.size != freqs.size:
            return True
        tol = np.maximum(self.n_sigma * np.where(np.isfinite(std), std, 0.0), self.freq_rel_tol * freqs)
        return bool(np.any(np.abs(freqs - self._last_freqs) > tol))

    def on_modes(self, modes: Sequence[Any], stamp_s: float | None = None) -> Publication | None:
        """A modal estimate (list of SSI-cov modes / ModalMode msgs / dicts). Returns the publication
        of an accepted update, or None (no material change, or rejected)."""
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
        up = self.guideway_layer.fit(nominal_span, tgt)
        cur_vals = [getattr(span.props, n) for n in GUIDEWAY_PARAMS]
        f_cur = SpanModel(span, n_modes=self.max_modes + 2).modes(cur_vals)[0]
        err_cur = float(np.max(np.abs(np.sort(f_cur)[:f.size] / f - 1))) if f.size else float("inf")
        err_up = float(np.max(np.abs(np.asarray(up.frequencies_updated_hz) / f - 1)))
        self._last_freqs = f
        if not err_up < err_cur and self.current:
            self.log.append(f"guideway update rejected: max frequency error {err_up:.4f} >= current {err_cur:.4f}")
            return None
        space_lo = [s * (1 - self.guideway_layer.rel_range) for s in up.nominal]
        space_hi = [s * (1 + self.guideway_layer.rel_range) for s in up.nominal]
        at_bound = [n for n, v, lo, hi in zip(up.names, up.values, space_lo, space_hi)
                    if v <= lo * (1 + 1e-6) or v >= hi * (1 - 1e-6)]
        params = {n: {"value": float(v), "unit": UNITS[n], "std": None if s is None else float(s),
                      "identifiable": bool(ok)}
                  for n, v, s, ok in zip(up.names, up.values, up.std, up.identifiable)}
        data_used = {"kind": "modes", "stamp_s": stamp_s, "frequencies_hz": f.tolist(), "span": span.span_id,
                     "matched_fe_modes": info["matched_fe_modes"]}
        fit = {"layer": "guideway", "max_freq_error_before": err_cur, "max_freq_error_after": err_up,
               "combinations": [c.to_dict() for c in up.identifiability.combinations if c.identifiable],
               "at_bound": at_bound, "n_model_evaluations": up.n_model_evaluations}
        return self._accept(params, data_used, fit)

    # ------------------------------------------------------------------ magnet layer
    def on_vehicle_block(self, topic: str, block) -> None:
        if topic in self._buf:
            self._buf[topic].append(block)
            self._trim(topic)

    def _trim(self, topic: str) -> None:
        b = self._buf[topic]
        while len(b) > 1 and (b[-1].times_s()[-1] - b[0].times_s()[0]) > self.max_window_s:
            b.pop(0)

    def _series(self, topic: str):
        b = self._buf[topic]
        if not b:
            return None, None, ()
        t = np.concatenate([x.times_s() for x in b])
        d = np.concatenate([np.asarray(x.data, float) for x in b])
        return t, d, b[-1].channels

    def residual_ready(self, block) -> float | None:
        """Buffer a /maglev/twin/residual/vehicle_accel block; returns the residual NRMSE when the
        magnet layer should run (enough moving-vehicle evidence and NRMSE > ``nrmse_trigger``)."""
        self._res.append(block)
        while len(self._res) > 1 and (self._res[-1].times_s()[-1] - self._res[0].times_s()[0]) > self.max_window_s:
            self._res.pop(0)
        span_s = self._res[-1].times_s()[-1] - self._res[0].times_s()[0]
        if self.md is None or span_s < self.magnet_min_s:
            return None
        ta, a, ach = self._series(TOPIC_VEHICLE_ACCEL)
        if ta is None:
            return None
        tr = np.concatenate([x.times_s() for x in self._res])
        r = np.concatenate([np.asarray(x.data, float) for x in self._res])
        rch = self._res[-1].channels
        pairs = [(i, ach.index(c)) for i, c in enumerate(rch) if c in ach]
        if not pairs:
            return None
        meas = np.stack([np.interp(tr, ta, a[:, j]) for _, j in pairs], axis=1)
        res = r[:, [i for i, _ in pairs]]
        e = float(np.sqrt(np.mean(res ** 2)) / max(np.sqrt(np.mean(meas ** 2)), 1e-300))
        return e if e > self.nrmse_trigger else None

    def on_residual(self, block) -> Publication | None:
        """``residual_ready`` then, when warranted, ``run_magnet_layer`` (synchronous)."""
        e = self.residual_ready(block)
        if e is None:
            return None
        self._res.clear()
        return self.run_magnet_layer(residual_nrmse=e)

    def run_magnet_layer(self, residual_nrmse: float | None = None) -> Publication | None:
        """Synchronous: snapshot, compute, accept."""
        return self.accept_magnet_update(self.compute_magnet_update(self.snapshot_magnet_job(), residual_nrmse))

    def snapshot_magnet_job(self) -> dict:
        """Copies of what the magnet layer needs (buffered vehicle window, metadata, current config),
        so ``compute_magnet_update`` can run without the caller's lock."""
        return {"series": {tp: self._series(tp) for tp in self._buf}, "md": self.md,
                "config": self.config() if self.nominal is not None else None}

    def compute_magnet_update(self, job: dict, residual_nrmse: float | None = None) -> dict | None:
        """The magnet layer on a snapshot (long; touches no state). Returns a result for
        ``accept_magnet_update`` or None."""
        md, cfg = job["md"], job["config"]
        ta, a, ach = job["series"][TOPIC_VEHICLE_ACCEL]
        tg, g, gch = job["series"][TOPIC_VEHICLE_GAP]
        tp, p, pch = job["series"][TOPIC_VEHICLE_POSITION]
        if md is None or cfg is None:
            return {"log": "magnet layer: no metadata yet"}
        if ta is None or tg is None or tp is None or "position_m" not in pch or "speed_mps" not in pch:
            return {"log": "magnet layer: vehicle accel/gap/position not buffered"}
        sens = md.sensors
        ma = {sens[c].magnet: i for i, c in enumerate(ach) if c in sens and sens[c].magnet}
        mg = {sens[c].magnet: i for i, c in enumerate(gch) if c in sens and sens[c].magnet}
        mags = sorted(set(ma) & set(mg))
        spd = p[:, pch.index("speed_mps")]
        if not mags or np.median(spd) <= 0.1:
            return None
        from types import SimpleNamespace as NS
        lo, hi = max(ta[0], tg[0], tp[0]), min(ta[-1], tg[-1], tp[-1])
        keep = (ta >= lo) & (ta <= hi)
        keep_p = (tp >= lo - 1.0) & (tp <= hi + 1.0)
        fs = 1.0 / float(np.median(np.diff(ta[keep])))
        acc = NS(time_s=ta[keep], data=a[keep], channels=tuple(ach), sample_rate_hz=fs)
        gap = NS(time_s=tg, data=g, channels=tuple(gch), sample_rate_hz=None)
        posd = p[keep_p][:, [pch.index("position_m"), pch.index("speed_mps")]]
        pos = NS(time_s=tp[keep_p], data=posd, channels=("position_m", "speed_mps"), sample_rate_hz=None,
                 channel=lambda n, _d=posd: _d[:, ("position_m", "speed_mps").index(n)])
        pairs = {m: [ach[ma[m]], gch[mg[m]]] for m in mags}
        rec = PassRecording(acc, gap, pos, tuple(mags), None, {"channel_pairs": pairs}, md, "online window")
        line = md.raw["line"]
        logs: list[str] = []
        ev = pass_evidence(rec, cfg, line, magnet_fs_hz=self.magnet_fs_hz, log=logs.append)
        up = self.magnet_layer.fit(cfg, line, [ev])
        t = ta[keep] - ta[keep][0]
        data_used = {"kind": "vehicle window", "t0_s": float(ta[keep][0]), "duration_s": float(t[-1]),
                     "magnets": mags, "irregularity": rec.info["irregularity"]["method"],
                     "irregularity_failure": rec.info["irregularity"].get("reason"),
                     "residual_nrmse": residual_nrmse}
        return {"update": up, "data_used": data_used, "log": "; ".join(logs) or None}

    def accept_magnet_update(self, result: dict | None) -> Publication | None:
        if result is None:
            return None
        if result.get("log"):
            self.log.append(result["log"])
        up = result.get("update")
        if up is None:
            return None
        if not up.nrmse_updated < up.nrmse_nominal:     # "nominal" of the layer = the current gains
            self.log.append(f"magnet update rejected: NRMSE {up.nrmse_updated:.3f} >= {up.nrmse_nominal:.3f}")
            return None
        params = {n: {"value": float(v), "unit": UNITS[n], "std": None if s is None else float(s),
                      "identifiable": bool(ok)} for n, v, s, ok in zip(up.names, up.values, up.std, up.identifiable)}
        fit = {"layer": "magnet", "nrmse_before": up.nrmse_nominal, "nrmse_after": up.nrmse_updated,
               "combinations": [c.to_dict() for c in up.identifiability.combinations if c.identifiable],
               "uncertainty": up.uncertainty, "n_model_evaluations": up.n_model_evaluations}
        return self._accept(params, result["data_used"], fit)
