"""The scripts import the package (``qtl.bench`` for the benchmarks' plumbing), never each other or a sys.path edit."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

SCRIPTS = Path(__file__).resolve().parents[2] / "scripts"
FILES = sorted(SCRIPTS.rglob("*.py"))


@pytest.mark.parametrize("path", FILES, ids=lambda p: str(p.relative_to(SCRIPTS)))
def test_a_script_neither_edits_sys_path_nor_imports_another_script(path: Path) -> None:
    text = path.read_text(encoding="utf-8")
    assert "sys.path" not in text
    neighbours = {p.stem for p in FILES}
    imported = set(re.findall(r"^\s*(?:from|import) (\w+)", text, flags=re.M))
    assert not imported & neighbours, f"{path.name} imports {sorted(imported & neighbours)}"


@pytest.mark.parametrize("path", FILES, ids=lambda p: str(p.relative_to(SCRIPTS)))
def test_a_script_writes_its_tables_through_markdown_table(path: Path) -> None:
    """A hand-written alignment row (``| --- | ---: |``) is a table that skipped ``qtl.bench.markdown_table``."""
    assert not re.search(r"\|\s*:?-{3,}:?\s*\|", path.read_text(encoding="utf-8"))


def test_the_research_scripts_are_listed_in_their_readme() -> None:
    readme = (SCRIPTS / "research" / "README.md").read_text(encoding="utf-8")
    assert all(f"`{p.name}`" in readme for p in (SCRIPTS / "research").glob("*.py"))
