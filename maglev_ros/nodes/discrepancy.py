"""Node ``discrepancy``: watches the twin's residual stream and publishes mismatch reports.

Subscribes every /maglev/twin/residual/<group> (SensorBlock; the twin's groups from the start, other
residual topics as they appear in the graph),
/testline/vehicle/position and the measured streams ``measured_topics`` (for the relative
allowance; channels matched by name); publishes maglev_msgs/MismatchReport on /maglev/mismatch
when ``discrepancy.online.OnlineDetector`` closes an incident (one report per incident: all its
channels, its time/position span, the union band; per-channel bands in ``detail_json``), and
flushes the open incident when the node shuts down. The report's header stamp is the stream time
at which the incident was concluded (monotonic; a late-arriving channel's earlier incident says
"reported late"), its t0_s/t1_s the incident itself. Thin adapter: the logic is in the core.
Parameters (``PARAMS``, with descriptions and ranges; see the core's docstring): ``threshold`` (10, residual power / noise floor),
``frame_s`` (0.5), ``hop_s`` (0.25), ``min_frames`` (2), ``max_s`` (5, longest incident),
``merge_gap_s`` (1, runs closer than this are one incident), ``allowance_factor`` (4, x the learned
peak residual of earlier passes), ``learn_rate`` (0.1), ``learn_rate_reported`` (1),
``rel_allowance`` (0.3, tolerated band amplitude misfit; 0 = off: the residual's own power is
judged), ``measured_topics``.

The incident rule (``discrepancy.online``): with the measured streams (default) a cell is judged
as ``maglev-ros diagnose`` judges one, by the band amplitudes of measured vs twin + noise floor
(tolerance max(``rel_allowance`` = 0.3, 3 / sqrt(dof)), excess over 3 x the floor); severity is the
band power excess over the floor.

The diagnosis (``live_diagnosis``, default true): the measured streams, the position and the
metadata are assembled into recordings (:mod:`maglev_ros.discrepancy.live`); an ambient recording
is kept and a pass is diagnosed on a worker thread with the ambient and the last ``max_passes`` (2)
passes by the same stages as ``maglev-ros diagnose`` (same recordings, same report). Each
missing-physics entry and located mismatch goes out as a MismatchReport (effect, category,
explanation filled; the entry in ``detail_json``) and the whole report (schema maglev-diagnosis/1)
on /maglev/diagnosis (std_msgs/String, latched). ``n_top`` and ``fit_every_effect``: the
diagnosis' settings (defaults as ``maglev-ros diagnose``; fewer hypotheses for a quicker answer).

Where a recording ends: with a replay (graph run protocol, :mod:`maglev_ros.nodes._lifecycle`) at
its ``recording_end``: the recording (with the metadata received last) goes to the diagnosis and,
once every residual producer (a node whose status ``detail`` carries ``residual_blocks``: the
twin) has said ``done`` for it and its residual blocks of that recording have all arrived (or
after ``residual_wait_s`` = 60 s, with a warning), the open incident is closed and published; the
node is ``busy`` until then and until the diagnosis and its MismatchReports are out. Without a
replay (a live stream: no replay event ever seen), a pause of ``recording_idle_s`` (2 s of wall
time) in the measured streams ends a recording, and the open incident is published at shutdown.
The node says ``ready`` once the twin's kernels are warm (:mod:`maglev_ros.twin.warm`; the
diagnosis runs the twin) when ``live_diagnosis`` is on.
"""
from __future__ import annotations

import json
import math
import queue
import sys
import threading
import time
from collections import Counter

from rclpy.node import Node
from std_msgs.msg import String

