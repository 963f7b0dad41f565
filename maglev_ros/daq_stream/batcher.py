"""Per-sample driver messages batched into contract SensorBlocks (no rclpy).

Each contract topic has a sample grid: slot k at t0 + k / rate, t0 whole blocks (covering
``max_wait_s``) before the first stamp received on the topic (a sample another driver's first
message overtook still has its slot), rate the topic's stated rate (mapping ``rates_hz`` or the metadata's
``acquisition.<topic>.sample_rate_hz``). A sample goes to the slot nearest its stamp, so channels of
one topic are aligned by stamp whatever order their messages arrive in. Block b holds slots
[b N, (b + 1) N) (N = round(block_s * rate)); its stamp is its first slot's time. A block is handed
out when every channel of its topic has a sample at or after its last slot, or, when a channel
stays behind, once another channel is ``max_wait_s`` of stream time past the block's end and the
block has waited ``max_wait_s`` of wall time since (``now_s``, monotonic; ``poll`` checks without
a new sample). A slot no sample came
for is NaN (counted ``missing``); a sample never moves to another slot than its stamp's. A sample
for a block already handed out is ``late`` (dropped; its slot stayed NaN), a second sample for a
filled slot is a ``duplicate`` (the first kept), a stamp more than a quarter period off the grid is
``off_grid`` (jitter, or a rate other than the stated one), a jump of a channel's slots by more
than one is a gap (``gaps`` events, ``gap_samples`` slots). A block with no sample at all is not
handed out (the next block's stamp shows the pause). ``flush()`` hands out what is open, the last
block cut after its last filled slot.

Stamps: the header stamp for types with a header; for Float64MultiArray the element
``stamp_index`` names (seconds, taken to the microsecond) when the mapping gives one, otherwise (and for Float64) the time
the message was received, which at kHz rates carries the transport's jitter (more than a period):
give a stamp element for such streams.
"""
from __future__ import annotations

import math
import struct
import time
from dataclasses import dataclass

import numpy as np

from maglev_ros.daq_stream.cdr import field_reader
from maglev_ros.daq_stream.mapping import DaqMapping
from maglev_ros.sensor_block import Block

__all__ = ["BlockBatcher", "ChannelStats", "TopicStats", "AdapterStats", "OFF_GRID_FRACTION",
           "RATE_TOLERANCE"]

OFF_GRID_FRACTION = 0.25      # a stamp further than this part of a period from its slot is off the grid
RATE_TOLERANCE = 0.01         # stamp rate vs stated rate: relative difference reported as a mismatch
_RATE_MIN_INTERVALS = 10


@dataclass(frozen=True)
class ChannelStats:
    channel: str
    driver_topic: str
    samples: int          # placed in a slot
    missing: int          # NaN slots in blocks handed out
    late: int
    duplicate: int
    off_grid: int
    gaps: int
    gap_samples: int

    def to_dict(self) -> dict:
        return dict(self.__dict__)


@dataclass(frozen=True)
class TopicStats:
    topic: str
    rate_hz: float                  # stated
    stamp_rate_hz: float | None     # from consecutive stamps of each channel (None: too few yet)
    blocks: int
    empty_blocks: int               # blocks with no sample, not handed out
    channels: tuple[ChannelStats, ...]

    @property
    def rate_mismatch(self) -> bool:
        return self.stamp_rate_hz is not None and abs(self.stamp_rate_hz / self.rate_hz - 1) > RATE_TOLERANCE

    def total(self, key: str) -> int:
        return sum(getattr(c, key) for c in self.channels)

    def to_dict(self) -> dict:
        return {"topic": self.topic, "rate_hz": self.rate_hz, "stamp_rate_hz": self.stamp_rate_hz,
                "rate_mismatch": self.rate_mismatch, "blocks": self.blocks, "empty_blocks": self.empty_blocks,
                "channels": [c.to_dict() for c in self.channels]}


