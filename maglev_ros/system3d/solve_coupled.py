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
  max|u^{j+1} - u^j| <= tolerance * max|u^{j+1}| in every column (iterations per step recorded).
  The vehicle step and the forces are linear in the iterate, so each iteration applies them as
  one matrix on the girder coordinates (``_separated``): the same iterates without forming x_j;
* ``monolithic``: the same discrete equations in one linear system per step, the vehicle states
  eliminated: (K_eff + sum_cars R^T (H_x G1 + H_w) E) u_{n+1} = rhs (LU per step);
both converge to the same discrete solution, so they agree to the iteration tolerance.

Columns: every array carries a trailing column axis, so one run integrates many load cases at
once with the matrices of each step built and factorised once: the mean run (1 real column,
static forces on), the PEM (complex columns, one per frequency and process, the irregularity's
harmonic part integrated exactly by ``VehicleStep.harmonic_input``), Monte Carlo (real columns,
sampled irregularity under the first-order hold). The vehicle is stepped in the eigenvector
basis of its balanced A (``ModalVehicle``: diagonal Phi).
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
QUANTITIES = ("acceleration", "displacement", "current")


def _rt(r: np.ndarray, f: np.ndarray) -> np.ndarray:
    """sum over cars of R_c^T F_c."""
    return (r.transpose(0, 2, 1) @ f).sum(axis=0)


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
                "iterations_mean": float(it.mean()) if it.size else 0.0,
                "iterations_per_step": it.tolist()}


@dataclass(frozen=True)
class ModalVehicle:
    """The vehicle step in the eigenvector coordinates of the balanced A: x = T z, T = S V
    (S the balancing scale, V the eigenvectors), so Phi is diagonal (e^{lambda h}) and a step
    costs O(n) per column instead of O(n^2). Falls back to T = I (dense Phi) when V is badly
    conditioned (a near-defective A)."""
    T: np.ndarray
    Ti: np.ndarray
    phi: np.ndarray                  # (n,) diagonal, or (n, n) dense
    input_now: np.ndarray            # Ti G0
    input_next: np.ndarray           # Ti G1
    Hx: np.ndarray                   # H_x T (rail forces from the modal state)
    condition: float

    @classmethod
    def of(cls, step: VehicleStep, Hx: np.ndarray, max_condition: float = 1e8, dense: bool = False) -> "ModalVehicle":
        Ab, (scale, _) = scipy.linalg.matrix_balance(step.A, permute=False, separate=True)
        lam, V = np.linalg.eig(Ab)
        cond = 1.0 if dense else float(np.linalg.cond(V))
        if dense or cond > max_condition:
            eye = np.eye(step.A.shape[0])
            return cls(eye, eye, step.transition, step.input_now, step.input_next, Hx, cond)
        T = scale[:, None] * V
        Ti = np.linalg.inv(V) / scale[None, :]
        return cls(T, Ti, np.exp(lam * step.time_step_s), Ti @ step.input_now, Ti @ step.input_next, Hx @ T, cond)

    def to_modal(self, x: np.ndarray) -> np.ndarray:
        return (self.Ti @ x).astype(complex)

    def transition_apply(self, z: np.ndarray) -> np.ndarray:
        return self.phi[:, None] * z if self.phi.ndim == 1 else self.phi @ z


