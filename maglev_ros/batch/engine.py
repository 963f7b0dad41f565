"""Running a batch's jobs on Dask (``dask.distributed``): a ``LocalCluster`` of worker processes
by default, or an existing cluster by its scheduler's address.

Workers are processes with one thread each (the verbs hold the GIL in numpy-light Python and
numba code), BLAS/OpenMP at one thread per worker (the nanny's environment, and threadpoolctl in
each job), so N workers use N cores; glibc's allocator keeps freed memory as in a plain process
(:data:`maglev_ros.parallel.MALLOC_ENV`; Dask's own 64 KiB trim threshold cost a job 25 % in page faults). The twin's numba kernels are cached next to their source
(``cache=True``); numba writes its cache files under a temporary name and renames them
(``numba.core.caching``), so workers sharing the cache never read a half-written file (at worst
one worker's index entry overwrites another's and a kernel is compiled again).

A worker that dies (killed, out of memory) takes its task with it: the scheduler gives the task
to another worker, up to ``allowed-failures`` times (Dask's setting, 3 by default), after which
it is a ``KilledWorker`` error recorded as the job's failure. A job's outputs appear by one
rename (:func:`maglev_ros.batch.jobs.run_job`), so every recording has its directory exactly
once whatever ran twice or died halfway.
"""
from __future__ import annotations

import contextlib
import os
import secrets
import shutil
from pathlib import Path

from maglev_ros import outputs
from maglev_ros.batch.jobs import (FAILED_DIR, WORK_DIR, Job, JobResult, job_key, read_done,
                                   read_failed, run_job)
from maglev_ros.errors import UserError
from maglev_ros.parallel import MALLOC_ENV

ONE_THREAD_ENV = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1",
                  "NUMEXPR_NUM_THREADS": "1", "VECLIB_MAXIMUM_THREADS": "1"}


def cores() -> int:
    """Cores this process may use (its CPU affinity, not the machine's count)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:
        return os.cpu_count() or 1


@contextlib.contextmanager
def dask_client(scheduler: str | None = None, workers: int | None = None,
                allowed_failures: int | None = None):
    """A ``distributed.Client``: to ``scheduler`` (tcp://host:port) when given, else to a new
    ``LocalCluster`` of ``workers`` processes (default: the cores), closed at the end."""
    import dask
    from distributed import Client, LocalCluster
    if scheduler:
        try:
            client = Client(scheduler, timeout="30s")
        except (OSError, TimeoutError) as exc:
            raise UserError(f"--scheduler {scheduler}: cannot connect ({str(exc).splitlines()[0]})") from None
        try:
            yield client
        finally:
            client.close()
        return
    n = workers or cores()
    # a worker holds only the task it runs (saturation 1.0: long tasks gain nothing from a queue
    # on the worker), so a worker's death counts against that task alone
    cfg = {"distributed.scheduler.worker-saturation": 1.0,
           "distributed.nanny.pre-spawn-environ": {
               **dask.config.get("distributed.nanny.pre-spawn-environ", {}), **ONE_THREAD_ENV, **MALLOC_ENV}}
    if allowed_failures is not None:
        cfg["distributed.scheduler.allowed-failures"] = allowed_failures
    with dask.config.set(cfg):
        cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True, dashboard_address=None,
                               env=dict(ONE_THREAD_ENV))
    try:
        with Client(cluster) as client:
            yield client
    finally:
        cluster.close()


@contextlib.contextmanager
def _out_lock(out: Path):
    """One batch at a time in an output directory (a second one would remove the first's work)."""
    import fcntl
    fh = open(out / ".lock", "a+")
    try:
        try:
            fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            fh.seek(0)
            holder = fh.read().strip() or "another process"
            raise UserError(f"--out {out}: another batch is running in this directory (pid {holder})") from None
        fh.seek(0)
        fh.truncate()
        fh.write(str(os.getpid()))
        fh.flush()
        yield
    finally:
        fh.close()


def prepare_out(out: Path) -> None:
    outputs.check_dir(out, "--out")
    with outputs.Batch() as b:
        b.make_dir(out, "--out")
    (out / FAILED_DIR).mkdir(exist_ok=True)


def run_jobs(jobs: list[Job], out, client, progress) -> tuple[list[JobResult], set[str]]:
    """Run every job of ``jobs`` not done in ``out`` on the client's cluster; returns the results
    of all jobs (done earlier, done now, failed) in ``jobs``' order and the names run now."""
    out = Path(out).resolve()
    prepare_out(out)
    with _out_lock(out):
        # left-overs of a worker killed on an earlier run: never counted, removed
        shutil.rmtree(out / WORK_DIR, ignore_errors=True)
        results: dict[str, JobResult] = {}
        todo = []
        for j in jobs:
            done = read_done(out, j)
            if done is not None:
                results[j.name] = done
            else:
                todo.append(j)
        progress.stage(f"{len(todo)} to run, {len(jobs) - len(todo)} done earlier", total=len(todo))
        if todo:
            token = secrets.token_hex(3)
            futures = client.map(run_job, todo, [str(out)] * len(todo), key=[job_key(j, token) for j in todo],
                                 pure=False)
            by_key = {f.key: j for f, j in zip(futures, todo)}
            from distributed import as_completed
            for fut in as_completed(futures):
                job = by_key[fut.key]
                try:
                    res = fut.result()
                except Exception as exc:       # the task itself failed: a killed worker (KilledWorker), ...
                    msg = str(exc).splitlines()[0] if str(exc) else ""
                    res = JobResult(job.name, job.verb, job.bag, "failed",
                                    error=f"{type(exc).__name__}: {msg}".rstrip(": "),
                                    ambient=job.ambient, spec=job.spec())
                if res.status != "done":
                    prev = read_failed(out, job.name)
                    outputs.write_json(out / FAILED_DIR / f"{job.name}.json", res.to_dict(), indent=1, default=str)
                    if prev is None or prev.error != res.error:
                        progress.note(f"{job.name}: failed: {res.error}")
                results[job.name] = res
                progress.advance(note=f"{job.name} {res.status}")
            shutil.rmtree(out / WORK_DIR, ignore_errors=True)
        return [results[j.name] for j in jobs], {j.name for j in todo}
