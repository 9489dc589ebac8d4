"""The package's import structure, read from the source with ``ast`` (no imports are executed).

Asserts what issue 13 set down for the outer ring: no import cycle among
brdfjax's modules, nothing imports the CLI, the differentiable core imports
nothing from the edges, no underscore name crosses a subpackage boundary,
and the few function-local imports left each say why.
"""

from __future__ import annotations

import ast
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2] / "brdfjax"
#: The layers, bottom up: each folder (or top-level module) imports only itself and what it lists here.
#: ``brdfjax`` is the package's ``__init__`` (for ``__version__``); ``reference`` is the NumPy oracle,
#: apart from the core; nothing imports ``cli``.
LAYERS: dict[str, set[str]] = {
    "runtime": set(),
    "core": {"runtime"},
    "io": {"core", "runtime"},
    "config": {"core", "runtime"},
    "reference": set(),
    "plotting": {"core", "io", "runtime"},
    "instrument": {"brdfjax", "core", "runtime", "io", "config", "plotting"},
    "simulate": {"brdfjax", "core", "runtime", "io", "config", "plotting"},
    "fit": {"core", "runtime", "io", "config", "plotting", "instrument"},
    # lightcurve -> diagnose: the sky gap diagnosis runs the frame/table diagnosis's search (diagnose/search.py)
    "lightcurve": {"core", "runtime", "io", "config", "plotting", "instrument", "fit", "sample", "diagnose"},
    "devices": {"core", "runtime", "io", "config", "plotting", "instrument"},
    "sample": {"core", "runtime", "io", "config", "plotting", "instrument", "fit"},
    "diagnose": {"core", "runtime", "io", "config", "plotting", "instrument", "fit", "sample", "reference"},
    "batch": {"core", "runtime", "io", "config", "instrument", "fit", "sample", "diagnose", "simulate", "lightcurve"},
    "cli": {"brdfjax", "core", "runtime", "io", "config", "plotting", "instrument", "simulate", "fit", "sample",
            "diagnose", "devices", "lightcurve", "batch"},
    "brdfjax": {"core", "runtime", "_compat"},
    "_compat": set(),
    "__main__": {"cli"},
}
#: The differentiable core: pure JAX, no I/O.
CORE = ("distributions", "fields", "fresnel", "geometry", "detector", "render", "shadowing", "terms", "registry", "presets")
#: Most function-local imports allowed (each with a comment saying why).
MAX_LOCAL_IMPORTS = 20


@dataclass(frozen=True)
class Import:
    importer: str  # dotted module name
    target: str  # dotted module the name comes from (resolved)
    name: str | None  # imported name (None for ``import x``)
    line: int
    local: bool  # inside a function body
    comment: str  # the source line's trailing comment, if any


def _module_name(path: Path) -> tuple[str, str]:
    parts = list(path.relative_to(ROOT.parent).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
        return ".".join(parts), ".".join(parts)
    return ".".join(parts), ".".join(parts[:-1])


MODULES = {(_module_name(p)[0]): p for p in sorted(ROOT.rglob("*.py"))}


def _resolve(node: ast.ImportFrom, package: str) -> str:
    if not node.level:
        return node.module or ""
    base = package.split(".")
    if node.level > 1:
        base = base[: -(node.level - 1)]
    return ".".join(base) + (f".{node.module}" if node.module else "")


def _owner(dotted: str) -> str:
    """The brdfjax module that defines ``dotted`` (a module, or a name in one)."""
    while dotted and dotted not in MODULES:
        dotted = dotted.rpartition(".")[0]
    return dotted


def imports() -> Iterator[Import]:
    for mod, path in MODULES.items():
        source = path.read_text()
        lines = source.splitlines()
        tree = ast.parse(source)
        _, package = _module_name(path)
        in_function: set[int] = set()
        for node in ast.walk(tree):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef | ast.Lambda):
                in_function.update(id(c) for c in ast.walk(node) if c is not node)
        for node in ast.walk(tree):
            if not isinstance(node, ast.Import | ast.ImportFrom):
                continue
            text = lines[node.lineno - 1]
            comment = text.split("#", 1)[1].strip() if "#" in text else ""
            local = id(node) in in_function
            if isinstance(node, ast.Import):
                for a in node.names:
                    yield Import(mod, a.name, None, node.lineno, local, comment)
            else:
                src = _resolve(node, package)
                for a in node.names:
                    full = f"{src}.{a.name}"
                    target = full if full in MODULES else src
                    yield Import(mod, target, a.name, node.lineno, local, comment)


