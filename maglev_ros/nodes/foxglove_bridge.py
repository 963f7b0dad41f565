"""Node ``foxglove_bridge``: the live view of the graph, served to Foxglove over WebSocket.

Serves the Foxglove WebSocket protocol (foxglove-sdk's server) on ``host``:``port`` and shows
what the graph measures and concludes on the ``/maglev/view/...`` channels (see docs/live_view.md
and :mod:`maglev_ros.live_view`, where every conversion lives; this node only adapts):

- ``/maglev/view/<group>/{measured,predicted,residual}``: each stream decimated for display (min,
  max and mean per ``1 / display_rate_hz`` bin of stream time, :mod:`maglev_ros.live_view.decimate`);
- ``/maglev/view/<group>/residual_map`` (JSON) and ``.../residual_map/grid`` (foxglove.Grid): the
  residual RMS per (position bin, band), sent every ``map_period_s`` while it grows;
- ``/maglev/view/modes``, ``.../modes/history``, ``.../mismatch``, ``.../mismatch/log``,
  ``.../diagnosis``, ``.../parameters``, ``.../irregularity``, ``.../metadata`` (JSON);
- ``/maglev/view/scene`` (foxglove.SceneUpdate: spans, sensors, vehicle, mismatch zones) and
  ``/maglev/view/tf`` (foxglove.FrameTransform line -> vehicle, at most ``scene_rate_hz``).
Messages carry stream time (the recording's stamps) as their log time, and the server's time
follows the stream, so the app's plots line up measured, predicted and residual although the twin
publishes seconds later. Results that change rarely are sent again to a client that subscribes late.

An observer: it subscribes to the graph's topics (relative names, so it follows its namespace)
best-effort, keep-last, so it never holds a replay back, and it formats no time series while no
client is subscribed. The latched results (metadata, parameters, profile, diagnosis) are subscribed
when their publisher shows: transient-local when it is latched (the last one, even sent before the
bridge started), best-effort volatile otherwise. Parameters: ``host`` (127.0.0.1; 0.0.0.0 serves
other machines), ``port`` (8765), ``display_rate_hz`` (50), ``position_bin_m`` (1.0),
``map_period_s`` (1.0), ``scene_rate_hz`` (30).
"""
from __future__ import annotations

import array
import json
import sys
import threading
import time
from pathlib import Path

import numpy as np
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.qos_overriding_options import QoSOverridingOptions
from std_msgs.msg import String

from maglev_msgs.msg import IrregularityProfile, MismatchReport, ModalEstimate, SensorBlock, TwinParameters
from maglev_ros import live_view as lv
from maglev_ros.contract import TOPIC_METADATA, TOPIC_VEHICLE_POSITION, parse_metadata
from maglev_ros.errors import ContractError, UserError
from maglev_ros.live_view import messages as lm
from maglev_ros.live_view import scene as ls
from maglev_ros.live_view.decimate import Decimator, series_messages, series_schema
from maglev_ros.live_view.residual_map import GRID_BAND_HEIGHT_M, ResidualMap, grid_cells, map_schema
from maglev_ros.nodes._common import BlockGate, rel, run_node
from maglev_ros.nodes._diagnostics import NodeDiagnostics

TOPIC_MODES = "/maglev/modes"
TOPIC_MISMATCH = "/maglev/mismatch"
TOPIC_DIAGNOSIS = "/maglev/diagnosis"
TOPIC_PARAMETERS = "/maglev/twin/parameters"
TOPIC_IRREGULARITY = "/maglev/irregularity"
FOXGLOVE_PIN = "foxglove-sdk==0.30.3"
IDLE_FLUSH_S = 1.0             # a stream quiet this long (wall time) has its last display bin sent
DEFAULT_GIRDER_WIDTH_M = 2.0    # drawn when the metadata gives no girder section

