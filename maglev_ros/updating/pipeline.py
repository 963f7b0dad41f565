"""Two-layer update from recordings (used by ``maglev-ros update`` and the ``updater`` node).

Evidence builders turn contract data into layer targets; ``update_from_bags`` runs the whole
hierarchical update (000 Sec. 4-5); ``public_params`` writes the public ``maglev-params/1`` JSON.

Choices (the paper's text is vague here):

- Modes -> FE modes (``modal_target``): the identified modes of the instrumented span (the span
  named by most guideway sensors) are matched to the span's nominal FE modes at the sensor
  positions from the metadata: left/right sensors of one section are averaged into one shape
  entry; a measured mode is kept when its MPC >= ``min_mpc`` and it matches an FE mode with
  MAC >= ``min_mac`` within +-40 % in frequency (best MAC wins, each FE mode used once). Without
  shapes (one section) the nearest frequency is used.
- Quasi-static deflection (``static_target_from_pass``): the pass's
  /testline/guideway/displacement channel on the instrumented span, low-passed below the first
  mode, against the magnets' static forces of the twin's vehicle (``levitation.build_vehicle``,
  they depend on the vehicle design only, not on the gains) at the measured positions.
- Irregularity for the magnet layer (``pass_evidences``): ``irregularity.twin_input.profile_for_twin``
  (loaded -> unloaded with the twin's predicted deflection), built ONCE per pass with the
  guideway-updated twin and the nominal gains (not per candidate gain set; the gains enter the
  profile only through the dynamic part of the girder deflection). Time high-pass ``highpass_hz``
  1 Hz (a pass needs >= ~5 s of record; the profiler trims 1.5/f_c at both ends). Grid
  ``profile_spacing_m`` 1 cm with the band of a 2 cm grid (shortest wave max(8 cm, 4 v_max / fs)):
  the profiler bins (boxcar) and the twin interpolates linearly, which at 2 cm cost 1.5 % of the
  amplitude of a 0.3 m wave and biased the gains along their weak direction (measured on
  bags/paper_pass: true-gain NRMSE 0.033 -> 0.030 with 1 cm). The acquisition delay of the vehicle
  accel topic relative to the position topic (metadata ``acquisition``, docs/contract-extensions.md)
  is honoured (profile at its true positions, twin output delayed alike); without it the profile
  is shifted by speed x delay, which the twin driven by it reproduces (on paper_pass the true-gain
  NRMSE is 0.0326 without and 0.0330 with it: not a cause of gain bias, but the geometry is right
  only with it). The twin is driven by what the magnets agree on (the coherent gain of
  ``irregularity.denoise``: one rule with the diagnosing twin and the online updater). That alone does not clean the
  shortest waves: on a 9 m/s test pass (band to 112 Hz) the reconstruction carried ~3 um at
  0.08-0.2 m where the true rail has none, coherent over the magnets (0.6), and the twin on it
  predicted 0.12 m/s^2 rms at 50-112 Hz (0.115 denoised) where the magnets measured their noise
  floor, 0.008 (true rail: 0.008); every gain came out unidentifiable (std 40-250 %). The compared
  band therefore ends where the measured accelerations sink into their noise (below).
  Passes over one line share their short waves (``shared_twin_inputs``, as in the diagnosis):
  on a foreign simulator's passes (rail with short stator-pack waves, gap noise 5 um, two
  magnets per pass) the held-out magnet NRMSE of the true gains fell 0.140 -> 0.106 with the rail
  of two passes; a held-out pass (``heldout``) is judged with the rail of every pass.
  If ``profile_for_twin`` raises, the failure is logged and
  recorded in the pass's provenance (``irregularity.reason``) and only then the demoted inertial
  fallback ``magnet_layer.irregularity_from_signals`` is used.
- Compared: each magnet while it is over the valid profile (taper + 1 m margin), band-passed to
  the profile's band cut where the measured accelerations sink into their noise floor
  (``magnet_layer.above_noise_hz``), at <= ``magnet_fs_hz`` (every k-th measured sample after the band-pass).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np
from scipy.signal import butter, sosfiltfilt

from maglev_ros.contract import (TOPIC_GUIDEWAY_ACCEL, TOPIC_GUIDEWAY_DISP, TOPIC_VEHICLE_ACCEL,
                                 TOPIC_VEHICLE_GAP, TOPIC_VEHICLE_POSITION, Metadata)
from maglev_ros.errors import UserError
from maglev_ros.parallel import SERIAL, Executor, one_blas_thread
from maglev_ros.progress import NULL, Progress
from maglev_ros.twin.design import SpanSpec, TwinConfig, line_spans, twin_config_from_metadata, with_guideway
from maglev_ros.updating.guideway_layer import (GuidewayLayer, GuidewayUpdate, ModalTarget, SpanModel,
                                                StaticTarget, mac)
from maglev_ros.updating.magnet_layer import (MagnetLayer, MagnetModel, MagnetUpdate, PassEvidence,
                                              irregularity_from_signals, make_evidence, nrmse)
from maglev_ros.updating.parameters import GUIDEWAY_PARAMS, MAGNET_PARAMS, SYMBOLS, UNITS

PARAMS_SCHEMA = "maglev-params/1"
# twin-node parameter names (OnlineTwin.set_parameters dotted design paths)
TWIN_NAMES = {**{n: f"guideway.{n}" for n in GUIDEWAY_PARAMS}, **{n: f"levitation.{n}" for n in MAGNET_PARAMS},
              "static_current_a": "levitation.static_current_a"}


def _f(x):
    return None if x is None or not math.isfinite(float(x)) else float(x)


def updated_config(config: TwinConfig, gw: GuidewayUpdate | None, mag: MagnetUpdate | None = None) -> TwinConfig:
    from maglev_ros.twin.design import with_levitation
    if gw is not None:
        config = with_guideway(config, **dict(zip(gw.names, gw.values)))
    if mag is not None:
        config = with_levitation(config, **dict(zip(mag.names, mag.values)))
    return config


def public_params(gw: GuidewayUpdate, mag: MagnetUpdate | None, nrmse_override: dict | None = None) -> dict:
    """The ``maglev-params/1`` document. ``magnet_accel_nrmse`` is null without a magnet layer."""
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
    if nrmse_override is not None:
        out_nrmse = {"nominal": float(nrmse_override["nominal"]), "updated": float(nrmse_override["updated"])}
    return {"schema": PARAMS_SCHEMA, "parameters": params, "identifiable_combinations": combos,
            "frequencies_hz": {"measured": list(gw.frequencies_measured_hz), "nominal": list(gw.frequencies_nominal_hz),
                               "updated": list(gw.frequencies_updated_hz)},
            "mac": {"nominal": list(gw.mac_nominal), "updated": list(gw.mac_updated)},
            "magnet_accel_nrmse": out_nrmse}


# ---------------------------------------------------------------------------------------- modes
def instrumented_span(md: Metadata, config: TwinConfig, topic: str = TOPIC_GUIDEWAY_ACCEL) -> SpanSpec:
    """The span carrying most of the vertical guideway sensors of ``topic``."""
    counts: dict[str, int] = {}
    for s in md.sensors_on_topic(topic).values():
        if s.span is not None and s.position_m is not None and s.direction in (None, "vertical"):
            counts[s.span] = counts.get(s.span, 0) + 1
    if not counts:
        raise UserError(f"{md.source}: metadata key sensors: no vertical {topic} sensor with span and position_m "
                        f"(the guideway layer needs sensor positions)")
    sid = max(counts, key=counts.get)
    spans = {s.span_id: s for s in line_spans(md.raw["line"], config)}
    if sid not in spans:
        raise UserError(f"{md.source}: metadata key sensors: span {sid!r} is not in line.spans")
    return spans[sid]


@dataclass(frozen=True)
class MeasuredMode:
    """A mode as the modal stage reports it (SSI-cov ``Mode`` or a ModalEstimate ``ModalMode``)."""
    frequency_hz: float
    std_frequency_hz: float
    mpc: float
    mode_shape: Mapping[str, float]

    @classmethod
    def of(cls, m: Any) -> "MeasuredMode":
        get = (lambda k, d=None: m.get(k, d)) if isinstance(m, Mapping) else (lambda k, d=None: getattr(m, k, d))
        shape = get("mode_shape", {})
        if not isinstance(shape, Mapping):            # ModalMode msg: parallel channels / mode_shape arrays
            shape = dict(zip(list(get("channels", [])), [float(v) for v in shape]))
        sf = get("std_frequency_hz", float("nan"))
        return cls(float(get("frequency_hz")), float("nan") if sf is None else float(sf),
                   float(get("mpc", 1.0) if get("mpc", 1.0) is not None else 1.0), dict(shape))


def modal_target(modes: Sequence[Any], md: Metadata, config: TwinConfig, max_modes: int = 4,
                 min_mpc: float = 0.7, min_mac: float = 0.6, freq_tol: float = 0.4) -> tuple[SpanSpec, ModalTarget, dict]:
    """Measured modes -> (instrumented span, ModalTarget, info) (see module docstring)."""
    span = instrumented_span(md, config)
    sens = {k: s for k, s in md.sensors_on_topic(TOPIC_GUIDEWAY_ACCEL).items()
            if s.span == span.span_id and s.position_m is not None and s.direction in (None, "vertical")}
    mm = [MeasuredMode.of(m) for m in modes]
    chans = [c for c in sens if all(c in m.mode_shape for m in mm)] if mm else []
    xs = np.array(sorted({round(sens[c].position_m, 6) for c in chans}))
    groups = [[c for c in chans if round(sens[c].position_m, 6) == x] for x in xs]

    def shape_of(m):
        return np.array([np.mean([m.mode_shape[c] for c in g]) for g in groups])

    model = SpanModel(span, n_modes=max_modes + 2)
    f_fe, s_fe = model.modes([getattr(span.props, n) for n in GUIDEWAY_PARAMS], xs if xs.size else None)
    use_shapes = xs.size >= 2
    cand = [i for i, m in enumerate(mm) if m.mpc >= min_mpc and np.isfinite(m.frequency_hz) and m.frequency_hz > 0]
    chosen: dict[int, tuple[int, float]] = {}
    for j in range(f_fe.size):
        best, best_score = None, -np.inf
        for i in cand:
            if i in [c[0] for c in chosen.values()]:
                continue
            if abs(mm[i].frequency_hz / f_fe[j] - 1) > freq_tol:
                continue
            if use_shapes:
                score = mac(shape_of(mm[i]), s_fe[j])
                if score < min_mac:
                    continue
            else:
                score = -abs(np.log(mm[i].frequency_hz / f_fe[j]))
            if score > best_score:
                best, best_score = i, score
        if best is not None:
            chosen[j] = (best, float(best_score))
        if len(chosen) >= max_modes:
            break
    if not chosen:
        raise UserError(f"{md.source}: no identified mode of span {span.span_id} matches the span's FE modes "
                        f"(checked {len(mm)} modes; expected MPC >= {min_mpc}, MAC >= {min_mac}, frequency within "
                        f"+-{100 * freq_tol:.0f} % of {', '.join(f'{f:.1f}' for f in f_fe[:max_modes])} Hz)")
    order = sorted(chosen, key=lambda j: mm[chosen[j][0]].frequency_hz)
    sel = [mm[chosen[j][0]] for j in order]
    tgt = ModalTarget(np.array([m.frequency_hz for m in sel]), np.array([m.std_frequency_hz for m in sel]),
                      np.array([shape_of(m) for m in sel]) if use_shapes else None, xs if use_shapes else None)
    info = {"span": span.span_id, "sensor_x_m": xs.tolist(), "channels": [list(g) for g in groups],
            "matched_fe_modes": [int(j) + 1 for j in order], "n_identified": len(mm)}
    return span, tgt, info


def identify_ambient(path: str | Path, fmax_hz: float | None = None, block_rows: int = 40,
                     max_order: int = 60) -> tuple[Metadata, Any, dict]:
    """SSI-cov modes of an ambient bag's /testline/guideway/accel: (metadata, ModalResult, info).
    ``path``: a bag, or a :class:`~maglev_ros.bag_memory.MemoryBag` (a recording a node received)."""
    from maglev_ros.bag_memory import open_reader, source_name
    from maglev_ros.modal.ssi_cov import SSICov
    reader, path = open_reader(path), source_name(path)
    with reader as r:
        md = r.metadata
        if md is None:
            raise UserError(f"{path}: no /testline/metadata; the updater needs sensor positions and the design")
        if md.run_kind != "ambient":
            raise UserError(f"{path}: metadata run.kind is {md.run_kind!r}; --ambient expects an ambient recording")
        if TOPIC_GUIDEWAY_ACCEL not in r.topics:
            raise UserError(f"{path}: topic {TOPIC_GUIDEWAY_ACCEL} not in bag (topics: {', '.join(sorted(r.topics)) or 'none'})")
        read, health = r.read_checked(TOPIC_GUIDEWAY_ACCEL, sensor_map=True)
        cd = read[TOPIC_GUIDEWAY_ACCEL]
    fs = float(cd.sample_rate_hz)
    fmax = min(0.4 * fs, 250.0) if fmax_hz is None else float(fmax_hz)
    est = SSICov(block_rows=block_rows, orders=range(2, max_order + 1, 2),
                 decimate_to_hz=3.3 * fmax if fs > 4.0 * fmax else None, freq_range_hz=(1.0, fmax))
    res = est.fit(np.asarray(cd.data, float), fs, cd.channels)
    return md, res, {"bag": str(path), "fs_hz": fs, "fmax_hz": fmax, "duration_s": float(cd.time_s[-1] - cd.time_s[0]),
                     "channels": list(cd.channels), "health": health.to_dict()}


# ---------------------------------------------------------------------------------------- passes
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


def static_magnet_forces(config: TwinConfig) -> np.ndarray:
    from maglev_ros.twin.levitation import build_vehicle
    return np.asarray(build_vehicle(config).levitation.static_force_n, float)


def _fallback_irregularity(t, accel, gap, position_m, speed_mps, md: Metadata, magnets, config: TwinConfig, line,
                           deflection_iterations: int = 2, lowpass_hz: float | None = 60.0):
    """(x, r) of the demoted inertial fallback (``magnet_layer.irregularity_from_signals``)."""
    from maglev_ros.twin.guideway import Guideway
    offs = [md.magnet_offsets_m[m - 1] for m in magnets]
    num = config.numerics
    modal = Guideway(line_spans(line, config), num.n_elements_per_span).modes(num.mode_cutoff_hz, num.min_modes_per_span)
    F = static_magnet_forces(config)[[m - 1 for m in magnets]]
    g0 = md.nominal_gap_m if md.nominal_gap_m is not None else config.levitation.nominal_gap_m
    x, r = irregularity_from_signals(t, accel, gap, position_m, offs, g0, modal=modal, magnet_force_n=F,
                                     lowpass_hz=lowpass_hz)
    for _ in range(max(0, int(deflection_iterations))):
        w = twin_rail_deflection(config, line, t, position_m, speed_mps, (x, r), magnets)
        x, r = irregularity_from_signals(t, accel, gap, position_m, offs, g0, deflection_m=w, lowpass_hz=lowpass_hz)
    return x, r


def twin_rail_deflection(config: TwinConfig, line, t, position_m, speed_mps, irregularity, magnets) -> np.ndarray:
    """Girder deflection (n, len(magnets)) under the measured magnets predicted by the coupled twin
    driven by ``irregularity`` along the measured position: w = gap - g0 - r(x_k) + z_k."""
    from maglev_ros.twin.coupling import as_irregularity, simulate_pass
    t = np.asarray(t, float)
    fs = 1.0 / float(np.median(np.diff(t)))
    dt = 1.0 / fs
    tt = np.concatenate([[0.0], t - t[0] + dt])
    vv = np.concatenate([[speed_mps[0]], speed_mps])
    res = simulate_pass(config, line, speed_mps=(tt, vv), irregularity=irregularity,
                        duration_s=float(tt[-1]) + dt, fs_out_hz=fs,
                        start_position_m=float(position_m[0] - speed_mps[0] * dt))
    irr = as_irregularity(irregularity)
    offs = np.asarray(config.vehicle.magnet_offsets_m, float)
    out = []
    for m in magnets:
        k = m - 1
        z = res.vehicle_disp_m[:, res.dof_names.index(f"magnet{m}.z")]
        w = res.magnet_gap_m[:, k] - config.levitation.nominal_gap_m - irr.elevation(res.position_m + offs[k]) + z
        out.append(np.interp(t - t[0] + dt, res.time_s, w))
    return np.stack(out, axis=1)


def _runs(mask: np.ndarray, x: np.ndarray) -> list[tuple[float, float]]:
    """(first, last) x of each run of True in ``mask`` (the valid stretches of a profile)."""
    m = np.concatenate([[False], np.asarray(mask, bool), [False]])
    d = np.diff(m.astype(np.int8))
    return [(float(x[i0]), float(x[i1 - 1])) for i0, i1 in zip(np.flatnonzero(d == 1), np.flatnonzero(d == -1))]


@dataclass(frozen=True)
class PassRecording:
    """What a pass bag gives the updater: the vehicle channels, optional static target, info."""
    accel: Any
    gap: Any
    position: Any
    magnets: tuple[int, ...]
    static: StaticTarget | None
    info: dict
    md: Metadata
    label: str = ""


def pass_evidence(rec: PassRecording, config: TwinConfig, line=None, *, magnet_fs_hz: float = 500.0,
                  max_window_s: float | None = None, highpass_hz: float = 1.0, skip_s: float = 0.3,
                  use_twin_input: bool = True, profile_spacing_m: float = 0.01, log=None) -> PassEvidence:
    """Magnet-layer evidence of one pass, with its own irregularity (:func:`pass_evidences`)."""
    return pass_evidences([rec], config, line, magnet_fs_hz=magnet_fs_hz, max_window_s=max_window_s,
                          highpass_hz=highpass_hz, skip_s=skip_s, use_twin_input=use_twin_input,
                          profile_spacing_m=profile_spacing_m, log=log)[0]


def pass_evidences(recs: Sequence[PassRecording], config: TwinConfig, line=None, *, magnet_fs_hz: float = 500.0,
                   max_window_s: float | None = None, highpass_hz: float = 1.0, skip_s: float = 0.3,
                   use_twin_input: bool = True, profile_spacing_m: float = 0.01, share: bool = True,
                   rail_only: Sequence[PassRecording] = (), log=None) -> list[PassEvidence]:
    """Magnet-layer evidence of passes over one line with the irregularity for the twin ``config``
    (the guideway-updated twin; built once, see module docstring). With two or more passes their
    short waves are shared (:func:`~maglev_ros.irregularity.twin_input.shared_twin_inputs`: the
    same rail seen by every pass's magnets: less gap noise in the twin's input). ``rail_only``:
    passes that only measure the rail for ``recs`` (a held-out pass judged with the rail of every
    pass, its accelerations never fitted). Records the method
    in each ``rec.info["irregularity"]``; a failure of ``profile_for_twin`` is logged and recorded
    there before that pass's inertial fallback is used."""
    from maglev_ros.irregularity.twin_input import shared_twin_inputs
    say = log or (lambda s: None)
    line = recs[0].md.raw["line"] if line is None else line
    kw = dict(highpass_hz=highpass_hz, profile_spacing_m=profile_spacing_m, say=say)
    if use_twin_input:
        _measure_sensor_delay([*recs, *rail_only], highpass_hz, say)
    tis = [_twin_input(r, config, line, **kw) if use_twin_input else (None, "use_twin_input=False") for r in recs]
    extra = [_twin_input(r, config, line, **kw)[0] for r in rail_only] if use_twin_input else []
    got = [ti for ti, _ in tis if ti is not None] + [ti for ti in extra if ti is not None]
    inputs, shared = (None, None)
    if share and len(got) >= 2:
        inputs, shared = shared_twin_inputs(got)
        if not shared.used:
            say(f"passes: short waves not shared ({shared.reason})")
    out, k = [], 0
    for rec, (ti, reason) in zip(recs, tis):
        if ti is None:
            out.append(_fallback_evidence(rec, config, line, reason, magnet_fs_hz, max_window_s, skip_s))
            continue
        x_ir, r_ir, g = ti.denoised_twin_input()
        if shared is not None and shared.used:
            x_ir, r_ir = inputs[k]
        k += 1
        rec.info["irregularity"] = {"method": "irregularity.twin_input.profile_for_twin",
                                    "config": "guideway-updated twin, nominal gains", **ti.to_dict(),
                                    "denoise": None if g is None else g.to_dict(),
                                    "shared": None if shared is None else shared.to_dict()}
        out.append(_evidence(rec, ti, (x_ir, r_ir), magnet_fs_hz, max_window_s, skip_s))
    return out


