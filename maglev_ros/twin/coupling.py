"""Vehicle/guideway coupled time integration: moving magnet forces on a modal FE guideway.

Model. The vehicle is the closed-loop state space of ``levitation.closed_loop`` (DOFs measured from
the solved static equilibrium; the magnet force is its linear part plus the nonlinear remainder
N = C (I/gap)^2 - F_lin, fed back as an input). The guideway is the truncated modal model of
``guideway.Guideway.modes`` (modes up to ``numerics.mode_cutoff_hz``): each magnet force F_i pulls the
rail down at x_i(t), distributed to the modes with the Hermite-interpolated FE mode shapes,
q'' + 2 zeta w q' + w^2 q = -Phi(x(t))^T F. Rail-underside displacement at a magnet:
y = r(x) + w(x), its rate y' = v r'(x) + Phi q' + v Phi' q; gap = g0 + y - z_m (contract).

Two solution schemes per time step h (both iterate until the magnet forces stop changing):
- ``method="newmark"`` (000): vehicle and guideway both by Newmark average acceleration (for the
  vehicle in state-space form this is the trapezoidal rule, the same scheme). The linear
  vehicle/guideway coupling is solved together each step (the "equivalent stiffness" system of
  000, condensed onto the magnet forces: an n_mag x n_mag system whose inverse is precomputed for
  every step of a block); iteration only resolves the nonlinear force remainder.
- ``method="separated"`` (001): vehicle by precise integration (exact matrix exponential with
  piecewise-linear input, scipy.linalg.expm) and guideway by Newmark, solved separately and
  exchanging interface forces / rail displacements until converged (Gauss-Seidel).

Speed: everything that depends only on the position (mode shapes at the magnets, irregularity,
the condensed coupling matrices) is precomputed vectorised per block, so the compiled loop per step
is a few small matrix-vector products. A mode lives on one span, so only the modes of the spans
under the magnets during a block enter those products (span-local stepping: the cost per step does
not grow with the line's length); every other mode vibrates freely, and the scheme on a free mode is
linear: modes a sensor sees are stepped alone (their outputs), the rest jump over the block by the
scheme's transition matrix to the block's length (per mode, 3x3 on q, q', q''). The results equal
stepping every mode to round-off (bitwise while no free-ringing span is re-entered);
``TwinStepper(reference=True)`` steps every mode (the check, bench/bench_twin.py). Time stepping
is written by hand because no maintained library integrates a moving-load, nonlinearly coupled
system like this.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Callable, Mapping, Sequence

import numpy as np
from scipy.linalg import expm

from maglev_ros.errors import UserError
from maglev_ros.twin.design import SpanSpec, TwinConfig, line_spans
from maglev_ros.twin.guideway import Guideway, ModalBasis
from maglev_ros.twin.levitation import VehicleSystem, build_vehicle

METHODS = ("newmark", "separated")
CURRENT_LIMIT_SIDES = ("both", "upper")    # which side of the static current a current limit acts on
_NO_EXCESS = np.zeros(1)


# ---------------------------------------------------------------------------------------------
# irregularity input
class Irregularity:
    """Rail-underside vertical irregularity r(x) (positive up) and its slope r'(x)."""

    def __init__(self, elevation: Callable[[np.ndarray], np.ndarray] | None = None,
                 slope: Callable[[np.ndarray], np.ndarray] | None = None, dx_m: float = 1e-3):
        self._elev = elevation
        self._slope = slope
        self._dx = dx_m

    @classmethod
    def from_samples(cls, x_m, r_m) -> "Irregularity":
        x = np.asarray(x_m, dtype=float)
        r = np.asarray(r_m, dtype=float)
        if x.ndim != 1 or x.shape != r.shape or x.size < 2 or np.any(np.diff(x) <= 0):
            raise UserError("irregularity: expected increasing position samples and elevations of equal length")
        s = np.gradient(r, x)
        return cls(lambda q: np.interp(q, x, r), lambda q: np.interp(q, x, s))

    def elevation(self, x_m: np.ndarray) -> np.ndarray:
        if self._elev is None:
            return np.zeros_like(x_m, dtype=float)
        return np.asarray(self._elev(x_m), dtype=float).reshape(np.shape(x_m))

    def slope(self, x_m: np.ndarray) -> np.ndarray:
        if self._elev is None:
            return np.zeros_like(x_m, dtype=float)
        if self._slope is not None:
            return np.asarray(self._slope(x_m), dtype=float).reshape(np.shape(x_m))
        d = self._dx
        return (self.elevation(x_m + d) - self.elevation(x_m - d)) / (2 * d)


def as_irregularity(obj: Any) -> Irregularity:
    """None (perfect guideway), an ``Irregularity``, a callable r(x), an (x, r) pair of arrays, or a
    mapping with ``position_m`` and ``elevation_m``."""
    if obj is None:
        return Irregularity()
    if isinstance(obj, Irregularity):
        return obj
    if callable(obj):
        return Irregularity(obj)
    if isinstance(obj, Mapping):
        return Irregularity.from_samples(obj["position_m"], obj["elevation_m"])
    if isinstance(obj, (tuple, list)) and len(obj) == 2:
        return Irregularity.from_samples(obj[0], obj[1])
    raise UserError(f"irregularity: expected None, a callable r(x), (x, r) arrays or a mapping, got {type(obj).__name__}")


# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class PassResult:
    """Time histories at the output rate. Displacements from the static equilibrium, positive up."""
    time_s: np.ndarray                 # (n,)
    position_m: np.ndarray             # (n,) vehicle reference point
    speed_mps: np.ndarray              # (n,)
    dof_names: tuple[str, ...]
    vehicle_disp_m: np.ndarray         # (n, n_dof) (pitch DOFs in rad)
    vehicle_acc_mps2: np.ndarray       # (n, n_dof) (pitch DOFs in rad/s^2)
    magnet_accel_mps2: np.ndarray      # (n, n_mag)
    magnet_gap_m: np.ndarray           # (n, n_mag)
    magnet_current_a: np.ndarray       # (n, n_mag)
    magnet_force_n: np.ndarray         # (n, n_mag) upward on magnet (= downward on rail)
    sensor_names: tuple[str, ...]
    sensor_x_m: np.ndarray             # (n_sensors,)
    guideway_disp_m: np.ndarray        # (n, n_sensors)
    guideway_accel_mps2: np.ndarray    # (n, n_sensors)
    iterations: np.ndarray             # (n,) max iterations per output interval
    method: str = "newmark"
    dt_s: float = 1e-3

    @property
    def n_samples(self) -> int:
        return int(self.time_s.size)

    def sensor(self, name: str) -> int:
        return self.sensor_names.index(name)

    def summary(self) -> dict:
        def pk(a):
            return float(np.max(np.abs(a))) if a.size else 0.0
        return {
            "duration_s": float(self.time_s[-1] - self.time_s[0]) if self.n_samples else 0.0,
            "n_samples": self.n_samples, "method": self.method, "dt_s": self.dt_s,
            "magnet_accel_peak_mps2": pk(self.magnet_accel_mps2),
            "gap_min_m": float(self.magnet_gap_m.min()) if self.n_samples else 0.0,
            "gap_max_m": float(self.magnet_gap_m.max()) if self.n_samples else 0.0,
            "guideway_disp_peak_m": {n: pk(self.guideway_disp_m[:, i]) for i, n in enumerate(self.sensor_names)},
            "guideway_accel_peak_mps2": {n: pk(self.guideway_accel_mps2[:, i]) for i, n in enumerate(self.sensor_names)},
            "max_iterations": int(self.iterations.max()) if self.n_samples else 0,
        }

    def to_dict(self) -> dict:
        d = {}
        for k, v in self.__dict__.items():
            d[k] = v.tolist() if isinstance(v, np.ndarray) else (list(v) if isinstance(v, tuple) else v)
        return d

    @staticmethod
    def concat(parts: Sequence["PassResult"]) -> "PassResult":
        parts = [p for p in parts if p.n_samples] or list(parts[:1])
        p0 = parts[0]
        kw = {}
        for k, v in p0.__dict__.items():
            if isinstance(v, np.ndarray) and k != "sensor_x_m":
                kw[k] = np.concatenate([getattr(p, k) for p in parts], axis=0)
            else:
                kw[k] = v
        return PassResult(**kw)


# ---------------------------------------------------------------------------------------------
def _sensor_list(sensors: Any) -> tuple[tuple[str, ...], np.ndarray]:
    if sensors is None:
        return (), np.zeros(0)
    if isinstance(sensors, Mapping):
        names, xs = [], []
        for k, v in sensors.items():
            if isinstance(v, Mapping):
                if "position_m" not in v:
                    continue
                v = v["position_m"]
            names.append(str(k))
            xs.append(float(v))
        return tuple(names), np.array(xs, dtype=float)
    xs = np.atleast_1d(np.asarray(sensors, dtype=float))
    return tuple(f"x{x:g}" for x in xs), xs


def output_index(t_s: float, t0_s: float, fs_hz: float) -> int:
    """Index of the last output sample at or before ``t_s`` on the grid t0_s + k / fs_hz. Stamps are
    absolute (~1.7e9 s): their rounding is ~1e-4 of a 1 kHz sample, so a time on a sample must not
    floor to the one before it (a caller waiting for that sample then looped forever)."""
    return int(math.floor((t_s - t0_s) * fs_hz + 1e-3))


