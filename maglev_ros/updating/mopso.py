"""Multi-objective particle swarm optimisation with a grid archive (000 Sec. 4.2.3; Coello et al. 2004).

- External archive of non-dominated solutions with a fixed capacity; the objective space spanned by
  the archive is divided into ``n_grid`` cells per objective (000 Eq. 29: cell side = (max - min) / M,
  the paper uses M = 7). The number of archive members in a cell is its density.
- Leader (group best) per particle: an archive member chosen by roulette with probability
  proportional to 1 / density of its cell (sparse regions preferred, as in 000).
- Archive overflow: members are removed at random from the most crowded cell.
- Velocity/position update v = w v + c1 r1 (pbest - x) + c2 r2 (gbest - x) (000 Eqs. 30-31), positions
  clipped into the box (velocity reflected); personal best replaced when the new position dominates
  it (random choice when neither dominates); uniform mutation with a probability that decays over
  the iterations (Coello's mutation operator, 000's "mutation probability 0.1").
Objective functions are vectorised: ``f(X (n, d)) -> (n, m)``.

Hand-written because pymoo has no MOPSO with the paper's grid archive; pymoo's NSGA-II solves the
same problem as a cross-check in the tests (tests/test_updating_core.py).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from maglev_ros.errors import UserError


def dominates(a: np.ndarray, b: np.ndarray) -> bool:
    return bool(np.all(a <= b) and np.any(a < b))


def nondominated_mask(f: np.ndarray) -> np.ndarray:
    n = f.shape[0]
    le = np.all(f[:, None, :] <= f[None, :, :], axis=2)
    lt = np.any(f[:, None, :] < f[None, :, :], axis=2)
    dom = le & lt                                  # dom[i, j]: i dominates j
    return ~np.any(dom, axis=0)


@dataclass(frozen=True)
class ParetoResult:
    x: np.ndarray            # (k, d) archive positions (in the optimiser's variables)
    f: np.ndarray            # (k, m) objectives
    n_evaluations: int
    n_iterations: int
    method: str = "mopso"

    def to_dict(self) -> dict:
        return {"method": self.method, "x": self.x.tolist(), "f": self.f.tolist(),
                "n_evaluations": int(self.n_evaluations), "n_iterations": int(self.n_iterations)}


class MOPSO:
    def __init__(self, n_particles: int = 100, archive_size: int = 80, n_iterations: int = 200,
                 n_grid: int = 7, inertia: float = 0.5, c1: float = 1.0, c2: float = 2.0,
                 mutation_rate: float = 0.1, seed: int | None = 0):
        if n_particles < 2 or archive_size < 1 or n_iterations < 1 or n_grid < 1:
            raise UserError("MOPSO: expected n_particles >= 2, archive_size >= 1, n_iterations >= 1, n_grid >= 1")
        self.n_particles, self.archive_size, self.n_iterations = int(n_particles), int(archive_size), int(n_iterations)
        self.n_grid, self.inertia, self.c1, self.c2 = int(n_grid), float(inertia), float(c1), float(c2)
        self.mutation_rate = float(mutation_rate)
        self.seed = seed

    # grid ----------------------------------------------------------------------------------
    def _cells(self, f: np.ndarray) -> np.ndarray:
        lo, hi = f.min(axis=0), f.max(axis=0)
        side = np.where(hi > lo, (hi - lo) / self.n_grid, 1.0)
        idx = np.clip(np.floor((f - lo) / side).astype(int), 0, self.n_grid - 1)
        return np.ravel_multi_index(idx.T, (self.n_grid,) * f.shape[1])

    def _update_archive(self, ax, af, x, f, rng):
        X = np.vstack([ax, x]) if ax.size else x
        F = np.vstack([af, f]) if af.size else f
        _, uniq = np.unique(np.round(X, 12), axis=0, return_index=True)
        X, F = X[np.sort(uniq)], F[np.sort(uniq)]
        keep = nondominated_mask(F)
        X, F = X[keep], F[keep]
        while X.shape[0] > self.archive_size:
            cells = self._cells(F)
            c, counts = np.unique(cells, return_counts=True)
            crowded = c[np.argmax(counts)]
            members = np.flatnonzero(cells == crowded)
            drop = rng.choice(members)
            X, F = np.delete(X, drop, axis=0), np.delete(F, drop, axis=0)
        return X, F

    def _leaders(self, af, n, rng):
        cells = self._cells(af)
        c, inv, counts = np.unique(cells, return_inverse=True, return_counts=True)
        p = 1.0 / counts[inv]
        p /= p.sum()
        return rng.choice(af.shape[0], size=n, p=p)

    # run -----------------------------------------------------------------------------------
    def minimize(self, func: Callable[[np.ndarray], np.ndarray], lower, upper, x0=None) -> ParetoResult:
        lo, hi = np.asarray(lower, dtype=float), np.asarray(upper, dtype=float)
        if lo.shape != hi.shape or np.any(hi <= lo):
            raise UserError("MOPSO: expected lower < upper bounds of equal length")
        rng = np.random.default_rng(self.seed)
        d, n = lo.size, self.n_particles
        x = lo + rng.random((n, d)) * (hi - lo)
        if x0 is not None:
            x0 = np.atleast_2d(np.asarray(x0, dtype=float))[: n]
            x[: x0.shape[0]] = np.clip(x0, lo, hi)
        v = np.zeros((n, d))
        f = np.asarray(func(x), dtype=float)
        n_eval = n
        pbx, pbf = x.copy(), f.copy()
        ax, af = self._update_archive(np.empty((0, d)), np.empty((0, f.shape[1])), x, f, rng)
        vmax = 0.5 * (hi - lo)
        for it in range(self.n_iterations):
            g = ax[self._leaders(af, n, rng)]
            r1, r2 = rng.random((n, d)), rng.random((n, d))
            v = self.inertia * v + self.c1 * r1 * (pbx - x) + self.c2 * r2 * (g - x)
            v = np.clip(v, -vmax, vmax)
            x = x + v
            out = (x < lo) | (x > hi)
            v[out] *= -1.0
            x = np.clip(x, lo, hi)
            # mutation (Coello 2004): range shrinks as iterations advance
            pm = (1.0 - it / self.n_iterations) ** (1.0 / max(self.mutation_rate, 1e-9))
            if pm > 0:
                mut = rng.random(n) < pm
                if mut.any():
                    dim = rng.integers(0, d, size=mut.sum())
                    rows = np.flatnonzero(mut)
                    width = pm * (hi[dim] - lo[dim])
                    x[rows, dim] = np.clip(x[rows, dim] + (rng.random(rows.size) - 0.5) * width, lo[dim], hi[dim])
            f = np.asarray(func(x), dtype=float)
            n_eval += n
            better = np.all(f <= pbf, axis=1) & np.any(f < pbf, axis=1)
            worse = np.all(pbf <= f, axis=1) & np.any(pbf < f, axis=1)
            tie = ~better & ~worse & (rng.random(n) < 0.5)
            upd = better | tie
            pbx[upd], pbf[upd] = x[upd], f[upd]
            ax, af = self._update_archive(ax, af, x, f, rng)
        order = np.argsort(af[:, 0])
        return ParetoResult(ax[order], af[order], n_eval, self.n_iterations, "mopso")