def _measure_sensor_delay(recs: Sequence[PassRecording], highpass_hz: float, say) -> None:
    """With no delay stated, the delay of the vehicle sensors behind the position that two or more
    passes at different speeds measure (:mod:`maglev_ros.irregularity.sensor_delay`), into each
    ``rec.info["sensor_delay"]`` (and ``"sensor_delay_s"`` when applicable)."""
    from maglev_ros.irregularity.sensor_delay import measure_sensor_delay, stated_sensor_delay_s
    if len(recs) < 2 or any(stated_sensor_delay_s(r.md) is not None for r in recs):
        return
    est = measure_sensor_delay([(r.accel, r.gap, r.position, r.md, r.info["channel_pairs"], None, r.label)
                                for r in recs], highpass_hz)
    for r in recs:
        r.info["sensor_delay"] = est.to_dict()
        if est.applicable:
            r.info["sensor_delay_s"] = float(est.delay_s)
    if est.applicable:
        say(f"passes: vehicle sensors {est.delay_s * 1e3:.2f} ms behind the position (measured between the "
            "passes, none stated)")


def _signals(rec: PassRecording):
    from maglev_ros.irregularity.sensor_delay import stated_sensor_delay_s
    acc = rec.accel
    t = np.asarray(acc.time_s, float)
    a = np.asarray(acc.data, float)[:, [acc.channels.index(rec.info["channel_pairs"][m][0]) for m in rec.magnets]]
    stated = stated_sensor_delay_s(rec.md)
    tau = stated if stated is not None else float(rec.info.get("sensor_delay_s", 0.0))
    return t, a, tau