class TwinStepper:
    """Incremental coupled simulation (for the online twin): ``advance(t_end_s, speed_mps)``.

    Output samples are at t0 + k / fs_out_hz; the internal step is fs_out / n_sub with n_sub the
    smallest integer giving a step <= ``numerics.dt_max_s``. Within an ``advance`` call the speed
    ramps linearly from the previous speed to the new one.
    """

    def __init__(self, config: TwinConfig, line: Any = None, *, sensors: Any = None,
                 irregularity: Any = None, fs_out_hz: float = 1000.0, start_position_m: float = 0.0,
                 start_speed_mps: float = 0.0, t0_s: float = 0.0, method: str = "newmark",
                 dt_max_s: float | None = None, init: str = "static", block_steps: int = 1024,
                 current_limit_a: float | None = None, reference: bool = False,
                 current_limit_sides: str = "both"):
        if method not in METHODS:
            raise UserError(f"method: expected one of {METHODS}, got {method!r}")
        if not fs_out_hz > 0:
            raise UserError(f"fs_out_hz: expected a positive rate, got {fs_out_hz!r}")
        self.config = config
        self.method = method
        if current_limit_a is not None and not current_limit_a > 0:
            raise UserError(f"current_limit_a: expected a positive current headroom [A] or None, got {current_limit_a!r}")
        # magnet current saturation (default off): the force sees I0 + L tanh((I - I0) / L) with
        # L = current_limit_a [A] (see _kernel); Newmark scheme only
        if current_limit_a is not None and method != "newmark":
            raise UserError("current_limit_a: current saturation is available with method='newmark' only")
        self.current_limit_a = None if current_limit_a is None else float(current_limit_a)
        # "both": I0 +- L; "upper": the current cannot exceed I0 + L but follows any lower demand (a
        # supply's maximum current: the magnet's current is far from zero at the static gap)
        if current_limit_sides not in CURRENT_LIMIT_SIDES:
            raise UserError(f"current_limit_sides: expected one of {CURRENT_LIMIT_SIDES}, got {current_limit_sides!r}")
        self.current_limit_sides = current_limit_sides
        self.spans: tuple[SpanSpec, ...] = line_spans(line, config)
        num = config.numerics
        self.guideway = Guideway(self.spans, num.n_elements_per_span)
        self.modal: ModalBasis = self.guideway.modes(num.mode_cutoff_hz, num.min_modes_per_span)
        self.vehicle: VehicleSystem = build_vehicle(config)
        self.irregularity = as_irregularity(irregularity)
        self.sensor_names, self.sensor_x_m = _sensor_list(sensors)
        self.sensor_shapes = self.modal.shapes_at(self.sensor_x_m) if self.sensor_x_m.size else np.zeros((0, self.modal.n_modes))
        dt_max = num.dt_max_s if dt_max_s is None else float(dt_max_s)
        self.fs_out_hz = float(fs_out_hz)
        self.n_sub = max(1, int(math.ceil((1.0 / self.fs_out_hz) / dt_max - 1e-9)))
        self.dt_s = 1.0 / (self.fs_out_hz * self.n_sub)
        self.t0_s = float(t0_s)
        self.block_steps = int(block_steps)
        # reference: every mode of the line in every step (the span-local stepping's check, bench)
        self.reference = bool(reference)
        self.tol = num.iteration_tol
        self.max_iter = num.max_iterations
        self._setup_matrices()
        # state
        self._k = 0                                   # internal steps done
        self.position_m = float(start_position_m)
        self.speed_mps = float(start_speed_mps)
        nx, m, nq = self._nx, self._m, self.modal.n_modes
        self._x = np.zeros(nx)
        self._u = np.zeros(3 * m)
        self._q = np.zeros(nq)
        self._qd = np.zeros(nq)
        self._qdd = np.zeros(nq)
        self._F = self.vehicle.levitation.static_force_n.copy()
        if init == "static":
            self._init_static()
        elif init != "rest":
            raise UserError(f"init: expected 'static' or 'rest', got {init!r}")

    # ----------------------------------------------------------------------------------------
    @property
    def time_s(self) -> float:
        return self.t0_s + self._k * self.dt_s

    @property
    def magnet_offsets_m(self) -> np.ndarray:
        return self.vehicle.model.magnet_x_m

    def set_irregularity(self, irregularity: Any) -> None:
        self.irregularity = as_irregularity(irregularity)

    def set_vehicle_state(self, x: np.ndarray) -> None:
        """Overwrite the vehicle state (DOFs from static equilibrium, then velocities[, dI])."""
        x = np.asarray(x, dtype=float)
        if x.shape != self._x.shape:
            raise UserError(f"vehicle state: expected {self._x.shape[0]} values, got {x.shape}")
        self._x = x.copy()

    def _setup_matrices(self) -> None:
        vs = self.vehicle
        ss = vs.state_space
        lev = vs.levitation
        h = self.dt_s
        A, B = ss.A, ss.B
        nx, nu = A.shape[0], B.shape[1]
        m = ss.n_magnets
        self._nx, self._m = nx, m
        if self.method == "newmark":
            lhs = np.eye(nx) - 0.5 * h * A
            Ad = np.linalg.solve(lhs, np.eye(nx) + 0.5 * h * A)
            Bd1 = np.linalg.solve(lhs, 0.5 * h * B)
            Bd0 = Bd1.copy()
        else:
            aug = np.zeros((nx + 2 * nu, nx + 2 * nu))
            aug[:nx, :nx] = A * h
            aug[:nx, nx:nx + nu] = B * h
            aug[nx:nx + nu, nx + nu:] = np.eye(nu)
            E = expm(aug)
            Ad = E[:nx, :nx]
            G1 = E[:nx, nx:nx + nu]
            G2 = E[:nx, nx + nu:]
            Bd0, Bd1 = G1 - G2, G2
        Ad, Bd0, Bd1 = (np.ascontiguousarray(a) for a in (Ad, Bd0, Bd1))
        self._Ad, self._Bd0, self._Bd1 = Ad, Bd0, Bd1
        # outputs: [z_m; z_m'; a_m; dI]
        O = np.vstack([ss.out_z[0], ss.out_zd[0], ss.out_acc[0], ss.out_dcurrent[0]])
        OD = np.vstack([ss.out_z[1], ss.out_zd[1], ss.out_acc[1], ss.out_dcurrent[1]])
        # linear force F_lin = F0 + Lx x + Lu u
        p = lev.partials()
        # F_lin - F0 = ki dI - kgap (y - z_m) + N, dI = out_dcurrent (C x + D u): one form for the plain
        # law, coil dynamics and a delayed law
        ki, kgap = p.df_dcurrent_n_per_a, -p.df_dgap_fixed_current_n_per_m
        Lx = ki[:, None] * ss.out_dcurrent[0] + kgap[:, None] * ss.out_z[0]
        Lu = (ki[:, None] * ss.out_dcurrent[1]
              + np.hstack([-np.diag(kgap), np.zeros((m, m)), np.eye(m)]))
        self._O, self._OD = np.ascontiguousarray(O), np.ascontiguousarray(OD)
        self._OL = np.ascontiguousarray(np.vstack([O, Lx]))          # (5m, nx)
        self._G = np.ascontiguousarray(O @ Bd1 + OD)                  # (4m, 3m)
        E = Lx @ Bd1 + Lu                                            # (m, 3m)
        self._E = E
        self._GL = np.ascontiguousarray(np.vstack([self._G, E]))     # (5m, 3m)
        self._ABd0 = np.ascontiguousarray(np.hstack([Ad, Bd0]))
        # guideway Newmark (average acceleration) per mode, prewarped (:func:`prewarped_modes`)
        w, z, self._force_gain = prewarped_modes(self.modal.omega_rad_s, self.modal.damping_ratio, h,
                                                 self.config.numerics.modal_prewarp)
        self._khat = w ** 2 + 2 * z * w * (2 / h) + 4 / h ** 2
        self._gq = 1.0 / self._khat
        self._c2zw = 2 * z * w
        self._acc_x, self._acc_u = ss.out_dof_acc
        self._Ey = np.ascontiguousarray(E[:, :m])
        self._Eyd = np.ascontiguousarray(E[:, m:2 * m])
        self._EN = np.ascontiguousarray(E[:, 2 * m:])
        # the kernel's matrices, transposed (see _kernel)
        self._kmats = tuple(np.ascontiguousarray(a.T) for a in (self._OL, self._GL, self._ABd0, self._Bd1, self._O,
                                                               self._OD, self._Ey, self._Eyd))
        self._free_T = _free_transition(self._gq, self._c2zw, h)
        self._free_pow: dict[int, np.ndarray] = {}
        self._obs_for = None

    # ----------------------------------------------------------------------------------------
    def _init_static(self) -> None:
        """Guideway statically deflected under the static magnet forces at the start position and
        the vehicle in its closed-loop static state on that rail (a few fixed-point passes)."""
        ss = self.vehicle.state_space
        m = self._m
        X = self.position_m + self.magnet_offsets_m
        phi = self.modal.shapes_at(X)
        r = self.irregularity.elevation(X)
        F = self.vehicle.levitation.static_force_n.copy()
        w2 = self.modal.omega_rad_s ** 2
        Ainv_B = np.linalg.solve(ss.A, ss.B[:, :m])
        for _ in range(4):
            q = -(phi.T @ F) / w2
            y = r + phi @ q
            x = -Ainv_B @ y
            zm = ss.out_z[0] @ x
            # only static linear stiffness matters here
            p = self.vehicle.levitation.partials()
            dI = ss.out_dcurrent[0] @ x + ss.out_dcurrent[1] @ np.concatenate([y, np.zeros(2 * m)])
            F = self.vehicle.levitation.static_force_n + p.df_dcurrent_n_per_a * dI \
                + p.df_dgap_fixed_current_n_per_m * (y - zm)
        self._q = q
        self._x = x
        self._u = np.concatenate([y, np.zeros(2 * m)])
        self._F = F

    # ----------------------------------------------------------------------------------------
    def _prepare(self, pos: np.ndarray, vel: np.ndarray, local: bool = False) -> dict:
        """Position-dependent quantities for a block of steps (vectorised). ``local``: only the
        modes of the spans under the magnets (``modes``, the columns of every modal array)."""
        m = self._m
        X = pos[:, None] + self.magnet_offsets_m[None, :]
        Xf = X.ravel()
        if local:
            spans, phi, dphi = self.modal.local_shapes_at(Xf)
            modes = self.modal.mode_columns(spans)
        else:
            phi, dphi, modes = self.modal.shapes_at(Xf), self.modal.slopes_at(Xf), None
        nq = phi.shape[1]
        phi = phi.reshape(X.shape[0], m, nq)
        dphi = dphi.reshape(X.shape[0], m, nq)
        r = self.irregularity.elevation(Xf).reshape(X.shape)
        rd = self.irregularity.slope(Xf).reshape(X.shape) * vel[:, None]
        g = self._gq if modes is None else self._gq[modes]
        gain = self._force_gain if modes is None else self._force_gain[modes]
        phig = phi * g[None, None, :]
        # the modal forces phi^T F, times the prewarp's force gain (the rail displacement phi q is not)
        phiT = np.ascontiguousarray(np.transpose(phi, (0, 2, 1)) * gain[None, :, None])
        P = phig @ phiT
        Qc = (dphi * g[None, None, :]) @ phiT
        Q = (2 / self.dt_s) * P + vel[:, None, None] * Qc
        # the kernel takes its matrices transposed (phiF: phiT's transpose)
        out = {"modes": modes, "phit": np.ascontiguousarray(np.transpose(phi, (0, 2, 1))),
               "dphit": np.ascontiguousarray(np.transpose(dphi, (0, 2, 1))),
               "phiF": phi * gain[None, None, :], "r": r, "rd": rd}
        if self.method == "newmark":
            Ey, Eyd = self._E[:, :m], self._E[:, m:2 * m]
            S = np.linalg.inv(np.eye(m)[None] + Ey @ P + Eyd @ Q)
            out["St"] = np.ascontiguousarray(np.transpose(S, (0, 2, 1)))
            out["SENt"] = np.ascontiguousarray(np.transpose(S @ self._E[:, 2 * m:], (0, 2, 1)))
        else:
            out["St"] = out["SENt"] = np.zeros((1, m, m))
        return out

    def advance(self, t_end_s: float, speed_mps: float | None = None) -> PassResult:
        """Advance to the last output sample at or before ``t_end_s``; returns those samples."""
        v_new = self.speed_mps if speed_mps is None else float(speed_mps)
        k_out_end = output_index(t_end_s, self.t0_s, self.fs_out_hz)
        k_end = k_out_end * self.n_sub
        n_total = k_end - self._k
        if n_total <= 0:
            self.speed_mps = v_new
            return self._empty()
        v0 = self.speed_mps
        parts = []
        done = 0
        while done < n_total:
            nb = min(self.block_steps, n_total - done)
            # linear speed ramp over the whole advance() span
            frac = (done + np.arange(1, nb + 1)) / n_total
            frac_prev = (done + np.arange(0, nb)) / n_total
            vel = v0 + (v_new - v0) * frac
            vel_prev = v0 + (v_new - v0) * frac_prev
            pos = self.position_m + np.cumsum(0.5 * (vel + vel_prev) * self.dt_s)
            parts.append(self._run_block(pos, vel))
            done += nb
        self.speed_mps = v_new
        return parts[0] if len(parts) == 1 else PassResult.concat(parts)

    def _saturation(self, lev) -> tuple:
        """(sat, L below, L above, unused) for the kernel: smooth current limit L = current_limit_a
        (below: 0, no limit, when only the upper side is limited)."""
        lim = self.current_limit_a
        if lim is None or not math.isfinite(lim):
            return False, 0.0, 0.0, _NO_EXCESS
        return True, (float(lim) if self.current_limit_sides == "both" else 0.0), float(lim), _NO_EXCESS

    def _empty(self) -> PassResult:
        m, nd, ns = self._m, self.vehicle.model.n_dof, self.sensor_x_m.size
        z = np.zeros
        return PassResult(z(0), z(0), z(0), self.vehicle.model.dof_names, z((0, nd)), z((0, nd)), z((0, m)),
                          z((0, m)), z((0, m)), z((0, m)), self.sensor_names, self.sensor_x_m, z((0, ns)),
                          z((0, ns)), z(0, dtype=int), self.method, self.dt_s)

    # ----------------------------------------------------------------------------------------
    def _run_block(self, pos: np.ndarray, vel: np.ndarray) -> PassResult:
        """One block of steps. Only the modes of the spans under the magnets during the block enter
        the coupled kernel; the others vibrate freely: those seen by a sensor are stepped one by one
        (for their outputs), the rest jump to the block's end by the scheme's transition matrix."""
        if self.reference:
            return self._run_block_full(pos, vel)
        ns = pos.size
        m, nq = self._m, self.modal.n_modes
        pre = self._prepare(pos, vel, local=True)
        act = pre["modes"]
        lev = self.vehicle.levitation
        h = self.dt_s
        newmark = self.method == "newmark"
        k0 = self._k
        out_idx = _output_steps(k0, ns, self.n_sub)
        no = out_idx.size
        x, u, F = self._x.copy(), self._u.copy(), self._F.copy()
        q, qd, qdd = self._q[act], self._qd[act], self._qdd[act]
        rec_x = np.empty((no, self._x.size))
        rec_u = np.empty((no, self._u.size))
        rec_q = np.empty((no, act.size))
        rec_qdd = np.empty((no, act.size))
        rec_mag = np.empty((no, 4, m))
        rec_it = np.zeros(no, dtype=np.int64)
        _KERNEL(newmark, h, float(lev.nominal_gap_m), float(lev.static_current_a), lev.force_coeff,
                lev.static_force_n, self.tol * float(np.mean(lev.static_force_n)), int(self.max_iter),
                *self._kmats, self._gq[act], self._c2zw[act], pre["phit"], pre["dphit"], pre["phiF"],
                pre["r"], pre["rd"], np.ascontiguousarray(vel, dtype=float), pre["St"], pre["SENt"],
                x, u, q, qd, qdd, F, out_idx, rec_x, rec_u, rec_q, rec_qdd, rec_mag, rec_it,
                *self._saturation(lev))
        self._x, self._u, self._F = x, u, F
        # the modes the sensors see: loaded ones from the kernel, free ones stepped here
        obs, shapes = self._observed()
        loaded = np.zeros(nq, bool)
        loaded[act] = True
        in_act = loaded[obs]
        Qo = np.empty((no, obs.size))
        Qddo = np.empty((no, obs.size))
        where = np.searchsorted(act, obs[in_act])
        Qo[:, in_act], Qddo[:, in_act] = rec_q[:, where], rec_qdd[:, where]
        # (called with no modes too: compiled with the kernel, not first when a span rings alone)
        fo = obs[~in_act]
        fq, fqd, fqdd = self._q[fo], self._qd[fo], self._qdd[fo]
        rq, rqdd = np.empty((no, fo.size)), np.empty((no, fo.size))
        _FREE(h, self._gq[fo], self._c2zw[fo], ns, fq, fqd, fqdd, out_idx, rq, rqdd)
        self._q[fo], self._qd[fo], self._qdd[fo] = fq, fqd, fqdd
        Qo[:, ~in_act], Qddo[:, ~in_act] = rq, rqdd
        loaded[fo] = True
        self._q[act], self._qd[act], self._qdd[act] = q, qd, qdd
        # every other mode: n steps of free vibration in one product per mode
        rest = np.flatnonzero(~loaded)
        if rest.size:
            Tn = self._free_power(ns)[rest]
            s0 = np.stack([self._q[rest], self._qd[rest], self._qdd[rest]], axis=1)
            s1 = np.einsum("kij,kj->ki", Tn, s0)
            self._q[rest], self._qd[rest], self._qdd[rest] = s1[:, 0], s1[:, 1], s1[:, 2]
        self._k += ns
        self.position_m = float(pos[-1])
        t = self.t0_s + (k0 + out_idx + 1) * h
        nd = self.vehicle.model.n_dof
        acc = rec_x @ self._acc_x.T + rec_u @ self._acc_u.T
        return PassResult(
            time_s=t, position_m=pos[out_idx], speed_mps=vel[out_idx], dof_names=self.vehicle.model.dof_names,
            vehicle_disp_m=rec_x[:, :nd], vehicle_acc_mps2=acc,
            magnet_accel_mps2=rec_mag[:, 0], magnet_gap_m=rec_mag[:, 1], magnet_current_a=rec_mag[:, 2],
            magnet_force_n=rec_mag[:, 3], sensor_names=self.sensor_names, sensor_x_m=self.sensor_x_m,
            guideway_disp_m=Qo @ shapes.T, guideway_accel_mps2=Qddo @ shapes.T,
            iterations=rec_it, method=self.method, dt_s=h)

    def _observed(self) -> tuple[np.ndarray, np.ndarray]:
        """Modes a sensor sees (non-zero shape at some sensor) and the sensors' shapes on them."""
        if self._obs_for is not self.sensor_shapes:     # (re)built with the basis (discrepancy models swap it)
            obs = np.flatnonzero(np.any(self.sensor_shapes != 0.0, axis=0))
            self._obs = (obs, np.ascontiguousarray(self.sensor_shapes[:, obs]))
            self._obs_for = self.sensor_shapes
        return self._obs

    def _free_power(self, n: int) -> np.ndarray:
        """Transition of n free steps per mode, (n_modes, 3, 3) on (q, q', q'')."""
        Tn = self._free_pow.get(n)
        if Tn is None:
            if len(self._free_pow) > 16:
                self._free_pow.clear()
            Tn = self._free_pow[n] = np.linalg.matrix_power(self._free_T, n)
        return Tn

    def _run_block_full(self, pos: np.ndarray, vel: np.ndarray) -> PassResult:
        """``_run_block`` with every mode of the line in every step (reference)."""
        ns = pos.size
        pre = self._prepare(pos, vel)
        lev = self.vehicle.levitation
        m = self._m
        h = self.dt_s
        newmark = self.method == "newmark"
        k0 = self._k
        out_idx = np.array([i for i in range(ns) if (k0 + i + 1) % self.n_sub == 0], dtype=np.int64)
        no = out_idx.size
        state = [self._x.copy(), self._u.copy(), self._q.copy(), self._qd.copy(), self._qdd.copy(), self._F.copy()]
        rec_x = np.empty((no, self._x.size))
        rec_u = np.empty((no, self._u.size))
        rec_q = np.empty((no, self._q.size))
        rec_qdd = np.empty((no, self._q.size))
        rec_mag = np.empty((no, 4, m))
        rec_it = np.zeros(no, dtype=np.int64)
        _KERNEL(newmark, h, float(lev.nominal_gap_m), float(lev.static_current_a), lev.force_coeff,
                lev.static_force_n, self.tol * float(np.mean(lev.static_force_n)), int(self.max_iter),
                *self._kmats, self._gq, self._c2zw, pre["phit"], pre["dphit"], pre["phiF"], pre["r"], pre["rd"],
                np.ascontiguousarray(vel, dtype=float), pre["St"], pre["SENt"],
                state[0], state[1], state[2], state[3], state[4], state[5],
                out_idx, rec_x, rec_u, rec_q, rec_qdd, rec_mag, rec_it, *self._saturation(lev))
        self._x, self._u, self._q, self._qd, self._qdd, self._F = state
        self._k += ns
        self.position_m = float(pos[-1])
        t = self.t0_s + (k0 + out_idx + 1) * h
        nd = self.vehicle.model.n_dof
        acc = rec_x @ self._acc_x.T + rec_u @ self._acc_u.T
        return PassResult(
            time_s=t, position_m=pos[out_idx], speed_mps=vel[out_idx], dof_names=self.vehicle.model.dof_names,
            vehicle_disp_m=rec_x[:, :nd], vehicle_acc_mps2=acc,
            magnet_accel_mps2=rec_mag[:, 0], magnet_gap_m=rec_mag[:, 1], magnet_current_a=rec_mag[:, 2],
            magnet_force_n=rec_mag[:, 3], sensor_names=self.sensor_names, sensor_x_m=self.sensor_x_m,
            guideway_disp_m=rec_q @ self.sensor_shapes.T, guideway_accel_mps2=rec_qdd @ self.sensor_shapes.T,
            iterations=rec_it, method=self.method, dt_s=h)


