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
and updating the guideway meanwhile); only accepting and storing the result takes the lock.
"""
from __future__ import annotations

import math
import sys
import threading

from rclpy.node import Node
from std_msgs.msg import String

from maglev_msgs.msg import ModalEstimate, SensorBlock, TwinParameters
from maglev_ros.contract import parse_metadata
from maglev_ros.nodes._common import BlockGate, run_node
from maglev_ros.nodes._diagnostics import NodeDiagnostics
from maglev_ros.nodes._params import Param, declare
from maglev_ros.nodes._qos import publisher, subscription

TOPIC_PARAMETERS = "/maglev/twin/parameters"
TOPIC_MODES = "/maglev/modes"
TOPIC_RESIDUAL = "/maglev/twin/residual/vehicle_accel"
VEHICLE_TOPICS = ("/testline/vehicle/accel", "/testline/vehicle/gap", "/testline/vehicle/position")


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
        self.pub = publisher(self, TwinParameters, TOPIC_PARAMETERS)
        self.diagnostics = NodeDiagnostics(self)
        self.gate = BlockGate(self, self.diagnostics)
        self.lock = threading.Lock()
        self.worker: threading.Thread | None = None
        subscription(self, String, "/testline/metadata", self._on_metadata)
        subscription(self, ModalEstimate, TOPIC_MODES, self._on_modes)
        subscription(self, SensorBlock, TOPIC_RESIDUAL, self._on_residual)
        for t in VEHICLE_TOPICS:
            subscription(self, SensorBlock, t, self._vehicle(t))
        self.line: str | None = None      # line key of the metadata the history was restored for
        if self.core.history.path is None:
            self.get_logger().warning("history_path not set: accepted parameters are kept in memory only")
        else:   # the one writer of this file from now on (a second updater is refused here, one line)
            for w in self.core.history.open_writer():
                self.get_logger().warning(w)
        self.n_warned = 0

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
        stamp = msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec
        try:
            with self.lock:
                pub = self.core.on_modes(list(msg.modes), stamp)
                self._drain_log()
        except UserError as exc:
            self.get_logger().error(f"{TOPIC_MODES}: {exc}")
            return
        if pub is not None:
            self.get_logger().info(f"guideway update accepted: rev {pub.revision}")
            self._publish(pub)

    def _vehicle(self, topic: str):
        def cb(msg) -> None:
            blk = self.gate.block(msg, topic)
            if blk is None:
                return
            with self.lock:
                self.core.on_vehicle_block(topic, blk)
        return cb

    def _on_residual(self, msg) -> None:
        blk = self.gate.block(msg, TOPIC_RESIDUAL)
        if blk is None or not self.magnet_enabled:
            return
        with self.lock:
            if self.worker is not None and self.worker.is_alive():
                return
            job = self.core.take_magnet_job(blk)       # copies of the window's streams + current parameters
            self._drain_log()
            if job is None:
                return
            e = job["residual_nrmse"]

        def work():
            from maglev_ros.errors import UserError
            try:                                       # the long part runs WITHOUT the lock
                result = self.core.compute_magnet_update(job, residual_nrmse=e)
            except UserError as exc:
                self.get_logger().error(f"magnet layer: {exc}")
                return
            with self.lock:                            # short: accept + store in the history
                pub = self.core.accept_magnet_update(result)
                self._drain_log()
            if pub is not None:
                self.get_logger().info(f"magnet update accepted: rev {pub.revision}")
                self._publish(pub)
        self.get_logger().info(f"residual NRMSE {e:.3f}: running the magnet layer")
        self.worker = threading.Thread(target=work, daemon=True)
        self.worker.start()


    # the launcher waits 5 s after SIGINT before it kills a node
    SHUTDOWN_WAIT_S = 3.0

    def unfinished_work(self) -> bool:
        """At shutdown: wait up to ``SHUTDOWN_WAIT_S`` for a running magnet layer; True if it is still
        running (its result is then discarded: the process must end without the interpreter's
        teardown, which aborted in the worker's native code, 'terminate called without an active
        exception', when the demo's graph stopped while the layer ran)."""
        w = self.worker
        if w is None or not w.is_alive():
            return False
        w.join(self.SHUTDOWN_WAIT_S)
        if w.is_alive():
            self.get_logger().warning("shutdown while the magnet layer is running: its result is discarded "
                                      "(the parameter history holds every accepted update)")
            return True
        return False


def main(args=None) -> int:
    return run_node(UpdaterNode, args)


if __name__ == "__main__":
    sys.exit(main())
