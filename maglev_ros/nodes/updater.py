"""Node ``updater``: online model updating (thin adapter over maglev_ros/updating/online.py).

Subscribes /testline/metadata (latched), /maglev/modes (ModalEstimate),
/maglev/twin/residual/vehicle_accel (SensorBlock) and, for the magnet layer's twin input,
/testline/vehicle/{accel,gap,position}. Publishes /maglev/twin/parameters (TwinParameters,
latched) after each accepted update; each accepted update is stored in the parameter history
(parameter ``history_path``, append-only JSON lines, one writer: a second updater on the same file
is refused at start; unset: memory only), tagged with the line (a hash
of the metadata's line and design blocks). When the metadata arrives, the last record of THAT line
is republished, so a restarted node (and a late twin) get the current parameters; records of
another line are never loaded, and the log says what was loaded and from where.

Parameters (``PARAMS``, with descriptions and ranges): ``history_path`` (default unset: memory
only; ``maglev-ros launch`` sets it in its ``--out`` directory), ``freq_rel_tol`` (2e-3, live),
``n_sigma`` (3.0, live), ``max_modes`` (4), ``magnet_min_s`` (3.0), ``nrmse_trigger`` (0.15, live),
``max_window_s`` (8.0), ``max_lag_s`` (10.0: extra seconds of vehicle streams kept, as the twin's
residuals lag the stream), ``min_speed_mps`` (0.1), ``magnet_layer`` (true, live: run it when the
residual warrants). Residual blocks with NaN (the twin had no measured irregularity under every
magnet) or of a parameter revision older than the accepted one (frame_id "twin rev <n>") are
never judged; why the magnet layer waits is logged once per reason.
The magnet layer takes tens of seconds; it runs in a worker thread on copies of the buffered
window and the current parameters, without holding the node's lock (the node keeps receiving
and updating the guideway meanwhile); only accepting and storing the result takes the lock. The
guideway layer (seconds per fit) runs the same way on a worker of its own, one fit at a time: an
estimate that arrives meanwhile waits, a newer one replaces it (counted on /diagnostics as
``guideway_estimates_superseded``), so the ``maglev/modes`` callback never holds the streams back.
These moving-window updates give the twin better parameters while a long recording still runs;
they see a window, not the recording, so they are not what the recording says.

At the end of each recording (the replay's ``recording_end``, :mod:`maglev_ros.nodes._lifecycle`;
on a live stream, metadata that differs from the current) the node runs the pipeline of
``maglev-ros update`` (``updating.pipeline.update_from_bags``, the verb's settings) on the
recordings as it received them (:class:`~maglev_ros.bag_memory.MemoryBag`, read by the verb's
own readers): an ambient recording alone (``update --ambient A``: E, rho, kb; it is kept as the
line's ambient), a pass with the last ambient recording of its line (``update --ambient A --pass
P``: every parameter). That runs on a worker thread (``busy()`` meanwhile; online results of the
ended recording are dropped), and its ``maglev-params/1`` parameters are stored in the history
and published as the next revision: the verb's ``params.json`` values. Its settings are
parameters named after the verb's options: ``end_max_modes`` (4), ``end_samples`` (60),
``end_polish_evals`` (8), ``end_swarm`` (int[] PARTICLES ITERATIONS; [] the verb's default),
``end_max_window_s`` (0: all), ``end_seed`` (0); ``recording_update`` (true) turns it off;
``max_recording_mb`` (1000): a longer recording, as received, is not kept and gets no
recording-end update (a live stream that never ends must not fill the memory).
"""
from __future__ import annotations

import math
import queue
import sys
import threading

from rclpy.duration import Duration
from rclpy.node import Node
from std_msgs.msg import String

from maglev_msgs.msg import ModalEstimate, SensorBlock, TwinParameters
from maglev_ros.contract import TOPIC_GUIDEWAY_ACCEL, TOPIC_GUIDEWAY_DISP, parse_metadata
from maglev_ros.nodes._common import BlockGate, background_thread, block_from_msg, run_node
from maglev_ros.nodes._diagnostics import NodeDiagnostics
from maglev_ros.nodes._lifecycle import RECORDING_END, NodeLifecycle
from maglev_ros.nodes._params import Param, declare
from maglev_ros.nodes._qos import publisher, subscription