def _twin_input(rec: PassRecording, config: TwinConfig, line, *, highpass_hz: float, profile_spacing_m: float, say):
    """(the pass's TwinIrregularity or None, why not)."""
    from maglev_ros.irregularity.twin_input import profile_for_twin
    acc, gap, pos = rec.accel, rec.gap, rec.position
    t, _, tau = _signals(rec)
    v_pos = np.interp(t, pos.time_s, pos.channel("speed_mps"))
    fs_a = float(acc.sample_rate_hz or 1.0 / np.median(np.diff(t)))
    lam_min = max(0.08, 4.0 * float(np.nanmax(np.abs(v_pos))) / fs_a)
    try:
        return profile_for_twin(acc, gap, pos, rec.md, config, line, highpass_hz=highpass_hz,
                                channel_pairs=rec.info["channel_pairs"], spacing_m=profile_spacing_m,
                                min_wavelength_m=lam_min, sensor_delay_s=tau), None
    except (UserError, ValueError, np.linalg.LinAlgError) as exc:
        reason = f"{type(exc).__name__}: {exc}"
        say(f"{rec.label}: irregularity.twin_input.profile_for_twin failed ({reason}); using the inertial fallback")
        return None, reason


def _evidence(rec: PassRecording, ti, xr, magnet_fs_hz, max_window_s, skip_s) -> PassEvidence:
    pos = rec.position
    t, a, tau = _signals(rec)
    fs = float(rec.accel.sample_rate_hz or 1.0 / np.median(np.diff(t)))
    v_max = float(np.nanmax(np.abs(np.interp(t, pos.time_s, pos.channel("speed_mps")))))
    band = (ti.highpass_hz, min(v_max / ti.min_wavelength_m, 0.45 * fs))
    return make_evidence(t, a, list(rec.magnets), pos.time_s, pos.channel("position_m"), pos.channel("speed_mps"),
                         xr, rec.md.magnet_offsets_m, valid_range_m=_runs(ti.valid, ti.position_m),
                         band_hz=band, model_fs_hz=magnet_fs_hz, skip_s=skip_s,
                         margin_m=ti.taper_m + 1.0, sensor_delay_s=tau, max_window_s=max_window_s,
                         label=rec.label, irregularity_method="profile_for_twin")


