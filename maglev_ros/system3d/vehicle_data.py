"""The ``maglev-vehicle`` YAML: a 3D multibody maglev vehicle as data (bodies, connections,
magnets, current loops), loaded and validated into frozen dataclasses.

Axes (shared by ``system3d``): x along the line (forward), y lateral (positive left), z vertical
up, right-handed; rotations rx (roll), ry (pitch), rz (yaw). All positions are in the vehicle
frame at rest, in metres; every body DOF is a small displacement of the body centre.

Every number may be written plain or as ``{value: ..., assumed: "..."}`` / ``{value: ...,
source: "..."}`` (with an optional ``unit``): the tags document where a value comes from and are
kept in ``VehicleData.provenance``. YAML anchors (``&name`` / ``*name``) let one tagged value be
used by many items. A mistake raises ``UserError`` with one line naming the file and the key
(``bodies[3].dofs``) and what was expected.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

import yaml

from maglev_ros.errors import UserError
from maglev_ros.system3d.scenario_values import is_value_node, tag_text

FORMAT = "maglev-vehicle"
DOF_NAMES = ("x", "y", "z", "rx", "ry", "rz")
DIRECTIONS = ("x", "y", "z")
GROUND = "ground"
#: Directions each joint kind releases (transmits no force in). 001: "the fixed sliding table ...
#: can transmit translational loads, while the lateral sliding table only transmits vertical load".
JOINT_RELEASES = {"spring": (), "fixed_sliding_table": (), "lateral_sliding_table": ("x", "y")}
SIDES = ("left", "right")
ROLES = ("levitation", "guidance")
ABSENT_DOF_RULES = ("held", "quasi_static")
PASSIVE_LATERAL = ("none", "fringing")


@dataclass(frozen=True)
class RigidBody:
    name: str
    mass_kg: float
    inertia_kg_m2: tuple[float, float, float]   # Ixx, Iyy, Izz about the centre (principal axes = x, y, z)
    centre_m: tuple[float, float, float]
    dofs: tuple[str, ...]                        # subset of DOF_NAMES, in DOF_NAMES order


@dataclass(frozen=True)
class Connection:
    """Spring-dashpot per direction between ``body_a`` and ``body_b`` (or ``ground``) at one point."""
    name: str
    body_a: str
    body_b: str
    point_m: tuple[float, float, float]
    kind: str
    stiffness_n_per_m: tuple[float, float, float]     # x, y, z (0 in released directions)
    damping_n_s_per_m: tuple[float, float, float]


@dataclass(frozen=True)
class Magnet:
    name: str
    body: str
    point_m: tuple[float, float, float]
    side: str          # left / right rail
    role: str          # levitation (force +z, rail above) or guidance (force towards its rail side)
    loop: str

    @property
    def direction(self) -> tuple[float, float, float]:
        """Unit vector of the attractive force on the magnet (and of the gap opening towards the rail)."""
        if self.role == "levitation":
            return (0.0, 0.0, 1.0)
        return (0.0, 1.0, 0.0) if self.side == "left" else (0.0, -1.0, 0.0)


@dataclass(frozen=True)
class CurrentLoop:
    """One control circuit: L0 di/dt + R i - (L0 i0/h0) dh/dt = u, u = kp h + kv h' - ka a (deviations)."""
    id: str
    nominal_gap_m: float
    static_current_a: float
    inductance_h: float
    resistance_ohm: float
    kp_v_per_m: float
    kv_v_s_per_m: float
    ka_v_s2_per_m: float
    preload_force_n: float = 0.0       # static force per magnet of a guidance loop (levitation: from equilibrium)


@dataclass(frozen=True)
class VehicleData:
    name: str
    gravity_mps2: float
    half_gauge_m: float
    absent_dofs: str                  # held: an absent DOF is fixed at 0; quasi_static: massless, condensed
    passive_lateral: str              # none / fringing: levitation magnets' lateral restoring force
    pole_width_m: float               # magnet pole width w (fringing lateral stiffness 2 F0 / (pi w))
    bodies: tuple[RigidBody, ...]
    connections: tuple[Connection, ...]
    magnets: tuple[Magnet, ...]
    loops: tuple[CurrentLoop, ...]
    provenance: Mapping[str, str] = field(default_factory=dict, compare=False)

    def body(self, name: str) -> RigidBody:
        return next(b for b in self.bodies if b.name == name)

    @property
    def total_mass_kg(self) -> float:
        return float(sum(b.mass_kg for b in self.bodies))

    @property
    def n_dof(self) -> int:
        return sum(len(b.dofs) for b in self.bodies)


