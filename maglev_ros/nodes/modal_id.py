"""Node ``modal_id``: guideway modes from /testline/guideway/accel, during the stream and per recording.

During the stream: sliding-window SSI-cov (``maglev_ros.modal.tracking.OnlineModalID``) with modes
tracked across updates (stable ids, "new"/"tracked"/"lost"); a ModalEstimate on /maglev/modes
(method ``ssi-cov online``, window_s the window) every ``update_s`` of stream time once
``window_s`` has filled. Its settings follow the stream as the ``modes`` verb's follow a
recording (bands, decimation, block rows and orders by ``maglev_ros.modal.bands.plan_bands`` on a
record of ``window_s`` at the stream's rate); the window, unless given, is the shortest record on
which those rules look down to ``fmin_hz`` (1 Hz: 40 s). The tracker restarts with each recording.
The executor only takes the blocks in (covariances per ``update_s`` chunk: cheap); each window's
SSI (about half a second for a 30 s window of ten channels) runs on the node's worker thread, in
order, and its estimate is published from there. When a window completes while the previous one
is still being identified and another waits, the waiting one is left out (``skip_when_busy``,
counted on /diagnostics as ``windows_skipped``): at a replay rate the SSI cannot follow the node
publishes fewer updates instead of falling ever further behind the stream.

At the end of each recording (the replay's ``recording_end``, :mod:`maglev_ros.nodes._lifecycle`;
on a live stream, metadata that differs from the current): the recording's guideway accelerations
(and, for a pass's free decay, the vehicle position), kept as received, are identified by the
``modes`` verb's own function (``commands.modes.identify_modes`` on a
:class:`~maglev_ros.bag_memory.MemoryBag`, the verb's defaults) on a worker thread, and published as
one ModalEstimate: method ``ssi-cov whole recording`` (``..., free decay`` for a pass), window_s the
data used, stamp the recording's last sample, modes with the verb's ids and status
``identified``: the same modes as ``maglev-ros modes BAG`` on the replayed bag.

Parameters (also from YAML: ``--params-file config/modal_id.yaml``); 0 = chosen from the stream:
window_s (0), update_s (2), decimate_to_hz (0; a rate: one band there), block_rows (0),
max_order (0), order_step (4), fmin_hz (0), fmax_hz (0), n_blocks (0), freq_tol (0.03), mac_min
(0.8), max_misses (3), min_confirm (2), channels (string[]; default: every vertical guideway
accelerometer), skip_when_busy (true), recording_modes (true: the whole-recording identification
at each end),
max_recording_mb (1000: a longer recording, as received, is not kept and gets no whole-recording
modes: a live stream that never ends must not fill the memory).
"""
from __future__ import annotations

import math
import sys
import threading
from collections import deque
from dataclasses import fields

from rclpy.duration import Duration
from rclpy.node import Node
from std_msgs.msg import String

from maglev_msgs.msg import ModalEstimate, ModalMode, SensorBlock
from maglev_ros.contract import TOPIC_GUIDEWAY_ACCEL, TOPIC_METADATA, TOPIC_VEHICLE_POSITION, parse_metadata
from maglev_ros.modal.tracking import OnlineModalConfig, OnlineModalID
from maglev_ros.nodes._common import BlockGate, background_thread, block_from_msg, run_node, stamp_to_msg
from maglev_ros.nodes._diagnostics import NodeDiagnostics
from maglev_ros.nodes._lifecycle import RECORDING_END, NodeLifecycle
from maglev_ros.nodes._params import Param, declare
from maglev_ros.nodes._qos import publisher, subscription

