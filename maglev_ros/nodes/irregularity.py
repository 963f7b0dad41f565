"""Node ``irregularity``: guideway irregularity by the inertial reference method, as it grows.

Subscribes /testline/metadata (latched), /testline/vehicle/{accel,gap,position}; feeds
:class:`maglev_ros.irregularity.profile.IncrementalProfiler`; publishes the profile on
/maglev/irregularity (maglev_msgs/IrregularityProfile, latched, so the twin gets the newest
profile whenever it joins) every ``publish_period_s`` x max(1, ``stream_rate``) of STREAM time when
it has grown (never an all-NaN one): about every ``publish_period_s`` of wall time whatever the
replay's rate, which the launcher passes as ``stream_rate`` (a ``set_rate`` during the run does not
change it). The blocks are fed in (stamp, topic) order whatever order DDS delivers the topics in
(:mod:`maglev_ros.stream_order`), and each live profile is that of a copy of the profiler taken
when the ordered stream reaches its mark (every block stamped before it, none after), computed on
a worker thread (its ``result()`` re-processes the buffered tail: a few tenths of a second, which
in the executor held back every stream) and published from there, stamped at the mark: a replay
gives the same live profiles on every run. When the worker falls more than ``LIVE_BACKLOG_S`` of
stream behind (a long recording replayed far faster than the profiles are computed), a mark is
skipped, counted on /diagnostics and said once; only then do runs differ.

At a recording's end (graph run protocol, :mod:`maglev_ros.nodes._lifecycle`) it publishes the
profile of the whole recording as ``maglev-ros irregularity`` computes it of the same bag: the
recording's blocks are kept (up to ``max_recording_s`` of stream; beyond, the growing profile's
final state is published instead, with the band fixed up front) and fitted by the verb's
:class:`~maglev_ros.irregularity.profile.InertialProfiler` with the verb's defaults (corner and
band speed from the whole pass), then the node starts afresh for the next recording. That fit runs
on the same worker, after any live one (the node says ``busy`` until it is published).

Parameters: highpass_hz (0: chosen from the stream by the rule of ``maglev-ros irregularity``),
spacing_m (0.25), band_speed_mps (0: growing profile at 80% of the metadata's nominal speed, else
15 km/h; the recording's profile at the verb's default), max_profile_m (0: unbounded),
publish_period_s (1.0 s), stream_rate (1.0), max_recording_s (1800); each with its description and
range in ``PARAMS``.
"""
from __future__ import annotations

import copy
import json
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np
from rclpy.duration import Duration
from rclpy.node import Node
from std_msgs.msg import String

from maglev_msgs.msg import IrregularityProfile, SensorBlock
from maglev_ros.contract import (TOPIC_METADATA, TOPIC_VEHICLE_ACCEL, TOPIC_VEHICLE_GAP,
                                 TOPIC_VEHICLE_POSITION, parse_metadata)
from maglev_ros.errors import UserError
from maglev_ros.nodes._common import BlockGate, run_node, stamp_to_msg
from maglev_ros.nodes._diagnostics import NodeDiagnostics
from maglev_ros.nodes._params import Param, declare
from maglev_ros.nodes._qos import publisher, subscription
from maglev_ros.nodes._lifecycle import NodeLifecycle

TOPIC_IRREGULARITY = "/maglev/irregularity"
MAX_PENDING_BLOCKS = 5000
# stream time of live profiles that may wait for the worker before a further mark is skipped: a
# whole short pass even when replayed unpaced, so its live profiles are the same on every run
LIVE_BACKLOG_S = 30.0
ACK_TIMEOUT_S = 2.0   # at most this long for the subscribers to acknowledge a profile before the next
POLL_S = 0.5          # wall period of the timer that lets a silent topic stop holding the others back
IDLE_FLUSH_S = 2.0    # a live stream (no replay) that stopped this long: its tail's profile is published
TOPIC_KEYS = {TOPIC_VEHICLE_ACCEL: "accel", TOPIC_VEHICLE_GAP: "gap", TOPIC_VEHICLE_POSITION: "position"}

