"""Benchmarks attach through what a user has: ``beavr_sim/bench`` never monkeypatches.

Read with ``ast`` (nothing imported): no ``setattr`` / ``delattr`` anywhere in ``bench/``, and
every attribute a bench module assigns belongs to an object the benchmark made itself -
``self`` (or a class it defines, instantiated), a parsed argument namespace - never a product
module, class or object (a stage's method, a guard's ``filter``, a module's function, a
counter). Writing items (an array's values, a dict's key) is data, not a patch; ``__dict__``
never. Timing a product call goes through :class:`beavr_sim.bench.timing.CallTimer`, tested
here too.
"""

from __future__ import annotations

import ast
import threading
from pathlib import Path

import pytest

from beavr_sim.bench.timing import CallTimer

BENCH_DIR = Path(__file__).resolve().parents[1] / "beavr_sim" / "bench"

#: (file, assigned attribute) -> why it is not a monkeypatch.
ALLOWED = {
    ("sim.py", "ref.opt.timestep"): "a MuJoCo option of the reference model the bench compiled",
}


def _bench_classes(trees: dict[str, ast.Module]) -> set[str]:
    return {
        node.name
        for tree in trees.values()
        for node in ast.walk(tree)
        if isinstance(node, ast.ClassDef)
    }


def _owned_names(fn: ast.AST, classes: set[str]) -> set[str]:
    """Names ``fn`` binds to objects the benchmark made: ``self``, an instance of a bench
    class (assigned from its call, a parameter annotated with it or a list of it, an item of
    such a list in a ``for``), parsed arguments."""
    owned = {"self", "cls"}
    if isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)):
        for arg in [*fn.args.posonlyargs, *fn.args.args, *fn.args.kwonlyargs]:
            annotation = ast.unparse(arg.annotation) if arg.annotation is not None else ""
            if annotation in classes or annotation in {f"list[{c}]" for c in classes}:
                owned.add(arg.arg)
    for node in ast.walk(fn):
        if isinstance(node, ast.Assign) and isinstance(node.value, ast.Call):
            func = node.value.func
            made = (isinstance(func, ast.Name) and func.id in classes) or (
                isinstance(func, ast.Attribute) and func.attr == "parse_args"
            )
            if made:
                owned.update(t.id for t in node.targets if isinstance(t, ast.Name))
        elif isinstance(node, ast.For):
            pairs = [(node.target, node.iter)]
            if (
                isinstance(node.iter, ast.Call)
                and ast.unparse(node.iter.func) == "zip"
                and isinstance(node.target, ast.Tuple)
            ):
                pairs = list(zip(node.target.elts, node.iter.args, strict=False))
            for target, items in pairs:
                if isinstance(target, ast.Name) and isinstance(items, ast.Name):
                    if items.id in owned:
                        owned.add(target.id)
    return owned


def violations(trees: dict[str, ast.Module]) -> list[str]:
    """Each ``file:line what`` where a bench module patches something it does not own."""
    classes = _bench_classes(trees)
    found = []

    def visit(name: str, scope: ast.AST, owned: set[str]) -> None:
        for node in ast.iter_child_nodes(scope):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)):
                visit(name, node, owned | _owned_names(node, classes))
                continue
            if isinstance(node, ast.ClassDef):
                visit(name, node, {"self", "cls"})
                continue
            check(name, node, owned)
            visit(name, node, owned)

    def check(name: str, node: ast.AST, owned: set[str]) -> None:
        if isinstance(node, ast.Call) and ast.unparse(node.func) in ("setattr", "delattr"):
            found.append(f"{name}:{node.lineno} {ast.unparse(node)}")
        targets: list[ast.expr] = []
        if isinstance(node, ast.Assign):
            targets = node.targets
        elif isinstance(node, (ast.AugAssign, ast.AnnAssign)):
            targets = [node.target]
        elif isinstance(node, ast.Delete):
            targets = node.targets
        elements = [e for t in targets for e in (t.elts if isinstance(t, ast.Tuple) else [t])]
        for target in elements:
            chain = []  # the attributes the target reaches through (x.a[k].b: a, b)
            node_ = target
            while isinstance(node_, (ast.Attribute, ast.Subscript)):
                if isinstance(node_, ast.Attribute):
                    chain.append(node_.attr)
                node_ = node_.value
            if "__dict__" not in chain and not isinstance(target, ast.Attribute):
                continue  # a local name, or items written (an array's values, a dict's key)
            text = ast.unparse(target)
            if (name, text) in ALLOWED:
                continue
            patches_type = {"__dict__", "__class__"} & set(chain)
            if isinstance(node_, ast.Name) and node_.id in owned and not patches_type:
                continue
            found.append(f"{name}:{target.lineno} {text} = ...")

    for name, tree in trees.items():
        visit(name, tree, set())
    return found


