"""The twin driven along a recording's measured trajectory: noisy positions smoothed, the stepper
landing on the trajectory block after block (where integrating a noisy speed channel random-walks)."""
import numpy as np

from maglev_ros.twin.coupling import TwinStepper
from maglev_ros.twin.design import twin_config
from maglev_ros.twin.trajectory import MeasuredTrajectory, drive

RATE_HZ = 100.0          # position stream rate
POS_NOISE_M = 0.002      # position and speed noise of a plausible location system
SPEED_NOISE_MPS = 0.01


def _true(t):
    """A vehicle accelerating gently then braking: x(t) [m] and v(t) [m/s]."""
    v = 5.0 + 0.3 * np.sin(2 * np.pi * t / 8.0)
    x = 1.0 + 5.0 * t + 0.3 * 8.0 / (2 * np.pi) * (1 - np.cos(2 * np.pi * t / 8.0))
    return x, v


def _measured(seed=3, seconds=8.0):
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, seconds, 1.0 / RATE_HZ)
    x, v = _true(t)
    return t, x + rng.normal(0, POS_NOISE_M, t.size), v + rng.normal(0, SPEED_NOISE_MPS, t.size)


def test_smoothed_positions_are_closer_to_the_truth_than_the_samples():
    t, xm, vm = _measured()
    traj = MeasuredTrajectory.from_samples(t, xm, vm)
    inner = (t > 0.5) & (t < t[-1] - 0.5)
    err = np.abs(traj.position_at(t) - _true(t)[0])[inner]
    # a cubic fit over 100 samples: noise down by ~sqrt(100 / 2.2)
    assert np.sqrt(np.mean(err ** 2)) < POS_NOISE_M / 4
    # the speed is the fit's derivative, closer to the truth than the speed channel's samples
    assert np.sqrt(np.mean((traj.speed_mps - _true(t)[1])[inner] ** 2)) < SPEED_NOISE_MPS / 2
    # extrapolated with the end speed before the first sample
    assert np.isclose(traj.position_at(-0.01), traj.position_m[0] - 0.01 * traj.speed_mps[0])


def test_the_stepper_lands_on_the_trajectory_where_the_integrated_speed_drifts():
    t, xm, vm = _measured()
    traj = MeasuredTrajectory.from_samples(t, xm, vm)
    cfg = twin_config()
    fs = 200.0
    st = TwinStepper(cfg, None, fs_out_hz=fs, start_position_m=float(traj.position_at(0.0)),
                     start_speed_mps=float(traj.speed_at(0.0)), t0_s=0.0)
    res = [r for r in drive(st, traj, 7.5, block_s=0.25)]
    tt = np.concatenate([r.time_s for r in res])
    xx = np.concatenate([r.position_m for r in res])
    assert np.isclose(tt[-1], 7.5) and np.all(np.diff(tt) > 0)
    err_driven = np.max(np.abs(xx - _true(tt)[0]))
    # the former way: the speed channel's sample at each block end, integrated
    st2 = TwinStepper(cfg, None, fs_out_hz=fs, start_position_m=float(xm[0]), start_speed_mps=float(vm[0]),
                      t0_s=0.0)
    parts, tc = [], 0.0
    while tc < 7.5 - 1e-9:
        tc = min(7.5, tc + 0.25)
        parts.append(st2.advance(tc, float(np.interp(tc, t, vm))))
    t2 = np.concatenate([r.time_s for r in parts])
    x2 = np.concatenate([r.position_m for r in parts])
    err_integrated = np.max(np.abs(x2 - _true(t2)[0]))
    assert err_driven < 1e-3                       # within a millimetre everywhere
    assert err_driven < err_integrated / 2


def test_the_live_tracker_estimates_the_newest_position_within_its_stated_error():
    """Causal fit at each 0.1 s block's end: errors against the truth match the stated standard
    error (over the blocks of several noisy streams) and are well below the raw newest sample's."""
    from maglev_ros.twin.trajectory import TrajectoryTracker
    err, sds, raw = [], [], []
    for seed in range(6):
        t, xm, vm = _measured(seed=seed)
        tr = TrajectoryTracker()
        for k in range(0, t.size, 10):
            last = min(k + 9, t.size - 1)
            tr.add(t[k:k + 10], xm[k:k + 10], vm[k:k + 10])
            t_next = t[last] + 1.0 / RATE_HZ
            x, _v, sd = tr.estimate(t_next)
            if sd > 0:
                err.append(x - _true(t_next)[0])
                sds.append(sd)
                raw.append(xm[last] + vm[last] / RATE_HZ - _true(t_next)[0])
    z = np.asarray(err) / np.asarray(sds)
    print(f"z std {np.std(z):.3f}, rms error {np.sqrt(np.mean(np.square(err))) * 1e3:.2f} mm, "
          f"raw {np.sqrt(np.mean(np.square(raw))) * 1e3:.2f} mm")
    assert z.size > 300
    assert 0.8 < np.std(z) < 1.25                      # the stated error is the real one
    assert np.mean(np.abs(z) < 3) > 0.98
    assert np.sqrt(np.mean(np.square(err))) < 0.5 * np.sqrt(np.mean(np.square(raw)))


def test_absolute_stamps_reach_every_end_sample_and_end():
    """On a recording's absolute time base (~1.7e9 s, float rounding ~1e-4 of a 1 kHz sample) the
    stepper lands on every asked end sample: each end on the output grid advances it to exactly that
    sample count (the exact arithmetic reference: k samples after t0), and drive() returns."""
    t0 = 1718122400.0
    t, xm, vm = _measured(seconds=2.0)
    traj = MeasuredTrajectory.from_samples(t0 + t, xm, vm)
    fs = 1000.0
    st = TwinStepper(twin_config(), None, fs_out_hz=fs, start_position_m=float(xm[0]),
                     start_speed_mps=float(vm[0]), t0_s=t0)
    for k in range(1, 400, 7):
        st.advance(t0 + k / fs, 5.0)
        assert st._k == k * st.n_sub
    res = drive(st, traj, t0 + 1.6840, block_s=0.25)
    tt = np.concatenate([r.time_s for r in res])
    assert round((tt[-1] - t0) * fs) == 1684 and np.all(np.diff(tt) > 0)
