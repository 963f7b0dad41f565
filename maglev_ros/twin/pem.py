"""Random vibration of a linear(ised) moving vehicle/guideway system by the pseudo-excitation
method (PEM), with a Monte Carlo peer on the same integrator (no rclpy).

Model
-----
Any linear time-varying second-order system

    M(t) q'' + C(t) q' + K(t) q = f_det(t) + B_r(t) r(t) + B_rd(t) r'(t)

where r(t) holds the guideway irregularity under each input point (magnet) k,
r_k(t) = r(x_ref(t) + d_k), x_ref(t) = x0 + v t (constant speed v, offsets d_k per the
recording contract, negative behind the reference point), r' = dr/dt = v dr/dx. M, C, K may
change with time because the magnets move along the guideway (mode shapes at the magnet
positions); M may be non-symmetric (acceleration feedback of the levitation control puts the
magnet acceleration into the rail force). Outputs y = Cu q + Cv q' + Ca q'' + Dr r + Drd r'.
A system is described by ``LinearMovingSystem`` (callables returning the matrices at (t, x_ref)).

Pseudo-excitation
-----------------
For a stationary one-sided spatial PSD S(Omega) the frequency axis is split into bins with
exact band integrals W_j = int_bin S dOmega (``ProfilePsd.band_variance``). Bin j drives
r_k(t) = sqrt(W_j) exp(i Omega_j (x_ref(t) + d_k)),  r'_k = i Omega_j v r_k,
from rest; |y_j(t)|^2 / dOmega_j is the evolutionary (time-dependent) PSD of y at Omega_j in
unit^2/(rad/m) (divide by v for unit^2/(rad/s) at omega = v Omega), and sum_j |y_j(t)|^2 its
variance. The deterministic part (static magnet forces = moving vehicle weight on the guideway)
is integrated as one more, real, column: its response is the time-dependent mean. RMS =
sqrt(mean^2 + SD^2), 3-sigma bounds = mean +- 3 SD.

Paper 001 sec. 4.1 scheme: ALL frequencies are integrated together. The state is shaped
(n_dof, 1 + n_freq); one Newmark step factorises the effective stiffness once (real LU; the
complex columns are solved as interleaved real/imaginary columns of one float view) and
updates every frequency with a single multi-right-hand-side solve. ``freq_batch=1`` gives the
classic frequency-by-frequency scheme (one complete complex time integration per frequency)
with the same integrator, used by bench/bench_pem.py as the honest baseline.

Integrator choice: Newmark average acceleration (beta = 1/4, gamma = 1/2, unconditionally
stable, no numerical damping) applied to the MONOLITHIC coupled linear system, so no
vehicle/guideway iteration is needed (paper 001 iterates precise integration against Newmark;
for a linear system the monolithic solve gives the same converged answer). The equation of
motion is enforced at t_{n+1} with the matrices of t_{n+1}.

Written by hand because scipy's ODE solvers cannot batch thousands of complex right-hand sides
through one factorisation per step of a time-varying second-order system, which is the point
of the method.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, NamedTuple, Sequence

import numpy as np
from scipy.linalg import get_lapack_funcs

from maglev_ros.errors import UserError
from maglev_ros.twin.irregularity_psd import ProfilePsd, _check_band, band_from_wavelengths

__all__ = [
    "SystemMatrices",
    "OutputMatrices",
    "LinearMovingSystem",
    "frequency_bins",
    "PseudoExcitation",
    "PemResult",
    "MonteCarlo",
    "MonteCarloResult",
    "linearised_magnet_gains",
    "MagnetGains",
    "vehicle_on_modal_beam",
    "coupled_twin_system",
]

GRAVITY_MPS2 = 9.81


class SystemMatrices(NamedTuple):
    """Matrices of the linear system at one instant (SI).

    mass, damping, stiffness: (n, n); input_r: (n, n_in) generalised force per metre of
    irregularity at each input point; input_r_rate: (n, n_in) per m/s of dr/dt;
    force_det: (n,) deterministic load (e.g. static magnet forces pulling the guideway down).
    """

    mass: np.ndarray
    damping: np.ndarray
    stiffness: np.ndarray
    input_r: np.ndarray
    input_r_rate: np.ndarray
    force_det: np.ndarray


class OutputMatrices(NamedTuple):
    """y = disp q + vel q' + acc q'' + r_gain r + r_rate_gain r' ; (n_out, n) and (n_out, n_in)."""

    disp: np.ndarray
    vel: np.ndarray
    acc: np.ndarray
    r_gain: np.ndarray | None = None
    r_rate_gain: np.ndarray | None = None


@dataclass(frozen=True, eq=False)
class LinearMovingSystem:
    """A linear (time-varying) second-order system excited through moving input points.

    ``matrices_at(t_s, x_ref_m)`` and ``outputs_at(t_s, x_ref_m)`` return the matrices at time t
    with the reference point at x_ref = start_m + speed_mps t. ``input_offsets_m`` (n_in,) are
    the input points' x relative to the reference point (magnet offsets). Set
    ``time_invariant=True`` when the matrices never change (factorised once).
    """

    n_dof: int
    input_offsets_m: np.ndarray
    speed_mps: float
    start_m: float
    matrices_at: Callable[[float, float], SystemMatrices]
    outputs_at: Callable[[float, float], OutputMatrices]
    output_names: tuple[str, ...]
    output_units: tuple[str, ...] = ()
    time_invariant: bool = False
    description: str = ""

    def __post_init__(self) -> None:
        offs = np.atleast_1d(np.asarray(self.input_offsets_m, dtype=float))
        object.__setattr__(self, "input_offsets_m", offs)
        if self.speed_mps <= 0:
            raise UserError(f"LinearMovingSystem.speed_mps: expected > 0, got {self.speed_mps}")
        if not self.output_units:
            object.__setattr__(self, "output_units", tuple("" for _ in self.output_names))
        if len(self.output_units) != len(self.output_names):
            raise UserError("LinearMovingSystem.output_units: expected one unit per output name")

    @property
    def n_inputs(self) -> int:
        return int(self.input_offsets_m.size)

    def position_m(self, t_s: Any) -> Any:
        return self.start_m + self.speed_mps * np.asarray(t_s, dtype=float)


# ============================================================== frequency grid
def frequency_bins(
    psd: ProfilePsd, band_rad_per_m: tuple[float, float], n_freq: int, spacing: str = "log"
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(centres Omega_j, widths dOmega_j, exact band integrals W_j) of n_freq bins tiling the band.

    spacing "log": geometric bins, centre = geometric mean of the edges (suits the ~1/Omega^2..4
    track spectra); "linear": equal widths, arithmetic centres.
    """
    lo, hi = _check_band(band_rad_per_m, "band_rad_per_m")
    if int(n_freq) < 1:
        raise UserError(f"n_freq: expected >= 1, got {n_freq}")
    if spacing == "log":
        edges = np.geomspace(lo, hi, int(n_freq) + 1)
        centre = np.sqrt(edges[:-1] * edges[1:])
    elif spacing == "linear":
        edges = np.linspace(lo, hi, int(n_freq) + 1)
        centre = 0.5 * (edges[:-1] + edges[1:])
    else:
        raise UserError(f"spacing: expected 'log' or 'linear', got {spacing!r}")
    width = np.diff(edges)
    weight = psd.band_variance(edges[:-1], edges[1:])
    return centre, width, weight


