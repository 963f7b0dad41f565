"""Small 3D cases for the solver and PEM tests (generated here, no files): a one-body 3D vehicle
on four magnets, a short three-span girder and a reduced paper 001 setting."""
from __future__ import annotations

from maglev_ros.system3d.girder import GirderSpec, assemble_girder
from maglev_ros.system3d.girder_rails import RailInterpolation, RailLayout
from maglev_ros.system3d.irregularity import load_irregularity
from maglev_ros.system3d.solve_coupled import CoupledSolver, ResponsePoint
from maglev_ros.system3d.solve_girder import girder_dynamics
from maglev_ros.system3d.train import Train
from maglev_ros.system3d.vehicle_data import CONFIG_DIR, load_vehicle, vehicle_data_from_dict
from maglev_ros.system3d.vehicle_state_space import build_state_space

SPEED_MPS = 27.77778


def small_vehicle_doc(mass_kg: float = 3200.0) -> dict:
    """One body (y, z, roll, pitch, yaw) on four levitation magnets (one loop each) at x = +-1.5 m
    under the rails at y = +-1 m; lateral damping to the ground (the passive lateral force has none)."""
    loop = dict(nominal_gap_m=0.008, static_current_a=25.0, inductance_h=0.2, resistance_ohm=1.0,
                kp_v_per_m=12300.0, kv_v_s_per_m=764.5, ka_v_s2_per_m=19.1)
    mags = []
    for i, (x, y) in enumerate([(1.5, 1.0), (1.5, -1.0), (-1.5, 1.0), (-1.5, -1.0)]):
        mags.append({"name": f"m{i}", "body": "car", "point_m": [x, y, 0.0], "side": "left" if y > 0 else "right",
                     "role": "levitation", "loop": f"L{i}"})
    return {
        "format": "maglev-vehicle", "absent_dofs": "held", "passive_lateral": "fringing", "pole_width_m": 0.028,
        "half_gauge_m": 1.0,
        "bodies": [{"name": "car", "mass_kg": mass_kg, "inertia_kg_m2": {"xx": 1600.0, "yy": 3000.0, "zz": 3000.0},
                    "centre_m": [0.0, 0.0, 0.3], "dofs": ["y", "z", "rx", "ry", "rz"]}],
        "connections": [{"name": f"lat{k}", "between": ["car", "ground"], "point_m": [x, 0.0, 0.3],
                         "stiffness_n_per_m": {"y": 0.0}, "damping_n_s_per_m": {"y": 2.0e4}}
                        for k, x in enumerate((1.5, -1.5))],
        "magnets": mags,
        "loops": [dict(id=f"L{i}", **loop) for i in range(4)],
    }


def small_girder(spans=(20.0, 30.0, 20.0), elements: int = 6):
    """Three-span continuous girder (a scaled box), rails 2 x 1 m apart, 1 m above the shear centre."""
    spec = GirderSpec.from_dict({
        "name": "small", "spans_m": list(spans), "elements_per_span": elements, "start_m": 0.0,
        "section": {"axial_rigidity_n": 2.0e11, "vertical_bending_rigidity_n_m2": 3.0e10,
                    "lateral_bending_rigidity_n_m2": 1.2e11, "torsional_rigidity_n_m2": 4.0e10,
                    "mass_per_length_kg_m": 8000.0, "polar_mass_kg_m": 9000.0},
        "supports": [{"at_support": i, "restrained": ["y", "z", "rx"] + (["x"] if i == 1 else [])}
                     for i in range(len(spans) + 1)],
        "damping": {"kind": "rayleigh", "ratio": 0.02, "frequencies_hz": [2.0, 10.0]},
    })
    girder = assemble_girder(spec)
    return girder, RailInterpolation(girder, RailLayout(1.0, 1.0, 0.0))


def paper_irregularity():
    return load_irregularity(CONFIG_DIR / "paper001_irregularity.yaml")


def paper_state_space():
    return build_state_space(load_vehicle(CONFIG_DIR / "paper001_vehicle.yaml"))


PAPER_OUTPUTS = (
    ResponsePoint("cabin_acc_z", car=1, body="cabin", direction="z"),
    ResponsePoint("cabin_acc_y", car=1, body="cabin", direction="y"),
    ResponsePoint("bogie_acc_z", car=1, body="bogie_l3", direction="z"),
    ResponsePoint("current", car=1, quantity="current", loop="l3_front"),
    ResponsePoint("mid_acc_z", girder_x_m=35.0, direction="z"),
    ResponsePoint("mid_acc_y", girder_x_m=35.0, direction="y"),
    ResponsePoint("mid_disp_z", girder_x_m=35.0, quantity="displacement", direction="z"),
)


def reduced_paper_solver(ss, coupling="separated", time_step_s=0.01, cutoff_hz=12.0, outputs=PAPER_OUTPUTS,
                         front_start_m=-9.0, tolerance=1e-11, n_cars=1, vehicle_basis="eigen"):
    """Paper 001's vehicle (1 car) over the small girder, modal girder with few modes."""
    girder, rails = small_girder()
    dyn = girder_dynamics(girder, "modal", cutoff_hz)
    train = Train(n_cars, 16.1, SPEED_MPS, front_start_m, ss.magnet_x_m)
    return CoupledSolver(ss, train, time_step_s, dyn, rails, coupling=coupling, tolerance=tolerance,
                         outputs=outputs, vehicle_basis=vehicle_basis)


def small_vehicle_state_space(mass_kg: float = 3200.0):
    return build_state_space(vehicle_data_from_dict(small_vehicle_doc(mass_kg), "small"))


def mirror_side(side: str) -> str:
    return "right" if side == "left" else "left"


