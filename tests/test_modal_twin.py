"""SSI-cov (through ``maglev-ros modes``' core) on the twin's simulated ambient record of the
paper line: the FE modes of the instrumented span (truth sidecar) are the reference."""
from __future__ import annotations

import json

import numpy as np
import pytest

twin_sim = pytest.importorskip("maglev_ros.twin.simulate")


def test_twin_ambient_modes_match_fe_truth(tmp_path):
    bag = tmp_path / "amb"
    twin_sim.simulate(twin_sim.builtin_scenarios()["paper-ambient"], bag,
                      sets=["duration_s=60"], overwrite=True)
    truth = json.loads(twin_sim.truth_paths(bag)[0].read_text())["instrumented_span"]
    from maglev_ros.commands.modes import identify_bag
    res, info = identify_bag(bag, fmin_hz=5.0, fmax_hz=150.0)
    assert info["run_kind"] == "ambient"
    f_true = np.array(truth["freq_hz"])
    z_true = np.array(truth["damping_ratio"])
    inband = (f_true > 5.0) & (f_true < 150.0)
    assert inband.sum() >= 2
    f = res.frequencies_hz()
    assert len(f) == inband.sum()                       # no spurious modes in 5-150 Hz
    for f0, z0 in zip(f_true[inband], z_true[inband]):
        k = int(np.argmin(np.abs(f - f0)))
        m = res.modes[k]
        # 60 s record: 0.5 % or 4 x the reported (block) std, whichever is larger
        assert abs(m.frequency_hz - f0) < max(0.005 * f0, 4 * m.std_frequency_hz)
        assert abs(m.damping_ratio - z0) < 0.006
        # vertical bending: left and right sensors of a section move together
        sh = m.mode_shape
        for j in range(1, 6):
            assert sh[f"G{j}LV"] == pytest.approx(sh[f"G{j}RV"], abs=0.05)


def test_free_decay_of_a_twin_pass_matches_the_ambient_modes(tmp_path):
    """Issue 4: on a twin pass recording, the modes identified from the free decay after the
    vehicle leaves match those from the ambient recording of the same line within 1 %."""
    from maglev_ros.commands.modes import identify_bag
    amb, pas = tmp_path / "amb", tmp_path / "pass"
    sc = twin_sim.builtin_scenarios()
    twin_sim.simulate(sc["paper-ambient"], amb, sets=["duration_s=60"], seed=7, overwrite=True)
    twin_sim.simulate(sc["paper"], pas, seed=8, overwrite=True)
    res_a, _ = identify_bag(amb, fmin_hz=5.0, fmax_hz=150.0)
    res_p, info = identify_bag(pas, fmin_hz=5.0, fmax_hz=150.0)
    assert info["run_kind"] == "pass"
    truth = json.loads(twin_sim.truth_paths(amb)[0].read_text())["instrumented_span"]["freq_hz"]
    for f_true in [f for f in truth if f < 150.0]:
        fa = min((m.frequency_hz for m in res_a.modes), key=lambda f: abs(f - f_true))
        fp = min((m.frequency_hz for m in res_p.modes), key=lambda f: abs(f - f_true))
        assert abs(fa / f_true - 1) < 0.01                    # both are the FE mode ...
        assert abs(fp / fa - 1) < 0.01, (f_true, fa, fp)      # ... and agree within 1 %


@pytest.fixture(scope="module")
def sample_ambient(tmp_path_factory):
    """The sample bag's settings (paper-ambient, 120 s) per seed, each simulated once."""
    bags = {}

    def get(seed):
        if seed not in bags:
            bag = tmp_path_factory.mktemp(f"amb{seed}") / "amb"
            twin_sim.simulate(twin_sim.builtin_scenarios()["paper-ambient"], bag, seed=seed, overwrite=True)
            bags[seed] = bag
        return bags[seed]
    return get


@pytest.mark.parametrize("seed", [2, 4])
def test_no_spurious_mode_on_the_sample_ambient_settings(sample_ambient, seed):
    """Issue 4: the sample bag's settings (paper-ambient, 120 s; seed 2 is bags/paper_ambient,
    seed 4 another realization) gave a stable, 4-9 %-damped mode-1-shaped pole at 30-41 Hz from
    the anti-alias-coloured mass line; the FE modes of the instrumented span are the only modes
    in 5-150 Hz."""
    bag = sample_ambient(seed)
    truth = json.loads(twin_sim.truth_paths(bag)[0].read_text())["instrumented_span"]
    from maglev_ros.commands.modes import identify_bag
    res, _ = identify_bag(bag, fmin_hz=5.0, fmax_hz=150.0)
    f_true = np.array([f for f in truth["freq_hz"] if 5.0 < f < 150.0])
    f = res.frequencies_hz()
    assert len(f) == f_true.size, f
    assert np.all(np.abs(np.sort(f) / f_true - 1) < 0.005), (f, f_true)


def test_every_mode_reported_with_the_defaults_is_a_mode_of_the_line(sample_ambient):
    """The sample ambient settings with the verb's defaults (1-200 Hz, three bands): a pole that
    stabilizes between the first two modes without a spectral peak (30 Hz, 6 % damped, on this
    realization) is not reported; the FE modes of the instrumented span still are."""
    bag = sample_ambient(2)
    truth = json.loads(twin_sim.truth_paths(bag)[0].read_text())["instrumented_span"]
    from maglev_ros.commands.modes import identify_modes
    out = identify_modes(bag)
    f_true = np.array([f for f in truth["freq_hz"] if f < 0.4 * 500.0])
    f = out.result.frequencies_hz()
    assert all(np.min(np.abs(f_true / x - 1)) < 0.01 for x in f), (f, f_true)
    assert all(np.min(np.abs(f / x - 1)) < 0.01 for x in f_true), (f, f_true)
    assert all(np.min(np.abs(f_true / x - 1)) > 0.05 for x in out.info["not_spectral_peaks_hz"])
