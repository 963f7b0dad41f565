"""system3d continuous 3D girder: element/assembly checks against PyNiteFEA (static and modal),
analytic continuous-beam and torsion frequencies, supports, damping, paper 001's scenario."""
from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from maglev_ros.errors import UserError
from maglev_ros.system3d.girder import (Damping, GirderSpec, Support, assemble_girder,
                                        load_girder)
from maglev_ros.system3d.girder_element import GirderSection
from maglev_ros.system3d.girder_rails import RailInterpolation, RailLayout
from maglev_ros.system3d.scenario_values import load_yaml
from system3d_refs import continuous_beam_freqs_hz, pynite_girder, pynite_nodal

CONFIG = Path(__file__).resolve().parents[1] / "maglev_ros" / "config" / "system3d"
E, G, A, IY, IZ, J = 3.5e10, 3.5e10 / 2.6, 6.0, 8.0, 30.0, 12.0
RHO = 2500.0
SPANS = (24.0, 36.0, 30.0)          # unequal spans
N_EL = 6


def _section(polar=RHO * J):
    return GirderSection(E * A, E * IY, E * IZ, G * J, RHO * A, polar)


def _pinned(spans=SPANS, n=N_EL, **kw):
    x = np.concatenate([[0.0], np.cumsum(spans)])
    sup = tuple(Support(float(xi), ("y", "z", "rx") + (("x",) if i == 0 else ())) for i, xi in enumerate(x))
    return GirderSpec("t", tuple(spans), n, kw.pop("section", _section()), sup, **kw)


@pytest.fixture(scope="module")
def girder():
    return assemble_girder(_pinned())


def _pynite_supports(g):
    flags = {}
    for k, xs in enumerate(np.concatenate([[0.0], np.cumsum(SPANS)])):
        flags[g.node_at(xs)] = (k == 0, True, True, True, False, False)
    return flags


def test_static_point_loads_match_pynite(girder):
    """Vertical, lateral point loads and a torque at a node, plus an eccentric load inside an
    element, against PyNiteFEA: nodal displacements within 0.5 %."""
    g = girder
    node = 8                      # inside the 36 m span, off its centre
    x_in = 0.5 * (g.node_x_m[3] + g.node_x_m[4]) + 0.7     # inside element 3
    rails = RailLayout(half_gauge_m=1.1, rail_height_m=0.0)
    ri = RailInterpolation(g, rails)
    f = np.zeros(g.n_free)
    f[g.dof(g.node_x_m[node], "z")] += -2.0e6
    f[g.dof(g.node_x_m[node], "y")] += 5.0e5
    f[g.dof(g.node_x_m[node], "rx")] += 3.0e6
    f += ri.load_vector(x_in, "left", force_z_n=-1.0e6)   # eccentric: F_z and torque b F_z
    ours = g.expand(g.static_displacement(f))

    m = pynite_girder(g.node_x_m, (E, G, A, IY, IZ, J), _pynite_supports(g), RHO)
    m.add_node_load(f"N{node}", "FZ", -2.0e6)
    m.add_node_load(f"N{node}", "FY", 5.0e5)
    m.add_node_load(f"N{node}", "MX", 3.0e6)
    xl = x_in - g.node_x_m[3]
    m.add_member_pt_load("M3", "FZ", -1.0e6, xl)
    m.add_member_pt_load("M3", "MX", -1.0e6 * 1.1, xl)
    m.analyze_linear()
    ref = pynite_nodal(m, g.n_nodes)
    for dof, name in enumerate(("u", "v", "w", "rx", "ry", "rz")):
        scale = np.abs(ref[:, dof]).max()
        if scale == 0:
            continue
        err = np.abs(ours[:, dof] - ref[:, dof]).max() / scale
        assert err <= 5e-3, f"{name}: max error {err:.2e} of max |{name}| {scale:.3e}"
    # the three actions really were exercised
    assert min(np.abs(ref[:, 1]).max(), np.abs(ref[:, 2]).max(), np.abs(ref[:, 3]).max()) > 0


