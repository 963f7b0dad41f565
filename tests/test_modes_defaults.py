"""``maglev-ros modes`` with no options on recordings it did not make (issue 25, item 4).

References are independent of our output: the weimar-frame README's table (koma-python SSI-cov,
a peer), the partner simulator's ``truth.json`` (``s3_modes_hz``), and the sample bags' truth
sidecars (FE modes of the instrumented span). Shared data sit next to the repo (``../shared``);
tests that need them skip when it is absent.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from frame_data import (FRAME_DIR, FRAME_EXTRA_HZ, FRAME_FS_HZ, FRAME_REFERENCE_HZ, PARTNER_SIM,
                        write_frame_bag)
from maglev_ros.cli import main
from maglev_ros.modal.bands import FMAX_FRACTION, LAG_FRACTION, MAX_BAND_RATIO, PERIODS, plan_bands

BAGS = Path(__file__).resolve().parents[1] / "bags"
# the partner's README: Rayleigh damping 2 % on modes 1-2
PARTNER_ZETA = 0.02


def _modes(bag, tmp_path, capsys, *opts):
    out = tmp_path / f"{Path(bag).name}.json"
    assert main(["modes", str(bag), "--json", str(out), *opts]) == 0
    return json.loads(out.read_text()), capsys.readouterr().out


def _freqs(doc) -> np.ndarray:
    return np.array([m["frequency_hz"] for m in doc["modes"]])


def _nearest_rel(f: np.ndarray, f0: float) -> float:
    return float(np.min(np.abs(f - f0)) / f0) if f.size else np.inf


# ----------------------------------------------------------------------------- the rules
@pytest.mark.parametrize("fs_hz, duration_s, n_ch", [(256.0, 240.0, 5), (1000.0, 100.0, 10),
                                                     (2000.0, 5.9, 10), (500.0, 30.0, 15)])
def test_plan_follows_its_stated_rules(fs_hz, duration_s, n_ch):
    n = int(fs_hz * duration_s)
    plan = plan_bands(fs_hz, n, n_ch)
    assert plan.fmax_hz == pytest.approx(FMAX_FRACTION * fs_hz)
    assert plan.fmin_hz == pytest.approx(max(1.0, 2 * PERIODS / (LAG_FRACTION * duration_s)))
    cores = [b.core_hz for b in plan.bands]
    assert cores[0][0] == pytest.approx(plan.fmin_hz)
    assert cores[-1][1] == pytest.approx(plan.fmax_hz)
    for (_, hi), (lo, _) in zip(cores[:-1], cores[1:]):
        assert hi == pytest.approx(lo)                           # contiguous
    for b in plan.bands:
        assert b.core_hz[1] / b.core_hz[0] <= MAX_BAND_RATIO * (1 + 1e-9)
        assert b.search_hz[1] <= FMAX_FRACTION * b.fs_hz * (1 + 1e-9)     # below the band's corner
        assert b.fs_hz == pytest.approx(fs_hz / b.decimation)
        assert (2 * b.block_rows) / b.fs_hz <= LAG_FRACTION * duration_s * (1 + 1e-9)
        # the lags span PERIODS periods of the band's lowest frequency (to one sample)
        assert b.block_rows / b.fs_hz >= PERIODS / b.search_hz[0] - 1.0 / b.fs_hz
        assert 2 <= b.max_order <= min(n_ch * b.block_rows, 100)


def test_plan_given_settings_override():
    plan = plan_bands(256.0, 61440, 5, fmin_hz=0.5, fmax_hz=11.0, block_rows=40, max_order=100,
                      decimate_to_hz=28.0)
    assert len(plan.bands) == 1
    b = plan.bands[0]
    assert (b.fs_hz, b.block_rows, b.max_order) == (pytest.approx(256.0 / 9), 40, 100)
    assert b.core_hz == (0.5, 11.0)
    assert {plan.sources[k] for k in ("fmin_hz", "fmax_hz", "block_rows", "max_order")} == {"user"}


# -------------------------------------------------------------------- measured steel frame
@pytest.fixture(scope="module")
def frame_bag(tmp_path_factory):
    if not FRAME_DIR.exists():
        pytest.skip(f"{FRAME_DIR} not available")
    return write_frame_bag(tmp_path_factory.mktemp("frame") / "frame1", setup=1)


def test_frame_all_eight_reference_modes_with_defaults(frame_bag, tmp_path, capsys):
    doc, out = _modes(frame_bag, tmp_path, capsys)
    f = _freqs(doc)
    for f0 in FRAME_REFERENCE_HZ:
        assert _nearest_rel(f, f0) < 0.01, (f0, f)
    # nothing the README does not list: each mode is a reference one or one of the four > 11 Hz
    known = np.concatenate([FRAME_REFERENCE_HZ, FRAME_EXTRA_HZ])
    for fi in f:
        assert _nearest_rel(known, fi) < 0.01, (fi, f)
    s = doc["source"]["settings"]
    assert s["fmax_hz"] == pytest.approx(FMAX_FRACTION * FRAME_FS_HZ)
    assert s["fmin_hz"] == pytest.approx(1.0)
    assert "user" not in s["sources"].values()
    assert len(s["bands"]) >= 2 and "band 1:" in out and "block rows" in out


def test_frame_explicit_flags_override(frame_bag, tmp_path, capsys):
    doc, out = _modes(frame_bag, tmp_path, capsys, "--fmin-hz", "0.5", "--fmax-hz", "11",
                      "--decimate-to-hz", "28", "--block-rows", "40")
    s = doc["source"]["settings"]
    assert len(s["bands"]) == 1
    assert s["bands"][0]["fs_hz"] == pytest.approx(FRAME_FS_HZ / 9)
    assert s["bands"][0]["block_rows"] == 40
    f = _freqs(doc)
    assert np.all((f >= 0.5) & (f <= 11.0))
    for f0 in FRAME_REFERENCE_HZ:
        assert _nearest_rel(f, f0) < 0.01, (f0, f)


# ---------------------------------------------------------------------- bundled sample bags
@pytest.mark.parametrize("name", ["paper_ambient", "paper_pass", "paper_pass2"])
def test_sample_bags_with_defaults(name, tmp_path, capsys):
    truth = json.loads((BAGS / f"{name}.truth.json").read_text())["instrumented_span"]
    f_true, z_true = np.array(truth["freq_hz"]), np.array(truth["damping_ratio"])
    doc, _ = _modes(BAGS / name, tmp_path, capsys)
    f = _freqs(doc)
    fmax = doc["source"]["settings"]["fmax_hz"]
    ambient = doc["source"]["run_kind"] == "ambient"
    for f0, z0 in zip(f_true[:2], z_true[:2]):
        # ambient: 0.5 %; a free decay of a few seconds: within the half-power half-width zeta f
        assert _nearest_rel(f, f0) < (0.005 if ambient else z0), (f0, f)
    for fi in f:                                   # no mode the FE model does not have
        assert _nearest_rel(f_true[f_true < 1.2 * fmax], fi) < 0.02, (fi, f_true)


# ------------------------------------------------------------------ partner's simulator
PARTNER_CASES = [f"H{k:02d}" for k in range(1, 15)]


@pytest.mark.parametrize("case", PARTNER_CASES)
@pytest.mark.parametrize("kind", ["ambient", "pass"])
def test_partner_sim_first_modes_with_defaults(case, kind, tmp_path, capsys):
    d = PARTNER_SIM / case
    if not (d / kind).exists():
        pytest.skip(f"{d / kind} not available")
    truth = json.loads((d / "truth.json").read_text())["s3_modes_hz"]["truth"]
    doc, _ = _modes(d / kind, tmp_path, capsys)
    f = _freqs(doc)
    # ambient (100 s): 1 %; a free decay of a few seconds: within the half-power half-width
    assert _nearest_rel(f, truth[0]) < (0.01 if kind == "ambient" else PARTNER_ZETA), (truth[0], f)


def _two_channel_result(modes):
    """A ModalResult on channels a, b of ``modes`` ((frequency_hz, shape)), for the band merge."""
    from maglev_ros.modal.ssi_cov import ModalResult, Mode
    ms = tuple(Mode(f"M{k + 1}", f, 0.01, {"a": s[0], "b": s[1]}, 1.0, 0.0, 0.001, 0.001)
               for k, (f, s) in enumerate(modes))
    return ModalResult(ms, None, None, 100.0, ("a", "b"),
                       complex_shapes=tuple(np.array(s, complex) for _, s in modes))


def test_merge_keeps_one_estimate_of_a_mode_found_in_two_bands():
    """A mode in the overlap of two bands is reported once, from the band it lies deeper in;
    a close mode with another shape is kept."""
    from maglev_ros.modal.bands import Band, BandResult, merge_band_results
    low = Band((1.0, 10.0), (1.0, 11.5), 25.0, 40, 50, 40, 10)
    high = Band((10.0, 100.0), (8.7, 100.0), 250.0, 4, 50, 40, 10)
    same = (1.0, 1.0)
    other = (1.0, -1.0)
    res = merge_band_results([
        BandResult(low, _two_channel_result([(3.0, same), (9.2, same)])),             # 9.2: near low's top
        BandResult(high, _two_channel_result([(9.25, same), (9.3, other), (40.0, same)]))])
    f = [m.frequency_hz for m in res.modes]
    # 9.2 Hz lies inside the low band's core, 9.25 Hz in the high band's overlap (outside its core)
    assert f == [3.0, 9.2, 9.3, 40.0]
    assert [m.id for m in res.modes] == ["M1", "M2", "M3", "M4"]


def test_merge_drops_the_edge_copy_of_a_mode_the_next_band_owns():
    """A mode just beyond a band's search edge leaves a copy in that band's overlap margin, off by the
    edge (the band's own estimate is outside its core); the band whose core holds it has the mode: one
    estimate, the owner's. A margin mode with another shape is a mode of its own and stays."""
    from maglev_ros.modal.bands import MARGIN, Band, BandResult, merge_band_results
    low = Band((1.0, 10.0), (1.0, 11.5), 25.0, 40, 50, 40, 10)
    high = Band((10.0, 100.0), (8.7, 100.0), 250.0, 4, 50, 40, 10)
    same, other = (1.0, 0.6), (1.0, -1.0)
    f_copy, f_own = 10.9, 11.4               # 4.6 % apart: beyond the 2 % of two interior estimates
    assert 1.02 < f_own / f_copy < MARGIN
    res = merge_band_results([BandResult(low, _two_channel_result([(3.0, same), (f_copy, same), (10.6, other)])),
                              BandResult(high, _two_channel_result([(f_own, same), (40.0, same)]))])
    assert [m.frequency_hz for m in res.modes] == [3.0, 10.6, f_own, 40.0]


# ------------------------------------------------------------- identical spans, each instrumented
def test_identical_spans_each_with_sensors_get_their_own_modes(tmp_path, capsys):
    """Three decoupled spans of one design ring at one frequency: the joint identification's poles are
    repeated and never stabilize. Each span's sensors are identified alone too; the reference is the
    generator's own FE eigenproblem of the true spans (tests/discrepancy_cases.py)."""
    from discrepancy_cases import make_ambient, write_recording_bag
    rec, modal = make_ambient(None, {}, seed=11, design_error={"E": 0.0, "kb": 0.0, "kp": 0.0},
                              variant={"ambient_rms_mps2": 0.02})
    bag = tmp_path / "three_spans"
    write_recording_bag(rec, bag)
    doc, out = _modes(bag, tmp_path, capsys)
    grouping = doc["source"]["span_groups"]
    assert grouping["identified_apart"] and grouping["weighted_coherence"] <= grouping["chance_99"]
    groups = doc["source"]["channel_groups"]
    assert [g["span"] for g in groups] == ["S1", "S2", "S3"]
    spans = rec.metadata["line"]["spans"]
    for i, g in enumerate(groups):
        mine = [m for m in doc["modes"] if max(abs(m["mode_shape"][c]) for c in g["channels"]) == 1.0]
        # the shape was measured on the span's own sensors: zero elsewhere
        for m in mine:
            assert all(m["mode_shape"][c] == 0.0 for c in m["mode_shape"] if c not in g["channels"])
        f_true = np.sort(modal.freq_hz[modal.span_index == i])[:2]
        f_id = np.array([m["frequency_hz"] for m in mine])
        for f0 in f_true:
            k = int(np.argmin(np.abs(f_id - f0)))
            assert abs(f_id[k] - f0) <= max(3 * mine[k]["std_frequency_hz"], 0.002 * f0), (spans[i]["id"], f0)
            assert abs(mine[k]["damping_ratio"] - 0.02) <= 3 * mine[k]["std_damping_ratio"]
        # and nothing else: a two-sensor group cannot tell a pole on its mode's skirt by shape, the spectrum can
        f_all = np.sort(modal.freq_hz[modal.span_index == i])
        for m in mine:
            assert np.min(np.abs(f_all - m["frequency_hz"]) / f_all) < 0.03, (spans[i]["id"], m["frequency_hz"])
    assert "no stable modes found" not in out