class _Reader:
    """Walks the YAML tree with the key path for one-line errors; records value tags."""

    def __init__(self, source: str):
        self.source = source
        self.provenance: dict[str, str] = {}

    def fail(self, where: str, what: str):
        raise UserError(f"{self.source}: {where}: {what}")

    def untag(self, node: Any, where: str) -> Any:
        """``{value: v, assumed|source: ..., unit: ...}`` -> v, keeping the tag."""
        if is_value_node(node):
            text = tag_text(node)
            if text is not None:
                self.provenance[where] = text
            return node["value"]
        return node

    def mapping(self, node: Any, where: str, allowed: tuple[str, ...], required: tuple[str, ...] = ()) -> Mapping:
        node = self.untag(node, where)
        if not isinstance(node, Mapping):
            self.fail(where, f"expected a mapping with keys {list(allowed)}, got {type(node).__name__}")
        for k in node:
            if k not in allowed:
                self.fail(f"{where}.{k}" if where else str(k), f"unknown key (expected one of {list(allowed)})")
        for k in required:
            if k not in node:
                self.fail(f"{where}.{k}" if where else k, "missing")
        return node

    def number(self, node: Any, where: str, *, minimum: float | None = 0.0, strict: bool = False) -> float:
        node = self.untag(node, where)
        if isinstance(node, bool) or not isinstance(node, (int, float)) or not math.isfinite(float(node)):
            self.fail(where, f"expected a finite number, got {node!r}")
        v = float(node)
        if minimum is not None and (v < minimum or (strict and v == minimum)):
            self.fail(where, f"expected a number {'>' if strict else '>='} {minimum}, got {v!r}")
        return v

    def vector3(self, node: Any, where: str) -> tuple[float, float, float]:
        node = self.untag(node, where)
        if not isinstance(node, (list, tuple)) or len(node) != 3:
            self.fail(where, f"expected [x, y, z] in metres, got {node!r}")
        return tuple(self.number(v, f"{where}[{i}]", minimum=None) for i, v in enumerate(node))

    def name(self, node: Any, where: str) -> str:
        if not isinstance(node, str) or not node.strip():
            self.fail(where, f"expected a non-empty name, got {node!r}")
        return node

    def choice(self, node: Any, where: str, options: tuple[str, ...]) -> str:
        node = self.untag(node, where)
        if not isinstance(node, str) or node not in options:
            self.fail(where, f"expected one of {list(options)}, got {node!r}")
        return node

    def items(self, node: Any, where: str) -> list:
        if not isinstance(node, list) or not node:
            self.fail(where, "expected a non-empty list")
        return node


_BODY_KEYS = ("name", "mass_kg", "inertia_kg_m2", "centre_m", "dofs")
_CONN_KEYS = ("name", "between", "point_m", "kind", "stiffness_n_per_m", "damping_n_s_per_m")
_MAG_KEYS = ("name", "body", "point_m", "side", "role", "loop")
_LOOP_KEYS = ("nominal_gap_m", "static_current_a", "inductance_h", "resistance_ohm",
              "kp_v_per_m", "kv_v_s_per_m", "ka_v_s2_per_m", "preload_force_n")
_TOP_KEYS = ("format", "version", "name", "description", "values", "gravity_mps2", "half_gauge_m",
             "absent_dofs", "passive_lateral", "pole_width_m", "bodies", "connections", "magnets",
             "loop_defaults", "loops")


