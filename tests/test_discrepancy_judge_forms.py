"""Forms of one levitation effect are told apart where they act.

A transport delay and a first-order lag of the control current change the magnet and gap channels
only; the whole recording also carries what the calibration traded for the effect. The form that
fits the held-out passes best on those channels stands for the effect; other effects, and
hypotheses judged on the whole recording, are left as they are.
"""
from types import SimpleNamespace

from maglev_ros.discrepancy.pipeline.judge import _one_form_per_effect


def _fit(effect, label, category):
    return SimpleNamespace(hyp=SimpleNamespace(effect=effect, label=label, category=category))


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
    sensor = _fit("sensor_error", "sensor_error@M8G", "instrumentation")
    accepted = [(lag, None, 0.0), (sensor, None, 0.0)]
    assert _one_form_per_effect(accepted, {id(lag): (0.1, 0.05), id(sensor): (0.6, 0.04)}) == accepted
