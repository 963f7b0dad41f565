"""Where independent work items run: in this process, in a local process pool, or on a Dask cluster.

An executor has one method, ``map(fn, items, done=None) -> list``: ``fn(item)`` for every item, the
results in the order of ``items`` (``done(i)`` is called in this process as item ``i`` finishes, for
progress). The expensive verbs take one (``diagnose(..., executor=...)``,
``update_from_bags(..., executor=...)``) and hand it their independent items (the hypotheses'
fits, the surrogate's training simulations); with none they run :class:`Serial`, the plain loop.

- :class:`Serial`: the loop in this process (the default: nothing is pickled).
- :class:`LocalPool`: ``concurrent.futures.ProcessPoolExecutor`` with forkserver (spawn where there
  is none) workers, BLAS at one thread in each (two BLAS threads fight over the twin's 34x34
  eigenproblems: 30-35 % more CPU for the same report), numba's on-disk cache loaded read-only as
  in any process.
- :class:`DaskExecutor`: a ``dask.distributed.Client`` (``client.map`` + ``client.gather``).

Work items and functions are serialised with cloudpickle (the catalogue's hypotheses carry lambdas
that the stdlib pickle refuses); the function is serialised once per ``map`` and unpickled once per
worker. The results equal the serial run's only when ``fn`` is pure: a worker's caches (the twin's
simulation cache) may hit or miss differently, so a function must not depend on them.
:func:`one_blas_thread` is what every executor runs its items under, the serial one too, so the
three give the same floating-point results.
"""
from __future__ import annotations

import contextlib
import hashlib
import multiprocessing
import os
from typing import Any, Callable, Iterable

from maglev_ros.errors import UserError

__all__ = ["Executor", "Serial", "LocalPool", "DaskExecutor", "SERIAL", "one_blas_thread", "executor_from_options",
           "add_executor_arguments", "keep_freed_memory", "MALLOC_ENV"]

# glibc's allocator as in a plain process: Dask's nanny starts workers with MALLOC_TRIM_THRESHOLD_=64 KiB,
# which hands every freed numpy temporary back to the kernel; the twin then page-faults ~140k times a
# second (measured: a diagnose job 58 s -> 72 s, 20 % of it system time). 32 MiB mmap threshold is
# glibc's own dynamic ceiling; 128 MiB trim keeps one job's working set.
MALLOC_MMAP_THRESHOLD_B = 32 * 2**20
MALLOC_TRIM_THRESHOLD_B = 128 * 2**20
MALLOC_ENV = {"MALLOC_MMAP_THRESHOLD_": str(MALLOC_MMAP_THRESHOLD_B),
              "MALLOC_TRIM_THRESHOLD_": str(MALLOC_TRIM_THRESHOLD_B)}


@contextlib.contextmanager
def one_blas_thread():
    """BLAS (OpenBLAS, MKL) at one thread inside the block (threadpoolctl; nothing without it)."""
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:            # an optional speed-up only: the results are the same without it
        yield
        return
    with threadpool_limits(limits=1, user_api="blas"):
        yield


class Executor:
    """``map(fn, items, done=None) -> list`` in the order of ``items``; ``close()`` frees workers."""
    workers: int = 1

    def map(self, fn: Callable[[Any], Any], items: Iterable, done: Callable[[int], None] | None = None) -> list:
        raise NotImplementedError

    def close(self) -> None:
        pass

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class Serial(Executor):
    """The plain loop in this process."""

    def map(self, fn, items, done=None) -> list:
        out = []
        with one_blas_thread():
            for i, item in enumerate(items):
                out.append(fn(item))
                if done is not None:
                    done(i)
        return out


SERIAL = Serial()


# --- worker side ----------------------------------------------------------------------------------
_MALLOC_SET = False


def keep_freed_memory() -> None:
    """Set glibc's mmap and trim thresholds in this process (see ``MALLOC_ENV``), once: a worker
    started by someone else's ``dask worker`` gets them at its first task. No-op off glibc."""
    global _MALLOC_SET
    if _MALLOC_SET:
        return
    _MALLOC_SET = True
    try:
        import ctypes
        libc = ctypes.CDLL("libc.so.6")
    except OSError:
        return
    m_trim_threshold, m_mmap_threshold = -1, -3          # malloc.h
    libc.mallopt(m_mmap_threshold, MALLOC_MMAP_THRESHOLD_B)
    libc.mallopt(m_trim_threshold, MALLOC_TRIM_THRESHOLD_B)

_LOADED: dict[str, Callable] = {}       # token -> function, in a worker: unpickled once per map


def _load(token: str, fn_bytes: bytes) -> Callable:
    fn = _LOADED.get(token)
    if fn is None:
        import cloudpickle
        _LOADED.clear()                 # one map at a time: the last function's context is let go
        fn = _LOADED[token] = cloudpickle.loads(fn_bytes)
    return fn


def _call(token: str, fn_bytes: bytes, item_bytes: bytes):
    """Run one item in a worker (pool or Dask): BLAS at one thread, result cloudpickled."""
    import cloudpickle
    keep_freed_memory()
    fn = _load(token, fn_bytes)
    with one_blas_thread():
        return cloudpickle.dumps(fn(cloudpickle.loads(item_bytes)))


