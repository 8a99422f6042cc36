"""Every relative link in README.md and docs/ resolves, and every docs/ path the tree cites exists."""

from __future__ import annotations

import re

import pytest
from docsutil import ROOT, broken, links

PAGES = sorted([ROOT / "README.md", *(ROOT / "docs").rglob("*.md")])
#: files outside docs/ and README that cite docs pages by path (comments, help texts, units)
CITING = ("*.py", "*.sh", "*.toml", "*.json5", "*.service", "*.rules", "Makefile", "*.md")
SKIP_DIRS = {".venv", ".git", "build", "out", "data", "__pycache__", ".pytest_cache"}
#: a path to one of our docs, as code and configs cite them
DOCS_PATH = re.compile(r"(?<![\w/.-])docs/[\w./-]*\w\.(?:md|py|json|png)")
#: docs/ paths that name another project's file (ros2/rmw_zenoh's design document)
EXTERNAL = {"docs/design.md"}


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_relative_link_resolves(page):
    bad = [
        f"line {n}: {target}: {why}" for n, target in links(page) if (why := broken(target, page))
    ]
    assert not bad, f"{page.relative_to(ROOT)} has broken links:\n" + "\n".join(bad)


def cited_paths() -> list[tuple[str, int, str]]:
    """(file, line, docs path) of every docs/ path cited in the tree outside docs/."""
    found = []
    for pattern in CITING:
        for path in ROOT.rglob(pattern):
            rel = path.relative_to(ROOT)
            if SKIP_DIRS & set(rel.parts) or rel.parts[0] == "docs" or not path.is_file():
                continue
            for number, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
                found += [(str(rel), number, m) for m in DOCS_PATH.findall(line)]
    return found


def test_every_docs_path_cited_in_the_tree_exists():
    missing = [
        f"{file}:{line}: {path}"
        for file, line, path in cited_paths()
        if path not in EXTERNAL and not (ROOT / path).exists()
    ]
    assert not missing, "docs paths that do not exist:\n" + "\n".join(missing)


def test_the_checker_sees_links_and_their_anchors(tmp_path):
    page = tmp_path / "a.md"
    (tmp_path / "b.md").write_text("# Title\n\n## A heading (`with code`)\n")
    page.write_text("[ok](b.md#a-heading-with-code) [bad](c.md) [anchor](b.md#nope) `[no](x.md)`\n")
    found = [target for _, target in links(page)]
    assert found == ["b.md#a-heading-with-code", "c.md", "b.md#nope"]
    assert broken("b.md#a-heading-with-code", page) is None
    assert broken("c.md", page) and broken("b.md#nope", page)
    assert broken("https://example.org/x.md", page) is None
