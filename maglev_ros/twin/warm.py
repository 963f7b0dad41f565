"""Compile, or load from numba's on-disk cache, every jitted kernel of the twin before a stream needs it.

``python -m maglev_ros.twin.warm`` (run by ``scripts/install``) and the ``twin`` node at start call
:func:`warm`: it steps a tiny twin (one short span, the default vehicle) through the same
:class:`~maglev_ros.twin.coupling.TwinStepper` path the online twin takes, with both integration
methods and with the current limit on, so every argument type the kernel sees is compiled once.
The first call on a machine compiles (tens of seconds on a loaded CPU) and writes numba's cache
beside ``coupling.py``; later processes load it (about a second). Without numba the kernel is plain
Python and there is nothing to warm. No rclpy here: the node reports ``ready`` when this returns.
"""
from __future__ import annotations

import sys
import time
from dataclasses import dataclass


@dataclass(frozen=True)
class KernelWarmth:
    """What :func:`warm` did for one jitted function."""
    name: str
    signatures: int            # compiled variants now in the process
    compiled: int              # of them compiled in this call
    loaded: int                # of them loaded from numba's cache in this call

    def to_dict(self) -> dict:
        return dict(self.__dict__)


@dataclass(frozen=True)
class WarmResult:
    numba: bool
    kernels: tuple[KernelWarmth, ...]
    seconds: float

    @property
    def compiled(self) -> int:
        return sum(k.compiled for k in self.kernels)

    def summary(self) -> str:
        if not self.numba:
            return f"numba not available: the twin's kernel runs as plain Python (checked in {self.seconds:.1f} s)"
        # functions called only inside the kernel come with its cached code: not listed
        parts = ", ".join(f"{k.name} {'compiled' if k.compiled else 'loaded from cache'}"
                          for k in self.kernels if k.compiled or k.loaded) or "already in this process"
        return f"twin kernels warm in {self.seconds:.1f} s: {parts}"


def _dispatchers() -> dict:
    from maglev_ros.twin import coupling, guideway
    return {"kernel": coupling._KERNEL, "free_steps": coupling._FREE, "mvt_into": coupling._mvt_into,
            "absmax": coupling._absmax, "sat_newton_step": coupling._sat_newton_step,
            "hermite_rows": guideway._HERMITE_ROWS, "locate_points": guideway._LOCATE}


def _counts(disp) -> tuple[int, int, int]:
    """(signatures, cache hits, cache misses) of a numba dispatcher."""
    st = disp.stats
    return len(disp.overloads), sum(st.cache_hits.values()), sum(st.cache_misses.values())


def _step_tiny_twins() -> None:
    """A short run of a one-span twin with each method, and with the current limit (the kernel's
    saturation branch): the argument types of every call the online twin makes."""
    import numpy as np

    from maglev_ros.twin.coupling import TwinStepper
    from maglev_ros.twin.design import twin_config
    cfg = twin_config()
    line = [{"id": "W1", "start_m": 0.0, "length_m": 24.0}]
    irr = (np.array([-100.0, 100.0]), np.zeros(2))
    for method, limit in (("newmark", None), ("separated", None), ("newmark", 5.0)):
        st = TwinStepper(cfg, line, sensors={"mid": 12.0}, irregularity=irr, fs_out_hz=1000.0,
                         start_position_m=2.0, start_speed_mps=5.0, method=method, dt_max_s=5e-4,
                         current_limit_a=limit)
        st.advance(0.01, 5.0)


def warm() -> WarmResult:
    """Make every jitted kernel of the twin ready in this process; see the module docstring."""
    t0 = time.perf_counter()
    from maglev_ros.twin import coupling
    if not coupling.HAVE_NUMBA:
        _step_tiny_twins()
        return WarmResult(False, (), time.perf_counter() - t0)
    before = {n: _counts(d) for n, d in _dispatchers().items()}
    _step_tiny_twins()
    kernels = []
    for n, d in _dispatchers().items():
        sig, hit, miss = _counts(d)
        s0, h0, m0 = before[n]
        # a miss that found nothing to load was compiled; a hit was loaded
        kernels.append(KernelWarmth(n, sig, compiled=miss - m0, loaded=hit - h0))
    return WarmResult(True, tuple(kernels), time.perf_counter() - t0)


def main(argv=None) -> int:
    res = warm()
    print(res.summary(), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
