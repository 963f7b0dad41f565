"""Which structure the diagnosis tests, and how a found attachment is reported."""
import json
from pathlib import Path

import numpy as np
import pytest

from maglev_ros.discrepancy.acceptance import Verdict
from maglev_ros.discrepancy.attachment import Resonator
from maglev_ros.discrepancy.pipeline.report import _resonator_entry
from maglev_ros.discrepancy.pipeline.propose import structural_hypotheses
from maglev_ros.discrepancy.model import base_spec
from maglev_ros.discrepancy.recording import recording_from_arrays
from maglev_ros.discrepancy.resonator import ResonatorFit

L = 12.384
SHARED = Path(__file__).resolve().parents[2] / "shared"


def _line_with_sensors_on(span_ids):
    spans = [{"id": f"S{i + 1}", "start_m": i * L, "length_m": L} for i in range(5)]
    sensors, signals = {}, {}
    t = np.arange(0.0, 1.0, 1e-3)
    for k, sid in enumerate(span_ids):
        i = int(sid[1:]) - 1
        for j, frac in enumerate((0.25, 0.5)):
            n = f"G{k}{j}"
            sensors[n] = {"topic": "/testline/guideway/accel", "quantity": "acceleration", "direction": "vertical",
                          "span": sid, "position_m": (i + frac) * L}
            signals[n] = (t, np.zeros_like(t))
    md = {"schema": "maglev-testline/1", "line": {"spans": spans}, "sensors": sensors, "run": {"kind": "ambient"}}
    return md, recording_from_arrays(md, signals)


def test_structure_is_tested_only_on_spans_with_guideway_sensors():
    md, rec = _line_with_sensors_on(["S3"])
    spec = base_spec(md)
    hyps, unseen = structural_hypotheses(spec, rec, np.full(5, 25.0), zones=True)
    assert unseen == ["S1", "S2", "S4", "S5"]
    # zones only when asked for
    assert not [h for h in structural_hypotheses(spec, rec, np.full(5, 25.0))[0] if h.form == "zone"]
    assert {h.location["span"] for h in hyps} == {"S3"}
    kinds = sorted((h.effect, h.form) for h in hyps)
    # a uniform loss, a zone per quarter, a bearing at each end
    assert kinds.count(("girder_stiffness_loss", "")) == 1
    assert kinds.count(("girder_stiffness_loss", "zone")) == 4
    assert kinds.count(("bearing_stiffness", "")) == 2
    zones = sorted(tuple(h.location["position_m"]) for h in hyps if h.form == "zone")
    assert zones[0] == pytest.approx((2 * L, 2.25 * L)) and zones[-1] == pytest.approx((2.75 * L, 3 * L))
    # both bearings of the measured span, at its ends
    ends = [h for h in hyps if h.effect == "bearing_stiffness"]
    assert sorted(np.mean(h.location["position_m"]) for h in ends) == pytest.approx([2 * L, 3 * L])


def test_every_span_with_sensors_gets_its_hypotheses():
    md, rec = _line_with_sensors_on(["S1", "S2", "S3", "S4", "S5"])
    hyps, unseen = structural_hypotheses(base_spec(md), rec, np.full(5, 25.0))
    assert unseen == [] and {h.location["span"] for h in hyps} == {f"S{i}" for i in range(1, 6)}


def _found_attachment():
    res = Resonator(span_index=2, x_rel_m=6.0, freq_hz=60.0, mass_ratio=0.08, damping_ratio=0.01)
    rf = ResonatorFit(res, "S3", 2 * L + 6.0, 3700.0, (0.0, 0.0, 0.0, 0.0),
                      Verdict(True, (), 0.30, 0.20, -120.0), 40, span_length_m=L)
    d = {"kind": "added_resonator", "explanation": "a 60 Hz spring-mass on S3",
         "frequency_hz": [57.0, 63.0], "residual_band_hz": [52.0, 74.0],
         "model": {**rf.to_dict(), "accepted": True}}
    return rf, d


def test_a_found_attachment_is_a_missing_physics_entry_with_place_band_and_evidence():
    e = _found_attachment()
    entry = _resonator_entry(*e)
    json.dumps(entry)
    assert entry["effect"] == "resonant_attachment" and entry["category"] == "guideway_structure"
    assert entry["out_of_catalogue"] is True
    assert entry["location"]["span"] == "S3"
    lo, hi = entry["location"]["position_m"]
    assert lo <= 2 * L + 6.0 <= hi and 2 * L <= lo and hi <= 3 * L
    assert entry["frequency_hz"] == [57.0, 63.0]
    assert entry["parameters"]["own_frequency_hz"] == 60.0 and entry["parameters"]["mass_kg"] == 3700.0
    assert entry["evidence"]["heldout_nrmse_after"] < entry["evidence"]["heldout_nrmse_before"]


@pytest.mark.skipif(not (SHARED / "validation" / "score.py").exists(), reason="../shared/validation not beside the repo")
def test_the_partners_scorer_reads_a_found_attachment_as_its_attachment():
    import importlib.util
    spec = importlib.util.spec_from_file_location("partner_score", SHARED / "validation" / "score.py")
    score = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(score)
    # the partner's matching rule for an out-of-catalogue attachment on S3 (the scorer's truth format)
    effect = {"match": {"name": None, "categories": ["guideway_structure", "other"],
                        "location": {"kind": "freq_or_span", "span": "S3", "x_m": [2 * L, 3 * L],
                                     "freq_hz": [58.0, 62.8]}}}
    ok, _, why = score.find(effect, [_resonator_entry(*_found_attachment())])
    assert ok, why
