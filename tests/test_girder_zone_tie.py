"""A damaged zone of a measured span with the line's E tied to the span's measured first mode: the
tie against the Euler-Bernoulli formula, the zone's effect on the mode ratio against the modal
strain-energy argument, and when zones are tried at all."""
import math

import numpy as np
import pytest

from maglev_ros.discrepancy import catalogue as cat
from maglev_ros.discrepancy.damping import ExtraMode
from maglev_ros.discrepancy.mode_pattern import ModePattern
from maglev_ros.discrepancy.model import CAL_PARAMS, base_spec, guideway_modal
from maglev_ros.discrepancy.pipeline.propose import measured_first_modes, zones_to_try

L = 12.384


def _spec(kb_ln: float = 0.0):
    spans = [{"id": f"S{i + 1}", "start_m": i * L, "length_m": L} for i in range(5)]
    spec = base_spec({"schema": "maglev-testline/1", "line": {"spans": spans}})
    cal = [0.0] * len(CAL_PARAMS)
    cal[CAL_PARAMS.index("kb")] = kb_ln
    return spec.with_(cal=tuple(cal))


def _modes(spec, i=2):
    m = guideway_modal(spec)
    return np.sort(m.freq_hz[m.span_index == i])


def test_tie_sets_e_so_the_span_rings_at_the_measured_mode_as_the_beam_formula_says():
    spec = _spec(kb_ln=2.5)                      # stiff bearings: the simply supported beam
    target = 21.0
    tied = cat.tie_first_mode(spec, 2, target)
    assert _modes(tied)[0] == pytest.approx(target, rel=1e-4)
    sp = tied.effective_spans()[2].props
    m = sp.density_kg_m3 * sp.area_m2
    # f1 = (pi / 2 L^2) sqrt(E I / m)  ->  E = m (2 L^2 f1 / pi)^2 / I
    e_beam = m * (2 * L ** 2 * target / math.pi) ** 2 / sp.second_moment_m4
    assert sp.youngs_modulus_pa == pytest.approx(e_beam, rel=5e-3)
    # every span alike: it is the line's E, not the span's
    assert len({s.props.youngs_modulus_pa for s in tied.effective_spans()}) == 1


def test_a_zone_between_quarter_point_and_midspan_raises_the_mode_ratio_a_zone_at_the_end_lowers_it():
    # modal strain energy of a pinned beam in [0, L/4]: mode 1 9 %, mode 2 25 %; in [L/4, L/2]: 41 % and 25 %
    spec = _spec(kb_ln=2.5)
    f = _modes(spec)
    r0 = f[1] / f[0]
    inner = _modes(spec.with_(girder_zones=((2, L / 4, L / 2, 0.5),)))
    end = _modes(spec.with_(girder_zones=((2, 0.0, L / 4, 0.5),)))
    assert inner[1] / inner[0] > r0 * 1.02
    assert end[1] / end[0] < r0 * 0.98
    # with the zone in and E tied, the first mode stays where it was measured
    hyp = next(h for h in cat.girder_zone_hypotheses(spec, [2], f[:1].repeat(5), {2: float(f[0])})
               if h.location["position_m"][0] == pytest.approx(2 * L + L / 4))
    z = hyp.apply(spec, np.array([0.5]))
    assert _modes(z)[0] == pytest.approx(f[0], rel=1e-4)
    assert z.cal_factor("E") > 1.05                  # the sound girder is stiffer than the one that matched f1


def _pattern(shift: float, std: float) -> ModePattern:
    return ModePattern("S3", (2 * L, 3 * L), ("G3",), (0.0, 1.0), "ambient", (22.5, 94.4), (0.04, 0.07),
                       (23.5, 92.0), shift, std)


def test_zones_are_tried_where_the_mode_ratio_is_off_beyond_its_error():
    assert zones_to_try(None, (_pattern(0.07, 0.002),))
    assert not zones_to_try(None, (_pattern(0.003, 0.002),))         # 1.5 standard errors
    assert not zones_to_try(None, ())                          # no ambient recording
    assert zones_to_try(True, ()) and not zones_to_try(False, (_pattern(0.07, 0.002),))
    assert measured_first_modes(_spec(), (_pattern(0.07, 0.002),)) == {2: 22.5}


def test_no_zone_where_the_ambient_recording_shows_a_mode_the_twin_lacks():
    # a stiffness change moves the span's modes but adds none: an extra vertical mode is an attachment's
    extra = ExtraMode(63.5, 0.02, 0.99, 0.99, "M2", peak_ratio=4.2, peak_needed=1.6)
    assert not zones_to_try(None, (_pattern(0.09, 0.002),), (extra,))
    # a numerical pole (no spectral peak) or a torsional mode does not count
    assert zones_to_try(None, (_pattern(0.09, 0.002),), (ExtraMode(30.2, 0.0005, 0.99, 0.99, "M2", 1.5, 1.6),))
    assert zones_to_try(None, (_pattern(0.09, 0.002),), (ExtraMode(63.5, 0.02, 0.5, 0.1, "M2", 4.2, 1.6),))
