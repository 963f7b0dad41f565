"""Guideway FE: static deflection, frequencies, mode shapes and damping vs closed-form beam theory."""
import math

import numpy as np
import pytest

from maglev_ros.errors import ContractError
from maglev_ros.twin.design import GuidewayProps, SpanSpec, default_line, line_spans, twin_config
from maglev_ros.twin.guideway import Guideway


def props(E=4.0e10, rho=2500.0, A=1.5, I=0.5, kb=3.0e10, zeta=0.02):
    return GuidewayProps(E, rho, A, I, kb, zeta)


def ss_deflection(P, a, x, L, EI, kb):
    """Simply supported beam, point load P (down) at a: deflection (down positive) at x, plus the
    rigid-body motion of the two bearings (reactions / kb)."""
    b = L - a
    if x <= a:
        d = P * b * x * (L ** 2 - b ** 2 - x ** 2) / (6 * L * EI)
    else:
        d = P * a * (L - x) * (L ** 2 - a ** 2 - (L - x) ** 2) / (6 * L * EI)
    if math.isfinite(kb):
        r0, r1 = P * b / L, P * a / L
        d += (1 - x / L) * r0 / kb + (x / L) * r1 / kb
    return d


@pytest.mark.parametrize("L,kb,n_el", [(12.384, 3.0e10, 16), (24.768, 5.0e9, 10), (30.0, math.inf, 8)])
def test_static_midspan_deflection_matches_beam_theory(L, kb, n_el):
    p = props(kb=kb)
    g = Guideway([SpanSpec("S1", 0.0, L, p)], n_elements_per_span=n_el)
    P = 1.0e5
    w = g.static_displacement([L / 2], [-P], [L / 2])[0]
    ref = P * L ** 3 / (48 * p.bending_stiffness_n_m2) + (P / (2 * kb) if math.isfinite(kb) else 0.0)
    assert -w == pytest.approx(ref, rel=0.01)


@pytest.mark.parametrize("a_frac,x_frac", [(0.3, 0.5), (0.5, 0.2), (0.81, 0.77), (0.137, 0.9)])
def test_static_deflection_off_centre(a_frac, x_frac):
    L, kb = 12.384, 2.0e9
    p = props(kb=kb)
    g = Guideway([SpanSpec("S1", 100.0, L, p)], n_elements_per_span=12)
    P = 7.0e4
    w = g.static_displacement([100.0 + a_frac * L], [-P], [100.0 + x_frac * L])[0]
    assert -w == pytest.approx(ss_deflection(P, a_frac * L, x_frac * L, L, p.bending_stiffness_n_m2, kb),
                               rel=0.01)


@pytest.mark.parametrize("L,E,I,A", [(12.384, 4.0e10, 0.5, 1.5), (24.768, 3.5e10, 2.1, 4.0)])
def test_rigid_support_frequencies_match_closed_form(L, E, I, A):
    p = props(E=E, I=I, A=A, kb=math.inf)
    g = Guideway([SpanSpec("S1", 0.0, L, p)], n_elements_per_span=16)
    f = g.frequencies_hz(0, 3)
    ref = [(n * math.pi / L) ** 2 * math.sqrt(p.bending_stiffness_n_m2 / p.mass_per_length_kg_m) / (2 * math.pi)
           for n in (1, 2, 3)]
    np.testing.assert_allclose(f, ref, rtol=0.005)


def test_elastic_bearings_lower_frequencies_and_tend_to_rigid():
    L = 12.384
    rigid = Guideway([SpanSpec("S1", 0.0, L, props(kb=math.inf))]).frequencies_hz(0, 3)
    prev = np.zeros(3)
    for kb in (1e8, 1e9, 1e10, 1e11, 1e12, 1e14):
        f = Guideway([SpanSpec("S1", 0.0, L, props(kb=kb))]).frequencies_hz(0, 3)
        assert np.all(f < rigid * (1 + 1e-9))
        assert np.all(f > prev)
        prev = f
    np.testing.assert_allclose(prev, rigid, rtol=1e-4)


