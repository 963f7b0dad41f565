"""The expensive verbs' independent work on executors: the same results serially, on a 2-worker local
pool and on a Dask client (diagnose: the hypotheses' screening and fits; update: the surrogate's
training simulations). A small generated case keeps it cheap: one span, a coarse twin, no rail
reconstruction, three physics hypotheses and every sensor/ambient one."""
import dataclasses
import json
import os
import sys

import numpy as np
import pytest

sys.path.insert(0, os.path.dirname(__file__))
from discrepancy_cases import make_case  # noqa: E402

from maglev_ros.discrepancy.diagnose import DiagnoseConfig  # noqa: E402
from maglev_ros.discrepancy.pipeline.calibrate import calibrate  # noqa: E402
from maglev_ros.discrepancy.pipeline.fit import fit_hypotheses  # noqa: E402
from maglev_ros.discrepancy.pipeline.localize import localize  # noqa: E402
from maglev_ros.discrepancy.pipeline.propose import propose  # noqa: E402
from maglev_ros.errors import UserError  # noqa: E402
from maglev_ros.parallel import SERIAL, DaskExecutor, LocalPool, executor_from_options, one_blas_thread  # noqa: E402

FAST = {"n_el": 20, "noise_colour": "pink", "ambient_s": 8.0, "aa": ("cheby", 0.38), "body_sensors": False}
CFG = DiagnoseConfig(n_top=6, fit_every_effect=False, irregularity=False, base_max_nfev=2, base_refit_nfev=1,
                     n_elements=8, dt_max_s=2e-3)


@pytest.fixture(scope="module")
def pool():
    with LocalPool(2) as p:
        yield p


@pytest.fixture(scope="module")
def staged():
    case = make_case("cd", "control_delay", {"lag_s": 0.006}, seed=51, speeds=(24.0, 30.0), variant=FAST, n_spans=1)
    with one_blas_thread():
        cal = calibrate(case.passes, case.ambient, CFG)
        loc = localize(cal, case.ambient, CFG)
        prop = propose(cal, loc, CFG)
    # a girder hypothesis, a levitation one (its null model computed where it is fitted) and one whose
    # fit fails on this case (the pure delay form: reported untestable)
    keep = [h for h in prop.fitted_in_full if h.label in ("girder_stiffness_loss@S1", "magnet_nonlinearity",
                                                            "control_delay")]
    assert len(keep) == 3
    return cal, loc, dataclasses.replace(prop, fitted_in_full=keep)


def _square(x):
    return x * x


def test_executors_keep_the_order_and_report_each_item(pool):
    seen = []
    assert pool.map(_square, range(7), done=seen.append) == [x * x for x in range(7)]
    assert sorted(seen) == list(range(7))
    # lambdas travel too (cloudpickle): the catalogue's hypotheses carry them
    assert pool.map(lambda x: -x, [1, 2]) == [-1, -2]
    assert SERIAL.map(_square, [3]) == [9] and pool.map(_square, []) == []


def test_executor_options_are_checked():
    assert executor_from_options(None, None) is SERIAL and executor_from_options(1, None) is SERIAL
    with pytest.raises(UserError, match="--workers"):
        executor_from_options(0, None)
    with pytest.raises(UserError, match="one of them"):
        executor_from_options(2, "tcp://127.0.0.1:1")


def _screening(prop):
    return [(float(r), h.label) for r, h in prop.screened], prop.untestable


def _fits_doc(fr) -> str:
    """Every fit and verdict as JSON (what the later stages read)."""
    fits = [{"label": hf.hyp.label, "params": hf.params.tolist(), "cal_delta": hf.cal_delta.tolist(),
             "rss": hf.rss, "n_sims": hf.n_sims, "profile": list(hf.profile),
             "verdict": dataclasses.asdict(v), "delta_bic": d, "local": fr.local_ev.get(id(hf)),
             "own_rail": id(hf) in fr.own_rail} for hf, v, d in fr.fits]
    return json.dumps({"fits": fits, "untestable": fr.untestable}, sort_keys=True)


def _references(fr):
    """The fitted twins and the reference models, compared by value (their keys hold frozensets, whose
    order, and so repr, differs between processes)."""
    return [hf.spec for hf, _, _ in fr.fits], fr.evidence.nulls, fr.evidence.test0


def test_screening_is_the_same_on_a_local_pool(staged, pool):
    cal, loc, prop = staged
    with one_blas_thread():
        serial = propose(cal, loc, CFG)
    assert _screening(propose(cal, loc, CFG, executor=pool)) == _screening(serial)


def test_hypothesis_fits_are_the_same_serially_and_on_two_workers(staged, pool):
    cal, loc, prop = staged
    with one_blas_thread():
        serial = fit_hypotheses(cal, loc, prop, CFG)
    parallel = fit_hypotheses(cal, loc, prop, CFG, executor=pool)
    doc = _fits_doc(serial)
    assert serial.evidence.nulls, "the levitation hypothesis' null model was computed"
    assert any(u["label"] == "control_delay" for u in json.loads(doc)["untestable"])
    assert _fits_doc(parallel) == doc
    assert _references(parallel) == _references(serial)


def test_screening_is_the_same_on_a_dask_client(staged):
    distributed = pytest.importorskip("distributed")
    cal, loc, prop = staged
    with one_blas_thread():
        serial = propose(cal, loc, CFG)
    with distributed.Client(processes=False, n_workers=1, threads_per_worker=1, dashboard_address=None) as client:
        assert _screening(propose(cal, loc, CFG, executor=DaskExecutor(client))) == _screening(serial)


# --- update: the magnet layer's surrogate samples -------------------------------------------------
def _magnet_doc(up) -> str:
    doc = up.to_dict()
    doc.pop("wall_time_s")                      # the only timing field
    return json.dumps(doc, sort_keys=True, default=lambda a: np.asarray(a).tolist())


def test_magnet_layer_samples_are_the_same_serially_and_on_two_workers(pool):
    from updating_data import LINE, random_truth, simulate_measurement, twin_config, with_guideway
    from maglev_ros.updating.magnet_layer import MagnetLayer, make_evidence
    from maglev_ros.updating.parameters import GUIDEWAY_PARAMS
    nom = twin_config()
    tcfg = random_truth(0).config(nom)
    gcfg = with_guideway(nom, **{k: getattr(tcfg.guideway, k) for k in GUIDEWAY_PARAMS})
    m = simulate_measurement(tcfg, 6.944, 3, 2.0, start_position_m=5.0)
    ev = make_evidence(m["time_s"], m["accel"], range(1, 9), m["time_s"], m["position_m"], m["speed_mps"],
                       m["true_irregularity"], m["offsets"], band_hz=(1.0, 80.0), model_fs_hz=500.0)

    def layer():
        return MagnetLayer(n_samples=8, polish_max_nfev=2, n_particles=10, n_iterations=5, model_error=False)
    with one_blas_thread():
        serial = layer().fit(gcfg, LINE, [ev])
    parallel = layer().fit(gcfg, LINE, [ev], executor=pool)
    assert serial.n_model_evaluations >= 9       # the nominal point and the 8 samples at least
    assert _magnet_doc(parallel) == _magnet_doc(serial)