IMPORTS = list(imports())


def _internal() -> list[Import]:
    return [i for i in IMPORTS if i.target == "brdfjax" or i.target.startswith("brdfjax.")]


def _graph() -> dict[str, set[str]]:
    graph: dict[str, set[str]] = {m: set() for m in MODULES}
    for i in _internal():
        owner = _owner(i.target)
        if owner and owner != i.importer:
            graph[i.importer].add(owner)
    return graph


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in graph:
        if v not in index:
            visit(v)
    return out


def test_the_walker_sees_the_package():
    assert "brdfjax.core.terms" in MODULES and "brdfjax.cli" in MODULES
    assert len(_internal()) > 150
    # a cycle in a hand-built graph is found, and a chain is not a cycle
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert _cycles({"a": {"b"}, "b": set()}) == []


def test_no_import_cycle():
    assert _cycles(_graph()) == []


def test_nothing_imports_the_cli():
    offenders = sorted({i.importer for i in _internal() if _owner(i.target) == "brdfjax.cli"} - {"brdfjax.__main__"})
    assert offenders == []


def _layer(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else "brdfjax"


def test_every_folder_is_a_layer():
    assert {_layer(m) for m in MODULES} <= set(LAYERS)
    assert {f"brdfjax.core.{c}" for c in CORE} <= set(MODULES)
    # nothing but the package's face, its entry point, the oracle, the figures and the batch runner sits loose
    loose = sorted(m for m, p in MODULES.items() if p.parent == ROOT)
    assert loose == ["brdfjax", "brdfjax.__main__", "brdfjax._compat", "brdfjax.batch", "brdfjax.plotting",
                     "brdfjax.reference"]


def test_each_layer_imports_only_the_layers_below_it():
    bad = []
    for i in _internal():
        owner = _owner(i.target)
        if not owner:
            continue
        a, b = _layer(i.importer), _layer(owner)
        if a != b and b not in LAYERS[a]:
            bad.append(f"{i.importer}:{i.line} ({a}) imports {owner} ({b})")
    assert bad == []


def test_the_layer_rules_bite():
    # a hand-made violation is caught by the same rule the package is held to
    assert "instrument" not in LAYERS["core"] and "cli" not in set().union(*(v for k, v in LAYERS.items() if k != "__main__"))


def test_no_function_local_import_dodges_a_cycle():
    # the graph with local imports must be acyclic on its own module-level imports *and* with them included
    graph: dict[str, set[str]] = {m: set() for m in MODULES}
    for i in _internal():
        owner = _owner(i.target)
        if owner and owner != i.importer and not i.local:
            graph[i.importer].add(owner)
    assert _cycles(graph) == []
    assert _cycles(_graph()) == []
    assert not [i for i in IMPORTS if i.local and "cycle" in i.comment.lower()]


def _package(module: str) -> str:
    path = MODULES[module]
    return module if path.name == "__init__.py" else module.rpartition(".")[0]


def _private(part: str) -> bool:
    return part.startswith("_") and not part.startswith("__")


def test_no_underscore_name_crosses_a_subpackage():
    bad = []
    for i in _internal():
        owner = _owner(i.target)
        if not owner or _package(owner) == _package(i.importer):
            continue
        # a private module of another package, or a private name from another package
        tail = owner.removeprefix(_package(owner)).lstrip(".")
        if (tail and _private(tail)) or (i.name is not None and _private(i.name)):
            bad.append(f"{i.importer}:{i.line} imports {i.name} from {i.target}")
    assert bad == []


def test_function_local_imports_are_few_and_say_why():
    # one entry per import statement (``from x import a, b`` is one)
    local = list({(i.importer, i.line): i for i in IMPORTS if i.local}.values())
    assert len(local) <= MAX_LOCAL_IMPORTS, [f"{i.importer}:{i.line} {i.target}" for i in local]
    silent = [f"{i.importer}:{i.line} {i.target}" for i in local if not i.comment]
    assert silent == []
