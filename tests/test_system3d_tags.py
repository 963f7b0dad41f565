"""Every number in a shipped 3D scenario is tagged 'assumed' (with a reason) or 'source' (paper 001's
Table 1 and equations are missing from our copy: a reader must see which values are ours)."""
from pathlib import Path

import pytest
import yaml

from maglev_ros.system3d.scenario_values import is_tagged

CONFIG = Path(__file__).resolve().parents[1] / "maglev_ros" / "config" / "system3d"
# keys that are no physical value: a file format version, an index into the span list
NOT_VALUES = (".version", ".at_support")


@pytest.mark.parametrize("name", sorted(p.name for p in CONFIG.glob("*.yaml")))
def test_every_number_of_a_shipped_scenario_is_tagged(name):
    raw = yaml.safe_load((CONFIG / name).read_text())
    bare = []

    def walk(node, where):
        if is_tagged(node):
            assert str(node.get("assumed", node.get("source", ""))).strip(), where
            return
        if isinstance(node, dict):
            for k, v in node.items():
                walk(v, f"{where}.{k}")
        elif isinstance(node, list):
            for i, v in enumerate(node):
                walk(v, f"{where}[{i}]")
        elif isinstance(node, (int, float)) and not isinstance(node, bool) and not where.endswith(NOT_VALUES):
            bare.append(where)

    walk(raw, name)
    assert not bare, f"untagged numbers: {bare}"
