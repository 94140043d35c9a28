"""The import graph of cosy_lite has no cycles, and every module imports by itself, cheaply.

Why: a cycle between packages (``geometry`` importing ``bop`` while ``bop`` imports ``geometry``)
means neither can be read, tested or reused without the other, and import order starts to matter
(a function-local import that "fixes" a cycle is still a cycle, only one found later at run time).
So every import counts here: module level, function-local and ``if TYPE_CHECKING:`` ones, relative
ones resolved. The graph is taken between top-level units (subpackages such as ``geometry``,
``bop``; top-level modules such as ``config``, ``errors``, ``structures``) and, inside each
package, between its modules. A failure prints the cycle with the file:line of each import in it.

Then, in a fresh interpreter, every module is imported in dependency order (each must import), and
importing ``cosy_lite`` and its packages does nothing heavy: no files or folders made, torch not
imported (STYLE: nothing happens at import).
"""

from __future__ import annotations

import ast
import json
import os
import subprocess
import sys
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PACKAGE = "cosy_lite"
ROOT = REPO / PACKAGE


@dataclass(frozen=True)
class Import:
    """One import statement's edge: ``source`` module imports ``target`` module (file:line)."""

    source: str
    target: str
    file: str
    line: int
    text: str

    def where(self) -> str:
        return f"{self.file}:{self.line} `{self.text}`"


def module_names() -> dict[str, Path]:
    """Dotted module name -> file, of every module under cosy_lite/ (packages by their __init__)."""
    out = {}
    for path in sorted(ROOT.rglob("*.py")):
        parts = path.relative_to(REPO).with_suffix("").parts
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = path
    return out


def _is_package(path: Path) -> bool:
    return path.name == "__init__.py"


def _resolve_relative(module: str, is_package: bool, level: int, name: str | None) -> str:
    base = module.split(".") if is_package else module.split(".")[:-1]
    if level > 1:
        base = base[: len(base) - (level - 1)]
    return ".".join(base + ([name] if name else []))


def _ancestors(name: str) -> list[str]:
    parts = name.split(".")
    return [".".join(parts[:i]) for i in range(1, len(parts))]


def imports(modules: dict[str, Path], repo: Path = REPO) -> list[Import]:
    """Every import between cosy_lite modules, wherever it is written (module level, in functions,
    under ``if TYPE_CHECKING:``). ``from a import b`` is an edge to ``a.b`` when that is a module,
    else to ``a``; importing ``a.b.c`` also runs ``a`` and ``a.b`` (edges to those packages, except
    the importer's own)."""
    edges = []
    for module, path in modules.items():
        tree = ast.parse(path.read_text(), str(path))
        lines = path.read_text().splitlines()
        file = str(path.relative_to(repo))
        own = set(_ancestors(module)) | {module}
        for node in ast.walk(tree):
            targets: list[str] = []
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = (_resolve_relative(module, _is_package(path), node.level, node.module) if node.level
                        else node.module or "")
                for a in node.names:
                    sub = f"{base}.{a.name}"
                    targets.append(sub if sub in modules else base)
            for target in targets:
                if not (target == PACKAGE or target.startswith(PACKAGE + ".")):
                    continue
                while target not in modules:  # an attribute path such as cosy_lite.x.Name
                    target = target.rsplit(".", 1)[0]
                text = lines[node.lineno - 1].strip()
                for t in [*_ancestors(target), target]:
                    if t not in own:
                        edges.append(Import(module, t, file, node.lineno, text))
    return edges


