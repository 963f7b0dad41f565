"""Nominal design of line, vehicle and levitation for the twin: defaults YAML + contract `design` block.

``twin_config(metadata_design)`` merges the optional ``design`` block of a recording's metadata
(keys exactly as in RECORDING.md "Design block") over ``config/twin_defaults.yaml`` and returns a
frozen ``TwinConfig``. ``line_spans(line, config)`` turns the metadata ``line`` block into
``SpanSpec``s, applying per-span guideway overrides. Missing keys keep the default; unknown keys
are ignored (contract rule); a wrong type or a non-physical value raises ``ContractError`` naming
``design.<path>``.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, Mapping, Sequence

import yaml

from maglev_ros.errors import ContractError

DEFAULTS_PATH = Path(__file__).resolve().parent.parent / "config" / "twin_defaults.yaml"

GUIDEWAY_KEYS = ("youngs_modulus_pa", "density_kg_m3", "area_m2", "second_moment_m4",
                 "bearing_stiffness_n_per_m", "damping_ratio")


def _jsonable(obj: Any) -> Any:
    if isinstance(obj, float) and math.isinf(obj):
        return "inf"
    if isinstance(obj, dict):
        return {k: _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    return obj


class _Dict:
    def to_dict(self) -> dict:
        return _jsonable(asdict(self))


@dataclass(frozen=True)
class GuidewayProps(_Dict):
    """Section and support properties of one span (SI). ``bearing_stiffness_n_per_m`` is the
    vertical stiffness of the support at each span end (inf = rigid)."""
    youngs_modulus_pa: float
    density_kg_m3: float
    area_m2: float
    second_moment_m4: float
    bearing_stiffness_n_per_m: float
    damping_ratio: float

    @property
    def mass_per_length_kg_m(self) -> float:
        return self.density_kg_m3 * self.area_m2

    @property
    def bending_stiffness_n_m2(self) -> float:
        return self.youngs_modulus_pa * self.second_moment_m4


@dataclass(frozen=True)
class SpanSpec(_Dict):
    span_id: str
    start_m: float
    length_m: float
    props: GuidewayProps

    @property
    def end_m(self) -> float:
        return self.start_m + self.length_m


@dataclass(frozen=True)
class BodySpec(_Dict):
    mass_kg: float
    pitch_inertia_kg_m2: float
    x_m: float


@dataclass(frozen=True)
class FrameSpec(_Dict):
    mass_kg: float
    pitch_inertia_kg_m2: float
    x_m: float
    magnets: tuple[int, ...]          # 1-based magnet numbers carried by this frame


@dataclass(frozen=True)
class SuspensionSpec(_Dict):
    stiffness_n_per_m: float
    damping_n_s_per_m: float


@dataclass(frozen=True)
class VehicleDesign(_Dict):
    """Vertical vehicle: car body, levitation frames, magnets (x relative to the reference point)."""
    car_body: BodySpec
    frames: tuple[FrameSpec, ...]
    magnet_mass_kg: float
    magnet_offsets_m: tuple[float, ...]
    primary: SuspensionSpec
    secondary: SuspensionSpec
    secondary_x_m: tuple[float, ...]
    gravity_mps2: float = 9.81

    @property
    def n_magnets(self) -> int:
        return len(self.magnet_offsets_m)

    @property
    def total_mass_kg(self) -> float:
        return (self.car_body.mass_kg + sum(f.mass_kg for f in self.frames)
                + self.n_magnets * self.magnet_mass_kg)


@dataclass(frozen=True)
class LevitationDesign(_Dict):
    """Magnet force F = C (I/gap)^2 with I = I0 + kp (gap-g0) + kv d(gap)/dt - ka a_m."""
    nominal_gap_m: float
    static_current_a: float
    kp_a_per_m: float
    kv_a_s_per_m: float
    ka_a_s2_per_m: float
    coil_inductance_h: float = 0.0
    coil_resistance_ohm: float = 1.0
    # transport delay of the control law (sampling, filters, bus): the current follows the law's
    # value control_delay_s earlier (twin/levitation.py: a (2,2) Pade all-pass)
    control_delay_s: float = 0.0


@dataclass(frozen=True)
class NumericsConfig(_Dict):
    n_elements_per_span: int = 16
    mode_cutoff_hz: float = 2000.0
    min_modes_per_span: int = 2
    dt_max_s: float = 1e-3
    # guideway modes integrated by frequency-prewarped Newmark (twin/coupling.py); False: plain
    # average acceleration, whose modes ring (2/h) arctan(w h / 2) low (a 93 Hz mode at 90.5 Hz at 1 ms)
    modal_prewarp: bool = True
    iteration_tol: float = 1e-9
    max_iterations: int = 20


@dataclass(frozen=True)
class TwinConfig(_Dict):
    guideway: GuidewayProps
    vehicle: VehicleDesign
    levitation: LevitationDesign
    numerics: NumericsConfig = field(default_factory=NumericsConfig)
    n_spans_default: int = 5
    span_length_default_m: float = 12.384


# ----------------------------------------------------------------------------------------------
def _strip(node: Any) -> Any:
    """YAML {value, unit, source} leaves -> value."""
    if isinstance(node, dict):
        if "value" in node and set(node) <= {"value", "unit", "source"}:
            return node["value"]
        return {k: _strip(v) for k, v in node.items() if not k.endswith("_source")}
    if isinstance(node, list):
        return [_strip(v) for v in node]
    return node


def load_defaults(path: str | Path | None = None) -> dict:
    """The defaults YAML with unit/source annotations stripped (plain nested dict)."""
    p = Path(path) if path is not None else DEFAULTS_PATH
    try:
        raw = yaml.safe_load(p.read_text())
    except (OSError, yaml.YAMLError) as exc:
        raise ContractError(f"{p}: cannot read twin defaults ({exc})") from None
    return _strip(raw)


def _num(value: Any, where: str, *, positive: bool = True, allow_zero: bool = False,
         allow_inf: bool = False) -> float:
    if isinstance(value, str) and allow_inf and value.strip().lower() in ("inf", "infinity"):
        return math.inf
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ContractError(f"{where}: expected a number, got {value!r}")
    v = float(value)
    if math.isnan(v) or (math.isinf(v) and not allow_inf):
        raise ContractError(f"{where}: expected a finite number, got {value!r}")
    if positive and (v < 0 or (v == 0 and not allow_zero)):
        raise ContractError(f"{where}: expected a {'non-negative' if allow_zero else 'positive'}"
                            f" number, got {value!r}")
    return v


def _section(d: Any, where: str) -> Mapping:
    if d is None:
        return {}
    if not isinstance(d, Mapping):
        raise ContractError(f"{where}: expected an object, got {type(d).__name__}")
    return d


def _guideway(base: Mapping, over: Mapping, where: str) -> GuidewayProps:
    vals = {}
    for k in GUIDEWAY_KEYS:
        v = over.get(k, base.get(k))
        if v is None:
            raise ContractError(f"{where}.{k}: missing (no default either)")
        vals[k] = _num(v, f"{where}.{k}",
                       allow_zero=(k == "damping_ratio"),
                       allow_inf=(k == "bearing_stiffness_n_per_m"))
    if vals["damping_ratio"] >= 1.0:
        raise ContractError(f"{where}.damping_ratio: expected a ratio < 1, got {vals['damping_ratio']}")
    return GuidewayProps(**vals)


def _body(base: Mapping, over: Mapping, where: str) -> BodySpec:
    return BodySpec(
        mass_kg=_num(over.get("mass_kg", base["mass_kg"]), f"{where}.mass_kg"),
        pitch_inertia_kg_m2=_num(over.get("pitch_inertia_kg_m2", base["pitch_inertia_kg_m2"]),
                                 f"{where}.pitch_inertia_kg_m2"),
        x_m=_num(over.get("x_m", base["x_m"]), f"{where}.x_m", positive=False))


def _susp(base: Mapping, over: Mapping, where: str) -> SuspensionSpec:
    return SuspensionSpec(
        stiffness_n_per_m=_num(over.get("stiffness_n_per_m", base["stiffness_n_per_m"]),
                               f"{where}.stiffness_n_per_m"),
        damping_n_s_per_m=_num(over.get("damping_n_s_per_m", base["damping_n_s_per_m"]),
                               f"{where}.damping_n_s_per_m", allow_zero=True))


def _floats(v: Any, where: str) -> tuple[float, ...]:
    if not isinstance(v, (list, tuple)) or not v:
        raise ContractError(f"{where}: expected a non-empty list of numbers, got {v!r}")
    return tuple(_num(x, f"{where}[{i}]", positive=False) for i, x in enumerate(v))


def twin_config(metadata_design: dict | None = None, *, magnet_offsets_m: Sequence[float] | None = None,
                nominal_gap_m: float | None = None, defaults_path: str | Path | None = None) -> TwinConfig:
    """Merge a contract ``design`` block over the defaults YAML.

    ``magnet_offsets_m`` / ``nominal_gap_m`` are the metadata's ``vehicle`` entries (they are not in
    the design block, but the vehicle model needs them). If the design block lists frames whose
    magnets do not match the default magnet count, pass ``magnet_offsets_m`` as well.
    """
    d = load_defaults(defaults_path)
    design = _section(metadata_design, "design")
    g_over = _section(design.get("guideway"), "design.guideway")
    v_over = _section(design.get("vehicle"), "design.vehicle")
    l_over = _section(design.get("levitation"), "design.levitation")

    guideway = _guideway(d["guideway"], g_over, "design.guideway")

    dv = d["vehicle"]
    offsets = _floats(list(magnet_offsets_m) if magnet_offsets_m is not None else dv["magnet_offsets_m"],
                      "vehicle.magnet_offsets_m")
    n_mag = len(offsets)
    car = _body(dv["car_body"], _section(v_over.get("car_body"), "design.vehicle.car_body"),
                "design.vehicle.car_body")
    frames_raw = v_over.get("frames", dv["frames"])
    if not isinstance(frames_raw, list) or not frames_raw:
        raise ContractError(f"design.vehicle.frames: expected a non-empty list, got {frames_raw!r}")
    frames = []
    seen: set[int] = set()
    for i, fr in enumerate(frames_raw):
        w = f"design.vehicle.frames[{i}]"
        fr = _section(fr, w)
        base = dv["frames"][min(i, len(dv["frames"]) - 1)]
        mags = fr.get("magnets", base["magnets"])
        if not isinstance(mags, list) or not mags or not all(
                isinstance(m, int) and not isinstance(m, bool) and 1 <= m <= n_mag for m in mags):
            raise ContractError(f"{w}.magnets: expected a list of magnet numbers 1..{n_mag}, got {mags!r}")
        if seen & set(mags):
            raise ContractError(f"{w}.magnets: magnet(s) {sorted(seen & set(mags))} already on another frame")
        seen |= set(mags)
        b = _body(base, fr, w)
        frames.append(FrameSpec(b.mass_kg, b.pitch_inertia_kg_m2, b.x_m, tuple(mags)))
    if seen != set(range(1, n_mag + 1)):
        raise ContractError(f"design.vehicle.frames: magnets {sorted(set(range(1, n_mag + 1)) - seen)} "
                            f"are on no frame (vehicle has {n_mag} magnets)")
    sec_over = _section(v_over.get("secondary"), "design.vehicle.secondary")
    vehicle = VehicleDesign(
        car_body=car,
        frames=tuple(frames),
        magnet_mass_kg=_num(v_over.get("magnet_mass_kg", dv["magnet_mass_kg"]), "design.vehicle.magnet_mass_kg"),
        magnet_offsets_m=offsets,
        primary=_susp(dv["primary"], _section(v_over.get("primary"), "design.vehicle.primary"),
                      "design.vehicle.primary"),
        secondary=_susp(dv["secondary"], sec_over, "design.vehicle.secondary"),
        secondary_x_m=_floats(sec_over.get("x_m", dv["secondary"]["x_m"]), "design.vehicle.secondary.x_m"),
        gravity_mps2=float(dv.get("gravity_mps2", 9.81)),
    )

    dl = d["levitation"]
    gap = nominal_gap_m if nominal_gap_m is not None else dl["nominal_gap_m"]
    lev = LevitationDesign(
        nominal_gap_m=_num(gap, "vehicle.nominal_gap_m"),
        static_current_a=_num(l_over.get("static_current_a", dl["static_current_a"]),
                              "design.levitation.static_current_a"),
        kp_a_per_m=_num(l_over.get("kp_a_per_m", dl["kp_a_per_m"]), "design.levitation.kp_a_per_m",
                        positive=False),
        kv_a_s_per_m=_num(l_over.get("kv_a_s_per_m", dl["kv_a_s_per_m"]), "design.levitation.kv_a_s_per_m",
                          positive=False),
        ka_a_s2_per_m=_num(l_over.get("ka_a_s2_per_m", dl["ka_a_s2_per_m"]),
                           "design.levitation.ka_a_s2_per_m", positive=False),
        coil_inductance_h=_num(l_over.get("coil_inductance_h", dl.get("coil_inductance_h", 0.0)),
                               "design.levitation.coil_inductance_h", allow_zero=True),
        coil_resistance_ohm=_num(l_over.get("coil_resistance_ohm", dl.get("coil_resistance_ohm", 1.0)),
                                 "design.levitation.coil_resistance_ohm"),
    )
    dn = d.get("numerics", {})
    numerics = NumericsConfig(**{k: type(getattr(NumericsConfig(), k))(v) for k, v in dn.items()
                                 if k in NumericsConfig.__dataclass_fields__})
    dline = d.get("line", {})
    return TwinConfig(guideway=guideway, vehicle=vehicle, levitation=lev, numerics=numerics,
                      n_spans_default=int(dline.get("n_spans", 5)),
                      span_length_default_m=float(dline.get("span_length_m", 12.384)))


def twin_config_from_metadata(metadata: Mapping) -> TwinConfig:
    """Convenience: ``twin_config`` fed from a whole metadata dict (design + vehicle entries)."""
    veh = metadata.get("vehicle") or {}
    return twin_config(metadata.get("design"), magnet_offsets_m=veh.get("magnet_offsets_m"),
                       nominal_gap_m=veh.get("nominal_gap_m"))


def default_line(config: TwinConfig, n_spans: int | None = None) -> tuple[SpanSpec, ...]:
    n = config.n_spans_default if n_spans is None else int(n_spans)
    L = config.span_length_default_m
    return tuple(SpanSpec(f"S{i + 1}", i * L, L, config.guideway) for i in range(n))


def line_spans(line: Any, config: TwinConfig) -> tuple[SpanSpec, ...]:
    """Spans from the metadata ``line`` block (dict with ``spans``), a list of span dicts, or
    ``SpanSpec``s (returned as given). A span dict may repeat any guideway key of the design block
    to override it for that span. None -> ``default_line(config)``."""
    if line is None:
        return default_line(config)
    if isinstance(line, Mapping):
        if "spans" not in line:
            raise ContractError("line.spans: missing")
        line = line["spans"]
    if not isinstance(line, (list, tuple)) or not line:
        raise ContractError(f"line.spans: expected a non-empty list, got {line!r}")
    out = []
    base = asdict(config.guideway)
    for i, s in enumerate(line):
        if isinstance(s, SpanSpec):
            out.append(s)
            continue
        w = f"line.spans[{i}]"
        s = _section(s, w)
        for k in ("start_m", "length_m"):
            if k not in s:
                raise ContractError(f"{w}.{k}: missing")
        props = _guideway(base, s, w)
        out.append(SpanSpec(str(s.get("id", f"S{i + 1}")), _num(s["start_m"], f"{w}.start_m", positive=False),
                            _num(s["length_m"], f"{w}.length_m"), props))
    out.sort(key=lambda sp: sp.start_m)
    for a, b in zip(out, out[1:]):
        if b.start_m < a.end_m - 1e-9:
            raise ContractError(f"line.spans: span {b.span_id} starts at {b.start_m} m inside span {a.span_id}")
    return tuple(out)


def with_guideway(config: TwinConfig, **changes: float) -> TwinConfig:
    """A copy of ``config`` with some guideway properties changed (for updating / tests)."""
    return replace(config, guideway=replace(config.guideway, **changes))


def with_levitation(config: TwinConfig, **changes: float) -> TwinConfig:
    return replace(config, levitation=replace(config.levitation, **changes))