def test_mode_shapes_are_mass_normalised_sines_on_rigid_supports():
    L = 12.384
    p = props(kb=math.inf)
    g = Guideway([SpanSpec("S1", 5.0, L, p)], n_elements_per_span=20)
    mb = g.modes(cutoff_hz=1e9, max_modes_per_span=3)
    x = 5.0 + np.linspace(0.0, L, 37)
    phi = mb.shapes_at(x)
    m = p.mass_per_length_kg_m
    for n in range(3):
        ref = math.sqrt(2 / (m * L)) * np.sin((n + 1) * math.pi * (x - 5.0) / L)
        s = np.sign(phi[:, n] @ ref)
        np.testing.assert_allclose(s * phi[:, n], ref, atol=2e-3 * np.max(np.abs(ref)))
        dref = math.sqrt(2 / (m * L)) * (n + 1) * math.pi / L * np.cos((n + 1) * math.pi * (x - 5.0) / L)
        np.testing.assert_allclose(s * mb.slopes_at(x)[:, n], dref, atol=1e-2 * np.max(np.abs(dref)))


@pytest.mark.parametrize("zeta", [0.01, 0.035])
def test_rayleigh_damping_ratio_on_first_two_modes(zeta):
    g = Guideway([SpanSpec("S1", 0.0, 12.384, props(zeta=zeta))])
    fe = g.spans_fe[0]
    w, phi = fe.eig()
    c_modal = phi.T @ fe.damping @ phi
    np.testing.assert_allclose(np.diag(c_modal)[:2] / (2 * w[:2]), zeta, rtol=1e-6)
    mb = g.modes()
    np.testing.assert_allclose(mb.damping_ratio[:2], zeta, rtol=1e-6)
    assert mb.damping_ratio[2] > zeta  # stiffness-proportional part grows above mode 2


def test_multi_span_modes_live_on_their_own_span_and_per_span_overrides():
    cfg = twin_config()
    line = {"spans": [{"id": "A", "start_m": 0.0, "length_m": 12.384},
                      {"id": "B", "start_m": 12.384, "length_m": 12.384, "second_moment_m4": 4 * cfg.guideway.second_moment_m4},
                      {"id": "C", "start_m": 24.768, "length_m": 24.768}]}
    spans = line_spans(line, cfg)
    assert spans[1].props.second_moment_m4 == pytest.approx(4 * cfg.guideway.second_moment_m4)
    assert spans[0].props == cfg.guideway
    g = Guideway(spans)
    f_a, f_b = g.frequencies_hz(0, 1)[0], g.frequencies_hz(1, 1)[0]
    assert f_b / f_a == pytest.approx(2.0, rel=0.02)   # f ~ sqrt(EI), bearings make it slightly < 2
    mb = g.modes(cutoff_hz=150.0)
    phi = mb.shapes_at([6.0, 18.0, 36.0])
    for row, span in enumerate((0, 1, 2)):
        assert np.all(phi[row, mb.span_index != span] == 0.0)
        assert np.any(phi[row, mb.span_index == span] != 0.0)
    assert mb.shapes_at([-1.0, 60.0]).sum() == 0.0


def test_default_guideway_is_paper_like():
    cfg = twin_config()
    g = Guideway(default_line(cfg))
    f1 = g.frequencies_hz(0, 1)[0]
    assert 22.5 < f1 < 24.5          # 000: 23.49 Hz measured first vertical mode


def test_bad_span_override_names_the_key():
    with pytest.raises(ContractError, match=r"line.spans\[0\].area_m2"):
        line_spans({"spans": [{"start_m": 0.0, "length_m": 10.0, "area_m2": "big"}]}, twin_config())
    with pytest.raises(ContractError, match=r"line.spans\[1\].length_m"):
        line_spans([{"start_m": 0.0, "length_m": 10.0}, {"start_m": 10.0}], twin_config())


