"""The package's import graph: no circles among its modules, and imports run downward only.

Every ``import`` / ``from ... import`` statement of every module counts, the ones inside
functions too (read with ``ast``, nothing imported). An edge goes to the module the statement
names: ``from beavr_sim.operator import kernels`` is an edge to ``beavr_sim.operator.kernels``
when that is a module, else to the package ``beavr_sim.operator``. The parent packages that
Python also initialises on the way are not edges (every module would reach
``beavr_sim/__init__``).

Layers (lowest first) are the data flow of ``docs/architecture.md``: a module may import its own
package and the packages of lower layers, never a package of its own layer or above. Entry
points (``__main__`` modules) sit on top; no module imports one.
"""

from __future__ import annotations

import ast
from collections.abc import Iterable, Mapping
from pathlib import Path

PACKAGE_DIR = Path(__file__).resolve().parents[1] / "beavr_sim"

#: Top-level modules and packages of ``beavr_sim``, lowest layer first.
LAYERS: tuple[tuple[str, ...], ...] = (
    ("naming", "assets", "workcell", "scaling", "heap"),  # names, files, world frame, jobs, heap
    ("robots",),  # arms, hands, embodiments (MjSpec composition)
    ("tasks",),  # objects, resets, success checkers
    ("envs", "reference"),  # the gym env; reference models for tests and benchmarks
    ("beavr_sim",),  # the package root: registers the envs on import
    ("experts",),  # scripted experts on the env
    ("wire",),  # records that cross stages, messages, transport, ports
    ("traces",),  # the VR trace file format
    ("headset",),  # stage 1: detector
    ("operator",),  # stage 2: hands -> joint commands
    ("twin",),  # stage 3: twin and collision guard
    ("hardware", "cameras"),  # stage 4: drivers, emulators, mirroring; real cameras (LeRobot)
    ("datasets", "viz"),  # beside the runners: recorder, browser view, rerun log
    ("teleop",),  # the runners
    ("synthetic", "eval"),  # what drives the runners: synthetic operator, policy evaluation
    ("integrations",),  # LeRobot's env, robot and teleoperator plugins over all of the above
    ("bench", "demo"),  # measurements and the scripted demo
)
RANK = {unit: rank for rank, units in enumerate(LAYERS) for unit in units}


def module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE_DIR.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def all_modules() -> dict[str, Path]:
    return {module_name(p): p for p in sorted(PACKAGE_DIR.rglob("*.py"))}


def imported_modules(path: Path, name: str, modules: Iterable[str]) -> set[str]:
    """The ``beavr_sim`` modules that ``path`` (module ``name``) imports, anywhere in it."""
    modules = set(modules)
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            targets = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.rsplit(".", node.level - 1)[0] if node.level > 1 else package
                source = f"{base}.{node.module}" if node.module else base
            else:
                source = node.module or ""
            targets = [f"{source}.{alias.name}" for alias in node.names]
            targets = [t if t in modules else source for t in targets]
        else:
            continue
        found.update(t for t in targets if t in modules)
    found.discard(name)
    return found


def import_graph() -> dict[str, set[str]]:
    modules = all_modules()
    return {name: imported_modules(path, name, modules) for name, path in modules.items()}


def find_circles(graph: Mapping[str, Iterable[str]]) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    circles: list[list[str]] = []

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

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return circles


def unit_of(module: str) -> str:
    """Top-level module or package of ``beavr_sim.<unit>...`` (the root is ``beavr_sim``)."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else parts[0]


def upward_imports(graph: Mapping[str, Iterable[str]]) -> list[str]:
    """Imports that do not run downward, as readable lines."""
    bad = []
    for source, targets in sorted(graph.items()):
        for target in sorted(targets):
            if target.endswith("__main__"):
                bad.append(f"{source} imports the entry point {target}")
            elif source.endswith("__main__") or unit_of(source) == unit_of(target):
                continue
            elif RANK[unit_of(target)] >= RANK[unit_of(source)]:
                bad.append(
                    f"{source} ({unit_of(source)}, layer {RANK[unit_of(source)]}) imports "
                    f"{target} ({unit_of(target)}, layer {RANK[unit_of(target)]})"
                )
    return bad


def test_finder_sees_circles_and_nested_imports(tmp_path):
    # The finder itself: a circle through an import inside a function is found.
    assert find_circles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert find_circles({"a": {"b"}, "b": set()}) == []
    source = tmp_path / "m.py"
    source.write_text("def f():\n    from beavr_sim.teleop import session\n")
    assert imported_modules(source, "beavr_sim.x", {"beavr_sim.teleop.session"}) == {
        "beavr_sim.teleop.session"
    }
    assert upward_imports({"beavr_sim.tasks.base": {"beavr_sim.envs.scene"}})
    assert upward_imports({"beavr_sim.teleop.session": {"beavr_sim.datasets.__main__"}})
    assert not upward_imports({"beavr_sim.envs.scene": {"beavr_sim.tasks.base"}})


def test_every_package_has_a_layer():
    units = {unit_of(m) for m in all_modules()}
    missing = sorted(units - set(RANK))
    assert not missing, f"give these a layer in LAYERS (tests/test_import_layers.py): {missing}"


def test_no_import_circles():
    circles = find_circles(import_graph())
    assert not circles, "import circles among beavr_sim's modules:\n" + "\n".join(
        " <-> ".join(c) for c in circles
    )


def test_imports_run_downward():
    bad = upward_imports(import_graph())
    assert not bad, "imports that run up a layer or into an entry point:\n" + "\n".join(bad)


def emulator_reach(graph: Mapping[str, Iterable[str]]) -> list[str]:
    """Hardware drivers and device configs that import an emulator, directly or through
    another module, as readable lines (a driver must not lean on its test double)."""
    emulators = {m for m in graph if m.startswith("beavr_sim.hardware.") and "emulator" in m}
    bad = []
    for source in sorted(graph):
        leaf = source.rsplit(".", 1)[-1]
        if not source.startswith("beavr_sim.hardware.") or leaf not in ("driver", "config"):
            continue
        seen, todo = set(), list(graph[source])
        while todo:
            module = todo.pop()
            if module in seen:
                continue
            seen.add(module)
            todo.extend(graph.get(module, ()))
        bad += [f"{source} reaches {m}" for m in sorted(seen & emulators)]
    return bad


def test_drivers_never_import_emulators():
    assert emulator_reach(
        {
            "beavr_sim.hardware.x.driver": {"beavr_sim.hardware.y"},
            "beavr_sim.hardware.y": {"beavr_sim.hardware.x.emulator"},
            "beavr_sim.hardware.x.emulator": set(),
        }
    ) == ["beavr_sim.hardware.x.driver reaches beavr_sim.hardware.x.emulator"]
    bad = emulator_reach(import_graph())
    assert not bad, "drivers that import an emulator:\n" + "\n".join(bad)
