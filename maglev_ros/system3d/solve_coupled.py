"""A train of 3D vehicles crossing the girder: precise integration (vehicle) + Newmark (girder),
coupled by separated iteration or solved monolithically (001 Sec. 5).

Coupling, per car and step (m magnets; R (2m x n_g) the rail rows of the girder coordinates
under the magnets at t_{n+1}, first the vertical rows, then the lateral; R' their x-slopes; rails
read zero off the girder: the approach is rigid ground):
* vehicle input w = [z; y; z'; y'] = [R u; v R' u + R u'] + w_irr (the girder's rail motion
  under each magnet, moving at speed v, plus the irregularity);
* rail loads F = -(n F0 + n dF) - [0; F_lat]: the magnets' static force F0 (the "mean" input,
  the train's weight moving over the girder), the force deviation dF = C_f x + D_f w along each
  magnet's direction n (the rail gets the opposite) and the passive lateral force
  F_lat = C_l x + D_l w; girder load R^T F.
With u'_{n+1} = a1 u_{n+1} + c (Newmark) the input at t_{n+1} is w = E u_{n+1} + e,
E = [R; v R' + a1 R], and the vehicle step x_{n+1} = Phi x_n + G0 w_n + G1 w_{n+1} is linear in
u_{n+1}: x_{n+1} = p + G1 E u_{n+1}. Then
* ``separated`` (001's scheme): start from u_{n+1} = u_n; vehicle step with the rail motion of
  the current girder iterate, rail forces, girder step with them; repeat until
  max|u^{j+1} - u^j| <= tolerance * max|u^{j+1}| in every column (iterations per step recorded);
* ``monolithic``: the same discrete equations in one linear system per step, the vehicle states
  eliminated: (K_eff + sum_cars R^T (H_x G1 + H_w) E) u_{n+1} = rhs (LU per step);
both converge to the same discrete solution, so they agree to the iteration tolerance.

Columns: every array carries a trailing column axis, so one run integrates many load cases at
once with the matrices of each step built and factorised once: the mean run (1 real column,
static forces on), the PEM (complex columns, one per frequency and process, the irregularity's
harmonic part integrated exactly by ``VehicleStep.harmonic_input``), Monte Carlo (real columns,
sampled irregularity under the first-order hold).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np
import scipy.linalg

from maglev_ros.errors import UserError
from maglev_ros.progress import NULL, Progress
from maglev_ros.system3d.girder_rails import RailInterpolation
from maglev_ros.system3d.solve_girder import GirderDynamics, Newmark
from maglev_ros.system3d.solve_vehicle import VehicleStep, discretise
from maglev_ros.system3d.train import Train
from maglev_ros.system3d.vehicle_state_space import VehicleStateSpace3D
from maglev_ros.twin.pem import _blas_single_thread

COUPLINGS = ("separated", "monolithic")


def _mm(a: np.ndarray, x: np.ndarray) -> np.ndarray:
    """a @ x[c] for every car c (BLAS through matmul broadcasting)."""
    return a @ x


def _rt(r: np.ndarray, f: np.ndarray) -> np.ndarray:
    """sum over cars of R_c^T F_c."""
    return (r.transpose(0, 2, 1) @ f).sum(axis=0)
QUANTITIES = ("acceleration", "displacement", "current")


@dataclass(frozen=True)
class ResponsePoint:
    """One output: a vehicle body point (``car``, ``body``, ``point_m``, ``direction``), a loop
    current (``car``, ``loop``) or a girder point (``girder_x_m`` on the section's shear centre, or
    a rail with ``rail`` left/right, ``direction``)."""
    name: str
    quantity: str = "acceleration"
    direction: str = "z"
    car: int | None = None
    body: str | None = None
    point_m: tuple[float, float, float] | None = None
    loop: str | None = None
    girder_x_m: float | None = None
    rail: str | None = None

    @property
    def on_girder(self) -> bool:
        return self.girder_x_m is not None

    @property
    def unit(self) -> str:
        return {"acceleration": "m/s^2", "displacement": "m", "current": "A"}[self.quantity]

    def to_dict(self) -> dict:
        return {k: v for k, v in self.__dict__.items() if v is not None}


@dataclass
class RunRecord:
    """What a run reports besides the outputs: time axis and separated-iteration counts."""
    time_s: np.ndarray
    iterations: np.ndarray           # per step (0 before the first step; 1 = no girder coupling)
    coupling: str

    def to_dict(self) -> dict:
        it = self.iterations[1:]
        return {"coupling": self.coupling, "steps": int(it.size),
                "iterations_max": int(it.max()) if it.size else 0,
                "iterations_mean": float(it.mean()) if it.size else 0.0}


@dataclass(frozen=True)
class HarmonicInput:
    """Irregularity w_irr(t) = w_hat e^{i omega t} per column (complex; the PEM)."""
    omega_rad_s: np.ndarray          # (cols,)
    w_hat: np.ndarray                # (n_cars, 4m, cols)


@dataclass
class CoupledSolver:
    """Config in the constructor (one-time costs: Phi, G0, G1, K_eff factor, output rows);
    ``run`` integrates a set of columns."""
    state_space: VehicleStateSpace3D
    train: Train
    time_step_s: float
    dynamics: GirderDynamics | None = None       # None: rigid track everywhere
    rails: RailInterpolation | None = None
    coupling: str = "separated"
    tolerance: float = 1e-10
    max_iterations: int = 200
    hold: str = "linear"
    outputs: tuple[ResponsePoint, ...] = ()
    step: VehicleStep = field(init=False)

    def __post_init__(self) -> None:
        if self.coupling not in COUPLINGS:
            raise UserError(f"solver.coupling: expected one of {list(COUPLINGS)}, got {self.coupling!r}")
        if (self.dynamics is None) != (self.rails is None):
            raise UserError("CoupledSolver: give both the girder dynamics and its rail interpolation, or neither")
        ss = self.state_space
        self.step = discretise(ss.A, ss.B, self.time_step_s, self.hold)
        data = ss.vehicle.data
        m = len(data.magnets)
        self.n_mag = m
        dirs = np.array([mg.direction for mg in data.magnets])
        pf = np.vstack([np.diag(dirs[:, 2]), np.diag(dirs[:, 1])])      # (2m, m): force along n -> (z, y)
        q = np.vstack([np.zeros((m, m)), np.eye(m)])
        fo, lo = ss.outputs("force:"), ss.outputs("lateral_force:")
        self.Hx = pf @ ss.C[fo] + q @ ss.C[lo]
        self.Hw = pf @ ss.D[fo] + q @ ss.D[lo]
        self.J = self.Hx @ self.step.input_next + self.Hw
        self.rail_static_n = -pf @ ss.static.magnet_force_n               # (2m,) static loads on the rails
        self.sides = [mg.side for mg in data.magnets]
        self.ng = 0 if self.dynamics is None else self.dynamics.n
        if self.dynamics is not None:
            self.newmark = Newmark(self.dynamics, self.time_step_s)
            yr = np.array([self.rails.rails.offset(s)[0] for s in self.sides])
            self._yr = np.tile(yr, self.train.n_cars)
            self._zr = self.rails.rails.rail_height_m
        self._output_rows()

    # ------------------------------------------------------------------ outputs
    def _output_rows(self) -> None:
        ss = self.state_space
        veh = ss.vehicle
        acc = ss.outputs("acc:")
        nc = self.train.n_cars
        rows_c, rows_d, rows_g, kinds = [], [], [], []
        for o in self.outputs:
            if o.quantity not in QUANTITIES:
                raise UserError(f"outputs.{o.name}.quantity: expected one of {list(QUANTITIES)}, got {o.quantity!r}")
            if o.on_girder:
                if self.dynamics is None:
                    raise UserError(f"outputs.{o.name}: a girder point needs a girder")
                if o.quantity == "current":
                    raise UserError(f"outputs.{o.name}: a girder point has no current")
                sec = self.rails.section_rows([o.girder_x_m])
                if o.rail is None:
                    row = sec["w"] if o.direction == "z" else sec["v"]
                else:
                    row = self.rails.matrix([o.girder_x_m], o.rail, o.direction)
                if o.direction not in ("z", "y"):
                    raise UserError(f"outputs.{o.name}.direction: expected z or y, got {o.direction!r}")
                rows_g.append((row @ self.dynamics.basis)[0])
                kinds.append("girder_" + o.quantity)
                continue
            if o.car is None or not 1 <= o.car <= nc:
                raise UserError(f"outputs.{o.name}.car: expected 1..{nc}, got {o.car!r}")
            if o.quantity == "current":
                name = f"current:{o.loop}"
                if name not in ss.output_names:
                    raise UserError(f"outputs.{o.name}.loop: unknown loop {o.loop!r}")
                i = ss.output_names.index(name)
                rc, rd = ss.C[i], ss.D[i]
            else:
                names = [b.name for b in veh.data.bodies]
                if o.body not in names:
                    raise UserError(f"outputs.{o.name}.body: unknown body {o.body!r} (bodies: {names})")
                if o.direction not in ("x", "y", "z"):
                    raise UserError(f"outputs.{o.name}.direction: expected x, y or z, got {o.direction!r}")
                point = o.point_m if o.point_m is not None else veh.data.body(o.body).centre_m
                prow = veh.point_rows(o.body, point)["xyz".index(o.direction)]
                if o.quantity == "acceleration":
                    rc, rd = prow @ ss.C[acc], prow @ ss.D[acc]
                else:
                    n = veh.n_dof
                    rc, rd = np.concatenate([prow, np.zeros(ss.n_states - n)]), np.zeros(ss.B.shape[1])
            rows_c.append((o.car - 1, rc, rd))
            kinds.append("vehicle")
        self._veh_rows = rows_c
        self._gir_rows = np.array(rows_g).reshape(len(rows_g), self.ng)
        self._kinds = kinds

    def _outputs_now(self, x, w, u, a) -> np.ndarray:
        cols = x.shape[-1]
        y = np.zeros((len(self.outputs), cols), dtype=np.result_type(x, w, u))
        iv = ig = 0
        for k, kind in enumerate(self._kinds):
            if kind == "vehicle":
                car, rc, rd = self._veh_rows[iv]
                y[k] = rc @ x[car] + rd @ w[car]
                iv += 1
            else:
                y[k] = self._gir_rows[ig] @ (a if kind == "girder_acceleration" else u)
                ig += 1
        return y

    # ------------------------------------------------------------------ rails
    def rail_rows(self, t_s: float) -> tuple[np.ndarray, np.ndarray]:
        """(R, R') each (n_cars, 2m, n_g): the girder coordinates' rail motion and slope under
        every magnet at time t (zero off the girder)."""
        nc, m = self.train.n_cars, self.n_mag
        xs = self.train.magnet_positions_m(t_s).ravel()
        out = []
        g = self.rails.girder
        on = (xs >= g.node_x_m[0]) & (xs <= g.node_x_m[-1])
        for der in (0, 1):
            R = np.zeros((nc * m * 2, self.ng))
            if on.any():
                sec = self.rails.section_rows(xs[on], der)
                z = sec["w"] + self._yr[on, None] * sec["rx"]
                y = sec["v"] - self._zr * sec["rx"]
                zy = np.vstack([z, y]) @ self.dynamics.basis
                idx = np.flatnonzero(on)
                car, mag = np.divmod(idx, m)
                R[car * 2 * m + mag] = zy[:idx.size]
                R[car * 2 * m + m + mag] = zy[idx.size:]
            out.append(R.reshape(nc, 2 * m, self.ng))
        return out[0], out[1]

    # ------------------------------------------------------------------ run
    def run(self, n_steps: int, n_columns: int = 1, *, static_load: bool = True,
            harmonic: HarmonicInput | None = None,
            sampled: Callable[[float], np.ndarray] | None = None,
            x0: np.ndarray | None = None,
            record: Callable[[int, float, np.ndarray], None] | None = None,
            progress: Progress = NULL) -> RunRecord:
        """Integrate ``n_steps`` steps from t = 0. ``static_load``: the magnets' static forces load
        the girder (the mean run). ``harmonic``: complex PEM input; ``sampled(t)`` -> (n_cars, 4m,
        cols) real irregularity input (first-order hold). ``x0`` (n_cars, n_states, cols) initial
        vehicle state (default 0: static equilibrium on a perfect rail). ``record(n, t, y)`` gets
        the outputs (n_out, cols) at every step n = 0..n_steps."""
        if harmonic is not None and sampled is not None:
            raise UserError("CoupledSolver.run: give a harmonic or a sampled irregularity, not both")
        with _blas_single_thread():
            return self._run(n_steps, n_columns, static_load, harmonic, sampled, x0, record, progress)

    def _run(self, n_steps, n_columns, static_load, harmonic, sampled, x0, record, progress) -> RunRecord:
        ss, st, tr = self.state_space, self.step, self.train
        nc, ns, m4 = tr.n_cars, ss.n_states, 4 * self.n_mag
        h, v = self.time_step_s, tr.speed_mps
        cplx = harmonic is not None or (x0 is not None and np.iscomplexobj(x0))
        dt = complex if cplx else float
        cols = n_columns if harmonic is None else harmonic.omega_rad_s.size
        x = np.zeros((nc, ns, cols), dt) if x0 is None else np.array(x0, dt)
        ng = self.ng
        u = np.zeros((ng, cols), dt)
        ud = np.zeros((ng, cols), dt)
        ua = np.zeros((ng, cols), dt)
        fstat = (self.rail_static_n if static_load else np.zeros(2 * self.n_mag))[:, None]
        if harmonic is not None:
            g_step = np.stack([st.harmonic_input(harmonic.omega_rad_s, harmonic.w_hat[c]) for c in range(nc)])
            om = harmonic.omega_rad_s

        def w_irr(t):
            if harmonic is not None:
                return harmonic.w_hat * np.exp(1j * om * t)[None, None, :]
            if sampled is not None:
                return np.asarray(sampled(t), float)
            return np.zeros((nc, m4, cols))

        wi = w_irr(0.0)
        wg = np.zeros((nc, m4, cols), dt)            # girder part of the input at t_n
        if ng:
            R, _ = self.rail_rows(0.0)
            F = fstat[None] - _mm(self.Hx, x) - _mm(self.Hw, wi)
            f = _rt(R, F)
            if np.any(f):
                ua = np.linalg.solve(self.dynamics.mass, f)
        iters = np.zeros(n_steps + 1, dtype=int)
        if record is not None:
            record(0, 0.0, self._outputs_now(x, wg + wi, u, ua))
        w_hold = wg if harmonic is not None else wg + wi     # input the hold interpolates from
        progress.stage("time steps", n_steps)
        for n in range(n_steps):
            t0, t1 = n * h, (n + 1) * h
            wi1 = w_irr(t1)
            p = _mm(st.transition, x) + _mm(st.input_now, w_hold)
            if harmonic is not None:
                p += g_step * np.exp(1j * om * t0)[None, None, :]
            else:
                p += _mm(st.input_next, wi1)
            if ng:
                R, Rs = self.rail_rows(t1)
                E = np.concatenate([R, v * Rs + self.newmark.a1 * R], axis=1)      # (nc, 4m, ng)
                cv = -(self.newmark.a1 * u + ud)
                wfix = np.concatenate([np.zeros((nc, 2 * self.n_mag, cols), dt), (R @ cv)],
                                      axis=1)
                p += _mm(st.input_next, wfix)
                e0 = wfix + wi1
                hist = self.newmark.history_load(u, ud, ua)
                rhs = (hist + _rt(R, fstat[None] - _mm(self.Hx, p)
                                   - _mm(self.Hw, e0)))
                if self.coupling == "monolithic" or not np.any(R):
                    if np.any(R):
                        kc = self.newmark.effective_stiffness + _rt(R, self.J @ E)
                        u1 = scipy.linalg.lu_solve(scipy.linalg.lu_factor(kc), rhs)
                    else:
                        u1 = self.newmark.solve(rhs)
                    iters[n + 1] = 1
                else:
                    u1, iters[n + 1] = self._separated(u, hist, R, E, p, e0, fstat)
                ud1, ua1 = self.newmark.update(u1, u, ud, ua)
                wg = (E @ u1) + wfix
                x = p + _mm(st.input_next, (E @ u1))
                u, ud, ua = u1, ud1, ua1
            else:
                x = p
                iters[n + 1] = 1
            w_hold = wg if harmonic is not None else wg + wi1
            if record is not None:
                record(n + 1, t1, self._outputs_now(x, wg + wi1, u, ua))
            progress.advance()
        return RunRecord(np.arange(n_steps + 1) * h, iters, self.coupling if ng else "rigid")

    def _separated(self, u, hist, R, E, p, e0, fstat):
        """Separated iteration: vehicle step with the girder iterate's rail motion, rail forces,
        girder step with them, until the girder displacement stops changing."""
        st = self.step
        u_j = u
        for j in range(1, self.max_iterations + 1):
            du_rail = (E @ u_j)              # E u_j: input from the iterate
            x_j = p + _mm(st.input_next, du_rail)
            F = (fstat[None] - _mm(self.Hx, x_j)
                 - _mm(self.Hw, du_rail + e0))
            rhs = hist + _rt(R, F)
            u_new = self.newmark.solve(rhs)
            diff = np.max(np.abs(u_new - u_j), axis=0)
            size = np.max(np.abs(u_new), axis=0)
            u_j = u_new
            if np.all(diff <= self.tolerance * size):
                return u_j, j
        raise UserError(f"separated iteration did not converge in {self.max_iterations} iterations "
                        f"(tolerance {self.tolerance}); use coupling: monolithic or a smaller time step")
