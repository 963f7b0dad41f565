"""Test-line simulator: a scenario (YAML) -> a contract bag, plus the hidden truth beside it.

``simulate(scenario, out_bag)`` runs the coupled twin (``coupling.simulate_pass``) for a vehicle
pass, or a modal superposition of the guideway under broadband forces for an ambient record,
passes every channel through the instrument chain (``sensors.InstrumentChain``: gain/offset,
causal anti-alias filter at an oversampled internal rate, decimation, white + 1/f noise) and
writes a rosbag2 bag that follows docs/contract/RECORDING.md:

- topics /testline/metadata, /testline/guideway/accel, /testline/guideway/displacement (pass),
  /testline/vehicle/{accel,gap,position} (pass); blocks of ``block_s``; header stamps
  ``start_stamp_ns + k / rate`` (integer ns); every channel is listed in metadata ``sensors``;
- sign conventions: vertical displacement/acceleration positive up; the gap is the absolute gap
  g0 + (rail rise) - (magnet rise); accelerations are kinematic (gravity removed, as an
  AC-coupled accelerometer reports); guideway displacement is the girder deflection from its
  unloaded static shape (negative under the vehicle);
- the metadata ``design`` block is the scenario's NOMINAL ``design``; the simulation uses the
  nominal design with the scenario's ``truth`` overrides merged on top. The truth never enters
  the bag: it goes to ``<BAG>.truth.json`` (with the resolved scenario, the simulated twin
  configuration and the true modes of the instrumented span), and the true irregularity profile
  to ``<BAG>.irregularity.csv`` (columns position_m, elevation_m).

Guideway model: vertical bending only (guideway.py), so left and right vertical sensors of one
section see the same motion (they differ by their noise); no lateral channels are simulated.

Ambient records: independent band-limited white point forces on every span (``points_per_span``
evenly spaced per span, RMS ``force_rms_n`` each within ``band_hz``), projected on the FE modes;
each mode is integrated exactly for piecewise-constant (ZOH) force (scipy.signal.cont2discrete +
lfilter), streaming in chunks after a discarded warm-up; no vehicle.

Scenario keys (defaults in ``DEFAULTS``; see config/scenarios/paper.yaml for a commented one):
kind, description, seed, start_stamp_ns, line, guideway_sensors, vehicle_sensors, speed_mps,
speed_profile, lead_in_s, free_decay_s, duration_s (ambient), rates, block_s, irregularity,
excitation (ambient), instrument, design, truth, vehicle, effects, method.

``effects`` is a list of ``{name: ..., <params>}`` physics effects that the nominal twin lacks,
applied by the simulator only (recorded in the truth sidecar, never in the metadata). Known:
``ambient_excitation`` (pass only: the ambient guideway response of ``excitation``-like
parameters superposed on the guideway channels, e.g. vibration from an adjacent line; it is
not fed back into the vehicle). New effects register in ``EFFECTS``.

Written by hand (orchestration of our own twin core); filters and ZOH discretisation use scipy.
"""
from __future__ import annotations

import copy
import csv
import io
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np
import yaml
from scipy import signal

from maglev_ros import outputs
from maglev_ros.contract import (TOPIC_GUIDEWAY_ACCEL, TOPIC_GUIDEWAY_DISP, TOPIC_VEHICLE_ACCEL,
                                 TOPIC_VEHICLE_GAP, TOPIC_VEHICLE_POSITION, CONTRACT_SCHEMA)
from maglev_ros.errors import UserError
from maglev_ros.progress import NULL, Progress
from maglev_ros.twin.design import SpanSpec, TwinConfig, line_spans, twin_config
from maglev_ros.twin.guideway import Guideway, ModalBasis
from maglev_ros.twin.sensors import AntiAlias, InstrumentChain, NoiseSpec, anti_alias_delay_s

__all__ = ["DEFAULTS", "SCENARIO_DIR", "builtin_scenarios", "load_scenario", "apply_sets",
           "Scenario", "SimulatedRecord", "SimulationResult", "run_scenario", "write_record",
           "simulate", "EFFECTS", "ambient_modal_response", "truth_paths"]

SCENARIO_DIR = Path(__file__).resolve().parent.parent / "config" / "scenarios"

GROUPS = {  # group name -> topic, unit
    "guideway_accel": (TOPIC_GUIDEWAY_ACCEL, "m/s^2"),
    "guideway_displacement": (TOPIC_GUIDEWAY_DISP, "m"),
    "vehicle_accel": (TOPIC_VEHICLE_ACCEL, "m/s^2"),
    "vehicle_gap": (TOPIC_VEHICLE_GAP, "m"),
    "position": (TOPIC_VEHICLE_POSITION, None),
}

DEFAULTS: dict = {
    "kind": "pass",
    "description": "",
    "seed": 0,
    "start_stamp_ns": 1_700_000_000_000_000_000,
    "method": "newmark",
    "line": {"n_spans": 5, "span_length_m": 12.384, "start_m": 0.0, "instrumented_span": None},
    "guideway_sensors": {"sections": 5, "fractions": None, "sides": ["left", "right"],
                         "displacement_sections": "midspan"},
    "vehicle_sensors": {"magnets": [1, 2, 7, 8], "accel": True, "gap": True},
    "speed_mps": 6.944,
    "speed_profile": None,
    "lead_in_s": 2.0,
    "free_decay_s": 6.0,
    "duration_s": 120.0,
    "warmup_s": 3.0,
    "rates": {"guideway_hz": 2000.0, "vehicle_hz": 2000.0, "position_hz": 200.0, "oversample": 4},
    "block_s": 0.1,
    "irregularity": {"components": [{"psd": "maglev_001", "band_m": [1.0, 20.0], "scale": 1.0}],
                     "spacing_m": 0.02, "csv": None},
    "excitation": {"kind": "distributed_white_noise", "force_rms_n": 2000.0, "band_hz": [0.5, 250.0],
                   "points_per_span": 9},
    "instrument": {
        "anti_alias": {"kind": "butterworth", "order": 8, "cutoff_frac": 0.4},
        "guideway_accel": {"noise_rms": 2.0e-3},
        "guideway_displacement": {"noise_rms": 2.0e-6},
        "vehicle_accel": {"noise_rms": 2.0e-2},
        "vehicle_gap": {"noise_rms": 5.0e-6},
        "position": {"noise_rms": 0.0},
    },
    "design": None,
    "truth": None,
    "vehicle": None,          # {magnet_offsets_m, nominal_gap_m}: geometry (not a truth parameter)
    "effects": [],
}
_SUBKEYS = {"line", "guideway_sensors", "vehicle_sensors", "rates", "irregularity", "excitation",
            "instrument"}


