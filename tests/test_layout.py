"""The package layout is the architecture: dependencies point one way (math <- mavlink <- flows <- app <- fleet
<- cli): the fleet report consumes the application (replay, calibration), and only the CLI's commands sit above it.

Every `import` of every module under rover_bridge/ (at any depth, also inside functions) is read from
the source and checked against the layer rules below; the pure layers also may not touch sockets,
clocks, threads or signals. A new module that breaks the direction fails here, not in review.

Across the whole project (rover_bridge/, sitl/, benchmarks/, tests/) no modules import each other, directly or
round a longer circle, type names under TYPE_CHECKING included (a types module or a Protocol breaks such a
circle: app/demo_series.py, sitl/autopilot_view.py), and no source file is over 1000 lines.
"""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parent.parent / "rover_bridge"
IO_MODULES = {"socket", "select", "time", "threading", "signal", "selectors", "asyncio", "subprocess"}
SHELL_EDGE = "rover_bridge.mavlink.links"  # the one I/O module below app


def layer(module: str) -> str:
    parts = module.split(".")
    if len(parts) == 1:
        return "package"
    if parts[1] == "__main__" or parts[1:3] in (["app", "cli"], ["app", "commands"]):
        return "cli"
    if parts[1] in ("mavlink", "command", "estimate", "app", "fleet"):
        return parts[1]
    return "math"  # kinematics, limits, odometry, frames, params, errors


# Which layers each layer may import (its own included).
ALLOWED = {
    "math": {"math", "package"},
    "mavlink": {"math", "mavlink", "package"},
    "command": {"math", "mavlink", "command", "package"},
    "estimate": {"math", "mavlink", "estimate", "package"},
    "app": {"math", "mavlink", "command", "estimate", "app", "package"},
    "fleet": {"math", "mavlink", "command", "estimate", "app", "fleet", "package"},
    "cli": {"math", "mavlink", "command", "estimate", "app", "fleet", "cli", "package"},
    "package": {"package"},
}


def module_name(path: Path) -> str:
    rel = path.relative_to(PACKAGE.parent).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def imports(path: Path) -> list[str]:
    tree = ast.parse(path.read_text(encoding="utf-8"))
    out: list[str] = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            out.append(node.module)
            # `from rover_bridge.app import runner` imports the submodule rover_bridge.app.loop
            out += [f"{node.module}.{alias.name}" for alias in node.names if node.module.startswith("rover_bridge")]
    return out


def all_modules() -> dict[str, list[str]]:
    return {module_name(p): imports(p) for p in sorted(PACKAGE.rglob("*.py"))}


def test_every_package_says_what_it_does_and_what_it_may_import() -> None:
    for pkg in ("mavlink", "command", "estimate", "app", "fleet"):
        doc = ast.get_docstring(ast.parse((PACKAGE / pkg / "__init__.py").read_text()))
        assert doc and "May import" in doc, pkg


def test_dependencies_point_one_way() -> None:
    bad = []
    for mod, imported in all_modules().items():
        src = layer(mod)
        for target in imported:
            if not target.startswith("rover_bridge"):
                continue
            dst = layer(target)
            if dst not in ALLOWED[src]:
                bad.append(f"{mod} ({src}) imports {target} ({dst})")
            if src in ("command", "estimate") and target.startswith(SHELL_EDGE):
                bad.append(f"{mod} ({src}) imports the I/O module {target}")
    assert bad == []


def test_pure_layers_have_no_sockets_clocks_threads_or_signals() -> None:
    bad = []
    for mod, imported in all_modules().items():
        if layer(mod) in ("app", "fleet", "cli") or mod == SHELL_EDGE:
            continue
        bad += [f"{mod} imports {t}" for t in imported if t.split(".")[0] in IO_MODULES]
    assert bad == []


def test_the_rules_catch_a_wrong_import() -> None:
    # The checker itself must be able to fail: a flow importing the application is refused.
    assert "app" not in ALLOWED[layer("rover_bridge.command.core")]
    assert layer("rover_bridge.estimate.core") == "estimate" and "command" not in ALLOWED["estimate"]
    assert layer("rover_bridge.kinematics") == "math" and ALLOWED["math"] == {"math", "package"}


def test_no_two_modules_differ_only_by_a_suffix_and_none_is_named_after_the_product() -> None:
    stems = sorted({p.stem for p in PACKAGE.rglob("*.py") if not p.stem.startswith("__")})
    assert "bridge" not in stems and "rover_bridge" not in stems
    clashes = [(a, b) for a in stems for b in stems if a < b and (b.startswith(a) and len(b) - len(a) <= 3)]
    assert clashes == []


