"""The random-vibration scenario (``config/system3d/paper001.yaml``): which vehicle, girder and
irregularity files, the train (cars, car length, speed, start), the solver settings, the PEM
frequency grid and the outputs. Values may be tagged (``scenario_values``); file names are
relative to the scenario file. ``load_scenario(name_or_path)`` accepts a built-in name
(``paper001``); ``build(scenario)`` assembles everything the solvers need (one-time costs).
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from maglev_ros.errors import UserError
from maglev_ros.system3d.girder import assemble_girder, load_girder
from maglev_ros.system3d.girder_rails import RailInterpolation, RailLayout
from maglev_ros.system3d.irregularity import PROCESSES, TrackIrregularity, load_irregularity
from maglev_ros.system3d.pem import FrequencyGrid, PseudoExcitation3D
from maglev_ros.system3d.scenario_values import load_yaml, number, plain, require
from maglev_ros.system3d.solve_coupled import CoupledSolver, ResponsePoint
from maglev_ros.system3d.solve_girder import girder_dynamics
from maglev_ros.system3d.train import Train
from maglev_ros.system3d.vehicle_data import CONFIG_DIR, load_vehicle
from maglev_ros.system3d.vehicle_state_space import build_state_space

FORMAT = "maglev-random-vibration-scenario"
BUILTIN = {"paper001": CONFIG_DIR / "paper001.yaml"}
_TOP = ("format", "version", "name", "description", "vehicle", "girder", "irregularity", "train", "solver",
        "pem", "outputs", "quick")
_SECTION_KEYS = {
    "train": ("cars", "car_length_m", "speed_mps", "front_start_m"),
    "solver": ("time_step_s", "duration_s", "girder_model", "mode_cutoff_hz", "coupling", "tolerance", "hold"),
    "pem": ("frequency_grid", "start", "psd_time_step_s", "processes"),
    "pem.frequency_grid": ("min_rad_per_m", "max_rad_per_m", "n", "spacing", "weights"),
}
_OUT_KEYS = ("name", "quantity", "direction", "car", "body", "point_m", "loop", "girder_x_m", "rail")


@dataclass(frozen=True)
class Scenario:
    name: str
    path: Path
    vehicle_path: Path
    girder_path: Path
    irregularity_path: Path
    cars: int
    car_length_m: float
    speed_mps: float
    front_start_m: float
    time_step_s: float
    duration_s: float
    girder_model: str
    mode_cutoff_hz: float | None
    coupling: str
    tolerance: float
    hold: str
    grid_min_rad_per_m: float
    grid_max_rad_per_m: float
    grid_n: int
    grid_spacing: str
    grid_weights: str
    start: str
    psd_time_step_s: float
    processes: tuple[str, ...]
    outputs: tuple[ResponsePoint, ...]
    quick: dict

    @property
    def n_steps(self) -> int:
        return int(round(self.duration_s / self.time_step_s))

    def quick_variant(self) -> "Scenario":
        """The scenario with its ``quick`` overrides (a cheaper run of the same case)."""
        allowed = {"time_step_s", "grid_n", "mode_cutoff_hz", "psd_time_step_s", "duration_s"}
        bad = sorted(set(self.quick) - allowed)
        if bad:
            raise UserError(f"{self.path}: quick: unknown key {bad[0]!r} (expected {sorted(allowed)})")
        kw = {k: (int(v) if k == "grid_n" else float(v)) for k, v in self.quick.items()}
        return replace(self, **kw)

    def to_dict(self) -> dict:
        d = {k: (str(v) if isinstance(v, Path) else v) for k, v in self.__dict__.items()
             if k not in ("outputs", "quick")}
        d["processes"] = list(self.processes)
        d["outputs"] = [o.to_dict() for o in self.outputs]
        return d


def resolve(name_or_path: str | Path) -> Path:
    if str(name_or_path) in BUILTIN:
        return BUILTIN[str(name_or_path)]
    p = Path(name_or_path)
    if not p.exists():
        raise UserError(f"{p}: no such scenario file (built-in names: {', '.join(BUILTIN)})")
    return p


def load_scenario(name_or_path: str | Path) -> Scenario:
    path = resolve(name_or_path)
    raw = load_yaml(path)
    for k in raw:
        if k not in _TOP:
            raise UserError(f"{path}: {k}: unknown key (expected one of {list(_TOP)})")
    d = plain(raw, str(path))
    if d.get("format") != FORMAT:
        raise UserError(f"{path}: format: expected {FORMAT!r}, got {d.get('format')!r}")

    def file(key):
        p = path.parent / str(require(d, key, str(path)))
        if not p.exists():
            raise UserError(f"{path}: {key}: no such file {p}")
        return p
    tr = require(d, "train", str(path))
    so = require(d, "solver", str(path))
    pe = require(d, "pem", str(path))
    grid = require(pe, "frequency_grid", f"{path}: pem")
    for sec, node in (("train", tr), ("solver", so), ("pem", pe), ("pem.frequency_grid", grid)):
        if not isinstance(node, dict):
            raise UserError(f"{path}: {sec}: expected a mapping, got {type(node).__name__}")
        bad = [k for k in node if k not in _SECTION_KEYS[sec]]
        if bad:
            raise UserError(f"{path}: {sec}.{bad[0]}: unknown key (expected one of {list(_SECTION_KEYS[sec])})")
    w = f"{path}: train"
    ws, wp, wg = f"{path}: solver", f"{path}: pem", f"{path}: pem.frequency_grid"
    outs = []
    for i, o in enumerate(require(d, "outputs", str(path)) or []):
        wo = f"{path}: outputs[{i}]"
        if not isinstance(o, dict) or "name" not in o:
            raise UserError(f"{wo}: expected a mapping with a name")
        bad = [k for k in o if k not in _OUT_KEYS]
        if bad:
            raise UserError(f"{wo}.{bad[0]}: unknown key (expected one of {list(_OUT_KEYS)})")
        outs.append(ResponsePoint(
            name=str(o["name"]), quantity=str(o.get("quantity", "acceleration")), direction=str(o.get("direction", "z")),
            car=int(o["car"]) if "car" in o else None, body=o.get("body"),
            point_m=tuple(float(v) for v in o["point_m"]) if "point_m" in o else None, loop=o.get("loop"),
            girder_x_m=float(o["girder_x_m"]) if "girder_x_m" in o else None, rail=o.get("rail")))
    procs = tuple(pe.get("processes", PROCESSES))
    cutoff = so.get("mode_cutoff_hz")
    return Scenario(
        name=str(d.get("name", path.stem)), path=path, vehicle_path=file("vehicle"), girder_path=file("girder"),
        irregularity_path=file("irregularity"),
        cars=int(number(tr, "cars", w, positive=True)), car_length_m=number(tr, "car_length_m", w, positive=True),
        speed_mps=number(tr, "speed_mps", w, positive=True), front_start_m=number(tr, "front_start_m", w),
        time_step_s=number(so, "time_step_s", ws, positive=True), duration_s=number(so, "duration_s", ws, positive=True),
        girder_model=str(so.get("girder_model", "modal")), mode_cutoff_hz=None if cutoff is None else float(cutoff),
        coupling=str(so.get("coupling", "separated")), tolerance=number(so, "tolerance", ws, default=1e-8, positive=True),
        hold=str(so.get("hold", "linear")),
        grid_min_rad_per_m=number(grid, "min_rad_per_m", wg, positive=True),
        grid_max_rad_per_m=number(grid, "max_rad_per_m", wg, positive=True),
        grid_n=int(number(grid, "n", wg, positive=True)), grid_spacing=str(grid.get("spacing", "linear")),
        grid_weights=str(grid.get("weights", "bin")), start=str(pe.get("start", "steady")),
        psd_time_step_s=number(pe, "psd_time_step_s", wp, default=0.05, positive=True), processes=procs,
        outputs=tuple(outs), quick=dict(d.get("quick") or {}))


@dataclass
class Built:
    """Everything assembled for a scenario (the one-time costs)."""
    scenario: Scenario
    solver: CoupledSolver
    irregularity: TrackIrregularity
    grid: FrequencyGrid
    train: Train

    def pem(self) -> PseudoExcitation3D:
        sc = self.scenario
        every = max(int(round(sc.psd_time_step_s / sc.time_step_s)), 1)
        return PseudoExcitation3D(self.solver, self.irregularity, self.grid, processes=sc.processes,
                                  start=sc.start, psd_every=every)

    def on_girder_s(self) -> list[dict]:
        g = self.solver.rails.girder
        return [dict(zip(("car", "enter_s", "leave_s"), (c,) + self.train.on_span_s(c, g.node_x_m[0], g.node_x_m[-1])))
                for c in range(1, self.train.n_cars + 1)]


def build(sc: Scenario) -> Built:
    ss = build_state_space(load_vehicle(sc.vehicle_path))
    gspec = load_girder(sc.girder_path)
    layout = RailLayout.from_dict(require(load_yaml(sc.girder_path), "rails", str(sc.girder_path)),
                                  f"{sc.girder_path}: rails")
    irr = load_irregularity(sc.irregularity_path)
    if abs(irr.half_gauge_m - layout.half_gauge_m) > 1e-9 or abs(ss.vehicle.data.half_gauge_m - layout.half_gauge_m) > 1e-9:
        raise UserError(f"{sc.path}: the rail half gauge differs between the girder ({layout.half_gauge_m} m), "
                        f"irregularity ({irr.half_gauge_m} m) and vehicle ({ss.vehicle.data.half_gauge_m} m) files")
    girder = assemble_girder(gspec)
    dyn = girder_dynamics(girder, sc.girder_model, sc.mode_cutoff_hz)
    train = Train(sc.cars, sc.car_length_m, sc.speed_mps, sc.front_start_m, ss.magnet_x_m)
    solver = CoupledSolver(ss, train, sc.time_step_s, dyn, RailInterpolation(girder, layout), coupling=sc.coupling,
                           tolerance=sc.tolerance, hold=sc.hold, outputs=sc.outputs)
    grid = FrequencyGrid.build(sc.grid_min_rad_per_m, sc.grid_max_rad_per_m, sc.grid_n, sc.grid_spacing,
                               sc.grid_weights)
    if np.any(train.magnet_positions_m(0.0) >= girder.node_x_m[0]):
        raise UserError(f"{sc.path}: train.front_start_m: the train must start off the girder (a magnet is at "
                        f"{train.magnet_positions_m(0.0).max():.4g} m, the girder starts at {girder.node_x_m[0]:.4g} m)")
    return Built(sc, solver, irr, grid, train)
