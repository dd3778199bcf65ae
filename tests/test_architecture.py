"""The parts of lapreco_hil and who may import whom (DESIGN.md), read from the source with ``ast``.

A part is a first-level subpackage or module of ``lapreco_hil`` (``lapreco_hil.mapping``, ``lapreco_hil.types``),
including the folders pyproject's package-dir maps in (drivers, simulators, calib, robot_models). Every import
counts, lazy ones inside functions too: a cycle through a lazy import is still a cycle in the design."""

from __future__ import annotations

import ast
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = "lapreco_hil"
CORE_EXCEPTIONS = {"app", "bench", "simulators"}  # the parts that may use a simulator
PIPELINE_PARTS = {"pipeline", "mapping", "frontend", "runtime", "app", "offline", "cli", "bench"}


def _package_dirs() -> dict[str, Path]:
    """Dotted package name -> folder, from pyproject's package-dir."""
    conf = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["package-dir"]
    return {name: ROOT / folder for name, folder in conf.items()}


def _modules() -> dict[str, tuple[Path, bool]]:
    """Dotted module name -> (file, is a package's __init__)."""
    modules: dict[str, tuple[Path, bool]] = {}
    dirs = _package_dirs()
    for name, folder in dirs.items():
        for path in folder.rglob("*.py"):
            rel = path.relative_to(folder).with_suffix("")
            parts = [name, *rel.parts]
            # a folder mapped in by package-dir of its own is walked from there, not from its parent
            if any(f"{'.'.join(parts[:i])}" in dirs and dirs[".".join(parts[:i])] != folder
                   for i in range(2, len(parts))):
                continue
            is_pkg = parts[-1] == "__init__"
            if is_pkg:
                parts = parts[:-1]
            modules[".".join(parts)] = (path, is_pkg)
    return modules


MODULES = _modules()


def part_of(module: str) -> str | None:
    bits = module.split(".")
    if bits[0] != PACKAGE:
        return None
    return bits[1] if len(bits) > 1 else PACKAGE


def imports_of(module: str) -> set[str]:
    """Every lapreco_hil module that ``module`` imports, anywhere in its body."""
    path, is_pkg = MODULES[module]
    tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
    package = module if is_pkg else module.rpartition(".")[0]
    found: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[:len(base) - (node.level - 1)]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            found.add(target)
            # ``from .. import x`` imports the submodule x when there is one
            found.update(f"{target}.{a.name}" for a in node.names if f"{target}.{a.name}" in MODULES)
    return {m for m in found if part_of(m) is not None}


def part_graph() -> dict[str, dict[str, set[str]]]:
    """part -> imported part -> the modules whose imports make that edge."""
    graph: dict[str, dict[str, set[str]]] = {}
    for module in MODULES:
        src = part_of(module)
        graph.setdefault(src, {})
        for target in imports_of(module):
            dst = part_of(target)
            if dst != src and dst != PACKAGE:  # the root holds only __version__ and the docstring
                graph[src].setdefault(dst, set()).add(module)
    return graph


def find_cycle(graph: dict[str, dict[str, set[str]]]) -> list[str] | None:
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(node: str) -> list[str] | None:
        state[node] = 1
        stack.append(node)
        for nxt in sorted(graph.get(node, {})):
            if state.get(nxt) == 1:
                return stack[stack.index(nxt):] + [nxt]
            if state.get(nxt) is None:
                cycle = visit(nxt)
                if cycle:
                    return cycle
        stack.pop()
        state[node] = 2
        return None

    for node in sorted(graph):
        if state.get(node) is None:
            cycle = visit(node)
            if cycle:
                return cycle
    return None


def _describe(graph, cycle: list[str]) -> str:
    return " -> ".join(cycle) + "\n" + "\n".join(
        f"  {a} -> {b} via {', '.join(sorted(graph[a][b]))}" for a, b in zip(cycle, cycle[1:]))


def test_the_mapping_sees_every_part():
    parts = {part_of(m) for m in MODULES}
    assert {"drivers", "simulators", "calib", "robot_models", "mapping", "cli", "app", "types"} <= parts
    # lazy imports count: cli.run imports the app only inside cmd_run
    assert "lapreco_hil.app.run" in imports_of("lapreco_hil.cli.run")
    # relative imports resolve, and ``from .. import x`` names the submodule x
    assert {"lapreco_hil.ground_truth", "lapreco_hil.geometry"} <= imports_of("lapreco_hil.sessions.session")
    assert "lapreco_hil.ground_truth" in imports_of("lapreco_hil.simulators.devices")


def test_find_cycle_reports_a_cycle():
    graph = {"a": {"b": {"m1"}}, "b": {"c": {"m2"}}, "c": {"a": {"m3"}}}
    assert find_cycle(graph) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b": {"m"}}, "b": {}}) is None


def test_no_import_cycle_between_parts():
    graph = part_graph()
    cycle = find_cycle(graph)
    if cycle:
        pytest.fail("import cycle between parts: " + _describe(graph, cycle))


def test_nothing_imports_the_cli():
    offenders = sorted(m for m in MODULES if part_of(m) != "cli"
                       and any(part_of(t) == "cli" for t in imports_of(m)))
    assert not offenders, f"these modules import lapreco_hil.cli (a thin shell nothing may import): {offenders}"


def test_core_never_imports_simulators():
    offenders = sorted(m for m in MODULES if part_of(m) not in CORE_EXCEPTIONS
                       and any(part_of(t) == "simulators" for t in imports_of(m)))
    assert not offenders, f"core modules that import a simulator (use the registry's URL): {offenders}"


@pytest.mark.parametrize("part", ["drivers", "simulators"])
def test_devices_never_import_the_pipeline(part):
    offenders = sorted(f"{m} -> {t}" for m in MODULES if part_of(m) == part
                       for t in imports_of(m) if part_of(t) in PIPELINE_PARTS)
    assert not offenders, f"{part} import the pipeline: {offenders}"