def _body(r: _Reader, node: Any, where: str) -> RigidBody:
    m = r.mapping(node, where, _BODY_KEYS, _BODY_KEYS)
    name = r.name(m["name"], f"{where}.name")
    if name == GROUND:
        r.fail(f"{where}.name", f"{GROUND!r} is reserved for the fixed frame")
    dofs = m["dofs"]
    if not isinstance(dofs, list) or not dofs or any(d not in DOF_NAMES for d in dofs) or len(set(dofs)) != len(dofs):
        r.fail(f"{where}.dofs", f"expected a non-empty list of distinct DOFs from {list(DOF_NAMES)}, got {dofs!r}")
    inertia = r.mapping(m["inertia_kg_m2"], f"{where}.inertia_kg_m2", ("xx", "yy", "zz"), ("xx", "yy", "zz"))
    ixyz = tuple(r.number(inertia[k], f"{where}.inertia_kg_m2.{k}") for k in ("xx", "yy", "zz"))
    for d, i in zip(("rx", "ry", "rz"), ixyz):
        if d in dofs and i <= 0:
            r.fail(f"{where}.inertia_kg_m2.{d[1] * 2}", f"must be > 0 because the body has DOF {d}")
    return RigidBody(name, r.number(m["mass_kg"], f"{where}.mass_kg", strict=True), ixyz,
                     r.vector3(m["centre_m"], f"{where}.centre_m"),
                     tuple(d for d in DOF_NAMES if d in dofs))


def _directional(r: _Reader, node: Any, where: str, released: tuple[str, ...], kind: str) -> tuple:
    m = r.mapping(node, where, DIRECTIONS)
    out = []
    for d in DIRECTIONS:
        v = r.number(m.get(d, 0.0), f"{where}.{d}")
        if d in released and v != 0.0:
            r.fail(f"{where}.{d}", f"a {kind} releases {d}: leave it out or give 0, got {v!r}")
        out.append(v)
    return tuple(out)


def _connection(r: _Reader, node: Any, where: str, bodies: set[str]) -> Connection:
    m = r.mapping(node, where, _CONN_KEYS, ("name", "between", "point_m", "stiffness_n_per_m"))
    pair = m["between"]
    if not isinstance(pair, list) or len(pair) != 2 or pair[0] == pair[1]:
        r.fail(f"{where}.between", f"expected [body, body] or [body, {GROUND}] (two different names), got {pair!r}")
    for i, b in enumerate(pair):
        if b not in bodies and b != GROUND:
            r.fail(f"{where}.between[{i}]", f"unknown body {b!r} (bodies: {sorted(bodies)} or {GROUND!r})")
    if pair[0] == GROUND:
        pair = [pair[1], pair[0]]
    kind = r.choice(m.get("kind", "spring"), f"{where}.kind", tuple(JOINT_RELEASES))
    rel = JOINT_RELEASES[kind]
    k = _directional(r, m["stiffness_n_per_m"], f"{where}.stiffness_n_per_m", rel, kind)
    c = _directional(r, m.get("damping_n_s_per_m", {}), f"{where}.damping_n_s_per_m", rel, kind)
    return Connection(r.name(m["name"], f"{where}.name"), pair[0], pair[1],
                      r.vector3(m["point_m"], f"{where}.point_m"), kind, k, c)


def _loop(r: _Reader, node: Any, defaults: Mapping, where: str) -> CurrentLoop:
    m = r.mapping(node, where, ("id",) + _LOOP_KEYS, ("id",))
    vals = {}
    for key in _LOOP_KEYS:
        src, path = (m, f"{where}.{key}") if key in m else (defaults, f"loop_defaults.{key}")
        if key not in src:
            if key == "preload_force_n":
                vals[key] = 0.0
                continue
            r.fail(f"{where}.{key}", "missing (and no loop_defaults entry)")
        strict = key in ("nominal_gap_m", "static_current_a", "resistance_ohm")
        vals[key] = r.number(src[key], path, strict=strict)
    return CurrentLoop(id=str(m["id"]), **vals)


