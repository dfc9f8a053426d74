"""The packages' layers: each module imports only from its own layer and the layers below it, there is no import
circle, and the core imports nothing of the ROS package. Read from the source (every import statement, also those
inside functions), so that a lazy import does not hide a dependency."""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

# Lowest first. A module belongs to the first entry that its dotted name (without `eslam_core.`) starts with.
LAYERS = [
    ("base", ["__init__", "native", "cpu", "device", "child_process", "camera", "geometry", "atomic", "config",
              "frames", "trajectory", "map_file"]),
    ("representation", ["representation"]),
    ("rendering", ["rendering"]),
    ("datasets", ["datasets"]),
    ("mapping", ["mapping"]),
    ("tracking", ["tracking"]),
    ("submaps", ["submaps"]),
    ("lock-step system", ["slam"]),
    ("outputs", ["outputs"]),
    ("runtime", ["runtime"]),
    ("evaluation", ["evaluation"]),
    ("applications", ["runner", "demo", "doctor", "cli", "__main__"]),
]


def module_names() -> dict[str, Path]:
    names = {}
    for package in ("eslam_core", "eslam_ros"):
        for path in (ROOT / package).rglob("*.py"):
            parts = path.relative_to(ROOT).with_suffix("").parts
            names[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return names


MODULES = module_names()


def imported_modules(name: str) -> set[str]:
    """The project's modules that `name` imports (the deepest existing module of each imported name)."""
    path = MODULES[name]
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parent = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join(parent + ([base] if base else []))
            targets = [f"{base}.{a.name}" for a in node.names]
        else:
            continue
        for target in targets:
            while target and target not in MODULES:
                target = target.rpartition(".")[0]
            if target and target != name:
                found.add(target)
    return found


GRAPH = {name: imported_modules(name) for name in MODULES}


def layer_of(name: str) -> int:
    if name.startswith("eslam_ros"):
        return len(LAYERS)
    local = name.removeprefix("eslam_core").removeprefix(".") or "__init__"
    for rank, (_, prefixes) in enumerate(LAYERS):
        if any(local == p or local.startswith(p + ".") for p in prefixes):
            return rank
    raise AssertionError(f"{name} is in no layer: add it to LAYERS in {Path(__file__).name}")


def layer_name(name: str) -> str:
    rank = layer_of(name)
    return LAYERS[rank][0] if rank < len(LAYERS) else "the ROS package"


def test_every_module_has_a_layer():
    for name in MODULES:
        layer_of(name)


def test_the_core_imports_nothing_of_the_ros_package():
    wrong = sorted(f"{m} imports {d}" for m, deps in GRAPH.items() if m.startswith("eslam_core")
                   for d in deps if d.startswith("eslam_ros"))
    assert not wrong, "the core holds no ROS: " + "; ".join(wrong)


def test_no_module_imports_from_a_higher_layer():
    wrong = sorted(f"{m} ({layer_name(m)}) imports {d} ({layer_name(d)})"
                   for m, deps in GRAPH.items() if m.startswith("eslam_core")
                   for d in deps if layer_of(d) > layer_of(m))
    assert not wrong, "imports that run up a layer: " + "; ".join(wrong)


def import_circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan), each a set of modules that import each
    other, directly or through others."""
    index, low, stack, on_stack, circles = {}, {}, [], set(), []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph.get(v, ()):
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
                circles.append(sorted(component))

    for v in graph:
        if v not in index:
            visit(v)
    return circles


def test_no_import_circle():
    assert import_circles(GRAPH) == []


def test_the_circle_finder_finds_circles():
    assert import_circles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert import_circles({"a": {"b"}, "b": set()}) == []


@pytest.mark.parametrize("statement, expected", [
    ("from eslam_core.tracking.result import TrackingResult", {"eslam_core.tracking.result"}),
    ("from eslam_core.tracking import result", {"eslam_core.tracking.result"}),
    ("import eslam_core.geometry as g", {"eslam_core.geometry"}),
    ("def f():\n    from eslam_ros.bag import main", {"eslam_ros.bag"}),
])
def test_imports_are_read_from_every_statement(tmp_path, monkeypatch, statement, expected):
    probe = tmp_path / "probe.py"
    probe.write_text(statement + "\n")
    monkeypatch.setitem(MODULES, "eslam_core.probe", probe)
    assert imported_modules("eslam_core.probe") == expected


def test_no_class_of_the_ros_package_is_over_400_lines():
    """The node is glue over its parts (slam_node.py's docstring), not the place where everything lands."""
    long = sorted(f"{path.name}: {node.name} ({node.end_lineno - node.lineno + 1} lines)"
                  for path in (ROOT / "eslam_ros").glob("*.py")
                  for node in ast.parse(path.read_text()).body
                  if isinstance(node, ast.ClassDef) and node.end_lineno - node.lineno + 1 > 400)
    assert not long, long
