"""A Dask cluster started as on separate machines: ``dask scheduler`` and ``dask worker`` processes
(the CLIs of the venv), on loopback with random ports; for the batch tests and bench."""
from __future__ import annotations

import contextlib
import json
import os
import subprocess
import sys
import time
from pathlib import Path

from rosgraph import stop_processes

DASK = str(Path(sys.executable).with_name("dask"))


@contextlib.contextmanager
def dask_cli_cluster(directory, n_workers: int = 2, timeout_s: float = 120.0, env: dict | None = None):
    """Yield the scheduler's address once ``n_workers`` single-thread workers (each its own
    ``dask worker`` process) have joined; every process is stopped at the end."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    sched_file = directory / "scheduler.json"
    env = {**os.environ, **(env or {})}
    procs = []
    logs = []
    try:
        log = open(directory / "scheduler.log", "w")
        logs.append(log)
        procs.append(subprocess.Popen([DASK, "scheduler", "--host", "127.0.0.1", "--port", "0", "--no-dashboard",
                                       "--scheduler-file", str(sched_file)], stdout=log, stderr=subprocess.STDOUT,
                                      env=env))
        t_end = time.monotonic() + timeout_s
        while not sched_file.is_file() or not sched_file.read_text().strip():
            if procs[0].poll() is not None or time.monotonic() > t_end:
                raise RuntimeError(f"dask scheduler did not start: {(directory / 'scheduler.log').read_text()[-2000:]}")
            time.sleep(0.2)
        address = json.loads(sched_file.read_text())["address"]
        for k in range(n_workers):
            log = open(directory / f"worker{k}.log", "w")
            logs.append(log)
            procs.append(subprocess.Popen([DASK, "worker", address, "--nthreads", "1", "--nworkers", "1",
                                           "--no-dashboard", "--host", "127.0.0.1", "--name", f"w{k}"],
                                          stdout=log, stderr=subprocess.STDOUT, env=env))
        from distributed import Client
        with Client(address, timeout="60s") as client:
            client.wait_for_workers(n_workers, timeout=timeout_s)
        yield address
    finally:
        stop_processes(*reversed(procs))
        for log in logs:
            log.close()
