"""Blocks of several topics in one order whatever order they arrive in (no rclpy).

DDS keeps each topic's messages in order but not the interleaving of topics (under a fast replay
one topic's blocks arrived more than 10 s of stream time after the others'), and a node whose
state depends on what it has seen of every topic (the online twin steps the vehicle with the
irregularity measured from the blocks received so far) then gives a different result on every run.
:class:`StreamOrder` holds the blocks and releases them sorted by (header stamp, topic rank) as
soon as no block still to come can sort before them: a topic's next block is stamped after its
last, so every block stamped at or before the oldest of the topics' newest stamps is final (the
stream's watermark). A topic that has delivered nothing for ``max_silence_s`` of wall time (a
sensor that stopped, a topic the metadata names but nobody publishes) no longer holds the others
back (the order then depends on arrival again; :attr:`released_early` counts those blocks), and
:meth:`flush` releases everything at a recording's end. The offline equivalent is
``sorted(items, key=(stamp, rank))``. The caller passes the wall time (``now_s``) so that this
module stays a pure function of its inputs.
"""
from __future__ import annotations

import heapq
import math
from typing import Sequence


class StreamOrder:
    def __init__(self, topics: Sequence[str], max_silence_s: float = 30.0):
        self.rank = {t: i for i, t in enumerate(topics)}
        self.max_silence_s = float(max_silence_s)
        self.released_early = 0
        self._heap: list = []
        self._seq = 0
        self._newest = {t: -math.inf for t in topics}      # newest stamp received per topic
        self._heard: dict[str, float | None] = {t: None for t in topics}   # wall time of its last block
        self._since: float | None = None                  # wall time of the first call

    def key(self, topic: str, block) -> tuple[int, int]:
        """The release order: header stamp, then the topic's rank (unknown topics last)."""
        return int(block.stamp_ns), self.rank.get(topic, len(self.rank))

    def add(self, topic: str, block, now_s: float) -> list[tuple[str, object]]:
        """Take one block; returns the (topic, block) pairs now final, in order."""
        heapq.heappush(self._heap, (*self.key(topic, block), self._seq, topic, block))
        self._seq += 1
        if topic in self._newest:
            self._newest[topic] = max(self._newest[topic], block.stamp_ns)
            self._heard[topic] = now_s
        return self.poll(now_s)

    def poll(self, now_s: float) -> list[tuple[str, object]]:
        """What is final now (call now and then: a topic falls silent without a block saying so)."""
        if self._since is None:
            self._since = now_s
        holding = [self._newest[t] for t, h in self._heard.items()
                   if now_s - (self._since if h is None else h) < self.max_silence_s]
        mark = min(holding) if holding else math.inf
        strict = min(self._newest.values(), default=math.inf)
        out = self._release(mark)
        self.released_early += sum(1 for _t, b in out if b.stamp_ns > strict)
        return out

    def flush(self) -> list[tuple[str, object]]:
        """Everything held, in order (the end of a recording)."""
        return self._release(math.inf)

    def _release(self, mark: float) -> list[tuple[str, object]]:
        out = []
        while self._heap and self._heap[0][0] <= mark:
            *_k, topic, block = heapq.heappop(self._heap)
            out.append((topic, block))
        return out

    def __len__(self) -> int:
        return len(self._heap)