from maglev_msgs.msg import MismatchReport, SensorBlock
from maglev_ros.contract import DATA_TOPICS, TOPIC_METADATA, TOPIC_VEHICLE_POSITION, parse_metadata
from maglev_ros.discrepancy.online import OnlineDetector
from maglev_ros.errors import ContractError
from maglev_ros.nodes._common import BlockGate, background_thread, run_node, stamp_to_msg
from maglev_ros.nodes._diagnostics import NodeDiagnostics
from maglev_ros.nodes._params import Param, declare
from maglev_ros.nodes._qos import local_topic, publisher, subscription
from maglev_ros.nodes._lifecycle import QOS_STATUS_READER, TOPIC_STATUS, WARMING, NodeLifecycle, NodeStatus

TOPIC_MISMATCH = "/maglev/mismatch"
TOPIC_DIAGNOSIS = "/maglev/diagnosis"
RESIDUAL_PREFIX = "/maglev/twin/residual/"
# the measured streams the twin's residual groups are computed from
MEASURED_TOPICS = tuple(t for t in DATA_TOPICS if t != TOPIC_VEHICLE_POSITION)
# the twin's residual groups (twin/online.py GROUP_TOPICS), subscribed from the start
RESIDUAL_GROUPS = ("guideway_accel", "guideway_displacement", "vehicle_accel", "vehicle_gap", "body_accel")

# the online detector's settings (OnlineDetector), read at construction
PARAMS = (
    Param("frame_s", 0.5, "analysis frame of the residual [s]", range=(0.01, 600.0)),
    Param("hop_s", 0.25, "hop between frames [s]", range=(0.001, 600.0)),
    Param("threshold", 10.0, "residual power / noise floor that counts as a mismatch", range=(1.0, 1e9)),
    Param("min_frames", 2, "frames in a row above the threshold that open an incident", range=(1, 10000)),
    Param("max_s", 5.0, "longest incident [s]", range=(0.01, 86400.0)),
    Param("merge_gap_s", 1.0, "runs closer than this are one incident [s]", range=(0.0, 86400.0)),
    Param("allowance_factor", 4.0, "times the peak residual learned on earlier passes that is tolerated",
          range=(0.0, 1e6)),
    Param("learn_rate", 0.1, "learning rate of the tolerated residual", range=(0.0, 1.0)),
    Param("learn_rate_reported", 1.0, "learning rate after a reported incident", range=(0.0, 1.0)),
    Param("rel_allowance", 0.3, "tolerated residual / measured amplitude (0: off)", range=(0.0, 1e3)),
    Param("measured_topics", list(MEASURED_TOPICS), "measured streams the relative allowance and the "
                                                     "diagnosis read"),
    Param("live_diagnosis", True, "diagnose each recording as maglev-ros diagnose does"),
    Param("recording_idle_s", 2.0, "no data for this long (wall time) ends a recording [s]",
          range=(0.01, 1e9), apply=lambda node, v: setattr(node, "idle_s", v)),
    Param("residual_wait_s", 60.0, "after a recording's end, wait this long for the twin's last residual "
                                   "blocks before closing its incidents [s]", range=(0.0, 1e6)),
)


def diagnosis_params(config) -> tuple[Param, ...]:
    """The diagnosis' settings (declared with live_diagnosis), defaults from ``config``
    (DiagnoseConfig, imported only then: it takes seconds)."""
    return (
        Param("n_top", config.n_top, "physics hypotheses fully fitted after screening", range=(0, 1000)),
        Param("fit_every_effect", config.fit_every_effect, "also fit the best of every further effect "
                                                           "(false: the n_top only)"),
        Param("max_passes", 2, "latest passes diagnosed together with the ambient recording", range=(1, 100)),
    )


