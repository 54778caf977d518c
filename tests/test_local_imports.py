"""Function-local imports guard only heavy or optional dependencies.

An ``import`` inside a function (read with ``ast``, nothing imported) of ``beavr_sim`` or
``plugins`` must either name a module of ``HEAVY_OR_OPTIONAL`` (chosen from
``python -X importtime`` numbers or because the package is an optional extra) or carry a
``# local: heavy|optional|cycle (<why>)`` comment on one of its lines. Everything else goes at
module top.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

#: Top-level packages that may be imported inside a function without a mark.
HEAVY_OR_OPTIONAL = frozenset(
    {
        # optional extras or vendor SDKs
        "lerobot", "datasets", "torch", "viser", "rerun", "cv2", "playwright", "xarm",
        "dynamixel_sdk", "scservo_sdk", "av", "segno", "ray", "dex_retargeting",
        # measured cold import cost (ms): mujoco ~110, pandas ~380, imageio ~90, matplotlib
        # ~350, mink/scipy ~400, tqdm ~45, zmq ~40, mcap ~25-50 (with its codecs
        # zstandard / lz4), websockets (asyncio, ssl)
        "mujoco", "pandas", "imageio", "matplotlib", "mink", "tqdm", "zmq", "mcap",
        "zstandard", "lz4", "websockets",
    }
)  # fmt: skip

#: Files not checked yet (none: every module is).
NOT_YET_CHECKED: tuple[str, ...] = ()

MARK = re.compile(r"#\s*local:\s*(heavy|optional|cycle)\b")


def local_imports(source: str) -> list[tuple[int, str]]:
    """``(line, module)`` of every import inside a function, ``module`` as written."""
    found: list[tuple[int, str]] = []

    def walk(node: ast.AST, in_function: bool) -> None:
        for child in ast.iter_child_nodes(node):
            if in_function and isinstance(child, ast.Import):
                found.extend((child.lineno, alias.name) for alias in child.names)
            elif in_function and isinstance(child, ast.ImportFrom):
                found.append((child.lineno, "." * child.level + (child.module or "")))
            walk(child, in_function or isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef))

    walk(ast.parse(source), False)
    return found


def unjustified(source: str) -> list[tuple[int, str]]:
    """The local imports of ``source`` that are neither heavy/optional nor marked."""
    lines = source.splitlines()
    tree_ends = {
        n.lineno: n.end_lineno or n.lineno
        for n in ast.walk(ast.parse(source))
        if isinstance(n, ast.Import | ast.ImportFrom)
    }
    bad = []
    for line, module in local_imports(source):
        if module.split(".")[0] in HEAVY_OR_OPTIONAL:
            continue
        text = "\n".join(lines[line - 1 : tree_ends[line]])
        if not MARK.search(text):
            bad.append((line, module))
    return bad


def checked_files() -> list[Path]:
    files = sorted(
        [*ROOT.joinpath("beavr_sim").rglob("*.py"), *ROOT.joinpath("plugins").rglob("*.py")]
    )
    return [p for p in files if not p.relative_to(ROOT).as_posix().startswith(NOT_YET_CHECKED)]


def test_scanner_sees_unmarked_local_imports():
    source = (
        "import json\n"
        "def f():\n    import json\n    import torch\n"
        "    from beavr_sim.teleop import session  # local: heavy (the whole pipeline)\n"
        "class C:\n    def g(self):\n        from .x import y\n"
    )
    assert unjustified(source) == [(3, "json"), (8, ".x")]


def test_function_local_imports_are_heavy_optional_or_marked():
    bad = [
        f"{p.relative_to(ROOT)}:{line} imports {module}"
        for p in checked_files()
        for line, module in unjustified(p.read_text())
    ]
    assert not bad, (
        "function-local imports of cheap modules: move them to module top, or mark them "
        "'# local: heavy|optional|cycle (<why>)':\n" + "\n".join(bad)
    )