def _output_steps(k0: int, ns: int, n_sub: int) -> np.ndarray:
    """Indices i of the block's steps k0 + i (0 <= i < ns) that end an output interval."""
    first = (-(k0 + 1)) % n_sub
    return np.arange(first, ns, n_sub, dtype=np.int64)


def _free_transition(gq: np.ndarray, c2zw: np.ndarray, h: float) -> np.ndarray:
    """One Newmark step of each unloaded mode as a matrix on (q, q', q''): (n_modes, 3, 3)."""
    a4, a2, b = 4.0 / (h * h), 2.0 / h, 4.0 / h
    T = np.zeros((gq.size, 3, 3))
    T[:, 0, 0] = gq * (a4 + c2zw * a2)
    T[:, 0, 1] = gq * (b + c2zw)
    T[:, 0, 2] = gq
    T[:, 1] = a2 * T[:, 0]
    T[:, 1, 0] -= a2
    T[:, 1, 1] -= 1.0
    T[:, 2] = a4 * T[:, 0]
    T[:, 2, 0] -= a4
    T[:, 2, 1] -= b
    T[:, 2, 2] -= 1.0
    return T


def _free_steps(h, gq, c2zw, ns, q, qd, qdd, out_idx, rec_q, rec_qdd):
    """ns Newmark steps of unloaded modes (in place), the kernel's own arithmetic; records q, q''
    at ``out_idx``."""
    a4 = 4.0 / (h * h)
    a2 = 2.0 / h
    j = 0
    n_out = out_idx.size
    for i in range(ns):
        for k in range(q.size):
            qc = q[k]
            qdc = qd[k]
            qn = (a4 * qc + (4.0 / h) * qdc + qdd[k] + c2zw[k] * (a2 * qc + qdc)) * gq[k]
            qdd[k] = a4 * (qn - qc) - (4.0 / h) * qdc - qdd[k]
            qd[k] = a2 * (qn - qc) - qdc
            q[k] = qn
        if j < n_out and out_idx[j] == i:
            rec_q[j] = q
            rec_qdd[j] = qdd
            j += 1


