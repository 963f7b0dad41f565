"""The ratio of the instrumented span's first two modes in the ambient recording against the twin's.

References: ambient recordings synthesised from a truth structure on a mesh twice the twin's (each
mode's response to white point forces through scipy.signal's bilinear filter, plus sensor noise), and
the physics of the ratio: a girder and bearings stiffer together, or a lighter girder, leave it alone;
a soft bearing lowers it."""
import os
import sys

import numpy as np
import pytest

sys.path.insert(0, os.path.dirname(__file__))
from discrepancy_cases import NOISE_STD, metadata  # noqa: E402

from maglev_ros.discrepancy.damping import measure_damping  # noqa: E402
from maglev_ros.discrepancy.mode_pattern import mode_pattern  # noqa: E402
from maglev_ros.discrepancy.model import base_spec, guideway_modal  # noqa: E402
from maglev_ros.discrepancy.recording import recording_from_arrays  # noqa: E402

N_SPANS = 3


def _ambient(truth_spec, seed=2, seconds=60.0):
    """White point forces at two places per span, each mode's acceleration response by a bilinear
    (scipy.signal) second-order filter, 1 kHz, 5 vertical accelerometers on the middle span."""
    from scipy import signal
    rng = np.random.default_rng(seed)
    md = metadata({}, "ambient", 0.0, N_SPANS)
    sp = truth_spec.spans[1]
    x = sp.start_m + sp.length_m * np.arange(1, 6) / 6
    md["sensors"] = {f"G2V{j}": {"topic": "/testline/guideway/accel", "quantity": "acceleration",
                                 "direction": "vertical", "span": sp.span_id, "position_m": float(xj),
                                 "side": "center"} for j, xj in enumerate(x)}
    modal = guideway_modal(truth_spec)
    fs, n = 1000.0, int(seconds * 1000)
    pts = np.concatenate([s.start_m + rng.uniform(0.1, 0.9, 2) * s.length_m for s in truth_spec.spans])
    fq = rng.standard_normal((n, pts.size)) @ modal.shapes_at(pts)          # modal forces
    acc_modal = np.empty_like(fq)
    for k, (w, z) in enumerate(zip(modal.omega_rad_s, modal.damping_ratio)):
        if w >= 0.8 * np.pi * fs:
            # above 0.4 fs: the instrument's anti-alias filter removes it (and the pre-warp fails at Nyquist)
            acc_modal[:, k] = 0.0
            continue
        w = 2 * fs * np.tan(w / (2 * fs))          # pre-warped: the digital resonance lands on the mode
        b, a = signal.bilinear([1.0, 0.0, 0.0], [1.0, 2 * z * w, w * w], fs)
        acc_modal[:, k] = signal.lfilter(b, a, fq[:, k])
    acc = acc_modal @ modal.shapes_at(x).T
    acc *= 0.05 / np.std(acc)
    t = np.arange(1, n + 1) / fs
    ch = {k: (t, acc[:, j] + rng.normal(0, NOISE_STD["guideway_accel"], n)) for j, k in enumerate(md["sensors"])}
    return recording_from_arrays(md, ch, None, source="synthetic/ambient")


@pytest.fixture(scope="module")
def twin():
    return base_spec(metadata({}, "pass", 25.0, N_SPANS))


def _fine(spec):
    from dataclasses import replace
    num = spec.config.numerics
    return spec.with_(config=replace(spec.config, numerics=replace(num, n_elements_per_span=2 * num.n_elements_per_span)))


def test_stiffness_and_density_leave_the_ratio_alone(twin):
    # E and the bearings +20 % (the girder as stiff relative to its supports), density -10 %
    truth = _fine(twin).with_(cal=(np.log(1.2), np.log(1.2), 0.0, 0.0, np.log(0.9)))
    amb = _ambient(truth)
    p = mode_pattern(measure_damping(amb, twin), twin, amb)
    assert p is not None
    # the modes themselves moved by sqrt(1.2 / 0.9) - 1 = 15 %
    assert p.measured_hz[0] / p.twin_hz[0] == pytest.approx(np.sqrt(1.2 / 0.9), rel=0.01)
    assert not p.flagged, p.to_dict()


def test_a_soft_bearing_lowers_the_ratio_and_is_located(twin):
    dm0 = measure_damping(_ambient(_fine(twin)), twin)
    i = [s.span_id for s in twin.spans].index(dm0.span_id)
    bf = tuple((1.0, 0.15) if k == i else (1.0, 1.0) for k in range(N_SPANS))
    amb = _ambient(_fine(twin).with_(bearing_factor=bf))
    dm = measure_damping(amb, twin)
    p = mode_pattern(dm, twin, amb)
    assert p is not None and p.flagged and p.log_ratio_shift < 0, p.to_dict()
    m = p.to_mismatch()
    assert m.position_m == (twin.spans[i].start_m, twin.spans[i].end_m)
    assert "bearings" in m.explanation
    # the twin with that bearing has the measured pattern
    q = mode_pattern(dm, twin.with_(bearing_factor=bf), amb)
    assert not q.flagged, q.to_dict()