TOPIC_PARAMETERS = "/maglev/twin/parameters"
TOPIC_MODES = "/maglev/modes"
TOPIC_RESIDUAL = "/maglev/twin/residual/vehicle_accel"
VEHICLE_TOPICS = ("/testline/vehicle/accel", "/testline/vehicle/gap", "/testline/vehicle/position")
# what the verb reads: the ambient's guideway accelerations, a pass's vehicle streams and displacement
RECORDED_TOPICS = (TOPIC_GUIDEWAY_ACCEL, TOPIC_GUIDEWAY_DISP, *VEHICLE_TOPICS)
# the modal_id node's whole-recording estimate: this node's own recording-end update covers it
WHOLE_RECORDING = "whole recording"
# upper bound on waiting for reliable subscribers to acknowledge a recording's result
ACK_TIMEOUT_S = 30.0


def _core(attr):
    """A live change of the core's setting ``attr`` (read by the core at each decision)."""
    return lambda node, value: setattr(node.core, attr, value)


PARAMS = (
    Param("history_path", "", "parameter history file (JSON lines, append-only, one writer; empty: "
                              "memory only)"),
    Param("freq_rel_tol", 2e-3, "relative frequency change of a mode that calls for a guideway update",
          range=(0.0, 1.0), apply=_core("freq_rel_tol")),
    Param("n_sigma", 3.0, "a change must exceed this many standard deviations", range=(0.0, 100.0),
          apply=_core("n_sigma")),
    Param("max_modes", 4, "modes used by the guideway layer", range=(1, 100)),
    Param("magnet_min_s", 3.0, "shortest window of valid residuals for the magnet layer [s]",
          range=(0.0, 3600.0)),
    Param("nrmse_trigger", 0.15, "residual NRMSE above which the magnet layer runs", range=(0.0, 100.0),
          apply=_core("nrmse_trigger")),
    Param("max_window_s", 8.0, "longest window of the magnet layer [s]", range=(0.1, 3600.0)),
    Param("max_lag_s", 10.0, "extra vehicle stream kept, as the twin's residuals lag the stream [s]",
          range=(0.0, 3600.0)),
    Param("min_speed_mps", 0.1, "slowest vehicle speed the magnet layer judges [m/s]", range=(0.0, 200.0)),
    Param("magnet_layer", True, "run the magnet layer when the residual warrants",
          apply=lambda node, v: setattr(node, "magnet_enabled", v)),
    Param("recording_update", True, "at each pass's end, the update verb's two-layer update on the recordings "
                                    "received (ambient + pass)"),
    Param("end_max_modes", 4, "recording-end update: modes used (as the verb's --max-modes)", range=(1, 100)),
    Param("end_samples", 60, "recording-end update: surrogate training samples (as the verb's)", range=(1, 100000)),
    Param("end_polish_evals", 8, "recording-end update: polishing evaluations (as the verb's)", range=(0, 100000)),
    Param("end_swarm", [0], "recording-end update: MOPSO particles and iterations (0: the verb's)"),
    Param("end_max_window_s", 0.0, "recording-end update: longest magnet-layer window [s] (0: the verb's)",
          range=(0.0, 1e6)),
    Param("end_seed", 0, "recording-end update: random seed (as the verb's --seed)", range=(0, 2**31 - 1)),
    Param("max_recording_mb", 1000.0, "keep at most this much of a recording for its end [MB]", range=(0.0, 1e6)),
)


