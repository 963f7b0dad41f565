"""Layout rules: the science core never imports rclpy; the contract message is carried unchanged."""
import os
import pkgutil
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
CONTRACT_MSG = ROOT.parent / "shared" / "contract" / "msg" / "SensorBlock.msg"


def _core_modules():
    import maglev_ros
    for info in pkgutil.walk_packages(maglev_ros.__path__, "maglev_ros."):
        if not info.name.startswith("maglev_ros.nodes"):
            yield info.name


def test_no_rclpy_import_in_core_source():
    pattern = re.compile(r"^\s*(import rclpy|from rclpy)", re.M)
    offenders = [str(p.relative_to(ROOT)) for p in (ROOT / "maglev_ros").rglob("*.py")
                 if "nodes" not in p.relative_to(ROOT / "maglev_ros").parts[:1]
                 and pattern.search(p.read_text())]
    assert offenders == []


def test_importing_every_core_module_leaves_rclpy_unloaded():
    mods = sorted(_core_modules())
    code = ("import importlib, sys\n"
            f"for m in {mods!r}:\n    importlib.import_module(m)\n"
            "print('rclpy' in sys.modules)\n")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         env=dict(os.environ, PYTHONPATH=str(ROOT)), timeout=300)
    assert res.returncode == 0, res.stderr[-2000:]
    assert res.stdout.strip() == "False"


def _fields(text):
    out = []
    for line in text.splitlines():
        line = line.split("#", 1)[0].strip()
        if line:
            out.append(" ".join(line.split()))
    return out


def test_sensorblock_msg_matches_the_contract():
    ours = (ROOT / "msg_defs" / "msg" / "SensorBlock.msg").read_text()
    if CONTRACT_MSG.exists():
        assert _fields(ours) == _fields(CONTRACT_MSG.read_text())
    assert _fields(ours) == ["std_msgs/Header header", "float64 sample_rate_hz",
                             "string[] channels", "string[] units", "float32[] data"]


def test_readme_command_is_installed_in_the_environment_bin():
    """The README runs `.venv/bin/maglev-ros demo`: the install must put the console script next
    to the interpreter."""
    if sys.prefix == sys.base_prefix:
        pytest.skip("not running from the project's virtual environment")
    assert (Path(sys.executable).parent / "maglev-ros").exists()


def test_contract_travels_with_the_repo_and_readme_links_resolve():
    """docs/contract carries the shared contract unchanged; every relative README link exists."""
    ours = (ROOT / "docs" / "contract" / "RECORDING.md").read_text()
    assert (ROOT / "docs" / "contract" / "msg" / "SensorBlock.msg").is_file()
    shared = ROOT.parent / "shared" / "contract" / "RECORDING.md"
    if shared.exists():
        assert ours.endswith(shared.read_text())
    for doc in [ROOT / "README.md", *(ROOT / "docs").glob("*.md")]:
        for target in re.findall(r"\]\(([^)#]+)\)", doc.read_text()):
            if "://" not in target:
                assert (doc.parent / target).exists(), f"{doc.name}: broken link {target}"
        assert "../shared" not in doc.read_text(), f"{doc.name} points outside the repository"


def _package_imports() -> dict[str, set[str]]:
    """module -> maglev_ros modules it imports (top level or inside functions)."""
    import ast
    graph = {}
    for p in (ROOT / "maglev_ros").rglob("*.py"):
        rel = p.relative_to(ROOT).with_suffix("")
        name = ".".join(rel.parts[:-1] if rel.name == "__init__" else rel.parts)
        pkg = name if rel.name == "__init__" else name.rsplit(".", 1)[0]
        deps = set()
        for node in ast.walk(ast.parse(p.read_text())):
            if isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    parent = pkg.split(".")
                    parent = parent[:len(parent) - node.level + 1]
                    base = ".".join(parent + ([base] if base else []))
                if base.startswith("maglev_ros"):
                    deps.add(base)
                    deps.update(f"{base}.{a.name}" for a in node.names)
            elif isinstance(node, ast.Import):
                deps.update(a.name for a in node.names if a.name.startswith("maglev_ros"))
        graph[name] = deps
    return {m: {d for d in deps if d in graph and d != m} for m, deps in graph.items()}


def test_no_import_cycle_between_modules():
    graph = _package_imports()
    state: dict[str, int] = {}
    cycles = []

    def visit(m, path):
        state[m] = 1
        for d in sorted(graph[m]):
            if d.startswith(m + ".") or m.startswith(d + ".") and d == m.rsplit(".", 1)[0]:
                continue                  # a package and its own submodules
            if state.get(d) == 1:
                cycles.append(path[path.index(d):] + [d])
            elif d not in state:
                visit(d, path + [d])
        state[m] = 2

    for m in sorted(graph):
        if m not in state:
            visit(m, [m])
    assert not cycles, cycles[:3]


def test_product_code_names_no_benchmark_or_validation_case():
    """A rule must hold for any recording: case ids, benchmark splits and session numbers belong in
    tests, benches and notes, never in the shipped code."""
    pattern = re.compile(r"\b(tune|heldout|blind)( case| split)?\s+\d+\b|\b(tune|heldout|blind) split\b|"
                         r"\bsession \d+\b|\bH\d\d\b|partner-sim", re.I)
    hits = [f"{p.relative_to(ROOT)}:{i}: {line.strip()}"
            for p in sorted((ROOT / "maglev_ros").rglob("*.py"))
            for i, line in enumerate(p.read_text().splitlines(), 1) if pattern.search(line)]
    assert hits == [], hits[:5]