def test_modes_match_pynite_modal(girder):
    """Lowest 12 frequencies (vertical, lateral, axial, torsion mixed) within 1 % of PyNiteFEA's
    modal analysis of the same girder (Pynite's polar mass is rho J, as in ``_section``)."""
    m = pynite_girder(girder.node_x_m, (E, G, A, IY, IZ, J), _pynite_supports(girder), RHO)
    m.add_member_self_weight("FZ", 1.0, "Case 1")
    m.analyze_modal(num_modes=12, mass_combo_name="Combo 1", mass_direction="Z", gravity=1.0)
    ref = np.sort(np.asarray(m.frequencies))
    ours = girder.modes(12)
    assert set(ours.kind) >= {"vertical", "lateral", "torsion"}
    np.testing.assert_allclose(ours.freq_hz, ref, rtol=1e-2)


@pytest.mark.parametrize("kind, ei", [("vertical", E * IY), ("lateral", E * IZ)])
def test_bending_modes_match_characteristic_equation(kind, ei):
    """First 5 bending frequencies of the unequal 3-span continuous girder within 1 % of the
    exact Euler-Bernoulli roots of the continuous beam's characteristic equation."""
    g = assemble_girder(_pinned(n=12))
    md = g.modes(40)
    ours = md.freq_hz[md.of_kind(kind)][:5]
    ref = continuous_beam_freqs_hz(SPANS, ei, RHO * A, 5, 1.2 * ours[-1])
    np.testing.assert_allclose(ours, ref, rtol=1e-2)


def test_torsion_of_a_span_fixed_in_torsion_at_both_ends():
    """f_n = n / (2 L) sqrt(GJ / (rho I_p)) for a single span, first 3 within 1 %, and the same
    set per span for the continuous girder (torsion restrained at every support)."""
    polar = RHO * (IY + IZ)
    ct = np.sqrt(G * J / polar)
    g1 = assemble_girder(_pinned(spans=(40.0,), n=40, section=_section(polar)))
    md = g1.modes(60)
    ours = md.freq_hz[md.of_kind("torsion")][:3]
    np.testing.assert_allclose(ours, np.arange(1, 4) * ct / (2 * 40.0), rtol=1e-2)
    g3 = assemble_girder(_pinned(n=24, section=_section(polar)))
    md3 = g3.modes(120)
    ref = np.sort(np.concatenate([np.arange(1, 3) * ct / (2 * L) for L in SPANS]))[:4]
    np.testing.assert_allclose(md3.freq_hz[md3.of_kind("torsion")][:4], ref, rtol=1e-2)


def test_mass_spd_and_free_girder_has_six_rigid_body_modes():
    spec = replace(_pinned(), supports=())
    g = assemble_girder(spec)
    assert np.allclose(g.mass, g.mass.T) and np.allclose(g.stiffness, g.stiffness.T)
    assert np.linalg.eigvalsh(g.mass).min() > 0
    md = g.modes(8)
    assert np.all(md.freq_hz[:6] < 1e-4 * md.freq_hz[6]), md.freq_hz
    # the six are rigid: zero strain energy and they span the 6 rigid motions (rank 6)
    assert np.abs(md.vectors[:, :6].T @ g.stiffness @ md.vectors[:, :6]).max() < 1e-6 * md.omega_rad_s[6] ** 2
    with pytest.raises(UserError, match="mechanism"):
        g.static_displacement(np.ones(g.n_free))


def test_spring_supports_add_their_compliance():
    """Midspan point load P on one span on vertical springs k: P L^3 / (48 EI) + P / (2 k)."""
    L, k, P = 30.0, 2.0e8, 1.0e6
    sup = (Support(0.0, ("x", "y", "rx"), (("z", k),)), Support(L, ("y", "rx"), (("z", k),)))
    g = assemble_girder(GirderSpec("s", (L,), 10, _section(), sup))
    f = np.zeros(g.n_free)
    f[g.dof(L / 2, "z")] = -P
    w = g.expand(g.static_displacement(f))[g.node_at(L / 2), 2]
    assert w == pytest.approx(-(P * L**3 / (48 * E * IY) + P / (2 * k)), rel=1e-9)


@pytest.mark.parametrize("damping", [Damping("rayleigh", 0.03, frequencies_hz=(2.0, 6.0)),
                                     Damping("rayleigh", 0.02, modes=(1, 3)), Damping("modal", 0.025)])
