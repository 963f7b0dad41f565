"""Forms of one levitation effect are told apart where they act.

A transport delay and a first-order lag of the control current change the magnet and gap channels
only; the whole recording also carries what the calibration traded for the effect. The form that
fits the held-out passes best on those channels stands for the effect; other effects, and
hypotheses judged on the whole recording, are left as they are.
"""
from types import SimpleNamespace

from maglev_ros.discrepancy.pipeline.judge import _one_form_per_effect


def _fit(effect, label, category, channels=("M1A", "M8A", "M1G", "M8G")):
    return SimpleNamespace(hyp=SimpleNamespace(effect=effect, label=label, category=category,
                                               location={"channels": list(channels)}))


def test_the_form_that_fits_its_channels_best_stands_for_the_effect():
    delay, lag = _fit("control_delay", "control_delay", "control"), _fit("control_delay", "control_delay.lag", "control")
    zone = _fit("girder_stiffness_loss", "girder_stiffness_loss@S3[6.2-9.3 m]", "guideway_structure")
    # whole held-out NRMSE favours the lag, the magnets' own held-out items the delay
    accepted = [(lag, SimpleNamespace(heldout_after=0.152), -300.0), (zone, SimpleNamespace(heldout_after=0.180), -700.0),
                (delay, SimpleNamespace(heldout_after=0.178), -900.0)]
    local_ev = {id(lag): (0.132, 0.084), id(delay): (0.132, 0.061)}
    kept = _one_form_per_effect(accepted, local_ev)
    assert [t[0] for t in kept] == [zone, delay]


def test_a_single_form_and_whole_recording_hypotheses_are_kept():
    lag = _fit("control_delay", "control_delay.lag", "control")
    sensor = _fit("sensor_error", "sensor_error@M8G", "instrumentation", ("M8G",))
    accepted = [(lag, None, 0.0), (sensor, None, 0.0)]
    assert _one_form_per_effect(accepted, {id(lag): (0.1, 0.05), id(sensor): (0.6, 0.04)}) == accepted


def test_sensor_errors_on_two_channels_are_not_forms_of_one_effect():
    from maglev_ros.discrepancy.pipeline.judge import judged_where_it_acts
    a = _fit("sensor_error", "sensor_error@M8G", "instrumentation", ("M8G",))
    b = _fit("sensor_error", "sensor_error@M1G", "instrumentation", ("M1G",))
    local_ev = {id(a): (0.6, 0.04), id(b): (0.3, 0.2)}
    assert not judged_where_it_acts(a, local_ev)
    accepted = [(a, None, 0.0), (b, None, 0.0)]
    assert _one_form_per_effect(accepted, local_ev) == accepted


def test_levitation_physics_on_top_of_another_effect_keeps_the_gains_it_was_fitted_with():
    import math

    import numpy as np

    from discrepancy_cases import metadata
    from maglev_ros.discrepancy.model import CAL_PARAMS, base_spec
    from maglev_ros.discrepancy.pipeline.judge import combine
    base = base_spec(metadata({}, "pass", 25.0, 2))
    kp, kv, e = CAL_PARAMS.index("kp"), CAL_PARAMS.index("kv"), CAL_PARAMS.index("E")
    # the twin with a structural effect (E re-scaled by its fit) and a delay fitted with lower kp
    now = base.with_(cal=tuple(0.3 if i in (kp, e) else 0.0 for i in range(len(CAL_PARAMS))), span_e_factor=(0.8, 1.0))
    delay_cal = tuple(0.03 if i == kp else (0.02 if i == kv else 0.0) for i in range(len(CAL_PARAMS)))
    hyp = SimpleNamespace(effect="control_delay", category="control",
                          apply=lambda sp, p: sp.with_(control_delay_s=float(p[0])))
    hf = SimpleNamespace(hyp=hyp, params=np.array([0.002]), spec=base.with_(cal=delay_cal, control_delay_s=0.002))
    out = combine(now, hf)
    assert out.control_delay_s == 0.002 and out.span_e_factor == (0.8, 1.0)
    assert out.cal[kp] == 0.03 and out.cal[kv] == 0.02 and out.cal[e] == 0.3
    assert math.isclose(out.cal_factor("kp"), math.exp(0.03))
    # physics of the guideway keeps the twin's gains
    zone = SimpleNamespace(hyp=SimpleNamespace(effect="girder_stiffness_loss", category="guideway_structure",
                                               apply=lambda sp, p: sp.with_(span_e_factor=(1.0, float(p[0])))),
                           params=np.array([0.7]), spec=base)
    assert combine(now, zone).cal == now.cal


def test_the_shortest_delay_that_counts_is_a_sample_or_a_control_period():
    """Below one sample period of the vehicle channels a delay is no finding, but a recording slower
    than a levitation controller (250 Hz: 4 ms samples) does not make a 2.3 ms delay the controller's
    own: its phase at the magnets' 60 Hz band is 2 pi 60 0.0023 = 50 degrees."""
    from maglev_ros.discrepancy.catalogue import CONTROL_PERIOD_S, control_delay_hypothesis
    for fs, tau, counts in ((250.0, 2.3e-3, True), (250.0, 0.9e-3, False), (1000.0, 0.8e-3, False),
                            (1000.0, 1.2e-3, True), (2000.0, 0.6e-3, True), (2000.0, 0.4e-3, False)):
        for form in ("delay", "lag"):
            ok, why = control_delay_hypothesis(["M1A"], form, fs).plausible([tau])
            assert ok is counts, (fs, tau, form, why)
            if not ok:
                floor_ms = min(1.0 / fs, CONTROL_PERIOD_S) * 1e3
                assert f"{floor_ms:.2f} ms" in why
