"""The import graph of topseg's own modules has no cycle, counting every import: at module
top, inside functions (a cycle hidden in a function is still a cycle) and under
`if TYPE_CHECKING:` (a cycle of annotations still ties two modules together)."""

import ast
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
#: package name -> folder, as pyproject.toml maps them
ROOTS = {
    "topseg.core": REPO / "core",
    "topseg.drivers": REPO / "drivers",
    "topseg.services": REPO / "services",
    "topseg": REPO / "topseg_pkg",
}


def module_files() -> dict[str, Path]:
    """Every topseg module, by dotted name."""
    out = {}
    for package, folder in ROOTS.items():
        for path in folder.rglob("*.py"):
            parts = list(path.relative_to(folder).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            out[".".join([package, *parts])] = path
    return out


def _type_checking_only(node: ast.If) -> bool:
    """Whether `node` is `if TYPE_CHECKING:` (imports for annotations only)."""
    test = node.test
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"
    )


def imports_of(
    path: Path, modules: dict[str, Path], name: str, type_checking: bool = True
) -> list[tuple[str, bool]]:
    """(imported topseg module, made inside a function) for every import in `path` (those
    under `if TYPE_CHECKING:` too unless `type_checking` is False)."""
    tree = ast.parse(path.read_text(), str(path))
    found: list[tuple[str, bool]] = []
    is_package = path.name == "__init__.py"
    package = name if is_package else name.rpartition(".")[0]

    def target(mod: str) -> str | None:
        while mod and mod not in modules:
            mod = mod.rpartition(".")[0]
        return mod or None

    def visit(node: ast.AST, in_function: bool) -> None:
        if not type_checking and isinstance(node, ast.If) and _type_checking_only(node):
            for child in node.orelse:
                visit(child, in_function)
            return
        if isinstance(node, ast.Import):
            for alias in node.names:
                if (t := target(alias.name)) is not None:
                    found.append((t, in_function))
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")
                anchor = anchor[: len(anchor) - (node.level - 1)]
                base = ".".join([*anchor, base]) if base else ".".join(anchor)
            for alias in node.names:
                full = f"{base}.{alias.name}"
                t = full if full in modules else target(base)
                if t is not None:
                    found.append((t, in_function))
        inner = in_function or isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef)
        for child in ast.iter_child_nodes(node):
            visit(child, inner)

    visit(tree, False)
    return [(t, f) for t, f in found if t != name]


def import_graph(include_functions: bool = True, type_checking: bool = True) -> dict[str, set[str]]:
    """module -> the topseg modules it imports (inside functions and for annotations only
    too, unless told otherwise)."""
    modules = module_files()
    graph = {}
    for name, path in modules.items():
        edges = imports_of(path, modules, name, type_checking)
        graph[name] = {t for t, in_fn in edges if include_functions or not in_fn}
    return graph


def _is_ancestor_package(a: str, b: str) -> bool:
    """Whether `a` is a package containing `b` (importing a submodule imports its parents)."""
    return b.startswith(a + ".")


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan), each sorted.

    A package's `__init__` that imports its own submodules (to re-export them) does not make a
    cycle with them: edges from a submodule up to its own package are left out."""
    edges = {
        a: {b for b in bs if not _is_ancestor_package(b, a) and b in graph}
        for a, bs in graph.items()
    }
    index, low, stack, on, out = {}, {}, [], set(), []
    counter = [0]

    def strong(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in edges[v]:
            if w not in index:
                strong(w)
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

    for v in sorted(edges):
        if v not in index:
            strong(v)
    return out


def test_the_graph_is_found():
    graph = import_graph()
    assert "topseg.core.segmenter" in graph
    assert "topseg.core.stages" in graph["topseg.core.segmenter"]
    assert "topseg.core.camera" in graph["topseg.core.sensors"]


def test_cycle_finder_finds_a_cycle():
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert cycles({"p": {"p.x"}, "p.x": {"p"}}) == []  # a package and its own submodule


def test_no_import_cycle():
    found = cycles(import_graph())
    assert not found, "import cycles (imports inside functions count too):\n" + "\n".join(
        " <-> ".join(c) for c in found
    )


@pytest.mark.parametrize("package", ["topseg.core"])
def test_core_never_imports_services_or_drivers(package):
    graph = import_graph()
    bad = sorted(
        f"{a} -> {b}"
        for a, bs in graph.items()
        if a.startswith(package)
        for b in bs
        if b.startswith(("topseg.services", "topseg.drivers"))
    )
    assert not bad, bad