def _fallback_evidence(rec: PassRecording, config: TwinConfig, line, reason, magnet_fs_hz, max_window_s,
                       skip_s) -> PassEvidence:
    gap, pos = rec.gap, rec.position
    t, a, _ = _signals(rec)
    mags = list(rec.magnets)
    cg = [gap.channels.index(rec.info["channel_pairs"][m][1]) for m in mags]
    x_pos = np.interp(t, pos.time_s, pos.channel("position_m"))
    v_pos = np.interp(t, pos.time_s, pos.channel("speed_mps"))
    g = np.stack([np.interp(t, gap.time_s, np.asarray(gap.data, float)[:, j]) for j in cg], axis=1)
    xr, rr = _fallback_irregularity(t - t[0], a, g, x_pos, v_pos, rec.md, mags, config, line)
    rec.info["irregularity"] = {"method": "fallback: magnet_layer.irregularity_from_signals (girder deflection "
                                          "removed: quasi-static, then 2 twin-predicted iterations)",
                                "reason": reason or "use_twin_input=False"}
    return make_evidence(t, a, mags, pos.time_s, pos.channel("position_m"), pos.channel("speed_mps"), (xr, rr),
                         rec.md.magnet_offsets_m, band_hz=(0.5, 60.0), model_fs_hz=magnet_fs_hz, skip_s=skip_s,
                         margin_m=0.5, max_window_s=max_window_s, label=rec.label, irregularity_method="fallback")


