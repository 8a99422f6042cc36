"""Every public module, class and function of the package says what it is for."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PACKAGE_DIRS = ("core", "drivers", "services", "topseg_pkg")


def public_definitions_without_docstring() -> list[str]:
    """'path:line name' of each public def/class (at module level or in a public class)
    that has no docstring; names starting with '_' and overloads are private."""
    missing = []
    for folder in PACKAGE_DIRS:
        for path in sorted((ROOT / folder).rglob("*.py")):
            tree = ast.parse(path.read_text(), str(path))
            rel = path.relative_to(ROOT)
            if ast.get_docstring(tree) is None:
                missing.append(f"{rel}:1 (module)")
            missing += _walk(tree.body, rel, prefix="")
    return missing


def _walk(body, rel, prefix: str) -> list[str]:
    out = []
    for node in body:
        if not isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef):
            continue
        if node.name.startswith("_"):
            continue
        if ast.get_docstring(node) is None:
            out.append(f"{rel}:{node.lineno} {prefix}{node.name}")
        if isinstance(node, ast.ClassDef):
            out += _walk(node.body, rel, prefix=f"{node.name}.")
    return out


def test_every_public_function_and_class_has_a_docstring():
    missing = public_definitions_without_docstring()
    assert not missing, f"{len(missing)} public definitions lack a docstring:\n" + "\n".join(
        missing
    )