class UpdaterNode(Node):
    def __init__(self) -> None:
        super().__init__("updater")
        from maglev_ros.updating.online import OnlineUpdater
        v = declare(self, PARAMS)
        self.core = OnlineUpdater(
            v["history_path"] or None,
            freq_rel_tol=v["freq_rel_tol"], n_sigma=v["n_sigma"], max_modes=v["max_modes"],
            magnet_min_s=v["magnet_min_s"], nrmse_trigger=v["nrmse_trigger"], max_window_s=v["max_window_s"],
            max_lag_s=v["max_lag_s"], min_speed_mps=v["min_speed_mps"])
        self.n_logged = 0
        self.magnet_enabled = v["magnet_layer"]
        self.recording_update = bool(v["recording_update"])
        swarm = [int(x) for x in v["end_swarm"] if int(x) > 0]
        self.end_settings = {"max_modes": int(v["end_max_modes"]),
                             "samples": int(v["end_samples"]),
                             "polish_evals": int(v["end_polish_evals"]),
                             "swarm": swarm[:2] if len(swarm) >= 2 else None,
                             "max_window_s": float(v["end_max_window_s"]) or None,
                             "seed": int(v["end_seed"])}
        self.pub = publisher(self, TwinParameters, TOPIC_PARAMETERS)
        self.diagnostics = NodeDiagnostics(self)
        self.gate = BlockGate(self, self.diagnostics)
        self.lock = threading.Lock()
        self.worker: threading.Thread | None = None
        # the guideway layer's worker (see _modes_work): running, the estimate waiting, superseded ones
        self.modes_worker: threading.Thread | None = None
        self.modes_running = False
        self.modes_next = None
        self.modes_superseded = 0
        self.diagnostics.add_check(self._modes_check)
        from maglev_ros.bag_memory import RecordingCollector
        self.collector = RecordingCollector(RECORDED_TOPICS, name=f"{self.get_fully_qualified_name()} recording",
                                            max_bytes=float(v["max_recording_mb"]) * 1e6)
        self.ambient = None               # the line's last ambient recording (MemoryBag)
        self.closed = False               # the recording has ended: its online results are dropped
        self.ended_span = None            # stream time [s] of the last ended recording's guideway data
        self.end_jobs: queue.SimpleQueue = queue.SimpleQueue()
        self.n_end_jobs = 0               # recordings handed to the end worker, not yet published
        self.end_worker: threading.Thread | None = None
        subscription(self, String, "/testline/metadata", self._on_metadata)
        subscription(self, ModalEstimate, TOPIC_MODES, self._on_modes)
        subscription(self, SensorBlock, TOPIC_RESIDUAL, self._on_residual)
        for t in VEHICLE_TOPICS:
            subscription(self, SensorBlock, t, self._vehicle(t))
        if self.recording_update:
            for t in (TOPIC_GUIDEWAY_ACCEL, TOPIC_GUIDEWAY_DISP):
                subscription(self, SensorBlock, t, self._recorded(t))
            self.end_worker = threading.Thread(target=self._end_work, daemon=True)
            self.end_worker.start()
        self.line: str | None = None      # line key of the metadata the history was restored for
        if self.core.history.path is None:
            self.get_logger().warning("history_path not set: accepted parameters are kept in memory only")
        else:   # the one writer of this file from now on (a second updater is refused here, one line)
            for w in self.core.history.open_writer():
                self.get_logger().warning(w)
        self.n_warned = 0
        self.lifecycle = NodeLifecycle(self, ready=True, diagnostics=self.diagnostics)

    def _drain_log(self) -> None:
        """Print the core's new log lines (call with the lock held)."""
        for line in self.core.log[self.n_logged:]:
            self.get_logger().info(line)
        self.n_logged = len(self.core.log)
        for line in self.core.warnings[self.n_warned:]:
            self.get_logger().warning(line)
        self.n_warned = len(self.core.warnings)

    def _publish(self, pub) -> None:
        m = TwinParameters()
        now = self.get_clock().now().to_msg()
        m.header.stamp = now
        m.revision = int(pub.revision)
        m.names = list(pub.names)
        m.values = [float(v) for v in pub.values]
        m.units = list(pub.units)
        m.std = [float(s) if math.isfinite(s) else float("nan") for s in pub.std]
        m.identifiable = [bool(b) for b in pub.identifiable]
        m.provenance_json = pub.provenance_json
        self.pub.publish(m)

    def _on_metadata(self, msg) -> None:
        from maglev_ros.errors import UserError
        from maglev_ros.updating.history import line_key
        self.gate.new_stream()
        waited = self.collector.waiting
        # a recording that ended before its metadata came; on a live stream (no recording_end)
        # the recording that new metadata ends
        done = self._finish(lambda: self.collector.set_metadata(
            msg.data, metadata_ends=not self.lifecycle.events_seen))
        if done is not None:
            self._recording_ended(done)
        if not waited:
            with self.lock:
                self.closed = False        # a new recording: its online results count again
        try:
            with self.lock:
                self.core.set_metadata(parse_metadata(msg.data, "/testline/metadata").raw)
                key = line_key(self.core.md.raw)
                if key == self.line:
                    return
                # a new line (or the first metadata): its own history, never another line's
                self.line = key
                restored = self.core.restore()
        except (UserError, ValueError) as exc:
            self.get_logger().error(f"/testline/metadata: {exc}")
            return
        self.get_logger().info(restored.message)
        for w in restored.warnings:
            self.get_logger().warning(w)
        if restored.publication is not None:
            self._publish(restored.publication)

    def _on_modes(self, msg) -> None:
        from maglev_ros.errors import UserError
        if WHOLE_RECORDING in msg.method and self.recording_update:
            return                                     # the recording-end update identifies them itself
        if all(m.status == "lost" for m in msg.modes):
            return                                     # no mode to update on
        stamp = msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec
        try:
            with self.lock:
                if self.closed or not self._of_this_recording(stamp):
                    return
                job = self.core.take_modes_job(list(msg.modes), stamp)
                self._drain_log()
                if job is None:
                    return
                if self.modes_running:         # one fit at a time; the newest estimate waits
                    self.modes_superseded += self.modes_next is not None
                    self.modes_next = job
                    return
                self.modes_running = True
        except UserError as exc:
            self.get_logger().error(f"{TOPIC_MODES}: {exc}")
            return
        self.modes_worker = threading.Thread(target=self._modes_work, args=(job,), daemon=True)
        self.modes_worker.start()

    def _modes_work(self, job) -> None:
        """The guideway layer's fits, one after the other, off the executor and without the lock (a
        fit takes seconds: run in the ``maglev/modes`` callback it held back every stream of the
        node); only accepting and storing a result takes the lock. An estimate that arrives while
        a fit runs waits; a newer one replaces it (the newest modes are the ones to fit)."""
        background_thread()
        from maglev_ros.errors import UserError
        while job is not None:
            try:
                result = self.core.compute_modes_update(job)
            except UserError as exc:
                self.get_logger().error(f"{TOPIC_MODES}: guideway layer: {exc}")
                result = None
            pub = None
            with self.lock:
                if result is not None and not self.closed:    # an ended recording: the end update decides
                    pub = self.core.accept_modes_update(result)
                    self._drain_log()
                job, self.modes_next = self.modes_next, None
                # the waiting estimate is fitted only if it still differs from the one just fitted
                while job is not None and not self.core.changed(job["f"], job["std"]):
                    job = None
                self.modes_running = job is not None
            if pub is not None:
                self.get_logger().info(f"guideway update accepted: rev {pub.revision}")
                self._publish(pub)

    def _modes_check(self):
        from maglev_ros.nodes._diagnostics import OK, Check
        return Check(OK, "", {"guideway_fit_running": self.modes_running,
                              "guideway_estimates_superseded": self.modes_superseded})

    def _of_this_recording(self, stamp_s: float) -> bool:
        """Whether an online estimate stamped ``stamp_s`` (the end of its window) was made from the
        recording now coming in: within the guideway accelerations this node has received of it. An
        estimate of the previous recording can arrive after the next one has begun (another node's
        output, no order across topics): adopted then, it would outlive that recording's end update.
        Before this recording's first block: not within the last ended recording. Without the
        recording-end update nothing is collected and every estimate counts."""
        if not self.recording_update:
            return True
        span = self.collector.span_s(TOPIC_GUIDEWAY_ACCEL)
        if span is not None:
            return span[0] <= stamp_s <= span[1]
        last = self.ended_span
        return last is None or not last[0] <= stamp_s <= last[1]

    def _vehicle(self, topic: str):
        def cb(msg) -> None:
            blk = self.gate.block(msg, topic)
            if blk is None:
                return
            with self.lock:
                self.core.on_vehicle_block(topic, blk)
            if self.recording_update:
                self._keep(topic, msg)
        return cb

    def _recorded(self, topic: str):
        """Guideway streams: only kept for the recording-end update."""
        def cb(msg) -> None:
            if self.gate.block(msg, topic) is not None:
                self._keep(topic, msg)
        return cb

    def _keep(self, topic: str, msg) -> None:
        """The block as received (the verb's reader converts units itself) for the recording's end."""
        with self.lock:
            was = self.collector.overflowed
            self.collector.add(topic, block_from_msg(msg))
            now = self.collector.overflowed
        if now and not was:
            self.get_logger().warning(
                f"the recording exceeds max_recording_mb ({self.collector.max_bytes / 1e6:g} MB): it is not "
                f"kept and gets no recording-end update; the moving-window updates go on")

    def _on_residual(self, msg) -> None:
        blk = self.gate.block(msg, TOPIC_RESIDUAL)
        if blk is None or not self.magnet_enabled:
            return
        with self.lock:
            if self.closed or (self.worker is not None and self.worker.is_alive()):
                return
            job = self.core.take_magnet_job(blk)       # copies of the window's streams + current parameters
            self._drain_log()
            if job is None:
                return
            e = job["residual_nrmse"]

        def work():
            from maglev_ros.errors import UserError
            background_thread()                        # the magnet layer's fit: the streams come first
            try:                                       # the long part runs WITHOUT the lock
                result = self.core.compute_magnet_update(job, residual_nrmse=e)
            except UserError as exc:
                self.get_logger().error(f"magnet layer: {exc}")
                return
            with self.lock:                            # short: accept + store in the history
                if self.closed:                        # its recording ended: the end update decides
                    self.get_logger().info("magnet layer result of an ended recording dropped")
                    return
                pub = self.core.accept_magnet_update(result)
                self._drain_log()
            if pub is not None:
                self.get_logger().info(f"magnet update accepted: rev {pub.revision}")
                self._publish(pub)
        self.get_logger().info(f"residual NRMSE {e:.3f}: running the magnet layer")
        self.worker = threading.Thread(target=work, daemon=True)
        self.worker.start()


    # ------------------------------------------------------------------ recording ends
    def on_recording_start(self, index: int) -> None:
        with self.lock:
            self.closed = False
            lost = self.collector.abandon()
        if lost is not None:
            self.get_logger().error(f"{lost}: its /testline/metadata never came: no recording-end update for it")

    def on_recording_end(self, index: int) -> None:
        """The replay's recording ``index`` has ended: the verb's update on it (worker thread)."""
        ev = self.lifecycle.event(RECORDING_END, index)
        source = ev.bag if ev is not None and ev.bag else None
        with self.lock:
            self.closed = True
        bag = self._finish(lambda: self.collector.end(source))
        if bag is not None:
            self._recording_ended(bag)
        elif self.collector.waiting:
            self.get_logger().info(f"recording {index} ended before its /testline/metadata: waiting for it")

    def _finish(self, step):
        """``step`` (a collector call that may complete a recording) under the lock; a recording
        whose metadata is not valid is logged and skipped."""
        from maglev_ros.errors import ContractError
        try:
            with self.lock:
                return step()
        except ContractError as exc:
            self.get_logger().error(f"recording not used for the update: {exc}")
            return None

    def _recording_ended(self, bag) -> None:
        from maglev_ros.updating.history import line_key
        with self.lock:
            self.closed = True
            self.ended_span = bag.span_s(TOPIC_GUIDEWAY_ACCEL) or self.ended_span
            self.core.new_recording()
        kind = bag.metadata.run_kind
        if kind == "ambient":
            if not bag.has(TOPIC_GUIDEWAY_ACCEL):
                self.get_logger().warning(f"{bag.path}: ambient recording without {TOPIC_GUIDEWAY_ACCEL}: not used")
                return
            self.ambient = bag
            job = (bag, [])
        elif kind == "pass":
            amb = self.ambient
            if amb is None or line_key(amb.metadata.raw) != line_key(bag.metadata.raw):
                self.get_logger().warning(
                    f"{bag.path}: no ambient recording of this line received before the pass: the "
                    f"recording-end update (maglev-ros update --ambient A --pass P) needs one; the "
                    f"moving-window updates stand")
                return
            job = (amb, [bag])
        else:
            return
        with self.lock:
            self.n_end_jobs += 1
        self.end_jobs.put(job)

    def busy(self) -> bool:
        return self.n_end_jobs > 0 or self.collector.waiting

    def _end_work(self) -> None:
        background_thread()          # the recording-end update: the streams come first
        while True:
            ambient, passes = self.end_jobs.get()
            try:
                self._end_update(ambient, passes)
            except Exception as exc:  # noqa: BLE001  (a recording the pipeline refuses must not end the node)
                self.get_logger().error(f"recording-end update of {(passes or [ambient])[0].path} failed: {exc}")
            finally:
                with self.lock:
                    self.n_end_jobs -= 1

    def _end_update(self, ambient, passes) -> None:
        from maglev_ros.updating.pipeline import update_from_bags, update_layers
        st = self.end_settings
        w = self.worker                    # a moving-window layer still running: its result is dropped
        if w is not None and w.is_alive():
            w.join()
        label = ", ".join(str(b.path) for b in (ambient, *passes))
        self.get_logger().info(f"recording-end update on {label} (the maglev-ros update pipeline)")
        gl, ml = update_layers(st["samples"], st["polish_evals"], st["swarm"], st["seed"])
        up = update_from_bags(ambient, passes, max_modes=st["max_modes"], max_window_s=st["max_window_s"],
                              guideway_layer=gl, magnet_layer=ml, log=self.get_logger().info)
        data_used = {"kind": "recording end", "ambient": str(ambient.path),
                     "passes": [str(b.path) for b in passes],
                     "pipeline": "maglev_ros.updating.pipeline.update_from_bags", "settings": st}
        with self.lock:
            pub = self.core.accept_recording_update(up.document, data_used)
            self._drain_log()
        if pub is not None:
            self._publish(pub)
            # done (maglev/status) only once reliable subscribers hold the result
            self.pub.wait_for_all_acked(Duration(seconds=ACK_TIMEOUT_S))

    # the launcher waits 5 s after SIGINT before it kills a node
    SHUTDOWN_WAIT_S = 3.0

    def unfinished_work(self) -> bool:
        """At shutdown: wait up to ``SHUTDOWN_WAIT_S`` for a running guideway or magnet layer or
        recording-end update; True if one is still running (its result is then discarded: the
        process must end without the interpreter's teardown, which aborted in the worker's native
        code, 'terminate called without an active exception', when the demo's graph stopped while
        the layer ran)."""
        workers = [w for w in (self.worker, getattr(self, "modes_worker", None)) if w is not None]

        def ending() -> bool:
            return getattr(self, "n_end_jobs", 0) > 0
        if not any(w.is_alive() for w in workers) and not ending():
            return False
        for w in workers:
            w.join(self.SHUTDOWN_WAIT_S)
        if any(w.is_alive() for w in workers) or ending():
            self.get_logger().warning("shutdown while a layer or a recording-end update is running: "
                                      "its result is discarded (the parameter history holds every accepted update)")
            return True
        return False


def main(args=None) -> int:
    return run_node(UpdaterNode, args)


if __name__ == "__main__":
    sys.exit(main())