def read_pass(path: str | Path, config: TwinConfig | None = None) -> PassRecording:
    """Read a pass bag: vehicle accel/gap/position, the magnets with both channels, and the
    quasi-static deflection target when the bag has /testline/guideway/displacement on the
    instrumented span (``config``: the twin whose static magnet forces are used; default nominal).
    ``path``: a bag, or a :class:`~maglev_ros.bag_memory.MemoryBag` (a recording a node received)."""
    from maglev_ros.bag_memory import open_reader, source_name
    from maglev_ros.irregularity.profile import magnet_channel_pairs
    reader, path = open_reader(path), Path(source_name(path))
    with reader as r:
        md = r.metadata
        if md is None:
            raise UserError(f"{path}: no /testline/metadata; the updater needs the magnet offsets and the design")
        if md.run_kind != "pass":
            raise UserError(f"{path}: metadata run.kind is {md.run_kind!r}; --pass expects a vehicle pass recording")
        for tp in (TOPIC_VEHICLE_ACCEL, TOPIC_VEHICLE_GAP, TOPIC_VEHICLE_POSITION):
            if tp not in r.topics:
                raise UserError(f"{path}: topic {tp} not in bag; the magnet layer needs magnet accelerations, gaps "
                                f"and the vehicle position")
        read, health = r.read_checked([TOPIC_VEHICLE_ACCEL, TOPIC_VEHICLE_GAP, TOPIC_VEHICLE_POSITION]
                                      + ([TOPIC_GUIDEWAY_DISP] if TOPIC_GUIDEWAY_DISP in r.topics else []),
                                      sensor_map=True)
        acc, gap, pos = (read[tp] for tp in (TOPIC_VEHICLE_ACCEL, TOPIC_VEHICLE_GAP, TOPIC_VEHICLE_POSITION))
        disp = read.get(TOPIC_GUIDEWAY_DISP)
        if disp is not None and not disp.channels:      # every displacement channel left out
            disp = None
    cfg = config if config is not None else twin_config_from_metadata(md.raw)
    for ch in ("position_m", "speed_mps"):
        if ch not in pos.channels:
            raise UserError(f"{path}: topic {TOPIC_VEHICLE_POSITION}: channel {ch} missing (channels: {', '.join(pos.channels)})")
    pairs = magnet_channel_pairs(md, tuple(acc.channels), tuple(gap.channels)) or {}
    mags = sorted(pairs)
    if not mags:
        raise UserError(f"{path}: no magnet has both an acceleration ({TOPIC_VEHICLE_ACCEL}) and a gap "
                        f"({TOPIC_VEHICLE_GAP}) channel with metadata sensors.<id>.magnet")
    if max(mags) > len(md.magnet_offsets_m):
        raise UserError(f"{path}: metadata key vehicle.magnet_offsets_m: {len(md.magnet_offsets_m)} offsets but magnet {max(mags)} is recorded")
    sens = md.sensors
    t0 = float(acc.time_s[0])
    info = {"bag": str(path), "magnets": mags, "fs_hz": float(acc.sample_rate_hz),
            "duration_s": float(acc.time_s[-1] - t0), "channel_pairs": {m: list(pairs[m]) for m in mags},
            "health": health.to_dict()}
    static = None
    if disp is not None:
        try:
            span = instrumented_span(md, cfg)
        except UserError:
            span = None
        dch = [c for c in disp.channels if c in sens and sens[c].position_m is not None
               and span is not None and sens[c].span == span.span_id]
        if dch:
            mid = span.start_m + 0.5 * span.length_m
            c = min(dch, key=lambda c: abs(sens[c].position_m - mid))
            static = static_target(disp.time_s - t0, disp.channel(c), pos.time_s - t0, pos.channel("position_m"),
                                   md.magnet_offsets_m, static_magnet_forces(cfg), sens[c].position_m)
            info["static_displacement_channel"] = c
    return PassRecording(acc, gap, pos, tuple(mags), static, info, md, path.name)