def prewarped_modes(omega_rad_s: np.ndarray, damping_ratio: np.ndarray, h_s: float,
                    prewarp: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(frequency, damping ratio, force gain) per mode to integrate with Newmark average acceleration.

    That scheme is the trapezoidal rule (Tustin map s -> (2/h)(z-1)/(z+1)): a mode at w rings at
    (2/h) arctan(w h/2), 2.7 % low for 93 Hz at h = 1 ms, which moved the guideway's second bending
    mode across the 88 Hz band edge and was most of a calibrated twin's misfit on quarter-span
    accelerometers (held-out NRMSE 0.15-0.18; 0.07-0.11 with the frequency prewarp alone, blind clean case). Prewarped (written by hand: a
    standard filter-design step, for modal oscillators here): w' = (2/h) tan(w h/2) puts the discrete
    resonance at w exactly, a force gain g = (w'/w)^2 keeps the static deflection g/w'^2 = 1/w^2, and
    the damping ratio g*zeta makes the acceleration response's peak and half-power width those of
    the continuous mode (to 0.1 % at w h = 0.58, 3 % at w h = 1.6); the displacement's resonant peak
    is 1/g low, the quasi-static deflection exact. Tan is capped at w h/2 = 1.4 (modes near the step's
    Nyquist rate stay finite): a mode above the cap rings at it (0.89 x the step's Nyquist frequency,
    outside the bands a recording is compared in: the twin steps at least at the recording's rate) and is
    kept for its quasi-static share at the sensors. ``prewarp=False``: the plain scheme."""
    w = np.asarray(omega_rad_s, float)
    z = np.asarray(damping_ratio, float)
    if not prewarp:
        return w, z, np.ones_like(w)
    wp = (2.0 / h_s) * np.tan(np.minimum(0.5 * w * h_s, 1.4))
    g = np.divide(wp, w, out=np.ones_like(w), where=w > 0) ** 2
    return wp, z * g, g


def _mvt_into(out, At, x):
    """out = A @ x from At = A^T: each out[i] sums A[i, j] x[j] over j = 0, 1, ... in order (the
    rounding of a row-by-row loop) while the inner loop over i runs over contiguous memory
    without a carried dependency (SIMD; a row-by-row dot product waits on its accumulator)."""
    k, n = At.shape
    for i in range(n):
        out[i] = 0.0
    for j in range(k):
        xj = x[j]
        for i in range(n):
            out[i] += At[j, i] * xj


def _sat_current(c, I0, i_lo, i_hi):
    """The current the force sees for a commanded current c: I0 + L tanh((c - I0) / L) on a limited
    side (L = i_hi above I0, i_lo below it; i_lo = 0: no limit below)."""
    x = c - I0
    if x >= 0.0:
        return I0 + i_hi * np.tanh(x / i_hi)
    if i_lo > 0.0:
        return I0 + i_lo * np.tanh(x / i_lo)
    return c


def _sat_slope(c, I0, i_lo, i_hi):
    """d(_sat_current)/dc."""
    x = c - I0
    if x >= 0.0:
        t = np.tanh(x / i_hi)
        return 1.0 - t * t
    if i_lo > 0.0:
        t = np.tanh(x / i_lo)
        return 1.0 - t * t
    return 1.0


def _sat_newton_step(res, cur, cur_cmd, gap, Cc, I0, i_lo, i_hi, GLt, phit, phiF, dphit, gq, SENt, a2, v, m):
    """Newton step dN for res(N) = F_true(N) - F_coupled(N) = 0 with saturating currents.

    Within a step the command current and the gap are affine in the force remainder N (rail
    through the condensed guideway compliance P, Q; vehicle through GL), so the Jacobian is exact
    up to the force law's curvature: J = diag(dF/dI [unclipped]) D_I + diag(dF/dgap) D_gap - SEN.
    Matrices come transposed as in :func:`_kernel`."""
    GL = np.ascontiguousarray(GLt.T)
    phi = np.ascontiguousarray(phit.T)
    phiT = np.ascontiguousarray(phiF.T)
    dphi = np.ascontiguousarray(dphit.T)
    SEN = np.ascontiguousarray(SENt.T)
    m2 = 2 * m
    m3 = 3 * m
    P = phi @ (gq.reshape(-1, 1) * phiT)
    Qm = a2 * P + v * (dphi @ (gq.reshape(-1, 1) * phiT))
    dy = -(P @ SEN)
    dyd = -(Qm @ SEN)
    gi = np.ascontiguousarray(GL[m3:m3 + m])
    gz = np.ascontiguousarray(GL[:m])
    D_i = np.ascontiguousarray(gi[:, :m]) @ dy + np.ascontiguousarray(gi[:, m:m2]) @ dyd + gi[:, m2:m3]
    D_z = np.ascontiguousarray(gz[:, :m]) @ dy + np.ascontiguousarray(gz[:, m:m2]) @ dyd + gz[:, m2:m3]
    D_g = dy - D_z
    f = Cc * (cur / gap) ** 2
    sl = np.empty(m)
    for a in range(m):
        sl[a] = _sat_slope(cur_cmd[a], I0, i_lo, i_hi)
    dF_di = 2.0 * f / cur * sl
    dF_dg = -2.0 * f / gap
    J = dF_di.reshape(-1, 1) * D_i + dF_dg.reshape(-1, 1) * D_g - SEN
    return np.linalg.solve(J, res)


def _kernel(newmark, h, g0, I0, Cc, F0, tol_abs, max_iter, OLt, GLt, ABd0t, Bd1t, Ot, ODt, Eyt, Eydt, gq, c2zw,
            phit_all, dphit_all, phiF_all, r_all, rd_all, vel, St_all, SENt_all,
            x, u, q, qd, qdd, F, out_idx, rec_x, rec_u, rec_q, rec_qdd, rec_mag, rec_it,
            sat=False, i_lo=0.0, i_hi=0.0, sat_excess=np.zeros(1)):
    """Time loop over one block (state arrays x, u, q, qd, qdd, F updated in place).

    ``sat``: magnet current saturation (``TwinStepper.current_limit_a`` = L, off by default): the
    force is made by I_eff = I0 + L tanh((I - I0) / L) (:func:`_sat_current`, above I0 with
    L = ``i_hi``, below with ``i_lo``, none below when ``i_lo`` = 0; smooth: slope 1 at the static current, so
    the linearised model is unchanged, and |I_eff - I0| < L; a hard clip makes the EMS magnet
    lose levitation as soon as demand exceeds L, a smooth limit degrades gradually like a
    saturating core/chopper). The plain update N += res diverges when the current saturates
    (the control law's acceleration feed-through path is cut), so with ``sat`` the force
    remainder is solved by Newton (:func:`_sat_newton_step`). ``sat_excess`` unused.

    Matrices come transposed (``*t``; ``phiF`` = phi^T's transpose, the magnet-to-mode force map):
    ``_mvt_into`` then sums each product over the same index order as a row-by-row product, in a loop
    the compiler can vectorise.

    Work arrays are allocated once per block and every per-step quantity is computed in place,
    element by element in the order of the vector expressions it replaces (the same rounding; an
    allocation per small vector was half the compiled loop's time). Plain code that numba compiles
    (it is jitted when numba is installed; otherwise it runs as ordinary Python, much slower)."""
    m = F0.size
    m2 = 2 * m
    m3 = 3 * m
    m4 = 4 * m
    nx = x.size
    nq = q.size
    a4 = 4.0 / (h * h)
    a2 = 2.0 / h
    ns = vel.size
    xu = np.empty(nx + u.size)
    xp = np.empty(nx)
    oxp = np.empty(OLt.shape[1])
    o = np.empty(GLt.shape[1])
    o2 = np.empty(Ot.shape[1])
    o3 = np.empty(Ot.shape[1])
    qp = np.empty(nq)
    qdp = np.empty(nq)
    gF = np.empty(nq)
    ucur = np.empty(m3)
    yp = np.empty(m)
    ydp = np.empty(m)
    base = np.empty(m)
    Sb = np.zeros(m)
    y = np.empty(m)
    yd = np.empty(m)
    pg = np.empty(m)
    t1 = np.empty(m)
    t2 = np.empty(m)
    gap = np.empty(m)
    cur = np.empty(m)
    cur_cmd = np.empty(m)
    Ft = np.empty(m)
    res = np.empty(m)
    N = u[m2:].copy()
    xc = x.copy()
    uc = u.copy()
    qc = q.copy()
    qdc = qd.copy()
    qddc = qdd.copy()
    Fc = F.copy()
    j = 0
    it_max = 0
    n_out = out_idx.size
    for i in range(ns):
        phit = phit_all[i]
        phiF = phiF_all[i]
        dphit = dphit_all[i]
        v = vel[i]
        xu[:nx] = xc
        xu[nx:] = uc
        _mvt_into(xp, ABd0t, xu)
        _mvt_into(oxp, OLt, xp)
        for k in range(nq):
            qp[k] = (a4 * qc[k] + (4.0 / h) * qdc[k] + qddc[k] + c2zw[k] * (a2 * qc[k] + qdc[k])) * gq[k]
            qdp[k] = a2 * (qp[k] - qc[k]) - qdc[k]
        _mvt_into(t1, phit, qp)
        for a in range(m):
            yp[a] = r_all[i, a] + t1[a]
        _mvt_into(t1, phit, qdp)
        _mvt_into(t2, dphit, qp)
        for a in range(m):
            ydp[a] = rd_all[i, a] + t1[a] + v * t2[a]
        if newmark:
            _mvt_into(t1, Eyt, yp)
            _mvt_into(t2, Eydt, ydp)
            for a in range(m):
                base[a] = F0[a] + oxp[m4 + a] + t1[a] + t2[a]
            _mvt_into(Sb, St_all[i], base)
        it = 0
        while it < max_iter:
            it += 1
            if newmark:
                _mvt_into(t1, SENt_all[i], N)
                for a in range(m):
                    Fc[a] = Sb[a] + t1[a]
            _mvt_into(gF, phiF, Fc)
            for k in range(nq):
                gF[k] = gq[k] * gF[k]
            _mvt_into(pg, phit, gF)
            _mvt_into(t2, dphit, gF)
            for a in range(m):
                y[a] = yp[a] - pg[a]
                yd[a] = ydp[a] - a2 * pg[a] - v * t2[a]
                ucur[a] = y[a]
                ucur[m + a] = yd[a]
                ucur[m2 + a] = N[a]
            _mvt_into(o, GLt, ucur)
            for k in range(o.size):
                o[k] = oxp[k] + o[k]
            for a in range(m):
                gap[a] = g0 + y[a] - o[a]
                cur[a] = I0 + o[m3 + a]
            if sat:
                for a in range(m):
                    cur_cmd[a] = cur[a]
                    cur[a] = _sat_current(cur_cmd[a], I0, i_lo, i_hi)
            for a in range(m):
                Ft[a] = Cc[a] * (cur[a] / gap[a]) ** 2
            if newmark:
                for a in range(m):
                    res[a] = Ft[a] - Fc[a]
                if sat:
                    dN = _sat_newton_step(res, cur, cur_cmd, gap, Cc, I0, i_lo, i_hi, GLt, phit, phiF, dphit,
                                          gq, SENt_all[i], a2, v, m)
                    for a in range(m):
                        N[a] = N[a] - dN[a]
                else:
                    for a in range(m):
                        N[a] = N[a] + res[a]
                Fc[:] = Ft
                if _absmax(res) < tol_abs:
                    break
            else:
                for a in range(m):
                    res[a] = Ft[a] - (F0[a] + o[m4 + a])      # o[m4:] = F_lin - F0 + N
                    t1[a] = Ft[a] - Fc[a]
                dF = _absmax(t1)
                dN = _absmax(res)
                Fc[:] = Ft
                for a in range(m):
                    N[a] = N[a] + res[a]
                if dF < tol_abs and dN < tol_abs:
                    break
        if it > it_max:
            it_max = it
        _mvt_into(gF, phiF, Fc)
        for k in range(nq):
            gF[k] = gq[k] * gF[k]
        _mvt_into(pg, phit, gF)
        _mvt_into(t2, dphit, gF)
        for a in range(m):
            y[a] = yp[a] - pg[a]
            yd[a] = ydp[a] - a2 * pg[a] - v * t2[a]
            uc[a] = y[a]
            uc[m + a] = yd[a]
            uc[m2 + a] = N[a]
        _mvt_into(xc, Bd1t, uc)
        for k in range(nx):
            xc[k] = xp[k] + xc[k]
        for k in range(nq):
            qn = qp[k] - gF[k]
            qddc[k] = a4 * (qn - qc[k]) - (4.0 / h) * qdc[k] - qddc[k]
            qdc[k] = a2 * (qn - qc[k]) - qdc[k]
            qc[k] = qn
        if j < n_out and out_idx[j] == i:
            _mvt_into(o2, Ot, xc)
            _mvt_into(o3, ODt, uc)
            for k in range(o2.size):
                o2[k] = o2[k] + o3[k]
            for a in range(m):
                gap[a] = g0 + y[a] - o2[a]
                cur[a] = I0 + o2[m3 + a]
                if sat:
                    cur[a] = _sat_current(cur[a], I0, i_lo, i_hi)
                rec_mag[j, 0, a] = o2[m2 + a]
                rec_mag[j, 1, a] = gap[a]
                rec_mag[j, 2, a] = cur[a]
                rec_mag[j, 3, a] = Cc[a] * (cur[a] / gap[a]) ** 2
            rec_x[j] = xc
            rec_u[j] = uc
            rec_q[j] = qc
            rec_qdd[j] = qddc
            rec_it[j] = it_max
            it_max = 0
            j += 1
    x[:] = xc
    u[:] = uc
    q[:] = qc
    qd[:] = qdc
    qdd[:] = qddc
    F[:] = Fc


def _absmax(v):
    """max |v_i| (NaN if any is NaN, like np.abs(v).max())."""
    r = 0.0
    for a in range(v.size):
        e = abs(v[a])
        if e > r or e != e:
            r = e
            if e != e:
                return e
    return r


try:  # optional accelerator
    import numba as _numba
    _mvt_into = _numba.njit(cache=True)(_mvt_into)
    _absmax = _numba.njit(cache=True)(_absmax)
    _sat_current = _numba.njit(cache=True)(_sat_current)
    _sat_slope = _numba.njit(cache=True)(_sat_slope)
    _sat_newton_step = _numba.njit(cache=True)(_sat_newton_step)
    _KERNEL = _numba.njit(cache=True)(_kernel)
    _FREE = _numba.njit(cache=True)(_free_steps)
    HAVE_NUMBA = True
except Exception:  # pragma: no cover - numba missing or broken: plain Python (slower; BLAS products)
    def _mvt_into(out, At, x):
        np.dot(x, At, out=out)
    _KERNEL = _kernel
    _FREE = _free_steps
    HAVE_NUMBA = False


# ---------------------------------------------------------------------------------------------
def _speed_profile(speed_mps: Any) -> Callable[[float], float]:
    if callable(speed_mps):
        return lambda t: float(speed_mps(t))
    if isinstance(speed_mps, (tuple, list)) and len(speed_mps) == 2:
        ts = np.asarray(speed_mps[0], dtype=float)
        vs = np.asarray(speed_mps[1], dtype=float)
        return lambda t: float(np.interp(t, ts, vs))
    v = float(speed_mps)
    return lambda t: v


def simulate_pass(config: TwinConfig, line: Any = None, speed_mps: Any = 6.944, irregularity: Any = None,
                  sensors: Any = None, duration_s: float | None = None, fs_out_hz: float = 1000.0, *,
                  start_position_m: float | None = None, method: str = "newmark",
                  dt_max_s: float | None = None, block_s: float = 0.5) -> PassResult:
    """One vehicle pass over ``line`` (metadata ``line`` block, span dicts or ``SpanSpec``s).

    ``speed_mps``: constant, a callable v(t) or (t, v) arrays (linear in between). The vehicle
    reference point starts at ``start_position_m`` (default: front magnet 2 m before the line) in its
    static equilibrium; ``duration_s`` defaults (constant speed) to the time until the rear magnet is
    2 m past the line end. ``sensors``: guideway x positions (list, or mapping name -> x or -> a
    contract sensor entry with ``position_m``).
    """
    stepper = TwinStepper(config, line, sensors=sensors, irregularity=irregularity, fs_out_hz=fs_out_hz,
                          start_position_m=0.0, method=method, dt_max_s=dt_max_s, init="rest")
    offs = stepper.magnet_offsets_m
    gw = stepper.guideway
    x0 = gw.start_m - float(offs.max()) - 2.0 if start_position_m is None else float(start_position_m)
    prof = _speed_profile(speed_mps)
    if duration_s is None:
        if callable(speed_mps) or isinstance(speed_mps, (tuple, list)):
            raise UserError("duration_s: required when the speed is not constant")
        v = prof(0.0)
        if v <= 0:
            raise UserError(f"speed_mps: expected a positive speed, got {v}")
        duration_s = (gw.end_m + 2.0 - (x0 + float(offs.min()))) / v
    stepper.position_m = x0
    stepper.speed_mps = prof(0.0)
    stepper._init_static()
    parts = []
    t = 0.0
    while t < duration_s - 1e-12:
        t_next = min(duration_s, t + block_s)
        parts.append(stepper.advance(t_next, prof(t_next)))
        t = t_next
    return PassResult.concat(parts)


def moving_force_response(modal: ModalBasis, forces_n: Sequence[float], offsets_m: Sequence[float],
                          start_position_m: float, speed_mps: float, duration_s: float, dt_s: float,
                          sensors_x_m: Sequence[float], prewarp: bool = True
                          ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Guideway response to constant vertical forces (positive up) moving at constant speed, with
    the same modal Newmark scheme (:func:`prewarped_modes`) and shape functions as the coupled solver
    (no vehicle).

    Returns (time_s, displacement_m (n, n_sensors), acceleration_mps2 (n, n_sensors)).
    """
    f = np.asarray(forces_n, dtype=float)
    offs = np.asarray(offsets_m, dtype=float)
    h = float(dt_s)
    n = int(round(duration_s / h))
    t = np.arange(1, n + 1) * h
    X = start_position_m + speed_mps * t[:, None] + offs[None, :]
    phi = modal.shapes_at(X.ravel()).reshape(n, offs.size, modal.n_modes)
    w, z, gain = prewarped_modes(modal.omega_rad_s, modal.damping_ratio, h, prewarp)
    fq = np.einsum("sij,i->sj", phi, f) * gain     # modal forces at each step
    khat = w ** 2 + 2 * z * w * (2 / h) + 4 / h ** 2
    q = np.zeros(modal.n_modes)
    qd = np.zeros_like(q)
    qdd = np.zeros_like(q)
    Q = np.empty((n, q.size))
    Qdd = np.empty((n, q.size))
    for i in range(n):
        qn = (fq[i] + (4 / h ** 2) * q + (4 / h) * qd + qdd + 2 * z * w * ((2 / h) * q + qd)) / khat
        qdd = (4 / h ** 2) * (qn - q) - (4 / h) * qd - qdd
        qd = (2 / h) * (qn - q) - qd
        q = qn
        Q[i] = q
        Qdd[i] = qdd
    S = modal.shapes_at(np.asarray(sensors_x_m, dtype=float))
    return t, Q @ S.T, Qdd @ S.T