def unit(module: str) -> str:
    """The top-level unit of a module: ``cosy_lite.geometry.points`` -> ``geometry``,
    ``cosy_lite.config`` -> ``config``, ``cosy_lite`` -> ``cosy_lite``."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else parts[0]


def graph(edges: list[Import]) -> dict[str, dict[str, list[Import]]]:
    """source -> target -> the imports making that edge."""
    out: dict[str, dict[str, list[Import]]] = defaultdict(lambda: defaultdict(list))
    for e in edges:
        if e.source != e.target and all((e.file, e.line) != (o.file, o.line) for o in out[e.source][e.target]):
            out[e.source][e.target].append(e)
    return out


def cycles(g: dict[str, dict[str, list[Import]]]) -> list[list[str]]:
    """One cycle (list of nodes, first repeated at the end) per strongly connected component with
    more than one node (Tarjan), in sorted order."""
    nodes = sorted(set(g) | {t for s in g for t in g[s]})
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    components: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(g.get(v, {})):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                components.append(sorted(comp))

    for v in nodes:
        if v not in index:
            visit(v)
    out = []
    for comp in sorted(components):
        members = set(comp)
        start = comp[0]
        # shortest path back to start inside the component (BFS)
        prev = {start: None}
        queue = [start]
        found = None
        while queue and found is None:
            v = queue.pop(0)
            for w in sorted(g.get(v, {})):
                if w == start:
                    found = v
                    break
                if w in members and w not in prev:
                    prev[w] = v
                    queue.append(w)
        path = [start]
        v = found
        while v is not None and v != start:
            path.insert(1, v)
            v = prev[v]
        out.append(path + [start])
    return out


def describe(cycle: list[str], g: dict[str, dict[str, list[Import]]]) -> str:
    lines = [" -> ".join(cycle)]
    for a, b in zip(cycle, cycle[1:]):
        lines.append(f"  {a} -> {b}:")
        lines += [f"      {e.where()}" for e in g[a][b]]
    return "\n".join(lines)


def topological_order(modules: dict[str, Path], edges: list[Import]) -> list[str]:
    """Modules with every module after what it imports (ties by name); cycles broken by name."""
    deps: dict[str, set[str]] = {m: set() for m in modules}
    for e in edges:
        if e.source != e.target:
            deps[e.source].add(e.target)
    order: list[str] = []
    state: dict[str, int] = {}

    def visit(m: str) -> None:
        if state.get(m):
            return
        state[m] = 1
        for d in sorted(deps[m]):
            visit(d)
        state[m] = 2
        order.append(m)

    for m in sorted(modules):
        visit(m)
    return order


@pytest.fixture(scope="module")
def import_graph():
    modules = module_names()
    return modules, imports(modules)


def test_graph_sees_every_kind_of_import(tmp_path):
    """The parser finds module-level, function-local, TYPE_CHECKING and relative imports."""
    mods = {"cosy_lite": tmp_path / "__init__.py", "cosy_lite.a": tmp_path / "a" / "__init__.py",
            "cosy_lite.a.x": tmp_path / "a" / "x.py", "cosy_lite.a.y": tmp_path / "a" / "y.py",
            "cosy_lite.b": tmp_path / "b.py", "cosy_lite.c": tmp_path / "c.py"}
    (tmp_path / "a").mkdir()
    for p in mods.values():
        p.write_text("")
    mods["cosy_lite.a.x"].write_text(
        "from typing import TYPE_CHECKING\n"
        "from . import y\n"
        "if TYPE_CHECKING:\n    from cosy_lite.b import Thing\n"
        "def f():\n    import cosy_lite.c\n")
    edges = imports(mods, tmp_path)
    found = {(e.source, e.target, e.line) for e in edges}
    assert ("cosy_lite.a.x", "cosy_lite.a.y", 2) in found
    assert ("cosy_lite.a.x", "cosy_lite.b", 4) in found
    assert ("cosy_lite.a.x", "cosy_lite.c", 6) in found
    g = graph([Import("m.a", "m.b", "f", 1, ""), Import("m.b", "m.c", "f", 2, ""), Import("m.c", "m.a", "f", 3, "")])
    assert cycles(g) == [["m.a", "m.b", "m.c", "m.a"]]


def test_no_cycles_between_packages(import_graph):
    """Top-level units (geometry, bop, config, ...) form a DAG."""
    _, edges = import_graph
    g = graph([Import(unit(e.source), unit(e.target), e.file, e.line, e.text) for e in edges])
    found = cycles(g)
    assert not found, "import cycles between cosy_lite packages:\n" + "\n".join(describe(c, g) for c in found)


def test_no_cycles_inside_packages(import_graph):
    """Inside each package, its modules form a DAG (e.g. no onnx_export <-> quantize)."""
    _, edges = import_graph
    g = graph([e for e in edges if unit(e.source) == unit(e.target)])
    found = cycles(g)
    assert not found, "import cycles inside cosy_lite packages:\n" + "\n".join(describe(c, g) for c in found)


_IMPORT_ALL = """
import importlib, json, sys, traceback
failed = {}
for name in json.loads(sys.argv[1]):
    try:
        importlib.import_module(name)
    except BaseException as e:
        failed[name] = "".join(traceback.format_exception_only(type(e), e)).strip()