def magnet_nrmse(config: TwinConfig, line, passes: Sequence[PassEvidence], dt_max_s: float | None = 2e-3
                 ) -> tuple[float, list]:
    """Pooled NRMSE of the twin's compared, band-passed magnet accelerations (config's gains) over
    passes, and the per-pass (time, measured, predicted) with NaN where not compared (plots)."""
    meas, pred, series = [], [], []
    lev = config.levitation
    for ev in passes:
        m = MagnetModel(config, line, ev, dt_max_s)
        P = m.predict_full([getattr(lev, n) for n in MAGNET_PARAMS])
        meas.append(ev.accel_mps2[ev.compare])
        pred.append(P[ev.compare])
        series.append((ev.time_s - ev.time_s[0], np.where(ev.compare, ev.accel_mps2, np.nan),
                       np.where(ev.compare, P, np.nan)))
    return nrmse(np.concatenate(pred), np.concatenate(meas)), series


def _merge_static(targets: Sequence[StaticTarget]) -> StaticTarget | None:
    targets = [s for s in targets if s is not None]
    if not targets:
        return None
    if len({round(s.sensor_x_m, 6) for s in targets}) > 1:
        targets = targets[:1]
    return StaticTarget(targets[0].sensor_x_m, np.vstack([s.magnet_x_m for s in targets]),
                        targets[0].magnet_force_n, np.concatenate([s.displacement_m for s in targets]),
                        targets[0].std_rel)