def _init_worker() -> None:
    # libraries a work item imports later (torch) start at one thread; BLAS is limited per item
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
        os.environ[var] = "1"


def _cloudpickle():
    try:
        import cloudpickle
    except ImportError:
        raise UserError("--workers/--scheduler: cloudpickle is not installed (pip install cloudpickle)") from None
    return cloudpickle


def _pack(fn) -> tuple[str, bytes]:
    cloudpickle = _cloudpickle()
    fn_bytes = cloudpickle.dumps(fn)
    return hashlib.sha1(fn_bytes).hexdigest(), fn_bytes


def _collect(completed, index_of, n: int, done) -> list:
    """Results in item order from futures as they complete (``index_of(future)``: its item)."""
    cloudpickle = _cloudpickle()
    out: list = [None] * n
    for f in completed:
        i = index_of(f)
        out[i] = cloudpickle.loads(f.result())
        if done is not None:
            done(i)
    return out


class LocalPool(Executor):
    """``workers`` local processes (forkserver where available, else spawn), started on first use and
    kept for later maps until :meth:`close`."""

    def __init__(self, workers: int):
        if int(workers) < 1:
            raise UserError(f"--workers: expected a whole number >= 1, got {workers}")
        self.workers = int(workers)
        self._pool = None

    def _executor(self):
        if self._pool is None:
            from concurrent.futures import ProcessPoolExecutor
            method = "forkserver" if "forkserver" in multiprocessing.get_all_start_methods() else "spawn"
            ctx = multiprocessing.get_context(method)
            if method == "forkserver":
                # imported once in the server, then every worker forks with them loaded
                ctx.set_forkserver_preload(["numpy", "scipy.linalg", "maglev_ros.discrepancy.model"])
            self._pool = ProcessPoolExecutor(self.workers, mp_context=ctx, initializer=_init_worker)
        return self._pool

    def map(self, fn, items, done=None) -> list:
        from concurrent.futures import as_completed
        cloudpickle = _cloudpickle()
        items = list(items)
        if not items:
            return []
        token, fn_bytes = _pack(fn)
        pool = self._executor()
        futs = {pool.submit(_call, token, fn_bytes, cloudpickle.dumps(it)): i for i, it in enumerate(items)}
        try:
            return _collect(as_completed(futs), futs.__getitem__, len(items), done)
        except BaseException:
            for f in futs:
                f.cancel()
            raise

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None


class DaskExecutor(Executor):
    """Items as tasks of a ``dask.distributed.Client`` (given, or connected to ``address`` and then
    closed by :meth:`close`); the function is scattered once to every worker."""

    def __init__(self, client=None, address: str | None = None):
        if client is None:
            if not address:
                raise UserError("--scheduler: expected a Dask scheduler address such as tcp://host:8786")
            try:
                from distributed import Client
            except ImportError:
                raise UserError("--scheduler: dask.distributed is not installed (pip install distributed)") from None
            try:
                client = Client(address, timeout="20s")
            except OSError as exc:
                raise UserError(f"--scheduler {address}: no Dask scheduler answered ({exc})") from None
            self._own = True
        else:
            self._own = False
        self.client = client
        self.workers = max(1, sum(w.get("nthreads", 1) for w in client.scheduler_info().get("workers", {}).values()))

    def map(self, fn, items, done=None) -> list:
        from distributed import as_completed
        cloudpickle = _cloudpickle()
        items = list(items)
        if not items:
            return []
        token, fn_bytes = _pack(fn)
        fn_fut = self.client.scatter(fn_bytes, broadcast=True, hash=False)
        futs = self.client.map(_call, [token] * len(items), [fn_fut] * len(items),
                               [cloudpickle.dumps(it) for it in items], pure=False)
        index = {f.key: i for i, f in enumerate(futs)}
        try:
            return _collect(as_completed(futs), lambda f: index[f.key], len(items), done)
        finally:
            self.client.cancel(futs + [fn_fut])

    def close(self) -> None:
        if self._own:
            self.client.close()


def add_executor_arguments(p) -> None:
    """``--workers N`` and ``--scheduler ADDRESS`` of a verb whose core takes an executor."""
    p.add_argument("--workers", type=int, default=None, metavar="N",
                   help="run the independent fits/simulations on N local worker processes (default: serial)")
    p.add_argument("--scheduler", metavar="ADDRESS", default=None,
                   help="run them on a Dask cluster instead (scheduler address, e.g. tcp://host:8786)")


def executor_from_options(workers: int | None, scheduler: str | None) -> Executor:
    """The executor the verb options ask for (close it after use; :data:`SERIAL` needs nothing)."""
    if workers is not None and scheduler:
        raise UserError("--workers and --scheduler: give one of them, not both")
    if scheduler:
        return DaskExecutor(address=scheduler)
    if workers is not None:
        if workers < 1:
            raise UserError(f"--workers: expected a whole number >= 1, got {workers}")
        return SERIAL if workers == 1 else LocalPool(workers)
    return SERIAL

