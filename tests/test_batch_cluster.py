"""``maglev-ros batch --scheduler``: a scheduler and two workers started by the ``dask`` CLIs on
loopback (as on separate machines) give the outputs and the summary of the local cluster, and
those of a direct run of the verb."""
from __future__ import annotations

import csv
import json

import numpy as np
import pytest

from bagfactory import GUIDEWAY_ACCEL, make_metadata, write_contract_bag
from dask_cluster import dask_cli_cluster
from maglev_ros.cli import main
from modal_data import guideway_model, simulate_ambient

N = 2
# what depends on where and when a job ran, not on its result
VOLATILE = {"elapsed_s", "worker", "ran_this_run"}


@pytest.fixture(scope="module")
def archive(tmp_path_factory):
    d = tmp_path_factory.mktemp("archive")
    model = guideway_model(None)
    fs = 200.0
    for k in range(N):
        y = simulate_ambient(model, fs, 8.0, noise_frac=0.05, seed=k)[:, :6]
        topics = {GUIDEWAY_ACCEL: (model.channels[:6], ("m/s^2",) * 6, fs, y)}
        write_contract_bag(d / f"amb{k}.mcap", make_metadata(topics, kind="ambient"), topics,
                           t0_ns=(1_790_000_000 + k * 3600) * 10**9)
    return d


def _table(path) -> list[dict]:
    with open(path, newline="") as fh:
        return [{k: v for k, v in r.items() if k not in VOLATILE} for r in csv.DictReader(fh)]


def test_scheduler_and_cli_workers_give_the_local_outputs(archive, tmp_path):
    local, remote = tmp_path / "local", tmp_path / "remote"
    pattern = str(archive / "*.mcap")
    assert main(["batch", "modes", "--glob", pattern, "--out", str(local), "--workers", "2", "--quiet"]) == 0
    with dask_cli_cluster(tmp_path / "cluster", n_workers=2) as address:
        assert main(["batch", "modes", "--glob", pattern, "--out", str(remote), "--scheduler", address,
                     "--quiet"]) == 0
        jobs = [json.loads((remote / f"amb{k}" / "job.json").read_text()) for k in range(N)]
    assert _table(remote / "summary.csv") == _table(local / "summary.csv")
    for k in range(N):
        a = json.loads((local / f"amb{k}" / "modes.json").read_text())
        b = json.loads((remote / f"amb{k}" / "modes.json").read_text())
        assert b == a and len(a["modes"]) >= 1
        assert (remote / f"amb{k}" / "modes.png").stat().st_size > 10000
    # and each is the direct run's
    direct = tmp_path / "direct.json"
    assert main(["modes", str(archive / "amb0.mcap"), "--json", str(direct)]) == 0
    assert json.loads(direct.read_text()) == json.loads((local / "amb0" / "modes.json").read_text())
    # the jobs ran in the CLI workers' processes, not in this one
    import os
    assert all(not j["worker"].endswith(f":{os.getpid()}") for j in jobs)
