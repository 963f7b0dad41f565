"""A Foxglove WebSocket client for tests: connects, subscribes, decodes what the server sends.

JSON messages are parsed with json; protobuf ones (the SDK's typed channels: SceneUpdate,
FrameTransform, Grid) are decoded with the FileDescriptorSet the server advertises, by the small
wire-format reader below (protobuf is no dependency of the suite; the wire format has four kinds
of field and the descriptor gives every name and type), so nothing of the bridge is reused here.
"""
from __future__ import annotations

import base64
import json
import struct
import time

# foxglove-sdk 0.30 speaks foxglove.sdk.v1; older servers foxglove.websocket.v1
SUBPROTOCOLS = ["foxglove.sdk.v1", "foxglove.websocket.v1"]


# ----------------------------------------------------------------- protobuf wire format
def _varint(buf: bytes, i: int) -> tuple[int, int]:
    shift = value = 0
    while True:
        b = buf[i]
        i += 1
        value |= (b & 0x7F) << shift
        if not b & 0x80:
            return value, i
        shift += 7


def wire_fields(buf: bytes):
    """(field number, wire type, raw value) of every field: int (varint), bytes (others)."""
    i = 0
    while i < len(buf):
        key, i = _varint(buf, i)
        num, wt = key >> 3, key & 7
        if wt == 0:
            v, i = _varint(buf, i)
        elif wt == 1:
            v, i = buf[i:i + 8], i + 8
        elif wt == 2:
            n, i = _varint(buf, i)
            v, i = buf[i:i + n], i + n
        elif wt == 5:
            v, i = buf[i:i + 4], i + 4
        else:
            raise ValueError(f"wire type {wt} not supported")
        yield num, wt, v


# descriptor.proto field numbers (FileDescriptorSet / FileDescriptorProto / DescriptorProto /
# FieldDescriptorProto): what is needed to name and type the fields of a message
def _descriptor_messages(fds: bytes) -> dict[str, dict]:
    out: dict[str, dict] = {}

    def message(buf: bytes, prefix: str) -> None:
        name, fields, nested = "", {}, []
        for num, _, v in wire_fields(buf):
            if num == 1:
                name = v.decode()
            elif num == 2:
                f = {"label": 1}
                for fn, _, fv in wire_fields(v):
                    if fn == 1:
                        f["name"] = fv.decode()
                    elif fn == 3:
                        f["number"] = fv
                    elif fn == 4:
                        f["label"] = fv
                    elif fn == 5:
                        f["type"] = fv
                    elif fn == 6:
                        f["type_name"] = fv.decode()
                fields[f["number"]] = f
            elif num == 3:
                nested.append(v)
        full = f"{prefix}.{name}"
        out[full] = fields
        for n in nested:
            message(n, full)

    for num, _, f in wire_fields(fds):
        if num != 1:
            continue
        package = ""
        msgs = []
        for fn, _, fv in wire_fields(f):
            if fn == 2:
                package = fv.decode()
            elif fn == 4:
                msgs.append(fv)
        for m in msgs:
            message(m, "." + package if package else "")
    return out


_DOUBLE, _FLOAT, _FIXED64, _FIXED32, _SFIXED32, _SFIXED64 = 1, 2, 6, 7, 15, 16
_STRING, _MESSAGE, _BYTES = 9, 11, 12
_FIXED = {_DOUBLE: ("<d", 8), _FLOAT: ("<f", 4), _FIXED64: ("<Q", 8), _FIXED32: ("<I", 4),
          _SFIXED32: ("<i", 4), _SFIXED64: ("<q", 8)}


def decode_protobuf(buf: bytes, type_name: str, types: dict[str, dict]) -> dict:
    """A message as a dict by its descriptor (repeated fields as lists, absent ones left out)."""
    fields = types[type_name]
    out: dict = {}
    for num, wt, v in wire_fields(buf):
        f = fields.get(num)
        if f is None:
            continue
        t = f.get("type")
        if t == _MESSAGE:
            vals = [decode_protobuf(v, f["type_name"], types)]
        elif t == _STRING:
            vals = [v.decode()]
        elif t == _BYTES:
            vals = [bytes(v)]
        elif t in _FIXED:
            fmt, size = _FIXED[t]
            vals = [struct.unpack(fmt, v[k:k + size])[0] for k in range(0, len(v), size)]
        elif wt == 2:               # packed varints
            vals, i = [], 0
            while i < len(v):
                x, i = _varint(v, i)
                vals.append(x)
        else:
            vals = [v]
        if f["label"] == 3:
            out.setdefault(f["name"], []).extend(vals)
        else:
            out[f["name"]] = vals[-1]
    return out


