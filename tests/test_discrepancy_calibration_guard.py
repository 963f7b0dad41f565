"""The calibration guard: a base fit that does worse than the nominal twin on the held-out pass is
refused. The case is clean and simulated at the design values, so the nominal twin is the truth
and a calibration dragged away from it (here forced: E x0.55) must lose on held-out data."""
import os
import sys

import numpy as np
import pytest

sys.path.insert(0, os.path.dirname(__file__))
from discrepancy_cases import make_case  # noqa: E402

from maglev_ros.discrepancy.diagnose import DiagnoseConfig  # noqa: E402
from maglev_ros.discrepancy.evaluate import fit_report  # noqa: E402
from maglev_ros.discrepancy.pipeline import calibrate as calibrate_mod  # noqa: E402


@pytest.fixture(scope="module")
def case():
    return make_case("guard", None, {}, seed=5, speeds=(24.0, 30.0),
                     variant={"n_el": 20, "noise_colour": "white", "ambient_s": 8.0}, n_spans=2)


def test_a_calibration_worse_on_held_out_data_is_refused(case, monkeypatch):
    real_fit_base = calibrate_mod.fit_base

    def dragged(spec, rds, max_nfev=6):
        fb = real_fit_base(spec, rds, max_nfev=1)    # the nominal point and its Jacobian
        if max_nfev == 1:
            return fb
        bad = spec.with_(cal=(float(np.log(0.55)), *spec.cal[1:]))     # E x0.55: what a local fault did
        return calibrate_mod.BaseFit(bad, np.array(bad.cal), fb.jac, fb.r0, fb.n_sims)

    monkeypatch.setattr(calibrate_mod, "fit_base", dragged)
    cal = calibrate_mod.calibrate(case.passes, case.ambient, DiagnoseConfig())
    g = cal.guard
    assert g is not None and g.kept == "nominal"
    assert g.heldout_calibrated > g.heldout_nominal
    assert cal.base.spec.cal == cal.base0.cal
    # the kept twin's fit is the nominal twin's, on the passes as the nominal twin sees them
    assert cal.fit_nrmse == pytest.approx(fit_report(cal.base0, cal.data.rd_all)[0], rel=1e-9)
    assert any("calibration refused" in n for n in cal.notes)


@pytest.mark.slow     # a whole calibration to see a None; the refusal test covers the guard
def test_one_pass_has_no_held_out_check(case):
    cal = calibrate_mod.calibrate(case.passes[:1], case.ambient, DiagnoseConfig())
    assert cal.guard is None