# ============================================================== integrator
class _Newmark:
    """Newmark constants for step dt (average acceleration by default)."""

    def __init__(self, dt: float, beta: float, gamma: float) -> None:
        if not (dt > 0):
            raise UserError(f"time_step_s: expected > 0, got {dt}")
        if not (beta > 0 and gamma >= 0.5 and beta >= 0.25 * (0.5 + gamma) ** 2 - 1e-12):
            raise UserError(
                f"Newmark beta/gamma: expected gamma >= 1/2 and beta >= (1/2 + gamma)^2 / 4 "
                f"(unconditionally stable), got beta={beta}, gamma={gamma}"
            )
        self.dt, self.beta, self.gamma = dt, beta, gamma
        self.c0 = 1.0 / (beta * dt * dt)
        self.c1 = gamma / (beta * dt)
        self.c2 = 1.0 / (beta * dt)
        self.c3 = 1.0 / (2.0 * beta) - 1.0
        self.c4 = gamma / beta - 1.0
        self.c5 = 0.5 * dt * (gamma / beta - 2.0)


_GETRF, _GETRS = get_lapack_funcs(("getrf", "getrs"), dtype=np.float64)


class _StepSolver:
    """Solve K_eff X = B for one step. Many columns (>= n): explicit inverse then one GEMM
    (OpenBLAS's triangular solves are slow for short, wide right-hand sides); few columns:
    LAPACK getrf/getrs called directly (no wrapper overhead). Both are one factorisation of
    K_eff per step; each caller gets the faster path for its column count."""

    def __init__(self, n: int, n_cols: int) -> None:
        self.use_inverse = n_cols >= n and n <= 400

    def factor(self, a: np.ndarray) -> None:
        if self.use_inverse:
            try:
                self.inv = np.linalg.inv(a)
            except np.linalg.LinAlgError:
                raise UserError("LinearMovingSystem: singular effective stiffness at a time step") from None
        else:
            self.lu, self.piv, info = _GETRF(a)
            if info != 0:
                raise UserError("LinearMovingSystem: singular effective stiffness at a time step")

    def solve(self, b: np.ndarray) -> np.ndarray:
        if self.use_inverse:
            return self.inv @ b
        x, _info = _GETRS(self.lu, self.piv, b)
        return x


def _blas_single_thread():
    """Context limiting BLAS to one thread: the per-step matrices are small, and OpenBLAS
    threads spin-waiting on a loaded 2-core machine made each tiny solve ~100x slower.
    Uses threadpoolctl when installed, else does nothing."""
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # pragma: no cover - optional dependency
        import contextlib

        return contextlib.nullcontext()
    return threadpool_limits(limits=1, user_api="blas")


def _integrate(
    system: LinearMovingSystem,
    n_steps: int,
    nm: _Newmark,
    n_cols: int,
    excitation: Callable[[int, float, float], tuple[np.ndarray, np.ndarray]],
    det_weight: np.ndarray,
    sink: Callable[[int, np.ndarray], None],
) -> None:
    """Integrate from rest over n_steps steps with n_cols REAL right-hand-side columns (BLAS
    limited to one thread, see ``_blas_single_thread``).

    excitation(i, t, x_ref) -> (R, Rd), each (n_in, n_cols) float; det_weight (n_cols,) scales
    force_det into each column; sink(i, Y) receives outputs Y (n_out, n_cols) at step i.
    """
    with _blas_single_thread():
        _integrate_impl(system, n_steps, nm, n_cols, excitation, det_weight, sink)


