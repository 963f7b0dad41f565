"""Replay timing against hand-computed schedules (fake clock, no ROS)."""
import pytest

from maglev_ros.errors import UserError
from maglev_ros.replay_timing import ReplayClock, check_rate


class FakeTime:
    def __init__(self):
        self.t = 100.0

    def __call__(self):
        return self.t


def test_rate_scales_bag_time():
    now = FakeTime()
    clk = ReplayClock(rate=10.0, now=now)
    clk.start(5_000_000_000)
    # 2 s of bag time at 10x is due 0.2 s of wall time later
    assert clk.wall_due(7_000_000_000) == pytest.approx(100.2)
    now.t = 100.1
    assert clk.bag_now_ns() == pytest.approx(6_000_000_000, abs=10)


def test_pause_freezes_bag_time_and_shifts_schedule():
    now = FakeTime()
    clk = ReplayClock(rate=1.0, now=now)
    clk.start(0)
    now.t = 101.0
    clk.pause()
    now.t = 105.0
    assert clk.paused and clk.bag_now_ns() == pytest.approx(1e9, abs=10)
    clk.resume()
    # 4 s spent paused: a message at bag 2 s is now due at wall 106
    assert clk.wall_due(2_000_000_000) == pytest.approx(106.0)


def test_fast_is_always_due():
    now = FakeTime()
    clk = ReplayClock(rate=None, now=now)
    clk.start(0)
    assert clk.wall_due(10**12) == 100.0


@pytest.mark.parametrize("bad", [0.0, 0.05, 100.5, -1.0])
def test_rate_outside_range_is_a_user_error(bad):
    with pytest.raises(UserError, match="rate"):
        check_rate(bad)


@pytest.mark.parametrize("good", [0.1, 1.0, 100.0])
def test_rate_inside_range(good):
    assert check_rate(good) == good


def test_rate_change_keeps_bag_time_continuous_and_scales_what_follows():
    now = FakeTime()
    clk = ReplayClock(rate=1.0, now=now)
    clk.start(0)
    now.t = 102.0                                   # bag 2 s
    clk.set_rate(4.0)
    assert clk.bag_now_ns() == pytest.approx(2e9, abs=10)
    # 4 s more of bag time at 4x: 1 s of wall time
    assert clk.wall_due(6_000_000_000) == pytest.approx(103.0)
    with pytest.raises(UserError, match="rate"):
        clk.set_rate(1000.0)


def test_rate_change_while_paused_starts_counting_at_resume():
    now = FakeTime()
    clk = ReplayClock(rate=1.0, now=now)
    clk.start(0)
    now.t = 101.0
    clk.pause()
    now.t = 110.0
    clk.set_rate(2.0)
    assert clk.paused and clk.bag_now_ns() == pytest.approx(1e9, abs=10)
    now.t = 120.0
    clk.resume()
    assert clk.wall_due(3_000_000_000) == pytest.approx(121.0)


def test_fast_to_a_rate_goes_on_from_the_given_bag_time():
    now = FakeTime()
    clk = ReplayClock(rate=None, now=now)
    clk.start(0)
    now.t = 100.5
    clk.set_rate(1.0, bag_ns=7_000_000_000)         # fast mode does not track bag time itself
    assert clk.wall_due(8_000_000_000) == pytest.approx(101.5)
