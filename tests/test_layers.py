"""The walls between the layers, read from the source with `ast` (function-level imports too).

Layers, top to bottom: `dexdrake/cli/` (the command line); `systems/` (Drake systems and
diagrams, installed as dexdrake.systems) and `hardware/` (drivers, emulators, perception,
installed as dexdrake.hardware); the core (the rest of `dexdrake/`). Rules:
- the core imports neither systems/, hardware/ nor the CLI;
- hardware/ imports neither systems/, learn/, eval/ nor the CLI;
- systems/ does not import the CLI;
- Drake LeafSystems are defined only in systems/;
- no import circle between files.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
# source folder -> the package it installs as (pyproject.toml's package-dir)
PACKAGES = {"dexdrake": "dexdrake", "systems": "dexdrake.systems", "hardware": "dexdrake.hardware"}

# layer -> the packages it must not import, each with the reason printed on a violation
FORBIDDEN = {
    "core": ("dexdrake.systems", "dexdrake.hardware", "dexdrake.cli"),
    "hardware": ("dexdrake.systems", "dexdrake.learn", "dexdrake.eval", "dexdrake.cli"),
    "systems": ("dexdrake.cli",),
    "cli": (),
}

# Temporary exceptions, (importing file, imported package); each says why and until when.
ALLOWED: set[tuple[str, str]] = set()


def module_files(root: Path) -> dict[str, Path]:
    """Dotted module name -> file, for every .py under the source folders of `root`."""
    modules = {}
    for folder, package in PACKAGES.items():
        for path in sorted((root / folder).rglob("*.py")):
            parts = path.relative_to(root / folder).with_suffix("").parts
            if parts[-1] == "__init__":
                parts = parts[:-1]
            modules[".".join((package, *parts))] = path
    return modules


def layer(module: str) -> str:
    for name in ("cli", "systems", "hardware"):
        if module == f"dexdrake.{name}" or module.startswith(f"dexdrake.{name}."):
            return name
    return "core"


def _within(module: str, package: str) -> bool:
    return module == package or module.startswith(package + ".")


def imports(module: str, path: Path, modules: dict[str, Path]) -> list[tuple[str, int]]:
    """(imported module, line) for every import statement in the file, at any depth; a
    relative import is resolved, and `from P import m` names module P.m where that exists."""
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found |= {(alias.name, node.lineno) for alias in node.names}
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[:len(package.split(".")) - node.level + 1]
                base = ".".join(anchor + ([base] if base else []))
            for alias in node.names:
                sub = f"{base}.{alias.name}"
                found.add((sub if sub in modules else base, node.lineno))
    return sorted(found, key=lambda f: (f[1], f[0]))


def _is_leaf_system(base: ast.expr) -> bool:
    return (isinstance(base, ast.Name) and base.id == "LeafSystem") or (
        isinstance(base, ast.Attribute) and base.attr == "LeafSystem")


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    components = []
    for start in sorted(graph):
        if start in index:
            continue
        work = [(start, iter(sorted(graph[start])))]
        index[start] = low[start] = len(index)
        stack.append(start)
        on_stack.add(start)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = len(index)
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph[child]))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.append(member)
                    if member == node:
                        break
                if len(component) > 1:
                    components.append(sorted(component))
    return components


def violations(root: Path, allowed: set[tuple[str, str]] = frozenset()) -> list[str]:
    """One line per broken rule under `root`, naming the file and line."""
    modules = module_files(root)
    problems = []
    graph: dict[str, set[str]] = {m: set() for m in modules}
    for module, path in modules.items():
        where = path.relative_to(root).as_posix()
        for target, line in imports(module, path, modules):
            for package in FORBIDDEN[layer(module)]:
                if _within(target, package) and (where, package) not in allowed:
                    problems.append(f"{where}:{line}: the {layer(module)} layer imports {target} "
                                    f"(it must not import {package})")
            if target in modules and target != module:
                graph[module].add(target)
        if layer(module) != "systems":
            for node in ast.walk(ast.parse(path.read_text(), str(path))):
                if isinstance(node, ast.ClassDef) and any(map(_is_leaf_system, node.bases)):
                    problems.append(f"{where}:{node.lineno}: LeafSystem {node.name} is defined "
                                    "outside systems/")
    for component in _cycles(graph):
        files = ", ".join(modules[m].relative_to(root).as_posix() for m in component)
        problems.append(f"import circle between {files}")
    return problems


def test_layers_hold():
    problems = violations(REPO, ALLOWED)
    assert not problems, "layer rules broken (see tests/test_layers.py):\n" + "\n".join(problems)


def test_allowed_exceptions_are_still_needed():
    """An allow-list entry whose import is gone must be removed."""
    for entry in ALLOWED:
        assert any(entry[0] in p for p in violations(REPO)), f"{entry} is no longer needed"


# name -> ({file: text} of a tiny tree, a fragment the one violation's message holds)
BROKEN_TREES = {
    "core imports systems": ({"dexdrake/eval/envs.py": "def f():\n    from dexdrake.systems import scene\n",
                              "systems/scene.py": ""}, "dexdrake/eval/envs.py:2: the core layer"),
    "core imports hardware (relative)": ({"dexdrake/learn/x.py": "from ..hardware import kinect\n"},
                                         "dexdrake/learn/x.py:1: the core layer imports dexdrake.hardware"),
    "core imports cli": ({"dexdrake/task.py": "import dexdrake.cli.sim\n"},
                         "imports dexdrake.cli.sim"),
    "hardware imports systems": ({"hardware/z1.py": "from dexdrake.systems.scene import add_table\n"},
                                 "hardware/z1.py:1: the hardware layer"),
    "hardware imports learn": ({"hardware/z1.py": "from dexdrake.learn import policy\n"},
                               "imports dexdrake.learn"),
    "hardware imports eval": ({"hardware/z1.py": "if True:\n    import dexdrake.eval.tables\n"},
                              "imports dexdrake.eval.tables"),
    "systems imports cli": ({"systems/station.py": "from dexdrake.cli import station\n"},
                            "systems/station.py:1: the systems layer imports dexdrake.cli"),
    "LeafSystem outside systems": ({"hardware/drv.py": "from pydrake.systems.framework import LeafSystem\n"
                                                       "class Drv(LeafSystem):\n    pass\n"},
                                   "hardware/drv.py:2: LeafSystem Drv"),
    "LeafSystem by attribute": ({"dexdrake/x.py": "import pydrake.systems.framework as f\n"
                                                  "class Y(f.LeafSystem):\n    pass\n"},
                                "LeafSystem Y is defined outside systems/"),
    "import circle": ({"dexdrake/a.py": "from dexdrake import b\n",
                       "dexdrake/b.py": "def f():\n    from . import c\n",
                       "dexdrake/c.py": "import dexdrake.a\n"},
                      "import circle between dexdrake/a.py, dexdrake/b.py, dexdrake/c.py"),
}


@pytest.mark.parametrize("name", sorted(BROKEN_TREES))
def test_each_rule_can_fail(tmp_path, name):
    files, message = BROKEN_TREES[name]
    for folder in PACKAGES:
        (tmp_path / folder).mkdir()
        (tmp_path / folder / "__init__.py").write_text("")
    for rel, text in files.items():
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_text(text)
    problems = violations(tmp_path)
    assert len(problems) == 1 and message in problems[0], problems


def test_allowed_tree_passes(tmp_path):
    """The layers as intended: cli over systems and hardware over the core, no circle."""
    for rel, text in {"dexdrake/cli/sim.py": "from dexdrake.systems import scene\nimport dexdrake.hardware.z1\n",
                      "systems/scene.py": "from dexdrake.hardware import z1\nfrom dexdrake.learn import p\n"
                                          "from pydrake.systems.framework import LeafSystem\n"
                                          "class S(LeafSystem):\n    pass\n",
                      "hardware/z1.py": "from dexdrake import task\n",
                      "dexdrake/learn/p.py": "from dexdrake import task\n",
                      "dexdrake/task.py": ""}.items():
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_text(text)
    assert violations(tmp_path) == []