def test_no_class_in_the_command_flow_is_over_300_lines() -> None:
    sizes = {}
    for path in sorted((Path(__file__).resolve().parents[1] / "rover_bridge" / "command").glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.ClassDef):
                sizes[f"{path.name}:{node.name}"] = (node.end_lineno or node.lineno) - node.lineno + 1
    assert "core.py:CommandCore" in sizes and "gcs_failsafe.py:GcsSilence" in sizes
    assert {name: n for name, n in sizes.items() if n > 300} == {}


# ------------------------------------------------------------------ the whole project: no circles, no huge files

REPO = PACKAGE.parent
PACKAGES = ("rover_bridge", "sitl")
# Scripts import their neighbours by bare name: `python benchmarks/bench_bridge.py` puts benchmarks/ first on
# sys.path, pytest puts tests/ there. Their modules are named "benchmarks:bridge.harness", "tests:lockstep".
SCRIPT_FOLDERS = ("benchmarks", "tests")
MAX_SOURCE_LINES = 1000


def project_modules() -> dict[str, Path]:
    """Every module of the project by a name unique across it (packages dotted, scripts as FOLDER:dotted)."""
    out: dict[str, Path] = {}
    for top, prefix in [*((p, "") for p in PACKAGES), *((f, f"{f}:") for f in SCRIPT_FOLDERS)]:
        base = REPO if not prefix else REPO / top
        for path in sorted((REPO / top).rglob("*.py")):
            parts = list(path.relative_to(base).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts.pop()
            if parts:
                out[prefix + ".".join(parts)] = path
    return out


def imports_of(source: str, package: str, known: set[str], prefix: str = "") -> set[str]:
    """The known modules this source imports: top level, in functions, under `if TYPE_CHECKING:` alike (a circle
    through a type name is still a circle); relative imports made absolute from `package`. `from a import b` is
    an import of a.b where that is a module, else of a; a script's neighbour (prefix + name) before a package."""

    def resolve(*choices: str) -> str | None:
        for name in choices:
            for candidate in ((f"{prefix}{name}", name) if prefix else (name,)):
                if candidate in known:
                    return candidate
        return None

    found: set[str | None] = set()
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            found |= {resolve(alias.name) for alias in node.names}
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = package.split(".")
                base = ".".join([*parts[: len(parts) - node.level + 1], *([base] if base else [])])
            found |= {resolve(f"{base}.{alias.name}", base) for alias in node.names}
    return {name for name in found if name is not None}


def import_graph() -> dict[str, set[str]]:
    """module -> the project modules it imports."""
    modules = project_modules()
    graph: dict[str, set[str]] = {}
    for name, path in modules.items():
        folder, _, dotted = name.rpartition(":")
        package = dotted if path.name == "__init__.py" else dotted.rpartition(".")[0]
        source = path.read_text(encoding="utf-8")
        graph[name] = imports_of(source, package, set(modules), f"{folder}:" if folder else "") - {name}
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan's algorithm), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return sorted(found)


def test_no_modules_import_each_other_anywhere_in_the_project() -> None:
    graph = import_graph()
    # The reader sees the project: packages, scripts' neighbours, and a package's own modules.
    assert "rover_bridge.fleet.analysis" in graph["rover_bridge.app.commands.fleet"]
    assert "benchmarks:bridge.harness" in graph["benchmarks:bridge.process"]
    assert "tests:lockstep" in graph["tests:navrig"]
    assert "sitl.autopilot_view" in graph["sitl.commands"]
    assert cycles(graph) == []


def test_the_cycle_check_can_fail() -> None:
    # A circle of three is found, whoever imports into it; a type name under TYPE_CHECKING is an import, and so
    # are relative imports and imports inside functions.
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}, "e": set()}) == [["a", "b", "c"]]
    known = {"sitl", "sitl.autopilot", "sitl.incoming"}
    typed = "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from sitl.autopilot import Autopilot\n"
    assert imports_of(typed, "sitl", known) == {"sitl.autopilot"}
    assert imports_of("from .autopilot import Autopilot\n", "sitl", known) == {"sitl.autopilot"}
    assert imports_of("def f() -> None:\n    from sitl import incoming\n", "sitl", known) == {"sitl.incoming"}
    assert imports_of("from sitl import Autopilot\n", "sitl", known) == {"sitl"}  # a name of the package


def test_no_source_file_is_over_1000_lines() -> None:
    sizes = {str(path.relative_to(REPO)): len(path.read_text(encoding="utf-8").splitlines())
             for path in project_modules().values()}
    assert "benchmarks/bench_bridge.py" in sizes and "rover_bridge/fleet/analysis.py" in sizes
    assert {name: n for name, n in sizes.items() if n > MAX_SOURCE_LINES} == {}
