"""Complete message definitions (``ros2msg``) as rosbag2 stores them in an MCAP schema record.

The text of a type is its .msg file followed by every type it uses, recursively, each once and
after a two-line delimiter: 80 ``=`` and ``MSG: <name as written in the field>``; dependencies
come in sorted order, depth first (rosbag2's ``LocalMessageDefinitionSource``, documented in
rosbag2's docs/message_definition_encoding.md). Foxglove, rosbags and the mcap tools read it.

.msg files are looked up where the ROS 2 tools find them: our own ``maglev_msgs`` through
:func:`maglev_ros.sensor_block.msg_dir`, others under ``share/<pkg>/msg/`` of the venv and of
every ``AMENT_PREFIX_PATH`` prefix. A type without a .msg file on this machine falls back to the
definition rosbags' type store generates for it (its built-in ROS 2 types and ours). No rclpy.
"""
from __future__ import annotations

import functools
import os
import sys
from pathlib import Path

from maglev_ros.errors import UserError

__all__ = ["DELIMITER", "message_definition", "msg_file_text", "field_types", "has_header",
           "split_type"]

DELIMITER = "=" * 80
PRIMITIVES = frozenset({"bool", "byte", "char", "float32", "float64", "int8", "uint8", "int16",
                        "uint16", "int32", "uint32", "int64", "uint64", "string", "wstring"})
_HEADER_NAMES = ("std_msgs/Header", "std_msgs/msg/Header", "Header")


def split_type(msgtype: str) -> tuple[str, str]:
    """``pkg/msg/Type`` or ``pkg/Type`` -> (pkg, Type); UserError for anything else."""
    parts = msgtype.split("/")
    if len(parts) == 2 or (len(parts) == 3 and parts[1] == "msg"):
        if all(parts):
            return parts[0], parts[-1]
    raise UserError(f"message type {msgtype!r}: expected 'package/msg/Type' or 'package/Type'")


def _share_dirs(pkg: str) -> list[Path]:
    dirs = []
    if pkg == "maglev_msgs":
        from maglev_ros.sensor_block import msg_dir
        try:
            dirs.append(msg_dir())
        except UserError:
            pass
    prefixes = [sys.prefix] + [p for p in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p]
    dirs += [Path(p) / "share" / pkg / "msg" for p in prefixes]
    return dirs


@functools.lru_cache(maxsize=None)
def msg_file_text(msgtype: str) -> str | None:
    """The .msg file text of a type, or None when no .msg file is found on this machine."""
    pkg, name = split_type(msgtype)
    for d in _share_dirs(pkg):
        f = d / f"{name}.msg"
        if f.is_file():
            return f.read_text()
    return None


def _fields(text: str):
    """(type, name) of each field of one .msg text, in order (comments, constants and the
    definitions after a first delimiter left out)."""
    for line in text.splitlines():
        if line.startswith(DELIMITER):
            return
        decl = line.split("#", 1)[0].split('"', 1)[0].split("'", 1)[0]
        parts = decl.split()
        if len(parts) < 2 or "=" in decl.replace("<=", ""):
            continue                       # blank, comment, or a constant ("uint8 OK=0")
        yield parts[0], parts[1]


def field_types(text: str, package: str) -> list[str]:
    """The non-primitive field types of a .msg text, package-qualified, in field order
    (array and bound suffixes left out)."""
    out = []
    for typ, _ in _fields(text):
        typ = typ.split("[", 1)[0].split("<=", 1)[0]
        if typ not in PRIMITIVES:
            out.append(typ if "/" in typ else f"{package}/{typ}")
    return out


def has_header(msgtype: str) -> bool:
    """Whether the type's first field is a ``std_msgs/Header`` (its CDR starts with the stamp)."""
    first = next(_fields(msg_file_text(msgtype) or _generated(msgtype)), None)
    return first is not None and first[0] in _HEADER_NAMES


@functools.lru_cache(maxsize=None)
def _generated(msgtype: str) -> str:
    """rosbags' generated complete definition (for types without a .msg file here)."""
    from maglev_ros.sensor_block import typestore
    pkg, name = split_type(msgtype)
    try:
        text, _ = typestore().generate_msgdef(f"{pkg}/msg/{name}", ros_version=2)
    except KeyError:
        raise UserError(f"message type {msgtype}: no .msg file found (looked in "
                        + ", ".join(str(d) for d in _share_dirs(pkg))
                        + ") and rosbags does not know it") from None
    return text


@functools.lru_cache(maxsize=None)
def message_definition(msgtype: str) -> str:
    """The complete ``ros2msg`` definition of ``msgtype`` (``pkg/msg/Type``), as rosbag2 writes it."""
    root = msg_file_text(msgtype)
    if root is None:
        return _generated(msgtype)
    seen: set[str] = set()

    class _Missing(Exception):
        pass

    def with_deps(name: str, text: str, depth: int) -> str:
        if depth > 32:
            raise UserError(f"message type {msgtype}: definitions nest deeper than 32 levels")
        out = text
        for dep in sorted(set(field_types(text, split_type(name)[0]))):
            if dep in seen:
                continue
            seen.add(dep)
            dep_text = msg_file_text(dep)
            if dep_text is None:
                raise _Missing(dep)
            out += f"\n{DELIMITER}\nMSG: {dep}\n" + with_deps(dep, dep_text, depth + 1)
        return out

    try:
        return with_deps(msgtype, root, 0)
    except _Missing:
        # one dependency without a .msg file here: rosbags' text for the whole type, so that the
        # definition stays complete (its own, equivalent, wording without comments)
        return _generated(msgtype)