import torch
print(json.dumps({"failed": failed, "cuda_initialised": torch.cuda.is_initialized()}))
"""


def _clean_env(tmp_path: Path) -> dict[str, str]:
    home = tmp_path / "home"
    home.mkdir()
    env = {**os.environ, "HOME": str(home), "PYTHONPATH": str(REPO), "PYOPENGL_PLATFORM": "egl",
           "MPLCONFIGDIR": str(tmp_path / "mpl"), "XDG_CACHE_HOME": str(tmp_path / "cache"),
           "OMP_WAIT_POLICY": "PASSIVE"}
    env.pop("COSY_LITE_DATA", None)
    return env


def _files(folder: Path) -> set[Path]:
    return {p for p in folder.rglob("*")}


def test_every_module_imports_in_dependency_order(import_graph, tmp_path):
    """In a fresh interpreter, each module imports after what it imports; CUDA stays untouched."""
    modules, edges = import_graph
    order = topological_order(modules, edges)
    work = tmp_path / "cwd"
    work.mkdir()
    env = _clean_env(tmp_path)
    res = subprocess.run([sys.executable, "-c", _IMPORT_ALL, json.dumps(order)], cwd=work, env=env,
                         capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr[-3000:]
    out = json.loads(res.stdout.strip().splitlines()[-1])
    assert not out["failed"], "modules that do not import:\n" + "\n".join(f"  {k}: {v}" for k, v in out["failed"].items())
    assert not out["cuda_initialised"], "importing cosy_lite modules initialised CUDA"
    made = _files(work) | _files(tmp_path / "home")
    assert not made, f"importing cosy_lite modules made {sorted(made)}"


_IMPORT_PACKAGES = """
import importlib, json, sys
for name in json.loads(sys.argv[1]):
    importlib.import_module(name)
heavy = sorted(m for m in ("torch", "torchvision", "pyrender", "OpenGL", "onnxruntime", "open3d", "mujoco",
                           "matplotlib", "cv2") if m in sys.modules)
print(json.dumps({"heavy": heavy}))
"""

# packages whose __init__ imports its modules on purpose (and so what those import)
EAGER_PACKAGES = {"cosy_lite.render"}


def test_importing_packages_does_nothing_heavy(import_graph, tmp_path):
    """``import cosy_lite`` and each package's ``__init__``: no files or folders made anywhere we
    can see (working folder, HOME), no torch / renderer / onnxruntime pulled in."""
    modules, _ = import_graph
    packages = sorted(m for m, p in modules.items() if _is_package(p) and m not in EAGER_PACKAGES)
    work = tmp_path / "cwd"
    work.mkdir()
    env = _clean_env(tmp_path)
    before = _files(tmp_path)
    res = subprocess.run([sys.executable, "-c", _IMPORT_PACKAGES, json.dumps(packages)], cwd=work, env=env,
                         capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-3000:]
    heavy = json.loads(res.stdout.strip().splitlines()[-1])["heavy"]
    assert not heavy, f"importing {packages} imported {heavy}"
    made = _files(tmp_path) - before
    assert not made, f"importing cosy_lite packages made {sorted(made)}"
