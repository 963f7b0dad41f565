"""Scenario YAML of ``config/system3d``: values tagged with where they come from.

A leaf is either a plain number / string or ``{value: X, assumed: "why"}`` (a value we chose
because paper 001's Table 1 and equations are missing from our copy) or ``{value: X, source:
"where"}`` (read from a source). ``plain`` strips the tags; ``tagged_leaves`` lists them so a
report or a test can show every assumption.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any, Iterator, Mapping

import yaml

from maglev_ros.errors import UserError

_TAGS = ("assumed", "source")
#: Keys a value node may carry: the value, its unit and one tag.
VALUE_KEYS = frozenset(("value", "unit") + _TAGS)


def is_tagged(node: Any) -> bool:
    return isinstance(node, Mapping) and "value" in node and any(t in node for t in _TAGS)


def is_value_node(node: Any) -> bool:
    """``{value: X, [unit], [assumed | source]}``: a value written with its metadata only."""
    return isinstance(node, Mapping) and "value" in node and set(node) <= VALUE_KEYS


def tag_text(node: Any) -> str | None:
    """``"assumed: why"`` / ``"source: where"`` of a tagged node, None for anything else."""
    if not is_tagged(node):
        return None
    tag = "assumed" if "assumed" in node else "source"
    return f"{tag}: {node[tag]}"


def plain(node: Any, where: str = "") -> Any:
    """The tree with every tagged leaf replaced by its value."""
    if isinstance(node, dict):
        if "value" in node:
            if not any(t in node for t in _TAGS):
                raise UserError(f"{where or 'scenario'}: a value needs an 'assumed' or 'source' tag, got keys {sorted(node)}")
            return plain(node["value"], where)
        return {k: plain(v, f"{where}.{k}" if where else str(k)) for k, v in node.items()}
    if isinstance(node, list):
        return [plain(v, f"{where}[{i}]") for i, v in enumerate(node)]
    return node


def tagged_leaves(node: Any, where: str = "") -> Iterator[tuple[str, Any, str, str]]:
    """(path, value, tag, text) for every tagged leaf, depth first."""
    if is_tagged(node):
        tag = "assumed" if "assumed" in node else "source"
        yield where, node["value"], tag, str(node[tag])
    elif isinstance(node, dict):
        for k, v in node.items():
            yield from tagged_leaves(v, f"{where}.{k}" if where else str(k))
    elif isinstance(node, list):
        for i, v in enumerate(node):
            yield from tagged_leaves(v, f"{where}[{i}]")


def load_yaml(path: str | Path) -> dict:
    """The raw (still tagged) mapping of a scenario file."""
    p = Path(path)
    try:
        raw = yaml.safe_load(p.read_text())
    except (OSError, yaml.YAMLError) as exc:
        raise UserError(f"{p}: cannot read scenario YAML ({exc.__class__.__name__}: {exc})") from exc
    if not isinstance(raw, dict):
        raise UserError(f"{p}: expected a mapping at the top level, got {type(raw).__name__}")
    return raw


def require(mapping: dict, key: str, where: str) -> Any:
    if not isinstance(mapping, dict) or key not in mapping:
        raise UserError(f"{where}: missing key '{key}'")
    return mapping[key]


def number(mapping: dict, key: str, where: str, default: Any = None, positive: bool = False) -> float:
    """A float from ``mapping[key]`` (plain tree), with a one-line error naming the key."""
    if key not in mapping:
        if default is None:
            raise UserError(f"{where}: missing key '{key}'")
        return float(default)
    try:
        val = float(mapping[key])
    except (TypeError, ValueError) as exc:
        raise UserError(f"{where}.{key}: expected a number, got {mapping[key]!r}") from exc
    if positive and not val > 0:
        raise UserError(f"{where}.{key}: expected a number > 0, got {val}")
    return val