# ------------------------------------------------------------------------------ loading
def builtin_scenarios() -> dict[str, Path]:
    """Built-in scenario names (``paper``, ``paper-ambient``, ...) -> YAML path."""
    return {p.stem: p for p in sorted(SCENARIO_DIR.glob("*.yaml"))}


def _deep_merge(base: Any, over: Any) -> Any:
    if isinstance(base, Mapping) and isinstance(over, Mapping):
        out = dict(base)
        for k, v in over.items():
            out[k] = _deep_merge(base.get(k), v) if k in base else copy.deepcopy(v)
        return out
    return copy.deepcopy(over)


def apply_sets(doc: dict, sets: Sequence[str], source: str = "--set") -> dict:
    """Apply ``key.sub=value`` overrides (value parsed as YAML; list items by index)."""
    doc = copy.deepcopy(doc)
    for item in sets or ():
        if "=" not in item:
            raise UserError(f"{source} {item!r}: expected KEY=VALUE (e.g. speed_mps=10)")
        key, raw = item.split("=", 1)
        key = key.strip()
        try:
            value = yaml.safe_load(raw)
        except yaml.YAMLError:
            raise UserError(f"{source} {item!r}: value is not valid YAML") from None
        if isinstance(value, str):
            try:                      # YAML 1.1 reads 4.0e10 (no exponent sign) as a string
                value = float(value)
            except ValueError:
                pass
        parts = key.split(".")
        if not key or any(not p for p in parts):
            raise UserError(f"{source} {item!r}: empty key")
        if parts[0] not in DEFAULTS:
            raise UserError(f"{source} {item!r}: unknown scenario key {parts[0]!r} "
                            f"(known: {', '.join(sorted(DEFAULTS))})")
        node: Any = doc
        for i, p in enumerate(parts[:-1]):
            nxt_is_index = parts[i + 1].isdigit()
            if isinstance(node, list):
                if not p.isdigit() or int(p) >= len(node):
                    raise UserError(f"{source} {item!r}: {'.'.join(parts[:i + 1])} is not a list index")
                node = node[int(p)]
                continue
            if node.get(p) is None:
                node[p] = [] if nxt_is_index else {}
            node = node[p]
            if not isinstance(node, (dict, list)):
                raise UserError(f"{source} {item!r}: {'.'.join(parts[:i + 1])} is not a mapping")
        last = parts[-1]
        if isinstance(node, list):
            if not last.isdigit() or int(last) > len(node):
                raise UserError(f"{source} {item!r}: {last!r} is not a valid list index")
            if int(last) == len(node):
                node.append(value)
            else:
                node[int(last)] = value
        else:
            node[last] = value
    return doc


def load_scenario(spec: str | Path | Mapping, sets: Sequence[str] = (), seed: int | None = None) -> "Scenario":
    """Scenario from a YAML file, a built-in name or a dict, with ``--set`` overrides and seed."""
    if isinstance(spec, Mapping):
        raw, source, name = dict(spec), "<scenario>", str(spec.get("name", "scenario"))
    else:
        s = str(spec)
        builtins = builtin_scenarios()
        path = builtins[s] if s in builtins else Path(s)
        if not path.is_file():
            raise UserError(f"{s}: no such scenario file (built-in scenarios: {', '.join(builtins) or 'none'})")
        try:
            raw = yaml.safe_load(path.read_text()) or {}
        except (OSError, yaml.YAMLError) as exc:
            raise UserError(f"{path}: cannot read scenario YAML ({str(exc).splitlines()[0]})") from None
        if not isinstance(raw, dict):
            raise UserError(f"{path}: scenario must be a YAML mapping, got {type(raw).__name__}")
        source, name = str(path), path.stem
    raw.pop("name", None)
    unknown = set(raw) - set(DEFAULTS)
    if unknown:
        raise UserError(f"{source}: unknown scenario key(s) {sorted(unknown)} (known: {', '.join(sorted(DEFAULTS))})")
    raw = apply_sets(raw, sets)
    if seed is not None:
        raw["seed"] = int(seed)
    merged = {}
    for k, dv in DEFAULTS.items():
        if k in _SUBKEYS and isinstance(raw.get(k), Mapping):
            if k == "irregularity" and ("csv" in raw[k] and raw[k]["csv"]) and "components" not in raw[k]:
                merged[k] = _deep_merge({**dv, "components": []}, raw[k])
            else:
                merged[k] = _deep_merge(dv, raw[k])
        elif k in raw:
            merged[k] = copy.deepcopy(raw[k])
        else:
            merged[k] = copy.deepcopy(dv)
    return Scenario.from_dict(merged, source=source, name=name)


# ------------------------------------------------------------------------------ scenario
def _num(v: Any, where: str, lo: float | None = None, hi: float | None = None, strict_lo: bool = True) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise UserError(f"scenario key {where}: expected a finite number, got {v!r}")
    v = float(v)
    if lo is not None and (v <= lo if strict_lo else v < lo):
        raise UserError(f"scenario key {where}: expected {'>' if strict_lo else '>='} {lo:g}, got {v:g}")
    if hi is not None and v > hi:
        raise UserError(f"scenario key {where}: expected <= {hi:g}, got {v:g}")
    return v