# an observer: matches reliable and best-effort publishers, is never waited for (best-effort
# readers take no part in a reliable writer's flow control), keeps the newest blocks
QOS_OBSERVER = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=50,
                          reliability=ReliabilityPolicy.BEST_EFFORT, durability=DurabilityPolicy.VOLATILE)
# latched results from latched publishers: the last one even when it came before the bridge
QOS_OBSERVER_LATCHED = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                                  reliability=ReliabilityPolicy.RELIABLE,
                                  durability=DurabilityPolicy.TRANSIENT_LOCAL)


def _foxglove():
    try:
        import foxglove
        import foxglove.channels
        import foxglove.messages
        import foxglove.websocket
    except ImportError:
        raise UserError(f"the live view needs foxglove-sdk, which is not installed: pip install "
                        f"{FOXGLOVE_PIN} (scripts/install does)") from None
    return foxglove


def plain(msg):
    """A ROS message as a dict of its fields (arrays as lists; NaN kept: live_view makes it null)."""
    if hasattr(msg, "get_fields_and_field_types"):
        return {f: plain(getattr(msg, f)) for f in msg.get_fields_and_field_types()}
    if isinstance(msg, (list, tuple)):
        return [plain(v) for v in msg]
    if isinstance(msg, (array.array, np.ndarray)):
        return [float(v) for v in msg]
    return msg


def _stamp_ns(header) -> int:
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