def test_shapes_on_a_long_line_are_the_hermite_interpolation_of_each_spans_own_modes():
    """shapes_at / slopes_at sum each point's own span's modes only: the same values as the cubic
    Hermite interpolation of every mode's nodal values (zero off its span), on a 12-span line with
    spans given out of order, points on joints, on the last span's end and off the line."""
    cfg = twin_config()
    order = [3, 0, 7, 1, 11, 5, 2, 9, 4, 10, 6, 8]
    L = 12.384
    spans = line_spans({"spans": [{"id": f"S{i}", "start_m": i * L, "length_m": L} for i in order]}, cfg)
    mb = Guideway(spans, n_elements_per_span=8).modes(cutoff_hz=250.0)
    rng = np.random.default_rng(3)
    x = np.concatenate([rng.uniform(-2.0, 12 * L + 2.0, 400), np.arange(13) * L, [-1e-9, 12 * L + 1e-9]])
    ref_phi = np.zeros((x.size, mb.n_modes))
    ref_dphi = np.zeros((x.size, mb.n_modes))
    col = 0
    for fe, vec in zip(mb.spans_fe, mb.vectors):
        full = np.zeros((2 * (fe.n_elements + 1), vec.shape[1]))
        full[fe.free_dofs] = vec
        le = fe.element_length_m
        last = fe.span.end_m == max(s.end_m for s in spans)
        for i, xi_m in enumerate(x):
            inside = fe.span.start_m <= xi_m < fe.span.end_m or (last and xi_m == fe.span.end_m)
            if not inside:
                continue
            e = min(int((xi_m - fe.span.start_m) // le), fe.n_elements - 1)
            t = (xi_m - fe.span.start_m) / le - e
            h = (1 - 3 * t ** 2 + 2 * t ** 3, le * (t - 2 * t ** 2 + t ** 3), 3 * t ** 2 - 2 * t ** 3, le * (t ** 3 - t ** 2))
            dh = ((-6 * t + 6 * t ** 2) / le, 1 - 4 * t + 3 * t ** 2, (6 * t - 6 * t ** 2) / le, 3 * t ** 2 - 2 * t)
            nodal = full[2 * e:2 * e + 4]
            ref_phi[i, col:col + vec.shape[1]] = np.dot(h, nodal)
            ref_dphi[i, col:col + vec.shape[1]] = np.dot(dh, nodal)
        col += vec.shape[1]
    scale = np.abs(ref_phi).max()
    np.testing.assert_allclose(mb.shapes_at(x), ref_phi, rtol=1e-12, atol=1e-12 * scale)
    np.testing.assert_allclose(mb.slopes_at(x), ref_dphi, rtol=1e-12, atol=1e-12 * np.abs(ref_dphi).max())
    assert np.count_nonzero(np.abs(ref_phi).sum(axis=1)) < x.size      # points off the line are zero rows


def test_default_modal_basis_reproduces_the_beams_receptance_at_sensor_points():
    """The twin's default mode cutoff keeps enough modes for the quasi-static share of the higher
    modes at quarter and eighth points: the modal receptance there, 60-180 Hz, against the continuous
    Euler-Bernoulli beam's series (4000 analytic modes). A 300 Hz cutoff was 10-41 % off here."""
    cfg = twin_config()
    L = 12.384
    p = props(E=cfg.guideway.youngs_modulus_pa, rho=cfg.guideway.density_kg_m3, A=cfg.guideway.area_m2,
              I=cfg.guideway.second_moment_m4, kb=math.inf, zeta=0.0)
    mb = Guideway([SpanSpec("S1", 0.0, L, p)], n_elements_per_span=cfg.numerics.n_elements_per_span).modes(
        cfg.numerics.mode_cutoff_hz, cfg.numerics.min_modes_per_span)
    w2 = (2 * np.pi * mb.freq_hz) ** 2
    EI, m = p.bending_stiffness_n_m2, p.mass_per_length_kg_m
    n = np.arange(1, 4001)
    wn2 = (n * np.pi / L) ** 4 * EI / m
    for x, a in [(L / 8, L / 8), (L / 4, L / 4), (L / 4, L / 8), (L / 2, L / 2)]:
        for f_hz in (60.0, 120.0, 180.0):
            w = 2 * np.pi * f_hz
            ref = np.sum(2 / (m * L) * np.sin(n * np.pi * x / L) * np.sin(n * np.pi * a / L) / (wn2 - w ** 2))
            got = np.sum(mb.shapes_at([x])[0] * mb.shapes_at([a])[0] / (w2 - w ** 2))
            assert got == pytest.approx(ref, rel=0.03), (x, a, f_hz)
