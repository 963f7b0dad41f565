"""Acceptance gates on given numbers (maglev_ros.discrepancy.acceptance): the rules, not our output."""
import numpy as np
import pytest

from maglev_ros.discrepancy.acceptance import AcceptanceConfig, judge, judge_where_it_acts

CFG = AcceptanceConfig()      # 5 % and 0.005 held-out gain, LLR >= 10, delta BIC <= -10
OK = (True, "")


def test_judge_needs_every_gate():
    assert judge(0.20, 0.15, -50.0, OK, 0.5, CFG, 40.0).accepted
    v = judge(0.20, 0.195, -50.0, OK, 0.5, CFG, 40.0)          # 2.5 % gain only
    assert not v.accepted and "not a clear improvement" in v.reasons[0]
    assert not judge(0.20, 0.15, -5.0, OK, 0.5, CFG, 40.0).accepted        # BIC
    assert not judge(0.20, 0.15, -50.0, OK, 0.5, CFG, 4.0).accepted        # held-out LLR
    assert not judge(0.20, 0.15, -50.0, (False, "implausible"), 0.5, CFG, 40.0).accepted
    assert not judge(0.20, 0.15, -50.0, OK, 0.99, CFG, 40.0).accepted      # a calibrated parameter


def test_levitation_physics_is_judged_on_its_channels():
    # a control delay: vehicle channels 0.179 -> 0.121, the whole recording 0.153 -> 0.157 (+2.6 %,
    # just over the half-gain tolerance of 2.5 %) -> rejected for the rest of the recording
    v = judge_where_it_acts(0.153, 0.157, 0.179, 0.121, -1400.0, OK, 0.5, CFG, 200.0)
    assert not v.accepted and any("rest of the recording worse" in r for r in v.reasons)
    v = judge_where_it_acts(0.153, 0.156, 0.179, 0.121, -1400.0, OK, 0.5, CFG, 200.0)
    assert v.accepted
    # the verdict carries the whole-recording numbers (effects are ranked on them)
    assert (v.heldout_before, v.heldout_after) == (0.153, 0.156)


def test_levitation_physics_needs_its_own_margin_on_its_few_channels():
    # its channels' NRMSE is small (0.01-0.02 on the magnets' own items): a gain is judged there with
    # the local margins, relative min_rel_gain_local and absolute min_abs_gain_local
    below = 0.020 * (1 - 0.8 * CFG.min_rel_gain_local)
    v = judge_where_it_acts(0.107, 0.105, 0.020, below, -60.0, OK, 0.5, CFG, 30.0)
    assert not v.accepted
    assert any("not a clear improvement" in r and f"{CFG.min_rel_gain_local * 100:.0f} %" in r for r in v.reasons)
    above = 0.020 * (1 - 1.2 * CFG.min_rel_gain_local)
    assert 0.020 - above >= CFG.min_abs_gain_local
    assert judge_where_it_acts(0.107, 0.105, 0.020, above, -60.0, OK, 0.5, CFG, 30.0).accepted
    # the same gain over the whole recording would miss the ordinary absolute margin
    assert not judge(0.020, above, -60.0, OK, 0.5, CFG, 30.0).accepted


def test_levitation_physics_without_a_gain_on_its_channels_is_rejected():
    v = judge_where_it_acts(0.153, 0.150, 0.179, 0.175, -40.0, OK, 0.5, CFG, 3.0)
    assert not v.accepted
    assert any(r.startswith("on its channels: held-out NRMSE") for r in v.reasons)
    assert any(r.startswith("on its channels: held-out log-likelihood") for r in v.reasons)
    # the penalised criterion is given over its channels' rows too, and says so when it fails
    v = judge_where_it_acts(0.153, 0.120, 0.179, 0.100, +242.0, OK, 0.5, CFG, 200.0)
    assert not v.accepted and v.reasons == ("on its channels: delta BIC +242.0 does not beat the calibrated "
                                            "twin (needs <= -10)",)


def test_levitation_physics_names_its_null_model_and_what_would_separate_them():
    # judged against the calibrated twin with kp, kv re-fitted on its channels (the null of levitation
    # physics): a rejection names that reference, and when the held-out gain is not clear, what the
    # gains absorbed and which evidence would tell them apart
    kw = dict(reference="the gains-refitted twin", absorbed_by="kp, kv", separated_by="a faster pass")
    v = judge_where_it_acts(0.114, 0.110, 0.053, 0.049, +5.0, OK, 0.5, CFG, 3.0, **kw)
    assert not v.accepted
    assert "on its channels: delta BIC +5.0 does not beat the gains-refitted twin (needs <= -10)" in v.reasons
    assert v.reasons[-1] == ("on the held-out data kp, kv explain nearly as much: these recordings cannot "
                             "separate them (a faster pass would)")
    # a clear local gain that fails elsewhere does not blame the gains
    v = judge_where_it_acts(0.114, 0.135, 0.053, 0.020, -50.0, OK, 0.5, CFG, 80.0, **kw)
    assert not v.accepted and not any("cannot separate" in r for r in v.reasons)