class FoxgloveBridge(Node):
    def __init__(self) -> None:
        super().__init__("foxglove_bridge")
        p = self.declare_parameter
        host = str(p("host", "127.0.0.1").value)
        port = int(p("port", 8765).value)
        rate = float(p("display_rate_hz", 50.0).value)
        self.map_period_s = float(p("map_period_s", 1.0).value)
        scene_rate = float(p("scene_rate_hz", 30.0).value)
        bin_m = float(p("position_bin_m", 1.0).value)
        for name, v in (("display_rate_hz", rate), ("scene_rate_hz", scene_rate), ("position_bin_m", bin_m),
                        ("map_period_s", self.map_period_s)):
            if not v > 0:
                raise UserError(f"parameter {name}: expected a value > 0, got {v}")
        if not 0 <= port <= 65535:
            raise UserError(f"parameter port: expected 0-65535, got {port}")
        fg = _foxglove()
        self.fg = fg
        self.lock = threading.Lock()            # state shared with the server's subscribe callback
        self.latest: dict[str, tuple] = {}      # view -> (channel, payload, log time): sent again to late clients
        self.channels: dict[str, object] = {}
        self.grid_ch: dict[str, object] = {}
        self.scene_entities: dict[str, dict] = {}
        self.decimators = {t: Decimator(rate) for t in lv.source_topics()}
        self.last_block_wall: dict[str, float] = {}
        self.last_source: dict[str, str] = {}      # topic -> frame_id of its last block
        self.map = ResidualMap(position_bin_m=bin_m)
        self.map_frames_sent: dict[str, int] = {}
        self.t_map = time.monotonic()
        self.metadata: dict | None = None
        self.girder_width_m = DEFAULT_GIRDER_WIDTH_M     # drawn width of the girders (from the metadata)
        self.modes = lm.ModeHistory()
        self.mismatches = lm.MismatchLog()
        self.n_mismatch = 0
        self.tf_period_ns = max(1, int(round(1e9 / scene_rate)))
        self.tf_slot: int | None = None
        self.stream_ns: int | None = None
        self.time_sent: int | None = None
        self.ctx = fg.Context()
        # every channel exists before the server takes a client, and none is ever replaced: a
        # client then gets them all in its first advertisement (foxglove-sdk 0.30 can refuse a
        # subscription to a channel advertised while the client is connected: "unknown channel")
        for topic, schema in ((lv.VIEW_MODES, lm.modes_schema()), (lv.VIEW_MISMATCH, lm.mismatch_schema()),
                              (lv.VIEW_MODE_HISTORY, lm.mode_history_schema()),
                              (lv.VIEW_MISMATCH_LOG, lm.mismatch_log_schema()),
                              (lv.VIEW_PARAMETERS, lm.parameters_schema()),
                              (lv.VIEW_IRREGULARITY, lm.irregularity_schema()),
                              (lv.VIEW_DIAGNOSIS, lm.diagnosis_schema()), (lv.VIEW_METADATA, lm.metadata_schema())):
            self._json_channel(topic, schema)
        for group, kind in lv.source_topics().values():
            self._json_channel(lv.series_topic(group, kind), series_schema())
        for group in lv.TWIN_GROUPS:
            self._json_channel(lv.map_topic(group), map_schema())
            self._grid_channel(group)
        self.scene_ch = fg.channels.SceneUpdateChannel(lv.VIEW_SCENE, context=self.ctx)
        self.tf_ch = fg.channels.FrameTransformChannel(lv.VIEW_TF, context=self.ctx)
        try:
            self.server = fg.start_server(name=f"maglev_ros {self.get_namespace()}", host=host, port=port,
                                          context=self.ctx, capabilities=[fg.websocket.Capability.Time],
                                          server_listener=_listener(fg, self))
        except Exception as exc:  # the SDK raises a plain RuntimeError for a port in use
            raise UserError(f"parameter port: cannot serve the live view on {host}:{port} ({exc})") from None
        self.url = f"ws://{host}:{self.server.port}"

        self.diagnostics = NodeDiagnostics(self)
        self.gate = BlockGate(self, self.diagnostics)
        overrides = QoSOverridingOptions.with_default_policies()
        for topic in lv.source_topics():
            self.create_subscription(SensorBlock, rel(topic), self._on_block(topic), QOS_OBSERVER,
                                     qos_overriding_options=overrides)
        self.create_subscription(ModalEstimate, rel(TOPIC_MODES), self._on_modes, QOS_OBSERVER)
        self.create_subscription(MismatchReport, rel(TOPIC_MISMATCH), self._on_mismatch, QOS_OBSERVER)
        # latched results: subscribed once a publisher shows, with its durability (module docstring)
        self.pending = {TOPIC_METADATA: (String, self._on_metadata), TOPIC_DIAGNOSIS: (String, self._on_diagnosis),
                        TOPIC_PARAMETERS: (TwinParameters, self._on_parameters),
                        TOPIC_IRREGULARITY: (IrregularityProfile, self._on_profile)}
        self._subscribe_latched()
        self.create_timer(0.2, self._tick)
        layout = Path(__file__).resolve().parents[1] / "config" / "foxglove_layout.json"
        self.get_logger().info(f"live view on {self.url}: open https://app.foxglove.dev/?ds=foxglove-websocket"
                               f"&ds.url={self.url} (layout: {layout})")

    # ------------------------------------------------------------------ output helpers
    def _json_channel(self, topic: str, schema: dict):
        ch = self.channels.get(topic)
        if ch is None:
            fg = self.fg
            ch = self.channels[topic] = fg.Channel(
                topic, message_encoding="json", context=self.ctx,
                schema=fg.Schema(name=schema.get("title", topic), encoding="jsonschema",
                                 data=json.dumps(schema).encode()))
        return ch

    def _log(self, topic: str, message: dict, t_ns: int, latched: bool = False) -> None:
        ch = self.channels[topic]
        data = json.dumps(message, allow_nan=False, separators=(",", ":")).encode()
        self._emit(topic, ch, data, t_ns, latched)

    def _emit(self, topic: str, ch, payload, t_ns: int, latched: bool) -> None:
        if latched:
            with self.lock:
                self.latest[topic] = (ch, payload, max(0, int(t_ns)))
        ch.log(payload, log_time=max(0, int(t_ns)))

    def _now_ns(self, header_ns: int = 0) -> int:
        """Log time of a result without its own stream stamp: the stream's time (else its stamp)."""
        return self.stream_ns if self.stream_ns is not None else header_ns

    def _timestamp(self, t_ns: int):
        from foxglove.messages import Timestamp
        sec, nsec = divmod(max(0, int(t_ns)), 1_000_000_000)
        return Timestamp(sec, nsec)

    def _scene_update(self, entities: list[dict], t_ns: int, clear: bool = False):
        from foxglove.messages import SceneEntityDeletion, SceneEntityDeletionType, SceneUpdate
        ts = self._timestamp(t_ns)
        dels = [SceneEntityDeletion(timestamp=ts, type=SceneEntityDeletionType.All)] if clear else []
        return SceneUpdate(deletions=dels, entities=[_entity(e, ts) for e in entities])

    def _send_scene(self, entities: list[dict], t_ns: int, clear: bool = False) -> None:
        with self.lock:
            if clear:
                self.scene_entities.clear()
            self.scene_entities.update({e["id"]: e for e in entities})
        self.scene_ch.log(self._scene_update(entities, t_ns, clear), log_time=max(0, int(t_ns)))

    def resend(self, topic: str) -> None:
        """A client subscribed to ``topic``: send the current state of a latched view again."""
        with self.lock:
            latest = self.latest.get(topic)
            entities = list(self.scene_entities.values()) if topic == lv.VIEW_SCENE else None
        if latest is not None:
            ch, payload, t_ns = latest
            ch.log(payload, log_time=t_ns)
        if entities:
            t = self._now_ns()
            self.scene_ch.log(self._scene_update(entities, t or 0, clear=True), log_time=max(0, t or 0))

    # --------------------------------------------------------------------- callbacks
    def _subscribe_latched(self) -> None:
        """Subscribe each latched result once it has a publisher: transient local when every
        publisher is (the last message even if it came before us), else best-effort volatile, which
        matches any publisher (a replay of recorded results publishes them volatile); a reader
        asking for more than a publisher offers would get nothing from it."""
        for topic, (cls, cb) in list(self.pending.items()):
            infos = self.get_publishers_info_by_topic(self.resolve_topic_name(rel(topic)))
            if not infos:
                continue
            latched = all(i.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL
                          and i.qos_profile.reliability == ReliabilityPolicy.RELIABLE for i in infos)
            self.create_subscription(cls, rel(topic), cb, QOS_OBSERVER_LATCHED if latched else QOS_OBSERVER)
            del self.pending[topic]

    def _on_block(self, topic: str):
        group, kind = lv.source_topics()[topic]
        view = lv.series_topic(group, kind)

        def cb(msg) -> None:
            b = self.gate.block(msg, topic)
            if b is None:
                return
            self.last_block_wall[topic] = time.monotonic()
            self.last_source[topic] = b.frame_id
            if kind == "measured":                 # the twin's streams lag: the measurement sets the time
                end = int(b.end_ns)
                if self.stream_ns is None or end > self.stream_ns or end < self.stream_ns - 5_000_000_000:
                    self.stream_ns = end               # (a jump back: the stream started again)
            if topic == TOPIC_VEHICLE_POSITION and "position_m" in b.channels:
                x = b.channel("position_m")
                self.map.add_position(b.times_s(), x)
                self._move_vehicle(b, x)
            if kind == "residual":
                self.map.add_block(group, b)
            self._send_bins(view, self.decimators[topic].add(b), b.frame_id)
        return cb

    def _send_bins(self, view: str, bins, source: str) -> None:
        ch = self.channels.get(view)
        if bins is None or ch is None or not ch.has_sinks():
            return
        for t_ns, m in series_messages(bins, source):
            ch.log(json.dumps(m, allow_nan=False, separators=(",", ":")).encode(), log_time=max(0, t_ns))

    def _move_vehicle(self, b, x) -> None:
        from foxglove.messages import FrameTransform, Quaternion, Vector3
        t_ns = int(b.stamp_ns) + np.round(np.arange(b.n_samples) * (1e9 / b.sample_rate_hz)).astype(np.int64)
        idx, self.tf_slot = ls.transform_samples(t_ns, self.tf_period_ns, self.tf_slot)
        for i in idx:
            if not np.isfinite(x[i]):
                continue
            tf = ls.vehicle_transform(int(t_ns[i]), float(x[i]))
            self.tf_ch.log(FrameTransform(timestamp=self._timestamp(tf["timestamp_ns"]),
                                          parent_frame_id=tf["parent_frame_id"],
                                          child_frame_id=tf["child_frame_id"],
                                          translation=Vector3(x=tf["translation"][0], y=0.0, z=0.0),
                                          rotation=Quaternion(x=0.0, y=0.0, z=0.0, w=1.0)),
                           log_time=int(t_ns[i]))

    def _on_metadata(self, msg) -> None:
        try:
            md = parse_metadata(msg.data, rel(TOPIC_METADATA)).raw
        except ContractError as exc:
            self.get_logger().warning(f"metadata not shown: {exc}")
            return
        self.gate.new_stream()
        self.metadata = dict(md)
        try:
            self.girder_width_m = ls.girder_width_m(self.metadata)
        except (UserError, KeyError, TypeError, ValueError):
            self.girder_width_m = DEFAULT_GIRDER_WIDTH_M
        self.map.set_metadata(self.metadata)
        self.map_frames_sent.clear()
        self.tf_slot = None
        t = self._now_ns()
        self._log(lv.VIEW_METADATA, lm.jsonable(self.metadata), t, latched=True)
        try:
            entities = ls.line_entities(self.metadata) + ls.vehicle_entities(self.metadata)
        except (ContractError, UserError, KeyError, TypeError, ValueError) as exc:
            self.get_logger().warning(f"scene: the line cannot be drawn from the metadata ({exc})")
            entities = []
        self._send_scene(entities, t, clear=True)

    def _on_modes(self, msg) -> None:
        m = lm.modes_message(plain(msg))
        t = _stamp_ns(msg.header)
        self._log(lv.VIEW_MODES, m, t, latched=True)
        self._log(lv.VIEW_MODE_HISTORY, self.modes.add(m), t, latched=True)

    def _on_mismatch(self, msg) -> None:
        m = lm.mismatch_message(plain(msg))
        t = _stamp_ns(msg.header)
        self._log(lv.VIEW_MISMATCH, m, t, latched=True)
        self._log(lv.VIEW_MISMATCH_LOG, self.mismatches.add(m), t, latched=True)
        width = self.girder_width_m
        e = ls.mismatch_entity(m, self.n_mismatch, width)
        self.n_mismatch += 1
        if e is not None:
            self._send_scene([e], t)

    def _on_diagnosis(self, msg) -> None:
        self._log(lv.VIEW_DIAGNOSIS, lm.diagnosis_message(msg.data), self._now_ns(), latched=True)

    def _on_parameters(self, msg) -> None:
        t = self._now_ns(_stamp_ns(msg.header))
        self._log(lv.VIEW_PARAMETERS, lm.parameters_message(plain(msg), t * 1e-9), t, latched=True)

    def _on_profile(self, msg) -> None:
        self._log(lv.VIEW_IRREGULARITY, lm.irregularity_message(plain(msg)), _stamp_ns(msg.header), latched=True)

    # ------------------------------------------------------------------------- timer
    def _tick(self) -> None:
        if self.pending:
            self._subscribe_latched()
        now = time.monotonic()
        for topic, t_wall in list(self.last_block_wall.items()):
            if now - t_wall > IDLE_FLUSH_S:         # the stream paused or ended: its last bin
                del self.last_block_wall[topic]
                group, kind = lv.source_topics()[topic]
                self._send_bins(lv.series_topic(group, kind), self.decimators[topic].flush(),
                                self.last_source.get(topic, ""))
        if now - self.t_map >= self.map_period_s:
            self.t_map = now
            self._send_maps()
        if self.stream_ns is not None and self.stream_ns != self.time_sent:
            self.time_sent = self.stream_ns
            self.server.broadcast_time(int(self.stream_ns))

    def _send_maps(self) -> None:
        for group, frames in list(self.map.frames.items()):
            if self.map_frames_sent.get(group) == frames:
                continue
            self.map_frames_sent[group] = frames
            t = int(self.map.t_last_s.get(group, 0.0) * 1e9)
            self._log(lv.map_topic(group), self.map.message(group), t, latched=True)
            self._send_grid(group, t)

    def _grid_channel(self, group: str):
        ch = self.grid_ch.get(group)
        if ch is None:
            ch = self.grid_ch[group] = self.fg.channels.GridChannel(lv.map_grid_topic(group), context=self.ctx)
        return ch

    def _send_grid(self, group: str, t_ns: int) -> None:
        from foxglove.messages import (Grid, PackedElementField, PackedElementFieldNumericType, Pose,
                                       Quaternion, Vector2, Vector3)
        ch = self._grid_channel(group)
        width = self.girder_width_m
        cols, stride, fields, data = grid_cells(self.map.rms(group))
        x, y = ls.grid_origin_m(self.map.x0_m, width, lv.TWIN_GROUPS.index(group) if group in lv.TWIN_GROUPS
                                else len(lv.TWIN_GROUPS), self.map.n_bands, GRID_BAND_HEIGHT_M)
        self._emit(lv.map_grid_topic(group), ch, Grid(timestamp=self._timestamp(t_ns), frame_id="line",
                    pose=Pose(position=Vector3(x=x, y=y, z=0.0), orientation=Quaternion(x=0.0, y=0.0, z=0.0, w=1.0)),
                    column_count=cols, cell_size=Vector2(x=self.map.bin_m, y=GRID_BAND_HEIGHT_M),
                    row_stride=cols * stride, cell_stride=stride,
                    fields=[PackedElementField(name=n, offset=o, type=PackedElementFieldNumericType.Float32)
                            for n, o in fields], data=data), t_ns, latched=True)

    def destroy_node(self):
        server = getattr(self, "server", None)      # None: the node failed before serving
        if server is not None:
            server.stop()
        return super().destroy_node()