# ------------------------------------------------------------------------------ client
class FoxgloveClient:
    """Subscribes to every advertised channel whose topic ``want(topic)`` accepts and keeps what
    arrives: ``channels`` (topic -> advertised channel), ``messages`` (topic -> [(log time ns,
    decoded message)]), ``server_time_ns`` (the last time broadcast)."""

    def __init__(self, url: str, want=lambda topic: True, timeout_s: float = 30.0) -> None:
        from websockets.sync.client import connect
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                self.ws = connect(url, subprotocols=SUBPROTOCOLS, open_timeout=5, max_size=None).__enter__()
                break
            except OSError:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.2)
        self.want = want
        self.channels: dict[str, dict] = {}
        self.by_sub: dict[int, dict] = {}
        self.messages: dict[str, list] = {}
        self.server_info: dict | None = None
        self.unadvertised: list[str] = []              # topics of channels the server took back
        self.other: list[dict] = []                     # other text ops (status, ...)
        self.server_time_ns: int | None = None
        self.closed = False
        self._next_sub = 1
        self._types: dict[str, dict] = {}

    def close(self) -> None:
        self.ws.close()

    def _on_advertise(self, channels: list[dict]) -> None:
        subs = []
        for c in channels:
            self.channels[c["topic"]] = c
            if c.get("encoding") == "protobuf":
                self._types.update(_descriptor_messages(base64.b64decode(c["schema"])))
            if self.want(c["topic"]):
                sid = self._next_sub
                self._next_sub += 1
                self.by_sub[sid] = c
                subs.append({"id": sid, "channelId": c["id"]})
        if subs:
            self.ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))

    def _decode(self, c: dict, payload: bytes):
        if c["encoding"] == "json":
            return json.loads(payload)
        if c["encoding"] == "protobuf":
            return decode_protobuf(payload, "." + c["schemaName"], self._types)
        return payload

    def poll(self, seconds: float) -> None:
        """Handle what arrives for ``seconds`` (until the server closes the connection)."""
        from websockets.exceptions import ConnectionClosed
        end = time.monotonic() + seconds
        while (left := end - time.monotonic()) > 0:
            try:
                frame = self.ws.recv(timeout=left)
            except TimeoutError:
                return
            except ConnectionClosed:              # the server stopped
                self.closed = True
                return
            if isinstance(frame, str):
                d = json.loads(frame)
                if d.get("op") == "serverInfo":
                    self.server_info = d
                elif d.get("op") == "advertise":
                    self._on_advertise(d["channels"])
                elif d.get("op") == "unadvertise":
                    gone = set(d["channelIds"])
                    self.unadvertised += [t for t, c in self.channels.items() if c["id"] in gone]
                    self.channels = {t: c for t, c in self.channels.items() if c["id"] not in gone}
                else:
                    self.other.append(d)
                continue
            op = frame[0]
            if op == 1:                        # message data: subscription id, log time, payload
                sid, t_ns = struct.unpack_from("<IQ", frame, 1)
                c = self.by_sub.get(sid)
                if c is not None:
                    self.messages.setdefault(c["topic"], []).append((t_ns, self._decode(c, frame[13:])))
            elif op == 2:                      # time
                self.server_time_ns = struct.unpack_from("<Q", frame, 1)[0]

    def wait_for(self, condition, timeout_s: float) -> bool:
        """Poll until ``condition(self)`` holds (True), ``timeout_s`` passes or the server closes (the
        condition then)."""
        end = time.monotonic() + timeout_s
        while time.monotonic() < end and not self.closed:
            if condition(self):
                return True
            self.poll(0.2)
        return condition(self)