def _parse(sources: dict[str, str]) -> dict[str, ast.Module]:
    return {name: ast.parse(text, name) for name, text in sources.items()}


def test_bench_modules_never_patch_what_they_do_not_own():
    trees = _parse({p.name: p.read_text() for p in sorted(BENCH_DIR.glob("*.py"))})
    found = violations(trees)
    assert not found, (
        "bench/ assigns attributes of objects it did not make (time product calls with "
        "beavr_sim.bench.timing.CallTimer, attach through the loop's listeners and the twin "
        "stage's hooks):\n" + "\n".join(found)
    )


@pytest.mark.parametrize(
    "patch",
    [
        "setattr(loop.twin, 'step', wrapped)",
        "loop.twin.guard.filter = wrapped",
        "session.build_loop = wrapped",
        "op.observe = self.observe",
        "loop.twin.__dict__['step'] = wrapped",
    ],
)
def test_the_scan_finds_each_kind_of_patch(patch):
    """The scan is not vacuous: each way of patching, planted in a bench-like module, is found;
    the same assignments on the bench's own objects are not."""
    source = (
        "from beavr_sim.teleop import session\n"
        "class Timed:\n"
        "    def __init__(self, op):\n"
        "        self.op = op\n"
        "        self.n = 0\n"
        "def run(loop, op, wrapped):\n"
        "    timed = Timed(op)\n"
        "    timed.n += 1\n"
        f"    {patch.replace('self.', 'timed.')}\n"
    )
    (found,) = violations(_parse({"planted.py": source}))
    assert found.startswith("planted.py:9 ")


# ---------------------------------------------------------------------- CallTimer


class _Stage:
    def work(self, n: int) -> int:
        if n < 0:
            raise ValueError(n)
        return sum(range(n))

    def outer(self) -> int:
        return self.work(10) + self.work(20)


def _free(n: int) -> int:
    return n + 1


def test_call_timer_counts_calls_per_instance_and_leaves_the_object_alone():
    a, b = _Stage(), _Stage()
    seen: list[str] = []
    timer = CallTimer(
        {"a": a.work, "free": _free, "outer": a.outer}, sink=lambda label, s: seen.append(label)
    )
    with timer:
        assert a.work(3) == 3 and b.work(3) == 3  # b's calls are not a's
        assert _free(1) == 2
        with pytest.raises(ValueError):
            a.work(-1)  # raised: not counted
        a.outer()  # nested calls of a.work inside a timed call
        thread = threading.Thread(target=a.work, args=(5,))
        thread.start()
        thread.join()
    assert timer.calls == {"a": 4, "free": 1, "outer": 1}
    assert seen.count("a") == 4 and "outer" in seen
    assert all(v >= 0 for v in timer.totals.values())
    assert timer.totals["outer"] >= 0 and "work" not in vars(a)  # nothing assigned on a
    a.work(1)  # after the block: no longer watched
    assert timer.calls["a"] == 4


def test_call_timer_refuses_what_it_cannot_time():
    def gen():
        yield 1

    with pytest.raises(TypeError, match="generator"):
        CallTimer({"g": gen})
    with pytest.raises(TypeError, match="Python function"):
        CallTimer({"len": len})
    with pytest.raises(ValueError, match="at least one"):
        CallTimer({})
    with CallTimer({"free": _free}), pytest.raises(RuntimeError, match="tool id"):
        with CallTimer({"x": _free}), CallTimer({"y": _free}), CallTimer({"z": _free}):
            pass
