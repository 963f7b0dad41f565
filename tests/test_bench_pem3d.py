"""bench/bench_pem3d.py on a tiny case (a one-body 3D vehicle over a short girder): the three
methods' SDs agree and the JSON has every column; no timing assertion."""
from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

from maglev_ros.system3d.solve_coupled import CoupledSolver, ResponsePoint
from maglev_ros.system3d.solve_girder import girder_dynamics
from maglev_ros.system3d.train import Train
from system3d_cases import SPEED_MPS, paper_irregularity, small_girder, small_vehicle_state_space

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))

import bench_pem3d as bp  # noqa: E402


@pytest.fixture(scope="module")
def result():
    ss = small_vehicle_state_space()
    girder, rails = small_girder()
    dyn = girder_dynamics(girder, "modal", 8.0)
    train = Train(1, 4.0, SPEED_MPS, -3.0, ss.magnet_x_m)
    outs = (ResponsePoint("z", car=1, body="car", direction="z"), ResponsePoint("y", car=1, body="car", direction="y"),
            ResponsePoint("girder_z", girder_x_m=35.0, direction="z"))
    sol = CoupledSolver(ss, train, 0.005, dyn, rails, coupling="separated", tolerance=1e-10, outputs=outs)
    case = bp.Case("tiny", sol, paper_irregularity(), 500, "log")
    lines = []
    out = bp.bench(case, n_freq0=8, max_freq=64, mc_se=0.02, mc_pilot=64, mc_batch=128, mc_max=1500, seed=3,
                   log=lines.append)
    return out, lines


def test_methods_agree(result):
    out, _ = result
    for name, a in out["agreement"].items():
        # FBF is the same linear superposition as PEM, written per input point with the cross spectrum
        assert a["sd_fbf"] == pytest.approx(a["sd_pem"], rel=1e-8), name
        # MC: independent band-exact samples; within 3 of its standard errors plus the grid tolerance
        assert abs(a["sd_mc"] / a["sd_pem"] - 1) <= 3 * a["mc_se_rel"] + out["freq_tol"], name
        assert a["mc_se_rel"] <= 0.03, name


def test_json_has_every_column(result):
    out, lines = result
    back = json.loads(json.dumps(out))
    assert {"n_freq", "grid_study", "grid_study_s", "setup_s", "methods", "ratios", "agreement"} <= set(back)
    for k in ("pem", "fbf", "mc"):
        assert {"columns", "steps", "column_steps", "prepare_s", "loop_s", "loop_cpu_s", "loop_us_per_column_step",
                "timed_columns", "extrapolated"} <= set(back["methods"][k]), k
    assert back["methods"]["fbf"]["columns"] == back["n_freq"] * 1 * 2 * 4      # 1 car x (z, y) x 4 magnets per bin
    assert back["methods"]["pem"]["columns"] == back["n_freq"] * 4
    for k in ("fbf/pem", "mc/pem"):
        assert {"loop_wall", "loop_cpu", "columns", "per_column_step"} <= set(back["ratios"][k])
    st = back["grid_study"]
    assert st[-1]["max_change"] < 0.005 and st[-1]["n_freq"] == back["n_freq"]
    assert any(ln.startswith("ratio fbf/pem") for ln in lines)
