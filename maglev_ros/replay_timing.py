"""Replay timing: when to publish a recorded message, given a rate, pauses and loops (no rclpy).

Bag time runs at ``rate`` times wall time from the moment the replay starts; a pause freezes bag
time; ``rate=None`` means as fast as possible (every message is due at once). Loops restart bag
time at the window start, so a loop is a jump back in bag time, as in ``ros2 bag play --loop``.
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

    ``start(bag_ns)`` anchors bag time ``bag_ns`` to now; ``wall_due(bag_ns)`` is the monotonic
    time at which a message of bag time ``bag_ns`` should go out; ``pause()``/``resume()`` hold
    bag time still in between.
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