@dataclass(frozen=True)
class AdapterStats:
    topics: tuple[TopicStats, ...]
    messages: dict                  # driver topic -> messages taken
    malformed: dict                 # driver topic -> messages without the mapped element/field

    def total(self, key: str) -> int:
        return sum(t.total(key) for t in self.topics)

    def to_dict(self) -> dict:
        return {"topics": [t.to_dict() for t in self.topics], "messages": dict(self.messages),
                "malformed": dict(self.malformed),
                "totals": {k: self.total(k) for k in ("samples", "missing", "late", "duplicate",
                                                      "off_grid", "gaps", "gap_samples")}}


class _TopicGrid:
    """One contract topic's grid, open blocks and counters."""

    def __init__(self, topic: str, specs, rate_hz: float, n_block: int, frame_id: str, max_wait_s: float):
        self.topic = topic
        self.names = tuple(s.name for s in specs)
        self.drivers = tuple(s.driver_topic for s in specs)
        self.units = tuple(s.si_unit for s in specs)
        self.nch = len(specs)
        self.rate = float(rate_hz)
        self.n = int(n_block)
        self.frame_id = frame_id
        self.max_wait_s = float(max_wait_s)
        self.wait_slots = max(1, int(round(max_wait_s * self.rate)))
        self.lead_wall: dict[int, float] = {}       # block -> wall time a channel went max_wait_s past it
        # the grid starts this many whole blocks before the first stamp received: a sample that another
        # driver's first message overtook still has its slot (start-up order is arbitrary)
        self.lead_blocks = -(-self.wait_slots // self.n)
        self.t0: int | None = None
        self.started = False
        self.open: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self.next_b = 0
        self.last_slot = [-1] * self.nch
        self.last_rx = [None] * self.nch              # stamp of the channel's last sample, placed or not
        z = [0] * self.nch
        self.samples, self.missing, self.late, self.dup = list(z), list(z), list(z), list(z)
        self.off_grid, self.gaps, self.gap_samples = list(z), list(z), list(z)
        self.dt_sum_ns = 0
        self.dt_n = 0
        self.blocks = 0
        self.empty = 0

    def put(self, cols, stamp_ns: int, values, now_s: float) -> list[Block]:
        if self.t0 is None:
            self.t0 = stamp_ns - int(round(self.lead_blocks * self.n * 1e9 / self.rate))
        x = (stamp_ns - self.t0) * self.rate * 1e-9
        k = math.floor(x + 0.5)
        if k < self.next_b * self.n:
            for c in cols:
                self.late[c] += 1
            return []
        off = abs(x - k) > OFF_GRID_FRACTION
        b, i = divmod(k, self.n)
        ent = self.open.get(b)
        if ent is None:
            ent = self.open[b] = (np.full((self.n, self.nch), np.nan), np.zeros((self.n, self.nch), bool))
        data, filled = ent
        row_d, row_f = data[i], filled[i]
        jumped = False
        for c, v in zip(cols, values):
            prev = self.last_rx[c]
            if prev is not None and 0 < stamp_ns - prev < 1.5e9 / self.rate:
                self.dt_sum_ns += stamp_ns - prev       # the stamps' own rate, not the grid's
                self.dt_n += 1
            self.last_rx[c] = stamp_ns
            if row_f[c]:
                self.dup[c] += 1
                continue
            row_d[c] = v
            row_f[c] = True
            self.samples[c] += 1
            if off:
                self.off_grid[c] += 1
            ls = self.last_slot[c]
            if k > ls:
                if ls >= 0 and k > ls + 1:
                    self.gaps[c] += 1
                    self.gap_samples[c] += k - ls - 1
                    jumped = True
                self.last_slot[c] = k
        # blocks can only become ready at a block's first or last slot or after a jump
        if i == 0 or i == self.n - 1 or jumped:
            return self.ready(now_s)
        return []

    def _waited(self, b: int, now_s: float) -> bool:
        t = self.lead_wall.get(b)
        return t is not None and now_s - t >= self.max_wait_s

    def ready(self, now_s: float) -> list[Block]:
        """The blocks that may go: every channel has a sample at or after the block's end, or one is
        ``max_wait_s`` of stream time past it and the block has waited ``max_wait_s`` of wall time
        since (both: an unpaced stream runs ahead of the wall clock, a dead channel of neither)."""
        out = []
        if not self.open:
            return out
        lo, hi = min(self.last_slot), max(self.last_slot)
        done_last = (lo + 1) // self.n - 1
        lead_last = -(-(hi - self.wait_slots + 1) // self.n) - 2
        for b in self.open:
            if b <= lead_last and b not in self.lead_wall:
                self.lead_wall[b] = now_s
        while self.open:
            b = self.next_b
            if b not in self.open:          # no sample at all in it: on to the next open block once it may go
                m = min(self.open)
                if m <= done_last or self._waited(m, now_s):
                    self._skip(m)
                elif b <= done_last:
                    self._skip(done_last + 1)
                else:
                    break
                continue
            if b <= done_last or self._waited(b, now_s):
                out.append(self._pop(b))
                continue
            break
        return out

    def _skip(self, to: int) -> None:
        if self.started:
            self.empty += to - self.next_b
        self.next_b = to

    def _pop(self, b: int, rows: int | None = None) -> Block:
        data, filled = self.open.pop(b)
        self.lead_wall.pop(b, None)
        self.next_b = b + 1
        self.started = True
        if rows is not None:
            data, filled = data[:rows], filled[:rows]
        have = filled.sum(axis=0)
        for c in range(self.nch):
            self.missing[c] += int(data.shape[0] - have[c])
        self.blocks += 1
        stamp = self.t0 + int(round(b * self.n * 1e9 / self.rate))
        return Block.from_arrays(stamp, self.rate, self.names, self.units, data, frame_id=self.frame_id)

    def flush(self) -> list[Block]:
        out = []
        while self.open:
            b = min(self.open)
            if b > self.next_b:
                self._skip(b)
            rows = None
            if len(self.open) == 1:         # the last block: cut after its last filled slot
                rows = int(np.flatnonzero(self.open[b][1].any(axis=1)).max()) + 1
            out.append(self._pop(b, rows))
        return out

    def stats(self) -> TopicStats:
        rate = self.dt_n / (self.dt_sum_ns * 1e-9) if self.dt_n >= _RATE_MIN_INTERVALS and self.dt_sum_ns > 0 else None
        chans = tuple(ChannelStats(self.names[c], self.drivers[c], self.samples[c], self.missing[c], self.late[c],
                                   self.dup[c], self.off_grid[c], self.gaps[c], self.gap_samples[c])
                      for c in range(self.nch))
        return TopicStats(self.topic, self.rate, rate, self.blocks, self.empty, chans)


class _DriverPlan:
    """How one driver topic's message becomes samples: stamp, raw values, (grid, columns, scale, offset)."""

    def __init__(self, driver, grids: dict, gravity: float):
        self.topic = driver.topic
        self.header = driver.has_header
        self.stamp_index = driver.stamp_index
        self.getters = [s.getter() for s in driver.channels]
        self.msg_type = driver.msg_type
        self.cdr = field_reader(driver.msg_type, [s.field if s.index is None else s.index for s in driver.channels],
                                driver.stamp_index)
        groups: dict[str, list] = {}
        for j, s in enumerate(driver.channels):
            grid = grids[s.contract_topic]
            groups.setdefault(s.contract_topic, []).append(
                (grid.names.index(s.name), j, s.factor * s.sign, gravity if s.remove_gravity else 0.0))
        self.groups = [(grids[t], tuple(g[0] for g in gs), tuple(g[1] for g in gs), tuple(g[2] for g in gs),
                        tuple(g[3] for g in gs)) for t, gs in groups.items()]

    def stamp_ns(self, msg, recv_ns: int) -> int:
        if self.header:
            st = msg.header.stamp
            return st.sec * 1_000_000_000 + st.nanosec
        if self.stamp_index is not None:
            # float64 seconds resolve ~0.24 us at epoch times: taken to the microsecond
            return int(round(msg.data[self.stamp_index] * 1e6)) * 1000
        return int(recv_ns)


class BlockBatcher:
    """Batch a mapping's driver messages into contract SensorBlocks.

    ``add_message(driver_topic, msg, recv_ns)`` takes one driver message (any object with the mapped
    attributes: an rclpy message in the node) and returns the blocks it completed as
    ``[(contract topic, Block)]``; ``add_raw(driver_topic, stamp_ns, raw)`` takes the raw values
    (in the mapping's channel order of that driver topic) directly; ``flush()`` hands out the rest.
    Values in SI: raw * unit factor * sign, minus gravity where ``remove_gravity``."""

    def __init__(self, mapping: DaqMapping, frame_id: str = "daq", max_wait_s: float = 0.5) -> None:
        self.mapping = mapping
        self.grids = {t: _TopicGrid(t, mapping.on_topic(t), mapping.rates_hz[t], mapping.block_samples(t),
                                    frame_id, max_wait_s) for t in mapping.contract_topics}
        self.plans = {d.topic: _DriverPlan(d, self.grids, mapping.gravity_mps2) for d in mapping.drivers.values()}
        self.messages = {t: 0 for t in self.plans}
        self.malformed = {t: 0 for t in self.plans}

    def add_message(self, driver_topic: str, msg, recv_ns: int = 0,
                    now_s: float | None = None) -> list[tuple[str, Block]]:
        plan = self.plans[driver_topic]
        try:
            stamp = plan.stamp_ns(msg, recv_ns)
            raw = [g(msg) for g in plan.getters]
        except (IndexError, AttributeError, TypeError, ValueError, OverflowError):
            self.malformed[driver_topic] += 1
            return []
        return self._put(plan, stamp, raw, now_s)

    def add_cdr(self, driver_topic: str, buf, recv_ns: int = 0,
                now_s: float | None = None) -> list[tuple[str, Block]] | None:
        """The same from the message's serialised bytes (daq_stream.cdr); None when they are not
        little-endian CDR the reader knows (deserialise and use :meth:`add_message` then)."""
        plan = self.plans[driver_topic]
        try:
            stamp, raw = plan.cdr(buf)
        except (ValueError, IndexError, struct.error):
            return None
        return self._put(plan, recv_ns if stamp is None else stamp, raw, now_s)

    def add_raw(self, driver_topic: str, stamp_ns: int, raw, now_s: float | None = None) -> list[tuple[str, Block]]:
        return self._put(self.plans[driver_topic], int(stamp_ns), raw, now_s)

    def _put(self, plan: _DriverPlan, stamp: int, raw, now_s) -> list[tuple[str, Block]]:
        self.messages[plan.topic] += 1
        now = time.monotonic() if now_s is None else now_s
        out = []
        for grid, cols, idx, scale, offset in plan.groups:
            vals = [raw[j] * s - o for j, s, o in zip(idx, scale, offset)]
            for blk in grid.put(cols, stamp, vals, now):
                out.append((grid.topic, blk))
        return out

    def poll(self, now_s: float | None = None) -> list[tuple[str, Block]]:
        """Blocks whose wait for a lagging channel ended (call now and then: no sample may come)."""
        now = time.monotonic() if now_s is None else now_s
        return [(t, b) for t, grid in self.grids.items() for b in grid.ready(now)]

    def flush(self) -> list[tuple[str, Block]]:
        out = []
        for t, grid in self.grids.items():
            out += [(t, b) for b in grid.flush()]
        return out

    def stats(self) -> AdapterStats:
        return AdapterStats(tuple(g.stats() for g in self.grids.values()), dict(self.messages), dict(self.malformed))
