"""The package layout is the architecture: dependencies point one way (math <- mavlink <- flows <- app <- fleet
<- cli): the fleet report consumes the application (replay, calibration), and only the CLI's commands sit above it.

Every `import` of every module under rover_bridge/ (at any depth, also inside functions) is read from
the source and checked against the layer rules below; the pure layers also may not touch sockets,
clocks, threads or signals. A new module that breaks the direction fails here, not in review.
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
