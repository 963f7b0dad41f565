"""``maglev-ros batch --scheduler``: a scheduler and two workers started by the ``dask`` CLIs on
loopback (as on separate machines) give the outputs and the summary of the local cluster."""
from __future__ import annotations

import csv
import json
import os

import numpy as np
import pytest

from bagfactory import GUIDEWAY_ACCEL, VEHICLE_POSITION, make_metadata, write_contract_bag
from dask_cluster import dask_cli_cluster
from maglev_ros.cli import main

N = 4
# what depends on where and when a job ran, not on its result
VOLATILE = {"elapsed_s", "worker", "ran_this_run"}


@pytest.fixture(scope="module")
def archive(tmp_path_factory):
    """Ambient and pass recordings an hour apart (info runs on both kinds)."""
    d = tmp_path_factory.mktemp("archive")
    rng = np.random.default_rng(4)
    for k in range(N):
        fs = 200.0
        topics = {GUIDEWAY_ACCEL: (("G1LV", "G2LV"), ("m/s^2",) * 2, fs, rng.standard_normal((300 + 50 * k, 2)))}
        kind = "pass" if k % 2 else "ambient"
        if kind == "pass":
            t = np.arange(150) / 100.0
            topics[VEHICLE_POSITION] = (("position_m", "speed_mps"), ("m", "m/s"), 100.0,
                                        np.stack([20.0 * t, np.full(t.size, 20.0)], axis=1))
        write_contract_bag(d / f"rec{k}.mcap", make_metadata(topics, kind=kind), topics,
                           t0_ns=(1_790_000_000 + k * 3600) * 10**9)
    return d


def _table(path) -> list[dict]:
    with open(path, newline="") as fh:
        return [{k: v for k, v in r.items() if k not in VOLATILE} for r in csv.DictReader(fh)]


def test_scheduler_and_cli_workers_give_the_local_outputs(archive, tmp_path):
    local, remote = tmp_path / "local", tmp_path / "remote"
    pattern = str(archive / "*.mcap")
    assert main(["batch", "info", "--glob", pattern, "--out", str(local), "--workers", "2", "--quiet"]) == 0
    with dask_cli_cluster(tmp_path / "cluster", n_workers=2) as address:
        assert main(["batch", "info", "--glob", pattern, "--out", str(remote), "--scheduler", address,
                     "--quiet"]) == 0
    table = _table(remote / "summary.csv")
    assert table == _table(local / "summary.csv")
    assert [r["name"] for r in table] == [f"rec{k}" for k in range(N)]
    assert [r["run_kind"] for r in table] == ["ambient", "pass"] * (N // 2)
    for k in range(N):
        a = json.loads((local / f"rec{k}" / "info.json").read_text())
        b = json.loads((remote / f"rec{k}" / "info.json").read_text())
        assert b == a and a["ok"]
        job = json.loads((remote / f"rec{k}" / "job.json").read_text())
        # ran in a CLI worker's process, with BLAS at one thread (the nanny's environment)
        assert not job["worker"].endswith(f":{os.getpid()}")
        assert job["blas_threads"] and all(t[1] == 1 for t in job["blas_threads"])
