"""Updating core: guideway layer vs known truth (several truths/seeds), identifiability ridges,
Elman surrogate accuracy, MOPSO vs analytic Pareto front and pymoo, GRP, durable history."""
from __future__ import annotations

import json
import multiprocessing as mp
import os
import signal
import time
from dataclasses import replace
from typing import Callable

import numpy as np
import pytest

from maglev_ros.twin.design import line_spans, twin_config
from maglev_ros.twin.guideway import Guideway
from maglev_ros.updating.grp import grey_relational_projection
from maglev_ros.updating.guideway_layer import GuidewayLayer, ModalTarget, SpanModel, StaticTarget
from maglev_ros.updating.history import ParameterHistory
from maglev_ros.updating.mopso import MOPSO, ParetoResult
from maglev_ros.updating.sampling import maximin_distance, optimal_lhs

SPAN = {"spans": [{"id": "S1", "start_m": 0.0, "length_m": 12.384}]}
XS = np.linspace(1.5, 10.9, 7)
OFFS = np.array([0.0, -1.548, -6.192, -7.740, -12.384, -13.932, -18.576, -20.124])


def pymoo_nsga2(func: Callable[[np.ndarray], np.ndarray], lower, upper, n_obj: int, pop_size: int = 100,
                n_generations: int = 100, seed: int = 0) -> ParetoResult:
    """The same problem solved with pymoo's NSGA-II (an independent peer of ``MOPSO``)."""
    from pymoo.algorithms.moo.nsga2 import NSGA2
    from pymoo.core.problem import Problem
    from pymoo.optimize import minimize

    lo, hi = np.asarray(lower, dtype=float), np.asarray(upper, dtype=float)
    counter = {"n": 0}

    class _P(Problem):
        def __init__(self):
            super().__init__(n_var=lo.size, n_obj=n_obj, xl=lo, xu=hi)

        def _evaluate(self, X, out, *args, **kwargs):
            counter["n"] += X.shape[0]
            out["F"] = np.asarray(func(X), dtype=float)

    res = minimize(_P(), NSGA2(pop_size=pop_size), ("n_gen", n_generations), seed=seed, verbose=False)
    X, F = np.atleast_2d(res.X), np.atleast_2d(res.F)
    order = np.argsort(F[:, 0])
    return ParetoResult(X[order], F[order], counter["n"], n_generations, "pymoo-nsga2")


def _span(cfg=None):
    return line_spans(SPAN, cfg or twin_config())[0]


def _truth(span, fe, frho, fkb):
    p = span.props
    return replace(span, props=replace(p, youngs_modulus_pa=p.youngs_modulus_pa * fe,
                                       density_kg_m3=p.density_kg_m3 * frho,
                                       bearing_stiffness_n_per_m=p.bearing_stiffness_n_per_m * fkb))


def _measure(truth, seed, f_noise=3e-4, s_noise=0.004):
    """Modes of the TRUE span from the twin's own Guideway class (independent of SpanModel), + noise."""
    g = Guideway([truth])
    modal = g.modes(cutoff_hz=1e4, min_modes_per_span=4, max_modes_per_span=4)
    f = modal.freq_hz
    s = modal.shapes_at(XS).T
    s = s / np.max(np.abs(s), axis=1, keepdims=True)
    rng = np.random.default_rng(seed)
    return f, ModalTarget(f * (1 + f_noise * rng.standard_normal(4)), f_noise * f,
                          s + s_noise * rng.standard_normal(s.shape), XS)


TRUTHS = [(1.12, 0.93, 0.88, 0), (0.87, 1.10, 1.13, 1), (1.06, 1.14, 0.90, 2)]


@pytest.mark.parametrize("fe,frho,fkb,seed", TRUTHS)
def test_guideway_layer_modes_only_ridge(fe, frho, fkb, seed):
    span = _span()
    truth = _truth(span, fe, frho, fkb)
    f_true, tgt = _measure(truth, seed)
    up = GuidewayLayer(n_particles=30, n_iterations=30, seed=seed).fit(span, tgt)
    # updated frequencies vs the true structure's frequencies
    assert np.max(np.abs(np.array(up.frequencies_updated_hz) / f_true - 1)) < 0.005
    # the common scale of E, rho, kb is a ridge: E and rho are not identifiable alone
    assert len(up.identifiability.ridge_directions) == 1
    ridge = np.abs(up.identifiability.ridge_directions[0])
    assert np.allclose(ridge, 1 / np.sqrt(3), atol=1e-2)
    assert not any(up.identifiable)
    combos = {c.expression: c for c in up.identifiability.combinations}
    p = truth.props
    e_rho = p.youngs_modulus_pa / p.density_kg_m3
    assert combos["E/rho"].identifiable
    assert abs(combos["E/rho"].value / e_rho - 1) < 0.02
    assert abs(combos["E/rho"].value / e_rho - 1) < 4 * combos["E/rho"].std / e_rho + 1e-4
    assert up.mac_updated[0] > 0.999


