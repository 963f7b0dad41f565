"""``maglev-ros batch`` on a LocalCluster: a dozen small recordings, workers killed mid-run (one
job kills its worker once and is retried, one kills it on every attempt and is failed), a rerun
that redoes only the failure; every output exactly once, each equal to a direct run of the verb,
and the summary (CSV read back by csv, Parquet by pyarrow) saying so."""
from __future__ import annotations

import csv
import json

import numpy as np
import pytest

from bagfactory import GUIDEWAY_ACCEL, make_metadata, write_contract_bag
from maglev_ros.cli import main

N = 12
DAY_NS = 86400 * 10**9
T0_NS = 1_790_000_000 * 10**9


def _topics(seed: int) -> dict:
    rng = np.random.default_rng(seed)
    fs = 200.0
    t = np.arange(int(2.0 * fs)) / fs
    y = np.stack([np.sin(2 * np.pi * (5 + j + seed) * t) + 0.1 * rng.standard_normal(t.size)
                  for j in range(3)], axis=1)
    return {GUIDEWAY_ACCEL: (("G1LV", "G2LV", "G3LV"), ("m/s^2",) * 3, fs, y)}


@pytest.fixture(scope="module")
def archive(tmp_path_factory):
    """12 recordings a day apart, listed in the manifest out of time order."""
    d = tmp_path_factory.mktemp("archive")
    order = [5, 0, 11, 3, 8, 1, 10, 2, 7, 4, 9, 6]
    bags = {}
    for k in range(N):
        topics = _topics(k)
        bags[f"rec{k:02d}"] = write_contract_bag(d / f"rec{k:02d}.mcap", make_metadata(topics, kind="ambient"),
                                                 topics, t0_ns=T0_NS + k * DAY_NS)
    manifest = d / "manifest.csv"
    manifest.write_text("bag,name\n" + "".join(f"{bags[f'rec{k:02d}'].name},rec{k:02d}\n" for k in order))
    return d, manifest, bags


def _direct_info(bag, capsys) -> dict:
    capsys.readouterr()
    assert main(["info", str(bag), "--json"]) == 0
    return json.loads(capsys.readouterr().out)


def _csv_rows(path) -> list[dict]:
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def test_killed_workers_rerun_every_output_once(archive, tmp_path, monkeypatch, capsys):
    import pyarrow.parquet as pq
    d, manifest, bags = archive
    out = tmp_path / "out"
    kill = tmp_path / "kill.json"
    kill.write_text(json.dumps({"rec03": "once", "rec07": "always"}))
    monkeypatch.setenv("MAGLEV_BATCH_TEST_KILL", str(kill))     # inherited by the cluster's workers
    argv = ["batch", "info", "--manifest", str(manifest), "--out", str(out), "--workers", "2",
            "--allowed-failures", "1", "--quiet"]
    assert main(argv) == 1                                       # rec07 failed: exit 1, one line
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "rec07" in err[0] and "failed" in err[0]
    # rec03's worker was killed (its marker) and the task retried; rec07 failed on its second death
    assert (tmp_path / "kill.json.rec03.killed").exists()
    rows = {r["name"]: r for r in _csv_rows(out / "summary.csv")}
    assert set(rows) == set(bags)
    assert rows["rec07"]["status"] == "failed" and "KilledWorker" in rows["rec07"]["error"]
    assert all(r["status"] == "done" and r["error"] == "" for n, r in rows.items() if n != "rec07")
    assert not (out / "rec07").exists()                          # a killed job leaves no directory
    assert json.loads((out / ".failed" / "rec07.json").read_text())["status"] == "failed"
    assert not any((out / ".work").glob("*"))
    first = {n: (out / n / "job.json").stat().st_mtime_ns for n in bags if n != "rec07"}

    monkeypatch.delenv("MAGLEV_BATCH_TEST_KILL")
    assert main(argv) == 0
    rows = _csv_rows(out / "summary.csv")
    # rows in recording-time order, whatever the manifest's
    assert [r["name"] for r in rows] == [f"rec{k:02d}" for k in range(N)]
    assert all(r["status"] == "done" for r in rows)
    assert [r["name"] for r in rows if r["ran_this_run"] == "True"] == ["rec07"]
    # exactly once: the earlier directories untouched, no other directory, no failure record left
    assert {n: (out / n / "job.json").stat().st_mtime_ns for n in first} == first
    dirs = sorted(p.name for p in out.iterdir() if p.is_dir() and not p.name.startswith("."))
    assert dirs == sorted(bags)
    assert not (out / ".failed" / "rec07.json").exists()
    # every output equals the direct run, and the table's figures are those of the direct run
    for r in rows:
        direct = _direct_info(bags[r["name"]], capsys)
        assert json.loads((out / r["name"] / "info.json").read_text()) == direct
        assert int(r["message_count"]) == direct["message_count"]
        assert float(r["duration_s"]) == pytest.approx(direct["data_span"]["duration_s"], rel=1e-12)
        assert float(r["time_unix_s"]) == pytest.approx(direct["data_span"]["start_s"], abs=1e-6)
    table = pq.read_table(out / "summary.parquet").to_pylist()
    assert [t["name"] for t in table] == [r["name"] for r in rows]
    assert [t["message_count"] for t in table] == [int(r["message_count"]) for r in rows]
    assert all(t["status"] == "done" for t in table)
    html = (out / "index.html").read_text()
    assert all(f"href='{n}/info.json'" in html for n in bags) and "trend.png" in html
    assert (out / "trend.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # BLAS at one thread in the workers (as recorded by each job)
    for n in bags:
        threads = json.loads((out / n / "job.json").read_text())["blas_threads"]
        assert threads and all(t[1] == 1 for t in threads)


def test_local_workers_keep_freed_memory_as_a_plain_process():
    """Dask's nanny starts workers with a 64 KiB malloc trim threshold (every freed numpy temporary
    goes back to the kernel: a diagnose job ran 25 % slower in page faults); ours set glibc's
    thresholds before the worker starts, and a job sets them again in a worker it did not start."""
    import os

    from maglev_ros.batch.engine import dask_client
    from maglev_ros.parallel import MALLOC_ENV
    with dask_client(workers=1) as client:
        seen = client.run(lambda: {k: os.environ.get(k) for k in (*MALLOC_ENV, "OMP_NUM_THREADS")})
    (env,) = seen.values()
    assert env == {**MALLOC_ENV, "OMP_NUM_THREADS": "1"}, env