class DiscrepancyNode(Node):
    def __init__(self) -> None:
        super().__init__("discrepancy")
        v = declare(self, PARAMS)
        self.detector = OnlineDetector(
            frame_s=v["frame_s"], hop_s=v["hop_s"], threshold=v["threshold"], min_frames=v["min_frames"],
            max_s=v["max_s"], merge_gap_s=v["merge_gap_s"], allowance_factor=v["allowance_factor"],
            learn_rate=v["learn_rate"], learn_rate_reported=v["learn_rate_reported"],
            rel_allowance=v["rel_allowance"])
        measured = list(v["measured_topics"] or [])
        self.live = v["live_diagnosis"]
        self.idle_s = v["recording_idle_s"]
        self.residual_wait_s = v["residual_wait_s"]
        self.pub = publisher(self, MismatchReport, TOPIC_MISMATCH)
        self.pub_diag = publisher(self, String, TOPIC_DIAGNOSIS)
        self.diagnostics = NodeDiagnostics(self)
        self.gate = BlockGate(self, self.diagnostics)
        self.subs = {}
        subscription(self, SensorBlock, TOPIC_VEHICLE_POSITION, self._on_position)
        if self.detector.rel_allowance > 0 or self.live:
            for topic in measured:
                if topic:
                    subscription(self, SensorBlock, topic, self._on_measured(topic))
        self.assembler = self.diagnoser = None
        if self.live:
            from maglev_ros.discrepancy.live import LiveDiagnoser, RecordingAssembler
            self.assembler = RecordingAssembler(source=self.get_fully_qualified_name())
            from maglev_ros.discrepancy.diagnose import DiagnoseConfig
            d = declare(self, diagnosis_params(DiagnoseConfig))
            cfg = DiagnoseConfig(n_top=d["n_top"], fit_every_effect=d["fit_every_effect"])
            self.diagnoser = LiveDiagnoser(cfg, max_passes=d["max_passes"])
            subscription(self, String, TOPIC_METADATA, self._on_metadata)
            self._lock = threading.Lock()           # the assembler is fed by callbacks, emptied by the timer
            self._last_data = None
            self._metadata = None
            self._queue = queue.SimpleQueue()    # completed recordings, diagnosed in order by one worker
            threading.Thread(target=self._diagnose_queue, daemon=True).start()
            self.create_timer(0.5, self._check_idle)
        # graph run protocol: recording ends, residual producers' counts, results out before done
        self._diag_pending = 0                  # recordings submitted, their reports not yet out
        self._diag_lock = threading.Lock()
        self._ending: int | None = None         # a recording that ended, its incidents not yet out
        self._ending_since = 0.0
        self._received: Counter = Counter()     # residual group -> blocks of this recording
        self._producers: dict[str, NodeStatus] = {}
        self.create_subscription(String, TOPIC_STATUS, self._on_status, QOS_STATUS_READER)
        for g in RESIDUAL_GROUPS:
            self._subscribe_residual(RESIDUAL_PREFIX + g)
        self.create_timer(0.1, self._progress)
        self.create_timer(0.5, self._discover)
        self._discover()
        self._warm = None if self.live else "no live diagnosis: nothing to warm"
        self.lifecycle = NodeLifecycle(self, ready=not self.live, diagnostics=self.diagnostics)
        if self.live:
            threading.Thread(target=self._warm_kernels, daemon=True).start()
            self.create_timer(0.2, self._check_warm)

    def _warm_kernels(self) -> None:
        from maglev_ros.twin.warm import warm
        try:
            self._warm = warm().summary()
        except Exception as exc:  # noqa: BLE001  (the diagnosis then compiles on first use)
            self._warm = f"warm-up failed ({exc}); kernels compile on first use"

    def _check_warm(self) -> None:
        if self._warm is not None and self.lifecycle.status.state == WARMING:
            self.get_logger().info(self._warm)
            self.lifecycle.set_ready(self._warm)

    # --- graph run protocol
    def on_recording_end(self, index: int) -> None:
        """The recording goes to the diagnosis; its incidents are closed once the twin's residuals
        of it are all in (:meth:`_progress`)."""
        if self.live:
            with self._lock:
                self._last_data = None
                done = self._finished(lambda: self.assembler.finish(self._metadata))
            if done is not None:
                self._submit(done)
        self.gate.new_stream()          # the next recording sets its own layout
        self._ending, self._ending_since = index, time.monotonic()
        self._progress()

    def busy(self) -> bool:
        with self._diag_lock:
            return self._ending is not None or self._diag_pending > 0

    def _on_status(self, msg) -> None:
        st = NodeStatus.from_json(msg.data)
        if st is None:
            return
        try:
            detail = json.loads(st.detail) if st.detail.startswith("{") else {}
        except ValueError:
            detail = {}
        if isinstance(detail, dict) and "residual_blocks" in detail:
            self._producers[st.node] = st
            self._progress()

    def _residuals_in(self, index: int) -> bool:
        """Every residual producer said done for ``index`` and its residual blocks of it arrived."""
        for st in self._producers.values():
            d = json.loads(st.detail)
            if st.state == WARMING or st.done < index or d.get("recording") != index:
                return False
            if any(self._received[g] < n for g, n in d.get("residual_blocks", {}).items()):
                return False
        return True

    def _progress(self) -> None:
        """Close the ended recording's incidents once its residuals are all in."""
        index = self._ending
        if index is None:
            return
        if not self._residuals_in(index):
            if time.monotonic() - self._ending_since < self.residual_wait_s:
                return
            self.get_logger().warning(
                f"recording {index}: residual blocks still missing after {self.residual_wait_s:g} s "
                f"(received {dict(self._received)}; producers {[s.to_json() for s in self._producers.values()]}); "
                f"closing its incidents without them")
        for ev in self.detector.flush():
            self._publish(ev)
        self.detector.new_stream()
        self._received.clear()
        with self._diag_lock:
            self._ending = None

    def _discover(self) -> None:
        for fq_name, types in self.get_topic_names_and_types():
            name = local_topic(self, fq_name)       # only the residuals of our own namespace
            if (name is not None and name.startswith(RESIDUAL_PREFIX) and name not in self.subs
                    and "maglev_msgs/msg/SensorBlock" in types):
                self._subscribe_residual(name)

    def _subscribe_residual(self, name: str) -> None:
        if name not in self.subs:
            self.subs[name] = subscription(self, SensorBlock, name, self._on_residual(name))

    def _on_position(self, msg) -> None:
        b = self.gate.block(msg, TOPIC_VEHICLE_POSITION)
        if b is not None and "position_m" in b.channels:
            self.detector.add_position(b.times_s(), b.data[:, b.channels.index("position_m")])
        if b is not None:
            self._collect(TOPIC_VEHICLE_POSITION, b)

    def _on_measured(self, topic: str):
        def cb(msg) -> None:
            b = self.gate.block(msg, topic)
            if b is None:
                return
            if self.detector.rel_allowance > 0:
                for ev in self.detector.add_measured_block(b):
                    self._publish(ev)
            self._collect(topic, b)
        return cb

    # --- the diagnosis of whole recordings (same stages as `maglev-ros diagnose`)
    def _collect(self, topic, block) -> None:
        if self.assembler is None:
            return
        with self._lock:
            self.assembler.add_block(topic, block)
            self._last_data = time.monotonic()

    def _on_metadata(self, msg) -> None:
        try:
            md = parse_metadata(msg.data, TOPIC_METADATA).raw
        except ContractError as exc:
            self.get_logger().error(f"{exc}; recordings are not diagnosed")
            return
        self.gate.new_stream()       # a new recording may have its own layout (rate, channels)
        with self._lock:
            # taken when the recording ends: across topics DDS does not order delivery, and the first
            # blocks of a new recording can arrive before its metadata
            self._metadata = md

    def _check_idle(self) -> None:
        """Without a replay: a pause of ``recording_idle_s`` in the stream ends a recording; it
        carries the metadata received last."""
        if self.lifecycle.events_seen:
            return
        with self._lock:
            idle = self._last_data is not None and time.monotonic() - self._last_data > self.idle_s
            done = None
            if idle:
                self._last_data = None
                done = self._finished(lambda: self.assembler.finish(self._metadata))
        if idle:
            self.gate.new_stream()   # the next recording sets its own layout
        if done is not None:
            self._submit(done)

    def _finished(self, step):
        try:
            return step()
        except ContractError as exc:     # a recording that cannot be diagnosed must not end the node
            self.get_logger().error(f"recording not diagnosed: {exc}")
            return None

    def _submit(self, rec) -> None:
        with self._diag_lock:
            self._diag_pending += 1
        self._queue.put(rec)

    def _diagnose_queue(self) -> None:
        background_thread()          # a diagnosis takes tens of CPU seconds: the streams come first
        while True:
            rec = self._queue.get()
            self.get_logger().info(f"recording complete ({rec.kind}, {rec.t1_s - rec.t0_s:.1f} s)"
                                   + (": diagnosing" if rec.kind == "pass" else ": kept as the ambient recording"))
            try:
                d = self.diagnoser.add_recording(rec)
                if d is not None:
                    self._publish_diagnosis(d.to_dict())
            except Exception as exc:      # a recording the diagnosis refuses must not end the node
                self.get_logger().error(f"diagnosis failed: {exc}")
            finally:
                with self._diag_lock:
                    self._diag_pending -= 1

    def _publish_diagnosis(self, rep) -> None:
        from maglev_ros.discrepancy.live import diagnosis_events
        self.pub_diag.publish(String(data=json.dumps(rep, default=_json_default)))
        for ev in diagnosis_events(rep):
            out = MismatchReport()
            stamp_to_msg(self.get_clock().now().nanoseconds, out.header)
            out.header.frame_id = "testline"
            out.channels = [str(c) for c in ev["channels"]]
            out.t0_s, out.t1_s = (float(x) for x in ev["time_s"])
            out.position_start_m, out.position_end_m = (float(x) for x in ev["position_m"])
            out.f0_hz, out.f1_hz = (float(x) for x in ev["frequency_hz"])
            out.severity = float(ev["severity"])
            out.effect, out.category, out.explanation = ev["effect"], ev["category"], ev["explanation"]
            out.detail_json = json.dumps(ev["detail"], default=_json_default)
            self.pub.publish(out)
        n = len(rep.get("missing_physics", []))
        self.get_logger().info(f"diagnosis: fit {rep['fit_before']['nrmse']:.3f} -> {rep['fit_after']['nrmse']:.3f}; "
                               f"missing physics: {', '.join(m['effect'] for m in rep['missing_physics']) or 'none'}"
                               f" ({n} entr{'y' if n == 1 else 'ies'})")

    def _on_residual(self, topic: str):
        group = topic.rsplit("/", 1)[-1]

        def cb(msg) -> None:
            self._received[group] += 1
            b = self.gate.block(msg, topic)
            if b is None:
                return
            for ev in self.detector.add_block(b):
                self._publish(ev)
        return cb

    def _publish(self, ev) -> None:
        out = MismatchReport()
        # stamped when concluded (monotonic; the incident's own interval is t0_s..t1_s)
        stamp_to_msg(int(round(ev.reported_s * 1e9)), out.header)
        out.header.frame_id = "testline"
        out.channels = list(ev.channels)
        out.t0_s, out.t1_s = float(ev.t0_s), float(ev.t1_s)
        out.position_start_m, out.position_end_m = float(ev.position_start_m), float(ev.position_end_m)
        out.f0_hz, out.f1_hz = float(ev.f0_hz), float(ev.f1_hz)
        out.severity = float(ev.severity)
        out.effect, out.category, out.explanation = ev.effect, ev.category, ev.explanation
        out.detail_json = ev.detail_json
        self.pub.publish(out)

    def destroy_node(self):
        """Shutdown: publish the incident still open (end of stream) before going away."""
        try:
            for ev in self.detector.flush():
                self._publish(ev)
        except Exception as exc:  # never block the shutdown
            self.get_logger().warning(f"flush on shutdown failed: {exc}")
        return super().destroy_node()


def _json_default(x):
    f = float(x)
    return None if not math.isfinite(f) else f


def main(args=None) -> int:
    return run_node(DiscrepancyNode, args)


if __name__ == "__main__":
    sys.exit(main())
