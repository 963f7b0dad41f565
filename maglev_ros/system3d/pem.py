"""Random vibration of the 3D train-girder system by the pseudo-excitation method (PEM), its
mean from the deterministic run, and a Monte Carlo peer on the same solver (no rclpy).

Irregularity: four independent processes k (elevation, cross-level, alignment, gauge;
``irregularity.TrackIrregularity``), each mapped to the four rail components (z_L, z_R, y_L, y_R)
by the column T[:, k]. The spatial frequency axis is split into bins j (``FrequencyGrid``) with
weight W_jk (the band integral of S_k over the bin, or S_k(Omega_j) dOmega_j). The pseudo-
excitation of (j, k) puts on magnet r of car c (global position X_cr(t) = X_cr(0) + v t, side s_r)

    z_rail = T[z_{s_r}, k] sqrt(W_jk) e^{i Omega_j X_cr(t)},  y_rail likewise with T[y_{s_r}, k],
    rates = i omega_j times them, omega_j = Omega_j v,

so magnet r lags the first by e^{-i omega_j (x_1 - x_r)/v}. All (j, k) pairs are integrated
together as the columns of one run (001 Sec. 4.1's scheme: the matrices of a step are built and
factorised once for every frequency; ``solve_coupled``); the harmonic input is integrated exactly
(``VehicleStep.harmonic_input``). For every output y and time t:

    variance(t) = sum_jk |y_jk(t)|^2,   PSD(Omega_j, t) = sum_k |y_jk(t)|^2 / dOmega_j  [unit^2/(rad/m)],

mean(t) from the deterministic run (static magnet forces moving over the girder, perfect rail),
SD = sqrt(variance), RMS = sqrt(mean^2 + SD^2), 3-sigma bounds mean +/- 3 SD.

Start: ``steady`` (default) starts every pseudo-response at the vehicle's harmonic steady state
on rigid track (the train has run over the irregular approach for long), ``rest`` at zero (as a
Monte Carlo run that starts at rest). One-time costs (discretisation, factorisations, harmonic
step increments, steady states) are in ``prepare``; ``run`` is the time loop.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from maglev_ros.errors import UserError
from maglev_ros.progress import NULL, Progress
from maglev_ros.system3d.irregularity import PROCESSES, RAILS, TrackIrregularity
from maglev_ros.system3d.solve_coupled import CoupledSolver, HarmonicInput
from maglev_ros.twin.pem import _blas_single_thread

SPACINGS = ("linear", "log")
WEIGHTS = ("bin", "midpoint")
STARTS = ("steady", "rest")


@dataclass(frozen=True)
class FrequencyGrid:
    """Bins of the spatial angular frequency Omega [rad/m]: centres and edges."""
    centre_rad_per_m: np.ndarray
    edges_rad_per_m: np.ndarray
    weights: str = "bin"

    def __post_init__(self) -> None:
        if self.weights not in WEIGHTS:
            raise UserError(f"pem.frequency_grid.weights: expected one of {list(WEIGHTS)}, got {self.weights!r}")

    @classmethod
    def build(cls, lo_rad_per_m: float, hi_rad_per_m: float, n: int, spacing: str = "linear",
              weights: str = "bin") -> "FrequencyGrid":
        if spacing not in SPACINGS:
            raise UserError(f"pem.frequency_grid.spacing: expected one of {list(SPACINGS)}, got {spacing!r}")
        if not (0 < lo_rad_per_m < hi_rad_per_m) or int(n) < 1:
            raise UserError(f"pem.frequency_grid: expected 0 < min < max and n >= 1, got "
                            f"{lo_rad_per_m}, {hi_rad_per_m}, {n}")
        if spacing == "linear":
            edges = np.linspace(lo_rad_per_m, hi_rad_per_m, int(n) + 1)
            centre = 0.5 * (edges[1:] + edges[:-1])
        else:
            edges = np.geomspace(lo_rad_per_m, hi_rad_per_m, int(n) + 1)
            centre = np.sqrt(edges[1:] * edges[:-1])
        return cls(centre, edges, weights)

    @property
    def n(self) -> int:
        return int(self.centre_rad_per_m.size)

    @property
    def width_rad_per_m(self) -> np.ndarray:
        return np.diff(self.edges_rad_per_m)

    def process_weights(self, irregularity: TrackIrregularity) -> np.ndarray:
        """(n, 4) W_jk: variance of process k carried by bin j."""
        if self.weights == "midpoint":
            return irregularity.process_psd(self.centre_rad_per_m) * self.width_rad_per_m[:, None]
        lo, hi = self.edges_rad_per_m[:-1], self.edges_rad_per_m[1:]
        return np.stack([irregularity.psds[k].band_variance(lo, hi) for k in PROCESSES], axis=-1)

    def to_dict(self) -> dict:
        return {"n": self.n, "min_rad_per_m": float(self.edges_rad_per_m[0]),
                "max_rad_per_m": float(self.edges_rad_per_m[-1]), "weights": self.weights}


@dataclass
class RandomResponse:
    """Time-dependent statistics of each output (rows) along the run."""
    names: tuple[str, ...]
    units: tuple[str, ...]
    time_s: np.ndarray
    mean: np.ndarray                 # (n_out, n_t)
    variance: np.ndarray             # (n_out, n_t)
    variance_by_process: np.ndarray  # (n_out, n_t, n_proc)
    processes: tuple[str, ...]
    psd_time_s: np.ndarray           # (n_tp,)
    psd: np.ndarray                  # (n_out, n_tp, n_freq) unit^2/(rad/m)
    grid: FrequencyGrid
    info: dict = field(default_factory=dict)

    @property
    def sd(self) -> np.ndarray:
        return np.sqrt(self.variance)

    @property
    def rms(self) -> np.ndarray:
        return np.sqrt(self.mean ** 2 + self.variance)

    def bounds(self, k: float = 3.0) -> tuple[np.ndarray, np.ndarray]:
        return self.mean - k * self.sd, self.mean + k * self.sd

    def index(self, name: str) -> int:
        return self.names.index(name)

    def summary(self) -> dict:
        """Per output: peaks over the run of |mean|, SD, RMS, |3-sigma bound|, and the PSD peak."""
        out = {}
        lo, hi = self.bounds()
        for i, n in enumerate(self.names):
            pk = np.unravel_index(np.argmax(self.psd[i]), self.psd[i].shape) if self.psd.size else (0, 0)
            om = float(self.grid.centre_rad_per_m[pk[1]]) if self.psd.size else float("nan")
            out[n] = {"unit": self.units[i], "max_abs_mean": float(np.max(np.abs(self.mean[i]))),
                      "max_sd": float(np.max(self.sd[i])), "max_rms": float(np.max(self.rms[i])),
                      "max_abs_3sigma": float(np.max(np.maximum(np.abs(lo[i]), np.abs(hi[i])))),
                      "psd_peak_rad_per_m": om,
                      "psd_peak_hz": om * self.info.get("speed_mps", float("nan")) / (2 * np.pi),
                      "psd_peak_time_s": float(self.psd_time_s[pk[0]]) if self.psd.size else float("nan")}
        return out


def pseudo_inputs(solver: CoupledSolver, irregularity: TrackIrregularity, grid: FrequencyGrid,
                  processes: tuple[str, ...] = PROCESSES) -> HarmonicInput:
    """The (n_cars, 4m, n_freq * n_proc) pseudo-excitation amplitudes at t = 0 (columns
    frequency-major: column j * n_proc + k)."""
    unknown = [p for p in processes if p not in PROCESSES]
    if unknown or not processes:
        raise UserError(f"pem.processes: expected some of {list(PROCESSES)}, got {list(processes)}")
    tr = solver.train
    v = tr.speed_mps
    kidx = [PROCESSES.index(p) for p in processes]
    W = grid.process_weights(irregularity)[:, kidx]                     # (nf, np)
    T = irregularity.mapping[:, kidx]                                   # rails x processes
    sides = solver.sides
    zrow = np.array([RAILS.index("z_left" if s == "left" else "z_right") for s in sides])
    yrow = np.array([RAILS.index("y_left" if s == "left" else "y_right") for s in sides])
    om = grid.centre_rad_per_m                                          # (nf,)
    X = tr.magnet_positions_m(0.0)                                      # (nc, m)
    phase = np.exp(1j * X[:, :, None] * om[None, None, :])              # (nc, m, nf)
    amp = np.sqrt(W)                                                    # (nf, np)
    z = phase[:, :, :, None] * (T[zrow][None, :, None, :] * amp[None, None])   # (nc, m, nf, np)
    y = phase[:, :, :, None] * (T[yrow][None, :, None, :] * amp[None, None])
    iw = (1j * om * v)[None, None, :, None]
    w_hat = np.concatenate([z, y, iw * z, iw * y], axis=1)              # (nc, 4m, nf, np)
    nc, m4 = w_hat.shape[:2]
    omega = np.repeat(om * v, len(kidx))
    return HarmonicInput(omega, w_hat.reshape(nc, m4, -1))


class PseudoExcitation3D:
    """PEM of the train-girder system (config in the constructor, the time loop in ``run``)."""

    def __init__(self, solver: CoupledSolver, irregularity: TrackIrregularity, grid: FrequencyGrid,
                 *, processes: tuple[str, ...] = PROCESSES, start: str = "steady", psd_every: int = 1):
        if start not in STARTS:
            raise UserError(f"pem.start: expected one of {list(STARTS)}, got {start!r}")
        self.solver, self.irregularity, self.grid = solver, irregularity, grid
        self.processes, self.start, self.psd_every = tuple(processes), start, max(int(psd_every), 1)
        self.harmonic: HarmonicInput | None = None
        self.x0: np.ndarray | None = None

    def prepare(self) -> None:
        """One-time costs outside the time loop: pseudo-excitations, their exact step increments,
        steady states."""
        h = pseudo_inputs(self.solver, self.irregularity, self.grid, self.processes)
        self.harmonic = replace(h, increment=self.solver.harmonic_increments(h))
        self.x0 = None
        if self.start == "steady":
            st = self.solver.step
            with _blas_single_thread():
                self.x0 = np.stack([st.steady_state(self.harmonic.omega_rad_s, self.harmonic.w_hat[c])
                                    for c in range(self.solver.train.n_cars)])

    def mean(self, n_steps: int, progress: Progress = NULL) -> tuple[np.ndarray, dict]:
        """Deterministic run (static forces moving over the girder): (n_out, n_t), run info."""
        ys = []
        rec = self.solver.run(n_steps, 1, static_load=True, record=lambda n, t, y: ys.append(y[:, 0]),
                              progress=progress)
        return np.array(ys).T, rec.to_dict()

    def run(self, n_steps: int, progress: Progress = NULL, mean: np.ndarray | None = None) -> RandomResponse:
        if self.harmonic is None:
            self.prepare()
        sol = self.solver
        n_out, nf, npr = len(sol.outputs), self.grid.n, len(self.processes)
        info = {}
        if mean is None:
            mean, info["mean_run"] = self.mean(n_steps, progress)
        var_p = np.zeros((n_out, n_steps + 1, npr))
        psd_steps = np.arange(0, n_steps + 1, self.psd_every)
        psd = np.zeros((n_out, psd_steps.size, nf))
        width = self.grid.width_rad_per_m

        def record(n, t, y):
            p2 = (y.real ** 2 + y.imag ** 2).reshape(n_out, nf, npr)
            var_p[:, n, :] = p2.sum(axis=1)
            if n % self.psd_every == 0:
                psd[:, n // self.psd_every, :] = p2.sum(axis=2) / width[None, :]

        rec = sol.run(n_steps, harmonic=self.harmonic, static_load=False, x0=self.x0, record=record,
                      progress=progress)
        info["pem_run"] = rec.to_dict()
        info["speed_mps"] = sol.train.speed_mps
        info["start"] = self.start
        return RandomResponse(tuple(o.name for o in sol.outputs), tuple(o.unit for o in sol.outputs),
                              rec.time_s, mean, var_p.sum(axis=2), var_p, self.processes,
                              psd_steps * sol.time_step_s, psd, self.grid, info)


def sampled_rails(solver: CoupledSolver, x_m: np.ndarray, rails: dict[str, np.ndarray]):
    """``sampled(t)`` for ``CoupledSolver.run``: the rails of irregularity samples (RAILS -> (n_s,
    n_x) on the uniform grid ``x_m``) at every magnet, linearly interpolated, with the rates
    v dr/dx (central differences on the grid)."""
    x = np.asarray(x_m, float)
    dx = float(x[1] - x[0])
    v = solver.train.speed_mps
    side_z = ["z_left" if s == "left" else "z_right" for s in solver.sides]
    side_y = ["y_left" if s == "left" else "y_right" for s in solver.sides]
    vals = np.stack([np.asarray(rails[k], float) for k in RAILS])      # (4, n_s, n_x)
    slopes = np.gradient(vals, dx, axis=-1)

    def sampled(t):
        X = solver.train.magnet_positions_m(t)                  # (nc, m)
        if X.min() < x[0] or X.max() > x[-1]:
            raise UserError(f"Monte Carlo: the irregularity samples cover {x[0]:.4g}..{x[-1]:.4g} m, "
                            f"a magnet is at {X.min():.4g}..{X.max():.4g} m")
        f = (X - x[0]) / dx
        i = np.clip(np.floor(f).astype(int), 0, x.size - 2)
        a = f - i

        def at(arr, names):                                     # (nc, m, n_s)
            col = np.array([RAILS.index(nm) for nm in names])
            lo = arr[col[None, :], :, i]                         # (nc, m, n_s)
            hi = arr[col[None, :], :, i + 1]
            return lo * (1 - a)[..., None] + hi * a[..., None]
        return np.concatenate([at(vals, side_z), at(vals, side_y), v * at(slopes, side_z), v * at(slopes, side_y)],
                              axis=1)
    return sampled


@dataclass
class MonteCarloResponse:
    names: tuple[str, ...]
    time_s: np.ndarray
    mean: np.ndarray                 # (n_out, n_t) sample mean
    variance: np.ndarray             # (n_out, n_t) sample variance (about the sample mean)
    n_samples: int
    examples: np.ndarray             # (n_out, n_t, n_keep) the first samples' histories


def monte_carlo(solver: CoupledSolver, n_steps: int, x_m: np.ndarray, rails: dict[str, np.ndarray], *,
                batch: int = 100, static_load: bool = False, keep: int = 2,
                progress: Progress = NULL) -> MonteCarloResponse:
    """Time histories for irregularity samples (RAILS -> (n_s, n_x)), ``batch`` samples per run
    as columns; returns the sample mean and variance of every output."""
    n_s = np.asarray(rails[RAILS[0]]).shape[0]
    n_out = len(solver.outputs)
    s1 = np.zeros((n_out, n_steps + 1))
    s2 = np.zeros((n_out, n_steps + 1))
    examples = np.zeros((n_out, n_steps + 1, min(keep, n_s)))
    for b0 in range(0, n_s, batch):
        sl = slice(b0, min(b0 + batch, n_s))
        sub = {k: np.asarray(rails[k])[sl] for k in RAILS}

        def record(n, t, y, b0=b0):
            s1[:, n] += y.sum(axis=1)
            s2[:, n] += (y ** 2).sum(axis=1)
            if b0 == 0:
                examples[:, n, :] = y[:, :examples.shape[2]]
        solver.run(n_steps, sl.stop - sl.start, static_load=static_load,
                   sampled=sampled_rails(solver, x_m, sub), record=record, progress=progress)
    mean = s1 / n_s
    var = (s2 - n_s * mean ** 2) / max(n_s - 1, 1)
    return MonteCarloResponse(tuple(o.name for o in solver.outputs), np.arange(n_steps + 1) * solver.time_step_s,
                              mean, var, n_s, examples)
