"""Two-layer update from recordings (used by ``maglev-ros update`` and the ``updater`` node).

Evidence builders turn contract data into layer targets; ``public_params`` writes the public
``maglev-params/1`` JSON.
"""
from __future__ import annotations

import math
from dataclasses import replace
from typing import Sequence

import numpy as np
from scipy.signal import butter, sosfiltfilt

from maglev_ros.errors import UserError
from maglev_ros.twin.design import TwinConfig, with_guideway
from maglev_ros.updating.guideway_layer import GuidewayUpdate, ModalTarget, StaticTarget
from maglev_ros.updating.magnet_layer import MagnetUpdate, PassEvidence, irregularity_from_signals
from maglev_ros.updating.parameters import UNITS, SYMBOLS

PARAMS_SCHEMA = "maglev-params/1"


def _f(x):
    return None if x is None or not math.isfinite(float(x)) else float(x)


def updated_config(config: TwinConfig, gw: GuidewayUpdate | None, mag: MagnetUpdate | None = None) -> TwinConfig:
    from maglev_ros.twin.design import with_levitation
    if gw is not None:
        config = with_guideway(config, **dict(zip(gw.names, gw.values)))
    if mag is not None:
        config = with_levitation(config, **dict(zip(mag.names, mag.values)))
    return config


def public_params(gw: GuidewayUpdate, mag: MagnetUpdate | None) -> dict:
    params, combos = {}, []
    for n, v, s, ok in zip(gw.names, gw.values, gw.std, gw.identifiable):
        params[n] = {"value": float(v), "unit": UNITS[n], "std": _f(s), "identifiable": bool(ok)}
    combos += [c.to_dict() for c in gw.identifiability.combinations if c.identifiable]
    out_nrmse = None
    if mag is not None:
        for n, v, s, ok in zip(mag.names, mag.values, mag.std, mag.identifiable):
            params[n] = {"value": float(v), "unit": UNITS[n], "std": _f(s), "identifiable": bool(ok)}
        params["static_current_a"] = {"value": float(mag.static_current_a), "unit": "A", "std": None,
                                      "identifiable": False}
        combos += [c.to_dict() for c in mag.identifiability.combinations if c.identifiable]
        out_nrmse = {"nominal": float(mag.nrmse_nominal), "updated": float(mag.nrmse_updated)}
    return {"schema": PARAMS_SCHEMA, "parameters": params, "identifiable_combinations": combos,
            "frequencies_hz": {"measured": list(gw.frequencies_measured_hz), "nominal": list(gw.frequencies_nominal_hz),
                               "updated": list(gw.frequencies_updated_hz)},
            "mac": {"nominal": list(gw.mac_nominal), "updated": list(gw.mac_updated)},
            "magnet_accel_nrmse": out_nrmse}


def static_target(disp_time_s, disp_m, pos_time_s, position_m, magnet_offsets_m, magnet_force_n, sensor_x_m,
                  lowpass_hz: float = 5.0) -> StaticTarget:
    """Quasi-static deflection evidence: the displacement low-passed (zero-phase Butterworth, 4th order)
    below the first bending mode, with the magnet positions at the displacement sample times."""
    t = np.asarray(disp_time_s, float)
    fs = 1.0 / float(np.median(np.diff(t)))
    sos = butter(4, min(lowpass_hz, 0.4 * fs), fs=fs, output="sos")
    d = sosfiltfilt(sos, np.asarray(disp_m, float))
    X = np.interp(t, pos_time_s, position_m)[:, None] + np.asarray(magnet_offsets_m, float)[None, :]
    step = max(1, int(fs / (4 * lowpass_hz)))
    return StaticTarget(float(sensor_x_m), X[::step], np.asarray(magnet_force_n, float), d[::step])


def pass_evidence(accel_time_s, accel_mps2, gap_time_s, gap_m, pos_time_s, position_m, speed_mps,
                  magnet_offsets_m, nominal_gap_m, magnets: Sequence[int], t_start_s: float | None = None,
                  window_s: float | None = None, modal=None, magnet_force_n=None, label: str = "") -> PassEvidence:
    """PassEvidence from measured channels (magnets 1-based, accel/gap columns in that order)."""
    t = np.asarray(accel_time_s, float)
    a = np.atleast_2d(np.asarray(accel_mps2, float))
    g = np.stack([np.interp(t, gap_time_s, col) for col in np.atleast_2d(np.asarray(gap_m, float)).T], axis=1)
    pos = np.interp(t, pos_time_s, position_m)
    spd = np.interp(t, pos_time_s, speed_mps)
    offs = [magnet_offsets_m[m - 1] for m in magnets]
    xg, rg = irregularity_from_signals(t, a, g, pos, offs, nominal_gap_m, modal=modal,
                                       magnet_force_n=None if magnet_force_n is None else np.asarray(magnet_force_n)[[m - 1 for m in magnets]])
    t0 = t[0] if t_start_s is None else float(t_start_s)
    sel = t >= t0
    if window_s is not None:
        sel &= t <= t0 + window_s
    if sel.sum() < 20:
        raise UserError(f"pass {label}: fewer than 20 magnet acceleration samples in the selected window")
    ts, dt = t[sel], float(np.median(np.diff(t)))
    rel = ts - ts[0] + dt
    return PassEvidence(rel, a[sel], tuple(magnets), np.concatenate([[0.0], rel]),
                        np.concatenate([[spd[sel][0]], spd[sel]]), float(pos[sel][0] - spd[sel][0] * dt), xg, rg, label)