@dataclass(frozen=True)
class Scenario:
    """A resolved scenario (``raw``: the full merged dict, also written to the truth sidecar)."""
    raw: Mapping[str, Any]
    source: str = "<scenario>"
    name: str = "scenario"

    @classmethod
    def from_dict(cls, d: Mapping, source: str = "<scenario>", name: str = "scenario") -> "Scenario":
        sc = cls(raw=d, source=source, name=name)
        sc.validate()
        return sc

    # ---- accessors
    @property
    def kind(self) -> str:
        return self.raw["kind"]

    @property
    def seed(self) -> int:
        return int(self.raw["seed"])

    def validate(self) -> None:
        r = self.raw
        if r["kind"] not in ("pass", "ambient"):
            raise UserError(f"{self.source}: scenario key kind: expected 'pass' or 'ambient', got {r['kind']!r}")
        if isinstance(r["seed"], bool) or not isinstance(r["seed"], int) or r["seed"] < 0:
            raise UserError(f"{self.source}: scenario key seed: expected an integer >= 0, got {r['seed']!r}")
        rates = r["rates"]
        for k in ("guideway_hz", "vehicle_hz", "position_hz"):
            _num(rates[k], f"rates.{k}", 0.0)
        if not isinstance(rates["oversample"], int) or rates["oversample"] < 1:
            raise UserError(f"{self.source}: scenario key rates.oversample: expected an integer >= 1, "
                            f"got {rates['oversample']!r}")
        _num(r["block_s"], "block_s", 0.0, 10.0)
        for k in ("lead_in_s", "free_decay_s", "warmup_s"):
            _num(r[k], k, 0.0, strict_lo=False)
        if r["kind"] == "ambient":
            _num(r["duration_s"], "duration_s", 0.0)
        if r["speed_profile"] is None:
            _num(r["speed_mps"], "speed_mps", 0.0)
        if r["method"] not in ("newmark", "separated"):
            raise UserError(f"{self.source}: scenario key method: expected newmark or separated, got {r['method']!r}")
        for key in ("design", "truth", "vehicle"):
            if r[key] is not None and not isinstance(r[key], Mapping):
                raise UserError(f"{self.source}: scenario key {key}: expected a mapping, got {r[key]!r}")
        if not isinstance(r["effects"], list):
            raise UserError(f"{self.source}: scenario key effects: expected a list of {{name: ...}}, got {r['effects']!r}")
        for i, e in enumerate(r["effects"]):
            if not isinstance(e, Mapping) or e.get("name") not in EFFECTS:
                raise UserError(f"{self.source}: scenario key effects[{i}]: expected {{name: one of "
                                f"{', '.join(sorted(EFFECTS))}, ...}}, got {e!r}")
            if r["kind"] not in EFFECTS[e["name"]].kinds:
                raise UserError(f"{self.source}: scenario key effects[{i}]: effect {e['name']!r} "
                                f"does not apply to a {r['kind']} record")
        # instrument
        inst = r["instrument"]
        AntiAlias.from_dict(inst.get("anti_alias"))
        for g in GROUPS:
            NoiseSpec.from_dict(inst.get(g), f"instrument.{g}")
        unknown = set(inst) - set(GROUPS) - {"anti_alias"}
        if unknown:
            raise UserError(f"{self.source}: scenario key instrument: unknown group(s) {sorted(unknown)} "
                            f"(known: anti_alias, {', '.join(GROUPS)})")

    def to_dict(self) -> dict:
        return json.loads(json.dumps(self.raw))

    # ---- derived model pieces
    def nominal_design(self) -> dict | None:
        return None if self.raw["design"] is None else copy.deepcopy(dict(self.raw["design"]))

    def truth_design(self) -> dict:
        truth = dict(self.raw["truth"] or {})
        truth.pop("spans", None)
        return _deep_merge(self.nominal_design() or {}, truth)

    def _vehicle_geometry(self) -> tuple[list | None, float | None]:
        v = self.raw["vehicle"] or {}
        return v.get("magnet_offsets_m"), v.get("nominal_gap_m")

    def nominal_config(self) -> TwinConfig:
        offs, gap = self._vehicle_geometry()
        return twin_config(self.nominal_design(), magnet_offsets_m=offs, nominal_gap_m=gap)

    def truth_config(self) -> TwinConfig:
        offs, gap = self._vehicle_geometry()
        return twin_config(self.truth_design(), magnet_offsets_m=offs, nominal_gap_m=gap)

    def nominal_spans(self) -> list[dict]:
        """``line.spans`` as written to the metadata (nominal; per-span design keys allowed)."""
        line = self.raw["line"]
        if line.get("spans"):
            spans = [dict(s) for s in line["spans"]]
        else:
            n = int(line["n_spans"])
            L = _num(line["span_length_m"], "line.span_length_m", 0.0)
            x0 = _num(line.get("start_m", 0.0), "line.start_m")
            if n < 1:
                raise UserError(f"{self.source}: scenario key line.n_spans: expected >= 1, got {n}")
            spans = [{"id": f"S{i + 1}", "start_m": round(x0 + i * L, 9), "length_m": L} for i in range(n)]
        return spans

    def truth_span_specs(self, config: TwinConfig) -> tuple[SpanSpec, ...]:
        spans = self.nominal_spans()
        over = dict((self.raw["truth"] or {}).get("spans") or {})
        ids = [str(s.get("id")) for s in spans]
        for sid, o in over.items():
            if str(sid) not in ids:
                raise UserError(f"{self.source}: scenario key truth.spans.{sid}: no such span (spans: {', '.join(ids)})")
            spans[ids.index(str(sid))].update(dict(o))
        return line_spans({"spans": spans}, config)

    def instrumented_span(self) -> dict:
        spans = self.nominal_spans()
        sid = self.raw["line"].get("instrumented_span")
        if sid is None:
            return spans[len(spans) // 2]
        for s in spans:
            if s.get("id") == sid:
                return s
        raise UserError(f"{self.source}: scenario key line.instrumented_span: {sid!r} is not a span "
                        f"({', '.join(str(s.get('id')) for s in spans)})")

    def guideway_sections(self) -> list[tuple[int, float]]:
        """(section number, x_m) of the instrumented sections."""
        gs = self.raw["guideway_sensors"]
        sp = self.instrumented_span()
        fr = gs.get("fractions")
        if fr is None:
            n = int(gs["sections"])
            if n < 1:
                raise UserError(f"{self.source}: scenario key guideway_sensors.sections: expected >= 1, got {n}")
            fr = [(k + 1) / (n + 1) for k in range(n)]
        out = []
        for k, f in enumerate(fr):
            f = _num(f, f"guideway_sensors.fractions[{k}]", 0.0, 1.0)
            out.append((k + 1, float(sp["start_m"]) + f * float(sp["length_m"])))
        return out

    def displacement_sections(self) -> list[int]:
        ds = self.raw["guideway_sensors"].get("displacement_sections")
        secs = self.guideway_sections()
        if ds in (None, False, "none", []):
            return []
        if ds == "midspan":
            sp = self.instrumented_span()
            mid = float(sp["start_m"]) + 0.5 * float(sp["length_m"])
            return [min(secs, key=lambda s: abs(s[1] - mid))[0]]
        if not isinstance(ds, list) or not all(isinstance(k, int) and 1 <= k <= len(secs) for k in ds):
            raise UserError(f"{self.source}: scenario key guideway_sensors.displacement_sections: expected "
                            f"'midspan', none or a list of section numbers 1..{len(secs)}, got {ds!r}")
        return list(ds)

    def rates(self) -> dict:
        r = self.raw["rates"]
        out = {"guideway_hz": float(r["guideway_hz"]), "vehicle_hz": float(r["vehicle_hz"]),
               "position_hz": float(r["position_hz"]), "oversample": int(r["oversample"])}
        top = out["guideway_hz"] if self.kind == "ambient" else max(out["guideway_hz"], out["vehicle_hz"])
        out["internal_hz"] = top * out["oversample"]
        for k in ("guideway_hz", "vehicle_hz", "position_hz"):
            if self.kind == "ambient" and k != "guideway_hz":
                continue
            ratio = out["internal_hz"] / out[k]
            if abs(ratio - round(ratio)) > 1e-9:
                raise UserError(f"{self.source}: scenario key rates.{k}: {out[k]:g} Hz does not divide the "
                                f"internal rate {out['internal_hz']:g} Hz (oversample x fastest rate)")
        return out


# ------------------------------------------------------------------------------ outputs
@dataclass
class SimulatedRecord:
    """What ``run_scenario`` produced: per topic (channels, units, rate, first sample index, data)."""
    metadata: dict
    truth: dict
    irregularity: tuple[np.ndarray, np.ndarray] | None
    streams: dict[str, dict] = field(default_factory=dict)   # topic -> {channels, units, rate_hz, t0_s, data}
    internal: dict[str, Any] = field(default_factory=dict)    # noise-free internal signals (tests)

    def stream(self, topic: str) -> dict:
        return self.streams[topic]


@dataclass(frozen=True)
class SimulationResult:
    bag: str
    truth_json: str
    irregularity_csv: str | None
    kind: str
    duration_s: float
    topics: dict
    summary: dict

    def to_dict(self) -> dict:
        return json.loads(json.dumps(self.__dict__, default=float))


def truth_paths(bag: str | Path) -> tuple[Path, Path]:
    """Sidecar paths next to a bag: (<BAG>.truth.json, <BAG>.irregularity.csv)."""
    b = Path(str(bag).rstrip("/"))
    return b.with_name(b.name + ".truth.json"), b.with_name(b.name + ".irregularity.csv")


# ------------------------------------------------------------------------------ irregularity
def _irregularity(sc: Scenario, x_lo: float, x_hi: float, rng_seq: np.random.SeedSequence):
    from maglev_ros.twin.irregularity_psd import psd_by_name, random_profile
    ir = sc.raw["irregularity"]
    if ir is None:
        return None, []
    if not isinstance(ir, Mapping):
        raise UserError(f"{sc.source}: scenario key irregularity: expected a mapping or null, got {ir!r}")
    if ir.get("csv"):
        p = Path(str(ir["csv"]))
        if not p.is_absolute() and sc.source not in ("<scenario>",):
            cand = Path(sc.source).parent / p
            p = cand if cand.is_file() else p
        try:
            arr = np.genfromtxt(p, delimiter=",", names=True)
            x, r = np.asarray(arr["position_m"], float), np.asarray(arr["elevation_m"], float)
        except (OSError, ValueError) as exc:
            raise UserError(f"{p}: cannot read irregularity CSV with columns position_m, elevation_m ({exc})") from None
        if x.size < 2 or np.any(np.diff(x) <= 0):
            raise UserError(f"{p}: irregularity CSV positions must increase")
        if x[0] > x_lo or x[-1] < x_hi:
            raise UserError(f"{p}: irregularity CSV covers {x[0]:g}..{x[-1]:g} m; the run needs {x_lo:g}..{x_hi:g} m")
        return (x, r), [{"csv": str(p)}]
    spacing = _num(ir.get("spacing_m", 0.02), "irregularity.spacing_m", 0.0)
    comps = ir.get("components") or []
    if not isinstance(comps, list):
        raise UserError(f"{sc.source}: scenario key irregularity.components: expected a list, got {comps!r}")
    n = int(math.floor((x_hi - x_lo) / spacing)) + 1
    x = x_lo + spacing * np.arange(n)
    r = np.zeros(n)
    used = []
    seqs = rng_seq.spawn(max(1, len(comps)))
    for i, c in enumerate(comps):
        w = f"irregularity.components[{i}]"
        if not isinstance(c, Mapping):
            raise UserError(f"{sc.source}: scenario key {w}: expected a mapping, got {c!r}")
        if "periodic_wavelength_m" in c:
            lam = _num(c["periodic_wavelength_m"], f"{w}.periodic_wavelength_m", 0.0)
            amp = _num(c.get("amplitude_m", 0.0), f"{w}.amplitude_m", 0.0, strict_lo=False)
            ph = float(np.random.default_rng(seqs[i]).uniform(0, 2 * np.pi))
            r += amp * np.cos(2 * np.pi * x / lam + ph)
            used.append({"periodic_wavelength_m": lam, "amplitude_m": amp, "phase_rad": ph})
            continue
        psd = psd_by_name(str(c.get("psd", "maglev_001")))
        band = c.get("band_m", [1.0, 20.0])
        scale = _num(c.get("scale", 1.0), f"{w}.scale", 0.0)
        if not (isinstance(band, (list, tuple)) and len(band) == 2):
            raise UserError(f"{sc.source}: scenario key {w}.band_m: expected [min_wavelength, max_wavelength], got {band!r}")
        _, ri = random_profile(psd, x_hi - x_lo, spacing, (float(band[0]), float(band[1])),
                               rng=np.random.default_rng(seqs[i]), start_m=x_lo)
        r += math.sqrt(scale) * ri[:n]
        used.append({"psd": psd.to_dict(), "band_m": [float(band[0]), float(band[1])], "scale": scale})
    return (x, r), used


# ------------------------------------------------------------------------------ ambient modal response
def _zoh_mode_filters(modal: ModalBasis, fs_hz: float):
    """Per mode: (num_disp, num_acc, den) of the ZOH-discretised SDOF q'' + 2 z w q' + w^2 q = p. A mode
    above 0.45 x the rate responds quasi-statically to forces band-limited below it (q = p / w^2, its
    acceleration a second difference): discretised as a resonator above the rate's Nyquist frequency
    it would ring at its folded frequency, inside the band."""
    out = []
    dt = 1.0 / fs_hz
    for w, z in zip(modal.omega_rad_s, modal.damping_ratio):
        if w >= 0.9 * math.pi * fs_hz:
            out.append((np.array([1.0, 0.0, 0.0]) / w ** 2, np.array([1.0, -2.0, 1.0]) * (fs_hz / w) ** 2,
                        np.array([1.0, 0.0, 0.0])))
            continue
        A = np.array([[0.0, 1.0], [-w * w, -2 * z * w]])
        B = np.array([[0.0], [1.0]])
        C = np.array([[1.0, 0.0], [-w * w, -2 * z * w]])
        D = np.array([[0.0], [1.0]])
        Ad, Bd, Cd, Dd, _ = signal.cont2discrete((A, B, C, D), dt, method="zoh")
        num, den = signal.ss2tf(Ad, Bd, Cd, Dd)
        out.append((num[0], num[1], den))
    return out


def ambient_modal_response(modal: ModalBasis, sensor_x_m: Sequence[float], fs_hz: float, n_samples: int,
                           force_rms_n: float, band_hz: Sequence[float], points_per_span: int,
                           rng: np.random.Generator, *, warmup_samples: int = 0, chunk: int = 200_000,
                           spans: Sequence[int] | None = None):
    """Yield (disp (n, s), accel (n, s)) chunks of the guideway response at ``sensor_x_m`` to
    independent band-limited white point forces (RMS ``force_rms_n`` each in ``band_hz``) at
    ``points_per_span`` evenly spaced interior points of every span (or of ``spans``).
    The first ``warmup_samples`` are simulated and dropped (start from rest)."""
    sx = np.asarray(sensor_x_m, dtype=float)
    S = modal.shapes_at(sx) if sx.size else np.zeros((0, modal.n_modes))
    pts = []
    for k, fe in enumerate(modal.spans_fe):
        if spans is not None and k not in spans:
            continue
        sp = fe.span
        pts += [sp.start_m + sp.length_m * (i + 1) / (points_per_span + 1) for i in range(points_per_span)]
    P = modal.shapes_at(np.array(pts))          # (n_points, n_modes)
    lo, hi = float(band_hz[0]), min(float(band_hz[1]), 0.45 * fs_hz)
    if not 0 < lo < hi:
        raise UserError(f"excitation.band_hz: expected 0 < low < high < 0.45 x internal rate, got {list(band_hz)}")
    sos = signal.butter(4, [lo, hi], btype="bandpass", output="sos", fs=fs_hz)
    # white std so that the band-limited force has RMS force_rms_n (ideal band-pass approximation)
    sigma_w = force_rms_n * math.sqrt(0.5 * fs_hz / (hi - lo))
    filt = _zoh_mode_filters(modal, fs_hz)
    nm = modal.n_modes
    zi_bp = None
    zi_d = [np.zeros(len(f[2]) - 1) for f in filt]
    zi_a = [np.zeros(len(f[2]) - 1) for f in filt]
    total = n_samples + warmup_samples
    done = 0
    while done < total:
        n = min(chunk, total - done)
        w = rng.standard_normal((n, len(pts))) * sigma_w
        pm = w @ P                                  # modal forces (n, nm)
        if zi_bp is None:
            zi_bp = np.zeros((sos.shape[0], 2, nm))
        pm, zi_bp = signal.sosfilt(sos, pm, axis=0, zi=zi_bp)
        q = np.empty((n, nm))
        qa = np.empty((n, nm))
        for j, (nd, na, den) in enumerate(filt):
            q[:, j], zi_d[j] = signal.lfilter(nd, den, pm[:, j], zi=zi_d[j])
            qa[:, j], zi_a[j] = signal.lfilter(na, den, pm[:, j], zi=zi_a[j])
        d, a = q @ S.T, qa @ S.T
        s0 = max(0, warmup_samples - done)
        done += n
        if s0 < n:
            yield d[s0:], a[s0:]


# ------------------------------------------------------------------------------ effects
@dataclass(frozen=True)
class Effect:
    kinds: tuple[str, ...]
    apply: Callable[..., None]
    doc: str = ""


def _effect_ambient_excitation(ctx: dict, params: Mapping) -> dict:
    """Superpose an ambient guideway response (e.g. adjacent-line traffic) on the guideway
    channels of a pass (internal rate, before the instrument chain)."""
    exc = _deep_merge(DEFAULTS["excitation"], {k: v for k, v in params.items() if k != "name"})
    modal: ModalBasis = ctx["modal"]
    n = ctx["n_internal"]
    chunks = list(ambient_modal_response(modal, ctx["sensor_x_m"], ctx["fs_internal_hz"], n,
                                         float(exc["force_rms_n"]), exc["band_hz"], int(exc["points_per_span"]),
                                         ctx["rng"], warmup_samples=int(ctx["fs_internal_hz"] * 3.0)))
    d = np.concatenate([c[0] for c in chunks])
    a = np.concatenate([c[1] for c in chunks])
    ctx["guideway_disp_m"] += d
    ctx["guideway_accel_mps2"] += a
    return {"name": "ambient_excitation", **json.loads(json.dumps(exc))}


EFFECTS: dict[str, Effect] = {
    "ambient_excitation": Effect(("pass",), _effect_ambient_excitation,
                                 "band-limited white forces on all spans superposed on the guideway channels"),
}


# ------------------------------------------------------------------------------ metadata
def _metadata(sc: Scenario, cfg_truth: TwinConfig) -> tuple[dict, list[str], list[str], dict]:
    spans = sc.nominal_spans()
    isp = sc.instrumented_span()
    secs = sc.guideway_sections()
    sides = sc.raw["guideway_sensors"]["sides"]
    if not isinstance(sides, list) or not sides or any(s not in ("left", "right", "center") for s in sides):
        raise UserError(f"{sc.source}: scenario key guideway_sensors.sides: expected a list of left/right/center, got {sides!r}")
    sensors: dict[str, dict] = {}
    accel_ch, sec_of = [], {}
    for k, x in secs:
        for side in sides:
            name = f"G{k}{side[0].upper()}V"
            sensors[name] = {"topic": TOPIC_GUIDEWAY_ACCEL, "quantity": "acceleration", "direction": "vertical",
                             "span": isp["id"], "position_m": round(x, 6), "side": side}
            accel_ch.append(name)
            sec_of[name] = k
    disp_ch = []
    if sc.kind == "pass":
        for k in sc.displacement_sections():
            name = f"G{k}D"
            sensors[name] = {"topic": TOPIC_GUIDEWAY_DISP, "quantity": "displacement", "direction": "vertical",
                             "span": isp["id"], "position_m": round(dict(secs)[k], 6), "side": "center"}
            disp_ch.append(name)
            sec_of[name] = k
        vs = sc.raw["vehicle_sensors"]
        n_mag = cfg_truth.vehicle.n_magnets
        mags = vs.get("magnets") or []
        if not isinstance(mags, list) or not all(isinstance(m, int) and 1 <= m <= n_mag for m in mags):
            raise UserError(f"{sc.source}: scenario key vehicle_sensors.magnets: expected magnet numbers 1..{n_mag}, got {mags!r}")
        if vs.get("accel", True):
            for m in mags:
                sensors[f"M{m}A"] = {"topic": TOPIC_VEHICLE_ACCEL, "quantity": "acceleration",
                                     "direction": "vertical", "magnet": m}
        if vs.get("gap", True):
            for m in mags:
                sensors[f"M{m}G"] = {"topic": TOPIC_VEHICLE_GAP, "quantity": "gap", "magnet": m}
        sensors["position_m"] = {"topic": TOPIC_VEHICLE_POSITION, "quantity": "position"}
        sensors["speed_mps"] = {"topic": TOPIC_VEHICLE_POSITION, "quantity": "speed"}
    run = {"kind": sc.kind, "source": "maglev-ros simulate", "scenario": sc.name}
    if sc.kind == "pass":
        run["nominal_speed_mps"] = float(sc.raw["speed_mps"]) if sc.raw["speed_profile"] is None \
            else float(np.mean([p[1] for p in sc.raw["speed_profile"]]))
    md = {"schema": CONTRACT_SCHEMA,
          "description": sc.raw["description"] or f"simulated {sc.kind} record ({sc.name})",
          "line": {"spans": spans}, "sensors": sensors, "run": run}
    if sc.kind == "pass":
        md["vehicle"] = {"magnet_offsets_m": [float(x) for x in cfg_truth.vehicle.magnet_offsets_m],
                         "nominal_gap_m": float(cfg_truth.levitation.nominal_gap_m)}
    nd = sc.nominal_design()
    if nd is not None:
        md["design"] = nd
    return md, accel_ch, disp_ch, sec_of


# ------------------------------------------------------------------------------ speed
def _speed_arrays(sc: Scenario) -> tuple[np.ndarray, np.ndarray] | float:
    prof = sc.raw["speed_profile"]
    if prof is None:
        return float(sc.raw["speed_mps"])
    try:
        arr = np.asarray(prof, dtype=float)
    except (TypeError, ValueError):
        arr = np.zeros((0,))
    if arr.ndim != 2 or arr.shape[1] != 2 or arr.shape[0] < 2 or np.any(np.diff(arr[:, 0]) <= 0) \
            or np.any(arr[:, 1] <= 0):
        raise UserError(f"{sc.source}: scenario key speed_profile: expected [[t_s, speed_mps], ...] with "
                        f"increasing times and positive speeds, got {prof!r}")
    return arr[:, 0], arr[:, 1]


def _distance(speed, t: np.ndarray) -> np.ndarray:
    """Distance travelled from t=0 (trapezoid on a fine grid)."""
    if isinstance(speed, float):
        return speed * t
    tg = np.linspace(0.0, max(float(t.max()), 1e-9), 20001)
    vg = np.interp(tg, speed[0], speed[1])
    dg = np.concatenate([[0.0], np.cumsum(0.5 * (vg[1:] + vg[:-1]) * np.diff(tg))])
    return np.interp(t, tg, dg)


# ------------------------------------------------------------------------------ runs
def _chains(sc: Scenario, groups: dict[str, list[str]], rates: dict, rng_seq: np.random.SeedSequence):
    inst = sc.raw["instrument"]
    aa = AntiAlias.from_dict(inst.get("anti_alias"))
    seqs = rng_seq.spawn(len(groups))
    out = {}
    for (g, chans), s in zip(groups.items(), seqs):
        fs = rates["vehicle_hz"] if g.startswith("vehicle") else rates["guideway_hz"]
        over = int(round(rates["internal_hz"] / fs))
        out[g] = InstrumentChain(chans, fs, over, aa, NoiseSpec.from_dict(inst.get(g), f"instrument.{g}"),
                                 rng=np.random.default_rng(s))
    return out


def _state_acquisition(md: dict, chains: dict) -> None:
    """Write the optional ``acquisition`` block (docs/contract-extensions.md): the delay of each
    filtered topic behind its stamps, as a data sheet of the acquisition system would state."""
    acq = md.setdefault("acquisition", {})
    for g, ch in chains.items():
        acq[GROUPS[g][0]] = {"delay_s": anti_alias_delay_s(ch.anti_alias, ch.fs_out_hz, ch.fs_internal_hz),
                             "anti_alias": ch.anti_alias.to_dict()}


def _lcm(values) -> int:
    out = 1
    for v in values:
        out = out * int(v) // math.gcd(out, int(v))
    return out


def run_scenario(sc: Scenario, progress: Progress = NULL) -> SimulatedRecord:
    """Simulate a scenario in memory (see module docstring)."""
    progress.stage("line and guideway modes")
    cfg = sc.truth_config()
    sc.nominal_config()                         # validate the nominal design too
    spans = sc.truth_span_specs(cfg)
    md, accel_ch, disp_ch, sec_of = _metadata(sc, cfg)
    rates = sc.rates()
    fs_int = rates["internal_hz"]
    ss = np.random.SeedSequence(sc.seed)
    seq_irr, seq_noise, seq_exc, seq_eff = ss.spawn(4)
    secs = dict(sc.guideway_sections())
    gw = Guideway(spans, cfg.numerics.n_elements_per_span)
    modal = gw.modes(cfg.numerics.mode_cutoff_hz, cfg.numerics.min_modes_per_span)
    isp = sc.instrumented_span()
    k_isp = [s.span_id for s in spans].index(isp["id"])
    fe = gw.spans_fe[k_isp]
    w_isp, _ = fe.eig()
    sel = modal.span_index == k_isp
    truth = {
        "scenario": sc.to_dict(), "scenario_name": sc.name, "seed": sc.seed,
        "truth_design": sc.truth_design(), "truth_overrides": copy.deepcopy(sc.raw["truth"]),
        "truth_spans": [s.to_dict() for s in spans],
        "twin_config": cfg.to_dict(),
        "instrumented_span": {"id": isp["id"], "start_m": float(isp["start_m"]), "length_m": float(isp["length_m"]),
                              "freq_hz": modal.freq_hz[sel].tolist(), "damping_ratio": modal.damping_ratio[sel].tolist()},
        "effects": [],
    }
    streams: dict[str, dict] = {}
    internal: dict[str, Any] = {"fs_internal_hz": fs_int}
    sec_names = [f"sec{k}" for k in secs]
    sec_x = np.array([secs[k] for k in secs])

    if sc.kind == "pass":
        from maglev_ros.twin.coupling import simulate_pass
        speed = _speed_arrays(sc)
        offs = np.asarray(cfg.vehicle.magnet_offsets_m, dtype=float)
        lead = float(sc.raw["lead_in_s"])
        x0 = float(isp["start_m"]) - float(offs.max()) - float(_distance(speed, np.array([lead]))[0])
        # time the rear magnet leaves the instrumented span
        t_grid = np.linspace(0.0, 3600.0, 360001)
        d = _distance(speed, t_grid)
        rear = x0 + float(offs.min()) + d
        idx = np.flatnonzero(rear >= float(isp["start_m"]) + float(isp["length_m"]))
        if idx.size == 0:
            raise UserError(f"{sc.source}: the vehicle never leaves span {isp['id']} within an hour")
        duration = float(t_grid[idx[0]]) + float(sc.raw["free_decay_s"])
        x_end = x0 + float(_distance(speed, np.array([duration]))[0])
        irr, irr_used = _irregularity(sc, x0 + float(offs.min()) - 5.0, x_end + float(offs.max()) + 5.0, seq_irr)
        progress.stage(f"coupled vehicle/guideway simulation ({duration:.1f} s)")
        res = simulate_pass(cfg, spans, speed, irr, dict(zip(sec_names, sec_x)), duration_s=duration,
                            fs_out_hz=fs_int, start_position_m=x0, method=sc.raw["method"])
        truth["irregularity"] = irr_used
        truth["pass"] = {"start_position_m": x0, "duration_s": duration, "lead_in_s": lead,
                         "enter_instrumented_s": lead, "leave_instrumented_s": float(t_grid[idx[0]]),
                         "dt_internal_s": res.dt_s}
        n_int = res.n_samples
        ctx = {"modal": modal, "sensor_x_m": sec_x, "fs_internal_hz": fs_int, "n_internal": n_int,
               "guideway_disp_m": res.guideway_disp_m.copy(), "guideway_accel_mps2": res.guideway_accel_mps2.copy()}
        eff_seqs = seq_eff.spawn(max(1, len(sc.raw["effects"])))
        progress.stage("effects and instrument chains")
        for e, s in zip(sc.raw["effects"], eff_seqs):
            ctx["rng"] = np.random.default_rng(s)
            truth["effects"].append(EFFECTS[e["name"]].apply(ctx, e))
        col = {n: i for i, n in enumerate(sec_names)}
        mags = [int(ch[1:-1]) for ch in md["sensors"] if ch.startswith("M") and ch.endswith("A")]
        gmags = [int(ch[1:-1]) for ch in md["sensors"] if ch.startswith("M") and ch.endswith("G")]
        sig = {
            "guideway_accel": ctx["guideway_accel_mps2"][:, [col[f"sec{sec_of[c]}"] for c in accel_ch]],
            "guideway_displacement": ctx["guideway_disp_m"][:, [col[f"sec{sec_of[c]}"] for c in disp_ch]],
            "vehicle_accel": res.magnet_accel_mps2[:, [m - 1 for m in mags]],
            "vehicle_gap": res.magnet_gap_m[:, [m - 1 for m in gmags]],
        }
        chans = {"guideway_accel": accel_ch, "guideway_displacement": disp_ch,
                 "vehicle_accel": [f"M{m}A" for m in mags], "vehicle_gap": [f"M{m}G" for m in gmags]}
        chans = {g: c for g, c in chans.items() if c}
        internal.update({"time_s": res.time_s, **{g: sig[g] for g in chans},
                         "position_m": res.position_m, "speed_mps": res.speed_mps})
        chains = _chains(sc, chans, rates, seq_noise)
        _state_acquisition(md, chains)
        decs = {g: ch.oversample for g, ch in chains.items()}
        d_pos = int(round(fs_int / rates["position_hz"]))
        if abs(fs_int / rates["position_hz"] - d_pos) > 1e-9:
            raise UserError(f"{sc.source}: scenario key rates.position_hz must divide the internal rate {fs_int:g} Hz")
        i0 = _lcm(list(decs.values()) + [d_pos])          # first common output instant (internal index, 1-based)
        for g, ch in chains.items():
            y = ch.process(sig[g])
            D = decs[g]
            y = y[i0 // D - 1:]
            streams[GROUPS[g][0]] = {"channels": chans[g], "units": [GROUPS[g][1]] * len(chans[g]),
                                     "rate_hz": ch.fs_out_hz, "first_index": i0 // D, "data": y,
                                     "chain": ch.describe()}
        pos_noise = NoiseSpec.from_dict(sc.raw["instrument"].get("position"), "instrument.position")
        take = np.arange(i0 - 1, n_int, d_pos)
        pos = res.position_m[take].copy()
        if pos_noise.noise_rms > 0:
            pos += pos_noise.noise_rms * np.random.default_rng(seq_noise.spawn(1)[0]).standard_normal(pos.size)
        streams[TOPIC_VEHICLE_POSITION] = {"channels": ["position_m", "speed_mps"], "units": ["m", "m/s"],
                                           "rate_hz": rates["position_hz"], "first_index": i0 // d_pos,
                                           "data": np.column_stack([pos, res.speed_mps[take]])}
        summary = res.summary()
        truth["summary"] = {"magnet_accel_peak_mps2": summary["magnet_accel_peak_mps2"],
                            "gap_min_m": summary["gap_min_m"], "gap_max_m": summary["gap_max_m"],
                            "guideway_disp_peak_m": summary["guideway_disp_peak_m"],
                            "guideway_accel_peak_mps2": summary["guideway_accel_peak_mps2"]}
        irr_out = irr
    else:
        exc = sc.raw["excitation"]
        if exc.get("kind", "distributed_white_noise") != "distributed_white_noise":
            raise UserError(f"{sc.source}: scenario key excitation.kind: expected distributed_white_noise, got {exc.get('kind')!r}")
        chans = {"guideway_accel": accel_ch}
        chains = _chains(sc, chans, rates, seq_noise)
        _state_acquisition(md, chains)
        ch = chains["guideway_accel"]
        D = ch.oversample
        n_out = int(round(float(sc.raw["duration_s"]) * ch.fs_out_hz))
        n_int = n_out * D
        col = [list(secs).index(sec_of[c]) for c in accel_ch]
        outs = []
        progress.stage(f"ambient guideway response ({n_int / fs_int:.0f} s, modal superposition)", total=n_int)
        for _d, a in ambient_modal_response(modal, sec_x, fs_int, n_int, _num(exc["force_rms_n"], "excitation.force_rms_n", 0.0),
                                            exc["band_hz"], int(exc["points_per_span"]), np.random.default_rng(seq_exc),
                                            warmup_samples=int(round(float(sc.raw["warmup_s"]) * fs_int))):
            outs.append(ch.process(a[:, col]))
            progress.advance(a.shape[0])
        y = np.concatenate(outs)
        streams[TOPIC_GUIDEWAY_ACCEL] = {"channels": accel_ch, "units": ["m/s^2"] * len(accel_ch),
                                         "rate_hz": ch.fs_out_hz, "first_index": 1, "data": y,
                                         "chain": ch.describe()}
        truth["excitation"] = json.loads(json.dumps(exc))
        truth["ambient"] = {"duration_s": n_out / ch.fs_out_hz}
        irr_out = None
    truth["instrument"] = {t: s.get("chain") for t, s in streams.items() if s.get("chain")}
    return SimulatedRecord(metadata=md, truth=truth, irregularity=irr_out, streams=streams, internal=internal)


# ------------------------------------------------------------------------------ writing
def write_record(rec: SimulatedRecord, out: str | Path, *, start_stamp_ns: int, block_s: float = 0.1,
                 overwrite: bool = False, storage: str = "mcap") -> dict:
    """Write a simulated record as a contract bag + sidecars; returns per-topic block counts."""
    from maglev_ros.bag_writer import BagWriter
    from maglev_ros.sensor_block import Block

    out = Path(str(out).rstrip("/"))
    truth_json, irr_csv = truth_paths(out)
    frames = {TOPIC_GUIDEWAY_ACCEL: "guideway", TOPIC_GUIDEWAY_DISP: "guideway", TOPIC_VEHICLE_ACCEL: "vehicle",
              TOPIC_VEHICLE_GAP: "vehicle", TOPIC_VEHICLE_POSITION: "vehicle"}
    items = []      # (stamp_ns, order, topic, Block)
    for order, (topic, s) in enumerate(rec.streams.items()):
        fs = float(s["rate_hz"])
        nb = max(1, int(round(block_s * fs)))
        data = np.asarray(s["data"], dtype=np.float32)
        if data.ndim == 1:
            data = data[:, None]
        for b0 in range(0, data.shape[0], nb):
            j = s["first_index"] + b0
            stamp = int(start_stamp_ns) + int(round(j * 1e9 / fs))
            items.append((stamp, order, topic, Block(stamp, frames[topic], fs, tuple(s["channels"]),
                                                     tuple(s["units"]), np.ascontiguousarray(data[b0:b0 + nb]))))
    items.sort(key=lambda it: (it[0], it[1]))
    counts: dict[str, int] = {}
    truth = dict(rec.truth)
    truth["bag"] = out.name
    truth["start_stamp_ns"] = int(start_stamp_ns)
    # the sidecars are staged before the bag is finished and renamed after it: a failure anywhere
    # leaves neither a bag without its truth nor a partial bag (a rerun is not refused)
    try:
        with outputs.Batch() as batch, BagWriter(out, rec.metadata, storage=storage,
                                                  overwrite=overwrite) as w:
            for _stamp, _o, topic, blk in items:
                w.write_block(topic, blk)
                counts[topic] = counts.get(topic, 0) + 1
            if rec.irregularity is not None:
                x, r = rec.irregularity
                f = io.StringIO(newline="")
                wr = csv.writer(f)
                wr.writerow(["position_m", "elevation_m"])
                for xi, ri in zip(x, r):
                    wr.writerow([f"{xi:.6f}", f"{ri:.9e}"])
                batch.write_text(irr_csv, f.getvalue())
                truth["irregularity_csv"] = irr_csv.name
            else:
                batch.remove(irr_csv)
            batch.write_json(truth_json, truth, indent=1, default=float)
    except OSError as exc:
        raise UserError(f"{out}: cannot write the bag ({exc.strerror or exc})") from None
    return counts


def simulate(scenario: Scenario | str | Path | Mapping, out: str | Path, *, sets: Sequence[str] = (),
             seed: int | None = None, overwrite: bool = False, storage: str = "mcap",
             progress: Progress = NULL) -> SimulationResult:
    """Scenario -> contract bag at ``out`` + ``<out>.truth.json`` (+ ``<out>.irregularity.csv``)."""
    sc = scenario if isinstance(scenario, Scenario) else load_scenario(scenario, sets, seed)
    out = Path(str(out).rstrip("/"))
    if out.exists() and not overwrite:
        raise UserError(f"{out}: already exists; refusing to overwrite (pass --overwrite)")
    rec = run_scenario(sc, progress)
    progress.stage("write the bag")
    counts = write_record(rec, out, start_stamp_ns=int(sc.raw["start_stamp_ns"]),
                          block_s=float(sc.raw["block_s"]), overwrite=overwrite, storage=storage)
    tj, ic = truth_paths(out)
    dur = max(s["data"].shape[0] / s["rate_hz"] for s in rec.streams.values())
    topics = {t: {"channels": list(s["channels"]), "rate_hz": s["rate_hz"], "blocks": counts.get(t, 0)}
              for t, s in rec.streams.items()}
    summ = dict(rec.truth.get("summary", {}))
    summ["instrumented_span_freq_hz"] = rec.truth["instrumented_span"]["freq_hz"]
    return SimulationResult(str(out), str(tj), str(ic) if rec.irregularity is not None else None,
                            sc.kind, float(dur), topics, summ)
