"""A damaged girder zone: the FE span with lowered EI over part of its length, against beam theory."""
import math

import numpy as np
import pytest

from maglev_ros.discrepancy.model import zone_element_factors
from maglev_ros.twin.design import GuidewayProps, SpanSpec
from maglev_ros.twin.guideway import assemble_span

L = 12.384
N_EL = 48


def _freqs(ei_factors=None, n=3):
    span = SpanSpec("S1", 0.0, L, GuidewayProps(4.0e10, 2500.0, 1.5, 0.5, math.inf, 0.02))
    w, _ = assemble_span(span, N_EL, ei_factors=ei_factors).eig()
    return w[:n]


def test_a_zone_over_the_whole_span_is_a_uniform_loss():
    f = 0.7
    ratio = _freqs(zone_element_factors(L, N_EL, [(0.0, L, f)])) / _freqs()
    assert np.allclose(ratio, math.sqrt(f), rtol=1e-9)


@pytest.mark.parametrize("x0,x1", [(L / 4, L / 2), (0.0, L / 4), (0.3 * L, 0.55 * L)])
def test_small_zone_loss_shifts_each_mode_by_its_curvature_energy_there(x0, x1):
    """First-order perturbation (Rayleigh quotient) for a simply supported beam: mode n's curvature is
    ~ sin(n pi x / L), so d(w_n^2) / w_n^2 = -(1 - f) * (share of int sin^2 over the zone)."""
    f = 0.98
    shift = (_freqs(zone_element_factors(L, N_EL, [(x0, x1, f)])) / _freqs()) ** 2 - 1.0
    for n in (1, 2, 3):
        k = n * math.pi / L
        share = ((x1 - x0) / 2 - (math.sin(2 * k * x1) - math.sin(2 * k * x0)) / (4 * k)) / (L / 2)
        assert shift[n - 1] == pytest.approx(-(1 - f) * share, rel=0.05, abs=2e-4)


def test_an_element_partly_in_the_zone_gets_the_factor_by_its_overlap():
    fac = zone_element_factors(4.0, 4, [(1.5, 3.0, 0.5)])
    assert np.allclose(fac, [1.0, 0.75, 0.5, 1.0])