TOPIC_MODES = "/maglev/modes"
METHOD_ONLINE = "ssi-cov online"
METHOD_RECORDING = "ssi-cov whole recording"
STATUS_RECORDING = "identified"
# upper bound on waiting for reliable subscribers to acknowledge a recording's result
ACK_TIMEOUT_S = 30.0
# settings whose 0 means "chosen from the stream" (None in OnlineModalConfig)
AUTO = ("window_s", "decimate_to_hz", "block_rows", "max_order", "fmin_hz", "fmax_hz", "n_blocks")
INTS = ("block_rows", "max_order", "order_step", "n_blocks", "max_misses", "min_confirm")
# the parameters are OnlineModalConfig's fields (defaults from there): description, range
DESCRIPTIONS = {
    "window_s": ("sliding window [s] (0: the recording so far, from the shortest record the verb's rules "
                 "need for fmin, up to max_window_s)", (0.0, 3600.0)),
    "max_window_s": ("with window_s 0: the tracking horizon [s]", (0.0, 1e6)),
    "update_s": ("stream time between identifications [s]", (0.01, 3600.0)),
    "decimate_to_hz": ("decimate the stream to this rate before SSI [Hz] (0: bands as the verb)", (0.0, 1e6)),
    "block_rows": ("block rows of the SSI Hankel matrix (0: as the verb)", (0, 100000)),
    "max_order": ("highest model order of the stabilization diagram (0: as the verb)", (0, 100000)),
    "order_step": ("step between model orders", (1, 1000)),
    "fmin_hz": ("lowest frequency of a mode [Hz] (0: as the verb)", (0.0, 1e6)),
    "fmax_hz": ("highest frequency of a mode [Hz] (0: as the verb)", (0.0, 1e6)),
    "n_blocks": ("blocks of the covariance estimate, its uncertainty (0: as the verb)", (0, 100000)),
    "freq_tol": ("relative frequency tolerance when tracking a mode", (0.0, 1.0)),
    "mac_min": ("lowest MAC when tracking a mode", (0.0, 1.0)),
    "max_misses": ("updates a mode may miss before it is lost", (0, 100000)),
    "min_confirm": ("updates a new mode needs before it is published as tracked", (0, 100000)),
}


def _params() -> tuple[Param, ...]:
    out = []
    defaults = OnlineModalConfig()
    for f in fields(OnlineModalConfig):
        d = getattr(defaults, f.name)
        d = 0 if d is None else d
        d = int(d) if f.name in INTS else float(d)
        text, rng = DESCRIPTIONS.get(f.name, (f"OnlineModalConfig.{f.name} (maglev_ros.modal.tracking)", None))
        out.append(Param(f.name, d, text, range=rng))
    out += [Param("channels", [""], "guideway accelerometer channels to identify from (empty: every "
                                    "vertical one in the metadata)"),
            Param("skip_when_busy", True, "leave out a window that completes while the previous one is still "
                                          "identified and another waits (false: every window, however late)"),
            Param("recording_modes", True, "at each recording's end, the whole-recording identification "
                                           "of the modes verb"),
            Param("max_recording_mb", 1000.0, "keep at most this much of a recording for its end [MB]",
                  range=(0.0, 1e6))]
    return tuple(out)


