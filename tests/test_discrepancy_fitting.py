"""Fitting levitation physics where it acts: residual rows of the vehicle channels and the
projection of the calibrated parameters onto them.

References: the residual vector restricted through ``channels`` (an independent path through the
fit items) for the rows, and a direct least-squares solve of the gains-only problem for the
projection.
"""
import numpy as np
import pytest

from maglev_ros.discrepancy.evaluate import (Selection, _fit_items, levitation_items, prepare, residual_rows,
                                             residual_vector)
from maglev_ros.discrepancy.fitting import _GAINS, PRIOR_SIGMA, BaseFit, _project
from maglev_ros.discrepancy.model import base_spec

VEHICLE = ["M1A", "M8A", "M1G", "M8G"]


@pytest.fixture(scope="module")
def pass_rd():
    from test_discrepancy_discovery import _truth_pass
    rec = _truth_pass(26.0, None, 11)
    spec = base_spec(rec.metadata)
    return spec, [prepare(rec, spec)]


def test_residual_rows_are_the_items_of_those_channels(pass_rd):
    spec, rds = pass_rd
    full = residual_vector(spec, rds)
    rows = residual_rows(spec, rds, VEHICLE)
    sub = residual_vector(spec, rds, VEHICLE)
    assert rows.shape == full.shape
    assert 0 < rows.sum() < rows.size
    assert rows.sum() == sub.size
    # the same residuals, scaled by the item count: each item of a recording is weighted
    # 1 / sqrt(n_items), so the restricted vector is sqrt(n_all / n_sub) times the rows
    nz = np.abs(full[rows]) > 1e-12 * np.abs(full).max()
    ratio = sub[nz] / full[rows][nz]
    assert np.allclose(ratio, ratio[0], rtol=1e-9)
    # guideway channels are not among the rows
    rows_g = residual_rows(spec, rds, ["G1A"])
    assert not np.any(rows & rows_g)


def test_levitation_items_are_the_magnets_own_bands_and_transmissibilities(pass_rd):
    spec, rds = pass_rd
    kinds: list = []
    items = _fit_items(spec, rds[0], names_out=kinds)
    # reference: the items listed one by one, kept by kind and by channel names
    want = [am.size for (am, _, _), (kind, nm, _) in zip(items, kinds)
            if kind in ("bands", "transmissibility") and set(nm) <= set(VEHICLE)]
    assert {k for k, _, _ in kinds} >= {"bands", "transmissibility", "level", "body"}
    rows = residual_rows(spec, rds, levitation_items(VEHICLE))
    assert rows.sum() == sum(want)
    assert residual_vector(spec, rds, levitation_items(VEHICLE)).size == sum(want)
    # the car-body ratios and the gaps' frame means are among the plain channel selection's rows
    wide = residual_rows(spec, rds, VEHICLE)
    assert np.all(wide[rows]) and wide.sum() > rows.sum()
    assert np.array_equal(wide, residual_rows(spec, rds, Selection(frozenset(VEHICLE))))


def test_a_frame_selection_splits_the_rows_by_frame(pass_rd):
    spec, rds = pass_rd
    rd = rds[0]
    lev = levitation_items(VEHICLE)
    n = rd.grid.n_frames
    first = np.arange(n) < n // 2
    a = residual_rows(spec, rds, lev.on_frames(rd, first))
    b = residual_rows(spec, rds, lev.on_frames(rd, ~first))
    full = residual_rows(spec, rds, lev)
    assert a.any() and b.any()
    assert not np.any(a & b) and np.array_equal(a | b, full)
    # the restricted vector holds exactly those rows; every frame selected is the plain selection
    assert residual_vector(spec, rds, lev.on_frames(rd, first)).size == a.sum()
    assert np.array_equal(residual_rows(spec, rds, lev.on_frames(rd, np.ones(n, bool))), full)
    # reference for the rows of one item: the magnet accelerometer's bands, counted frame by frame from
    # its measured band powers and fit mask (every band of a usable frame is finite there)
    from maglev_ros.discrepancy.evaluate import fit_mask
    pm = rd.pm["M1A"][:, fit_mask(rd, "M1A")]
    n_first = int(np.sum(np.isfinite(pm[first])))
    kinds: list = []
    _fit_items(spec, rd, lev.on_frames(rd, first), names_out=kinds)
    m1a = [fr for kind, nm, fr in kinds if kind == "bands" and nm == ("M1A",)]
    assert len(m1a) == 1 and m1a[0].size == n_first and np.all(first[m1a[0]])


def test_projection_on_vehicle_rows_refits_the_gains_only():
    rng = np.random.default_rng(3)
    n = 300
    J = rng.normal(size=(n, 5))                      # E, kb, kp, kv, rho
    theta = np.array([0.05, -0.1, 0.02, -0.3, 0.04])
    d_true = np.array([0.1, 0.2, -0.05, 0.15, -0.08])
    r = -J @ d_true                                  # the residual that d_true removes
    base = BaseFit(spec=None, theta=theta, jac=J, r0=np.zeros(n), n_sims=0)
    rows = np.zeros(n, bool)
    rows[::3] = True
    r_rows, d = _project(base, r[rows], rows)
    assert d[0] == 0.0 and d[1] == 0.0 and d[4] == 0.0   # E, kb and rho held
    # reference: min ||r + J_g d_g||^2 + lam ||theta_g + d_g||^2 over the gains, solved directly
    lam = (0.02 / PRIOR_SIGMA) ** 2
    Jg = J[rows][:, _GAINS]
    A = np.vstack([Jg, np.sqrt(lam) * np.eye(2)])
    b = -np.concatenate([r[rows], np.sqrt(lam) * theta[_GAINS]])
    d_ref = np.linalg.lstsq(A, b, rcond=None)[0]
    assert np.allclose(d[_GAINS], d_ref, rtol=1e-9, atol=1e-12)
    assert np.allclose(r_rows, r[rows] + Jg @ d_ref)
    # every row: all five re-fitted, close to the generating step (weak prior)
    _, d_all = _project(base, r)
    assert np.allclose(d_all, d_true, atol=0.01)