@pytest.mark.parametrize("fe,frho,fkb,seed", TRUTHS[:2])
def test_guideway_layer_static_deflection_pins_scale(fe, frho, fkb, seed):
    span = _span()
    truth = _truth(span, fe, frho, fkb)
    f_true, tgt = _measure(truth, seed)
    pos = np.linspace(-2, 34, 300)
    X = pos[:, None] + OFFS[None, :]
    F = np.full(8, 68000.0)
    # independent reference: static displacement from the twin's Guideway (load superposition)
    g = Guideway([truth])
    d = np.array([g.static_displacement(x, -F, [6.192])[0] for x in X])
    d += 2e-6 * np.random.default_rng(seed).standard_normal(d.size)
    up = GuidewayLayer(n_particles=30, n_iterations=30, seed=seed).fit(span, tgt, StaticTarget(6.192, X, F, d))
    assert all(up.identifiable[:2])
    tv = np.array([truth.props.youngs_modulus_pa, truth.props.density_kg_m3])
    assert np.all(np.abs(np.array(up.values[:2]) / tv - 1) < 0.02)
    assert np.all(np.abs(np.array(up.values[:2]) - tv) < 4 * np.array(up.std[:2], dtype=float) + 1e-3 * tv)


def test_span_model_matches_twin_guideway():
    span = _truth(_span(), 1.1, 0.9, 1.2)
    p = span.props
    f, _ = SpanModel(_span()).modes([p.youngs_modulus_pa, p.density_kg_m3, p.bearing_stiffness_n_per_m])
    assert np.allclose(f, Guideway([span]).frequencies_hz(0, 4), rtol=1e-9)


def test_elman_surrogate_frequencies_heldout():
    from maglev_ros.updating.parameters import guideway_space
    from maglev_ros.updating.surrogate import ElmanSurrogate, score
    cfg = twin_config()
    space = guideway_space(cfg)
    model = SpanModel(_span(cfg))
    U = optimal_lhs(160, 3, seed=1, n_candidates=1)   # LHS quality is tested below; 1 candidate saves ~10 s
    X = np.array([space.from_unit(u) for u in U])
    Y = np.array([model.modes(x)[0] for x in X])
    # independent held-out set: plain random points (not LHS) in the same box
    Xt = np.array([space.from_unit(u) for u in np.random.default_rng(7).random((80, 3))])
    Yt = np.array([model.modes(x)[0] for x in Xt])
    sc = score(Yt, ElmanSurrogate(hidden=12, adam_epochs=300, lbfgs_iter=200).fit(X, Y).predict(Xt))
    assert min(sc.r2) >= 0.99
    assert max(sc.mape_percent) <= 0.5


def test_optimal_lhs_strata_and_maximin():
    u = optimal_lhs(40, 3, seed=3, n_candidates=3)
    for j in range(3):
        assert sorted(np.floor(u[:, j] * 40).astype(int)) == list(range(40))
    rnd = np.random.default_rng(3).random((40, 3))
    assert maximin_distance(u) > maximin_distance(rnd)


def _zdt1(X):
    f1 = X[:, 0]
    g = 1 + 9 * X[:, 1:].mean(axis=1)
    return np.stack([f1, g * (1 - np.sqrt(f1 / g))], axis=1)


def test_mopso_finds_analytic_pareto_front_and_agrees_with_pymoo():
    lo, hi = np.zeros(3), np.ones(3)
    res = MOPSO(n_particles=60, archive_size=40, n_iterations=120, seed=0).minimize(_zdt1, lo, hi)
    # analytic front of ZDT1: f2 = 1 - sqrt(f1) at x2 = x3 = 0
    err = res.f[:, 1] - (1 - np.sqrt(res.f[:, 0]))
    assert np.median(err) < 0.02
    assert np.ptp(res.f[:, 0]) > 0.8      # spread along the front
    nsga = pymoo_nsga2(_zdt1, lo, hi, 2, pop_size=40, n_generations=80)
    err2 = nsga.f[:, 1] - (1 - np.sqrt(nsga.f[:, 0]))
    assert np.median(err2) < 0.05
    assert nsga.n_evaluations > 0 and res.n_evaluations == 60 * 121


def test_grp_picks_knee_and_extremes():
    f1 = np.linspace(0, 1, 21)
    front = np.stack([f1, 1 - np.sqrt(1 - (1 - f1) ** 2)], axis=1)   # convex quarter circle
    i = grey_relational_projection(front).index
    assert 5 <= i <= 15                                             # a balanced (knee) solution
    assert grey_relational_projection(front, weights=[0.95, 0.05]).index < i
    # a solution best in both objectives is always chosen
    f = np.array([[0.5, 0.5], [0.1, 0.1], [0.2, 0.9]])
    assert grey_relational_projection(f).index == 1


def _append_slowly(path, ready):
    h = ParameterHistory(path)

    def hang():
        ready.set()
        time.sleep(60)
    h.append({"kp_a_per_m": {"value": 2.0}}, {"pass": "b"}, {}, _before_write=hang)


def test_history_survives_kill_mid_write_and_reloads(tmp_path):
    path = tmp_path / "hist.jsonl"
    h = ParameterHistory(path)
    r1 = h.append({"kp_a_per_m": {"value": 1.0}}, {"pass": "a"}, {"nrmse": 0.1})
    h.close()                                        # one writer per file: the child writes next
    ctx = mp.get_context("fork")
    ready = ctx.Event()
    p = ctx.Process(target=_append_slowly, args=(str(path), ready))
    p.start()
    assert ready.wait(20)
    os.kill(p.pid, signal.SIGKILL)
    p.join()
    h2 = ParameterHistory(path)                      # "restart"
    recs = h2.records()
    assert len(recs) == 1 and recs[0]["parameters"] == r1["parameters"]
    r2 = h2.append({"kp_a_per_m": {"value": 3.0}})
    assert ParameterHistory(path).last()["revision"] == 2 == r2["revision"]
    with open(path, "a") as f:                      # a torn line written by something else
        f.write('{"schema": "maglev-param')
    h3 = ParameterHistory(path)
    assert h3.last()["parameters"]["kp_a_per_m"]["value"] == 3.0 and h3.skipped