class ModalIdNode(Node):
    def __init__(self) -> None:
        super().__init__("modal_id")
        v = declare(self, _params())
        values = {f.name: (None if (f.name in AUTO and not v[f.name]) else v[f.name])
                  for f in fields(OnlineModalConfig)}
        self.core = OnlineModalID(OnlineModalConfig(**values))
        self.wanted = [c for c in v["channels"] if c]
        self.wanted_given = bool(self.wanted)
        self.recording_modes = bool(v["recording_modes"])
        self.skip_when_busy = bool(v["skip_when_busy"])
        self.pub = publisher(self, ModalEstimate, TOPIC_MODES)
        self.diagnostics = NodeDiagnostics(self)
        self.gate = BlockGate(self, self.diagnostics)
        from maglev_ros.bag_memory import RecordingCollector
        max_mb = float(v["max_recording_mb"])
        self.collector = RecordingCollector((TOPIC_GUIDEWAY_ACCEL, TOPIC_VEHICLE_POSITION),
                                            name=f"{self.get_fully_qualified_name()} recording",
                                            max_bytes=max_mb * 1e6)
        self.lock = threading.Lock()               # the collector: fed by callbacks, emptied at an end
        # the worker's queue, in order: ("window", job, stamp_ns) | ("recording", bag, None); a
        # recording's windows come before its whole-recording job and before the next one's windows,
        # and a job carries its own tracker: what a recording's windows give stays that recording's
        self.jobs: deque = deque()
        self.wake = threading.Condition(self.lock)
        self.n_jobs = 0                            # queued or running, not yet published
        self.windows_skipped = 0
        subscription(self, String, TOPIC_METADATA, self._on_metadata)
        subscription(self, SensorBlock, TOPIC_GUIDEWAY_ACCEL, self._on_block)
        if self.recording_modes:   # a pass's free decay starts where the vehicle has left the span
            subscription(self, SensorBlock, TOPIC_VEHICLE_POSITION, self._on_position)
        self.worker = threading.Thread(target=self._work, name="modal_id-worker", daemon=True)
        self.worker.start()
        self.diagnostics.add_check(self._worker_check)
        self.lifecycle = NodeLifecycle(self, ready=True, diagnostics=self.diagnostics)

    # ------------------------------------------------------------------ the stream
    def _on_metadata(self, msg) -> None:
        self.gate.new_stream()
        # a recording that ended before its metadata came; on a live stream (no recording_end)
        # the recording that new metadata ends
        done = self._finish(lambda: self.collector.set_metadata(
            msg.data, metadata_ends=not self.lifecycle.events_seen))
        if done is not None:
            self._recording_ended(done)
        if self.wanted_given:
            return
        try:
            md = parse_metadata(msg.data, TOPIC_METADATA)
        except Exception as exc:  # noqa: BLE001
            self.get_logger().error(f"metadata unusable: {exc}")
            return
        self.wanted = [sid for sid, s in md.sensors_on_topic(TOPIC_GUIDEWAY_ACCEL).items()
                       if s.direction in (None, "vertical")]

    def _on_position(self, msg) -> None:
        if self.gate.block(msg, TOPIC_VEHICLE_POSITION) is not None:
            self._keep(TOPIC_VEHICLE_POSITION, msg)

    def _on_block(self, msg) -> None:
        block = self.gate.block(msg, TOPIC_GUIDEWAY_ACCEL)
        if block is None:
            return
        if self.recording_modes:
            self._keep(TOPIC_GUIDEWAY_ACCEL, msg)
        cols = list(range(len(block.channels)))
        if self.wanted:
            cols = [j for j, c in enumerate(block.channels) if c in self.wanted] or cols
        channels = [block.channels[j] for j in cols]
        try:
            windows = self.core.push_windows(block.stamp_s, block.data[:, cols], channels,
                                             block.sample_rate_hz)
        except Exception as exc:  # noqa: BLE001  (bad block: report, keep running)
            self.get_logger().error(f"{TOPIC_GUIDEWAY_ACCEL} block at {block.stamp_s:.3f} s: {exc}")
            return
        for job in windows:
            self._submit(("window", job, block.stamp_ns))

    def _submit(self, item) -> None:
        with self.wake:
            if item[0] == "window" and self.skip_when_busy:
                waiting = [j for j in self.jobs if j[0] == "window"]
                for j in waiting:                  # the newest window replaces one still waiting
                    self.jobs.remove(j)
                self.windows_skipped += len(waiting)
                self.n_jobs -= len(waiting)
            self.jobs.append(item)
            self.n_jobs += 1
            self.wake.notify()

    def _identify_window(self, job, stamp_ns: int) -> None:
        try:
            up = self.core.identify(job)
        except Exception as exc:  # noqa: BLE001  (a window the SSI refuses: report, keep running)
            self.get_logger().error(f"{TOPIC_GUIDEWAY_ACCEL} window ending {stamp_ns * 1e-9:.3f} s: {exc}")
            return
        if up.modes or up.events:       # nothing confirmed yet (a mode gets its id when seen twice)
            self.pub.publish(self._message(up, stamp_ns, job["window_s"]))

    def _worker_check(self):
        from maglev_ros.nodes._diagnostics import OK, Check
        return Check(OK, "", {"windows_skipped": self.windows_skipped, "worker_queue": self.n_jobs})

    def _keep(self, topic: str, msg) -> None:
        """The block as received (the verb's reader converts units itself) for the recording's end."""
        with self.lock:
            was = self.collector.overflowed
            self.collector.add(topic, block_from_msg(msg))
            now = self.collector.overflowed
        if now and not was:
            self.get_logger().warning(
                f"the recording exceeds max_recording_mb ({self.collector.max_bytes / 1e6:g} MB): it is not "
                f"kept and gets no whole-recording modes; the online estimates go on")

    def _message(self, update, stamp_ns: int, window_s: float) -> ModalEstimate:
        out = ModalEstimate()
        stamp_to_msg(stamp_ns, out.header)
        out.header.frame_id = "guideway"
        out.method = METHOD_ONLINE
        out.window_s = float(window_s)
        new = {e.id for e in update.events if e.kind == "new"}
        for m in update.modes:
            out.modes.append(_mode_msg(m.id, "new" if m.id in new else "tracked", m))
        for e in update.events:
            if e.kind == "lost":
                mm = ModalMode()
                mm.id, mm.status, mm.frequency_hz = e.id, "lost", float(e.frequency_hz)
                mm.damping_ratio = mm.std_frequency_hz = mm.std_damping_ratio = mm.mpc = float("nan")
                out.modes.append(mm)
        return out

    # ------------------------------------------------------------------ recording ends
    def on_recording_start(self, index: int) -> None:
        with self.lock:
            lost = self.collector.abandon()
        if lost is not None:
            self.get_logger().error(f"{lost}: its {TOPIC_METADATA} never came: no whole-recording modes for it")

    def on_recording_end(self, index: int) -> None:
        """The replay's recording ``index`` has ended: identify it whole (worker thread)."""
        ev = self.lifecycle.event(RECORDING_END, index)
        source = ev.bag if ev is not None and ev.bag else None
        bag = self._finish(lambda: self.collector.end(source))
        if bag is not None:
            self._recording_ended(bag)
            return
        self.core.reset()
        if self.collector.waiting:
            self.get_logger().info(f"recording {index} ended before its {TOPIC_METADATA}: waiting for it")

    def _finish(self, step):
        """``step`` (a collector call that may complete a recording) under the lock; a recording
        whose metadata is not valid is logged and skipped."""
        from maglev_ros.errors import ContractError
        try:
            with self.lock:
                return step()
        except ContractError as exc:
            self.get_logger().error(f"recording not identified: {exc}")
            return None

    def _recording_ended(self, bag) -> None:
        self.core.reset()                    # the next recording is tracked afresh
        if not self.recording_modes or not bag.has(TOPIC_GUIDEWAY_ACCEL):
            return
        self._submit(("recording", bag, None))     # after the recording's last windows

    def busy(self) -> bool:
        return self.n_jobs > 0 or self.collector.waiting

    def _work(self) -> None:
        if self.skip_when_busy:
            # windows left out when it is busy: its SSI yields to the stream work of the graph's
            # nodes (fewer updates on a machine short of cores, the streams still taken in time)
            background_thread()
        while True:
            with self.wake:
                while not self.jobs:
                    self.wake.wait()
                kind, what, stamp_ns = self.jobs.popleft()
            try:
                if kind == "window":
                    self._identify_window(what, stamp_ns)
                else:
                    self._identify(what)
            except Exception as exc:  # noqa: BLE001  (a recording the verb refuses must not end the node)
                self.get_logger().error(f"{what.path}: whole-recording modes not identified: {exc}")
            finally:
                with self.lock:
                    self.n_jobs -= 1

    def _identify(self, bag) -> None:
        from maglev_ros.commands.modes import identify_modes
        out = identify_modes(bag)
        res, info = out.result, out.info
        acc = bag.read_topic(TOPIC_GUIDEWAY_ACCEL)
        end_s = float(acc.time_s[-1]) if acc.n_samples else 0.0
        msg = ModalEstimate()
        stamp_to_msg(int(round(end_s * 1e9)), msg.header)
        msg.header.frame_id = "guideway"
        w = info.get("free_decay_window")
        msg.method = METHOD_RECORDING + (", free decay" if w else "")
        msg.window_s = float(w["stop_s"] - w["start_s"]) if w else info["n_samples"] / info["fs_hz"]
        for m in res.modes:
            msg.modes.append(_mode_msg(m.id, STATUS_RECORDING, m))
        self.pub.publish(msg)
        # done (maglev/status) only once reliable subscribers hold the result
        self.pub.wait_for_all_acked(Duration(seconds=ACK_TIMEOUT_S))
        self.get_logger().info(
            f"{bag.path}: whole-recording modes ({info['run_kind']}, as `maglev-ros modes`): "
            + (", ".join(f"{m.frequency_hz:.3f} Hz ({100 * m.damping_ratio:.2f} %)" for m in res.modes)
               or "none stable"))


def _mode_msg(mode_id: str, status: str, m) -> ModalMode:
    """A ModalMode from a tracked or identified mode (frequency, damping, stds, MPC, shape dict)."""
    mm = ModalMode()
    mm.id, mm.status = str(mode_id), status
    mm.frequency_hz = float(m.frequency_hz)
    mm.damping_ratio = float(m.damping_ratio)
    mm.std_frequency_hz = _finite(m.std_frequency_hz)
    mm.std_damping_ratio = _finite(m.std_damping_ratio)
    mm.mpc = _finite(m.mpc)
    mm.channels = [str(c) for c in m.mode_shape]
    mm.mode_shape = [float(v) for v in m.mode_shape.values()]
    return mm


def _finite(x) -> float:
    return float(x) if x is not None and math.isfinite(float(x)) else float("nan")


def main(args=None) -> int:
    return run_node(ModalIdNode, args)


if __name__ == "__main__":
    sys.exit(main())