def test_damping_ratios(girder, damping):
    """Modal damping ratios phi^T C phi / (2 w): Rayleigh exact at its two targets, a/(2w) + b w/2
    in between; modal damping equal on every mode."""
    g = assemble_girder(replace(girder.spec, damping=damping))
    md = g.modes(10)
    zeta = np.einsum("im,ij,jm->m", md.vectors, g.damping, md.vectors) / (2 * md.omega_rad_s)
    if damping.kind == "modal":
        np.testing.assert_allclose(zeta, 0.025, rtol=1e-6)
        return
    targets = (2 * np.pi * np.array(damping.frequencies_hz) if damping.frequencies_hz
               else md.omega_rad_s[[0, 2]])
    a, b = g.rayleigh_alpha_per_s, g.rayleigh_beta_s
    np.testing.assert_allclose(a / (2 * targets) + b * targets / 2, damping.ratio, rtol=1e-9)
    np.testing.assert_allclose(zeta, a / (2 * md.omega_rad_s) + b * md.omega_rad_s / 2, rtol=1e-6)
    if damping.modes:
        np.testing.assert_allclose(zeta[[0, 2]], damping.ratio, rtol=1e-6)


def test_user_errors_name_the_item():
    with pytest.raises(UserError, match="no FE node"):
        assemble_girder(replace(_pinned(), supports=(Support(5.0, ("z",)),)))
    with pytest.raises(UserError, match="unknown DOF 'zz'"):
        Support(0.0, ("zz",))
    with pytest.raises(UserError, match="spans_m"):
        GirderSpec.from_dict({"section": {}, "supports": []})
    with pytest.raises(UserError, match=r"girder\.section: missing key 'vertical_bending_rigidity_n_m2'"):
        GirderSpec.from_dict({"spans_m": [10], "supports": [], "section": {"axial_rigidity_n": 1.0}})
    with pytest.raises(UserError, match="'assumed' or 'source'"):
        GirderSpec.from_dict({"spans_m": [{"value": 10}], "supports": [], "section": {}})


# ---------------------------------------------------------------- paper 001 scenario
PAPER_SPEED_MPS = 100 / 3.6    # paper 001 sec. 6: the PSDs are at 100 km/h


@pytest.fixture(scope="module")
def paper():
    path = CONFIG / "paper001_girder.yaml"
    g = assemble_girder(load_girder(path))
    rails = RailLayout.from_dict(load_yaml(path)["rails"])
    return g, rails, g.modes(30)


def test_paper001_girder_frequencies_sit_at_the_paper_psd_peaks(paper):
    """The paper's midpoint PSD peaks 0.24 / 0.66 rad/m (vertical) and 0.38 rad/m (lateral) at
    100 km/h are f = Omega v / (2 pi): first vertical, second vertical mode seen at the main-span
    midpoint (the next symmetric one) and first lateral mode."""
    g, rails, md = paper
    ref = {k: om * PAPER_SPEED_MPS / (2 * np.pi) for k, om in (("v1", 0.24), ("v2", 0.66), ("l1", 0.38))}
    vert = md.of_kind("vertical")
    mid = RailInterpolation(g, rails).section_rows([85.0 + 55.0])["w"][0]
    amp = np.abs(mid @ md.vectors[:, vert])
    seen = vert[amp > 0.3 * amp.max()]
    assert md.freq_hz[vert[0]] == pytest.approx(ref["v1"], rel=0.03)
    assert md.freq_hz[seen[1]] == pytest.approx(ref["v2"], rel=0.05)
    assert md.freq_hz[md.of_kind("lateral")[0]] == pytest.approx(ref["l1"], rel=0.03)
    assert np.linalg.eigvalsh(g.mass).min() > 0
    summary = json.loads(json.dumps({"girder": g.spec.to_dict(), "rails": rails.to_dict(), "modes": md.to_dict()}))
    assert summary["modes"]["kind"][0] == "vertical" and summary["girder"]["span_lengths_m"] == [85.0, 110.0, 85.0]
    # the paper's 3 % Rayleigh damping holds at the two vertical peaks
    for f in (md.freq_hz[vert[0]], md.freq_hz[seen[1]]):
        w = 2 * np.pi * f
        assert g.rayleigh_alpha_per_s / (2 * w) + g.rayleigh_beta_s * w / 2 == pytest.approx(0.03, rel=0.03)