def _integrate_impl(system, n_steps, nm, n_cols, excitation, det_weight, sink) -> None:
    """Newmark in acceleration (predictor-corrector) form, identical to the displacement form:
    u* = u + dt v + (1/2 - beta) dt^2 a,  v* = v + (1 - gamma) dt a,
    (M + gamma dt C + beta dt^2 K) a_new = F - C v* - K u*,
    u_new = u* + beta dt^2 a_new,  v_new = v* + gamma dt a_new  (fewest array passes per step)."""
    n = system.n_dof
    x0, v = system.start_m, system.speed_mps
    mats = system.matrices_at(0.0, x0)
    outs = system.outputs_at(0.0, x0)
    _check_shapes(system, mats, outs)
    det_cols = np.flatnonzero(det_weight)
    all_det = det_cols.size == n_cols
    det_w = det_weight[det_cols]

    def forcing(m: SystemMatrices, R: np.ndarray, Rd: np.ndarray) -> np.ndarray:
        F = m.input_r @ R
        F += m.input_r_rate @ Rd
        if det_cols.size and m.force_det.any():
            if all_det:
                F += np.outer(m.force_det, det_weight)
            else:  # PEM: only the deterministic column carries the load
                F[:, det_cols] += m.force_det[:, None] * det_w
        return F

    def output(o: OutputMatrices, u, vel, acc, R, Rd) -> np.ndarray:
        Y = o.acc @ acc
        if o.disp.any():
            Y += o.disp @ u
        if o.vel.any():
            Y += o.vel @ vel
        if o.r_gain is not None:
            Y += o.r_gain @ R
        if o.r_rate_gain is not None:
            Y += o.r_rate_gain @ Rd
        return Y

    u = np.zeros((n, n_cols))
    vel = np.zeros((n, n_cols))
    R, Rd = excitation(0, 0.0, x0)
    acc = np.linalg.solve(mats.mass, forcing(mats, R, Rd))
    sink(0, output(outs, u, vel, acc, R, Rd))

    dt, beta, gamma = nm.dt, nm.beta, nm.gamma
    bdt2, gdt = beta * dt * dt, gamma * dt
    pu, pv = (0.5 - beta) * dt * dt, (1.0 - gamma) * dt
    solver = _StepSolver(n, n_cols)
    solver.factor(mats.mass + gdt * mats.damping + bdt2 * mats.stiffness)
    for i in range(1, n_steps + 1):
        t = i * dt
        x = x0 + v * t
        if not system.time_invariant:
            mats = system.matrices_at(t, x)
            outs = system.outputs_at(t, x)
            solver.factor(mats.mass + gdt * mats.damping + bdt2 * mats.stiffness)
        R, Rd = excitation(i, t, x)
        # predictors (in place: u <- u*, vel <- v*)
        u += dt * vel
        u += pu * acc
        vel += pv * acc
        rhs = forcing(mats, R, Rd)
        rhs -= mats.damping @ vel
        rhs -= mats.stiffness @ u
        acc = solver.solve(rhs)
        u += bdt2 * acc
        vel += gdt * acc
        sink(i, output(outs, u, vel, acc, R, Rd))


def _check_shapes(system: LinearMovingSystem, m: SystemMatrices, o: OutputMatrices) -> None:
    n, n_in, n_out = system.n_dof, system.n_inputs, len(system.output_names)
    want = {
        "mass": (m.mass, (n, n)), "damping": (m.damping, (n, n)), "stiffness": (m.stiffness, (n, n)),
        "input_r": (m.input_r, (n, n_in)), "input_r_rate": (m.input_r_rate, (n, n_in)),
        "force_det": (m.force_det, (n,)), "outputs.disp": (o.disp, (n_out, n)),
        "outputs.vel": (o.vel, (n_out, n)), "outputs.acc": (o.acc, (n_out, n)),
    }
    if o.r_gain is not None:
        want["outputs.r_gain"] = (o.r_gain, (n_out, n_in))
    if o.r_rate_gain is not None:
        want["outputs.r_rate_gain"] = (o.r_rate_gain, (n_out, n_in))
    for key, (arr, shape) in want.items():
        if np.shape(arr) != shape:
            raise UserError(f"LinearMovingSystem {key}: expected shape {shape}, got {np.shape(arr)}")


def _n_steps(duration_s: float, dt: float) -> int:
    if not (duration_s > 0):
        raise UserError(f"duration_s: expected > 0, got {duration_s}")
    return int(round(duration_s / dt))


# ============================================================== PEM
@dataclass(frozen=True, eq=False)
class PemResult:
    """Time-dependent statistics from the pseudo-excitation method.

    mean, variance: (n_t, n_out); psd: (n_snap, n_out, n_freq) evolutionary one-sided PSD in
    unit^2/(rad/m) at spatial frequencies ``omega_rad_per_m`` and times ``psd_time_s``.
    """

    time_s: np.ndarray
    output_names: tuple[str, ...]
    output_units: tuple[str, ...]
    mean: np.ndarray
    variance: np.ndarray
    omega_rad_per_m: np.ndarray
    bin_width_rad_per_m: np.ndarray
    psd_time_s: np.ndarray
    psd: np.ndarray
    speed_mps: float
    n_integrations: int
    elapsed_s: float = 0.0

    @property
    def sd(self) -> np.ndarray:
        return np.sqrt(np.maximum(self.variance, 0.0))

    @property
    def rms(self) -> np.ndarray:
        """sqrt(mean^2 + SD^2) at each time (paper 001's RMS)."""
        return np.sqrt(self.mean**2 + np.maximum(self.variance, 0.0))

    def time_rms(self) -> np.ndarray:
        """sqrt of the run-averaged mean square per output (compare ``MonteCarloResult.time_rms_and_se``)."""
        return np.sqrt(np.mean(self.mean**2 + np.maximum(self.variance, 0.0), axis=0))

    @property
    def upper_3sigma(self) -> np.ndarray:
        return self.mean + 3.0 * self.sd

    @property
    def lower_3sigma(self) -> np.ndarray:
        return self.mean - 3.0 * self.sd

    def temporal_psd(self) -> tuple[np.ndarray, np.ndarray]:
        """(omega [rad/s], PSD [unit^2/(rad/s)]) = (v Omega, psd / v)."""
        return self.speed_mps * self.omega_rad_per_m, self.psd / self.speed_mps

    def output_index(self, name: str) -> int:
        try:
            return self.output_names.index(name)
        except ValueError:
            raise UserError(f"PemResult output: expected one of {list(self.output_names)}, got {name!r}") from None

    def to_dict(self) -> dict:
        return {
            "method": "pseudo-excitation",
            "time_s": self.time_s.tolist(),
            "output_names": list(self.output_names),
            "output_units": list(self.output_units),
            "mean": self.mean.tolist(),
            "sd": self.sd.tolist(),
            "rms": self.rms.tolist(),
            "omega_rad_per_m": self.omega_rad_per_m.tolist(),
            "psd_time_s": self.psd_time_s.tolist(),
            "psd_units": "unit^2/(rad/m), one-sided",
            "psd": self.psd.tolist(),
            "speed_mps": self.speed_mps,
            "n_integrations": self.n_integrations,
            "elapsed_s": self.elapsed_s,
        }