def _profile(x1, x2, y, grid):
    """RSS of y ~ a x1 + b x2 with b re-fitted at each a (the profile of a)."""
    out = []
    for a in grid:
        r = y - a * x1
        b = float(x2 @ r) / float(x2 @ x2)
        out.append((float(a), float(np.sum((r - b * x2) ** 2))))
    return out


def test_profile_spread_tells_an_absorbed_parameter_from_a_determined_one():
    from maglev_ros.discrepancy.fitting import IDENTIFIABLE_LLR, profile_spread
    rng = np.random.default_rng(3)
    n = 400
    x1 = rng.standard_normal(n)
    noise = 0.5 * rng.standard_normal(n)
    grid = np.linspace(0.0, 2.0, 5)
    # a second regressor equal to the first absorbs any value of a: a flat profile
    y = 1.0 * x1 + noise
    flat = _profile(x1, x1.copy(), y, grid)
    assert profile_spread(flat, n) < 1e-9 < IDENTIFIABLE_LLR
    # an independent second regressor: a is determined. Expected RSS per sample: the noise variance
    # 0.25 at the true a = 1, 0.25 + (a - 1)^2 |x1|^2 / n ~ 1.25 at the grid ends a = 0, 2, so the
    # spread is about 0.5 n ln(1.25 / 0.25)
    x2 = rng.standard_normal(n)
    y = 1.0 * x1 + 0.7 * x2 + noise
    det = _profile(x1, x2, y, grid)
    assert profile_spread(det, n) == pytest.approx(0.5 * n * np.log(1.25 / 0.25), rel=0.1)
    assert profile_spread(det, n) > 50 * IDENTIFIABLE_LLR
    assert profile_spread(det[:1], n) == float("inf")      # one point: nothing to compare


def test_levitation_physics_whose_trade_is_the_gains_is_recalibrated_on_every_channel(monkeypatch):
    """Rejected by the rest-of-recording gate alone, levitation physics is re-calibrated with kp, kv on
    every channel: accepted (and that twin reported) when the whole held-out fit is then not worse
    than the allowance, still rejected otherwise; the gates on its channels are not re-opened."""
    from types import SimpleNamespace as NS

    import maglev_ros.discrepancy.pipeline.fit as D
    from maglev_ros.discrepancy.acceptance import AcceptanceConfig, REST_WORSE, Verdict

    whole = {"value": 0.1045}
    calls = []
    monkeypatch.setattr(D, "residual_vector", lambda sp, rds: np.zeros(5))
    monkeypatch.setattr(D, "fit_gains", lambda b, rds, rows: calls.append(rows.sum()) or NS(
        name="all-rows", calibrated_values=lambda: {"kp_a_per_m": 7000.0, "kv_a_s_per_m": 41.5}))
    monkeypatch.setattr(D, "fit_report", lambda sp, rds: (whole["value"], {}))
    base = NS(spec="base", theta=np.zeros(4), jac=None, r0=None)

    def case():
        hyp = NS(apply=lambda sp, p: "physics", effect="magnet_nonlinearity")
        return NS(hyp=hyp, params=np.array([1.3]), spec="vehicle-rows")
    v = Verdict(False, (f"{REST_WORSE} (whole held-out NRMSE 0.103 -> 0.111)",), 0.1035, 0.111, -39.0)
    hf, v2 = D.recalibrated_whole(base, case(), v, [], [], 0.1035, AcceptanceConfig())
    assert v2.accepted and v2.heldout_after == pytest.approx(0.1045) and hf.spec.name == "all-rows"
    assert calls == [5] and v2.reasons[0].startswith(D.RECALIBRATED) and "0.111" in v2.reasons[0]
    whole["value"] = 0.1035 * 1.03          # worse than the 2.5 % allowance with every channel re-fitted too
    hf, v3 = D.recalibrated_whole(base, case(), v, [], [], 0.1035, AcceptanceConfig())
    assert not v3.accepted and hf.spec == "vehicle-rows" and v3.reasons[0] == v.reasons[0]
    assert "re-calibrated on every channel too" in v3.reasons[-1]