def vehicle_data_from_dict(doc: Any, source: str = "vehicle") -> VehicleData:
    """Validate a parsed ``maglev-vehicle`` document (see module docstring)."""
    r = _Reader(source)
    top = r.mapping(doc, "", _TOP_KEYS, ("format", "bodies", "magnets", "loops"))
    if top["format"] != FORMAT:
        r.fail("format", f"expected {FORMAT!r}, got {top['format']!r}")
    if top.get("version", 1) != 1:
        r.fail("version", f"expected 1, got {top.get('version')!r}")
    bodies = [_body(r, b, f"bodies[{i}]") for i, b in enumerate(r.items(top["bodies"], "bodies"))]
    names = [b.name for b in bodies]
    for i, n in enumerate(names):
        if names.index(n) != i:
            r.fail(f"bodies[{i}].name", f"duplicate body name {n!r}")
    conns = [_connection(r, c, f"connections[{i}]", set(names))
             for i, c in enumerate(top.get("connections") or [])]
    defaults = r.mapping(top.get("loop_defaults") or {}, "loop_defaults", _LOOP_KEYS)
    loops = [_loop(r, lp, defaults, f"loops[{i}]") for i, lp in enumerate(r.items(top["loops"], "loops"))]
    ids = [lp.id for lp in loops]
    for i, n in enumerate(ids):
        if ids.index(n) != i:
            r.fail(f"loops[{i}].id", f"duplicate loop id {n!r}")
    magnets = []
    for i, node in enumerate(r.items(top["magnets"], "magnets")):
        where = f"magnets[{i}]"
        m = r.mapping(node, where, _MAG_KEYS, _MAG_KEYS)
        if m["body"] not in names:
            r.fail(f"{where}.body", f"unknown body {m['body']!r} (bodies: {names})")
        if str(m["loop"]) not in ids:
            r.fail(f"{where}.loop", f"unknown loop {m['loop']!r} (loops: {ids})")
        magnets.append(Magnet(r.name(m["name"], f"{where}.name"), m["body"], r.vector3(m["point_m"], f"{where}.point_m"),
                              r.choice(m["side"], f"{where}.side", SIDES),
                              r.choice(m["role"], f"{where}.role", ROLES), str(m["loop"])))
    for i, lp in enumerate(loops):
        roles = {mg.role for mg in magnets if mg.loop == lp.id}
        if not roles:
            r.fail(f"loops[{i}]", f"loop {lp.id!r} drives no magnet")
        if len(roles) > 1:
            r.fail(f"loops[{i}]", f"loop {lp.id!r} mixes levitation and guidance magnets")
        if roles == {"guidance"} and lp.preload_force_n <= 0:
            r.fail(f"loops[{i}].preload_force_n", f"guidance loop {lp.id!r} needs its static force per magnet > 0")
    passive = r.choice(top.get("passive_lateral", "none"), "passive_lateral", PASSIVE_LATERAL)
    width = r.number(top["pole_width_m"], "pole_width_m", strict=True) if "pole_width_m" in top else 0.0
    if passive == "fringing" and width <= 0:
        r.fail("pole_width_m", "needed (> 0) for passive_lateral: fringing")
    return VehicleData(
        name=str(top.get("name", source)),
        gravity_mps2=r.number(top.get("gravity_mps2", 9.81), "gravity_mps2", strict=True),
        half_gauge_m=r.number(top.get("half_gauge_m", 0.0), "half_gauge_m"),
        absent_dofs=r.choice(top.get("absent_dofs", "held"), "absent_dofs", ABSENT_DOF_RULES),
        passive_lateral=passive, pole_width_m=width,
        bodies=tuple(bodies), connections=tuple(conns), magnets=tuple(magnets), loops=tuple(loops),
        provenance=dict(r.provenance))


def load_vehicle(path: str | Path) -> VehicleData:
    """Read and validate a ``maglev-vehicle`` YAML file."""
    p = Path(path)
    try:
        doc = yaml.safe_load(p.read_text())
    except OSError as exc:
        raise UserError(f"{p}: cannot read ({exc.strerror or exc})") from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        at = f" at line {mark.line + 1}" if mark is not None else ""
        raise UserError(f"{p}: not valid YAML{at}") from None
    return vehicle_data_from_dict(doc, str(p))


CONFIG_DIR = Path(__file__).resolve().parent.parent / "config" / "system3d"
PAPER001_VEHICLE = CONFIG_DIR / "paper001_vehicle.yaml"
