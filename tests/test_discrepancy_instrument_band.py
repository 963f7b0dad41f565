"""An instrument's low-pass inside the compared bands (maglev_ros.discrepancy.instrument_band).

Reference: the filter itself. A clean generated line whose guideway accelerometers are low-passed by a
zero-phase Butterworth (scipy) well below 0.7 x Nyquist: the calibrate stage compares those channels
below the band where the filter's power gain falls to one half (scipy's sosfreqz), within one band,
and leaves the other groups alone; the same line unfiltered is compared on every band."""
import os
import sys
from dataclasses import replace

import numpy as np
import pytest
from scipy import signal

sys.path.insert(0, os.path.dirname(__file__))
from discrepancy_cases import make_case  # noqa: E402

from maglev_ros.discrepancy.diagnose import DiagnoseConfig  # noqa: E402
from maglev_ros.discrepancy.features import BAND_EDGES_HZ  # noqa: E402
from maglev_ros.discrepancy.pipeline.calibrate import calibrate  # noqa: E402

CORNER_HZ = 60.0


def _low_passed(rec, sos):
    chs = {n: (replace(c, values=signal.sosfiltfilt(sos, c.values)) if c.group == "guideway_accel" else c)
           for n, c in rec.channels.items()}
    return replace(rec, channels=chs)


@pytest.fixture(scope="module")
def case():
    return make_case("band", None, {}, seed=7, speeds=(24.0, 30.0),
                     variant={"n_el": 20, "noise_colour": "white", "ambient_s": 8.0}, n_spans=2,
                     design_error={"E": 0.04, "kb": 0.1, "kp": 0.04})


@pytest.fixture(scope="module")
def filtered(case):
    """The case with its guideway accelerometers low-passed, calibrated; and the filter's half-power frequency."""
    fs = case.passes[0].channels[next(n for n, c in case.passes[0].channels.items()
                                      if c.group == "guideway_accel")].sample_rate_hz
    sos = signal.butter(4, CORNER_HZ, fs=fs, output="sos")
    f = np.linspace(1.0, fs / 2, 4000)
    _, h = signal.sosfreqz(sos, worN=f, fs=fs)
    power = np.abs(h) ** 4                                 # zero-phase: the filter twice, power squared
    ambient = _low_passed(case.ambient, sos)
    return calibrate([_low_passed(p, sos) for p in case.passes], ambient, DiagnoseConfig()), ambient, \
        float(f[np.argmax(power < 0.5)])


def test_a_low_passed_group_is_compared_below_its_half_power_band(filtered):
    cal, _, f_half = filtered
    limits = cal.prepare.band_limits
    assert limits and {g for _, g in limits} == {"guideway_accel"}
    k_half = np.searchsorted(BAND_EDGES_HZ, f_half)         # edge index just above the half-power frequency
    for lim in limits.values():
        k = int(np.argmin(np.abs(BAND_EDGES_HZ - lim.upper_hz)))
        assert abs(k - k_half) <= 1, (lim.upper_hz, f_half)
    rd = cal.data.rd_all[0]
    for n, c in rd.rec.channels.items():
        top = BAND_EDGES_HZ[1:][rd.masks[n]].max()
        assert (top <= max(lim.upper_hz for lim in limits.values())) == (c.group == "guideway_accel"), n


def test_the_ambient_recording_is_compared_below_the_passes_limit(filtered):
    from maglev_ros.discrepancy.pipeline.localize import localize
    cal, ambient, f_half = filtered
    upper = min(lim.upper_hz for lim in cal.prepare.band_limits.values())
    rd = localize(cal, ambient, DiagnoseConfig()).ambient
    tops = [BAND_EDGES_HZ[1:][rd.masks[n]].max() for n, c in rd.rec.channels.items()
            if c.group == "guideway_accel" and rd.masks[n].any()]
    assert tops and max(tops) <= upper + 1e-9 < BAND_EDGES_HZ[-1]


def test_an_unfiltered_line_keeps_every_band(case):
    cal = calibrate(case.passes, case.ambient, DiagnoseConfig())
    assert cal.prepare.band_limits == {}



def test_reprojection_without_rows_is_the_least_squares_solution_of_the_rest(case):
    """reprojected_without: one Gauss-Newton step from the calibration = numpy's least squares on the kept rows
    with the calibration's prior rows (a linear residual r(th) = r0 + J (th - th0) is exact for it)."""
    from maglev_ros.discrepancy.fitting import CAL_HI, CAL_LO, PRIOR_SIGMA, BaseFit, reprojected_without
    from maglev_ros.discrepancy.model import base_spec
    rng = np.random.default_rng(3)
    spec0 = base_spec(case.passes[0].metadata)
    th0 = np.array([0.05, 0.2, -0.03, 0.04, 0.02])
    jac, r0 = rng.standard_normal((40, 5)), 0.1 * rng.standard_normal(40)
    base = BaseFit(spec0.with_(cal=tuple(th0)), th0, jac, r0, 0)
    drop = np.zeros(40, bool)
    drop[25:] = True
    got = np.array(reprojected_without(base, drop).cal)
    lam = 0.02 / PRIOR_SIGMA
    a = np.vstack([jac[~drop], lam * np.eye(5)])
    b = np.concatenate([-(r0[~drop] - jac[~drop] @ th0), np.zeros(5)])
    ref = np.linalg.lstsq(a, b, rcond=None)[0]
    assert np.all(CAL_LO < ref) and np.all(ref < CAL_HI)
    assert np.allclose(got, ref, atol=1e-10)