def _entity(d: dict, ts):
    from foxglove.messages import (Color, CubePrimitive, Pose, Quaternion, SceneEntity, SpherePrimitive,
                                   TextPrimitive, Vector3)

    def pose(p):
        return Pose(position=Vector3(x=p[0], y=p[1], z=p[2]), orientation=Quaternion(x=0.0, y=0.0, z=0.0, w=1.0))

    def color(c):
        return Color(r=c[0], g=c[1], b=c[2], a=c[3])

    def size(s):
        return Vector3(x=s[0], y=s[1], z=s[2])
    return SceneEntity(
        timestamp=ts, frame_id=d["frame_id"], id=d["id"], frame_locked=bool(d.get("frame_locked")),
        cubes=[CubePrimitive(pose=pose(c["position"]), size=size(c["size"]), color=color(c["color"]))
               for c in d.get("cubes", [])],
        spheres=[SpherePrimitive(pose=pose(c["position"]), size=size(c["size"]), color=color(c["color"]))
                 for c in d.get("spheres", [])],
        texts=[TextPrimitive(pose=pose(t["position"]), billboard=True, font_size=t["font_size"],
                             scale_invariant=False, color=color(t["color"]), text=t["text"])
               for t in d.get("texts", [])])


def _listener(fg, node: FoxgloveBridge):
    """The server's callbacks (foxglove.websocket.ServerListener, whose defaults do nothing): a
    client subscribing to a latched view gets its current state."""

    class Listener(fg.websocket.ServerListener):
        def on_subscribe(self, client, channel) -> None:
            node.resend(channel.topic)
    return Listener()


def main(args=None) -> int:
    return run_node(FoxgloveBridge, args)


if __name__ == "__main__":
    sys.exit(main())