@dataclass(frozen=True)
class HarmonicInput:
    """Irregularity w_irr(t) = w_hat e^{i omega t} per column (complex; the PEM). ``increment``:
    the exact one-step vehicle increments (``CoupledSolver.harmonic_increments``), computed in the
    run when missing."""
    omega_rad_s: np.ndarray          # (cols,)
    w_hat: np.ndarray                # (n_cars, 4m, cols)
    increment: np.ndarray | None = None   # (n_cars, n_states, cols), vehicle eigen coordinates


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
    vehicle_basis: str = "eigen"                  # eigen: diagonal Phi (fast); dense: Phi as is
    step: VehicleStep = field(init=False)

    def __post_init__(self) -> None:
        if self.coupling not in COUPLINGS:
            raise UserError(f"solver.coupling: expected one of {list(COUPLINGS)}, got {self.coupling!r}")
        if (self.dynamics is None) != (self.rails is None):
            raise UserError("CoupledSolver: give both the girder dynamics and its rail interpolation, or neither")
        with _blas_single_thread():
            self._setup()

    def _setup(self) -> None:
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
        if self.vehicle_basis not in ("eigen", "dense"):
            raise UserError(f"solver.vehicle_basis: expected eigen or dense, got {self.vehicle_basis!r}")
        self.basis = ModalVehicle.of(self.step, self.Hx, dense=self.vehicle_basis == "dense")
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
        rows_c, rows_g, kinds = [], [], []
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
        self._veh_rows_modal = [(c, rc @ self.basis.T, rd) for c, rc, rd in rows_c]
        self._gir_rows = np.array(rows_g).reshape(len(rows_g), self.ng)
        self._kinds = kinds

    def _outputs_now(self, z, wi, u, ud, ua, R, Rs, real: bool) -> np.ndarray:
        """Outputs at one instant: vehicle rows C z + D w with w = [R u; v R' u + R u'] + w_irr."""
        m2 = 2 * self.n_mag
        v = self.train.speed_mps
        y = np.zeros((len(self.outputs), z.shape[-1]), complex)
        iv = ig = 0
        for k, kind in enumerate(self._kinds):
            if kind == "vehicle":
                car, rcz, rd = self._veh_rows_modal[iv]
                val = rcz @ z[car]
                if R is not None and np.any(R[car]):
                    val = val + (rd[:m2] @ R[car] + v * (rd[m2:] @ Rs[car])) @ u + (rd[m2:] @ R[car]) @ ud
                if wi is not None:
                    val = val + rd @ wi[car]
                y[k] = val
                iv += 1
            else:
                y[k] = self._gir_rows[ig] @ (ua if kind == "girder_acceleration" else u)
                ig += 1
        return y.real if real else y

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
        the outputs (n_out, cols) at every step n = 0..n_steps (real unless the input is complex)."""
        if harmonic is not None and sampled is not None:
            raise UserError("CoupledSolver.run: give a harmonic or a sampled irregularity, not both")
        with _blas_single_thread():
            return self._run(n_steps, n_columns, static_load, harmonic, sampled, x0, record, progress)

    def harmonic_increments(self, harmonic: HarmonicInput) -> np.ndarray:
        """Per car, the exact step increment of the harmonic input in the solver's vehicle basis (a
        one-time cost: one balanced solve per frequency)."""
        with _blas_single_thread():
            return self.basis.to_modal(np.stack([self.step.harmonic_input(harmonic.omega_rad_s, harmonic.w_hat[c])
                                                 for c in range(self.train.n_cars)]))

    def _run(self, n_steps, n_columns, static_load, harmonic, sampled, x0, record, progress) -> RunRecord:
        ss, tr, mb = self.state_space, self.train, self.basis
        nc, m2 = tr.n_cars, 2 * self.n_mag
        h, v = self.time_step_s, tr.speed_mps
        real = harmonic is None and not (x0 is not None and np.iscomplexobj(x0))
        cols = n_columns if harmonic is None else harmonic.omega_rad_s.size
        ng = self.ng
        z = np.zeros((nc, ss.n_states, cols), complex) if x0 is None else mb.to_modal(np.asarray(x0))
        u = np.zeros((ng, cols), complex)
        ud = np.zeros_like(u)
        ua = np.zeros_like(u)
        fstat = (self.rail_static_n if static_load else np.zeros(m2))[:, None]
        g0, g1 = mb.input_now, mb.input_next
        if harmonic is not None:
            om = harmonic.omega_rad_s
            g_step = harmonic.increment if harmonic.increment is not None else self.harmonic_increments(harmonic)

        def w_irr(t):
            if harmonic is not None:
                return harmonic.w_hat * np.exp(1j * om * t)[None, None, :]
            if sampled is not None:
                return np.asarray(sampled(t), float)
            return None

        wi = w_irr(0.0)
        R0 = Rs0 = None
        if ng:
            R0, Rs0 = self.rail_rows(0.0)
            F = fstat[None] - mb.Hx @ z
            if wi is not None:
                F = F - self.Hw @ wi
            f = _rt(R0, F)
            if np.any(f):
                ua = np.linalg.solve(self.dynamics.mass, f)
        iters = np.zeros(n_steps + 1, dtype=int)
        if record is not None:
            record(0, 0.0, self._outputs_now(z, wi, u, ud, ua, R0, Rs0, real))
        progress.stage("time steps", n_steps)
        for n in range(n_steps):
            t0, t1 = n * h, (n + 1) * h
            wi1 = w_irr(t1)
            p = mb.transition_apply(z)
            if harmonic is not None:
                p += g_step * np.exp(1j * om * t0)[None, None, :]
            elif wi is not None:
                p += g0 @ wi + g1 @ wi1
            if ng:
                nm = self.newmark
                R1, Rs1 = self.rail_rows(t1)
                on0 = [bool(np.any(R0[c])) for c in range(nc)]
                on1 = [bool(np.any(R1[c])) for c in range(nc)]
                cv = -(nm.a1 * u + ud)
                hist = nm.history_load(u, ud, ua)
                const = hist.astype(complex)
                couple = np.zeros((ng, ng), complex)
                G1E = [None] * nc
                for c in range(nc):
                    if on0[c]:        # girder part of the input at t_n: G0 (W_u u + W_v u')
                        g0wu = g0[:, :m2] @ R0[c] + v * (g0[:, m2:] @ Rs0[c])
                        p[c] += g0wu @ u + (g0[:, m2:] @ R0[c]) @ ud
                    if not on1[c]:
                        continue
                    E = np.concatenate([R1[c], v * Rs1[c] + nm.a1 * R1[c]])     # w_{n+1} = E u_{n+1} + [0; R c] + w_irr
                    G1E[c] = g1 @ E
                    p[c] += (g1[:, m2:] @ R1[c]) @ cv
                    rhx = R1[c].T @ mb.Hx                                        # R^T H_x (girder <- vehicle state)
                    rhw = R1[c].T @ self.Hw                                      # R^T H_w (girder <- rail input)
                    const += R1[c].T @ fstat - rhx @ p[c] - (rhw[:, m2:] @ R1[c]) @ cv
                    if wi1 is not None:
                        const -= rhw @ wi1[c]
                    couple += rhx @ G1E[c] + rhw @ E                             # R^T (H_x G1 + H_w) E
                if not any(on1):
                    u1 = nm.solve(hist)
                    iters[n + 1] = 1
                elif self.coupling == "monolithic":
                    kc = nm.effective_stiffness + couple
                    u1 = scipy.linalg.lu_solve(scipy.linalg.lu_factor(kc), const)
                    iters[n + 1] = 1
                else:
                    u1, iters[n + 1] = self._separated(u, const, couple)
                if real:
                    u1 = u1.real.astype(complex)
                ud1, ua1 = nm.update(u1, u, ud, ua)
                for c in range(nc):
                    if on1[c]:
                        p[c] += G1E[c] @ u1
                z, u, ud, ua, R0, Rs0 = p, u1, ud1, ua1, R1, Rs1
            else:
                z = p
                iters[n + 1] = 1
            wi = wi1
            if record is not None:
                record(n + 1, t1, self._outputs_now(z, wi, u, ud, ua, R0, Rs0, real))
            progress.advance()
        return RunRecord(np.arange(n_steps + 1) * h, iters, self.coupling if ng else "rigid")

    def _separated(self, u, const, couple):
        """Separated iteration from u_{n+1} = u_n. The vehicle step with the rail motion of the
        girder iterate u_j is x_j = p + G1 E u_j and the rail forces it gives load the girder by
        R^T F_j = R^T F_p - R^T (H_x G1 + H_w) E u_j; both are linear in u_j, so an iteration is
        u_{j+1} = K_eff^{-1} (const - couple u_j), the same iterates as stepping the vehicle
        explicitly, without forming x_j. Stops when max|u_{j+1} - u_j| <= tolerance max|u_{j+1}|
        in every column."""
        nm = self.newmark
        u_j = u
        for j in range(1, self.max_iterations + 1):
            u_new = nm.solve(const - couple @ u_j)
            diff = np.max(np.abs(u_new - u_j), axis=0)
            size = np.max(np.abs(u_new), axis=0)
            u_j = u_new
            if np.all(diff <= self.tolerance * size):
                return u_j, j
        raise UserError(f"separated iteration did not converge in {self.max_iterations} iterations "
                        f"(tolerance {self.tolerance}); use coupling: monolithic or a smaller time step")