PARAMS = (
    Param("highpass_hz", 0.0, "high-pass corner of the integration [Hz] (0: chosen from the stream, "
                              "as maglev-ros irregularity does)", range=(0.0, 100.0)),
    Param("spacing_m", 0.25, "spacing of the published profile [m]", range=(0.001, 10.0)),
    Param("band_speed_mps", 0.0, "speed that sets the valid wavelength band [m/s] (0: 80% of the "
                                 "metadata's nominal speed, else 15 km/h)", range=(0.0, 200.0)),
    Param("max_profile_m", 0.0, "longest profile kept [m] (0: unbounded)", range=(0.0, 1e7)),
    Param("publish_period_s", 1.0, "period of publishing the grown profile, in stream time at real time "
                                   "(every publish_period_s x max(1, stream_rate) of stream) [s]",
          range=(0.01, 1e9), apply=lambda node, v: node.set_publish_period(period_s=v)),
    # a live profile re-processes tens of seconds of the tail: at 10x, one per stream second would
    # be ten per wall second; one per wall second is what a viewer sees anyway
    Param("stream_rate", 1.0, "bag seconds per wall second of the streams (the launcher sets the replay's "
                              "rate; 1 for live data): stretches the live profiles' stream-time period",
          range=(0.1, 100.0), apply=lambda node, v: node.set_publish_period(stream_rate=v)),
    Param("max_recording_s", 1800.0, "keep at most this much stream of a recording for its end-of-recording "
                                     "profile [s]", range=(0.0, 1e7)),
)


