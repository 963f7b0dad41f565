"""The accelerometer bias signature (maglev_ros.discrepancy.bias_signature) on generated recordings:
sound sensors of one structure, each with its own mode amplitudes and phases, stay together; a
wandering bias of 0.02-0.04 m/s^2 (a fifth to a half of the channel's vibration RMS) on one stands out, and the RMS of its 1 s means is the injected bias's."""
from __future__ import annotations

import numpy as np
import pytest

from maglev_ros.discrepancy.bias_signature import MIN_LEVEL_RATIO, bias_level, bias_signature
from maglev_ros.discrepancy.recording import Channel, Recording

FS_HZ = 500.0


def _recording(seed: int, duration_s: float, bias: np.ndarray | None = None, n: int = 8,
               group: str = "guideway_accel") -> Recording:
    """``n`` accelerometers on one structure: a burst of its three modes (6.3, 15.7, 24.1 Hz) with
    amplitudes 0.02-0.2 m/s^2 and phases of each sensor's own, plus white noise; A3 gets ``bias``."""
    rng = np.random.default_rng(seed)
    t = np.arange(int(duration_s * FS_HZ)) / FS_HZ
    chans = {}
    for k in range(n):
        env = np.exp(-((t - rng.uniform(0.3, 0.7) * duration_s) / (0.25 * duration_s)) ** 2)
        y = rng.normal(0, 0.003, t.size)
        for f in (6.3, 15.7, 24.1):
            y = y + rng.uniform(0.02, 0.2) * env * np.sin(2 * np.pi * f * t + rng.uniform(0, 2 * np.pi))
        name = f"A{k}"
        if bias is not None and name == "A3":
            y = y + bias[: t.size]
        chans[name] = Channel(name, group, t, y, FS_HZ, position_m=3.0 * k)
    return Recording({}, chans)


def _wandering_bias(seed: int, duration_s: float, rms_mps2: float) -> np.ndarray:
    """A random walk low-passed below 0.5 Hz, scaled to ``rms_mps2``, with a mean of its own."""
    rng = np.random.default_rng(seed)
    from scipy.signal import butter, sosfiltfilt
    w = np.cumsum(rng.normal(0, 1, int(duration_s * FS_HZ)))
    w = sosfiltfilt(butter(2, 0.5, fs=FS_HZ, output="sos"), w)
    w = w - w.mean() + 0.5 * w.std()
    return w * rms_mps2 / np.sqrt(np.mean(w ** 2))


def test_a_sine_over_whole_seconds_has_no_bias_level():
    # a sine with a whole number of periods in every 1 s segment: every mean is 0 (analytic)
    t = np.arange(4000) / 1000.0
    assert bias_level(np.sin(2 * np.pi * 7.0 * t), 1000.0) == pytest.approx(0.0, abs=1e-12)
    # a constant c on a sine of amplitude a: level = |c| / (a / sqrt(2))
    assert bias_level(0.01 + 0.1 * np.sin(2 * np.pi * 7.0 * t), 1000.0) == pytest.approx(0.01 / (0.1 / np.sqrt(2)), rel=1e-9)


@pytest.mark.parametrize("rms", [0.02, 0.04])
def test_a_wandering_bias_on_one_accelerometer_stands_out_in_every_recording(rms):
    recs = [_recording(s, d, _wandering_bias(s + 100, d, rms)) for s, d in ((1, 12.0), (2, 10.0))]
    sig = bias_signature("A3", recs)
    assert sig is not None and sig.holds, sig
    assert len(sig.level_ratio_per_rec) == 2 and min(sig.level_ratio_per_rec) >= MIN_LEVEL_RATIO
    # the RMS of its 1 s means is that of the injected bias (the vibration nearly averages out)
    for rec, d, s, m in zip(recs, (12.0, 10.0), (1, 2), sig.mean_rms_per_rec):
        b = _wandering_bias(s + 100, d, rms)
        k = int(d)
        ref = np.sqrt(np.mean(b[: k * int(FS_HZ)].reshape(k, -1).mean(axis=1) ** 2))
        assert m == pytest.approx(ref, rel=0.1)
    assert "A3" not in sig.peers and len(sig.peers) == 7


def test_sound_accelerometers_stay_within_the_margin():
    recs = [_recording(s, 12.0) for s in range(3, 9)]
    for name in recs[0].channels:
        sig = bias_signature(name, recs)
        assert sig is not None and not sig.holds
        assert max(sig.level_ratio_per_rec) < MIN_LEVEL_RATIO / 2, (name, sig.level_ratio_per_rec)


def test_not_testable_without_peers_or_segments_or_for_other_quantities():
    b = _wandering_bias(7, 12.0, 0.03)
    assert bias_signature("A3", [_recording(1, 12.0, b, n=4)]).holds            # three peers
    assert bias_signature("A1", [_recording(1, 12.0, None, n=2)]) is None        # one peer only
    assert bias_signature("A3", [_recording(1, 3.0, b)]) is None                 # < 4 whole seconds
    assert bias_signature("A3", [_recording(1, 12.0, b, group="gap")]) is None   # not an accelerometer
    assert bias_signature("nope", [_recording(1, 12.0, b)]) is None


def _sensor_fit(channel: str, accepted: bool = False):
    from types import SimpleNamespace

    from maglev_ros.discrepancy.acceptance import Verdict
    hyp = SimpleNamespace(effect="sensor_error", label=f"sensor_error@{channel}", category="instrumentation",
                          location={"channels": [channel]}, plausible=lambda p: (True, ""))
    hf = SimpleNamespace(hyp=hyp, params=np.array([0.0, 0.02, -0.002]))
    return hf, Verdict(accepted, ("held-out NRMSE 0.143 -> 0.138 is not a clear improvement",), 0.143, 0.138, -200.0)


def test_the_judge_accepts_a_bias_on_its_channel_only_where_the_signature_holds():
    """A sensor_error fit the whole recording cannot accept is accepted on its channel when the bias
    signature holds there; the same evidence on a sound channel, a weak gain on its channel or no
    BIC support is not enough."""
    from maglev_ros.discrepancy.acceptance import AcceptanceConfig
    from maglev_ros.discrepancy.pipeline.judge import _bias_signatures
    acc = AcceptanceConfig()
    recs = [_recording(s, d, _wandering_bias(s + 100, d, 0.03)) for s, d in ((1, 12.0), (2, 10.0))]
    biased, sound = _sensor_fit("A3"), _sensor_fit("A5")
    weak, no_bic = _sensor_fit("A3"), _sensor_fit("A3")
    fits = [(*biased, -200.0), (*sound, -200.0), (*weak, -200.0), (*no_bic, acc.max_delta_bic + 1.0)]
    local_ev = {id(biased[0]): (0.30, 0.256), id(sound[0]): (0.30, 0.256), id(no_bic[0]): (0.30, 0.256),
                id(weak[0]): (0.30, 0.30 * (1 - 0.5 * acc.min_rel_gain))}
    out = _bias_signatures(fits, recs, local_ev, acc)
    assert set(out) == {id(biased[0])}
    sig, verdict = out[id(biased[0])]
    assert verdict.accepted and sig.channel == "A3" and "bias signature" in verdict.reasons[0]