class PseudoExcitation:
    """Pseudo-excitation random vibration analysis of a ``LinearMovingSystem``.

    psd: one-sided spatial PSD of the irregularity; wavelength_band_m: (min, max) wavelength;
    n_freq / spacing: frequency bins; time_step_s: Newmark step; psd_stride: keep the
    evolutionary PSD every this many steps (None: about 200 snapshots);
    freq_batch: frequencies integrated together (None = all: paper 001 scheme; 1 = classic
    frequency-by-frequency).
    """

    def __init__(
        self,
        psd: ProfilePsd,
        wavelength_band_m: tuple[float, float] = (1.0, 20.0),
        n_freq: int = 256,
        spacing: str = "log",
        time_step_s: float = 1e-3,
        psd_stride: int | None = None,
        freq_batch: int | None = None,
        beta: float = 0.25,
        gamma: float = 0.5,
    ) -> None:
        if not isinstance(psd, ProfilePsd):
            raise UserError(f"PseudoExcitation psd: expected a ProfilePsd, got {type(psd).__name__}")
        self.psd = psd
        self.band_rad_per_m = band_from_wavelengths(*_check_band(wavelength_band_m, "wavelength_band_m"))
        self.omega, self.width, self.weight = frequency_bins(psd, self.band_rad_per_m, n_freq, spacing)
        self.nm = _Newmark(float(time_step_s), beta, gamma)
        if psd_stride is not None and int(psd_stride) < 1:
            raise UserError(f"psd_stride: expected >= 1, got {psd_stride}")
        self.psd_stride = psd_stride
        if freq_batch is not None and int(freq_batch) < 1:
            raise UserError(f"freq_batch: expected >= 1 or None, got {freq_batch}")
        self.freq_batch = freq_batch

    def run(self, system: LinearMovingSystem, duration_s: float) -> PemResult:
        import time as _time

        t_start = _time.perf_counter()
        nm = self.nm
        n_steps = _n_steps(duration_s, nm.dt)
        n_t = n_steps + 1
        n_out = len(system.output_names)
        n_f = self.omega.size
        stride = self.psd_stride or max(1, int(np.ceil(n_t / 200)))
        snap_idx = np.arange(0, n_t, stride)
        mean = np.zeros((n_t, n_out))
        variance = np.zeros((n_t, n_out))
        psd = np.zeros((snap_idx.size, n_out, n_f))
        offs = system.input_offsets_m
        v = system.speed_mps
        batch = n_f if self.freq_batch is None else int(self.freq_batch)
        n_runs = 0
        for j0 in range(0, n_f, batch):
            j1 = min(n_f, j0 + batch)
            with_det = j0 == 0
            om = self.omega[j0:j1]
            amp = np.sqrt(self.weight[j0:j1])
            inv_width = 1.0 / self.width[j0:j1]
            n_c = (j1 - j0) + (1 if with_det else 0)
            first = 1 if with_det else 0
            # complex columns, solved as interleaved real/imag float columns (K_eff is real)
            Rc = np.zeros((offs.size, n_c), dtype=complex)
            Rdc = np.zeros((offs.size, n_c), dtype=complex)
            Rf, Rdf = Rc.view(np.float64), Rdc.view(np.float64)
            iwv = 1j * om * v
            det_w = np.zeros(2 * n_c)
            if with_det:
                det_w[0] = 1.0

            # phases advance by exp(i Omega v dt) per step (one complex multiply instead of an exp);
            # recomputed exactly every 256 steps so round-off cannot accumulate
            rot = np.exp(1j * om * v * nm.dt)
            state = {"i": -10, "ph": None}

            def excitation(i, t, x, Rc=Rc, Rdc=Rdc, Rf=Rf, Rdf=Rdf, om=om, amp=amp, iwv=iwv, first=first,
                           rot=rot, state=state):
                if i == state["i"] + 1 and i % 256:
                    ph = state["ph"]
                    ph *= rot
                else:
                    ph = np.exp(1j * np.outer(x + offs, om))
                    ph *= amp
                    state["ph"] = ph
                state["i"] = i
                Rc[:, first:] = ph
                np.multiply(ph, iwv, out=Rdc[:, first:])
                return Rf, Rdf

            def sink(i, Yf, first=first, with_det=with_det, j0=j0, j1=j1, inv_width=inv_width):
                Y = Yf.view(complex)
                if with_det:
                    mean[i] = Y[:, 0].real
                Yr = Y[:, first:]
                p = Yr.real**2 + Yr.imag**2
                variance[i] += p.sum(axis=1)
                if i % stride == 0:
                    psd[i // stride, :, j0:j1] = p * inv_width

            _integrate(system, n_steps, nm, 2 * n_c, excitation, det_w, sink)
            n_runs += 1
        return PemResult(
            time_s=nm.dt * np.arange(n_t),
            output_names=tuple(system.output_names),
            output_units=tuple(system.output_units),
            mean=mean,
            variance=variance,
            omega_rad_per_m=self.omega.copy(),
            bin_width_rad_per_m=self.width.copy(),
            psd_time_s=nm.dt * snap_idx,
            psd=psd,
            speed_mps=v,
            n_integrations=n_runs,
            elapsed_s=_time.perf_counter() - t_start,
        )


# ============================================================== Monte Carlo
@dataclass(frozen=True, eq=False)
class MonteCarloResult:
    """Sample statistics over profiles: mean, sd (ddof=1): (n_t, n_out); histories (n_keep, n_t, n_out);
    sample_mean_square (n_samples, n_out): each sample's time average of y^2 over the whole run
    (its mean over samples estimates the time-averaged RMS^2, its spread gives that estimate's
    sampling error: ``time_rms_and_se``)."""

    time_s: np.ndarray
    output_names: tuple[str, ...]
    mean: np.ndarray
    sd: np.ndarray
    n_samples: int
    histories: np.ndarray
    sample_mean_square: np.ndarray
    elapsed_s: float = 0.0

    def time_rms_and_se(self) -> tuple[np.ndarray, np.ndarray]:
        """(sqrt of the run-averaged mean square, its standard error) per output."""
        q = self.sample_mean_square
        ms = q.mean(axis=0)
        se_ms = q.std(axis=0, ddof=1) / np.sqrt(max(q.shape[0], 1)) if q.shape[0] > 1 else np.zeros_like(ms)
        rms = np.sqrt(ms)
        return rms, np.where(rms > 0, se_ms / (2.0 * np.maximum(rms, 1e-300)), 0.0)

    @property
    def rms(self) -> np.ndarray:
        return np.sqrt(self.mean**2 + self.sd**2)

    def to_dict(self) -> dict:
        return {
            "method": "monte-carlo",
            "time_s": self.time_s.tolist(),
            "output_names": list(self.output_names),
            "mean": self.mean.tolist(),
            "sd": self.sd.tolist(),
            "rms": self.rms.tolist(),
            "n_samples": self.n_samples,
            "elapsed_s": self.elapsed_s,
        }


class MonteCarlo:
    """Run sampled profiles through the SAME Newmark integrator as ``PseudoExcitation``.

    sample_batch: samples integrated together as columns (None = all; 1 = one time integration
    per sample, the classic way). r at each input point is linearly interpolated on the profile
    grid; dr/dt = v dr/dx with dr/dx from 2nd-order central differences (np.gradient), both
    O(spacing^2): use spacing << shortest wavelength (e.g. <= 1/50 of it).
    """

    def __init__(self, time_step_s: float = 1e-3, sample_batch: int | None = None, keep_histories: int = 2,
                 beta: float = 0.25, gamma: float = 0.5) -> None:
        self.nm = _Newmark(float(time_step_s), beta, gamma)
        if sample_batch is not None and int(sample_batch) < 1:
            raise UserError(f"sample_batch: expected >= 1 or None, got {sample_batch}")
        self.sample_batch = sample_batch
        self.keep_histories = int(keep_histories)

    def run(self, system: LinearMovingSystem, x_m: np.ndarray, r_m: np.ndarray, duration_s: float) -> MonteCarloResult:
        import time as _time

        t_start = _time.perf_counter()
        nm = self.nm
        x_m = np.asarray(x_m, dtype=float)
        r_m = np.atleast_2d(np.asarray(r_m, dtype=float))
        if x_m.ndim != 1 or r_m.shape[1] != x_m.size or x_m.size < 3:
            raise UserError(f"MonteCarlo profiles: expected x_m (n,) and r_m (n_samples, n), got {x_m.shape}, {r_m.shape}")
        dx = float(x_m[1] - x_m[0])
        if not np.allclose(np.diff(x_m), dx, rtol=1e-6, atol=1e-12):
            raise UserError("MonteCarlo profiles: x_m must be uniformly spaced")
        n_steps = _n_steps(duration_s, nm.dt)
        n_t = n_steps + 1
        offs = system.input_offsets_m
        v = system.speed_mps
        pos_lo = system.start_m + offs.min()
        pos_hi = system.start_m + v * n_steps * nm.dt + offs.max()
        if pos_lo < x_m[0] or pos_hi > x_m[-1]:
            raise UserError(
                f"MonteCarlo profiles: cover x = {x_m[0]:.3f}..{x_m[-1]:.3f} m but the inputs travel "
                f"{pos_lo:.3f}..{pos_hi:.3f} m"
            )
        slope = np.gradient(r_m, dx, axis=1)
        n_s = r_m.shape[0]
        n_out = len(system.output_names)
        s1 = np.zeros((n_t, n_out))
        s2 = np.zeros((n_t, n_out))
        n_keep = min(self.keep_histories, n_s)
        hist = np.zeros((n_keep, n_t, n_out))
        msq = np.zeros((n_s, n_out))
        batch = n_s if self.sample_batch is None else int(self.sample_batch)
        for b0 in range(0, n_s, batch):
            b1 = min(n_s, b0 + batch)
            rb = np.ascontiguousarray(r_m[b0:b1].T)  # (n_x, n_b)
            sb = np.ascontiguousarray(slope[b0:b1].T) * v
            det_w = np.ones(b1 - b0)

            def excitation(i, t, x, rb=rb, sb=sb):
                p = (x + offs - x_m[0]) / dx
                k = np.minimum(np.floor(p).astype(int), x_m.size - 2)
                w = (p - k)[:, None]
                R = rb[k] * (1.0 - w) + rb[k + 1] * w
                Rd = sb[k] * (1.0 - w) + sb[k + 1] * w
                return R, Rd

            def sink(i, Y, b0=b0, b1=b1):
                Y2 = Y * Y
                s1[i] += Y.sum(axis=1)
                s2[i] += Y2.sum(axis=1)
                msq[b0:b1] += Y2.T
                if b0 < n_keep:
                    m = min(n_keep - b0, Y.shape[1])
                    hist[b0:b0 + m, i, :] = Y[:, :m].T

            _integrate(system, n_steps, nm, b1 - b0, excitation, det_w, sink)
        mean = s1 / n_s
        var = np.maximum(s2 - n_s * mean**2, 0.0) / max(n_s - 1, 1)
        return MonteCarloResult(
            time_s=nm.dt * np.arange(n_t),
            output_names=tuple(system.output_names),
            mean=mean,
            sd=np.sqrt(var),
            n_samples=n_s,
            histories=hist,
            sample_mean_square=msq / n_t,
            elapsed_s=_time.perf_counter() - t_start,
        )


# ============================================================== linearised magnet
@dataclass(frozen=True)
class MagnetGains:
    """Linearised levitation force dF = k_gap dgap + c_gap dgap/dt - added_mass a_m (upward on magnet)."""

    k_gap_n_per_m: float
    c_gap_n_s_per_m: float
    added_mass_kg: float

    def to_dict(self) -> dict:
        return {"k_gap_n_per_m": self.k_gap_n_per_m, "c_gap_n_s_per_m": self.c_gap_n_s_per_m,
                "added_mass_kg": self.added_mass_kg}


def linearised_magnet_gains(
    static_force_n: float,
    static_current_a: float,
    nominal_gap_m: float,
    kp_a_per_m: float,
    kv_a_s_per_m: float,
    ka_a_s2_per_m: float,
) -> MagnetGains:
    """Linearise F = C (I/gap)^2 with I = I0 + kp dgap + kv dgap' - ka a_m about (I0, g0).

    dF/dI = 2 F0 / I0, dF/dgap = -2 F0 / g0 (current dynamics neglected: the current follows the
    control law instantly), so dF = 2F0 (kp/I0 - 1/g0) dgap + 2F0 kv/I0 dgap' - 2F0 ka/I0 a_m.
    Private copy of the recording-contract levitation law (maglev_ros.twin.levitation is owned by
    another module; use its linearisation when it exposes one).
    """
    if not (static_force_n > 0 and static_current_a > 0 and nominal_gap_m > 0):
        raise UserError("linearised_magnet_gains: static_force_n, static_current_a, nominal_gap_m must be > 0")
    ki = 2.0 * static_force_n / static_current_a
    kh = 2.0 * static_force_n / nominal_gap_m
    k_gap = ki * kp_a_per_m - kh
    if k_gap <= 0:
        raise UserError(
            f"levitation kp_a_per_m={kp_a_per_m}: the closed loop has no positive gap stiffness "
            f"(need kp > I0/g0 = {static_current_a / nominal_gap_m:.4g} A/m)"
        )
    return MagnetGains(k_gap, ki * kv_a_s_per_m, ki * ka_a_s2_per_m)


# ============================================================== reference model
def vehicle_on_modal_beam(
    *,
    speed_mps: float = 30.0,
    start_m: float = -30.0,
    span_m: float = 24.768,
    n_modes: int = 4,
    mass_per_length_kg_m: float = 3750.0,
    bending_stiffness_n_m2: float = 2.0e10,
    damping_ratio: float = 0.02,
    car_body_mass_kg: float = 20000.0,
    car_body_pitch_inertia_kg_m2: float = 2.0e5,
    magnet_mass_kg: float = 1500.0,
    magnet_offsets_m: Sequence[float] = (0.0, -2.58, -5.16, -7.74),
    secondary_stiffness_n_per_m: float = 2.0e5,
    secondary_damping_n_s_per_m: float = 1.25e4,
    static_current_a: float = 25.0,
    nominal_gap_m: float = 0.010,
    kp_a_per_m: float = 7000.0,
    kv_a_s_per_m: float = 40.0,
    ka_a_s2_per_m: float = 0.1,
    gravity_mps2: float = GRAVITY_MPS2,
) -> LinearMovingSystem:
    """Small reference model: rigid car body (heave, pitch) on air springs over n PD-controlled
    magnets, crossing one simply supported Euler-Bernoulli beam (modal, n_modes sine modes).

    DOFs: [q_1..q_nm (beam modal coordinates, modal mass m L / 2), z_b, theta_b, z_1..z_n].
    Car body CG at the mean magnet offset (equal static load shares F0 = (m_b/n + m_m) g);
    pitch positive nose-up (z at offset d is z_b + (d - d_cg) theta). Off the beam the rail is
    rigid. Gap change r + w(x_k) - z_k (contract sign); the gap rate includes the convective
    term v w'(x_k). Deterministic load: -F0 phi_j(x_k) on the beam (vehicle weight); the
    vehicle is in static equilibrium at nominal gap on a rigid rail. Outputs: car-body heave
    acceleration, beam midspan acceleration and displacement, gap change of magnet 1.
    Used by the tests and bench/bench_pem.py; the full 18-DOF + FE model lives in the twin.
    """
    offs = np.asarray(magnet_offsets_m, dtype=float)
    n_mag = offs.size
    nm_ = int(n_modes)
    n = nm_ + 2 + n_mag
    L, mbar, EI = span_m, mass_per_length_kg_m, bending_stiffness_n_m2
    j = np.arange(1, nm_ + 1)
    beta_j = j * np.pi / L
    modal_mass = 0.5 * mbar * L
    omega_j = beta_j**2 * np.sqrt(EI / mbar)
    static_force = (car_body_mass_kg / n_mag + magnet_mass_kg) * gravity_mps2
    g = linearised_magnet_gains(static_force, static_current_a, nominal_gap_m, kp_a_per_m, kv_a_s_per_m, ka_a_s2_per_m)
    ke, ce, ma = g.k_gap_n_per_m, g.c_gap_n_s_per_m, g.added_mass_kg
    ks, cs = secondary_stiffness_n_per_m, secondary_damping_n_s_per_m
    d_cg = offs.mean()
    arm = offs - d_cg
    zb, th = nm_, nm_ + 1
    zm = nm_ + 2 + np.arange(n_mag)
    q = np.arange(nm_)
    sq, sm = slice(0, nm_), slice(nm_ + 2, n)  # contiguous blocks: beam modes, magnets

    # constant part (beam alone, vehicle on a rigid rail)
    M0 = np.zeros((n, n)); C0 = np.zeros((n, n)); K0 = np.zeros((n, n))
    M0[q, q] = modal_mass
    C0[q, q] = 2.0 * damping_ratio * omega_j * modal_mass
    K0[q, q] = omega_j**2 * modal_mass
    M0[zb, zb] = car_body_mass_kg
    M0[th, th] = car_body_pitch_inertia_kg_m2
    M0[zm, zm] = magnet_mass_kg + ma
    # air spring k joins body point (z_b + arm_k theta) to magnet k
    for k in range(n_mag):
        e = np.zeros(n); e[zb] = 1.0; e[th] = arm[k]; e[zm[k]] = -1.0
        K0 += ks * np.outer(e, e); C0 += cs * np.outer(e, e)
        # levitation on a rigid rail: +ke z_k, +ce z_k'
        K0[zm[k], zm[k]] += ke; C0[zm[k], zm[k]] += ce
    Br0 = np.zeros((n, n_mag)); Brd0 = np.zeros((n, n_mag))
    Br0[zm, np.arange(n_mag)] = ke
    Brd0[zm, np.arange(n_mag)] = ce
    mid = np.sin(beta_j * 0.5 * L)
    v = float(speed_mps)

    def shapes(x: float):
        xk = x + offs
        on = (xk >= 0.0) & (xk <= L)
        arg = np.outer(beta_j, xk)
        phi = np.sin(arg) * on  # (nm, n_mag), zero off the beam
        dphi = (beta_j[:, None] * np.cos(arg)) * on
        return phi, dphi

    def matrices_at(t: float, x: float) -> SystemMatrices:
        phi, dphi = shapes(x)
        M = M0.copy(); C = C0.copy(); K = K0.copy()
        Br = Br0.copy(); Brd = Brd0.copy()
        if phi.any():
            phiT = phi.T
            # magnet rows: - ke phi^T q - ce (phi^T q' + v dphi^T q)
            K[sm, sq] -= ke * phiT + (ce * v) * dphi.T
            C[sm, sq] -= ce * phiT
            # beam rows: + sum_k phi_k [ke(phi_k^T q - z_k) + ce(phi_k^T q' + v dphi_k^T q - z_k') - ma z_k'']
            K[sq, sq] += ke * (phi @ phiT) + (ce * v) * (phi @ dphi.T)
            C[sq, sq] += ce * (phi @ phiT)
            K[sq, sm] -= ke * phi
            C[sq, sm] -= ce * phi
            M[sq, sm] -= ma * phi
            # irregularity under magnet k pulls the rail down: -phi_k (ke r_k + ce r_k')
            Br[sq] = -ke * phi
            Brd[sq] = -ce * phi
        f = np.zeros(n)
        f[sq] = -static_force * phi.sum(axis=1)
        return SystemMatrices(M, C, K, Br, Brd, f)

    names = ("car_body_accel", "midspan_accel", "midspan_disp", "gap1")
    units = ("m/s^2", "m/s^2", "m", "m")
    Ca = np.zeros((4, n)); Cu = np.zeros((4, n)); Cv = np.zeros((4, n))
    Ca[0, zb] = 1.0
    Ca[1, q] = mid
    Cu[2, q] = mid
    Dr = np.zeros((4, n_mag)); Dr[3, 0] = 1.0

    def outputs_at(t: float, x: float) -> OutputMatrices:
        phi, _ = shapes(x)
        Cu_t = Cu.copy()
        Cu_t[3, q] = phi[:, 0]
        Cu_t[3, zm[0]] = -1.0
        return OutputMatrices(Cu_t, Cv, Ca, Dr, None)

    return LinearMovingSystem(
        n_dof=n,
        input_offsets_m=offs,
        speed_mps=speed_mps,
        start_m=start_m,
        matrices_at=matrices_at,
        outputs_at=outputs_at,
        output_names=names,
        output_units=units,
        time_invariant=False,
        description=f"rigid car body + {n_mag} PD magnets on a {span_m} m simply supported beam, {nm_} modes",
    )


# ============================================================== adapter: the twin's coupled model
def coupled_twin_system(
    config: Any = None,
    spans: Any = None,
    *,
    speed_mps: float = 30.0,
    start_m: float | None = None,
    lead_in_m: float = 20.0,
    guideway_points_m: Sequence[float] | None = None,
    mode_cutoff_hz: float | None = None,
    min_modes_per_span: int | None = None,
    n_elements_per_span: int | None = None,
) -> LinearMovingSystem:
    """Linearised coupled vehicle/guideway system of the twin as a ``LinearMovingSystem``.

    Built from the twin's own modules: ``levitation.build_vehicle`` (data-driven vehicle M, C, K,
    magnet input B, static equilibrium magnet forces F0, linearised magnet force
    dF = k_g dgap + c_g dgap' - m_a a_m from ``LevitationModel.partials``) and
    ``guideway.Guideway(...).modes(...)`` (mass-normalised span modes phi_j(x), slopes).
    ``config``: a ``design.TwinConfig`` (None: defaults); ``spans``: SpanSpecs / metadata line
    (None: ``design.default_line``).

    DOFs [vehicle (n_v), guideway modal (n_m)]. With y_k = r_k + phi(x_k)^T q the rail under
    magnet k and dgap_k = y_k - B_k^T z:
      vehicle:  M_v z'' + C_v z' + K_v z = B dF
      guideway: q'' + 2 zeta w q' + w^2 q = -Phi (F0 + dF)
    dgap' includes the convective term v phi'(x_k)^T q. Coil dynamics (inductance > 0) add first
    order current states that this second-order integrator does not carry: refused.
    Outputs: car-body heave acceleration, magnet 1 acceleration and gap change, and guideway
    vertical acceleration and displacement at ``guideway_points_m`` (default: each span's
    midpoint).
    """
    from maglev_ros.twin.design import default_line, line_spans, twin_config
    from maglev_ros.twin.guideway import Guideway
    from maglev_ros.twin.levitation import build_vehicle

    cfg = twin_config() if config is None else config
    if cfg.levitation.coil_inductance_h > 0:
        raise UserError("design.levitation.coil_inductance_h: the PEM adapter needs 0 (current follows the "
                        "control law); coil current states are not second-order DOFs")
    line = default_line(cfg) if spans is None else line_spans(spans, cfg)
    num = cfg.numerics
    gw = Guideway(line, num.n_elements_per_span if n_elements_per_span is None else n_elements_per_span)
    modes = gw.modes(cutoff_hz=num.mode_cutoff_hz if mode_cutoff_hz is None else mode_cutoff_hz,
                     min_modes_per_span=num.min_modes_per_span if min_modes_per_span is None else min_modes_per_span)
    veh = build_vehicle(cfg)
    vm, lev = veh.model, veh.levitation
    p = lev.partials()
    kg = np.asarray(p.df_dgap_n_per_m, dtype=float)
    cg = np.asarray(p.df_dgap_rate_n_s_per_m, dtype=float)
    ma = -np.asarray(p.df_daccel_n_s2_per_m, dtype=float)
    f0 = np.asarray(lev.static_force_n, dtype=float)
    Bm = np.asarray(vm.magnet_input, dtype=float)  # (n_v, n_mag)
    offs = np.asarray(vm.magnet_x_m, dtype=float)
    n_v, n_mag, n_m = vm.n_dof, offs.size, modes.n_modes
    n = n_v + n_m
    sv, sq = slice(0, n_v), slice(n_v, n)
    w = modes.omega_rad_s
    zeta = modes.damping_ratio
    v = float(speed_mps)
    if start_m is None:
        start_m = gw.start_m - float(offs.max()) - float(lead_in_m)

    M0 = np.zeros((n, n)); C0 = np.zeros((n, n)); K0 = np.zeros((n, n))
    M0[sv, sv] = vm.mass + Bm @ (ma[:, None] * Bm.T)
    C0[sv, sv] = vm.damping + Bm @ (cg[:, None] * Bm.T)
    K0[sv, sv] = vm.stiffness + Bm @ (kg[:, None] * Bm.T)
    iq = np.arange(n_v, n)
    M0[iq, iq] = 1.0
    C0[iq, iq] = 2.0 * zeta * w
    K0[iq, iq] = w**2
    Br0 = np.zeros((n, n_mag)); Brd0 = np.zeros((n, n_mag))
    Br0[sv] = Bm * kg
    Brd0[sv] = Bm * cg
    BmKgT = kg[:, None] * Bm.T  # (n_mag, n_v)
    BmCgT = cg[:, None] * Bm.T
    BmMaT = ma[:, None] * Bm.T

    cache: dict = {}

    def shapes(x: float):
        if cache.get("x") != x:
            xk = x + offs
            cache["x"] = x
            cache["phi"] = modes.shapes_at(xk).T  # (n_m, n_mag)
            cache["dphi"] = modes.slopes_at(xk).T
        return cache["phi"], cache["dphi"]

    def matrices_at(t: float, x: float) -> SystemMatrices:
        phi, dphi = shapes(x)
        M = M0.copy(); C = C0.copy(); K = K0.copy()
        Br = Br0.copy(); Brd = Brd0.copy()
        f = np.zeros(n)
        if phi.any():
            phi_kg, phi_cg = phi * kg, phi * cg  # (n_m, n_mag)
            # vehicle rows: - B (Kg Phi^T + v Cg Phi'^T) q - B Cg Phi^T q'
            K[sv, sq] -= Bm @ (kg[:, None] * phi.T + v * cg[:, None] * dphi.T)
            C[sv, sq] -= Bm @ (cg[:, None] * phi.T)
            # guideway rows: + Phi dF(q, z part)
            K[sq, sq] += phi_kg @ phi.T + v * (phi_cg @ dphi.T)
            C[sq, sq] += phi_cg @ phi.T
            K[sq, sv] -= phi @ BmKgT
            C[sq, sv] -= phi @ BmCgT
            M[sq, sv] -= phi @ BmMaT
            Br[sq] = -phi_kg
            Brd[sq] = -phi_cg
            f[sq] = -phi @ f0
        return SystemMatrices(M, C, K, Br, Brd, f)

    pts = ([0.5 * (s.start_m + s.end_m) for s in line] if guideway_points_m is None
           else [float(xp) for xp in guideway_points_m])
    phi_pts = modes.shapes_at(np.asarray(pts)).T if pts else np.zeros((n_m, 0))  # (n_m, n_pts)
    names = ["car_body_accel", "magnet1_accel", "gap1"]
    units = ["m/s^2", "m/s^2", "m"]
    for i, xp in enumerate(pts):
        names += [f"guideway_accel@{xp:g}", f"guideway_disp@{xp:g}"]
        units += ["m/s^2", "m"]
    n_out = len(names)
    Ca = np.zeros((n_out, n)); Cu0 = np.zeros((n_out, n)); Cv = np.zeros((n_out, n))
    Ca[0, vm.dof_index("car.z")] = 1.0
    Ca[1, sv] = Bm[:, 0]
    for i in range(len(pts)):
        Ca[3 + 2 * i, sq] = phi_pts[:, i]
        Cu0[4 + 2 * i, sq] = phi_pts[:, i]
    Cu0[2, sv] = -Bm[:, 0]
    Dr = np.zeros((n_out, n_mag)); Dr[2, 0] = 1.0

    def outputs_at(t: float, x: float) -> OutputMatrices:
        phi, _ = shapes(x)
        Cu = Cu0.copy()
        Cu[2, sq] = phi[:, 0]
        return OutputMatrices(Cu, Cv, Ca, Dr, None)

    return LinearMovingSystem(
        n_dof=n,
        input_offsets_m=offs,
        speed_mps=v,
        start_m=float(start_m),
        matrices_at=matrices_at,
        outputs_at=outputs_at,
        output_names=tuple(names),
        output_units=tuple(units),
        time_invariant=False,
        description=f"twin: {n_v}-DOF vehicle + {n_m} guideway modes over {len(line)} spans",
    )
