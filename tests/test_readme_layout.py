"""The README's layout table names every folder and top-level module of `bench/`, and nothing else."""
from __future__ import annotations

import re
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent


def _layout_section() -> str:
    readme = (REPO / "README.md").read_text()
    return readme.split("\n## Layout\n", 1)[1].split("\n## ", 1)[0]


def test_readme_layout_matches_the_tree():
    named = set(re.findall(r"`(bench/[\w./]*?)/?`", _layout_section()))
    top = {f"bench/{p.name}" for p in (REPO / "bench").iterdir()
           if p.name not in ("__init__.py", "__pycache__") and (p.is_dir() or p.suffix == ".py")}
    top_named = {n for n in named if n.count("/") == 1}
    assert top - top_named == set(), "add these to the README's layout table"
    assert {n for n in named if not (REPO / n).exists()} == set(), "the README names paths that do not exist"