class IrregularityNode(Node):
    def __init__(self) -> None:
        super().__init__("irregularity")
        v = declare(self, PARAMS)
        self.highpass_hz = v["highpass_hz"] or None     # 0: the offline verb's rule
        self.spacing_m = v["spacing_m"]
        self.band_speed_mps = v["band_speed_mps"]
        self.max_profile_m = v["max_profile_m"]
        self.publish_period_s, self.stream_rate = float(v["publish_period_s"]), float(v["stream_rate"])
        self.period_ns = self._period_ns()
        self.max_recording_s = float(v["max_recording_s"])
        self.profiler = None
        self.metadata = None
        self.pending: list[tuple[str, object]] = []
        self.kept: dict[str, list] | None = {k: [] for k in TOPIC_KEYS.values()}
        self.first_stamp_ns = None
        self.spent = False           # the recording ended: blocks wait for the next one's metadata
        self.last_stamp_ns = 0
        self.published_signature = None
        self.warned: set = set()
        self.pub = publisher(self, IrregularityProfile, TOPIC_IRREGULARITY)
        self.diagnostics = NodeDiagnostics(self)
        self.gate = BlockGate(self, self.diagnostics)
        subscription(self, String, TOPIC_METADATA, self._on_metadata)
        for topic in TOPIC_KEYS:
            subscription(self, SensorBlock, topic, self._on_block(topic))
        # one worker: the live profile (of a copy of the profiler) and the recording's profile
        self.worker = ThreadPoolExecutor(max_workers=1, thread_name_prefix="irregularity")
        self.live: list = []         # futures of the live profiles queued or computing (and publishing)
        self.live_skipped = 0        # marks skipped because the worker fell behind
        self.final = None            # future of the recording's profile being computed (and published)
        self.order = None            # the recording's StreamOrder
        self.next_mark_ns = None     # stream time of the next live profile
        self.send_lock = threading.Lock()   # the worker publishes; the signature is shared
        self.epoch = 0               # a new recording (metadata) or its end: older results are dropped
        self.n_taken = 0             # blocks fed to the profiler (a copy is made only when it grew)
        self.n_copied = -1
        self.live_cost_s = 0.0
        self.last_input = time.monotonic()
        self.timer = self.create_timer(POLL_S, self._poll)
        self.diagnostics.add_check(self._worker_check)
        self.lifecycle = NodeLifecycle(self, diagnostics=self.diagnostics)

    def _period_ns(self) -> int:
        return int(round(self.publish_period_s * max(1.0, self.stream_rate) * 1e9))

    def set_publish_period(self, period_s: float | None = None, stream_rate: float | None = None) -> None:
        """A live change of ``publish_period_s`` or ``stream_rate`` (from the next mark on)."""
        if period_s is not None:
            self.publish_period_s = float(period_s)
        if stream_rate is not None:
            self.stream_rate = float(stream_rate)
        self.period_ns = self._period_ns()

    def _on_metadata(self, msg) -> None:
        from maglev_ros.irregularity.profile import IncrementalProfiler, magnet_channel_pairs
        try:
            md = parse_metadata(msg.data, TOPIC_METADATA)
            offsets = md.magnet_offsets_m
        except Exception as exc:  # noqa: BLE001  (a bad recording must not kill the node)
            self.get_logger().error(f"metadata unusable for the irregularity: {exc}")
            return
        if self.metadata is not None and not self.spent and md.raw == self.metadata.raw:
            return                  # the same recording's metadata again (a latched copy)
        self.gate.new_stream()
        self.metadata, self.spent, self.profiler = md, False, None
        self.published_signature = None
        self.epoch += 1
        self.n_taken, self.n_copied = 0, -1
        self.order, self.next_mark_ns = self._stream_order(md), None
        if not offsets:
            self.get_logger().warning("metadata has no vehicle.magnet_offsets_m (ambient run?)")
            self.pending.clear()
            return
        band = self.band_speed_mps or (0.8 * md.nominal_speed_mps if md.nominal_speed_mps
                                       else 15.0 / 3.6)
        self.profiler = IncrementalProfiler(
            offsets, md.nominal_gap_m or 0.010, channel_pairs=magnet_channel_pairs(md),
            band_speed_mps=band, max_profile_m=self.max_profile_m or None,
            highpass_hz=self.highpass_hz, spacing_m=self.spacing_m)
        pending, self.pending = self.pending, []
        for topic, block in pending:
            self._add(topic, block)

    @staticmethod
    def _stream_order(md):
        from maglev_ros.stream_order import StreamOrder
        topics = [t for t in TOPIC_KEYS if t == TOPIC_VEHICLE_POSITION or md.sensors_on_topic(t)]
        return StreamOrder(topics)

    def _add(self, topic: str, block) -> None:
        for t, b in self.order.add(topic, block, time.monotonic()):
            self._take_ordered(t, b)

    def _take_ordered(self, topic: str, block) -> None:
        """Blocks in (stamp, topic) order: a live mark passed is a copy of the profiler before it."""
        if self.next_mark_ns is None:
            self.next_mark_ns = block.stamp_ns + self.period_ns
        if block.stamp_ns >= self.next_mark_ns:
            marks = (block.stamp_ns - self.next_mark_ns) // self.period_ns
            mark = self.next_mark_ns + marks * self.period_ns
            self.next_mark_ns = mark + self.period_ns
            self._live_at(mark)
        self._take(TOPIC_KEYS[topic], block)

    def _on_block(self, topic: str):
        def cb(msg) -> None:
            block = self.gate.block(msg, topic)
            if block is None:
                return
            self.last_input = time.monotonic()
            if self.metadata is None or self.spent:      # wait for this recording's metadata
                if len(self.pending) < MAX_PENDING_BLOCKS:
                    self.pending.append((topic, block))
            elif self.profiler is not None:
                self._add(topic, block)
        return cb

    def _take(self, key: str, block) -> None:
        self.last_stamp_ns = max(self.last_stamp_ns, block.end_ns)
        self._keep(key, block)
        self.n_taken += 1
        try:
            self.profiler.partial_fit(**{key: block})
        except Exception as exc:  # noqa: BLE001
            self.get_logger().error(f"irregularity: {key} block at {block.stamp_s:.3f} s: {exc}")

    def _keep(self, key: str, block) -> None:
        """The recording's blocks, for the whole-recording profile at its end (bounded)."""
        if self.kept is None:
            return
        self.first_stamp_ns = block.stamp_ns if self.first_stamp_ns is None else min(self.first_stamp_ns,
                                                                                   block.stamp_ns)
        if (block.end_ns - self.first_stamp_ns) * 1e-9 > self.max_recording_s:
            self.kept = None
            self.get_logger().warning(
                f"recording longer than max_recording_s = {self.max_recording_s:g} s: its end publishes "
                f"the growing profile (band fixed up front), not the offline verb's whole-pass fit")
            return
        self.kept[key].append(block)

    # ------------------------------------------------------------------ protocol
    def on_recording_end(self, index: int) -> None:
        """Compute the whole recording's profile (the verb's) on the worker, then start afresh;
        the timer publishes it, ``busy()`` until then."""
        if self.profiler is not None and not self.spent:
            for t, b in self.order.flush():
                self._take_ordered(t, b)
            # the live profiles still queued are of this recording's marks: the worker publishes
            # them first (its queue is in order), then this recording's profile
            job = (self.metadata, self.kept, self.profiler, self.last_stamp_ns)
            self.final = self.worker.submit(self._final_job, *job)
        self.spent = True
        self.kept = {k: [] for k in TOPIC_KEYS.values()}
        self.first_stamp_ns = None
        self.gate.new_stream()      # the next recording sets its own layout

    def busy(self) -> bool:
        """The recording's profile is not out yet (the worker publishes it, then the job is done)."""
        if self.final is not None and self.final.done():
            self._outcome(self.final, "the recording's profile")
            self.final = None
        return self.final is not None

    def _final_job(self, metadata, kept, profiler, stamp_ns: int) -> None:
        res = self._recording_profile(metadata, kept, profiler)
        if res is not None:
            with self.send_lock:
                self._send(res, stamp_ns)

    def _recording_profile(self, metadata, kept, profiler):
        from maglev_ros.irregularity.recording import recording_profile
        try:
            if kept is None or not all(kept.values()):
                return profiler.result()
            return recording_profile(metadata, {t: kept[k] for t, k in TOPIC_KEYS.items()},
                                     highpass_hz=self.highpass_hz, spacing_m=self.spacing_m,
                                     band_speed_mps=self.band_speed_mps or None)
        except UserError as exc:
            self.get_logger().error(f"irregularity of the recording: {exc}")
            return None

    # ------------------------------------------------------------------ output
    def _live_at(self, mark_ns: int) -> None:
        """Queue the live profile of the data before ``mark_ns`` (when the profiler grew)."""
        self._prune()
        if self.profiler is None or self.n_taken == self.n_copied:
            return
        if len(self.live) >= max(2, int(LIVE_BACKLOG_S * 1e9 / max(self.period_ns, 1))):
            self.live_skipped += 1
            if self.live_skipped == 1:
                self.get_logger().warning("the live profile falls behind the stream: marks are skipped (counted "
                                          "on /diagnostics; this run's live profiles differ from a slower one's)")
            return
        self.n_copied = self.n_taken
        snapshot = copy.deepcopy(self.profiler)      # milliseconds; the fit goes on meanwhile
        self.live.append(self.worker.submit(self._live_job, snapshot, self.epoch, mark_ns))

    def _prune(self) -> None:
        for f in [f for f in self.live if f.done()]:
            self._outcome(f, "the growing profile")
            self.live.remove(f)

    def _poll(self) -> None:
        """Timer: a topic silent for long no longer holds the others back; finished jobs reported;
        a live stream (no replay) that stopped has its tail's profile published."""
        self._prune()
        if self.order is None or self.profiler is None or self.spent:
            return
        for t, b in self.order.poll(time.monotonic()):
            self._take_ordered(t, b)
        if not self.lifecycle.events_seen and time.monotonic() - self.last_input >= IDLE_FLUSH_S:
            self.flush_live()

    def flush_live(self) -> None:
        """Everything held taken, and the profile of all of it queued (a stream that stopped)."""
        if self.order is None or self.profiler is None or self.spent:
            return
        for t, b in self.order.flush():
            self._take_ordered(t, b)
        self._live_at(self.last_stamp_ns)

    def _live_job(self, profiler, epoch: int, stamp_ns: int) -> None:
        t = time.thread_time()                   # this worker thread's CPU time
        try:
            res = profiler.result()
        except UserError:       # not enough of all three topics yet
            res = None
        finally:
            self.live_cost_s = time.thread_time() - t
        # a recording's end queues its own profile behind this job: this one is out first; a new
        # recording (epoch) drops it
        if res is not None and epoch == self.epoch:
            with self.send_lock:
                self._send_grown(res, stamp_ns)

    def _outcome(self, fut, what: str):
        try:
            return fut.result()
        except Exception as exc:  # noqa: BLE001  (a failed fit must not end the node)
            self.get_logger().error(f"irregularity: {what} failed: {exc}")
            return None

    def _send_grown(self, res, stamp_ns: int) -> None:
        signature = (res.position_m.size, int(np.isfinite(res.irregularity_m).sum()))
        if signature[1] == 0 or signature == self.published_signature:
            return
        self.published_signature = signature
        self._send(res, stamp_ns)

    def _worker_check(self):
        from maglev_ros.nodes._diagnostics import OK, Check
        return Check(OK, "", {"live_profile_cost_s": f"{self.live_cost_s:.3f}",
                              "live_profiles_skipped": str(self.live_skipped),
                              "recording_profile_running": self.final is not None})

    def unfinished_work(self) -> bool:
        """At shutdown: True while the worker still computes (the process then ends without the
        interpreter's teardown, which would join the worker's thread and wait for a result no one
        needs any more)."""
        self.worker.shutdown(wait=False, cancel_futures=True)
        return any(j is not None and not j.done() for j in (*self.live, self.final))

    def _send(self, res, stamp_ns: int) -> None:
        if not np.isfinite(res.irregularity_m).any():
            return
        msg = IrregularityProfile()
        stamp_to_msg(stamp_ns, msg.header)
        msg.header.frame_id = "guideway"
        msg.start_position_m = float(res.position_m[0])
        msg.spacing_m = float(res.spacing_m)
        msg.irregularity_m = np.asarray(res.irregularity_m, dtype=np.float64)
        msg.std_m = np.asarray(res.std_m, dtype=np.float64)
        msg.min_wavelength_m = float(res.min_wavelength_m)
        msg.max_wavelength_m = float(res.max_wavelength_m)
        msg.kind = res.kind
        msg.sources = list(res.magnet_names)
        self.pub.publish(msg)
        # the topic is latched with depth 1: a profile published before the subscribers acknowledged
        # the previous one would replace it unseen, so what they receive would depend on timing
        self.pub.wait_for_all_acked(Duration(seconds=ACK_TIMEOUT_S))
        for w in res.warnings:
            key = (w.kind, w.channel, w.start_s)
            if key not in self.warned:
                self.warned.add(key)
                self.get_logger().warning(json.dumps(w.to_dict()))


def main(args=None) -> int:
    return run_node(IrregularityNode, args)


if __name__ == "__main__":
    sys.exit(main())