@dataclass(frozen=True)
class TwoLayerUpdate:
    """Result of ``update_from_bags``: both layers, the public document and provenance."""
    guideway: GuidewayUpdate
    magnet: MagnetUpdate | None
    document: dict
    provenance: dict
    nominal_config: TwinConfig
    updated_config: TwinConfig
    modal_result: Any = None
    magnet_series: dict = field(default_factory=dict)     # label -> (t, measured, nominal, updated, magnets)
    heldout_series: dict = field(default_factory=dict)    # the same for passes never fitted

    def to_dict(self) -> dict:
        return self.document


def update_layers(samples: int = 60, polish_evals: int = 8, swarm: Sequence[int] | None = None,
                  seed: int = 0) -> tuple[GuidewayLayer, MagnetLayer]:
    """The two layers as ``maglev-ros update`` sets them from its options (``--samples``,
    ``--polish-evals``, ``--swarm PARTICLES ITERATIONS``, ``--seed``): one place, so the updater
    node's recording-end update runs the verb's settings."""
    sw = {} if not swarm else {"n_particles": int(swarm[0]), "n_iterations": int(swarm[1])}
    return (GuidewayLayer(seed=seed, **sw),
            MagnetLayer(n_samples=samples, polish_max_nfev=polish_evals, seed=seed, **sw))


def update_from_bags(ambient: str | Path, passes: Sequence[str | Path] = (), *,
                     heldout: Sequence[str | Path] = (), guideway_layer: GuidewayLayer | None = None,
                     magnet_layer: MagnetLayer | None = None,
                     magnet_fs_hz: float = 500.0, max_window_s: float | None = None, max_modes: int = 4,
                     use_twin_input: bool = True, highpass_hz: float = 1.0, log=None,
                     progress: Progress = NULL, executor: Executor = SERIAL) -> TwoLayerUpdate:
    """Ambient bag -> modes -> guideway layer [+ static deflection of the passes] -> irregularity of
    each pass for the guideway-updated twin -> magnet layer on the passes. Returns the public
    document and the details (provenance says how each pass's irregularity was obtained).
    Recordings are bag paths or :class:`~maglev_ros.bag_memory.MemoryBag` (what the ``updater``
    node received). ``heldout``: passes never fitted, on which the nominal and the updated twin's
    magnet accelerations are judged (``provenance["heldout"]``). ``log``: one-line messages
    (default: ``progress.note``). ``executor``: where
    the magnet layer's surrogate simulations run (:mod:`maglev_ros.parallel`; the same result).
    BLAS runs at one thread throughout (sample bags, shared 2-core machine: 62 s wall, 25 s CPU
    against 115 s, 30 s at its default two threads; the parameters then differ by 1e-7-1e-5
    relative, floating-point order, so every executor runs at one thread too)."""
    with one_blas_thread():
        return _update_from_bags(ambient, passes, heldout=heldout, guideway_layer=guideway_layer, magnet_layer=magnet_layer,
                                 magnet_fs_hz=magnet_fs_hz, max_window_s=max_window_s, max_modes=max_modes,
                                 use_twin_input=use_twin_input, highpass_hz=highpass_hz, log=log,
                                 progress=progress, executor=executor)


def _plot_series(evs: Sequence[PassEvidence], s_nom, s_up) -> dict:
    """label -> (t, measured, nominal, updated, magnets) of each pass, from :func:`magnet_nrmse`'s series."""
    return {ev.label: (a[0], a[1], a[2], b[2], list(ev.magnets)) for ev, a, b in zip(evs, s_nom, s_up)}


