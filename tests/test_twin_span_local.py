"""Span-local stepping of the coupled twin (``TwinStepper``): only the modes of the spans under the
magnets enter the coupled kernel; modes a sensor sees are stepped alone while free, the others jump
a block at once by the Newmark scheme's transition matrix.

Reference: the same stepper with ``reference=True``, every mode of the line in every step (the
computation before span-local stepping). Both must agree to round-off on every output and on the
final modal state, on a long line with spans of different lengths given out of order, sensors on
loaded, left-behind, not-yet-reached and never-reached spans, uneven block lengths, a speed ramp and
position jumps back onto spans that rang freely meanwhile (as the online twin's resync does).
Measured: outputs within 1.2e-12 of their peak (bitwise without the jumps), final modal state 1.1e-11.
"""
import numpy as np
import pytest

from maglev_ros.twin.coupling import PassResult, TwinStepper
from maglev_ros.twin.design import twin_config
from maglev_ros.twin.guideway import Guideway

L = 12.384
ORDER = [5, 0, 17, 3, 11, 8, 1, 20, 14, 6, 22, 9, 2, 19, 13, 4, 23, 10, 16, 7, 21, 12, 18, 15]


def _line():
    """24 spans, given out of order; span 4 is half as long (fewer modes below the cutoff)."""
    return [{"id": f"S{i}", "start_m": STARTS[i], "length_m": STARTS[i + 1] - STARTS[i]} for i in ORDER]


STARTS = np.concatenate([[0.0], np.cumsum([L / 2 if i == 4 else L for i in range(24)])])


def _irregularity(x):
    return 6e-4 * np.sin(2 * np.pi * x / 7.3) + 2e-4 * np.sin(2 * np.pi * x / 0.83)


# the magnets (20 m long) start over spans 0-2, pass the short span 4 and jump onto span 6
SENSORS = {"start_span": STARTS[2] + 4.0, "left_behind": STARTS[0] + 6.0, "joint": STARTS[4],
           "short_span": STARTS[4] + 1.5, "reached": STARTS[6] + 6.0, "never": STARTS[22] + 6.0}
# (advance to t [s], speed at t [m/s], position jump after it [m]): uneven blocks (one internal
# step, blocks ending between output samples, longer than block_steps), a ramp, jumps back and ahead
SCHEDULE = [(0.0005, 20.0, 0.0), (0.0371, 20.0, 0.0), (0.2, 24.0, 0.0), (0.2003, 24.0, 0.0), (0.55, 30.0, 0.0),
            (0.9, 30.0, -22.0), (1.3, 12.0, 0.0), (1.6, 12.0, 40.0), (1.9, 18.0, 0.0)]


def _run(reference: bool, **kw) -> tuple[PassResult, TwinStepper]:
    cfg = twin_config()
    st = TwinStepper(cfg, _line(), sensors=SENSORS, irregularity=_irregularity, fs_out_hz=2000.0,
                     start_position_m=2.2 * L, start_speed_mps=20.0, dt_max_s=2.5e-4, block_steps=1000,
                     reference=reference, **kw)
    parts = []
    for t, v, jump in SCHEDULE:
        parts.append(st.advance(t, v))
        st.position_m += jump
    return PassResult.concat(parts), st


@pytest.mark.parametrize("kw", [{}, {"method": "separated"}, {"current_limit_a": 4.0}],
                         ids=["newmark", "separated", "current_limit"])
def test_span_local_stepping_equals_every_mode_stepping(kw):
    ref, st_ref = _run(True, **kw)
    new, st_new = _run(False, **kw)
    n_modes = st_new.modal.n_modes
    # the kernel really ran on a few spans' modes of this line
    pos = st_new.position_m + np.arange(1, 5) * 1e-3
    assert st_new._prepare(pos, np.full(4, 18.0), local=True)["modes"].size <= 3 * n_modes // 24 + 3
    assert ref.n_samples == new.n_samples == 3800
    for name, a in ref.__dict__.items():
        if isinstance(a, np.ndarray):
            b = getattr(new, name)
            assert b.shape == a.shape, name
            peak = float(np.max(np.abs(a))) if a.size else 0.0
            np.testing.assert_allclose(b, a, rtol=0, atol=1e-10 * peak + 1e-300, err_msg=name)
    np.testing.assert_array_equal(new.iterations, ref.iterations)
    # every mode's final state (the ones that jumped by the transition matrix too): a mode ringing
    # freely for thousands of steps accumulates phase round-off either way (1e-10 of its amplitude
    # after 7600 steps, stepped or by the matrix power, against a long-double recurrence)
    for name in ("_q", "_qd", "_qdd", "_x", "_u", "_F"):
        a, b = getattr(st_ref, name), getattr(st_new, name)
        np.testing.assert_allclose(b, a, rtol=0, atol=1e-9 * float(np.max(np.abs(a))), err_msg=name)
    # the scenario covered what it claims: the spans the jump back re-entered were ringing, sensors
    # saw the vehicle and its wake, the never-reached span stayed at rest
    g = new.guideway_disp_m
    for s in ("start_span", "reached", "left_behind", "joint", "short_span"):
        assert np.max(np.abs(g[:, new.sensor(s)])) > 1e-6, s        # (the joint: bearing compliance)
    assert np.all(g[:, new.sensor("never")] == 0.0)


def test_local_shapes_are_the_line_shapes_own_columns():
    cfg = twin_config()
    from maglev_ros.twin.design import line_spans
    mb = Guideway(line_spans(_line(), cfg), cfg.numerics.n_elements_per_span).modes(cfg.numerics.mode_cutoff_hz, 2)
    rng = np.random.default_rng(5)
    x = np.concatenate([rng.uniform(3 * L, 11 * L, 300), STARTS[2:10], [STARTS[-1], STARTS[-1] + 1e-9, -1.0]])
    spans, phi, dphi = mb.local_shapes_at(x)
    cols = mb.mode_columns(spans)
    assert np.array_equal(spans, np.unique(mb.span_of(x)[mb.span_of(x) >= 0]))
    assert np.array_equal(phi, mb.shapes_at(x)[:, cols]) and np.array_equal(dphi, mb.slopes_at(x)[:, cols])
    assert np.count_nonzero(mb.shapes_at(x)[:, np.setdiff1d(np.arange(mb.n_modes), cols)]) == 0
    with pytest.raises(ValueError, match="not among"):
        mb.shapes_at(x, spans[1:])
