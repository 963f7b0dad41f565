"""Replay timing: when to publish a recorded message, given a rate, pauses and loops (no rclpy).

Bag time runs at ``rate`` times wall time from the moment the replay starts; a pause freezes bag
time; ``rate=None`` means as fast as possible (every message is due at once). Loops restart bag
time at the window start, so a loop is a jump back in bag time, as in ``ros2 bag play --loop``.
:class:`Backpressure` paces the replay to reliable subscribers that cannot keep up.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

from maglev_ros.errors import UserError

RATE_MIN = 0.1
RATE_MAX = 100.0


def check_rate(rate: float | None) -> float | None:
    """Return ``rate`` if it is inside [0.1, 100] or None (as fast as possible), else raise."""
    if rate is None:
        return None
    if not (RATE_MIN <= float(rate) <= RATE_MAX):
        raise UserError(f"rate {rate} is outside {RATE_MIN}-{RATE_MAX} "
                        "(use --fast for as fast as possible)")
    return float(rate)


@dataclass
class ReplayClock:
    """Maps bag time [ns] to monotonic wall time [s] for a replay at ``rate``.

    ``start(bag_ns)`` anchors bag time ``bag_ns`` to now (also a seek); ``wall_due(bag_ns)`` is the
    monotonic time at which a message of bag time ``bag_ns`` should go out; ``pause()``/``resume()``
    hold bag time still in between; ``set_rate`` changes the rate from the current bag time on.
    """

    rate: float | None = 1.0
    now: callable = field(default=time.monotonic, repr=False)
    _anchor_bag_ns: int = 0
    _anchor_wall_s: float = 0.0
    _paused_at_s: float | None = None

    def __post_init__(self) -> None:
        self.rate = check_rate(self.rate)

    def start(self, bag_ns: int) -> None:
        self._anchor_bag_ns = int(bag_ns)
        self._anchor_wall_s = self.now()
        if self._paused_at_s is not None:
            self._paused_at_s = self._anchor_wall_s

    @property
    def paused(self) -> bool:
        return self._paused_at_s is not None

    def pause(self) -> None:
        if self._paused_at_s is None:
            self._paused_at_s = self.now()

    def resume(self) -> None:
        if self._paused_at_s is not None:
            self._anchor_wall_s += self.now() - self._paused_at_s
            self._paused_at_s = None

    def set_rate(self, rate: float | None, bag_ns: int | None = None) -> None:
        """Go on at ``rate`` from bag time ``bag_ns`` (default: now's), with no jump in bag time."""
        rate = check_rate(rate)
        at = self.bag_now_ns() if bag_ns is None else int(bag_ns)
        self.rate = rate
        self._anchor_bag_ns = at
        # while paused the anchor is the pause's start: resume() adds the time spent paused
        self._anchor_wall_s = self._paused_at_s if self._paused_at_s is not None else self.now()

    def wall_due(self, bag_ns: int) -> float:
        """Monotonic wall time at which bag time ``bag_ns`` is due (now if as fast as possible)."""
        if self.rate is None:
            return self._anchor_wall_s
        return self._anchor_wall_s + (int(bag_ns) - self._anchor_bag_ns) * 1e-9 / self.rate

    def bag_now_ns(self) -> int:
        """Bag time that corresponds to now (frozen while paused)."""
        wall = self._paused_at_s if self._paused_at_s is not None else self.now()
        if self.rate is None:
            return self._anchor_bag_ns
        return self._anchor_bag_ns + int((wall - self._anchor_wall_s) * self.rate * 1e9)


class Stalled(Exception):
    """A reliable subscriber of ``topic`` took nothing for ``waited_s`` (stuck, or gone unnoticed)."""

    def __init__(self, topic: str, waited_s: float, what: str = "took no message") -> None:
        super().__init__(f"{topic}: a reliable subscriber {what} for {waited_s:.0f} s (stuck, or "
                         "killed and not yet dropped by DDS); replay stopped")
        self.topic, self.waited_s = topic, waited_s


@dataclass
class Backpressure:
    """Pacing a replay to reliable subscribers that cannot keep up; when one counts as stuck.

    A reliable keep-all DDS writer holds every message until each reliable reader has acknowledged
    it; once its history is full, a write waits for room (``max_blocking_time``, 100 ms in Fast DDS)
    and then fails, storing nothing (DDS returns TIMEOUT). So the replay offers a refused message
    again until it is taken: nothing is dropped or doubled and the replay runs at the pace of its
    slowest reliable subscriber (best-effort readers acknowledge nothing and hold nothing).

    The node reports each refusal (``refused``: the wait before the next offer, doubling from
    ``first_wait_s`` to ``max_wait_s``) and each message taken (``accepted`` with the time from the
    first offer); an offer that took ``held_after_s`` or more waited for room (queuing into a
    writer with room takes microseconds). A stall (refusals with nothing taken) longer than
    ``stall_timeout_s`` raises :class:`Stalled` (a killed subscriber is dropped by DDS before: Fast
    DDS after its 20 s lease); ``drain_budget_s`` bounds the wait for the final acknowledgements.
    """

    stall_timeout_s: float = 300.0
    warn_after_s: float = 5.0
    first_wait_s: float = 0.005
    max_wait_s: float = 0.25
    held_after_s: float = 1e-3
    history_limit: int = 5000       # Fast DDS's keep-all resource limit (rmw_fastrtps keeps it)
    now: callable = field(default=time.monotonic, repr=False)
    held_n: dict = field(default_factory=dict)         # topic -> messages that waited for room
    held_s: dict = field(default_factory=dict)         # topic -> wall seconds they waited
    refused_n: dict = field(default_factory=dict)      # topic -> messages refused at least once
    accepted_n: dict = field(default_factory=dict)     # topic -> messages taken
    _full: dict = field(default_factory=dict)          # topic -> (wall s, accepted_n) 1st time full
    _topic: str | None = None
    _since_s: float | None = None
    _wait_s: float = 0.0
    _warned: bool = False

    def __post_init__(self) -> None:
        if not self.stall_timeout_s > 0:
            raise UserError(f"stall_timeout_s: expected seconds > 0, got {self.stall_timeout_s}")

    def refused(self, topic: str) -> float:
        """The writer of ``topic`` refused a message: seconds to wait before offering it again."""
        now = self.now()
        if self._since_s is None or topic != self._topic:
            self._topic, self._since_s, self._wait_s, self._warned = topic, now, self.first_wait_s, False
            self.refused_n[topic] = self.refused_n.get(topic, 0) + 1
        else:
            self._wait_s = min(2.0 * self._wait_s, self.max_wait_s)
        if now - self._since_s > self.stall_timeout_s:
            raise Stalled(topic, now - self._since_s)
        return self._wait_s

    def accepted(self, topic: str, offer_s: float) -> None:
        """The writer of ``topic`` took a message ``offer_s`` after it was first offered."""
        if offer_s >= self.held_after_s:
            self.held_n[topic] = self.held_n.get(topic, 0) + 1
            self.held_s[topic] = self.held_s.get(topic, 0.0) + offer_s
            self._full.setdefault(topic, (self.now() - offer_s, self.accepted_n.get(topic, 0)))
        self.accepted_n[topic] = self.accepted_n.get(topic, 0) + 1
        self._since_s = None

    def stalled_s(self) -> float:
        """Length of the current stall (0 when none)."""
        return 0.0 if self._since_s is None else self.now() - self._since_s

    def warn_due(self) -> bool:
        """True once per stall, when it has lasted ``warn_after_s``."""
        if self._warned or self.stalled_s() < self.warn_after_s:
            return False
        self._warned = True
        return True

    def paced(self, wall_s: float) -> list[str]:
        """Topics whose subscribers set the replay's pace: a message was refused, or publishing
        waited for room for at least 0.5 s and 5 % of ``wall_s`` (a busy machine delays a few
        publish calls by milliseconds without any subscriber)."""
        return sorted(t for t in set(self.held_s) | set(self.refused_n)
                      if self.refused_n.get(t, 0) > 0
                      or self.held_s.get(t, 0.0) >= max(0.5, 0.05 * wall_s))

    def drain_budget_s(self, topic: str) -> float:
        """Longest wait for the final acknowledgements on ``topic`` before calling it stalled.

        A writer that held the replay back still holds a backlog its slowest subscriber has not
        acknowledged: up to ``history_limit`` messages, which at the pace the subscriber showed
        since the writer was first full take ``history_limit / pace``; as the limit is the RMW's
        and may be larger, at least as long as that paced stretch took (a backlog no larger than
        what was taken meanwhile). The stall allowance comes on top.
        """
        if topic not in self._full:
            return self.stall_timeout_s
        t0_s, n0 = self._full[topic]
        paced_s = self.now() - t0_s
        taken = max(self.accepted_n.get(topic, 0) - n0, 1)
        return self.stall_timeout_s + max(paced_s, paced_s * self.history_limit / taken)