def _update_from_bags(ambient, passes, *, heldout, guideway_layer, magnet_layer, magnet_fs_hz, max_window_s, max_modes,
                      use_twin_input, highpass_hz, log, progress, executor) -> TwoLayerUpdate:
    from maglev_ros.bag_memory import same_source, source_name
    t_start = time.perf_counter()
    say = log or progress.note
    for p in passes:                  # cheap input checks before the SSI of the ambient record
        if same_source(p, ambient):
            raise UserError(f"{p}: the same bag is given as --ambient and --pass")
    for h in heldout:
        if same_source(h, ambient) or any(same_source(h, p) for p in passes):
            raise UserError(f"{h}: a held-out pass must be a bag not given as --ambient or --pass")
    if heldout and not passes:
        raise UserError(f"{heldout[0]}: a held-out pass needs at least one --pass to update the magnet layer on")
    progress.stage("guideway modes of the ambient recording (SSI-cov)")
    md_a, modal_res, amb_info = identify_ambient(ambient)
    cfg0 = twin_config_from_metadata(md_a.raw)
    span, target, tinfo = modal_target(modal_res.modes, md_a, cfg0, max_modes)
    say(f"ambient: {len(modal_res.modes)} modes identified, {target.n_modes} matched to FE modes of span {span.span_id}")
    recs = []
    progress.stage("read the passes", total=len(passes))
    for p in progress.steps(passes, source_name):
        if same_source(p, ambient):
            raise UserError(f"{p}: the same bag is given as --ambient and --pass")
        rec = read_pass(p, cfg0)
        if rec.md.vehicle.get("magnet_offsets_m") is None:
            raise UserError(f"{p}: metadata key vehicle.magnet_offsets_m: missing")
        recs.append(rec)
    held = [read_pass(h, cfg0) for h in heldout]
    static = _merge_static([r.static for r in recs])
    gl = guideway_layer or GuidewayLayer()
    progress.stage("guideway layer (E, rho, kb)")
    gw = gl.fit(span, target, static)
    say(f"guideway layer: {gw.n_model_evaluations} model evaluations, {gw.wall_time_s:.1f} s")
    cfg_g = updated_config(cfg0 if not recs else twin_config_from_metadata(recs[0].md.raw), gw)
    mag = None
    series, held_series = {}, {}
    nrmse_doc = heldout_doc = None
    if recs:
        line = recs[0].md.raw["line"]
        ml = magnet_layer or MagnetLayer()
        # irregularity with the UPDATED guideway (its deflection is what is removed), nominal gains
        t_irr = time.perf_counter()
        progress.stage("irregularity of each pass (updated guideway)", total=len(recs))
        ekw = dict(magnet_fs_hz=magnet_fs_hz, max_window_s=max_window_s, highpass_hz=highpass_hz,
                   use_twin_input=use_twin_input, log=say)
        evs = pass_evidences(recs, cfg_g, line, **ekw)
        progress.advance(len(recs))
        for r, ev in zip(recs, evs):
            say(f"{r.label}: irregularity by {r.info['irregularity']['method']}; compared "
                f"{', '.join(f'{s:.1f}' for s in ev.compared_s)} s per magnet in {ev.band_hz[0]:.2g}-"
                f"{ev.band_hz[1]:.3g} Hz")
        t_irr = time.perf_counter() - t_irr
        mag = ml.fit(cfg_g, line, evs, progress=progress, executor=executor)
        say(f"magnet layer: {mag.n_model_evaluations} coupled simulations, {mag.wall_time_s:.1f} s")
        progress.stage("magnet accelerations, nominal and updated twin", total=2)
        cfg_nom = twin_config_from_metadata(recs[0].md.raw)
        e_nom, s_nom = magnet_nrmse(cfg_nom, line, evs, ml.dt_max_s)
        progress.advance(note="nominal")
        cfg_up = updated_config(cfg_g, None, mag)
        e_up, s_up = magnet_nrmse(cfg_up, line, evs, ml.dt_max_s)
        progress.advance(note="updated")
        nrmse_doc = {"nominal": e_nom, "updated": e_up}
        series = _plot_series(evs, s_nom, s_up)
        if held:
            # judged with the rail every pass measured (training and held-out), never fitted to
            hevs = pass_evidences(held, cfg_g, line, rail_only=recs, **ekw)
            h_nom, hs_nom = magnet_nrmse(cfg_nom, line, hevs, ml.dt_max_s)
            h_up, hs_up = magnet_nrmse(cfg_up, line, hevs, ml.dt_max_s)
            held_series = _plot_series(hevs, hs_nom, hs_up)
            heldout_doc = {"passes": [r.label for r in held], "nominal": h_nom, "updated": h_up,
                           "irregularity": [r.info["irregularity"].get("method") for r in held]}
            say(f"held-out magnet accelerations: NRMSE nominal {h_nom:.3f}, updated {h_up:.3f} "
                f"({', '.join(r.label for r in held)})")
    else:
        cfg_up = cfg_g
        t_irr = 0.0
    doc = public_params(gw, mag, nrmse_doc)
    prov = {"ambient": amb_info | {"modes": tinfo}, "passes": [r.info for r in recs],
            "guideway": {"n_model_evaluations": gw.n_model_evaluations, "wall_time_s": gw.wall_time_s,
                         "used_static": gw.used_static, "surrogate_score": gw.surrogate_score},
            "irregularity_wall_time_s": t_irr,
            "heldout": heldout_doc,
            "magnet": None if mag is None else {"n_model_evaluations": mag.n_model_evaluations,
                                                "wall_time_s": mag.wall_time_s, "uncertainty": mag.uncertainty,
                                                "surrogate_score": mag.surrogate_score,
                                                "nrmse_fit": {"nominal": mag.nrmse_nominal, "updated": mag.nrmse_updated}},
            "wall_time_s": time.perf_counter() - t_start,
            # the sensor-health check of every bag (maglev-params/1 itself has a fixed key set)
            "health": [amb_info["health"], *(r.info["health"] for r in recs)]}
    return TwoLayerUpdate(gw, mag, doc, prov, cfg0, cfg_up, modal_res, series, held_series)
