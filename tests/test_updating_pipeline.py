"""``maglev-ros update`` end to end on small simulated recordings whose hidden truth differs from the
nominal design (E, rho, kb within +-15 %, gains 20-30 % off so that the nominal magnet model is
clearly worse than the noise floor), and the held-out criterion on a second pass.

References are the simulator's truth sidecars (<BAG>.truth.json: true modes of the instrumented
span, true design), never our own output."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from maglev_ros.twin.simulate import Scenario, load_scenario, simulate

NOMINAL = {"guideway": {"youngs_modulus_pa": 3.9e10, "density_kg_m3": 2500.0, "area_m2": 1.48,
                        "second_moment_m4": 0.457, "bearing_stiffness_n_per_m": 3.0e10, "damping_ratio": 0.02},
           "levitation": {"static_current_a": 25.0, "kp_a_per_m": 6500.0, "kv_a_s_per_m": 35.0, "ka_a_s2_per_m": 0.25}}
TRUTH = {"guideway": {"youngs_modulus_pa": 3.9e10 * 1.10, "density_kg_m3": 2500.0 * 0.93,
                      "bearing_stiffness_n_per_m": 3.0e10 * 1.12},
         "levitation": {"kp_a_per_m": 6500.0 * 1.25, "kv_a_s_per_m": 35.0 * 0.78, "ka_a_s2_per_m": 0.25 * 1.2}}


def _bag(tmp, name, kind, truth=None, **over):
    sc = load_scenario("paper-ambient" if kind == "ambient" else "paper")
    raw = dict(sc.raw)
    raw.update({"design": NOMINAL, "truth": truth or TRUTH, "line": {"n_spans": 3, "span_length_m": 12.384,
                                                              "instrumented_span": "S2"}})
    if kind == "pass":      # ~10.7 s: profile_for_twin needs >= ~5 s; ~8 s per magnet pin the gains
        raw.update({"lead_in_s": 3.0, "free_decay_s": 3.0,
                    "rates": {"guideway_hz": 1000, "vehicle_hz": 1000, "position_hz": 100, "oversample": 4}})
    raw.update(over)
    out = tmp / name
    simulate(Scenario.from_dict(raw, name=name), out)
    return out


@pytest.fixture(scope="module")
def bags(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("upd")
    return {"amb": _bag(tmp, "amb", "ambient", duration_s=60.0, seed=5),
            "p1": _bag(tmp, "p1", "pass", seed=21, speed_mps=6.944),
            "p2": _bag(tmp, "p2", "pass", seed=22, speed_mps=8.0)}


@pytest.fixture(scope="module")
def result(bags, tmp_path_factory):
    out = tmp_path_factory.mktemp("res")
    cmd = [sys.executable, "-m", "maglev_ros.cli", "update", "--ambient", str(bags["amb"]), "--pass", str(bags["p1"]),
           "--out", str(out / "params.json"), "--plot", str(out / "plots"), "--samples", "10",
           "--polish-evals", "10", "--swarm", "40", "40", "--details", str(out / "details.json")]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    print(r.stdout)
    return json.loads((out / "params.json").read_text()), out


def test_command_schema_and_frequencies_vs_truth(bags, result):
    doc, out = result
    assert set(doc) == {"schema", "parameters", "identifiable_combinations", "frequencies_hz", "mac", "magnet_accel_nrmse"}
    assert doc["schema"] == "maglev-params/1"
    for name, p in doc["parameters"].items():
        assert set(p) == {"value", "unit", "std", "identifiable"}
        assert isinstance(p["value"], float) and isinstance(p["unit"], str) and isinstance(p["identifiable"], bool)
        assert p["std"] is None or isinstance(p["std"], float)
    for c in doc["identifiable_combinations"]:
        assert set(c) == {"expression", "value", "std"}
    assert set(doc["magnet_accel_nrmse"]) == {"nominal", "updated"}
    true_f = np.array(json.loads(Path(str(bags["amb"]) + ".truth.json").read_text())["instrumented_span"]["freq_hz"])
    fu = np.array(doc["frequencies_hz"]["updated"])
    fn = np.array(doc["frequencies_hz"]["nominal"])
    ref = true_f[: fu.size]
    assert fu.size >= 2
    assert np.all(np.abs(fu / ref - 1) < np.abs(fn / ref - 1))          # closer to the truth than nominal
    assert np.max(np.abs(fu / ref - 1)) < 0.005                          # done-when: within 0.5 %
    assert min(doc["mac"]["updated"]) > 0.99
    for f in ("pareto.png", "frequencies.png", "magnet_accel.png"):
        assert (out / "plots" / f).stat().st_size > 10_000


def test_identifiable_combinations_and_static_pinned_values(result):
    doc, _ = result
    tg = {k: NOMINAL["guideway"][k] for k in NOMINAL["guideway"]} | TRUTH["guideway"]
    tl = NOMINAL["levitation"] | TRUTH["levitation"]
    true = {"E/rho": tg["youngs_modulus_pa"] / tg["density_kg_m3"],
            "kp/I0": tl["kp_a_per_m"] / tl["static_current_a"], "kv/I0": tl["kv_a_s_per_m"] / tl["static_current_a"],
            "ka/I0": tl["ka_a_s2_per_m"] / tl["static_current_a"]}
    combos = {c["expression"]: c["value"] for c in doc["identifiable_combinations"]}
    assert abs(combos["E/rho"] / true["E/rho"] - 1) < 0.02
    p = doc["parameters"]
    # the passes' midspan displacement pins the scale: E and rho identifiable on their own
    assert p["youngs_modulus_pa"]["identifiable"] and p["density_kg_m3"]["identifiable"]
    assert abs(p["youngs_modulus_pa"]["value"] / tg["youngs_modulus_pa"] - 1) < 0.02
    assert abs(p["density_kg_m3"]["value"] / tg["density_kg_m3"] - 1) < 0.02


def _exponents(expr: str) -> dict:
    """'kp^1.00 kv^-0.10 ka^-0.22' -> {'kp': 1.0, 'kv': -0.1, 'ka': -0.22}; 'kp/I0' -> {'kp': 1, 'I0': -1}."""
    if "/" in expr:
        a, b = expr.split("/")
        return {a: 1.0, b: -1.0}
    return {t.split("^")[0]: float(t.split("^")[1]) for t in expr.split()}


def test_gains_within_5pct_where_identifiable_and_std_covers_error(result):
    """Gains given I0 (the design's static current): within 5 % of the truth where the layer says
    they are identifiable; for every gain the stated std (sandwich + between-band model error)
    covers the actual error: |estimate - truth| / std of order 1. Every reported magnet
    combination (well-determined direction) holds the truth within 3 std."""
    doc, out = result
    det = json.loads((out / "details.json").read_text())
    assert det["provenance"]["passes"][0]["irregularity"]["method"] == "irregularity.twin_input.profile_for_twin"
    p = doc["parameters"]
    tl = NOMINAL["levitation"] | TRUTH["levitation"]
    n_ident = 0
    for k in ("kp_a_per_m", "kv_a_s_per_m", "ka_a_s2_per_m"):
        err = p[k]["value"] / tl[k] - 1
        assert p[k]["std"] is not None and p[k]["std"] > 0
        assert abs(p[k]["value"] - tl[k]) / p[k]["std"] < 3.0, (k, err, p[k]["std"] / p[k]["value"])
        if p[k]["identifiable"]:
            n_ident += 1
            assert abs(err) < 0.05, (k, err)
        # a gain not identifiable alone is judged by its stated std (above; it moved 8 -> 11 % with the
        # twin's input read finer, std 25 %) and by the combinations it enters (below); the std must
        # still say something
        assert p[k]["std"] / p[k]["value"] < 0.5, (k, p[k]["std"] / p[k]["value"])
    assert p["static_current_a"]["identifiable"] is False
    sym = {"kp": tl["kp_a_per_m"], "kv": tl["kv_a_s_per_m"], "ka": tl["ka_a_s2_per_m"], "I0": tl["static_current_a"]}
    n_mag = 0
    for c in doc["identifiable_combinations"]:
        ex = _exponents(c["expression"])
        if not set(ex) <= set(sym) or not set(ex) & {"kp", "kv", "ka"}:
            continue
        n_mag += 1
        # the printed expression IS the combination: its value follows from the reported values
        fitted = {"kp": p["kp_a_per_m"]["value"], "kv": p["kv_a_s_per_m"]["value"],
                  "ka": p["ka_a_s2_per_m"]["value"], "I0": p["static_current_a"]["value"]}
        assert c["value"] == pytest.approx(float(np.prod([fitted[k] ** v for k, v in ex.items()])), rel=1e-9), c
        truth = float(np.prod([sym[k] ** v for k, v in ex.items()]))
        assert abs(np.log(c["value"] / truth)) < 3 * c["std"] / c["value"] + 2e-3, (c, truth)
        assert abs(c["value"] / truth - 1) < 0.02, (c, truth)       # done-when: identifiable combinations within 2 %
    assert n_ident + n_mag >= 1          # the data determine something about the gains, and say what


def test_heldout_pass_magnet_nrmse(bags, result):
    """Parameters from pass 1 predict a HELD-OUT pass (other irregularity seed and speed); each
    model gets the irregularity reconstructed with its own twin."""
    from maglev_ros.twin.design import twin_config_from_metadata, with_guideway, with_levitation
    from maglev_ros.updating.pipeline import magnet_nrmse, pass_evidence, read_pass
    doc, _ = result
    p = {k: v["value"] for k, v in doc["parameters"].items()}
    rec = read_pass(bags["p2"])
    nom = twin_config_from_metadata(rec.md.raw)
    up = with_levitation(with_guideway(nom, **{k: p[k] for k in ("youngs_modulus_pa", "density_kg_m3",
                                                                 "bearing_stiffness_n_per_m")}),
                         **{k: p[k] for k in ("kp_a_per_m", "kv_a_s_per_m", "ka_a_s2_per_m")})
    line = rec.md.raw["line"]
    e_nom = magnet_nrmse(nom, line, [pass_evidence(rec, nom, line)])[0]
    e_up = magnet_nrmse(up, line, [pass_evidence(rec, up, line)])[0]
    assert e_up <= 0.15 and e_up <= 0.5 * e_nom, (e_nom, e_up)


def test_bad_inputs_one_line_errors(bags, tmp_path, capsys):
    from maglev_ros.cli import main      # in-process (the CLI as a subprocess is covered by ``result``)

    def run(*a):
        capsys.readouterr()
        code = main(["update", *a, "--out", str(tmp_path / "x.json")])
        return code, capsys.readouterr().err.strip()
    code, err = run("--ambient", str(bags["p1"]))
    assert code == 1 and "run.kind is 'pass'" in err and len(err.splitlines()) == 1
    code, err = run("--ambient", str(bags["amb"]), "--pass", str(bags["amb"]))
    assert code == 1 and len(err.splitlines()) == 1
    code, err = run("--ambient", str(tmp_path / "nope"))
    assert code == 1 and "no such bag" in err


def test_fast_pass_compares_only_above_the_noise_floor(tmp_path):
    """A 9 m/s pass with another truth (gains -28/+10/-25 %, E/rho/kb -13/+12/+14 %): its compared band
    (1 Hz to v / 8 cm = 112 Hz) reaches where the magnets measure only their noise floor; compared
    there, the twin on the reconstructed rail fitted noise and every gain came out unidentifiable
    (std 42-251 %, updated NRMSE 0.078). Every combination reported identifiable must hold the truth
    within 2 %, and the update must fit the magnets well (NRMSE <= 0.05 and <= 0.2 x the nominal's)."""
    truth = {"guideway": {"youngs_modulus_pa": 3.9e10 * 0.87, "density_kg_m3": 2500.0 * 1.12,
                          "bearing_stiffness_n_per_m": 3.0e10 * 1.14},
             "levitation": {"kp_a_per_m": 6500.0 * 0.72, "kv_a_s_per_m": 35.0 * 1.1, "ka_a_s2_per_m": 0.25 * 0.75}}
    amb = _bag(tmp_path, "amb", "ambient", truth, duration_s=60.0, seed=151)
    p1 = _bag(tmp_path, "p1", "pass", truth, seed=51, speed_mps=9.0)
    tl = NOMINAL["levitation"] | truth["levitation"]
    out = tmp_path / "params.json"
    r = subprocess.run([sys.executable, "-m", "maglev_ros.cli", "update", "--ambient", str(amb), "--pass", str(p1),
                        "--out", str(out), "--samples", "10", "--polish-evals", "10", "--swarm", "40", "40"],
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    doc = json.loads(out.read_text())
    sym = {"kp": tl["kp_a_per_m"], "kv": tl["kv_a_s_per_m"], "ka": tl["ka_a_s2_per_m"], "I0": tl["static_current_a"]}
    for c in doc["identifiable_combinations"]:
        ex = _exponents(c["expression"])
        if set(ex) <= set(sym):
            true_value = float(np.prod([sym[k] ** v for k, v in ex.items()]))
            assert abs(c["value"] / true_value - 1) < 0.02, (c, true_value)
    e = doc["magnet_accel_nrmse"]
    assert e["updated"] <= 0.05 and e["updated"] <= 0.2 * e["nominal"], e
    kp = doc["parameters"]["kp_a_per_m"]
    assert kp["std"] < 0.15 * kp["value"], kp                 # was 42 % when noise was compared
    assert abs(kp["value"] / tl["kp_a_per_m"] - 1) < 2 * kp["std"] / kp["value"], kp


def test_passes_over_one_rail_share_its_short_waves_and_a_heldout_pass_is_judged(bags, tmp_path):
    """Two passes over the SAME rail (the first pass's true profile replayed at another speed, other
    noise) share their short waves (a pass over another rail is not shared with:
    tests/test_irregularity_rail_gain.py). Sharing changes the
    twin's input only at the level of the gap noise (5 um rms here; on a foreign simulator's passes,
    whose rail has short waves, it took the held-out magnet NRMSE of the true gains 0.140 -> 0.106).
    The held-out pass is judged, never fitted."""
    from maglev_ros.twin.design import twin_config_from_metadata
    from maglev_ros.twin.simulate import truth_paths
    from maglev_ros.updating.pipeline import pass_evidences, read_pass, update_from_bags, update_layers
    _, csv_p1 = truth_paths(bags["p1"])
    p3 = _bag(tmp_path, "p3", "pass", seed=23, speed_mps=6.0, irregularity={"csv": str(csv_p1)})
    recs = [read_pass(bags["p1"]), read_pass(p3)]
    line = recs[0].md.raw["line"]
    cfg = twin_config_from_metadata(recs[0].md.raw)
    own = [pass_evidences([r], cfg, line)[0] for r in recs]
    assert all(r.info["irregularity"]["shared"] is None for r in recs)
    shared = pass_evidences(recs, cfg, line)
    assert all(r.info["irregularity"]["shared"]["used"] for r in recs)
    for a, b in zip(own, shared):
        d = np.abs(a.irregularity_m - b.irregularity_m)
        assert 0 < d.max() < 5e-6

    gl, ml = update_layers(samples=10, polish_evals=10, swarm=(40, 40))
    up = update_from_bags(bags["amb"], [bags["p1"]], heldout=[p3], guideway_layer=gl, magnet_layer=ml)
    h = up.provenance["heldout"]
    assert h["passes"] == ["p3"] and h["updated"] < h["nominal"]
    assert [r["bag"] for r in up.provenance["passes"]] == [str(bags["p1"])]      # fitted on p1 alone
    # its plot: the held-out pass's measured accelerations and both twins', the NRMSE in the title
    from maglev_ros.updating.plot import save_update_plots
    paths = save_update_plots(up, tmp_path / "plots")
    assert str(tmp_path / "plots" / "magnet_accel_heldout.png") in paths
    assert (tmp_path / "plots" / "magnet_accel_heldout.png").stat().st_size > 10_000
    t, meas, nom, upd, mags = up.heldout_series["p3"]
    ok = np.isfinite(meas)
    assert np.sqrt(np.mean((upd[ok] - meas[ok]) ** 2)) < np.sqrt(np.mean((nom[ok] - meas[ok]) ** 2))
